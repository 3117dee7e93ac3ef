//! The job config a user submits (TOML).
//!
//! Owns: [`JobConfig`], the job's kind and its dependencies ([`DepRole`]), and
//! [`JobConfig::validate`], whose errors name the field. Each section lives in its own file with
//! its defaults and its checks beside its fields: `env` (`[env]`), `net` (`[net]`), `sac`
//! (`[sac]`, the paper's SAC table by default), `train` (`[train]`, `[worker]`) and
//! `validation` (`[validation]`, `[coordinator]`); a check that reads another section lives with
//! the field it refuses. The learner validates before it stores a job; workers parse the
//! resolved config they are assigned. Must not: know about burn types (the learner and worker
//! map these sections onto `NetConfig` / `SacConfig`).

use serde::{Deserialize, Serialize};

use crate::ids::JobId;

mod env;
mod net;
mod sac;
mod train;
mod validation;

pub use env::{ActionMode, EnvSection, RewardNeighbours};
pub use net::NetSection;
pub use sac::{
    BcTarget, CriticLoss, SacConfig, WarmupPolicy, AWAC_MAX_WEIGHT, DEFAULT_CQL_SAMPLES, MAX_N_STEP,
};
pub use train::{TrainSection, WorkerSection};
pub use validation::{CoordinatorSection, ValidationSection};

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("job config is not valid TOML for a job: {0}")]
    Parse(String),
    #[error("job config field `{field}`: {reason}")]
    Field { field: &'static str, reason: String },
}

fn bad<T>(field: &'static str, reason: impl Into<String>) -> Result<T, ConfigError> {
    Err(ConfigError::Field { field, reason: reason.into() })
}

/// What the job trains.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum JobKind {
    /// An ego policy (no SVO input) among frozen background traffic.
    #[default]
    Ego,
    /// MACAD traffic flow: every vehicle a learner of one shared policy, no SVO, individual
    /// reward (Stage 1, independent learning).
    Macad,
    /// CoPO Stage 1: each vehicle sees its own SVO (uniform in [0, 90] deg per agent and
    /// episode) and is rewarded with the SVO-composed reward.
    Copo,
    /// SocialComm Stage 1: SVOs of self and neighbours visible, SVO-composed reward.
    Socialcomm,
    /// FailMaker: the background vehicles learn one shared policy on `cos(c) R_i + sin(c)
    /// R_ego` (c uniform in [-90, 90] deg, seen as the own SVO; no collision penalty in R_i),
    /// with the ego flagged in their observations; the ego is the frozen policy of
    /// `env.ego_job`. One RARL phase: alternate with ego jobs through `train.init_job`.
    Failmaker,
    /// SocialCommAdv Stage 2: the adversary's upper-level policy (1-dim action: the ego's SVO
    /// that background agents within the ego's radius are told), conditioned on the ego's
    /// observation, trained on `-R_ego`. The background is the frozen SocialComm flow of
    /// `env.background_job`, the ego the frozen policy of `env.ego_job`. One RARL phase.
    SocialcommAdv,
}

impl JobKind {
    /// Every vehicle is a learner of the job's policy (Stage 1 flows).
    pub fn multi_agent(self) -> bool {
        matches!(self, Self::Macad | Self::Copo | Self::Socialcomm)
    }

    /// The job's final policy is a traffic flow an ego can train or be evaluated against.
    pub fn is_flow(self) -> bool {
        !matches!(self, Self::Ego)
    }

    /// A RARL phase: needs a frozen ego (`env.ego_job`) to act against.
    pub fn needs_ego(self) -> bool {
        matches!(self, Self::Failmaker | Self::SocialcommAdv)
    }

    pub fn svo_seen(self) -> sf_sim::SvoVisibility {
        use sf_sim::SvoVisibility as V;
        match self {
            Self::Ego | Self::Macad | Self::SocialcommAdv => V::None,
            Self::Copo | Self::Failmaker => V::Own,
            Self::Socialcomm => V::All,
        }
    }

