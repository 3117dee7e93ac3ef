//! Maps as data: the scenario file format, its validating loader, and the runtime map.
//!
//! Owns: [`ScenarioFile`] (serde, JSON on disk), [`Map`] (lanes, road edges, routes, zones,
//! spawn points, spatial indices). Must not: hold vehicles or any per-episode state; a `Map`
//! is immutable after loading and shared (`Arc`) by every environment on it.
//!
//! Invariants established by [`Map::from_file`]: ids are dense indices; the boundary is at most
//! [`MAX_EXTENT_M`] a side; every polyline has at least two finite points inside the boundary; consecutive lanes of a route are connected
//! (`successors`); every route crosses the interaction zone; every spawn point lies on the
//! first lane of each route it lists, outside the interaction zone.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::geom::{self, Grid, P2};

/// The only format version this loader reads.
pub const FORMAT_VERSION: u32 = 1;

/// Spawn points closer than this overlap (less than a lane width, more than a car's width).
pub const MIN_SPAWN_SEPARATION_M: f32 = 3.0;

/// Largest side of a map's boundary, in metres. The spatial grids hold one cell per 4 m square
/// of the boundary, so a larger (if finite) boundary could exhaust memory while loading; the
/// shipped maps are at most 250 m a side.
pub const MAX_EXTENT_M: f32 = 5_000.0;

/// Resampling spacing of route polylines and lane centre-lines, in metres.
pub const POINT_SPACING_M: f32 = 2.0;

/// On-disk scenario description.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ScenarioFile {
    pub format_version: u32,
    pub name: String,
    pub boundary: Boundary,
    pub lanes: Vec<LaneSpec>,
    pub edges: Vec<EdgeSpec>,
    pub routes: Vec<RouteSpec>,
    /// Polygon of the interaction zone; success requires passing through it.
    pub interaction_zone: Vec<P2>,
    /// Polygons inside which the wrong-lane rule is not applied (junction boxes, rings).
    pub junction_zones: Vec<Vec<P2>>,
    pub spawn_points: Vec<SpawnSpec>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Boundary {
    pub min: P2,
    pub max: P2,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LaneSpec {
    pub id: u32,
    pub width_m: f32,
    /// Centre-line points in travel order.
    pub centre: Vec<P2>,
    pub successors: Vec<u32>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EdgeSpec {
    pub id: u32,
    pub points: Vec<P2>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RouteSpec {
    pub id: u32,
    pub lanes: Vec<u32>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SpawnSpec {
    /// Arc length along the route(s), which all start with the same lane.
    pub s_m: f32,
    pub routes: Vec<u32>,
}

/// Why a scenario file was rejected. Messages name the file, the field and the reason.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    #[error("cannot read scenario file {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("scenario file {path} is not valid JSON for the scenario format: {source}")]
    Parse { path: String, source: serde_json::Error },
    #[error("scenario file {path}: field `{field}`: {reason}")]
    Invalid { path: String, field: String, reason: String },
}

/// A lane at run time.
#[derive(Clone, Debug)]
pub struct Lane {
    pub width_m: f32,
    pub centre: Vec<P2>,
    pub headings: Vec<f32>,
    pub cum_m: Vec<f32>,
    pub successors: Vec<u32>,
}

/// A route at run time: its lanes joined and resampled every [`POINT_SPACING_M`].
#[derive(Clone, Debug)]
pub struct Route {
    pub lanes: Vec<u32>,
    pub points: Vec<P2>,
    pub headings: Vec<f32>,
    pub cum_m: Vec<f32>,
    pub length_m: f32,
    /// Width of the route's first lane (used as the route polyline's width feature).
    pub width_m: f32,
}

/// A spawn pose with the routes that may start there.
#[derive(Clone, Debug)]
pub struct SpawnPoint {
    pub s_m: f32,
    pub pos: P2,
    pub heading_rad: f32,
    pub routes: Vec<u32>,
}

/// A static map polyline kind, for observations and rendering.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PolyKind {
    Lane,
    Edge,
}

/// The immutable runtime map.
#[derive(Clone, Debug)]
pub struct Map {
    pub name: String,
    pub boundary: Boundary,
    pub lanes: Vec<Lane>,
    pub edges: Vec<Vec<P2>>,
    pub routes: Vec<Route>,
    pub zone: Vec<P2>,
    pub junction_zones: Vec<Vec<P2>>,
    pub spawns: Vec<SpawnPoint>,
    /// Every edge segment as (a, b).
    pub edge_segments: Vec<(P2, P2)>,
    pub edge_grid: Grid,
    /// Every lane centre point as (point, heading).
    pub lane_points: Vec<(P2, f32)>,
    pub lane_point_grid: Grid,
}

fn invalid(path: &str, field: impl Into<String>, reason: impl Into<String>) -> MapError {
    MapError::Invalid { path: path.to_string(), field: field.into(), reason: reason.into() }
}

impl ScenarioFile {
    /// Reads and parses a scenario file; use [`Map::from_file`] to validate it too.
    pub fn read(path: &Path) -> Result<Self, MapError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|source| MapError::Io { path: p.clone(), source })?;
        serde_json::from_str(&text).map_err(|source| MapError::Parse { path: p, source })
    }

    /// Writes the file as pretty JSON (write to a temporary file, then rename).
    pub fn write(&self, path: &Path) -> std::io::Result<()> {
        let text = serde_json::to_string_pretty(self).map_err(std::io::Error::other)?;
        let tmp = path.with_extension("json.tmp");
        std::fs::write(&tmp, text + "\n")?;
        std::fs::rename(tmp, path)
    }
}

