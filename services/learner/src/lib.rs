//! The learner: owns all training state and serves the job and experience APIs.
//!
//! Owns: [`start`] (validates the [`LearnerConfig`] before any port is bound, binds the gRPC and
//! admin ports, opens the job store, starts the scheduler) and [`Inner`], the shared state
//! behind the handlers: the job store and every stored job's parsed [`sf_job::JobSpec`]
//! (parsed once), the running jobs ([`slot::Slots`]: training [`job::ActiveJob`]s side by side,
//! or one evaluation [`eval::EvalJob`] alone), the worker registry ([`workers::Workers`]),
//! metrics. The scheduler starts jobs while [`slot::Slots::admits`] them — RUNNING jobs left by
//! a previous process first (auto-resume from their checkpoints), then QUEUED jobs in id order,
//! a job behind an unfinished dependency skipped, an evaluation waiting for the running jobs to
//! end — a training job on a dedicated trainer thread ([`trainer`]) with its own replay, rate
//! limiter and metrics, an evaluation job ([`eval`]) by leasing its cells to the workers.
//! Training jobs share the workers (each gets the least served job; `experience.rs`). Must
//! not: expose wire types outside [`service`] (the gRPC edge), or pick a status for an error
//! (`error.rs` maps each domain error to one).
//!
//! Shutdown ([`RunningLearner::shutdown`], SIGTERM in the binary): the running jobs are asked
//! to stop, their trainers write checkpoints, the jobs stay RUNNING in the store and resume on
//! the next start.

mod artifacts;
pub mod cmd;
pub mod config;
mod deps;
mod error;
pub mod eval;
mod experience;
pub mod job;
pub mod metrics;
pub mod service;
pub mod slot;
pub mod storage;
pub mod store;
pub mod trainer;
pub mod validation;
pub mod workers;

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use prometheus_client::registry::Registry;
use sf_job::{JobRecord, JobSpec, JobState};
use sf_proto::pb::experience_service_server::ExperienceServiceServer;
use sf_proto::pb::job_service_server::JobServiceServer;
use sf_rollout::setup;
use sf_sac::RateLimiter;
use sf_service::auth::{RequireToken, Token, Transport};
use sf_service::ServiceError;
use sf_sim::Map;
use tokio::sync::{oneshot, Notify};
use tonic::service::interceptor::InterceptedService;

pub use crate::config::LearnerConfig;
pub use crate::error::{IngestError, LearnerError};
use crate::job::{ActiveJob, StopReason};
use crate::metrics::LearnerMetrics;
use crate::slot::{Kind, Running, Slots};
use crate::store::Store;
use crate::trainer::Outcome;
use crate::workers::Workers;
use sf_service::sync::lock;

/// State shared by the handlers, the scheduler and the trainer's completion task.
pub struct Inner {
    cfg: LearnerConfig,
    store: Arc<Store>,
    pub metrics: LearnerMetrics,
    /// The running training jobs or evaluation job.
    slots: Slots,
    wake: Notify,
    idle: Notify,
    workers: Workers,
    assignments: AtomicU64,
    shutting_down: AtomicBool,
    /// Every stored job's text, parsed once (by submit, or on first use after a restart): a
    /// stored config never changes, so the scheduler and job starts read it here.
    specs: Mutex<BTreeMap<u64, Arc<JobSpec>>>,
    /// Whether the data directory takes writes; while it does not, no job starts.
    storage: storage::StorageHealth,
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, store::StoreError> + Send + 'static,
) -> Result<T, ServiceError> {
    match tokio::task::spawn_blocking(f).await {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(LearnerError::Store(e).into()),
        Err(e) => Err(LearnerError::Join(e).into()),
    }
}

impl Inner {
    /// The running training job `id`.
    pub fn training(&self, id: u64) -> Option<Arc<ActiveJob>> {
        self.slots.train(id)
    }

    /// Every running training job, by id.
    pub fn trainings(&self) -> Vec<Arc<ActiveJob>> {
        self.slots.trains()
    }

    /// Why the data directory refuses writes, while it does.
    pub fn storage_fault(&self) -> Option<String> {
        self.storage.cause()
    }

