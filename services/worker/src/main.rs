//! `socialflow-worker`: see `sf_worker::cmd`.
use clap::Parser;

fn main() -> anyhow::Result<()> {
    sf_nn::device::tune_allocator();
    let args = sf_worker::cmd::WorkerArgs::parse();
    tokio::runtime::Runtime::new()?.block_on(sf_worker::cmd::run(args))
}
