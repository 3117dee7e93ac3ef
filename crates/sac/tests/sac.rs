//! SAC correctness: log-probability, update semantics, frozen modules, checkpoint exactness.

use std::sync::Arc;

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Tensor, TensorData};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sf_nn::policy::tanh_gaussian_log_prob;
use sf_nn::NetConfig;
use sf_sac::{checkpoint, Batch, Replay, Sac, SacConfig, Transition};
use sf_sim::obs::MapSegments;
use sf_sim::policy::route_follower;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Map, Mode, SimConfig};

fn tiny_net() -> NetConfig {
    NetConfig { d_model: 16, set_hidden: 16, head_hidden: 32, heads: 2, ..NetConfig::fast() }
}

fn map() -> Arc<Map> {
    let p = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../configs/scenarios/merge.json");
    Arc::new(Map::load(&p).expect("merge loads"))
}

/// A replay filled from real simulator rollouts (route follower with noise).
fn replay_from_sim(sim: &Arc<SimConfig>, n: usize) -> (Replay, Arc<Map>) {
    let m = map();
    let mut v = VecEnv::new(
        m.clone(),
        sim.clone(),
        VecEnvConfig { n_envs: 2, mode: Mode::MultiAgent, vehicles: (6, 10), seed: 3 },
    );
    let spec = v.spec.clone();
    let mut r = Replay::new(10_000, spec.len, 2);
    let mut acts = vec![Action::default(); v.alive().len()];
    while r.len() < n {
        let before = v.observations().to_vec();
        let alive = v.alive().to_vec();
        for (i, a) in acts.iter_mut().enumerate() {
            *a = route_follower(
                &spec,
                &before[i * spec.len..(i + 1) * spec.len],
                &sim.vehicle,
                2,
                0.5,
            );
        }
        v.step(&acts);
        for i in 0..alive.len() {
            if alive[i] == 1.0 {
                let next = &v.observations()[i * spec.len..(i + 1) * spec.len];
                let a = [acts[i].ref_speed, acts[i].steer];
                r.push(Transition {
                    obs: &before[i * spec.len..(i + 1) * spec.len],
                    action: &a,
                    reward: 0.1,
                    next_obs: next,
                    terminal: false,
                    steps: 1,
                    map_id: 0,
                    oracle: &[],
                })
                .expect("valid transition");
            }
        }
    }
    (r, m)
}

fn sac_for(sim: &SimConfig, m: &Map, seed: u64) -> Sac {
    sac_with(
        sim,
        m,
        SacConfig { seed, batch_size: 16, reward_scale: 1.0, ..SacConfig::default() },
        tiny_net(),
    )
}

/// A learner on `m`'s segments with `cfg` and `net`.
fn sac_with(sim: &SimConfig, m: &Map, cfg: SacConfig, net: NetConfig) -> Sac {
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let segs = MapSegments::build(m, sim.obs.segment_points);
    Sac::new(cfg, net, spec, sim.dt_s, &[&segs]).expect("sac")
}

struct Flat(Vec<f32>);

impl ModuleVisitor for Flat {
    fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
        self.0.extend(p.val().into_data().try_to_vec::<f32>().expect("f32"));
    }
}

fn flat<M: Module>(m: &M) -> Vec<f32> {
    let mut f = Flat(Vec::new());
    m.visit(&mut f);
    f.0
}

#[test]
fn tanh_gaussian_log_prob_matches_change_of_variables() {
    let dev = burn::tensor::Device::flex();
    let (mu, log_std) = (0.3f64, -0.7f64);
    let sigma = log_std.exp();
    let eps: Vec<f32> = vec![-1.5, -0.2, 0.0, 0.9, 2.0];
    let n = eps.len();
    let a: Vec<f32> = eps.iter().map(|e| (mu + sigma * *e as f64).tanh() as f32).collect();
    let lp = tanh_gaussian_log_prob(
        Tensor::from_data(TensorData::new(eps.clone(), [n, 1]), &dev),
        Tensor::from_data(TensorData::new(vec![log_std as f32; n], [n, 1]), &dev),
        Tensor::from_data(TensorData::new(a.clone(), [n, 1]), &dev),
    );
    let lp: Vec<f32> = lp.into_data().try_to_vec().expect("f32");
    for i in 0..n {
        // Density of a = tanh(u), u ~ N(mu, sigma): N(atanh a) / (1 - a^2).
        let u = (a[i] as f64).atanh();
        let want = -0.5 * ((u - mu) / sigma).powi(2)
            - sigma.ln()
            - 0.5 * (2.0 * std::f64::consts::PI).ln()
            - (1.0 - (a[i] as f64).powi(2)).ln();
        assert!(
            (lp[i] as f64 - want).abs() < 2e-3 * want.abs().max(1.0),
            "a = {}: {} vs {want}",
            a[i],
            lp[i]
        );
    }
    // And the density integrates to 1 over (-1, 1).
    let k = 20_000;
    let mut total = 0.0;
    for j in 0..k {
        let aa = -1.0 + (j as f64 + 0.5) * 2.0 / k as f64;
        let u = aa.atanh();
        let logp = -0.5 * ((u - mu) / sigma).powi(2)
            - sigma.ln()
            - 0.5 * (2.0 * std::f64::consts::PI).ln()
            - (1.0 - aa * aa).ln();
        total += logp.exp() * 2.0 / k as f64;
    }
    assert!((total - 1.0).abs() < 1e-3, "integral {total}");
}

