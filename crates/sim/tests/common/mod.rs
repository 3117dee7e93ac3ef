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
    Arc::new(Map::load(&configs().join(format!("scenarios/{name}.json"))).expect("shipped scenario loads"))
}

/// The first spawn point (in file order) whose routes include `route`, skipping `skip` of them.
pub fn spawn_for(map: &Map, route: u32, skip: usize) -> u32 {
    map.spawns.iter().enumerate().filter(|(_, s)| s.routes.contains(&route)).nth(skip).map(|(i, _)| i as u32).expect("a spawn point for the route")
}

pub fn case(vehicles: &[(u32, u32, f32)]) -> Case {
    Case { id: 0, vehicles: vehicles.iter().map(|&(spawn, route, svo_deg)| CaseVehicle { spawn, route, svo_deg }).collect() }
}

pub fn env(map: &Arc<Map>) -> Env {
    Env::new(map.clone(), Arc::new(SimConfig::default()))
}
