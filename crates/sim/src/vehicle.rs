//! Vehicle dynamics: the kinematic bicycle model, the PID speed loop and the action mapping.
//!
//! Owns: [`VehicleParams`] (digest limits), [`VehicleState`], [`Pid`], [`Action`] decoding.
//! Must not: know about maps, other vehicles or rules. Explicit Euler, as the released code.

use serde::{Deserialize, Serialize};

use crate::geom::wrap_angle;

/// Physical limits of every vehicle (digest defaults).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct VehicleParams {
    pub length_m: f32,
    pub width_m: f32,
    pub wheelbase_m: f32,
    pub max_speed_mps: f32,
    pub max_accel_mps2: f32,
    pub max_steer_deg: f32,
    pub pid_kp: f32,
    pub pid_ki: f32,
    pub pid_kd: f32,
    /// The integral term is reset when |sum of errors| exceeds this.
    pub pid_integral_reset: f32,
}

impl Default for VehicleParams {
    fn default() -> Self {
        Self {
            length_m: 4.2,
            width_m: 2.0,
            wheelbase_m: 2.6,
            max_speed_mps: 6.0,
            max_accel_mps2: 5.0,
            max_steer_deg: 45.0,
            pid_kp: 1.0,
            pid_ki: 0.01,
            pid_kd: 0.05,
            pid_integral_reset: 10.0,
        }
    }
}

/// Pose and speed of a vehicle; `x_m, y_m` is the box centre (and the bicycle reference point).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VehicleState {
    pub x_m: f32,
    pub y_m: f32,
    pub theta_rad: f32,
    pub speed_mps: f32,
}

impl VehicleState {
    /// One explicit-Euler bicycle step with acceleration and steer held for `dt_s`.
    #[inline]
    pub fn step(&mut self, p: &VehicleParams, accel_mps2: f32, steer_rad: f32, dt_s: f32) {
        let a = accel_mps2.clamp(-p.max_accel_mps2, p.max_accel_mps2);
        let max_steer = p.max_steer_deg.to_radians();
        let d = steer_rad.clamp(-max_steer, max_steer);
        let (s, c) = self.theta_rad.sin_cos();
        self.x_m += dt_s * self.speed_mps * c;
        self.y_m += dt_s * self.speed_mps * s;
        self.theta_rad =
            wrap_angle(self.theta_rad + dt_s * self.speed_mps * d.tan() / p.wheelbase_m);
        self.speed_mps = (self.speed_mps + dt_s * a).clamp(0.0, p.max_speed_mps);
    }

    pub fn pos(&self) -> [f32; 2] {
        [self.x_m, self.y_m]
    }
}

/// PID speed controller turning a reference speed into an acceleration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pid {
    integral: f32,
    prev_error: Option<f32>,
}

impl Pid {
    /// Acceleration command (m/s^2, clipped to the vehicle's limit) for one sub-step.
    #[inline]
    pub fn command(
        &mut self,
        p: &VehicleParams,
        ref_speed_mps: f32,
        speed_mps: f32,
        dt_s: f32,
    ) -> f32 {
        let e = ref_speed_mps - speed_mps;
        self.integral += e;
        if self.integral.abs() > p.pid_integral_reset {
            self.integral = 0.0;
        }
        let de = self.prev_error.map_or(0.0, |pe| (e - pe) / dt_s);
        self.prev_error = Some(e);
        (p.pid_kp * e + p.pid_ki * self.integral + p.pid_kd * de)
            .clamp(-p.max_accel_mps2, p.max_accel_mps2)
    }
}

/// The paper's action, normalised: `[ref_speed, steer]`, each in [-1, 1].
///
/// `idm_accel`, when set, replaces both with a residual on the IDM driver: the vehicle is
/// driven exactly as an IDM car (pure-pursuit steer and IDM acceleration, both recomputed every
/// sub-step) with its acceleration moved linearly towards full braking (-1) or full
/// acceleration (+1) (`env::residual_accel`; clipped to [-1, 1], non-finite counts as 0).
/// `Some(0.0)` is the IDM driver, bit for bit.
///
/// `lateral`, with `idm_accel` set, moves the point IDM's pure pursuit steers towards sideways
/// off the route: the target offset in [-1, 1] of `lateral.max_offset_m` (positive to the left
/// of travel), approached at `lateral.rate_mps` (`SimConfig::lateral`); IDM's leader is then
/// searched along the offset path. `None` or `Some(0.0)` from the start keeps the route: the
/// IDM driver, bit for bit. Without `idm_accel` it is ignored.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Action {
    pub ref_speed: f32,
    pub steer: f32,
    pub idm_accel: Option<f32>,
    pub lateral: Option<f32>,
}

