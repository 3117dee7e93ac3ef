//! A stateless rollout worker.
//!
//! Owns: the worker's session loop ([`run`]): connect, register, take an assignment, fetch the
//! policy, stream transitions, follow new policy versions, and start over with bounded backoff
//! when the learner goes away or the job ends; an evaluation job's cells ([`evalcell`]), one
//! per assignment. Simulation and inference run on a dedicated rollout thread ([`rollout`]) or
//! a blocking task (evaluation); the async side only moves bytes. Every unary call has a
//! deadline. Must not: keep state across sessions (everything comes from the learner).

pub mod cmd;
pub mod evalcell;
pub mod rollout;

use std::path::PathBuf;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{anyhow, Context};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use sf_proto::pb;
use sf_proto::pb::experience_service_client::ExperienceServiceClient;
use sf_svc::auth::{AttachToken, Token};
use sf_svc::backoff::Backoff;
use sf_svc::metrics::CommonMetrics;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::{Code, Request};

use crate::rollout::{Control, Credits, RolloutSpec};
use sf_svc::sync::lock;

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// `http://host:port` of the learner.
    pub learner_url: String,
    pub name: String,
    pub scenarios_dir: PathBuf,
    /// Stored evaluation cases (evaluation jobs).
    pub cases_dir: PathBuf,
    pub token: Option<Token>,
    /// Deadline of every unary call.
    pub rpc_timeout: Duration,
    pub max_backoff: Duration,
    /// Rayon threads for stepping simulators (0 = rayon's default).
    pub threads: usize,
    /// Trust root for an `https://` learner and the worker's client certificate (mutual TLS).
    pub tls: sf_svc::tls::ClientTls,
}

#[derive(Clone)]
pub struct WorkerMetrics {
    pub common: CommonMetrics,
    pub env_steps: Counter,
    pub transitions_sent: Counter,
    pub batches_sent: Counter,
    pub episodes: Counter,
    pub policy_version: Gauge,
    pub policy_fetches: Counter,
    pub sessions: Counter,
    pub inference_obs: Counter,
    pub inference_seconds: Counter<f64, AtomicU64>,
    pub eval_cells: Counter,
}

impl WorkerMetrics {
    pub fn register(reg: &mut Registry) -> Self {
        let m = Self {
            common: CommonMetrics::register(reg, "worker"),
            env_steps: Counter::default(),
            transitions_sent: Counter::default(),
            batches_sent: Counter::default(),
            episodes: Counter::default(),
            policy_version: Gauge::default(),
            policy_fetches: Counter::default(),
            sessions: Counter::default(),
            inference_obs: Counter::default(),
            inference_seconds: Counter::default(),
            eval_cells: Counter::default(),
        };
        reg.register("socialflow_worker_env_steps", "Environment decision steps simulated", m.env_steps.clone());
        reg.register("socialflow_worker_transitions_sent", "Learner transitions sent", m.transitions_sent.clone());
        reg.register("socialflow_worker_batches_sent", "Transition batches sent", m.batches_sent.clone());
        reg.register("socialflow_worker_episodes", "Episodes finished", m.episodes.clone());
        reg.register("socialflow_worker_policy_version", "Policy version acting now (0 = warm-up actions)", m.policy_version.clone());
        reg.register("socialflow_worker_policy_fetches", "Policy weights fetched", m.policy_fetches.clone());
        reg.register("socialflow_worker_sessions", "Sessions started (register + assignment); more than one means reconnects", m.sessions.clone());
        reg.register("socialflow_worker_inference_observations", "Observations run through the actor", m.inference_obs.clone());
        reg.register("socialflow_worker_inference_seconds", "Time spent in actor inference", m.inference_seconds.clone());
        reg.register("socialflow_worker_eval_cells", "Evaluation cells run and pushed", m.eval_cells.clone());
        m
    }
}

type Client = ExperienceServiceClient<InterceptedService<Channel, AttachToken>>;

fn req<T>(msg: T, timeout: Duration) -> Request<T> {
    let mut r = Request::new(msg);
    r.set_timeout(timeout);
    r
}

/// Why a session ended.
#[derive(Debug)]
enum SessionEnd {
    /// The job stopped running: ask for a new assignment at once.
    JobEnded,
    /// Shutdown requested.
    Stop,
}

