//! IDM with MOBIL's lane changes: a reference driver that steers, for the ego's seat and as a
//! lateral demonstrator.
//!
//! Owns: [`MobilParams`], [`lateral_target`] (the lane a car driven by IDM wants to be in, as
//! the lateral component of the `idm-residual-lateral` action) and [`action`] (that action
//! whole; a car that never changes lanes is the IDM driver bit for bit). MOBIL (Kesting,
//! Treiber and Helbing, "General lane-changing model MOBIL for car-following models", 2007): a
//! change to a neighbouring lane is *safe* if the car that would follow there brakes no harder
//! than `max_imposed_braking_mps2`, and *worth it* if the driver's own IDM acceleration gains
//! more than `gain_threshold_mps2`, counting the two followers' changes times `politeness` and
//! a small bias back towards the route's own lane. Must not: step the episode or read anything
//! a driver could not see; it reads the episode through [`Env`]'s public state.
//!
//! Lanes are the route's lane and the paths one lane width to either side of it (the lateral
//! action's range, `SimConfig::lateral.max_offset_m`). A neighbour is taken only where it runs
//! the route's way for `enter_ahead_m` ahead ([`Map::lane_runs_along`]: never the opposite
//! carriageway or the verge); a car on a neighbour that stops running on within `stay_ahead_m`
//! returns to its route's lane (a mandatory change: no incentive, no safety test, as a driver
//! whose lane ends must merge). Decisions are taken every `decision_every_steps` decision steps
//! and only once the path has reached its last target, so a change is never reversed halfway.
//! Every other car is judged by the same IDM (MOBIL's assumption), whoever drives it.
//!
//! While it changes lanes the car brakes for the nearer of the leaders where its body is and in
//! the lane it moves to (highway-env's IDM does the same), through the action's acceleration
//! residual: the simulator's IDM looks along the moved path only, which runs ahead of the car's
//! body (the path's offset moves at a fixed rate, the body as fast as the car can steer), so
//! alone it would stop braking for a car the body has not yet cleared. Settled in a lane, the
//! residual is exactly 0.
//!
//! [`Map::lane_runs_along`]: crate::map::Map::lane_runs_along

use crate::env::Env;
use crate::geom;
use crate::idm::idm_accel;

/// MOBIL's constants (defaults: highway-env's MOBIL vehicles, with a route bias added).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MobilParams {
    /// Weight of the followers' acceleration changes (0: selfish, highway-env's default).
    pub politeness: f32,
    /// The least acceleration gain, m/s^2, that makes a change worth it.
    pub gain_threshold_mps2: f32,
    /// The hardest braking a change may impose on the car that would follow, m/s^2.
    pub max_imposed_braking_mps2: f32,
    /// Added to the gain of a change back towards the route's lane (taken from one away), m/s^2.
    pub route_bias_mps2: f32,
    /// A neighbour lane is entered only if it runs the route's way this far ahead.
    pub enter_ahead_m: f32,
    /// A car off its route's lane returns once its lane stops running on within this distance.
    pub stay_ahead_m: f32,
    /// Lane decisions every this many decision steps (every step by default: a change is never
    /// reconsidered before the path has reached it, 2.3 s for a lane at the default rate).
    pub decision_every_steps: u32,
}

impl Default for MobilParams {
    fn default() -> Self {
        Self {
            politeness: 0.0,
            gain_threshold_mps2: 0.2,
            max_imposed_braking_mps2: 2.0,
            route_bias_mps2: 0.1,
            enter_ahead_m: 40.0,
            stay_ahead_m: 25.0,
            decision_every_steps: 1,
        }
    }
}

/// Where a path's offset counts as arrived at its target, m.
const SETTLED_M: f32 = 0.05;
/// Where the car's body counts as arrived in its target lane (no more braking for the lane it
/// left), m.
const BODY_SETTLED_M: f32 = 0.5;
/// Sections checked along a lane, m apart.
const LANE_CHECK_STEP_M: f32 = 5.0;
/// How far behind the car its followers are searched for, m.
const LOOK_BACK_M: f32 = 50.0;

