//! The networks' arithmetic, counted from their configuration: FLOPs (2 per multiply-add) of
//! every linear layer and of the attention's two products, per forward pass, by part.
//!
//! Owns: the counting only (what `socialflow bench sac --profile` divides by time for its
//! roofline). Must not: run anything. Elementwise work (activations, masks, masked sums,
//! LayerNorm, softmax, the type embedding, the cat of tokens) is not counted: it is memory-bound and a few percent
//! of the multiply-adds at these widths. Invariant: the layer sizes here are the ones
//! [`crate::Encoder::new`], [`crate::Actor::new`] and [`crate::Critic::new`] build (checked by
//! this module's test against their parameter counts).

use sf_sim::obs::{ObsSpec, AGENT_CTX, EGO_CTX, SEG_POSE};

use crate::batch::{AGENT_IN, STATIC_IN};
use crate::config::{Layout, NetConfig};

/// One part of a forward pass: `rows` inputs through linear layers `layers` (`(d_in, d_out)`
/// each), plus `other_per_row` FLOPs per row that are not a layer (the attention's products).
#[derive(Clone, Debug, PartialEq)]
pub struct Part {
    pub name: &'static str,
    pub rows: usize,
    pub layers: Vec<(usize, usize)>,
    pub other_per_row: u64,
}

impl Part {
    fn new(name: &'static str, rows: usize, sizes: &[usize]) -> Self {
        Self {
            name,
            rows,
            layers: sizes.windows(2).map(|w| (w[0], w[1])).collect(),
            other_per_row: 0,
        }
    }

    /// FLOPs of one row.
    pub fn flops_per_row(&self) -> u64 {
        self.layers.iter().map(|&(i, o)| 2 * (i * o) as u64).sum::<u64>() + self.other_per_row
    }

    pub fn flops(&self) -> u64 {
        self.rows as u64 * self.flops_per_row()
    }
}

/// FLOPs per row and parameters of an MLP through `sizes` (weights and biases).
fn mlp(sizes: &[usize]) -> (u64, u64) {
    sizes
        .windows(2)
        .fold((0, 0), |(f, p), w| (f + 2 * (w[0] * w[1]) as u64, p + (w[0] * w[1] + w[1]) as u64))
}

fn phi_sizes(cfg: &NetConfig, d_in: usize) -> Vec<usize> {
    let mut s = vec![d_in];
    s.extend(std::iter::repeat_n(cfg.set_hidden, cfg.phi_layers.max(1)));
    s
}

fn rho_sizes(cfg: &NetConfig) -> [usize; 4] {
    [cfg.set_hidden, cfg.set_hidden, cfg.set_hidden, cfg.d_model]
}

fn pose_sizes(cfg: &NetConfig, d_in: usize) -> Vec<usize> {
    let mut s = vec![d_in];
    s.extend(std::iter::repeat_n(cfg.d_model, cfg.pose_layers.max(1)));
    s
}

/// Tokens per observation the attention reads: ego, neighbours, route, map pieces.
pub fn tokens(spec: &ObsSpec) -> usize {
    1 + spec.neighbours + 1 + spec.map_pieces
}

/// One encoder forward on `b` observations (histories one copy per observation, as in
/// training batches), without the query-centric segment table ([`segment_table`]).
pub fn encoder(cfg: &NetConfig, spec: &ObsSpec, b: usize) -> Vec<Part> {
    let (d, n, h) = (cfg.d_model, spec.neighbours, spec.history);
    let t = tokens(spec);
    let mut parts = vec![
        Part::new(
            "agent DeepSet phi (per history vector)",
            b * (1 + n) * h,
            &phi_sizes(cfg, AGENT_IN),
        ),
        Part::new("agent DeepSet rho", b * (1 + n), &rho_sizes(cfg)),
        Part::new(
            "route DeepSet phi (per point)",
            b * spec.route_points,
            &phi_sizes(cfg, STATIC_IN),
        ),
        Part::new("route DeepSet rho", b, &rho_sizes(cfg)),
        Part::new("ego context", b, &[EGO_CTX, d]),
        Part::new("agent pose MLP", b * n, &pose_sizes(cfg, AGENT_CTX)),
    ];
    match spec.layout {
        Layout::EgoFrame => {
            parts.push(Part::new(
                "map DeepSet phi (per point)",
                b * spec.map_pieces * spec.piece_points,
                &phi_sizes(cfg, STATIC_IN),
            ));
            parts.push(Part::new("map DeepSet rho", b * spec.map_pieces, &rho_sizes(cfg)));
        }
        Layout::QueryCentric => {
            // The pose MLP's last layer is folded into the attention (`TokenRun::tail`): per
            // segment only the layers before it, and the tail's scores and means (`K H`
            // multiply-adds each); per observation its weight times the query and the means.
            let sizes = pose_sizes(cfg, SEG_POSE);
            let k = sizes[sizes.len() - 2];
            parts.push(Part::new(
                "segment pose MLP but its last layer (per segment)",
                b * spec.map_pieces,
                &sizes[..sizes.len() - 1],
            ));
            parts.push(Part {
                name: "segment pose tail in the attention (per segment)",
                rows: b * spec.map_pieces,
                layers: Vec::new(),
                other_per_row: 2 * 2 * (cfg.heads * k) as u64,
            });
            parts.push(Part {
                name: "segment pose tail in the attention (per observation)",
                rows: b,
                layers: Vec::new(),
                other_per_row: 2 * 2 * (cfg.heads * k * d) as u64,
            });
        }
    }
    // `EgoAttention::forward`: the query, its image through the key projection, the per-head
    // value means through the value projection and the output: four D x D products per
    // observation; per token only the scores and the weighted means (H x D multiply-adds each).
    let projections = Part {
        name: "attention projections (per observation)",
        rows: b,
        layers: vec![(d, d); 4],
        other_per_row: 0,
    };
    let products = Part {
        name: "attention scores, weighted means (per token)",
        rows: b * t,
        layers: Vec::new(),
        other_per_row: 2 * 2 * (cfg.heads * d) as u64,
    };
    parts.extend([projections, products]);
    parts
}

