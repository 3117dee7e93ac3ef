//! The running job's shared state: what RPC handlers and the trainer thread both touch.
//!
//! Owns: [`ActiveJob`] — the replay buffer, the rate limiter, published policy versions, the
//! counters and rolling episode statistics, and the stop request. Ingest ([`ActiveJob::ingest`])
//! validates a batch against the job, drops stale data, waits on the rate limiter and copies
//! rows into replay; it blocks, so async handlers call it through `spawn_blocking`.
//! Must not: run tensor code (the trainer thread does).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use sf_job::{
    ActedBy, Ends, EpisodeResult, JobConfig, JobId, PolicyVersion, Progress, TransitionBatch,
};
use sf_sac::rate_limiter::RateLimitError;
use sf_sac::replay::Stored;
use sf_sac::{Losses, RateLimiter, Replay};
use tokio::sync::watch;

use crate::error::IngestError;
use crate::metrics::JobMetrics;
use sf_service::sync::{lock, read, write};

/// Why the trainer should stop.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopReason {
    Cancelled,
    /// The learner is shutting down: checkpoint and leave the job RUNNING for the next start.
    Shutdown,
}

/// One published policy version.
#[derive(Clone)]
pub struct Published {
    pub version: PolicyVersion,
    pub weights: Arc<Vec<u8>>,
}

/// Counters and statistics, restored from the job's checkpoint on resume.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct Counters {
    pub env_steps: u64,
    pub episodes: u64,
    pub dropped_stale: u64,
    pub sim_steps: u64,
    pub wall_s: f64,
}

pub struct Stats {
    pub c: Counters,
    /// Transitions admitted (reserved) toward the target, including ones being inserted.
    reserved: u64,
    window: VecDeque<EpisodeResult>,
    pub losses: Losses,
    pub updates: u64,
    rate: VecDeque<(Instant, u64)>,
    /// Policy lag of the batches since [`ActiveJob::take_mean_lag`] last read it.
    lag_sum: u64,
    lag_batches: u64,
    /// `[validation]`: the last and best held-out points (what progress shows).
    validation: Option<sf_job::ValidationProgress>,
}

/// The reply to one batch.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ack {
    pub accepted: u32,
    pub dropped_stale: u32,
    pub latest_policy_version: PolicyVersion,
    pub warmup: bool,
}

pub struct ActiveJob {
    pub id: JobId,
    pub cfg: JobConfig,
    /// `cfg` resolved once when the job started (network, observation layout, SAC config,
    /// simulator settings): what the trainer builds and ingest checks against.
    pub resolved: Arc<sf_rollout::setup::ResolvedJob>,
    /// The frozen policies the job acts with (background flow, ego, adversary).
    pub frozen: Vec<sf_job::Frozen>,
    pub obs_len: usize,
    pub action_dim: usize,
    /// Per map id, the map's segment count: with `resolved.obs`, what ingest checks before a
    /// row can reach the networks.
    segments: Vec<usize>,
    pub replay: Mutex<Replay>,
    pub limiter: RateLimiter,
    latest: RwLock<Option<Published>>,
    /// Recent versions kept for workers that ask for one by number.
    recent: Mutex<VecDeque<Published>>,
    pub versions: watch::Sender<PolicyVersion>,
    stats: Mutex<Stats>,
    stop: Mutex<Option<StopReason>>,
    stopping: AtomicBool,
    /// All transitions are in.
    complete: AtomicBool,
    next_scenario: AtomicU64,
    started: Instant,
    pub metrics: JobMetrics,
}

impl ActiveJob {
    #[allow(clippy::too_many_arguments)]
    /// `resolved`: `cfg` resolved (once, by whoever starts the job). `segments`: per map id
    /// (the job's scenarios in order), its query-centric segment count.
    pub fn new(
        id: JobId,
        cfg: JobConfig,
        resolved: Arc<sf_rollout::setup::ResolvedJob>,
        frozen: Vec<sf_job::Frozen>,
        segments: Vec<usize>,
        limiter: RateLimiter,
        restored: Counters,
        metrics: JobMetrics,
    ) -> Self {
        let (obs_len, action_dim) = (resolved.obs.len, resolved.net.action_dim);
        let replay = Replay::new(cfg.train.replay_capacity, obs_len, action_dim);
        let complete = restored.env_steps >= cfg.train.env_steps;
        Self {
            id,
            resolved,
            frozen,
            obs_len,
            action_dim,
            segments,
            replay: Mutex::new(replay),
            limiter,
            latest: RwLock::new(None),
            recent: Mutex::new(VecDeque::new()),
            versions: watch::channel(PolicyVersion::default()).0,
            stats: Mutex::new(Stats {
                reserved: restored.env_steps,
                c: restored,
                window: VecDeque::new(),
                losses: Losses::default(),
                updates: 0,
                rate: VecDeque::new(),
                lag_sum: 0,
                lag_batches: 0,
                validation: None,
            }),
            stop: Mutex::new(None),
            stopping: AtomicBool::new(false),
            complete: AtomicBool::new(complete),
            next_scenario: AtomicU64::new(0),
            started: Instant::now(),
            cfg,
            metrics,
        }
    }