#[test]
fn one_update_moves_online_nets_and_the_target_only_by_polyak() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let mut sac = sac_for(&sim, &m, 1);
    let (actor0, critic0, target0) = (flat(&sac.actor), flat(&sac.critic), flat(&sac.target));
    assert_eq!(critic0, target0, "the target starts as a copy");
    let batch = r.sample(&mut ChaCha8Rng::seed_from_u64(9), 16).expect("batch");
    let l = sac.update(&batch);
    assert!(l.critic.is_finite() && l.actor.is_finite() && l.alpha > 0.0);
    let (actor1, critic1, target1) = (flat(&sac.actor), flat(&sac.critic), flat(&sac.target));
    assert!(actor0.iter().zip(&actor1).any(|(a, b)| a != b), "actor unchanged");
    assert!(critic0.iter().zip(&critic1).any(|(a, b)| a != b), "critic unchanged");
    for i in 0..target1.len() {
        let want = 0.995 * target0[i] + 0.005 * critic1[i];
        assert!(
            (target1[i] - want).abs() <= 1e-6 * want.abs().max(1.0),
            "target param {i}: {} vs {want}",
            target1[i]
        );
    }
    assert_ne!(sac.alpha(), 1.0, "alpha is tuned");
}

#[test]
fn the_averaged_actor_follows_the_actor_by_polyak_and_survives_a_checkpoint() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let segs = MapSegments::build(&m, sim.obs.segment_points);
    let make = |seed| {
        Sac::new(
            SacConfig {
                seed,
                batch_size: 16,
                reward_scale: 1.0,
                actor_average_tau: Some(0.1),
                ..SacConfig::default()
            },
            tiny_net(),
            spec.clone(),
            sim.dt_s,
            &[&segs],
        )
        .expect("sac")
    };
    let mut a = make(4);
    let avg0 = flat(a.actor_avg.as_ref().expect("an average"));
    assert_eq!(avg0, flat(&a.actor), "the average starts at the actor");
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let batches: Vec<Batch> = (0..4).map(|_| r.sample(&mut rng, 16).expect("batch")).collect();
    a.update(&batches[0]);
    let (actor1, avg1) = (flat(&a.actor), flat(a.actor_avg.as_ref().expect("an average")));
    assert!(actor1.iter().zip(&avg0).any(|(x, y)| x != y), "the actor moved");
    for i in 0..avg1.len() {
        let want = 0.9 * avg0[i] + 0.1 * actor1[i];
        assert!(
            (avg1[i] - want).abs() <= 1e-6 * want.abs().max(1.0),
            "param {i}: {} vs {want}",
            avg1[i]
        );
    }
    // What validation scores and the final policy takes is the average, not the actor;
    // rollouts keep the actor unless `act_with_average` says otherwise.
    assert_ne!(a.selected_actor_bytes().expect("bytes"), a.actor_bytes().expect("bytes"));
    assert_eq!(a.acting_actor_bytes().expect("bytes"), a.actor_bytes().expect("bytes"));
    a.cfg.act_with_average = true;
    assert_eq!(a.acting_actor_bytes().expect("bytes"), a.selected_actor_bytes().expect("bytes"));
    a.cfg.act_with_average = false;
    let dir = std::env::temp_dir().join(format!("sf-sac-avg-{}", std::process::id()));
    checkpoint::save(&a, &dir).expect("save");
    a.update(&batches[1]);
    let mut b = make(99);
    checkpoint::restore(&mut b, &dir).expect("restore");
    b.update(&batches[1]);
    assert_eq!(
        flat(a.actor_avg.as_ref().expect("avg")),
        flat(b.actor_avg.as_ref().expect("avg")),
        "the average continues exactly"
    );
    // Without the setting there is no average and the actor is what is selected.
    let plain = sac_for(&sim, &m, 4);
    assert!(plain.actor_avg.is_none());
    assert_eq!(plain.selected_actor_bytes().expect("bytes"), plain.actor_bytes().expect("bytes"));
    assert_eq!(plain.acting_actor_bytes().expect("bytes"), plain.actor_bytes().expect("bytes"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// A continuation (`train.init_job`) goes on with the other run's kept actor, not the actor of
/// its last checkpoint, and with the checkpoint's critic; a kept actor that does not decode
/// changes nothing.
#[test]
fn a_continuation_starts_from_the_kept_actor_and_the_last_critic() {
    let sim = Arc::new(SimConfig::default());
    let (replay, m) = replay_from_sim(&sim, 200);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut batch = Batch::default();
    let mut a = sac_for(&sim, &m, 1);
    replay.sample_into(&mut rng, 16, &mut batch).expect("sample");
    a.update(&batch);
    let kept = a.actor_bytes().expect("bytes");
    for _ in 0..3 {
        replay.sample_into(&mut rng, 16, &mut batch).expect("sample");
        a.update(&batch);
    }
    assert_ne!(a.actor_bytes().expect("bytes"), kept, "the last actor moved on from the kept one");
    let dir = std::env::temp_dir().join(format!("sf-sac-continue-{}", std::process::id()));
    checkpoint::save(&a, &dir).expect("save");
    let mut b = sac_for(&sim, &m, 2);
    checkpoint::warm_start(&mut b, &dir, Some(&kept)).expect("continue");
    assert_eq!(b.actor_bytes().expect("bytes"), kept, "the kept actor, which adversaries attacked");
    assert_eq!(flat(&b.critic), flat(&a.critic), "the last critic");
    assert_eq!(b.updates, 0);
    let mut c = sac_for(&sim, &m, 3);
    checkpoint::warm_start(&mut c, &dir, None).expect("continue");
    assert_eq!(
        c.actor_bytes().expect("bytes"),
        a.actor_bytes().expect("bytes"),
        "no kept actor: the checkpoint's"
    );
    let mut d = sac_for(&sim, &m, 4);
    let fresh = d.actor_bytes().expect("bytes");
    let e = checkpoint::warm_start(&mut d, &dir, Some(b"not a module")).expect_err("garbage");
    assert!(e.to_string().contains("kept actor"), "{e}");
    assert_eq!(d.actor_bytes().expect("bytes"), fresh, "nothing changed on error");
    assert_eq!(d.updates, 0);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn gradients_do_not_reach_frozen_modules() {
    let sim = Arc::new(SimConfig::default());
    let m = map();
    let sac = sac_for(&sim, &m, 2);
    let dev = sac.ad.clone();
    let x =
        Tensor::<2>::from_data(TensorData::new(vec![0.1f32; 2 * 18], [2, 18]), &dev).require_grad();
    let frozen = sac.critic.q1.clone().no_grad();
    let y = frozen.forward(x.clone()).sum();
    let grads = y.backward();
    assert!(x.grad(&grads).is_some(), "gradient reaches the input (the actor's action)");
    assert!(frozen.layers[0].weight.val().grad(&grads).is_none(), "frozen weights get no gradient");
    // The original critic head is still trainable.
    let y = sac.critic.q1.forward(x).sum();
    let grads = y.backward();
    assert!(sac.critic.q1.layers[0].weight.val().grad(&grads).is_some());
}

/// Trains `a` for `before` updates, checkpoints it, trains on over the remaining batches; a
/// fresh learner (another seed) restored from the checkpoint and fed the same batches must end
/// bit-identical: weights, targets, optimizer state and alpha all come back.
fn assert_restore_continues_exactly(
    make: impl Fn(u64) -> Sac,
    batches: &[Batch],
    before: usize,
    tag: &str,
) {
    let mut a = make(3);
    for b in &batches[..before] {
        a.update(b);
    }
    let dir = std::env::temp_dir().join(format!("sf-sac-ckpt-{tag}-{}", std::process::id()));
    checkpoint::save(&a, &dir).expect("save");
    checkpoint::save(&a, &dir).expect("save over an existing checkpoint");
    for b in &batches[before..] {
        a.update(b);
    }
    let mut b = make(77);
    checkpoint::restore(&mut b, &dir).expect("restore");
    assert_eq!(b.updates, before as u64);
    for batch in &batches[before..] {
        b.update(batch);
    }
    assert_eq!(flat(&a.actor), flat(&b.actor), "{tag}: actor differs after restore");
    assert_eq!(flat(&a.critic), flat(&b.critic), "{tag}: critic differs after restore");
    assert_eq!(flat(&a.target), flat(&b.target), "{tag}: target differs after restore");
    assert_eq!(a.alpha(), b.alpha(), "{tag}: alpha differs after restore");
    // A corrupt checkpoint is refused and leaves the learner as it was.
    std::fs::write(dir.join("critic.bpk"), b"not a record").expect("corrupt");
    let before = flat(&b.critic);
    let e = checkpoint::restore(&mut b, &dir).expect_err("corrupt checkpoint");
    assert!(e.to_string().contains("critic"), "{e}");
    assert_eq!(flat(&b.critic), before);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn checkpoint_restore_continues_exactly() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let batches: Vec<Batch> = (0..6).map(|_| r.sample(&mut rng, 16).expect("batch")).collect();
    assert_restore_continues_exactly(|seed| sac_for(&sim, &m, seed), &batches, 3, "plain");
}

/// A warm start across kinds (`train.warm_start_from`: a SocialComm flow from a MACAD flow's
/// checkpoint): the job that reads SVOs acts exactly as its source on observations whose SVOs
/// it now reads, its critic differs from the source's only in the zeroed weights that read
/// them, it starts at update 0 and trains on; a network of other sizes is refused untouched.
#[test]
fn a_warm_start_across_kinds_starts_as_its_source() {
    use sf_nn::SvoVisibility;
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let batches: Vec<Batch> = (0..4).map(|_| r.sample(&mut rng, 16).expect("batch")).collect();
    let mut src = sac_for(&sim, &m, 3);
    for b in &batches[..3] {
        src.update(b);
    }
    let dir = std::env::temp_dir().join(format!("sf-sac-warm-{}", std::process::id()));
    checkpoint::save(&src, &dir).expect("save");
    let cfg = SacConfig { seed: 9, batch_size: 16, reward_scale: 1.0, ..SacConfig::default() };
    let svo_net = NetConfig { svo: SvoVisibility::All, ..tiny_net() };
    let mut dst = sac_with(&sim, &m, cfg.clone(), svo_net);
    // Observations with SVOs on every channel that carries one.
    let spec = dst.spec.clone();
    let mut rows = batches[3].obs.clone();
    for row in rows.chunks_mut(spec.len) {
        row[spec.ego_ctx.start] = 0.6;
        for j in 0..spec.neighbours {
            row[spec.agents_ctx.start + j * sf_sim::obs::AGENT_CTX + 4] = -0.4;
        }
    }
    let ids = &batches[3].map_ids;
    let act = |s: &Sac| -> Vec<f32> {
        let (a, t) = s.policy();
        a.act_mean(&s.obs_batch(&rows, ids), t.as_ref())
            .into_data()
            .try_to_vec::<f32>()
            .expect("f32")
    };
    assert_ne!(act(&src), act(&dst), "a fresh network acts otherwise");
    let from = checkpoint::warm_start_across(&mut dst, &dir).expect("warm start");
    assert_eq!(from.svo, SvoVisibility::None);
    assert_eq!(dst.updates, 0);
    assert_eq!(act(&src), act(&dst), "the warm-started job acts as its source, SVOs shown");
    // The critic: the weights that read the own SVO (one row of the ego context layer) and the
    // neighbours' (one row of the agent context MLP's first layer) are zero, the rest as loaded.
    let d = tiny_net().d_model;
    for (what, a, b) in [
        ("critic", flat(&src.critic), flat(&dst.critic)),
        ("target", flat(&src.target), flat(&dst.target)),
    ] {
        let differ: Vec<usize> = (0..a.len()).filter(|&i| a[i] != b[i]).collect();
        assert_eq!(differ.len(), 2 * d, "{what}: {} weights differ", differ.len());
        assert!(differ.iter().all(|&i| b[i] == 0.0), "{what}: only zeroed weights differ");
    }
    // The zeroed weights are leaves again: every later backward finds its graph.
    for b in &batches {
        dst.update(b);
    }
    assert_eq!(dst.updates, 4, "it trains on");
    // Other sizes: refused, nothing changed.
    let mut wide = sac_with(&sim, &m, cfg, NetConfig { d_model: 32, ..tiny_net() });
    let before = flat(&wide.actor);
    let e = checkpoint::warm_start_across(&mut wide, &dir).expect_err("other sizes");
    assert!(e.to_string().contains("network"), "{e}");
    assert_eq!(flat(&wide.actor), before);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The same with `configs/stage1`'s recipe (a shared encoder, a LayerNorm critic with the ego
/// skip, Q-filtered cloning towards the zero residual, a Huber critic loss, cloning then critic
/// pretraining then SAC), checkpointed during critic pretraining and continued into SAC: what a
/// Stage-1 run continued from its committed state (`train.continue_from`) restores.
#[test]
fn checkpoint_restore_continues_exactly_with_the_stage1_recipe() {
    use sf_sac::sac::{BcTarget, CriticLoss};
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let batches: Vec<Batch> = (0..8).map(|_| r.sample(&mut rng, 16).expect("batch")).collect();
    let make = |seed| {
        let cfg = SacConfig {
            seed,
            batch_size: 16,
            gamma: 0.97,
            reward_scale: 10.0,
            critic_loss: CriticLoss::Huber,
            huber_delta: 10.0,
            bc_updates: 2,
            critic_pretrain_updates: 2,
            bc_weight: 0.4,
            bc_target: BcTarget::Zero,
            bc_q_filter: true,
            initial_alpha: 0.05,
            shared_encoder: true,
            ..SacConfig::default()
        };
        let net =
            NetConfig { critic_layer_norm: true, ego_skip: true, pose_layers: 2, ..tiny_net() };
        sac_with(&sim, &m, cfg, net)
    };
    assert_restore_continues_exactly(make, &batches, 3, "stage1");
}

/// The learner on wgpu (Vulkan; Mesa's software lavapipe in CI) against the CPU one: the same
/// seed starts both from the same weights (drawn on the host), and the same batches and
/// host-drawn noise then give the same losses and weights, up to the order of float sums. Needs
/// the `wgpu` feature and a Vulkan driver; without the driver it fails, naming the device,
/// rather than passing.
#[cfg(feature = "wgpu")]
#[test]
fn the_wgpu_learner_updates_as_the_cpu_learner_does() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let batches: Vec<Batch> = (0..4).map(|_| r.sample(&mut rng, 16).expect("batch")).collect();
    let cfg = |device| SacConfig {
        seed: 4,
        batch_size: 16,
        reward_scale: 1.0,
        device,
        ..SacConfig::default()
    };
    let mut cpu = sac_with(&sim, &m, cfg(sf_job::config::Device::Cpu), tiny_net());
    // Without a usable driver this panics with the device error, which names `wgpu`.
    let mut gpu = sac_with(&sim, &m, cfg(sf_job::config::Device::Wgpu), tiny_net());
    assert_eq!(flat(&cpu.actor), flat(&gpu.actor), "both start from the host-drawn weights");
    let close = |a: f32, b: f32, what: &str| {
        assert!((a - b).abs() <= 2e-3 * a.abs().max(b.abs()).max(1.0), "{what}: cpu {a}, wgpu {b}");
    };
    for (i, b) in batches.iter().enumerate() {
        let (lc, lg) = (cpu.update(b), gpu.update(b));
        close(lc.critic, lg.critic, &format!("critic loss, update {i}"));
        close(lc.actor, lg.actor, &format!("actor loss, update {i}"));
        close(lc.alpha, lg.alpha, &format!("alpha, update {i}"));
    }
    for (what, a, b) in [
        ("actor", flat(&cpu.actor), flat(&gpu.actor)),
        ("critic", flat(&cpu.critic), flat(&gpu.critic)),
        ("target", flat(&cpu.target), flat(&gpu.target)),
    ] {
        assert_eq!(a.len(), b.len());
        let worst = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-3, "{what} weights differ by up to {worst} after four updates");
    }
}

/// The IDM warm-up's cloning phase: for the first `bc_updates` updates the actor's mean action
/// is fitted to the stored actions (here a route follower's, a function of the observation) and
/// alpha stays put; the first update after them tunes alpha again.
#[test]
fn cloning_updates_fit_the_stored_actions_and_hold_alpha() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 512);
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let segs = MapSegments::build(&m, sim.obs.segment_points);
    let cfg = SacConfig {
        seed: 2,
        batch_size: 32,
        lr_actor: 1e-3,
        initial_alpha: 0.5,
        bc_updates: 300,
        warmup_noise: (-2.0f32).exp(),
        reward_scale: 1.0,
        ..SacConfig::default()
    };
    let mut sac = Sac::new(cfg, tiny_net(), spec, sim.dt_s, &[&segs]).expect("sac");
    let probe = r.sample(&mut ChaCha8Rng::seed_from_u64(5), 128).expect("probe batch");
    let mse = |sac: &Sac| -> f32 {
        let (actor, table) = sac.policy();
        let a: Vec<f32> = actor
            .act_mean(&sac.obs_batch(&probe.obs, &probe.map_ids), table.as_ref())
            .into_data()
            .try_to_vec()
            .expect("f32");
        a.iter().zip(&probe.actions).map(|(x, y)| (x - y).powi(2)).sum::<f32>() / a.len() as f32
    };
    let before = mse(&sac);
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    for _ in 0..300 {
        let l = sac.update(&r.sample(&mut rng, 32).expect("batch"));
        assert_eq!(l.alpha, 0.5, "alpha is not tuned while cloning");
    }
    let after = mse(&sac);
    assert!(after < 0.25 * before, "cloning error {before} -> {after}");
    let l = sac.update(&r.sample(&mut rng, 32).expect("batch"));
    assert_ne!(l.alpha, 0.5, "alpha is tuned again after the cloning updates");
}

