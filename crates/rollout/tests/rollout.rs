//! Running policies in simulators: batched inference, the zero residual (ladder L0), braking
//! segments and an external ego through the evaluation path.

use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sf_nn::NetConfig;
use sf_rollout::inference::PolicyRunner;
use sf_sim::obs::{MapSegments, ObsSpec};
use sf_sim::policy::route_follower;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Map, Mode, SimConfig};

fn tiny_net() -> NetConfig {
    NetConfig { d_model: 16, set_hidden: 16, head_hidden: 32, heads: 2, ..NetConfig::fast() }
}

/// An untrained actor of [`tiny_net`] (seed 7) on the CPU, reading `m`'s segments.
fn tiny_runner(m: &Map, spec: &ObsSpec, sim: &SimConfig) -> PolicyRunner {
    let segs = MapSegments::build(m, sim.obs.segment_points);
    let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).expect("cpu");
    PolicyRunner::new(
        sf_nn::Actor::new(&tiny_net(), 7, &device),
        &tiny_net(),
        spec,
        sim.dt_s,
        &[&segs],
        sf_job::PolicyVersion::new(1),
        &device,
    )
}

fn map() -> Arc<Map> {
    let p = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../configs/scenarios/merge.json");
    Arc::new(Map::load(&p).expect("merge loads"))
}