impl Map {
    /// Loads and validates a scenario file.
    pub fn load(path: &Path) -> Result<Self, MapError> {
        let file = ScenarioFile::read(path)?;
        Self::from_file(&file, &path.display().to_string())
    }

    /// Validates a parsed scenario; `origin` names it in error messages.
    pub fn from_file(f: &ScenarioFile, origin: &str) -> Result<Self, MapError> {
        let v = Checker::new(f, origin)?;
        let lanes = v.lanes()?;
        v.shapes()?;
        let routes = v.routes(&lanes)?;
        let spawns = v.spawns(&lanes, &routes)?;
        Ok(Self::indexed(f, lanes, routes, spawns))
    }

    /// The map of a checked file: its parts and the spatial indices over them.
    fn indexed(
        f: &ScenarioFile,
        lanes: Vec<Lane>,
        routes: Vec<Route>,
        spawns: Vec<SpawnPoint>,
    ) -> Self {
        let b = &f.boundary;
        let edges: Vec<Vec<P2>> = f.edges.iter().map(|e| e.points.clone()).collect();
        let edge_segments: Vec<(P2, P2)> =
            edges.iter().flat_map(|e| e.windows(2).map(|w| (w[0], w[1]))).collect();
        let seg_boxes: Vec<(P2, P2)> = edge_segments
            .iter()
            .map(|(a, b)| ([a[0].min(b[0]), a[1].min(b[1])], [a[0].max(b[0]), a[1].max(b[1])]))
            .collect();
        let edge_grid = Grid::build(b.min, b.max, 8.0, &seg_boxes);
        let lane_points: Vec<(P2, f32)> = lanes
            .iter()
            .flat_map(|l| {
                // Dense points (about every metre) so the nearest lane is found reliably.
                let dense = geom::resample(&l.centre, 1.0);
                let hs = geom::polyline_headings(&dense);
                dense.into_iter().zip(hs).collect::<Vec<_>>()
            })
            .collect();
        let lp_boxes: Vec<(P2, P2)> = lane_points.iter().map(|(p, _)| (*p, *p)).collect();
        let lane_point_grid = Grid::build(b.min, b.max, 4.0, &lp_boxes);
        Map {
            name: f.name.clone(),
            boundary: f.boundary.clone(),
            lanes,
            edges,
            routes,
            zone: f.interaction_zone.clone(),
            junction_zones: f.junction_zones.clone(),
            spawns,
            edge_segments,
            edge_grid,
            lane_points,
            lane_point_grid,
        }
    }

    /// Whether `p` lies in a zone where the wrong-lane rule is off.
    pub fn in_junction(&self, p: P2) -> bool {
        self.junction_zones.iter().any(|z| geom::point_in_polygon(p, z))
    }