/// The actor step reads Q1 through a `no_grad` copy; every head of the critic (and the actor)
/// must still learn on every later update (burn's `no_grad` on a clone must not freeze the
/// original).
#[test]
fn every_critic_head_and_the_actor_keep_learning_across_updates() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let mut sac = sac_for(&sim, &m, 4);
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    for k in 0..4 {
        let (q1, q2, enc, actor) =
            (flat(&sac.critic.q1), flat(&sac.critic.q2), flat(&sac.critic.enc), flat(&sac.actor));
        sac.update(&r.sample(&mut rng, 16).expect("batch"));
        assert_ne!(q1, flat(&sac.critic.q1), "update {k}: Q1 head unchanged");
        assert_ne!(q2, flat(&sac.critic.q2), "update {k}: Q2 head unchanged");
        assert_ne!(enc, flat(&sac.critic.enc), "update {k}: critic encoder unchanged");
        assert_ne!(actor, flat(&sac.actor), "update {k}: actor unchanged");
    }
}

/// The mean head is squashed once: a pre-squash mean of 3 gives a deterministic action of
/// tanh(3) = 0.995, beyond the released code's ceiling tanh(1) = 0.762, which
/// `squash_mean_twice` keeps for fidelity.
#[test]
fn the_mean_action_reaches_the_full_range_unless_squashed_twice() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let segs = MapSegments::build(&m, sim.obs.segment_points);
    let probe = r.sample(&mut ChaCha8Rng::seed_from_u64(1), 8).expect("batch");
    for twice in [false, true] {
        let net = NetConfig { squash_mean_twice: twice, ..tiny_net() };
        let mut sac = Sac::new(
            SacConfig { reward_scale: 1.0, ..SacConfig::default() },
            net,
            spec.clone(),
            sim.dt_s,
            &[&segs],
        )
        .expect("sac");
        // A mean head that outputs 3 whatever it reads.
        let last = sac.actor.mean.layers.last_mut().expect("layers");
        last.weight = Param::from_tensor(Tensor::zeros(last.weight.dims(), &sac.ad));
        last.bias = Some(Param::from_tensor(Tensor::from_data(
            TensorData::new(vec![3.0f32; 2], [2]),
            &sac.ad,
        )));
        let (actor, table) = sac.policy();
        let a: Vec<f32> = actor
            .act_mean(&sac.obs_batch(&probe.obs, &probe.map_ids), table.as_ref())
            .into_data()
            .try_to_vec()
            .expect("f32");
        let want = if twice { 3f32.tanh().tanh() } else { 3f32.tanh() };
        assert!(a.iter().all(|&x| (x - want).abs() < 1e-5), "twice {twice}: {a:?}, want {want}");
    }
}

