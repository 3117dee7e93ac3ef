//! `socialflow-learner`: see `sf_learner::cmd`.
use clap::Parser;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    sf_learner::cmd::run(sf_learner::cmd::LearnerArgs::parse()).await
}
