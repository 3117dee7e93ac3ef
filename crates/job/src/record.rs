//! A job's record and what the learner tells workers about it: [`JobState`] (final states
//! never change: [`JobRecord::advance`] is the one way a record's state moves), [`JobRecord`]
//! with its [`Progress`] and the [`Learning`] it shares with curve points, [`Assignment`] and
//! the [`Frozen`] policies a worker acts with. Must not: parse configs (`config`, `spec`) or
//! know the wire format.

use sf_sim::SvoGaussian;

use crate::ids::{JobId, PolicyVersion};

use serde::{Deserialize, Serialize};

/// Where a job is in its life. Final states never change again.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn is_final(self) -> bool {
        matches!(self, Self::Succeeded | Self::Failed | Self::Cancelled)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::Queued => "queued",
            Self::Running => "running",
            Self::Succeeded => "succeeded",
            Self::Failed => "failed",
            Self::Cancelled => "cancelled",
        }
    }
}

/// Where a job's learning stands: its counters, the rolling scores of its last finished
/// training episodes and its last update's losses. A job's [`Progress`] reports it and every
/// point of its learning curve (`sf_sac::CurvePoint`) records it; both flatten it, so the
/// JSON and CSV they write keep these fields at their top level.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Learning {
    /// Learner transitions accepted into replay.
    pub env_steps: u64,
    pub updates: u64,
    pub episodes: u64,
    /// Rolling means over the last finished training episodes.
    #[serde(flatten)]
    pub scores: sf_sim::Scores,
    /// The last update's single-batch losses and temperature.
    pub critic_loss: f32,
    pub actor_loss: f32,
    pub alpha: f32,
    /// Training wall-clock, summed over restarts.
    pub wall_s: f64,
}

/// A job's progress: where its learning stands, its budget, its policy version and rates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Progress {
    #[serde(flatten)]
    pub learning: Learning,
    pub target_env_steps: u64,
    pub policy_version: PolicyVersion,
    pub env_steps_per_s: f64,
    pub dropped_stale: u64,
    /// A job with `[validation]`: its last and best held-out points so far.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub validation: Option<ValidationProgress>,
}

/// Where a job's held-out validation stands: the last point and the best (the actor it keeps).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ValidationProgress {
    pub updates: u64,
    pub success: f32,
    pub best_updates: u64,
    pub best_success: f32,
}

/// A job as the store keeps it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobRecord {
    pub id: JobId,
    pub name: String,
    pub state: JobState,
    pub config_toml: String,
    /// Why it failed or was cancelled.
    pub message: String,
    pub created_unix_ms: u64,
    pub updated_unix_ms: u64,
    pub progress: Progress,
    pub artifact_dir: String,
}

impl JobRecord {
    /// The one way a job's state changes: to `to` (with `message`, where given) unless the job
    /// is already in a final state, which never changes again, so a cancel that a job's end
    /// races (or an end that a cancel races) keeps whichever was recorded first. Returns whether
    /// the state changed.
    pub fn advance(&mut self, to: JobState, message: Option<&str>) -> bool {
        if self.state.is_final() {
            return false;
        }
        self.state = to;
        if let Some(m) = message {
            self.message = m.to_string();
        }
        true
    }
}

/// What a worker is told to do.
#[derive(Clone, Debug, PartialEq)]
pub struct Assignment {
    pub job_id: JobId,
    pub config_toml: String,
    pub scenario_index: u32,
    pub seed: u64,
    pub policy_version: PolicyVersion,
    pub obs_len: u32,
    pub action_dim: u32,
    /// The job is in its random-action warm-up.
    pub warmup: bool,
    /// The frozen policies the job acts with besides its own.
    pub frozen: Vec<Frozen>,
}

/// What a frozen policy drives in a job's simulators.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FrozenRole {
    /// The externally driven background vehicles.
    Background,
    /// Agent 0, the ego (FailMaker and SocialCommAdv phases).
    Ego,
    /// The ego's SVO told to background vehicles near it (SocialCommAdv).
    Adversary,
}

/// A finished job's final policy that another job acts with.
#[derive(Clone, Debug, PartialEq)]
pub struct Frozen {
    pub role: FrozenRole,
    pub job_id: JobId,
    pub config_toml: String,
    /// CoPO Stage 2: per scenario, the Gaussian the background's SVOs are redrawn from every
    /// step (empty: the cases' SVOs).
    pub svo_gaussians: Vec<(String, SvoGaussian)>,
}

impl Frozen {
    pub fn new(role: FrozenRole, job_id: JobId, config_toml: String) -> Self {
        Self { role, job_id, config_toml, svo_gaussians: Vec::new() }
    }

    pub fn svo_gaussian(&self, scenario: &str) -> Option<SvoGaussian> {
        self.svo_gaussians.iter().find(|(s, _)| s == scenario).map(|(_, g)| *g)
    }
}

/// Milliseconds since the Unix epoch (0 if the clock is before it).
pub fn now_unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Job records stored before `Learning` existed (flat fields) still read, and records
    /// written now keep the same flat layout.
    #[test]
    fn progress_json_stays_flat() {
        let old = r#"{"env_steps":120,"target_env_steps":500,"updates":30,"policy_version":4,"episodes":9,"success":0.5,"safety":0.75,"speed":0.25,"critic_loss":1.5,"actor_loss":-2.0,"alpha":0.25,"env_steps_per_s":61.0,"wall_s":12.5,"dropped_stale":3}"#;
        let p: Progress = serde_json::from_str(old).expect("an old record's progress");
        let l = p.learning;
        assert_eq!(
            (
                l.env_steps,
                l.updates,
                l.episodes,
                p.target_env_steps,
                p.policy_version.get(),
                p.dropped_stale
            ),
            (120, 30, 9, 500, 4, 3)
        );
        assert_eq!((l.scores.success, l.scores.safety, l.scores.speed), (0.5, 0.75, 0.25));
        assert_eq!(
            (l.critic_loss, l.actor_loss, l.alpha, l.wall_s, p.env_steps_per_s),
            (1.5, -2.0, 0.25, 12.5, 61.0)
        );
        let again: serde_json::Value = serde_json::to_value(p).expect("serialises");
        let old: serde_json::Value = serde_json::from_str(old).expect("json");
        assert_eq!(again, old, "the written layout is the old flat one");
    }

    /// A final state never changes; every other state moves to any state asked for.
    #[test]
    fn a_final_state_never_changes() {
        use JobState::*;
        let all = [Queued, Running, Succeeded, Failed, Cancelled];
        for from in all {
            for to in all {
                let mut r = JobRecord {
                    id: JobId::new(1),
                    name: "j".into(),
                    state: from,
                    config_toml: String::new(),
                    message: "before".into(),
                    created_unix_ms: 0,
                    updated_unix_ms: 0,
                    progress: Progress::default(),
                    artifact_dir: String::new(),
                };
                let moved = r.advance(to, Some("after"));
                assert_eq!(moved, !from.is_final(), "{from:?} -> {to:?}");
                assert_eq!(r.state, if from.is_final() { from } else { to }, "{from:?} -> {to:?}");
                assert_eq!(
                    r.message,
                    if from.is_final() { "before" } else { "after" },
                    "{from:?} -> {to:?}"
                );
            }
        }
    }
}