/// The log-std head starts at the configured spread (its output bias, through the squash).
#[test]
fn the_first_policy_starts_at_the_configured_log_std() {
    for want in [-2.3f32, -1.2, 0.0] {
        let net = NetConfig { init_log_std: want, ..tiny_net() };
        let actor = sf_nn::Actor::new(&net, 3, &burn::tensor::Device::flex());
        let b = actor.log_std.layers.last().and_then(|l| l.bias.as_ref()).expect("bias").val();
        let got: Vec<f32> = sf_nn::policy::squash_log_std(b.unsqueeze_dim::<2>(0), net.log_std_min)
            .into_data()
            .try_to_vec()
            .expect("f32");
        assert!(got.iter().all(|&g| (g - want).abs() < 1e-4), "{got:?} vs {want}");
    }
    assert!(
        NetConfig { init_log_std: -3.0, ..tiny_net() }.validate().is_err(),
        "outside the log-std range"
    );
    // A lower floor (`net.log_std_min`) admits a smaller first spread, and the released
    // code's range is the default: 1.5 tanh(x) - 1.
    let low = NetConfig { init_log_std: -4.0, log_std_min: -5.0, ..tiny_net() };
    low.validate().expect("inside the lower range");
    let actor = sf_nn::Actor::new(&low, 3, &burn::tensor::Device::flex());
    let b = actor.log_std.layers.last().and_then(|l| l.bias.as_ref()).expect("bias").val();
    let got: Vec<f32> = sf_nn::policy::squash_log_std(b.unsqueeze_dim::<2>(0), low.log_std_min)
        .into_data()
        .try_to_vec()
        .expect("f32");
    assert!(got.iter().all(|&g| (g + 4.0).abs() < 1e-4), "{got:?} vs -4");
    let x = Tensor::<2>::from_data(
        TensorData::new(vec![-20.0f32, -0.3, 0.0, 0.7, 20.0], [1, 5]),
        &burn::tensor::Device::flex(),
    );
    let paper: Vec<f32> = sf_nn::policy::squash_log_std(x, tiny_net().log_std_min)
        .into_data()
        .try_to_vec()
        .expect("f32");
    for (got, x) in paper.iter().zip([-20.0f32, -0.3, 0.0, 0.7, 20.0]) {
        assert!((got - (1.5 * x.tanh() - 1.0)).abs() < 1e-5, "{x}: {got}");
    }
    for m in [0.5f32, -11.0, f32::NAN] {
        assert!(
            NetConfig { log_std_min: m, init_log_std: 0.0, ..tiny_net() }.validate().is_err(),
            "log_std_min {m}"
        );
    }
}

