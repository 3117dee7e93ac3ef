//! Building blocks: orthogonally initialised MLPs, the DeepSets polyline encoder and the
//! single-query multi-head attention.

use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::activation::{relu, softmax};
use burn::tensor::{Bool, Device, Tensor, TensorData};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// Seeded source of initial weights, so a network is reproducible from its seed.
pub struct Init {
    rng: ChaCha8Rng,
}

impl Init {
    pub fn new(seed: u64) -> Self {
        Self { rng: ChaCha8Rng::seed_from_u64(seed) }
    }

    /// A linear layer `d_in -> d_out` with orthogonal weights (gain 1) and bias 0.01.
    pub fn linear(&mut self, d_in: usize, d_out: usize, device: &Device) -> Linear {
        let (rows, cols) = (d_in.min(d_out), d_in.max(d_out));
        // `rows` orthonormal vectors of length `cols` (modified Gram-Schmidt).
        let mut v: Vec<Vec<f64>> = Vec::with_capacity(rows);
        while v.len() < rows {
            let mut x: Vec<f64> =
                (0..cols).map(|_| self.rng.sample::<f64, _>(StandardNormal)).collect();
            for u in &v {
                let d: f64 = x.iter().zip(u).map(|(a, b)| a * b).sum();
                x.iter_mut().zip(u).for_each(|(a, b)| *a -= d * b);
            }
            let n = x.iter().map(|a| a * a).sum::<f64>().sqrt();
            if n > 1e-6 {
                v.push(x.into_iter().map(|a| a / n).collect());
            }
        }
        // Weight is [d_in, d_out]; orthonormal along the shorter side.
        let mut w = vec![0f32; d_in * d_out];
        for i in 0..d_in {
            for o in 0..d_out {
                w[i * d_out + o] = if d_in >= d_out { v[o][i] } else { v[i][o] } as f32;
            }
        }
        Linear {
            weight: Param::from_tensor(Tensor::from_data(
                TensorData::new(w, [d_in, d_out]),
                device,
            )),
            bias: Some(Param::from_tensor(Tensor::from_data(
                TensorData::new(vec![0.01f32; d_out], [d_out]),
                device,
            ))),
        }
    }

    /// An MLP through `sizes` with ReLU between layers (none after the last).
    pub fn mlp(&mut self, sizes: &[usize], device: &Device) -> Mlp {
        Mlp { layers: sizes.windows(2).map(|w| self.linear(w[0], w[1], device)).collect() }
    }
}

/// Linear layers with ReLU in between.
#[derive(Module, Debug)]
pub struct Mlp {
    pub layers: Vec<Linear>,
}

impl Mlp {
    /// `[..., d_in] -> [..., d_out]`.
    pub fn forward<const D: usize>(&self, mut x: Tensor<D>) -> Tensor<D> {
        let n = self.layers.len();
        for (i, l) in self.layers.iter().enumerate() {
            x = l.forward(x);
            if i + 1 < n {
                x = relu(x);
            }
        }
        x
    }
}

/// DeepSets over the vectors of each polyline: phi per vector, masked sum, rho.
#[derive(Module, Debug)]
pub struct DeepSet {
    pub phi: Mlp,
    pub rho: Mlp,
}

impl DeepSet {
    /// phi: `d_in -> hidden` then `phi_layers - 1` layers `hidden -> hidden`; rho: 3 layers to `d_out`.
    /// With one phi layer a ReLU follows it before the sum (phi must be non-linear).
    pub fn new(
        init: &mut Init,
        d_in: usize,
        hidden: usize,
        d_out: usize,
        phi_layers: usize,
        device: &Device,
    ) -> Self {
        let mut sizes = vec![d_in];
        sizes.extend(std::iter::repeat_n(hidden, phi_layers.max(1)));
        Self {
            phi: init.mlp(&sizes, device),
            rho: init.mlp(&[hidden, hidden, hidden, d_out], device),
        }
    }

