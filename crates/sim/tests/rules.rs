//! Failure types, success, rewards and IDM following, each in a constructed situation.

mod common;

use common::{case, env, map, spawn_for};
use sf_sim::env::{Controller, Mode, Termination};
use sf_sim::vehicle::Action;

fn stop() -> Action {
    Action { ref_speed: -1.0, steer: 0.0, ..Action::default() }
}

/// Steps with constant actions until agent 0 ends; returns its termination and step count.
fn run_until_end(e: &mut sf_sim::Env, actions: &[Action]) -> (Option<Termination>, u32) {
    while e.agents()[0].alive && !e.done() {
        e.step(actions).expect("step");
    }
    (e.agents()[0].termination, e.step_index())
}

#[test]
fn collision_ends_both_and_nothing_else() {
    let m = map("intersection");
    let mut e = env(&m);
    e.reset(
        &case(&[(spawn_for(&m, 0, 0), 0, 0.0), (spawn_for(&m, 2, 0), 2, 0.0)]),
        Mode::MultiAgent,
        None,
    )
    .expect("reset");
    // Agent 1 placed just ahead of agent 0 in the same lane, overlapping after one step.
    let p0 = e.agents()[0].state.pos();
    e.place_agent(1, [p0[0], p0[1] + 4.5], std::f32::consts::FRAC_PI_2, 0.0);
    e.place_agent(0, p0, std::f32::consts::FRAC_PI_2, 6.0);
    e.step(&[Action { ref_speed: 1.0, steer: 0.0, ..Action::default() }, stop()]).expect("step");
    let t: Vec<_> = e.agents().iter().map(|a| a.termination).collect();
    assert_eq!(t, vec![Some(Termination::Collision), Some(Termination::Collision)]);
    assert!(e.done(), "every learner ended");
    assert!(e.rewards()[0].individual < -4.9, "collision penalty: {:?}", e.rewards()[0]);
    assert!(!e.agents()[0].outcome().success);
}

#[test]
fn off_road_from_steering_into_the_edge() {
    let m = map("intersection");
    let mut e = env(&m);
    // Outer inbound lane of the south arm (x = 5.25): the road edge is 1.75 m to its right.
    let r = 2;
    e.reset(&case(&[(spawn_for(&m, r, 0), r, 0.0)]), Mode::MultiAgent, None).expect("reset");
    let (t, _) =
        run_until_end(&mut e, &[Action { ref_speed: 0.0, steer: -0.5, ..Action::default() }]);
    assert_eq!(t, Some(Termination::OffRoad));
}

#[test]
fn off_route_inside_the_junction() {
    let m = map("intersection");
    let mut e = env(&m);
    // Route 0 goes straight north along x = 1.75; inside the junction box (no wrong-lane rule,
    // no edges) a vehicle at x = -5.5 is 7.25 m off its route.
    e.reset(&case(&[(spawn_for(&m, 0, 0), 0, 0.0)]), Mode::MultiAgent, None).expect("reset");
    e.place_agent(0, [-5.5, 0.0], std::f32::consts::FRAC_PI_2, 0.0);
    e.step(&[stop()]).expect("step");
    assert_eq!(e.agents()[0].termination, Some(Termination::OffRoute));
}

#[test]
fn wrong_lane_against_traffic() {
    let m = map("intersection");
    let mut e = env(&m);
    // Heading north on the southbound lane (x = -1.75), 3.5 m from its route: wrong lane only.
    e.reset(&case(&[(spawn_for(&m, 0, 0), 0, 0.0)]), Mode::MultiAgent, None).expect("reset");
    e.place_agent(0, [-1.75, -40.0], std::f32::consts::FRAC_PI_2, 0.0);
    e.step(&[stop()]).expect("step");
    assert_eq!(e.agents()[0].termination, Some(Termination::WrongLane));
    // The same pose on its own lane is fine.
    e.reset(&case(&[(spawn_for(&m, 0, 0), 0, 0.0)]), Mode::MultiAgent, None).expect("reset");
    e.place_agent(0, [1.75, -40.0], std::f32::consts::FRAC_PI_2, 0.0);
    e.step(&[stop()]).expect("step");
    assert_eq!(e.agents()[0].termination, None);
}

