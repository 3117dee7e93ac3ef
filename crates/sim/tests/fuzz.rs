//! Fuzzing of the scenario and case file loaders (property tests, stable Rust, deterministic,
//! bounded for CI).
//!
//! What is fuzzed: the scenario loader (`ScenarioFile` JSON -> [`Map::from_file`], what
//! [`Map::load`] runs after reading the file) and the case loader ([`CaseFile::load`], against
//! the shipped map of the file's scenario) on the shipped files under `configs/scenarios/` and
//! `configs/cases/` after structural edits (an array element removed, duplicated or swapped, an
//! object field removed, a number replaced by an extreme, by a nearby value or by a value of
//! another type), after text edits (truncation, bytes flipped, inserted or removed), and on
//! JSON-ish token soup.
//!
//! What is asserted: nothing panics; a refusal's message is non-empty and names the file; what
//! a loader accepts can be used: a map steps a few all-IDM episodes with observations
//! ([`VecEnv::new`]), a case file's cases run as stored episodes ([`VecEnv::from_episodes`],
//! which treats a failed re-check of a loaded case as a broken invariant).
//!
//! Cases: 256 per property (fixed seed, no persistence file); a few seconds in all in the debug
//! profile.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};

use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::{Config as ProptestConfig, RngSeed};
use serde_json::Value;
use sf_sim::map::ScenarioFile;
use sf_sim::scenarios::SCENARIOS;
use sf_sim::vec_env::{EpisodeSpec, VecEnv, VecEnvConfig};
use sf_sim::{Action, CaseFile, Map, Mode, SimConfig};

/// Deterministic and bounded for CI: a fixed seed and `cases` cases, no regression files
/// written into the crate. `PROPTEST_CASES` and `PROPTEST_RNG_SEED` override both for a longer
/// local run.
fn config(cases: u32) -> ProptestConfig {
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse().ok());
    ProptestConfig {
        cases: env("PROPTEST_CASES").map_or(cases, |c: u64| c as u32),
        rng_seed: RngSeed::Fixed(env("PROPTEST_RNG_SEED").unwrap_or(0x50c1_a1f1)),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

fn configs() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs")
}

struct Shipped {
    name: &'static str,
    scenario_text: String,
    scenario: Value,
    map: Arc<Map>,
    cases_text: String,
    cases: Value,
}

fn shipped() -> &'static [Shipped] {
    static FILES: OnceLock<Vec<Shipped>> = OnceLock::new();
    FILES.get_or_init(|| {
        SCENARIOS
            .iter()
            .map(|&name| {
                let scenario_text =
                    std::fs::read_to_string(configs().join(format!("scenarios/{name}.json")))
                        .expect("shipped scenario is readable");
                let cases_text =
                    std::fs::read_to_string(configs().join(format!("cases/{name}.v1.json")))
                        .expect("shipped case file is readable");
                let file: ScenarioFile =
                    serde_json::from_str(&scenario_text).expect("shipped scenario parses");
                Shipped {
                    name,
                    scenario: serde_json::from_str(&scenario_text).expect("JSON"),
                    map: Arc::new(Map::from_file(&file, name).expect("shipped scenario is valid")),
                    cases: serde_json::from_str(&cases_text).expect("JSON"),
                    scenario_text,
                    cases_text,
                }
            })
            .collect()
    })
}

/// What the scenario loader does after reading the file.
fn load_scenario(text: &str, origin: &str) -> Result<Map, String> {
    let file: ScenarioFile = serde_json::from_str(text).map_err(|e| {
        format!("scenario file {origin} is not valid JSON for the scenario format: {e}")
    })?;
    Map::from_file(&file, origin).map_err(|e| e.to_string())
}

