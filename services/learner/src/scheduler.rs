//! The scheduler: which job starts when, and how a running job's end is recorded.
//!
//! Owns: [`Scheduler`] — [`Scheduler::schedule_once`] starts jobs while [`Slots::admits`] them:
//! RUNNING jobs left by a previous process first (they resume from their checkpoints), then
//! QUEUED jobs in id order whose dependencies succeeded (a failed or cancelled one fails the
//! job); a training job on its trainer thread ([`trainer::spawn`]), an evaluation by leasing its
//! cells ([`EvalJob`]). One routine puts either kind in its slot and marks it RUNNING
//! ([`Scheduler::occupy`]); one records how either ends and frees the slot
//! ([`Scheduler::finish`]), then deletes the replays no unfinished job carries any more.
//! While the disk refuses writes it starts nothing, and [`Scheduler::recover_storage`] probes
//! until it takes them again. [`Scheduler::stop_all`]: shutdown. Invariant: a job is in its
//! slot before it is marked RUNNING, so a CancelJob racing a start either finds it there (and
//! stops it) or wrote CANCELLED first (and the start undoes itself). Must not: answer workers or clients (the experience side and the job table do), or
//! change a final state (records change only through `JobRecord::advance`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use sf_job::eval::EvalConfig;
use sf_job::{
    DepRole, Frozen, FrozenRole, JobConfig, JobId, JobRecord, JobSpec, JobState, Progress,
};
use sf_rollout::setup;
use sf_sac::RateLimiter;
use tokio::sync::Notify;

use crate::artifacts::read_final;
use crate::deps::InitDep;
use crate::error::LearnerError;
use crate::eval::{self, EvalJob};
use crate::job::{ActiveJob, StopReason};
use crate::jobs::Jobs;
use crate::metrics::{JobMetrics, LearnerMetrics};
use crate::slot::{Kind, Outcome, Running, Slots};
use crate::storage::{self, StorageHealth};
use crate::task::blocking;
use crate::workers::Workers;
use crate::{deps, trainer};

/// Starts jobs, follows them to their end and records it.
pub struct Scheduler {
    jobs: Arc<Jobs>,
    slots: Arc<Slots>,
    workers: Arc<Workers>,
    storage: Arc<StorageHealth>,
    metrics: LearnerMetrics,
    shutting_down: Arc<AtomicBool>,
    /// Something may start: a job was queued or ended, the disk recovered.
    wake: Arc<Notify>,
    /// A slot was freed (shutdown waits on it).
    idle: Notify,
    /// The data directory the storage probe writes to.
    data_dir: PathBuf,
}

impl Scheduler {
    pub(crate) fn new(
        jobs: Arc<Jobs>,
        workers: Arc<Workers>,
        metrics: LearnerMetrics,
        data_dir: PathBuf,
        shared: crate::jobs::Shared,
    ) -> Self {
        let crate::jobs::Shared { slots, storage, shutting_down, wake } = shared;
        Self {
            jobs,
            slots,
            workers,
            storage,
            metrics,
            shutting_down,
            wake,
            idle: Notify::new(),
            data_dir,
        }
    }

    pub fn shutting_down(&self) -> bool {
        self.shutting_down.load(Ordering::Acquire)
    }

    /// Until something may start, or a second passed.
    pub async fn wait(&self) {
        tokio::select! {
            _ = self.wake.notified() => {}
            _ = tokio::time::sleep(Duration::from_secs(1)) => {}
        }
    }