/// Runs sessions until `stop` turns true. Errors are logged and retried with backoff.
pub async fn run(cfg: WorkerConfig, metrics: WorkerMetrics, mut stop: watch::Receiver<bool>) -> anyhow::Result<()> {
    let mut backoff = Backoff::new(Duration::from_millis(200), cfg.max_backoff);
    // Registered id and heartbeat interval, kept from one job to the next (a new registration
    // per job would leave the learner a stale worker to time out); dropped after an error.
    let mut registration: Option<(u64, Duration)> = None;
    loop {
        if *stop.borrow() {
            return Ok(());
        }
        metrics.sessions.inc();
        let r = tokio::select! {
            r = session(&cfg, &metrics, &mut registration) => r,
            _ = stop.changed() => Ok(SessionEnd::Stop),
        };
        match r {
            Ok(SessionEnd::Stop) => return Ok(()),
            Ok(SessionEnd::JobEnded) => backoff.reset(),
            Err(e) => {
                registration = None;
                let d = backoff.next_delay();
                tracing::warn!(error = %format!("{e:#}"), retry_ms = d.as_millis() as u64, "session ended");
                tokio::select! {
                    _ = tokio::time::sleep(d) => {}
                    _ = stop.changed() => return Ok(()),
                }
            }
        }
    }
}

async fn connect(cfg: &WorkerConfig) -> anyhow::Result<Client> {
    let ch = sf_svc::tls::endpoint(&cfg.learner_url, &cfg.tls)?.connect().await.with_context(|| format!("connecting to {}", cfg.learner_url))?;
    Ok(ExperienceServiceClient::with_interceptor(ch, AttachToken::new(cfg.token.clone())).max_decoding_message_size(sf_svc::MAX_MESSAGE_BYTES).max_encoding_message_size(sf_svc::MAX_MESSAGE_BYTES))
}

fn status_err(what: &str, s: tonic::Status, metrics: &WorkerMetrics) -> anyhow::Error {
    metrics.common.rpc(what, s.code());
    anyhow!("{what}: {} ({})", s.message(), sf_svc::error::code_label(s.code()))
}

