//! socialflow-lab: the experiment tooling behind the `socialflow` command: the learning ladder
//! ([`ladder`]), the critic probe ([`probe`]), the benchmarks ([`bench`]: `sim`, `sac`,
//! `ingest`, `e2e`, `replay`, `soak`) and curve plots ([`plot`]).
//!
//! Owns: each lab command's arguments (`clap` structs the CLI's `Cmd` embeds, so names and flags
//! stay the CLI's contract) and its `run`. Must not: define a simulator rule, network or update
//! (it calls the library crates as production does), nor be used by the product commands
//! (`train`, `eval`, `pipeline`, ...): what both need lives below, in `sf_embedded`.

pub mod bench;
mod bench_replay;
mod bench_sac;
mod bench_soak;
mod bench_svc;
pub mod ladder;
pub mod plot;
pub mod probe;
