//! The learner's Prometheus metrics (`socialflow_learner_*`).

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
    pub replay_size: Gauge,
    pub replay_bytes: Gauge,
    pub policy_version: Gauge,
    pub policy_lag: Histogram,
    pub critic_loss: FGauge,
    pub actor_loss: FGauge,
    pub alpha: FGauge,
    pub success: FGauge,
    pub safety: FGauge,
    pub speed: FGauge,
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
            replay_size: Gauge::default(),
            replay_bytes: Gauge::default(),
            policy_version: Gauge::default(),
            policy_lag: Histogram::new(exponential_buckets(1.0, 2.0, 8)),
            critic_loss: FGauge::default(),
            actor_loss: FGauge::default(),
            alpha: FGauge::default(),
            success: FGauge::default(),
            safety: FGauge::default(),
            speed: FGauge::default(),
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
            "socialflow_learner_replay_size_transitions",
            "Transitions held in the replay buffer",
            m.replay_size.clone(),
        );
        reg.register(
            "socialflow_learner_replay_bytes",
            "Bytes the replay buffer holds",
            m.replay_bytes.clone(),
        );
        reg.register(
            "socialflow_learner_policy_version",
            "Latest published policy version of the running job",
            m.policy_version.clone(),
        );
        reg.register(
            "socialflow_learner_policy_lag_versions",
            "Learner version minus the version that produced each received batch",
            m.policy_lag.clone(),
        );
        reg.register(
            "socialflow_learner_critic_loss",
            "Critic loss of the latest update",
            m.critic_loss.clone(),
        );
        reg.register(
            "socialflow_learner_actor_loss",
            "Actor loss of the latest update",
            m.actor_loss.clone(),
        );
        reg.register("socialflow_learner_alpha", "Entropy temperature", m.alpha.clone());
        reg.register(
            "socialflow_learner_episode_success_ratio",
            "Rolling success rate of finished episodes",
            m.success.clone(),
        );
        reg.register(
            "socialflow_learner_episode_safety_ratio",
            "Rolling safety rate of finished episodes",
            m.safety.clone(),
        );
        reg.register(
            "socialflow_learner_episode_speed_ratio",
            "Rolling mean speed / v_max of finished episodes",
            m.speed.clone(),
        );
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