/// Runs the case loader on `text` (written to a temporary file, as the loader reads paths).
fn load_cases(text: &str, map: &Map) -> Result<CaseFile, String> {
    static N: AtomicUsize = AtomicUsize::new(0);
    let path = std::env::temp_dir().join(format!(
        "sf-sim-fuzz-{}-{}.json",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::write(&path, text).expect("temporary file is writable");
    let r = CaseFile::load(&path, map).map_err(|e| e.to_string());
    let _ = std::fs::remove_file(&path);
    r
}

/// An accepted map is usable: a few all-IDM episodes with observations, random resets included.
fn use_map(map: Map) {
    let mut v = VecEnv::new(
        Arc::new(map),
        Arc::new(SimConfig::default()),
        VecEnvConfig { n_envs: 2, mode: Mode::AllIdm, vehicles: (1, 6), seed: 7 },
    );
    let actions = vec![Action::default(); v.alive().len()];
    for _ in 0..10 {
        v.step(&actions);
    }
    assert!(v.observations().iter().all(|x| x.is_finite()), "non-finite observation");
}

/// Accepted cases are usable: the first few run as stored episodes on their map.
fn use_cases(f: &CaseFile, map: &Arc<Map>) {
    let eps: Vec<EpisodeSpec> = f
        .cases
        .iter()
        .take(3)
        .enumerate()
        .map(|(k, c)| EpisodeSpec { case: c.clone(), vehicles: None, svo_deg: None, tag: k as u64 })
        .collect();
    let mut v = VecEnv::from_episodes(
        Arc::clone(map),
        Arc::new(SimConfig::default()),
        Mode::AllIdm,
        2,
        eps,
    )
    .expect("loaded cases pass the simulator's check");
    let actions = vec![Action::default(); v.alive().len()];
    for _ in 0..5 {
        v.step(&actions);
    }
}

/// A structural edit of a JSON document.
#[derive(Clone, Debug)]
enum Edit {
    RemoveElement(Index),
    DuplicateElement(Index),
    SwapElements(Index, Index),
    RemoveField(Index),
    /// A number (under a field drawn among the file's field names, so that rare fields such as
    /// `boundary` are hit as often as coordinates) replaced by an extreme or another type.
    Replace(Index, Index, usize),
    /// Such a number moved by a small amount (geometry that still parses and nearly fits).
    Nudge(Index, Index, f64),
}

const REPLACEMENTS: [&str; 16] = [
    "-1",
    "0",
    "1",
    "1.5",
    "1e308",
    "-1e308",
    "1e30",
    "-1e30",
    "3e38",
    "1e6",
    "4294967295",
    "4294967296",
    "18446744073709551615",
    "null",
    "\"\"",
    "[]",
];

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        1 => any::<Index>().prop_map(Edit::RemoveElement),
        1 => any::<Index>().prop_map(Edit::DuplicateElement),
        1 => (any::<Index>(), any::<Index>()).prop_map(|(a, b)| Edit::SwapElements(a, b)),
        1 => any::<Index>().prop_map(Edit::RemoveField),
        2 => (any::<Index>(), any::<Index>(), 0..REPLACEMENTS.len()).prop_map(|(k, i, v)| Edit::Replace(k, i, v)),
        2 => (any::<Index>(), any::<Index>(), prop_oneof![-0.5f64..0.5, -20.0f64..20.0, -500.0f64..500.0]).prop_map(|(k, i, d)| Edit::Nudge(k, i, d)),
    ]
}

/// A step into a JSON value.
#[derive(Clone, Debug)]
enum Step {
    At(usize),
    Key(String),
}

/// Paths to every node of `v` for which `want` holds.
fn paths(v: &Value, want: &dyn Fn(&Value) -> bool, at: &mut Vec<Step>, out: &mut Vec<Vec<Step>>) {
    if want(v) {
        out.push(at.clone());
    }
    match v {
        Value::Array(a) => {
            for (k, x) in a.iter().enumerate() {
                at.push(Step::At(k));
                paths(x, want, at, out);
                at.pop();
            }
        }
        Value::Object(o) => {
            for (k, x) in o {
                at.push(Step::Key(k.clone()));
                paths(x, want, at, out);
                at.pop();
            }
        }
        _ => {}
    }
}

fn node<'a>(v: &'a mut Value, path: &[Step]) -> &'a mut Value {
    path.iter().fold(v, |v, s| match s {
        Step::At(k) => &mut v[*k],
        Step::Key(k) => &mut v[k.as_str()],
    })
}

fn pick(v: &Value, i: &Index, want: &dyn Fn(&Value) -> bool) -> Option<Vec<Step>> {
    let mut out = Vec::new();
    paths(v, want, &mut Vec::new(), &mut out);
    (!out.is_empty()).then(|| out.swap_remove(i.index(out.len())))
}

