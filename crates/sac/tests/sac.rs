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
    let p = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs/scenarios/merge.json");
    Arc::new(Map::load(&p).expect("merge loads"))
}

/// A replay filled from real simulator rollouts (route follower with noise).
fn replay_from_sim(sim: &Arc<SimConfig>, n: usize) -> (Replay, Arc<Map>) {
    let m = map();
    let mut v = VecEnv::new(m.clone(), sim.clone(), VecEnvConfig { n_envs: 2, mode: Mode::MultiAgent, vehicles: (6, 10), seed: 3 });
    let spec = v.spec.clone();
    let mut r = Replay::new(10_000, spec.len, 2);
    let mut acts = vec![Action::default(); v.alive().len()];
    while r.len() < n {
        let before = v.observations().to_vec();
        let alive = v.alive().to_vec();
        for (i, a) in acts.iter_mut().enumerate() {
            *a = route_follower(&spec, &before[i * spec.len..(i + 1) * spec.len], &sim.vehicle, 2, 0.5);
        }
        v.step(&acts);
        for i in 0..alive.len() {
            if alive[i] == 1.0 {
                let next = &v.observations()[i * spec.len..(i + 1) * spec.len];
                let a = [acts[i].ref_speed, acts[i].steer];
                r.push(Transition { obs: &before[i * spec.len..(i + 1) * spec.len], action: &a, reward: 0.1, next_obs: next, terminal: false, map_id: 0 })
                    .expect("valid transition");
            }
        }
    }
    (r, m)
}

fn sac_for(sim: &SimConfig, m: &Map, seed: u64) -> Sac {
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let segs = MapSegments::build(m, sim.obs.segment_points);
    Sac::new(SacConfig { seed, batch_size: 16, ..SacConfig::default() }, tiny_net(), spec, sim.dt_s, &[&segs]).expect("sac")
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
        let want = -0.5 * ((u - mu) / sigma).powi(2) - sigma.ln() - 0.5 * (2.0 * std::f64::consts::PI).ln() - (1.0 - (a[i] as f64).powi(2)).ln();
        assert!((lp[i] as f64 - want).abs() < 2e-3 * want.abs().max(1.0), "a = {}: {} vs {want}", a[i], lp[i]);
    }
    // And the density integrates to 1 over (-1, 1).
    let k = 20_000;
    let mut total = 0.0;
    for j in 0..k {
        let aa = -1.0 + (j as f64 + 0.5) * 2.0 / k as f64;
        let u = aa.atanh();
        let logp = -0.5 * ((u - mu) / sigma).powi(2) - sigma.ln() - 0.5 * (2.0 * std::f64::consts::PI).ln() - (1.0 - aa * aa).ln();
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
        assert!((target1[i] - want).abs() <= 1e-6 * want.abs().max(1.0), "target param {i}: {} vs {want}", target1[i]);
    }
    assert_ne!(sac.alpha(), 1.0, "alpha is tuned");
}

