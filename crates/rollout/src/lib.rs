//! socialflow-rollout: running policies in simulators, shared by the worker, the learner and
//! the CLI.
//!
//! Owns: the job-config mapping to everything that runs a job ([`setup`]), batched inference
//! ([`inference`]), who acts in a step of batched simulators ([`drive`]), one cell of an
//! evaluation grid ([`evaluate`]) and CoPO's coordinator ([`coordinator`]). Must not: update
//! networks (that is `sf_sac`) or know about gRPC. The critic probe built on these is the lab's
//! (`sf_lab::probe::critic`).

pub mod coordinator;
pub mod drive;
pub mod evaluate;
pub mod inference;
pub mod setup;
