//! Actor (tanh-squashed Gaussian), twin critic and adversary, each with its own encoder.

use std::f32::consts::PI;

use burn::module::{Module, Param};
use burn::nn::{LayerNorm, LayerNormConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};

use crate::batch::ObsBatch;
use crate::config::{NetConfig, LOG_STD_MAX};
use crate::encoder::{Encoder, SegmentTable};
use crate::layers::{Init, Mlp};

/// Policy: `obs -> (mean, log_std)` of a Gaussian squashed by tanh.
/// The adversary is an actor with `action_dim = 1`.
#[derive(Module, Debug)]
pub struct Actor {
    pub enc: Encoder,
    pub mean: Mlp,
    pub log_std: Mlp,
    /// `NetConfig::squash_mean_twice` (the released code's double tanh).
    #[module(skip)]
    pub squash_mean_twice: bool,
    /// `NetConfig::log_std_min`: the bottom of the log-std range.
    #[module(skip)]
    pub log_std_min: f32,
}

/// Twin Q: `(obs, action) -> (Q1, Q2)`.
#[derive(Module, Debug)]
pub struct Critic {
    pub enc: Encoder,
    pub q1: Mlp,
    pub q2: Mlp,
    /// `NetConfig::critic_layer_norm`: one LayerNorm on the encoder features, then one after
    /// each hidden layer of each head (`[features, q1 hidden.., q2 hidden..]`); empty when off.
    pub norms: Vec<LayerNorm>,
}

/// Half the width and the middle of the log-std range `[min, LOG_STD_MAX]`.
fn log_std_range(min: f32) -> (f32, f32) {
    ((LOG_STD_MAX - min) / 2.0, (LOG_STD_MAX + min) / 2.0)
}

/// `x -> atanh((x - mid) / half)`: the pre-squash value whose [`squash_log_std`] is `x`.
fn unsquash_log_std(x: f32, min: f32) -> f32 {
    let (half, mid) = log_std_range(min);
    let y = ((x - mid) / half).clamp(-0.999, 0.999);
    0.5 * ((1.0 + y) / (1.0 - y)).ln()
}

/// `mid + half tanh(x)`: log standard deviation in `[min, 0.5]`; with the released code's
/// `min = -2.5` that is `0.5 * (3 tanh(x) - 2)` (log variance in [-5, 1]).
pub fn squash_log_std(x: Tensor<2>, min: f32) -> Tensor<2> {
    let (half, mid) = log_std_range(min);
    x.tanh().mul_scalar(half).add_scalar(mid)
}

/// Log-probability `[B, 1]` of `a = tanh(mean + exp(log_std) * eps)`:
/// `sum(-eps^2 / 2 - log_std - log(2 pi) / 2) - sum(log(1 - a^2 + 1e-6))`.
pub fn tanh_gaussian_log_prob(eps: Tensor<2>, log_std: Tensor<2>, a: Tensor<2>) -> Tensor<2> {
    let gauss = eps.square().mul_scalar(-0.5) - log_std - 0.5 * (2.0 * PI).ln();
    let corr = (a.square().neg().add_scalar(1.0 + 1e-6)).log();
    (gauss - corr).sum_dim(1)
}

/// `a = tanh(mean + exp(log_std) * eps)` and its log-probability: `[B, A]` each in,
/// `(a [B, A], logp [B, 1])` out.
pub fn tanh_gaussian_sample(
    mean: Tensor<2>,
    log_std: Tensor<2>,
    eps: Tensor<2>,
) -> (Tensor<2>, Tensor<2>) {
    let a = (mean + log_std.clone().exp() * eps.clone()).tanh();
    let logp = tanh_gaussian_log_prob(eps, log_std, a.clone());
    (a, logp)
}

impl Actor {
    pub fn new(cfg: &NetConfig, seed: u64, device: &Device) -> Self {
        let mut init = Init::new(seed);
        let (d, h, a) = (cfg.d_model, cfg.head_hidden, cfg.action_dim);
        let enc = Encoder::new(cfg, &mut init, device);
        let mean = init.mlp(&[d, h, h, a], device);
        let mut log_std = init.mlp(&[d, h, h, a], device);
        // The first policy's spread: the log-std head's output bias.
        if let Some(last) = log_std.layers.last_mut() {
            let b =
                TensorData::new(vec![unsquash_log_std(cfg.init_log_std, cfg.log_std_min); a], [a]);
            last.bias = Some(Param::from_tensor(Tensor::from_data(b, device)));
        }
        Self {
            enc,
            mean,
            log_std,
            squash_mean_twice: cfg.squash_mean_twice,
            log_std_min: cfg.log_std_min,
        }
    }