/// During `critic_pretrain_updates` (after the cloning updates) only the critic learns: the
/// actor and alpha stay put; with `shared_encoder` the actor's encoder is the critic's.
#[test]
fn critic_pretraining_holds_the_actor_and_shared_encoders_follow_the_critic() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 128);
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let segs = MapSegments::build(&m, sim.obs.segment_points);
    let cfg = SacConfig {
        seed: 4,
        batch_size: 16,
        bc_updates: 2,
        critic_pretrain_updates: 3,
        shared_encoder: true,
        reward_scale: 1.0,
        ..SacConfig::default()
    };
    let mut sac = Sac::new(
        cfg,
        NetConfig { critic_layer_norm: true, ego_skip: true, pose_layers: 2, ..tiny_net() },
        spec,
        sim.dt_s,
        &[&segs],
    )
    .expect("sac");
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for _ in 0..2 {
        sac.update(&r.sample(&mut rng, 16).expect("batch"));
    }
    for k in 0..3 {
        let (actor, critic, alpha) = (flat(&sac.actor.mean), flat(&sac.critic), sac.alpha());
        sac.update(&r.sample(&mut rng, 16).expect("batch"));
        assert_eq!(actor, flat(&sac.actor.mean), "critic-only update {k} moved the actor");
        assert_eq!(alpha, sac.alpha(), "critic-only update {k} moved alpha");
        assert_ne!(critic, flat(&sac.critic), "critic-only update {k} did not train the critic");
        assert_eq!(
            flat(&sac.actor.enc),
            flat(&sac.critic.enc),
            "the shared encoder is the critic's"
        );
    }
    let actor = flat(&sac.actor.mean);
    sac.update(&r.sample(&mut rng, 16).expect("batch"));
    assert_ne!(actor, flat(&sac.actor.mean), "the actor learns after the critic-only updates");
    assert_eq!(flat(&sac.actor.enc), flat(&sac.critic.enc));
}