    /// Trained on the SVO-composed reward rather than the individual one.
    pub fn composed_reward(self) -> bool {
        matches!(self, Self::Copo | Self::Socialcomm)
    }

    /// Size of the policy's action: the adversary says one SVO, drivers steer and set speed.
    /// Whether its policy drives a vehicle (every kind but the SocialCommAdv adversary, whose
    /// action is an SVO).
    pub fn drives(self) -> bool {
        self != Self::SocialcommAdv
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ego => "ego",
            Self::Macad => "macad",
            Self::Copo => "copo",
            Self::Socialcomm => "socialcomm",
            Self::Failmaker => "failmaker",
            Self::SocialcommAdv => "socialcomm-adv",
        }
    }
}

/// Who drives the vehicles that are not the ego.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Background {
    #[default]
    Idm,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NetPreset {
    Paper,
    Compact,
    #[default]
    Fast,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Device {
    #[default]
    Cpu,
    Ndarray,
    Cuda,
    Wgpu,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobConfig {
    /// Shown in job lists and used for the artifact directory.
    pub name: String,
    #[serde(default)]
    pub kind: JobKind,
    pub env: EnvSection,
    #[serde(default)]
    pub net: NetSection,
    #[serde(default)]
    pub sac: SacConfig,
    pub train: TrainSection,
    #[serde(default)]
    pub worker: WorkerSection,
    /// CoPO Stage 2 (copo jobs only): how the coordinator's per-scenario SVO Gaussians are
    /// fitted once Stage 1 has all its transitions. Absent: the defaults below.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coordinator: Option<CoordinatorSection>,
    /// Policy selection by a held-out evaluation during training: absent, the job's final
    /// policy is its last actor; present, the actor that scored best on the validation cases.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validation: Option<ValidationSection>,
}

/// A job another one needs (it waits until that one has succeeded).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepRole {
    /// The frozen flow in the background (`env.background_job`).
    Background,
    /// The frozen ego (`env.ego_job`).
    Ego,
    /// The job whose final state this one starts from (`train.init_job`).
    Init,
}

/// Why a dependency's kind cannot serve in a role; the message completes "job N ...".
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum DepKindError {
    #[error("is a {} job; the adversary talks to a SocialComm flow", .dep.as_str())]
    NotSocialcomm { dep: JobKind },
    #[error("is an ego job, not a traffic flow")]
    NotAFlow,
    #[error("is a {} job, not an ego policy", .dep.as_str())]
    NotAnEgo { dep: JobKind },
    #[error("is a {} job; a job starts only from one of its own kind", .dep.as_str())]
    OtherKind { dep: JobKind },
}

/// A pipeline job's dependency name that no job carries.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field}: no job named `{name}`")]
pub struct UnknownJobName {
    pub field: &'static str,
    pub name: String,
}

impl DepRole {
    /// Whether a `dep`-kind job can serve a `job`-kind job in this role, by kind alone (the
    /// learner also compares networks and observation layouts).
    pub fn accepts(self, job: JobKind, dep: JobKind) -> Result<(), DepKindError> {
        match self {
            Self::Background if job == JobKind::SocialcommAdv && dep != JobKind::Socialcomm => {
                Err(DepKindError::NotSocialcomm { dep })
            }
            Self::Background if !dep.is_flow() => Err(DepKindError::NotAFlow),
            Self::Ego if dep != JobKind::Ego => Err(DepKindError::NotAnEgo { dep }),
            Self::Init if dep != job => Err(DepKindError::OtherKind { dep }),
            _ => Ok(()),
        }
    }

    pub fn field(self) -> &'static str {
        match self {
            Self::Background => "env.background_job",
            Self::Ego => "env.ego_job",
            Self::Init => "train.init_job",
        }
    }
}