/// A rollout step's observations (query-centric) share each agent's own-frame history among
/// all observers: the worker encodes every agent once per step, and the actions are those of
/// encoding each observation's copies.
#[test]
fn a_rollout_step_encodes_each_agent_history_once_and_acts_the_same() {
    let sim = Arc::new(SimConfig::default());
    let m = map();
    let mut v = VecEnv::new(
        m.clone(),
        sim.clone(),
        VecEnvConfig { n_envs: 2, mode: Mode::MultiAgent, vehicles: (10, 12), seed: 5 },
    );
    let spec = v.spec.clone();
    assert_eq!(spec.layout, sf_sim::Layout::QueryCentric);
    let mut acts = vec![Action::default(); v.alive().len()];
    for _ in 0..12 {
        for (i, a) in acts.iter_mut().enumerate() {
            *a = route_follower(
                &spec,
                &v.observations()[i * spec.len..(i + 1) * spec.len],
                &sim.vehicle,
                2,
                0.5,
            );
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
    let runner = tiny_runner(&m, &spec, &sim);
    let (shared, copies) = (runner.batch(&rows, &ids), runner.batch_unshared(&rows, &ids));
    assert!(matches!(shared.histories, sf_nn::AgentInput::Shared { .. }));
    let n = spec.neighbours;
    assert_eq!(copies.histories.encoded_histories(), b * (n + 1));
    // Each live agent once, plus at most one empty neighbour slot.
    assert!(
        shared.histories.encoded_histories() <= b + 1,
        "{} distinct histories for {b} agents",
        shared.histories.encoded_histories()
    );
    let (a, c) = (runner.mean_of(&shared), runner.mean_of(&copies));
    let diff = a.iter().zip(&c).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(diff < 1e-5, "shared and per-observation encodings act differently: {diff}");
    assert!(a.iter().any(|x| x.abs() > 1e-3), "the actions are not all zero");
}

/// `drive` with IDM residuals: the role records its raw action (the residual, here zero) while
/// the vehicles drive the IDM demonstrator's action, so a zero residual replays the
/// demonstrator exactly; the oracle labels are those actions.
#[test]
fn a_zero_idm_residual_drives_exactly_like_the_demonstrator() {
    use sf_rollout::drive::{apply, decide, Actor, Drivers};
    use sf_sim::DriveAction;
    let sim = Arc::new(SimConfig::default());
    let m = map();
    let run = |action: DriveAction| {
        let mut v = vec![VecEnv::new(
            m.clone(),
            sim.clone(),
            VecEnvConfig { n_envs: 2, mode: Mode::MultiAgent, vehicles: (6, 10), seed: 11 },
        )];
        let d = Drivers {
            alive: Actor::Demo { noise: 0.0, action },
            background: None,
            adversary: None,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut recorded = Vec::new();
        for _ in 0..30 {
            let dec = decide(&mut v, &d, &mut rng);
            assert_eq!(dec.alive_action, action);
            // The oracle labels (`sac.bc_target = "oracle"`) of the same rows in the same
            // state are the noise-free demonstrator's actions, row for row.
            assert_eq!(
                sf_rollout::drive::oracle_labels(&v, &dec.alive_rows, action),
                dec.alive_actions
            );
            recorded.extend_from_slice(&dec.alive_actions[0]);
            apply(&mut v, &dec);
        }
        (v[0].observations().to_vec(), recorded)
    };
    let (direct_obs, direct_actions) = run(DriveAction::Direct);
    let (residual_obs, residual_actions) = run(DriveAction::IdmResidual);
    assert_eq!(direct_obs, residual_obs, "same trajectories");
    assert!(residual_actions.iter().all(|&a| a == 0.0), "a residual role records its residual");
    assert!(
        direct_actions.iter().any(|&a| a != 0.0),
        "the demonstrator's own actions are recorded as they are"
    );
}

/// Braking segments in a residual warm-up: each row holds one value in [-1, -0.2] for 4 to 12
/// steps (the recorded action is the applied one), then may start another.
#[test]
fn braking_segments_hold_a_braking_residual_for_4_to_12_steps() {
    use sf_rollout::drive::{apply, decide, Actor, Drivers, WarmupSegments};
    use sf_sim::env::Controller;
    use sf_sim::DriveAction;
    let sim = Arc::new(SimConfig::default());
    let mut v = vec![VecEnv::new(
        map(),
        sim,
        VecEnvConfig {
            n_envs: 3,
            mode: Mode::Ego { background: Controller::Idm },
            vehicles: (4, 6),
            seed: 2,
        },
    )];
    let d = Drivers {
        alive: Actor::Demo { noise: 0.0, action: DriveAction::IdmAccelResidual },
        background: None,
        adversary: None,
    };
    let mut brakes = WarmupSegments::new(1.0, 0.0, &v);
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    // Per row: the run of equal values so far.
    let mut runs: std::collections::BTreeMap<usize, (f32, u32)> = Default::default();
    let mut finished_runs = Vec::new();
    for _ in 0..60 {
        let mut dec = decide(&mut v, &d, &mut rng);
        brakes.overlay(&mut dec, &mut rng);
        for (j, &r) in dec.alive_rows[0].iter().enumerate() {
            let a = dec.alive_actions[0][j];
            assert!((-1.0..=-0.2).contains(&a), "row {r}: {a}");
            let e = runs.entry(r).or_insert((a, 0));
            if e.0 == a {
                e.1 += 1;
            } else {
                finished_runs.push(e.1);
                *e = (a, 1);
            }
        }
        apply(&mut v, &dec);
        brakes.after_step(&v);
        for (r, st) in v[0].row_steps().iter().enumerate() {
            if st.ended.is_some() {
                runs.remove(&r);
            }
        }
    }
    assert!(!finished_runs.is_empty(), "segments ended and new ones started");
    assert!(finished_runs.iter().all(|&n| (4..=12).contains(&n)), "{finished_runs:?}");
}

/// An ego whose actions come from outside (`Actor::External`, what the Python package hands
/// in) runs through `evaluate::run_stored` exactly like the built-in IDM demonstrator when it
/// returns the same actions (zero acceleration residuals), sees one observation row per live
/// ego, and a different policy (always brake) gives different episodes.
#[test]
fn an_external_ego_evaluates_like_the_same_builtin_driver() {
    use sf_rollout::drive::Actor;
    use sf_rollout::evaluate::{run_stored, Episodes, FlowDef, FlowSetup, Runners};
    use sf_sim::DriveAction;
    let m = map();
    let cases = sf_sim::case::generate(&m, 12, 7, (3, 6));
    let mut runners =
        Runners::new(sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).expect("cpu"));
    let setup = FlowSetup::new(&FlowDef::Idm, &m, None, &mut runners).expect("idm flow");
    let episodes =
        Episodes { cases: &cases.cases, seeds: 2, envs: 5, vehicles: None, svo_deg: None };
    let demo = setup.drivers(Actor::Demo { noise: 0.0, action: DriveAction::IdmAccelResidual });
    let want = run_stored(&m, &setup.sim, setup.mode, None, &episodes, &demo).expect("demo");
    let len = setup.sim.obs.layout;
    let seen = std::cell::Cell::new(0usize);
    let zero = |obs: &[f32], n: usize| {
        assert_eq!(obs.len() % n.max(1), 0, "{n} whole rows");
        seen.set(seen.get() + n);
        vec![0.0; n]
    };
    let got = run_stored(
        &m,
        &setup.sim,
        setup.mode,
        None,
        &episodes,
        &setup.drivers(Actor::External { act: &zero, action: DriveAction::IdmAccelResidual }),
    )
    .expect("external");
    assert_eq!(got, want);
    assert!(seen.get() > 24, "the external actor saw {} rows ({len:?})", seen.get());
    let brake = |_: &[f32], n: usize| vec![-1.0; n];
    let braked = run_stored(
        &m,
        &setup.sim,
        setup.mode,
        None,
        &episodes,
        &setup.drivers(Actor::External { act: &brake, action: DriveAction::IdmAccelResidual }),
    )
    .expect("brake");
    assert_ne!(braked, want);
    assert!(
        braked.iter().map(|e| e.scores.success).sum::<f32>()
            < want.iter().map(|e| e.scores.success).sum::<f32>()
    );
}

/// A job's own policy sits where its kind says: FailMaker drives the background around its
/// frozen ego, SocialCommAdv speaks the SVO message with the frozen ego driving, the others
/// drive the `alive` rows; the trained rows and actions follow the seat.
#[test]
fn a_jobs_seat_follows_its_kind() {
    use sf_job::config::JobKind;
    use sf_rollout::drive::{Actor, Decision, Seat};
    use sf_sim::DriveAction;
    assert_eq!(
        [JobKind::Ego, JobKind::Macad, JobKind::Socialcomm].map(Seat::for_job),
        [Seat::Alive; 3]
    );
    assert_eq!(
        (Seat::for_job(JobKind::Failmaker), Seat::for_job(JobKind::SocialcommAdv)),
        (Seat::Background, Seat::Adversary)
    );
    let own = Actor::Random { dim: 1 };
    let ego = Actor::Demo { noise: 0.0, action: DriveAction::IdmAccelResidual };
    let d = Seat::Background.drivers(own, None, Some(ego), None);
    assert!(matches!(
        (d.alive, d.background, d.adversary),
        (Actor::Demo { .. }, Some(Actor::Random { dim: 1 }), None)
    ));
    let d = Seat::Adversary.drivers(own, None, None, None);
    assert!(
        matches!(
            (d.alive, d.adversary),
            (Actor::Random { dim: 2 }, Some(Actor::Random { dim: 1 }))
        ),
        "a missing frozen ego drives randomly"
    );
    let d = Seat::Alive.drivers(own, Some(ego), None, None);
    assert!(matches!(
        (d.alive, d.background),
        (Actor::Random { dim: 1 }, Some(Actor::Demo { .. }))
    ));
    let dec = Decision {
        alive_rows: vec![vec![0, 2]],
        background_rows: vec![vec![1]],
        alive_actions: vec![vec![0.1, 0.2]],
        background_actions: vec![vec![0.3]],
        adversary_actions: vec![vec![0.4, 0.5]],
        ..Decision::default()
    };
    assert_eq!(Seat::Alive.trained(&dec), (&dec.alive_rows[..], &dec.alive_actions[..]));
    assert_eq!(
        Seat::Background.trained(&dec),
        (&dec.background_rows[..], &dec.background_actions[..])
    );
    assert_eq!(Seat::Adversary.trained(&dec), (&dec.alive_rows[..], &dec.adversary_actions[..]));
}

/// Loading a scenario or a finished job's policy fails with the variant of what is wrong and a
/// message naming the file or scenario.
#[test]
fn evaluation_loading_errors_name_what_is_wrong() {
    use sf_rollout::evaluate::{load_scenario, EvalError, Policy};
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let (scen, cases) = (root.join("configs/scenarios"), root.join("configs/cases"));
    let Err(e) = load_scenario(&scen, &cases, "nowhere") else { panic!("no such scenario") };
    assert!(
        matches!(e, EvalError::Scenario { .. })
            && e.to_string().starts_with("scenario `nowhere`: "),
        "{e}"
    );
    let empty = std::env::temp_dir().join(format!("sf-rollout-noc-{}", std::process::id()));
    std::fs::create_dir_all(&empty).expect("tmp");
    let Err(e) = load_scenario(&scen, &empty, "merge") else { panic!("no cases") };
    assert!(
        matches!(e, EvalError::Cases { .. }) && e.to_string().starts_with("cases of `merge` ("),
        "{e}"
    );
    std::fs::write(
        empty.join("config.toml"),
        "name = \"x\"\nkind = \"ego\"\n[env]\nscenarios = []\n",
    )
    .expect("config");
    let Err(e) = Policy::load(&empty) else { panic!("invalid config") };
    assert!(
        matches!(e, EvalError::JobFile { .. }) && e.to_string().contains("config.toml: "),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&empty);
}

/// The noise-matched IDM flow (`FlowDef::IdmNoise`): with no noise it is the IDM flow exactly,
/// on its own (every vehicle) and around the IDM driver in the ego's seat; with the learned
/// flows' noise it drives differently, and its episodes follow the seed alone.
#[test]
fn the_noise_matched_idm_flow_without_noise_is_the_idm_flow() {
    use sf_job::eval::Cell;
    use sf_rollout::evaluate::{load_scenario, run_cell, CellSize, EgoDef, FlowDef, Runners};
    let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let (m, cases) =
        load_scenario(&root.join("configs/scenarios"), &root.join("configs/cases"), "merge")
            .expect("merge and its cases");
    let mut runners =
        Runners::new(sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).expect("cpu"));
    let size = CellSize { cases: 12, seeds: 2, envs: 5 };
    let cell = |ego: &str, flow: &str| Cell {
        experiment: "flow_quality".into(),
        ego: ego.into(),
        flow: flow.into(),
        scenario: "merge".into(),
        svo_deg: None,
        vehicles: None,
    };
    let mut run = |flow: &FlowDef, ego: Option<&EgoDef>, name: &str, envs: usize| {
        let c = cell(if ego.is_some() { "IDM driver" } else { "" }, name);
        run_cell(&c, CellSize { envs, ..size }, &m, &cases, flow, ego, &mut runners).expect("cell")
    };
    let idm = run(&FlowDef::Idm, None, "idm", 5);
    let quiet = run(&FlowDef::IdmNoise { std: 0.0 }, None, "idm-noise", 5);
    assert_eq!(quiet, idm, "a zero noise drives every vehicle as the IDM flow does");
    let ego = EgoDef::Idm;
    assert_eq!(
        run(&FlowDef::IdmNoise { std: 0.0 }, Some(&ego), "idm-noise", 5),
        run(&FlowDef::Idm, Some(&ego), "idm", 5),
        "and around the IDM driver in the ego's seat"
    );
    let noisy = run(&FlowDef::IdmNoise { std: 0.3 }, None, "idm-noise", 5);
    assert_ne!(noisy, idm, "the learned flows' noise changes the episodes");
    assert_eq!(noisy, run(&FlowDef::IdmNoise { std: 0.3 }, None, "idm-noise", 5), "repeatable");
}

/// Every random draw of a stored episode is the episode's own (`Draws::PerEpisode`) and a
/// learned policy infers in fixed-width chunks (`PolicyRunner::with_fixed_width`, what
/// evaluation's runners do): the noise-matched IDM flow, a sampled learned flow and its mean
/// action end every episode identically at batch widths 1, 7 and 40.
#[test]
fn a_stored_episode_ends_the_same_at_any_batch_width() {
    use sf_rollout::drive::{Actor, Drivers};
    use sf_rollout::evaluate::{run_stored, Episodes, EVAL_INFERENCE_ROWS};
    use sf_sim::DriveAction;
    let m = map();
    let sim = Arc::new(SimConfig::default());
    let cases = sf_sim::case::generate(&m, 12, 7, (3, 6));
    let probe = VecEnvConfig { n_envs: 1, mode: Mode::MultiAgent, vehicles: (3, 3), seed: 0 };
    let spec = VecEnv::new(m.clone(), sim.clone(), probe).spec.clone();
    let runner = tiny_runner(&m, &spec, &sim).with_fixed_width(EVAL_INFERENCE_ROWS);
    let flow = |alive| Drivers { alive, background: None, adversary: None };
    let run = |d: &Drivers, envs| {
        let episodes =
            Episodes { cases: &cases.cases, seeds: 2, envs, vehicles: None, svo_deg: None };
        run_stored(&m, &sim, Mode::MultiAgent, None, &episodes, d).expect("episodes run")
    };
    let noisy = flow(Actor::IdmNoise { std: 0.3, action: DriveAction::IdmAccelResidual });
    let alone = run(&noisy, 1);
    assert_eq!(alone.len(), 24, "12 cases x 2 seeds");
    assert_eq!(run(&noisy, 7), alone, "IDM+noise: 7 simulators stepped together");
    assert_eq!(run(&noisy, 40), alone, "IDM+noise: 40 simulators, most of them idle");
    for (what, actor) in [("sampled", Actor::sampled(&runner)), ("mean", Actor::mean(&runner))] {
        let alone = run(&flow(actor), 1);
        for envs in [7, 40] {
            assert_eq!(
                run(&flow(actor), envs),
                alone,
                "learned flow ({what}) at {envs} simulators"
            );
        }
    }
    let sampled = flow(Actor::sampled(&runner));
    // The draws matter: the flow's mean action and the noise-free IDM flow end otherwise.
    assert_ne!(run(&flow(Actor::mean(&runner)), 7), run(&sampled, 7), "sampling changes episodes");
    let quiet = flow(Actor::IdmNoise { std: 0.0, action: DriveAction::IdmAccelResidual });
    assert_ne!(run(&quiet, 7), run(&noisy, 7), "the noise changes episodes");
}
