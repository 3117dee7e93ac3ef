//! `[sac]`: the learning recipe ([`SacConfig`], the paper's table by default), its schedules and
//! their checks, including what the warm-up and cloning levers need of the action. Must not:
//! know burn types (the learner maps this onto `sf_sac`'s).

use serde::{Deserialize, Serialize};

use super::ActionMode;
use super::{bad, ConfigError, Device, JobConfig};

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

impl JobConfig {
    /// `[sac]`: ranges and learning rates, then the warm-up, the extras and the cloning term (one
    /// check each, in this order, so a config with several faults names the same field first).
    pub(super) fn validate_sac(&self) -> Result<(), ConfigError> {
        self.validate_sac_rates()?;
        self.validate_sac_warmup()?;
        self.validate_sac_extras()?;
        self.validate_sac_cloning()
    }

    /// `[sac]`'s discount, rates (and the actor's decay), batch size, temperature and reward scale.
    fn validate_sac_rates(&self) -> Result<(), ConfigError> {
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
        Ok(())
    }

    /// `[sac]`'s warm-up: its policy and segments, and what they need of the job's kind and action.
    fn validate_sac_warmup(&self) -> Result<(), ConfigError> {
        let s = &self.sac;
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
        if s.warmup_policy == WarmupPolicy::Policy && !self.train.starts_from_weights() {
            return bad("sac.warmup_policy", "\"policy\" warms up with the policy a job starts from: set train.init_job, train.init_from or train.warm_start_from");
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
        Ok(())
    }

    /// `[sac]`'s averaged actor, advantage weights and conservative critic.
    fn validate_sac_extras(&self) -> Result<(), ConfigError> {
        let s = &self.sac;
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
        Ok(())
    }

    /// `[sac]`'s cloning term (held components, Q filter, demonstrator, weight), the n-step return,
    /// the Huber loss and the target entropy.
    fn validate_sac_cloning(&self) -> Result<(), ConfigError> {
        let s = &self.sac;
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
}
