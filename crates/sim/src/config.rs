//! Simulator configuration: timing, vehicle limits, IDM, observation layout and caps, rewards.
//!
//! Owns: [`SimConfig`] and its parts, their defaults (the spec digest's numbers) and
//! [`SimConfig::validate`]. Must not: read files itself; callers deserialise a TOML table
//! into it (unknown fields are rejected) and then validate.

use serde::{Deserialize, Serialize};

use crate::idm::IdmParams;
use crate::vehicle::VehicleParams;

/// Which observation layout to build (see `obs`).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum Layout {
    /// The paper's: every map vector expressed in the observer's frame.
    EgoFrame,
    /// Map segments stored once per map in their own frames, referenced by index with their
    /// pose relative to the observer; agent histories in each agent's own frame.
    QueryCentric,
}

impl Layout {
    /// The name in configuration files (`ego-frame`, `query-centric`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::EgoFrame => "ego-frame",
            Self::QueryCentric => "query-centric",
        }
    }

    /// Parses [`Layout::as_str`]'s names; the error lists them.
    pub fn parse(s: &str) -> Result<Self, LayoutError> {
        match s {
            "ego-frame" => Ok(Self::EgoFrame),
            "query-centric" => Ok(Self::QueryCentric),
            other => Err(LayoutError::Unknown { name: other.to_string() }),
        }
    }
}

/// A layout name [`Layout::parse`] does not know.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LayoutError {
    #[error("unknown layout `{name}` (expected `ego-frame` or `query-centric`)")]
    Unknown { name: String },
}

/// Whose Social Value Orientation an observer sees.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum SvoVisibility {
    /// MACAD, and every ego policy.
    None,
    /// CoPO: the observer's own SVO only.
    Own,
    /// SocialComm: the observer's own and every neighbour's communicated SVO.
    All,
}

/// Observation caps and contents; fixed caps give every batch a static shape.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ObsConfig {
    pub layout: Layout,
    pub radius_m: f32,
    /// History frames per agent, at the decision rate (the last is the current frame).
    pub history: usize,
    /// Maximum number of other agents observed (nearest first).
    pub max_neighbours: usize,
    /// Route points ahead of the agent, every 2 m.
    pub route_points: usize,
    /// Ego-frame layout: maximum map polylines and points per polyline.
    pub max_polylines: usize,
    pub polyline_points: usize,
    /// Query-centric layout: maximum map segments and points per segment.
    pub max_segments: usize,
    pub segment_points: usize,
    pub svo: SvoVisibility,
    /// FailMaker: background agents can tell the ego apart.
    pub ego_flag: bool,
    /// Evaluation probes only: constants in place of the SVOs observers are told.
    #[serde(skip_serializing_if = "MessageProbe::is_off")]
    pub messages: MessageProbe,
}

/// An evaluation probe of what the SVO messages carry: constants in place of the SVOs that
/// observers are told (with [`SvoVisibility`] showing them). Off in training and by default.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct MessageProbe {
    /// Every other agent's SVO as any observer is told it, in degrees (each agent still knows its
    /// own): does a policy read its neighbours' messages?
    pub neighbours_deg: Option<f32>,
    /// The ego's (agent 0's) SVO as every other observer is told it, in degrees: a
    /// constant-message adversary.
    pub told_ego_deg: Option<f32>,
}

impl MessageProbe {
    pub fn is_off(&self) -> bool {
        *self == Self::default()
    }

    /// The first constant that is not an SVO in [-90, 90] degrees, as (field, value).
    pub fn out_of_range(&self) -> Option<(&'static str, f32)> {
        [("neighbours_deg", self.neighbours_deg), ("told_ego_deg", self.told_ego_deg)]
            .into_iter()
            .find_map(|(field, v)| {
                v.filter(|v| !(v.is_finite() && (-90.0..=90.0).contains(v))).map(|v| (field, v))
            })
    }
}

