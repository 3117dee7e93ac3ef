//! `[net]`: the network's preset and overrides, and their checks. Must not: know burn types
//! (the learner maps this onto `sf_nn::NetConfig`).

use serde::{Deserialize, Serialize};

use super::{bad, ConfigError, JobConfig, NetPreset};

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

impl JobConfig {
    /// `[net]`: the width and the pose embedding's depth.
    pub(super) fn validate_net(&self) -> Result<(), ConfigError> {
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
}
