//! IDM with MOBIL's lane changes (`sf_sim::mobil`): it leaves a lane blocked by a slow car for a
//! free neighbour running its way, never for the opposite carriageway, not in front of a car
//! that would have to brake hard, and it passes the L6 rung's slow leaders the IDM driver waits
//! behind.

mod common;

use common::{env, map, spawn_for};
use sf_sim::case::{Case, CaseVehicle};
use sf_sim::env::{Controller, Env, Mode, Termination};
use sf_sim::mobil::{action, lateral_target, MobilParams};
use sf_sim::vehicle::{Action, DriveAction};

/// Bottleneck, direction +x: route 2 starts on the outer lane (y = -5.25 m), route 0 on the
/// inner lane (y = -1.75 m), whose left neighbour is the opposite carriageway.
const OUTER_ROUTE: u32 = 2;
const INNER_ROUTE: u32 = 0;

fn car(m: &sf_sim::Map, route: u32, skip: usize, cap: Option<f32>) -> CaseVehicle {
    CaseVehicle { spawn: spawn_for(m, route, skip), route, svo_deg: 45.0, max_speed_mps: cap }
}

/// The ego's action under MOBIL, as the evaluation's MOBIL seat sends it.
fn mobil(e: &Env) -> Action {
    DriveAction::IdmResidualLateral.command(&action(e, 0, &MobilParams::default()), None)
}

/// Runs the ego (agent 0) under MOBIL among IDM cars; every lateral target it chose.
fn run(e: &mut Env) -> Vec<f32> {
    let mut targets = Vec::new();
    let mut actions = vec![Action::default(); e.len()];
    while !e.done() {
        actions[0] = mobil(e);
        targets.push(actions[0].lateral.unwrap_or_default());
        e.step(&actions).expect("step");
    }
    targets
}

/// The ego at `x_m` on the outer lane at 8 m/s behind a car standing 12 m ahead; with `follower`
/// a car on the inner lane 6 m behind it at 12 m/s.
fn overtaking_state(follower: bool) -> Env {
    let m = map("bottleneck");
    let mut vehicles = vec![car(&m, OUTER_ROUTE, 0, None), car(&m, OUTER_ROUTE, 2, Some(0.0))];
    if follower {
        vehicles.push(car(&m, INNER_ROUTE, 0, None));
    }
    let mut e = env(&m);
    e.reset(&Case { id: 0, vehicles }, Mode::Ego { background: Controller::Idm }, None)
        .expect("reset");
    let x_m = -100.0;
    e.place_agent(0, [x_m, -5.25], 0.0, 8.0);
    e.place_agent(1, [x_m + 12.0, -5.25], 0.0, 0.0);
    if follower {
        e.place_agent(2, [x_m - 6.0, -1.75], 0.0, 12.0);
    }
    e
}

#[test]
fn a_car_standing_ahead_sends_it_to_the_free_lane_unless_a_follower_would_brake_hard() {
    let free = overtaking_state(false);
    assert_eq!(lateral_target(&free, 0, &MobilParams::default()), 1.0, "one lane left");
    let guarded = overtaking_state(true);
    assert_eq!(lateral_target(&guarded, 0, &MobilParams::default()), 0.0, "unsafe: it stays");
    // A careless driver (any braking imposed) goes anyway: the safety test is what held it.
    let careless = MobilParams { max_imposed_braking_mps2: 1e9, ..MobilParams::default() };
    assert_eq!(lateral_target(&guarded, 0, &careless), 1.0);
    // Nothing to gain on a free road.
    let m = map("bottleneck");
    let mut e = env(&m);
    e.reset(&Case { id: 0, vehicles: vec![car(&m, OUTER_ROUTE, 0, None)] }, Mode::MultiAgent, None)
        .expect("reset");
    assert_eq!(lateral_target(&e, 0, &MobilParams::default()), 0.0);
}

/// The ego on `route`'s first spawn point among IDM cars, a car capped at 0 m/s four spawn points
/// (30 m) ahead on the same lane: the map, the case and the episode, reset.
fn standing_car_ahead(route: u32) -> (std::sync::Arc<sf_sim::Map>, Case, Env) {
    let m = map("bottleneck");
    let case =
        Case { id: 0, vehicles: vec![car(&m, route, 0, None), car(&m, route, 4, Some(0.0))] };
    let mut e = env(&m);
    e.reset(&case, Mode::Ego { background: Controller::Idm }, None).expect("reset");
    (m, case, e)
}