    /// `obs -> (mean [B, A] before the sample's tanh, log_std [B, A])`. The mean is unbounded,
    /// or in (-1, 1) with `squash_mean_twice`.
    pub fn dist(&self, obs: &ObsBatch, table: Option<&SegmentTable>) -> (Tensor<2>, Tensor<2>) {
        self.dist_from_features(self.enc.forward(obs, table))
    }

    /// [`Actor::dist`] on encoder features `[B, D]` (another encoder's, when they are shared).
    pub fn dist_from_features(&self, f: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let mean = self.mean.forward(f.clone());
        let mean = if self.squash_mean_twice { mean.tanh() } else { mean };
        (mean, squash_log_std(self.log_std.forward(f), self.log_std_min))
    }

    /// Reparameterised sample with standard-normal noise `eps: [B, A]` -> `(a [B, A], logp [B, 1])`.
    pub fn sample(
        &self,
        obs: &ObsBatch,
        table: Option<&SegmentTable>,
        eps: Tensor<2>,
    ) -> (Tensor<2>, Tensor<2>) {
        let (mean, log_std) = self.dist(obs, table);
        tanh_gaussian_sample(mean, log_std, eps)
    }

    /// The deterministic action `tanh(mean)` `[B, A]` (evaluation).
    pub fn act_mean(&self, obs: &ObsBatch, table: Option<&SegmentTable>) -> Tensor<2> {
        self.dist(obs, table).0.tanh()
    }

    /// This actor read as `to` reads (see [`Encoder::silence_new_context`]).
    pub fn silence_new_context(mut self, from: &NetConfig, to: &NetConfig) -> Self {
        self.enc = self.enc.silence_new_context(from, to);
        self
    }
}

impl Critic {
    pub fn new(cfg: &NetConfig, seed: u64, device: &Device) -> Self {
        let mut init = Init::new(seed);
        let (d, h, a) = (cfg.d_model, cfg.head_hidden, cfg.action_dim);
        let enc = Encoder::new(cfg, &mut init, device);
        let (q1, q2) = (init.mlp(&[d + a, h, h, 1], device), init.mlp(&[d + a, h, h, 1], device));
        let norms = if cfg.critic_layer_norm {
            std::iter::once(d)
                .chain(std::iter::repeat_n(h, 4))
                .map(|w| LayerNormConfig::new(w).init(device))
                .collect()
        } else {
            Vec::new()
        };
        Self { enc, q1, q2, norms }
    }

    /// This critic read as `to` reads (see [`Encoder::silence_new_context`]).
    pub fn silence_new_context(mut self, from: &NetConfig, to: &NetConfig) -> Self {
        self.enc = self.enc.silence_new_context(from, to);
        self
    }

    /// One Q head, with LayerNorm after each hidden layer (`norms`, one per hidden layer) or not.
    fn head(q: &Mlp, norms: &[LayerNorm], mut x: Tensor<2>) -> Tensor<2> {
        if norms.is_empty() {
            return q.forward(x);
        }
        let n = q.layers.len();
        for (i, l) in q.layers.iter().enumerate() {
            x = l.forward(x);
            if i + 1 < n {
                x = relu(norms[i].forward(x));
            }
        }
        x
    }

    /// Q heads on encoder features `f: [B, D]` and actions `[B, A]` -> `([B, 1], [B, 1])`.
    pub fn heads(&self, f: Tensor<2>, a: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let f = match self.norms.first() {
            Some(ln) => ln.forward(f),
            None => f,
        };
        let x = Tensor::cat(vec![f, a], 1);
        let hidden = self.q1.layers.len().saturating_sub(1);
        let (n1, n2) = if self.norms.is_empty() {
            (&[][..], &[][..])
        } else {
            self.norms[1..].split_at(hidden)
        };
        (Self::head(&self.q1, n1, x.clone()), Self::head(&self.q2, n2, x))
    }

    pub fn forward(
        &self,
        obs: &ObsBatch,
        table: Option<&SegmentTable>,
        a: Tensor<2>,
    ) -> (Tensor<2>, Tensor<2>) {
        self.heads(self.enc.forward(obs, table), a)
    }
}
