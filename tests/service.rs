//! The actor-learner service as deployed: real `socialflow-learner` and `socialflow-worker`
//! processes on loopback, driven through the gRPC job API.

use std::path::{Path, PathBuf};
use std::time::Duration;

use sf_proto::pb;
use socialflow_e2e::grpc::{
    exp, get, jobs, metric, progress, push_one, rt, submit, wait_final, SUCCEEDED,
};
use socialflow_e2e::{
    bin, fill_disk, http_get, move_data_dir, restart, scratch, socialflow_env, start_learner,
    start_learner_with, start_worker, tiny_job, wait_for, Proc, Tmpfs, TOKEN, TWO_MAPS,
};
use tonic::Code;

#[test]
fn a_job_runs_to_completion_with_two_workers_and_bad_calls_change_nothing() {
    let dir = scratch("complete");
    let l = start_learner(&dir, 1 << 20);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));

    // Authentication: nothing is created without the right token.
    for bad in [None, Some("wrong-token-9876543")] {
        let mut b = jobs(&rt, &l.url, bad);
        let e = rt
            .block_on(
                b.submit_job(pb::SubmitJobRequest { config_toml: tiny_job(TWO_MAPS, "nope", 100) }),
            )
            .expect_err("unauthenticated");
        assert_eq!(e.code(), Code::Unauthenticated, "{e:?}");
        let e = rt.block_on(b.list_jobs(pb::ListJobsRequest {})).expect_err("unauthenticated");
        assert_eq!(e.code(), Code::Unauthenticated);
    }
    assert!(
        rt.block_on(c.list_jobs(pb::ListJobsRequest {}))
            .expect("list")
            .into_inner()
            .jobs
            .is_empty(),
        "a refused call created a job"
    );

    // Malformed requests.
    let e = rt
        .block_on(c.submit_job(pb::SubmitJobRequest {
            config_toml: tiny_job(TWO_MAPS, "x", 100).replace("batch_size = 32", "batch_size = 0"),
        }))
        .expect_err("bad config");
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("sac.batch_size"), "{}", e.message());
    let e = rt
        .block_on(c.submit_job(pb::SubmitJobRequest {
            config_toml: tiny_job(TWO_MAPS, "x", 100).replace("\"merge\"", "\"atlantis\""),
        }))
        .expect_err("unknown scenario");
    assert_eq!(e.code(), Code::InvalidArgument);
    let e = rt.block_on(c.get_job(pb::GetJobRequest { job_id: 4242 })).expect_err("unknown job");
    assert_eq!(e.code(), Code::NotFound);
    let e = rt
        .block_on(c.submit_job(pb::SubmitJobRequest { config_toml: "#".repeat(2 << 20) }))
        .expect_err("oversized");
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");

    // Three scenarios, two workers: every worker simulates every scenario of the job.
    let job = submit(
        &rt,
        &mut c,
        tiny_job(r#""roundabout", "merge", "bottleneck""#, "two-workers", 1500),
    );
    let mut e = exp(&rt, &l.url);
    let wid = rt
        .block_on(e.register(pb::RegisterRequest { name: "probe".into(), ..Default::default() }))
        .expect("register")
        .into_inner()
        .worker_id;
    let good = || {
        let obs_len = 8usize;
        let mut b = sf_job::TransitionBatch::new(job.job_id.into(), wid.into(), obs_len, 2);
        b.push(&[0.0; 8], &[0.0, 0.0], 0.0, &[0.0; 8], false, 0);
        b
    };
    let mut short = sf_proto::batch_to_wire(&good());
    short.obs_f16.truncate(3);
    assert_eq!(push_one(&rt, &mut e, short).code(), Code::InvalidArgument);
    let mut nan = sf_proto::batch_to_wire(&good());
    nan.rewards[0] = f32::NAN;
    assert_eq!(push_one(&rt, &mut e, nan).code(), Code::InvalidArgument);
    // An action outside the action space [-1, 1] is refused, naming the transition.
    let mut wild = sf_proto::batch_to_wire(&good());
    wild.actions[1] = 7.0;
    let st = push_one(&rt, &mut e, wild);
    assert_eq!(st.code(), Code::InvalidArgument, "{st:?}");
    assert!(
        st.message().contains("transition 0, component 1") && st.message().contains("[-1, 1]"),
        "{}",
        st.message()
    );
    let mut unknown = sf_proto::batch_to_wire(&good());
    unknown.job_id = 777;
    assert_eq!(push_one(&rt, &mut e, unknown).code(), Code::NotFound);
    let wrong_width = sf_proto::batch_to_wire(&good());
    let st = push_one(&rt, &mut e, wrong_width);
    assert!(matches!(st.code(), Code::InvalidArgument | Code::FailedPrecondition), "{st:?}");
    let mut huge = sf_proto::batch_to_wire(&good());
    huge.obs_f16 = vec![0; 2 << 20];
    assert_eq!(push_one(&rt, &mut e, huge).code(), Code::ResourceExhausted);

    let _w: Vec<Proc> = (0..2).map(|k| start_worker(&l, &dir, k)).collect();
    let done = wait_final(&rt, &mut c, job.job_id, "the job to finish");
    assert_eq!(done.state, SUCCEEDED, "job ended: {}", done.message);
    let p = progress(&done);
    assert_eq!(p.env_steps, 1500);
    assert!(p.updates > 50, "updates {}", p.updates);
    assert!(p.policy_version > 5, "policy version {}", p.policy_version);
    let art = PathBuf::from(&done.artifact_dir);
    for f in ["config.toml", "curve.csv", "state.json", "policy.bpk", "checkpoint/state.json"] {
        assert!(art.join(f).exists(), "missing artifact {f} in {}", art.display());
    }
    // TensorBoard event files: our reader checks the records, the official package (CI has it
    // in a venv: SOCIALFLOW_TB_PYTHON) reads the scalars.
    let tb = art.join("tensorboard");
    let files: Vec<PathBuf> = std::fs::read_dir(&tb)
        .expect("tensorboard dir")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    assert_eq!(files.len(), 1, "{files:?}");
    let events =
        sf_report::tensorboard::read_events(&std::fs::read(&files[0]).expect("event file"))
            .expect("valid TFRecords");
    assert!(events.len() >= 10, "{} events", events.len());
    assert!(!art.join("replay").exists(), "a succeeded job keeps no replay segments");
    match std::env::var("SOCIALFLOW_TB_PYTHON") {
        Ok(py) => {
            let out = std::process::Command::new(py).arg(socialflow_e2e::repo().join("tests/python/read_tensorboard.py")).arg(&tb).arg("10").output().expect("python");
            assert!(out.status.success(), "tensorboard could not read the events: {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        }
        Err(_) => eprintln!("SKIPPED, SOCIALFLOW_TB_PYTHON not set (tests/run.sh sets it): the tensorboard package's read is skipped"),
    }
    // ONNX export of the final actor; onnxruntime (CI: SOCIALFLOW_ONNX_PYTHON, a venv with it)
    // must give burn's actions on the 100 stored observations of the check file within 1e-4.
    let onnx = dir.join("policy.onnx");
    let out = std::process::Command::new(socialflow_e2e::bin("socialflow"))
        .current_dir(socialflow_e2e::repo())
        .arg("export-onnx")
        .arg(&art)
        .arg("--out")
        .arg(&onnx)
        .output()
        .expect("export-onnx");
    assert!(out.status.success(), "export-onnx: {}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&out.stdout).expect("export-onnx prints JSON");
    assert_eq!(report["observations"], 100, "{report}");
    assert!(std::fs::metadata(&onnx).expect("model").len() > 10_000);
    match std::env::var("SOCIALFLOW_ONNX_PYTHON") {
        Ok(py) => {
            let out = std::process::Command::new(py).arg(socialflow_e2e::repo().join("tests/python/check_onnx.py")).arg(&onnx).arg("1e-4").output().expect("python");
            assert!(out.status.success(), "onnxruntime disagrees with burn: {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
        }
        Err(_) => eprintln!("SKIPPED, SOCIALFLOW_ONNX_PYTHON not set (tests/run.sh sets it): the onnxruntime comparison is skipped"),
    }
    let m = http_get(&l.admin, "/metrics").expect("metrics");
    assert!(metric(&m, "socialflow_learner_updates_total") >= p.updates as f64);
    assert!(metric(&m, "socialflow_learner_transitions_received_total") >= 1500.0);
    assert!(
        m.contains(
            "socialflow_learner_rpcs_total{method=\"PushTransitions\",code=\"invalid_argument\"}"
        ),
        "rpc errors by code"
    );
    // Per-job series (replay size, policy version, ...) go with the job; the totals stay.
    assert!(m.contains("# HELP socialflow_learner_running_jobs"));
    for scenario in ["roundabout", "merge", "bottleneck"] {
        assert!(
            metric(&m, &format!("socialflow_learner_episodes_total{{scenario=\"{scenario}\"}}"))
                > 0.0,
            "no episodes of {scenario}"
        );
    }
    // Still serving after all of the above.
    assert!(rt.block_on(c.list_jobs(pb::ListJobsRequest {})).is_ok());
    let fetched = rt
        .block_on(e.get_policy(pb::GetPolicyRequest { job_id: job.job_id, version: 0 }))
        .expect("final policy")
        .into_inner();
    assert!(!fetched.weights.is_empty());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_job_completes_after_a_worker_is_killed() {
    let dir = scratch("killworker");
    let l = start_learner(&dir, 64 << 20);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let job = submit(&rt, &mut c, tiny_job(TWO_MAPS, "kill-worker", 1500));
    let mut w0 = start_worker(&l, &dir, 0);
    let _w1 = start_worker(&l, &dir, 1);
    wait_for("training to start", Duration::from_secs(300), || {
        (progress(&get(&rt, &mut c, job.job_id)).env_steps > 400).then_some(())
    });
    w0.kill9();
    let done = wait_final(&rt, &mut c, job.job_id, "the job to finish");
    assert_eq!(done.state, SUCCEEDED, "job ended: {}", done.message);
    assert_eq!(progress(&done).env_steps, 1500);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A continuation that warms up with the policy it continues (`warmup_policy = "policy"`, as
/// Stage 2's RARL rounds do) trains to its end: its workers fetch that policy before the first
/// step (they once waited for it forever: no transition, so no acknowledgement to fetch it on).
/// With `init_replay` it starts with its source's replay, which the learner keeps while the
/// continuation is queued or running and deletes after; a continuation submitted once that
/// replay is gone is refused, naming the field.
#[test]
fn a_continuation_warms_up_with_the_policy_it_continues_and_carries_its_replay() {
    let dir = scratch("continuation");
    let l = start_learner(&dir, 64 << 20);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let _w: Vec<Proc> = (0..2).map(|k| start_worker(&l, &dir, k)).collect();
    let continued = |name: &str, from: u64| {
        tiny_job(TWO_MAPS, name, 800)
            .replace("[train]\n", &format!("[train]\ninit_job = {from}\ninit_replay = true\n"))
            .replace("warmup_steps = 200\n", "warmup_steps = 200\nwarmup_policy = \"policy\"\n")
    };
    let first = submit(&rt, &mut c, tiny_job(TWO_MAPS, "first", 600));
    // Queued behind its source, so the source's replay is kept for it.
    let job = submit(&rt, &mut c, continued("continued", first.job_id));
    let src = wait_final(&rt, &mut c, first.job_id, "the first job to finish");
    assert_eq!(src.state, SUCCEEDED, "job ended: {}", src.message);
    let done = wait_final(&rt, &mut c, job.job_id, "the continuation to finish");
    assert_eq!(done.state, SUCCEEDED, "job ended: {}", done.message);
    assert_eq!(progress(&done).env_steps, 800);
    let state: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(Path::new(&done.artifact_dir).join("state.json")).expect("state"),
    )
    .expect("state.json");
    assert_eq!(state["carried"], 600, "the source's 600 transitions carried in");
    wait_for("the carried replay to be released", Duration::from_secs(30), || {
        (!Path::new(&src.artifact_dir).join("replay").exists()).then_some(())
    });
    let late = rt
        .block_on(
            c.submit_job(pb::SubmitJobRequest { config_toml: continued("too-late", first.job_id) }),
        )
        .expect_err("its replay is gone");
    assert_eq!(late.code(), Code::InvalidArgument, "{late:?}");
    assert!(late.message().contains("train.init_job"), "{}", late.message());
    let _ = std::fs::remove_dir_all(&dir);
}

/// Two training jobs side by side on one learner with two workers: both progress at once, each
/// with its own series on /metrics and one worker each; one is cancelled, the other is
/// unaffected, takes both workers and finishes.
#[test]
fn two_jobs_train_side_by_side_and_cancelling_one_leaves_the_other() {
    let dir = scratch("sidebyside");
    let l = start_learner_with(&dir, 64 << 20, "max_running_jobs = 2\n");
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let _w: Vec<Proc> = (0..2).map(|k| start_worker(&l, &dir, k)).collect();
    let a = submit(&rt, &mut c, tiny_job(TWO_MAPS, "side-a", 100_000));
    let b = submit(&rt, &mut c, tiny_job(TWO_MAPS, "side-b", 3000));
    let series = |m: &str, name: &str, id: u64| metric(m, &format!("{name}{{job=\"{id}\"}}"));
    // Both learn at once: each past its warm-up with updates, one worker each.
    let m = wait_for("both jobs updating at once, a worker each", Duration::from_secs(600), || {
        let m = http_get(&l.admin, "/metrics")?;
        let (ja, jb) = (get(&rt, &mut c, a.job_id), get(&rt, &mut c, b.job_id));
        let running = pb::JobState::Running as i32;
        let both = ja.state == running && jb.state == running;
        let updating = [a.job_id, b.job_id].iter().all(|&id| {
            series(&m, "socialflow_learner_job_updates_total", id) > 1.0
                && series(&m, "socialflow_learner_job_transitions_received_total", id) > 0.0
        });
        let spread = [a.job_id, b.job_id]
            .iter()
            .all(|&id| series(&m, "socialflow_learner_job_workers", id) == 1.0);
        (both && updating && spread).then_some(m)
    });
    assert_eq!(metric(&m, "socialflow_learner_running_jobs"), 2.0);
    for id in [a.job_id, b.job_id] {
        assert!(m.contains(&format!("socialflow_learner_policy_version{{job=\"{id}\"}}")));
        assert!(m.contains(&format!("socialflow_learner_replay_size_transitions{{job=\"{id}\"}}")));
    }
    let b_before = progress(&get(&rt, &mut c, b.job_id)).env_steps;
    rt.block_on(c.cancel_job(pb::CancelJobRequest { job_id: a.job_id })).expect("cancel");
    // The cancelled job's series go, its worker joins the other job.
    wait_for("the other job to take both workers", Duration::from_secs(120), || {
        let m = http_get(&l.admin, "/metrics")?;
        let gone = !m.contains(&format!("job=\"{}\"", a.job_id));
        (gone && series(&m, "socialflow_learner_job_workers", b.job_id) == 2.0).then_some(())
    });
    let done = wait_final(&rt, &mut c, b.job_id, "the other job to finish");
    assert_eq!(done.state, SUCCEEDED, "job ended: {}", done.message);
    assert_eq!(progress(&done).env_steps, 3000);
    assert!(progress(&done).env_steps > b_before);
    let ja = get(&rt, &mut c, a.job_id);
    assert_eq!(ja.state, pb::JobState::Cancelled as i32, "{}", ja.message);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Killed mid-job, its data directory moved elsewhere (a restored backup, a volume mounted at
/// another path), the learner resumes from the moved checkpoint and replay.
#[test]
fn a_killed_learner_resumes_the_job_from_its_checkpoint() {
    let dir = scratch("killlearner");
    // One job at a time: the first finishes before the second is killed mid-way.
    let mut l = start_learner_with(&dir, 64 << 20, "max_running_jobs = 1\n");
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let queued = submit(&rt, &mut c, tiny_job(TWO_MAPS, "queued-behind", 300));
    let _ = queued;
    let _w: Vec<Proc> = (0..2).map(|k| start_worker(&l, &dir, k)).collect();
    // The first job runs; a second waits behind it.
    let job = submit(&rt, &mut c, tiny_job(TWO_MAPS, "resume", 2500));
    let mid = wait_for("a checkpoint of the second job", Duration::from_secs(600), || {
        let j = get(&rt, &mut c, job.job_id);
        let state = std::fs::read_to_string(Path::new(&j.artifact_dir).join("state.json")).ok()?;
        let v: serde_json::Value = serde_json::from_str(&state).ok()?;
        (v["counters"]["env_steps"].as_u64()? > 600 && v["policy_version"].as_u64()? > 3)
            .then_some(v)
    });
    let version_before = mid["policy_version"].as_u64().expect("version");
    l.proc.kill9();
    drop(c);
    move_data_dir(&l, &dir, "moved-data");
    restart(&mut l);
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let j = get(&rt, &mut c, job.job_id);
    assert_eq!(j.state, pb::JobState::Running as i32, "the job is still running after the restart");
    assert_eq!(j.name, "resume");
    assert!(
        Path::new(&j.artifact_dir).starts_with(dir.join("moved-data")),
        "artifact directory {} is not under the moved data directory",
        j.artifact_dir
    );
    assert_eq!(get(&rt, &mut c, queued.job_id).state, SUCCEEDED, "the finished job kept its state");
    let done = wait_final(&rt, &mut c, job.job_id, "the resumed job to finish");
    assert_eq!(done.state, SUCCEEDED, "job ended: {}", done.message);
    let p = progress(&done);
    assert_eq!(p.env_steps, 2500);
    assert!(
        p.policy_version > version_before,
        "policy version went from {version_before} to {}",
        p.policy_version
    );
    let log = std::fs::read_to_string(&l.log).unwrap_or_default();
    assert!(log.contains("resumed from checkpoint"), "the learner log does not show a resume");
    // The replay came back with the checkpoint (segments in the job's replay/ directory).
    let restored = log.lines().filter(|l| l.contains("replay restored")).find_map(|l| {
        l.split_whitespace().find_map(|w| w.strip_prefix("transitions=")?.parse::<u64>().ok())
    });
    assert!(restored.is_some_and(|n| n >= 600), "the replay was not restored: {restored:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A data directory that fills up mid-job (a tmpfs): the learner stops starting work, keeps
/// answering reads, withholds readiness, logs the cause a bounded number of times and shows it
/// as a metric; the running job stays RUNNING at its last checkpoint (not failed) and, once
/// space is freed, resumes from it by itself and finishes.
#[test]
fn a_full_disk_pauses_the_job_and_it_resumes_when_space_returns() {
    let dir = scratch("fulldisk");
    let Some(_mount) = Tmpfs::mount(&dir.join("data"), 48) else {
        eprintln!("SKIPPED, cannot mount a tmpfs (needs root; tests/run.sh requires it when run as root): the full-disk test");
        return;
    };
    let l = start_learner(&dir, 64 << 20);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let job = submit(&rt, &mut c, tiny_job(TWO_MAPS, "fills-the-disk", 3000));
    let _w: Vec<Proc> = (0..2).map(|k| start_worker(&l, &dir, k)).collect();
    let art = PathBuf::from(get(&rt, &mut c, job.job_id).artifact_dir);
    wait_for("a checkpoint", Duration::from_secs(600), || {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(art.join("state.json")).ok()?).ok()?;
        (v["counters"]["env_steps"].as_u64()? > 600).then_some(())
    });
    fill_disk(&dir.join("data"), "filler");
    let not_ready = || http_get(&l.admin, "/readyz").is_none();
    wait_for("readiness to go false", Duration::from_secs(120), || not_ready().then_some(()));
    let m = http_get(&l.admin, "/metrics").expect("metrics are served during the fault");
    assert_eq!(metric(&m, "socialflow_learner_storage_ok"), 0.0);
    assert!(metric(&m, "socialflow_learner_storage_faults_total") >= 1.0);
    // Reads answer; the job is paused, not failed; nothing new is accepted.
    let j = get(&rt, &mut c, job.job_id);
    assert_eq!(
        j.state,
        pb::JobState::Running as i32,
        "the job must not fail on a full disk: {}",
        j.message
    );
    let e = rt
        .block_on(
            c.submit_job(pb::SubmitJobRequest { config_toml: tiny_job(TWO_MAPS, "refused", 300) }),
        )
        .expect_err("no job is accepted while the disk is full");
    assert_eq!(e.code(), Code::Unavailable, "{}", e.message());
    assert!(e.message().contains("refuses writes"), "{}", e.message());
    std::thread::sleep(Duration::from_secs(5));
    let log = std::fs::read_to_string(&l.log).unwrap_or_default();
    let errors = log.lines().filter(|l| l.contains("ERROR")).count();
    assert!(
        errors <= 5,
        "{errors} ERROR lines during the fault:\n{}",
        log.lines().filter(|l| l.contains("ERROR")).take(20).collect::<Vec<_>>().join("\n")
    );
    assert!(log.contains("refuses writes"), "the cause is logged");
    // Space returns: readiness, then the job resumes from its checkpoint and finishes.
    std::fs::remove_file(dir.join("data/filler")).expect("freeing space");
    wait_for("readiness after space returns", Duration::from_secs(60), || {
        (!not_ready()).then_some(())
    });
    let done = wait_final(&rt, &mut c, job.job_id, "the resumed job to finish");
    assert_eq!(done.state, SUCCEEDED, "job ended: {}", done.message);
    assert_eq!(progress(&done).env_steps, 3000);
    let log = std::fs::read_to_string(&l.log).unwrap_or_default();
    assert!(
        log.contains("takes writes again") && log.contains("resumed from checkpoint"),
        "no resume after the fault in the log"
    );
    assert_eq!(
        metric(&http_get(&l.admin, "/metrics").expect("metrics"), "socialflow_learner_storage_ok"),
        1.0
    );
    drop(_w);
    drop(l);
    drop(_mount);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_tls_learner_serves_only_clients_that_trust_its_certificate() {
    let dir = scratch("tls");
    let ck = rcgen::generate_simple_self_signed(vec!["localhost".to_string()])
        .expect("test certificate");
    let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert, ck.cert.pem()).expect("cert");
    std::fs::write(&key, ck.signing_key.serialize_pem()).expect("key");
    let l = start_learner_with(
        &dir,
        64 << 20,
        &format!("tls_cert_file = \"{}\"\ntls_key_file = \"{}\"\n", cert.display(), key.display()),
    );
    let port = l.url.rsplit(':').next().expect("port");
    let https = format!("https://localhost:{port}");
    let env = [("SOCIALFLOW_TOKEN", TOKEN)];
    let t = Duration::from_secs(60);
    let ca = cert.display().to_string();
    let job = dir.join("job.toml");
    std::fs::write(&job, tiny_job(r#""merge""#, "over-tls", 600)).expect("job");
    let out = socialflow_env(
        &["submit", &job.display().to_string(), "--learner", &https, "--tls-ca-file", &ca],
        &env,
        t,
    );
    assert!(out.status.success(), "submit over TLS: {}", String::from_utf8_lossy(&out.stderr));
    // Without the CA, or in plain text, nothing gets through.
    let out = socialflow_env(&["status", "--learner", &https], &env, t);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--tls-ca-file"));
    let out =
        socialflow_env(&["status", "--learner", &format!("http://127.0.0.1:{port}")], &env, t);
    assert!(!out.status.success(), "a plain-text client must not be served");
    let _w = Proc::spawn_logged(
        &bin("socialflow-worker"),
        &["--learner", &https, "--tls-ca-file", &ca, "--max-backoff-s", "1"],
        &env,
        &dir.join("worker.log"),
    );
    wait_for("the job over TLS to finish", Duration::from_secs(300), || {
        let out = socialflow_env(
            &["status", "1", "--json", "--learner", &https, "--tls-ca-file", &ca],
            &env,
            t,
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).ok()?;
        (v["state"] == "succeeded").then_some(())
    });
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_ego_job_waits_for_its_flow_and_trains_among_it_frozen() {
    let dir = scratch("pipeline");
    let l = start_learner(&dir, 64 << 20);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    // A CoPO flow: Stage 1, then its coordinator (CoPO Stage 2), which the ego job's worker uses.
    let copo = tiny_job(r#""merge""#, "flow-copo", 1500).replacen('\n', "\nkind = \"copo\"\n", 1)
        + "[coordinator]\niterations = 1\npopulation = 3\nenvs = 3\n";
    let flow = submit(&rt, &mut c, copo);
    let ego_cfg = |dep: u64| {
        tiny_job(r#""merge""#, "ego-in-flow", 800).replacen(
            "vehicles_max = 3\n",
            &format!("vehicles_max = 3\nbackground_job = {dep}\n"),
            1,
        )
    };
    let e = rt
        .block_on(c.submit_job(pb::SubmitJobRequest { config_toml: ego_cfg(99) }))
        .expect_err("unknown dependency");
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("env.background_job"), "{}", e.message());
    let ego = submit(&rt, &mut c, ego_cfg(flow.job_id));
    let _w = start_worker(&l, &dir, 0);
    // The ego job stays queued while its flow trains.
    let flow_done = wait_for("the flow job to finish", Duration::from_secs(600), || {
        let f = get(&rt, &mut c, flow.job_id);
        if f.state != SUCCEEDED {
            assert_eq!(
                get(&rt, &mut c, ego.job_id).state,
                pb::JobState::Queued as i32,
                "the ego job ran before its flow finished"
            );
            return None;
        }
        Some(f)
    });
    let frozen =
        std::fs::read(Path::new(&flow_done.artifact_dir).join("policy.bpk")).expect("flow policy");
    let done = wait_final(&rt, &mut c, ego.job_id, "the ego job to finish");
    assert_eq!(done.state, SUCCEEDED, "ego job ended: {}", done.message);
    assert_eq!(progress(&done).env_steps, 800);
    // The flow stayed frozen: same bytes on disk and over the API.
    assert_eq!(
        std::fs::read(Path::new(&flow_done.artifact_dir).join("policy.bpk")).expect("flow policy"),
        frozen
    );
    let mut e = exp(&rt, &l.url);
    let served = rt
        .block_on(e.get_policy(pb::GetPolicyRequest { job_id: flow.job_id, version: 0 }))
        .expect("flow policy")
        .into_inner();
    assert_eq!(served.weights, frozen);
    let log = std::fs::read_to_string(dir.join("worker0.log")).unwrap_or_default();
    assert!(
        log.contains("frozen policy") && log.contains("Background"),
        "the worker did not load the frozen flow"
    );
    assert!(
        Path::new(&flow_done.artifact_dir).join("coordinator.json").exists(),
        "the CoPO job fitted its coordinator"
    );
    assert!(
        log.contains("from the coordinator's Gaussians in 1 scenario(s)"),
        "the ego job's background did not get the CoPO Stage-2 Gaussians"
    );
    // One worker ran both jobs under one registration (a new one per job left stale workers
    // for the learner to time out).
    let m = http_get(&l.admin, "/metrics").expect("metrics");
    assert!(
        m.contains("socialflow_learner_rpcs_total{method=\"Register\",code=\"ok\"} 1\n"),
        "one registration expected:\n{m}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// An evaluation grid over one trained ego and the two scripted drivers (IDM, IDM with MOBIL's
/// lane changes) in the ego's seat in the IDM flow, `runs` / `out` for `socialflow eval`; each
/// cell's worst episode mined into a viewer page at the end.
fn eval_grid(data: &Path, out: &Path, ego_job: &str) -> String {
    format!(
        r#"kind = "eval"
name = "grid"
runs = "{}"
out = "{}"
scenarios = ["merge", "roundabout"]
cases = 2
seeds = 2
envs = 4
mine_worst = 1
flows = [{{ name = "IDM", job = "idm" }}]
egos = [{{ name = "RL/IDM", job = "{ego_job}", trained_in = "IDM" }}, {{ name = "IDM ego", job = "idm" }}, {{ name = "IDM+MOBIL", job = "idm-mobil" }}]
[experiments]
flow_quality = ["IDM"]
cross_validation = ["IDM"]
density = {{ scenario = "merge", flows = ["IDM"], vehicles = [2, 3] }}
"#,
        data.display(),
        out.display()
    )
}

fn sorted_rows(p: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    let mut rows: Vec<String> = text.lines().skip(1).map(str::to_string).collect();
    rows.sort();
    rows
}

#[test]
fn an_evaluation_is_shared_by_workers_and_a_lost_workers_cell_goes_to_another() {
    let dir = scratch("evaljob");
    let l = start_learner_with(&dir, 64 << 20, "worker_timeout_s = 2\n");
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let data = dir.join("data");
    // Refused before anything is stored: unknown jobs and bad fields are named.
    let e = rt
        .block_on(c.submit_job(pb::SubmitJobRequest {
            config_toml: eval_grid(&data, &dir.join("x"), "nope"),
        }))
        .expect_err("unknown ego job");
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("egos.job") && e.message().contains("nope"), "{}", e.message());
    let e = rt
        .block_on(c.submit_job(pb::SubmitJobRequest {
            config_toml: eval_grid(&data, &dir.join("x"), "e").replace("cases = 2", "cases = 0"),
        }))
        .expect_err("bad field");
    assert!(
        e.code() == Code::InvalidArgument && e.message().contains("`cases`"),
        "{}",
        e.message()
    );
    assert!(rt
        .block_on(c.list_jobs(pb::ListJobsRequest {}))
        .expect("list")
        .into_inner()
        .jobs
        .is_empty());

    let ego = submit(&rt, &mut c, tiny_job(TWO_MAPS, "ego-t", 300));
    let mut w0 = start_worker(&l, &dir, 0);
    assert_eq!(wait_final(&rt, &mut c, ego.job_id, "the ego to train").state, SUCCEEDED);
    w0.kill9();

    // A worker that leases a cell and is never heard from again.
    let mut x = exp(&rt, &l.url);
    let lost = rt
        .block_on(x.register(pb::RegisterRequest { name: "lost".into(), ..Default::default() }))
        .expect("register")
        .into_inner()
        .worker_id;
    let job = submit(&rt, &mut c, eval_grid(&data, &dir.join("embedded"), "ego-t"));
    assert!(
        job.config_toml.contains(&format!("job_id = {}", ego.job_id)),
        "the names are pinned: {}",
        job.config_toml
    );
    // Flow quality, cross-validation (the trained ego and the two scripted drivers), density.
    let cells = 2 + 3 * 2 + 2;
    assert_eq!(progress(&job).target_env_steps, cells * 4);
    let leased = wait_for("a cell for the lost worker", Duration::from_secs(60), || {
        let r = rt
            .block_on(x.get_assignment(pb::GetAssignmentRequest { worker_id: lost }))
            .expect("assignment")
            .into_inner();
        r.eval
    });
    assert_eq!(leased.cases * leased.seeds, 4);
    // Results that do not match the cell change nothing.
    let ep = |case_id, seed| pb::EvalEpisode {
        case_id,
        seed,
        success: 1.0,
        safety: 1.0,
        speed: 0.5,
        collision: 0.0,
        lane_change: None,
        road_closed: None,
    };
    let short = pb::EvalResults {
        job_id: job.job_id,
        worker_id: lost,
        cell_id: leased.cell_id,
        episodes: vec![ep(0, 0)],
        error: String::new(),
    };
    let e = rt.block_on(x.push_eval_results(short)).expect_err("one episode of four");
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    let bad = pb::EvalResults {
        job_id: job.job_id,
        worker_id: lost,
        cell_id: 999,
        episodes: vec![],
        error: String::new(),
    };
    assert_eq!(
        rt.block_on(x.push_eval_results(bad)).expect_err("no such cell").code(),
        Code::NotFound
    );

    let _w: Vec<Proc> = (1..3).map(|k| start_worker(&l, &dir, k)).collect();
    let done = wait_final(&rt, &mut c, job.job_id, "the evaluation to finish");
    assert_eq!(done.state, SUCCEEDED, "evaluation ended: {}", done.message);
    assert_eq!(progress(&done).env_steps, cells * 4, "every episode of every cell");
    let results = Path::new(&done.artifact_dir).join("episodes.csv");
    let rows = sorted_rows(&results);
    assert_eq!(rows.len() as u64, cells * 4);
    assert_eq!(
        rows.iter().filter(|r| r.starts_with("cross,IDM ego,IDM,")).count(),
        2 * 4,
        "the IDM driver's cells, run by workers: {rows:?}"
    );
    assert_eq!(
        rows.iter().filter(|r| r.starts_with("cross,IDM+MOBIL,IDM,")).count(),
        2 * 4,
        "the MOBIL driver's cells, run by workers: {rows:?}"
    );
    let metrics = http_get(&l.admin, "/metrics").expect("metrics");
    assert!(
        metric(&metrics, "socialflow_learner_eval_cells_reassigned") >= 1.0,
        "the lost worker's cell went to another worker"
    );
    assert_eq!(metric(&metrics, "socialflow_learner_eval_episodes_total"), (cells * 4) as f64);
    // The lost worker's late results are refused; what is stored stays.
    let four = pb::EvalResults {
        job_id: job.job_id,
        worker_id: lost,
        cell_id: leased.cell_id,
        episodes: vec![ep(0, 0), ep(0, 1), ep(1, 0), ep(1, 1)],
        error: String::new(),
    };
    assert!(rt.block_on(x.push_eval_results(four)).is_err());
    assert_eq!(sorted_rows(&results), rows);
    assert!(Path::new(&done.artifact_dir).join("meta.json").exists());
    let pinned = std::fs::read_to_string(Path::new(&done.artifact_dir).join("config.toml"))
        .expect("the grid beside its results");
    assert!(pinned.contains(&format!("job_id = {}", ego.job_id)), "{pinned}");
    // Mined at the end (`mine_worst = 1`): one page per cell, the index, what the report links.
    let mined = Path::new(&done.artifact_dir).join("mined");
    let linked = std::fs::read_to_string(mined.join("cells.json")).expect("mined/cells.json");
    assert_eq!(linked.matches("\"href\"").count() as u64, cells, "{linked}");
    let pages = std::fs::read_dir(&mined).expect("mined pages").count();
    assert_eq!(pages as u64, cells + 2, "a page per cell, index.html and cells.json");
    assert!(std::fs::read_to_string(mined.join("index.html")).expect("index").contains(".html"));

    // The same grid evaluated in one process: the same numbers.
    let cfg = dir.join("grid.toml");
    std::fs::write(&cfg, eval_grid(&data, &dir.join("embedded"), "ego-t")).expect("eval config");
    let o = socialflow_env(&["eval", &cfg.display().to_string()], &[], Duration::from_secs(300));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        sorted_rows(&dir.join("embedded/episodes.csv")),
        rows,
        "embedded and shared by workers: the same episodes"
    );
    assert_eq!(
        std::fs::read_to_string(dir.join("embedded/mined/cells.json")).expect("embedded mining"),
        linked,
        "and the same episodes mined"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_killed_learner_resumes_an_evaluation_from_the_cells_it_stored() {
    let dir = scratch("evalresume");
    let mut l = start_learner(&dir, 64 << 20);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    // IDM only: 2 + 2 x 10 cells of 80 episodes, slow enough to stop halfway.
    let grid = format!(
        r#"kind = "eval"
runs = "{}"
out = "{}"
scenarios = ["merge", "roundabout"]
cases = 20
seeds = 4
envs = 8
flows = [{{ name = "IDM", job = "idm" }}]
egos = []
[experiments]
flow_quality = ["IDM"]
density = {{ scenario = "merge", flows = ["IDM"], vehicles = [2, 3, 4, 5, 6, 7, 8, 9, 10, 11] }}
"#,
        dir.join("data").display(),
        dir.join("embedded").display()
    );
    let job = submit(&rt, &mut c, grid.clone());
    let _w = start_worker(&l, &dir, 0);
    let results = Path::new(&job.artifact_dir).join("episodes.csv");
    let total = 12 * 80;
    let stored_before = wait_for("some cells stored", Duration::from_secs(300), || {
        let n = std::fs::read_to_string(&results).ok()?.lines().count().saturating_sub(1);
        (n >= 80).then_some(n)
    });
    l.proc.kill9();
    assert!(
        stored_before < total,
        "the evaluation finished before the learner was killed ({stored_before} episodes)"
    );
    drop(c);
    restart(&mut l);
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let done = wait_final(&rt, &mut c, job.job_id, "the resumed evaluation");
    assert_eq!(done.state, SUCCEEDED, "evaluation ended: {}", done.message);
    let rows = sorted_rows(&results);
    assert_eq!(
        rows.len(),
        total,
        "every cell once: nothing stored before the kill was lost or repeated"
    );
    let log = std::fs::read_to_string(&l.log).unwrap_or_default();
    assert!(
        log.matches("evaluation started").count() >= 2,
        "the learner log does not show the resume"
    );
    let cfg = dir.join("grid.toml");
    std::fs::write(&cfg, grid).expect("eval config");
    let o = socialflow_env(&["eval", &cfg.display().to_string()], &[], Duration::from_secs(300));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        sorted_rows(&dir.join("embedded/episodes.csv")),
        rows,
        "resumed and embedded: the same episodes"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
