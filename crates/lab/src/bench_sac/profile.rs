//! `socialflow bench sac --profile`: one SAC update against this CPU's limit.
//!
//! Three reports: the update's FLOPs by stage and network part, counted from the network and
//! SAC configs (`sf_nn::cost`); this CPU's f32 FMA peak, measured with a register-only FMA loop
//! on one thread and on every core; and the update's stages timed one by one, beside the time
//! of the same matrix products alone, which bounds what the arithmetic itself costs here.
//!
//! The stages are the update's (`sf_sac::Sac::update`) rebuilt from its public parts on copies
//! of the networks, with their own Adam optimizers, so the timed update itself is untouched:
//! their sum tracks the update's median but is not that measurement.
//!
//! Owns: the roofline report of `--profile`. Must not: touch the networks the benchmark times
//! (it works on copies) or count FLOPs itself (`sf_nn::cost` does).

use std::time::Instant;

use anyhow::Result;
use serde_json::{json, Value};
use sf_nn::burn::module::Module;
use sf_nn::burn::optim::{AdamConfig, GradientsParams};
use sf_nn::burn::tensor::{Device, Distribution, Tensor, TensorData};
use sf_nn::cost::{self, Part};
use sf_nn::encoder::SegmentInput;
use sf_nn::policy::tanh_gaussian_sample;
use sf_nn::{Histories, ObsBatch};
use sf_sac::sac::{polyak, BcTarget, LogAlpha};
use sf_sac::{Batch, Sac};
use sf_sim::obs::MapSegments;

use super::Phase;

/// How a part's FLOPs enter the update: its forward, its backward (about twice the forward:
/// input and weight gradients), or gradients for the input only (the critic heads under the
/// actor's loss: the critic's weights take none).
#[derive(Clone, Copy, Debug)]
enum Pass {
    Forward,
    Backward,
    InputGrad,
}

impl Pass {
    fn factor(self) -> u64 {
        match self {
            Pass::Forward | Pass::InputGrad => 1,
            Pass::Backward => 2,
        }
    }
}

/// One row of the FLOP table.
struct Row {
    stage: &'static str,
    pass: Pass,
    part: Part,
}

impl Row {
    fn flops(&self) -> u64 {
        self.part.flops() * self.pass.factor()
    }
}

/// What one update of `phase` multiplies and adds, as [`Sac::update`] runs it.
fn update_rows(sac: &Sac, segs: &MapSegments, phase: Phase) -> Vec<Row> {
    let (net, spec, b) = (&sac.net, &sac.spec, sac.cfg.batch_size);
    let qc = spec.layout == sf_sim::Layout::QueryCentric;
    let table = || if qc { cost::segment_table(net, segs.len(), segs.points) } else { vec![] };
    let encoder = || table().into_iter().chain(cost::encoder(net, spec, b)).collect::<Vec<_>>();
    let mut rows = Vec::new();
    let mut add = |stage, pass, parts: Vec<Part>| {
        rows.extend(parts.into_iter().map(|part| Row { stage, pass, part }));
    };
    // 1. TD target: the actor on the next observations, the target critic.
    add("target", Pass::Forward, encoder());
    add("target", Pass::Forward, vec![cost::actor_heads(net, b)]);
    add("target", Pass::Forward, encoder());
    add("target", Pass::Forward, vec![cost::critic_heads(net, b)]);
    // 2. Critic step.
    let critic: Vec<Part> = encoder().into_iter().chain([cost::critic_heads(net, b)]).collect();
    add("critic", Pass::Forward, critic.clone());
    add("critic", Pass::Backward, critic);
    if sac.cfg.cql_weight > 0.0 {
        // The conservative term: the actor's samples in the batch's states, both heads on
        // `cql_samples` uniform and as many policy actions per state.
        let n = 2 * sac.cfg.cql_samples * b;
        add(
            "critic",
            Pass::Forward,
            encoder().into_iter().chain([cost::actor_heads(net, b)]).collect(),
        );
        add("critic", Pass::Forward, vec![cost::critic_heads(net, n)]);
        add("critic", Pass::Backward, vec![cost::critic_heads(net, n)]);
    }
    if phase == Phase::Critic {
        return rows;
    }
    // 3. Actor step.
    let cfg = &sac.cfg;
    if !(cfg.reuse_critic_features || cfg.shared_encoder) {
        add("actor", Pass::Forward, encoder());
    }
    let actor: Vec<Part> = if cfg.shared_encoder {
        vec![cost::actor_heads(net, b)]
    } else {
        encoder().into_iter().chain([cost::actor_heads(net, b)]).collect()
    };
    add("actor", Pass::Forward, actor.clone());
    add("actor", Pass::Backward, actor);
    if phase == Phase::Full {
        add("actor", Pass::Forward, vec![cost::critic_heads(net, b)]);
        add("actor", Pass::InputGrad, vec![cost::critic_heads(net, b)]);
        let bc_extra = match cfg.bc_target {
            BcTarget::Replay => cfg.bc_awac_lambda.is_some(),
            BcTarget::Zero | BcTarget::Oracle => cfg.bc_q_filter,
        };
        if bc_weight_now(sac) > 0.0 && bc_extra {
            add("actor", Pass::Forward, vec![cost::critic_heads(net, b)]);
        }
    }
    rows
}

