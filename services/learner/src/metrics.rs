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
use sf_job::JobId;
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

/// The per-job series, written once: each row is a field, its metric kind, its Prometheus name
/// and help. Makes [`JobFamilies`] (one family per quantity, label `job`, registered with the
/// learner's registry) and [`JobMetrics`] (one running job's series, made by `new` and removed
/// by `remove` when the job stops), so the three lists cannot drift apart.
macro_rules! job_series {
    ($($field:ident: $kind:ty = $name:literal, $help:literal;)*) => {
        /// The per-job series (label `job`), one family per quantity.
        #[derive(Clone, Default)]
        pub struct JobFamilies {
            $($field: Per<$kind>,)*
        }

        impl JobFamilies {
            fn register(&self, reg: &mut Registry) {
                $(reg.register($name, $help, self.$field.clone());)*
            }
        }

        /// One running job's series and the learner's totals it adds to.
        #[derive(Clone)]
        pub struct JobMetrics {
            pub totals: LearnerMetrics,
            label: JobLabel,
            $(pub $field: $kind,)*
        }

        impl JobMetrics {
            /// The series of job `id` (created, or the existing ones of a job started again).
            pub fn new(totals: &LearnerMetrics, id: JobId) -> Self {
                let label = JobLabel { job: id.to_string() };
                let f = &totals.jobs;
                Self {
                    $($field: f.$field.get_or_create(&label).clone(),)*
                    totals: totals.clone(),
                    label,
                }
            }

            /// Removes the job's series (it stopped): a scrape shows only running jobs.
            pub fn remove(&self) {
                $(self.totals.jobs.$field.remove(&self.label);)*
            }
        }
    };
}

job_series! {
    transitions: Counter = "socialflow_learner_job_transitions_received", "Transitions accepted into the job's replay";
    updates: Counter = "socialflow_learner_job_updates", "The job's SAC updates";
    workers: Gauge = "socialflow_learner_job_workers", "Live workers assigned to the job";
    replay_size: Gauge = "socialflow_learner_replay_size_transitions", "Transitions held in the job's replay buffer";
    replay_bytes: Gauge = "socialflow_learner_replay_bytes", "Bytes the job's replay buffer holds";
    policy_version: Gauge = "socialflow_learner_policy_version", "Latest published policy version of the job";
    critic_loss: FGauge = "socialflow_learner_critic_loss", "Critic loss of the job's latest update";
    actor_loss: FGauge = "socialflow_learner_actor_loss", "Actor loss of the job's latest update";
    alpha: FGauge = "socialflow_learner_alpha", "The job's entropy temperature";
    success: FGauge = "socialflow_learner_episode_success_ratio", "Rolling success rate of the job's finished episodes";
    safety: FGauge = "socialflow_learner_episode_safety_ratio", "Rolling safety rate of the job's finished episodes";
    speed: FGauge = "socialflow_learner_episode_speed_ratio", "Rolling mean speed / v_max of the job's finished episodes";
}
