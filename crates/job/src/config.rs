//! The job config a user submits (TOML).
//!
//! Owns: [`JobConfig`] and its sections, defaults (the paper's SAC table, our default network)
//! and [`JobConfig::validate`], whose errors name the field. The learner validates before it
//! stores a job; workers parse the resolved config they are assigned. Must not: know about
//! burn types (the learner and worker map these sections onto `NetConfig` / `SacConfig`).

use serde::{Deserialize, Serialize};

use crate::JobId;

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

/// A held-out evaluation of the training actor (mean action) every `every_updates` updates on
/// `episodes` generated cases per scenario, drawn once from `seed` like the training episodes
/// (the job's vehicle range and `env.conflict_share`) and the same at every point, so points
/// are paired. The job's final policy (`policy.bpk`) is the best-scoring actor (success, then
/// safety; the earlier on ties); `validation.csv` holds every point. The checkpoint, and so
/// `train.init_job` continuations, keep the last SAC state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ValidationSection {
    pub every_updates: u64,
    /// Generated cases per scenario.
    pub episodes: u32,
    /// Seeds the cases: keep it apart from evaluation's (the ladder's generated cases use 2026).
    pub seed: u64,
    /// Simulators stepped together.
    pub envs: usize,
    /// Seeds the test cases: generated like the validation cases but from this seed, and
    /// scored once, at the end, with the kept actor and the IDM driver. They select nothing,
    /// so the side-by-side a finished job reports is on cases apart from those that chose its
    /// actor. Default: `seed + 1`; must differ from `seed`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub test_seed: Option<u64>,
    /// Test cases per scenario (default: `episodes`); 0 skips the test.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub test_episodes: Option<u32>,
}

impl Default for ValidationSection {
    fn default() -> Self {
        Self {
            every_updates: 500,
            episodes: 100,
            seed: 0x76_616c,
            envs: 25,
            test_seed: None,
            test_episodes: None,
        }
    }
}

impl ValidationSection {
    /// The seed of the test cases.
    pub fn test_seed(&self) -> u64 {
        self.test_seed.unwrap_or(self.seed.wrapping_add(1))
    }

    /// Test cases per scenario (0: no test).
    pub fn test_episodes(&self) -> u32 {
        self.test_episodes.unwrap_or(self.episodes)
    }
}

/// CoPO's Stage-2 coordinator: the cross-entropy method over a Gaussian on the SVO, per
/// scenario, each candidate SVO scored by the frozen Stage-1 flow's mean individual reward
/// with every agent at that SVO (generated cases of the job's vehicle range).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CoordinatorSection {
    /// CEM iterations per scenario; 0 leaves the flow at Stage 1 (SVOs uniform in [0, 90]).
    pub iterations: u32,
    /// Candidate SVOs per iteration.
    pub population: u32,
    /// Episodes scoring each candidate.
    pub episodes: u32,
    /// Fraction of the candidates the Gaussian is refitted to.
    pub elite_frac: f32,
    /// Simulators stepped together while scoring.
    pub envs: usize,
}

impl Default for CoordinatorSection {
    fn default() -> Self {
        Self { iterations: 6, population: 12, episodes: 1, elite_frac: 0.25, envs: 12 }
    }
}

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

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NetSection {
    pub preset: NetPreset,
    /// Overrides the preset's encoder: the observation layout it reads (`ego-frame`, `query-centric`).
    pub encoder: Option<sf_sim::Layout>,
    /// Overrides token width and DeepSets width (heads get twice it).
    pub width: Option<usize>,
    /// Overrides the preset's layers in the pose embeddings (`fast`: 1, a linear map, so the
    /// attention cannot prefer near vehicles; 2 makes it non-linear).
    pub pose_layers: Option<usize>,
    /// The encoder's output is `(attention + ego token) / 2`.
    pub ego_skip: bool,
    /// LayerNorm on the critic's features and between its Q-head layers.
    pub critic_layer_norm: bool,
    /// The released code's doubly squashed mean (deterministic actions within +-0.762); off
    /// by default, kept for fidelity comparisons.
    pub squash_mean_twice: bool,
    /// The bottom of the actor's log-std range (absent: the released code's -2.5, a spread of
    /// at least 0.082 per action component); must be in [-10, 0.5). The cloning updates'
    /// log-std target (`sac.warmup_noise`) is clamped into the range.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub log_std_min: Option<f32>,
}

/// `sac.cql_samples` when the config leaves it out.
pub const DEFAULT_CQL_SAMPLES: usize = 10;

fn is_default_cql_samples(n: &usize) -> bool {
    *n == DEFAULT_CQL_SAMPLES
}

fn is_zero_u64(v: &u64) -> bool {
    *v == 0
}

fn is_zero(v: &f32) -> bool {
    *v == 0.0
}

/// The largest `sac.n_step`: longer sums mostly add the behaviour policy's bias.
pub const MAX_N_STEP: u8 = 16;

/// The largest weight a row of `sac.bc_awac_lambda`'s cloning term gets before the batch's
/// normalisation (AWAC and IQL clip theirs likewise, so one row cannot take the whole term).
pub const AWAC_MAX_WEIGHT: f32 = 20.0;

