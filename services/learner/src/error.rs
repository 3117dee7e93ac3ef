//! The learner's domain errors and their one mapping to `sf_service::ServiceError`.
//!
//! Owns: [`LearnerError`] — why a submitted job or grid is refused, why a job cannot start
//! (pinning a grid's names, loading its policies, a job's dependencies, files, blocking tasks),
//! and why the trainer thread stops with a failure — and [`IngestError`], why a transition
//! batch is refused; for each, its `From<_> for ServiceError`, the table from each variant to
//! a status kind. Messages are lowercase without
//! a trailing period and name the field, job or file; they are what clients see in a status and
//! what a failed job records as its message, so their text is part of the interface.
//! Must not: build `tonic::Status` or pick gRPC codes (`sf_service::ServiceError` is the one table
//! from status kinds to codes), nor log.

use std::path::PathBuf;

use sf_job::{CellId, JobId, PolicyRequest, PolicyVersion, WorkerId};
use sf_service::ServiceError;

/// Why the learner refused or failed something. `Display` is the message a client or a failed
/// job's record shows.
#[derive(Debug, thiserror::Error)]
pub enum LearnerError {
    // --- Evaluation grids: names pinned to jobs, policies, cells, cases.
    /// A flow or ego of an evaluation grid names a job that cannot serve it.
    #[error("eval config field `{field}` of `{name}`: {reason}")]
    BadEvalConfig { field: &'static str, name: String, reason: String },
    /// A cell of the grid asks for more cases than its scenario has stored.
    #[error(transparent)]
    TooFewCases(#[from] sf_job::eval::TooFewCases),
    /// A flow or ego of a grid that [`crate::eval::resolve_names`] has not pinned to a job.
    #[error("`{name}` is not pinned to a job")]
    NotPinned { name: String },
    /// A pinned job that has not (or no longer) succeeded.
    #[error("job {job_id} has not succeeded")]
    NotSucceeded { job_id: JobId },
    /// Resolving the policy of the grid's flow or ego `name` failed.
    #[error("`{name}`: {source}")]
    Grid { name: String, source: Box<LearnerError> },
    /// An ego job without an ego policy.
    #[error("ego `{name}`: no policy")]
    NoEgoPolicy { name: String },
    /// A succeeded job's `policy.bpk` could not be read.
    #[error("reading the final policy of job {job_id}: {source}")]
    FinalPolicy { job_id: JobId, source: std::io::Error },
    /// Scenarios, cases, policies and cells that do not fit together, or the GIFs.
    #[error(transparent)]
    Eval(#[from] sf_rollout::evaluate::EvalError),
    /// An evaluation grid that does not parse or validate.
    #[error(transparent)]
    EvalConfig(#[from] sf_job::eval::EvalConfigError),
    /// An evaluation's `episodes.csv`. Not `transparent`: the `FileError` itself is in the
    /// source chain, where `storage::is_storage_fault` looks for it.
    #[error("{0}")]
    Episodes(#[from] sf_report::episodes::FileError),

    // --- Requests: the learner's state, jobs, workers and policies.
    #[error("the learner is shutting down")]
    ShuttingDown,
    #[error(
        "worker {worker_id} is not registered (the learner may have restarted): register again"
    )]
    WorkerNotRegistered { worker_id: WorkerId },
    #[error("job {job_id} is {state}, not running")]
    NotRunning { job_id: JobId, state: &'static str },
    #[error("field `name`: `{name}` is not a job file a client may read (one of {readable})")]
    UnknownJobFile { name: String, readable: String },
    #[error("job {job_id} has no {name} (not written yet, or not a file this kind of job writes)")]
    NoJobFile { job_id: JobId, name: &'static str },
    #[error(
        "{name} of job {job_id} is {bytes} bytes, over the learner's message limit of {limit}"
    )]
    JobFileTooLarge { job_id: JobId, name: &'static str, bytes: u64, limit: u64 },
    /// Training jobs share the workers: this one is to end its session and ask again.
    #[error("job {job_id} has more workers than its share; worker {worker_id} moves to job {to}")]
    WorkerMoved { job_id: JobId, worker_id: WorkerId, to: JobId },
    /// A policy version the running job does not hold (never published, or evicted).
    #[error("job {job_id} holds no policy version {version}")]
    NoPolicyVersion { job_id: JobId, version: PolicyRequest },
    /// A finished job keeps only its final version.
    #[error("job {job_id} finished at policy version {final_version}; version {version} is gone")]
    VersionGone { job_id: JobId, final_version: PolicyVersion, version: PolicyVersion },
    /// A submitted job that names its dependencies instead of giving their ids.
    #[error("job config names job `{name}` (env.background_from, env.ego_from or train.init_from): names are resolved by `socialflow pipeline`; submit with job ids")]
    UnresolvedName { name: String },
    /// An evaluation grid that asks for a probe only `socialflow eval` runs.
    #[error("eval config entry `{name}`: probes (`messages`, `flow_actor`) run in `socialflow eval` only, not as a learner's evaluation job")]
    ProbeInService { name: String },

    /// An evaluation grid with the noise-matched IDM flow, which only `socialflow eval` runs.
    #[error("eval config flow `{name}`: the noise-matched IDM flow (`job = \"idm-noise\"`) runs in `socialflow eval` only, not as a learner's evaluation job")]
    NoiseFlowInService { name: String },
    /// A submitted job's `sac.device` this learner cannot open.
    #[error("job config field `sac.device`: {0}")]
    DeviceField(#[source] sf_nn::device::DeviceError),

    // --- A worker's results for one cell of a running evaluation.
    #[error("evaluation job {job_id} has no cell {cell_id}")]
    NoCell { job_id: JobId, cell_id: CellId },
    /// The worker could not run the cell: the evaluation fails with this message.
    #[error("cell {cell} failed on worker {worker}: {error}")]
    CellFailed { cell: String, worker: WorkerId, error: String },
    /// Results that are not one valid episode per stored case and seed of the grid.
    #[error("cell {cell_id}: {reason}")]
    BadCellResults { cell_id: CellId, reason: String },
    #[error("job {job_id} is {state}, not a running evaluation")]
    NotEvaluating { job_id: JobId, state: &'static str },

    // --- Jobs and their dependencies.
    /// A job config that does not parse or validate.
    #[error(transparent)]
    JobConfig(#[from] sf_job::ConfigError),
    #[error("job {job_id} not found")]
    JobNotFound { job_id: JobId },
    /// The stored config of a job this one depends on does not parse (any more).
    #[error("stored config of job {job_id}: {source}")]
    StoredConfig { job_id: JobId, source: sf_job::SpecError },
    #[error("socialcomm-adv job {job_id} has no background flow")]
    NoBackgroundFlow { job_id: JobId },
    /// Looking up the flow a SocialCommAdv job `job_id` talks to failed.
    #[error("job {flow} (the flow of job {job_id}): {source}")]
    BackgroundFlow { flow: JobId, job_id: JobId, source: Box<LearnerError> },
    /// A flow's `coordinator.json` (CoPO Stage 2) could not be read or does not validate.
    #[error(transparent)]
    Coordinator(sf_rollout::coordinator::CoordinatorError),
    /// A submitted job names job `dep` in `field`, but that job cannot serve it: `reason`
    /// completes "job N ...".
    #[error("job config field `{field}`: job {dep} {reason}")]
    Dependency { field: &'static str, dep: JobId, reason: String },
    /// `train.continue_from` names a directory the job cannot continue.
    #[error("job config field `train.continue_from`: {reason}")]
    Continuation { reason: String },
    /// `train.warm_start_from` names a directory whose weights the job cannot start from.
    #[error("job config field `train.warm_start_from`: {reason}")]
    WarmStart { reason: String },
    /// A starting job's dependency could not be looked up.
    #[error("job {dep} ({field}): {source}")]
    DependencyLookup { dep: JobId, field: &'static str, source: ServiceError },
    /// A starting job's dependency did not leave a final policy.
    #[error("job {dep} ({field}) has no final policy ({state})")]
    NoFinalPolicy { dep: JobId, field: &'static str, state: &'static str },
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
    /// Not `transparent`, which would hide the `StoreError` from the source chain (its
    /// `source()` is the store error's own): `storage::is_storage_fault` looks for a
    /// `StoreError::Storage` there.
    #[error("{0}")]
    Store(#[from] crate::store::StoreError),
    /// The data directory refuses writes (`storage::StorageHealth`): nothing new is accepted
    /// until it takes writes again.
    #[error("the learner's data directory refuses writes ({cause}); try again when it has space")]
    StorageFault { cause: String },
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
    #[error("fitting the coordinator of {scenario}: {source}")]
    FitCoordinator { scenario: String, source: sf_rollout::coordinator::CoordinatorError },
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
            | L::TooFewCases(_)
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
            | L::Continuation { .. }
            | L::WarmStart { .. }
            | L::Scenario { .. }
            | L::Task { .. } => S::InvalidArgument,
            L::UnresolvedName { .. }
            | L::DeviceField(_)
            | L::ProbeInService { .. }
            | L::NoiseFlowInService { .. } => S::InvalidArgument,
            L::ShuttingDown
            | L::StorageFault { .. }
            | L::Store(crate::store::StoreError::Storage { .. }) => S::Unavailable,
            L::JobNotFound { .. }
            | L::WorkerNotRegistered { .. }
            | L::NoPolicyVersion { .. }
            | L::VersionGone { .. } => S::NotFound,
            L::UnknownJobFile { .. } => S::InvalidArgument,
            L::NoJobFile { .. } => S::NotFound,
            L::JobFileTooLarge { .. } => S::ResourceExhausted,
            L::NotRunning { .. }
            | L::WorkerMoved { .. }
            | L::NotEvaluating { .. }
            | L::CellFailed { .. } => S::FailedPrecondition,
            L::NoCell { .. } => S::NotFound,
            L::BadCellResults { .. } => S::InvalidArgument,
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

/// Why a worker's transition batch was refused (`PushTransitions`; `ActiveJob::ingest`).
/// `Display` is the status message the worker sees.
#[derive(Debug, thiserror::Error)]
pub enum IngestError {
    /// The job is being cancelled, shut down or has finished its updates: the worker should
    /// ask for its next assignment.
    #[error("job {job_id} is stopping")]
    Stopping { job_id: JobId },
    /// Every transition the job needs is in; the trainer is finishing its updates.
    #[error("job {job_id} has all its transitions")]
    Complete { job_id: JobId },
    #[error("batch rows are {obs_len} observation floats and {action_dim} actions; job {job_id} expects {want_obs_len} and {want_action_dim}")]
    Shape {
        obs_len: usize,
        action_dim: usize,
        job_id: JobId,
        want_obs_len: usize,
        want_action_dim: usize,
    },
    #[error("map id {map_id} out of range: job {job_id} has {maps} scenarios")]
    MapOutOfRange { map_id: u32, job_id: JobId, maps: u32 },
    #[error("batch field `steps`: a transition spans {steps} steps; job {job_id} sums at most sac.n_step = {n_step}")]
    Span { steps: u8, job_id: JobId, n_step: u8 },
    /// A row the networks would index or branch on wrongly (masks, segment ids).
    #[error("batch field `{field}`, transition {index}: {reason}")]
    BadRow { field: &'static str, index: usize, reason: sf_sim::obs::ObsRowError },
    #[error("policy version {version} was never published (latest {latest})")]
    UnpublishedVersion { version: PolicyVersion, latest: PolicyVersion },
    #[error("deadline passed waiting for the trainer (rate limiter)")]
    Deadline,
    /// The rate limiter refused an insert it should have taken (a bug, not the worker's).
    #[error(transparent)]
    RateLimit(sf_sac::rate_limiter::RateLimitError),
    /// The replay refused a row that decoding had accepted.
    #[error(transparent)]
    Replay(#[from] sf_sac::replay::ReplayError),
}

impl From<IngestError> for ServiceError {
    fn from(e: IngestError) -> Self {
        use IngestError as I;
        let kind: fn(String) -> ServiceError = match &e {
            I::Stopping { .. } | I::Complete { .. } => ServiceError::FailedPrecondition,
            I::Shape { .. }
            | I::MapOutOfRange { .. }
            | I::Span { .. }
            | I::BadRow { .. }
            | I::UnpublishedVersion { .. }
            | I::Replay(_) => ServiceError::InvalidArgument,
            I::Deadline => ServiceError::DeadlineExceeded,
            I::RateLimit(_) => ServiceError::Internal,
        };
        kind(e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

    #[test]
    fn variants_map_to_their_status_and_name_the_field_or_job() {
        let e = ServiceError::from(LearnerError::BadEvalConfig {
            field: "egos.job",
            name: "nope".into(),
            reason: "job 3 does not exist".into(),
        });
        assert_eq!(e.code(), Code::InvalidArgument);
        assert_eq!(e.to_string(), "eval config field `egos.job` of `nope`: job 3 does not exist");

        let e = ServiceError::from(LearnerError::TooFewCases(sf_job::eval::TooFewCases {
            field: "cases".into(),
            cases: 9,
            stored: 4,
            scenario: "merge".into(),
        }));
        assert_eq!(e.code(), Code::InvalidArgument);
        assert!(e.to_string().contains("`cases`"), "{e}");

        // A wrapper takes the status of what it wraps.
        let e = ServiceError::from(LearnerError::Grid {
            name: "copo".into(),
            source: Box::new(LearnerError::NotSucceeded { job_id: JobId::new(7) }),
        });
        assert_eq!(e.code(), Code::InvalidArgument);
        assert_eq!(e.to_string(), "`copo`: job 7 has not succeeded");

        let e = ServiceError::from(LearnerError::JobNotFound { job_id: JobId::new(12) });
        assert_eq!((e.code(), e.to_string().as_str()), (Code::NotFound, "job 12 not found"));

        let e = ServiceError::from(LearnerError::Io {
            action: "writing",
            path: "/jobs/3-x/meta.json".into(),
            source: std::io::Error::other("disk full"),
        });
        assert_eq!(
            (e.code(), e.to_string().as_str()),
            (Code::Internal, "writing /jobs/3-x/meta.json: disk full")
        );

        // Ingest: the worker moves on (stopping), fixes its batch (shape) or retries (deadline).
        let e = ServiceError::from(IngestError::Stopping { job_id: JobId::new(4) });
        assert_eq!(
            (e.code(), e.to_string().as_str()),
            (Code::FailedPrecondition, "job 4 is stopping")
        );
        let e = ServiceError::from(IngestError::Shape {
            obs_len: 10,
            action_dim: 2,
            job_id: JobId::new(4),
            want_obs_len: 12,
            want_action_dim: 2,
        });
        assert_eq!(
            (e.code(), e.to_string().as_str()),
            (
                Code::InvalidArgument,
                "batch rows are 10 observation floats and 2 actions; job 4 expects 12 and 2"
            )
        );
        assert_eq!(ServiceError::from(IngestError::Deadline).code(), Code::DeadlineExceeded);
        assert_eq!(
            ServiceError::from(IngestError::UnpublishedVersion {
                version: PolicyVersion::new(9),
                latest: PolicyVersion::new(3),
            })
            .to_string(),
            "policy version 9 was never published (latest 3)"
        );

        // A handler's own error passes through unchanged.
        let e = ServiceError::from(LearnerError::from(ServiceError::Unavailable(
            "the learner is shutting down".into(),
        )));
        assert_eq!(
            (e.code(), e.to_string().as_str()),
            (Code::Unavailable, "the learner is shutting down")
        );
    }
}
