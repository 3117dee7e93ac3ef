//! The lateral IDM residual (`Action::lateral`, `DriveAction::IdmResidualLateral`): zeros are
//! the IDM driver bit for bit (rung L0 for this action); a lateral target moves the path IDM
//! follows sideways at a bounded rate, so a car can change lanes, pass a slow vehicle and cross
//! into the opposite lane, where the usual rules judge it.

mod common;

use common::{env, map, spawn_for};
use rand::SeedableRng;
use sf_sim::case::{Case, CaseVehicle};
use sf_sim::env::{lateral_step, Controller, Mode, Termination};
use sf_sim::vec_env::{draw_case, CaseDraw, SlowLeader};
use sf_sim::vehicle::{Action, DriveAction};
use sf_sim::SimConfig;

fn act(r: f32, lateral: f32) -> Action {
    DriveAction::IdmResidualLateral.command(&[r, lateral], None)
}

/// L0: on the stored cases of every scenario, an ego driven by zeros (and by a non-finite
/// lateral target, which counts as zero) follows the IDM driver's trajectory to the last bit.
#[test]
fn zeros_drive_exactly_like_the_idm_driver() {
    common::assert_ego_drives_like_idm(|k| act(0.0, if k % 2 == 0 { 0.0 } else { f32::NAN }));
}

#[test]
fn the_action_has_two_numbers_and_zero_is_its_demonstrator() {
    let a = DriveAction::parse("idm-residual-lateral").expect("known name");
    assert_eq!(
        (a, a.dim(), a.as_str()),
        (DriveAction::IdmResidualLateral, 2, "idm-residual-lateral")
    );
    assert_eq!(
        a.demonstrator(Action { ref_speed: 0.3, steer: 0.1, ..Action::default() }),
        vec![0.0, 0.0]
    );
    assert_eq!(
        act(-0.5, 0.25),
        Action { idm_accel: Some(-0.5), lateral: Some(0.25), ..Action::default() }
    );
    assert!(!a.needs_demo());
}

/// The path's offset moves by at most `rate * dt` per call and stops at its target.
#[test]
fn the_offset_is_rate_limited_and_reaches_its_target() {
    assert_eq!(lateral_step(0.0, 3.5, 1.5, 0.025), 1.5 * 0.025);
    assert_eq!(lateral_step(0.0, -3.5, 1.5, 0.025), -1.5 * 0.025);
    assert_eq!(lateral_step(3.49, 3.5, 1.5, 0.025), 3.5);
    let mut x = 0.0;
    for _ in 0..100 {
        x = lateral_step(x, 3.5, 1.5, 0.025);
    }
    assert_eq!(x, 3.5, "2.5 s at 1.5 m/s covers the 3.5 m");
}

/// Bottleneck, direction +x: route 2 starts on the outer lane (y = -5.25 m), whose left
/// neighbour is the inner lane (y = -1.75 m).
const OUTER_ROUTE: u32 = 2;
const INNER_ROUTE: u32 = 0;

fn one_car(route: u32) -> Case {
    let m = map("bottleneck");
    Case {
        id: 0,
        vehicles: vec![CaseVehicle {
            spawn: spawn_for(&m, route, 0),
            route,
            svo_deg: 45.0,
            max_speed_mps: None,
        }],
    }
}

/// A full left target takes the car one lane over (3.5 m) and keeps it there on the straight;
/// after one decision step it has moved no more than the rate allows.
#[test]
fn a_full_left_target_changes_one_lane() {
    let m = map("bottleneck");
    let mut e = env(&m);
    e.reset(&one_car(OUTER_ROUTE), Mode::MultiAgent, None).expect("reset");
    let y0 = e.agents()[0].state.y_m;
    e.step(&[act(0.0, 1.0)]).expect("step");
    let cfg = SimConfig::default();
    let moved = e.agents()[0].state.y_m - y0;
    assert!(
        moved >= 0.0 && moved <= cfg.lateral.rate_mps * cfg.dt_s + 1e-4,
        "moved {moved} m in one step"
    );
    for _ in 0..20 {
        e.step(&[act(0.0, 1.0)]).expect("step");
    }
    let a = &e.agents()[0];
    assert!(a.state.x_m < -40.0, "still on the two-lane stretch at x = {}", a.state.x_m);
    assert!((a.lateral_m - 3.5).abs() < 0.3, "lateral {} m", a.lateral_m);
    assert!((a.state.y_m + 1.75).abs() < 0.3, "in the inner lane: y = {}", a.state.y_m);
    assert!(a.termination.is_none() && a.outcome().left_lane);
}

