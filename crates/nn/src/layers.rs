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
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let (x, last) = self.split_last(x);
        last.forward(x)
    }

    /// Every layer but the last (each with its ReLU), and the last layer: `forward(x)` is
    /// `last.forward(hidden)`. For callers that fold the last, linear layer into what reads
    /// its output ([`TokenRun::tail`]).
    pub fn split_last<const D: usize>(&self, mut x: Tensor<D>) -> (Tensor<D>, &Linear) {
        let (last, first) = self.layers.split_last().expect("an MLP has at least one layer");
        for l in first {
            x = relu(l.forward(x));
        }
        (x, last)
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

/// Tokens that enter the attention together. Keys are `key + tail + key_shift`, values
/// `value + tail`, where `tail = x W + b` is a linear layer every token of the run went through
/// last (e.g. the map segments' pose MLP): the attention folds `W` into the query side, so that
/// layer never runs per token. `key_shift` is one key offset for the whole run (its type
/// embedding).
pub struct TokenRun<'a> {
    /// `[B, T, D]`.
    pub key: Tensor<3>,
    /// `[B, T, D]`.
    pub value: Tensor<3>,
    /// `x: [B, T, K]` and the layer `K -> D` it still has to go through.
    pub tail: Option<(Tensor<3>, &'a Linear)>,
    /// `[D]`.
    pub key_shift: Option<Tensor<1>>,
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
    pub fn forward(
        &self,
        query: Tensor<2>,
        keys: Tensor<3>,
        values: Tensor<3>,
        pad: Tensor<2, Bool>,
    ) -> Tensor<2> {
        let run = TokenRun { key: keys, value: values, tail: None, key_shift: None };
        self.forward_runs(query, vec![run], pad)
    }

    /// The same over runs of tokens, concatenated along `T` in order (`pad` covers them all).
    ///
    /// With a single query the key and value projections need not run on every token: per head
    /// `h`, `(Wk x + bk)_h . q_h = x . (Wk_h q_h) + bk_h . q_h`, and the bias term is the same for
    /// every token, which the softmax ignores; the weights sum to one over the tokens, so
    /// `sum_t w_t (Wv x_t + bv)_h = Wv_h (sum_t w_t x_t) + bv_h`. The query is projected
    /// into token space (`[B, D, H]`), scored against the raw keys and the raw values averaged
    /// per head before the value projection: `B T H D` multiply-adds each instead of
    /// `B T D^2` per projection (16x fewer at D = 64, 4 heads). The key bias therefore never
    /// reaches the output and takes no gradient (it never mattered: a per-token constant).
    /// A run's `tail` layer `W` folds the same way one step earlier: its tokens are scored
    /// through `W q_h` and averaged before `W`; its bias and the run's key shift are one
    /// score per run (which does matter: runs differ) and one weighted bias per run.
    pub fn forward_runs(
        &self,
        query: Tensor<2>,
        runs: Vec<TokenRun<'_>>,
        pad: Tensor<2, Bool>,
    ) -> Tensor<2> {
        let [b, d] = query.dims();
        let h = self.heads;
        let dh = d / h;
        // [B, D] -> [H, B, dh], scaled.
        let q = self
            .wq
            .forward(query)
            .div_scalar((dh as f32).sqrt())
            .reshape([b, h, dh])
            .swap_dims(0, 1);
        // Wk [D, D] -> per head [H, dh, D]; the query in token space: [H, B, D] -> [B, D, H].
        let wk = self.wk.weight.val().reshape([d, h, dh]).swap_dims(0, 1).swap_dims(1, 2);
        let qk = q.matmul(wk).swap_dims(0, 1).swap_dims(1, 2);
        let mut scores = Vec::with_capacity(runs.len());
        for run in &runs {
            let mut s = run.key.clone().matmul(qk.clone()); // [B, T_run, H]
            let mut shift = run.key_shift.clone();
            if let Some((x, layer)) = &run.tail {
                let k = x.dims()[2];
                // W q_h per observation and head: [K, D] x [D, B H] -> [B, K, H].
                let wq = layer
                    .weight
                    .val()
                    .matmul(qk.clone().swap_dims(0, 1).reshape([d, b * h]))
                    .reshape([k, b, h])
                    .swap_dims(0, 1);
                s = s + x.clone().matmul(wq);
                if let Some(bias) = &layer.bias {
                    shift = Some(shift.map_or_else(|| bias.val(), |c| c + bias.val()));
                }
            }
            if let Some(c) = shift {
                // One score per observation and head for the whole run: [B, 1, H].
                s = s + (qk.clone() * c.reshape([1, d, 1])).sum_dim(1);
            }
            scores.push(s);
        }
        let lens: Vec<usize> = runs.iter().map(|r| r.key.dims()[1]).collect();
        let t = lens.iter().sum();
        let scores = Tensor::cat(scores, 1).mask_fill(pad.reshape([b, t, 1]), -1.0e9);
        let w = softmax(scores, 1).swap_dims(1, 2); // [B, H, T]
        let ws = if runs.len() == 1 { vec![w] } else { w.split_with_sizes(lens, 2) };
        // Per head, the weighted mean of the raw values (and of each tail before its layer):
        // [B, H, T] x [B, T, D] -> [B, H, D].
        let mut mean: Option<Tensor<3>> = None;
        for (run, w) in runs.into_iter().zip(ws) {
            let mut m = w.clone().matmul(run.value);
            if let Some((x, layer)) = run.tail {
                let k = x.dims()[2];
                let xm = w.clone().matmul(x).reshape([b * h, k]); // [B H, K]
                m = m + xm.matmul(layer.weight.val()).reshape([b, h, d]);
                if let Some(bias) = &layer.bias {
                    let total = w.sum_dim(2).reshape([b * h, 1]);
                    m = m + total.matmul(bias.val().reshape([1, d])).reshape([b, h, d]);
                }
            }
            mean = Some(match mean {
                Some(a) => a + m,
                None => m,
            });
        }
        let mean = mean.expect("at least one run of tokens");
        // Through each head's slice of Wv: [H, B, D] x [H, D, dh] -> [H, B, dh] -> [B, D].
        let wv = self.wv.weight.val().reshape([d, h, dh]).swap_dims(0, 1);
        let ctx = mean.swap_dims(0, 1).matmul(wv).swap_dims(0, 1).reshape([b, d]);
        let ctx = match &self.wv.bias {
            Some(bv) => ctx + bv.val().unsqueeze_dim::<2>(0),
            None => ctx,
        };
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

    /// The attention as it was written before the projections were moved off the tokens:
    /// keys and values projected per token, products broadcast per head.
    fn projected_attention(
        att: &EgoAttention,
        query: Tensor<2>,
        keys: Tensor<3>,
        values: Tensor<3>,
        pad: Tensor<2, Bool>,
    ) -> Tensor<2> {
        let [b, t, d] = keys.dims();
        let (h, dh) = (att.heads, d / att.heads);
        let q = att.wq.forward(query).reshape([b, 1, h, dh]).div_scalar((dh as f32).sqrt());
        let k = att.wk.forward(keys).reshape([b, t, h, dh]);
        let v = att.wv.forward(values).reshape([b, t, h, dh]);
        let scores = (k * q).sum_dim(3).mask_fill(pad.reshape([b, t, 1, 1]), -1.0e9);
        let w = softmax(scores, 1);
        att.wo.forward((v * w).sum_dim(1).reshape([b, d]))
    }

    fn close(a: Tensor<2>, b: Tensor<2>, tol: f32, what: &str) {
        let (a, b): (Vec<f32>, Vec<f32>) =
            (a.into_data().try_to_vec().expect("f32"), b.into_data().try_to_vec().expect("f32"));
        let scale = b.iter().fold(1e-3f32, |m, x| m.max(x.abs()));
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= tol * scale, "{what}: {x} vs {y} (scale {scale})");
        }
    }

    /// Same outputs and the same gradients as the per-token projections, padding included,
    /// with non-trivial biases: of the inputs and of all four weight matrices, and for a second
    /// run of tokens with a folded tail layer and a key shift, of the tail's input, weight and
    /// bias and of the shift.
    #[test]
    fn attention_matches_the_per_token_projections_with_gradients() {
        use burn::tensor::Distribution;
        let dev = Device::flex().autodiff();
        let mut init = Init::new(9);
        let (b, t0, t1, d, h, k) = (5, 9, 7, 16, 4, 6);
        let mut att = EgoAttention::new(&mut init, d, h, &dev);
        let u = Distribution::Uniform(-1.0, 1.0);
        let mut tail = init.linear(k, d, &dev);
        for l in [&mut att.wq, &mut att.wk, &mut att.wv, &mut att.wo, &mut tail] {
            l.bias = Some(Param::from_tensor(Tensor::random([d], u, &dev)));
        }
        let query = Tensor::<2>::random([b, d], u, &dev).require_grad();
        let keys = Tensor::<3>::random([b, t0, d], u, &dev).require_grad();
        let values = Tensor::<3>::random([b, t0, d], u, &dev).require_grad();
        let base = Tensor::<3>::random([b, t1, d], u, &dev).require_grad();
        let x = Tensor::<3>::random([b, t1, k], u, &dev).require_grad();
        let shift = Tensor::<1>::random([d], u, &dev).require_grad();
        let t = t0 + t1;
        let pad: Vec<bool> = (0..b * t).map(|j| j % t != 0 && (j * 7) % 5 == 0).collect();
        let pad = Tensor::<2, Bool>::from_data(TensorData::new(pad, [b, t]), &dev);
        let weights = Tensor::<2>::random([b, d], u, &dev);
        let run = |f: &dyn Fn() -> Tensor<2>| {
            let out = f();
            let grads = (out.clone() * weights.clone()).sum().backward();
            let g2 = |x: &Tensor<2>| x.grad(&grads).expect("grad");
            let g3 = |x: &Tensor<3>| {
                let g = x.grad(&grads).expect("grad");
                let [p, q, r] = g.dims();
                g.reshape([p * q, r])
            };
            let w = |l: &Linear| g2(&l.weight.val());
            let bias = |l: &Linear| {
                let g = l.bias.as_ref().expect("bias").val().grad(&grads).expect("grad");
                g.reshape([1, d])
            };
            [
                out.detach(),
                g2(&query),
                g3(&keys),
                g3(&values),
                g3(&base),
                g3(&x),
                shift.grad(&grads).expect("grad").reshape([1, d]),
                w(&att.wq),
                w(&att.wk),
                w(&att.wv),
                w(&att.wo),
                w(&tail),
                bias(&tail),
            ]
        };
        let new = run(&|| {
            let runs = vec![
                TokenRun { key: keys.clone(), value: values.clone(), tail: None, key_shift: None },
                TokenRun {
                    key: base.clone(),
                    value: base.clone(),
                    tail: Some((x.clone(), &tail)),
                    key_shift: Some(shift.clone()),
                },
            ];
            att.forward_runs(query.clone(), runs, pad.clone())
        });
        let old = run(&|| {
            let tokens = base.clone() + tail.forward(x.clone());
            let k1 = tokens.clone() + shift.clone().reshape([1, 1, d]);
            let keys = Tensor::cat(vec![keys.clone(), k1], 1);
            let values = Tensor::cat(vec![values.clone(), tokens], 1);
            projected_attention(&att, query.clone(), keys, values, pad.clone())
        });
        let names = [
            "output",
            "d query",
            "d keys",
            "d values",
            "d base",
            "d x",
            "d shift",
            "d wq",
            "d wk",
            "d wv",
            "d wo",
            "d tail",
            "d tail bias",
        ];
        for ((a, b), what) in new.into_iter().zip(old).zip(names) {
            close(a, b, 1e-4, what);
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