/// Huber: half the squared error within delta, linear beyond.
#[test]
fn huber_is_quadratic_within_delta_and_linear_beyond() {
    let dev = burn::tensor::Device::flex();
    let d = Tensor::<2>::from_data(TensorData::new(vec![0.5f32, -2.0, 30.0, -10.0], [4, 1]), &dev);
    let got = sf_sac::sac::huber(d, 10.0).into_scalar::<f32>();
    let want = (0.125 + 2.0 + 10.0 * (30.0 - 5.0) + 50.0) / 4.0;
    assert!((got - want).abs() < 1e-4, "{got} vs {want}");
}

/// AWAC's row weights: exp of the advantage over lambda, clipped, mean 1 over the batch. The
/// row whose replayed action the critic rates highest weighs most; equal advantages weigh 1.
#[test]
fn awac_weights_follow_the_advantage_and_average_one() {
    let dev = burn::tensor::Device::flex();
    let col = |v: &[f32]| Tensor::<2>::from_data(TensorData::new(v.to_vec(), [v.len(), 1]), &dev);
    let w: Vec<f32> =
        sf_sac::sac::awac_weights(col(&[1.0, 2.0, 3.0, 2.0]), col(&[2.0, 2.0, 2.0, 2.0]), 1.0)
            .into_data()
            .try_to_vec()
            .expect("f32");
    let raw = [(-1f32).exp(), 1.0, 1f32.exp(), 1.0];
    let mean = raw.iter().sum::<f32>() / 4.0;
    for (got, r) in w.iter().zip(raw) {
        assert!((got - r / mean).abs() < 1e-5, "{w:?}");
    }
    assert!(w[2] > w[1] && w[1] > w[0], "ordered by advantage: {w:?}");
    let flat: Vec<f32> = sf_sac::sac::awac_weights(col(&[5.0; 3]), col(&[5.0; 3]), 0.3)
        .into_data()
        .try_to_vec()
        .expect("f32");
    assert!(flat.iter().all(|x| (x - 1.0).abs() < 1e-6), "{flat:?}");
    // A huge advantage is clipped at AWAC_MAX_WEIGHT before the normalisation: the other rows
    // keep weight, instead of exp(100) taking the whole term.
    let clipped: Vec<f32> = sf_sac::sac::awac_weights(col(&[100.0, 0.0]), col(&[0.0, 0.0]), 1.0)
        .into_data()
        .try_to_vec()
        .expect("f32");
    let max = sf_job::config::AWAC_MAX_WEIGHT;
    assert!(
        (clipped[0] - 2.0 * max / (max + 1.0)).abs() < 1e-4
            && (clipped[1] - 2.0 / (max + 1.0)).abs() < 1e-5,
        "{clipped:?}"
    );
}

/// With `bc_awac_lambda` the SAC updates after cloning run the weighted cloning term and stay
/// finite.
#[test]
fn awac_weighted_cloning_updates_run_and_stay_finite() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 128);
    let cfg = SacConfig {
        seed: 5,
        batch_size: 16,
        bc_updates: 1,
        bc_weight: 0.5,
        bc_awac_lambda: Some(1.0),
        reward_scale: 1.0,
        ..SacConfig::default()
    };
    let mut sac = sac_with(&sim, &m, cfg, tiny_net());
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..4 {
        let before = flat(&sac.actor.mean);
        let l = sac.update(&r.sample(&mut rng, 16).expect("batch"));
        assert!(l.actor.is_finite() && l.critic.is_finite(), "{l:?}");
        assert_ne!(before, flat(&sac.actor.mean));
    }
}

