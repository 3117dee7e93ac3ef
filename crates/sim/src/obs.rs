//! Observations: fixed-shape `f32` vectors with validity masks, in two layouts.
//!
//! Owns: [`ObsSpec`] (the flat layout and its offsets, shared with the networks),
//! [`MapSegments`] (map polylines cut into fixed-length pieces, each stored once in its own
//! frame) and [`Observer`] (writes one agent's observation into a caller's slice without
//! allocating). Must not: know about policies or networks beyond the layout contract below.
//!
//! # Layout (all `f32`, in this order; N = max_neighbours, H = history, R = route_points)
//! | block | shape | contents |
//! |---|---|---|
//! | ego_hist | H x 4 | own history, oldest first, in the observer's current frame: x/50, y/50, theta/pi, v/v_max |
//! | ego_ctx | 2 | own SVO / 90 (if visible), ego flag (1 if the observer is the flagged ego) |
//! | agents_hist | N x H x 4 | neighbours' histories: ego-frame layout: in the observer's frame; query-centric: in each neighbour's own current frame |
//! | agents_ctx | N x 6 | neighbour's current pose in the observer's frame (x/50, y/50, cos, sin), communicated SVO / 90 (if visible), ego flag |
//! | agents_mask | N | 1 for a present neighbour |
//! | route | R x 4 | route points ahead (2 m apart) in the observer's frame: x/50, y/50, theta/pi, k/R |
//! | route_mask | R | |
//! | ego-frame: map | M x P x 5 | nearest map pieces, points in the observer's frame: x/50, y/50, theta/pi, lane width/5, k/P |
//! | ego-frame: map_mask | M x P | 1 for a point within the radius |
//! | query-centric: seg_id | S | index into [`MapSegments`] (as f32; exact below 2^24) |
//! | query-centric: seg_pose | S x 4 | segment frame in the observer's frame: x/50, y/50, cos, sin |
//! | query-centric: seg_mask | S | |
//!
//! Time offsets of history frames are implicit in the frame index (frame k is
//! (H - 1 - k) * dt_s before now); networks add them as a constant channel.
//! Neighbours are the nearest other live vehicles within the radius; map pieces the nearest
//! whose bounding circle reaches within the radius; both in ascending (distance, index) order.

use std::f32::consts::PI;
use std::ops::Range;
use std::sync::Arc;

use crate::config::{Layout, ObsConfig, SvoVisibility};
use crate::env::Env;
use crate::geom::{self, Frame, P2};
use crate::map::{Map, PolyKind};

pub const AGENT_FEATS: usize = 4;
pub const AGENT_CTX: usize = 6;
pub const EGO_CTX: usize = 2;
pub const ROUTE_FEATS: usize = 4;
pub const MAP_FEATS: usize = 5;
pub const SEG_POSE: usize = 4;
/// Position normaliser, metres (digest: x, y / 50).
pub const POS_SCALE_M: f32 = 50.0;

/// Offsets of every block of the flat observation.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ObsSpec {
    pub layout: Layout,
    pub history: usize,
    pub neighbours: usize,
    pub route_points: usize,
    /// Map pieces (M or S) and points per piece (P).
    pub map_pieces: usize,
    pub piece_points: usize,
    pub ego_hist: Range<usize>,
    pub ego_ctx: Range<usize>,
    pub agents_hist: Range<usize>,
    pub agents_ctx: Range<usize>,
    pub agents_mask: Range<usize>,
    pub route: Range<usize>,
    pub route_mask: Range<usize>,
    /// Ego-frame: M x P x 5; query-centric: empty.
    pub map: Range<usize>,
    /// Ego-frame: M x P; query-centric: empty.
    pub map_mask: Range<usize>,
    /// Query-centric only (else empty).
    pub seg_id: Range<usize>,
    pub seg_pose: Range<usize>,
    pub seg_mask: Range<usize>,
    pub len: usize,
}