/// A number under the field drawn by `key` (among the names of fields holding numbers).
fn pick_number(v: &Value, key: &Index, i: &Index) -> Option<Vec<Step>> {
    let mut all = Vec::new();
    paths(v, &Value::is_number, &mut Vec::new(), &mut all);
    let mut keys: Vec<String> = all
        .iter()
        .flatten()
        .filter_map(|s| if let Step::Key(k) = s { Some(k.clone()) } else { None })
        .collect();
    keys.sort();
    keys.dedup();
    if keys.is_empty() {
        return None;
    }
    let k = &keys[key.index(keys.len())];
    let mut under: Vec<Vec<Step>> =
        all.into_iter().filter(|p| p.iter().any(|s| matches!(s, Step::Key(x) if x == k))).collect();
    let n = under.len();
    Some(under.swap_remove(i.index(n)))
}

fn apply(v: &mut Value, e: &Edit) {
    let nonempty_array = |x: &Value| x.as_array().is_some_and(|a| !a.is_empty());
    match e {
        Edit::RemoveElement(i) | Edit::DuplicateElement(i) | Edit::SwapElements(i, _) => {
            let Some(p) = pick(v, i, &nonempty_array) else { return };
            let a = node(v, &p).as_array_mut().expect("picked an array");
            let k = match e {
                Edit::SwapElements(_, j) => j.index(a.len()),
                _ => i.index(a.len()),
            };
            match e {
                Edit::RemoveElement(_) => {
                    a.remove(k);
                }
                Edit::DuplicateElement(_) => a.insert(k, a[k].clone()),
                _ => a.swap(0, k),
            }
        }
        Edit::RemoveField(i) => {
            let Some(p) = pick(v, i, &|x| x.as_object().is_some_and(|o| !o.is_empty())) else {
                return;
            };
            let o = node(v, &p).as_object_mut().expect("picked an object");
            let key = o.keys().nth(i.index(o.len())).cloned().expect("non-empty");
            o.remove(&key);
        }
        Edit::Replace(k, i, r) => {
            let Some(p) = pick_number(v, k, i) else { return };
            *node(v, &p) = serde_json::from_str(REPLACEMENTS[*r]).unwrap_or(Value::Null);
        }
        Edit::Nudge(k, i, d) => {
            let Some(p) = pick_number(v, k, i) else { return };
            let x = node(v, &p);
            let moved = x.as_f64().unwrap_or(0.0) + d;
            // Integers (ids, indices) stay integers so the edit survives deserialisation.
            *x = if x.is_f64() {
                serde_json::json!(moved)
            } else {
                serde_json::json!(moved.round().max(0.0) as u64)
            };
        }
    }
}

/// A text edit of a serialised file.
#[derive(Clone, Debug)]
enum TextEdit {
    Truncate(Index),
    Flip(Index, u8),
    Insert(Index, u8),
    Delete(Index),
}

fn text_edit() -> impl Strategy<Value = TextEdit> {
    prop_oneof![
        any::<Index>().prop_map(TextEdit::Truncate),
        (any::<Index>(), 0u8..7).prop_map(|(i, b)| TextEdit::Flip(i, b)),
        (any::<Index>(), prop::sample::select(b"0123456789-.,:[]{}\"e ".to_vec()))
            .prop_map(|(i, c)| TextEdit::Insert(i, c)),
        any::<Index>().prop_map(TextEdit::Delete),
    ]
}

/// Applies text edits on bytes (ASCII flips keep the text ASCII); non-UTF-8 results are lossy-decoded.
fn apply_text(text: &str, edits: &[TextEdit]) -> String {
    let mut b = text.as_bytes().to_vec();
    for e in edits {
        let len = b.len();
        match e {
            TextEdit::Insert(i, c) => b.insert(i.index(len + 1), *c),
            _ if len == 0 => {}
            TextEdit::Truncate(i) => b.truncate(i.index(len)),
            TextEdit::Flip(i, bit) => b[i.index(len)] ^= 1 << bit,
            TextEdit::Delete(i) => {
                b.remove(i.index(len));
            }
        }
    }
    String::from_utf8_lossy(&b).into_owned()
}