    /// Heading of the lane point nearest to `p` within `max_m`, if any.
    pub fn nearest_lane_heading(&self, p: P2, max_m: f32) -> Option<f32> {
        let mut best = (max_m * max_m, None);
        self.lane_point_grid.for_each_near(p, max_m, |i| {
            let (q, h) = self.lane_points[i];
            let d2 = geom::dist2(p, q);
            if d2 < best.0 {
                best = (d2, Some(h));
            }
        });
        best.1
    }

    /// Whether a car at `p` heading `heading_rad` drives on a lane the right way: within
    /// `reach_m` of a lane's centre line whose heading there is within `max_heading_rad` of its
    /// own (any lane inside a junction, where the wrong-lane rule is off). The opposite
    /// carriageway and the space beside the road are not. Shared by the corridor test
    /// ([`crate::passage`]) and MOBIL's choice of lanes ([`crate::mobil`]).
    pub fn lane_runs_along(
        &self,
        p: P2,
        heading_rad: f32,
        max_heading_rad: f32,
        reach_m: f32,
    ) -> bool {
        self.nearest_lane_heading(p, reach_m).is_some_and(|h| {
            self.in_junction(p) || geom::wrap_angle(h - heading_rad).abs() <= max_heading_rad
        })
    }

    /// Static polylines (lane centre-lines with their widths, then edges with width 0).
    pub fn static_polylines(&self) -> impl Iterator<Item = (PolyKind, &[P2], f32)> {
        self.lanes
            .iter()
            .map(|l| (PolyKind::Lane, l.centre.as_slice(), l.width_m))
            .chain(self.edges.iter().map(|e| (PolyKind::Edge, e.as_slice(), 0.0)))
    }
}

/// The checks of [`Map::from_file`], section by section, each error naming the file and field.
struct Checker<'a> {
    f: &'a ScenarioFile,
    origin: &'a str,
}

impl<'a> Checker<'a> {
    /// The format version, the name and the boundary.
    fn new(f: &'a ScenarioFile, origin: &'a str) -> Result<Self, MapError> {
        let c = Self { f, origin };
        if f.format_version != FORMAT_VERSION {
            return Err(c.bad(
                "format_version",
                format!(
                    "version {} is not supported (this build reads {FORMAT_VERSION})",
                    f.format_version
                ),
            ));
        }
        if f.name.is_empty() {
            return Err(c.bad("name", "must not be empty"));
        }
        let b = &f.boundary;
        if !(b.min.iter().chain(b.max.iter()).all(|v| v.is_finite())
            && b.min[0] < b.max[0]
            && b.min[1] < b.max[1])
        {
            return Err(c.bad("boundary", "min must be finite and below max on both axes"));
        }
        let extent_m = [b.max[0] - b.min[0], b.max[1] - b.min[1]];
        if extent_m.iter().any(|&e| e > MAX_EXTENT_M) {
            return Err(c.bad(
                "boundary",
                format!("{} x {} m exceeds {MAX_EXTENT_M} m a side", extent_m[0], extent_m[1]),
            ));
        }
        Ok(c)
    }

    fn bad(&self, field: impl Into<String>, reason: impl Into<String>) -> MapError {
        invalid(self.origin, field, reason)
    }

    /// At least `min_len` finite points, all inside the boundary.
    fn poly(&self, field: String, pts: &[P2], min_len: usize) -> Result<(), MapError> {
        let b = &self.f.boundary;
        let inside =
            |p: &P2| p[0] >= b.min[0] && p[0] <= b.max[0] && p[1] >= b.min[1] && p[1] <= b.max[1];
        if pts.len() < min_len {
            return Err(
                self.bad(field, format!("needs at least {min_len} points, has {}", pts.len()))
            );
        }
        for (k, p) in pts.iter().enumerate() {
            if !(p[0].is_finite() && p[1].is_finite()) {
                return Err(self.bad(format!("{field}[{k}]"), "point is not finite"));
            }
            if !inside(p) {
                return Err(self.bad(
                    format!("{field}[{k}]"),
                    format!("point {p:?} lies outside the boundary"),
                ));
            }
        }
        Ok(())
    }

