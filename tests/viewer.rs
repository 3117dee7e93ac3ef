//! The episode viewer and failure mining in a real headless browser: `socialflow eval --mine`
//! writes pages and an index, `socialflow view` one page; Chromium loads them, steps the
//! scrubber with the page's own `>` button, and the state the page drew is checked against the
//! simulator's, stepped here independently. A screenshot is kept (`SOCIALFLOW_ARTIFACTS`, else
//! the test's directory). Without a browser the test says so and passes, unless
//! `SOCIALFLOW_REQUIRE_BROWSER` is set (`tests/run.sh` sets it after installing Chromium).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::time::Duration;

use sf_sim::case::CaseFile;
use sf_sim::vec_env::{EpisodeSpec, VecEnv};
use sf_sim::{Action, Map, Mode, SimConfig};
use socialflow_e2e::{bin, repo, Proc};

fn socialflow(args: &[&str]) -> std::process::Output {
    let child = Command::new(bin("socialflow"))
        .args(args)
        .current_dir(repo())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn socialflow");
    Proc::new(child).output("socialflow", Duration::from_secs(300))
}

/// A Chromium-like browser: `SOCIALFLOW_CHROMIUM`, else the first on PATH.
fn browser() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("SOCIALFLOW_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    ["chromium", "chromium-browser", "google-chrome", "google-chrome-stable"].iter().find_map(|b| {
        std::env::var_os("PATH")
            .and_then(|path| std::env::split_paths(&path).map(|d| d.join(b)).find(|p| p.is_file()))
    })
}

/// Runs the browser on `url`; its standard output (a page's whole DOM: more than a pipe holds)
/// goes to a file beside the page and is returned.
fn headless(
    chrome: &Path,
    extra: &[&str],
    url: &str,
    out: &Path,
) -> (std::process::Output, String) {
    let file = std::fs::File::create(out).expect("browser output file");
    let child = Command::new(chrome)
        .args(["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"])
        .args(["--no-first-run", "--disable-extensions", "--virtual-time-budget=5000"])
        .args(extra)
        .arg(url)
        .stdout(file)
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("spawn the browser");
    let o = Proc::new(child).output("the headless browser", Duration::from_secs(120));
    (o, std::fs::read_to_string(out).unwrap_or_default())
}

/// The page's DOM after its scripts ran, at `#hash`.
fn dom(chrome: &Path, page: &Path, hash: &str) -> String {
    let url = format!("file://{}#{hash}", page.display());
    let (o, html) = headless(chrome, &["--dump-dom"], &url, &page.with_extension("dom.html"));
    assert!(o.status.success(), "the browser failed on {url}");
    html
}

/// The text of the element `<tag id="id">` in `html`, entities undone.
fn element_text(html: &str, tag: &str, id: &str) -> String {
    let at = html
        .find(&format!("id=\"{id}\""))
        .unwrap_or_else(|| panic!("no <{tag} id={id}> in the page"));
    let start = at + html[at..].find('>').expect("tag closed") + 1;
    let end = start + html[start..].find(&format!("</{tag}>")).expect("element closed");
    html[start..end]
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&quot;", "\"")
        .replace("&amp;", "&")
}

fn grid(dir: &Path) -> PathBuf {
    let cfg = dir.join("grid.toml");
    std::fs::write(
        &cfg,
        format!(
            r#"kind = "eval"
runs = "{data}"
out = "{out}"
scenarios = ["merge", "roundabout"]
cases = 4
seeds = 2
envs = 3
flows = [{{ name = "IDM", job = "idm" }}, {{ name = "IDM+noise", job = "idm-noise", noise_std = 0.6 }}]
egos = [{{ name = "IDM driver", job = "idm" }}]
[experiments]
flow_quality = ["IDM", "IDM+noise"]
cross_validation = ["IDM+noise"]
"#,
            data = dir.join("data").display(),
            out = dir.join("out").display()
        ),
    )
    .expect("grid");
    cfg
}

