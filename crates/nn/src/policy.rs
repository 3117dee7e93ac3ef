//! Actor (tanh-squashed Gaussian), twin critic and adversary, each with its own encoder.

use std::f32::consts::PI;

use burn::module::Module;
use burn::tensor::{Device, Tensor};

use crate::batch::ObsBatch;
use crate::config::NetConfig;
use crate::encoder::{Encoder, SegmentTable};
use crate::layers::{Init, Mlp};

/// Policy: `obs -> (mean, log_std)` of a Gaussian squashed by tanh.
/// The adversary is an actor with `action_dim = 1`.
#[derive(Module, Debug)]
pub struct Actor {
    pub enc: Encoder,
    pub mean: Mlp,
    pub log_std: Mlp,
}

/// Twin Q: `(obs, action) -> (Q1, Q2)`.
#[derive(Module, Debug)]
pub struct Critic {
    pub enc: Encoder,
    pub q1: Mlp,
    pub q2: Mlp,
}

/// `0.5 * (3 tanh(x) - 2)`: log standard deviation in [-2.5, 0.5] (log variance in [-5, 1]).
pub fn squash_log_std(x: Tensor<2>) -> Tensor<2> {
    x.tanh().mul_scalar(1.5).sub_scalar(1.0)
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
pub fn tanh_gaussian_sample(mean: Tensor<2>, log_std: Tensor<2>, eps: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
    let a = (mean + log_std.clone().exp() * eps.clone()).tanh();
    let logp = tanh_gaussian_log_prob(eps, log_std, a.clone());
    (a, logp)
}

impl Actor {
    pub fn new(cfg: &NetConfig, seed: u64, device: &Device) -> Self {
        let mut init = Init::new(seed);
        let (d, h, a) = (cfg.d_model, cfg.head_hidden, cfg.action_dim);
        Self { enc: Encoder::new(cfg, &mut init, device), mean: init.mlp(&[d, h, h, a], device), log_std: init.mlp(&[d, h, h, a], device) }
    }

    /// `obs -> (mean [B, A] in (-1, 1), log_std [B, A])`.
    pub fn dist(&self, obs: &ObsBatch, table: Option<&SegmentTable>) -> (Tensor<2>, Tensor<2>) {
        let f = self.enc.forward(obs, table);
        (self.mean.forward(f.clone()).tanh(), squash_log_std(self.log_std.forward(f)))
    }

    /// Reparameterised sample with standard-normal noise `eps: [B, A]` -> `(a [B, A], logp [B, 1])`.
    pub fn sample(&self, obs: &ObsBatch, table: Option<&SegmentTable>, eps: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let (mean, log_std) = self.dist(obs, table);
        tanh_gaussian_sample(mean, log_std, eps)
    }

    /// The deterministic action `tanh(mean)` `[B, A]` (evaluation).
    pub fn act_mean(&self, obs: &ObsBatch, table: Option<&SegmentTable>) -> Tensor<2> {
        self.dist(obs, table).0.tanh()
    }
}

impl Critic {
    pub fn new(cfg: &NetConfig, seed: u64, device: &Device) -> Self {
        let mut init = Init::new(seed);
        let (d, h, a) = (cfg.d_model, cfg.head_hidden, cfg.action_dim);
        Self { enc: Encoder::new(cfg, &mut init, device), q1: init.mlp(&[d + a, h, h, 1], device), q2: init.mlp(&[d + a, h, h, 1], device) }
    }

    /// Q heads on encoder features `f: [B, D]` and actions `[B, A]` -> `([B, 1], [B, 1])`.
    pub fn heads(&self, f: Tensor<2>, a: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        let x = Tensor::cat(vec![f, a], 1);
        (self.q1.forward(x.clone()), self.q2.forward(x))
    }

    pub fn forward(&self, obs: &ObsBatch, table: Option<&SegmentTable>, a: Tensor<2>) -> (Tensor<2>, Tensor<2>) {
        self.heads(self.enc.forward(obs, table), a)
    }
}