/// The behaviour-cloning term's weight in a full update at this point of the run.
fn bc_weight_now(sac: &Sac) -> f32 {
    let c = &sac.cfg;
    let since = sac.updates.saturating_sub(c.bc_updates + c.critic_pretrain_updates);
    match c.bc_decay_updates {
        0 => c.bc_weight,
        d if since < d => c.bc_weight * (1.0 - since as f32 / d as f32),
        _ => 0.0,
    }
}

/// The FLOP table (rows, per stage, per part) and the totals.
fn flop_report(rows: &[Row], update_s: f64, peak_gflops: f64) -> Value {
    let total: u64 = rows.iter().map(Row::flops).sum();
    let mut by_stage: Vec<(&str, u64)> = Vec::new();
    let mut by_part: Vec<(&str, u64)> = Vec::new();
    for r in rows {
        for (list, key) in [(&mut by_stage, r.stage), (&mut by_part, r.part.name)] {
            match list.iter_mut().find(|(k, _)| *k == key) {
                Some((_, f)) => *f += r.flops(),
                None => list.push((key, r.flops())),
            }
        }
    }
    let share = |f: u64| f as f64 / total.max(1) as f64;
    let table = |list: Vec<(&str, u64)>| -> Vec<Value> {
        list.into_iter()
            .map(|(k, f)| json!({"name": k, "mflops": f as f64 / 1e6, "share": share(f)}))
            .collect()
    };
    let achieved = total as f64 / update_s / 1e9;
    json!({
        "update_gflops": total as f64 / 1e9,
        "achieved_gflops_per_s": achieved,
        "peak_gflops_per_s": peak_gflops,
        "fraction_of_peak": achieved / peak_gflops,
        "by_stage": table(by_stage),
        "by_part": table(by_part),
        "rows": rows.iter().map(|r| json!({
            "stage": r.stage,
            "pass": format!("{:?}", r.pass).to_lowercase(),
            "part": r.part.name,
            "rows": r.part.rows,
            "mflops": r.flops() as f64 / 1e6,
        })).collect::<Vec<_>>(),
    })
}

/// Seconds of CPU time this process has used (every thread).
pub fn process_cpu_s() -> f64 {
    cpu_s(libc::CLOCK_PROCESS_CPUTIME_ID)
}

fn cpu_s(clock: libc::clockid_t) -> f64 {
    let mut t = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `t` is a valid timespec for the call to write into.
    let rc = unsafe { libc::clock_gettime(clock, &mut t) };
    if rc != 0 {
        return f64::NAN;
    }
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// 12 independent chains of 512-bit FMAs on registers: `iters * 12 * 16` FMAs.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn fma_avx512(iters: u64) -> f32 {
    use std::arch::x86_64::*;
    let (m, c) = (_mm512_set1_ps(0.999_999), _mm512_set1_ps(1e-7));
    let mut a = [_mm512_set1_ps(0.0); 12];
    for (i, x) in a.iter_mut().enumerate() {
        *x = _mm512_set1_ps(i as f32);
    }
    for _ in 0..iters {
        for x in a.iter_mut() {
            *x = _mm512_fmadd_ps(*x, m, c);
        }
    }
    a.iter().map(|&x| _mm512_reduce_add_ps(x)).sum()
}

