//! The service across a network of the test's own making (`netns`): the learner and each worker
//! in a namespace of their own, a worker's connections through a fault-injecting proxy, and
//! partitions made with iptables. One short partition test runs in CI; the figures (ingest under
//! delay and a bandwidth cap, 30 s partitions of a worker and of the learner) come from
//! `network_fault_figures`, run by hand:
//!
//! `cargo build --release --locked -p socialflow-learner -p socialflow-worker && SOCIALFLOW_BIN_DIR=$CARGO_TARGET_DIR/release SOCIALFLOW_NETFAULT_OUT=docs/results/network-faults.json cargo test --locked --test network -- --ignored --nocapture`
//! (release learner and worker; the harness itself can be a debug build).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use socialflow_e2e::grpc::{get, jobs, metric, progress, rt, submit, wait_final, Jobs, SUCCEEDED};
use socialflow_e2e::netns::{FaultProxy, Faults, Host, Lab};
use socialflow_e2e::{bin, http_get, scratch, tiny_job, wait_for, Proc, TOKEN, TWO_MAPS};

const GRPC_PORT: u16 = 50051;
const ADMIN_PORT: u16 = 9090;

/// A learner in its own namespace (its ports are the namespace's: fixed).
struct Learner {
    host: Host,
    _proc: Proc,
    url: String,
    admin: String,
}

fn start_learner(lab: &mut Lab, dir: &Path, worker_timeout_s: u64) -> Learner {
    start_learner_with(lab, dir, worker_timeout_s, "")
}

/// A learner whose config has `extra` (TOML lines) added.
fn start_learner_with(lab: &mut Lab, dir: &Path, worker_timeout_s: u64, extra: &str) -> Learner {
    let host = lab.host("learner");
    let cfg = dir.join("learner.toml");
    std::fs::write(
        &cfg,
        format!(
            "grpc_addr = \"{ip}:{GRPC_PORT}\"\nadmin_addr = \"{ip}:{ADMIN_PORT}\"\ndata_dir = \"{}\"\nscenarios_dir = \"configs/scenarios\"\nworker_timeout_s = {worker_timeout_s}\nallow_plaintext_token = true\n{extra}\n",
            dir.join("data").display(),
            ip = host.ip
        ),
    )
    .expect("learner config");
    let proc = host.spawn(
        &bin("socialflow-learner"),
        &["--config", &cfg.display().to_string()],
        &[("SOCIALFLOW_TOKEN", TOKEN)],
        &dir.join("learner.log"),
    );
    let admin = format!("{}:{ADMIN_PORT}", host.ip);
    wait_for("learner readiness", Duration::from_secs(60), || {
        http_get(&admin, "/readyz").filter(|b| b.contains("ready"))
    });
    Learner { url: format!("http://{}:{GRPC_PORT}", host.ip), host, _proc: proc, admin }
}

/// A worker in its own namespace that reaches the learner only through its proxy.
struct Worker {
    host: Host,
    proxy: FaultProxy,
    _proc: Proc,
    admin: String,
}

fn start_worker(lab: &mut Lab, l: &Learner, dir: &Path, k: usize, rpc_timeout_s: u64) -> Worker {
    start_worker_with(lab, l, dir, k, rpc_timeout_s, &[])
}

fn start_worker_with(
    lab: &mut Lab,
    l: &Learner,
    dir: &Path,
    k: usize,
    rpc_timeout_s: u64,
    extra: &[&str],
) -> Worker {
    let host = lab.host(&format!("w{k}"));
    let proxy = FaultProxy::start(
        SocketAddr::new(host.gw.into(), 0),
        SocketAddr::new(l.host.ip.into(), GRPC_PORT),
    );
    let admin = format!("{}:{ADMIN_PORT}", host.ip);
    let proc = host.spawn(
        &bin("socialflow-worker"),
        &[
            "--learner",
            &format!("http://{}", proxy.addr),
            "--name",
            &format!("w{k}"),
            "--admin-addr",
            &admin,
            "--max-backoff-s",
            "1",
            "--rpc-timeout-s",
            &rpc_timeout_s.to_string(),
        ]
        .into_iter()
        .chain(extra.iter().copied())
        .collect::<Vec<_>>(),
        &[("SOCIALFLOW_TOKEN", TOKEN)],
        &dir.join(format!("worker{k}.log")),
    );
    Worker { host, proxy, _proc: proc, admin }
}

fn metrics(admin: &str) -> Option<String> {
    http_get(admin, "/metrics")
}

/// Policy versions the learner reported, checked to never go back.
#[derive(Default)]
struct Versions(Vec<u64>);