    /// Starts what may start now: RUNNING jobs of a previous process, then ready QUEUED jobs
    /// in id order, while the slots admit them.
    pub async fn schedule_once(self: &Arc<Self>) {
        if self.shutting_down() || !self.storage.healthy() {
            return;
        }
        let all = self.jobs.list();
        // A job waits until every job it depends on has succeeded; it fails if one did not.
        // (An evaluation's jobs succeeded before it was accepted: it has none to wait for.)
        let dep_state = |r: &JobRecord| -> Option<(JobId, JobState)> {
            let deps = self.jobs.spec(r).ok()?.deps();
            let states = deps.iter().map(|&(_, dep)| {
                (dep, all.iter().find(|d| d.id == dep).map_or(JobState::Failed, |d| d.state))
            });
            // The worst: a failed one, else an unfinished one, else succeeded.
            states.max_by_key(|(_, s)| match s {
                JobState::Succeeded => 0,
                JobState::Queued | JobState::Running => 1,
                JobState::Failed | JobState::Cancelled => 2,
            })
        };
        for r in all.iter().filter(|r| r.state == JobState::Queued) {
            if let Some((dep, s @ (JobState::Failed | JobState::Cancelled))) = dep_state(r) {
                let msg = format!("job {dep}, which it depends on, ended {}", s.as_str());
                self.finish(r.id, Outcome::Failed(msg), None).await;
            }
        }
        let ready = |r: &&JobRecord| {
            r.state == JobState::Queued
                && dep_state(r).is_none_or(|(_, s)| s == JobState::Succeeded)
        };
        let candidates = all
            .iter()
            .filter(|r| r.state == JobState::Running)
            .chain(all.iter().filter(ready))
            .filter(|r| self.slots.progress(r.id).is_none());
        for rec in candidates {
            let kind = match self.jobs.spec(rec) {
                Ok(s) if s.is_eval() => Kind::Eval,
                _ => Kind::Train,
            };
            if !self.slots.admits(kind, self.workers.live().len()) {
                // In order: a job does not overtake one that waits for room.
                return;
            }
            if !self.storage.healthy() || self.shutting_down() {
                return;
            }
            match self.start(rec).await {
                Ok(()) => {}
                // The job waits, as it is, until the disk takes writes again.
                Err(e) if storage::is_storage_fault(&e) => {
                    self.storage.fault(&format!("starting job {}: {e}", rec.id))
                }
                Err(e) => {
                    tracing::error!(job_id = rec.id.get(), error = %e, "job failed to start");
                    self.finish(rec.id, Outcome::Failed(e.to_string()), None).await;
                }
            }
        }
    }

    /// Starts job `rec`, of either kind.
    async fn start(self: &Arc<Self>, rec: &JobRecord) -> Result<(), LearnerError> {
        match &*self.jobs.spec(rec)? {
            JobSpec::Eval(grid) => self.start_eval(rec, grid.clone()).await,
            JobSpec::Train(cfg) => self.start_train(rec, cfg.clone()).await,
        }
    }

    /// Puts `job` in its slot, then marks it RUNNING unless its record reached a final state
    /// meanwhile (a CancelJob came first): then the job is stopped and its slot freed again.
    /// `Ok(false)`: cancelled before it started.
    async fn occupy(&self, id: JobId, job: Running) -> Result<bool, LearnerError> {
        self.slots.fill(id, job.clone());
        let started = self
            .jobs
            .update(id, |r| {
                r.advance(JobState::Running, None);
            })
            .await;
        if matches!(&started, Ok(Some(r)) if r.state == JobState::Running) {
            return Ok(true);
        }
        job.request_stop(StopReason::Cancelled);
        if let Running::Train(j) = &job {
            j.metrics.remove();
        }
        self.slots.clear(id);
        self.wake.notify_one();
        started?;
        match job {
            Running::Train(_) => {
                tracing::info!(job_id = id.get(), "job cancelled before it started")
            }
            Running::Eval(_) => {
                tracing::info!(job_id = id.get(), "evaluation cancelled before it started")
            }
        }
        Ok(false)
    }

