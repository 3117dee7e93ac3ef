//! The job table: every job the learner knows, over the job store.
//!
//! Owns: [`Jobs`] — submission (a training job's config checked against its scenarios, device
//! and dependencies; an evaluation grid's names pinned and its cells checked), reads with live
//! progress of a running job ([`Jobs::get`], [`Jobs::list`]), cancellation, a job's readable
//! files, every stored job's parsed [`JobSpec`] (parsed once: [`Jobs::spec`]) and how a job's end
//! is recorded ([`record_end`]). Refuses submissions while the learner shuts down or the data
//! directory refuses writes. Must not: start or follow jobs (the scheduler does), or change a
//! final state: every state change goes through [`JobRecord::advance`], so a CancelJob racing a
//! job's end keeps whichever was recorded first.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use sf_job::eval::EvalConfig;
use sf_job::{DepRole, JobId, JobRecord, JobSpec, JobState, Progress};
use sf_service::sync::lock;
use sf_service::ServiceError;
use sf_sim::Map;
use tokio::sync::Notify;

use crate::error::LearnerError;
use crate::job::StopReason;
use crate::slot::{Outcome, Slots};
use crate::storage::StorageHealth;
use crate::store::Store;
use crate::task::blocking;
use crate::{artifacts, deps, eval};

/// Why a job was cancelled when the request gave no reason.
pub(crate) const CANCELLED_BY_REQUEST: &str = "cancelled by request";

/// The jobs, stored and parsed.
pub struct Jobs {
    store: Arc<Store>,
    /// Every stored job's text, parsed once (by submit, or on first use after a restart): a
    /// stored config never changes, so the scheduler and job starts read it here.
    specs: Mutex<BTreeMap<JobId, Arc<JobSpec>>>,
    /// The running jobs: their live progress, and whom a cancel stops.
    slots: Arc<Slots>,
    storage: Arc<StorageHealth>,
    shutting_down: Arc<AtomicBool>,
    /// The scheduler's: a queued job may start.
    wake: Arc<Notify>,
    pub(crate) scenarios_dir: PathBuf,
    pub(crate) cases_dir: PathBuf,
    /// The largest reply: a job file must fit in one.
    max_message_bytes: u64,
}

/// What [`Jobs`] shares with the other parts.
pub(crate) struct Shared {
    pub slots: Arc<Slots>,
    pub storage: Arc<StorageHealth>,
    pub shutting_down: Arc<AtomicBool>,
    pub wake: Arc<Notify>,
}

impl Jobs {
    pub(crate) fn new(
        store: Arc<Store>,
        cfg: &crate::config::LearnerConfig,
        shared: Shared,
    ) -> Self {
        let Shared { slots, storage, shutting_down, wake } = shared;
        Self {
            store,
            specs: Mutex::new(BTreeMap::new()),
            slots,
            storage,
            shutting_down,
            wake,
            scenarios_dir: cfg.scenarios_dir.clone(),
            cases_dir: cfg.cases_dir.clone(),
            max_message_bytes: cfg.max_message_bytes as u64,
        }
    }

    /// The parsed config of stored job `rec`, parsed on first use and kept.
    pub(crate) fn spec(&self, rec: &JobRecord) -> Result<Arc<JobSpec>, LearnerError> {
        if let Some(s) = lock(&self.specs).get(&rec.id) {
            return Ok(Arc::clone(s));
        }
        let s = Arc::new(
            JobSpec::from_toml(&rec.config_toml)
                .map_err(|source| LearnerError::StoredConfig { job_id: rec.id, source })?,
        );
        lock(&self.specs).insert(rec.id, Arc::clone(&s));
        Ok(s)
    }

    /// Keeps the spec a job was submitted with (its text was parsed by submit).
    fn keep_spec(&self, id: JobId, spec: JobSpec) {
        lock(&self.specs).insert(id, Arc::new(spec));
    }

    /// Loads and validates the job's scenario files off the async runtime (file IO).
    pub(crate) async fn load_maps(&self, names: &[String]) -> Result<Vec<Arc<Map>>, LearnerError> {
        let dir = self.scenarios_dir.clone();
        let names = names.to_vec();
        tokio::task::spawn_blocking(move || {
            names
                .iter()
                .map(|name| {
                    Map::load(&dir.join(format!("{name}.json")))
                        .map(Arc::new)
                        .map_err(|source| LearnerError::Scenario { name: name.clone(), source })
                })
                .collect::<Result<Vec<_>, _>>()
        })
        .await
        .map_err(|source| LearnerError::Task { task: "scenario loading task", source })?
    }

    /// Refuses new jobs while the learner shuts down or the disk refuses writes.
    fn accepting(&self) -> Result<(), LearnerError> {
        if self.shutting_down.load(Ordering::Acquire) {
            return Err(LearnerError::ShuttingDown);
        }
        match self.storage.cause() {
            Some(cause) => Err(LearnerError::StorageFault { cause }),
            None => Ok(()),
        }
    }

