//! ONNX export of an actor's deterministic action.
//!
//! Owns: the subset of ONNX's protobuf messages a model needs ([`proto`], written from the
//! ONNX IR specification with prost's derive: field numbers and types as in `onnx.proto`), a
//! small graph builder, and [`export_actor`], which writes the same computation as
//! `ObsBatch::from_rows` + `Encoder::forward` + `Actor::act_mean` as ONNX operators (opset 17).
//! Must not: run inference or know where the weights come from (callers hand over an `Actor`).
//!
//! The graph's inputs are the observation blocks of `sf_sim::obs` under their names, with a
//! dynamic batch dimension `batch` (the arrays the Python package's dict observations hold):
//! `ego_hist [B, H, 4]`, `ego_ctx [B, 2]`, `agents_hist [B, N, H, 4]`, `agents_ctx [B, N, 6]`,
//! `agents_mask [B, N]`, `route [B, R, 4]`, `route_mask [B, R]`, then either `map [B, M, P, 5]`
//! and `map_mask [B, M, P]` (ego-frame) or `seg_id [B, S]`, `seg_pose [B, S, 4]`,
//! `seg_mask [B, S]` and `map_id [B]` (int64: the index of the row's scenario in the job's
//! `env.scenarios`; the map segments' embeddings are constants of the graph). Output:
//! `action [B, A]`, `tanh` of the mean.

use burn::nn::Linear;
use prost::Message;
use sf_sim::obs::{ObsSpec, AGENT_CTX, EGO_CTX};
use sf_sim::Layout;

use crate::batch::TIME_SCALE_S;
use crate::config::{NetConfig, SvoVisibility};
use crate::encoder::{Encoder, SegmentTable};
use crate::layers::{DeepSet, Mlp};
use crate::policy::Actor;

