//! Network sizes and variants. Sizes are configuration, not code.

use serde::{Deserialize, Serialize};

/// Which encoder reads the observation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EncoderKind {
    EgoFrame,
    QueryCentric,
}

/// Which SVO inputs the network consumes (observation channels it does not consume are zeroed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SvoInput {
    /// MACAD, every ego policy, the adversary.
    None,
    /// CoPO: own SVO.
    Own,
    /// SocialComm: own and every neighbour's.
    All,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct NetConfig {
    pub encoder: EncoderKind,
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
    pub svo: SvoInput,
    /// FailMaker: the ego flag channel is consumed.
    pub ego_flag: bool,
    /// Action dimension (2 for driving, 1 for the adversary).
    pub action_dim: usize,
    /// The driving action is a residual added to the IDM driver's action (`env.action =
    /// "idm-residual"`); whoever runs the policy applies it (`sf_sac::drive`).
    pub idm_residual: bool,
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
            encoder: EncoderKind::EgoFrame,
            d_model: 128,
            set_hidden: 256,
            phi_layers: 3,
            pose_layers: 2,
            head_hidden: 256,
            heads: 4,
            svo: SvoInput::None,
            ego_flag: false,
            action_dim: 2,
            idm_residual: false,
        }
    }

    /// The reference script's `compact` size (hidden 128).
    pub fn compact() -> Self {
        Self { set_hidden: 128, ..Self::paper() }
    }

    /// Our default: query-centric encoder at widths this CPU can train.
    pub fn fast() -> Self {
        Self { encoder: EncoderKind::QueryCentric, d_model: 64, set_hidden: 64, phi_layers: 1, pose_layers: 1, head_hidden: 128, ..Self::paper() }
    }

    /// Checks sizes; names the field.
    pub fn validate(&self) -> Result<(), String> {
        for (f, v) in [("d_model", self.d_model), ("set_hidden", self.set_hidden), ("phi_layers", self.phi_layers), ("pose_layers", self.pose_layers), ("head_hidden", self.head_hidden), ("heads", self.heads), ("action_dim", self.action_dim)] {
            if v == 0 {
                return Err(format!("net config field `{f}` must be positive"));
            }
        }
        if !self.d_model.is_multiple_of(self.heads) {
            return Err(format!("net config field `heads`: d_model {} is not divisible by {}", self.d_model, self.heads));
        }
        Ok(())
    }
}
