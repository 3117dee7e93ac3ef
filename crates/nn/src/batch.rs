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
            Self::PerObservation { ego, agents, .. } => ego.dims()[0] + agents.dims()[0] * agents.dims()[1],
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
    pub fn from_rows(rows: &[f32], spec: &ObsSpec, cfg: &NetConfig, frame_dt_s: f32, map_ids: &[u32], map_offsets: &[u32], histories: Histories, device: &Device) -> Self {
        let b = rows.len() / spec.len;
        assert_eq!(b * spec.len, rows.len(), "rows must be whole observations");
        let (h, n, r, m, p) = (spec.history, spec.neighbours, spec.route_points, spec.map_pieces, spec.piece_points);
        let mut ego = Vec::with_capacity(b * h * AGENT_IN);
        let mut ego_ctx = Vec::with_capacity(b * EGO_CTX);
        let mut agents = Vec::with_capacity(b * n * h * AGENT_IN);
        let mut agents_vmask = Vec::with_capacity(b * n * h);
        let mut agents_ctx = Vec::with_capacity(b * n * AGENT_CTX);
        let mut route = Vec::with_capacity(b * r * STATIC_IN);
        let mut route_mask = Vec::with_capacity(b * r);
        let t = 1 + n + 1 + m;
        let mut pad = Vec::with_capacity(b * t);
        let mut map_pts = Vec::new();
        let mut map_mask = Vec::new();
        let mut ids: Vec<i64> = Vec::new();
        let mut pose = Vec::new();
        let time = |k: usize| (h - 1 - k) as f32 * frame_dt_s / TIME_SCALE_S;
        let svo_own = cfg.svo != SvoVisibility::None;
        let svo_all = cfg.svo == SvoVisibility::All;
        let shared = histories == Histories::Shared;
        let mut table = SharedHistories::default();
        let mut hist = vec![0f32; h * AGENT_IN];
        let mut hist_mask = vec![0f32; h];
        for (bi, row) in rows.chunks_exact(spec.len).enumerate() {
            for k in 0..h {
                hist[k * AGENT_IN..k * AGENT_IN + AGENT_FEATS].copy_from_slice(&row[spec.ego_hist.start + k * AGENT_FEATS..][..AGENT_FEATS]);
                hist[k * AGENT_IN + AGENT_FEATS] = time(k);
            }
            if shared {
                hist_mask.fill(1.0);
                let k = table.index(&hist, &hist_mask);
                table.ego_idx.push(k);
            } else {
                ego.extend_from_slice(&hist);
            }
            let ec = &row[spec.ego_ctx.clone()];
            ego_ctx.extend_from_slice(&[if svo_own { ec[0] } else { 0.0 }, if cfg.ego_flag { ec[1] } else { 0.0 }]);
            pad.push(false);
            for j in 0..n {
                let valid = row[spec.agents_mask.start + j];
                for k in 0..h {
                    hist[k * AGENT_IN..k * AGENT_IN + AGENT_FEATS].copy_from_slice(&row[spec.agents_hist.start + (j * h + k) * AGENT_FEATS..][..AGENT_FEATS]);
                    hist[k * AGENT_IN + AGENT_FEATS] = valid * time(k);
                }
                hist_mask.fill(valid);
                if shared {
                    let k = table.index(&hist, &hist_mask);
                    table.agent_idx.push(k);
                } else {
                    agents.extend_from_slice(&hist);
                    agents_vmask.extend_from_slice(&hist_mask);
                }
                let c = &row[spec.agents_ctx.start + j * AGENT_CTX..][..AGENT_CTX];
                agents_ctx.extend_from_slice(&[c[0], c[1], c[2], c[3], if svo_all { c[4] } else { 0.0 }, if cfg.ego_flag { c[5] } else { 0.0 }]);
                pad.push(valid == 0.0);
            }
            let mut any_route = false;
            for k in 0..r {
                let q = &row[spec.route.start + k * ROUTE_FEATS..][..ROUTE_FEATS];
                route.extend_from_slice(&[q[0], q[1], q[2], 0.0, q[3]]);
                let v = row[spec.route_mask.start + k];
                any_route |= v != 0.0;
                route_mask.push(v);
            }
            pad.push(!any_route);
            match spec.layout {
                Layout::EgoFrame => {
                    map_pts.extend_from_slice(&row[spec.map.clone()]);
                    let mm = &row[spec.map_mask.clone()];
                    map_mask.extend_from_slice(mm);
                    for piece in mm.chunks_exact(p) {
                        pad.push(piece.iter().all(|&v| v == 0.0));
                    }
                }
                Layout::QueryCentric => {
                    let off = map_ids.get(bi).and_then(|&k| map_offsets.get(k as usize)).copied().unwrap_or(0) as i64;
                    for s in 0..m {
                        let valid = row[spec.seg_mask.start + s] != 0.0;
                        ids.push(off + if valid { row[spec.seg_id.start + s] as i64 } else { 0 });
                        pose.extend_from_slice(&row[spec.seg_pose.start + s * SEG_POSE..][..SEG_POSE]);
                        pad.push(!valid);
                    }
                }
            }
        }
        let map = match spec.layout {
            Layout::EgoFrame => MapInput::EgoFrame { pts: tensor(map_pts, [b, m, p, MAP_FEATS], device), mask: tensor(map_mask, [b, m, p], device) },
            Layout::QueryCentric => MapInput::QueryCentric { ids: Tensor::from_data(TensorData::new(ids, [b * m]), device), pose: tensor(pose, [b, m, SEG_POSE], device) },
        };
        let histories = if shared {
            let u = table.ids.len();
            let idx = |v: Vec<i64>| Tensor::<1, Int>::from_data(TensorData::new(v.clone(), [v.len()]), device);
            AgentInput::Shared { hist: tensor(table.hist, [1, u, h, AGENT_IN], device), vmask: tensor(table.vmask, [1, u, h], device), ego_idx: idx(table.ego_idx), agent_idx: idx(table.agent_idx) }
        } else {
            AgentInput::PerObservation { ego: tensor(ego, [b, 1, h, AGENT_IN], device), agents: tensor(agents, [b, n, h, AGENT_IN], device), vmask: tensor(agents_vmask, [b, n, h], device) }
        };
        Self {
            batch: b,
            histories,
            ego_ctx: tensor(ego_ctx, [b, EGO_CTX], device),
            agents_ctx: tensor(agents_ctx, [b, n, AGENT_CTX], device),
            route: tensor(route, [b, 1, r, STATIC_IN], device),
            route_mask: tensor(route_mask, [b, 1, r], device),
            map,
            pad: Tensor::from_data(TensorData::new(pad, [b, t]), device),
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
