//! The observation encoder: DeepSets per polyline, token embeddings, one ego-query attention.

use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::{Device, Int, Tensor, TensorData};
use sf_sim::obs::{MapSegments, AGENT_CTX, EGO_CTX, MAP_FEATS, SEG_POSE};

use crate::batch::{AgentInput, MapInput, ObsBatch, AGENT_IN, STATIC_IN};
use crate::config::{Layout, NetConfig, SvoVisibility};
use crate::layers::{DeepSet, EgoAttention, Init, Mlp, TokenRun};

/// Token types (rows of the type embedding added to keys).
const TYPES: usize = 4;
const T_EGO: i64 = 0;
const T_AGENT: i64 = 1;
const T_ROUTE: i64 = 2;
const T_MAP: i64 = 3;

/// Encodes an observation batch into one feature vector per observation.
#[derive(Module, Debug)]
pub struct Encoder {
    pub agent_set: DeepSet,
    pub static_set: DeepSet,
    pub ego_ctx: Linear,
    pub agent_ctx: Mlp,
    /// Query-centric: the observer-relative pose of a map segment -> token offset.
    pub seg_pose: Mlp,
    /// `[4, D]`, added to keys.
    pub type_emb: Param<Tensor<2>>,
    pub attn: EgoAttention,
    #[module(skip)]
    pub kind: Layout,
    /// `NetConfig::ego_skip`: the output is `(attention + ego token) / 2`.
    #[module(skip)]
    pub ego_skip: bool,
}

/// Map-segment embeddings of one or more maps, computed once per weight version and shared
/// by every observation of the batch (rows of map `k` start at `offsets[k]`).
#[derive(Clone, Debug)]
pub struct SegmentTable {
    /// `[S_total, D]`
    pub emb: Tensor<2>,
    pub offsets: Vec<u32>,
}

/// The raw shape features of maps' segments, ready to encode: `[1, S, P, 5]`, `[1, S, P]`.
#[derive(Clone, Debug)]
pub struct SegmentInput {
    pub feats: Tensor<4>,
    pub mask: Tensor<3>,
    pub offsets: Vec<u32>,
}

impl SegmentInput {
    pub fn new(maps: &[&MapSegments], device: &Device) -> Self {
        let p = maps.first().map_or(1, |m| m.points);
        assert!(maps.iter().all(|m| m.points == p), "all maps use one segment length");
        let mut feats = Vec::new();
        let mut mask = Vec::new();
        let mut offsets = Vec::new();
        let mut s = 0u32;
        for m in maps {
            offsets.push(s);
            feats.extend_from_slice(&m.local_feats);
            mask.extend_from_slice(&m.local_mask);
            s += m.len() as u32;
        }
        let s = s as usize;
        Self {
            feats: Tensor::from_data(TensorData::new(feats, [1, s, p, MAP_FEATS]), device),
            mask: Tensor::from_data(TensorData::new(mask, [1, s, p]), device),
            offsets,
        }
    }
}

impl Encoder {
    pub fn new(cfg: &NetConfig, init: &mut Init, device: &Device) -> Self {
        let (d, hid, phi) = (cfg.d_model, cfg.set_hidden, cfg.phi_layers);
        let pose = |init: &mut Init, d_in: usize| {
            let mut sizes = vec![d_in];
            sizes.extend(std::iter::repeat_n(d, cfg.pose_layers.max(1)));
            init.mlp(&sizes, device)
        };
        let mut type_emb = vec![0f32; TYPES * d];
        for (k, v) in type_emb.iter_mut().enumerate() {
            *v = 0.02 * ((k as f32) * 0.7).sin();
        }
        Self {
            agent_set: DeepSet::new(init, AGENT_IN, hid, d, phi, device),
            static_set: DeepSet::new(init, STATIC_IN, hid, d, phi, device),
            ego_ctx: init.linear(EGO_CTX, d, device),
            agent_ctx: pose(init, AGENT_CTX),
            seg_pose: pose(init, SEG_POSE),
            type_emb: Param::from_tensor(Tensor::from_data(
                TensorData::new(type_emb, [TYPES, d]),
                device,
            )),
            attn: EgoAttention::new(init, d, cfg.heads, device),
            kind: cfg.encoder,
            ego_skip: cfg.ego_skip,
        }
    }

    /// Encodes map segments once: `[S_total, D]`.
    pub fn segment_table(&self, input: &SegmentInput) -> SegmentTable {
        let e = self.static_set.forward(input.feats.clone(), input.mask.clone());
        let [_, s, d] = e.dims();
        SegmentTable { emb: e.reshape([s, d]), offsets: input.offsets.clone() }
    }

