//! Whether standing vehicles close the road ahead of an agent: [`closed_ahead`], and
//! [`crate::Env::road_closed_ahead`] for an agent of a running episode.
//!
//! Owns: the corridor test. The road ahead of the agent, up to `ahead_m` along its route, is
//! laid out as a grid: a section across the route every `section_step_m`, sampled every
//! `lateral_step_m` out to the off-route limit (`SimConfig::off_route_m`, beyond which the
//! agent's episode ends). A sample is *drivable* if it lies on a lane (within half the route's
//! lane width of a lane's centre line) that runs the route's way there (within
//! `SimConfig::wrong_lane_deg`; any lane inside a junction), so the opposite carriageway, where
//! the wrong-lane rule ends an episode, does not count; it is *free* if drivable and no standing
//! vehicle's footprint covers it. A cell has room for a car if every sample within half a car's
//! width plus `clearance_m` of it is free, in every section within half a car's length. The road
//! is closed when no path of such cells (each step one section on or back, or one sample aside)
//! leads from the agent to the last section. Must not: change an episode or score it (the
//! metrics record its answer for agents that time out).
//!
//! It is a geometric bound at one moment, not a planner: a corridor it finds may still be hard
//! to steer through, vehicles slower than `stopped_mps` count as standing and faster ones as
//! gone, and the car is a box that does not turn.

use std::collections::VecDeque;

use crate::config::SimConfig;
use crate::geom::{self, P2};
use crate::map::Map;

/// The test's constants.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PassageRule {
    /// How far ahead along the route the corridor must reach.
    pub ahead_m: f32,
    pub section_step_m: f32,
    pub lateral_step_m: f32,
    /// Free width a vehicle needs beyond its own on each side.
    pub clearance_m: f32,
    /// Vehicles slower than this count as standing.
    pub stopped_mps: f32,
}

impl Default for PassageRule {
    fn default() -> Self {
        Self {
            ahead_m: 30.0,
            section_step_m: 1.0,
            lateral_step_m: 0.1,
            clearance_m: 0.3,
            stopped_mps: 0.5,
        }
    }
}

/// A standing vehicle's pose (its footprint is `SimConfig::vehicle`'s box).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Obstacle {
    pub pos: P2,
    pub theta_rad: f32,
}

