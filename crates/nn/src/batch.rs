//! Observation rows (the `sf_sim::obs` contract) -> the tensors the encoders read.

use burn::tensor::{Bool, Device, Int, Tensor, TensorData};
use sf_sim::obs::{ObsSpec, AGENT_CTX, AGENT_FEATS, EGO_CTX, MAP_FEATS, ROUTE_FEATS, SEG_POSE};
use sf_sim::Layout;

use crate::config::{NetConfig, SvoVisibility};

/// Features per history vector fed to the agent DeepSet: x, y, theta, v, time offset.
pub const AGENT_IN: usize = AGENT_FEATS + 1;
/// Features per static vector (map points and route points): x, y, theta, width, index.
pub const STATIC_IN: usize = MAP_FEATS;
/// Horizon of the time-offset normaliser, seconds (digest: time / 2.5).
pub const TIME_SCALE_S: f32 = 2.5;

/// Map part of a batch.
#[derive(Clone, Debug)]
pub enum MapInput {
    /// `pts: [B, M, P, 5]`, `mask: [B, M, P]`.
    EgoFrame { pts: Tensor<4>, mask: Tensor<3> },
    /// `ids: [B * S]` rows of the map-segment table, `pose: [B, S, 4]`.
    QueryCentric { ids: Tensor<1, Int>, pose: Tensor<3> },
}

/// Agent histories of a batch (the observer's own and its neighbours').
#[derive(Clone, Debug)]
// One value per batch, moved once: boxing the tensors would buy nothing.
#[allow(clippy::large_enum_variant)]
pub enum AgentInput {
    /// Every observation carries its own copies: own history `ego: [B, 1, H, 5]`, neighbours'
    /// `agents: [B, N, H, 5]` with vector mask `vmask: [B, N, H]`.
    PerObservation { ego: Tensor<4>, agents: Tensor<4>, vmask: Tensor<3> },
    /// Each distinct history once (`hist: [1, U, H, 5]`, `vmask: [1, U, H]`), referenced by
    /// row: `ego_idx: [B]` (own history), `agent_idx: [B * N]` (neighbour slots). In the
    /// query-centric layout an agent's history is in its own frame, identical for every
    /// observer of the same step, so a rollout step encodes each agent once instead of once
    /// per observer that sees it.
    Shared { hist: Tensor<4>, vmask: Tensor<3>, ego_idx: Tensor<1, Int>, agent_idx: Tensor<1, Int> },
}

impl AgentInput {
    /// Distinct histories the encoder runs its agent DeepSet on.
    pub fn encoded_histories(&self) -> usize {
        match self {
            Self::PerObservation { ego, agents, .. } => {
                ego.dims()[0] + agents.dims()[0] * agents.dims()[1]
            }
            Self::Shared { hist, .. } => hist.dims()[1],
        }
    }
}

/// Whether [`ObsBatch::from_rows`] gives each distinct agent history one encoding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Histories {
    /// One copy per observation (training batches: rows from different steps share nothing).
    PerObservation,
    /// Identical histories shared (rollout steps in the query-centric layout).
    Shared,
}

/// A batch of observations as tensors. Token order: ego, N agents, route, map pieces.
#[derive(Clone, Debug)]
pub struct ObsBatch {
    pub batch: usize,
    /// Own and neighbours' histories.
    pub histories: AgentInput,
    /// `[B, 2]`: own SVO (if consumed), ego flag (if consumed).
    pub ego_ctx: Tensor<2>,
    /// `[B, N, 6]`: pose in the observer's frame, SVO, ego flag (unconsumed channels zero).
    pub agents_ctx: Tensor<3>,
    /// `[B, 1, R, 5]` and `[B, 1, R]`.
    pub route: Tensor<4>,
    pub route_mask: Tensor<3>,
    pub map: MapInput,
    /// `[B, T]`, true where a token is padding.
    pub pad: Tensor<2, Bool>,
}

fn tensor<const D: usize>(v: Vec<f32>, shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), device)
}

impl ObsBatch {
    /// Builds a batch from `B` flat observation rows. `map_offsets[k]` is the first row of map
    /// `k` in the segment table and `map_ids[b]` the map of row `b` (query-centric only).
    /// `histories`: see [`Histories`]; sharing is exact (histories are compared bit for bit,
    /// time channel and mask included), so it never changes what the network computes.
    #[allow(clippy::too_many_arguments)]
    pub fn from_rows(
        rows: &[f32],
        spec: &ObsSpec,
        cfg: &NetConfig,
        frame_dt_s: f32,
        map_ids: &[u32],
        map_offsets: &[u32],
        histories: Histories,
        device: &Device,
    ) -> Self {
        let b = rows.len() / spec.len;
        assert_eq!(b * spec.len, rows.len(), "rows must be whole observations");
        let mut builder = Builder::new(spec, cfg, frame_dt_s, histories == Histories::Shared, b);
        for (bi, row) in rows.chunks_exact(spec.len).enumerate() {
            builder.ego(row);
            builder.agents(row);
            builder.route(row);
            let map_offset =
                map_ids.get(bi).and_then(|&k| map_offsets.get(k as usize)).copied().unwrap_or(0)
                    as i64;
            builder.map(row, map_offset);
        }
        builder.finish(device)
    }
}