impl JobConfig {
    /// How its training episodes' random cases are drawn (`env.conflict_share`,
    /// `env.slow_leader`); validation draws its held-out cases the same way.
    pub fn case_draw(&self) -> sf_sim::vec_env::CaseDraw {
        sf_sim::vec_env::CaseDraw {
            conflict_share: self.env.conflict_share,
            slow_leader: self.env.slow_leader,
        }
    }

    /// Floats in its policy's action: the drive action's for driving kinds, 1 (an SVO) for the
    /// SocialCommAdv adversary.
    pub fn action_dim(&self) -> usize {
        if self.kind.drives() {
            self.env.action.dim()
        } else {
            1
        }
    }

    /// The jobs this one depends on, by id.
    pub fn deps(&self) -> Vec<(DepRole, JobId)> {
        [
            (DepRole::Background, self.env.background_job),
            (DepRole::Ego, self.env.ego_job),
            (DepRole::Init, self.train.init_job),
        ]
        .into_iter()
        .filter_map(|(r, id)| id.map(|id| (r, id)))
        .collect()
    }

    /// The jobs this one depends on, by name (a pipeline directory).
    pub fn deps_by_name(&self) -> Vec<(DepRole, &str)> {
        [
            (DepRole::Background, &self.env.background_from),
            (DepRole::Ego, &self.env.ego_from),
            (DepRole::Init, &self.train.init_from),
        ]
        .into_iter()
        .filter_map(|(r, n)| n.as_deref().map(|n| (r, n)))
        .collect()
    }

    /// Replaces the name references by ids (`id_of` answers for a name).
    pub fn resolve_names(
        &mut self,
        mut id_of: impl FnMut(&str) -> Option<JobId>,
    ) -> Result<(), UnknownJobName> {
        let mut one = |name: &mut Option<String>,
                       id: &mut Option<JobId>,
                       field: &'static str|
         -> Result<(), UnknownJobName> {
            if let Some(n) = name.take() {
                *id = Some(id_of(&n).ok_or(UnknownJobName { field, name: n })?);
            }
            Ok(())
        };
        one(&mut self.env.background_from, &mut self.env.background_job, "env.background_from")?;
        one(&mut self.env.ego_from, &mut self.env.ego_job, "env.ego_from")?;
        one(&mut self.train.init_from, &mut self.train.init_job, "train.init_from")
    }

    /// Parses and validates.
    pub fn from_toml(text: &str) -> Result<Self, ConfigError> {
        let c: Self = toml::from_str(text)
            .map_err(|e| ConfigError::Parse(e.to_string().trim_end().to_string()))?;
        c.validate()?;
        Ok(c)
    }

    /// The config with every default written out.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a job config always serialises to TOML")
    }

    /// CoPO Stage 2's settings: `None` for other kinds and for a copo job that stays at Stage 1.
    pub fn coordinator(&self) -> Option<CoordinatorSection> {
        let c =
            (self.kind == JobKind::Copo).then(|| self.coordinator.clone().unwrap_or_default())?;
        (c.iterations > 0).then_some(c)
    }

    pub fn curve_every_steps(&self) -> u64 {
        self.train.curve_every_steps.unwrap_or((self.train.env_steps / 50).max(100))
    }

    /// Checks every field; the error names the first bad one.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.name.trim().is_empty()
            || !self.name.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        {
            return bad(
                "name",
                format!("`{}` must be non-empty ASCII letters, digits, '-', '_' or '.'", self.name),
            );
        }
        if self.name == "idm" || self.name == crate::eval::IDM_MOBIL {
            return bad(
                "name",
                format!("`{}` is reserved: evaluation grids read `job = \"idm\"` as the IDM driver and `job = \"{}\"` as IDM with MOBIL's lane changes", self.name, crate::eval::IDM_MOBIL),
            );
        }
        self.validate_env()?;
        self.validate_net()?;
        self.validate_sac()?;
        self.validate_train()?;
        self.validate_sections()
    }
}

#[cfg(test)]
mod tests;
