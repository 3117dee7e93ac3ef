//! `socialflow-learner`: see `sf_learner::cmd`.
use clap::Parser;

fn main() -> anyhow::Result<()> {
    sf_nn::device::tune_allocator();
    let args = sf_learner::cmd::LearnerArgs::parse();
    tokio::runtime::Runtime::new()?.block_on(sf_learner::cmd::run(args))
}