/// A car on one of the lanes, relative to agent `i`: its arc length along `i`'s route minus
/// `i`'s, and its speed along the route.
#[derive(Clone, Copy, Debug)]
struct Near {
    ds_m: f32,
    speed_mps: f32,
}

/// The nearest car ahead and behind on the path `offset_m` to the left of agent `i`'s route.
fn neighbours(env: &Env, i: usize, offset_m: f32) -> (Option<Near>, Option<Near>) {
    let cfg = &env.cfg;
    let (look, tol, len) =
        (cfg.idm.look_ahead_m, cfg.idm.lateral_tolerance_m, cfg.vehicle.length_m);
    let a = &env.agents()[i];
    let route = &env.map.routes[a.route as usize];
    let lo = route.cum_m.partition_point(|&c| c <= a.s_m - LOOK_BACK_M).saturating_sub(1);
    let hi = route.cum_m.partition_point(|&c| c <= a.s_m + look) + 1;
    let reach2 = (look.max(LOOK_BACK_M) + len).powi(2);
    let (mut ahead, mut behind): (Option<Near>, Option<Near>) = (None, None);
    for (j, b) in env.agents().iter().enumerate() {
        if j == i || !b.alive || geom::dist2(a.state.pos(), b.state.pos()) > reach2 {
            continue;
        }
        let pr = geom::project_range(&route.points, &route.cum_m, b.state.pos(), lo, hi);
        let ds_m = pr.s_m - a.s_m;
        if (pr.lateral_m - offset_m).abs() > tol || ds_m >= look || ds_m <= -LOOK_BACK_M {
            continue;
        }
        let along = route.headings[pr.seg];
        let near = Near {
            ds_m,
            speed_mps: b.state.speed_mps * (b.state.theta_rad - along).cos().max(0.0),
        };
        if ds_m > 0.0 {
            if ahead.is_none_or(|n| ds_m < n.ds_m) {
                ahead = Some(near);
            }
        } else if behind.is_none_or(|n| ds_m > n.ds_m) {
            behind = Some(near);
        }
    }
    (ahead, behind)
}

/// Whether the path `offset_m` left of agent `i`'s route lies on a lane running the route's way
/// from the car to `ahead_m` ahead (or the route's end).
fn lane_runs_on(env: &Env, i: usize, offset_m: f32, ahead_m: f32) -> bool {
    let cfg = &env.cfg;
    let a = &env.agents()[i];
    let route = &env.map.routes[a.route as usize];
    let reach_m = 0.5 * route.width_m + 0.05;
    let max_heading = cfg.wrong_lane_deg.to_radians();
    let end = (a.s_m + ahead_m).min(route.length_m);
    let mut s = a.s_m;
    loop {
        let (centre, heading) = geom::point_at(&route.points, &route.cum_m, s);
        let q = geom::add(centre, geom::scale([-heading.sin(), heading.cos()], offset_m));
        if !env.map.lane_runs_along(q, heading, max_heading, reach_m) {
            return false;
        }
        if s >= end {
            return true;
        }
        s = (s + LANE_CHECK_STEP_M).min(end);
    }
}

/// The IDM acceleration of a car at `speed_mps` behind `leader` (`ds_m` further along than it),
/// or on a free road.
fn accel(env: &Env, speed_mps: f32, ds_m: f32, leader: Option<Near>) -> f32 {
    let gap = leader.map(|l| (l.ds_m - ds_m - env.cfg.vehicle.length_m, l.speed_mps));
    idm_accel(&env.cfg.idm, speed_mps, gap)
}

