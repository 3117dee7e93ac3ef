//! A rollout worker that keeps no training state.
//!
//! Owns: the worker's session loop ([`run`]): connect, register, take an assignment, fetch the
//! policy, stream transitions, follow new policy versions, and start over with bounded backoff
//! when the learner goes away or the job ends. `session` only composes the parts, one job each
//! (Acme's actor side): `membership` (`register`, `Heartbeats`), `assignment`
//! (`next_assignment`, `load_job`), `policy` (`FrozenPolicies`, `PolicyClient`: the variable
//! client), [`rollout`] (the environment loop on its own thread and its `TransitionWriter`, the
//! adder) and `stream` (`PushTransitions` and its acknowledgements); an evaluation job's cells
//! ([`evalcell`]), one per assignment. Simulation and inference run on a dedicated rollout
//! thread or a blocking task (evaluation); the async side only moves bytes. Every unary call
//! has a deadline. What outlives one job: its config and name, metrics and its registration
//! (worker id, heartbeat interval), dropped after an error. Must not: keep a job, a policy or
//! transitions across sessions, or write to disk (everything comes from the learner).

mod assignment;
pub mod cmd;
pub mod evalcell;
mod membership;
mod policy;
pub mod rollout;
mod stream;

use std::path::PathBuf;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

use anyhow::{anyhow, Context};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use sf_proto::pb::experience_service_client::ExperienceServiceClient;
use sf_service::auth::{AttachToken, Token};
use sf_service::backoff::Backoff;
use sf_service::metrics::CommonMetrics;
use tokio::sync::watch;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::Request;

use crate::assignment::{load_job, next_assignment};
use crate::membership::{register, Heartbeats, Registration};
use crate::policy::{FrozenPolicies, PolicyClient};
use crate::rollout::{Rollout, RolloutSpec};
use crate::stream::stream;

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
    pub tls: sf_service::tls::ClientTls,
    /// Transition batches sent and not yet acknowledged, at most.
    pub in_flight_batches: u32,
}

/// The default window of unacknowledged batches: right for loopback and a LAN; across tens of
/// milliseconds ingest is bound by it (`docs/results/reliability.md`), where 8 carries it.
pub const DEFAULT_IN_FLIGHT_BATCHES: u32 = 2;

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
        reg.register(
            "socialflow_worker_env_steps",
            "Environment decision steps simulated",
            m.env_steps.clone(),
        );
        reg.register(
            "socialflow_worker_transitions_sent",
            "Learner transitions sent",
            m.transitions_sent.clone(),
        );
        reg.register(
            "socialflow_worker_batches_sent",
            "Transition batches sent",
            m.batches_sent.clone(),
        );
        reg.register("socialflow_worker_episodes", "Episodes finished", m.episodes.clone());
        reg.register(
            "socialflow_worker_policy_version",
            "Policy version acting now (0 = warm-up actions)",
            m.policy_version.clone(),
        );
        reg.register(
            "socialflow_worker_policy_fetches",
            "Policy weights fetched",
            m.policy_fetches.clone(),
        );
        reg.register(
            "socialflow_worker_sessions",
            "Sessions started (register + assignment); more than one means reconnects",
            m.sessions.clone(),
        );
        reg.register(
            "socialflow_worker_inference_observations",
            "Observations run through the actor",
            m.inference_obs.clone(),
        );
        reg.register(
            "socialflow_worker_inference_seconds",
            "Time spent in actor inference",
            m.inference_seconds.clone(),
        );
        reg.register(
            "socialflow_worker_eval_cells",
            "Evaluation cells run and pushed",
            m.eval_cells.clone(),
        );
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
pub async fn run(
    cfg: WorkerConfig,
    metrics: WorkerMetrics,
    mut stop: watch::Receiver<bool>,
) -> anyhow::Result<()> {
    let mut backoff = Backoff::new(Duration::from_millis(200), cfg.max_backoff);
    // Registered id and heartbeat interval, kept from one job to the next (a new registration
    // per job would leave the learner a stale worker to time out); dropped after an error.
    let mut registration: Option<Registration> = None;
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
    let ch = sf_service::tls::endpoint(&cfg.learner_url, &cfg.tls)?
        .connect()
        .await
        .with_context(|| format!("connecting to {}", cfg.learner_url))?;
    Ok(ExperienceServiceClient::with_interceptor(ch, AttachToken::new(cfg.token.clone()))
        .max_decoding_message_size(sf_service::MAX_MESSAGE_BYTES)
        .max_encoding_message_size(sf_service::MAX_MESSAGE_BYTES))
}

fn status_err(what: &str, s: tonic::Status, metrics: &WorkerMetrics) -> anyhow::Error {
    metrics.common.rpc(what, s.code());
    anyhow!("{what}: {} ({})", s.message(), sf_service::error::code_label(s.code()))
}

/// One session: who this worker is, what to work on, the policies to act with, then the
/// transition stream until the job or the connection ends.
async fn session(
    cfg: &WorkerConfig,
    metrics: &WorkerMetrics,
    registration: &mut Option<Registration>,
) -> anyhow::Result<SessionEnd> {
    let mut client = connect(cfg).await?;
    let me = match *registration {
        Some(r) => r,
        None => *registration.insert(register(&mut client, cfg, metrics).await?),
    };
    let mut heartbeats = Heartbeats::spawn(cfg, me, metrics).await?;
    let asg = next_assignment(&mut client, cfg, me.worker_id, &mut heartbeats, metrics).await?;
    let (job, maps) = load_job(cfg, me.worker_id, &asg)?;
    let frozen =
        FrozenPolicies::fetch(&client, me.worker_id, &asg.frozen, cfg.rpc_timeout, metrics).await?;
    let mut policy =
        PolicyClient::new(&client, asg.job_id, asg.policy_version, cfg.rpc_timeout, metrics);
    // The policy acts from the first step after the warm-up, and in it too where the job's
    // warm-up is its own (continued) policy: without weights that warm-up could not start, and
    // no acknowledgement would ever come to fetch them.
    let acts_in_warmup = job.sac.warmup_policy == sf_job::config::WarmupPolicy::Policy;
    let first = if asg.warmup && !acts_in_warmup { None } else { Some(policy.latest().await?) };
    let spec =
        RolloutSpec::for_assignment(&asg, job, frozen.into_vec(), maps, me.worker_id, cfg.threads);
    let (rollout, batches) =
        Rollout::start(spec, asg.warmup, first, cfg.in_flight_batches, metrics)?;
    stream(&mut client, batches, &rollout, &mut policy, &mut heartbeats, metrics).await
}