#[test]
fn timeout_at_the_horizon_without_success() {
    let m = map("roundabout");
    let mut e = env(&m);
    e.reset(&case(&[(spawn_for(&m, 0, 0), 0, 0.0)]), Mode::MultiAgent, None).expect("reset");
    let (t, steps) = run_until_end(&mut e, &[stop()]);
    assert_eq!((t, steps), (Some(Termination::Timeout), 100));
    let o = e.agents()[0].outcome();
    assert!(!o.success, "never reached the zone");
    assert_eq!(o.speed_ratio, 0.0);
}

#[test]
fn success_only_after_the_zone_is_passed_and_destination_ends() {
    for name in ["intersection", "merge", "roundabout", "bottleneck"] {
        let m = map(name);
        for r in 0..m.routes.len() as u32 {
            let mut e = env(&m);
            // One IDM car alone on each route: it must cross the zone cleanly.
            let sp = spawn_for(&m, r, 0);
            e.reset(&case(&[(sp, r, 0.0)]), Mode::AllIdm, None).expect("reset");
            let mut was_in_zone = false;
            while !e.done() {
                e.step(&[Action::default()]).expect("step");
                let a = &e.agents()[0];
                let inside = sf_sim::geom::point_in_polygon(a.state.pos(), &m.zone);
                if inside {
                    was_in_zone = true;
                    assert!(
                        !a.outcome().success,
                        "{name} route {r}: success while still inside the zone"
                    );
                }
            }
            let a = &e.agents()[0];
            assert!(was_in_zone, "{name} route {r} never entered the zone");
            assert!(a.outcome().success, "{name} route {r}: {:?}", a.termination);
            assert!(matches!(a.termination, Some(Termination::Destination | Termination::Timeout)));
        }
    }
    // Destination: a car placed at its route's end.
    let m = map("merge");
    let mut e = env(&m);
    e.reset(&case(&[(spawn_for(&m, 0, 0), 0, 0.0)]), Mode::MultiAgent, None).expect("reset");
    let end = *m.routes[0].points.last().expect("points");
    e.place_agent(0, [end[0] - 0.5, end[1]], 0.0, 3.0);
    e.step(&[Action::default()]).expect("step");
    assert_eq!(e.agents()[0].termination, Some(Termination::Destination));
    assert!(!e.agents()[0].outcome().success, "teleported past the zone: not a pass");
}

#[test]
fn idm_follower_stops_behind_a_stopped_leader() {
    let m = map("bottleneck");
    let mut e = env(&m);
    // Two spawn points on the same lane: the one further along leads.
    let r = 0;
    let (back, front) = (spawn_for(&m, r, 0), spawn_for(&m, r, 4));
    e.reset(
        &case(&[(front, r, 0.0), (back, r, 0.0)]),
        Mode::Ego { background: Controller::Idm },
        None,
    )
    .expect("reset");
    let mut min_gap = f32::INFINITY;
    for _ in 0..60 {
        e.step(&[stop(), Action::default()]).expect("step");
        let (a, b) = (&e.agents()[0], &e.agents()[1]);
        min_gap = min_gap.min(sf_sim::geom::dist(a.state.pos(), b.state.pos()) - 4.2);
    }
    let f = &e.agents()[1];
    assert!(f.alive, "follower ended: {:?}", f.termination);
    assert!(f.state.speed_mps < 0.05, "follower still moving at {}", f.state.speed_mps);
    assert!(min_gap >= 1.9, "closest bumper gap {min_gap}");
    assert!(min_gap < 4.0, "stopped far behind: {min_gap}");
}

