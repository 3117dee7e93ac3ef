//! Builders of the paper's four scenarios as [`ScenarioFile`]s.
//!
//! Owns: the geometry of intersection, bottleneck, merge and roundabout (numbers from the
//! spec digest; the rest designed here and listed in `configs/scenarios/README.md`).
//! The shipped files in `configs/scenarios/` are this module's output (`socialflow
//! gen-scenarios`), and a test keeps the two equal. Must not: be needed at run time; the
//! simulator only ever reads files.

use std::f32::consts::{FRAC_PI_2, PI};

use crate::geom::{self, P2};
use crate::map::{
    Boundary, EdgeSpec, LaneSpec, RouteSpec, ScenarioFile, SpawnSpec, FORMAT_VERSION,
    POINT_SPACING_M,
};

/// Lane width, metres (digest).
pub const LANE_W: f32 = 3.5;
/// First spawn point along a route, metres.
pub const FIRST_SPAWN_M: f32 = 10.0;
/// Spacing of spawn points along a lane, metres.
pub const SPAWN_SPACING_M: f32 = 7.5;
/// Clearance kept between the last spawn point and the end of its lane or the zone, metres.
pub const SPAWN_END_CLEARANCE_M: f32 = 6.0;

/// Names of the shipped scenarios, in the paper's order.
pub const SCENARIOS: [&str; 4] = ["intersection", "bottleneck", "merge", "roundabout"];

/// Builds a scenario by name.
pub fn build(name: &str) -> Option<ScenarioFile> {
    Some(match name {
        "intersection" => intersection(),
        "bottleneck" => bottleneck(),
        "merge" => merge(),
        "roundabout" => roundabout(),
        _ => return None,
    })
}

fn rot(p: P2, a: f32) -> P2 {
    let (s, c) = a.sin_cos();
    [p[0] * c - p[1] * s, p[0] * s + p[1] * c]
}

fn rot_all(ps: &[P2], a: f32) -> Vec<P2> {
    ps.iter().map(|p| rot(*p, a)).collect()
}

fn line(a: P2, b: P2) -> Vec<P2> {
    geom::resample(&[a, b], POINT_SPACING_M)
}

/// Circular arc from angle `a0` to `a1` (radians; `a1 < a0` runs clockwise).
fn arc(c: P2, r: f32, a0: f32, a1: f32) -> Vec<P2> {
    let n = (((a1 - a0).abs() * r / POINT_SPACING_M).ceil() as usize).max(2);
    (0..=n)
        .map(|k| {
            let a = a0 + (a1 - a0) * k as f32 / n as f32;
            [c[0] + r * a.cos(), c[1] + r * a.sin()]
        })
        .collect()
}

/// Cubic Hermite curve between two poses, resampled at the point spacing.
fn hermite(p0: P2, h0: f32, p1: P2, h1: f32) -> Vec<P2> {
    let d = geom::dist(p0, p1);
    let (t0, t1) = (geom::scale(geom::heading_vec(h0), d), geom::scale(geom::heading_vec(h1), d));
    let n = 200;
    let dense: Vec<P2> = (0..=n)
        .map(|k| {
            let t = k as f32 / n as f32;
            let (t2, t3) = (t * t, t * t * t);
            let h00 = 2.0 * t3 - 3.0 * t2 + 1.0;
            let h10 = t3 - 2.0 * t2 + t;
            let h01 = -2.0 * t3 + 3.0 * t2;
            let h11 = t3 - t2;
            [
                h00 * p0[0] + h10 * t0[0] + h01 * p1[0] + h11 * t1[0],
                h00 * p0[1] + h10 * t0[1] + h01 * p1[1] + h11 * t1[1],
            ]
        })
        .collect();
    geom::resample(&dense, POINT_SPACING_M)
}

fn round_mm(p: P2) -> P2 {
    [(p[0] * 1000.0).round() / 1000.0, (p[1] * 1000.0).round() / 1000.0]
}

/// Appends `b` to `a`, dropping `b`'s first point when it repeats `a`'s last.
fn chain(a: &mut Vec<P2>, b: &[P2]) {
    for &p in b {
        if a.last().is_none_or(|q| geom::dist(*q, p) > 1e-3) {
            a.push(p);
        }
    }
}

