//! The learner's Prometheus metrics (`socialflow_learner_*`).
//!
//! Owns: [`LearnerMetrics`] (the learner's totals: transitions, updates, episodes, workers,
//! storage, evaluation) and [`JobMetrics`], one running training job's series labelled
//! `job="<id>"` (replay, policy version, losses, rolling episode ratios, its own update and
//! transition counters), removed when the job stops. Several jobs train at once, so nothing
//! that belongs to one job is an unlabelled gauge.

use std::sync::atomic::AtomicU64;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use sf_service::metrics::CommonMetrics;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReasonLabel {
    pub reason: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct JobLabel {
    pub job: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ScenarioLabel {
    pub scenario: String,
}

type FGauge = Gauge<f64, AtomicU64>;

#[derive(Clone)]
pub struct LearnerMetrics {
    pub common: CommonMetrics,
    pub transitions_received: Counter,
    pub transitions_dropped: Family<ReasonLabel, Counter>,
    pub env_steps: Counter,
    pub updates: Counter,
    pub episodes: Family<ScenarioLabel, Counter>,
    pub policy_lag: Histogram,
    pub jobs: JobFamilies,
    pub running_jobs: Gauge,
    pub workers: Gauge,
    pub checkpoints: Counter,
    pub eval_episodes: Counter,
    pub eval_cells_pending: Gauge,
    pub eval_cells_reassigned: Counter,
    pub storage_ok: Gauge,
    pub storage_faults: Counter,
}

impl LearnerMetrics {
    pub fn register(reg: &mut Registry) -> Self {
        let m = Self {
            common: CommonMetrics::register(reg, "learner"),
            transitions_received: Counter::default(),
            transitions_dropped: Family::default(),
            env_steps: Counter::default(),
            updates: Counter::default(),
            episodes: Family::default(),
            policy_lag: Histogram::new(exponential_buckets(1.0, 2.0, 8)),
            jobs: JobFamilies::default(),
            running_jobs: Gauge::default(),
            workers: Gauge::default(),
            checkpoints: Counter::default(),
            eval_episodes: Counter::default(),
            eval_cells_pending: Gauge::default(),
            eval_cells_reassigned: Counter::default(),
            storage_ok: Gauge::default(),
            storage_faults: Counter::default(),
        };
        reg.register("socialflow_learner_storage_ok", "1 while the data directory takes writes, 0 while it refuses them (full, read-only, failing)", m.storage_ok.clone());
        reg.register(
            "socialflow_learner_storage_faults",
            "Writes to the data directory refused by the disk (each attempt)",
            m.storage_faults.clone(),
        );
        reg.register(
            "socialflow_learner_transitions_received",
            "Learner transitions accepted into replay",
            m.transitions_received.clone(),
        );
        reg.register(
            "socialflow_learner_transitions_dropped",
            "Transitions dropped, by reason (stale: over the policy lag)",
            m.transitions_dropped.clone(),
        );
        reg.register(
            "socialflow_learner_env_steps",
            "Vehicle decision steps simulated by workers",
            m.env_steps.clone(),
        );
        reg.register(
            "socialflow_learner_updates",
            "SAC updates (critic, actor, alpha, Polyak)",
            m.updates.clone(),
        );
        reg.register(
            "socialflow_learner_episodes",
            "Episodes finished by workers, by scenario",
            m.episodes.clone(),
        );
        reg.register(
            "socialflow_learner_running_jobs",
            "Training and evaluation jobs running now",
            m.running_jobs.clone(),
        );
        reg.register(
            "socialflow_learner_policy_lag_versions",
            "Learner version minus the version that produced each received batch",
            m.policy_lag.clone(),
        );
        m.jobs.register(reg);
        reg.register(
            "socialflow_learner_workers",
            "Workers that sent a heartbeat recently",
            m.workers.clone(),
        );
        reg.register(
            "socialflow_learner_checkpoints",
            "Checkpoints written",
            m.checkpoints.clone(),
        );
        reg.register(
            "socialflow_learner_eval_episodes",
            "Evaluated episodes stored by evaluation jobs",
            m.eval_episodes.clone(),
        );
        reg.register(
            "socialflow_learner_eval_cells_pending",
            "Cells of the running evaluation job not yet stored (queued or leased)",
            m.eval_cells_pending.clone(),
        );
        reg.register(
            "socialflow_learner_eval_cells_reassigned",
            "Leased cells handed to another worker because theirs stopped heartbeating",
            m.eval_cells_reassigned.clone(),
        );
        m
    }
}

type Per<M> = Family<JobLabel, M>;

/// The per-job series (label `job`), one family per quantity.
#[derive(Clone, Default)]
pub struct JobFamilies {
    transitions: Per<Counter>,
    updates: Per<Counter>,
    workers: Per<Gauge>,
    replay_size: Per<Gauge>,
    replay_bytes: Per<Gauge>,
    policy_version: Per<Gauge>,
    critic_loss: Per<FGauge>,
    actor_loss: Per<FGauge>,
    alpha: Per<FGauge>,
    success: Per<FGauge>,
    safety: Per<FGauge>,
    speed: Per<FGauge>,
}

impl JobFamilies {
    fn register(&self, reg: &mut Registry) {
        let f = self;
        reg.register(
            "socialflow_learner_job_transitions_received",
            "Transitions accepted into the job's replay",
            f.transitions.clone(),
        );
        reg.register("socialflow_learner_job_updates", "The job's SAC updates", f.updates.clone());
        reg.register(
            "socialflow_learner_job_workers",
            "Live workers assigned to the job",
            f.workers.clone(),
        );
        reg.register(
            "socialflow_learner_replay_size_transitions",
            "Transitions held in the job's replay buffer",
            f.replay_size.clone(),
        );
        reg.register(
            "socialflow_learner_replay_bytes",
            "Bytes the job's replay buffer holds",
            f.replay_bytes.clone(),
        );
        reg.register(
            "socialflow_learner_policy_version",
            "Latest published policy version of the job",
            f.policy_version.clone(),
        );
        reg.register(
            "socialflow_learner_critic_loss",
            "Critic loss of the job's latest update",
            f.critic_loss.clone(),
        );
        reg.register(
            "socialflow_learner_actor_loss",
            "Actor loss of the job's latest update",
            f.actor_loss.clone(),
        );
        reg.register("socialflow_learner_alpha", "The job's entropy temperature", f.alpha.clone());
        reg.register(
            "socialflow_learner_episode_success_ratio",
            "Rolling success rate of the job's finished episodes",
            f.success.clone(),
        );
        reg.register(
            "socialflow_learner_episode_safety_ratio",
            "Rolling safety rate of the job's finished episodes",
            f.safety.clone(),
        );
        reg.register(
            "socialflow_learner_episode_speed_ratio",
            "Rolling mean speed / v_max of the job's finished episodes",
            f.speed.clone(),
        );
    }
}

/// One running job's series and the learner's totals it adds to.
#[derive(Clone)]
pub struct JobMetrics {
    pub totals: LearnerMetrics,
    label: JobLabel,
    pub transitions: Counter,
    pub updates: Counter,
    pub workers: Gauge,
    pub replay_size: Gauge,
    pub replay_bytes: Gauge,
    pub policy_version: Gauge,
    pub critic_loss: FGauge,
    pub actor_loss: FGauge,
    pub alpha: FGauge,
    pub success: FGauge,
    pub safety: FGauge,
    pub speed: FGauge,
}

impl JobMetrics {
    /// The series of job `id` (created, or the existing ones of a job started again).
    pub fn new(totals: &LearnerMetrics, id: u64) -> Self {
        let label = JobLabel { job: id.to_string() };
        let f = &totals.jobs;
        Self {
            transitions: f.transitions.get_or_create(&label).clone(),
            updates: f.updates.get_or_create(&label).clone(),
            workers: f.workers.get_or_create(&label).clone(),
            replay_size: f.replay_size.get_or_create(&label).clone(),
            replay_bytes: f.replay_bytes.get_or_create(&label).clone(),
            policy_version: f.policy_version.get_or_create(&label).clone(),
            critic_loss: f.critic_loss.get_or_create(&label).clone(),
            actor_loss: f.actor_loss.get_or_create(&label).clone(),
            alpha: f.alpha.get_or_create(&label).clone(),
            success: f.success.get_or_create(&label).clone(),
            safety: f.safety.get_or_create(&label).clone(),
            speed: f.speed.get_or_create(&label).clone(),
            totals: totals.clone(),
            label,
        }
    }

    /// Removes the job's series (it stopped): a scrape shows only running jobs.
    pub fn remove(&self) {
        let (f, l) = (&self.totals.jobs, &self.label);
        f.transitions.remove(l);
        f.updates.remove(l);
        f.workers.remove(l);
        f.replay_size.remove(l);
        f.replay_bytes.remove(l);
        f.policy_version.remove(l);
        f.critic_loss.remove(l);
        f.actor_loss.remove(l);
        f.alpha.remove(l);
        f.success.remove(l);
        f.safety.remove(l);
        f.speed.remove(l);
    }
}
