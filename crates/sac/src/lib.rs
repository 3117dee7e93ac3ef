//! socialflow-sac: Soft Actor-Critic for the paper's networks.
//!
//! Owns: the replay buffer ([`replay`]), the Reverb-style rate limiter ([`rate_limiter`]),
//! the SAC state and update ([`sac`]) and checkpoints that restore training exactly
//! ([`checkpoint`]), the job-config mapping ([`setup`]), batched inference ([`inference`]) and
//! who acts in a step of batched simulators ([`drive`]), one cell of an evaluation grid ([`evaluate`]), the critic probe ([`probe`]) and the replay on disk ([`replay_store`], segments written beside checkpoints). Must not: do IO on the update path or know about gRPC.

pub mod checkpoint;
pub mod coordinator;
pub mod drive;
pub mod ego;
pub mod evaluate;
pub mod inference;
pub mod probe;
pub mod rate_limiter;
pub mod replay;
pub mod replay_store;
pub mod sac;
pub mod setup;

pub use rate_limiter::{RateLimiter, RateLimiterConfig};
pub use replay::{Batch, Replay, Transition};
pub use sac::{Losses, Sac, SacConfig};
