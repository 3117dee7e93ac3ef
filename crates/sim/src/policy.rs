//! Scripted policies that read observations: cheap stand-ins for learned policies.
//!
//! Owns: [`route_follower`], which steers towards the route a few metres ahead at a fixed
//! reference speed. Used by `bench sim` (a fixed, cheap policy for every agent) and by tests.
//! Must not: read simulator state; it sees only the observation, like a learned policy.

use crate::obs::{ObsSpec, POS_SCALE_M, ROUTE_FEATS};
use crate::vehicle::{Action, VehicleParams};

/// Pure pursuit on the observed route point `look` points ahead; `speed` in [-1, 1].
pub fn route_follower(
    spec: &ObsSpec,
    obs: &[f32],
    vp: &VehicleParams,
    look: usize,
    speed: f32,
) -> Action {
    let r = &obs[spec.route.clone()];
    let m = &obs[spec.route_mask.clone()];
    let mut k = look.min(spec.route_points - 1);
    while k > 0 && m[k] == 0.0 {
        k -= 1;
    }
    if m[k] == 0.0 {
        return Action { ref_speed: -1.0, steer: 0.0, ..Action::default() };
    }
    let (x, y) = (r[k * ROUTE_FEATS] * POS_SCALE_M, r[k * ROUTE_FEATS + 1] * POS_SCALE_M);
    let ld2 = (x * x + y * y).max(1e-6);
    let steer_rad = (2.0 * vp.wheelbase_m * y / ld2).atan();
    Action {
        ref_speed: speed,
        steer: steer_rad / vp.max_steer_deg.to_radians(),
        ..Action::default()
    }
}