async fn session(cfg: &WorkerConfig, metrics: &WorkerMetrics, registration: &mut Option<(u64, Duration)>) -> anyhow::Result<SessionEnd> {
    let mut client = connect(cfg).await?;
    let t = cfg.rpc_timeout;
    let (worker_id, hb_every) = match *registration {
        Some(r) => r,
        None => {
            let reg = client.register(req(pb::RegisterRequest { name: cfg.name.clone() }, t)).await.map_err(|s| status_err("Register", s, metrics))?.into_inner();
            metrics.common.rpc("Register", Code::Ok);
            tracing::info!(worker_id = reg.worker_id, learner = %cfg.learner_url, "registered");
            let r = (reg.worker_id, Duration::from_millis(reg.heartbeat_interval_ms.clamp(200, 30_000) as u64));
            *registration = Some(r);
            r
        }
    };
    // Heartbeats on the side; a NOT_FOUND or repeated failure ends the session.
    let (hb_tx, mut hb_rx) = watch::channel(false);
    // Their own connection: on the shared one, a transition stream the learner is not reading
    // (its rate limiter holds inserts) fills HTTP/2's connection window and starves them.
    let mut hb_client = connect(cfg).await?;
    let hb_metrics = metrics.clone();
    let hb = tokio::spawn(async move {
        let mut fails = 0;
        loop {
            tokio::time::sleep(hb_every).await;
            match hb_client.heartbeat(req(pb::HeartbeatRequest { worker_id }, t)).await {
                Ok(_) => {
                    hb_metrics.common.rpc("Heartbeat", Code::Ok);
                    fails = 0
                }
                Err(s) => {
                    hb_metrics.common.rpc("Heartbeat", s.code());
                    fails += 1;
                    if s.code() == Code::NotFound || fails >= 3 {
                        let _ = hb_tx.send(true);
                        return;
                    }
                }
            }
        }
    });
    let _abort_hb = AbortOnDrop(hb);
    // Assignment: a training job's, or evaluation cells one after another until one comes.
    let mut cells = evalcell::Cells::new(cfg);
    let asg = loop {
        let r = client.get_assignment(req(pb::GetAssignmentRequest { worker_id }, t)).await.map_err(|s| status_err("GetAssignment", s, metrics))?.into_inner();
        metrics.common.rpc("GetAssignment", Code::Ok);
        if let (true, Some(a)) = (r.has_assignment, r.assignment) {
            break sf_proto::assignment_from_wire(&a).context("assignment from the learner")?;
        }
        if let (true, Some(w)) = (r.has_assignment, r.eval) {
            let work = sf_proto::eval_work_from_wire(&w).context("evaluation cell from the learner")?;
            tokio::select! {
                r = cells.run(&mut client, worker_id, work, t, metrics) => r?,
                _ = hb_rx.changed() => anyhow::bail!("heartbeats failed while running an evaluation cell"),
            }
            continue;
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_millis(r.retry_after_ms.clamp(100, 10_000) as u64)) => {}
            _ = hb_rx.changed() => anyhow::bail!("heartbeats failed while waiting for an assignment"),
        }
    };
    let job = sf_job::JobConfig::from_toml(&asg.config_toml).context("job config in the assignment")?;
    tracing::info!(worker_id, job_id = asg.job_id, scenarios = ?job.env.scenarios, policy_version = asg.policy_version, warmup = asg.warmup, "assignment");
    let maps = job
        .env
        .scenarios
        .iter()
        .map(|s| sf_sim::Map::load(&cfg.scenarios_dir.join(format!("{s}.json"))).map(Arc::new).with_context(|| format!("scenario `{s}`")))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let policy_client = client.clone();
    let fetch = |version: u64| {
        let mut c = policy_client.clone();
        let job_id = asg.job_id;
        async move {
            let p = c.get_policy(req(pb::GetPolicyRequest { job_id, version }, t)).await.map_err(|s| status_err("GetPolicy", s, metrics))?.into_inner();
            metrics.common.rpc("GetPolicy", Code::Ok);
            metrics.policy_fetches.inc();
            anyhow::Ok((p.version, p.weights))
        }
    };
    // Frozen policies (background flow, ego, adversary): their networks and final weights,
    // fetched once per assignment.
    let mut frozen = Vec::new();
    for f in &asg.frozen {
        let fj = sf_job::JobConfig::from_toml(&f.config_toml).with_context(|| format!("config of frozen job {}", f.job_id))?;
        let mut c = client.clone();
        let p = c.get_policy(req(pb::GetPolicyRequest { job_id: f.job_id, version: 0 }, t)).await.map_err(|s| status_err("GetPolicy", s, metrics))?.into_inner();
        metrics.common.rpc("GetPolicy", Code::Ok);
        tracing::info!(worker_id, frozen_job = f.job_id, role = ?f.role, version = p.version, "frozen policy");
        frozen.push((f.role, fj, p.weights));
    }
    let control = Arc::new(Mutex::new(Control { warmup: asg.warmup, policy: None, stop: false }));
    if !asg.warmup {
        let (v, w) = fetch(0).await?;
        lock(&control).policy = Some((v, w));
    }
    let (batch_tx, batch_rx) = mpsc::channel::<pb::TransitionBatch>(2);
    // CoPO Stage 2 in the background: each scenario's coordinator Gaussian, if it has one.
    let bg = asg.frozen.iter().find(|f| f.role == sf_job::FrozenRole::Background);
    let svo_gaussians: Vec<_> = job.env.scenarios.iter().map(|s| bg.and_then(|f| f.svo_gaussian(s))).collect();
    let redrawn = svo_gaussians.iter().flatten().count();
    if redrawn > 0 {
        tracing::info!(worker_id, "CoPO Stage 2: background SVOs redrawn every step from the coordinator's Gaussians in {redrawn} scenario(s)");
    }
    let spec = RolloutSpec { job, frozen, svo_gaussians, maps, worker_id, job_id: asg.job_id, seed: asg.seed, obs_len: asg.obs_len as usize, threads: cfg.threads };
    let credits = Arc::new(Credits::new(2));
    let rollout = rollout::spawn(spec, Arc::clone(&control), Arc::clone(&credits), batch_tx, metrics.clone())?;
    let _stop_rollout = StopOnDrop(Arc::clone(&control));
    let mut acks = client.push_transitions(ReceiverStream::new(batch_rx)).await.map_err(|s| status_err("PushTransitions", s, metrics))?.into_inner();
    let mut held = asg.policy_version;
    loop {
        let ack = tokio::select! {
            a = acks.message() => a,
            _ = hb_rx.changed() => anyhow::bail!("heartbeats failed"),
        };
        let ack = match ack {
            Ok(Some(a)) => a,
            Ok(None) => {
                if rollout.is_finished() {
                    anyhow::bail!("the rollout thread stopped");
                }
                anyhow::bail!("the learner closed the transition stream")
            }
            Err(s) if s.code() == Code::FailedPrecondition => {
                metrics.common.rpc("PushTransitions", s.code());
                tracing::info!(job_id = asg.job_id, reason = s.message(), "job ended");
                return Ok(SessionEnd::JobEnded);
            }
            Err(s) => return Err(status_err("PushTransitions", s, metrics)),
        };
        metrics.common.rpc("PushTransitions", Code::Ok);
        credits.grant();
        let warm = ack.warmup;
        let need = !warm && (ack.latest_policy_version > held || lock(&control).policy.is_none());
        if need {
            let (v, w) = fetch(0).await?;
            held = v;
            let mut c = lock(&control);
            c.policy = Some((v, w));
            c.warmup = false;
        } else if !warm {
            lock(&control).warmup = false;
        }
    }
}

struct AbortOnDrop(tokio::task::JoinHandle<()>);
impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

struct StopOnDrop(Arc<Mutex<Control>>);
impl Drop for StopOnDrop {
    fn drop(&mut self) {
        lock(&self.0).stop = true;
    }
}