#[test]
fn rewards_individual_composed_and_failmaker() {
    let m = map("intersection");
    let mut e = env(&m);
    let (s0, s1) = (spawn_for(&m, 0, 0), spawn_for(&m, 0, 3));
    e.reset(&case(&[(s0, 0, 0.0), (s1, 0, 60.0)]), Mode::MultiAgent, None).expect("reset");
    e.step(&[Action { ref_speed: 1.0, steer: 0.0, ..Action::default() }, stop()]).expect("step");
    let a = e.agents();
    let r = e.rewards();
    let ind = |i: usize| 0.07 * (2.0 * a[i].state.speed_mps / 6.0 - 1.0);
    assert!((r[0].individual - ind(0)).abs() < 1e-6 && (r[1].individual - ind(1)).abs() < 1e-6);
    // Agent 0 is egoistic (0 deg): composed = own. Agent 1 (60 deg) mixes in agent 0's.
    assert!((r[0].composed - r[0].individual).abs() < 1e-6);
    let c = 60f32.to_radians();
    assert!((r[1].composed - (c.cos() * r[1].individual + c.sin() * r[0].individual)).abs() < 1e-6);
    // FailMaker background: own term plus sin(c) times the ego's reward.
    assert!(
        (r[1].failmaker - (c.cos() * r[1].individual + c.sin() * r[0].individual)).abs() < 1e-6
    );

    // A background car that collides gets no collision penalty in its FailMaker reward.
    let mut e = env(&m);
    e.reset(&case(&[(s0, 0, 0.0), (s1, 0, 0.0)]), Mode::MultiAgent, None).expect("reset");
    let p0 = e.agents()[0].state.pos();
    e.place_agent(1, [p0[0], p0[1] + 4.5], std::f32::consts::FRAC_PI_2, 0.0);
    e.place_agent(0, p0, std::f32::consts::FRAC_PI_2, 6.0);
    e.step(&[Action { ref_speed: 1.0, steer: 0.0, ..Action::default() }, stop()]).expect("step");
    let r = e.rewards();
    assert_eq!(e.agents()[1].termination, Some(Termination::Collision));
    assert!(r[1].individual < -4.9);
    assert!(r[1].failmaker > -0.1, "no collision penalty: {:?}", r[1]);
}

/// `reward.max_neighbours`: only the nearest candidates' rewards enter the composed reward (the
/// set the observation keeps), not every learner within the radius.
#[test]
fn composed_reward_over_the_nearest_neighbours_only() {
    use std::sync::Arc;
    let m = map("intersection");
    let (s0, s1, s2) = (spawn_for(&m, 0, 0), spawn_for(&m, 0, 2), spawn_for(&m, 0, 4));
    let c = case(&[(s0, 0, 60.0), (s1, 0, 0.0), (s2, 0, 0.0)]);
    // Agent 1 just ahead of agent 0 and stopping, agent 2 further ahead at speed: different rewards.
    let place = |e: &mut sf_sim::Env| {
        let p0 = e.agents()[0].state.pos();
        let up = std::f32::consts::FRAC_PI_2;
        e.place_agent(1, [p0[0], p0[1] + 10.0], up, 0.0);
        e.place_agent(2, [p0[0], p0[1] + 30.0], up, 6.0);
    };
    let acts = [Action::default(), stop(), Action { ref_speed: 1.0, ..Action::default() }];
    let mut composed = Vec::new();
    for cap in [None, Some(1)] {
        let mut cfg = sf_sim::SimConfig::default();
        cfg.reward.max_neighbours = cap;
        let mut e = sf_sim::Env::new(m.clone(), Arc::new(cfg));
        e.reset(&c, Mode::MultiAgent, None).expect("reset");
        place(&mut e);
        e.step(&acts).expect("step");
        let r = e.rewards();
        let w = 60f32.to_radians();
        let expect = match cap {
            None => (r[1].individual + r[2].individual) / 2.0,
            Some(_) => r[1].individual,
        };
        assert!(
            (r[0].composed - (w.cos() * r[0].individual + w.sin() * expect)).abs() < 1e-6,
            "cap {cap:?}: {:?}",
            r
        );
        composed.push(r[0].composed);
    }
    assert!((composed[0] - composed[1]).abs() > 1e-4, "the cap changed nothing: {composed:?}");
}