/// [`ObsBatch::from_rows`]'s buffers, filled row by row and token by token (ego, neighbours,
/// route, map pieces, each pushing its padding flags in token order), then made tensors.
struct Builder<'a> {
    spec: &'a ObsSpec,
    cfg: &'a NetConfig,
    frame_dt_s: f32,
    shared: bool,
    batch: usize,
    ego: Vec<f32>,
    ego_ctx: Vec<f32>,
    agents: Vec<f32>,
    agents_vmask: Vec<f32>,
    agents_ctx: Vec<f32>,
    route: Vec<f32>,
    route_mask: Vec<f32>,
    pad: Vec<bool>,
    map_pts: Vec<f32>,
    map_mask: Vec<f32>,
    ids: Vec<i64>,
    pose: Vec<f32>,
    table: SharedHistories,
    /// One history being assembled (features + time channel) and its vector mask.
    hist: Vec<f32>,
    hist_mask: Vec<f32>,
}

impl<'a> Builder<'a> {
    fn new(spec: &'a ObsSpec, cfg: &'a NetConfig, frame_dt_s: f32, shared: bool, b: usize) -> Self {
        let (h, n, r) = (spec.history, spec.neighbours, spec.route_points);
        Self {
            spec,
            cfg,
            frame_dt_s,
            shared,
            batch: b,
            ego: Vec::with_capacity(b * h * AGENT_IN),
            ego_ctx: Vec::with_capacity(b * EGO_CTX),
            agents: Vec::with_capacity(b * n * h * AGENT_IN),
            agents_vmask: Vec::with_capacity(b * n * h),
            agents_ctx: Vec::with_capacity(b * n * AGENT_CTX),
            route: Vec::with_capacity(b * r * STATIC_IN),
            route_mask: Vec::with_capacity(b * r),
            pad: Vec::with_capacity(b * Self::tokens(spec)),
            map_pts: Vec::new(),
            map_mask: Vec::new(),
            ids: Vec::new(),
            pose: Vec::new(),
            table: SharedHistories::default(),
            hist: vec![0f32; h * AGENT_IN],
            hist_mask: vec![0f32; h],
        }
    }

    /// Tokens per observation: ego, neighbours, route, map pieces.
    fn tokens(spec: &ObsSpec) -> usize {
        1 + spec.neighbours + 1 + spec.map_pieces
    }

    /// The time channel of history step `k` (oldest first), normalised.
    fn time(&self, k: usize) -> f32 {
        (self.spec.history - 1 - k) as f32 * self.frame_dt_s / TIME_SCALE_S
    }

    /// `hist[k]`'s features from `src` (step `k` at `src[k * AGENT_FEATS..]`) with its time
    /// channel times `valid`.
    fn load_history(&mut self, src: &[f32], valid: f32) {
        for k in 0..self.spec.history {
            let t = valid * self.time(k);
            self.hist[k * AGENT_IN..k * AGENT_IN + AGENT_FEATS]
                .copy_from_slice(&src[k * AGENT_FEATS..][..AGENT_FEATS]);
            self.hist[k * AGENT_IN + AGENT_FEATS] = t;
        }
    }

    /// The observer's own history and context (unconsumed channels zero).
    fn ego(&mut self, row: &[f32]) {
        let spec = self.spec;
        self.load_history(&row[spec.ego_hist.clone()], 1.0);
        if self.shared {
            self.hist_mask.fill(1.0);
            let k = self.table.index(&self.hist, &self.hist_mask);
            self.table.ego_idx.push(k);
        } else {
            self.ego.extend_from_slice(&self.hist);
        }
        let ec = &row[spec.ego_ctx.clone()];
        let svo_own = self.cfg.svo != SvoVisibility::None;
        self.ego_ctx.extend_from_slice(&[
            if svo_own { ec[0] } else { 0.0 },
            if self.cfg.ego_flag { ec[1] } else { 0.0 },
        ]);
        self.pad.push(false);
    }

    /// Each neighbour slot's history (time channel and mask zero in empty slots) and context.
    fn agents(&mut self, row: &[f32]) {
        let spec = self.spec;
        let h = spec.history;
        let svo_all = self.cfg.svo == SvoVisibility::All;
        for j in 0..spec.neighbours {
            let valid = row[spec.agents_mask.start + j];
            self.load_history(&row[spec.agents_hist.start + j * h * AGENT_FEATS..], valid);
            self.hist_mask.fill(valid);
            if self.shared {
                let k = self.table.index(&self.hist, &self.hist_mask);
                self.table.agent_idx.push(k);
            } else {
                self.agents.extend_from_slice(&self.hist);
                self.agents_vmask.extend_from_slice(&self.hist_mask);
            }
            let c = &row[spec.agents_ctx.start + j * AGENT_CTX..][..AGENT_CTX];
            self.agents_ctx.extend_from_slice(&[
                c[0],
                c[1],
                c[2],
                c[3],
                if svo_all { c[4] } else { 0.0 },
                if self.cfg.ego_flag { c[5] } else { 0.0 },
            ]);
            self.pad.push(valid == 0.0);
        }
    }