impl Default for ObsConfig {
    fn default() -> Self {
        Self {
            layout: Layout::QueryCentric,
            radius_m: 50.0,
            history: 10,
            max_neighbours: 20,
            route_points: 20,
            max_polylines: 40,
            polyline_points: 25,
            max_segments: 96,
            segment_points: 10,
            svo: SvoVisibility::None,
            ego_flag: false,
            messages: MessageProbe::default(),
        }
    }
}

/// Reward weights (digest: omega_1 = 0.07, omega_2 = 5).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct RewardConfig {
    pub speed_weight: f32,
    pub failure_penalty: f32,
    /// Neighbours whose rewards enter the SVO-composed reward: the learners within this
    /// distance.
    pub neighbour_radius_m: f32,
    /// Only the nearest this many live agents within `neighbour_radius_m` (any controller,
    /// ascending distance then index, as the observation picks its neighbours) are candidates;
    /// the learners among them enter the composed reward. `None`: every learner within the radius.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_neighbours: Option<usize>,
}

impl Default for RewardConfig {
    fn default() -> Self {
        Self {
            speed_weight: 0.07,
            failure_penalty: 5.0,
            neighbour_radius_m: 50.0,
            max_neighbours: None,
        }
    }
}

/// Everything the simulator needs besides the map.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    pub dt_s: f32,
    pub substeps: u32,
    pub horizon: u32,
    /// Lateral distance to the route beyond which an agent is off route.
    pub off_route_m: f32,
    /// The road-edge test uses the vehicle box scaled by this factor.
    pub off_road_box_scale: f32,
    /// Heading difference to the nearest lane beyond which an agent is in the wrong lane.
    pub wrong_lane_deg: f32,
    /// Distance before the route's end at which the destination counts as reached.
    pub destination_tolerance_m: f32,
    pub vehicle: VehicleParams,
    pub idm: IdmParams,
    pub obs: ObsConfig,
    pub reward: RewardConfig,
    /// The range a case's SVO (stored in [0, 90] deg) is mapped onto linearly at reset.
    /// FailMaker's background uses [-90, 90]: `c < 0` makes an agent want the ego to lose.
    pub svo_range_deg: [f32; 2],
    /// How far and how fast the `idm-residual-lateral` action moves a vehicle's path sideways.
    pub lateral: LateralConfig,
}

/// The lateral part of the `idm-residual-lateral` action (`Action::lateral`).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LateralConfig {
    /// The offset of a full lateral action (+-1) from the route, m: one lane by default.
    pub max_offset_m: f32,
    /// How fast the followed path's offset moves towards its target, m/s (a lane change of
    /// 3.5 m takes 2.3 s at the default).
    pub rate_mps: f32,
}

impl Default for LateralConfig {
    fn default() -> Self {
        Self { max_offset_m: 3.5, rate_mps: 1.5 }
    }
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            dt_s: 0.25,
            substeps: 10,
            horizon: 100,
            off_route_m: 6.0,
            off_road_box_scale: 0.6,
            wrong_lane_deg: 90.0,
            destination_tolerance_m: 2.0,
            vehicle: VehicleParams::default(),
            idm: IdmParams::default(),
            obs: ObsConfig::default(),
            reward: RewardConfig::default(),
            svo_range_deg: [0.0, 90.0],
            lateral: LateralConfig::default(),
        }
    }
}

/// A configuration value out of range; names the field.
#[derive(Debug, thiserror::Error)]
#[error("sim config field `{field}`: {reason}")]
pub struct ConfigError {
    pub field: &'static str,
    pub reason: String,
}