/// How a driving policy's action vector moves its vehicle (`env.action` of a job).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DriveAction {
    /// The paper's `[reference speed, steer]`, normalised.
    #[default]
    Direct,
    /// `[reference speed, steer]` added to the IDM driver's normalised action and clipped
    /// (tried 2026-11-22: it cannot stop when IDM sees no leader).
    IdmResidual,
    /// One number: a residual on the IDM driver's acceleration, moving it linearly to full
    /// braking at -1 and full acceleration at +1, with IDM's pure-pursuit steering. Zero is IDM
    /// exactly; -1 brakes at full force from any IDM command.
    IdmAccelResidual,
    /// Two numbers: the acceleration residual of `IdmAccelResidual` and a lateral target in
    /// [-1, 1] that moves the path IDM's pure pursuit follows sideways by up to one lane
    /// (`SimConfig::lateral`, rate-limited), so a policy can change lanes, cut in, block a lane
    /// or cross into the opposite one (judged by the usual rules). Zeros are IDM exactly.
    IdmResidualLateral,
}

/// An action name [`DriveAction::parse`] does not know.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum DriveActionError {
    #[error("unknown action `{name}` (expected one of {})", DriveAction::NAMES.join(", "))]
    Unknown { name: String },
}

impl DriveAction {
    pub const ALL: [Self; 4] =
        [Self::Direct, Self::IdmResidual, Self::IdmAccelResidual, Self::IdmResidualLateral];
    pub const NAMES: [&'static str; 4] =
        ["direct", "idm-residual", "idm-accel-residual", "idm-residual-lateral"];

    /// The name in configuration files (`env.action`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Direct => Self::NAMES[0],
            Self::IdmResidual => Self::NAMES[1],
            Self::IdmAccelResidual => Self::NAMES[2],
            Self::IdmResidualLateral => Self::NAMES[3],
        }
    }

    /// Parses [`DriveAction::as_str`]'s names; the error lists them.
    pub fn parse(s: &str) -> Result<Self, DriveActionError> {
        Self::ALL
            .into_iter()
            .find(|a| a.as_str() == s)
            .ok_or_else(|| DriveActionError::Unknown { name: s.to_string() })
    }

    /// Floats per action.
    pub fn dim(self) -> usize {
        match self {
            Self::Direct | Self::IdmResidual | Self::IdmResidualLateral => 2,
            Self::IdmAccelResidual => 1,
        }
    }

    /// The vehicle command of one policy action `a` (`dim()` floats). `demo` is the IDM
    /// driver's normalised action, needed only by `IdmResidual` (see `needs_demo`).
    pub fn command(self, a: &[f32], demo: Option<Action>) -> Action {
        match self {
            Self::Direct => Action { ref_speed: a[0], steer: a[1], ..Action::default() },
            Self::IdmResidual => {
                let d = demo.unwrap_or_default();
                Action {
                    ref_speed: (d.ref_speed + a[0]).clamp(-1.0, 1.0),
                    steer: (d.steer + a[1]).clamp(-1.0, 1.0),
                    ..Action::default()
                }
            }
            Self::IdmAccelResidual => Action { idm_accel: Some(a[0]), ..Action::default() },
            Self::IdmResidualLateral => {
                Action { idm_accel: Some(a[0]), lateral: Some(a[1]), ..Action::default() }
            }
        }
    }

    /// Whether [`DriveAction::command`] needs the IDM driver's normalised action.
    pub fn needs_demo(self) -> bool {
        self == Self::IdmResidual
    }

    /// The action of this kind that drives like the IDM driver (given its normalised action):
    /// the demonstrator of an IDM warm-up. Residual kinds: all zeros.
    pub fn demonstrator(self, demo: Action) -> Vec<f32> {
        match self {
            Self::Direct => vec![demo.ref_speed, demo.steer],
            Self::IdmResidual | Self::IdmAccelResidual | Self::IdmResidualLateral => {
                vec![0.0; self.dim()]
            }
        }
    }
}