/// Agent `i`'s `idm-residual-lateral` action under MOBIL: `[acceleration residual, lateral
/// target]`, the target its lane's offset as a share of `lateral.max_offset_m`, the residual 0
/// but while it changes lanes (see the module header). Agents that have ended get zeros.
pub fn action(env: &Env, i: usize, p: &MobilParams) -> [f32; 2] {
    let Some(a) = env.agents().get(i).filter(|a| a.alive) else { return [0.0, 0.0] };
    let lateral = lateral_target(env, i, p);
    let to_m = lateral * env.cfg.lateral.max_offset_m;
    let path_m = a.lateral_offset_m();
    if (path_m - to_m).abs() <= SETTLED_M && (a.lateral_m - to_m).abs() <= BODY_SETTLED_M {
        return [0.0, lateral];
    }
    let v = a.state.speed_mps;
    let idm = accel(env, v, 0.0, neighbours(env, i, path_m).0);
    let want = [a.lateral_m, to_m]
        .into_iter()
        .map(|o| accel(env, v, 0.0, neighbours(env, i, o).0))
        .fold(idm, f32::min);
    let max = env.cfg.vehicle.max_accel_mps2;
    // `env::residual_accel` moves IDM's acceleration linearly towards -max for r < 0.
    let r =
        if want < idm && idm + max > 0.0 { ((want - idm) / (idm + max)).max(-1.0) } else { 0.0 };
    [r, lateral]
}

/// The lateral component of agent `i`'s `idm-residual-lateral` action under MOBIL: its lane's
/// offset as a share of `lateral.max_offset_m`, in [-1, 1]. Agents that have ended keep 0.
pub fn lateral_target(env: &Env, i: usize, p: &MobilParams) -> f32 {
    let Some(a) = env.agents().get(i).filter(|a| a.alive) else { return 0.0 };
    let max_m = env.cfg.lateral.max_offset_m;
    let lane_m = env.map.routes[a.route as usize].width_m.min(max_m);
    let now_m = a.lateral_target_m();
    let norm = |o: f32| (o / max_m).clamp(-1.0, 1.0);
    // A neighbour that ends ahead: back to the route's lane.
    if now_m.abs() > SETTLED_M && !lane_runs_on(env, i, now_m, p.stay_ahead_m) {
        return 0.0;
    }
    let settled = (a.lateral_offset_m() - now_m).abs() <= SETTLED_M;
    if !settled || !env.step_index().is_multiple_of(p.decision_every_steps.max(1)) {
        return norm(now_m);
    }
    let v = a.state.speed_mps;
    let me = Some(Near { ds_m: 0.0, speed_mps: v });
    let (lead, follow) = neighbours(env, i, now_m);
    let own_now = accel(env, v, 0.0, lead);
    // The car behind now: it would follow our leader once we leave.
    let old_follower_change = follow.map_or(0.0, |f| {
        accel(env, f.speed_mps, f.ds_m, lead) - accel(env, f.speed_mps, f.ds_m, me)
    });
    let mut best = (now_m, p.gain_threshold_mps2);
    for to_m in [now_m - lane_m, now_m + lane_m] {
        if to_m.abs() > max_m + SETTLED_M || !lane_runs_on(env, i, to_m, p.enter_ahead_m) {
            continue;
        }
        let (new_lead, new_follow) = neighbours(env, i, to_m);
        // Safety: the new follower brakes no harder than allowed behind us.
        let new_follower_change = match new_follow {
            Some(f) => {
                let behind_me = accel(env, f.speed_mps, f.ds_m, me);
                if behind_me < -p.max_imposed_braking_mps2 || f.ds_m > -env.cfg.vehicle.length_m {
                    continue;
                }
                behind_me - accel(env, f.speed_mps, f.ds_m, new_lead)
            }
            None => 0.0,
        };
        let own = accel(env, v, 0.0, new_lead) - own_now;
        let bias = if to_m.abs() < now_m.abs() { p.route_bias_mps2 } else { -p.route_bias_mps2 };
        let gain = own + p.politeness * (new_follower_change + old_follower_change) + bias;
        if gain > best.1 {
            best = (to_m, gain);
        }
    }
    norm(best.0)
}