/// The `[sac]` section *is* the SAC learner's configuration: the paper's table (its
/// [`Default`]) plus the released code's and this project's levers. `sf_sac::Sac` takes it as
/// it is; nothing copies it field by field.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SacConfig {
    pub gamma: f32,
    /// Steps per stored transition (n-step returns): workers sum `n_step` rewards discounted by
    /// `gamma` and bootstrap from the observation `n_step` steps later with `gamma^n_step`
    /// (fewer steps where the agent's episode ends or the acting policy changes). 1: the paper.
    pub n_step: u8,
    pub tau: f32,
    pub lr_actor: f64,
    /// The actor's learning rate falls linearly from `lr_actor` to this over
    /// `lr_actor_decay_updates` updates of the actor's SAC phase (counted after the cloning and
    /// critic pre-training updates), then stays there (absent: constant `lr_actor`). Slows the
    /// policy's drift once it has learned what it can.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lr_actor_final: Option<f64>,
    pub lr_actor_decay_updates: u64,
    /// The actor's SAC phase (after the cloning and critic pre-training updates) starts with
    /// its learning rate ramped linearly from 0 over this many updates (0: none), so that
    /// Adam's second moments, fitted to the cloning loss's small gradients, adapt to SAC's
    /// larger ones before the steps grow. Written only when set.
    #[serde(skip_serializing_if = "is_zero_u64")]
    pub lr_actor_ramp_updates: u64,
    pub lr_critic: f64,
    pub lr_alpha: f64,
    pub batch_size: usize,
    pub initial_alpha: f32,
    pub reward_scale: f32,
    /// Environment steps of warm-up actions before the first update.
    pub warmup_steps: u64,
    /// Who acts during the warm-up: uniformly random actions (the paper), or the IDM driver
    /// expressed as the paper's action with `warmup_noise` added (a budget lever: see
    /// `bc_updates`). Driving roles only; the SocialCommAdv adversary always starts random.
    pub warmup_policy: WarmupPolicy,
    /// Standard deviation of the Gaussian noise on each component of the IDM demonstrator's
    /// normalised action during an IDM warm-up.
    pub warmup_noise: f32,
    /// IDM warm-up with a residual action: the probability per step that a vehicle starts a
    /// braking segment (its residual held at U(-1, -0.2) for 4-12 steps), so the data shows
    /// what braking early buys. 0: none.
    pub warmup_brake_prob: f32,
    /// IDM warm-up with the `idm-residual-lateral` action: the probability per step that a
    /// vehicle starts a lane-change segment (its lateral target held at -1 or +1 for 8-20
    /// steps), so the data shows what IDM never does: leave its lane. 0: none.
    #[serde(skip_serializing_if = "is_zero")]
    pub warmup_lane_change_prob: f32,
    /// The first this many updates fit the actor to the replayed actions (behaviour cloning:
    /// mean to the stored action, log-std to `ln(warmup_noise)`) while the critic learns as in
    /// SAC and alpha stays put; once the warm-up is over the cloned policy acts meanwhile.
    /// Requires `warmup_policy = "idm"`. 0: plain SAC.
    pub bc_updates: u64,
    /// The cloning updates draw their batches from the warm-up's transitions only (the first
    /// `warmup_steps` the replay took, all acted by the demonstrator) instead of the whole
    /// replay, which holds the clone's own actions once the warm-up is over: without it a
    /// clone that acts while it learns partly clones itself. Needs `bc_updates > 0` and
    /// `bc_target = "replay"`. The critic learns from the same batches meanwhile. Written
    /// only when set, so the configs stored before it read and write back the same.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub bc_from_warmup: bool,
    /// After the cloning updates, the cloning loss (mean action and log-std) stays in the actor
    /// loss as a term scaled by the critic's mean |Q| (as TD3+BC does) with this weight:
    /// constant if `bc_decay_updates` is 0, else falling linearly to 0 over that many updates.
    /// 0: plain SAC after cloning.
    pub bc_weight: f32,
    pub bc_decay_updates: u64,
    /// Entropy target of the temperature tuning (default: minus the action dimension).
    pub target_entropy: Option<f32>,
    /// After the cloning updates, this many more updates train the critic alone (policy
    /// evaluation of the cloned policy) before the actor and alpha move.
    pub critic_pretrain_updates: u64,
    /// The critic's regression loss: `"mse"` (the paper) or `"huber"` (quadratic within
    /// `huber_delta` of the target, linear beyond, on the scaled reward's units).
    pub critic_loss: CriticLoss,
    pub huber_delta: f32,
    /// What the cloning term pulls the mean action to: the replayed actions (`"replay"`), zero
    /// (`"zero"`: the IDM driver itself, for residual actions), or the IDM driver's action in
    /// each stored state as the worker recorded it (`"oracle"`: any action kind, on the
    /// policy's own states too); with `bc_q_filter` only in states where the critic rates
    /// that action at least as high as the policy's.
    pub bc_target: BcTarget,
    pub bc_q_filter: bool,
    /// With `bc_q_filter`: action components (0-based) the cloning term holds in every
    /// labelled row, whatever the critic rates higher; the filter applies to the others. For a
    /// component whose effect the critic cannot resolve (the direct action's steer, whose
    /// best offset the critic rates within noise of IDM's: `socialflow probe --kind handover`)
    /// while the clone's closed loop fails at a mean deviation of ~0.02. Empty: the filter
    /// applies to every component.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub bc_hold_dims: Vec<usize>,
    /// The components of `bc_hold_dims` learn from the cloning term alone: the actor loss's
    /// `min Q` sees them detached, so the critic's gradient (which, for a component it cannot
    /// resolve, pushes the mean off IDM's label in most states) does not reach them, and SAC
    /// learns only the other components. Needs `bc_hold_dims`. Written only when set.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub bc_hold_clone_only: bool,
    /// AWAC-style advantage weights on the cloning term towards the replayed actions
    /// (`bc_target = "replay"`; absent: every row weighs 1): row i weighs
    /// `exp((min Q(s, a_replay) - min Q(s, a~pi)) / lambda)`, clipped at [`AWAC_MAX_WEIGHT`]
    /// and normalised to mean 1 over the batch, so the policy is pulled towards the stored
    /// actions the critic rates above its own and let go of the others. Needs `bc_weight > 0`
    /// (the term it weighs); the `bc_updates` cloning phase stays unweighted.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bc_awac_lambda: Option<f32>,
    /// A conservative critic (CQL(H), Kumar et al. 2020): every critic update adds, per head,
    /// `cql_weight * (logsumexp_a Q(s, a) - Q(s, a_replay))`, the log-sum-exp over
    /// `cql_samples` uniform actions and `cql_samples` samples of the current policy in the
    /// batch's states (each weighed by its density), so Q falls on the actions the replay has not
    /// shown and rises on those it has: the actor is not led off the data by the critic's
    /// extrapolation when it starts to move. On the scaled reward's units (`reward_scale`).
    /// 0: none (the paper). Written only when set.
    #[serde(skip_serializing_if = "is_zero")]
    pub cql_weight: f32,
    /// Actions per state of each kind (uniform, policy) in `cql_weight`'s log-sum-exp. Written
    /// only when not the default.
    #[serde(skip_serializing_if = "is_default_cql_samples")]
    pub cql_samples: usize,
    /// A Polyak average of the actor's weights (`avg <- (1 - t) avg + t actor` after every
    /// update; absent: none). With it, validation scores and the final policy is the average,
    /// while rollouts keep acting with the online actor. Smooths the policy's oscillation
    /// between neighbouring updates.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub actor_average_tau: Option<f32>,
    /// Rollouts act with the averaged actor of `actor_average_tau` too (published to workers
    /// instead of the online actor), so the data comes from the policy that is validated and
    /// kept rather than from whichever snapshot the last update left. Needs
    /// `actor_average_tau`. Written only when set.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub act_with_average: bool,
    /// The actor reads the critic's (detached) encoder features and publishes a copy of the
    /// critic's encoder instead of training its own: one encoder pass forward and backward
    /// fewer per update.
    pub shared_encoder: bool,
    /// Take the actor loss's critic features from the critic step's forward pass (detached,
    /// before that step) instead of a fresh no-grad pass after it, saving one encoder pass.
    /// The reference script recomputes them (`false`; `socialflow bench sac` compares both).
    pub reuse_critic_features: bool,
    pub seed: u64,
    pub device: Device,
}

impl SacConfig {
    /// The log-std the cloning updates fit: the demonstrator's noise as the cloned policy's
    /// spread, inside the actor's log-std range `[log_std_min, 0.5]` (`net.log_std_min`).
    pub fn bc_log_std(&self, log_std_min: f32) -> f32 {
        self.warmup_noise.max(1e-3).ln().clamp(log_std_min, 0.5)
    }

    /// The actor's learning rate at update `updates` (0-based, counted from the job's first
    /// update): `lr_actor` until the actor's SAC phase starts, then the linear decay towards
    /// `lr_actor_final` if one is set.
    /// Where update number `updates` (0-based) draws its batch: `Some(n)` restricts it to the
    /// replay's first `n` transitions (`bc_from_warmup` during the cloning updates), `None` is
    /// the whole replay.
    pub fn sample_before(&self, updates: u64) -> Option<u64> {
        (self.bc_from_warmup && updates < self.bc_updates).then_some(self.warmup_steps)
    }

    pub fn actor_lr(&self, updates: u64) -> f64 {
        let start = self.bc_updates + self.critic_pretrain_updates;
        let since = updates.saturating_sub(start);
        let lr = match self.lr_actor_final {
            None => self.lr_actor,
            Some(last) => {
                let frac = (since as f64 / self.lr_actor_decay_updates.max(1) as f64).min(1.0);
                self.lr_actor + (last - self.lr_actor) * frac
            }
        };
        if self.lr_actor_ramp_updates > 0 && updates >= start {
            lr * ((since + 1) as f64 / self.lr_actor_ramp_updates as f64).min(1.0)
        } else {
            lr
        }
    }
}