fn json_soup() -> impl Strategy<Value = String> {
    #[rustfmt::skip]
    const VOCAB: &[&str] = &[
        "{", "}", "[", "]", ",", ":", "\"format_version\"", "\"name\"", "\"boundary\"", "\"min\"", "\"max\"", "\"lanes\"", "\"edges\"", "\"routes\"", "\"interaction_zone\"",
        "\"junction_zones\"", "\"spawn_points\"", "\"id\"", "\"width_m\"", "\"centre\"", "\"successors\"", "\"points\"", "\"s_m\"", "\"scenario\"", "\"generator_seed\"", "\"cases\"",
        "\"vehicles\"", "\"spawn\"", "\"route\"", "\"svo_deg\"", "\"merge\"", "0", "1", "-1", "3.5", "1e308", "1e30", "-90.0", "4294967296", "null", "true", "\"\"", "[0.0, 0.0]",
        "[[0,0],[10,0]]", " ",
    ];
    prop::collection::vec(prop::sample::select(VOCAB), 0..96).prop_map(|t| t.concat())
}

/// Checks a scenario loader outcome: a named refusal, or a usable map.
fn check_scenario(r: Result<Map, String>, origin: &str) -> Result<(), TestCaseError> {
    match r {
        Ok(map) => use_map(map),
        Err(msg) => prop_assert!(msg.contains(origin), "refusal does not name the file: {}", msg),
    }
    Ok(())
}

/// Checks a case loader outcome: a named refusal, or usable cases.
fn check_cases(r: Result<CaseFile, String>, map: &Arc<Map>) -> Result<(), TestCaseError> {
    match r {
        Ok(f) => use_cases(&f, map),
        Err(msg) => {
            prop_assert!(msg.contains("sf-sim-fuzz-"), "refusal does not name the file: {}", msg)
        }
    }
    Ok(())
}

#[test]
fn shipped_files_load_and_run() {
    for s in shipped() {
        use_map(load_scenario(&s.scenario_text, s.name).expect("shipped scenario"));
        use_cases(&load_cases(&s.cases_text, &s.map).expect("shipped cases"), &s.map);
    }
}

proptest! {
    #![proptest_config(config(256))]

    /// Structurally edited scenario files: refused naming the file, or usable.
    #[test]
    fn edited_scenarios_are_refused_or_usable(file in 0..SCENARIOS.len(), edits in prop::collection::vec(edit(), 1..=3)) {
        let s = &shipped()[file];
        let mut v = s.scenario.clone();
        for e in &edits {
            apply(&mut v, e);
        }
        let origin = format!("{}-edited.json", s.name);
        check_scenario(load_scenario(&v.to_string(), &origin), &origin)?;
    }

    /// Text-edited (truncated, flipped, spliced) scenario files: refused naming the file, or usable.
    #[test]
    fn damaged_scenario_text_is_refused_or_usable(file in 0..SCENARIOS.len(), edits in prop::collection::vec(text_edit(), 1..=4)) {
        let s = &shipped()[file];
        let origin = format!("{}-damaged.json", s.name);
        check_scenario(load_scenario(&apply_text(&s.scenario_text, &edits), &origin), &origin)?;
    }

    /// Structurally edited case files: refused naming the file, or runnable on their map.
    #[test]
    fn edited_case_files_are_refused_or_usable(file in 0..SCENARIOS.len(), edits in prop::collection::vec(edit(), 1..=3)) {
        let s = &shipped()[file];
        let mut v = s.cases.clone();
        for e in &edits {
            apply(&mut v, e);
        }
        check_cases(load_cases(&v.to_string(), &s.map), &s.map)?;
    }

    /// Text-edited case files: refused naming the file, or runnable on their map.
    #[test]
    fn damaged_case_text_is_refused_or_usable(file in 0..SCENARIOS.len(), edits in prop::collection::vec(text_edit(), 1..=4)) {
        let s = &shipped()[file];
        check_cases(load_cases(&apply_text(&s.cases_text, &edits), &s.map), &s.map)?;
    }

    /// JSON-ish token soup through both loaders.
    #[test]
    fn json_soup_is_refused_or_usable(text in json_soup()) {
        check_scenario(load_scenario(&text, "soup.json"), "soup.json")?;
        let s = &shipped()[2];
        check_cases(load_cases(&text, &s.map), &s.map)?;
    }
}
