//! The worker's Prometheus metrics (`socialflow_worker_*`).
//!
//! Owns: [`WorkerMetrics`], registered once per process; they outlive every session. Must not:
//! hold session state.

use std::sync::atomic::AtomicU64;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::registry::Registry;
use sf_service::metrics::CommonMetrics;

/// The worker's counters and gauges.
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
    pub in_flight_window: Gauge,
    pub link_min_rtt_seconds: Gauge<f64, AtomicU64>,
    pub link_acked_batches_per_second: Gauge<f64, AtomicU64>,
}

impl WorkerMetrics {
    /// Registers every metric in `reg`.
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
            in_flight_window: Gauge::default(),
            link_min_rtt_seconds: Gauge::default(),
            link_acked_batches_per_second: Gauge::default(),
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
            "socialflow_worker_in_flight_window",
            "Transition batches the worker may have unacknowledged now (sized to the link, up to --in-flight-batches)",
            m.in_flight_window.clone(),
        );
        reg.register(
            "socialflow_worker_link_min_rtt_seconds",
            "Shortest recent round trip of a transition batch (sent to acknowledged), which the window is sized from",
            m.link_min_rtt_seconds.clone(),
        );
        reg.register(
            "socialflow_worker_link_acked_batches_per_second",
            "Fastest recent rate of acknowledged transition batches, which the window is sized from",
            m.link_acked_batches_per_second.clone(),
        );
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