impl ObsSpec {
    pub fn new(c: &ObsConfig) -> Self {
        let mut at = 0;
        let mut take = |n: usize| {
            let r = at..at + n;
            at += n;
            r
        };
        let (h, n, r) = (c.history, c.max_neighbours, c.route_points);
        let ego_hist = take(h * AGENT_FEATS);
        let ego_ctx = take(EGO_CTX);
        let agents_hist = take(n * h * AGENT_FEATS);
        let agents_ctx = take(n * AGENT_CTX);
        let agents_mask = take(n);
        let route = take(r * ROUTE_FEATS);
        let route_mask = take(r);
        let (m, p) = match c.layout {
            Layout::EgoFrame => (c.max_polylines, c.polyline_points),
            Layout::QueryCentric => (c.max_segments, c.segment_points),
        };
        let (map, map_mask, seg_id, seg_pose, seg_mask) = match c.layout {
            Layout::EgoFrame => (take(m * p * MAP_FEATS), take(m * p), 0..0, 0..0, 0..0),
            Layout::QueryCentric => (0..0, 0..0, take(m), take(m * SEG_POSE), take(m)),
        };
        Self {
            layout: c.layout,
            history: h,
            neighbours: n,
            route_points: r,
            map_pieces: m,
            piece_points: p,
            ego_hist,
            ego_ctx,
            agents_hist,
            agents_ctx,
            agents_mask,
            route,
            route_mask,
            map,
            map_mask,
            seg_id,
            seg_pose,
            seg_mask,
            len: at,
        }
    }

    /// The non-empty blocks of the layout in order, as `(name, range, shape)`: the arrays a
    /// row splits into (the Python package's dict observations and the ONNX model's inputs).
    pub fn blocks(&self) -> Vec<(&'static str, Range<usize>, Vec<usize>)> {
        let (h, n, r, m, p) =
            (self.history, self.neighbours, self.route_points, self.map_pieces, self.piece_points);
        let all = [
            ("ego_hist", self.ego_hist.clone(), vec![h, AGENT_FEATS]),
            ("ego_ctx", self.ego_ctx.clone(), vec![EGO_CTX]),
            ("agents_hist", self.agents_hist.clone(), vec![n, h, AGENT_FEATS]),
            ("agents_ctx", self.agents_ctx.clone(), vec![n, AGENT_CTX]),
            ("agents_mask", self.agents_mask.clone(), vec![n]),
            ("route", self.route.clone(), vec![r, ROUTE_FEATS]),
            ("route_mask", self.route_mask.clone(), vec![r]),
            ("map", self.map.clone(), vec![m, p, MAP_FEATS]),
            ("map_mask", self.map_mask.clone(), vec![m, p]),
            ("seg_id", self.seg_id.clone(), vec![m]),
            ("seg_pose", self.seg_pose.clone(), vec![m, SEG_POSE]),
            ("seg_mask", self.seg_mask.clone(), vec![m]),
        ];
        all.into_iter().filter(|(_, r, _)| !r.is_empty()).collect()
    }

    /// Bytes of one observation stored as f32.
    pub fn bytes_f32(&self) -> usize {
        self.len * 4
    }

    /// Checks what a network will index or branch on in one observation row from outside
    /// (a worker's batch): every mask is 0 or 1 and every valid query-centric segment id is a
    /// whole number below `segments` (the map's piece count). The error names the block and slot.
    /// Generic over the stored value (`f32`, or the wire's half floats): only the checked
    /// values are converted.
    pub fn check_row<T: Copy + Into<f32>>(
        &self,
        row: &[T],
        segments: usize,
    ) -> Result<(), ObsRowError> {
        if row.len() != self.len {
            return Err(ObsRowError::Length { got: row.len(), want: self.len });
        }
        let at = |r: &Range<usize>| row[r.clone()].iter().map(|&v| v.into());
        for (block, r) in [
            ("agents_mask", &self.agents_mask),
            ("route_mask", &self.route_mask),
            ("map_mask", &self.map_mask),
            ("seg_mask", &self.seg_mask),
        ] {
            if let Some((slot, value)) = at(r).enumerate().find(|&(_, v)| v != 0.0 && v != 1.0) {
                return Err(ObsRowError::Mask { block, slot, value });
            }
        }
        for (slot, (id, valid)) in at(&self.seg_id).zip(at(&self.seg_mask)).enumerate() {
            if valid == 1.0 && !(id >= 0.0 && id.fract() == 0.0 && (id as usize) < segments) {
                return Err(ObsRowError::SegmentId { slot, id, segments });
            }
        }
        Ok(())
    }
}