/// The same with 256-bit FMAs: `iters * 12 * 8` FMAs.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn fma_avx2(iters: u64) -> f32 {
    use std::arch::x86_64::*;
    let (m, c) = (_mm256_set1_ps(0.999_999), _mm256_set1_ps(1e-7));
    let mut a = [_mm256_set1_ps(0.0); 12];
    for (i, x) in a.iter_mut().enumerate() {
        *x = _mm256_set1_ps(i as f32);
    }
    for _ in 0..iters {
        for x in a.iter_mut() {
            *x = _mm256_fmadd_ps(*x, m, c);
        }
    }
    let mut out = [0f32; 8];
    a.iter()
        .map(|&x| {
            // SAFETY: `out` holds 8 f32s.
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), x) };
            out.iter().sum::<f32>()
        })
        .sum()
}

/// f32 FMA throughput on `threads` threads at once, GFLOP/s (2 per FMA): by wall time, and
/// per second of each thread's own CPU time (what the core gives while the thread holds it,
/// whatever else the machine runs). `None` without AVX2 and FMA.
fn fma_peak(threads: usize) -> Option<(f64, f64, usize)> {
    #[cfg(target_arch = "x86_64")]
    {
        let wide = std::arch::is_x86_feature_detected!("avx512f");
        let narrow = is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma");
        if !(wide || narrow) {
            return None;
        }
        let iters = 20_000_000u64;
        let lanes = if wide { 16 } else { 8 };
        let run = || {
            let t0 = cpu_s(libc::CLOCK_THREAD_CPUTIME_ID);
            // SAFETY: the features were detected above.
            let s = unsafe {
                if wide {
                    fma_avx512(iters)
                } else {
                    fma_avx2(iters)
                }
            };
            std::hint::black_box(s);
            cpu_s(libc::CLOCK_THREAD_CPUTIME_ID) - t0
        };
        let start = Instant::now();
        let cpu: Vec<f64> = std::thread::scope(|s| {
            let hs: Vec<_> = (0..threads).map(|_| s.spawn(run)).collect();
            hs.into_iter().map(|h| h.join().unwrap_or(f64::NAN)).collect()
        });
        let wall = start.elapsed().as_secs_f64();
        let flops = (2 * iters * 12 * lanes) as f64;
        let per_cpu_s: f64 = cpu.iter().map(|c| flops / c).sum::<f64>() / 1e9;
        Some((flops * threads as f64 / wall / 1e9, per_cpu_s, lanes as usize * 32))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = threads;
        None
    }
}

/// The FMA peak on one thread and on all cores: best of three, wall and per CPU-second.
fn peak_report(cores: usize) -> Value {
    let best = |threads| {
        (0..3)
            .filter_map(|_| fma_peak(threads))
            .fold((0f64, 0f64, 0), |a, b| (a.0.max(b.0), a.1.max(b.1), b.2))
    };
    let (one_wall, one_cpu, bits) = best(1);
    let (all_wall, all_cpu, _) = best(cores);
    json!({
        "vector_bits": bits,
        "one_thread_wall_gflops_per_s": one_wall,
        "one_thread_per_cpu_s_gflops": one_cpu,
        "all_cores": cores,
        "all_cores_wall_gflops_per_s": all_wall,
        "all_cores_per_cpu_s_gflops": all_cpu,
    })
}

/// Seconds per call of `f`, median of `reps` after one untimed call.
fn median_time(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    super::median(&mut t)
}