    pub fn request_stop(&self, why: StopReason) {
        lock(&self.stop).get_or_insert(why);
        self.stopping.store(true, Ordering::Release);
        self.limiter.close();
    }

    /// The job ended (failed, or finished): batches waiting on the rate limiter return at once
    /// with FAILED_PRECONDITION, so workers move on instead of waiting out their deadline.
    pub fn close(&self) {
        self.stopping.store(true, Ordering::Release);
        self.limiter.close();
    }

    pub fn stop_reason(&self) -> Option<StopReason> {
        *lock(&self.stop)
    }

    pub fn is_complete(&self) -> bool {
        self.complete.load(Ordering::Acquire)
    }

    /// The scenario index for the next worker assignment (round robin).
    pub fn next_scenario(&self) -> u32 {
        (self.next_scenario.fetch_add(1, Ordering::Relaxed) % self.cfg.env.scenarios.len() as u64)
            as u32
    }

    pub fn latest(&self) -> Option<Published> {
        read(&self.latest).clone()
    }

    /// The latest published version; 0 before the first.
    pub fn latest_version(&self) -> PolicyVersion {
        self.latest().map(|p| p.version).unwrap_or_default()
    }

    /// A version still held, or `None`.
    pub fn version(&self, v: PolicyVersion) -> Option<Published> {
        lock(&self.recent).iter().find(|p| p.version == v).cloned()
    }

    /// Publishes a new policy version to workers.
    pub fn publish(&self, version: PolicyVersion, weights: Vec<u8>) {
        let p = Published { version, weights: Arc::new(weights) };
        {
            let mut r = lock(&self.recent);
            r.push_back(p.clone());
            while r.len() > 4 {
                r.pop_front();
            }
        }
        *write(&self.latest) = Some(p);
        self.versions.send_replace(version);
        self.metrics.policy_version.set(version.get() as i64);
    }

    /// Workers act with the warm-up policy (random or the IDM demonstrator) until
    /// `sac.warmup_steps` transitions are in.
    pub fn in_warmup(&self) -> bool {
        lock(&self.stats).c.env_steps < self.cfg.sac.warmup_steps
    }

    /// Validates `b` against the job, drops it if stale, waits on the rate limiter until
    /// `deadline`, then stores it. Blocking.
    pub fn ingest(&self, b: &TransitionBatch, deadline: Instant) -> Result<Ack, IngestError> {
        self.check(b)?;
        let latest = self.latest_version();
        if let Some(version) = b.acted_by.version().filter(|&v| v > latest) {
            return Err(IngestError::UnpublishedVersion { version, latest });
        }
        let warm = self.in_warmup();
        let ack = |accepted: usize, dropped: usize| Ack {
            accepted: accepted as u32,
            dropped_stale: dropped as u32,
            latest_policy_version: latest,
            warmup: warm,
        };
        if self.is_stale(b.acted_by, latest, warm) {
            lock(&self.stats).c.dropped_stale += b.count as u64;
            self.metrics
                .totals
                .transitions_dropped
                .get_or_create(&crate::metrics::ReasonLabel { reason: "stale".into() })
                .inc_by(b.count as u64);
            return Ok(ack(0, b.count));
        }
        let take = self.reserve(b.count)?;
        self.admit(take, deadline)?;
        self.store(b, take)?;
        self.count(b, take);
        Ok(ack(take, b.count - take))
    }