impl SimConfig {
    /// Checks ranges that would otherwise make the simulator misbehave.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let pos = |field: &'static str, v: f32| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(ConfigError { field, reason: format!("{v} must be a positive number") })
            }
        };
        let at_least = |field: &'static str, v: usize, min: usize| {
            if v >= min {
                Ok(())
            } else {
                Err(ConfigError { field, reason: format!("{v} must be at least {min}") })
            }
        };
        pos("dt_s", self.dt_s)?;
        pos("off_route_m", self.off_route_m)?;
        pos("off_road_box_scale", self.off_road_box_scale)?;
        pos("wrong_lane_deg", self.wrong_lane_deg)?;
        pos("destination_tolerance_m", self.destination_tolerance_m)?;
        pos("vehicle.length_m", self.vehicle.length_m)?;
        pos("vehicle.width_m", self.vehicle.width_m)?;
        pos("vehicle.wheelbase_m", self.vehicle.wheelbase_m)?;
        pos("vehicle.max_speed_mps", self.vehicle.max_speed_mps)?;
        pos("vehicle.max_accel_mps2", self.vehicle.max_accel_mps2)?;
        pos("vehicle.max_steer_deg", self.vehicle.max_steer_deg)?;
        pos("idm.desired_speed_mps", self.idm.desired_speed_mps)?;
        pos("idm.max_accel_mps2", self.idm.max_accel_mps2)?;
        pos("idm.comfort_decel_mps2", self.idm.comfort_decel_mps2)?;
        pos("obs.radius_m", self.obs.radius_m)?;
        pos("lateral.max_offset_m", self.lateral.max_offset_m)?;
        pos("lateral.rate_mps", self.lateral.rate_mps)?;
        at_least("substeps", self.substeps as usize, 1)?;
        let [lo, hi] = self.svo_range_deg;
        if !(lo.is_finite() && hi.is_finite() && -90.0 <= lo && lo <= hi && hi <= 90.0) {
            return Err(ConfigError {
                field: "svo_range_deg",
                reason: format!("[{lo}, {hi}] must lie in [-90, 90], low first"),
            });
        }
        at_least("horizon", self.horizon as usize, 1)?;
        at_least("obs.history", self.obs.history, 1)?;
        at_least("obs.route_points", self.obs.route_points, 1)?;
        at_least("obs.max_polylines", self.obs.max_polylines, 1)?;
        at_least("obs.polyline_points", self.obs.polyline_points, 2)?;
        at_least("obs.max_segments", self.obs.max_segments, 1)?;
        at_least("obs.segment_points", self.obs.segment_points, 2)?;
        if self.vehicle.max_steer_deg >= 90.0 {
            return Err(ConfigError {
                field: "vehicle.max_steer_deg",
                reason: "must be below 90".into(),
            });
        }
        if let Some((field, v)) = self.obs.messages.out_of_range() {
            let field = if field == "neighbours_deg" {
                "obs.messages.neighbours_deg"
            } else {
                "obs.messages.told_ego_deg"
            };
            return Err(ConfigError {
                field,
                reason: format!("{v} must be an SVO in [-90, 90] degrees"),
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toml_round_trip_and_unknown_fields_rejected() {
        let c = SimConfig::default();
        let text = toml::to_string(&c).expect("serialise");
        let back: SimConfig = toml::from_str(&text).expect("parse");
        assert_eq!(c, back);
        let err =
            toml::from_str::<SimConfig>("horizon = 10\nhorizn = 3\n").expect_err("unknown field");
        assert!(err.to_string().contains("horizn"), "{err}");
        let partial: SimConfig =
            toml::from_str("[obs]\nlayout = \"ego-frame\"\n").expect("partial");
        assert_eq!(partial.obs.layout, Layout::EgoFrame);
        assert_eq!(partial.horizon, 100);
    }

    #[test]
    fn validate_names_the_field() {
        let mut c = SimConfig::default();
        c.obs.history = 0;
        let e = c.validate().expect_err("invalid");
        assert_eq!(e.field, "obs.history");
        let c = SimConfig { dt_s: f32::NAN, ..SimConfig::default() };
        assert_eq!(c.validate().expect_err("nan").field, "dt_s");
    }
}