/// The matrix products of `parts` alone (random operands of the same shapes, plain device):
/// seconds per pass, median of `reps`.
fn matmul_alone(parts: &[Part], reps: usize, dev: &Device) -> f64 {
    let ops: Vec<(Tensor<2>, Tensor<2>)> = parts
        .iter()
        .flat_map(|p| p.layers.iter().map(move |&(i, o)| (p.rows, i, o)))
        .map(|(r, i, o)| {
            let u = Distribution::Uniform(-1.0, 1.0);
            (Tensor::random([r, i], u, dev), Tensor::random([i, o], u, dev))
        })
        .collect();
    median_time(reps, || {
        for (x, w) in &ops {
            std::hint::black_box(x.clone().matmul(w.clone()).into_data());
        }
    })
}

/// Laps of one update's stages.
struct Laps {
    names: Vec<&'static str>,
    times: Vec<Vec<f64>>,
    last: Instant,
    k: usize,
}

impl Laps {
    fn new() -> Self {
        Self { names: Vec::new(), times: Vec::new(), last: Instant::now(), k: 0 }
    }

    fn start(&mut self) {
        self.k = 0;
        self.last = Instant::now();
    }

    fn lap(&mut self, name: &'static str) {
        let t = self.last.elapsed().as_secs_f64();
        if self.k == self.names.len() {
            self.names.push(name);
            self.times.push(Vec::new());
        }
        self.times[self.k].push(t);
        self.k += 1;
        self.last = Instant::now();
    }

    fn report(mut self) -> (Vec<Value>, f64) {
        let mut sum = 0.0;
        let rows = self
            .names
            .iter()
            .zip(self.times.iter_mut())
            .map(|(n, t)| {
                let m = super::median(t);
                sum += m;
                json!({"stage": n, "median_s": m})
            })
            .collect();
        (rows, sum)
    }
}

fn scalar(t: Tensor<1>) -> f32 {
    t.into_scalar::<f32>()
}