    /// Stores a checked job as QUEUED, keeps its spec and wakes the scheduler.
    async fn queue(
        &self,
        spec: JobSpec,
        text: String,
        target: u64,
    ) -> Result<JobRecord, LearnerError> {
        let store = Arc::clone(&self.store);
        let name = spec.name().to_string();
        let rec = blocking(move || store.create(&name, &text, target)).await?;
        self.keep_spec(rec.id, spec);
        self.wake.notify_one();
        Ok(rec)
    }

    /// Validates a config and queues it.
    pub async fn submit(self: &Arc<Self>, toml_text: String) -> Result<JobRecord, ServiceError> {
        self.accepting()?;
        let cfg = match JobSpec::from_toml(&toml_text)? {
            JobSpec::Eval(grid) => return self.submit_eval(grid).await,
            JobSpec::Train(cfg) => cfg,
        };
        self.load_maps(&cfg.env.scenarios).await?;
        sf_nn::device::device(sf_sac::device_kind(cfg.sac.device))
            .map_err(LearnerError::DeviceField)?;
        if let Some((_, name)) = cfg.deps_by_name().first() {
            return Err(LearnerError::UnresolvedName { name: name.to_string() }.into());
        }
        for (role, dep) in cfg.deps() {
            let field = role.field();
            let refuse =
                |reason: &str| LearnerError::Dependency { field, dep, reason: reason.into() };
            let rec = self.get(dep).map_err(|_| refuse("does not exist"))?;
            let dep_spec = self.spec(&rec)?;
            let Some(dep_cfg) = dep_spec.train() else {
                return Err(refuse("is an evaluation, not a training job").into());
            };
            deps::check_dep(&cfg, role, dep, dep_cfg)?;
            if role == DepRole::Init
                && cfg.train.init_replay
                && rec.state == JobState::Succeeded
                && !Path::new(&rec.artifact_dir).join("replay").exists()
            {
                return Err(refuse("finished without a queued job carrying its replay, which was deleted then (train.init_replay: submit the continuation before its source ends)").into());
            }
            if matches!(rec.state, JobState::Failed | JobState::Cancelled) {
                return Err(refuse(&format!("is {}", rec.state.as_str())).into());
            }
        }
        if cfg.train.continue_from.is_some() || cfg.train.warm_start_from.is_some() {
            let c2 = cfg.clone();
            tokio::task::spawn_blocking(move || {
                crate::continuation::check(&c2)?;
                crate::warm_start::check(&c2)
            })
            .await
            .map_err(|source| LearnerError::Task { task: "blocking task", source })??;
        }
        let target = cfg.train.env_steps;
        let rec = self.queue(JobSpec::Train(cfg), toml_text, target).await?;
        tracing::info!(job_id = rec.id.get(), name = %rec.name, "job queued");
        Ok(rec)
    }

    /// Validates an evaluation grid, pins its names to this learner's succeeded jobs, checks
    /// every cell's ego and flow fit and that the cases exist, and queues it.
    async fn submit_eval(self: &Arc<Self>, mut cfg: EvalConfig) -> Result<JobRecord, ServiceError> {
        // A probe changes what a flow's observers are told or who sits in the ego's seat; the
        // workers' cells carry neither, so the learner refuses it rather than run it unprobed.
        if let Some(n) = cfg.flows.iter().chain(&cfg.egos).find(|n| n.is_probe()) {
            return Err(LearnerError::ProbeInService { name: n.name.clone() }.into());
        }
        // Its noise is drawn where the cell runs, and workers are told only policies.
        if let Some(n) = cfg.flows.iter().find(|n| n.is_idm_noise()) {
            return Err(LearnerError::NoiseFlowInService { name: n.name.clone() }.into());
        }
        let jobs = self.list();
        eval::resolve_names(&mut cfg, &jobs)?;
        let (scen, cases) = (self.scenarios_dir.clone(), self.cases_dir.clone());
        let (c2, me) = (cfg.clone(), Arc::clone(self));
        // A panicked check is the grid's fault as much as any other refusal: INVALID_ARGUMENT.
        tokio::task::spawn_blocking(move || -> Result<(), LearnerError> {
            let (_, _, grid) = eval::resolve_policies(&c2, &jobs, false, &|r| me.spec(r))?;
            grid.check(&c2.cells())?;
            eval::load_maps(&c2, &scen, &cases).map(|_| ())
        })
        .await
        .map_err(|source| LearnerError::Task { task: "blocking task", source })??;
        let (target, cells, resolved) = (cfg.episodes(), cfg.cells().len(), cfg.to_toml());
        let rec = self.queue(JobSpec::Eval(cfg), resolved, target).await?;
        tracing::info!(job_id = rec.id.get(), name = %rec.name, cells, "evaluation queued");
        Ok(rec)
    }

    /// Job `id`, with live progress if it is running. Records are read from memory: no IO.
    pub fn get(&self, id: JobId) -> Result<JobRecord, LearnerError> {
        let mut rec = self.store.get(id).ok_or(LearnerError::JobNotFound { job_id: id })?;
        if let Some(p) = self.slots.progress(id).filter(|_| !rec.state.is_final()) {
            rec.progress = p;
            rec.state = JobState::Running;
        }
        Ok(rec)
    }

