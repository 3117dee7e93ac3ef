//! Network sizes and variants. Sizes are configuration, not code.

use serde::{Deserialize, Serialize};

/// The top of the actor's log-std range (the released code's).
pub const LOG_STD_MAX: f32 = 0.5;
/// The bottom of it unless `NetConfig::log_std_min` says otherwise (the released code's).
pub const LOG_STD_MIN: f32 = -2.5;
pub use sf_sim::DriveAction;
/// Which encoder reads the observation: the observation layout it was built for (one type
/// for the choice, from the simulator to the job config).
pub use sf_sim::Layout;

/// Which SVO inputs the network consumes (observation channels it does not consume are
/// zeroed): the simulator's visibility type, one type for the concept.
pub use sf_sim::SvoVisibility;

/// A [`NetConfig`] that [`NetConfig::validate`] refuses; names the field and its value.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum NetConfigError {
    #[error("net config field `{field}` must be positive")]
    NotPositive { field: &'static str },
    #[error("net config field `init_log_std` must lie in the actor's log-std range [{log_std_min}, 0.5], got {init_log_std}")]
    InitLogStd { init_log_std: f32, log_std_min: f32 },
    #[error("net config field `log_std_min` must be finite and in [-10, 0.5), got {log_std_min}")]
    LogStdMin { log_std_min: f32 },
    #[error("net config field `heads`: d_model {d_model} is not divisible by {heads}")]
    Heads { d_model: usize, heads: usize },
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct NetConfig {
    pub encoder: Layout,
    /// Token width D.
    pub d_model: usize,
    /// Width of the DeepSets' phi and rho MLPs.
    pub set_hidden: usize,
    /// Linear layers of the per-vector phi MLP (the paper: 3). The per-vector MLP runs on every
    /// history and map vector, so its depth is the main cost of the encoder.
    pub phi_layers: usize,
    /// Linear layers of the MLPs that embed observer-relative poses (agent context, segments).
    pub pose_layers: usize,
    /// Width of the actor and critic head MLPs.
    pub head_hidden: usize,
    pub heads: usize,
    pub svo: SvoVisibility,
    /// FailMaker: the ego flag channel is consumed.
    pub ego_flag: bool,
    /// Action dimension (`action.dim()` for driving, 1 for the adversary).
    pub action_dim: usize,
    /// How a driving policy's action moves its vehicle (`env.action`); whoever runs the policy
    /// applies it (`sf_rollout::drive`).
    pub action: DriveAction,
    /// The released code's mean head: tanh on the mean *and* on the sample, so the
    /// deterministic action stays within +-tanh(1) = +-0.762. Off (default): the mean is
    /// squashed once, by the sample's tanh.
    pub squash_mean_twice: bool,
    /// The actor's log-std at initialisation (the log-std head's output bias); a warm-up with a
    /// demonstrator sets it to the demonstrator's noise so the first policy is not noisier.
    pub init_log_std: f32,
    /// The bottom of the actor's log-std range `[log_std_min, 0.5]` (the released code's:
    /// -2.5, a spread of at least e^-2.5 = 0.082 per action component). A policy that must
    /// act with less noise than that (steering a direct action) needs a lower one.
    pub log_std_min: f32,
    /// LayerNorm on the critic's encoder features and between its Q-head layers (RLPD, DroQ).
    pub critic_layer_norm: bool,
    /// The heads read `[ego token, attention output]` instead of the attention output alone,
    /// so the ego's own state reaches them undiluted (highway-env's ego-attention adds them).
    pub ego_skip: bool,
}

impl Default for NetConfig {
    fn default() -> Self {
        Self::fast()
    }
}

impl NetConfig {
    /// The paper's network at the reference script's `paper` size (D = 128, hidden 256).
    pub fn paper() -> Self {
        Self {
            encoder: Layout::EgoFrame,
            d_model: 128,
            set_hidden: 256,
            phi_layers: 3,
            pose_layers: 2,
            head_hidden: 256,
            heads: 4,
            svo: SvoVisibility::None,
            ego_flag: false,
            action_dim: 2,
            action: DriveAction::Direct,
            squash_mean_twice: false,
            init_log_std: -1.0,
            log_std_min: LOG_STD_MIN,
            critic_layer_norm: false,
            ego_skip: false,
        }
    }

    /// The reference script's `compact` size (hidden 128).
    pub fn compact() -> Self {
        Self { set_hidden: 128, ..Self::paper() }
    }

    /// Our default: query-centric encoder at widths this CPU can train.
    pub fn fast() -> Self {
        Self {
            encoder: Layout::QueryCentric,
            d_model: 64,
            set_hidden: 64,
            phi_layers: 1,
            pose_layers: 1,
            head_hidden: 128,
            ..Self::paper()
        }
    }

    /// Whether weights of a network built from `other` load into one built from `self` and
    /// mean the same: every field but `init_log_std`, which only sets fresh weights (a
    /// continuation or a restored checkpoint brings its own).
    pub fn same_network(&self, other: &Self) -> bool {
        Self { init_log_std: other.init_log_std, ..self.clone() } == *other
    }

    /// Whether weights of a network built from `other` load into one built from `self`, which
    /// may consume context channels `other` did not (its SVO inputs, the ego flag): the sizes
    /// are the same, and [`crate::encoder::Encoder::silence_new_context`] makes them mean the
    /// same. What a warm start across kinds needs.
    pub fn same_shapes(&self, other: &Self) -> bool {
        Self { svo: other.svo, ego_flag: other.ego_flag, ..self.clone() }.same_network(other)
    }

    /// Checks sizes; names the field.
    pub fn validate(&self) -> Result<(), NetConfigError> {
        for (f, v) in [
            ("d_model", self.d_model),
            ("set_hidden", self.set_hidden),
            ("phi_layers", self.phi_layers),
            ("pose_layers", self.pose_layers),
            ("head_hidden", self.head_hidden),
            ("heads", self.heads),
            ("action_dim", self.action_dim),
        ] {
            if v == 0 {
                return Err(NetConfigError::NotPositive { field: f });
            }
        }
        if !(self.log_std_min.is_finite() && (-10.0..LOG_STD_MAX).contains(&self.log_std_min)) {
            return Err(NetConfigError::LogStdMin { log_std_min: self.log_std_min });
        }
        if !(self.log_std_min..=LOG_STD_MAX).contains(&self.init_log_std) {
            return Err(NetConfigError::InitLogStd {
                init_log_std: self.init_log_std,
                log_std_min: self.log_std_min,
            });
        }
        if !self.d_model.is_multiple_of(self.heads) {
            return Err(NetConfigError::Heads { d_model: self.d_model, heads: self.heads });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A continuation may start fresh weights with another spread; any other field differs.
    #[test]
    fn the_same_network_ignores_only_the_initial_spread() {
        let a = NetConfig::fast();
        assert!(a.same_network(&NetConfig { init_log_std: -1.7, ..a.clone() }));
        assert!(!a.same_network(&NetConfig { d_model: 32, ..a.clone() }));
        assert!(!a.same_network(&NetConfig {
            action_dim: 2,
            action: DriveAction::IdmResidualLateral,
            ..a.clone()
        }));
    }
}