/// One update's stages, each timed (median over `reps` after one untimed update), on copies
/// of `sac`'s networks: the critic phase stops after the critic step; the cloning phase's
/// actor step is timed with the full update's loss (its critic heads included).
fn time_stages(sac: &Sac, segs: &MapSegments, batch: &Batch, reps: usize, phase: Phase) -> Value {
    let (net, spec, cfg) = (&sac.net, &sac.spec, &sac.cfg);
    let (plain, ad) = (sac.plain.clone(), sac.ad.clone());
    let qc = spec.layout == sf_sim::Layout::QueryCentric;
    let seg_plain = qc.then(|| SegmentInput::new(&[segs], &plain));
    let seg_ad = qc.then(|| SegmentInput::new(&[segs], &ad));
    let offsets = seg_plain.as_ref().map_or(Vec::new(), |s| s.offsets.clone());
    let rows_on = |rows: &[f32], dev: &Device| {
        let dt = sac.frame_dt_s;
        let ids = &batch.map_ids;
        ObsBatch::from_rows(rows, spec, net, dt, ids, &offsets, Histories::PerObservation, dev)
    };
    let (b, a_dim) = (batch.len(), net.action_dim);
    let noise = |dev: &Device| Tensor::<2>::random([b, a_dim], Distribution::Normal(0.0, 1.0), dev);
    let (mut actor, mut critic, mut target) =
        (sac.actor.clone(), sac.critic.clone(), sac.target.clone());
    let mut log_alpha = LogAlpha { value: sac.log_alpha.value.clone() };
    let (mut opt_c, mut opt_a, mut opt_al) =
        (AdamConfig::new().init(), AdamConfig::new().init(), AdamConfig::new().init());
    let alpha = sac.alpha();
    let mut laps = Laps::new();
    for _ in 0..reps + 1 {
        laps.start();
        let next = rows_on(&batch.next_obs, &plain);
        let obs = rows_on(&batch.obs, &ad);
        laps.lap("rows to tensors (obs on the autodiff device, next obs plain)");
        let (actor_v, critic_v) = (actor.valid(), critic.valid());
        laps.lap("inference copies (valid())");
        let table = seg_plain.as_ref().map(|s| actor_v.enc.segment_table(s));
        let f = actor_v.enc.forward(&next, table.as_ref());
        let (mean, log_std) = actor_v.dist_from_features(f);
        let (a2, logp2) = tanh_gaussian_sample(mean, log_std, noise(&plain));
        let _ = logp2.clone().into_data();
        laps.lap("target: actor encoder + sample (next obs)");
        let table = seg_plain.as_ref().map(|s| target.enc.segment_table(s));
        let (tq1, tq2) = target.forward(&next, table.as_ref(), a2);
        let soft = tq1.min_pair(tq2) - logp2.mul_scalar(alpha);
        let y = Tensor::<2>::from_data(soft.into_data(), &ad);
        laps.lap("target: target critic forward");
        let table = seg_ad.as_ref().map(|s| critic.enc.segment_table(s));
        let f_critic = critic.enc.forward(&obs, table.as_ref());
        let _ = f_critic.clone().into_data();
        laps.lap("critic: encoder forward (autodiff)");
        let features = Tensor::<2>::from_data(f_critic.clone().into_data(), &ad);
        let act = Tensor::<2>::from_data(TensorData::new(batch.actions.clone(), [b, a_dim]), &ad);
        let (q1, q2) = critic.heads(f_critic, act);
        let loss = (q1 - y.clone()).square().mean() + (q2 - y).square().mean();
        let _ = scalar(loss.clone());
        laps.lap("critic: heads + loss");
        let grads = GradientsParams::from_grads(loss.backward(), &critic);
        laps.lap("critic: backward");
        critic = opt_c.step(cfg.lr_critic, critic, grads);
        laps.lap("critic: Adam step");
        if phase != Phase::Critic {
            let fc = if cfg.reuse_critic_features || cfg.shared_encoder {
                features
            } else {
                let obs_plain = rows_on(&batch.obs, &plain);
                let table = seg_plain.as_ref().map(|s| critic_v.enc.segment_table(s));
                Tensor::<2>::from_data(
                    critic_v.enc.forward(&obs_plain, table.as_ref()).into_data(),
                    &ad,
                )
            };
            if cfg.shared_encoder {
                actor.enc = critic.enc.clone();
            }
            let (mean, log_std) = if cfg.shared_encoder {
                actor.dist_from_features(fc.clone())
            } else {
                let table = seg_ad.as_ref().map(|s| actor.enc.segment_table(s));
                actor.dist(&obs, table.as_ref())
            };
            let (a_new, logp) = tanh_gaussian_sample(mean, log_std, noise(&ad));
            let critic_ng = critic.clone().no_grad();
            let (q1, q2) = critic_ng.heads(fc.clone(), a_new);
            let mut loss = (logp.clone().mul_scalar(alpha) - q1.min_pair(q2)).mean();
            if bc_weight_now(sac) > 0.0 {
                let (q1, q2) = critic_ng.heads(fc, Tensor::zeros([b, a_dim], &ad));
                loss = loss + q1.min_pair(q2).detach().mean().mul_scalar(0.0);
            }
            let _ = scalar(loss.clone());
            laps.lap("actor: forward + loss");
            let grads = GradientsParams::from_grads(loss.backward(), &actor);
            laps.lap("actor: backward");
            actor = opt_a.step(cfg.actor_lr(sac.updates), actor, grads);
            laps.lap("actor: Adam step");
            let logp = Tensor::<2>::from_data(logp.into_data(), &ad);
            let loss_al = (log_alpha.value.val().unsqueeze_dim::<2>(0) * logp).mean().neg();
            let grads = GradientsParams::from_grads(loss_al.backward(), &log_alpha);
            log_alpha = opt_al.step(cfg.lr_alpha, log_alpha, grads);
            laps.lap("temperature step");
        }
        target = polyak(target, &critic.valid(), cfg.tau);
        laps.lap("polyak");
    }
    // The first pass warmed up; drop it.
    for t in &mut laps.times {
        t.remove(0);
    }
    let (rows, sum) = laps.report();
    json!({"stages": rows, "stages_sum_s": sum})
}