/// `sac.critic_loss`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CriticLoss {
    #[default]
    Mse,
    Huber,
}

/// `sac.bc_target`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BcTarget {
    /// The stored actions of the replay (the demonstrator's during the warm-up).
    #[default]
    Replay,
    /// The zero action (residual kinds: the IDM driver).
    Zero,
    /// The IDM driver's action in each stored state, expressed in the job's action (the
    /// direct action's reference speed and steer; zeros for residual kinds), recorded by the
    /// worker at every step of the job's agents: DAgger-style labels on the policy's own
    /// states, not only the demonstrator's.
    Oracle,
}

impl BcTarget {
    /// The cloning term's target comes from IDM itself, not from the replayed actions, so it
    /// needs no demonstrator's warm-up.
    pub fn is_idm(self, action: ActionMode) -> bool {
        match self {
            Self::Replay => false,
            Self::Zero => action != ActionMode::Direct,
            Self::Oracle => true,
        }
    }
}

/// Who acts during the warm-up (`sac.warmup_policy`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WarmupPolicy {
    /// Uniform in [-1, 1] per action component (the paper's random warm-up).
    #[default]
    Random,
    /// The IDM driver's action plus `warmup_noise`.
    Idm,
    /// The job's own first policy, sampled: for a continuation (`train.init_job`), whose first
    /// policy is the one it continues, so that its replay holds that policy's data and no
    /// demonstrator's (Stage 2's ego phases).
    Policy,
}