/// Every vehicle of stored case `case_index` of `scenario` under the all-IDM flow after `steps`
/// steps, stepped here: (x, y, heading, alive) per agent.
fn simulated(scenario: &str, case_index: usize, steps: usize) -> Vec<(f32, f32, f32, bool)> {
    let root = repo();
    let map =
        Arc::new(Map::load(&root.join(format!("configs/scenarios/{scenario}.json"))).expect("map"));
    let cases = CaseFile::load(&root.join(format!("configs/cases/{scenario}.v1.json")), &map)
        .expect("cases");
    let spec = EpisodeSpec {
        case: cases.cases[case_index].clone(),
        vehicles: None,
        svo_deg: None,
        tag: case_index as u64,
    };
    let mut v =
        VecEnv::from_episodes(map, Arc::new(SimConfig::default()), Mode::AllIdm, 1, vec![spec])
            .expect("episode");
    for _ in 0..steps {
        let rows = v.alive().len();
        v.step(&vec![Action::default(); rows]);
    }
    v.env(0)
        .agents()
        .iter()
        .map(|a| (a.state.x_m, a.state.y_m, a.state.theta_rad, a.alive))
        .collect()
}

#[test]
fn the_viewer_draws_the_simulators_state_and_mining_indexes_the_worst_episodes() {
    let Some(chrome) = browser() else {
        assert!(
            std::env::var_os("SOCIALFLOW_REQUIRE_BROWSER").is_none(),
            "SOCIALFLOW_REQUIRE_BROWSER is set but no chromium is on PATH (or SOCIALFLOW_CHROMIUM)"
        );
        eprintln!("skipped: no headless browser (chromium) on PATH; tests/run.sh installs one");
        return;
    };
    let dir = std::env::temp_dir().join(format!("sf-viewer-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("dir");
    let cfg = grid(&dir);
    let cfg_s = cfg.display().to_string();

    // Failure mining: evaluates the grid, then the 2 worst episodes of each of its 6 cells.
    let o = socialflow(&["eval", &cfg_s, "--mine", "worst=2"]);
    assert!(o.status.success(), "eval --mine: {}", String::from_utf8_lossy(&o.stderr));
    let mined = dir.join("out/mined");
    let index = mined.join("index.html");
    let html = dom(&chrome, &index, "");
    assert!(html.contains("data-ready=\"1\""), "the index's script did not finish");
    let rows: Vec<serde_json::Value> =
        serde_json::from_str(&element_text(&html, "script", "data")).expect("index rows");
    assert_eq!(rows.len(), 6 * 2, "2 episodes for each of the 6 cells");
    let rank = |o: &str| {
        ["collision", "off-road", "off-route", "wrong-lane", "road-closed", "timeout", "success"]
            .iter()
            .position(|x| *x == o)
            .unwrap_or_else(|| panic!("unknown outcome {o}"))
    };
    let ranks: Vec<usize> =
        rows.iter().map(|r| rank(r["outcome"].as_str().expect("outcome"))).collect();
    assert!(ranks.windows(2).all(|w| w[0] <= w[1]), "index sorted by outcome: {ranks:?}");
    for r in &rows {
        // Scripted flows draw per episode: every replay ends as its stored row.
        assert_eq!(r["replay_agrees"], serde_json::Value::Bool(true), "{r}");
        let page = mined.join(r["href"].as_str().expect("href"));
        assert!(page.exists(), "{} missing", page.display());
    }
    // The report links each cell's mined pages, copied beside it.
    let report = dir.join("report");
    let o = socialflow(&[
        "report",
        &dir.join("out").display().to_string(),
        "--out",
        &report.display().to_string(),
    ]);
    assert!(o.status.success(), "report: {}", String::from_utf8_lossy(&o.stderr));
    let md = std::fs::read_to_string(report.join("report.md")).expect("report.md");
    assert!(md.contains("## Worst episodes per cell"), "the report has the mined section");
    for r in &rows {
        let href = format!("mined/{}", r["href"].as_str().expect("href"));
        assert!(md.contains(&format!("]({href})")), "report links {href}");
        assert!(report.join(&href).exists(), "{href} copied beside the report");
    }
    // The table the browser built has one body row per episode, with a link each.
    assert_eq!(
        html.matches(".html\">open</a>").count(),
        rows.len(),
        "one link per row in the drawn table"
    );

    // One page by hand: the all-IDM flow in merge, its third stored case, seed 0.
    let cases = CaseFile::load(
        &repo().join("configs/cases/merge.v1.json"),
        &Map::load(&repo().join("configs/scenarios/merge.json")).expect("map"),
    )
    .expect("cases");
    let case_id = cases.cases[2].id.to_string();
    let page = dir.join("merge-idm.html");
    let o = socialflow(&[
        "view",
        &cfg_s,
        "--cell",
        "flow_quality||IDM|merge||",
        "--case",
        &case_id,
        "--seed",
        "0",
        "--page",
        &page.display().to_string(),
    ]);
    assert!(o.status.success(), "view: {}", String::from_utf8_lossy(&o.stderr));
    let bad = socialflow(&["view", &cfg_s, "--cell", "flow_quality||IDM|nowhere||", "--case", "0"]);
    assert!(!bad.status.success());
    assert!(
        String::from_utf8_lossy(&bad.stderr).contains("is not a cell of"),
        "names the bad cell"
    );

    // The page at step 3, then the scrubber's > pressed 4 times: the drawn state is step 7's.
    for (hash, step) in [("step=3&advance=4", 7usize), ("step=0", 0), ("step=12&advance=1", 13)] {
        let html = dom(&chrome, &page, hash);
        assert!(html.contains("data-ready=\"1\""), "the page's script did not finish ({hash})");
        let drawn: serde_json::Value =
            serde_json::from_str(&element_text(&html, "pre", "drawn")).expect("drawn state");
        assert_eq!(drawn["step"].as_u64(), Some(step as u64), "{hash}");
        let sim = simulated("merge", 2, step);
        let vehicles = drawn["vehicles"].as_array().expect("vehicles");
        let live = sim.iter().filter(|a| a.3).count();
        assert!(vehicles.len() >= live, "every live vehicle is drawn ({hash})");
        for v in vehicles {
            let i = v["agent"].as_u64().expect("agent") as usize;
            let (x, y, th, alive) = sim[i];
            let close = |key: &str, want: f32| {
                let got = v[key].as_f64().expect("number") as f32;
                assert!(
                    (got - want).abs() < 1e-4,
                    "agent {i} {key}: drawn {got}, simulated {want} ({hash})"
                );
            };
            close("x_m", x);
            close("y_m", y);
            close("heading_rad", th);
            assert_eq!(v["alive"].as_bool(), Some(alive), "agent {i} alive ({hash})");
        }
    }
    let agree = element_text(&dom(&chrome, &page, "step=0"), "p", "agree");
    assert!(agree.contains("ends as the stored episode did"), "{agree}");

    // A screenshot of the player mid-episode, kept as the run's artifact.
    let shots = std::env::var_os("SOCIALFLOW_ARTIFACTS").map_or_else(|| dir.clone(), PathBuf::from);
    std::fs::create_dir_all(&shots).expect("artifact dir");
    let shot = shots.join("viewer.png");
    let _ = std::fs::remove_file(&shot);
    let url = format!("file://{}#step=20", page.display());
    let (o, _) = headless(
        &chrome,
        &[&format!("--screenshot={}", shot.display()), "--window-size=1280,900"],
        &url,
        &dir.join("screenshot.log"),
    );
    assert!(o.status.success(), "the browser failed taking the screenshot");
    let png = std::fs::read(&shot).expect("screenshot written");
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "a real screenshot ({} bytes)",
        png.len()
    );
    eprintln!("screenshot: {}", shot.display());
    if std::env::var_os("SOCIALFLOW_ARTIFACTS").is_none() {
        let _ = std::fs::remove_dir_all(&dir);
    }
}