impl Action {
    /// Decodes to (reference speed in [0, v_max] m/s, steer in [-max, max] rad); non-finite
    /// components count as 0 and out-of-range ones are clipped.
    #[inline]
    pub fn decode(&self, p: &VehicleParams) -> (f32, f32) {
        let clean = |v: f32| if v.is_finite() { v.clamp(-1.0, 1.0) } else { 0.0 };
        let v = (clean(self.ref_speed) + 1.0) * 0.5 * p.max_speed_mps;
        (v, clean(self.steer) * p.max_steer_deg.to_radians())
    }

    /// Encodes physical values into a normalised action (inverse of [`Action::decode`]).
    pub fn encode(p: &VehicleParams, ref_speed_mps: f32, steer_rad: f32) -> Self {
        Self {
            ref_speed: (2.0 * ref_speed_mps / p.max_speed_mps - 1.0).clamp(-1.0, 1.0),
            steer: (steer_rad / p.max_steer_deg.to_radians()).clamp(-1.0, 1.0),
            ..Self::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Constant speed and steer: the bicycle traces a circle of radius L / tan(delta).
    #[test]
    fn bicycle_follows_closed_form_arc() {
        let p = VehicleParams::default();
        let delta = 0.3f32;
        let v = 5.0;
        let mut s = VehicleState { x_m: 0.0, y_m: 0.0, theta_rad: 0.0, speed_mps: v };
        let dt = 0.001;
        let t_end = 3.0;
        for _ in 0..(t_end / dt) as usize {
            s.step(&p, 0.0, delta, dt);
        }
        let r = p.wheelbase_m / delta.tan();
        let omega = v / r;
        let th = omega * t_end;
        let (x, y) = (r * th.sin(), r * (1.0 - th.cos()));
        assert!(
            (s.x_m - x).abs() < 0.05 && (s.y_m - y).abs() < 0.05,
            "got ({}, {}), want ({x}, {y})",
            s.x_m,
            s.y_m
        );
        assert!((wrap_angle(s.theta_rad - th)).abs() < 1e-2);
        // Distance from the circle's centre stays r.
        let rr = (s.x_m.powi(2) + (s.y_m - r).powi(2)).sqrt();
        assert!((rr - r).abs() < 0.05);
    }

    #[test]
    fn speed_and_steer_are_clipped() {
        let p = VehicleParams::default();
        let mut s = VehicleState { x_m: 0.0, y_m: 0.0, theta_rad: 0.0, speed_mps: 5.9 };
        s.step(&p, 100.0, 0.0, 0.1);
        assert_eq!(s.speed_mps, p.max_speed_mps);
        s.step(&p, -100.0, 0.0, 10.0);
        assert_eq!(s.speed_mps, 0.0);
        let (v, d) = Action { ref_speed: 7.0, steer: f32::NAN, ..Action::default() }.decode(&p);
        assert_eq!((v, d), (p.max_speed_mps, 0.0));
    }

    #[test]
    fn pid_reaches_reference_speed() {
        let p = VehicleParams::default();
        let mut s = VehicleState { x_m: 0.0, y_m: 0.0, theta_rad: 0.0, speed_mps: 0.0 };
        let mut pid = Pid::default();
        let dt = 0.025;
        for _ in 0..(8.0 / dt) as usize {
            let a = pid.command(&p, 4.0, s.speed_mps, dt);
            s.step(&p, a, 0.0, dt);
        }
        assert!((s.speed_mps - 4.0).abs() < 0.1, "speed {}", s.speed_mps);
        // And slows down to a lower reference.
        for _ in 0..(8.0 / dt) as usize {
            let a = pid.command(&p, 1.0, s.speed_mps, dt);
            s.step(&p, a, 0.0, dt);
        }
        assert!((s.speed_mps - 1.0).abs() < 0.1, "speed {}", s.speed_mps);
    }

    #[test]
    fn action_round_trip() {
        let p = VehicleParams::default();
        let a = Action::encode(&p, 3.0, 0.2);
        let (v, d) = a.decode(&p);
        assert!((v - 3.0).abs() < 1e-5 && (d - 0.2).abs() < 1e-5);
    }
}
