//! The SAC update's tensor helpers: the Huber loss, Polyak averaging, the AWAC-style row weights
//! of the cloning term and columns built from host values.
//!
//! Owns: pure functions of tensors (and modules, for Polyak). Must not: hold training state,
//! draw random numbers or read the SAC config (their callers in [`crate::sac`] pass what they use).

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor, TensorData};

/// AWAC-style row weights `[B, 1]` of the cloning term: `exp((q_data - q_pi) / lambda)`, the
/// critic's advantage of the replayed action over the policy's, clipped at
/// [`sf_job::config::AWAC_MAX_WEIGHT`] and normalised to mean 1 over the batch (so the term's
/// scale does not depend on lambda).
pub fn awac_weights(q_data: Tensor<2>, q_pi: Tensor<2>, lambda: f32) -> Tensor<2> {
    let w = (q_data - q_pi).div_scalar(lambda).exp().clamp_max(sf_job::config::AWAC_MAX_WEIGHT);
    let mean = w.clone().mean().into_scalar::<f32>().max(f32::MIN_POSITIVE);
    w.div_scalar(mean)
}

/// A column `[n, 1]` of `v` on `dev`.
pub(crate) fn column(v: &[f32], dev: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v.to_vec(), [v.len(), 1]), dev)
}

/// Huber loss, mean over the batch: `0.5 d^2` within `delta`, `delta (|d| - delta / 2)` beyond.
pub fn huber(d: Tensor<2>, delta: f32) -> Tensor<1> {
    let ad = d.abs();
    let quad = ad.clone().clamp_max(delta);
    (quad.clone() * (ad - quad.mul_scalar(0.5))).mean()
}

/// Flattened parameter values in visit order.
struct Collect(Vec<Tensor<1>>);

impl ModuleVisitor for Collect {
    fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
        let t = p.val();
        let n = t.shape().num_elements();
        self.0.push(t.reshape([n]));
    }
}

struct Blend {
    src: std::vec::IntoIter<Tensor<1>>,
    tau: f32,
}

impl ModuleMapper for Blend {
    fn map_float<const D: usize>(&mut self, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let s = self.src.next().expect("target and online nets have the same architecture");
        let tau = self.tau;
        p.map(|t| {
            let dims = t.dims();
            t.mul_scalar(1.0 - tau) + s.reshape(dims).mul_scalar(tau)
        })
    }
}

/// `target <- (1 - tau) target + tau online`, parameter by parameter.
pub fn polyak<M: Module>(target: M, online: &M, tau: f32) -> M {
    let mut c = Collect(Vec::new());
    online.visit(&mut c);
    target.map(&mut Blend { src: c.0.into_iter(), tau })
}