/// The cloning term towards IDM's action with the Q filter, for the zero residual and for the
/// worker's recorded oracle labels: where the critic rates IDM's action at least as high as the
/// policy's (here a critic flat in the action), the term pulls the mean action to it; where it
/// rates the policy's action higher (a critic rewarding positive actions) the rows are filtered
/// out and the mean action is left to the critic. Rows without a label are left out.
#[test]
fn the_q_filtered_cloning_term_clones_idm_only_where_the_critic_prefers_it() {
    use sf_sac::replay::Stored;
    use sf_sac::sac::BcTarget;
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 256);
    // The same transitions, each labelled with IDM's action (-0.4, -0.4).
    let mut labelled = Replay::new(10_000, r.obs_len(), 2);
    for k in r.oldest()..r.inserted() {
        let t = r.get(k).expect("held");
        labelled.push_f16(Stored { oracle: &[-0.4, -0.4], ..t }).expect("labelled");
    }
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let segs = MapSegments::build(&m, sim.obs.segment_points);
    let probe = r.sample(&mut ChaCha8Rng::seed_from_u64(2), 64).expect("probe");
    // Each component's mean action over the probe, before and after 80 updates.
    let run_held = |slope: f32,
                    bc_target: BcTarget,
                    r: &Replay,
                    bc_hold_dims: Vec<usize>,
                    bc_hold_clone_only: bool|
     -> ([f32; 2], [f32; 2]) {
        let cfg = SacConfig {
            seed: 5,
            batch_size: 32,
            lr_actor: 1e-3,
            lr_critic: 1e-12,
            initial_alpha: 1e-4,
            bc_weight: 5.0,
            bc_target,
            bc_q_filter: true,
            bc_hold_dims,
            bc_hold_clone_only,
            reward_scale: 1.0,
            ..SacConfig::default()
        };
        let mut sac = Sac::new(cfg, tiny_net(), spec.clone(), sim.dt_s, &[&segs]).expect("sac");
        let mean = |sac: &Sac| -> [f32; 2] {
            let (actor, table) = sac.policy();
            let a: Vec<f32> = actor
                .act_mean(&sac.obs_batch(&probe.obs, &probe.map_ids), table.as_ref())
                .into_data()
                .try_to_vec()
                .expect("f32");
            let n = (a.len() / 2) as f32;
            [0, 1].map(|k| a.iter().skip(k).step_by(2).sum::<f32>() / n)
        };
        // Start the mean action at tanh(0.5) in both components.
        let last = sac.actor.mean.layers.last_mut().expect("layers");
        last.weight = Param::from_tensor(Tensor::zeros(last.weight.dims(), &sac.ad));
        last.bias = Some(Param::from_tensor(Tensor::from_data(
            TensorData::new(vec![0.5f32; 2], [2]),
            &sac.ad,
        )));
        // Q = 1 + slope * (a0 + a1), through a ReLU-free path: first layer passes the action
        // (plus 10, to stay positive) to unit 0, the next layers copy unit 0.
        for q in [&mut sac.critic.q1, &mut sac.critic.q2] {
            let (d_in, d_out) = (q.layers[0].weight.dims()[0], q.layers[0].weight.dims()[1]);
            let mut w = vec![0f32; d_in * d_out];
            w[(d_in - 2) * d_out] = 1.0;
            w[(d_in - 1) * d_out] = 1.0;
            let mut b = vec![0f32; d_out];
            b[0] = 10.0;
            q.layers[0].weight =
                Param::from_tensor(Tensor::from_data(TensorData::new(w, [d_in, d_out]), &sac.ad));
            q.layers[0].bias =
                Some(Param::from_tensor(Tensor::from_data(TensorData::new(b, [d_out]), &sac.ad)));
            let (d_in, d_out) = (q.layers[1].weight.dims()[0], q.layers[1].weight.dims()[1]);
            let mut w = vec![0f32; d_in * d_out];
            w[0] = 1.0;
            q.layers[1].weight =
                Param::from_tensor(Tensor::from_data(TensorData::new(w, [d_in, d_out]), &sac.ad));
            q.layers[1].bias = Some(Param::from_tensor(Tensor::zeros([d_out], &sac.ad)));
            let d_in = q.layers[2].weight.dims()[0];
            let mut w = vec![0f32; d_in];
            w[0] = slope;
            q.layers[2].weight =
                Param::from_tensor(Tensor::from_data(TensorData::new(w, [d_in, 1]), &sac.ad));
            q.layers[2].bias = Some(Param::from_tensor(Tensor::from_data(
                TensorData::new(vec![1.0 - 10.0 * slope], [1]),
                &sac.ad,
            )));
        }
        let before = mean(&sac);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..80 {
            sac.update(&r.sample(&mut rng, 32).expect("batch"));
        }
        (before, mean(&sac))
    };
    let both = |(b, a): ([f32; 2], [f32; 2])| ((b[0] + b[1]) / 2.0, (a[0] + a[1]) / 2.0);
    let run = |slope: f32, bc_target: BcTarget, r: &Replay| {
        both(run_held(slope, bc_target, r, Vec::new(), false))
    };
    let (before, flat) = run(0.0, BcTarget::Zero, &r);
    assert!(
        flat.abs() < 0.5 * before.abs(),
        "flat critic: the term pulls to zero ({before} -> {flat})"
    );
    let (before, rising) = run(1.0, BcTarget::Zero, &r);
    assert!(
        rising > before,
        "a critic preferring larger actions filters the term out ({before} -> {rising})"
    );
    let (before, flat) = run(0.0, BcTarget::Oracle, &labelled);
    assert!(
        (flat + 0.4).abs() < 0.5 * (before + 0.4).abs() && flat < 0.0,
        "flat critic: the term pulls to the oracle's -0.4 ({before} -> {flat})"
    );
    let (before, rising) = run(1.0, BcTarget::Oracle, &labelled);
    assert!(
        rising > before,
        "a critic preferring larger actions filters the oracle term out ({before} -> {rising})"
    );
    // A row without a label weighs what a filtered-out row weighs: nothing. The same batches
    // without labels train exactly as the labelled ones whose every row the filter removed.
    let (_, unlabelled) = run(1.0, BcTarget::Oracle, &r);
    assert!(
        (unlabelled - rising).abs() < 1e-6,
        "rows without a label are not cloned ({unlabelled} against {rising} with every row filtered)"
    );
    // `bc_hold_dims = [1]`: the critic prefers larger actions, so the filter removes every row
    // for component 0, which rises; component 1 is cloned anyway and falls towards -0.4.
    let (before, after) = run_held(1.0, BcTarget::Oracle, &labelled, vec![1], false);
    assert!(after[0] > before[0], "component 0 follows the critic ({before:?} -> {after:?})");
    assert!(
        (after[1] + 0.4).abs() < 0.5 * (before[1] + 0.4).abs(),
        "component 1 is held at the oracle's -0.4 ({before:?} -> {after:?})"
    );
    // `bc_hold_clone_only`: the critic's pull towards larger actions no longer reaches the held
    // component, so it ends nearer the oracle's -0.4 than when the critic pulls against the
    // term, while component 0 still follows the critic.
    let (_, only) = run_held(1.0, BcTarget::Oracle, &labelled, vec![1], true);
    assert!(only[0] > before[0], "component 0 follows the critic ({before:?} -> {only:?})");
    assert!(
        (only[1] + 0.4).abs() < (after[1] + 0.4).abs(),
        "the held component is nearer the label without Q's gradient ({after:?} with, {only:?} without)"
    );
}