/// An observation row from outside that [`ObsSpec::check_row`] refuses; names the block and slot.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ObsRowError {
    #[error("observation has {got} values; the layout has {want}")]
    Length { got: usize, want: usize },
    #[error("{block}[{slot}] is {value}; masks are 0 or 1")]
    Mask { block: &'static str, slot: usize, value: f32 },
    #[error("seg_id[{slot}] is {id}; the map has {segments} segments")]
    SegmentId { slot: usize, id: f32, segments: usize },
}

/// Map polylines cut into pieces of `points` points (consecutive pieces share an end point),
/// each with its shape expressed in its own frame (first point, first heading).
#[derive(Clone, Debug)]
pub struct MapSegments {
    pub points: usize,
    /// Per piece: its frame in world coordinates.
    pub frames: Vec<Frame>,
    pub centres: Vec<P2>,
    pub radii_m: Vec<f32>,
    pub kinds: Vec<PolyKind>,
    pub widths_m: Vec<f32>,
    /// Per piece: `points` world points (padded by repeating the last) and their count.
    pub world: Vec<P2>,
    pub world_headings: Vec<f32>,
    pub counts: Vec<usize>,
    /// Shape features in the piece's own frame, `[pieces, points, 5]`, and mask `[pieces, points]`.
    pub local_feats: Vec<f32>,
    pub local_mask: Vec<f32>,
}

impl MapSegments {
    pub fn build(map: &Map, points: usize) -> Self {
        let mut s = Self {
            points,
            frames: vec![],
            centres: vec![],
            radii_m: vec![],
            kinds: vec![],
            widths_m: vec![],
            world: vec![],
            world_headings: vec![],
            counts: vec![],
            local_feats: vec![],
            local_mask: vec![],
        };
        for (kind, poly, width) in map.static_polylines() {
            let poly = geom::resample(poly, crate::map::POINT_SPACING_M);
            let heads = geom::polyline_headings(&poly);
            let mut start = 0;
            while start + 1 < poly.len() {
                let end = (start + points).min(poly.len());
                let pts = &poly[start..end];
                let hs = &heads[start..end];
                let frame = Frame::new(pts[0], hs[0]);
                let n = pts.len() as f32;
                let centre = [
                    pts.iter().map(|p| p[0]).sum::<f32>() / n,
                    pts.iter().map(|p| p[1]).sum::<f32>() / n,
                ];
                let radius = pts.iter().map(|p| geom::dist(*p, centre)).fold(0.0, f32::max);
                for k in 0..points {
                    let (p, h, valid) = if k < pts.len() {
                        (pts[k], hs[k], 1.0)
                    } else {
                        (pts[pts.len() - 1], hs[pts.len() - 1], 0.0)
                    };
                    s.world.push(p);
                    s.world_headings.push(h);
                    let l = frame.to_local(p);
                    s.local_feats.extend_from_slice(&[
                        valid * l[0] / POS_SCALE_M,
                        valid * l[1] / POS_SCALE_M,
                        valid * frame.angle_to_local(h) / PI,
                        valid * width / 5.0,
                        valid * k as f32 / points as f32,
                    ]);
                    s.local_mask.push(valid);
                }
                s.frames.push(frame);
                s.centres.push(centre);
                s.radii_m.push(radius);
                s.kinds.push(kind);
                s.widths_m.push(width);
                s.counts.push(pts.len());
                start = end - 1;
            }
        }
        s
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
}

/// Builds observations for agents of environments on one map with one configuration.
pub struct Observer {
    pub spec: ObsSpec,
    pub cfg: ObsConfig,
    pub segments: Arc<MapSegments>,
    vmax: f32,
    /// Per agent of the current step: own-frame history `[H, 4]` (query-centric sharing).
    own_hist: Vec<f32>,
    cand: Vec<(f32, u32)>,
    pieces: Vec<(f32, u32)>,
    pieces_in_reach: usize,
}

impl Observer {
    pub fn new(map: &Map, sim: &crate::config::SimConfig) -> Self {
        let cfg = sim.obs.clone();
        let points = match cfg.layout {
            Layout::EgoFrame => cfg.polyline_points,
            Layout::QueryCentric => cfg.segment_points,
        };
        Self::with_segments(Arc::new(MapSegments::build(map, points)), sim)
    }

    /// Shares an existing segment store (one per map and piece length).
    pub fn with_segments(segments: Arc<MapSegments>, sim: &crate::config::SimConfig) -> Self {
        let cfg = sim.obs.clone();
        Self {
            spec: ObsSpec::new(&cfg),
            cfg,
            segments,
            vmax: sim.vehicle.max_speed_mps,
            own_hist: Vec::new(),
            cand: Vec::new(),
            pieces: Vec::new(),
            pieces_in_reach: 0,
        }
    }

