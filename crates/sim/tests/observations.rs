//! Observation invariants in both layouts.
#![allow(clippy::needless_range_loop)]

mod common;

use std::f32::consts::PI;
use std::sync::Arc;

use sf_sim::case::random_case;
use sf_sim::config::{Layout, SvoVisibility};
use sf_sim::obs::{Observer, AGENT_CTX, AGENT_FEATS, MAP_FEATS, POS_SCALE_M, SEG_POSE};
use sf_sim::policy::route_follower;
use sf_sim::{Action, Env, Mode, SimConfig};

fn check_layout(layout: Layout) {
    use rand::SeedableRng;
    let mut cfg = SimConfig::default();
    cfg.obs.layout = layout;
    cfg.obs.svo = SvoVisibility::All;
    cfg.obs.ego_flag = true;
    let cfg = Arc::new(cfg);
    for name in sf_sim::scenarios::SCENARIOS {
        let m = common::map(name);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let case = random_case(&m, &mut rng, 0, 20);
        let mut env = Env::new(m.clone(), cfg.clone());
        env.reset(&case, Mode::MultiAgent, None).expect("reset");
        let mut ob = Observer::new(&m, &cfg);
        let spec = ob.spec.clone();
        let mut row = vec![f32::NAN; spec.len];
        let r = cfg.obs.radius_m / POS_SCALE_M + 1e-4;
        let h = cfg.obs.history;
        let mut actions = vec![Action::default(); env.len()];
        for step in 0..30 {
            ob.prepare(&env);
            for i in 0..env.len() {
                if !env.agents()[i].alive {
                    continue;
                }
                ob.write(&env, i, &mut row);
                assert!(row.iter().all(|v| v.is_finite()), "{name}: non-finite value");
                // Own current pose at the origin facing +x; speed normalised.
                let cur = &row[spec.ego_hist.start + (h - 1) * AGENT_FEATS..][..AGENT_FEATS];
                assert!(
                    cur[0].abs() < 1e-5 && cur[1].abs() < 1e-5 && cur[2].abs() < 1e-5,
                    "{name}: {cur:?}"
                );
                assert!((cur[3] - env.agents()[i].state.speed_mps / 6.0).abs() < 1e-5);
                assert_eq!(row[spec.ego_ctx.start + 1], if i == 0 { 1.0 } else { 0.0 });
                assert!((row[spec.ego_ctx.start] - env.agents()[i].svo_deg / 90.0).abs() < 1e-6);
                // Neighbours: masked, within the radius, headings as unit vectors, nearest first.
                let mask = &row[spec.agents_mask.clone()];
                let live_near = env
                    .agents()
                    .iter()
                    .enumerate()
                    .filter(|(j, b)| {
                        *j != i
                            && b.alive
                            && sf_sim::geom::dist(b.state.pos(), env.agents()[i].state.pos())
                                <= 50.0
                    })
                    .count();
                assert_eq!(
                    mask.iter().filter(|&&v| v == 1.0).count(),
                    live_near.min(spec.neighbours),
                    "{name}: neighbour count"
                );
                let mut last_d = 0.0;
                for (slot, &mv) in mask.iter().enumerate() {
                    let c = &row[spec.agents_ctx.start + slot * AGENT_CTX..][..AGENT_CTX];
                    if mv == 0.0 {
                        assert!(
                            c.iter().all(|&v| v == 0.0),
                            "{name}: masked neighbour carries data"
                        );
                        continue;
                    }
                    let d = (c[0] * c[0] + c[1] * c[1]).sqrt();
                    assert!(d <= r && d + 1e-6 >= last_d, "{name}: neighbour {slot} at {d}");
                    last_d = d;
                    assert!((c[2] * c[2] + c[3] * c[3] - 1.0).abs() < 1e-4);
                    if layout == Layout::QueryCentric {
                        // Own-frame history: its current frame is at its own origin.
                        let hc = &row[spec.agents_hist.start + (slot * h + h - 1) * AGENT_FEATS..]
                            [..AGENT_FEATS];
                        assert!(hc[0].abs() < 1e-5 && hc[1].abs() < 1e-5 && hc[2].abs() < 1e-5);
                    } else {
                        let hc = &row[spec.agents_hist.start + (slot * h + h - 1) * AGENT_FEATS..]
                            [..AGENT_FEATS];
                        assert!((hc[0] - c[0]).abs() < 1e-5 && (hc[1] - c[1]).abs() < 1e-5);
                    }
                }
                // Route: ahead of the agent in its frame, masked at the end.
                let rm = &row[spec.route_mask.clone()];
                let first = &row[spec.route.clone()][..4];
                if rm[0] == 1.0 {
                    assert!(first[0] > -0.1, "{name}: first route point behind: {first:?}");
                }
                // Map pieces.
                match layout {
                    Layout::QueryCentric => {
                        let n = row[spec.seg_mask.clone()].iter().filter(|&&v| v == 1.0).count();
                        assert!(n > 0, "{name}: no map segment in reach");
                        for s in 0..n {
                            let id = row[spec.seg_id.start + s];
                            assert!(
                                id >= 0.0 && (id as usize) < ob.segments.len() && id.fract() == 0.0
                            );
                            let p = &row[spec.seg_pose.start + s * SEG_POSE..][..SEG_POSE];
                            assert!((p[2] * p[2] + p[3] * p[3] - 1.0).abs() < 1e-4);
                        }
                    }
                    Layout::EgoFrame => {
                        let mm = &row[spec.map_mask.clone()];
                        assert!(mm.contains(&1.0), "{name}: no map point");
                        for (k, &v) in mm.iter().enumerate() {
                            let f = &row[spec.map.start + k * MAP_FEATS..][..MAP_FEATS];
                            if v == 1.0 {
                                assert!(
                                    (f[0] * f[0] + f[1] * f[1]).sqrt() <= r,
                                    "{name}: map point beyond radius"
                                );
                                assert!(f[2].abs() <= 1.0 + 1e-6);
                            } else {
                                assert!(f.iter().all(|&x| x == 0.0));
                            }
                        }
                    }
                }
                // What the learner checks at ingest passes on every real row, and a row with one
                // mask or segment id out of its range is refused.
                spec.check_row(&row, ob.segments.len())
                    .unwrap_or_else(|e| panic!("{name}: a real observation refused: {e}"));
                let mut bad = row.clone();
                bad[spec.agents_mask.start] = 0.5;
                assert!(spec
                    .check_row(&bad, ob.segments.len())
                    .expect_err("fractional mask")
                    .to_string()
                    .contains("agents_mask[0]"));
                if layout == Layout::QueryCentric {
                    let mut bad = row.clone();
                    bad[spec.seg_id.start] = ob.segments.len() as f32;
                    assert!(spec
                        .check_row(&bad, ob.segments.len())
                        .expect_err("segment id past the map")
                        .to_string()
                        .contains("seg_id[0]"));
                    bad[spec.seg_id.start] = -1.0;
                    assert!(spec.check_row(&bad, ob.segments.len()).is_err());
                }
                actions[i] = route_follower(
                    &spec,
                    &row,
                    &cfg.vehicle,
                    2,
                    if step % 7 == 0 { 0.0 } else { 1.0 },
                );
            }
            if env.done() {
                break;
            }
            env.step(&actions).expect("step");
        }
    }
}