#[test]
fn gradients_do_not_reach_frozen_modules() {
    let sim = Arc::new(SimConfig::default());
    let m = map();
    let sac = sac_for(&sim, &m, 2);
    let dev = sac.ad.clone();
    let x = Tensor::<2>::from_data(TensorData::new(vec![0.1f32; 2 * 18], [2, 18]), &dev).require_grad();
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

#[test]
fn checkpoint_restore_continues_exactly() {
    let sim = Arc::new(SimConfig::default());
    let (r, m) = replay_from_sim(&sim, 64);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let batches: Vec<Batch> = (0..6).map(|_| r.sample(&mut rng, 16).expect("batch")).collect();
    let mut a = sac_for(&sim, &m, 3);
    for b in &batches[..3] {
        a.update(b);
    }
    let dir = std::env::temp_dir().join(format!("sf-sac-ckpt-{}", std::process::id()));
    checkpoint::save(&a, &dir).expect("save");
    checkpoint::save(&a, &dir).expect("save over an existing checkpoint");
    for b in &batches[3..] {
        a.update(b);
    }
    let mut b = sac_for(&sim, &m, 77);
    checkpoint::restore(&mut b, &dir).expect("restore");
    assert_eq!(b.updates, 3);
    for batch in &batches[3..] {
        b.update(batch);
    }
    assert_eq!(flat(&a.actor), flat(&b.actor), "actor differs after restore");
    assert_eq!(flat(&a.critic), flat(&b.critic), "critic differs after restore");
    assert_eq!(flat(&a.target), flat(&b.target), "target differs after restore");
    assert_eq!(a.alpha(), b.alpha());
    // A corrupt checkpoint is refused and leaves the learner as it was.
    std::fs::write(dir.join("critic.bpk"), b"not a record").expect("corrupt");
    let before = flat(&b.critic);
    let e = checkpoint::restore(&mut b, &dir).expect_err("corrupt checkpoint");
    assert!(e.to_string().contains("critic"), "{e}");
    assert_eq!(flat(&b.critic), before);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A rollout step's observations (query-centric) share each agent's own-frame history among
/// all observers: the worker encodes every agent once per step, and the actions are those of
/// encoding each observation's copies.
#[test]
fn a_rollout_step_encodes_each_agent_history_once_and_acts_the_same() {
    let sim = Arc::new(SimConfig::default());
    let m = map();
    let mut v = VecEnv::new(m.clone(), sim.clone(), VecEnvConfig { n_envs: 2, mode: Mode::MultiAgent, vehicles: (10, 12), seed: 5 });
    let spec = v.spec.clone();
    assert_eq!(spec.layout, sf_sim::Layout::QueryCentric);
    let mut acts = vec![Action::default(); v.alive().len()];
    for _ in 0..12 {
        for (i, a) in acts.iter_mut().enumerate() {
            *a = route_follower(&spec, &v.observations()[i * spec.len..(i + 1) * spec.len], &sim.vehicle, 2, 0.5);
        }
        v.step(&acts);
    }
    let (mut rows, mut ids) = (Vec::new(), Vec::new());
    for r in (0..v.alive().len()).filter(|&r| v.alive()[r] == 1.0) {
        rows.extend_from_slice(&v.observations()[r * spec.len..(r + 1) * spec.len]);
        ids.push(0u32);
    }
    let b = ids.len();
    assert!(b >= 16, "two environments of 10-12 live vehicles ({b})");
    let segs = MapSegments::build(&m, sim.obs.segment_points);
    let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).expect("cpu");
    let actor = sf_nn::Actor::new(&tiny_net(), 7, &device);
    let runner = sf_sac::inference::PolicyRunner::new(actor, &tiny_net(), &spec, sim.dt_s, &[&segs], 1, &device);
    let (shared, copies) = (runner.batch(&rows, &ids), runner.batch_unshared(&rows, &ids));
    assert!(matches!(shared.histories, sf_nn::AgentInput::Shared { .. }));
    let n = spec.neighbours;
    assert_eq!(copies.histories.encoded_histories(), b * (n + 1));
    // Each live agent once, plus at most one empty neighbour slot.
    assert!(shared.histories.encoded_histories() <= b + 1, "{} distinct histories for {b} agents", shared.histories.encoded_histories());
    let (a, c) = (runner.mean_of(&shared), runner.mean_of(&copies));
    let diff = a.iter().zip(&c).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(diff < 1e-5, "shared and per-observation encodings act differently: {diff}");
    assert!(a.iter().any(|x| x.abs() > 1e-3), "the actions are not all zero");
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
    let cfg = SacConfig { seed: 2, batch_size: 32, lr_actor: 1e-3, initial_alpha: 0.5, bc_updates: 300, bc_log_std: -2.0, ..SacConfig::default() };
    let mut sac = Sac::new(cfg, tiny_net(), spec, sim.dt_s, &[&segs]).expect("sac");
    let probe = r.sample(&mut ChaCha8Rng::seed_from_u64(5), 128).expect("probe batch");
    let mse = |sac: &Sac| -> f32 {
        let (actor, table) = sac.policy();
        let a: Vec<f32> = actor.act_mean(&sac.obs_batch(&probe.obs, &probe.map_ids), table.as_ref()).into_data().try_to_vec().expect("f32");
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
        let (q1, q2, enc, actor) = (flat(&sac.critic.q1), flat(&sac.critic.q2), flat(&sac.critic.enc), flat(&sac.actor));
        sac.update(&r.sample(&mut rng, 16).expect("batch"));
        assert_ne!(q1, flat(&sac.critic.q1), "update {k}: Q1 head unchanged");
        assert_ne!(q2, flat(&sac.critic.q2), "update {k}: Q2 head unchanged");
        assert_ne!(enc, flat(&sac.critic.enc), "update {k}: critic encoder unchanged");
        assert_ne!(actor, flat(&sac.actor), "update {k}: actor unchanged");
    }
}

/// `drive` with IDM residuals: the role records its raw action (the residual, here zero) while
/// the vehicles drive the IDM demonstrator's action, so a zero residual replays the
/// demonstrator exactly.
#[test]
fn a_zero_idm_residual_drives_exactly_like_the_demonstrator() {
    use sf_sac::drive::{apply, decide, Actor, Drivers};
    let sim = Arc::new(SimConfig::default());
    let m = map();
    let run = |residual: bool| {
        let mut v = vec![VecEnv::new(m.clone(), sim.clone(), VecEnvConfig { n_envs: 2, mode: Mode::MultiAgent, vehicles: (6, 10), seed: 11 })];
        let d = Drivers { alive: Actor::Demo { noise: 0.0, residual }, background: None, adversary: None };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut recorded = Vec::new();
        for _ in 0..30 {
            let dec = decide(&mut v, &d, &mut rng);
            assert_eq!(dec.alive_residual, residual);
            recorded.extend_from_slice(&dec.alive_actions[0]);
            apply(&mut v, &dec);
        }
        (v[0].observations().to_vec(), recorded)
    };
    let (direct_obs, direct_actions) = run(false);
    let (residual_obs, residual_actions) = run(true);
    assert_eq!(direct_obs, residual_obs, "same trajectories");
    assert!(residual_actions.iter().all(|&a| a == 0.0), "a residual role records its residual");
    assert!(direct_actions.iter().any(|&a| a != 0.0), "the demonstrator's own actions are recorded as they are");
}
