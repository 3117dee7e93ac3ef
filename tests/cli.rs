//! The `socialflow` command as scripts use it: JSON contracts, files written, clear errors.

use std::time::Duration;

use socialflow_e2e::{socialflow, socialflow_env};

const T: Duration = Duration::from_secs(120);

fn json_of(out: &std::process::Output) -> serde_json::Value {
    assert!(out.status.success(), "failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("one JSON object on stdout")
}

#[test]
fn bench_sim_prints_the_contract_fields() {
    let v = json_of(&socialflow(
        &[
            "bench",
            "sim",
            "--scenario",
            "roundabout",
            "--vehicles",
            "12",
            "--seconds",
            "0.5",
            "--threads",
            "1",
            "--json",
        ],
        T,
    ));
    for k in ["scenario", "vehicles", "threads", "agent_steps_per_s", "env_steps_per_s"] {
        assert!(v.get(k).is_some(), "missing {k} in {v}");
    }
    assert_eq!(v["scenario"], "roundabout");
    assert_eq!(v["vehicles"], 12);
    assert!(v["agent_steps_per_s"].as_f64().unwrap_or(0.0) > 0.0);
}

#[test]
fn eval_flow_reports_metrics_with_intervals() {
    let v = json_of(&socialflow(
        &[
            "eval-flow",
            "--flow",
            "idm",
            "--scenario",
            "merge",
            "--cases",
            "6",
            "--seeds",
            "2",
            "--json",
        ],
        T,
    ));
    assert_eq!(v["episodes"], 12);
    for k in ["success", "safety", "speed"] {
        let m = v[k]["mean"].as_f64().expect("mean");
        let ci = v[k]["ci95"].as_f64().expect("ci95");
        assert!((0.0..=1.0).contains(&m) && ci >= 0.0, "{k}: {m} +- {ci}");
    }
    assert!(
        v["safety"]["mean"].as_f64() >= v["success"]["mean"].as_f64(),
        "success implies safety"
    );
}

#[test]
fn render_writes_gif_and_png() {
    let dir = std::env::temp_dir().join(format!("sf-e2e-render-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp");
    let gif = dir.join("ep.gif");
    let png = dir.join("frame.png");
    let g = gif.to_string_lossy().to_string();
    let p = png.to_string_lossy().to_string();
    let out = socialflow(
        &[
            "render",
            "--scenario",
            "intersection",
            "--flow",
            "idm",
            "--case",
            "3",
            "--seed",
            "0",
            "--out",
            &g,
            "--size",
            "200",
        ],
        T,
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(std::fs::read(&gif).expect("gif").starts_with(b"GIF89a"));
    let out = socialflow(
        &[
            "render",
            "--scenario",
            "merge",
            "--case",
            "1",
            "--step",
            "5",
            "--out",
            &p,
            "--size",
            "200",
        ],
        T,
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(std::fs::read(&png).expect("png").starts_with(b"\x89PNG"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_inputs_fail_with_a_message_naming_the_problem() {
    let out = socialflow(
        &["eval-flow", "--flow", "idm", "--scenario", "highway", "--cases", "1", "--seeds", "1"],
        T,
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown scenario `highway`") && err.contains("roundabout"), "{err}");

    // A scenario directory whose merge file has a broken route.
    let dir = std::env::temp_dir().join(format!("sf-e2e-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp");
    let good = std::fs::read_to_string(socialflow_e2e::repo().join("configs/scenarios/merge.json"))
        .expect("merge");
    let mut v: serde_json::Value = serde_json::from_str(&good).expect("json");
    v["routes"][1]["lanes"][0] = serde_json::json!(4242);
    std::fs::write(dir.join("merge.json"), v.to_string()).expect("write");
    let d = dir.to_string_lossy().to_string();
    let out = socialflow(
        &[
            "--scenarios",
            &d,
            "eval-flow",
            "--flow",
            "idm",
            "--scenario",
            "merge",
            "--cases",
            "1",
            "--seeds",
            "1",
        ],
        T,
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("merge.json") && err.contains("routes[1].lanes[0]") && err.contains("4242"),
        "{err}"
    );

    let out = socialflow(
        &["eval-flow", "--flow", "macad", "--scenario", "merge", "--cases", "1", "--seeds", "1"],
        T,
    );
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("needs a trained policy"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bench_sac_prints_the_contract_fields() {
    let v = json_of(&socialflow(
        &["bench", "sac", "--size", "default", "--seconds", "0.5", "--batch", "32", "--json"],
        T,
    ));
    for k in ["size", "batch", "updates_per_s", "inference_obs_per_s"] {
        assert!(v.get(k).is_some(), "missing {k} in {v}");
    }
    assert_eq!(v["size"], "default");
    assert_eq!(v["batch"], 32);
    assert!(v["updates_per_s"].as_f64().unwrap_or(0.0) > 0.0);
}

#[test]
fn plot_curves_overlays_runs_and_names_a_missing_column() {
    let dir = socialflow_e2e::scratch("plot");
    let a = dir.join("a.csv");
    let b = dir.join("b.csv");
    std::fs::write(&a, "env_steps,updates,success\n0,0,0.2\n100,10,0.5\n").expect("a");
    std::fs::write(&b, "env_steps,updates,success\n0,0,0.1\n100,10,0.9\n").expect("b");
    let png = dir.join("out.png");
    let (ra, rb, o) =
        (format!("a={}", a.display()), format!("b={}", b.display()), png.display().to_string());
    let out = socialflow(&["plot-curves", &ra, &rb, "--out", &o], T);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(std::fs::read(&png).expect("png").starts_with(b"\x89PNG"));
    let out = socialflow(&["plot-curves", &ra, "--column", "collision", "--out", &o], T);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("a.csv") && err.contains("no column `collision`"), "{err}");
    let out = socialflow(&["plot-curves", "just-a-path.csv", "--out", &o], T);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("must be NAME=PATH"));
    // A validation.csv (updates first) by updates; a curve without the x column is named.
    let v = dir.join("validation.csv");
    std::fs::write(
        &v,
        "updates,env_steps,episodes,success\n1000,19000,200,0.6\n2000,23000,200,0.8\n",
    )
    .expect("v");
    let rv = format!("v={}", v.display());
    let _ = std::fs::remove_file(&png);
    let out = socialflow(&["plot-curves", &rv, "--x", "updates", "--out", &o], T);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(std::fs::read(&png).expect("png").starts_with(b"\x89PNG"));
    std::fs::write(&b, "episodes,success\n3,0.1\n").expect("b without steps");
    let out = socialflow(&["plot-curves", &rb, "--out", &o], T);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("b.csv") && err.contains("no column `env_steps`"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn train_runs_a_job_embedded_and_writes_its_artifacts() {
    let dir = socialflow_e2e::scratch("train");
    let cfg = dir.join("tiny.toml");
    std::fs::write(&cfg, socialflow_e2e::tiny_job(r#""roundabout""#, "tiny", 1000))
        .expect("config");
    let data = dir.join("data");
    let out = socialflow(
        &[
            "train",
            &cfg.display().to_string(),
            "--workers",
            "2",
            "--data-dir",
            &data.display().to_string(),
            "--set",
            "sac.seed=7",
        ],
        T,
    );
    let v = json_of(&out);
    assert_eq!(v["state"], "succeeded");
    assert_eq!(v["progress"]["env_steps"], 1000);
    assert!(v["progress"]["updates"].as_u64().unwrap_or(0) > 20, "{v}");
    let art = std::path::PathBuf::from(v["artifact_dir"].as_str().expect("artifact_dir"));
    for f in ["curve.csv", "curve.png", "policy.bpk", "config.toml", "checkpoint/actor.bpk"] {
        assert!(art.join(f).exists(), "missing {f}");
    }
    // `--set` is recorded in the job's stored config.
    let stored = std::fs::read_to_string(art.join("config.toml")).expect("config.toml");
    assert!(stored.contains("seed = 7"), "{stored}");
    // Not a terminal: progress lines, not the service's log, which goes to the data directory.
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("job 1 running:") && err.contains("transitions"), "{err}");
    assert!(!err.contains(" INFO "), "INFO lines stay off the terminal:\n{err}");
    let log = std::fs::read_to_string(data.join("socialflow.log")).expect("socialflow.log");
    assert!(log.contains("job started") && log.contains("checkpoint written"), "{log}");
    // A misspelt override is refused naming the key, before anything is created.
    let bad = socialflow(
        &[
            "train",
            &cfg.display().to_string(),
            "--data-dir",
            &dir.join("d2").display().to_string(),
            "--set",
            "sac.seeed=1",
        ],
        T,
    );
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("seeed"));
    assert!(!dir.join("d2").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// `train` on a data directory that fills up mid-job (a tmpfs): it exits non-zero naming the
/// cause and the checkpoint its job's `state.json` records (never one it did not write), and
/// the same command resumes the job once space is freed.
#[test]
fn train_stops_on_a_full_disk_with_the_cause_and_resumes_after() {
    let dir = socialflow_e2e::scratch("train-full");
    let data = dir.join("data");
    let Some(_mount) = socialflow_e2e::Tmpfs::mount(&data, 48) else {
        eprintln!("SKIPPED, cannot mount a tmpfs (needs root; tests/run.sh requires it when run as root): train on a full disk");
        return;
    };
    let cfg = dir.join("tiny.toml");
    std::fs::write(&cfg, socialflow_e2e::tiny_job(r#""roundabout""#, "tiny-full", 2500))
        .expect("config");
    let args: Vec<String> = [
        "train",
        &cfg.display().to_string(),
        "--workers",
        "2",
        "--data-dir",
        &data.display().to_string(),
        "--quiet",
    ]
    .map(String::from)
    .to_vec();
    let run = {
        let args = args.clone();
        std::thread::spawn(move || {
            socialflow(&args.iter().map(String::as_str).collect::<Vec<_>>(), 4 * T)
        })
    };
    let state = data.join("jobs/1-tiny-full/state.json");
    let read_state =
        || serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(&state).ok()?).ok();
    socialflow_e2e::wait_for("a checkpoint", 4 * T, || {
        read_state().filter(|v| v["counters"]["env_steps"].as_u64().is_some_and(|n| n > 400))
    });
    socialflow_e2e::fill_disk(&data, "filler");
    let out = run.join().expect("the train thread");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "train must fail on a full disk: {err}");
    assert!(err.contains("refuses writes") && err.contains("No space left on device"), "{err}");
    let steps = read_state().and_then(|v| v["counters"]["env_steps"].as_u64()).expect("state.json");
    assert!(
        err.contains(&format!("is checkpointed at {steps} environment steps")),
        "the checkpoint on disk is at {steps} steps: {err}"
    );
    std::fs::remove_file(data.join("filler")).expect("freeing space");
    let again = socialflow(&args.iter().map(String::as_str).collect::<Vec<_>>(), 4 * T);
    assert!(
        String::from_utf8_lossy(&again.stderr).contains("resuming job 1 (tiny-full)"),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    let v = json_of(&again);
    assert_eq!(
        (v["state"].as_str(), v["progress"]["env_steps"].as_u64()),
        (Some("succeeded"), Some(2500)),
        "{v}"
    );
    drop(_mount);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn train_with_validation_keeps_the_best_validated_actor() {
    let dir = socialflow_e2e::scratch("validation");
    let cfg = dir.join("tiny.toml");
    let job = socialflow_e2e::tiny_job(r#""roundabout", "merge""#, "tiny-val", 1000)
        + "[validation]\nevery_updates = 20\nepisodes = 3\nenvs = 3\n";
    std::fs::write(&cfg, job).expect("config");
    let out = socialflow(
        &[
            "train",
            &cfg.display().to_string(),
            "--workers",
            "2",
            "--data-dir",
            &dir.join("data").display().to_string(),
            "--quiet",
        ],
        T,
    );
    let v = json_of(&out);
    assert_eq!(v["state"], "succeeded", "{v}");
    let updates = v["progress"]["updates"].as_u64().expect("updates");
    let art = std::path::PathBuf::from(v["artifact_dir"].as_str().expect("artifact_dir"));
    // One point every 20 updates and one for the last actor, each over 3 cases of 2 scenarios.
    let csv = std::fs::read_to_string(art.join("validation.csv")).expect("validation.csv");
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|x| x.parse().expect("number")).collect())
        .collect();
    assert!(csv.starts_with("updates,env_steps,episodes,success,safety"), "{csv}");
    assert_eq!(rows.len() as u64, updates / 20 + u64::from(!updates.is_multiple_of(20)), "{csv}");
    assert!(rows.iter().all(|r| r[2] == 6.0 && (0.0..=1.0).contains(&r[3])), "{csv}");
    assert_eq!(rows.last().map(|r| r[0] as u64), Some(updates));
    // The final policy is the best point's actor, with the point in policy.json.
    let best = rows.iter().fold(&rows[0], |b, r| {
        if r[3] > b[3] || (r[3] == b[3] && r[4] > b[4]) {
            r
        } else {
            b
        }
    });
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(art.join("policy.json")).expect("policy.json"))
            .expect("json");
    assert_eq!(meta["selected_by"], "validation", "{meta}");
    assert_eq!(meta["updates"].as_u64(), Some(best[0] as u64), "{meta} vs {csv}");
    assert_eq!(
        std::fs::read(art.join("policy.bpk")).expect("policy"),
        std::fs::read(art.join("best_policy.bpk")).expect("best")
    );
    // `train` ends with the policy's and the IDM driver's scores on the same held-out episodes:
    // the test cases (another seed), which chose nothing, not the validation cases that did.
    assert_eq!(meta["idm"]["episodes"], 6, "{meta}");
    assert_eq!(meta["test"]["used_for_selection"], false, "{meta}");
    assert_eq!(v["held_out"]["cases"], "test", "{v}");
    assert_eq!(v["held_out"]["used_for_selection"], false, "{v}");
    assert_eq!(v["held_out"]["cases_seed"], meta["test"]["seed"], "{v}");
    assert_ne!(meta["test"]["seed"].as_u64(), None, "{meta}");
    assert_eq!(v["held_out"]["episodes"], 6, "{v}");
    assert_eq!(v["held_out"]["policy"]["success"], meta["test"]["policy"]["success"], "{v}");
    assert_eq!(v["held_out"]["idm"]["collision"], meta["test"]["idm"]["collision"], "{v}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("test cases, seed") && stderr.contains("they chose nothing"),
        "{stderr}"
    );
    assert!(
        v["held_out"]["idm"]["success"].as_f64().is_some_and(|s| (0.0..=1.0).contains(&s)),
        "{v}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_ladder_trains_evaluates_against_idm_and_adds_seeds_to_one_summary() {
    let dir = socialflow_e2e::scratch("ladder");
    std::fs::write(
        dir.join("job.toml"),
        format!(
            "kind = \"ego\"\n{}",
            socialflow_e2e::tiny_job(r#""roundabout""#, "tiny-rung", 600)
        ),
    )
    .expect("job");
    let rung = "rung = \"L-test\"\nname = \"tiny\"\njob = \"job.toml\"\nseeds = [0]\n[eval]\nscenarios = [\"roundabout\"]\ncases = 3\nseeds = 2\nenvs = 3\n[gate]\nmin_success = 0.0\nmax_other_failures = 1.0\n";
    std::fs::write(dir.join("rung.toml"), rung).expect("rung");
    let (data, out) = (dir.join("data").display().to_string(), dir.join("out"));
    let ladder = |seed: &str| {
        let o = socialflow(
            &[
                "ladder",
                &dir.join("rung.toml").display().to_string(),
                "--seeds",
                seed,
                "--data-dir",
                &data,
                "--out",
                &out.display().to_string(),
                "--workers",
                "1",
                "--set",
                "sac.batch_size=24",
            ],
            T,
        );
        assert!(
            o.status.success(),
            "ladder --seeds {seed}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        // Off a terminal, a line per validation (or tenth) of the job it trains, and its end.
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.lines().any(|l| l.starts_with("job ") && l.contains(" succeeded: ")), "{err}");
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("summary.json")).expect("summary.json"))
                .expect("json");
        let episodes = std::fs::read_to_string(out.join("episodes.csv")).expect("episodes.csv");
        (summary, episodes)
    };
    let (summary, episodes) = ladder("0");
    assert_eq!(summary["passed"], true, "{summary}");
    assert_eq!(summary["seeds"].as_array().map(Vec::len), Some(1), "{summary}");
    assert_eq!(summary["seeds"][0]["episodes"], 6, "{summary}");
    // The policy's 3 cases x 2 seeds and the IDM ego's on the same ones.
    let lines: Vec<&str> = episodes.lines().collect();
    assert!(lines[0].starts_with("train_seed,driver,scenario,case,seed"), "{episodes}");
    let drivers = |s: &str| {
        lines[1..].iter().filter(|l| l.starts_with(&format!("0,{s},roundabout,"))).count()
    };
    assert_eq!((lines.len() - 1, drivers("policy"), drivers("idm")), (12, 6, 6), "{episodes}");
    assert!(out.join("seed-0/curve.csv").exists() && out.join("success.png").exists());
    let stored = std::fs::read_to_string(out.join("seed-0/config.toml")).expect("config.toml");
    assert!(stored.contains("batch_size = 24"), "the ladder's `--set` is recorded: {stored}");
    // A second seed run into the same directory keeps the first one's summary and episodes.
    let (summary, episodes) = ladder("1");
    let seeds: Vec<u64> = summary["seeds"]
        .as_array()
        .expect("seeds")
        .iter()
        .filter_map(|s| s["train_seed"].as_u64())
        .collect();
    assert_eq!(seeds, vec![0, 1], "{summary}");
    assert_eq!(episodes.lines().count() - 1, 24, "{episodes}");
    assert_eq!(episodes.lines().filter(|l| l.starts_with("1,")).count(), 12);
    // `eval.sampled`: the same finished policy re-evaluated (`--eval-only`) with its sampled
    // actions; the IDM driver's episodes are the same, the policy's are not.
    std::fs::write(
        dir.join("rung-sampled.toml"),
        rung.replace("envs = 3\n", "envs = 3\nsampled = true\n"),
    )
    .expect("rung");
    let out2 = dir.join("out-sampled");
    let o = socialflow(
        &[
            "ladder",
            &dir.join("rung-sampled.toml").display().to_string(),
            "--seeds",
            "0",
            "--eval-only",
            "--data-dir",
            &data,
            "--out",
            &out2.display().to_string(),
        ],
        T,
    );
    assert!(
        o.status.success(),
        "ladder --eval-only (sampled): {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let sampled = std::fs::read_to_string(out2.join("episodes.csv")).expect("episodes.csv");
    let rows = |text: &str, driver: &str| -> Vec<String> {
        text.lines()
            .filter(|l| l.starts_with(&format!("0,{driver},")))
            .map(str::to_string)
            .collect()
    };
    assert_eq!(rows(&sampled, "idm"), rows(&episodes, "idm"));
    assert_eq!(rows(&sampled, "policy").len(), 6, "{sampled}");
    assert_ne!(
        rows(&sampled, "policy"),
        rows(&episodes, "policy"),
        "sampled actions drive other episodes than the mean action"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn invalid_configs_are_refused_with_the_field_named() {
    let dir = socialflow_e2e::scratch("badcfg");
    let job = dir.join("bad.toml");
    std::fs::write(
        &job,
        socialflow_e2e::tiny_job(r#""roundabout""#, "bad", 1000)
            .replace("samples_per_insert = 0.1", "samples_per_insert = -1.0"),
    )
    .expect("config");
    let out = socialflow(
        &["train", &job.display().to_string(), "--data-dir", &dir.join("d").display().to_string()],
        T,
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("train.samples_per_insert"), "{err}");
    assert!(!dir.join("d").exists(), "nothing may be created for an invalid config");
    let learner = dir.join("learner.toml");
    std::fs::write(&learner, "grpc_addr = \"127.0.0.1:0\"\nmax_message_bytes = 10\n")
        .expect("config");
    let out = socialflow(&["learner", "--config", &learner.display().to_string()], T);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("max_message_bytes"), "{err}");
    std::fs::write(&learner, "grpc_port = 5\n").expect("config");
    let out = socialflow(&["learner", "--config", &learner.display().to_string()], T);
    assert!(String::from_utf8_lossy(&out.stderr).contains("grpc_port"), "unknown fields are named");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn stage_one_flows_train_through_the_service() {
    for kind in ["macad", "copo", "socialcomm"] {
        let dir = socialflow_e2e::scratch(&format!("flow-{kind}"));
        let cfg = dir.join("flow.toml");
        let mut text = socialflow_e2e::tiny_job(r#""merge""#, kind, 1200).replacen(
            '\n',
            &format!("\nkind = \"{kind}\"\n"),
            1,
        );
        if kind == "copo" {
            text.push_str("[coordinator]\niterations = 2\npopulation = 4\nenvs = 4\n");
        }
        std::fs::write(&cfg, text).expect("config");
        let v = json_of(&socialflow(
            &[
                "train",
                &cfg.display().to_string(),
                "--workers",
                "1",
                "--data-dir",
                &dir.join("data").display().to_string(),
                "--quiet",
            ],
            T,
        ));
        assert_eq!(v["state"], "succeeded", "{kind}");
        assert_eq!(v["progress"]["env_steps"], 1200);
        assert!(v["progress"]["episodes"].as_u64().unwrap_or(0) > 0, "{kind}: {v}");
        let resolved = std::fs::read_to_string(
            std::path::Path::new(v["artifact_dir"].as_str().expect("dir")).join("config.toml"),
        )
        .expect("resolved config");
        assert!(resolved.contains(&format!("kind = \"{kind}\"")), "{resolved}");
        // The learned flow drives every vehicle of stored cases; same seeds, same numbers.
        let art = v["artifact_dir"].as_str().expect("dir").to_string();
        let eval = || {
            json_of(&socialflow(
                &[
                    "eval-flow",
                    "--policy",
                    &art,
                    "--scenario",
                    "merge",
                    "--cases",
                    "2",
                    "--seeds",
                    "2",
                    "--json",
                ],
                T,
            ))
        };
        let e = eval();
        assert_eq!(e["flow"], kind);
        assert_eq!(e["episodes"], 4);
        for k in ["success", "safety", "speed"] {
            let m = e[k]["mean"].as_f64().expect("mean");
            assert!((0.0..=1.0).contains(&m), "{k} {m}");
        }
        assert_eq!(
            eval(),
            e,
            "an evaluation with the same policy, cases and seeds is reproducible"
        );
        if kind == "copo" {
            // CoPO Stage 2: the job fitted its coordinator on its frozen Stage-1 policy by itself
            // (a Gaussian over SVO per scenario, two CEM iterations as configured).
            let text = std::fs::read_to_string(std::path::Path::new(&art).join("coordinator.json"))
                .expect("the copo job wrote coordinator.json");
            let c: serde_json::Value = serde_json::from_str(&text).expect("json");
            let merge = &c["scenarios"][0];
            assert_eq!(merge["scenario"], "merge", "{c}");
            let m = merge["gaussian"]["mean_deg"].as_f64().expect("mean");
            assert!(
                (0.0..=90.0).contains(&m) && merge["history"].as_array().map(Vec::len) == Some(2),
                "{c}"
            );
            // The same on demand, to another file; a Stage-2 evaluation differs from Stage 1's.
            let other = dir.join("coord.json").display().to_string();
            let c = json_of(&socialflow(
                &[
                    "copo-coordinator",
                    "--policy",
                    &art,
                    "--iterations",
                    "1",
                    "--population",
                    "3",
                    "--envs",
                    "3",
                    "--out",
                    &other,
                ],
                T,
            ));
            assert_eq!(c["scenarios"][0]["history"].as_array().map(Vec::len), Some(1), "{c}");
            let stage1 = json_of(&socialflow(
                &[
                    "eval-flow",
                    "--policy",
                    &art,
                    "--scenario",
                    "merge",
                    "--cases",
                    "2",
                    "--seeds",
                    "2",
                    "--json",
                    "--stage1",
                ],
                T,
            ));
            assert_eq!(stage1["episodes"], 4);
            // An ego among the CoPO flow from Python: Stage 2's SVO draws included.
            python_ego_equals_cli(&art, "the CoPO flow");
        } else {
            let out = socialflow(&["copo-coordinator", "--policy", &art, "--scenario", "merge"], T);
            assert!(!out.status.success(), "the coordinator needs a CoPO flow");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}

#[test]
fn a_pipeline_runs_flows_before_the_egos_that_need_them_and_resumes() {
    let dir = socialflow_e2e::scratch("pipeline");
    let graph = dir.join("graph");
    std::fs::create_dir_all(&graph).expect("dir");
    let job = |name: &str, extra_top: &str, extra_env: &str, steps: u64| {
        socialflow_e2e::tiny_job(r#""merge""#, name, steps)
            .replacen('\n', &format!("\n{extra_top}"), 1)
            .replacen("vehicles_max = 3\n", &format!("vehicles_max = 3\n{extra_env}"), 1)
    };
    // Both validate: the ego among the flow's frozen policy, the flow driving every vehicle.
    let validation =
        |every: u32| format!("[validation]\nevery_updates = {every}\nepisodes = 3\nenvs = 3\n");
    std::fs::write(
        graph.join("a-ego.toml"),
        job("ego-in-flow", "", "background_from = \"flow\"\n", 600) + &validation(10),
    )
    .expect("config");
    std::fs::write(
        graph.join("b-flow.toml"),
        job("flow", "kind = \"macad\"\n", "", 900) + &validation(20),
    )
    .expect("config");
    let data = dir.join("data").display().to_string();
    let g = graph.display().to_string();
    let args =
        ["pipeline", &g, "--embedded", "1", "--data-dir", &data, "--set", "sac.batch_size=24"];
    let out = socialflow(&args, T);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    // Off a terminal, a line per job as it is queued, starts, validates and ends: the ego waits
    // for its flow, so it is first seen queued; each ends with its held-out success.
    let said = |name: &str, what: &str, also: &str| {
        err.lines().any(|l| {
            l.starts_with(&format!("{name}: job ")) && l.contains(what) && l.contains(also)
        })
    };
    assert!(said("ego-in-flow", " queued: ", ""), "{err}");
    for name in ["flow", "ego-in-flow"] {
        assert!(said(name, " succeeded: ", "held-out"), "no end line of {name}: {err}");
    }
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON line"))
        .collect();
    assert_eq!(lines.len(), 2);
    assert!(lines.iter().all(|v| v["state"] == "succeeded"), "{lines:?}");
    let id = |n: &str| {
        lines.iter().find(|v| v["name"] == n).and_then(|v| v["job_id"].as_u64()).expect("job id")
    };
    assert!(
        id("flow") < id("ego-in-flow"),
        "the flow is submitted first although its file sorts last"
    );
    for v in &lines {
        let art = std::path::PathBuf::from(v["artifact_dir"].as_str().expect("artifact_dir"));
        let csv = std::fs::read_to_string(art.join("validation.csv")).expect("validation.csv");
        assert!(csv.lines().count() >= 3, "{}: {csv}", v["name"]);
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(art.join("policy.json")).expect("policy.json"))
                .expect("json");
        assert_eq!(meta["selected_by"], "validation", "{}: {meta}", v["name"]);
        let stored = std::fs::read_to_string(art.join("config.toml")).expect("config.toml");
        assert!(stored.contains("batch_size = 24"), "`--set` is recorded: {stored}");
    }
    // Rerun: nothing new is submitted.
    let again = socialflow(&args, T);
    assert!(again.status.success());
    let err = String::from_utf8_lossy(&again.stderr);
    assert_eq!(err.matches("already on the learner").count(), 2, "{err}");
    // A dangling reference is refused before anything starts.
    std::fs::write(
        graph.join("c-bad.toml"),
        job("bad", "", "background_from = \"nowhere\"\n", 100),
    )
    .expect("config");
    let bad = socialflow(&args, T);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("nowhere"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// With `SOCIALFLOW_PKG_PYTHON` (an interpreter with the socialflow package): the IDM driver as a
/// Python policy among the trained flow in `flow` (a job directory) scores what
/// `eval-flow --policy <flow> --ego idm` scores, episode by episode, and the Gymnasium
/// environment steps among that flow (`tests/python/flow_ego_equality.py`).
fn python_ego_equals_cli(flow: &str, what: &str) {
    let Ok(py) = std::env::var("SOCIALFLOW_PKG_PYTHON") else {
        eprintln!("SKIPPED, SOCIALFLOW_PKG_PYTHON not set (tests/run.sh sets it): the Python package's run among {what} is skipped");
        return;
    };
    let cli = socialflow(
        &[
            "eval-flow",
            "--policy",
            flow,
            "--ego",
            "idm",
            "--scenario",
            "merge",
            "--cases",
            "6",
            "--seeds",
            "2",
            "--json",
        ],
        T,
    );
    assert!(cli.status.success(), "{what}: {}", String::from_utf8_lossy(&cli.stderr));
    let cli: serde_json::Value = serde_json::from_slice(&cli.stdout).expect("JSON");
    let out = std::process::Command::new(&py)
        .arg(socialflow_e2e::repo().join("tests/python/flow_ego_equality.py"))
        .args([flow, "merge", "6", "2"])
        .output()
        .expect("python");
    assert!(out.status.success(), "{what}: {}", String::from_utf8_lossy(&out.stderr));
    let py: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let (a, b) =
        (cli["episodes"].as_array().expect("rows"), py["episodes"].as_array().expect("rows"));
    assert_eq!(a.len(), 12, "{what}");
    assert_eq!(a.len(), b.len(), "{what}");
    for (x, y) in a.iter().zip(b) {
        for k in ["case", "seed", "success", "safety", "speed", "collision"] {
            let (x, y) = (x[k].as_f64().expect("number"), y[k].as_f64().expect("number"));
            assert!((x - y).abs() < 1e-6, "{what} {k}: CLI {x} vs Python {y}");
        }
    }
}

/// FNV-1a (64-bit) checksum of a file's bytes: enough to see any change.
fn checksum(p: &std::path::Path) -> u64 {
    let bytes = std::fs::read(p).unwrap_or_else(|e| panic!("reading {}: {e}", p.display()));
    bytes
        .iter()
        .fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
}

/// The paper's two RARL pipelines at a tiny budget, on top of a Stage-1 flow: FailMaker
/// (background trained against the frozen RL/IDM ego, then the ego continued against it) and
/// SocialCommAdv (the adversary trained against the frozen RL/SocialComm ego over the frozen
/// SocialComm flow, then the ego continued against both). Frozen policies stay bit-identical.
#[test]
fn the_rarl_pipelines_run_end_to_end_and_leave_frozen_policies_untouched() {
    let dir = socialflow_e2e::scratch("rarl");
    let graph = dir.join("graph");
    std::fs::create_dir_all(&graph).expect("dir");
    let job = |file: &str, name: &str, kind: &str, env: &str, train: &str, steps: u64| {
        let text = socialflow_e2e::tiny_job(r#""merge""#, name, steps)
            .replacen('\n', &format!("\nkind = \"{kind}\"\n"), 1)
            .replacen("vehicles_max = 3\n", &format!("vehicles_max = 3\n{env}"), 1)
            .replacen("max_policy_lag = 1000\n", &format!("max_policy_lag = 1000\n{train}"), 1);
        std::fs::write(graph.join(file), text).expect("config");
    };
    job("flow-sc.toml", "flow-sc", "socialcomm", "", "", 900);
    job("ego-idm.toml", "ego-idm", "ego", "", "", 600);
    job("ego-sc.toml", "ego-sc", "ego", "background_from = \"flow-sc\"\n", "", 600);
    let data = dir.join("data").display().to_string();
    let args = ["pipeline", &graph.display().to_string(), "--embedded", "1", "--data-dir", &data];
    let run = || {
        let out = socialflow(&args, 4 * T);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).expect("JSON line"))
            .collect::<Vec<_>>()
    };
    let first = run();
    let art = |lines: &[serde_json::Value], n: &str| {
        std::path::PathBuf::from(
            lines
                .iter()
                .find(|v| v["name"] == n)
                .and_then(|v| v["artifact_dir"].as_str())
                .unwrap_or_else(|| panic!("{n} missing")),
        )
    };
    let frozen = ["flow-sc", "ego-idm", "ego-sc"];
    let sums: Vec<u64> =
        frozen.iter().map(|n| checksum(&art(&first, n).join("policy.bpk"))).collect();
    // Round 1 of each RARL pipeline, added to the same graph: the finished jobs are reused.
    job("fm-1.toml", "fm-1", "failmaker", "ego_from = \"ego-idm\"\n", "", 600);
    job(
        "ego-fm-1.toml",
        "ego-fm-1",
        "ego",
        "background_from = \"fm-1\"\n",
        "init_from = \"ego-idm\"\n",
        600,
    );
    job(
        "adv-1.toml",
        "adv-1",
        "socialcomm-adv",
        "background_from = \"flow-sc\"\nego_from = \"ego-sc\"\n",
        "",
        600,
    );
    job(
        "ego-adv-1.toml",
        "ego-adv-1",
        "ego",
        "background_from = \"adv-1\"\n",
        "init_from = \"ego-sc\"\n",
        600,
    );
    let second = run();
    assert_eq!(second.len(), 7);
    assert!(second.iter().all(|v| v["state"] == "succeeded"), "{second:?}");
    for (n, s) in frozen.iter().zip(&sums) {
        assert_eq!(
            checksum(&art(&second, n).join("policy.bpk")),
            *s,
            "{n}'s policy changed while others trained against it"
        );
    }
    let id = |n: &str| {
        second.iter().find(|v| v["name"] == n).and_then(|v| v["job_id"].as_u64()).expect("id")
    };
    assert!(
        id("ego-sc") < id("adv-1") && id("adv-1") < id("ego-adv-1") && id("fm-1") < id("ego-fm-1"),
        "dependencies first: {second:?}"
    );
    for n in ["fm-1", "adv-1", "ego-fm-1", "ego-adv-1"] {
        let v = second.iter().find(|v| v["name"] == n).expect("job");
        assert_eq!(v["progress"]["env_steps"], 600, "{n}");
        assert!(v["progress"]["episodes"].as_u64().unwrap_or(0) > 0, "{n}: {v}");
    }
    // The Python package drives an ego among these flows (SocialCommAdv with its adversary and
    // its SocialComm flow, FailMaker) and scores what the CLI scores, episode by episode.
    for n in ["adv-1", "fm-1"] {
        python_ego_equals_cli(&art(&second, n).display().to_string(), n);
    }

    // The resolved configs carry the ids the names became.
    let cfg =
        std::fs::read_to_string(art(&second, "ego-adv-1").join("config.toml")).expect("config");
    assert!(
        cfg.contains(&format!("background_job = {}", id("adv-1")))
            && cfg.contains(&format!("init_job = {}", id("ego-sc"))),
        "{cfg}"
    );

    // The evaluation grid on these jobs: reproducible, resumable, and a report builds from it.
    let eval_cfg = |out: &str| {
        eval_toml(&data, &dir.join(out), 2, 4)
            + r#"ours = "RARL/SCA"
flows = [{ name = "IDM", job = "idm" }, { name = "SocialComm", job = "flow-sc" }, { name = "SocialCommAdv", job = "adv-1" }, { name = "FailMaker", job = "fm-1" }]
egos = [{ name = "RL/IDM", job = "ego-idm", trained_in = "IDM" }, { name = "RL/SocialComm", job = "ego-sc", trained_in = "SocialComm" }, { name = "RARL/FailMaker", job = "ego-fm-1", trained_in = "FailMaker" }, { name = "RARL/SCA", job = "ego-adv-1", trained_in = "SocialCommAdv" }]
[experiments]
flow_quality = ["IDM", "SocialComm"]
cross_validation = ["IDM", "SocialComm"]
svo_sweep = { flows = ["SocialComm"], values = 2, scenarios = ["merge"] }
density = { scenario = "merge", flows = ["SocialComm"], vehicles = [2, 3] }
adversary = { egos = ["RL/IDM", "RL/SocialComm"], flows = ["SocialComm", "SocialCommAdv", "FailMaker"] }
gifs = { ego = "RL/SocialComm", flows = ["SocialComm", "SocialCommAdv"], scenarios = ["merge"] }
"#
    };
    for out in ["eval-a", "eval-b"] {
        std::fs::write(dir.join(format!("{out}.toml")), eval_cfg(out)).expect("eval config");
        let o =
            socialflow(&["eval", &dir.join(format!("{out}.toml")).display().to_string()], 4 * T);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let a = std::fs::read_to_string(dir.join("eval-a/episodes.csv")).expect("results");
    assert_eq!(a.lines().count(), 1 + (2 + 8 + 2 + 2 + 6) * 4, "one line per episode of each cell");
    assert_eq!(
        a,
        std::fs::read_to_string(dir.join("eval-b/episodes.csv")).expect("results"),
        "same policies, cases and seeds: same numbers"
    );
    let again = socialflow(&["eval", &dir.join("eval-a.toml").display().to_string()], 4 * T);
    assert!(
        String::from_utf8_lossy(&again.stderr).contains("0 cells to run"),
        "{}",
        String::from_utf8_lossy(&again.stderr)
    );
    assert_eq!(
        std::fs::read_to_string(dir.join("eval-a/episodes.csv")).expect("results"),
        a,
        "a rerun keeps what is stored"
    );
    let report = dir.join("report");
    let r = json_of(&socialflow(
        &[
            "report",
            &dir.join("eval-a").display().to_string(),
            "--out",
            &report.display().to_string(),
        ],
        T,
    ));
    assert_eq!(r["experiments"].as_array().map(Vec::len), Some(5), "{r}");
    assert!(report.join("report.html").exists() && report.join("cross-success-merge.png").exists());
    let gif =
        std::fs::read(report.join("gif-merge.gif")).expect("the side-by-side GIF is in the report");
    assert!(gif.starts_with(b"GIF89a") && gif.len() > 10_000, "{} bytes", gif.len());
    // The page references its charts and the GIF beside it by file name, embedding nothing.
    let html = std::fs::read_to_string(report.join("report.html")).expect("html");
    assert!(html.contains("<img src=\"gif-merge.gif\"") && !html.contains("data:"), "{html}");

    // Two result sets as replicates of one graph: each its own report, the pooled one beside;
    // a result set of another grid is refused by name before anything is written.
    let both = dir.join("report-replicates");
    let (ea, eb) =
        (dir.join("eval-a").display().to_string(), dir.join("eval-b").display().to_string());
    let r = json_of(&socialflow(&["report", &ea, &eb, "--out", &both.display().to_string()], T));
    assert_eq!(r["replicates"].as_array().map(Vec::len), Some(2), "{r}");
    assert_eq!(r["episodes"].as_u64(), Some(2 * (a.lines().count() as u64 - 1)), "{r}");
    assert!(both.join("run-1/report.md").exists() && both.join("run-2/report.md").exists());
    let other = dir.join("eval-other");
    std::fs::create_dir_all(&other).expect("dir");
    std::fs::copy(dir.join("eval-a/episodes.csv"), other.join("episodes.csv")).expect("copy");
    let mut meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("eval-a/meta.json")).expect("meta"))
            .expect("meta JSON");
    meta["cases"] = serde_json::json!(3);
    std::fs::write(other.join("meta.json"), meta.to_string()).expect("meta");
    let bad = socialflow(
        &[
            "report",
            &ea,
            &other.display().to_string(),
            "--out",
            &dir.join("report-bad").display().to_string(),
        ],
        T,
    );
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success() && err.contains("eval-other") && err.contains("same grid"),
        "{err}"
    );
    assert!(!dir.join("report-bad").exists(), "nothing written");

    // The probes: a constant message told of the ego, a flow's actor in the ego's seat, and an
    // experiment sized on its own (3 cases, the grid's 2 elsewhere) run in `eval`.
    let probe = dir.join("probe.toml");
    std::fs::write(
        &probe,
        eval_toml(&data, &dir.join("probe"), 1, 3)
            + r#"flows = [{ name = "SocialComm", job = "flow-sc" }, { name = "SC told0", job = "flow-sc", messages = { told_ego_deg = 0.0 } }]
egos = [{ name = "RL/SocialComm", job = "ego-sc" }, { name = "SC actor", job = "flow-sc", flow_actor = true }]
[sizes]
adversary = { cases = 3 }
[experiments]
adversary = { egos = ["RL/SocialComm", "SC actor"], flows = ["SocialComm", "SC told0"] }
"#,
    )
    .expect("probe config");
    let o = socialflow(&["eval", &probe.display().to_string()], 4 * T);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let p = std::fs::read_to_string(dir.join("probe/episodes.csv")).expect("probe results");
    assert_eq!(p.lines().count(), 1 + 2 * 2 * 3, "2 egos x 2 flows x 3 cases x 1 seed: {p}");
    assert!(p.lines().any(|l| l.starts_with("adversary,SC actor,SC told0,merge,")), "{p}");

    // The same file submitted to a learner on that data directory: its cells shared by two
    // worker processes, the same episodes and the same GIF.
    let l = socialflow_e2e::start_learner(&dir, 64 << 20);
    let _w: Vec<socialflow_e2e::Proc> =
        (0..2).map(|k| socialflow_e2e::start_worker(&l, &dir, k)).collect();
    // `submit --set`: the override is in the config the learner stores (cancelled at once).
    let token = [("SOCIALFLOW_TOKEN", socialflow_e2e::TOKEN)];
    let job_file = dir.join("set-job.toml");
    let tiny = socialflow_e2e::tiny_job(r#""merge""#, "set-job", 100_000);
    std::fs::write(&job_file, format!("kind = \"ego\"\n{tiny}")).expect("job");
    let job_path = job_file.display().to_string();
    let args = ["submit", &job_path, "--learner", &l.url, "--set", "sac.batch_size=24"];
    let set = socialflow_env(&args, &token, T);
    assert!(set.status.success(), "{}", String::from_utf8_lossy(&set.stderr));
    let queued: serde_json::Value = String::from_utf8_lossy(&set.stdout)
        .lines()
        .next()
        .and_then(|l| serde_json::from_str(l).ok())
        .expect("the job as JSON");
    let stored = queued["config_toml"].as_str().unwrap_or_default();
    assert!(stored.contains("batch_size = 24"), "`submit --set` is recorded: {stored}");
    let id = queued["job_id"].to_string();
    let cancel = socialflow_env(&["cancel", &id, "--learner", &l.url], &token, T);
    assert!(cancel.status.success(), "{}", String::from_utf8_lossy(&cancel.stderr));
    // A probe only `socialflow eval` runs: the learner refuses it, naming the entry.
    let refused = socialflow_env(
        &["submit", &probe.display().to_string(), "--learner", &l.url],
        &[("SOCIALFLOW_TOKEN", socialflow_e2e::TOKEN)],
        T,
    );
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success()
            && err.contains("SC told0")
            && err.contains("`socialflow eval` only"),
        "{err}"
    );
    let sub = socialflow_env(
        &["submit", &dir.join("eval-a.toml").display().to_string(), "--learner", &l.url, "--watch"],
        &[("SOCIALFLOW_TOKEN", socialflow_e2e::TOKEN)],
        4 * T,
    );
    assert!(sub.status.success(), "{}", String::from_utf8_lossy(&sub.stderr));
    let job: serde_json::Value = String::from_utf8_lossy(&sub.stdout)
        .lines()
        .next()
        .and_then(|l| serde_json::from_str(l).ok())
        .expect("the job as JSON");
    let art = std::path::PathBuf::from(job["artifact_dir"].as_str().expect("artifact dir"));
    let sorted = |text: &str| {
        let mut rows: Vec<&str> = text.lines().collect();
        rows.sort();
        rows.join("\n")
    };
    let shared =
        std::fs::read_to_string(art.join("episodes.csv")).expect("the evaluation job's results");
    assert_eq!(sorted(&shared), sorted(&a), "embedded and shared by workers: the same episodes");
    assert_eq!(
        std::fs::read(art.join("gif-merge.gif")).expect("GIF"),
        std::fs::read(dir.join("eval-a/gif-merge.gif")).expect("GIF")
    );

    // The whole graph, its evaluation and the report from one command: everything is reused
    // from the runs above, and the report is built from the evaluation job's results.
    let mut l = l;
    assert!(l.proc.terminate(Duration::from_secs(30)), "the learner stops on SIGTERM");
    let report2 = dir.join("report2");
    let o = socialflow(
        &[
            "pipeline",
            &graph.display().to_string(),
            "--embedded",
            "1",
            "--data-dir",
            &data,
            "--eval",
            &dir.join("eval-a.toml").display().to_string(),
            "--report",
            &report2.display().to_string(),
        ],
        4 * T,
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON line"))
        .collect();
    assert!(
        lines.iter().any(|v| v["job_id"] == job["job_id"] && v["state"] == "succeeded"),
        "the evaluation job is reused: {lines:?}"
    );
    assert_eq!(
        lines.last().and_then(|v| v["experiments"].as_array()).map(Vec::len),
        Some(5),
        "the report's findings come last"
    );
    assert!(report2.join("report.html").exists() && report2.join("gif-merge.gif").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

/// The head of an evaluation grid over data directory `data` in merge, 2 cases per cell, its
/// results in `out`.
fn eval_toml(data: &str, out: &std::path::Path, seeds: u32, envs: u32) -> String {
    format!("kind = \"eval\"\nruns = \"{data}\"\nout = \"{}\"\nscenarios = [\"merge\"]\ncases = 2\nseeds = {seeds}\nenvs = {envs}\n", out.display())
}

/// `train --continue-from`: a run goes on from a copy of its job directory that has no replay
/// (as a committed run has), from exactly the state it stopped in, refills its replay and trains
/// to the new total; directories it cannot continue are refused naming the field.
#[test]
fn train_continues_a_run_from_a_copied_job_directory_without_its_replay() {
    use sha2::Digest;
    let dir = socialflow_e2e::scratch("continue");
    let validation = "[validation]\nevery_updates = 10\nepisodes = 3\nenvs = 3\n";
    let cfg = |steps: u64, kind: &str| {
        socialflow_e2e::tiny_job(r#""merge""#, "run", steps).replacen(
            '\n',
            &format!("\nkind = \"{kind}\"\n"),
            1,
        ) + "keep_actors_at_placeholder\n"
            + validation
    };
    // keep_actors_at belongs to [train]; put it after env_steps.
    let write = |name: &str, steps: u64, kind: &str| {
        let p = dir.join(name);
        let text = cfg(steps, kind).replace("keep_actors_at_placeholder\n", "").replacen(
            &format!("env_steps = {steps}\n"),
            &format!("env_steps = {steps}\nkeep_actors_at = [5]\n"),
            1,
        );
        std::fs::write(&p, text).expect("config");
        p.display().to_string()
    };
    let first = write("first.toml", 600, "macad");
    let data1 = dir.join("data1").display().to_string();
    let v = json_of(&socialflow(
        &["train", &first, "--workers", "1", "--quiet", "--data-dir", &data1],
        T,
    ));
    let art = std::path::PathBuf::from(v["artifact_dir"].as_str().expect("artifact_dir"));
    assert!(
        art.join("kept/actor-5.bpk").is_file(),
        "train.keep_actors_at keeps the actor at 5 updates"
    );
    // What a commit keeps: everything but the replay (and TensorBoard's files).
    let committed = dir.join("committed");
    for sub in ["", "checkpoint", "kept"] {
        std::fs::create_dir_all(committed.join(sub)).expect("dir");
        for e in std::fs::read_dir(art.join(sub)).expect("read") {
            let p = e.expect("entry").path();
            if p.is_file() {
                std::fs::copy(&p, committed.join(sub).join(p.file_name().expect("name")))
                    .expect("copy");
            }
        }
    }
    let src_state: serde_json::Value = serde_json::from_slice(
        &std::fs::read(committed.join("checkpoint/state.json")).expect("state"),
    )
    .expect("json");
    let src_updates = src_state["updates"].as_u64().expect("updates");
    let src_validation =
        std::fs::read_to_string(committed.join("validation.csv")).expect("validation.csv");
    let from = committed.display().to_string();

    let second = write("second.toml", 1200, "macad");
    let data2 = dir.join("data2").display().to_string();
    let args = [
        "train",
        &second,
        "--workers",
        "1",
        "--quiet",
        "--data-dir",
        &data2,
        "--continue-from",
        &from,
    ];
    let v = json_of(&socialflow(&args, T));
    assert_eq!(v["state"], "succeeded", "{v}");
    let art2 = std::path::PathBuf::from(v["artifact_dir"].as_str().expect("artifact_dir"));
    let marker: serde_json::Value =
        serde_json::from_slice(&std::fs::read(art2.join("continued_from.json")).expect("marker"))
            .expect("json");
    let sha = |p: &std::path::Path| {
        sha2::Sha256::digest(std::fs::read(p).expect("weights"))
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect::<String>()
    };
    assert_eq!(marker["updates"].as_u64(), Some(src_updates), "{marker}");
    assert_eq!(marker["replay"], false, "{marker}");
    assert_eq!(
        marker["actor_sha256"].as_str(),
        Some(sha(&committed.join("checkpoint/actor.bpk")).as_str()),
        "the first update starts from the source's final actor"
    );
    assert_eq!(
        marker["critic_sha256"].as_str(),
        Some(sha(&committed.join("checkpoint/critic.bpk")).as_str()),
        "and its critic"
    );
    let state: serde_json::Value =
        serde_json::from_slice(&std::fs::read(art2.join("state.json")).expect("state"))
            .expect("json");
    assert!(state["counters"]["env_steps"].as_u64() >= Some(1200), "{state}");
    let ckpt: serde_json::Value =
        serde_json::from_slice(&std::fs::read(art2.join("checkpoint/state.json")).expect("state"))
            .expect("json");
    assert!(
        ckpt["updates"].as_u64() > Some(src_updates + 10),
        "it trained on after the refill: {ckpt}"
    );
    let validation2 = std::fs::read_to_string(art2.join("validation.csv")).expect("validation.csv");
    assert!(
        validation2.starts_with(&src_validation) && validation2.len() > src_validation.len(),
        "the curve goes on from the source's points:\n{validation2}"
    );
    assert!(art2.join("kept/actor-5.bpk").is_file(), "kept actors come along");
    // The source is left as it was.
    assert!(!committed.join("continued_from.json").exists());

    // A warm start across kinds: a SocialComm job from the MACAD run's weights, a run of its
    // own (its own counters and kept actors), the source named beside it.
    let other = write("other.toml", 1200, "socialcomm");
    let data4 = dir.join("data4").display().to_string();
    let args = [
        "train",
        &other,
        "--workers",
        "1",
        "--quiet",
        "--data-dir",
        &data4,
        "--warm-start-from",
        &from,
    ];
    let v = json_of(&socialflow(&args, T));
    assert_eq!(v["state"], "succeeded", "{v}");
    let art4 = std::path::PathBuf::from(v["artifact_dir"].as_str().expect("artifact_dir"));
    let marker: serde_json::Value = serde_json::from_slice(
        &std::fs::read(art4.join("warm_started_from.json")).expect("marker"),
    )
    .expect("json");
    assert_eq!(marker["kind"], "macad", "{marker}");
    assert_eq!(marker["svo"], "none", "{marker}");
    assert!(!art4.join("continued_from.json").exists());
    let state4: serde_json::Value =
        serde_json::from_slice(&std::fs::read(art4.join("state.json")).expect("state"))
            .expect("json");
    let steps4 = state4["counters"]["env_steps"].as_u64().expect("env_steps");
    assert!((1200..1200 + 600).contains(&steps4), "its own transitions, from 0: {state4}");
    assert_ne!(
        std::fs::read(art4.join("kept/actor-5.bpk")).expect("its own kept actor"),
        std::fs::read(committed.join("kept/actor-5.bpk")).expect("the source's"),
    );

    // Refusals name the field, before anything starts.
    let refused = |args: &[&str], field: &str| {
        let out = socialflow(args, T);
        assert!(!out.status.success(), "{args:?} was accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(field), "{field} not named: {err}");
    };
    let data3 = dir.join("data3").display().to_string();
    let same = write("same.toml", 600, "macad");
    refused(
        &["train", &same, "--quiet", "--data-dir", &data3, "--continue-from", &from],
        "train.env_steps",
    );
    refused(
        &["train", &other, "--quiet", "--data-dir", &data3, "--continue-from", &from],
        "train.continue_from",
    );
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).expect("dir");
    refused(
        &[
            "train",
            &second,
            "--quiet",
            "--data-dir",
            &data3,
            "--continue-from",
            &empty.display().to_string(),
        ],
        "train.continue_from",
    );
    let wide = ["train", &other, "--set", "net.width=32", "--quiet", "--data-dir", &data3];
    refused(&[&wide[..], &["--warm-start-from", &from]].concat(), "train.warm_start_from");
    let empty = empty.display().to_string();
    refused(
        &["train", &other, "--quiet", "--data-dir", &data3, "--warm-start-from", &empty],
        "train.warm_start_from",
    );
    let _ = std::fs::remove_dir_all(&dir);
}
