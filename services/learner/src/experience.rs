//! The experience side: everything a worker calls.
//!
//! Owns: [`Experience`] — registration and heartbeats (through [`Workers`]), the answer to
//! `GetAssignment` ([`Experience::assignment`]: a training job, the running one with the fewest
//! workers; else a cell of the running evaluation; else when to ask again), policy weights by
//! version ([`Experience::policy`]: from the running job, or a succeeded job's final files),
//! the ingest of transition batches (a worker on a job with more than its share is told to
//! move, FAILED_PRECONDITION, before its batch is stored) and an evaluation cell's results.
//! Every call touches the worker. Must not: see wire types other than the transition batch it
//! decodes, start or end jobs (the scheduler does), or pick a status (errors are
//! `LearnerError`s, mapped in `error.rs`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use sf_job::eval::{EvalEpisode, EvalWork};
use sf_job::{Assignment, CellId, JobId, JobState, PolicyRequest, PolicyVersion, WorkerId};
use sf_proto::pb;
use sf_service::ServiceError;

use crate::artifacts::read_final;
use crate::error::LearnerError;
use crate::job::{Ack, ActiveJob};
use crate::jobs::Jobs;
use crate::slot::Slots;
use crate::storage::{self, StorageHealth};
use crate::task::blocking;
use crate::workers::Workers;

/// How long one batch may wait on the rate limiter before the call fails.
const INGEST_DEADLINE: Duration = Duration::from_secs(120);

/// What a worker is given to do.
pub enum Work {
    /// A training job's session.
    Train(Assignment),
    /// One cell of the running evaluation.
    Eval(EvalWork),
    /// Nothing now: ask again after this many milliseconds.
    Wait { retry_after_ms: u32 },
}

/// The worker-facing part of the learner.
pub struct Experience {
    jobs: Arc<Jobs>,
    slots: Arc<Slots>,
    workers: Arc<Workers>,
    storage: Arc<StorageHealth>,
    /// Assignments given, a term of each one's seed.
    assignments: AtomicU64,
}

impl Experience {
    pub(crate) fn new(
        jobs: Arc<Jobs>,
        slots: Arc<Slots>,
        workers: Arc<Workers>,
        storage: Arc<StorageHealth>,
    ) -> Self {
        Self { jobs, slots, workers, storage, assignments: AtomicU64::new(0) }
    }

    pub fn register(&self, name: &str, seats: sf_job::eval::ScriptedSeats) -> WorkerId {
        self.workers.register(name, seats)
    }

    pub fn heartbeat(&self, worker_id: WorkerId) -> Result<(), LearnerError> {
        self.workers.touch(worker_id)
    }

    /// What worker `worker_id` should do next: a cell is leased only when there is no training
    /// assignment to give.
    pub fn assignment(&self, worker_id: WorkerId) -> Result<Work, ServiceError> {
        if let Some(a) = self.train_assignment(worker_id)? {
            return Ok(Work::Train(a));
        }
        let Some(e) = self.slots.eval() else { return Ok(Work::Wait { retry_after_ms: 1000 }) };
        match e.lease(worker_id, &self.workers.live(), self.workers.seats(worker_id)) {
            Some(w) => Ok(Work::Eval(w)),
            // An evaluation's last cells are leased to others: ask again soon, one may come back.
            None => Ok(Work::Wait { retry_after_ms: 250 }),
        }
    }

    /// A session of the running training job with the fewest workers, if one takes workers.
    fn train_assignment(&self, worker_id: WorkerId) -> Result<Option<Assignment>, LearnerError> {
        self.workers.touch(worker_id)?;
        let pick = self.workers.assign(worker_id, &self.open_jobs());
        self.count_workers_per_job();
        let Some(j) = pick.and_then(|id| self.slots.train(id)) else { return Ok(None) };
        let scenario_index = j.next_scenario();
        let seed = j
            .cfg
            .sac
            .seed
            .wrapping_mul(1_000_003)
            .wrapping_add(worker_id.get().wrapping_mul(7919))
            .wrapping_add(self.assignments.fetch_add(1, Ordering::Relaxed));
        Ok(Some(Assignment {
            job_id: j.id,
            config_toml: j.cfg.to_toml(),
            scenario_index,
            seed,
            policy_version: j.latest_version(),
            obs_len: j.obs_len as u32,
            action_dim: j.action_dim as u32,
            warmup: j.in_warmup(),
            frozen: j.frozen.clone(),
        }))
    }

