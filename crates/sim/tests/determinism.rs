//! Same scenario + case + seed (+ actions) => bit-identical trajectories; thread count does
//! not change batched results.

mod common;

use std::sync::Arc;

use sf_sim::policy::route_follower;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, CaseFile, Env, Mode, Observer, SimConfig};

fn trajectory(name: &str, case_id: usize, mode: Mode) -> Vec<u32> {
    let m = common::map(name);
    let cases = CaseFile::load(&common::configs().join(format!("cases/{name}.v1.json")), &m)
        .expect("cases");
    let cfg = Arc::new(SimConfig::default());
    let mut env = Env::new(m.clone(), cfg.clone());
    env.reset(&cases.cases[case_id], mode, None).expect("reset");
    let mut ob = Observer::new(&m, &cfg);
    let mut row = vec![0.0; ob.spec.len];
    let mut bits = Vec::new();
    env.run_episode(
        |e, acts| {
            ob.prepare(e);
            for (i, a) in acts.iter_mut().enumerate() {
                if e.agents()[i].alive {
                    ob.write(e, i, &mut row);
                    *a = route_follower(&ob.spec, &row, &e.cfg.vehicle, 2, 1.0);
                }
            }
        },
        |e| {
            for a in e.agents() {
                bits.extend(
                    [a.state.x_m, a.state.y_m, a.state.theta_rad, a.state.speed_mps]
                        .map(f32::to_bits),
                );
            }
        },
    )
    .expect("episode");
    bits
}

#[test]
fn replays_are_bit_identical() {
    for name in sf_sim::scenarios::SCENARIOS {
        for mode in
            [Mode::MultiAgent, Mode::AllIdm, Mode::Ego { background: sf_sim::Controller::Idm }]
        {
            let a = trajectory(name, 3, mode);
            let b = trajectory(name, 3, mode);
            assert!(a.len() > 100);
            assert!(a == b, "{name} {mode:?}: replay differs");
        }
        assert!(
            trajectory(name, 3, Mode::AllIdm) != trajectory(name, 4, Mode::AllIdm),
            "different cases differ"
        );
    }
}

fn batched_run(threads: usize) -> (Vec<u32>, u64) {
    let m = common::map("intersection");
    let cfg = Arc::new(SimConfig::default());
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
    pool.install(|| {
        let mut v = VecEnv::new(
            m.clone(),
            cfg.clone(),
            VecEnvConfig { n_envs: 6, mode: Mode::MultiAgent, vehicles: (8, 20), seed: 11 },
        );
        let mut actions = vec![Action::default(); v.alive().len()];
        let spec = v.spec.clone();
        for _ in 0..150 {
            for (r, a) in actions.iter_mut().enumerate() {
                if v.alive()[r] != 0.0 {
                    *a = route_follower(
                        &spec,
                        &v.observations()[r * spec.len..(r + 1) * spec.len],
                        &cfg.vehicle,
                        2,
                        1.0,
                    );
                }
            }
            v.step(&actions);
        }
        let episodes = v.take_finished().len() as u64;
        (v.observations().iter().map(|x| x.to_bits()).collect(), episodes)
    })
}

#[test]
fn batched_stepping_is_independent_of_thread_count() {
    let (a, ea) = batched_run(1);
    let (b, eb) = batched_run(2);
    assert!(ea > 0, "episodes finish and reset");
    assert_eq!(ea, eb);
    assert!(a == b, "observations differ between 1 and 2 threads");
}