#[test]
fn query_centric_invariants() {
    check_layout(Layout::QueryCentric);
}

#[test]
fn ego_frame_invariants() {
    check_layout(Layout::EgoFrame);
}

/// A segment's stored shape, placed at its observed pose, reproduces the world geometry.
#[test]
fn query_centric_segments_round_trip_to_world() {
    let m = common::map("roundabout");
    let cfg = SimConfig::default();
    let ob = Observer::new(&m, &cfg);
    let s = &ob.segments;
    let p = s.points;
    for k in (0..s.len()).step_by(7) {
        for q in 0..s.counts[k] {
            let f = &s.local_feats[(k * p + q) * MAP_FEATS..][..MAP_FEATS];
            let w = s.frames[k].to_world([f[0] * POS_SCALE_M, f[1] * POS_SCALE_M]);
            assert!(sf_sim::geom::dist(w, s.world[k * p + q]) < 1e-3);
            assert!(f[2].abs() <= 1.0 + 1e-6 && (f[2] * PI).is_finite());
        }
    }
}

#[test]
fn visibility_none_hides_svo() {
    let m = common::map("merge");
    let cfg = Arc::new(SimConfig::default());
    assert_eq!(cfg.obs.svo, SvoVisibility::None);
    let c = common::case(&[
        (common::spawn_for(&m, 0, 0), 0, 45.0),
        (common::spawn_for(&m, 0, 2), 0, 80.0),
    ]);
    let mut env = Env::new(m.clone(), cfg.clone());
    env.reset(&c, Mode::MultiAgent, None).expect("reset");
    let mut ob = Observer::new(&m, &cfg);
    ob.prepare(&env);
    let mut row = vec![0.0; ob.spec.len];
    ob.write(&env, 0, &mut row);
    assert_eq!(row[ob.spec.ego_ctx.start], 0.0);
    assert_eq!(row[ob.spec.agents_mask.start], 1.0);
    assert_eq!(row[ob.spec.agents_ctx.start + 4], 0.0);
}

