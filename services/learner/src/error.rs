//! The learner's domain errors and their one mapping to `sf_svc::ServiceError`.
//!
//! Owns: [`LearnerError`] — why a submitted job or grid is refused, why a job cannot start
//! (pinning a grid's names, loading its policies, a job's dependencies, files, blocking tasks),
//! and why the trainer thread stops with a failure — and `impl From<LearnerError> for
//! ServiceError`, the table from each variant to a status kind. Messages are lowercase without
//! a trailing period and name the field, job or file; they are what clients see in a status and
//! what a failed job records as its message, so their text is part of the interface.
//! Must not: build `tonic::Status` or pick gRPC codes (`sf_svc::ServiceError` is the one table
//! from status kinds to codes), nor log.

use std::path::PathBuf;

use sf_svc::ServiceError;

/// Why the learner refused or failed something. `Display` is the message a client or a failed
/// job's record shows.
#[derive(Debug, thiserror::Error)]
pub enum LearnerError {
    // --- Evaluation grids: names pinned to jobs, policies, cells, cases.
    /// A flow or ego of an evaluation grid names a job that cannot serve it.
    #[error("eval config field `{field}` of `{name}`: {reason}")]
    BadEvalConfig { field: &'static str, name: String, reason: String },
    /// The grid asks for more cases than a scenario has stored.
    #[error("eval config field `cases`: {cases} exceeds the {stored} stored cases of {scenario}")]
    TooFewCases { cases: u32, stored: usize, scenario: String },
    /// A flow or ego of a grid that [`crate::eval::resolve_names`] has not pinned to a job.
    #[error("`{name}` is not pinned to a job")]
    NotPinned { name: String },
    /// A pinned job that has not (or no longer) succeeded.
    #[error("job {job_id} has not succeeded")]
    NotSucceeded { job_id: u64 },
    /// Resolving the policy of the grid's flow or ego `name` failed.
    #[error("`{name}`: {source}")]
    Grid { name: String, source: Box<LearnerError> },
    /// An ego job without an ego policy.
    #[error("ego `{name}`: no policy")]
    NoEgoPolicy { name: String },
    /// A succeeded job's `policy.bpk` could not be read.
    #[error("reading the final policy of job {job_id}: {source}")]
    FinalPolicy { job_id: u64, source: std::io::Error },
    /// Scenarios, cases, policies and cells that do not fit together, or the GIFs.
    #[error(transparent)]
    Eval(#[from] sf_sac::evaluate::EvalError),
    /// An evaluation grid that does not parse or validate.
    #[error(transparent)]
    EvalConfig(#[from] sf_job::eval::EvalConfigError),
    /// An evaluation's `episodes.csv`.
    #[error(transparent)]
    Episodes(#[from] sf_eval::episodes::FileError),

    // --- Jobs and their dependencies.
    /// A job config that does not parse or validate.
    #[error(transparent)]
    JobConfig(#[from] sf_job::ConfigError),
    #[error("job {job_id} not found")]
    JobNotFound { job_id: u64 },
    /// The stored config of a job this one depends on does not parse (any more).
    #[error("stored config of job {job_id}: {source}")]
    StoredConfig { job_id: u64, source: sf_job::ConfigError },
    #[error("socialcomm-adv job {job_id} has no background flow")]
    NoBackgroundFlow { job_id: u64 },
    /// Looking up the flow a SocialCommAdv job `job_id` talks to failed.
    #[error("job {flow} (the flow of job {job_id}): {source}")]
    BackgroundFlow { flow: u64, job_id: u64, source: Box<LearnerError> },
    /// A flow's `coordinator.json` (CoPO Stage 2) could not be read or does not validate.
    #[error("{0}")]
    Coordinator(String),
    /// A submitted job names job `dep` in `field`, but that job cannot serve it: `reason`
    /// completes "job N ...".
    #[error("job config field `{field}`: job {dep} {reason}")]
    Dependency { field: &'static str, dep: u64, reason: String },
    /// A starting job's dependency could not be looked up.
    #[error("job {dep} ({field}): {source}")]
    DependencyLookup { dep: u64, field: &'static str, source: ServiceError },
    /// A starting job's dependency did not leave a final policy.
    #[error("job {dep} ({field}) has no final policy ({state})")]
    NoFinalPolicy { dep: u64, field: &'static str, state: &'static str },
    #[error("scenario `{name}`: {source}")]
    Scenario { name: String, source: sf_sim::map::MapError },

    // --- Files, the store, tasks.
    #[error("{action} {}: {source}", path.display())]
    Io { action: &'static str, path: PathBuf, source: std::io::Error },
    /// A job's `state.json` does not parse.
    #[error("{}: {source}", path.display())]
    StateFile { path: PathBuf, source: serde_json::Error },
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    /// A call into the learner's own handlers (job records) failed.
    #[error(transparent)]
    Service(#[from] ServiceError),
    /// The blocking task `task` panicked or was cancelled.
    #[error("{task}: {source}")]
    Task { task: &'static str, source: tokio::task::JoinError },
    /// A blocking task panicked or was cancelled.
    #[error(transparent)]
    Join(#[from] tokio::task::JoinError),
    #[error("spawning the trainer thread: {0}")]
    SpawnTrainer(#[source] std::io::Error),

    // --- The trainer.
    #[error("building SAC: {0}")]
    BuildSac(#[source] sf_sac::sac::SacError),
    /// Restoring (`restoring`) or warm-starting (`starting from`) from the checkpoint at `path`.
    #[error("{action} {}: {source}", path.display())]
    Checkpoint { action: &'static str, path: PathBuf, source: sf_sac::checkpoint::CheckpointError },
    #[error("checkpoint: {0}")]
    SaveCheckpoint(#[source] sf_sac::checkpoint::CheckpointError),
    /// Restoring or writing the persisted replay.
    #[error("{action} the replay: {source}")]
    Replay { action: &'static str, source: sf_sac::replay_store::ReplayStoreError },
    #[error(transparent)]
    RateLimit(#[from] sf_sac::rate_limiter::RateLimitError),
    /// Serialising the actor or loading the final policy.
    #[error("{action}: {source}")]
    Weights { action: &'static str, source: sf_nn::weights::WeightsError },
    #[error(transparent)]
    Device(#[from] sf_nn::device::DeviceError),
    #[error("fitting the coordinator of {scenario}: {reason}")]
    FitCoordinator { scenario: String, reason: String },
}

impl LearnerError {
    /// The status kind of each variant. Everything that the checks of a submitted job or grid
    /// can return is INVALID_ARGUMENT (as `submit` and `submit_eval` have always answered,
    /// including a stored dependency config that no longer parses and a panicked check task);
    /// the rest only ever ends a job (its message) and is mapped by its nature.
    fn status(&self) -> fn(String) -> ServiceError {
        use LearnerError as L;
        use ServiceError as S;
        match self {
            L::Grid { source, .. } | L::BackgroundFlow { source, .. } => source.status(),
            L::BadEvalConfig { .. }
            | L::TooFewCases { .. }
            | L::NotPinned { .. }
            | L::NotSucceeded { .. }
            | L::NoEgoPolicy { .. }
            | L::Eval(_)
            | L::EvalConfig(_)
            | L::JobConfig(_)
            | L::StoredConfig { .. }
            | L::NoBackgroundFlow { .. }
            | L::Coordinator(_)
            | L::Dependency { .. }
            | L::Scenario { .. }
            | L::Task { .. } => S::InvalidArgument,
            L::JobNotFound { .. } => S::NotFound,
            L::DependencyLookup { .. } | L::NoFinalPolicy { .. } => S::FailedPrecondition,
            L::Service(s) => s.kind(),
            L::FinalPolicy { .. }
            | L::Episodes(_)
            | L::Io { .. }
            | L::StateFile { .. }
            | L::Json(_)
            | L::Store(_)
            | L::Join(_)
            | L::SpawnTrainer(_)
            | L::BuildSac(_)
            | L::Checkpoint { .. }
            | L::SaveCheckpoint(_)
            | L::Replay { .. }
            | L::RateLimit(_)
            | L::Weights { .. }
            | L::Device(_)
            | L::FitCoordinator { .. } => S::Internal,
        }
    }
}

impl From<LearnerError> for ServiceError {
    fn from(e: LearnerError) -> Self {
        (e.status())(e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

    #[test]
    fn variants_map_to_their_status_and_name_the_field_or_job() {
        let e = ServiceError::from(LearnerError::BadEvalConfig { field: "egos.job", name: "nope".into(), reason: "job 3 does not exist".into() });
        assert_eq!(e.code(), Code::InvalidArgument);
        assert_eq!(e.to_string(), "eval config field `egos.job` of `nope`: job 3 does not exist");

        let e = ServiceError::from(LearnerError::TooFewCases { cases: 9, stored: 4, scenario: "merge".into() });
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.to_string().contains("`cases`"), "{e}");

        // A wrapper takes the status of what it wraps.
        let e = ServiceError::from(LearnerError::Grid { name: "copo".into(), source: Box::new(LearnerError::NotSucceeded { job_id: 7 }) });
        assert_eq!(e.code(), Code::InvalidArgument);
        assert_eq!(e.to_string(), "`copo`: job 7 has not succeeded");

        let e = ServiceError::from(LearnerError::JobNotFound { job_id: 12 });
        assert_eq!((e.code(), e.to_string().as_str()), (Code::NotFound, "job 12 not found"));

        let e = ServiceError::from(LearnerError::Io { action: "writing", path: "/jobs/3-x/meta.json".into(), source: std::io::Error::other("disk full") });
        assert_eq!((e.code(), e.to_string().as_str()), (Code::Internal, "writing /jobs/3-x/meta.json: disk full"));

        // A handler's own error passes through unchanged.
        let e = ServiceError::from(LearnerError::from(ServiceError::Unavailable("the learner is shutting down".into())));
        assert_eq!((e.code(), e.to_string().as_str()), (Code::Unavailable, "the learner is shutting down"));
    }
}
