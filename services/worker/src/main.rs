//! `socialflow-worker`: see `sf_worker::cmd`.
use clap::Parser;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    sf_worker::cmd::run(sf_worker::cmd::WorkerArgs::parse()).await
}