    /// The running evaluation job.
    pub fn evaluating(&self) -> Option<Arc<eval::EvalJob>> {
        self.slots.eval()
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
    pub(crate) fn keep_spec(&self, id: u64, spec: JobSpec) {
        lock(&self.specs).insert(id, Arc::new(spec));
    }

    /// Live progress of the running job `id`, if it is running.
    fn live_progress(&self, id: u64) -> Option<sf_job::Progress> {
        self.slots.progress(id)
    }

    /// Loads and validates the job's scenario files off the async runtime (file IO).
    async fn load_maps(&self, names: &[String]) -> Result<Vec<Arc<Map>>, LearnerError> {
        let dir = self.cfg.scenarios_dir.clone();
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

    /// Validates a config and queues it.
    pub async fn submit(self: &Arc<Self>, toml_text: String) -> Result<JobRecord, ServiceError> {
        if self.shutting_down.load(Ordering::Acquire) {
            return Err(LearnerError::ShuttingDown.into());
        }
        if let Some(cause) = self.storage.cause() {
            return Err(LearnerError::StorageFault { cause }.into());
        }
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
            let rec = self.job(dep).await.map_err(|_| refuse("does not exist"))?;
            let dep_spec = self.spec(&rec)?;
            let Some(dep_cfg) = dep_spec.train() else {
                return Err(refuse("is an evaluation, not a training job").into());
            };
            deps::check_dep(&cfg, role, dep, dep_cfg)?;
            if matches!(rec.state, JobState::Failed | JobState::Cancelled) {
                return Err(refuse(&format!("is {}", rec.state.as_str())).into());
            }
        }
        let store = Arc::clone(&self.store);
        let name = cfg.name.clone();
        let target = cfg.train.env_steps;
        let rec = blocking(move || store.create(&name, &toml_text, target)).await?;
        self.keep_spec(rec.id, JobSpec::Train(cfg));
        tracing::info!(job_id = rec.id, name = %rec.name, "job queued");
        self.wake.notify_one();
        Ok(rec)
    }

    /// A job with live progress if it is running.
    pub async fn job(self: &Arc<Self>, id: u64) -> Result<JobRecord, ServiceError> {
        // Records are read from memory: no I/O, nothing to wait on.
        let mut rec = self.store.get(id).ok_or(LearnerError::JobNotFound { job_id: id })?;
        if let Some(p) = self.live_progress(id).filter(|_| !rec.state.is_final()) {
            rec.progress = p;
            rec.state = JobState::Running;
        }
        Ok(rec)
    }

    pub async fn jobs(self: &Arc<Self>) -> Result<Vec<JobRecord>, ServiceError> {
        let mut all = self.store.list();
        for r in all.iter_mut().filter(|r| !r.state.is_final()) {
            if let Some(p) = self.live_progress(r.id) {
                r.progress = p;
            }
        }
        Ok(all)
    }

    pub async fn cancel(self: &Arc<Self>, id: u64) -> Result<JobRecord, ServiceError> {
        let store = Arc::clone(&self.store);
        let rec = blocking(move || {
            store.update(id, |r| {
                r.advance(JobState::Cancelled, Some(CANCELLED_BY_REQUEST));
            })
        })
        .await?
        .ok_or(LearnerError::JobNotFound { job_id: id })?;
        if let Some(j) = self.training(id) {
            j.request_stop(StopReason::Cancelled);
        }
        if let Some(e) = self.evaluating().filter(|e| e.id == id) {
            e.request_stop(StopReason::Cancelled);
        }
        tracing::info!(job_id = id, state = rec.state.as_str(), "cancel requested");
        Ok(rec)
    }

    pub fn register_worker(&self, name: &str, runs_idm_ego: bool) -> u64 {
        self.workers.register(name, runs_idm_ego)
    }

    pub fn heartbeat(&self, id: u64) -> Result<(), ServiceError> {
        self.touch_worker(id)
    }

    /// Workers not yet forgotten for missing heartbeats.
    fn live_workers(&self) -> std::collections::BTreeSet<u64> {
        self.workers.live()
    }

    fn touch_worker(&self, id: u64) -> Result<(), ServiceError> {
        Ok(self.workers.touch(id)?)
    }

    /// Starts what may start now: RUNNING jobs of a previous process, then ready QUEUED jobs
    /// in id order, while the slots admit them.
    async fn schedule_once(self: &Arc<Self>) {
        if self.shutting_down.load(Ordering::Acquire) || !self.storage.healthy() {
            return;
        }
        let all = match self.jobs().await {
            Ok(a) => a,
            Err(e) => {
                tracing::error!(error = %e, "listing jobs");
                return;
            }
        };
        // A job waits until every job it depends on has succeeded; it fails if one did not.
        // (An evaluation's jobs succeeded before it was accepted: it has none to wait for.)
        let dep_state = |r: &JobRecord| -> Option<(u64, JobState)> {
            let deps = self.spec(r).ok()?.deps();
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
            let kind = match self.spec(rec) {
                Ok(s) if s.is_eval() => Kind::Eval,
                _ => Kind::Train,
            };
            if !self.slots.admits(kind, self.workers.live().len()) {
                // In order: a job does not overtake one that waits for room.
                return;
            }
            if !self.storage.healthy() || self.shutting_down.load(Ordering::Acquire) {
                return;
            }
            let rec = rec.clone();
            match self.start_job(&rec).await {
                Ok(()) => {}
                // The job waits, as it is, until the disk takes writes again.
                Err(e) if storage::is_storage_fault(&e) => {
                    self.storage.fault(&format!("starting job {}: {e}", rec.id))
                }
                Err(e) => {
                    tracing::error!(job_id = rec.id, error = %e, "job failed to start");
                    self.finish(rec.id, Outcome::Failed(e.to_string()), None).await;
                }
            }
        }
    }

    async fn start_job(self: &Arc<Self>, rec: &JobRecord) -> Result<(), LearnerError> {
        let spec = self.spec(rec)?;
        let cfg = match &*spec {
            JobSpec::Eval(grid) => return self.start_eval(rec, grid.clone()).await,
            JobSpec::Train(cfg) => cfg.clone(),
        };
        let maps = self.load_maps(&cfg.env.scenarios).await?;
        let dir = PathBuf::from(&rec.artifact_dir);
        let dir2 = dir.clone();
        let resume = tokio::task::spawn_blocking(move || trainer::load_state(&dir2)).await??;
        let capacity = cfg.train.replay_capacity as u64;
        let fill = if resume.is_some() {
            4 * cfg.sac.batch_size as u64
        } else {
            cfg.sac.warmup_steps.max(cfg.sac.batch_size as u64)
        };
        let limiter = RateLimiter::new(setup::rate_limiter(&cfg, fill.min(capacity)), capacity)?;
        let counters = resume.as_ref().map(|r| r.counters.clone()).unwrap_or_default();
        let deps::JobDeps { frozen, frozen_weights, init } = self.job_deps(&cfg).await?;
        let r = setup::resolve(&cfg, None);
        let (action_dim, spec, segment_points) =
            (r.net.action_dim, r.obs, r.sim.obs.segment_points);
        let maps2 = maps.clone();
        let segs = tokio::task::spawn_blocking(move || {
            maps2
                .iter()
                .map(|m| Arc::new(sf_sim::obs::MapSegments::build(m, segment_points)))
                .collect::<Vec<_>>()
        })
        .await?;
        let counts = segs.iter().map(|s| s.len()).collect();
        let job = Arc::new(ActiveJob::new(
            rec.id,
            cfg,
            frozen,
            spec,
            counts,
            action_dim,
            limiter,
            counters,
            metrics::JobMetrics::new(&self.metrics, rec.id),
        ));
        let store = Arc::clone(&self.store);
        let id = rec.id;
        // Active first, then RUNNING only if not cancelled meanwhile: a CancelJob either sees
        // the active job (and stops it) or wrote CANCELLED before this update (which keeps it).
        self.slots.fill(id, Running::Train(Arc::clone(&job)));
        let started = blocking(move || {
            store.update(id, |r| {
                r.advance(JobState::Running, None);
            })
        })
        .await;
        match started {
            Ok(Some(r)) if r.state == JobState::Running => {}
            other => {
                job.request_stop(StopReason::Cancelled);
                job.metrics.remove();
                self.slots.clear(id);
                self.wake.notify_one();
                return match other {
                    Err(e) => Err(e.into()),
                    _ => {
                        tracing::info!(job_id = id, "job cancelled before it started");
                        Ok(())
                    }
                };
            }
        }
        tracing::info!(job_id = id, resumed = resume.is_some(), "job started");
        let (tx, rx) = oneshot::channel();
        let input = trainer::TrainerInput {
            job: Arc::clone(&job),
            maps,
            segs,
            dir,
            resume,
            init,
            frozen_weights,
        };
        std::thread::Builder::new()
            .name(format!("trainer-{id}"))
            .spawn(move || {
                // A panic is a defect, but it must not leave the job without its cause.
                let out =
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| trainer::run(input)))
                        .unwrap_or_else(|p| {
                            let why = p
                                .downcast_ref::<String>()
                                .cloned()
                                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                                .unwrap_or_else(|| "no message".into());
                            Outcome::Failed(format!("the trainer panicked: {why}"))
                        });
                let _ = tx.send(out);
            })
            .map_err(LearnerError::SpawnTrainer)?;
        let me = Arc::clone(self);
        tokio::spawn(async move {
            let out =
                rx.await.unwrap_or_else(|_| Outcome::Failed("the trainer thread panicked".into()));
            me.finish(id, out, Some(job.progress())).await;
        });
        Ok(())
    }

    /// Records how a job ended and frees its slot.
    async fn finish(self: &Arc<Self>, id: u64, out: Outcome, progress: Option<sf_job::Progress>) {
        tracing::info!(job_id = id, outcome = ?out, "job stopped");
        if let Some(j) = self.training(id) {
            j.close();
            j.metrics.remove();
        }
        if let Outcome::Paused(cause) = &out {
            // Nothing to record: the job stays RUNNING at its last checkpoint.
            self.storage.fault(&format!("job {id}: {cause}"));
        } else {
            let store = Arc::clone(&self.store);
            let r = blocking(move || {
                store.update(id, |r| {
                    if let Some(p) = progress {
                        r.progress = p;
                    }
                    record_end(r, &out);
                })
            })
            .await;
            match r {
                Ok(_) => {}
                // Unrecorded, the job stays RUNNING and resumes (and ends again) after recovery.
                Err(e) if storage::is_storage_fault(&e) => {
                    self.storage.fault(&format!("recording the end of job {id}: {e}"))
                }
                Err(e) => tracing::error!(job_id = id, error = %e, "recording the job's end"),
            }
        }
        self.slots.clear(id);
        self.idle.notify_waiters();
        self.wake.notify_one();
    }
}