/// A frozen learned flow drives the background: its rows are observed and flagged apart from
/// the ego's, and with IDM background they never are.
#[test]
fn externally_driven_background_rows_are_observed_and_flagged() {
    use sf_sim::vec_env::{VecEnv, VecEnvConfig};
    use sf_sim::Controller;
    let m = common::map("merge");
    let cfg = Arc::new(SimConfig::default());
    let mut v = VecEnv::new(
        m.clone(),
        cfg.clone(),
        VecEnvConfig {
            n_envs: 2,
            mode: Mode::Ego { background: Controller::External },
            vehicles: (4, 6),
            seed: 1,
        },
    );
    let per = v.max_agents;
    for _ in 0..5 {
        for k in 0..v.n_envs() {
            let env = v.env(k);
            for i in 0..per {
                let row = k * per + i;
                let a = env.agents().get(i);
                assert_eq!(
                    v.alive()[row] == 1.0,
                    i == 0 && a.is_some_and(|a| a.alive),
                    "ego row {row}"
                );
                assert_eq!(
                    v.background()[row] == 1.0,
                    i > 0 && a.is_some_and(|a| a.alive),
                    "background row {row}"
                );
                let filled = v.observations()[row * v.spec.len..(row + 1) * v.spec.len]
                    .iter()
                    .any(|&x| x != 0.0);
                assert_eq!(
                    filled,
                    v.alive()[row] == 1.0 || v.background()[row] == 1.0,
                    "row {row} filled iff observed"
                );
            }
        }
        let acts =
            vec![Action { ref_speed: 0.5, steer: 0.0, ..Action::default() }; v.alive().len()];
        v.step(&acts);
    }
    let idm = VecEnv::new(
        m,
        cfg,
        VecEnvConfig {
            n_envs: 2,
            mode: Mode::Ego { background: Controller::Idm },
            vehicles: (4, 6),
            seed: 1,
        },
    );
    assert!(idm.background().iter().all(|&b| b == 0.0), "IDM background is not observed");
}

/// SocialCommAdv: the adversary's message reaches only background agents within the ego's
/// radius, and only as what they are told of the ego's SVO; everyone's genuine SVO and what
/// agents see of each other are unchanged; `None` restores the genuine SVO.
#[test]
fn the_adversary_message_reaches_only_background_agents_near_the_ego_as_the_egos_svo() {
    use sf_sim::vec_env::{VecEnv, VecEnvConfig};
    use sf_sim::Controller;
    let m = common::map("intersection");
    let mut sim = SimConfig::default();
    sim.obs.svo = SvoVisibility::All;
    sim.obs.ego_flag = true;
    sim.obs.radius_m = 30.0;
    let sim = Arc::new(sim);
    let mut v = VecEnv::new(
        m,
        sim.clone(),
        VecEnvConfig {
            n_envs: 3,
            mode: Mode::Ego { background: Controller::External },
            vehicles: (12, 12),
            seed: 7,
        },
    );
    let (per, len) = (v.max_agents, v.spec.len);
    let genuine: Vec<Vec<f32>> =
        (0..3).map(|k| v.env(k).agents().iter().map(|a| a.svo_deg).collect()).collect();
    v.communicate_ego_svo(&[Some(77.0), None, Some(5.0)]);
    let (mut near, mut far) = (0, 0);
    for (k, msg) in [(0, Some(77.0)), (1, None), (2, Some(5.0))] {
        let env = v.env(k);
        let ego = env.agents()[0].state.pos();
        assert_eq!(
            env.agents().iter().map(|a| a.svo_deg).collect::<Vec<_>>(),
            genuine[k],
            "genuine SVOs untouched"
        );
        for i in 1..env.len() {
            let within = sf_sim::geom::dist(env.agents()[i].state.pos(), ego) <= sim.obs.radius_m;
            let told = env.communicated_svo_deg(i, 0);
            match msg {
                Some(s) if within => {
                    near += 1;
                    assert_eq!(told, s, "env {k} agent {i} is within the radius");
                }
                _ => {
                    far += usize::from(msg.is_some());
                    assert_eq!(told, genuine[k][0], "env {k} agent {i} sees the genuine SVO");
                }
            }
            for j in 1..env.len() {
                assert_eq!(
                    env.communicated_svo_deg(i, j),
                    genuine[k][j],
                    "others' SVOs as they are"
                );
            }
            assert_eq!(env.communicated_svo_deg(0, i), genuine[k][i], "the ego is told nothing");
            // The observation row carries it in the ego's neighbour entry (the flagged one).
            let row = &v.observations()[(k * per + i) * len..][..len];
            for j in 0..v.spec.neighbours {
                let c = &row[v.spec.agents_ctx.start + j * AGENT_CTX..][..AGENT_CTX];
                if row[v.spec.agents_mask.start + j] == 1.0 && c[5] == 1.0 {
                    assert!(
                        (c[4] - told / 90.0).abs() < 1e-6,
                        "env {k} agent {i}: row shows {} not {}",
                        c[4] * 90.0,
                        told
                    );
                }
            }
        }
    }
    assert!(
        near > 0 && far > 0,
        "the case must put agents on both sides of the radius ({near} near, {far} far)"
    );
}