/// Left of the inner lane is the opposite direction's lane: a car can go there, and the
/// wrong-lane rule ends it.
#[test]
fn crossing_into_the_opposite_lane_is_possible_and_judged() {
    let m = map("bottleneck");
    let mut e = env(&m);
    e.reset(&one_car(INNER_ROUTE), Mode::MultiAgent, None).expect("reset");
    for _ in 0..40 {
        if e.done() {
            break;
        }
        e.step(&[act(0.0, 1.0)]).expect("step");
    }
    let a = &e.agents()[0];
    assert_eq!(
        a.termination,
        Some(Termination::WrongLane),
        "y = {}, lateral {}",
        a.state.y_m,
        a.lateral_m
    );
    assert!(a.state.y_m > 0.0, "ended across the centre line, y = {}", a.state.y_m);
}

/// A stopped car ahead in the ego's lane: the IDM driver (zeros) waits behind it; with a full
/// left target the ego changes lanes and passes it without touching it, because IDM's leader
/// is searched along the moved path.
#[test]
fn a_lane_change_passes_a_stopped_car_that_idm_waits_behind() {
    let m = map("bottleneck");
    let stopped = spawn_for(&m, OUTER_ROUTE, 2);
    let case = Case {
        id: 0,
        vehicles: vec![
            CaseVehicle {
                spawn: spawn_for(&m, OUTER_ROUTE, 0),
                route: OUTER_ROUTE,
                svo_deg: 45.0,
                max_speed_mps: None,
            },
            CaseVehicle {
                spawn: stopped,
                route: OUTER_ROUTE,
                svo_deg: 45.0,
                max_speed_mps: Some(0.0),
            },
        ],
    };
    let run = |lateral: f32| {
        let mut e = env(&m);
        e.reset(&case, Mode::Ego { background: Controller::Idm }, None).expect("reset");
        let mut passed = false;
        for _ in 0..40 {
            if e.done() {
                break;
            }
            e.step(&[act(0.0, lateral), Action::default()]).expect("step");
            assert_eq!(e.agents()[1].state.speed_mps, 0.0, "a car capped at 0 m/s never moves");
            passed |= e.agents()[0].state.x_m > e.agents()[1].state.x_m + 5.0;
            if passed {
                break;
            }
        }
        (passed, e.agents()[0].termination, e.agents()[0].state.speed_mps)
    };
    let (passed, end, speed) = run(0.0);
    assert!(
        !passed && end.is_none() && speed < 0.05,
        "IDM waits: passed {passed}, end {end:?}, speed {speed}"
    );
    let (passed, end, _) = run(1.0);
    assert!(passed && end.is_none(), "the lane change passes: passed {passed}, end {end:?}");
}

/// Slow-leader cases: the ego starts in the first half of its lane's spawn points, a capped car
/// 7.5-22.5 m ahead of it on the same lane and route, every other car off that lane.
#[test]
fn slow_leader_cases_put_a_capped_car_ahead_in_the_egos_lane() {
    let m = map("bottleneck");
    let sim = std::sync::Arc::new(SimConfig::default());
    for c in common::slow_leader_cases(&m, 3, 50) {
        c.check(&m).expect("a valid case");
        let (ego, lead) = (&c.vehicles[0], &c.vehicles[1]);
        let (se, sl) = (&m.spawns[ego.spawn as usize], &m.spawns[lead.spawn as usize]);
        assert_eq!(
            (lead.route, lead.max_speed_mps, ego.max_speed_mps),
            (ego.route, Some(1.5), None)
        );
        assert_eq!(se.routes, sl.routes, "same lane");
        let ahead = sl.s_m - se.s_m;
        assert!((7.0..=23.0).contains(&ahead), "leader {ahead} m ahead");
        assert!(se.s_m < 50.0, "ego in the first half of an 88 m lane: s = {}", se.s_m);
        assert!(c.vehicles[2..]
            .iter()
            .all(|v| m.spawns[v.spawn as usize].routes != se.routes && v.max_speed_mps.is_none()));
        assert!((2..=6).contains(&c.vehicles.len()));
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let none = CaseDraw {
        conflict_share: None,
        slow_leader: Some(SlowLeader { share: 0.0, speed_mps: 1.5 }),
    };
    assert!((0..50).all(|id| draw_case(&m, &sim, &mut rng, id, (2, 6), none)
        .vehicles
        .iter()
        .all(|v| v.max_speed_mps.is_none())));
    assert!(SlowLeader { share: 1.5, speed_mps: 1.0 }.check(6.0).unwrap_err().contains("share"));
    assert!(SlowLeader { share: 1.0, speed_mps: 6.0 }
        .check(6.0)
        .unwrap_err()
        .contains("speed_mps"));
}

/// A case file with a negative speed cap is refused, naming the vehicle's field; files without
/// caps keep their text.
#[test]
fn a_bad_speed_cap_is_refused_by_name() {
    let m = map("bottleneck");
    let mut c = one_car(OUTER_ROUTE);
    c.vehicles[0].max_speed_mps = Some(-1.0);
    let (field, reason) = c.check(&m).expect_err("negative cap");
    assert_eq!(field, "vehicles[0].max_speed_mps", "{reason}");
    let text = serde_json::to_string(&one_car(OUTER_ROUTE)).expect("json");
    assert!(!text.contains("max_speed_mps"), "{text}");
}