    /// Builds training job `rec` (maps, replay, limiter, dependencies), resuming from its
    /// directory's state if it has one, and runs it on its trainer thread.
    async fn start_train(
        self: &Arc<Self>,
        rec: &JobRecord,
        cfg: JobConfig,
    ) -> Result<(), LearnerError> {
        let maps = self.jobs.load_maps(&cfg.env.scenarios).await?;
        let dir = PathBuf::from(&rec.artifact_dir);
        let (dir2, cfg2) = (dir.clone(), cfg.clone());
        // A continuation's first start copies its source's state in; then it resumes as any
        // restarted job does.
        let (seeded, resume) = blocking(move || {
            let seeded = crate::continuation::seed(&cfg2, &dir2)?;
            Ok::<_, LearnerError>((seeded, trainer::load_state(&dir2)?))
        })
        .await?;
        if let Some(s) = seeded {
            tracing::info!(
                job_id = rec.id.get(),
                replay = s.replay,
                "continuing a run's directory (train.continue_from)"
            );
        }
        let capacity = cfg.train.replay_capacity as u64;
        // A resumed job samples again soon; one whose replay is not on disk (a continuation
        // from a directory without one) refills it with its policy first, as much as a warm-up.
        let has_replay = dir.join("replay").is_dir();
        let fill = if resume.is_some() && (has_replay || !cfg.train.persist_replay) {
            4 * cfg.sac.batch_size as u64
        } else {
            cfg.sac.warmup_steps.max(cfg.sac.batch_size as u64)
        };
        let limiter = RateLimiter::new(setup::rate_limiter(&cfg, fill.min(capacity)), capacity)?;
        let counters = resume.as_ref().map(|r| r.counters.clone()).unwrap_or_default();
        let JobDeps { frozen, frozen_weights, init } = job_deps(&self.jobs, &cfg).await?;
        let resolved = Arc::new(setup::resolve(&cfg, None));
        let segment_points = resolved.sim.obs.segment_points;
        let maps2 = maps.clone();
        let segs = tokio::task::spawn_blocking(move || {
            maps2
                .iter()
                .map(|m| Arc::new(sf_sim::obs::MapSegments::build(m, segment_points)))
                .collect::<Vec<_>>()
        })
        .await?;
        let counts = segs.iter().map(|s| s.len()).collect();
        let id = rec.id;
        let job = Arc::new(ActiveJob::new(
            id,
            cfg,
            resolved,
            frozen,
            counts,
            limiter,
            counters,
            JobMetrics::new(&self.metrics, id),
        ));
        if !self.occupy(id, Running::Train(Arc::clone(&job))).await? {
            return Ok(());
        }
        tracing::info!(job_id = id.get(), resumed = resume.is_some(), "job started");
        let input = trainer::TrainerInput {
            job: Arc::clone(&job),
            maps,
            segs,
            dir,
            resume,
            init,
            frozen_weights,
        };
        let ended = trainer::spawn(input)?;
        let me = Arc::clone(self);
        tokio::spawn(async move {
            let out = ended
                .await
                .unwrap_or_else(|_| Outcome::Failed("the trainer thread panicked".into()));
            me.finish(id, out, Some(job.progress())).await;
        });
        Ok(())
    }

    /// Opens evaluation `rec` (resuming from its stored cells) and follows it to its end: every
    /// cell stored (then the GIFs), a failed cell, cancel or shutdown.
    async fn start_eval(
        self: &Arc<Self>,
        rec: &JobRecord,
        cfg: EvalConfig,
    ) -> Result<(), LearnerError> {
        let jobs = self.jobs.list();
        let (r2, m2, all) = (rec.clone(), self.metrics.clone(), Arc::clone(&self.jobs));
        let job =
            Arc::new(blocking(move || EvalJob::open(&r2, cfg, &jobs, &|r| all.spec(r), m2)).await?);
        let id = rec.id;
        if !self.occupy(id, Running::Eval(Arc::clone(&job))).await? {
            return Ok(());
        }
        tracing::info!(
            job_id = id.get(),
            cells = job.cells(),
            stored = job.progress().learning.episodes,
            "evaluation started"
        );
        let me = Arc::clone(self);
        tokio::spawn(async move {
            let out = loop {
                if let Some(why) = job.stop_reason() {
                    break match why {
                        StopReason::Cancelled => Outcome::Cancelled,
                        StopReason::Shutdown => Outcome::Shutdown,
                    };
                }
                if let Some(msg) = job.failure() {
                    break Outcome::Failed(msg);
                }
                if job.is_complete() {
                    break me.finish_eval(&job).await;
                }
                job.changed.notified().await;
            };
            me.finish(id, out, Some(job.progress())).await;
        });
        Ok(())
    }