/// Why a job was cancelled when the request gave no reason.
const CANCELLED_BY_REQUEST: &str = "cancelled by request";

/// Records how a job ended in its record, unless it already ended (a cancel that came first
/// stays cancelled: [`JobRecord::advance`]). A shutdown leaves the job to resume.
fn record_end(r: &mut sf_job::JobRecord, out: &Outcome) {
    match out {
        Outcome::Succeeded => r.advance(JobState::Succeeded, None),
        Outcome::Cancelled => r.advance(JobState::Cancelled, Some(CANCELLED_BY_REQUEST)),
        Outcome::Shutdown | Outcome::Paused(_) => false,
        Outcome::Failed(m) => r.advance(JobState::Failed, Some(m.as_str())),
    };
}

/// A started learner.
pub struct RunningLearner {
    pub inner: Arc<Inner>,
    pub grpc_addr: SocketAddr,
    pub admin_addr: SocketAddr,
    stop_server: Option<oneshot::Sender<()>>,
    server: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
}

/// Rewrites tonic's OUT_OF_RANGE for oversized messages into the protocol's RESOURCE_EXHAUSTED
/// (trailers-only responses carry the status in headers).
fn size_status<B>(mut res: http::Response<B>) -> http::Response<B> {
    let h = res.headers_mut();
    let oversized = h.get("grpc-status").is_some_and(|v| v.as_bytes() == b"11")
        && h.get("grpc-message").is_some_and(|m| {
            m.to_str().is_ok_and(|m| {
                m.contains("message%20length%20too%20large")
                    || m.contains("message length too large")
            })
        });
    if oversized {
        h.insert("grpc-status", http::HeaderValue::from_static("8"));
    }
    res
}