    /// Lanes: dense ids, widths, centre-lines without repeated points, existing successors.
    fn lanes(&self) -> Result<Vec<Lane>, MapError> {
        let f = self.f;
        if f.lanes.is_empty() {
            return Err(self.bad("lanes", "a scenario needs at least one lane"));
        }
        let n_lanes = f.lanes.len() as u32;
        let mut lanes = Vec::with_capacity(f.lanes.len());
        for (i, l) in f.lanes.iter().enumerate() {
            if l.id != i as u32 {
                return Err(self.bad(
                    format!("lanes[{i}].id"),
                    format!("is {}, ids must equal their index {i}", l.id),
                ));
            }
            if !(l.width_m.is_finite() && l.width_m > 0.0 && l.width_m < 10.0) {
                return Err(self.bad(
                    format!("lanes[{i}].width_m"),
                    format!("{} is not in (0, 10) m", l.width_m),
                ));
            }
            self.poly(format!("lanes[{i}].centre"), &l.centre, 2)?;
            for (k, w) in l.centre.windows(2).enumerate() {
                if geom::dist(w[0], w[1]) < 1e-3 {
                    return Err(self.bad(
                        format!("lanes[{i}].centre[{}]", k + 1),
                        "repeats the previous point",
                    ));
                }
            }
            if let Some(s) = l.successors.iter().find(|&&s| s >= n_lanes) {
                return Err(
                    self.bad(format!("lanes[{i}].successors"), format!("lane {s} does not exist"))
                );
            }
            lanes.push(Lane {
                width_m: l.width_m,
                headings: geom::polyline_headings(&l.centre),
                cum_m: geom::cumulative_lengths(&l.centre),
                centre: l.centre.clone(),
                successors: l.successors.clone(),
            });
        }
        Ok(lanes)
    }

    /// Road edges (dense ids), the interaction zone and the junction zones.
    fn shapes(&self) -> Result<(), MapError> {
        let f = self.f;
        for (i, e) in f.edges.iter().enumerate() {
            if e.id != i as u32 {
                return Err(self.bad(
                    format!("edges[{i}].id"),
                    format!("is {}, ids must equal their index {i}", e.id),
                ));
            }
            self.poly(format!("edges[{i}].points"), &e.points, 2)?;
        }
        self.poly("interaction_zone".into(), &f.interaction_zone, 3)?;
        for (i, z) in f.junction_zones.iter().enumerate() {
            self.poly(format!("junction_zones[{i}]"), z, 3)?;
        }
        Ok(())
    }

    /// Routes: dense ids, connected existing lanes, entering the interaction zone and leaving it.
    fn routes(&self, lanes: &[Lane]) -> Result<Vec<Route>, MapError> {
        let f = self.f;
        if f.routes.is_empty() {
            return Err(self.bad("routes", "a scenario needs at least one route"));
        }
        let n_lanes = lanes.len() as u32;
        let mut routes = Vec::with_capacity(f.routes.len());
        for (i, r) in f.routes.iter().enumerate() {
            let field = format!("routes[{i}]");
            if r.id != i as u32 {
                return Err(self.bad(
                    format!("{field}.id"),
                    format!("is {}, ids must equal their index {i}", r.id),
                ));
            }
            if r.lanes.is_empty() {
                return Err(self.bad(format!("{field}.lanes"), "a route needs at least one lane"));
            }
            for (k, &l) in r.lanes.iter().enumerate() {
                if l >= n_lanes {
                    return Err(
                        self.bad(format!("{field}.lanes[{k}]"), format!("lane {l} does not exist"))
                    );
                }
                if k > 0 && !lanes[r.lanes[k - 1] as usize].successors.contains(&l) {
                    return Err(self.bad(
                        format!("{field}.lanes[{k}]"),
                        format!("lane {l} is not a successor of lane {}", r.lanes[k - 1]),
                    ));
                }
            }
            let route = build_route(lanes, &r.lanes);
            if !route.points.iter().any(|p| geom::point_in_polygon(*p, &f.interaction_zone)) {
                return Err(self.bad(field, "the route never enters the interaction zone"));
            }
            if geom::point_in_polygon(route.points[route.points.len() - 1], &f.interaction_zone) {
                return Err(self.bad(field, "the route ends inside the interaction zone"));
            }
            routes.push(route);
        }
        Ok(routes)
    }