/// The IDM driver waits behind a car capped at 0 m/s 30 m ahead; MOBIL's ego changes lanes, passes it, and
/// comes back to its route's lane before the narrow, without failing.
#[test]
fn it_passes_a_standing_car_the_idm_driver_waits_behind() {
    let (m, case, mut e) = standing_car_ahead(OUTER_ROUTE);
    let targets = run(&mut e);
    let ego = e.agents()[0].outcome();
    assert!(ego.success && ego.left_lane, "MOBIL's ego: {ego:?}");
    assert!(targets.contains(&1.0) && targets.iter().all(|&t| t == 0.0 || t == 1.0));
    assert_eq!(targets.last(), Some(&0.0), "back in its route's lane at the end");
    let mut idm = env(&m);
    idm.reset(&case, Mode::Ego { background: Controller::Idm }, None).expect("reset");
    let mut actions = vec![Action::default(); idm.len()];
    actions[0] = DriveAction::IdmResidualLateral.command(&[0.0, 0.0], None);
    while !idm.done() {
        idm.step(&actions).expect("step");
    }
    let o = idm.agents()[0].outcome();
    assert!(!o.success && o.termination == Some(Termination::Timeout), "IDM waits: {o:?}");
}

/// On the inner lane the only neighbour running its way is to the right: with a standing car
/// ahead, MOBIL goes right, never into the opposite carriageway on its left.
#[test]
fn it_never_takes_the_opposite_carriageway() {
    let (_, _, mut e) = standing_car_ahead(INNER_ROUTE);
    let targets = run(&mut e);
    assert!(targets.iter().all(|&t| t <= 0.0), "never left of the inner lane");
    assert!(targets.contains(&-1.0), "it went right");
    let ego = e.agents()[0].outcome();
    assert!(ego.success, "{ego:?}");
}

/// L6's task (a car capped at 1.5 m/s 7.5-22.5 m ahead on the bottleneck's approach, 0-4 IDM
/// cars elsewhere): the IDM driver never arrives; MOBIL's ego arrives in most episodes and fails
/// in few.
#[test]
fn it_passes_most_of_l6s_slow_leaders() {
    let m = map("bottleneck");
    let (mut success, mut failed, n) = (0, 0, 40);
    for c in common::slow_leader_cases(&m, 2026, n) {
        let mut e = env(&m);
        e.reset(&c, Mode::Ego { background: Controller::Idm }, None).expect("reset");
        run(&mut e);
        let o = e.agents()[0].outcome();
        success += o.success as u32;
        failed += o.termination.is_some_and(Termination::is_failure) as u32;
    }
    assert!(success >= n * 3 / 4 && failed <= n / 10, "success {success}, failed {failed} of {n}");
}

/// With nothing ahead to overtake (a car follows it) MOBIL's action is zeros, so its car drives
/// exactly like the IDM driver's (the same states, bit for bit, on both +x lanes).
#[test]
fn with_no_reason_to_change_lanes_it_is_the_idm_driver_bit_for_bit() {
    let m = map("bottleneck");
    for route in [OUTER_ROUTE, INNER_ROUTE] {
        let case = Case { id: 0, vehicles: vec![car(&m, route, 3, None), car(&m, route, 0, None)] };
        let (mut a, mut b) = (env(&m), env(&m));
        for e in [&mut a, &mut b] {
            e.reset(&case, Mode::Ego { background: Controller::Idm }, None).expect("reset");
        }
        let zeros = DriveAction::IdmResidualLateral.command(&[0.0, 0.0], None);
        while !a.done() {
            let act = mobil(&a);
            assert_eq!(act, zeros, "route {route}, step {}", a.step_index());
            a.step(&[act, Action::default()]).expect("step");
            b.step(&[zeros, Action::default()]).expect("step");
            let (x, y) = (&a.agents()[0].state, &b.agents()[0].state);
            assert_eq!((x.x_m, x.y_m, x.speed_mps), (y.x_m, y.y_m, y.speed_mps));
        }
    }
}
