//! socialflow-nn: the paper's policy networks as burn modules.
//!
//! Owns: DeepSets polyline encoders and the ego-query attention ([`layers`], [`encoder`]),
//! the tanh-Gaussian actor, the twin critic and the adversary ([`policy`]), the observation
//! batch that feeds them ([`batch`]), network sizes ([`config`]), device selection ([`device`]),
//! weight (de)serialisation ([`weights`]) and their FLOPs counted from the configuration
//! ([`cost`]). Must not: know about replay buffers, SAC losses or gRPC; it maps observations
//! to actions and values.
//!
//! Two encoders share one observation contract (`sf_sim::obs`): `ego-frame` (the paper's:
//! every map vector in the observer's frame, encoded per observation) and `query-centric`
//! (map segments encoded once per map in their own frame and gathered by index, plus an MLP of
//! each token's observer-relative pose before attention).

pub mod batch;
pub mod config;
pub mod cost;
pub mod device;
pub mod encoder;
pub mod layers;
pub mod onnx;
pub mod policy;
pub mod weights;

pub use batch::{AgentInput, Histories, ObsBatch};
/// The burn this crate builds on, for callers that drive the networks directly (the CLI's
/// `bench sac --profile`) without a dependency of their own that could drift from it.
pub use burn;
pub use config::{Layout, NetConfig, SvoVisibility};
pub use policy::{Actor, Critic};