/// Evaluation batches stored episodes: each runs exactly once with its own case, truncation and
/// SVO, and scores exactly as when run alone, whatever the batch width.
#[test]
fn stored_episodes_run_once_each_and_score_as_alone() {
    use sf_sim::metrics::EpisodeMetrics;
    use sf_sim::vec_env::EpisodeSpec;
    let m = common::map("merge");
    let cases = CaseFile::load(&common::configs().join("cases/merge.v1.json"), &m).expect("cases");
    let cfg = Arc::new(SimConfig::default());
    let eps: Vec<EpisodeSpec> = (0..7)
        .map(|k| EpisodeSpec {
            case: cases.cases[k].clone(),
            vehicles: (k % 2 == 0).then_some(4),
            svo_deg: (k == 3).then_some(30.0),
            tag: 100 + k as u64,
        })
        .collect();
    let alone: Vec<EpisodeMetrics> = eps
        .iter()
        .map(|e| {
            let mut env = Env::new(m.clone(), cfg.clone());
            env.reset(&e.case, Mode::AllIdm, e.vehicles).expect("reset");
            env.run_episode(|_, _| {}, |_| {}).expect("episode");
            EpisodeMetrics::from_outcomes(env.outcomes(), false)
        })
        .collect();
    for width in [1, 3, 16] {
        let mut v = VecEnv::from_episodes(m.clone(), cfg.clone(), Mode::AllIdm, width, eps.clone())
            .expect("valid cases");
        let mut got = Vec::new();
        let mut guard = 0;
        while !v.is_finished() {
            let acts = vec![Action::default(); v.alive().len()];
            v.step(&acts);
            got.extend(v.take_finished_tagged());
            guard += 1;
            assert!(guard < 10_000, "never finished");
        }
        got.sort_by_key(|(t, _)| *t);
        assert_eq!(
            got.iter().map(|(t, _)| *t).collect::<Vec<_>>(),
            (100..107).collect::<Vec<_>>(),
            "width {width}"
        );
        for ((_, g), a) in got.iter().zip(&alone) {
            assert_eq!(g, a, "width {width}");
        }
        assert!(v.alive().iter().all(|&x| x == 0.0), "finished: no live rows");
    }
}

/// CoPO Stage 2: with a coordinator's Gaussian set, every agent the flow drives gets a fresh SVO
/// from it after every step (within [0, 90], around the mean), the ego of `Mode::Ego` keeps
/// its own, stored episodes draw the same SVOs whatever the batch width, and `None` stops it.
#[test]
fn a_coordinator_gaussian_redraws_flow_svos_every_step_but_not_the_egos() {
    use sf_sim::vec_env::EpisodeSpec;
    use sf_sim::{Controller, SvoGaussian};
    let m = common::map("roundabout");
    let cases =
        CaseFile::load(&common::configs().join("cases/roundabout.v1.json"), &m).expect("cases");
    let cfg = Arc::new(SimConfig::default());
    let g = SvoGaussian { mean_deg: 72.0, std_deg: 4.5 };
    let mode = Mode::Ego { background: Controller::Idm };
    let eps: Vec<EpisodeSpec> = (0..4)
        .map(|k| EpisodeSpec {
            case: cases.cases[k].clone(),
            vehicles: None,
            svo_deg: None,
            tag: k as u64,
        })
        .collect();
    let run = |width: usize| {
        let mut v = VecEnv::from_episodes(m.clone(), cfg.clone(), mode, width, eps.clone())
            .expect("valid cases");
        v.set_svo_gaussian(Some(g));
        let ego_svo = v.env(0).agents()[0].svo_deg;
        assert_eq!(ego_svo, cases.cases[0].vehicles[0].svo_deg, "the ego keeps the case's SVO");
        let mut per_step: Vec<Vec<u32>> = Vec::new();
        let mut draws = Vec::new();
        for _ in 0..5 {
            let svos: Vec<f32> = v.env(0).agents().iter().skip(1).map(|a| a.svo_deg).collect();
            assert!(svos.iter().all(|s| (0.0..=90.0).contains(s)));
            draws.extend_from_slice(&svos);
            per_step.push(svos.iter().map(|s| s.to_bits()).collect());
            assert_eq!(v.env(0).agents()[0].svo_deg, ego_svo, "the ego's SVO is not redrawn");
            v.step(&vec![Action::default(); v.alive().len()]);
        }
        assert!(per_step.windows(2).all(|w| w[0] != w[1]), "SVOs are redrawn every step");
        (per_step, draws, v)
    };
    let (a, draws, mut v) = run(1);
    let (b, _, _) = run(3);
    assert_eq!(a, b, "draws of a stored episode do not depend on the batch width");
    let mean = draws.iter().sum::<f32>() / draws.len() as f32;
    assert!((mean - 72.0).abs() < 3.0, "mean of the draws {mean}");
    let case_svos: Vec<f32> = cases.cases[0].vehicles.iter().skip(1).map(|c| c.svo_deg).collect();
    assert!(
        case_svos.iter().any(|s| (s - 72.0).abs() > 15.0),
        "the case's own SVOs are spread, so the test can tell them apart"
    );
    v.set_svo_gaussian(None);
    let before: Vec<f32> = v.env(0).agents().iter().map(|a| a.svo_deg).collect();
    v.step(&vec![Action::default(); v.alive().len()]);
    let after: Vec<f32> = v.env(0).agents().iter().map(|a| a.svo_deg).collect();
    assert_eq!(before, after, "without a Gaussian SVOs stay put");
}
