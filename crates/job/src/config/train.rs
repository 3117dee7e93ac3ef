//! `[train]` (budget, replay, publishing, checkpoints, continuation, kept actors) and `[worker]`
//! (simulators per worker, batch size): their defaults and checks.

use serde::{Deserialize, Serialize};

use super::{bad, ConfigError, JobConfig};
use crate::ids::JobId;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainSection {
    /// Learner transitions to collect; the job succeeds when they are in.
    pub env_steps: u64,
    /// Updates per inserted transition (the replay ratio).
    #[serde(default = "d_spi")]
    pub samples_per_insert: f64,
    #[serde(default = "d_capacity")]
    pub replay_capacity: usize,
    /// Transitions from a policy more than this many versions behind are dropped.
    #[serde(default = "d_lag")]
    pub max_policy_lag: u64,
    /// A new policy version every this many updates.
    #[serde(default = "d_publish")]
    pub publish_every_updates: u64,
    #[serde(default = "d_ckpt")]
    pub checkpoint_every_s: u64,
    /// Write the replay beside each checkpoint (only what is new since the previous one) and
    /// read it back on resume, so a restarted learner keeps its data.
    #[serde(default = "d_true")]
    pub persist_replay: bool,
    /// A learning-curve point every this many transitions (default: 50 points per job).
    #[serde(default)]
    pub curve_every_steps: Option<u64>,
    /// Finished episodes averaged in rolling statistics.
    #[serde(default = "d_window")]
    pub window: usize,
    /// Start from the final SAC state (actor, critics, alpha, optimizers) of this job, of the
    /// same kind and network, instead of from scratch: how RARL phases continue each other.
    #[serde(default)]
    pub init_job: Option<JobId>,
    /// In a pipeline directory: `init_job` by job name.
    #[serde(default)]
    pub init_from: Option<String>,
    /// A continuation's replay starts as the replay of the job it continues (its newest
    /// `replay_capacity` transitions), as if one SAC run went on: the ego of a RARL round keeps
    /// its own data. The learner keeps a finished job's replay while a queued or running job
    /// carries it; both need `persist_replay` and the same `env.scenarios`.
    #[serde(default)]
    pub init_replay: bool,
    /// Update counts at which the actor that validation would score is kept as
    /// `kept/actor-<updates>.bpk` in the job directory (a long run's actors along its curve),
    /// strictly increasing.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub keep_actors_at: Vec<u64>,
    /// Continue a run from its job directory on the learner's host (a stopped or finished
    /// job's, copied or committed): its whole SAC state (actor, critic, target, optimizer
    /// moments, alpha, update counter, RNG), counters, curve, validation points, best and kept
    /// actors, and its replay when the directory has one; without one the replay refills with
    /// the continued policy (`sac.warmup_steps` transitions) before updates go on.
    /// `train.env_steps` is the total, counted from the source's start. `socialflow train
    /// --continue-from DIR` sets it as an absolute path.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub continue_from: Option<String>,
    /// Start from the weights of a job directory on the learner's host (its `checkpoint/`:
    /// actor, critic, target, alpha, optimizer moments) whose job may be of another kind, with
    /// the same network sizes: a SocialComm flow warm-started from a MACAD flow. The weights
    /// that read context channels the source did not consume (its SVOs) start at zero, so the
    /// job starts acting as the source did. Everything else is this job's own: a fresh replay
    /// (filled by `sac.warmup_policy`; `"policy"` warms up with the loaded actor), update 0,
    /// its own seed, counters and curve. Its cloning and critic pretraining
    /// (`sac.bc_updates`, `sac.critic_pretrain_updates`) run as in any job.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warm_start_from: Option<String>,
}
impl TrainSection {
    /// Whether the job continues another (`train.init_job`, or `train.init_from` by name).
    pub fn continues(&self) -> bool {
        self.init_job.is_some() || self.init_from.is_some()
    }

