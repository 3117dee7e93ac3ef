//! The service's domain types: job configs, job records and progress, worker assignments and
//! transition batches.
//!
//! Owns: [`JobConfig`] (the TOML a user submits; `deny_unknown_fields`, validated with errors
//! that name the field), the job's record ([`record`]: [`JobState`], [`JobRecord`],
//! [`Progress`] and the [`Learning`] it shares with curve points, [`Assignment`]), [`TransitionBatch`] with its shape and finiteness
//! checks, evaluation grids ([`eval`]), `--set` overrides of a config's text ([`overrides`]),
//! and [`JobSpec`], the one parse of a submitted or stored
//! text into either; [`WorkerId`], [`JobId`] and [`PolicyVersion`], typed ids that cross
//! processes. Must not: depend on burn, tokio or the wire format (`sf_proto` converts to and
//! from these types).

pub use sf_sim::{Scores, SvoGaussian};
pub mod batch;
pub mod config;
pub mod eval;
pub mod ids;
pub mod overrides;
pub mod record;
pub mod spec;

pub use batch::{
    ActedBy, BatchError, Ends, EpisodeResult, PolicyRequest, Transition, TransitionBatch,
};
pub use config::{ConfigError, DepRole, JobConfig};
pub use ids::{CellId, JobId, PolicyVersion, WorkerId};
pub use spec::{JobSpec, SpecError};

pub use record::{
    now_unix_ms, Assignment, Frozen, FrozenRole, JobRecord, JobState, Learning, Progress,
    ValidationProgress,
};