/// With the agent at arc length `s_m` on `route`, `lateral_m` to the left of it: the distance
/// ahead at which `obstacles` close every corridor a car fits through, or `None` if one reaches
/// `rule.ahead_m` ahead (or the route's end).
pub fn closed_ahead(
    map: &Map,
    cfg: &SimConfig,
    route: u32,
    s_m: f32,
    lateral_m: f32,
    obstacles: &[Obstacle],
    rule: &PassageRule,
) -> Option<f32> {
    let r = map.routes.get(route as usize)?;
    if obstacles.is_empty() || rule.section_step_m <= 0.0 || rule.lateral_step_m <= 0.0 {
        return None;
    }
    let vp = &cfg.vehicle;
    let (half_l, half_w) = (0.5 * vp.length_m, 0.5 * vp.width_m);
    let lane_reach_m = 0.5 * r.width_m + 0.05;
    let max_heading = cfg.wrong_lane_deg.to_radians();
    let near_m = cfg.off_route_m + half_l.hypot(half_w);
    let side = (cfg.off_route_m / rule.lateral_step_m).floor() as i32;
    let width = (2 * side + 1) as usize;
    let reach_m = (rule.ahead_m).min(r.length_m - s_m);
    if reach_m <= 0.0 {
        return None;
    }
    let last = (reach_m / rule.section_step_m).floor() as usize;
    if last == 0 {
        return None;
    }
    // Free samples, section by section (index 0 is the agent's own section).
    let mut free = vec![false; (last + 1) * width];
    let mut near: Vec<&Obstacle> = Vec::with_capacity(obstacles.len());
    for k in 0..=last {
        let (centre, heading) =
            geom::point_at(&r.points, &r.cum_m, s_m + k as f32 * rule.section_step_m);
        near.clear();
        near.extend(obstacles.iter().filter(|o| geom::dist(o.pos, centre) <= near_m));
        let normal = [-heading.sin(), heading.cos()];
        let junction = map.in_junction(centre);
        for i in -side..=side {
            let q = geom::add(centre, geom::scale(normal, i as f32 * rule.lateral_step_m));
            let drivable = if junction {
                map.nearest_lane_heading(q, lane_reach_m).is_some()
            } else {
                map.lane_runs_along(q, heading, max_heading, lane_reach_m)
            };
            let covered = near.iter().any(|o| {
                let f = geom::Frame::new(o.pos, o.theta_rad).to_local(q);
                f[0].abs() <= half_l && f[1].abs() <= half_w
            });
            free[k * width + (i + side) as usize] = drivable && !covered;
        }
    }
    // Cells with room for a car: free samples across its width and clearance (`fit`), in every
    // section along its length (`room`); window counts over prefix sums of the blocked cells.
    let across = ((half_w + rule.clearance_m) / rule.lateral_step_m).ceil() as usize;
    let along = (half_l / rule.section_step_m).ceil() as usize;
    let mut fit = vec![false; (last + 1) * width];
    let mut pre = vec![0u32; width.max(last + 1) + 1];
    for k in 0..=last {
        let row = &free[k * width..(k + 1) * width];
        for (j, f) in row.iter().enumerate() {
            pre[j + 1] = pre[j] + u32::from(!f);
        }
        for j in across..width.saturating_sub(across) {
            fit[k * width + j] = pre[j + across + 1] == pre[j - across];
        }
    }
    let mut room = vec![false; (last + 1) * width];
    for j in 0..width {
        for k in 0..=last {
            pre[k + 1] = pre[k] + u32::from(!fit[k * width + j]);
        }
        for k in 0..=last {
            let (lo, hi) = (k.saturating_sub(along), (k + along).min(last));
            room[k * width + j] = pre[hi + 1] == pre[lo];
        }
    }
    let room = |k: usize, i: i32| room[k * width + (i + side) as usize];
    let across = across as i32;
    // From the agent's own section, at its lateral place (or a sample beside it with room).
    let at = (lateral_m / rule.lateral_step_m).round() as i32;
    let mut seen = vec![false; (last + 1) * width];
    let mut queue = VecDeque::new();
    for i in (at - across).max(-side)..=(at + across).min(side) {
        if room(0, i) {
            seen[(i + side) as usize] = true;
            queue.push_back((0usize, i));
        }
    }
    let mut farthest = 0;
    while let Some((k, i)) = queue.pop_front() {
        if k == last {
            return None;
        }
        farthest = farthest.max(k);
        let steps = [(k + 1, i), (k, i - 1), (k, i + 1), (k.wrapping_sub(1), i)];
        for (kk, ii) in steps {
            if kk > last || ii < -side || ii > side {
                continue;
            }
            let c = kk * width + (ii + side) as usize;
            if !seen[c] && room(kk, ii) {
                seen[c] = true;
                queue.push_back((kk, ii));
            }
        }
    }
    Some((farthest + 1) as f32 * rule.section_step_m)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenarios;

    fn bottleneck() -> Map {
        Map::from_file(&scenarios::bottleneck(), "bottleneck").expect("builds")
    }

    /// The route running east from `y` (its first and last points there), and the arc length
    /// of its point nearest `x`.
    fn eastbound(map: &Map, y: f32) -> (u32, impl Fn(f32) -> f32 + '_) {
        let id = map
            .routes
            .iter()
            .position(|r| {
                let (a, b) = (r.points[0], r.points[r.points.len() - 1]);
                a[0] < b[0] && (a[1] - y).abs() < 0.1 && (b[1] - y).abs() < 0.1
            })
            .expect("an eastbound route");
        let r = &map.routes[id];
        let s_at =
            move |x: f32| geom::project_range(&r.points, &r.cum_m, [x, y], 0, r.points.len()).s_m;
        (id as u32, s_at)
    }

    /// `closed_ahead` with the default rule, the agent on its route's centre line.
    fn closed(map: &Map, route: u32, s_m: f32, obstacles: &[Obstacle]) -> Option<f32> {
        closed_ahead(
            map,
            &SimConfig::default(),
            route,
            s_m,
            0.0,
            obstacles,
            &PassageRule::default(),
        )
    }

    fn stopped(x: f32, y: f32, theta_rad: f32) -> Obstacle {
        Obstacle { pos: [x, y], theta_rad }
    }

    // The bottleneck: two lanes each way (eastbound at y = -1.75 and -5.25), one each way in the
    // narrow (|x| < 12 m); the eastbound inner route runs at y = -1.75 throughout.
    #[test]
    fn one_standing_car_closes_the_one_lane_narrow_but_not_the_two_lane_approach() {
        let map = bottleneck();
        let (route, s_at) = eastbound(&map, -1.75);
        // In the narrow, its tail 17.9 m ahead of the ego at x = -20: no way past but the
        // opposite lane. The ego's centre gets to within half a car's length of it.
        let d = closed(&map, route, s_at(-20.0), &[stopped(0.0, -1.75, 0.0)]).expect("closed");
        assert!((14.0..=17.0).contains(&d), "closed {d} m ahead");
        // On the approach (two lanes each way) the outer lane stays open...
        assert_eq!(closed(&map, route, s_at(-90.0), &[stopped(-70.0, -1.75, 0.0)]), None);
        // ... until a second car stands beside the first.
        let two = [stopped(-70.0, -1.75, 0.0), stopped(-70.0, -5.25, 0.0)];
        assert!(closed(&map, route, s_at(-90.0), &two).is_some());
    }

    #[test]
    fn cars_behind_beyond_reach_or_on_the_opposite_carriageway_do_not_close_it() {
        let map = bottleneck();
        let (route, s_at) = eastbound(&map, -1.75);
        let s = s_at(-20.0);
        let behind = [stopped(-30.0, -1.75, 0.0), stopped(-30.0, -5.25, 0.0)];
        assert_eq!(closed(&map, route, s, &behind), None);
        assert_eq!(closed(&map, route, s, &[stopped(25.0, -1.75, 0.0)]), None, "45 m ahead");
        let opposite = [stopped(0.0, 1.75, std::f32::consts::PI)];
        assert_eq!(closed(&map, route, s, &opposite), None);
        assert_eq!(closed(&map, route, s, &[]), None);
    }

    #[test]
    fn a_car_across_the_lane_edge_leaves_no_gap_where_one_on_its_lane_does() {
        let map = bottleneck();
        let (route, s_at) = eastbound(&map, -1.75);
        let s = s_at(-90.0);
        // Standing on the line between the two eastbound lanes (y = -3.5): 2.5 m free on
        // either side, less than a car and its clearance (2.0 + 2 x 0.3 m by default).
        assert!(closed(&map, route, s, &[stopped(-70.0, -3.5, 0.0)]).is_some());
        // Turned across the road, one car covers 4.2 m of the 7 m carriageway.
        let across = [stopped(-70.0, -3.5, std::f32::consts::FRAC_PI_2)];
        assert!(closed(&map, route, s, &across).is_some());
        assert_eq!(closed(&map, route, s, &[stopped(-70.0, -1.2, 0.0)]), None, "4.8 m free");
    }

    /// Merge's main road has three lanes (y = 3.5, 0, -3.5). A free lane the ego cannot reach
    /// does not open the road: on the bottom lane behind a standing car, a column of standing
    /// cars on the middle lane (0.8 m apart, less than a car) walls it off from the free top
    /// lane, until the column has a hole a car fits through; on the top lane the same cars leave
    /// it free. (The route is the middle lane's: the ego may move 6 m either side of it.)
    #[test]
    fn a_free_lane_behind_a_wall_of_cars_is_no_way_through() {
        let map = Map::from_file(&scenarios::merge(), "merge").expect("builds");
        let (route, s_at) = eastbound(&map, 0.0);
        let cars = |skip: &[f32]| {
            let mut v: Vec<Obstacle> = [-85.0, -80.0, -75.0, -70.0, -65.0, -60.0, -55.0, -50.0]
                .into_iter()
                .filter(|x| !skip.contains(x))
                .map(|x| stopped(x, 0.0, 0.0))
                .collect();
            v.push(stopped(-65.0, -3.5, 0.0));
            v
        };
        let (cfg, rule, s) = (SimConfig::default(), PassageRule::default(), s_at(-80.0));
        let from = |lateral_m: f32, cars: &[Obstacle]| {
            closed_ahead(&map, &cfg, route, s, lateral_m, cars, &rule)
        };
        assert!(from(-3.5, &cars(&[])).is_some(), "walled in");
        assert_eq!(from(-3.5, &cars(&[-75.0, -70.0])), None, "through the hole");
        assert_eq!(from(3.5, &cars(&[])), None, "on the free lane");
    }
}
