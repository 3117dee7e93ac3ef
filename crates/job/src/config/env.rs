//! `[env]`: scenarios, vehicles, the frozen jobs a kind drives with or against, the action, the
//! case draw and the observation caps, and their checks. Must not: know the learning recipe
//! (`[sac]`).

use serde::{Deserialize, Serialize};

use super::{bad, Background, ConfigError, JobConfig, JobKind};
use crate::ids::JobId;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvSection {
    /// Scenario names (files `<name>.json` in the learner's scenario directory). Workers are
    /// spread over them; the index is the map id of every transition.
    pub scenarios: Vec<String>,
    #[serde(default = "d_vmin")]
    pub vehicles_min: u32,
    #[serde(default = "d_vmax")]
    pub vehicles_max: u32,
    #[serde(default)]
    pub background: Background,
    /// Ego jobs: drive the background with the final policy of this (flow) job instead of
    /// IDM. The job waits until that one has succeeded (a pipeline dependency).
    #[serde(default)]
    pub background_job: Option<JobId>,
    /// In a pipeline directory: the background flow by job name; `socialflow pipeline` turns it
    /// into `background_job` when it submits (the learner accepts only ids).
    #[serde(default)]
    pub background_from: Option<String>,
    /// FailMaker and SocialCommAdv jobs: the ego job whose final policy drives the ego (a
    /// dependency, like `background_job`).
    #[serde(default)]
    pub ego_job: Option<JobId>,
    /// In a pipeline directory: `ego_job` by job name.
    #[serde(default)]
    pub ego_from: Option<String>,
    /// How a driving policy's action moves its vehicle: `"direct"` (the paper: reference speed
    /// and steer), `"idm-residual"` (added to the IDM driver's action and clipped, so a zero
    /// action drives like IDM; see `configs/paper-small/README.md`) or
    /// `"idm-accel-residual"` (one number moving the IDM driver's acceleration linearly to full
    /// braking at -1 and full acceleration at +1, steering left to IDM's pure pursuit: zero is
    /// IDM exactly).
    #[serde(default)]
    pub action: ActionMode,
    /// Ego jobs among IDM cars: the share of training episodes drawn among cases in which the
    /// IDM driver in the ego's seat collides (the rest as usual): the conflicts IDM does not
    /// yield in, for the ladder's learn-to-yield rung. Absent: every case as drawn.
    #[serde(default)]
    pub conflict_share: Option<f32>,
    /// Ego jobs: the share of training episodes with a slow vehicle ahead of the ego in its
    /// lane, and that vehicle's speed cap (`{ share = 1.0, speed_mps = 1.5 }`; the ladder's
    /// lane-change rung, `sf_sim::vec_env::SlowLeader`). Absent: every case as drawn.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slow_leader: Option<sf_sim::vec_env::SlowLeader>,
    /// Flow and FailMaker jobs: the range, in degrees within [-90, 90], that a case's SVO
    /// (stored in [0, 90]) is mapped onto for the job's vehicles, in training and wherever the
    /// job is the background (absent: [-90, 90] for FailMaker, the paper's c; [0, 90] for the
    /// other flows). `[-90, -90]`: every FailMaker vehicle is rewarded by `-R_ego` alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub svo_range_deg: Option<[f32; 2]>,
    /// CoPO and SocialComm jobs: whose rewards their SVO-composed reward averages: `"radius"`
    /// (every learner within 50 m, the released code's) or `"observed"` (the learners among the
    /// neighbours the observation keeps: the nearest `max_neighbours` within its radius).
    #[serde(default, skip_serializing_if = "RewardNeighbours::is_radius")]
    pub reward_neighbours: RewardNeighbours,
    /// Overrides the observation's cap on other agents (nearest first; default 20).
    #[serde(default)]
    pub max_neighbours: Option<usize>,
    /// Overrides the query-centric observation's cap on map segments (nearest first; default 96).
    #[serde(default)]
    pub max_segments: Option<usize>,
}

/// `env.reward_neighbours`: the neighbours whose rewards an SVO-composed reward averages.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RewardNeighbours {
    /// Every learner within 50 m (the released code's), seen or not.
    #[default]
    Radius,
    /// The learners among the agents the observation keeps (nearest first, within its radius).
    Observed,
}

impl RewardNeighbours {
    fn is_radius(&self) -> bool {
        *self == Self::Radius
    }
}

/// `env.action`: how a driving policy's action moves its vehicle (one type with the
/// simulator's, which applies it).
pub use sf_sim::DriveAction as ActionMode;

fn d_vmin() -> u32 {
    8
}
fn d_vmax() -> u32 {
    20
}

impl JobConfig {
    /// `[env]`: scenarios, vehicles, the frozen jobs a kind needs (and `train.init_*`), the action
    /// for the job's kind, conflict cases and observation caps.
    pub(super) fn validate_env(&self) -> Result<(), ConfigError> {
        self.validate_env_vehicles()?;
        self.validate_frozen_jobs()?;
        self.validate_env_draw()
    }

    /// `[env]`'s scenario names and vehicle range.
    fn validate_env_vehicles(&self) -> Result<(), ConfigError> {
        if self.env.scenarios.is_empty() {
            return bad("env.scenarios", "list at least one scenario");
        }
        for s in &self.env.scenarios {
            if s.is_empty() || !s.chars().all(|c| c.is_ascii_alphanumeric() || "-_".contains(c)) {
                return bad("env.scenarios", format!("`{s}` is not a scenario name"));
            }
        }
        if self.env.vehicles_min == 0 || self.env.vehicles_min > self.env.vehicles_max {
            return bad(
                "env.vehicles_min",
                format!(
                    "{} must be in 1..=vehicles_max ({})",
                    self.env.vehicles_min, self.env.vehicles_max
                ),
            );
        }
        Ok(())
    }