    /// Computes the per-step data shared by all observers (each agent's own-frame history).
    /// Call once after each reset or step, before [`Observer::write`].
    pub fn prepare(&mut self, env: &Env) {
        let h = self.cfg.history;
        self.own_hist.clear();
        for a in env.agents() {
            let f = a.frame();
            for k in 0..h {
                let st = a.history(h - 1 - k);
                let l = f.to_local([st[0], st[1]]);
                self.own_hist.extend_from_slice(&[
                    l[0] / POS_SCALE_M,
                    l[1] / POS_SCALE_M,
                    f.angle_to_local(st[2]) / PI,
                    st[3] / self.vmax,
                ]);
            }
        }
    }

    /// Writes agent `i`'s observation into `out` (length `spec.len`), overwriting all of it.
    pub fn write(&mut self, env: &Env, i: usize, out: &mut [f32]) {
        assert_eq!(out.len(), self.spec.len, "observation slice has the wrong length");
        assert_eq!(
            self.own_hist.len(),
            env.len() * self.cfg.history * AGENT_FEATS,
            "prepare() must run after each step"
        );
        out.fill(0.0);
        let me = &env.agents()[i];
        let frame = me.frame();
        self.write_ego(env, i, out);
        self.write_neighbours(env, i, &frame, out);
        self.write_route(env, i, &frame, out);
        self.write_map(me.state.pos(), &frame, out);
    }

    /// The ego's own history and context (its SVO, the ego flag).
    fn write_ego(&self, env: &Env, i: usize, out: &mut [f32]) {
        let (spec, cfg) = (&self.spec, &self.cfg);
        let hist_len = cfg.history * AGENT_FEATS;
        out[spec.ego_hist.clone()]
            .copy_from_slice(&self.own_hist[i * hist_len..(i + 1) * hist_len]);
        let ctx = &mut out[spec.ego_ctx.clone()];
        if cfg.svo != SvoVisibility::None {
            ctx[0] = env.agents()[i].svo_deg / 90.0;
        }
        if cfg.ego_flag && i == 0 {
            ctx[1] = 1.0;
        }
    }

    /// The live agents agent `i` observes as neighbours, nearest first (what its observation's
    /// neighbour slots hold, in their order).
    pub fn neighbours(&mut self, env: &Env, i: usize) -> Vec<usize> {
        self.nearest(env, i);
        self.cand.iter().map(|&(_, j)| j as usize).collect()
    }

    /// Fills `cand` with the nearest live agents within the radius of agent `i`, nearest first,
    /// at most the layout's neighbour slots.
    fn nearest(&mut self, env: &Env, i: usize) {
        let agents = env.agents();
        let me = &agents[i];
        let r2 = self.cfg.radius_m * self.cfg.radius_m;
        self.cand.clear();
        for (j, b) in agents.iter().enumerate() {
            if j != i && b.alive {
                let d2 = geom::dist2(me.state.pos(), b.state.pos());
                if d2 <= r2 {
                    self.cand.push((d2, j as u32));
                }
            }
        }
        geom::nearest_first(&mut self.cand, self.spec.neighbours);
    }

    /// Neighbours: the nearest live agents within the radius, their histories, poses relative
    /// to agent `i`, communicated SVO and ego flag.
    fn write_neighbours(&mut self, env: &Env, i: usize, frame: &Frame, out: &mut [f32]) {
        self.nearest(env, i);
        let (spec, cfg) = (&self.spec, &self.cfg);
        let h = cfg.history;
        let hist_len = h * AGENT_FEATS;
        let agents = env.agents();
        for (slot, &(_, j)) in self.cand.iter().enumerate() {
            let j = j as usize;
            let b = &agents[j];
            let hs = spec.agents_hist.start + slot * hist_len;
            match cfg.layout {
                Layout::QueryCentric => out[hs..hs + hist_len]
                    .copy_from_slice(&self.own_hist[j * hist_len..(j + 1) * hist_len]),
                Layout::EgoFrame => {
                    for k in 0..h {
                        let st = b.history(h - 1 - k);
                        let l = frame.to_local([st[0], st[1]]);
                        let o = hs + k * AGENT_FEATS;
                        out[o..o + AGENT_FEATS].copy_from_slice(&[
                            l[0] / POS_SCALE_M,
                            l[1] / POS_SCALE_M,
                            frame.angle_to_local(st[2]) / PI,
                            st[3] / self.vmax,
                        ]);
                    }
                }
            }
            let l = frame.to_local(b.state.pos());
            let dth = frame.angle_to_local(b.state.theta_rad);
            let c = spec.agents_ctx.start + slot * AGENT_CTX;
            out[c..c + 4].copy_from_slice(&[
                l[0] / POS_SCALE_M,
                l[1] / POS_SCALE_M,
                dth.cos(),
                dth.sin(),
            ]);
            if cfg.svo == SvoVisibility::All {
                out[c + 4] = env.communicated_svo_deg(i, j) / 90.0;
            }
            if cfg.ego_flag && j == 0 {
                out[c + 5] = 1.0;
            }
            out[spec.agents_mask.start + slot] = 1.0;
        }
    }