    /// Validates and stores one batch, in one blocking hop for decoding (every value of up to a
    /// few MiB is checked) and storing (which may wait on the rate limiter). As before, a batch
    /// that does not decode is refused as such before anything about its worker or job.
    pub async fn ingest(&self, msg: pb::TransitionBatch) -> Result<Ack, ServiceError> {
        let task = |e| ServiceError::from(LearnerError::Join(e));
        let worker = WorkerId::from(msg.worker_id);
        let job = self
            .workers
            .touch(worker)
            .and_then(|()| self.running(JobId::from(msg.job_id)))
            .map_err(ServiceError::from);
        let job = job.and_then(|j| match self.workers.rebalance(worker, j.id, &self.open_jobs()) {
            Some(to) => Err({
                self.count_workers_per_job();
                LearnerError::WorkerMoved { job_id: j.id, worker_id: worker, to }.into()
            }),
            None => Ok(j),
        });
        let job = match job {
            Ok(job) => job,
            Err(e) => {
                tokio::task::spawn_blocking(move || sf_proto::batch_from_wire(msg))
                    .await
                    .map_err(task)??;
                return Err(e);
            }
        };
        let deadline = Instant::now() + INGEST_DEADLINE;
        tokio::task::spawn_blocking(move || -> Result<Ack, ServiceError> {
            Ok(job.ingest(&sf_proto::batch_from_wire(msg)?, deadline)?)
        })
        .await
        .map_err(task)?
    }

    /// The running training job with this id; NOT_FOUND for unknown ids, FAILED_PRECONDITION
    /// otherwise.
    fn running(&self, id: JobId) -> Result<Arc<ActiveJob>, LearnerError> {
        if let Some(j) = self.slots.train(id) {
            return Ok(j);
        }
        let rec = self.jobs.get(id)?;
        Err(LearnerError::NotRunning { job_id: id, state: rec.state.as_str() })
    }

    /// Policy weights (the latest or one version) of the running job, or the final policy of a
    /// succeeded one.
    pub async fn policy(
        &self,
        job_id: JobId,
        which: PolicyRequest,
    ) -> Result<(PolicyVersion, Arc<Vec<u8>>), LearnerError> {
        match self.running(job_id) {
            Ok(j) => {
                let p = match which.version() {
                    None => j.latest(),
                    Some(v) => j.version(v),
                };
                p.map(|p| (p.version, p.weights))
                    .ok_or(LearnerError::NoPolicyVersion { job_id, version: which })
            }
            Err(not_running @ LearnerError::NotRunning { .. }) => {
                let rec = self.jobs.get(job_id)?;
                if rec.state != JobState::Succeeded {
                    return Err(not_running);
                }
                let dir = std::path::PathBuf::from(&rec.artifact_dir);
                let (final_version, weights) = blocking(move || -> Result<_, LearnerError> {
                    let weights = read_final(&dir, job_id, "policy.bpk")?;
                    let meta: serde_json::Value =
                        serde_json::from_slice(&read_final(&dir, job_id, "policy.json")?)
                            .map_err(|e| LearnerError::FinalPolicy { job_id, source: e.into() })?;
                    Ok((PolicyVersion::new(meta["version"].as_u64().unwrap_or(0)), weights))
                })
                .await?;
                match which.version() {
                    Some(version) if version != final_version => {
                        Err(LearnerError::VersionGone { job_id, final_version, version })
                    }
                    _ => Ok((final_version, Arc::new(weights))),
                }
            }
            Err(e) => Err(e),
        }
    }

    /// A worker's results for one cell of the running evaluation `job_id`.
    pub async fn eval_results(
        &self,
        job_id: JobId,
        worker: WorkerId,
        cell_id: CellId,
        episodes: Vec<EvalEpisode>,
        error: String,
    ) -> Result<bool, ServiceError> {
        self.workers.touch(worker)?;
        let job = match self.slots.eval() {
            Some(e) if e.id == job_id && e.stop_reason().is_none() => e,
            _ => {
                let rec = self.jobs.get(job_id)?;
                return Err(
                    LearnerError::NotEvaluating { job_id, state: rec.state.as_str() }.into()
                );
            }
        };
        match tokio::task::spawn_blocking(move || job.store(worker, cell_id, &episodes, &error))
            .await
            .map_err(LearnerError::from)?
        {
            Ok(stored) => Ok(stored),
            // The cell stays unstored (the worker sends it again); jobs wait for the disk.
            Err(e) if storage::is_storage_fault(&e) => {
                self.storage.fault(&format!("storing cell {cell_id} of evaluation {job_id}: {e}"));
                Err(LearnerError::StorageFault { cause: e.to_string() }.into())
            }
            Err(e) => Err(e.into()),
        }
    }

    /// The running training jobs that take workers: not stopping, not complete, a policy
    /// published.
    fn open_jobs(&self) -> Vec<JobId> {
        self.slots
            .trains()
            .iter()
            .filter(|j| j.stop_reason().is_none() && !j.is_complete() && j.latest().is_some())
            .map(|j| j.id)
            .collect()
    }

    /// Sets each running job's `job_workers` gauge.
    pub fn count_workers_per_job(&self) {
        let jobs = self.slots.trains();
        let ids: Vec<JobId> = jobs.iter().map(|j| j.id).collect();
        let n = self.workers.per_job(&ids);
        for j in jobs {
            j.metrics.workers.set(n.get(&j.id).copied().unwrap_or(0) as i64);
        }
    }
}