/// FailMaker draws c from [-90, 90]: a case's stored SVO in [0, 90] maps linearly onto the
/// configured range at reset, and the observation carries c / 90.
#[test]
fn the_svo_range_maps_stored_svos_linearly() {
    let m = common::map("merge");
    let mut cfg = SimConfig { svo_range_deg: [-90.0, 90.0], ..SimConfig::default() };
    cfg.obs.svo = SvoVisibility::Own;
    let cfg = Arc::new(cfg);
    let c = common::case(&[
        (common::spawn_for(&m, 0, 0), 0, 0.0),
        (common::spawn_for(&m, 0, 1), 0, 45.0),
        (common::spawn_for(&m, 0, 2), 0, 90.0),
    ]);
    let mut env = Env::new(m.clone(), cfg.clone());
    env.reset(&c, Mode::MultiAgent, None).expect("reset");
    assert_eq!(env.agents().iter().map(|a| a.svo_deg).collect::<Vec<_>>(), vec![-90.0, 0.0, 90.0]);
    let mut ob = Observer::new(&m, &cfg);
    ob.prepare(&env);
    let mut row = vec![0.0; ob.spec.len];
    ob.write(&env, 0, &mut row);
    assert_eq!(row[ob.spec.ego_ctx.start], -1.0);
    let bad = SimConfig { svo_range_deg: [10.0, -10.0], ..SimConfig::default() };
    assert_eq!(bad.validate().expect_err("reversed").field, "svo_range_deg");
}

/// `ObsSpec::blocks` tiles the row exactly, in order, with shapes that multiply out to their
/// ranges (the Python package's dict observations and the ONNX inputs rely on it).
#[test]
fn blocks_tile_the_row_in_both_layouts() {
    for layout in [Layout::EgoFrame, Layout::QueryCentric] {
        let mut cfg = SimConfig::default();
        cfg.obs.layout = layout;
        let spec = sf_sim::ObsSpec::new(&cfg.obs);
        let mut at = 0;
        for (name, r, shape) in spec.blocks() {
            assert_eq!(r.start, at, "{name} starts where the previous block ended");
            assert_eq!(r.len(), shape.iter().product::<usize>(), "{name}: {shape:?}");
            at = r.end;
        }
        assert_eq!(at, spec.len);
        let names: Vec<&str> = spec.blocks().iter().map(|b| b.0).collect();
        assert_eq!(names.contains(&"seg_id"), layout == Layout::QueryCentric);
        assert_eq!(names.contains(&"map"), layout == Layout::EgoFrame);
        assert_eq!(Layout::parse(layout.as_str()), Ok(layout));
    }
    assert!(Layout::parse("polar").unwrap_err().to_string().contains("ego-frame"));
    for a in [
        sf_sim::DriveAction::Direct,
        sf_sim::DriveAction::IdmResidual,
        sf_sim::DriveAction::IdmAccelResidual,
    ] {
        assert_eq!(sf_sim::DriveAction::parse(a.as_str()), Ok(a));
    }
    assert!(sf_sim::DriveAction::parse("fly")
        .unwrap_err()
        .to_string()
        .contains("idm-accel-residual"));
}
