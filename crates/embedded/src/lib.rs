//! socialflow-embedded: what the `socialflow` commands and the lab's (`sf_lab`) share, so
//! neither depends on the other.
//!
//! Owns: where data files are ([`Ctx`]), the learner and workers in one process ([`Embedded`],
//! [`runtime`]), following a job through the job API ([`client`]) and finding finished jobs in a
//! learner's data directory ([`runs`]). Must not: parse command lines or print results (the
//! commands do), nor hold simulator, network or training logic.

pub mod client;
mod dirs;
pub mod runs;
mod service;

pub use dirs::Ctx;
pub use service::{runtime, Embedded};