    /// What the networks index or branch on: widths, map ids, and every observation row
    /// (masks, segment ids), so one bad row refuses the batch here instead of failing the job
    /// in the trainer.
    fn check(&self, b: &TransitionBatch) -> Result<(), IngestError> {
        if self.stopping.load(Ordering::Acquire) {
            return Err(IngestError::Stopping { job_id: self.id });
        }
        if b.obs_len != self.obs_len || b.action_dim != self.action_dim {
            return Err(IngestError::Shape {
                obs_len: b.obs_len,
                action_dim: b.action_dim,
                job_id: self.id,
                want_obs_len: self.obs_len,
                want_action_dim: self.action_dim,
            });
        }
        let n_maps = self.cfg.env.scenarios.len() as u32;
        if let Some(&m) = b.map_ids.iter().find(|&&m| m >= n_maps) {
            return Err(IngestError::MapOutOfRange { map_id: m, job_id: self.id, maps: n_maps });
        }
        if let Some(&steps) = b.steps.iter().find(|&&s| s > self.cfg.sac.n_step) {
            return Err(IngestError::Span { steps, job_id: self.id, n_step: self.cfg.sac.n_step });
        }
        let ol = self.obs_len;
        for i in 0..b.count {
            let segments = self.segments.get(b.map_ids[i] as usize).copied().unwrap_or(0);
            for (field, rows) in [("obs_f16", &b.obs), ("next_obs_f16", &b.next_obs)] {
                self.resolved
                    .obs
                    .check_row(&rows[i * ol..(i + 1) * ol], segments)
                    .map_err(|reason| IngestError::BadRow { field, index: i, reason })?;
            }
        }
        Ok(())
    }

    /// Whether a batch acted by `acted_by` is dropped: warm-up data once the warm-up is over, a
    /// policy's data more than `max_policy_lag` versions old. Records the lag.
    fn is_stale(&self, acted_by: ActedBy, latest: PolicyVersion, warm: bool) -> bool {
        let Some(version) = acted_by.version() else { return !warm };
        let lag = latest.lag_of(version);
        self.metrics.totals.policy_lag.observe(lag as f64);
        let mut s = lock(&self.stats);
        s.lag_sum += lag;
        s.lag_batches += 1;
        lag > self.cfg.train.max_policy_lag
    }

    /// Reserves up to `count` of the transitions the job still needs.
    fn reserve(&self, count: usize) -> Result<usize, IngestError> {
        let mut s = lock(&self.stats);
        let take = (count as u64).min(self.cfg.train.env_steps.saturating_sub(s.reserved));
        if take == 0 {
            // Every transition the job needs is in; the trainer is finishing its updates.
            return Err(IngestError::Complete { job_id: self.id });
        }
        s.reserved += take;
        Ok(take as usize)
    }

    /// Waits until the rate limiter lets `take` transitions in (or `deadline`, or the job
    /// stops: the reservation is released).
    fn admit(&self, take: usize, deadline: Instant) -> Result<(), IngestError> {
        loop {
            let now = Instant::now();
            if now >= deadline {
                self.unreserve(take);
                return Err(IngestError::Deadline);
            }
            match self.limiter.insert(take as u64, (deadline - now).min(Duration::from_millis(250)))
            {
                Ok(()) => return Ok(()),
                Err(RateLimitError::Timeout(_)) => continue,
                Err(RateLimitError::Closed) => {
                    self.unreserve(take);
                    return Err(IngestError::Stopping { job_id: self.id });
                }
                Err(e @ RateLimitError::Invalid { .. }) => return Err(IngestError::RateLimit(e)),
            }
        }
    }

    /// Copies the first `take` rows into the replay.
    fn store(&self, b: &TransitionBatch, take: usize) -> Result<(), IngestError> {
        let mut r = lock(&self.replay);
        let (ol, ad) = (self.obs_len, self.action_dim);
        for i in 0..take {
            // Decoding validated shapes and values, so this cannot fail; if it did, the rows
            // already stored stay and the rest is released so the job can still complete.
            let row = Stored {
                obs: &b.obs[i * ol..(i + 1) * ol],
                next_obs: &b.next_obs[i * ol..(i + 1) * ol],
                action: &b.actions[i * ad..(i + 1) * ad],
                reward: b.rewards[i],
                terminal: b.terminals[i],
                steps: b.steps[i],
                map_id: b.map_ids[i],
                oracle: b.oracle_actions.get(i * ad..(i + 1) * ad).unwrap_or(&[]),
            };
            if let Err(e) = r.push_f16(row) {
                drop(r);
                let mut s = lock(&self.stats);
                s.reserved -= (take - i) as u64;
                s.c.env_steps += i as u64;
                return Err(IngestError::Replay(e));
            }
        }
        self.metrics.replay_size.set(r.len() as i64);
        self.metrics.replay_bytes.set((r.len() * r.bytes_per_transition()) as i64);
        Ok(())
    }