#[test]
fn adversary_svo_reaches_only_the_told_observer() {
    let m = map("intersection");
    let mut e = env(&m);
    let (s0, s1, s2) = (spawn_for(&m, 0, 0), spawn_for(&m, 0, 2), spawn_for(&m, 0, 4));
    e.reset(&case(&[(s0, 0, 10.0), (s1, 0, 20.0), (s2, 0, 30.0)]), Mode::MultiAgent, None)
        .expect("reset");
    e.set_seen_ego_svo(1, Some(-45.0));
    assert_eq!(e.communicated_svo_deg(1, 0), -45.0);
    assert_eq!(e.communicated_svo_deg(2, 0), 10.0, "other observers see the genuine SVO");
    assert_eq!(e.communicated_svo_deg(1, 2), 30.0, "background SVOs stay genuine");
    assert_eq!(e.communicated_svo_deg(0, 0), 10.0, "the ego is not fooled about itself");
}

/// The message probes: a constant in place of every neighbour's SVO (each agent keeps its own),
/// or of the ego's SVO as the others are told it; an SVO outside [-90, 90] is refused.
#[test]
fn message_probes_replace_what_observers_are_told() {
    let m = map("intersection");
    let mut cfg = sf_sim::SimConfig::default();
    cfg.obs.messages.neighbours_deg = Some(45.0);
    let mut e = sf_sim::Env::new(m.clone(), std::sync::Arc::new(cfg.clone()));
    let (s0, s1, s2) = (spawn_for(&m, 0, 0), spawn_for(&m, 0, 2), spawn_for(&m, 0, 4));
    let c = case(&[(s0, 0, 10.0), (s1, 0, 20.0), (s2, 0, 30.0)]);
    e.reset(&c, Mode::MultiAgent, None).expect("reset");
    assert_eq!(
        (e.communicated_svo_deg(1, 2), e.communicated_svo_deg(2, 0), e.communicated_svo_deg(0, 1)),
        (45.0, 45.0, 45.0)
    );
    assert_eq!(
        (e.communicated_svo_deg(1, 1), e.communicated_svo_deg(2, 2)),
        (20.0, 30.0),
        "each agent knows its own SVO"
    );
    cfg.obs.messages =
        sf_sim::config::MessageProbe { neighbours_deg: None, told_ego_deg: Some(90.0) };
    let mut e = sf_sim::Env::new(m.clone(), std::sync::Arc::new(cfg.clone()));
    e.reset(&c, Mode::MultiAgent, None).expect("reset");
    e.set_seen_ego_svo(1, Some(-45.0));
    assert_eq!(
        (e.communicated_svo_deg(1, 0), e.communicated_svo_deg(2, 0)),
        (90.0, 90.0),
        "the constant message wins over an adversary's"
    );
    assert_eq!(
        (e.communicated_svo_deg(0, 0), e.communicated_svo_deg(1, 2)),
        (10.0, 30.0),
        "the ego's own and the others' SVOs stay genuine"
    );
    cfg.obs.messages.told_ego_deg = Some(120.0);
    let err = cfg.validate().expect_err("out of range").to_string();
    assert!(err.contains("obs.messages.told_ego_deg"), "{err}");
}