    /// Every cell is stored: draws the grid's GIFs into the job's directory and, with
    /// `mine_worst`, replays every cell's worst episodes into viewer pages (`mined/`).
    async fn finish_eval(&self, job: &Arc<EvalJob>) -> Outcome {
        let (gifs, mine_worst) = (job.cfg.experiments.gifs.clone(), job.cfg.mine_worst);
        if gifs.is_none() && mine_worst.is_none() {
            return Outcome::Succeeded;
        }
        let (j, scen, cases) =
            (Arc::clone(job), self.jobs.scenarios_dir.clone(), self.jobs.cases_dir.clone());
        let r = blocking(move || -> Result<_, LearnerError> {
            let maps = eval::load_maps(&j.cfg, &scen, &cases)?;
            let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?;
            let mut runners = sf_rollout::evaluate::Runners::new(device);
            let drawn = match &gifs {
                Some(g) => j.grid.render_gifs(g, &j.dir, &maps, &mut runners)?.len(),
                None => 0,
            };
            let mined = match mine_worst {
                Some(worst) => {
                    let path = sf_report::episodes::episodes_file(&j.dir);
                    let rows: Vec<_> = sf_report::episodes::read_episodes(&path)?
                        .into_iter()
                        .map(|r| (r.cell, r.ep))
                        .collect();
                    let cells = j.cfg.cells();
                    let m = sf_rollout::evaluate::mine::mine(
                        &j.grid,
                        &maps,
                        &cells,
                        &rows,
                        &j.dir,
                        worst,
                        &mut runners,
                    )?;
                    m.pages
                }
                None => 0,
            };
            Ok((drawn, mined))
        })
        .await;
        match r {
            Ok((gifs, pages)) => {
                tracing::info!(
                    job_id = job.id.get(),
                    gifs,
                    mined_pages = pages,
                    "evaluation finished"
                );
                Outcome::Succeeded
            }
            // A full disk pauses the job like any other write; the GIFs and pages are made again
            // on resume.
            Err(e) if crate::storage::is_storage_fault(&e) => {
                Outcome::Paused(format!("every cell is stored, drawing the GIFs and pages: {e}"))
            }
            Err(e) => Outcome::Failed(format!(
                "every cell is stored, but the GIFs or the mined pages failed: {e}"
            )),
        }
    }

    /// Records how job `id` ended (with its last `progress`) and frees its slot.
    async fn finish(&self, id: JobId, out: Outcome, progress: Option<Progress>) {
        tracing::info!(job_id = id.get(), outcome = ?out, "job stopped");
        if let Some(j) = self.slots.train(id) {
            j.close();
            j.metrics.remove();
        }
        if let Outcome::Paused(cause) = &out {
            // Nothing to record: the job stays RUNNING at its last checkpoint.
            self.storage.fault(&format!("job {id}: {cause}"));
        } else {
            match self.jobs.record_end(id, out, progress).await {
                Ok(()) => {}
                // Unrecorded, the job stays RUNNING and resumes (and ends again) after recovery.
                Err(e) if storage::is_storage_fault(&e) => {
                    self.storage.fault(&format!("recording the end of job {id}: {e}"))
                }
                Err(e) => tracing::error!(job_id = id.get(), error = %e, "recording the job's end"),
            }
            self.release_replays().await;
        }
        self.slots.clear(id);
        self.idle.notify_waiters();
        self.wake.notify_one();
    }

    /// Deletes the replays of succeeded jobs that no queued or running job carries
    /// (`train.init_replay`; [`deps::replays_to_release`]). A replay that cannot be deleted
    /// stays, with a warning: it costs disk, not correctness.
    async fn release_replays(&self) {
        let jobs = Arc::clone(&self.jobs);
        let done = blocking(move || {
            for d in deps::replays_to_release(&jobs.list(), |r| jobs.spec(r).ok()) {
                let replay = d.join("replay");
                match std::fs::remove_dir_all(&replay) {
                    Ok(()) => tracing::info!(dir = %replay.display(), "replay released"),
                    Err(e) => {
                        tracing::warn!(dir = %replay.display(), error = %e, "replay not deleted")
                    }
                }
            }
            Ok::<(), LearnerError>(())
        })
        .await;
        if let Err(e) = done {
            tracing::warn!(error = %e, "releasing replays");
        }
    }

    /// While the data directory refuses writes: every few seconds, a probe write and, once it
    /// succeeds, the job store reopened (an I/O error poisons it); then jobs start again, a
    /// paused one from its last checkpoint.
    pub async fn recover_storage(self: Arc<Self>) {
        const EVERY: Duration = Duration::from_secs(2);
        while !self.shutting_down() {
            tokio::time::sleep(EVERY).await;
            if self.storage.healthy() {
                continue;
            }
            let (dir, jobs) = (self.data_dir.clone(), Arc::clone(&self.jobs));
            let r = tokio::task::spawn_blocking(move || {
                storage::probe(&dir).map_err(|source| LearnerError::Io {
                    action: "probing",
                    path: dir.clone(),
                    source,
                })?;
                jobs.reopen_store()
            })
            .await;
            match r {
                Ok(Ok(())) => {
                    self.storage.recovered();
                    self.wake.notify_one();
                }
                Ok(Err(e)) => self.storage.fault(&e.to_string()),
                Err(e) => tracing::error!(error = %e, "the storage probe task failed"),
            }
        }
    }