/// Opens the store, binds both ports and starts serving and scheduling.
pub async fn start(cfg: LearnerConfig, token: Token) -> anyhow::Result<RunningLearner> {
    cfg.validate()?;
    std::fs::create_dir_all(cfg.data_dir.join("jobs"))
        .with_context(|| format!("creating {}", cfg.data_dir.display()))?;
    let store = Arc::new(Store::open(&cfg.data_dir.join("jobs.redb"), &cfg.data_dir)?);
    let mut registry = Registry::default();
    let metrics = LearnerMetrics::register(&mut registry);
    let grpc = tokio::net::TcpListener::bind(cfg.grpc_addr)
        .await
        .with_context(|| format!("binding gRPC port {}", cfg.grpc_addr))?;
    let grpc_addr = grpc.local_addr()?;
    let ready = Arc::new(AtomicBool::new(false));
    let m2 = metrics.clone();
    let admin_addr = sf_service::admin::serve(
        cfg.admin_addr,
        Arc::new(registry),
        Arc::clone(&ready),
        Arc::new(move || m2.common.refresh()),
    )
    .await?;
    let first_worker = (sf_job::now_unix_ms() % 1_000_000_000) * 1000;
    let inner = Arc::new(Inner {
        cfg: cfg.clone(),
        store,
        metrics: metrics.clone(),
        slots: Slots::new(cfg.running_job_limit(), metrics.running_jobs.clone()),
        wake: Notify::new(),
        idle: Notify::new(),
        workers: Workers::new(
            first_worker,
            Duration::from_secs(cfg.worker_timeout_s),
            metrics.workers.clone(),
        ),
        assignments: AtomicU64::new(0),
        shutting_down: AtomicBool::new(false),
        specs: Mutex::new(BTreeMap::new()),
        storage: storage::StorageHealth::new(
            Arc::clone(&ready),
            metrics.storage_ok.clone(),
            metrics.storage_faults.clone(),
        ),
    });
    let m3 = metrics.clone();
    let transport = match (cfg.tls_cert_file.is_some(), cfg.allow_plaintext_token) {
        (true, _) => Transport::Tls,
        (false, allow_remote) => Transport::Plaintext { allow_remote },
    };
    if transport == (Transport::Plaintext { allow_remote: false })
        && !cfg.grpc_addr.ip().is_loopback()
    {
        tracing::warn!(%grpc_addr, "serving plaintext: tokens from peers off loopback are refused (serve TLS, or set allow_plaintext_token on a trusted network)");
    }
    let auth =
        RequireToken::new(&token, move || m3.common.rpc("any", tonic::Code::Unauthenticated))
            .transport(transport);
    let max = cfg.max_message_bytes;
    let jobs = JobServiceServer::new(service::Jobs(Arc::clone(&inner)))
        .max_decoding_message_size(max)
        .max_encoding_message_size(max);
    let exp = ExperienceServiceServer::new(service::Experience(Arc::clone(&inner)))
        .max_decoding_message_size(max)
        .max_encoding_message_size(max);
    let (health_reporter, health) = tonic_health::server::health_reporter();
    health_reporter.set_serving::<JobServiceServer<service::Jobs>>().await;
    health_reporter.set_serving::<ExperienceServiceServer<service::Experience>>().await;
    // Reflection in both versions: `v1alpha` is what older clients (and some GUI clients) ask.
    let reflection_builder = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(sf_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection = reflection_builder().build_v1().context("gRPC reflection service (v1)")?;
    let reflection_v1alpha =
        reflection_builder().build_v1alpha().context("gRPC reflection service (v1alpha)")?;
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let incoming = tokio_stream::wrappers::TcpListenerStream::new(grpc);
    // HTTP/2 receive windows sized to the link (BDP estimates), not a fixed 1 MB: with fixed
    // windows ingest across tens of milliseconds is bound by window / round trip
    // (`docs/results/reliability.md`, slow links).
    let mut builder = tonic::transport::Server::builder().http2_adaptive_window(Some(true));
    if let (Some(c), Some(k)) = (&cfg.tls_cert_file, &cfg.tls_key_file) {
        builder = builder
            .tls_config(sf_service::tls::server(c, k, cfg.tls_client_ca_file.as_deref())?)
            .context("TLS server configuration")?;
    }
    let server = tokio::spawn(
        builder
            .layer(tower::util::MapResponseLayer::new(size_status))
            .add_service(InterceptedService::new(jobs, auth.clone()))
            .add_service(InterceptedService::new(exp, auth))
            // Health and reflection answer without a token: Kubernetes' gRPC probes cannot send
            // one, and neither reveals more than the public schema and "serving".
            .add_service(health)
            .add_service(reflection)
            .add_service(reflection_v1alpha)
            .serve_with_incoming_shutdown(incoming, async {
                let _ = stop_rx.await;
            }),
    );
    let sched = Arc::clone(&inner);
    tokio::spawn(async move {
        loop {
            sched.workers.prune();
            sched.count_workers_per_job();
            sched.schedule_once().await;
            if sched.shutting_down.load(Ordering::Acquire) {
                return;
            }
            tokio::select! {
                _ = sched.wake.notified() => {}
                _ = tokio::time::sleep(Duration::from_secs(1)) => {}
            }
        }
    });
    tokio::spawn(recover_storage(Arc::clone(&inner)));
    ready.store(inner.storage.healthy(), Ordering::Release);
    tracing::info!(%grpc_addr, %admin_addr, tls = cfg.tls_cert_file.is_some(), mutual_tls = cfg.tls_client_ca_file.is_some(), data_dir = %cfg.data_dir.display(), "learner serving");
    Ok(RunningLearner { inner, grpc_addr, admin_addr, stop_server: Some(stop_tx), server })
}

/// While the data directory refuses writes: every few seconds, a probe write and, once it
/// succeeds, the job store reopened (an I/O error poisons it); then jobs start again, a paused
/// one from its last checkpoint.
async fn recover_storage(inner: Arc<Inner>) {
    const EVERY: Duration = Duration::from_secs(2);
    while !inner.shutting_down.load(Ordering::Acquire) {
        tokio::time::sleep(EVERY).await;
        if inner.storage.healthy() {
            continue;
        }
        let (dir, store) = (inner.cfg.data_dir.clone(), Arc::clone(&inner.store));
        let r = tokio::task::spawn_blocking(move || {
            storage::probe(&dir).map_err(|source| LearnerError::Io {
                action: "probing",
                path: dir.clone(),
                source,
            })?;
            store.reopen().map_err(LearnerError::Store)
        })
        .await;
        match r {
            Ok(Ok(())) => {
                inner.storage.recovered();
                inner.wake.notify_one();
            }
            Ok(Err(e)) => inner.storage.fault(&e.to_string()),
            Err(e) => tracing::error!(error = %e, "the storage probe task failed"),
        }
    }
}

impl RunningLearner {
    /// Checkpoints the running jobs (they stay RUNNING) and stops serving.
    pub async fn shutdown(mut self) -> anyhow::Result<()> {
        let inner = &self.inner;
        inner.shutting_down.store(true, Ordering::Release);
        let deadline =
            tokio::time::Instant::now() + Duration::from_secs(inner.cfg.shutdown_grace_s);
        for j in inner.trainings() {
            tracing::info!(job_id = j.id, "shutting down: checkpointing the running job");
            j.request_stop(StopReason::Shutdown);
        }
        if let Some(e) = inner.evaluating() {
            // Stored cells stay stored; the job stays RUNNING and resumes with the rest.
            tracing::info!(
                job_id = e.id,
                "shutting down: the evaluation resumes on the next start"
            );
            e.request_stop(StopReason::Shutdown);
        }
        loop {
            let idle = inner.idle.notified();
            if inner.slots.is_empty() {
                break;
            }
            if tokio::time::timeout_at(deadline, idle).await.is_err() {
                tracing::warn!("a running job did not stop (checkpoint) within the grace period");
                break;
            }
        }
        if let Some(tx) = self.stop_server.take() {
            let _ = tx.send(());
        }
        match tokio::time::timeout(Duration::from_secs(5), &mut self.server).await {
            Ok(Ok(Ok(()))) | Err(_) => Ok(()),
            Ok(Ok(Err(e))) => Err(e).context("gRPC server"),
            Ok(Err(e)) => Err(e).context("gRPC server task"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sf_job::JobConfig;
    use std::path::Path;

    /// Every shipped config parses and validates: job configs as jobs, the learner's as such.
    #[test]
    fn every_shipped_config_file_is_valid() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let mut files: Vec<PathBuf> = std::fs::read_dir(root.join("configs"))
            .expect("configs/")
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "toml"))
            .collect();
        files.push(root.join("deploy/smoke-job.toml"));
        for sub in [
            "configs/paper-small",
            "configs/paper",
            "configs/ladder/jobs",
            "configs/ladder/l7-steering-adversary",
        ] {
            files.extend(
                std::fs::read_dir(root.join(sub))
                    .expect("pipeline dir")
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.extension().is_some_and(|x| x == "toml")),
            );
        }
        assert!(files.len() >= 3, "{files:?}");
        for f in files {
            let text = std::fs::read_to_string(&f).expect("readable");
            if f.file_name().is_some_and(|n| n == "learner.toml") {
                let c: LearnerConfig =
                    toml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
                assert!(c.max_message_bytes >= 1 << 16);
            } else {
                JobConfig::from_toml(&text).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            }
        }
    }

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
