//! The Intelligent Driver Model and the pure-pursuit path follower used by rule-based traffic.
//!
//! Owns: [`IdmParams`] (digest defaults) and the two control laws. Must not: search for
//! leaders or touch the map; the environment supplies gap and route geometry.

use serde::{Deserialize, Serialize};

/// IDM parameters (digest: desired speed above v_max so a free road means full speed).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct IdmParams {
    pub desired_speed_mps: f32,
    pub time_headway_s: f32,
    pub min_gap_m: f32,
    pub delta: f32,
    pub max_accel_mps2: f32,
    pub comfort_decel_mps2: f32,
    /// Leader search distance along the remaining route.
    pub look_ahead_m: f32,
    /// A vehicle is on the route when its centre is within this lateral distance of it.
    pub lateral_tolerance_m: f32,
}

impl Default for IdmParams {
    fn default() -> Self {
        Self {
            desired_speed_mps: 12.0,
            time_headway_s: 1.0,
            min_gap_m: 2.0,
            delta: 4.0,
            max_accel_mps2: 5.0,
            comfort_decel_mps2: 5.0,
            look_ahead_m: 50.0,
            lateral_tolerance_m: 2.5,
        }
    }
}

/// IDM acceleration for speed `v`, bumper-to-bumper `gap_m` and leader speed `v_lead`
/// (no leader: `gap_m = None`).
pub fn idm_accel(p: &IdmParams, v_mps: f32, leader: Option<(f32, f32)>) -> f32 {
    let free = 1.0 - (v_mps / p.desired_speed_mps).powf(p.delta);
    let interaction = match leader {
        None => 0.0,
        Some((gap_m, v_lead_mps)) => {
            let dv = v_mps - v_lead_mps;
            let s_star = p.min_gap_m
                + (v_mps * p.time_headway_s
                    + v_mps * dv / (2.0 * (p.max_accel_mps2 * p.comfort_decel_mps2).sqrt()))
                .max(0.0);
            let g = gap_m.max(0.01);
            (s_star / g).powi(2)
        }
    };
    p.max_accel_mps2 * (free - interaction)
}

/// Pure-pursuit steering angle (rad) towards `target` given in the vehicle's own frame.
pub fn pure_pursuit_steer(wheelbase_m: f32, target_local: [f32; 2]) -> f32 {
    let ld2 = (target_local[0] * target_local[0] + target_local[1] * target_local[1]).max(1e-6);
    (2.0 * wheelbase_m * target_local[1] / ld2).atan()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vehicle::{VehicleParams, VehicleState};

    #[test]
    fn free_road_accelerates_and_close_leader_brakes() {
        let p = IdmParams::default();
        assert!(idm_accel(&p, 0.0, None) > 4.9);
        assert!(idm_accel(&p, 6.0, Some((3.0, 0.0))) < -4.0);
    }

    /// A follower approaching a stopped leader stops no closer than the minimum gap.
    #[test]
    fn follower_stops_behind_stopped_leader() {
        let p = IdmParams::default();
        let vp = VehicleParams::default();
        let leader_rear_m = 60.0;
        let mut s =
            VehicleState { x_m: 0.0, y_m: 0.0, theta_rad: 0.0, speed_mps: vp.max_speed_mps };
        let dt = 0.025;
        let mut min_gap = f32::INFINITY;
        for _ in 0..(30.0 / dt) as usize {
            let gap = leader_rear_m - (s.x_m + vp.length_m / 2.0);
            min_gap = min_gap.min(gap);
            let a = idm_accel(&p, s.speed_mps, Some((gap, 0.0)));
            s.step(&vp, a, 0.0, dt);
        }
        assert!(s.speed_mps < 0.05, "still moving at {}", s.speed_mps);
        assert!(min_gap >= p.min_gap_m - 0.05, "closest gap {min_gap}");
        assert!(min_gap < p.min_gap_m + 1.5, "stopped too early at {min_gap}");
    }

    #[test]
    fn pure_pursuit_turns_towards_target() {
        assert!(pure_pursuit_steer(2.6, [5.0, 1.0]) > 0.0);
        assert!(pure_pursuit_steer(2.6, [5.0, -1.0]) < 0.0);
        assert_eq!(pure_pursuit_steer(2.6, [5.0, 0.0]), 0.0);
    }
}