impl Versions {
    fn see(&mut self, v: u64) {
        if let Some(&last) = self.0.last() {
            assert!(v >= last, "the policy version went back from {last} to {v}");
        }
        self.0.push(v);
    }
}

/// Polls the job (and the learner's worker count) every 200 ms for `d`; calls that fail (the
/// learner cut off) are skipped. Returns the lowest worker count seen.
fn watch_for(
    rt: &tokio::runtime::Runtime,
    c: &mut Jobs,
    l: &Learner,
    job: u64,
    d: Duration,
    versions: &mut Versions,
) -> Option<f64> {
    let t = Instant::now();
    let mut fewest: Option<f64> = None;
    while t.elapsed() < d {
        if let Some(m) = metrics(&l.admin) {
            let w = metric(&m, "socialflow_learner_workers");
            fewest = Some(fewest.map_or(w, |f| f.min(w)));
            let req = sf_proto::pb::GetJobRequest { job_id: job };
            let got = rt.block_on(async {
                tokio::time::timeout(Duration::from_secs(2), c.get_job(req)).await
            });
            if let Ok(Ok(j)) = got {
                versions.see(progress(&j.into_inner()).policy_version);
            }
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    fewest
}

fn workers_at(l: &Learner, n: f64, within: Duration, what: &str) -> Duration {
    let t = Instant::now();
    wait_for(what, within, || {
        metrics(&l.admin).filter(|m| metric(m, "socialflow_learner_workers") == n).map(|_| ())
    });
    t.elapsed()
}

/// Submits a small job of `n` transitions and starts workers `first` and `first + 1` (RPC
/// deadline `rpc_timeout_s`); returns once both train it and its policy has moved.
fn two_workers_training(
    lab: &mut Lab,
    (rt, c): (&tokio::runtime::Runtime, &mut Jobs),
    l: &Learner,
    dir: &Path,
    (name, n): (&str, u64),
    (first, rpc_timeout_s): (usize, u64),
) -> (u64, Worker, Worker) {
    let job = submit(rt, c, tiny_job(TWO_MAPS, name, n)).job_id;
    let w0 = start_worker(lab, l, dir, first, rpc_timeout_s);
    let w1 = start_worker(lab, l, dir, first + 1, rpc_timeout_s);
    wait_for("training with both workers", Duration::from_secs(300), || {
        (progress(&get(rt, c, job)).policy_version > 2
            && metrics(&l.admin).is_some_and(|m| metric(&m, "socialflow_learner_workers") == 2.0))
        .then_some(())
    });
    (job, w0, w1)
}

const RECEIVED: &str = "socialflow_learner_transitions_received_total";

/// Transitions the learner has counted so far (all jobs).
fn received(l: &Learner) -> f64 {
    metric(&metrics(&l.admin).expect("learner metrics"), RECEIVED)
}

/// What a finished job's counters must say after any fault: it ends with exactly its
/// transitions, and the learner counted exactly those since `before` (its counter when the job
/// was submitted): nothing counted twice.
fn assert_counted_once(
    rt: &tokio::runtime::Runtime,
    c: &mut Jobs,
    l: &Learner,
    (job, n, before): (u64, u64, f64),
) {
    let done = wait_final(rt, c, job, "the job to finish after the fault");
    assert_eq!(done.state, SUCCEEDED, "job ended: {}", done.message);
    assert_eq!(progress(&done).env_steps, n, "the job's transitions");
    assert_eq!(received(l) - before, n as f64, "transitions the learner counted for the job");
}

fn lab_or_skip(what: &str) -> Option<Lab> {
    let lab = Lab::new();
    if lab.is_none() {
        eprintln!("SKIPPED, cannot make network namespaces (needs root; tests/run.sh requires them when run as root): {what}");
    }
    lab
}

/// One worker of two cut off for 12 s mid-job (every packet dropped both ways): the learner
/// forgets it, it comes back by itself with a new session, the job finishes with every
/// transition counted once and the policy version never goes back.
#[test]
fn a_partitioned_worker_is_timed_out_and_comes_back_and_nothing_is_counted_twice() {
    let Some(mut lab) = lab_or_skip("the worker partition test") else { return };
    let dir = scratch("partition");
    let l = start_learner(&mut lab, &dir, 4);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let n = 4000;
    let before = received(&l);
    let (job, w0, _w1) =
        two_workers_training(&mut lab, (&rt, &mut c), &l, &dir, ("partition", n), (0, 2));
    let mut versions = Versions::default();
    lab.partition(&w0.host);
    let fewest = watch_for(&rt, &mut c, &l, job, Duration::from_secs(12), &mut versions);
    assert_eq!(fewest, Some(1.0), "the learner did not time the cut-off worker out");
    lab.heal(&w0.host);
    workers_at(&l, 2.0, Duration::from_secs(60), "the worker to come back");
    let sessions =
        metric(&metrics(&w0.admin).expect("worker metrics"), "socialflow_worker_sessions");
    assert!(sessions >= 2.0, "the worker did not start a new session ({sessions})");
    watch_for(&rt, &mut c, &l, job, Duration::from_secs(2), &mut versions);
    assert_counted_once(&rt, &mut c, &l, (job, n, before));
    drop(lab);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Ingest figures for `docs/results/reliability.md` (JSON to `SOCIALFLOW_NETFAULT_OUT`): one
/// worker's warm-up transitions through the proxy at 0 / 25 / 100 ms one way and a 10 Mbit/s cap,
/// for the worker's window fixed at 2 (the old default) and 8 batches and sized to the link (the
/// default, cap 32); each row a fresh worker and connection, rows interleaved (every
/// repetition goes through all links and windows in turn, the order rotated), 3 repetitions
/// (`SOCIALFLOW_NETFAULT_REPS`), 8 s each after 3 s to settle. `SOCIALFLOW_NETFAULT_LEARNER`
/// adds lines to the learner's config (`http2_adaptive_window = true`: the windows before).
#[test]
#[ignore = "a measurement (about 10 minutes): run by hand, see the module header"]
fn network_ingest_figures() {
    let Some(mut lab) = lab_or_skip("the ingest figures") else { return };
    let dir = scratch("netingest");
    let out = std::env::var("SOCIALFLOW_NETFAULT_OUT").ok().map(PathBuf::from);
    let learner_extra = std::env::var("SOCIALFLOW_NETFAULT_LEARNER").unwrap_or_default();
    let reps: usize =
        std::env::var("SOCIALFLOW_NETFAULT_REPS").ok().and_then(|r| r.parse().ok()).unwrap_or(3);
    let l = start_learner_with(&mut lab, &dir, 10, &learner_extra);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    // Warm-up transitions only (no updates); a fresh job per repetition, so one replay never
    // holds more than a repetition's transitions.
    // `SOCIALFLOW_NETFAULT_CHECKPOINTS=1`: the job as `network_fault_figures` runs it, a
    // checkpoint every second with the replay's new rows written beside it.
    let as_before = std::env::var_os("SOCIALFLOW_NETFAULT_CHECKPOINTS").is_some();
    let ingest_job = |c: &mut Jobs, rep: usize| {
        let (big, warm) = (100_000_000u64, 1_000_000u64);
        let mut cfg = tiny_job(TWO_MAPS, &format!("ingest-{rep}"), big)
            .replace("warmup_steps = 200", &format!("warmup_steps = {warm}"))
            .replace("replay_capacity = 20000", &format!("replay_capacity = {warm}"));
        if !as_before {
            // Checkpoints as a long job takes them, not every second: the link is measured here.
            cfg = cfg.replace("checkpoint_every_s = 1", "checkpoint_every_s = 300").replace(
                &format!("replay_capacity = {warm}"),
                &format!("replay_capacity = {warm}\npersist_replay = false"),
            );
        }
        submit(&rt, c, cfg).job_id
    };
    let links = [
        ("0 ms", Faults::default()),
        ("25 ms one way", Faults { delay_ms: 25, ..Faults::default() }),
        ("100 ms one way", Faults { delay_ms: 100, ..Faults::default() }),
        ("10 Mbit/s", Faults { rate_bps: Some(10_000_000), ..Faults::default() }),
    ];
    let windows: [(&str, &[&str]); 3] = [
        ("fixed 2", &["--in-flight-batches", "2", "--fixed-window"]),
        ("fixed 8", &["--in-flight-batches", "8", "--fixed-window"]),
        ("adaptive (default, cap 32)", &[]),
    ];
    let mut rows = Vec::new();
    let mut k = 10;
    for rep in 0..reps {
        let ingest = ingest_job(&mut c, rep);
        let order: Vec<usize> = (0..links.len() * windows.len()).collect();
        let shift = rep * 5 % order.len();
        for &cell in order[shift..].iter().chain(&order[..shift]) {
            let ((label, f), (window, flags)) =
                (links[cell % links.len()], windows[cell / links.len()]);
            k += 1;
            let w = start_worker_with(&mut lab, &l, &dir, k, 10, flags);
            w.proxy.set(f);
            let steps = |c: &mut Jobs| progress(&get(&rt, c, ingest)).env_steps;
            let from = steps(&mut c);
            wait_for("ingest to start", Duration::from_secs(120), || {
                (steps(&mut c) > from + 200).then_some(())
            });
            std::thread::sleep(Duration::from_secs(3));
            let (t0, s0, b0) = (Instant::now(), steps(&mut c), w.proxy.bytes());
            std::thread::sleep(Duration::from_secs(8));
            let secs = t0.elapsed().as_secs_f64();
            let s = (steps(&mut c) - s0) as f64 / secs;
            let mbit = (w.proxy.bytes() - b0) as f64 * 8.0 / secs / 1e6;
            let m = metrics(&w.admin);
            let read = |name: &str| m.as_ref().map(|m| metric(m, name));
            let win = read("socialflow_worker_in_flight_window");
            let rtt_ms =
                read("socialflow_worker_link_min_rtt_seconds").map(|s| (s * 1e4).round() / 10.0);
            let acked = read("socialflow_worker_link_acked_batches_per_second").map(f64::round);
            eprintln!("rep {rep}: ingest at {label}, window {window}: {s:.0} transitions/s, {mbit:.2} Mbit/s, window now {win:?} (min rtt {rtt_ms:?} ms, acked {acked:?} batches/s)");
            rows.push(serde_json::json!({
                "rep": rep, "link": label, "window": window, "transitions_per_s": s.round(),
                "mbit_per_s": (mbit * 100.0).round() / 100.0, "window_batches_at_end": win,
                "min_rtt_ms": rtt_ms, "acked_batches_per_s": acked,
            }));
            drop(w);
            std::thread::sleep(Duration::from_secs(1));
        }
        rt.block_on(c.cancel_job(sf_proto::pb::CancelJobRequest { job_id: ingest }))
            .expect("cancel");
    }
    let figures = serde_json::json!({
        "learner_config_extra": learner_extra,
        "job_checkpoints_every_second_with_replay": as_before,
        "ingest": rows,
    });
    if let Some(p) = out {
        std::fs::write(&p, serde_json::to_string_pretty(&figures).expect("json"))
            .expect("figures file");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Figures for `docs/results/reliability.md`, written as JSON to `SOCIALFLOW_NETFAULT_OUT`:
/// ingest at 0 / 25 / 100 ms one-way delay and under a 10 Mbit/s cap (one worker, warm-up
/// transitions, 30 s each), then a 30 s partition of one worker of two and a 30 s partition of
/// the learner from every worker, each mid-job.
#[test]
#[ignore = "a measurement (about 6 minutes): run by hand, see the module header"]
fn network_fault_figures() {
    let Some(mut lab) = lab_or_skip("the network fault figures") else { return };
    let dir = scratch("netfigures");
    let out = std::env::var("SOCIALFLOW_NETFAULT_OUT").ok().map(PathBuf::from);
    let mut figures = serde_json::Map::new();
    let l = start_learner(&mut lab, &dir, 10);
    let rt = rt();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));

    // Ingest: warm-up transitions only (no updates, nothing waits on the learner's rate).
    let (big, warm) = (100_000_000u64, 2_000_000u64);
    let cfg = tiny_job(TWO_MAPS, "ingest", big)
        .replace("warmup_steps = 200", &format!("warmup_steps = {warm}"))
        .replace("replay_capacity = 20000", &format!("replay_capacity = {warm}"));
    let ingest = submit(&rt, &mut c, cfg).job_id;
    let mut rows = Vec::new();
    // The worker's default window of unacknowledged batches, then a wider one.
    for (k, window) in [(0, "default"), (1, "8")] {
        let flag: &[&str] = if k == 0 { &[] } else { &["--in-flight-batches", window] };
        let w = start_worker_with(&mut lab, &l, &dir, k, 10, flag);
        let from = progress(&get(&rt, &mut c, ingest)).env_steps;
        wait_for("ingest to start", Duration::from_secs(120), || {
            (progress(&get(&rt, &mut c, ingest)).env_steps > from + 1000).then_some(())
        });
        for (label, f) in [
            ("0 ms", Faults::default()),
            ("25 ms one way", Faults { delay_ms: 25, ..Faults::default() }),
            ("100 ms one way", Faults { delay_ms: 100, ..Faults::default() }),
            ("10 Mbit/s", Faults { rate_bps: Some(10_000_000), ..Faults::default() }),
        ] {
            w.proxy.set(f);
            std::thread::sleep(Duration::from_secs(5));
            let steps = |c: &mut Jobs| progress(&get(&rt, c, ingest)).env_steps;
            let (t0, s0, b0) = (Instant::now(), steps(&mut c), w.proxy.bytes());
            std::thread::sleep(Duration::from_secs(20));
            let secs = t0.elapsed().as_secs_f64();
            let s = (steps(&mut c) - s0) as f64 / secs;
            let mbit = (w.proxy.bytes() - b0) as f64 * 8.0 / secs / 1e6;
            eprintln!("ingest at {label}, {window} batches in flight: {s:.0} transitions/s, {mbit:.2} Mbit/s through the proxy");
            rows.push(serde_json::json!({
                "link": label, "in_flight_batches": window,
                "transitions_per_s": s.round(), "mbit_per_s": (mbit * 100.0).round() / 100.0,
            }));
        }
        drop(w);
        // Let the learner forget the stopped worker before the next one measures.
        std::thread::sleep(Duration::from_secs(2));
    }
    figures.insert("ingest".into(), rows.into());
    rt.block_on(c.cancel_job(sf_proto::pb::CancelJobRequest { job_id: ingest })).expect("cancel");

    // A 30 s partition of one worker of two, mid-job.
    let n = 12_000;
    let counted = received(&l);
    let (job, w0, _w1) =
        two_workers_training(&mut lab, (&rt, &mut c), &l, &dir, ("worker-partition", n), (2, 10));
    let mut versions = Versions::default();
    let before = progress(&get(&rt, &mut c, job)).env_steps;
    let cut = Instant::now();
    lab.partition(&w0.host);
    let forgotten =
        workers_at(&l, 1.0, Duration::from_secs(60), "the learner to time the worker out");
    let during = cut.elapsed();
    watch_for(&rt, &mut c, &l, job, Duration::from_secs(30).saturating_sub(during), &mut versions);
    let trained = progress(&get(&rt, &mut c, job)).env_steps - before;
    lab.heal(&w0.host);
    let back = workers_at(&l, 2.0, Duration::from_secs(120), "the worker to come back");
    let sessions =
        metric(&metrics(&w0.admin).expect("worker metrics"), "socialflow_worker_sessions");
    assert_counted_once(&rt, &mut c, &l, (job, n, counted));
    figures.insert("worker_partition".into(), serde_json::json!({
        "partition_s": 30, "learner_forgot_worker_after_s": forgotten.as_secs_f64().round(),
        "transitions_during_partition_other_worker": trained, "worker_back_after_heal_s": (back.as_secs_f64() * 10.0).round() / 10.0,
        "worker_sessions": sessions, "job_env_steps": n, "transitions_received": n, "policy_version_monotonic": true,
    }));

    // A 30 s partition of the learner from every worker, mid-job.
    let counted = received(&l);
    let job = submit(&rt, &mut c, tiny_job(TWO_MAPS, "learner-partition", n)).job_id;
    let mut versions = Versions::default();
    wait_for("training to go on", Duration::from_secs(300), || {
        (progress(&get(&rt, &mut c, job)).env_steps > 2000).then_some(())
    });
    watch_for(&rt, &mut c, &l, job, Duration::from_secs(2), &mut versions);
    let before = progress(&get(&rt, &mut c, job)).env_steps;
    lab.partition(&l.host);
    std::thread::sleep(Duration::from_secs(30));
    lab.heal(&l.host);
    let healed = Instant::now();
    let mut c = jobs(&rt, &l.url, Some(TOKEN));
    let resumed = wait_for("the job to take transitions again", Duration::from_secs(120), || {
        (progress(&get(&rt, &mut c, job)).env_steps > before + 500).then(|| healed.elapsed())
    });
    watch_for(&rt, &mut c, &l, job, Duration::from_secs(2), &mut versions);
    assert_counted_once(&rt, &mut c, &l, (job, n, counted));
    figures.insert("learner_partition".into(), serde_json::json!({
        "partition_s": 30, "transitions_resumed_after_heal_s": (resumed.as_secs_f64() * 10.0).round() / 10.0,
        "job_env_steps": n, "transitions_counted_for_job": received(&l) - counted,
        "policy_versions_seen": versions.0.len(), "policy_version_monotonic": true,
    }));
    let text = serde_json::to_string_pretty(&serde_json::Value::Object(figures)).expect("json");
    eprintln!("{text}");
    if let Some(p) = out {
        std::fs::write(&p, text + "\n").expect("writing the figures");
    }
    drop(lab);
    let _ = std::fs::remove_dir_all(&dir);
}