#[derive(Default)]
struct Builder {
    lanes: Vec<LaneSpec>,
    edges: Vec<EdgeSpec>,
    routes: Vec<RouteSpec>,
}

impl Builder {
    fn lane(&mut self, centre: Vec<P2>) -> u32 {
        let id = self.lanes.len() as u32;
        self.lanes.push(LaneSpec {
            id,
            width_m: LANE_W,
            centre: centre.into_iter().map(round_mm).collect(),
            successors: vec![],
        });
        id
    }

    fn connect(&mut self, from: u32, to: u32) {
        let s = &mut self.lanes[from as usize].successors;
        if !s.contains(&to) {
            s.push(to);
        }
    }

    fn route(&mut self, lanes: &[u32]) {
        for w in lanes.windows(2) {
            self.connect(w[0], w[1]);
        }
        self.routes.push(RouteSpec { id: self.routes.len() as u32, lanes: lanes.to_vec() });
    }

    fn edge(&mut self, pts: Vec<P2>) {
        self.edges.push(EdgeSpec {
            id: self.edges.len() as u32,
            points: pts.into_iter().map(round_mm).collect(),
        });
    }

    /// Spawn points every [`SPAWN_SPACING_M`] along each distinct first lane, from
    /// [`FIRST_SPAWN_M`] up to a clearance before the lane's end or the zone, whichever is first.
    fn finish(
        self,
        name: &str,
        boundary: Boundary,
        zone: Vec<P2>,
        junction_zones: Vec<Vec<P2>>,
    ) -> ScenarioFile {
        let mut spawn_points = Vec::new();
        let mut firsts: Vec<u32> = Vec::new();
        for r in &self.routes {
            if !firsts.contains(&r.lanes[0]) {
                firsts.push(r.lanes[0]);
            }
        }
        for first in firsts {
            let routes: Vec<u32> =
                self.routes.iter().filter(|r| r.lanes[0] == first).map(|r| r.id).collect();
            let centre = &self.lanes[first as usize].centre;
            let cum = geom::cumulative_lengths(centre);
            let zone_s = centre
                .iter()
                .zip(&cum)
                .find(|(p, _)| geom::point_in_polygon(**p, &zone))
                .map(|(_, s)| *s)
                .unwrap_or(f32::INFINITY);
            let last = (cum[cum.len() - 1]).min(zone_s) - SPAWN_END_CLEARANCE_M;
            let mut s = FIRST_SPAWN_M;
            while s <= last {
                spawn_points.push(SpawnSpec { s_m: s, routes: routes.clone() });
                s += SPAWN_SPACING_M;
            }
        }
        ScenarioFile {
            format_version: FORMAT_VERSION,
            name: name.to_string(),
            boundary,
            lanes: self.lanes,
            edges: self.edges,
            routes: self.routes,
            interaction_zone: zone.into_iter().map(round_mm).collect(),
            junction_zones: junction_zones
                .into_iter()
                .map(|z| z.into_iter().map(round_mm).collect())
                .collect(),
            spawn_points,
        }
    }
}

