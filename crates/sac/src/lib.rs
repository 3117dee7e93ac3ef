//! socialflow-sac: Soft Actor-Critic for the paper's networks.
//!
//! Owns: the replay buffer ([`replay`]), the Reverb-style rate limiter ([`rate_limiter`]), the
//! SAC state and update ([`sac`]) and its tensor helpers ([`ops`]), checkpoints that restore
//! training exactly ([`checkpoint`]), the replay on disk ([`replay_store`], segments written
//! beside checkpoints) and the training curve's points ([`curve`]). Must not: run simulators (that is `sf_rollout`), do IO on the
//! update path or know about gRPC.

pub mod checkpoint;
pub mod curve;
pub mod diagnostics;
pub mod ops;
pub mod rate_limiter;
pub mod replay;
pub mod replay_store;
pub mod sac;

pub use curve::CurvePoint;
pub use rate_limiter::{RateLimiter, RateLimiterConfig};
pub use replay::{Batch, Replay, Transition};
pub use sac::{device_kind, Losses, Sac, SacConfig};