    /// `x: [B, N, P, F]`, `mask: [B, N, P]` (1 valid, 0 padding) -> `[B, N, D]`.
    pub fn forward(&self, x: Tensor<4>, mask: Tensor<3>) -> Tensor<3> {
        let [b, n, p, f] = x.dims();
        let mut h = self.phi.forward(x.reshape([b * n * p, f]));
        if self.phi.layers.len() == 1 {
            h = relu(h);
        }
        let hid = h.dims()[1];
        let h = h.reshape([b, n, p, hid]) * mask.unsqueeze_dim::<4>(3);
        let s = h.sum_dim(2).reshape([b * n, hid]);
        let d = self.rho.layers.last().map_or(hid, |l| l.weight.dims()[1]);
        self.rho.forward(s).reshape([b, n, d])
    }
}

/// Multi-head attention with one query (the ego token) over a padded token set.
#[derive(Module, Debug)]
pub struct EgoAttention {
    pub wq: Linear,
    pub wk: Linear,
    pub wv: Linear,
    pub wo: Linear,
    pub heads: usize,
}

impl EgoAttention {
    pub fn new(init: &mut Init, d: usize, heads: usize, device: &Device) -> Self {
        Self {
            wq: init.linear(d, d, device),
            wk: init.linear(d, d, device),
            wv: init.linear(d, d, device),
            wo: init.linear(d, d, device),
            heads,
        }
    }

    /// `query: [B, D]`, `keys, values: [B, T, D]`, `pad: [B, T]` (true = padding) -> `[B, D]`.
    /// Every row must have at least one valid token (the ego token always is).
    ///
    /// With a single query, scores and the weighted sum are broadcast products summed over the
    /// head width and the tokens, which avoids transposing keys and values into head-major
    /// layout (copies that cost more than the arithmetic here).
    pub fn forward(
        &self,
        query: Tensor<2>,
        keys: Tensor<3>,
        values: Tensor<3>,
        pad: Tensor<2, Bool>,
    ) -> Tensor<2> {
        let [b, t, d] = keys.dims();
        let h = self.heads;
        let dh = d / h;
        let q = self.wq.forward(query).reshape([b, 1, h, dh]).div_scalar((dh as f32).sqrt());
        let k = self.wk.forward(keys).reshape([b, t, h, dh]);
        let v = self.wv.forward(values).reshape([b, t, h, dh]);
        let scores = (k * q).sum_dim(3); // [B, T, H, 1]
        let scores = scores.mask_fill(pad.reshape([b, t, 1, 1]), -1.0e9);
        let w = softmax(scores, 1);
        let ctx = (v * w).sum_dim(1).reshape([b, d]);
        self.wo.forward(ctx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orthogonal_init_is_orthonormal() {
        let dev = Device::flex();
        let mut init = Init::new(1);
        for (i, o) in [(8, 5), (5, 8)] {
            let l = init.linear(i, o, &dev);
            let w: Vec<f32> = l.weight.val().into_data().try_to_vec().expect("f32");
            // Gram matrix along the shorter side is the identity.
            let (short, long) = (i.min(o), i.max(o));
            for a in 0..short {
                for c in 0..short {
                    let dot: f32 = (0..long)
                        .map(|k| {
                            if i >= o {
                                w[k * o + a] * w[k * o + c]
                            } else {
                                w[a * o + k] * w[c * o + k]
                            }
                        })
                        .sum();
                    let want = if a == c { 1.0 } else { 0.0 };
                    assert!((dot - want).abs() < 1e-4, "({a},{c}) = {dot}");
                }
            }
            let bias: Vec<f32> = l.bias.expect("bias").val().into_data().try_to_vec().expect("f32");
            assert!(bias.iter().all(|&x| x == 0.01));
        }
    }

    fn lin(l: &Linear, x: &[f32]) -> Vec<f32> {
        let w: Vec<f32> = l.weight.val().into_data().try_to_vec().expect("f32");
        let bias: Vec<f32> =
            l.bias.as_ref().expect("bias").val().into_data().try_to_vec().expect("f32");
        let (i, o) = (x.len(), bias.len());
        (0..o).map(|c| bias[c] + (0..i).map(|r| x[r] * w[r * o + c]).sum::<f32>()).collect()
    }

    /// The attention against a direct per-head computation in plain Rust.
    #[test]
    fn attention_matches_a_naive_reference() {
        let dev = Device::flex();
        let mut init = Init::new(5);
        let (d, h, t) = (8, 2, 4);
        let att = EgoAttention::new(&mut init, d, h, &dev);
        let qv: Vec<f32> = (0..d).map(|k| (k as f32 * 0.3).cos()).collect();
        let kv: Vec<f32> = (0..t * d).map(|k| (k as f32 * 0.17).sin()).collect();
        let vv: Vec<f32> = (0..t * d).map(|k| (k as f32 * 0.11).cos()).collect();
        let pad = vec![false, false, true, false];
        let got: Vec<f32> = att
            .forward(
                Tensor::from_data(TensorData::new(qv.clone(), [1, d]), &dev),
                Tensor::from_data(TensorData::new(kv.clone(), [1, t, d]), &dev),
                Tensor::from_data(TensorData::new(vv.clone(), [1, t, d]), &dev),
                Tensor::from_data(TensorData::new(pad.clone(), [1, t]), &dev),
            )
            .into_data()
            .try_to_vec()
            .expect("f32");
        let q = lin(&att.wq, &qv);
        let ks: Vec<Vec<f32>> = (0..t).map(|j| lin(&att.wk, &kv[j * d..(j + 1) * d])).collect();
        let vs: Vec<Vec<f32>> = (0..t).map(|j| lin(&att.wv, &vv[j * d..(j + 1) * d])).collect();
        let dh = d / h;
        let mut ctx = vec![0f32; d];
        for head in 0..h {
            let r = head * dh..(head + 1) * dh;
            let sc: Vec<f32> = (0..t)
                .map(|j| {
                    if pad[j] {
                        f32::NEG_INFINITY
                    } else {
                        r.clone().map(|c| q[c] * ks[j][c]).sum::<f32>() / (dh as f32).sqrt()
                    }
                })
                .collect();
            let m = sc.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
            let e: Vec<f32> = sc.iter().map(|s| (s - m).exp()).collect();
            let z: f32 = e.iter().sum();
            for c in r {
                ctx[c] = (0..t).map(|j| e[j] / z * vs[j][c]).sum();
            }
        }
        let want = lin(&att.wo, &ctx);
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5, "{got:?} vs {want:?}");
        }
    }