    /// The route's points as static vectors (width channel zero); one token, padding when empty.
    fn route(&mut self, row: &[f32]) {
        let spec = self.spec;
        let mut any_route = false;
        for k in 0..spec.route_points {
            let q = &row[spec.route.start + k * ROUTE_FEATS..][..ROUTE_FEATS];
            self.route.extend_from_slice(&[q[0], q[1], q[2], 0.0, q[3]]);
            let v = row[spec.route_mask.start + k];
            any_route |= v != 0.0;
            self.route_mask.push(v);
        }
        self.pad.push(!any_route);
    }

    /// Map pieces: points and masks (ego frame) or segment-table rows offset by the row's map
    /// and poses (query-centric).
    fn map(&mut self, row: &[f32], map_offset: i64) {
        let spec = self.spec;
        match spec.layout {
            Layout::EgoFrame => {
                self.map_pts.extend_from_slice(&row[spec.map.clone()]);
                let mm = &row[spec.map_mask.clone()];
                self.map_mask.extend_from_slice(mm);
                for piece in mm.chunks_exact(spec.piece_points) {
                    self.pad.push(piece.iter().all(|&v| v == 0.0));
                }
            }
            Layout::QueryCentric => {
                for s in 0..spec.map_pieces {
                    let valid = row[spec.seg_mask.start + s] != 0.0;
                    self.ids.push(
                        map_offset + if valid { row[spec.seg_id.start + s] as i64 } else { 0 },
                    );
                    self.pose
                        .extend_from_slice(&row[spec.seg_pose.start + s * SEG_POSE..][..SEG_POSE]);
                    self.pad.push(!valid);
                }
            }
        }
    }

    fn finish(self, device: &Device) -> ObsBatch {
        let spec = self.spec;
        let (b, h, n, r, m, p) = (
            self.batch,
            spec.history,
            spec.neighbours,
            spec.route_points,
            spec.map_pieces,
            spec.piece_points,
        );
        let map = match spec.layout {
            Layout::EgoFrame => MapInput::EgoFrame {
                pts: tensor(self.map_pts, [b, m, p, MAP_FEATS], device),
                mask: tensor(self.map_mask, [b, m, p], device),
            },
            Layout::QueryCentric => MapInput::QueryCentric {
                ids: Tensor::from_data(TensorData::new(self.ids, [b * m]), device),
                pose: tensor(self.pose, [b, m, SEG_POSE], device),
            },
        };
        let histories = if self.shared {
            let table = self.table;
            let u = table.ids.len();
            let idx = |v: Vec<i64>| {
                Tensor::<1, Int>::from_data(TensorData::new(v.clone(), [v.len()]), device)
            };
            AgentInput::Shared {
                hist: tensor(table.hist, [1, u, h, AGENT_IN], device),
                vmask: tensor(table.vmask, [1, u, h], device),
                ego_idx: idx(table.ego_idx),
                agent_idx: idx(table.agent_idx),
            }
        } else {
            AgentInput::PerObservation {
                ego: tensor(self.ego, [b, 1, h, AGENT_IN], device),
                agents: tensor(self.agents, [b, n, h, AGENT_IN], device),
                vmask: tensor(self.agents_vmask, [b, n, h], device),
            }
        };
        ObsBatch {
            batch: b,
            histories,
            ego_ctx: tensor(self.ego_ctx, [b, EGO_CTX], device),
            agents_ctx: tensor(self.agents_ctx, [b, n, AGENT_CTX], device),
            route: tensor(self.route, [b, 1, r, STATIC_IN], device),
            route_mask: tensor(self.route_mask, [b, 1, r], device),
            map,
            pad: Tensor::from_data(TensorData::new(self.pad, [b, Self::tokens(spec)]), device),
        }
    }
}

/// Distinct agent histories of a batch, each stored once, keyed by their exact bits.
#[derive(Default)]
struct SharedHistories {
    ids: std::collections::HashMap<Vec<u32>, i64>,
    hist: Vec<f32>,
    vmask: Vec<f32>,
    ego_idx: Vec<i64>,
    agent_idx: Vec<i64>,
}

impl SharedHistories {
    /// The row of this history (with its mask), added if new.
    fn index(&mut self, hist: &[f32], mask: &[f32]) -> i64 {
        let key: Vec<u32> = hist.iter().chain(mask).map(|x| x.to_bits()).collect();
        let next = self.ids.len() as i64;
        let k = *self.ids.entry(key).or_insert(next);
        if k == next {
            self.hist.extend_from_slice(hist);
            self.vmask.extend_from_slice(mask);
        }
        k
    }
}
