//! What workers call during a training job: their assignment, policy weights by version (from
//! the running job or a finished job's files) and the ingest of their transition batches.
//!
//! Owns: the `impl Inner` blocks behind `GetAssignment`'s training half (a worker gets the
//! running job with the fewest workers), `GetPolicy` and `PushTransitions` (a worker on a job
//! with more than its share is told to move, FAILED_PRECONDITION, before its batch is stored).
//! Must not: see wire types other than the transition batch it decodes, or pick a status
//! (errors are `LearnerError`s, mapped in `error.rs`).

use std::sync::Arc;
use std::time::{Duration, Instant};

use sf_job::{Assignment, JobState, PolicyRequest};
use sf_proto::pb;
use sf_service::ServiceError;

use crate::{Inner, LearnerError};

/// How long one batch may wait on the rate limiter before the call fails.
const INGEST_DEADLINE: Duration = Duration::from_secs(120);

impl Inner {
    /// Validates and stores one batch, in one blocking hop for decoding (every value of up to a
    /// few MiB is checked) and storing (which may wait on the rate limiter). As before, a batch
    /// that does not decode is refused as such before anything about its worker or job.
    pub(crate) async fn ingest(
        self: &Arc<Self>,
        msg: pb::TransitionBatch,
    ) -> Result<crate::job::Ack, ServiceError> {
        let task = |e| ServiceError::from(LearnerError::Join(e));
        let touched = self.touch_worker(msg.worker_id);
        let job = match touched {
            Ok(()) => self.running(msg.job_id).await.map_err(ServiceError::from),
            Err(e) => Err(e),
        };
        let job = job.and_then(|j| {
            match self.workers.rebalance(msg.worker_id, j.id, &self.open_jobs()) {
                Some(to) => Err({
                    self.count_workers_per_job();
                    LearnerError::WorkerMoved { job_id: j.id, worker_id: msg.worker_id, to }.into()
                }),
                None => Ok(j),
            }
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
        tokio::task::spawn_blocking(move || -> Result<crate::job::Ack, ServiceError> {
            Ok(job.ingest(&sf_proto::batch_from_wire(msg)?, deadline)?)
        })
        .await
        .map_err(task)?
    }

    /// The running job with this id; NOT_FOUND for unknown ids, FAILED_PRECONDITION otherwise.
    pub(crate) async fn running(
        self: &Arc<Self>,
        id: u64,
    ) -> Result<Arc<crate::job::ActiveJob>, LearnerError> {
        if let Some(j) = self.training(id) {
            return Ok(j);
        }
        let rec = self.job(id).await?;
        Err(LearnerError::NotRunning { job_id: id, state: rec.state.as_str() })
    }

    /// Policy weights (the latest or one version) of the running job, or the final policy of a
    /// succeeded one.
    pub(crate) async fn policy(
        self: &Arc<Self>,
        job_id: u64,
        which: PolicyRequest,
    ) -> Result<(u64, Arc<Vec<u8>>), LearnerError> {
        match self.running(job_id).await {
            Ok(j) => {
                let p = match which {
                    PolicyRequest::Latest => j.latest(),
                    PolicyRequest::Version(v) => j.version(v.get()),
                };
                p.map(|p| (p.version, p.weights))
                    .ok_or(LearnerError::NoPolicyVersion { job_id, version: which })
            }
            Err(not_running @ LearnerError::NotRunning { .. }) => {
                let rec = self.job(job_id).await?;
                if rec.state != JobState::Succeeded {
                    return Err(not_running);
                }
                let dir = std::path::PathBuf::from(&rec.artifact_dir);
                let (final_version, weights) =
                    tokio::task::spawn_blocking(move || -> Result<(u64, Vec<u8>), LearnerError> {
                        let weights = crate::deps::read_final(&dir, job_id, "policy.bpk")?;
                        let meta: serde_json::Value = serde_json::from_slice(
                            &crate::deps::read_final(&dir, job_id, "policy.json")?,
                        )
                        .map_err(|e| LearnerError::FinalPolicy { job_id, source: e.into() })?;
                        Ok((meta["version"].as_u64().unwrap_or(0), weights))
                    })
                    .await??;
                match which {
                    PolicyRequest::Version(v) if v.get() != final_version => {
                        Err(LearnerError::VersionGone { job_id, final_version, version: v.get() })
                    }
                    _ => Ok((final_version, Arc::new(weights))),
                }
            }
            Err(e) => Err(e),
        }
    }

    /// The running training jobs that take workers: not stopping, not complete, a policy
    /// published.
    fn open_jobs(&self) -> Vec<u64> {
        self.trainings()
            .iter()
            .filter(|j| j.stop_reason().is_none() && !j.is_complete() && j.latest().is_some())
            .map(|j| j.id)
            .collect()
    }

    /// Sets each running job's `job_workers` gauge.
    pub(crate) fn count_workers_per_job(&self) {
        let jobs = self.trainings();
        let ids: Vec<u64> = jobs.iter().map(|j| j.id).collect();
        let n = self.workers.per_job(&ids);
        for j in jobs {
            j.metrics.workers.set(n.get(&j.id).copied().unwrap_or(0) as i64);
        }
    }

    pub(crate) fn assignment(
        self: &Arc<Self>,
        worker_id: u64,
    ) -> Result<Option<Assignment>, ServiceError> {
        self.touch_worker(worker_id)?;
        let pick = self.workers.assign(worker_id, &self.open_jobs());
        self.count_workers_per_job();
        let Some(j) = pick.and_then(|id| self.training(id)) else { return Ok(None) };
        let scenario_index = j.next_scenario();
        let seed = j
            .cfg
            .sac
            .seed
            .wrapping_mul(1_000_003)
            .wrapping_add(worker_id.wrapping_mul(7919))
            .wrapping_add(self.assignments.fetch_add(1, std::sync::atomic::Ordering::Relaxed));
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
}