/// The `--profile` report of `sac` after its timed updates (`update_s`: their median).
pub fn report(
    sac: &Sac,
    segs: &MapSegments,
    batch: &Batch,
    update_s: f64,
    phase: Phase,
) -> Result<Value> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let peak = peak_report(cores);
    let peak_all = peak["all_cores_per_cpu_s_gflops"].as_f64().unwrap_or(f64::NAN);
    let rows = update_rows(sac, segs, phase);
    let flops = flop_report(&rows, update_s, peak_all);
    let reps = 20;
    let stages = time_stages(sac, segs, batch, reps, phase);
    // The arithmetic alone: one encoder forward's and the whole update's matrix products
    // (backward passes as two products of the forward's shapes), at burn's matmul speed.
    let (net, spec, b) = (&sac.net, &sac.spec, sac.cfg.batch_size);
    let mut enc = cost::encoder(net, spec, b);
    if spec.layout == sf_sim::Layout::QueryCentric {
        enc.extend(cost::segment_table(net, segs.len(), segs.points));
    }
    let enc_mm = matmul_alone(&enc, reps, &sac.plain);
    let all_parts: Vec<Part> = rows
        .iter()
        .flat_map(|r| std::iter::repeat_n(r.part.clone(), r.pass.factor() as usize))
        .collect();
    let update_mm = matmul_alone(&all_parts, reps.min(8), &sac.plain);
    let enc_flops: u64 = enc.iter().map(Part::flops).sum();
    let upd_flops: u64 = all_parts.iter().map(Part::flops).sum();
    let (e, c, a) = cost::params(net);
    Ok(json!({
        "fma_peak": peak,
        "flops": flops,
        "timed": stages,
        "matmul_alone": {
            "encoder_forward_s": enc_mm,
            "encoder_forward_gflops_per_s": enc_flops as f64 / enc_mm / 1e9,
            "update_s": update_mm,
            "update_gflops_per_s": upd_flops as f64 / update_mm / 1e9,
            "update_share_of_median": update_mm / update_s,
        },
        "params": {"encoder": e, "actor": a, "critic": c},
        "segments": segs.len(),
        "batch": b,
        "tokens": cost::tokens(spec),
    }))
}

/// The profile as a few lines for people (the JSON carries everything).
pub fn print(p: &Value, update_s: f64) {
    let f = &p["flops"];
    eprintln!(
        "update: {:.3} GFLOP counted, {:.4} s median -> {:.1} GFLOP/s = {:.1}% of the {}-core FMA peak ({:.0} GFLOP/s per CPU-second; {:.0} by wall clock now)",
        f["update_gflops"].as_f64().unwrap_or(0.0),
        update_s,
        f["achieved_gflops_per_s"].as_f64().unwrap_or(0.0),
        100.0 * f["fraction_of_peak"].as_f64().unwrap_or(0.0),
        p["fma_peak"]["all_cores"],
        p["fma_peak"]["all_cores_per_cpu_s_gflops"].as_f64().unwrap_or(0.0),
        p["fma_peak"]["all_cores_wall_gflops_per_s"].as_f64().unwrap_or(0.0),
    );
    for key in ["by_stage", "by_part"] {
        eprintln!("{key}:");
        for r in f[key].as_array().into_iter().flatten() {
            eprintln!(
                "  {:<45} {:>9.1} MFLOP {:>5.1}%",
                r["name"].as_str().unwrap_or(""),
                r["mflops"].as_f64().unwrap_or(0.0),
                100.0 * r["share"].as_f64().unwrap_or(0.0)
            );
        }
    }
    eprintln!("stages timed alone (median):");
    for r in p["timed"]["stages"].as_array().into_iter().flatten() {
        eprintln!(
            "  {:<62} {:>8.2} ms",
            r["stage"].as_str().unwrap_or(""),
            1e3 * r["median_s"].as_f64().unwrap_or(0.0)
        );
    }
    let m = &p["matmul_alone"];
    eprintln!(
        "  sum {:.2} ms; the update's matrix products alone: {:.2} ms ({:.1} GFLOP/s, {:.0}% of the median update)",
        1e3 * p["timed"]["stages_sum_s"].as_f64().unwrap_or(0.0),
        1e3 * m["update_s"].as_f64().unwrap_or(0.0),
        m["update_gflops_per_s"].as_f64().unwrap_or(0.0),
        100.0 * m["update_share_of_median"].as_f64().unwrap_or(0.0),
    );
}