    /// The frozen jobs a kind drives with or against (`env.background_*`, `env.ego_*`) and the
    /// job a continuation starts from (`train.init_*`, `train.init_replay`).
    fn validate_frozen_jobs(&self) -> Result<(), ConfigError> {
        let frozen_bg = matches!(self.kind, JobKind::Ego | JobKind::SocialcommAdv);
        let e = &self.env;
        if e.background_job.is_some() && !frozen_bg {
            return bad("env.background_job", format!("a {} job trains its background; only ego and socialcomm-adv jobs drive a frozen flow", self.kind.as_str()));
        }
        if e.background_from.is_some() && (!frozen_bg || e.background_job.is_some()) {
            return bad(
                "env.background_from",
                "only for ego and socialcomm-adv jobs, and not together with env.background_job",
            );
        }
        if self.kind == JobKind::SocialcommAdv
            && e.background_job.is_none()
            && e.background_from.is_none()
        {
            return bad("env.background_job", "a socialcomm-adv job needs the frozen SocialComm flow (env.background_job or env.background_from)");
        }
        if (e.ego_job.is_some() || e.ego_from.is_some()) && !self.kind.needs_ego() {
            return bad(
                "env.ego_job",
                format!(
                    "only failmaker and socialcomm-adv jobs act against a frozen ego, not {}",
                    self.kind.as_str()
                ),
            );
        }
        if e.ego_job.is_some() && e.ego_from.is_some() {
            return bad("env.ego_from", "not together with env.ego_job");
        }
        if self.kind.needs_ego() && e.ego_job.is_none() && e.ego_from.is_none() {
            return bad(
                "env.ego_job",
                format!(
                    "a {} job needs the frozen ego it acts against (env.ego_job or env.ego_from)",
                    self.kind.as_str()
                ),
            );
        }
        if self.train.init_job.is_some() && self.train.init_from.is_some() {
            return bad("train.init_from", "not together with train.init_job");
        }
        if self.train.init_replay {
            if !self.train.continues() {
                return bad(
                    "train.init_replay",
                    "carries the replay of the job a continuation starts from: set train.init_job or train.init_from",
                );
            }
            if !self.train.persist_replay {
                return bad(
                    "train.init_replay",
                    "a carried replay is read from disk and written on as the job's own: set train.persist_replay = true",
                );
            }
        }
        for (f, v) in [
            ("env.background_job", e.background_job),
            ("env.ego_job", e.ego_job),
            ("train.init_job", self.train.init_job),
        ] {
            if v == Some(JobId::new(0)) {
                return bad(f, "job ids start at 1");
            }
        }
        Ok(())
    }

    /// `[env]`'s action for the job's kind, the case draw (conflict cases, a slow leader, the SVO
    /// range), the reward's neighbours and the observation caps.
    fn validate_env_draw(&self) -> Result<(), ConfigError> {
        if self.env.vehicles_max > 64 {
            return bad("env.vehicles_max", format!("{} exceeds 64", self.env.vehicles_max));
        }
        if self.env.action != ActionMode::Direct && !self.kind.drives() {
            return bad(
                "env.action",
                format!(
                    "a residual action is for driving policies; a {} job's action is an SVO",
                    self.kind.as_str()
                ),
            );
        }
        if let Some(p) = self.env.conflict_share {
            if !(p.is_finite() && (0.0..=1.0).contains(&p)) {
                return bad("env.conflict_share", format!("{p} must be in [0, 1]"));
            }
            if self.kind != JobKind::Ego
                || self.env.background_job.is_some()
                || self.env.background_from.is_some()
            {
                return bad("env.conflict_share", "conflict cases are chosen by the IDM ego's fate among IDM cars: an ego job with no background job");
            }
        }
        if let Some(slow) = &self.env.slow_leader {
            if let Err(why) = slow.check(sf_sim::vehicle::VehicleParams::default().max_speed_mps) {
                return bad("env.slow_leader", why);
            }
            if self.kind != JobKind::Ego {
                return bad(
                    "env.slow_leader",
                    format!(
                        "a slow vehicle ahead of the ego is for ego jobs, not a {} job",
                        self.kind.as_str()
                    ),
                );
            }
        }
        if let Some([lo, hi]) = self.env.svo_range_deg {
            if !self.kind.multi_agent() && self.kind != JobKind::Failmaker {
                return bad(
                    "env.svo_range_deg",
                    format!(
                        "the range of a flow's own SVOs is for flow and failmaker jobs, not a {} job (its background's range is the background job's)",
                        self.kind.as_str()
                    ),
                );
            }
            if !(lo.is_finite() && hi.is_finite() && -90.0 <= lo && lo <= hi && hi <= 90.0) {
                return bad(
                    "env.svo_range_deg",
                    format!(
                        "[{lo}, {hi}] must be an SVO range with -90 <= low <= high <= 90 degrees"
                    ),
                );
            }
        }
        if self.env.reward_neighbours != RewardNeighbours::Radius && !self.kind.composed_reward() {
            return bad(
                "env.reward_neighbours",
                format!(
                    "only copo and socialcomm jobs compose their reward from their neighbours' (a {} job's reward has no neighbour term)",
                    self.kind.as_str()
                ),
            );
        }
        for (f, v, hi) in [
            ("env.max_neighbours", self.env.max_neighbours, 64),
            ("env.max_segments", self.env.max_segments, 512),
        ] {
            if let Some(v) = v {
                if !(1..=hi).contains(&v) {
                    return bad(f, format!("{v} must be in 1..={hi}"));
                }
            }
        }
        Ok(())
    }
}