    /// The route ahead of agent `i`: its next points with headings and their rank.
    fn write_route(&self, env: &Env, i: usize, frame: &Frame, out: &mut [f32]) {
        let spec = &self.spec;
        let me = &env.agents()[i];
        let route = &env.map.routes[me.route as usize];
        for k in 0..spec.route_points {
            let idx = me.seg + 1 + k;
            if idx >= route.points.len() {
                break;
            }
            let l = frame.to_local(route.points[idx]);
            let o = spec.route.start + k * ROUTE_FEATS;
            out[o..o + ROUTE_FEATS].copy_from_slice(&[
                l[0] / POS_SCALE_M,
                l[1] / POS_SCALE_M,
                frame.angle_to_local(route.headings[idx]) / PI,
                k as f32 / spec.route_points as f32,
            ]);
            out[spec.route_mask.start + k] = 1.0;
        }
    }

    /// Map pieces whose bounding circle reaches within the radius of `pos`, nearest first: as
    /// segment ids and poses (query-centric) or as points in the observer's frame (ego frame).
    fn write_map(&mut self, pos: P2, frame: &Frame, out: &mut [f32]) {
        let (spec, cfg) = (&self.spec, &self.cfg);
        let r2 = cfg.radius_m * cfg.radius_m;
        let segs = &*self.segments;
        self.pieces.clear();
        for (k, c) in segs.centres.iter().enumerate() {
            let d = geom::dist(pos, *c) - segs.radii_m[k];
            if d <= cfg.radius_m {
                self.pieces.push((d, k as u32));
            }
        }
        self.pieces_in_reach = self.pieces.len();
        geom::nearest_first(&mut self.pieces, spec.map_pieces);
        let p = spec.piece_points;
        for (slot, &(_, k)) in self.pieces.iter().enumerate() {
            let k = k as usize;
            match cfg.layout {
                Layout::QueryCentric => {
                    let f = segs.frames[k];
                    let l = frame.to_local(f.origin);
                    let dth = frame.angle_to_local(f.theta_rad);
                    out[spec.seg_id.start + slot] = k as f32;
                    let o = spec.seg_pose.start + slot * SEG_POSE;
                    out[o..o + SEG_POSE].copy_from_slice(&[
                        l[0] / POS_SCALE_M,
                        l[1] / POS_SCALE_M,
                        dth.cos(),
                        dth.sin(),
                    ]);
                    out[spec.seg_mask.start + slot] = 1.0;
                }
                Layout::EgoFrame => {
                    for q in 0..segs.counts[k] {
                        let w = segs.world[k * p + q];
                        if geom::dist2(w, pos) > r2 {
                            continue;
                        }
                        let l = frame.to_local(w);
                        let o = spec.map.start + (slot * p + q) * MAP_FEATS;
                        out[o..o + MAP_FEATS].copy_from_slice(&[
                            l[0] / POS_SCALE_M,
                            l[1] / POS_SCALE_M,
                            frame.angle_to_local(segs.world_headings[k * p + q]) / PI,
                            segs.widths_m[k] / 5.0,
                            q as f32 / p as f32,
                        ]);
                        out[spec.map_mask.start + slot * p + q] = 1.0;
                    }
                }
            }
        }
    }

    /// How many map pieces were within reach for the last observation written (before the cap).
    pub fn last_pieces_in_reach(&self) -> usize {
        self.pieces_in_reach
    }
}