    /// Every job in id order, the running ones with live progress.
    pub fn list(&self) -> Vec<JobRecord> {
        let mut all = self.store.list();
        for r in all.iter_mut().filter(|r| !r.state.is_final()) {
            if let Some(p) = self.slots.progress(r.id) {
                r.progress = p;
            }
        }
        all
    }

    /// Records CANCELLED (unless the job already ended) and asks a running job to stop.
    pub async fn cancel(&self, id: JobId) -> Result<JobRecord, ServiceError> {
        let rec = self
            .update(id, |r| {
                r.advance(JobState::Cancelled, Some(CANCELLED_BY_REQUEST));
            })
            .await?
            .ok_or(LearnerError::JobNotFound { job_id: id })?;
        if let Some(j) = self.slots.get(id) {
            j.request_stop(StopReason::Cancelled);
        }
        tracing::info!(job_id = id.get(), state = rec.state.as_str(), "cancel requested");
        Ok(rec)
    }

    /// The content of file `name` of job `job_id`'s artifact directory.
    pub async fn job_file(&self, job_id: JobId, name: &str) -> Result<Vec<u8>, ServiceError> {
        let name = artifacts::readable(name)?;
        let dir = PathBuf::from(&self.get(job_id)?.artifact_dir);
        let limit = self.max_message_bytes;
        Ok(blocking(move || artifacts::read_job_file(&dir, job_id, name, limit)).await?)
    }

    /// Applies `f` to job `id`'s stored record (one transaction, off the runtime); `None` if
    /// there is no such job.
    pub(crate) async fn update(
        &self,
        id: JobId,
        f: impl FnOnce(&mut JobRecord) + Send + 'static,
    ) -> Result<Option<JobRecord>, LearnerError> {
        let store = Arc::clone(&self.store);
        blocking(move || store.update(id, f)).await
    }

    /// Records how job `id` ended ([`record_end`]), with its last `progress` if given.
    pub(crate) async fn record_end(
        &self,
        id: JobId,
        out: Outcome,
        progress: Option<Progress>,
    ) -> Result<(), LearnerError> {
        self.update(id, move |r| {
            if let Some(p) = progress {
                r.progress = p;
            }
            record_end(r, &out);
        })
        .await
        .map(|_| ())
    }

    /// Opens the job store again after a storage fault (blocking).
    pub(crate) fn reopen_store(&self) -> Result<(), LearnerError> {
        self.store.reopen().map_err(LearnerError::Store)
    }
}

/// Records how a job ended in its record, unless it already ended (a cancel that came first
/// stays cancelled: [`JobRecord::advance`]). A shutdown or a pause leaves the job to resume.
pub(crate) fn record_end(r: &mut JobRecord, out: &Outcome) {
    match out {
        Outcome::Succeeded => r.advance(JobState::Succeeded, None),
        Outcome::Cancelled => r.advance(JobState::Cancelled, Some(CANCELLED_BY_REQUEST)),
        Outcome::Shutdown | Outcome::Paused(_) => false,
        Outcome::Failed(m) => r.advance(JobState::Failed, Some(m.as_str())),
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `CancelJob` racing a job's end: both see one final state, the one recorded first (the
    /// cancel's answer and the stored record agree), never a cancel overwritten by the end.
    #[test]
    fn a_cancel_racing_a_jobs_end_keeps_whichever_was_recorded_first() {
        use std::sync::Barrier;
        let dir = std::env::temp_dir().join(format!("sf-race-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("tmp");
        let store = Arc::new(Store::open(&dir.join("jobs.redb"), &dir).expect("store"));
        let mut cancelled = 0;
        for _ in 0..40 {
            let id = store.create("race", "cfg", 1).expect("create").id;
            store.update(id, |r| assert!(r.advance(JobState::Running, None))).expect("running");
            let barrier = Arc::new(Barrier::new(2));
            let (s1, b1) = (Arc::clone(&store), Arc::clone(&barrier));
            let cancel = std::thread::spawn(move || {
                b1.wait();
                s1.update(id, |r| {
                    r.advance(JobState::Cancelled, Some(CANCELLED_BY_REQUEST));
                })
            });
            let (s2, b2) = (Arc::clone(&store), barrier);
            let end = std::thread::spawn(move || {
                b2.wait();
                s2.update(id, |r| record_end(r, &Outcome::Succeeded))
            });
            let c = cancel.join().expect("cancel thread").expect("cancel").expect("job");
            let e = end.join().expect("end thread").expect("end").expect("job");
            let stored = store.get(id).expect("job");
            assert_eq!(
                c.state, e.state,
                "the cancel answered {:?}, the end recorded {:?}",
                c.state, e.state
            );
            assert_eq!(stored.state, c.state);
            assert_eq!(
                stored.message.as_str(),
                if stored.state == JobState::Cancelled { CANCELLED_BY_REQUEST } else { "" }
            );
            cancelled += usize::from(stored.state == JobState::Cancelled);
        }
        eprintln!("the cancel came first in {cancelled} of 40 races");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
