//! SAC learns: a contextual bandit on real observations whose optimal action is known.

use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sf_nn::NetConfig;
use sf_sac::{Replay, Sac, SacConfig, Transition};
use sf_sim::obs::MapSegments;
use sf_sim::policy::route_follower;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Map, Mode, SimConfig};

/// Observations from the simulator; the optimal action is the route follower's steer with
/// full speed, and the reward is minus the squared distance to it (one-step episodes).
#[test]
fn learns_a_contextual_bandit_with_a_known_optimum() {
    let sim = Arc::new(SimConfig::default());
    let p = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../configs/scenarios/roundabout.json");
    let map = Arc::new(Map::load(&p).expect("map"));
    let mut v = VecEnv::new(
        map.clone(),
        sim.clone(),
        VecEnvConfig { n_envs: 2, mode: Mode::MultiAgent, vehicles: (8, 12), seed: 4 },
    );
    let spec = v.spec.clone();
    // A pool of observations and their optimal actions.
    let mut pool: Vec<(Vec<f32>, [f32; 2])> = Vec::new();
    let mut acts = vec![Action::default(); v.alive().len()];
    while pool.len() < 600 {
        for (i, a) in acts.iter_mut().enumerate() {
            let o = &v.observations()[i * spec.len..(i + 1) * spec.len];
            *a = route_follower(&spec, o, &sim.vehicle, 2, 1.0);
            if v.alive()[i] == 1.0 {
                pool.push((o.to_vec(), [1.0, a.steer.clamp(-0.9, 0.9)]));
            }
        }
        v.step(&acts);
    }
    let net =
        NetConfig { d_model: 32, set_hidden: 32, head_hidden: 64, heads: 2, ..NetConfig::fast() };
    let segs = MapSegments::build(&map, sim.obs.segment_points);
    let cfg = SacConfig {
        batch_size: 64,
        lr_actor: 1e-3,
        lr_critic: 1e-3,
        lr_alpha: 1e-3,
        initial_alpha: 0.05,
        seed: 1,
        reward_scale: 1.0,
        ..SacConfig::default()
    };
    let mut sac = Sac::new(cfg, net, spec.clone(), sim.dt_s, &[&segs]).expect("sac");
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut replay = Replay::new(50_000, spec.len, 2);
    let err = |sac: &Sac| {
        let (actor, table) = sac.policy();
        let rows: Vec<f32> = pool.iter().take(200).flat_map(|(o, _)| o.clone()).collect();
        let ob = sac.obs_batch(&rows, &vec![0; 200]);
        let a: Vec<f32> =
            actor.act_mean(&ob, table.as_ref()).into_data().try_to_vec().expect("f32");
        pool.iter()
            .take(200)
            .enumerate()
            .map(|(i, (_, best))| (a[2 * i] - best[0]).powi(2) + (a[2 * i + 1] - best[1]).powi(2))
            .sum::<f32>()
            / 200.0
    };
    let before = err(&sac);
    let reward =
        |a: &[f32; 2], best: &[f32; 2]| -((a[0] - best[0]).powi(2) + (a[1] - best[1]).powi(2));
    for round in 0..400 {
        // Explore around the current policy: uniformly random actions (off-policy is fine).
        for _ in 0..8 {
            use rand::Rng;
            let (o, best) = &pool[rng.random_range(0..pool.len())];
            let a = [rng.random_range(-1.0f32..1.0), rng.random_range(-1.0f32..1.0)];
            replay
                .push(Transition {
                    obs: o,
                    action: &a,
                    reward: reward(&a, best),
                    next_obs: o,
                    terminal: true,
                    steps: 1,
                    map_id: 0,
                    oracle: &[],
                })
                .expect("push");
        }
        if round >= 8 {
            let b = replay.sample(&mut rng, 64).expect("batch");
            sac.update(&b);
        }
    }
    let after = err(&sac);
    // Random actions in [-1, 1]^2 are off by about 2.0 (squared) on average from the optimum.
    assert!(
        after < 0.25 * before.min(2.0),
        "squared error to the optimum: before {before:.3}, after {after:.3}"
    );
}