fn rect(x0: f32, y0: f32, x1: f32, y1: f32) -> Vec<P2> {
    vec![[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
}

fn circle(r: f32, n: usize) -> Vec<P2> {
    (0..n)
        .map(|k| {
            let a = 2.0 * PI * k as f32 / n as f32;
            [r * a.cos(), r * a.sin()]
        })
        .collect()
}

/// Four-way junction, 70 m arms, two lanes each way; zone = the junction box |x|, |y| <= 12.5 m.
/// Inner lanes go straight or left, outer lanes straight or right: 16 routes.
pub fn intersection() -> ScenarioFile {
    const BOX: f32 = 12.5;
    const FAR: f32 = BOX + 70.0;
    let mut b = Builder::default();
    let offs = [LANE_W / 2.0, LANE_W * 1.5];
    // Arm k is the south arm rotated by k * 90 deg (0 south, 1 east, 2 north, 3 west).
    let mut inbound = [[0u32; 2]; 4];
    let mut outbound = [[0u32; 2]; 4];
    for k in 0..4 {
        let a = k as f32 * FRAC_PI_2;
        for i in 0..2 {
            inbound[k][i] = b.lane(rot_all(&line([offs[i], -FAR], [offs[i], -BOX]), a));
            outbound[k][i] = b.lane(rot_all(&line([-offs[i], -BOX], [-offs[i], -FAR]), a));
        }
    }
    for k in 0..4 {
        let a = k as f32 * FRAC_PI_2;
        for i in 0..2 {
            let straight = b.lane(rot_all(&line([offs[i], -BOX], [offs[i], BOX]), a));
            b.route(&[inbound[k][i], straight, outbound[(k + 2) % 4][i]]);
            if i == 0 {
                let left = b.lane(rot_all(&arc([-BOX, -BOX], BOX + offs[0], 0.0, FRAC_PI_2), a));
                b.route(&[inbound[k][0], left, outbound[(k + 3) % 4][0]]);
            } else {
                let right = b.lane(rot_all(&arc([BOX, -BOX], BOX - offs[1], PI, FRAC_PI_2), a));
                b.route(&[inbound[k][1], right, outbound[(k + 1) % 4][1]]);
            }
        }
    }
    let half = 2.0 * LANE_W;
    for k in 0..4 {
        let a = k as f32 * FRAC_PI_2;
        let mut e = line([half, -FAR], [half, -BOX]);
        chain(&mut e, &arc([BOX, -BOX], BOX - half, PI, FRAC_PI_2));
        chain(&mut e, &line([BOX, -half], [FAR, -half]));
        b.edge(rot_all(&e, a));
    }
    let zone = rect(-BOX, -BOX, BOX, BOX);
    let junction = rect(-BOX - 1.0, -BOX - 1.0, BOX + 1.0, BOX + 1.0);
    b.finish(
        "intersection",
        Boundary { min: [-90.0, -90.0], max: [90.0, 90.0] },
        zone,
        vec![junction],
    )
}

/// 240 m road, two lanes each way, narrowing to one lane each way over |x| <= 12 m with
/// 20 m tapers; zone = the narrow section. Every lane of a direction funnels through it.
pub fn bottleneck() -> ScenarioFile {
    const END: f32 = 120.0;
    const NARROW: f32 = 12.0;
    const TAPER: f32 = 32.0;
    let mut b = Builder::default();
    let (yi, yo) = (-LANE_W / 2.0, -LANE_W * 1.5);
    for dir in 0..2 {
        let a = dir as f32 * PI;
        let r = |v: Vec<P2>| rot_all(&v, a);
        let in_inner = b.lane(r(line([-END, yi], [-TAPER, yi])));
        let in_outer = b.lane(r(line([-END, yo], [-TAPER, yo])));
        let tap_inner = b.lane(r(line([-TAPER, yi], [-NARROW, yi])));
        let tap_outer = b.lane(r(hermite([-TAPER, yo], 0.0, [-NARROW, yi], 0.0)));
        let narrow = b.lane(r(line([-NARROW, yi], [NARROW, yi])));
        let div_inner = b.lane(r(line([NARROW, yi], [TAPER, yi])));
        let div_outer = b.lane(r(hermite([NARROW, yi], 0.0, [TAPER, yo], 0.0)));
        let out_inner = b.lane(r(line([TAPER, yi], [END, yi])));
        let out_outer = b.lane(r(line([TAPER, yo], [END, yo])));
        for (entry, taper) in [(in_inner, tap_inner), (in_outer, tap_outer)] {
            for (div, out) in [(div_inner, out_inner), (div_outer, out_outer)] {
                b.route(&[entry, taper, narrow, div, out]);
            }
        }
        let w = 2.0 * LANE_W;
        let mut e = line([-END, -w], [-TAPER, -w]);
        chain(&mut e, &hermite([-TAPER, -w], 0.0, [-NARROW, -LANE_W], 0.0));
        chain(&mut e, &line([-NARROW, -LANE_W], [NARROW, -LANE_W]));
        chain(&mut e, &hermite([NARROW, -LANE_W], 0.0, [TAPER, -w], 0.0));
        chain(&mut e, &line([TAPER, -w], [END, -w]));
        b.edge(r(e));
    }
    let zone = rect(-NARROW, -2.0 * LANE_W, NARROW, 2.0 * LANE_W);
    b.finish("bottleneck", Boundary { min: [-125.0, -20.0], max: [125.0, 20.0] }, zone, vec![])
}

/// Three-lane main road (x from -90 to 56 m) and a two-lane on-ramp whose lanes join the two
/// main lanes nearest to it at x = 20 m; five routes; zone = the merging area.
pub fn merge() -> ScenarioFile {
    const X0: f32 = -90.0;
    const X1: f32 = 56.0;
    const ZONE_X0: f32 = -12.0;
    const MERGE_X: f32 = 20.0;
    const ZONE_X1: f32 = 30.0;
    let mut b = Builder::default();
    let ys = [LANE_W, 0.0, -LANE_W];
    let top = ys[0] + LANE_W / 2.0;
    let bottom = ys[2] - LANE_W / 2.0;
    let mut down = [0u32; 3];
    for (k, &y) in ys.iter().enumerate() {
        let up = b.lane(line([X0, y], [ZONE_X0, y]));
        let mid = b.lane(line([ZONE_X0, y], [MERGE_X, y]));
        down[k] = b.lane(line([MERGE_X, y], [X1, y]));
        b.route(&[up, mid, down[k]]);
    }
    // Ramp reference line (between its two lanes), ending tangent to the main road.
    let reference = hermite([-80.0, -55.0], 30f32.to_radians(), [MERGE_X, -LANE_W / 2.0], 0.0);
    for j in 0..2 {
        let off = if j == 0 { LANE_W / 2.0 } else { -LANE_W / 2.0 };
        let ramp = b.lane(geom::offset_polyline(&reference, off));
        b.route(&[ramp, down[j + 1]]);
    }
    let upper = geom::offset_polyline(&reference, LANE_W);
    let lower = geom::offset_polyline(&reference, -LANE_W);
    // The ramp's upper edge stops where it meets the main road's lower edge.
    let cut = upper.iter().position(|p| p[1] >= bottom).unwrap_or(upper.len() - 1).max(1);
    let (p, q) = (upper[cut - 1], upper[cut]);
    let t = (bottom - p[1]) / (q[1] - p[1]);
    let meet = [p[0] + t * (q[0] - p[0]), bottom];
    let mut upper_edge = upper[..cut].to_vec();
    upper_edge.push(meet);
    b.edge(line([X0, top], [X1, top]));
    b.edge(line([X0, bottom], meet));
    b.edge(upper_edge);
    let mut lower_edge = lower.clone();
    chain(&mut lower_edge, &line([MERGE_X, bottom], [X1, bottom]));
    b.edge(lower_edge);
    // Zone: the main road between ZONE_X0 and ZONE_X1 plus the ramp from where it is at ZONE_X0.
    let iz = reference.iter().position(|p| p[0] >= ZONE_X0).unwrap_or(0);
    let zone = vec![
        [ZONE_X0, top],
        [ZONE_X1, top],
        [ZONE_X1, bottom],
        [MERGE_X, bottom],
        lower[iz],
        upper[iz],
        [ZONE_X0, bottom],
    ];
    b.finish("merge", Boundary { min: [-95.0, -65.0], max: [60.0, 10.0] }, zone, vec![])
}

/// Three arms (70 m, two lanes each way) around a two-lane ring (island radius 12 m, ring
/// 12-19 m); outer lanes take the first exit, inner lanes the second: 6 routes; zone = the ring.
pub fn roundabout() -> ScenarioFile {
    const ISLAND: f32 = 12.0;
    const RING_OUT: f32 = ISLAND + 2.0 * LANE_W;
    const ARM_IN: f32 = 30.0;
    const FAR: f32 = ARM_IN + 70.0;
    let alpha = 40f32.to_radians();
    let radii = [ISLAND + LANE_W / 2.0, ISLAND + LANE_W * 1.5];
    let offs = [LANE_W / 2.0, LANE_W * 1.5];
    let arm_rot = |k: usize| k as f32 * 2.0 * PI / 3.0;
    let phi = |k: usize| -FRAC_PI_2 + arm_rot(k);
    let ring_pt = |r: f32, a: f32| [r * a.cos(), r * a.sin()];
    let mut b = Builder::default();
    let mut inbound = [[0u32; 2]; 3];
    let mut outbound = [[0u32; 2]; 3];
    let mut entry = [[0u32; 2]; 3];
    let mut exit = [[0u32; 2]; 3];
    let mut entry_pts =
        [[Vec::new(), Vec::new()], [Vec::new(), Vec::new()], [Vec::new(), Vec::new()]];
    let mut exit_pts = entry_pts.clone();
    for k in 0..3 {
        let a = arm_rot(k);
        for i in 0..2 {
            inbound[k][i] = b.lane(rot_all(&line([offs[i], -FAR], [offs[i], -ARM_IN]), a));
            outbound[k][i] = b.lane(rot_all(&line([-offs[i], -ARM_IN], [-offs[i], -FAR]), a));
            let (ain, aout) = (phi(k) + alpha, phi(k) - alpha);
            let e = hermite(
                rot([offs[i], -ARM_IN], a),
                phi(k) + PI,
                ring_pt(radii[i], ain),
                ain + FRAC_PI_2,
            );
            let x = hermite(
                ring_pt(radii[i], aout),
                aout + FRAC_PI_2,
                rot([-offs[i], -ARM_IN], a),
                phi(k),
            );
            entry[k][i] = b.lane(e.clone());
            exit[k][i] = b.lane(x.clone());
            entry_pts[k][i] = e;
            exit_pts[k][i] = x;
        }
    }
    // Ring lanes split at every entry and exit angle into arcs (counter-clockwise).
    let mut cuts: Vec<f32> = (0..3)
        .flat_map(|k| [phi(k) + alpha, phi(k) - alpha])
        .map(|a| a.rem_euclid(2.0 * PI))
        .collect();
    cuts.sort_by(f32::total_cmp);
    let mut arcs = [Vec::new(), Vec::new()];
    for i in 0..2 {
        for c in 0..cuts.len() {
            let (a0, mut a1) = (cuts[c], cuts[(c + 1) % cuts.len()]);
            if a1 <= a0 {
                a1 += 2.0 * PI;
            }
            let id = b.lane(arc([0.0, 0.0], radii[i], a0, a1));
            arcs[i].push((a0, id));
        }
    }
    let arc_index = |a: f32| {
        cuts.iter().position(|c| (c - a.rem_euclid(2.0 * PI)).abs() < 1e-4).expect("cut angle")
    };
    for k in 0..3 {
        for i in 0..2 {
            let dest = (k + 2 - i) % 3; // outer lane (i = 1): next arm; inner lane: the one after
            let mut lanes = vec![inbound[k][i], entry[k][i]];
            let mut c = arc_index(phi(k) + alpha);
            let stop = arc_index(phi(dest) - alpha);
            while c != stop {
                lanes.push(arcs[i][c].1);
                c = (c + 1) % cuts.len();
            }
            lanes.push(exit[dest][i]);
            lanes.push(outbound[dest][i]);
            b.route(&lanes);
        }
    }
    b.edge({
        let mut c = circle(ISLAND, 40);
        c.push(c[0]);
        c
    });
    let half = 2.0 * LANE_W;
    for k in 0..3 {
        let n = (k + 1) % 3;
        let mut e = rot_all(&line([half, -FAR], [half, -ARM_IN]), arm_rot(k));
        chain(&mut e, &geom::offset_polyline(&entry_pts[k][1], -LANE_W / 2.0));
        let (a0, mut a1) = (phi(k) + alpha, phi(n) - alpha);
        if a1 < a0 {
            a1 += 2.0 * PI;
        }
        chain(&mut e, &arc([0.0, 0.0], RING_OUT, a0, a1));
        chain(&mut e, &geom::offset_polyline(&exit_pts[n][1], -LANE_W / 2.0));
        chain(&mut e, &rot_all(&line([-half, -ARM_IN], [-half, -FAR]), arm_rot(n)));
        b.edge(e);
    }
    let zone = circle(RING_OUT, 48);
    let junction = circle(ARM_IN + 1.0, 48);
    b.finish(
        "roundabout",
        Boundary { min: [-105.0, -105.0], max: [105.0, 105.0] },
        zone,
        vec![junction],
    )
}