#[test]
fn the_conservative_critic_lowers_q_off_the_replayed_actions() {
    use sf_sac::replay::Stored;
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 256);
    // The same transitions, every one acting (0.5, 0.5).
    let mut one = Replay::new(10_000, r.obs_len(), 2);
    for k in r.oldest()..r.inserted() {
        let t = r.get(k).expect("held");
        one.push_f16(Stored { action: &[0.5, 0.5], ..t }).expect("row");
    }
    let probe = one.sample(&mut ChaCha8Rng::seed_from_u64(2), 64).expect("probe");
    // Q(s, replayed action) - Q(s, an action the replay never shows), averaged over the probe,
    // after the critic alone learned from the replay with the given conservative weight.
    let gap = |cql_weight: f32| -> (f32, f32) {
        let cfg = SacConfig {
            seed: 5,
            batch_size: 32,
            reward_scale: 1.0,
            critic_pretrain_updates: 10_000,
            cql_weight,
            ..SacConfig::default()
        };
        let mut sac = sac_with(&sim, &m, cfg, tiny_net());
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut critic_loss = 0.0;
        for _ in 0..150 {
            critic_loss = sac.update(&one.sample(&mut rng, 32).expect("batch")).critic;
        }
        assert!(critic_loss.is_finite(), "cql_weight {cql_weight}: loss {critic_loss}");
        let q = |a: [f32; 2]| -> f32 {
            let acts: Vec<f32> = (0..probe.len()).flat_map(|_| a).collect();
            let v = sac.q_min(&probe.obs, &acts, &probe.map_ids);
            v.iter().sum::<f32>() / v.len() as f32
        };
        (q([0.5, 0.5]) - q([-0.9, -0.9]), q([0.5, 0.5]))
    };
    let ((plain, q_plain), (conservative, q_cql)) = (gap(0.0), gap(5.0));
    assert!(
        conservative > plain + 2.0,
        "the conservative critic's gap {conservative} (Q at the data {q_cql}) vs plain {plain} ({q_plain})"
    );
}

#[test]
fn the_action_gradient_matches_finite_differences_and_leaves_the_learner_as_it_was() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 256);
    let mut sac = sac_for(&sim, &m, 4);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for _ in 0..30 {
        sac.update(&r.sample(&mut rng, 16).expect("batch"));
    }
    let probe = r.sample(&mut rng, 16).expect("probe");
    let (critic, actor, updates) = (flat(&sac.critic), flat(&sac.actor), sac.updates);
    let g = sac.q_action_gradient(&probe.obs, &probe.actions, &probe.map_ids);
    let (mean, log_std) = sac.action_dist(&probe.obs, &probe.map_ids, false);
    assert_eq!(flat(&sac.critic), critic, "the probe leaves the critic as it was");
    assert_eq!(flat(&sac.actor), actor, "and the actor");
    assert_eq!(sac.updates, updates);
    assert_eq!((g.len(), mean.len(), log_std.len()), (32, 32, 32));
    assert!(mean.iter().all(|a| a.abs() < 1.0), "mean actions are squashed: {mean:?}");
    // Central differences of min(Q1, Q2) along each component; min's kink may fall between
    // the two probes of a row, so most rows, not all, must agree.
    let h = 1e-3f32;
    let (mut agree, mut largest) = (0, 0.0f32);
    for k in 0..2 {
        let q_at = |d: f32| {
            let mut a = probe.actions.clone();
            for row in a.chunks_exact_mut(2) {
                row[k] += d;
            }
            sac.q_min(&probe.obs, &a, &probe.map_ids)
        };
        let (up, down) = (q_at(h), q_at(-h));
        for i in 0..probe.len() {
            let fd = (up[i] - down[i]) / (2.0 * h);
            let an = g[i * 2 + k];
            largest = largest.max(an.abs());
            agree += ((fd - an).abs() <= 0.02 + 0.05 * an.abs()) as usize;
        }
    }
    assert!(largest > 1e-3, "the gradient is not trivially zero: largest |dQ/da| {largest}");
    assert!(agree >= 28, "{agree} of 32 components agree with central differences");
}