    /// Shutdown: starts nothing more, asks every running job to stop (a training job writes
    /// its checkpoint; both stay RUNNING and resume on the next start) and waits until every
    /// slot is free, or `grace` passed.
    pub async fn stop_all(&self, grace: Duration) {
        self.shutting_down.store(true, Ordering::Release);
        let deadline = tokio::time::Instant::now() + grace;
        for r in self.slots.all() {
            match &r {
                Running::Train(j) => {
                    tracing::info!(
                        job_id = j.id.get(),
                        "shutting down: checkpointing the running job"
                    )
                }
                // Stored cells stay stored; the job stays RUNNING and resumes with the rest.
                Running::Eval(e) => tracing::info!(
                    job_id = e.id.get(),
                    "shutting down: the evaluation resumes on the next start"
                ),
            }
            r.request_stop(StopReason::Shutdown);
        }
        loop {
            let idle = self.idle.notified();
            if self.slots.is_empty() {
                break;
            }
            if tokio::time::timeout_at(deadline, idle).await.is_err() {
                tracing::warn!("a running job did not stop (checkpoint) within the grace period");
                break;
            }
        }
    }
}

/// What a starting training job takes from its dependencies.
pub(crate) struct JobDeps {
    /// The frozen policies its workers act with (background, ego, adversary).
    pub frozen: Vec<Frozen>,
    /// `frozen`'s final weights, in order, when the job validates (`[validation]`); else empty.
    pub frozen_weights: Vec<Arc<Vec<u8>>>,
    /// `train.init_job`: a continuation starts from its checkpoint's critic and its final
    /// policy (`sf_sac::checkpoint::warm_start`).
    pub init: Option<InitDep>,
}

/// The dependencies of training job `cfg` among `jobs`: every one must have succeeded with a
/// final policy; the error names the field.
pub(crate) async fn job_deps(jobs: &Jobs, cfg: &JobConfig) -> Result<JobDeps, LearnerError> {
    let mut frozen = Vec::new();
    // Each frozen policy's artifact directory, for validation's weights.
    let mut dirs: HashMap<JobId, PathBuf> = HashMap::new();
    let mut init = None;
    for (role, dep) in cfg.deps() {
        let d = jobs.get(dep).map_err(|e| LearnerError::DependencyLookup {
            dep,
            field: role.field(),
            source: e.into(),
        })?;
        if d.state != JobState::Succeeded || !Path::new(&d.artifact_dir).join("policy.bpk").exists()
        {
            return Err(LearnerError::NoFinalPolicy {
                dep,
                field: role.field(),
                state: d.state.as_str(),
            });
        }
        match role {
            DepRole::Init => {
                init = Some(InitDep { job_id: dep, dir: PathBuf::from(&d.artifact_dir) })
            }
            DepRole::Ego => {
                dirs.insert(dep, PathBuf::from(&d.artifact_dir));
                frozen.push(Frozen::new(FrozenRole::Ego, dep, d.config_toml));
            }
            DepRole::Background => {
                let spec = jobs.spec(&d)?;
                let flow_cfg = spec
                    .train()
                    .ok_or_else(|| LearnerError::Dependency {
                        field: role.field(),
                        dep,
                        reason: "is an evaluation, not a training job".into(),
                    })?
                    .clone();
                let all = jobs.list();
                let fz = {
                    let jobs = all.clone();
                    tokio::task::spawn_blocking(move || {
                        deps::flow_frozen(&d, &flow_cfg, |id| {
                            jobs.iter()
                                .find(|r| r.id == id)
                                .cloned()
                                .ok_or(LearnerError::JobNotFound { job_id: id })
                        })
                    })
                    .await??
                };
                for f in &fz {
                    if let Some(r) = all.iter().find(|r| r.id == f.job_id) {
                        dirs.insert(f.job_id, PathBuf::from(&r.artifact_dir));
                    }
                }
                frozen.extend(fz);
            }
        }
    }
    // `[validation]` runs episodes with the frozen policies the workers fetch.
    let mut frozen_weights = Vec::new();
    if cfg.validation.is_some() {
        for f in &frozen {
            let job_id = f.job_id;
            let dir = dirs.get(&job_id).cloned().ok_or(LearnerError::JobNotFound { job_id })?;
            let bytes = tokio::task::spawn_blocking(move || read_final(&dir, job_id, "policy.bpk"))
                .await
                .map_err(|source| LearnerError::Task { task: "policy reading task", source })?;
            frozen_weights.push(Arc::new(bytes?));
        }
    }
    Ok(JobDeps { frozen, frozen_weights, init })
}
