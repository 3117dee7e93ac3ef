//! A batch of transitions as one worker sends it.
//!
//! Owns: [`TransitionBatch`] and [`TransitionBatch::validate`] (every array holds `count` rows
//! of the declared widths, observations, actions and rewards are finite, terminal flags are 0
//! or 1, every transition spans at least one step) and [`Transition`], one transition as a
//! rollout hands it over. Observations travel and are stored as IEEE half floats, so the
//! learner copies them into replay without converting. [`ActedBy`] and [`PolicyRequest`] say
//! which weights acted or are asked for, so that warm-up data and "the latest policy" are never
//! the same number.

use std::fmt;
use std::num::NonZeroU64;

use half::f16;

use crate::ids::{JobId, PolicyVersion, WorkerId};

/// Which actor chose a batch's actions: the warm-up's (uniformly random or the IDM
/// demonstrator), or a published policy version (versions start at 1).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ActedBy {
    #[default]
    Warmup,
    Policy(NonZeroU64),
}

impl ActedBy {
    /// The version, `None` for warm-up actions.
    pub fn version(self) -> Option<PolicyVersion> {
        match self {
            Self::Warmup => None,
            Self::Policy(v) => Some(PolicyVersion::new(v.get())),
        }
    }
}

/// Which weights a policy request asks for: the newest the job holds, or one version.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PolicyRequest {
    #[default]
    Latest,
    Version(NonZeroU64),
}

impl PolicyRequest {
    /// The version asked for, `None` for the latest.
    pub fn version(self) -> Option<PolicyVersion> {
        match self {
            Self::Latest => None,
            Self::Version(v) => Some(PolicyVersion::new(v.get())),
        }
    }
}

impl fmt::Display for PolicyRequest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Latest => f.write_str("latest"),
            Self::Version(v) => write!(f, "{v}"),
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct EpisodeResult {
    pub scenario_index: u32,
    pub scores: sf_sim::Scores,
    /// How the scored agents' episodes ended, as fractions of them (`EpisodeMetrics`).
    pub ends: Ends,
}

/// Fractions of an episode's scored agents that ended each way (the failures and timeouts;
/// the rest reached their destination).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct Ends {
    pub collision: f32,
    pub off_road: f32,
    pub off_route: f32,
    pub wrong_lane: f32,
    pub timeout: f32,
}