    #[test]
    fn deepset_ignores_padding_and_attention_ignores_pad_tokens() {
        let dev = Device::flex();
        let mut init = Init::new(2);
        let ds = DeepSet::new(&mut init, 3, 8, 4, 3, &dev);
        let x = Tensor::<4>::from_data(
            TensorData::new((0..24).map(|v| v as f32 * 0.1).collect::<Vec<_>>(), [1, 2, 4, 3]),
            &dev,
        );
        let mask = Tensor::<3>::from_data(
            TensorData::new(vec![1.0f32, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0], [1, 2, 4]),
            &dev,
        );
        let a: Vec<f32> =
            ds.forward(x.clone(), mask.clone()).into_data().try_to_vec().expect("f32");
        // Changing padded vectors changes nothing.
        let x2 = x.clone().slice_assign(
            [0..1, 0..1, 2..4, 0..3],
            Tensor::ones([1, 1, 2, 3], &dev).mul_scalar(9.0),
        );
        let b: Vec<f32> = ds.forward(x2, mask).into_data().try_to_vec().expect("f32");
        assert_eq!(a, b);

        let att = EgoAttention::new(&mut init, 8, 2, &dev);
        let q = Tensor::<2>::ones([1, 8], &dev);
        let keys = Tensor::<3>::from_data(
            TensorData::new((0..24).map(|v| (v as f32).sin()).collect::<Vec<_>>(), [1, 3, 8]),
            &dev,
        );
        let pad =
            Tensor::<2, Bool>::from_data(TensorData::new(vec![false, false, true], [1, 3]), &dev);
        let o1: Vec<f32> = att
            .forward(q.clone(), keys.clone(), keys.clone(), pad.clone())
            .into_data()
            .try_to_vec()
            .expect("f32");
        let keys2 = keys
            .clone()
            .slice_assign([0..1, 2..3, 0..8], Tensor::ones([1, 1, 8], &dev).mul_scalar(5.0));
        let o2: Vec<f32> =
            att.forward(q, keys2.clone(), keys2, pad).into_data().try_to_vec().expect("f32");
        for (x, y) in o1.iter().zip(&o2) {
            assert!((x - y).abs() < 1e-6);
        }
    }
}
