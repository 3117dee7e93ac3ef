//! The IDM acceleration residual (`Action::idm_accel`, `DriveAction::IdmAccelResidual`): a zero
//! residual is the IDM driver bit for bit (rung L0 of the learning ladder), and -1 stops the car
//! with full brake authority whatever IDM commands.

mod common;

use common::{case, env, map, spawn_for};
use sf_sim::env::{Controller, Mode};
use sf_sim::vehicle::{Action, DriveAction};

fn residual(r: f32) -> Action {
    DriveAction::IdmAccelResidual.command(&[r], None)
}

/// L0: on the stored cases of every scenario, an ego driven by a zero acceleration residual
/// follows the same trajectory as the same vehicle driven by IDM (every vehicle IDM), to the
/// last bit, and ends the same way.
#[test]
fn a_zero_residual_ego_drives_exactly_like_the_idm_driver() {
    common::assert_ego_drives_like_idm(|_| residual(0.0));
}

/// -1 brakes at the vehicle's full deceleration on a free road, where IDM still accelerates
/// (~4.7 m/s^2 at 6 m/s towards its desired 12 m/s): from 6 m/s to rest within 1.25 s plus one
/// decision step, against 3.85 s for the PID at Kp = 1. (An offset `a_idm - 5` failed this.)
#[test]
fn a_full_negative_residual_stops_the_car_from_full_speed() {
    let m = map("merge");
    let mut e = env(&m);
    e.reset(&case(&[(spawn_for(&m, 0, 0), 0, 0.0)]), Mode::MultiAgent, None).expect("reset");
    let (p0, th) = (e.agents()[0].state.pos(), e.agents()[0].state.theta_rad);
    e.place_agent(0, p0, th, 6.0);
    let dt_s = 0.25;
    let mut t_s = 0.0;
    while e.agents()[0].state.speed_mps > 0.0 {
        e.step(&[residual(-1.0)]).expect("step");
        t_s += dt_s;
        assert!(t_s <= 1.5, "still at {} m/s after {t_s} s", e.agents()[0].state.speed_mps);
    }
    // A positive residual cannot exceed v_max; NaN counts as zero (drives as IDM).
    e.step(&[residual(f32::NAN)]).expect("step");
    assert!(e.agents()[0].state.speed_mps > 0.0, "IDM accelerates from rest on a free road");
}

/// The residual moves IDM's acceleration linearly to -max at -1 and +max at +1.
#[test]
fn the_residual_interpolates_between_full_braking_idm_and_full_acceleration() {
    use sf_sim::env::residual_accel;
    for a_idm in [-3.0f32, 0.0, 4.7] {
        assert_eq!(residual_accel(a_idm, Some(0.0), 5.0), a_idm);
        assert_eq!(residual_accel(a_idm, None, 5.0), a_idm);
        assert!((residual_accel(a_idm, Some(-1.0), 5.0) + 5.0).abs() < 1e-6);
        assert!((residual_accel(a_idm, Some(1.0), 5.0) - 5.0).abs() < 1e-6);
        assert!((residual_accel(a_idm, Some(-0.5), 5.0) - (a_idm - 5.0) / 2.0).abs() < 1e-6);
    }
}

#[test]
fn drive_actions_have_their_dimensions_and_demonstrators() {
    assert_eq!(
        (
            DriveAction::Direct.dim(),
            DriveAction::IdmResidual.dim(),
            DriveAction::IdmAccelResidual.dim()
        ),
        (2, 2, 1)
    );
    let demo = Action { ref_speed: 0.5, steer: -0.2, ..Action::default() };
    assert_eq!(DriveAction::Direct.demonstrator(demo), vec![0.5, -0.2]);
    assert_eq!(DriveAction::IdmAccelResidual.demonstrator(demo), vec![0.0]);
    let c = DriveAction::IdmResidual.command(&[0.8, 0.0], Some(demo));
    assert_eq!((c.ref_speed, c.steer, c.idm_accel), (1.0, -0.2, None));
    assert_eq!(DriveAction::IdmAccelResidual.command(&[-0.3], None).idm_accel, Some(-0.3));
}

/// Conflict cases (the ladder's learn-to-yield rung): with share 1 every drawn intersection
/// case is one in which the IDM driver in agent 0's seat collides; a VecEnv with conflicts
/// resets its episodes from such cases.
#[test]
fn conflict_cases_are_those_the_idm_ego_collides_in() {
    use rand::SeedableRng;
    use sf_sim::vec_env::{draw_case, idm_ego_collides, CaseDraw, VecEnv, VecEnvConfig};
    let m = map("intersection");
    let sim = std::sync::Arc::new(sf_sim::SimConfig::default());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let conflicts: Vec<_> = (0..20)
        .map(|id| {
            draw_case(
                &m,
                &sim,
                &mut rng,
                id,
                (2, 3),
                CaseDraw { conflict_share: Some(1.0), slow_leader: None },
            )
        })
        .collect();
    assert!(
        conflicts.iter().all(|c| idm_ego_collides(&m, &sim, c)),
        "every conflict case makes the IDM ego collide"
    );
    let plain: Vec<_> =
        (0..200).map(|id| draw_case(&m, &sim, &mut rng, id, (2, 3), CaseDraw::default())).collect();
    let share = plain.iter().filter(|c| idm_ego_collides(&m, &sim, c)).count() as f32 / 200.0;
    assert!(share < 0.5, "without the filter the IDM ego collides less often ({share})");
    // An ego whose residual is zero collides in every episode of a conflicts-only VecEnv.
    let mut v = VecEnv::new(
        m.clone(),
        sim,
        VecEnvConfig {
            n_envs: 4,
            mode: Mode::Ego { background: Controller::Idm },
            vehicles: (2, 3),
            seed: 1,
        },
    )
    .with_conflicts(1.0);
    let mut ended = Vec::new();
    for _ in 0..200 {
        let acts: Vec<Action> = (0..v.alive().len()).map(|_| residual(0.0)).collect();
        v.step(&acts);
        ended.extend(v.take_finished());
    }
    assert!(ended.len() >= 8, "episodes finished: {}", ended.len());
    assert!(
        ended.iter().all(|m| m.collision == 1.0),
        "{:?}",
        ended.iter().map(|m| m.collision).collect::<Vec<_>>()
    );
}
