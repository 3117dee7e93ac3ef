//! Shared helpers for the simulator's integration tests.
#![allow(dead_code)]

use std::path::PathBuf;
use std::sync::Arc;

use sf_sim::case::{Case, CaseVehicle};
use sf_sim::{Env, Map, SimConfig};

pub fn configs() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs")
}

pub fn map(name: &str) -> Arc<Map> {
    Arc::new(
        Map::load(&configs().join(format!("scenarios/{name}.json")))
            .expect("shipped scenario loads"),
    )
}

/// The first spawn point (in file order) whose routes include `route`, skipping `skip` of them.
pub fn spawn_for(map: &Map, route: u32, skip: usize) -> u32 {
    map.spawns
        .iter()
        .enumerate()
        .filter(|(_, s)| s.routes.contains(&route))
        .nth(skip)
        .map(|(i, _)| i as u32)
        .expect("a spawn point for the route")
}

pub fn case(vehicles: &[(u32, u32, f32)]) -> Case {
    Case {
        id: 0,
        vehicles: vehicles
            .iter()
            .map(|&(spawn, route, svo_deg)| CaseVehicle {
                spawn,
                route,
                svo_deg,
                max_speed_mps: None,
            })
            .collect(),
    }
}

pub fn env(map: &Arc<Map>) -> Env {
    Env::new(map.clone(), Arc::new(SimConfig::default()))
}

/// `n` of rung L6's generated cases on `map` (2-6 vehicles, a car capped at 1.5 m/s ahead of the
/// ego in its lane in every case), drawn from `seed`.
pub fn slow_leader_cases(map: &Arc<Map>, seed: u64, n: u32) -> Vec<Case> {
    use rand::SeedableRng;
    use sf_sim::vec_env::{draw_case, CaseDraw, SlowLeader};
    let sim = Arc::new(SimConfig::default());
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let draw = CaseDraw {
        conflict_share: None,
        slow_leader: Some(SlowLeader { share: 1.0, speed_mps: 1.5 }),
    };
    (0..n).map(|id| draw_case(map, &sim, &mut rng, id, (2, 6), draw)).collect()
}

/// Rung L0 for an action: on the first 25 stored cases of every scenario, an ego driven by
/// `ego_action(k)` in case `k` follows the same trajectory as the same vehicle driven by IDM
/// (every vehicle IDM), to the last bit, and ends the same way.
pub fn assert_ego_drives_like_idm(ego_action: impl Fn(usize) -> sf_sim::Action) {
    use sf_sim::env::{Controller, Mode};
    for name in ["intersection", "bottleneck", "merge", "roundabout"] {
        let m = map(name);
        let cases = sf_sim::CaseFile::load(&configs().join(format!("cases/{name}.v1.json")), &m)
            .expect("shipped cases load");
        for (k, c) in cases.cases.iter().take(25).enumerate() {
            let (mut ego, mut idm) = (env(&m), env(&m));
            ego.reset(c, Mode::Ego { background: Controller::Idm }, None).expect("reset");
            idm.reset(c, Mode::AllIdm, None).expect("reset");
            let mut acts = vec![sf_sim::Action::default(); ego.agents().len()];
            acts[0] = ego_action(k);
            let idle = vec![sf_sim::Action::default(); idm.agents().len()];
            while !ego.done() {
                ego.step(&acts).expect("step");
                idm.step(&idle).expect("step");
                let (a, b) = (&ego.agents()[0], &idm.agents()[0]);
                assert_eq!(a.state, b.state, "{name} case {} step {}", c.id, ego.step_index());
                assert_eq!(
                    a.termination,
                    b.termination,
                    "{name} case {} step {}",
                    c.id,
                    ego.step_index()
                );
            }
            assert_eq!(
                ego.agents()[0].outcome(),
                idm.agents()[0].outcome(),
                "{name} case {}",
                c.id
            );
        }
    }
}