/// ONNX IR messages (the fields this exporter writes).
pub mod proto {
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct ModelProto {
        #[prost(int64, tag = "1")]
        pub ir_version: i64,
        #[prost(string, tag = "2")]
        pub producer_name: String,
        #[prost(string, tag = "3")]
        pub producer_version: String,
        #[prost(string, tag = "6")]
        pub doc_string: String,
        #[prost(message, optional, tag = "7")]
        pub graph: Option<GraphProto>,
        #[prost(message, repeated, tag = "8")]
        pub opset_import: Vec<OperatorSetIdProto>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct OperatorSetIdProto {
        #[prost(string, tag = "1")]
        pub domain: String,
        #[prost(int64, tag = "2")]
        pub version: i64,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct GraphProto {
        #[prost(message, repeated, tag = "1")]
        pub node: Vec<NodeProto>,
        #[prost(string, tag = "2")]
        pub name: String,
        #[prost(message, repeated, tag = "5")]
        pub initializer: Vec<TensorProto>,
        #[prost(message, repeated, tag = "11")]
        pub input: Vec<ValueInfoProto>,
        #[prost(message, repeated, tag = "12")]
        pub output: Vec<ValueInfoProto>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct NodeProto {
        #[prost(string, repeated, tag = "1")]
        pub input: Vec<String>,
        #[prost(string, repeated, tag = "2")]
        pub output: Vec<String>,
        #[prost(string, tag = "3")]
        pub name: String,
        #[prost(string, tag = "4")]
        pub op_type: String,
        #[prost(message, repeated, tag = "5")]
        pub attribute: Vec<AttributeProto>,
    }

    /// `type`: 1 FLOAT, 2 INT, 7 INTS.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct AttributeProto {
        #[prost(string, tag = "1")]
        pub name: String,
        #[prost(float, tag = "2")]
        pub f: f32,
        #[prost(int64, tag = "3")]
        pub i: i64,
        #[prost(int64, repeated, tag = "8")]
        pub ints: Vec<i64>,
        #[prost(int32, tag = "20")]
        pub r#type: i32,
    }

    /// `data_type`: 1 FLOAT, 7 INT64, 9 BOOL.
    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TensorProto {
        #[prost(int64, repeated, tag = "1")]
        pub dims: Vec<i64>,
        #[prost(int32, tag = "2")]
        pub data_type: i32,
        #[prost(string, tag = "8")]
        pub name: String,
        #[prost(bytes = "vec", tag = "9")]
        pub raw_data: Vec<u8>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct ValueInfoProto {
        #[prost(string, tag = "1")]
        pub name: String,
        #[prost(message, optional, tag = "2")]
        pub r#type: Option<TypeProto>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TypeProto {
        #[prost(message, optional, tag = "1")]
        pub tensor_type: Option<TensorType>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TensorType {
        #[prost(int32, tag = "1")]
        pub elem_type: i32,
        #[prost(message, optional, tag = "2")]
        pub shape: Option<TensorShapeProto>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct TensorShapeProto {
        #[prost(message, repeated, tag = "1")]
        pub dim: Vec<Dimension>,
    }

    #[derive(Clone, PartialEq, prost::Message)]
    pub struct Dimension {
        #[prost(int64, optional, tag = "1")]
        pub dim_value: Option<i64>,
        #[prost(string, optional, tag = "2")]
        pub dim_param: Option<String>,
    }
}

use proto::*;

const FLOAT: i32 = 1;
const INT64: i32 = 7;
/// ONNX IR version 8 goes with opset 17.
const IR_VERSION: i64 = 8;
pub const OPSET: i64 = 17;

fn floats(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

fn tensor_vec(t: burn::tensor::Tensor<2>) -> Vec<f32> {
    t.into_data().try_to_vec::<f32>().unwrap_or_default()
}

/// Builds a graph node by node; every value gets a fresh name.
#[derive(Default)]
struct Graph {
    nodes: Vec<NodeProto>,
    inits: Vec<TensorProto>,
    inputs: Vec<ValueInfoProto>,
    next: usize,
}

enum Attr {
    Int(i64),
    Ints(Vec<i64>),
}

impl Graph {
    fn fresh(&mut self, what: &str) -> String {
        self.next += 1;
        format!("{what}_{}", self.next)
    }

    fn input(&mut self, name: &str, elem: i32, dims: &[i64]) -> String {
        let dim = std::iter::once(Dimension { dim_value: None, dim_param: Some("batch".into()) })
            .chain(dims.iter().map(|&d| Dimension { dim_value: Some(d), dim_param: None }))
            .collect();
        self.inputs.push(ValueInfoProto {
            name: name.into(),
            r#type: Some(TypeProto {
                tensor_type: Some(TensorType {
                    elem_type: elem,
                    shape: Some(TensorShapeProto { dim }),
                }),
            }),
        });
        name.into()
    }

    fn constant(&mut self, what: &str, dims: &[usize], v: &[f32]) -> String {
        let name = self.fresh(what);
        self.inits.push(TensorProto {
            dims: dims.iter().map(|&d| d as i64).collect(),
            data_type: FLOAT,
            name: name.clone(),
            raw_data: floats(v),
        });
        name
    }

    fn ints(&mut self, what: &str, v: &[i64]) -> String {
        let name = self.fresh(what);
        self.inits.push(TensorProto {
            dims: vec![v.len() as i64],
            data_type: INT64,
            name: name.clone(),
            raw_data: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        });
        name
    }

    fn op(&mut self, op: &str, inputs: &[&str], attrs: Vec<(&str, Attr)>) -> String {
        let out = self.fresh(&op.to_lowercase());
        let attribute = attrs
            .into_iter()
            .map(|(name, a)| match a {
                Attr::Int(i) => {
                    AttributeProto { name: name.into(), i, r#type: 2, ..Default::default() }
                }
                Attr::Ints(ints) => {
                    AttributeProto { name: name.into(), ints, r#type: 7, ..Default::default() }
                }
            })
            .collect();
        self.nodes.push(NodeProto {
            input: inputs.iter().map(|s| s.to_string()).collect(),
            output: vec![out.clone()],
            name: out.clone(),
            op_type: op.into(),
            attribute,
        });
        out
    }

    fn linear(&mut self, l: &Linear, x: &str) -> String {
        let w = l.weight.val();
        let [i, o] = w.dims();
        let w = self.constant("w", &[i, o], &tensor_vec(w));
        let y = self.op("MatMul", &[x, &w], vec![]);
        match &l.bias {
            Some(b) => {
                let b = self.constant("b", &[o], &tensor_vec(b.val().unsqueeze::<2>()));
                self.op("Add", &[&y, &b], vec![])
            }
            None => y,
        }
    }

    /// `Mlp::forward`: ReLU between layers, none after the last.
    fn mlp(&mut self, m: &Mlp, x: &str) -> String {
        let mut x = x.to_string();
        let n = m.layers.len();
        for (i, l) in m.layers.iter().enumerate() {
            x = self.linear(l, &x);
            if i + 1 < n {
                x = self.op("Relu", &[&x], vec![]);
            }
        }
        x
    }

    /// `DeepSet::forward` on `x [B, N, P, F]` with `mask [B, N, P]` (or none: all ones) -> `[B, N, D]`.
    fn deep_set(&mut self, ds: &DeepSet, x: &str, mask: Option<&str>) -> String {
        let mut h = self.mlp(&ds.phi, x);
        if ds.phi.layers.len() == 1 {
            h = self.op("Relu", &[&h], vec![]);
        }
        if let Some(m) = mask {
            let axes = self.ints("axes", &[3]);
            let m4 = self.op("Unsqueeze", &[m, &axes], vec![]);
            h = self.op("Mul", &[&h, &m4], vec![]);
        }
        let axes = self.ints("axes", &[2]);
        let s = self.op("ReduceSum", &[&h, &axes], vec![("keepdims", Attr::Int(0))]);
        self.mlp(&ds.rho, &s)
    }
}

/// What the export needs beside the actor: the layout, the network's input switches, the
/// simulator's decision step and, for the query-centric layout, the segment table of the
/// job's maps (in `env.scenarios` order).
pub struct ExportSpec<'a> {
    pub spec: &'a ObsSpec,
    pub net: &'a NetConfig,
    pub frame_dt_s: f32,
    pub table: Option<&'a SegmentTable>,
    pub producer_version: &'a str,
    pub doc: &'a str,
}

/// The names of the graph's inputs for `spec`'s layout, in order.
pub fn input_names(spec: &ObsSpec) -> Vec<&'static str> {
    let mut v: Vec<&'static str> = spec.blocks().into_iter().map(|(name, _, _)| name).collect();
    if spec.layout == Layout::QueryCentric {
        v.push("map_id");
    }
    v
}

/// What [`export_actor`] cannot export.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum OnnxError {
    /// [`ExportSpec::table`] is `None` for a query-centric layout.
    #[error("a query-centric actor needs its maps' segment table")]
    NoSegmentTable,
}

/// The actor's deterministic action as a serialized ONNX model.
pub fn export_actor(actor: &Actor, x: &ExportSpec) -> Result<Vec<u8>, OnnxError> {
    let spec = x.spec;
    let enc: &Encoder = &actor.enc;
    let mut g = Graph::default();
    let ego_hist = g.input("ego_hist", FLOAT, &[spec.history as i64, 4]);
    let ego_ctx = g.input("ego_ctx", FLOAT, &[EGO_CTX as i64]);
    let agents_hist =
        g.input("agents_hist", FLOAT, &[spec.neighbours as i64, spec.history as i64, 4]);
    let agents_ctx = g.input("agents_ctx", FLOAT, &[spec.neighbours as i64, AGENT_CTX as i64]);
    let agents_mask = g.input("agents_mask", FLOAT, &[spec.neighbours as i64]);
    let route = g.input("route", FLOAT, &[spec.route_points as i64, 4]);
    let route_mask = g.input("route_mask", FLOAT, &[spec.route_points as i64]);

    // Time channel of history frame k: (H - 1 - k) dt / 2.5, as `[H, 1]`.
    let times: Vec<f32> = (0..spec.history)
        .map(|k| (spec.history - 1 - k) as f32 * x.frame_dt_s / TIME_SCALE_S)
        .collect();
    let (tc, zero, a1) = (
        g.constant("time", &[spec.history, 1], &times),
        g.constant("zero", &[], &[0.0]),
        g.ints("axes", &[1]),
    );
    let c = Shared { tc, zero, a1 };
    let ctx_masks = CtxMasks::of(x.net);
    let ego = ego_token(&mut g, enc, &c, &ctx_masks, &ego_hist, &ego_ctx);
    let agents = neighbour_tokens(
        &mut g,
        enc,
        spec,
        &c,
        &ctx_masks,
        &agents_hist,
        &agents_ctx,
        &agents_mask,
    );
    let (route_tok, route_any) = route_token(&mut g, enc, &c, &route, &route_mask);
    let (map_tok, map_any) = map_tokens(&mut g, enc, x, &c)?;

    // Tokens [B, T, D]: ego, neighbours, route, map; keys add the type embedding.
    let d = enc.d();
    let ego3 = g.op("Unsqueeze", &[&ego, &c.a1], vec![]);
    let tokens =
        g.op("Concat", &[&ego3, &agents, &route_tok, &map_tok], vec![("axis", Attr::Int(1))]);
    let t = 1 + spec.neighbours + 1 + spec.map_pieces;
    let type_rows: Vec<f32> = {
        let emb = tensor_vec(enc.type_emb.val());
        let row = |k: usize| emb[k * d..(k + 1) * d].to_vec();
        let mut v = row(0);
        (0..spec.neighbours).for_each(|_| v.extend(row(1)));
        v.extend(row(2));
        (0..spec.map_pieces).for_each(|_| v.extend(row(3)));
        v
    };
    let types = g.constant("type_rows", &[t, d], &type_rows);
    let keys = g.op("Add", &[&tokens, &types], vec![]);

    // Padding: the ego never; a neighbour slot, route or map piece without a valid point.
    let (c0, c1, ax1) = (g.ints("starts", &[0]), g.ints("ends", &[1]), g.ints("axes", &[1]));
    let ego_col = g.op("Slice", &[&agents_mask, &c0, &c1, &ax1], vec![]);
    let one = g.constant("one", &[], &[1.0]);
    let ego_col = g.op("Mul", &[&ego_col, &c.zero], vec![]);
    let ego_col = g.op("Add", &[&ego_col, &one], vec![]);
    let present = g.op(
        "Concat",
        &[&ego_col, &agents_mask, &route_any, &map_any],
        vec![("axis", Attr::Int(1))],
    );
    let pad = g.op("Equal", &[&present, &c.zero], vec![]);

    let feat = attention(&mut g, enc, &c, t, &ego, &tokens, &keys, &pad);
    let mut mean = g.mlp(&actor.mean, &feat);
    if actor.squash_mean_twice {
        mean = g.op("Tanh", &[&mean], vec![]);
    }
    let action = g.op("Tanh", &[&mean], vec![]);
    let out_dim = actor.mean.layers.last().map_or(0, |l| l.weight.dims()[1]) as i64;
    Ok(model(g, action, out_dim, x))
}

/// Values every part of the graph uses: the history's time channel `[H, 1]`, the scalar 0 and
/// the axes list `[1]`.
struct Shared {
    tc: String,
    zero: String,
    a1: String,
}

/// Which context features the network sees (`NetConfig::svo`, `ego_flag`), as 0/1 factors.
struct CtxMasks {
    svo_own: f32,
    svo_all: f32,
    flag: f32,
}

impl CtxMasks {
    fn of(net: &NetConfig) -> Self {
        let on = |b: bool| if b { 1.0 } else { 0.0 };
        Self {
            svo_own: on(net.svo != SvoVisibility::None),
            svo_all: on(net.svo == SvoVisibility::All),
            flag: on(net.ego_flag),
        }
    }
}

/// The ego's token `[B, D]`: its history (every frame valid) through the agent set, plus its
/// context.
fn ego_token(
    g: &mut Graph,
    enc: &Encoder,
    c: &Shared,
    m: &CtxMasks,
    ego_hist: &str,
    ego_ctx: &str,
) -> String {
    // Own history: [B, H, 4] ++ time -> [B, 1, H, 5].
    let (s0, s1, ax) = (g.ints("starts", &[0]), g.ints("ends", &[1]), g.ints("axes", &[2]));
    let first = g.op("Slice", &[ego_hist, &s0, &s1, &ax], vec![]);
    let zeros = g.op("Mul", &[&first, &c.zero], vec![]);
    let tcol = g.op("Add", &[&zeros, &c.tc], vec![]);
    let ego_in = g.op("Concat", &[ego_hist, &tcol], vec![("axis", Attr::Int(-1))]);
    let ego_in = g.op("Unsqueeze", &[&ego_in, &c.a1], vec![]);
    let ego_ds = g.deep_set(&enc.agent_set, &ego_in, None);
    let ego_ds = g.op("Squeeze", &[&ego_ds, &c.a1], vec![]);
    let ego_sel = g.constant("ego_ctx_mask", &[EGO_CTX], &[m.svo_own, m.flag]);
    let ego_ctx = g.op("Mul", &[ego_ctx, &ego_sel], vec![]);
    let ego_ctx = g.linear(&enc.ego_ctx, &ego_ctx);
    g.op("Add", &[&ego_ds, &ego_ctx], vec![])
}

/// The neighbours' tokens `[B, N, D]`: time channel times validity; padding slots masked out
/// of the set sum.
#[allow(clippy::too_many_arguments)]
fn neighbour_tokens(
    g: &mut Graph,
    enc: &Encoder,
    spec: &ObsSpec,
    c: &Shared,
    m: &CtxMasks,
    agents_hist: &str,
    agents_ctx: &str,
    agents_mask: &str,
) -> String {
    let a23 = g.ints("axes", &[2, 3]);
    let valid4 = g.op("Unsqueeze", &[agents_mask, &a23], vec![]);
    let vt = g.op("Mul", &[&valid4, &c.tc], vec![]);
    let agents_in = g.op("Concat", &[agents_hist, &vt], vec![("axis", Attr::Int(-1))]);
    let a2 = g.ints("axes", &[2]);
    let valid3 = g.op("Unsqueeze", &[agents_mask, &a2], vec![]);
    let ones_h = g.constant("ones_h", &[spec.history], &vec![1.0; spec.history]);
    let vmask = g.op("Mul", &[&valid3, &ones_h], vec![]);
    let agents_ds = g.deep_set(&enc.agent_set, &agents_in, Some(&vmask));
    let ag_sel =
        g.constant("agents_ctx_mask", &[AGENT_CTX], &[1.0, 1.0, 1.0, 1.0, m.svo_all, m.flag]);
    let agents_ctx = g.op("Mul", &[agents_ctx, &ag_sel], vec![]);
    let agents_ctx = g.mlp(&enc.agent_ctx, &agents_ctx);
    g.op("Add", &[&agents_ds, &agents_ctx], vec![])
}

/// The route's token `[B, 1, D]` (`[x, y, theta, 0, k]` per point, one polyline) and whether
/// it has a valid point `[B, 1]`.
fn route_token(
    g: &mut Graph,
    enc: &Encoder,
    c: &Shared,
    route: &str,
    route_mask: &str,
) -> (String, String) {
    let pick = g.ints("route_pick", &[0, 1, 2, 0, 3]);
    let route5 = g.op("Gather", &[route, &pick], vec![("axis", Attr::Int(2))]);
    let keep = g.constant("route_keep", &[5], &[1.0, 1.0, 1.0, 0.0, 1.0]);
    let route5 = g.op("Mul", &[&route5, &keep], vec![]);
    let route5 = g.op("Unsqueeze", &[&route5, &c.a1], vec![]);
    let rmask = g.op("Unsqueeze", &[route_mask, &c.a1], vec![]);
    let tok = g.deep_set(&enc.static_set, &route5, Some(&rmask));
    let any = g.op(
        "ReduceMax",
        &[route_mask],
        vec![("axes", Attr::Ints(vec![1])), ("keepdims", Attr::Int(1))],
    );
    (tok, any)
}

/// The map's tokens `[B, M, D]` and their validity `[B, M]`, with the layout's own inputs:
/// ego-frame polylines through the static set, or query-centric segment ids looked up in the
/// maps' segment table (a constant of the graph) plus their embedded poses.
fn map_tokens(
    g: &mut Graph,
    enc: &Encoder,
    x: &ExportSpec,
    c: &Shared,
) -> Result<(String, String), OnnxError> {
    let (m, p) = (x.spec.map_pieces as i64, x.spec.piece_points as i64);
    Ok(match x.spec.layout {
        Layout::EgoFrame => {
            let map = g.input("map", FLOAT, &[m, p, 5]);
            let map_mask = g.input("map_mask", FLOAT, &[m, p]);
            let tok = g.deep_set(&enc.static_set, &map, Some(&map_mask));
            let any = g.op(
                "ReduceMax",
                &[&map_mask],
                vec![("axes", Attr::Ints(vec![2])), ("keepdims", Attr::Int(0))],
            );
            (tok, any)
        }
        Layout::QueryCentric => {
            let table = x.table.ok_or(OnnxError::NoSegmentTable)?;
            let seg_id = g.input("seg_id", FLOAT, &[m]);
            let seg_pose = g.input("seg_pose", FLOAT, &[m, 4]);
            let seg_mask = g.input("seg_mask", FLOAT, &[m]);
            let map_id = g.input("map_id", INT64, &[]);
            let [s_total, _] = table.emb.dims();
            let emb =
                g.constant("segment_table", &[s_total, enc.d()], &tensor_vec(table.emb.clone()));
            let offsets: Vec<i64> = table.offsets.iter().map(|&o| o as i64).collect();
            let offsets = g.ints("map_offsets", &offsets);
            let local = g.op("Mul", &[&seg_id, &seg_mask], vec![]);
            let local = g.op("Cast", &[&local], vec![("to", Attr::Int(INT64 as i64))]);
            let off = g.op("Gather", &[&offsets, &map_id], vec![("axis", Attr::Int(0))]);
            let off = g.op("Unsqueeze", &[&off, &c.a1], vec![]);
            let ids = g.op("Add", &[&local, &off], vec![]);
            let rows = g.op("Gather", &[&emb, &ids], vec![("axis", Attr::Int(0))]);
            let pose = g.mlp(&enc.seg_pose, &seg_pose);
            (g.op("Add", &[&rows, &pose], vec![]), seg_mask)
        }
    })
}

/// The ego's one-query attention over the `t` tokens (`EgoAttention::forward`), padding
/// masked, then the output projection and the ego skip connection: the features `[B, D]`.
#[allow(clippy::too_many_arguments)]
fn attention(
    g: &mut Graph,
    enc: &Encoder,
    c: &Shared,
    t: usize,
    ego: &str,
    tokens: &str,
    keys: &str,
    pad: &str,
) -> String {
    let d = enc.d();
    let heads = enc.attn.heads;
    let dh = d / heads;
    let q = g.linear(&enc.attn.wq, ego);
    let qshape = g.ints("shape", &[-1, 1, heads as i64, dh as i64]);
    let q = g.op("Reshape", &[&q, &qshape], vec![]);
    let scale = g.constant("sqrt_dh", &[], &[(dh as f32).sqrt()]);
    let q = g.op("Div", &[&q, &scale], vec![]);
    let kvshape = g.ints("shape", &[-1, t as i64, heads as i64, dh as i64]);
    let k = g.linear(&enc.attn.wk, keys);
    let k = g.op("Reshape", &[&k, &kvshape], vec![]);
    let v = g.linear(&enc.attn.wv, tokens);
    let v = g.op("Reshape", &[&v, &kvshape], vec![]);
    let kq = g.op("Mul", &[&k, &q], vec![]);
    let a3 = g.ints("axes", &[3]);
    let scores = g.op("ReduceSum", &[&kq, &a3], vec![("keepdims", Attr::Int(1))]);
    let pshape = g.ints("shape", &[-1, t as i64, 1, 1]);
    let pad4 = g.op("Reshape", &[pad, &pshape], vec![]);
    let neg = g.constant("neg", &[], &[-1.0e9]);
    let scores = g.op("Where", &[&pad4, &neg, &scores], vec![]);
    let w = g.op("Softmax", &[&scores], vec![("axis", Attr::Int(1))]);
    let vw = g.op("Mul", &[&v, &w], vec![]);
    let ctx = g.op("ReduceSum", &[&vw, &c.a1], vec![("keepdims", Attr::Int(0))]);
    let cshape = g.ints("shape", &[-1, d as i64]);
    let ctx = g.op("Reshape", &[&ctx, &cshape], vec![]);
    let feat = g.linear(&enc.attn.wo, &ctx);
    if !enc.ego_skip {
        return feat;
    }
    let sum = g.op("Add", &[&feat, ego], vec![]);
    let half = g.constant("half", &[], &[0.5]);
    g.op("Mul", &[&sum, &half], vec![])
}

/// The model around the graph: its one output renamed `action` (`[batch, out_dim]`) through an
/// Identity, so callers can ask for it by name, and the opset.
fn model(g: Graph, action: String, out_dim: i64, x: &ExportSpec) -> Vec<u8> {
    let output = ValueInfoProto {
        name: action,
        r#type: Some(TypeProto {
            tensor_type: Some(TensorType {
                elem_type: FLOAT,
                shape: Some(TensorShapeProto {
                    dim: vec![
                        Dimension { dim_value: None, dim_param: Some("batch".into()) },
                        Dimension { dim_value: Some(out_dim), dim_param: None },
                    ],
                }),
            }),
        }),
    };
    let mut graph = GraphProto {
        node: g.nodes,
        name: "socialflow_actor".into(),
        initializer: g.inits,
        input: g.inputs,
        output: vec![],
    };
    graph.node.push(NodeProto {
        input: vec![output.name.clone()],
        output: vec!["action".into()],
        name: "action".into(),
        op_type: "Identity".into(),
        attribute: vec![],
    });
    graph.output.push(ValueInfoProto { name: "action".into(), ..output });
    let model = ModelProto {
        ir_version: IR_VERSION,
        producer_name: "socialflow".into(),
        producer_version: x.producer_version.into(),
        doc_string: x.doc.into(),
        graph: Some(graph),
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: OPSET }],
    };
    model.encode_to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::encoder::SegmentInput;
    use burn::tensor::Device;
    use sf_sim::obs::MapSegments;

    /// Both layouts export a well-formed graph: inputs named as the observation blocks (and
    /// `map_id`), every node input defined before use, one `action` output of the action width.
    #[test]
    fn exported_graphs_are_well_formed() {
        let dev = Device::flex();
        let map =
            sf_sim::Map::from_file(&sf_sim::scenarios::build("merge").expect("merge"), "merge")
                .expect("map");
        for layout in [Layout::EgoFrame, Layout::QueryCentric] {
            let mut sim = sf_sim::SimConfig::default();
            sim.obs.layout = layout;
            let spec = ObsSpec::new(&sim.obs);
            let net = NetConfig {
                encoder: layout,
                d_model: 16,
                set_hidden: 16,
                head_hidden: 32,
                heads: 2,
                action_dim: 2,
                ..NetConfig::fast()
            };
            let actor = Actor::new(&net, 3, &dev);
            let segs = MapSegments::build(&map, sim.obs.segment_points);
            let table = (layout == Layout::QueryCentric)
                .then(|| actor.enc.segment_table(&SegmentInput::new(&[&segs], &dev)));
            let x = ExportSpec {
                spec: &spec,
                net: &net,
                frame_dt_s: sim.dt_s,
                table: table.as_ref(),
                producer_version: "test",
                doc: "",
            };
            let bytes = export_actor(&actor, &x).expect("export");
            let model = ModelProto::decode(bytes.as_slice()).expect("decodes");
            assert_eq!(model.opset_import[0].version, OPSET);
            let g = model.graph.expect("graph");
            let inputs: Vec<&str> = g.input.iter().map(|i| i.name.as_str()).collect();
            assert_eq!(inputs, input_names(&spec));
            let mut defined: std::collections::HashSet<&str> = inputs
                .iter()
                .copied()
                .chain(g.initializer.iter().map(|t| t.name.as_str()))
                .collect();
            for n in &g.node {
                for i in &n.input {
                    assert!(
                        defined.contains(i.as_str()),
                        "{} reads {i} before it is defined",
                        n.name
                    );
                }
                defined.extend(n.output.iter().map(String::as_str));
            }
            assert_eq!(g.output.len(), 1);
            assert_eq!(g.output[0].name, "action");
            assert!(defined.contains("action"));
            let dims = &g.output[0]
                .r#type
                .as_ref()
                .and_then(|t| t.tensor_type.as_ref())
                .and_then(|t| t.shape.as_ref())
                .expect("shape")
                .dim;
            assert_eq!(dims[1].dim_value, Some(2));
            for t in &g.initializer {
                let n: i64 = t.dims.iter().product();
                let width = if t.data_type == INT64 { 8 } else { 4 };
                assert_eq!(t.raw_data.len() as i64, n * width, "{}: dims {:?}", t.name, t.dims);
            }
        }
    }
}