    /// Whether the job starts from weights it did not draw (a continuation of another job, or
    /// `train.warm_start_from`): a policy it can warm up with.
    pub fn starts_from_weights(&self) -> bool {
        self.continues() || self.warm_start_from.is_some()
    }
}

fn d_spi() -> f64 {
    0.25
}
fn d_capacity() -> usize {
    1_000_000
}
fn d_lag() -> u64 {
    20
}
fn d_publish() -> u64 {
    10
}
fn d_ckpt() -> u64 {
    60
}
fn d_window() -> usize {
    100
}
fn d_true() -> bool {
    true
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorkerSection {
    /// Simulators each worker steps in parallel.
    pub envs: usize,
    /// Transitions per pushed batch.
    pub batch_transitions: usize,
}

impl Default for WorkerSection {
    fn default() -> Self {
        Self { envs: 8, batch_transitions: 256 }
    }
}

impl JobConfig {
    /// `[train]` and `[worker]`: budgets, replay, publishing and batching.
    pub(super) fn validate_train(&self) -> Result<(), ConfigError> {
        let (t, s) = (&self.train, &self.sac);
        if t.env_steps == 0 {
            return bad("train.env_steps", "must be positive");
        }
        if !(t.samples_per_insert.is_finite()
            && t.samples_per_insert > 0.0
            && t.samples_per_insert <= 1024.0)
        {
            return bad(
                "train.samples_per_insert",
                format!("{} must be in (0, 1024]", t.samples_per_insert),
            );
        }
        if t.replay_capacity < s.batch_size || t.replay_capacity > 50_000_000 {
            return bad(
                "train.replay_capacity",
                format!(
                    "{} must be in sac.batch_size ({})..=50000000",
                    t.replay_capacity, s.batch_size
                ),
            );
        }
        if (s.warmup_steps.max(s.batch_size as u64)) > t.replay_capacity as u64 {
            return bad(
                "sac.warmup_steps",
                format!(
                    "{} exceeds train.replay_capacity {}: sampling could never start",
                    s.warmup_steps, t.replay_capacity
                ),
            );
        }
        if t.publish_every_updates == 0 {
            return bad("train.publish_every_updates", "must be positive");
        }
        if t.checkpoint_every_s == 0 {
            return bad("train.checkpoint_every_s", "must be positive");
        }
        if t.curve_every_steps == Some(0) {
            return bad("train.curve_every_steps", "must be positive");
        }
        if let Some(from) = &t.continue_from {
            if from.trim().is_empty() {
                return bad("train.continue_from", "must name a job directory");
            }
            if self.train.continues() {
                return bad(
                    "train.continue_from",
                    "continues a run's directory; train.init_job / init_from start from a job of this learner: set one of them",
                );
            }
        }
        if let Some(from) = &t.warm_start_from {
            if from.trim().is_empty() {
                return bad("train.warm_start_from", "must name a job directory");
            }
            if t.continue_from.is_some() || self.train.continues() {
                return bad(
                    "train.warm_start_from",
                    "starts fresh from another job's weights; train.continue_from, init_job and init_from continue a run: set one of them",
                );
            }
        }
        if t.keep_actors_at.first() == Some(&0) || t.keep_actors_at.windows(2).any(|w| w[0] >= w[1])
        {
            return bad(
                "train.keep_actors_at",
                format!("{:?} must be positive and strictly increasing", t.keep_actors_at),
            );
        }
        if t.window == 0 {
            return bad("train.window", "must be positive");
        }
        if self.worker.envs == 0 || self.worker.envs > 256 {
            return bad("worker.envs", format!("{} must be in 1..=256", self.worker.envs));
        }
        if self.worker.batch_transitions == 0 || self.worker.batch_transitions > 8192 {
            return bad(
                "worker.batch_transitions",
                format!("{} must be in 1..=8192", self.worker.batch_transitions),
            );
        }
        Ok(())
    }
}