    /// `obs -> [B, D]`. Query-centric batches need the segment table of their maps.
    pub fn forward(&self, obs: &ObsBatch, table: Option<&SegmentTable>) -> Tensor<2> {
        let (b, d) = (obs.batch, self.d());
        let [_, n, _] = obs.agents_ctx.dims();
        let (ego_hist, agents_hist) = match &obs.histories {
            AgentInput::PerObservation { ego, agents, vmask } => {
                let ego_mask = Tensor::<3>::ones([b, 1, ego.dims()[2]], &ego.device());
                (
                    self.agent_set.forward(ego.clone(), ego_mask).reshape([b, d]),
                    self.agent_set.forward(agents.clone(), vmask.clone()),
                )
            }
            AgentInput::Shared { hist, vmask, ego_idx, agent_idx } => {
                let u = hist.dims()[1];
                let table = self.agent_set.forward(hist.clone(), vmask.clone()).reshape([u, d]);
                (
                    table.clone().select(0, ego_idx.clone()),
                    table.select(0, agent_idx.clone()).reshape([b, n, d]),
                )
            }
        };
        let ego = ego_hist + self.ego_ctx.forward(obs.ego_ctx.clone());
        let agents = agents_hist + self.agent_ctx.forward(obs.agents_ctx.clone());
        let route = self.static_set.forward(obs.route.clone(), obs.route_mask.clone());
        // Ego, neighbours and route are one run of tokens; query-centric map segments are a
        // second run whose pose MLP's last layer the attention folds (`TokenRun::tail`: it
        // never runs per segment).
        let mut first = vec![ego.clone().reshape([b, 1, d]), agents, route];
        let mut types = vec![T_EGO];
        types.extend(std::iter::repeat_n(T_AGENT, n));
        types.push(T_ROUTE);
        let map_run = match &obs.map {
            MapInput::EgoFrame { pts, mask } => {
                let map = self.static_set.forward(pts.clone(), mask.clone());
                types.extend(std::iter::repeat_n(T_MAP, map.dims()[1]));
                first.push(map);
                None
            }
            MapInput::QueryCentric { ids, pose } => {
                let table = table.expect("a query-centric batch needs its segment table");
                let [_, s, _] = pose.dims();
                let segs = table.emb.clone().select(0, ids.clone()).reshape([b, s, d]);
                let (x, last) = self.seg_pose.split_last(pose.clone());
                let shift = self.type_emb.val().narrow(0, T_MAP as usize, 1).reshape([d]);
                Some(TokenRun {
                    key: segs.clone(),
                    value: segs,
                    tail: Some((x, last)),
                    key_shift: Some(shift),
                })
            }
        };
        let tokens = Tensor::cat(first, 1);
        let t = tokens.dims()[1];
        let types = Tensor::<1, Int>::from_data(TensorData::new(types, [t]), &tokens.device());
        let keys = tokens.clone() + self.type_emb.val().select(0, types).unsqueeze_dim::<3>(0);
        let mut runs = vec![TokenRun { key: keys, value: tokens, tail: None, key_shift: None }];
        runs.extend(map_run);
        let out = self.attn.forward_runs(ego.clone(), runs, obs.pad.clone());
        if self.ego_skip {
            (out + ego).mul_scalar(0.5)
        } else {
            out
        }
    }

    pub fn d(&self) -> usize {
        self.attn.wq.weight.dims()[1]
    }

    /// The encoder of a network trained as `from` (its weights) made to read observations as
    /// `to` (same sizes, more context channels consumed) exactly as it read them before: the
    /// weights that read a context channel `from` did not consume (its input was zero, so they
    /// never learned) are set to zero. A warm start across kinds (a MACAD flow's weights into a
    /// SocialComm job) thereby starts as the source policy, whatever SVOs it is now shown.
    pub fn silence_new_context(mut self, from: &NetConfig, to: &NetConfig) -> Self {
        let own = |n: &NetConfig| n.svo != SvoVisibility::None;
        let all = |n: &NetConfig| n.svo == SvoVisibility::All;
        let new = |seen: fn(&NetConfig) -> bool| !seen(from) && seen(to);
        let flag = !from.ego_flag && to.ego_flag;
        let ego_rows: Vec<usize> =
            [(new(own), 0), (flag, 1)].into_iter().filter(|p| p.0).map(|p| p.1).collect();
        let agent_rows: Vec<usize> =
            [(new(all), 4), (flag, 5)].into_iter().filter(|p| p.0).map(|p| p.1).collect();
        self.ego_ctx.weight = zero_rows(self.ego_ctx.weight, &ego_rows);
        if let Some(first) = self.agent_ctx.layers.first_mut() {
            first.weight = zero_rows(first.weight.clone(), &agent_rows);
        }
        self
    }
}

/// `w: [d_in, d_out]` with the input rows `rows` set to zero.
fn zero_rows(w: Param<Tensor<2>>, rows: &[usize]) -> Param<Tensor<2>> {
    if rows.is_empty() {
        return w;
    }
    w.map(|t| {
        let [_, d_out] = t.dims();
        let (device, learns) = (t.device(), t.is_require_grad());
        // A leaf again: the assignment must not stay in the autodiff graph as the weight's
        // history (the first backward would consume it, the second would find it gone).
        rows.iter()
            .fold(t, |t, &r| {
                t.slice_assign([r..r + 1, 0..d_out], Tensor::zeros([1, d_out], &device))
            })
            .detach()
            .set_require_grad(learns)
    })
}