/// The query-centric segment table: `segments` map segments of `points` points.
pub fn segment_table(cfg: &NetConfig, segments: usize, points: usize) -> Vec<Part> {
    vec![
        Part::new("segment table phi (per point)", segments * points, &phi_sizes(cfg, STATIC_IN)),
        Part::new("segment table rho", segments, &rho_sizes(cfg)),
    ]
}

/// The actor's mean and log-std heads on `b` feature rows.
pub fn actor_heads(cfg: &NetConfig, b: usize) -> Part {
    let (d, hh, a) = (cfg.d_model, cfg.head_hidden, cfg.action_dim);
    let mut p = Part::new("actor heads (mean, log-std)", b, &[d, hh, hh, a]);
    p.layers.extend(p.layers.clone());
    p
}

/// The critic's two Q heads on `b` (feature, action) rows.
pub fn critic_heads(cfg: &NetConfig, b: usize) -> Part {
    let (d, hh, a) = (cfg.d_model, cfg.head_hidden, cfg.action_dim);
    let mut p = Part::new("twin Q heads", b, &[d + a, hh, hh, 1]);
    p.layers.extend(p.layers.clone());
    p
}

/// Trainable parameters of the encoder, the actor and the critic (LayerNorms included).
pub fn params(cfg: &NetConfig) -> (u64, u64, u64) {
    let (d, hh, a) = (cfg.d_model, cfg.head_hidden, cfg.action_dim);
    let set = |d_in| mlp(&phi_sizes(cfg, d_in)).1 + mlp(&rho_sizes(cfg)).1;
    let enc = set(AGENT_IN)
        + set(STATIC_IN)
        + mlp(&[EGO_CTX, d]).1
        + mlp(&pose_sizes(cfg, AGENT_CTX)).1
        + mlp(&pose_sizes(cfg, SEG_POSE)).1
        + (4 * d) as u64
        + 4 * mlp(&[d, d]).1;
    let actor = enc + 2 * mlp(&[d, hh, hh, a]).1;
    let norms = if cfg.critic_layer_norm { 2 * (d + 4 * hh) as u64 } else { 0 };
    let critic = enc + 2 * mlp(&[d + a, hh, hh, 1]).1 + norms;
    (enc, actor, critic)
}

#[cfg(test)]
mod tests {
    use burn::module::Module;
    use burn::tensor::Device;

    use super::*;

    /// The counted layer sizes are the built ones: parameter counts agree.
    #[test]
    fn counted_sizes_match_the_built_networks() {
        let dev = Device::flex();
        for cfg in [
            NetConfig::paper(),
            NetConfig::compact(),
            NetConfig::fast(),
            NetConfig { pose_layers: 2, critic_layer_norm: true, ..NetConfig::fast() },
        ] {
            let (enc, actor, critic) = params(&cfg);
            assert_eq!(crate::Actor::new(&cfg, 1, &dev).enc.num_params() as u64, enc);
            assert_eq!(crate::Actor::new(&cfg, 1, &dev).num_params() as u64, actor);
            assert_eq!(crate::Critic::new(&cfg, 2, &dev).num_params() as u64, critic);
        }
    }

    #[test]
    fn a_linear_layer_costs_two_flops_per_multiply_add() {
        assert_eq!(mlp(&[3, 4, 5]), (2 * (12 + 20), 12 + 4 + 20 + 5));
    }
}