impl Default for SacConfig {
    /// The paper's table (gamma 0.9, batch 128, Adam 1e-4 / 5e-4 / 1e-4, tau 0.005, alpha 1,
    /// 30k random warm-up steps, the ego's reward scale 50), no levers.
    fn default() -> Self {
        Self {
            gamma: 0.9,
            n_step: 1,
            tau: 0.005,
            lr_actor: 1e-4,
            lr_actor_final: None,
            lr_actor_decay_updates: 0,
            lr_actor_ramp_updates: 0,
            lr_critic: 5e-4,
            lr_alpha: 1e-4,
            batch_size: 128,
            initial_alpha: 1.0,
            reward_scale: 50.0,
            warmup_steps: 30_000,
            warmup_policy: WarmupPolicy::Random,
            warmup_noise: 0.1,
            warmup_brake_prob: 0.0,
            warmup_lane_change_prob: 0.0,
            bc_updates: 0,
            bc_from_warmup: false,
            bc_weight: 0.0,
            bc_decay_updates: 0,
            target_entropy: None,
            critic_pretrain_updates: 0,
            critic_loss: CriticLoss::Mse,
            huber_delta: 10.0,
            bc_target: BcTarget::Replay,
            bc_q_filter: false,
            bc_hold_dims: Vec::new(),
            bc_hold_clone_only: false,
            bc_awac_lambda: None,
            cql_weight: 0.0,
            cql_samples: DEFAULT_CQL_SAMPLES,
            actor_average_tau: None,
            act_with_average: false,
            shared_encoder: false,
            reuse_critic_features: true,
            seed: 0,
            device: Device::Cpu,
        }
    }
}

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
}
impl TrainSection {
    /// Whether the job continues another (`train.init_job`, or `train.init_from` by name).
    pub fn continues(&self) -> bool {
        self.init_job.is_some() || self.init_from.is_some()
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

    /// `[env]`: scenarios, vehicles, the frozen jobs a kind needs (and `train.init_*`), the action
    /// for the job's kind, conflict cases and observation caps.
    fn validate_env(&self) -> Result<(), ConfigError> {
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

    /// `[net]`: the width and the pose embedding's depth.
    fn validate_net(&self) -> Result<(), ConfigError> {
        if let Some(w) = self.net.width {
            if w == 0 || w % 4 != 0 || w > 1024 {
                return bad(
                    "net.width",
                    format!(
                        "{w} must be a positive multiple of 4 (the attention heads) up to 1024"
                    ),
                );
            }
        }
        if let Some(m) = self.net.log_std_min {
            if !(m.is_finite() && (-10.0..0.5).contains(&m)) {
                return bad("net.log_std_min", format!("{m} must be finite and in [-10, 0.5)"));
            }
        }
        if let Some(p) = self.net.pose_layers {
            if !(1..=4).contains(&p) {
                return bad("net.pose_layers", format!("{p} must be in 1..=4"));
            }
        }
        Ok(())
    }

    /// `[sac]`: ranges, the warm-up and cloning levers and what they need of the action.
    fn validate_sac(&self) -> Result<(), ConfigError> {
        let s = &self.sac;
        if !(s.gamma > 0.0 && s.gamma < 1.0) {
            return bad("sac.gamma", format!("{} must be in (0, 1)", s.gamma));
        }
        if !(s.tau > 0.0 && s.tau <= 1.0) {
            return bad("sac.tau", format!("{} must be in (0, 1]", s.tau));
        }
        for (f, v) in [
            ("sac.lr_actor", s.lr_actor),
            ("sac.lr_critic", s.lr_critic),
            ("sac.lr_alpha", s.lr_alpha),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 1.0) {
                return bad(f, format!("{v} must be in (0, 1)"));
            }
        }
        match (s.lr_actor_final, s.lr_actor_decay_updates) {
            (None, 0) => {}
            (None, _) => return bad("sac.lr_actor_decay_updates", "decays towards sac.lr_actor_final: set it too"),
            (Some(_), 0) => return bad("sac.lr_actor_final", "is reached over sac.lr_actor_decay_updates: set it to a positive number of updates"),
            (Some(f), _) if !(f.is_finite() && f > 0.0 && f <= s.lr_actor) => {
                return bad("sac.lr_actor_final", format!("{f} must be in (0, sac.lr_actor = {}]", s.lr_actor));
            }
            (Some(_), _) => {}
        }
        if s.batch_size == 0 || s.batch_size > 65_536 {
            return bad("sac.batch_size", format!("{} must be in 1..=65536", s.batch_size));
        }
        if !(s.initial_alpha.is_finite() && s.initial_alpha > 0.0) {
            return bad("sac.initial_alpha", format!("{} must be positive", s.initial_alpha));
        }
        if !(s.reward_scale.is_finite() && s.reward_scale > 0.0) {
            return bad("sac.reward_scale", format!("{} must be positive", s.reward_scale));
        }
        if !(s.warmup_noise.is_finite() && (0.0..=1.0).contains(&s.warmup_noise)) {
            return bad("sac.warmup_noise", format!("{} must be in [0, 1]", s.warmup_noise));
        }
        if s.warmup_policy == WarmupPolicy::Idm && !self.kind.drives() {
            return bad(
                "sac.warmup_policy",
                format!(
                    "\"idm\" drives a vehicle; a {} job's action is an SVO",
                    self.kind.as_str()
                ),
            );
        }
        if s.warmup_policy == WarmupPolicy::Policy && !self.train.continues() {
            return bad("sac.warmup_policy", "\"policy\" warms up with the policy a continuation starts from: set train.init_job or train.init_from");
        }
        if self.env.action != ActionMode::Direct && s.warmup_policy == WarmupPolicy::Random {
            return bad("sac.warmup_policy", "a residual policy warms up around the IDM driver: set sac.warmup_policy = \"idm\" (or \"policy\" for a continuation)");
        }
        if !(s.warmup_brake_prob.is_finite() && (0.0..=1.0).contains(&s.warmup_brake_prob)) {
            return bad(
                "sac.warmup_brake_prob",
                format!("{} must be in [0, 1]", s.warmup_brake_prob),
            );
        }
        if !(s.warmup_lane_change_prob.is_finite()
            && (0.0..=1.0).contains(&s.warmup_lane_change_prob))
        {
            return bad(
                "sac.warmup_lane_change_prob",
                format!("{} must be in [0, 1]", s.warmup_lane_change_prob),
            );
        }
        if s.warmup_lane_change_prob > 0.0
            && (self.env.action != ActionMode::IdmResidualLateral
                || s.warmup_policy != WarmupPolicy::Idm)
        {
            return bad("sac.warmup_lane_change_prob", "lane-change segments hold the lateral target of an IDM warm-up: set env.action = \"idm-residual-lateral\" and sac.warmup_policy = \"idm\"");
        }
        if s.warmup_brake_prob > 0.0
            && (self.env.action == ActionMode::Direct || s.warmup_policy != WarmupPolicy::Idm)
        {
            return bad("sac.warmup_brake_prob", "braking segments hold a residual of an IDM warm-up: set env.action to a residual kind and sac.warmup_policy = \"idm\"");
        }
        if s.bc_target == BcTarget::Zero && self.env.action == ActionMode::Direct {
            return bad("sac.bc_target", "\"zero\" is the IDM driver only for residual actions: set env.action to a residual kind");
        }
        if s.actor_average_tau.is_some_and(|t| !(t > 0.0 && t <= 1.0)) {
            return bad(
                "sac.actor_average_tau",
                format!("{:?} must be in (0, 1]", s.actor_average_tau),
            );
        }
        if s.act_with_average && s.actor_average_tau.is_none() {
            return bad(
                "sac.act_with_average",
                "acts with the averaged actor: set sac.actor_average_tau",
            );
        }
        if let Some(l) = s.bc_awac_lambda {
            if !(l.is_finite() && l > 0.0) {
                return bad("sac.bc_awac_lambda", format!("{l} must be finite and positive"));
            }
            if s.bc_target != BcTarget::Replay {
                return bad(
                    "sac.bc_awac_lambda",
                    "advantage weights rate the replayed actions: set sac.bc_target = \"replay\"",
                );
            }
            if s.bc_weight <= 0.0 {
                return bad("sac.bc_awac_lambda", "weights the cloning term that stays after the cloning updates: set sac.bc_weight > 0");
            }
        }
        if !(s.cql_weight.is_finite() && s.cql_weight >= 0.0) {
            return bad("sac.cql_weight", format!("{} must be finite and >= 0", s.cql_weight));
        }
        if !(1..=100).contains(&s.cql_samples) {
            return bad("sac.cql_samples", format!("{} must be in 1..=100", s.cql_samples));
        }
        if !s.bc_hold_dims.is_empty() {
            if !s.bc_q_filter {
                return bad("sac.bc_hold_dims", "holds components out of the Q filter: set sac.bc_q_filter = true (without it the term holds every component)");
            }
            let dim = self.action_dim();
            if let Some(k) = s.bc_hold_dims.iter().find(|&&k| k >= dim) {
                return bad(
                    "sac.bc_hold_dims",
                    format!("component {k} does not exist: the action has {dim} (0-based)"),
                );
            }
            let mut seen = s.bc_hold_dims.clone();
            seen.sort_unstable();
            seen.dedup();
            if seen.len() != s.bc_hold_dims.len() {
                return bad("sac.bc_hold_dims", "lists a component twice");
            }
        }
        if s.bc_hold_clone_only && s.bc_hold_dims.is_empty() {
            return bad(
                "sac.bc_hold_clone_only",
                "applies to the held components: list them in sac.bc_hold_dims",
            );
        }
        if s.bc_hold_clone_only && s.bc_decay_updates > 0 {
            return bad("sac.bc_hold_clone_only", "the held components learn from the cloning term alone: it cannot fade (set sac.bc_decay_updates = 0)");
        }
        if s.bc_q_filter && s.bc_target == BcTarget::Replay {
            return bad("sac.bc_q_filter", "the Q filter compares the policy with the IDM driver's action: set sac.bc_target = \"zero\" (residual actions) or \"oracle\"");
        }
        if !(1..=MAX_N_STEP).contains(&s.n_step) {
            return bad("sac.n_step", format!("{} must be in 1..={MAX_N_STEP}", s.n_step));
        }
        if !(s.huber_delta.is_finite() && s.huber_delta > 0.0) {
            return bad("sac.huber_delta", format!("{} must be positive", s.huber_delta));
        }
        if s.bc_updates > 0 && s.warmup_policy != WarmupPolicy::Idm {
            return bad(
                "sac.bc_updates",
                "behaviour cloning needs a demonstrator: set sac.warmup_policy = \"idm\"",
            );
        }
        if s.bc_from_warmup && (s.bc_updates == 0 || s.bc_target == BcTarget::Zero) {
            return bad("sac.bc_from_warmup", "draws the cloning updates' batches from the demonstrator's warm-up: set sac.bc_updates > 0 and sac.bc_target = \"replay\" or \"oracle\"");
        }
        if !(s.bc_weight.is_finite() && s.bc_weight >= 0.0) {
            return bad("sac.bc_weight", format!("{} must be a non-negative number", s.bc_weight));
        }
        // Cloning towards the zero residual or the recorded IDM labels needs no
        // demonstrator's data.
        if (s.bc_weight > 0.0 || s.bc_decay_updates > 0)
            && s.warmup_policy != WarmupPolicy::Idm
            && !s.bc_target.is_idm(self.env.action)
        {
            return bad(
                "sac.bc_weight",
                "behaviour cloning needs a demonstrator: set sac.warmup_policy = \"idm\"",
            );
        }
        if let Some(t) = s.target_entropy {
            if !t.is_finite() {
                return bad("sac.target_entropy", format!("{t} must be finite"));
            }
        }
        Ok(())
    }

    /// `[train]` and `[worker]`: budgets, replay, publishing and batching.
    fn validate_train(&self) -> Result<(), ConfigError> {
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

    /// The optional `[coordinator]` (CoPO Stage 2) and `[validation]` sections.
    fn validate_sections(&self) -> Result<(), ConfigError> {
        if let Some(c) = &self.coordinator {
            if self.kind != JobKind::Copo {
                return bad(
                    "coordinator",
                    format!("only copo jobs fit a Stage-2 coordinator, not {}", self.kind.as_str()),
                );
            }
            if c.iterations > 1000 {
                return bad(
                    "coordinator.iterations",
                    format!("{} must be at most 1000", c.iterations),
                );
            }
            for (f, v) in
                [("coordinator.population", c.population), ("coordinator.episodes", c.episodes)]
            {
                if v == 0 || v > 10_000 {
                    return bad(f, format!("{v} must be in 1..=10000"));
                }
            }
            if !(c.elite_frac > 0.0 && c.elite_frac <= 1.0) {
                return bad(
                    "coordinator.elite_frac",
                    format!("{} must be in (0, 1]", c.elite_frac),
                );
            }
            if c.envs == 0 || c.envs > 256 {
                return bad("coordinator.envs", format!("{} must be in 1..=256", c.envs));
            }
        }
        if let Some(v) = &self.validation {
            if !(self.kind == JobKind::Ego || self.kind.multi_agent()) {
                return bad(
                    "validation",
                    format!(
                        "selects drivers by success: ego and flow jobs only, not {} (an adversary)",
                        self.kind.as_str()
                    ),
                );
            }
            if v.every_updates == 0 {
                return bad("validation.every_updates", "must be positive");
            }
            if v.episodes == 0 || v.episodes > 10_000 {
                return bad("validation.episodes", format!("{} must be in 1..=10000", v.episodes));
            }
            if v.envs == 0 || v.envs > 256 {
                return bad("validation.envs", format!("{} must be in 1..=256", v.envs));
            }
            if v.test_seed() == v.seed {
                return bad(
                    "validation.test_seed",
                    format!("{} is the validation seed: the test cases must be apart from the cases that select the actor", v.seed),
                );
            }
            if v.test_episodes() > 10_000 {
                return bad(
                    "validation.test_episodes",
                    format!("{} must be in 0..=10000", v.test_episodes()),
                );
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: &str = "name = \"t\"\n[env]\nscenarios = [\"merge\"]\n[train]\nenv_steps = 1000\n";

    #[test]
    fn a_minimal_config_gets_the_paper_defaults() {
        let c = JobConfig::from_toml(&format!("{MIN}[sac]\nwarmup_steps = 100\n")).expect("valid");
        assert_eq!(c.sac.gamma, 0.9);
        assert_eq!(c.sac.batch_size, 128);
        assert_eq!(c.net.preset, NetPreset::Fast);
        let again = JobConfig::from_toml(&c.to_toml()).expect("round trip");
        assert_eq!(again, c);
    }

    /// `env.reward_neighbours`: "observed" on the composed-reward flows; refused, with the
    /// field named, where the reward has no neighbour term; absent from a default's TOML.
    #[test]
    fn reward_neighbours_only_where_the_reward_composes() {
        let with = |kind: &str, v: &str| {
            JobConfig::from_toml(&format!(
                "kind = \"{kind}\"\n{}[sac]\nwarmup_steps = 100\n",
                MIN.replace("[train]", &format!("reward_neighbours = \"{v}\"\n[train]"))
            ))
        };
        let ok = with("socialcomm", "observed").expect("socialcomm observed");
        assert_eq!(ok.env.reward_neighbours, RewardNeighbours::Observed);
        assert_eq!(JobConfig::from_toml(&ok.to_toml()).expect("round trip"), ok);
        assert!(with("copo", "observed").is_ok());
        for kind in ["macad", "ego"] {
            let e = with(kind, "observed").expect_err(kind).to_string();
            assert!(e.contains("env.reward_neighbours") && e.contains(kind), "{e}");
        }
        assert!(with("socialcomm", "nearby").is_err());
        let radius = with("macad", "radius").expect("the default is fine anywhere");
        assert!(!radius.to_toml().contains("reward_neighbours"));
    }

    /// `env.svo_range_deg`: a flow's or FailMaker's own range, inside [-90, 90], low <= high;
    /// refused on ego jobs (whose background brings its own) with the field named.
    #[test]
    fn svo_range_is_a_flows_and_is_checked() {
        let fm = |r: &str, kind: &str| {
            let ego = if kind.contains("failmaker") { "ego_job = 1\n" } else { "" };
            JobConfig::from_toml(&format!(
                "{kind}{}[sac]\nwarmup_steps = 100\n",
                MIN.replace("[train]", &format!("svo_range_deg = {r}\n{ego}[train]"))
            ))
        };
        let ok = fm("[-90.0, -90.0]", "kind = \"failmaker\"\n").map(|j| j.env.svo_range_deg);
        assert_eq!(ok.ok().flatten(), Some([-90.0, -90.0]));
        assert!(fm("[0.0, 45.0]", "kind = \"copo\"\n").is_ok());
        for (r, kind) in [
            ("[10.0, -10.0]", "kind = \"failmaker\"\n"),
            ("[-100.0, 0.0]", "kind = \"failmaker\"\n"),
            ("[0.0, 90.0]", ""),
        ] {
            let e = fm(r, kind).expect_err(r);
            assert!(e.to_string().contains("env.svo_range_deg"), "{r} {kind}: {e}");
        }
    }

    #[test]
    fn lateral_action_slow_leader_and_policy_warmup_are_checked() {
        let lat = MIN.replace("[train]", "action = \"idm-residual-lateral\"\n[train]");
        let ok = JobConfig::from_toml(&format!("{lat}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_lane_change_prob = 0.05\n")).expect("valid");
        assert_eq!((ok.action_dim(), ok.sac.warmup_lane_change_prob), (2, 0.05));
        assert_eq!(JobConfig::from_toml(&ok.to_toml()).expect("round trip"), ok);
        let accel = MIN.replace("[train]", "action = \"idm-accel-residual\"\n[train]");
        let e = JobConfig::from_toml(&format!("{accel}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_lane_change_prob = 0.05\n")).expect_err("no lateral");
        assert!(
            e.to_string().contains("sac.warmup_lane_change_prob")
                && e.to_string().contains("idm-residual-lateral"),
            "{e}"
        );
        let e = JobConfig::from_toml(&format!("{lat}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_lane_change_prob = 1.5\n")).expect_err("range");
        assert!(e.to_string().contains("sac.warmup_lane_change_prob"), "{e}");
        let slow = |v: &str, kind: &str| {
            JobConfig::from_toml(&format!(
                "{kind}{}[sac]\nwarmup_steps = 100\n",
                MIN.replace("[train]", &format!("slow_leader = {v}\n[train]"))
            ))
        };
        assert_eq!(
            slow("{ share = 1.0, speed_mps = 1.5 }", "")
                .expect("valid")
                .case_draw()
                .slow_leader
                .map(|s| s.speed_mps),
            Some(1.5)
        );
        let e = slow("{ share = 1.0, speed_mps = 9.0 }", "").expect_err("too fast");
        assert!(
            e.to_string().contains("env.slow_leader") && e.to_string().contains("speed_mps"),
            "{e}"
        );
        let e = slow("{ share = 1.0, speed_mps = 1.0 }", "kind = \"macad\"\n")
            .expect_err("not an ego job");
        assert!(e.to_string().contains("env.slow_leader"), "{e}");
        let policy = format!("{lat}[sac]\nwarmup_steps = 100\nwarmup_policy = \"policy\"\nbc_weight = 0.4\nbc_target = \"zero\"\nbc_q_filter = true\n");
        let e = JobConfig::from_toml(&policy).expect_err("not a continuation");
        assert!(
            e.to_string().contains("sac.warmup_policy") && e.to_string().contains("init_job"),
            "{e}"
        );
        let cont = JobConfig::from_toml(&policy.replace("[train]\n", "[train]\ninit_job = 1\n"))
            .expect("a continuation warms up with its own policy");
        assert_eq!(cont.sac.warmup_policy, WarmupPolicy::Policy);
        assert!(!cont.train.init_replay, "a continuation starts with an empty replay unless asked");
        let carry = |extra: &str| {
            JobConfig::from_toml(&policy.replace("[train]\n", &format!("[train]\n{extra}")))
        };
        let c = carry("init_job = 1\ninit_replay = true\n").expect("a carried replay");
        assert!(c.train.init_replay);
        for (extra, says) in [
            ("init_replay = true\n", "init_job"),
            ("init_job = 1\ninit_replay = true\npersist_replay = false\n", "persist_replay"),
        ] {
            let e = carry(extra).expect_err(extra);
            assert!(
                e.to_string().contains("train.init_replay") && e.to_string().contains(says),
                "{e}"
            );
        }
        let e = JobConfig::from_toml(&format!("{lat}[sac]\nwarmup_steps = 100\n"))
            .expect_err("random warm-up");
        assert!(e.to_string().contains("sac.warmup_policy"), "{e}");
    }

    #[test]
    fn errors_name_the_field() {
        let e = JobConfig::from_toml(&format!("{MIN}[sac]\ngamma = 1.5\n")).expect_err("gamma");
        assert!(e.to_string().contains("sac.gamma"), "{e}");
        let e = JobConfig::from_toml(&format!("{MIN}[sac]\nbogus = 1\n")).expect_err("unknown");
        assert!(e.to_string().contains("bogus"), "{e}");
        let e = JobConfig::from_toml(
            &format!("{MIN}[sac]\nwarmup_steps = 5000\n")
                .replace("env_steps = 1000", "env_steps = 1000\nreplay_capacity = 1000"),
        )
        .expect_err("warm-up");
        assert!(e.to_string().contains("sac.warmup_steps"), "{e}");
        let e = JobConfig::from_toml(&format!("{MIN}[coordinator]\niterations = 2\n"))
            .expect_err("not copo");
        assert!(e.to_string().contains("coordinator"), "{e}");
        let copo = format!("kind = \"copo\"\n{MIN}[sac]\nwarmup_steps = 100\n");
        let e = JobConfig::from_toml(&format!("{copo}[coordinator]\nelite_frac = 0.0\n"))
            .expect_err("elite");
        assert!(e.to_string().contains("coordinator.elite_frac"), "{e}");
        assert_eq!(
            JobConfig::from_toml(&copo).expect("copo").coordinator(),
            Some(CoordinatorSection::default()),
            "copo fits one by default"
        );
        assert_eq!(
            JobConfig::from_toml(&format!("{copo}[coordinator]\niterations = 0\n"))
                .expect("stage 1 only")
                .coordinator(),
            None
        );
    }

    #[test]
    fn the_name_idm_is_reserved_for_the_idm_driver() {
        let e =
            JobConfig::from_toml(&MIN.replace("name = \"t\"", "name = \"idm\"")).expect_err("idm");
        assert!(e.to_string().contains("name") && e.to_string().contains("reserved"), "{e}");
        let e = JobConfig::from_toml(&MIN.replace("name = \"t\"", "name = \"idm-mobil\""))
            .expect_err("idm-mobil");
        assert!(e.to_string().contains("`idm-mobil` is reserved"), "{e}");
    }

    #[test]
    fn the_actor_rate_ramps_up_from_zero_when_the_sac_phase_starts() {
        let cfg = SacConfig {
            lr_actor: 1e-4,
            bc_updates: 100,
            critic_pretrain_updates: 50,
            lr_actor_ramp_updates: 10,
            ..SacConfig::default()
        };
        // Cloning at the full rate; the actor's first SAC update at a tenth, then up to full.
        assert_eq!(cfg.actor_lr(0), 1e-4);
        assert!((cfg.actor_lr(150) - 1e-5).abs() < 1e-12, "{}", cfg.actor_lr(150));
        assert!((cfg.actor_lr(154) - 5e-5).abs() < 1e-12, "{}", cfg.actor_lr(154));
        assert_eq!(cfg.actor_lr(159), 1e-4);
        assert_eq!(cfg.actor_lr(10_000), 1e-4);
        // With the decay the ramp multiplies the decayed rate.
        let decay =
            SacConfig { lr_actor_final: Some(0.0), lr_actor_decay_updates: 20, ..cfg.clone() };
        assert!((decay.actor_lr(159) - 1e-4 * 11.0 / 20.0).abs() < 1e-12);
        assert_eq!(decay.actor_lr(170), 0.0);
        let plain = SacConfig { lr_actor_ramp_updates: 0, ..cfg };
        assert_eq!(plain.actor_lr(150), 1e-4);
        let text = JobConfig::from_toml(&format!("{MIN}[sac]\nlr_actor_ramp_updates = 10\n"))
            .expect("set")
            .to_toml();
        assert!(text.contains("lr_actor_ramp_updates = 10"), "{text}");
        assert!(!JobConfig::from_toml(MIN).expect("none").to_toml().contains("lr_actor_ramp"));
    }

    #[test]
    fn held_components_need_the_filter_exist_once_and_round_trip_only_when_set_as_clone_only() {
        let dim = JobConfig::from_toml(MIN).expect("min").action_dim();
        let base = format!("{MIN}[sac]\nbc_target = \"oracle\"\nbc_q_filter = true\n");
        let ok = JobConfig::from_toml(&format!("{base}bc_hold_dims = [{}]\n", dim - 1))
            .expect("the last component");
        assert_eq!(ok.sac.bc_hold_dims, vec![dim - 1]);
        let back = JobConfig::from_toml(&ok.to_toml()).expect("round trip");
        assert_eq!(back.sac.bc_hold_dims, vec![dim - 1]);
        assert!(!JobConfig::from_toml(&base).expect("none").to_toml().contains("bc_hold_dims"));
        let only = JobConfig::from_toml(&format!(
            "{base}bc_hold_dims = [{}]\nbc_hold_clone_only = true\n",
            dim - 1
        ))
        .expect("clone only");
        assert!(only.sac.bc_hold_clone_only);
        assert!(JobConfig::from_toml(&only.to_toml()).expect("round trip").sac.bc_hold_clone_only);
        assert!(!ok.to_toml().contains("bc_hold_clone_only"));
        // Each refusal names the field it refuses and why.
        for (text, field, why) in [
            (format!("{base}bc_hold_dims = [{dim}]\n"), "sac.bc_hold_dims", "does not exist"),
            (format!("{base}bc_hold_dims = [0, 0]\n"), "sac.bc_hold_dims", "twice"),
            (
                format!("{MIN}[sac]\nbc_target = \"oracle\"\nbc_hold_dims = [0]\n"),
                "sac.bc_hold_dims",
                "bc_q_filter = true",
            ),
            (
                format!("{base}bc_hold_clone_only = true\n"),
                "sac.bc_hold_clone_only",
                "sac.bc_hold_dims",
            ),
            (
                format!(
                    "{base}bc_hold_dims = [0]\nbc_hold_clone_only = true\nbc_decay_updates = 100\n"
                ),
                "sac.bc_hold_clone_only",
                "sac.bc_decay_updates",
            ),
        ] {
            let e = JobConfig::from_toml(&text).expect_err(why);
            assert!(e.to_string().contains(field) && e.to_string().contains(why), "{e}");
        }
    }

    #[test]
    fn the_conservative_critic_validates_and_round_trips_only_when_set() {
        let base = format!("{MIN}[sac]\n");
        let plain = JobConfig::from_toml(&base).expect("none");
        assert_eq!((plain.sac.cql_weight, plain.sac.cql_samples), (0.0, DEFAULT_CQL_SAMPLES));
        let text = plain.to_toml();
        assert!(!text.contains("cql_"), "absent stays absent: {text}");
        let ok = JobConfig::from_toml(&format!("{base}cql_weight = 2.0\ncql_samples = 4\n"))
            .expect("set");
        let back = JobConfig::from_toml(&ok.to_toml()).expect("round trip");
        assert_eq!((back.sac.cql_weight, back.sac.cql_samples), (2.0, 4));
        for (extra, field, needle) in [
            ("cql_weight = -1.0", "sac.cql_weight", "finite and >= 0"),
            ("cql_weight = nan", "sac.cql_weight", "finite and >= 0"),
            ("cql_weight = inf", "sac.cql_weight", "finite and >= 0"),
            ("cql_samples = 0", "sac.cql_samples", "1..=100"),
            ("cql_samples = 101", "sac.cql_samples", "1..=100"),
        ] {
            let e = JobConfig::from_toml(&format!("{base}{extra}\n")).expect_err(extra);
            assert!(
                e.to_string().contains(field) && e.to_string().contains(needle),
                "{extra}: {e}"
            );
        }
    }

    #[test]
    fn awac_weights_need_a_positive_lambda_and_the_replayed_actions() {
        let base = format!("{MIN}[sac]\nwarmup_policy = \"idm\"\nbc_weight = 0.4\n");
        let ok = JobConfig::from_toml(&format!("{base}bc_awac_lambda = 1.0\n"))
            .expect("replay target by default");
        assert_eq!(ok.sac.bc_awac_lambda, Some(1.0));
        assert_eq!(
            JobConfig::from_toml(&ok.to_toml()).expect("round trip").sac.bc_awac_lambda,
            Some(1.0)
        );
        assert!(
            !JobConfig::from_toml(&base).expect("none").to_toml().contains("bc_awac_lambda"),
            "absent stays absent"
        );
        for (extra, needle) in [
            ("bc_awac_lambda = 0.0", "finite and positive"),
            ("bc_awac_lambda = -1.0", "finite and positive"),
            ("bc_awac_lambda = nan", "finite and positive"),
            ("bc_awac_lambda = inf", "finite and positive"),
        ] {
            let e = JobConfig::from_toml(&format!("{base}{extra}\n")).expect_err(extra);
            assert!(
                e.to_string().contains("sac.bc_awac_lambda") && e.to_string().contains(needle),
                "{extra}: {e}"
            );
        }
        let e = JobConfig::from_toml(&format!(
            "{MIN}[sac]\nwarmup_policy = \"idm\"\nbc_awac_lambda = 1.0\n"
        ))
        .expect_err("no cloning term");
        assert!(
            e.to_string().contains("sac.bc_awac_lambda") && e.to_string().contains("bc_weight > 0"),
            "{e}"
        );
        let zero = MIN.replace("[train]", "action = \"idm-accel-residual\"\n[train]")
            + "[sac]\nwarmup_policy = \"idm\"\nbc_target = \"zero\"\nbc_awac_lambda = 1.0\n";
        let e = JobConfig::from_toml(&zero).expect_err("zero target");
        assert!(
            e.to_string().contains("sac.bc_awac_lambda") && e.to_string().contains("replay"),
            "{e}"
        );
    }

    #[test]
    fn validation_section_is_checked_and_round_trips() {
        let ego = MIN.replace("name = \"t\"\n", "name = \"t\"\nkind = \"ego\"\n");
        let cfg = JobConfig::from_toml(&format!("{ego}[validation]\nevery_updates = 250\n"))
            .expect("ego with validation");
        assert_eq!(
            cfg.validation,
            Some(ValidationSection { every_updates: 250, ..Default::default() })
        );
        assert_eq!(
            JobConfig::from_toml(&cfg.to_toml()).expect("round trip").validation,
            cfg.validation
        );
        assert_eq!(JobConfig::from_toml(&ego).expect("no section").validation, None);
        for (body, field) in [
            ("every_updates = 0", "validation.every_updates"),
            ("episodes = 0", "validation.episodes"),
            ("envs = 0", "validation.envs"),
            ("shots = 3", "shots"),
        ] {
            let e = JobConfig::from_toml(&format!("{ego}[validation]\n{body}\n")).expect_err(body);
            assert!(e.to_string().contains(field), "{body}: {e}");
        }
        let fm = MIN
            .replace("name = \"t\"\n", "name = \"t\"\nkind = \"failmaker\"\n")
            .replace("[train]", "ego_job = 1\n[train]");
        let e = JobConfig::from_toml(&format!("{fm}[validation]\n")).expect_err("an adversary");
        assert!(e.to_string().contains("validation") && e.to_string().contains("failmaker"), "{e}");
    }

    #[test]
    fn the_idm_warm_up_is_checked() {
        let ok = JobConfig::from_toml(&format!("{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 50\ntarget_entropy = -3.0\n")).expect("valid");
        assert_eq!(
            (ok.sac.warmup_policy, ok.sac.bc_updates, ok.sac.target_entropy),
            (WarmupPolicy::Idm, 50, Some(-3.0))
        );
        let e = JobConfig::from_toml(&format!("{MIN}[sac]\nwarmup_steps = 100\nbc_updates = 50\n"))
            .expect_err("nothing to clone");
        assert!(e.to_string().contains("sac.bc_updates"), "{e}");
    }

    /// The averaged actor: its rate in (0, 1], acting with it only when there is one, and
    /// `act_with_average` written only when set.
    #[test]
    fn acting_with_the_averaged_actor_needs_an_average() {
        let off = JobConfig::from_toml(&format!("{MIN}[sac]\nactor_average_tau = 0.01\n"))
            .expect("valid");
        assert!(
            !off.sac.act_with_average && !off.to_toml().contains("act_with_average"),
            "unset is not written"
        );
        let on = JobConfig::from_toml(&format!(
            "{MIN}[sac]\nactor_average_tau = 0.01\nact_with_average = true\n"
        ))
        .expect("valid");
        assert!(on.sac.act_with_average);
        assert_eq!(JobConfig::from_toml(&on.to_toml()).expect("round trip").sac, on.sac);
        for (body, field) in [
            ("act_with_average = true\n", "sac.act_with_average"),
            ("actor_average_tau = 0.0\n", "sac.actor_average_tau"),
            ("actor_average_tau = 1.5\n", "sac.actor_average_tau"),
        ] {
            let e = JobConfig::from_toml(&format!("{MIN}[sac]\n{body}")).expect_err(body);
            assert!(e.to_string().contains(field), "{body}: {e}");
        }
    }

    /// `bc_from_warmup` restricts the cloning updates, and only those, to the warm-up's rows;
    /// it needs cloning updates towards the replayed actions, and is written only when set.
    #[test]
    fn cloning_from_the_warmup_only() {
        let sac = "[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 50\n";
        let off = JobConfig::from_toml(&format!("{MIN}{sac}")).expect("valid");
        assert_eq!((off.sac.sample_before(0), off.sac.sample_before(49)), (None, None));
        assert!(!off.to_toml().contains("bc_from_warmup"), "unset is not written");
        let on =
            JobConfig::from_toml(&format!("{MIN}{sac}bc_from_warmup = true\n")).expect("valid");
        assert_eq!(
            (on.sac.sample_before(0), on.sac.sample_before(49), on.sac.sample_before(50)),
            (Some(100), Some(100), None)
        );
        assert_eq!(JobConfig::from_toml(&on.to_toml()).expect("round trip").sac, on.sac);
        for body in
            ["warmup_steps = 100\nwarmup_policy = \"idm\"\nbc_from_warmup = true\n", "warmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 5\nbc_target = \"zero\"\nbc_from_warmup = true\n"]
        {
            let cfg = if body.contains("zero") { MIN.replace("[train]", "action = \"idm-accel-residual\"\n[train]") } else { MIN.to_string() };
            let e = JobConfig::from_toml(&format!("{cfg}[sac]\n{body}")).expect_err(body);
            assert!(e.to_string().contains("sac.bc_from_warmup"), "{body}: {e}");
        }
        let e = JobConfig::from_toml(&format!(
            "{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nwarmup_noise = 2.0\n"
        ))
        .expect_err("noise");
        assert!(e.to_string().contains("sac.warmup_noise"), "{e}");
        let adv = "kind = \"socialcomm-adv\"\n".to_string()
            + &MIN.replace("[train]", "ego_job = 1\nbackground_job = 2\n[train]");
        let e = JobConfig::from_toml(&format!(
            "{adv}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"
        ))
        .expect_err("adversary");
        assert!(e.to_string().contains("sac.warmup_policy"), "{e}");
        let e = JobConfig::from_toml(&format!(
            "{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"expert\"\n"
        ))
        .expect_err("unknown policy");
        assert!(e.to_string().contains("warmup_policy"), "{e}");
    }

    /// The acceleration residual, the critic's and the cloning term's options, and the
    /// observation caps: accepted when they fit, refused naming the field otherwise.
    #[test]
    fn the_learning_recipe_is_checked() {
        let env = MIN.replace(
            "[train]",
            "action = \"idm-accel-residual\"\nmax_neighbours = 10\nmax_segments = 48\n[train]",
        );
        let ok = JobConfig::from_toml(&format!(
            "{env}[net]\npose_layers = 2\nego_skip = true\ncritic_layer_norm = true\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\ncritic_loss = \"huber\"\nbc_target = \"zero\"\nbc_q_filter = true\ncritic_pretrain_updates = 10\nshared_encoder = true\n"
        ))
        .expect("valid");
        assert_eq!(
            (ok.action_dim(), ok.env.max_neighbours, ok.sac.critic_loss, ok.sac.bc_target),
            (1, Some(10), CriticLoss::Huber, BcTarget::Zero)
        );
        assert_eq!(JobConfig::from_toml(&ok.to_toml()).expect("round trip"), ok);
        // IDM's recorded labels, Q-filtered, with the direct action: no demonstrator needed.
        let oracle = JobConfig::from_toml(&format!(
            "{MIN}[sac]\nwarmup_steps = 100\nbc_target = \"oracle\"\nbc_q_filter = true\nbc_weight = 1.0\n"
        ))
        .expect("oracle labels");
        assert_eq!(
            (oracle.env.action, oracle.sac.bc_target),
            (ActionMode::Direct, BcTarget::Oracle)
        );
        assert_eq!(JobConfig::from_toml(&oracle.to_toml()).expect("round trip"), oracle);
        for (text, field) in [
            (format!("{env}[sac]\nwarmup_steps = 100\n"), "sac.warmup_policy"),
            (format!("{MIN}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_target = \"zero\"\n"), "sac.bc_target"),
            (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_q_filter = true\n"), "sac.bc_q_filter"),
            (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nhuber_delta = 0.0\n"), "sac.huber_delta"),
            (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nn_step = 0\n"), "sac.n_step"),
            (format!("{env}[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nn_step = 17\n"), "sac.n_step"),
            (format!("{env}[net]\npose_layers = 9\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"), "net.pose_layers"),
            (format!("{env}[net]\nlog_std_min = 0.5\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"), "net.log_std_min"),
            (format!("{env}[net]\nlog_std_min = -12.0\n[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\n"), "net.log_std_min"),
            (format!("{}[sac]\nwarmup_steps = 100\n", MIN.replace("[train]", "max_segments = 0\n[train]")), "env.max_segments"),
            (format!("{}[sac]\nwarmup_steps = 100\n", MIN.replace("[train]", "action = \"idm-brake\"\n[train]")), "action"),
        ] {
            let e = JobConfig::from_toml(&text).expect_err(field);
            assert!(e.to_string().contains(field), "{field}: {e}");
        }
        let adv = "kind = \"socialcomm-adv\"\n".to_string()
            + &MIN.replace(
                "[train]",
                "ego_job = 1\nbackground_job = 2\naction = \"idm-accel-residual\"\n[train]",
            );
        let e = JobConfig::from_toml(&format!("{adv}[sac]\nwarmup_steps = 100\n"))
            .expect_err("adversary");
        assert!(e.to_string().contains("env.action"), "{e}");
    }

    /// `sac.lr_actor_final`: constant before the actor's SAC phase, linear over the decay,
    /// flat after it; both fields or neither, the final rate within (0, lr_actor].
    #[test]
    fn the_actor_learning_rate_decays_after_cloning_and_pretraining() {
        let sac = "[sac]\nwarmup_steps = 100\nwarmup_policy = \"idm\"\nbc_updates = 10\ncritic_pretrain_updates = 20\nlr_actor = 1e-4\n";
        let c = JobConfig::from_toml(&format!(
            "{MIN}{sac}lr_actor_final = 2e-5\nlr_actor_decay_updates = 100\n"
        ))
        .expect("valid");
        let lr = |u| c.sac.actor_lr(u);
        assert_eq!((lr(0), lr(30)), (1e-4, 1e-4), "constant through cloning and pre-training");
        assert!((lr(80) - 6e-5).abs() < 1e-12, "half way: {}", lr(80));
        assert!(
            (lr(130) - 2e-5).abs() < 1e-12 && (lr(10_000) - 2e-5).abs() < 1e-12,
            "flat at the end"
        );
        assert_eq!(JobConfig::from_toml(&c.to_toml()).expect("round trip"), c);
        let plain = JobConfig::from_toml(&format!("{MIN}{sac}")).expect("no decay");
        assert_eq!(plain.sac.actor_lr(5_000), 1e-4);
        for (extra, field) in [
            ("lr_actor_decay_updates = 100\n", "sac.lr_actor_decay_updates"),
            ("lr_actor_final = 2e-5\n", "sac.lr_actor_final"),
            ("lr_actor_final = 2e-4\nlr_actor_decay_updates = 100\n", "sac.lr_actor_final"),
            ("lr_actor_final = 0.0\nlr_actor_decay_updates = 100\n", "sac.lr_actor_final"),
        ] {
            let e = JobConfig::from_toml(&format!("{MIN}{sac}{extra}")).expect_err(field);
            assert!(e.to_string().contains(field), "{extra}: {e}");
        }
    }

    #[test]
    fn dependencies_serve_only_in_roles_their_kind_fits() {
        use JobKind::*;
        assert!(DepRole::Background.accepts(Ego, Failmaker).is_ok());
        assert!(DepRole::Background
            .accepts(Ego, Ego)
            .expect_err("ego")
            .to_string()
            .contains("not a traffic flow"));
        assert!(DepRole::Background
            .accepts(SocialcommAdv, Copo)
            .expect_err("not socialcomm")
            .to_string()
            .contains("SocialComm"));
        assert!(DepRole::Background.accepts(SocialcommAdv, Socialcomm).is_ok());
        assert!(DepRole::Ego.accepts(Failmaker, Macad).is_err());
        assert!(DepRole::Ego.accepts(Failmaker, Ego).is_ok());
        assert!(DepRole::Init.accepts(Ego, Failmaker).is_err());
        assert!(DepRole::Init.accepts(Failmaker, Failmaker).is_ok());
    }
}
