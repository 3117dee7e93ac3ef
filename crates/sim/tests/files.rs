//! Shipped scenario and case files: they load, match their generators, and bad files are
//! rejected with messages that name the file, the field and the reason.

mod common;

use std::path::Path;

use common::configs;
use sf_sim::case::{self, CaseFile, DEFAULT_VEHICLES};
use sf_sim::map::{Map, MapError, ScenarioFile};
use sf_sim::scenarios::{self, SCENARIOS};

#[test]
fn shipped_scenarios_equal_their_builders() {
    for name in SCENARIOS {
        let path = configs().join(format!("scenarios/{name}.json"));
        let file = ScenarioFile::read(&path).expect("readable");
        let built = scenarios::build(name).expect("builder");
        assert!(
            file == built,
            "configs/scenarios/{name}.json is stale: run `socialflow gen-scenarios`"
        );
        let map = Map::from_file(&file, name).expect("valid");
        assert!(
            map.spawns.len() >= 40,
            "{name}: {} spawn points, the 40-vehicle benchmark needs 40",
            map.spawns.len()
        );
    }
}

#[test]
fn scenario_shapes_match_the_digest() {
    let routes: Vec<usize> = SCENARIOS.iter().map(|n| common::map(n).routes.len()).collect();
    assert_eq!(routes, vec![16, 8, 5, 6]);
    for name in SCENARIOS {
        let m = common::map(name);
        assert!(m.lanes.iter().all(|l| (l.width_m - 3.5).abs() < 1e-6));
    }
}

#[test]
fn shipped_cases_load_and_replay_their_generator() {
    for (k, name) in SCENARIOS.iter().enumerate() {
        let m = common::map(name);
        let path = configs().join(format!("cases/{name}.v{}.json", case::CASES_VERSION));
        let f = CaseFile::load(&path, &m).expect("valid case file");
        assert_eq!(f.cases.len(), 200);
        let again = case::generate(&m, 200, f.generator_seed, DEFAULT_VEHICLES);
        assert!(
            again == f,
            "{name}: stored cases differ from the generator (seed {})",
            f.generator_seed
        );
        assert_eq!(f.generator_seed, 20221 + k as u64);
        for c in &f.cases {
            assert!((8..=20).contains(&c.vehicles.len()));
        }
    }
}

fn reject(file: &ScenarioFile, field: &str) -> String {
    match Map::from_file(file, "test.json") {
        Ok(_) => panic!("accepted a file with a bad `{field}`"),
        Err(e) => {
            let msg = e.to_string();
            assert!(
                msg.contains("test.json") && msg.contains(field),
                "message `{msg}` does not name `{field}`"
            );
            msg
        }
    }
}

#[test]
fn malformed_scenarios_are_rejected_with_the_field_named() {
    let good = scenarios::build("intersection").expect("builder");
    let mut f = good.clone();
    f.format_version = 9;
    reject(&f, "format_version");
    let mut f = good.clone();
    f.lanes[3].centre[1] = [f32::NAN, 0.0];
    reject(&f, "lanes[3].centre[1]");
    let mut f = good.clone();
    f.lanes[2].width_m = -1.0;
    reject(&f, "lanes[2].width_m");
    let mut f = good.clone();
    f.routes[4].lanes.swap(0, 1);
    reject(&f, "routes[4].lanes[1]");
    let mut f = good.clone();
    f.routes[0].lanes.push(999);
    reject(&f, "routes[0].lanes[3]");
    let mut f = good.clone();
    f.spawn_points[5].s_m = 1e4;
    reject(&f, "spawn_points[5].s_m");
    let mut f = good.clone();
    f.interaction_zone.truncate(2);
    reject(&f, "interaction_zone");
    let mut f = good.clone();
    f.edges[1].points[0] = [1e6, 0.0];
    let msg = reject(&f, "edges[1].points[0]");
    assert!(msg.contains("outside the boundary"), "{msg}");
    let mut f = good.clone();
    f.lanes[7].id = 8;
    reject(&f, "lanes[7].id");
}

#[test]
fn unreadable_and_unparsable_files_name_the_path() {
    let dir = std::env::temp_dir().join(format!("sf-sim-files-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp dir");
    let missing = dir.join("missing.json");
    let e = Map::load(&missing).expect_err("missing file");
    assert!(matches!(e, MapError::Io { .. }) && e.to_string().contains("missing.json"));
    let bad = dir.join("bad.json");
    std::fs::write(&bad, "{\"format_version\": 1, \"name\": \"x\", \"bogus\": 3}").expect("write");
    let e = Map::load(&bad).expect_err("unknown field");
    let msg = e.to_string();
    assert!(msg.contains("bad.json") && msg.contains("bogus"), "{msg}");
    // A case file referring to a route that does not start at its spawn point.
    let m = common::map("merge");
    let mut cf = case::generate(&m, 3, 1, (8, 8));
    let wrong = (0..m.routes.len() as u32)
        .find(|r| !m.spawns[cf.cases[1].vehicles[2].spawn as usize].routes.contains(r))
        .expect("some other route");
    cf.cases[1].vehicles[2].route = wrong;
    let p = dir.join("cases.json");
    cf.write(&p).expect("write");
    let msg = CaseFile::load(&p, &m).expect_err("bad case").to_string();
    assert!(msg.contains("cases[1].vehicles[2].route"), "{msg}");
    let _ = std::fs::remove_dir_all(Path::new(&dir));
}