    /// Counts a stored batch: counters, the rolling episode window, the transition rate,
    /// completion and the metrics.
    fn count(&self, b: &TransitionBatch, take: usize) {
        self.metrics.transitions.inc_by(take as u64);
        self.metrics.totals.transitions_received.inc_by(take as u64);
        self.metrics.totals.env_steps.inc_by(b.sim_steps);
        for e in &b.episodes {
            let scenario = self
                .cfg
                .env
                .scenarios
                .get(e.scenario_index as usize)
                .cloned()
                .unwrap_or_else(|| "unknown".into());
            self.metrics
                .totals
                .episodes
                .get_or_create(&crate::metrics::ScenarioLabel { scenario })
                .inc();
        }
        let mut s = lock(&self.stats);
        s.c.env_steps += take as u64;
        s.c.sim_steps += b.sim_steps;
        s.c.episodes += b.episodes.len() as u64;
        for e in &b.episodes {
            s.window.push_back(e.clone());
            if s.window.len() > self.cfg.train.window {
                s.window.pop_front();
            }
        }
        let now = Instant::now();
        let steps = s.c.env_steps;
        s.rate.push_back((now, steps));
        while s.rate.len() > 2 && now.duration_since(s.rate[0].0) > Duration::from_secs(10) {
            s.rate.pop_front();
        }
        if s.c.env_steps >= self.cfg.train.env_steps {
            self.complete.store(true, Ordering::Release);
        }
        let m = means(&s.window);
        self.metrics.success.set(m.success as f64);
        self.metrics.safety.set(m.safety as f64);
        self.metrics.speed.set(m.speed as f64);
    }

    fn unreserve(&self, n: usize) {
        lock(&self.stats).reserved -= n as u64;
    }

    /// Mean policy lag (versions) of the policy batches since the previous call, if any.
    pub fn take_mean_lag(&self) -> Option<f64> {
        let mut s = lock(&self.stats);
        let m = (s.lag_batches > 0).then(|| s.lag_sum as f64 / s.lag_batches as f64);
        (s.lag_sum, s.lag_batches) = (0, 0);
        m
    }

    /// Episodes in the rolling window (none at the start and after a resume until the first
    /// episode ends).
    pub fn window_episodes(&self) -> usize {
        lock(&self.stats).window.len()
    }

    /// Rolling means of how episodes ended (the window of [`ActiveJob::progress`]).
    pub fn ends(&self) -> Ends {
        let s = lock(&self.stats);
        let n = s.window.len().max(1) as f32;
        let mut sum = [0f32; 5];
        for e in &s.window {
            for (a, v) in sum.iter_mut().zip(e.ends.values()) {
                *a += v;
            }
        }
        Ends::from_values(sum.map(|v| v / n))
    }

    /// Called by the trainer after each update.
    /// A validation point at `updates` with held-out success `success`, and the best point so
    /// far (`best`: updates, success), for progress displays.
    pub fn record_validation(&self, updates: u64, success: f32, best: (u64, f32)) {
        lock(&self.stats).validation = Some(sf_job::ValidationProgress {
            updates,
            success,
            best_updates: best.0,
            best_success: best.1,
        });
    }

    pub fn record_update(&self, updates: u64, l: Losses) {
        let mut s = lock(&self.stats);
        s.updates = updates;
        s.losses = l;
        self.metrics.updates.inc();
        self.metrics.totals.updates.inc();
        self.metrics.critic_loss.set(l.critic as f64);
        self.metrics.actor_loss.set(l.actor as f64);
        self.metrics.alpha.set(l.alpha as f64);
    }

    pub fn counters(&self) -> Counters {
        let s = lock(&self.stats);
        let mut c = s.c.clone();
        c.wall_s += self.started.elapsed().as_secs_f64();
        c
    }

    pub fn progress(&self) -> Progress {
        let s = lock(&self.stats);
        let scores = means(&s.window);
        let env_steps_per_s = match (s.rate.front(), s.rate.back()) {
            (Some(a), Some(b)) if b.0 > a.0 => {
                (b.1 - a.1) as f64 / b.0.duration_since(a.0).as_secs_f64()
            }
            _ => 0.0,
        };
        Progress {
            learning: sf_job::Learning {
                env_steps: s.c.env_steps,
                updates: s.updates,
                episodes: s.c.episodes,
                scores,
                critic_loss: s.losses.critic,
                actor_loss: s.losses.actor,
                alpha: s.losses.alpha,
                wall_s: s.c.wall_s + self.started.elapsed().as_secs_f64(),
            },
            target_env_steps: self.cfg.train.env_steps,
            policy_version: self.latest_version(),
            env_steps_per_s,
            dropped_stale: s.c.dropped_stale,
            validation: s.validation,
        }
    }
}

fn means(w: &VecDeque<EpisodeResult>) -> sf_job::Scores {
    sf_job::Scores::mean(w.iter().map(|e| e.scores))
}
