//! socialflow-rollout: running policies in simulators, shared by the worker, the learner and
//! the CLI.
//!
//! Owns: the job-config mapping to everything that runs a job ([`setup`]), batched inference
//! ([`inference`]), who acts in a step of batched simulators ([`drive`]), one cell of an
//! evaluation grid ([`evaluate`]), CoPO's coordinator ([`coordinator`]) and the critic probe
//! ([`probe`]). Must not: update networks (that is `sf_sac`) or know about gRPC.

pub mod coordinator;
pub mod drive;
pub mod evaluate;
pub mod inference;
pub mod probe;
pub mod setup;