impl Ends {
    pub const FIELDS: [&'static str; 5] =
        ["collision", "off_road", "off_route", "wrong_lane", "timeout"];

    pub fn values(&self) -> [f32; 5] {
        [self.collision, self.off_road, self.off_route, self.wrong_lane, self.timeout]
    }

    pub fn from_values(v: [f32; 5]) -> Self {
        Self { collision: v[0], off_road: v[1], off_route: v[2], wrong_lane: v[3], timeout: v[4] }
    }
}

/// One transition as a rollout hands it over and the replay takes it: `reward` is the discounted
/// sum over its `steps` decision steps (n-step returns; 1 for one step), `next_obs` the
/// observation after the last of them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transition<'a> {
    pub obs: &'a [f32],
    pub action: &'a [f32],
    pub reward: f32,
    pub next_obs: &'a [f32],
    /// The last step ended the agent's episode by a failure or its destination (timeouts are
    /// not terminal for bootstrapping).
    pub terminal: bool,
    /// Decision steps the transition spans: the TD target bootstraps with `gamma^steps`.
    pub steps: u8,
    /// Index of the map the observation refers to (query-centric segment ids).
    pub map_id: u32,
    /// The IDM driver's action in `obs`'s state, expressed in the job's action
    /// (`sac.bc_target = "oracle"`: the label the cloning term pulls towards); empty when the
    /// job asks for none.
    pub oracle: &'a [f32],
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct TransitionBatch {
    pub job_id: JobId,
    pub worker_id: WorkerId,
    /// The policy version (or the warm-up) that chose these actions.
    pub acted_by: ActedBy,
    pub count: usize,
    pub obs_len: usize,
    pub action_dim: usize,
    /// `count x obs_len`.
    pub obs: Vec<f16>,
    pub next_obs: Vec<f16>,
    /// `count x action_dim`.
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub terminals: Vec<bool>,
    /// Decision steps each transition spans (n-step returns: its reward is the discounted sum
    /// over them and it bootstraps with `gamma^steps`); 1 for one-step transitions.
    pub steps: Vec<u8>,
    pub map_ids: Vec<u32>,
    /// `count x action_dim` oracle labels ([`Transition::oracle`]), or empty: a batch has a
    /// label for every transition or for none.
    pub oracle_actions: Vec<f32>,
    pub episodes: Vec<EpisodeResult>,
    /// Decision steps of all vehicles simulated since the previous batch.
    pub sim_steps: u64,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum BatchError {
    #[error("transition batch field `{field}` has {got} values, expected {want}")]
    Shape { field: &'static str, got: usize, want: usize },
    #[error("transition batch field `{field}` holds a non-finite value at index {index}")]
    NotFinite { field: &'static str, index: usize },
    #[error("transition batch field `{field}`: {reason}")]
    Invalid { field: &'static str, reason: String },
}

impl TransitionBatch {
    /// An empty batch for `obs_len`-float observations and `action_dim` actions.
    pub fn new(job_id: JobId, worker_id: WorkerId, obs_len: usize, action_dim: usize) -> Self {
        Self { job_id, worker_id, obs_len, action_dim, ..Self::default() }
    }

    /// Appends one one-step transition.
    pub fn push(
        &mut self,
        obs: &[f32],
        action: &[f32],
        reward: f32,
        next_obs: &[f32],
        terminal: bool,
        map_id: u32,
    ) {
        self.push_transition(Transition {
            obs,
            action,
            reward,
            next_obs,
            terminal,
            steps: 1,
            map_id,
            oracle: &[],
        });
    }

    /// Appends one transition spanning `t.steps` decision steps.
    pub fn push_transition(&mut self, t: Transition<'_>) {
        self.obs.extend(t.obs.iter().map(|&v| f16::from_f32(v)));
        self.next_obs.extend(t.next_obs.iter().map(|&v| f16::from_f32(v)));
        self.actions.extend_from_slice(t.action);
        self.rewards.push(t.reward);
        self.terminals.push(t.terminal);
        self.steps.push(t.steps);
        self.map_ids.push(t.map_id);
        self.oracle_actions.extend_from_slice(t.oracle);
        self.count += 1;
    }

    /// Empties the batch, keeping its buffers.
    pub fn clear(&mut self) {
        self.obs.clear();
        self.next_obs.clear();
        self.actions.clear();
        self.rewards.clear();
        self.terminals.clear();
        self.steps.clear();
        self.map_ids.clear();
        self.oracle_actions.clear();
        self.episodes.clear();
        self.count = 0;
        self.sim_steps = 0;
    }

    /// Checks shapes and values; the error names the field.
    pub fn validate(&self) -> Result<(), BatchError> {
        let n = self.count;
        if n == 0 {
            return Err(BatchError::Invalid {
                field: "count",
                reason: "a batch holds at least one transition".into(),
            });
        }
        if self.obs_len == 0 {
            return Err(BatchError::Invalid {
                field: "obs_len",
                reason: "must be positive".into(),
            });
        }
        if self.action_dim == 0 {
            return Err(BatchError::Invalid {
                field: "action_dim",
                reason: "must be positive".into(),
            });
        }
        let shape = |field, got: usize, want: usize| {
            if got == want {
                Ok(())
            } else {
                Err(BatchError::Shape { field, got, want })
            }
        };
        let want_obs = n.checked_mul(self.obs_len).ok_or(BatchError::Invalid {
            field: "count",
            reason: "count x obs_len overflows".into(),
        })?;
        shape("obs_f16", self.obs.len(), want_obs)?;
        shape("next_obs_f16", self.next_obs.len(), want_obs)?;
        shape("actions", self.actions.len(), n * self.action_dim)?;
        shape("rewards", self.rewards.len(), n)?;
        shape("terminals", self.terminals.len(), n)?;
        shape("steps", self.steps.len(), n)?;
        shape("map_ids", self.map_ids.len(), n)?;
        if !self.oracle_actions.is_empty() {
            shape("oracle_actions", self.oracle_actions.len(), n * self.action_dim)?;
        }
        if let Some(i) = self.steps.iter().position(|&s| s == 0) {
            return Err(BatchError::Invalid {
                field: "steps",
                reason: format!("transition {i} spans 0 steps (at least 1)"),
            });
        }
        let finite16 = |field, v: &[f16]| match v.iter().position(|x| !x.is_finite()) {
            Some(index) => Err(BatchError::NotFinite { field, index }),
            None => Ok(()),
        };
        let finite32 = |field, v: &[f32]| match v.iter().position(|x| !x.is_finite()) {
            Some(index) => Err(BatchError::NotFinite { field, index }),
            None => Ok(()),
        };
        finite16("obs_f16", &self.obs)?;
        finite16("next_obs_f16", &self.next_obs)?;
        finite32("actions", &self.actions)?;
        // Every action space is [-1, 1] per component (tanh-squashed policies, clipped
        // demonstrators, uniform warm-ups); a value outside it is a misbehaving worker.
        if let Some(i) = self.actions.iter().position(|a| !(-1.0..=1.0).contains(a)) {
            let (t, k) = (i / self.action_dim, i % self.action_dim);
            return Err(BatchError::Invalid {
                field: "actions",
                reason: format!(
                    "transition {t}, component {k}: {} is outside the action space [-1, 1]",
                    self.actions[i]
                ),
            });
        }
        finite32("rewards", &self.rewards)?;
        finite32("oracle_actions", &self.oracle_actions)?;
        if let Some(i) = self.oracle_actions.iter().position(|a| !(-1.0..=1.0).contains(a)) {
            return Err(BatchError::Invalid {
                field: "oracle_actions",
                reason: format!(
                    "transition {}: {} is outside the action space [-1, 1]",
                    i / self.action_dim,
                    self.oracle_actions[i]
                ),
            });
        }
        for (i, e) in self.episodes.iter().enumerate() {
            let [c, r, o, w, t] = e.ends.values();
            for (field, v) in [
                ("episodes.success", e.scores.success),
                ("episodes.safety", e.scores.safety),
                ("episodes.speed", e.scores.speed),
                ("episodes.collision", c),
                ("episodes.off_road", r),
                ("episodes.off_route", o),
                ("episodes.wrong_lane", w),
                ("episodes.timeout", t),
            ] {
                if !(v.is_finite() && (0.0..=1.5).contains(&v)) {
                    return Err(BatchError::Invalid {
                        field,
                        reason: format!("episode {i}: {v} is not a fraction"),
                    });
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one() -> TransitionBatch {
        let mut b = TransitionBatch::new(1.into(), 2.into(), 3, 2);
        b.push(&[0.0, 1.0, 2.0], &[0.5, -0.5], 1.0, &[1.0, 2.0, 3.0], false, 0);
        b
    }

    #[test]
    fn a_well_formed_batch_validates() {
        assert_eq!(one().validate(), Ok(()));
    }

    #[test]
    fn shapes_and_values_are_checked_by_field() {
        let mut b = one();
        b.rewards.push(0.0);
        assert_eq!(b.validate(), Err(BatchError::Shape { field: "rewards", got: 2, want: 1 }));
        let mut b = one();
        b.obs[1] = f16::NAN;
        assert_eq!(b.validate(), Err(BatchError::NotFinite { field: "obs_f16", index: 1 }));
        let mut b = one();
        b.actions[1] = f32::INFINITY;
        assert_eq!(b.validate(), Err(BatchError::NotFinite { field: "actions", index: 1 }));
        let mut b = one();
        b.actions[1] = -1.5;
        assert!(
            matches!(b.validate(), Err(BatchError::Invalid { field: "actions", ref reason }) if reason.contains("transition 0, component 1")),
            "{:?}",
            b.validate()
        );
        let mut b = one();
        b.actions = vec![1.0, -1.0];
        assert_eq!(b.validate(), Ok(()), "the bounds themselves are in the action space");
        let mut b = one();
        b.obs_len = 0;
        assert!(matches!(b.validate(), Err(BatchError::Invalid { field: "obs_len", .. })));
        // An empty batch is a malformed one (workers send only full or flushed batches).
        assert!(matches!(
            TransitionBatch::new(1.into(), 2.into(), 3, 2).validate(),
            Err(BatchError::Invalid { field: "count", .. })
        ));
        let mut b = one();
        b.steps[0] = 0;
        assert!(
            matches!(b.validate(), Err(BatchError::Invalid { field: "steps", .. })),
            "a transition spans at least one step"
        );
        let mut b = one();
        b.steps.clear();
        assert_eq!(b.validate(), Err(BatchError::Shape { field: "steps", got: 0, want: 1 }));
    }

    #[test]
    fn oracle_labels_come_for_every_transition_or_none() {
        let mut b = one();
        b.oracle_actions = vec![0.25, -1.0];
        assert_eq!(b.validate(), Ok(()));
        b.oracle_actions.pop();
        assert_eq!(
            b.validate(),
            Err(BatchError::Shape { field: "oracle_actions", got: 1, want: 2 })
        );
        b.oracle_actions = vec![0.25, f32::NAN];
        assert_eq!(b.validate(), Err(BatchError::NotFinite { field: "oracle_actions", index: 1 }));
        b.oracle_actions = vec![0.25, 1.5];
        assert!(matches!(b.validate(), Err(BatchError::Invalid { field: "oracle_actions", .. })));
        // Labelled transitions fill the column row by row; clearing empties it.
        let mut b = TransitionBatch::new(1.into(), 2.into(), 1, 2);
        for label in [[0.5, 0.0], [-0.5, 0.25]] {
            b.push_transition(Transition {
                obs: &[0.0],
                action: &[0.0, 0.0],
                reward: 0.0,
                next_obs: &[0.0],
                terminal: false,
                steps: 1,
                map_id: 0,
                oracle: &label,
            });
        }
        assert_eq!(b.oracle_actions, vec![0.5, 0.0, -0.5, 0.25]);
        assert_eq!(b.validate(), Ok(()));
        b.clear();
        assert!(b.oracle_actions.is_empty());
    }
}