/// The IDM warm-up's demonstrator: its action, held for whole decision steps by an externally
/// driven car, crosses every route of every scenario cleanly at nearly full speed, and it asks
/// for a lower reference speed than free road when a stopped car is close ahead.
#[test]
fn the_idm_demonstrator_drives_every_route_and_brakes_for_a_stopped_leader() {
    for name in ["intersection", "merge", "roundabout", "bottleneck"] {
        let m = map(name);
        for r in 0..m.routes.len() as u32 {
            let mut e = env(&m);
            e.reset(&case(&[(spawn_for(&m, r, 0), r, 0.0)]), Mode::MultiAgent, None)
                .expect("reset");
            while !e.done() {
                let a = e.demo_action(0);
                assert!(
                    (-1.0..=1.0).contains(&a.ref_speed) && (-1.0..=1.0).contains(&a.steer),
                    "{a:?}"
                );
                e.step(&[a]).expect("step");
            }
            let o = e.agents()[0].outcome();
            assert!(o.success, "{name} route {r}: {:?}", e.agents()[0].termination);
            assert!(o.speed_ratio > 0.8, "{name} route {r}: speed {}", o.speed_ratio);
        }
    }
    let m = map("merge");
    let mut e = env(&m);
    e.reset(
        &case(&[(spawn_for(&m, 0, 0), 0, 0.0), (spawn_for(&m, 0, 1), 0, 0.0)]),
        Mode::MultiAgent,
        None,
    )
    .expect("reset");
    let (p0, th) = (e.agents()[0].state.pos(), e.agents()[0].state.theta_rad);
    e.place_agent(0, p0, th, 6.0);
    e.place_agent(1, [p0[0] + 500.0, p0[1] + 500.0], th, 0.0);
    let free = e.demo_action(0).ref_speed;
    e.place_agent(1, [p0[0] + 8.0 * th.cos(), p0[1] + 8.0 * th.sin()], th, 0.0);
    e.step(&[e.demo_action(0), stop()]).expect("step");
    let near = e.demo_action(0).ref_speed;
    assert_eq!(free, 1.0, "free road: full reference speed");
    assert!(near < 0.0, "a stopped car 8 m ahead: brake (got {near})");
}

#[test]
fn a_timeout_behind_a_car_standing_in_the_narrow_is_a_closed_road_and_not_otherwise() {
    let m = map("bottleneck");
    // Route 0 runs east on the inner lane (y = -1.75) through the one-lane narrow (|x| < 12).
    let r = 0;
    let outcomes = |other: ([f32; 2], f32)| {
        let mut e = env(&m);
        let c = case(&[(spawn_for(&m, r, 0), r, 0.0), (spawn_for(&m, r, 4), r, 0.0)]);
        e.reset(&c, Mode::MultiAgent, None).expect("reset");
        e.place_agent(0, [-20.0, -1.75], 0.0, 0.0);
        e.place_agent(1, other.0, other.1, 0.0);
        while !e.done() {
            e.step(&[stop(), stop()]).expect("step");
        }
        // Training's metrics skip the corridor test: the same ends, none judged closed.
        let unjudged: Vec<_> = e.outcomes_judged(false).collect();
        assert!(unjudged.iter().all(|o| !o.road_closed));
        let judged: Vec<_> = e.outcomes().collect();
        for (u, j) in unjudged.iter().zip(&judged) {
            assert_eq!((u.termination, u.success, u.steps), (j.termination, j.success, j.steps));
        }
        judged
    };
    // A car standing in the narrow 20 m ahead: nothing gets past it but the opposite lane.
    let o = outcomes(([0.0, -1.75], 0.0));
    assert_eq!(o[0].termination, Some(Termination::Timeout));
    assert!(o[0].road_closed, "the car behind is blocked");
    assert!(!o[1].road_closed, "nothing stands ahead of the car in front");
    // The same car on the opposite carriageway closes nothing.
    let o = outcomes(([0.0, 1.75], std::f32::consts::PI));
    assert_eq!(o[0].termination, Some(Termination::Timeout));
    assert!(!o[0].road_closed);
}