    /// Spawn points: on the shared first lane of every route they list, outside the
    /// interaction zone, apart from each other.
    fn spawns(&self, lanes: &[Lane], routes: &[Route]) -> Result<Vec<SpawnPoint>, MapError> {
        let f = self.f;
        if f.spawn_points.is_empty() {
            return Err(self.bad("spawn_points", "a scenario needs at least one spawn point"));
        }
        let mut spawns = Vec::with_capacity(f.spawn_points.len());
        for (i, s) in f.spawn_points.iter().enumerate() {
            let field = format!("spawn_points[{i}]");
            if s.routes.is_empty() {
                return Err(self.bad(format!("{field}.routes"), "lists no route"));
            }
            let mut pose = None;
            for &r in &s.routes {
                let Some(route) = routes.get(r as usize) else {
                    return Err(
                        self.bad(format!("{field}.routes"), format!("route {r} does not exist"))
                    );
                };
                let first_lane = route.lanes[0];
                let lane_len = lanes[first_lane as usize].cum_m.last().copied().unwrap_or(0.0);
                if !(s.s_m.is_finite() && s.s_m >= 0.0 && s.s_m <= lane_len) {
                    return Err(self.bad(
                        format!("{field}.s_m"),
                        format!(
                            "{} is not on the first lane of route {r} (length {lane_len:.1} m)",
                            s.s_m
                        ),
                    ));
                }
                let here = geom::point_at(&route.points, &route.cum_m, s.s_m);
                match pose {
                    None => pose = Some((first_lane, here)),
                    Some((l0, _)) if l0 != first_lane => {
                        return Err(self.bad(
                            format!("{field}.routes"),
                            "routes listed do not share their first lane",
                        ))
                    }
                    _ => {}
                }
            }
            let Some((_, (pos, heading_rad))) = pose else {
                return Err(self.bad(format!("{field}.routes"), "lists no route"));
            };
            if geom::point_in_polygon(pos, &f.interaction_zone) {
                return Err(self.bad(field, "spawn point lies inside the interaction zone"));
            }
            spawns.push(SpawnPoint { s_m: s.s_m, pos, heading_rad, routes: s.routes.clone() });
        }
        for (i, a) in spawns.iter().enumerate() {
            if let Some(j) =
                spawns[..i].iter().position(|b| geom::dist(a.pos, b.pos) < MIN_SPAWN_SEPARATION_M)
            {
                return Err(
                    self.bad(format!("spawn_points[{i}]"), format!("overlaps spawn point {j}"))
                );
            }
        }
        Ok(spawns)
    }
}

fn build_route(lanes: &[Lane], ids: &[u32]) -> Route {
    let mut pts: Vec<P2> = Vec::new();
    for &l in ids {
        for &p in &lanes[l as usize].centre {
            if pts.last().is_none_or(|q| geom::dist(*q, p) > 1e-3) {
                pts.push(p);
            }
        }
    }
    let points = geom::resample(&pts, POINT_SPACING_M);
    let cum_m = geom::cumulative_lengths(&points);
    Route {
        lanes: ids.to_vec(),
        headings: geom::polyline_headings(&points),
        length_m: cum_m[cum_m.len() - 1],
        cum_m,
        points,
        width_m: lanes[ids[0] as usize].width_m,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (found by `tests/fuzz.rs`): a finite but huge boundary was accepted and the
    /// spatial grids' cell count overflowed (or their allocation aborted the process).
    #[test]
    fn a_huge_boundary_is_refused() {
        let good = crate::scenarios::build("merge").expect("builder");
        for (axis, v) in [(0, -1e9), (1, -1e30), (0, -f32::MAX)] {
            let mut f = good.clone();
            f.boundary.min[axis] = v;
            let e = Map::from_file(&f, "big.json").expect_err("huge boundary").to_string();
            assert!(
                e.contains("big.json") && e.contains("`boundary`") && e.contains("exceeds"),
                "{e}"
            );
        }
        let mut f = good.clone();
        f.boundary.min[0] = f.boundary.max[0] - MAX_EXTENT_M;
        assert!(Map::from_file(&f, "wide.json").is_ok(), "the limit itself is allowed");
    }
}
