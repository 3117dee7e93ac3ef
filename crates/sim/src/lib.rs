//! socialflow-sim: a fast, deterministic 2-D multi-agent driving simulator.
//!
//! Owns: maps as data ([`map`]), the four scenarios' geometry ([`scenarios`]), vehicles
//! ([`vehicle`]), IDM traffic ([`idm`]), episodes with collisions, failure/success rules and
//! rewards ([`env`]), observations in two layouts ([`obs`]), evaluation cases ([`case`]),
//! metrics ([`metrics`]), IDM with MOBIL's lane changes ([`mobil`]), whether standing vehicles close the road ahead ([`passage`]), batched stepping ([`vec_env`]), rendering ([`render`]) and episode traces for the browser viewer ([`trace`]).
//! Must not: depend on burn, tokio or prost; anything learned reaches it only as actions.
//!
//! Determinism: no randomness inside a step and no hash-map iteration; the same scenario
//! file, case, seed and actions give bit-identical trajectories, on any thread count.

#![allow(clippy::needless_range_loop)] // index loops over parallel per-agent arrays read clearer

pub mod case;
pub mod config;
pub mod env;
pub mod geom;
pub mod idm;
pub mod map;
pub mod metrics;
pub mod mobil;
pub mod obs;
pub mod passage;
pub mod policy;
pub mod render;
pub mod scenarios;
pub mod trace;
pub mod vec_env;
pub mod vehicle;

pub use case::{Case, CaseFile, SvoGaussian};
pub use config::{Layout, ObsConfig, SimConfig, SvoVisibility};
pub use env::{Controller, Env, Mode, Role, Termination};
pub use map::Map;
pub use metrics::Scores;
pub use obs::{ObsSpec, Observer};
pub use vehicle::{Action, DriveAction};
