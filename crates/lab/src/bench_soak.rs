//! `socialflow bench soak`: many worker streams against one learner process for a long time,
//! optionally killing a random stream every N seconds (chaos), with exact transition accounting.
//!
//! The learner is a child process (`socialflow learner` on loopback) training a real job; the
//! streams are in this process and push batches of real simulator observations, each stream as
//! a worker would (register, assignment, one push stream, the acked policy version). A killed
//! stream is aborted mid-flight and replaced, as Swarm or Kubernetes would replace a worker.
//! Checks, printed and in the JSON: no RPC error other than on killed streams; the learner
//! counted (accepted + dropped stale, from its /metrics) exactly what the streams saw acked,
//! plus at most what killed streams had in flight; its resident memory from the first sample
//! with the replay full to the end stays within 10 % (the curve is in the output, with the
//! replay's size at each sample).
//!
//! Owns: [`SoakArgs`], the streams, the chaos kills and the accounting. Must not: change the
//! learner (it runs the same binary's `learner` subcommand) or keep its data directory (a fresh
//! temporary one, removed at the end).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use rand::Rng;
use serde_json::json;
use sf_embedded::client::jobs_client;
use sf_embedded::{runtime, Ctx};
use sf_job::{JobConfig, JobId, TransitionBatch};
use sf_proto::pb;
use sf_proto::pb::experience_service_client::ExperienceServiceClient;
use sf_rollout::setup;
use sf_service::auth::{AttachToken, Token};
use sf_service::client::submit;
use sf_service::sync::lock;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Mode};
use tokio_stream::StreamExt;

#[derive(Args, Debug)]
pub struct SoakArgs {
    /// Concurrent worker streams.
    #[arg(long, default_value_t = 64)]
    streams: usize,
    #[arg(long, default_value_t = 600.0)]
    seconds: f64,
    /// Abort a random stream every this many seconds and start a replacement (0: never).
    #[arg(long, default_value_t = 0.0)]
    kill_every_s: f64,
    /// Transitions per batch.
    #[arg(long, default_value_t = 64)]
    batch: usize,
    /// The job the learner trains (its budget and replay are overridden below).
    #[arg(long, default_value = "configs/bench/service.toml")]
    config: PathBuf,
    /// The job's replay ratio: small, so 2 cores keep up with many streams.
    #[arg(long, default_value_t = 0.01)]
    samples_per_insert: f64,
    /// Replay capacity: reached early, so the memory curve shows what follows.
    #[arg(long, default_value_t = 100_000)]
    replay_capacity: usize,
    /// Resident memory of the learner every this many seconds.
    #[arg(long, default_value_t = 10.0)]
    sample_every_s: f64,
    #[arg(long)]
    json: bool,
}

type Exp = ExperienceServiceClient<
    tonic::service::interceptor::InterceptedService<tonic::transport::Channel, AttachToken>,
>;

/// What one stream saw.
#[derive(Default)]
struct StreamStats {
    sent: AtomicU64,
    acked: AtomicU64,
    errors: Mutex<BTreeMap<String, u64>>,
}

/// Real observation rows of the job's first scenario, for synthetic batches that pass ingest.
fn observation_pool(ctx: &Ctx, cfg: &JobConfig) -> Result<(Vec<f32>, usize)> {
    let map = ctx.map(&cfg.env.scenarios[0])?;
    let sim = Arc::new(setup::resolve(cfg, None).sim);
    let mut venv = VecEnv::new(
        map,
        sim,
        VecEnvConfig {
            n_envs: 4,
            mode: Mode::MultiAgent,
            vehicles: (cfg.env.vehicles_min, cfg.env.vehicles_max),
            seed: 5,
        },
    );
    let len = venv.spec.len;
    let mut pool = Vec::new();
    let actions = vec![Action { ref_speed: 3.0, ..Action::default() }; venv.alive().len()];
    for _ in 0..40 {
        for (k, &a) in venv.alive().iter().enumerate() {
            if a != 0.0 {
                pool.extend_from_slice(&venv.observations()[k * len..(k + 1) * len]);
            }
        }
        venv.step(&actions);
    }
    anyhow::ensure!(!pool.is_empty(), "no observation rows from {}", cfg.env.scenarios[0]);
    Ok((pool, len))
}

/// One worker stream until `until`: register, take the assignment, push until the end.
async fn stream(
    mut exp: Exp,
    job_id: JobId,
    pool: Arc<(Vec<f32>, usize)>,
    batch: usize,
    act: usize,
    until: Instant,
    st: Arc<StreamStats>,
) {
    let note = |st: &StreamStats, code: tonic::Code| {
        *lock(&st.errors).entry(format!("{code:?}")).or_default() += 1
    };
    let wid =
        match exp.register(pb::RegisterRequest { name: "soak".into(), ..Default::default() }).await
        {
            Ok(r) => r.into_inner().worker_id,
            Err(s) => return note(&st, s.code()),
        };
    let mut version = loop {
        match exp.get_assignment(pb::GetAssignmentRequest { worker_id: wid }).await {
            Ok(r) => match r.into_inner().assignment {
                Some(a) if a.job_id == job_id.get() => break a.policy_version,
                _ => tokio::time::sleep(Duration::from_millis(200)).await,
            },
            Err(s) => return note(&st, s.code()),
        }
    };
    let latest = Arc::new(AtomicU64::new(version));
    while Instant::now() < until {
        let (tx, rx) = tokio::sync::mpsc::channel(2);
        let acks = exp.push_transitions(tokio_stream::wrappers::ReceiverStream::new(rx)).await;
        let mut acks = match acks {
            Ok(a) => a.into_inner(),
            Err(s) => {
                note(&st, s.code());
                tokio::time::sleep(Duration::from_millis(200)).await;
                continue;
            }
        };
        let (pool2, st2, latest2) = (Arc::clone(&pool), Arc::clone(&st), Arc::clone(&latest));
        let producer = tokio::spawn(async move {
            let (rows, len) = (&pool2.0, pool2.1);
            let n_rows = rows.len() / len;
            while Instant::now() < until {
                let mut b = TransitionBatch::new(job_id, wid.into(), len, act);
                {
                    let mut rng = rand::rng();
                    for k in 0..batch {
                        let (i, j) = (rng.random_range(0..n_rows), rng.random_range(0..n_rows));
                        let a: Vec<f32> = (0..act).map(|_| rng.random_range(-1.0..1.0)).collect();
                        b.push(
                            &rows[i * len..(i + 1) * len],
                            &a,
                            0.1,
                            &rows[j * len..(j + 1) * len],
                            k % 97 == 0,
                            0,
                        );
                    }
                }
                b.acted_by = sf_proto::acted_by_from_wire(latest2.load(Ordering::Relaxed));
                if tx.send(sf_proto::batch_to_wire(&b)).await.is_err() {
                    break;
                }
                st2.sent.fetch_add(batch as u64, Ordering::Relaxed);
            }
        });
        while let Some(a) = acks.next().await {
            match a {
                Ok(a) => {
                    st.acked.fetch_add((a.accepted + a.dropped_stale) as u64, Ordering::Relaxed);
                    version = version.max(a.latest_policy_version);
                    latest.store(version, Ordering::Relaxed);
                }
                Err(s) => {
                    note(&st, s.code());
                    break;
                }
            }
        }
        producer.abort();
    }
}

fn rss_mb(pid: u32) -> Option<f64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kb: f64 = s
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    Some(kb / 1024.0)
}

fn counter(body: &str, name: &str) -> f64 {
    body.lines()
        .filter(|l| l.starts_with(name))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

pub fn run(ctx: &Ctx, a: SoakArgs) -> Result<()> {
    if a.streams == 0 || a.batch == 0 || a.seconds <= 0.0 {
        bail!("--streams, --batch and --seconds must be positive");
    }
    let cfg = soak_config(&a)?;
    let act = setup::resolve(&cfg, None).net.action_dim;
    let pool = Arc::new(observation_pool(ctx, &cfg)?);

    let dir = std::env::temp_dir().join(format!("socialflow-soak-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let free =
        || -> Result<u16> { Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port()) };
    let (g, adm) = (free()?, free()?);
    let secret: String =
        (0..32).map(|_| format!("{:x}", rand::rng().random_range(0..16u8))).collect();
    let token = Token::new(&secret, "soak").context("token")?;
    let mut learner = spawn_learner(ctx, &dir, g, adm, &secret)?;
    let pid = learner.id();
    let urls = (format!("http://127.0.0.1:{g}"), format!("http://127.0.0.1:{adm}/metrics"));
    let out = runtime()?.block_on(soak(&a, &cfg, pool, act, &urls, token, pid));
    let _ = std::process::Command::new("kill").arg("-TERM").arg(pid.to_string()).status();
    let _ = learner.wait();
    let _ = std::fs::remove_dir_all(&dir);
    let out = out?;
    if a.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    let failed: Vec<&String> = out["checks"]
        .as_object()
        .map(|m| m.iter().filter(|(_, v)| v != &&json!(true)).map(|(k, _)| k).collect())
        .unwrap_or_default();
    if !failed.is_empty() {
        bail!("soak checks failed: {failed:?}");
    }
    Ok(())
}

/// `--config` with the soak's overrides: an endless budget, the soak's replay ratio and
/// capacity, no staleness limit, a warm-up within the replay.
fn soak_config(a: &SoakArgs) -> Result<JobConfig> {
    let text = std::fs::read_to_string(&a.config)
        .with_context(|| format!("reading {}", a.config.display()))?;
    let mut cfg = JobConfig::from_toml(&text).with_context(|| a.config.display().to_string())?;
    cfg.name = "soak".into();
    cfg.train.env_steps = 1 << 40;
    cfg.train.samples_per_insert = a.samples_per_insert;
    cfg.train.replay_capacity = a.replay_capacity;
    cfg.train.max_policy_lag = 1 << 20;
    cfg.sac.warmup_steps = cfg.sac.warmup_steps.min(a.replay_capacity as u64 / 2);
    cfg.validate().context("job config after the soak's overrides")?;
    Ok(cfg)
}

/// `socialflow learner` (this executable) on loopback with the soak's token, its log in the
/// temporary directory.
fn spawn_learner(
    ctx: &Ctx,
    dir: &std::path::Path,
    grpc_port: u16,
    admin_port: u16,
    secret: &str,
) -> Result<std::process::Child> {
    std::process::Command::new(std::env::current_exe().context("this executable")?)
        .args([
            "learner",
            "--grpc-addr",
            &format!("127.0.0.1:{grpc_port}"),
            "--admin-addr",
            &format!("127.0.0.1:{admin_port}"),
            "--data-dir",
        ])
        .arg(dir)
        .arg("--scenarios-dir")
        .arg(&ctx.scenarios)
        .arg("--eval-cases-dir")
        .arg(&ctx.cases)
        .env("SOCIALFLOW_TOKEN", secret)
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .stderr(
            std::fs::File::create(
                std::env::temp_dir().join(format!("socialflow-soak-{}.log", std::process::id())),
            )
            .context("learner log")?,
        )
        .spawn()
        .context("starting the learner")
}

/// Submits the job, runs the streams for `--seconds` (killing and replacing one every
/// `--kill-every-s`), samples the learner's memory, and returns the soak's JSON with its checks.
async fn soak(
    a: &SoakArgs,
    cfg: &JobConfig,
    pool: Arc<(Vec<f32>, usize)>,
    act: usize,
    urls: &(String, String),
    token: Token,
    pid: u32,
) -> Result<serde_json::Value> {
    let (url, admin) = urls;
    let ep = sf_service::tls::endpoint(url, &Default::default())?;
    let start_wait = Instant::now();
    let mut c = loop {
        match jobs_client(ep.clone(), url, Some(token.clone())).await {
            Ok(c) => break c,
            Err(e) if start_wait.elapsed() > Duration::from_secs(60) => return Err(e),
            Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
        }
    };
    let job = submit(&mut c, cfg.to_toml()).await?;
    let ch = ep.connect().await?;
    let exp: Exp =
        ExperienceServiceClient::with_interceptor(ch, AttachToken::new(Some(token.clone())))
            .max_encoding_message_size(sf_service::MAX_MESSAGE_BYTES);
    let t0 = Instant::now();
    let until = t0 + Duration::from_secs_f64(a.seconds);
    let spawn = |st: Arc<StreamStats>| {
        tokio::spawn(stream(exp.clone(), job.id, Arc::clone(&pool), a.batch, act, until, st))
    };
    let mut live: Vec<(Arc<StreamStats>, tokio::task::JoinHandle<()>)> = (0..a.streams)
        .map(|_| Arc::new(StreamStats::default()))
        .map(|s| (Arc::clone(&s), spawn(s)))
        .collect();
    let mut killed: Vec<Arc<StreamStats>> = Vec::new();
    let mut in_flight_killed = 0u64;
    let mut rss = Vec::new();
    let (mut next_sample, mut next_kill) =
        (0.0, if a.kill_every_s > 0.0 { a.kill_every_s } else { f64::INFINITY });
    while Instant::now() < until {
        let t = t0.elapsed().as_secs_f64();
        if t >= next_sample {
            let replay = http_get(admin)
                .ok()
                .map(|m| counter(&m, "socialflow_learner_replay_size_transitions"));
            rss.push(json!([t.round(), rss_mb(pid), replay]));
            next_sample += a.sample_every_s;
        }
        if t >= next_kill {
            let k = rand::rng().random_range(0..live.len());
            let (st, h) = live.swap_remove(k);
            h.abort();
            let _ = h.await;
            in_flight_killed +=
                st.sent.load(Ordering::Relaxed).saturating_sub(st.acked.load(Ordering::Relaxed));
            killed.push(st);
            let fresh = Arc::new(StreamStats::default());
            live.push((Arc::clone(&fresh), spawn(fresh)));
            next_kill += a.kill_every_s;
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    for (_, h) in live.iter_mut() {
        let _ = tokio::time::timeout(Duration::from_secs(150), h).await;
    }
    // The learner's own count, after every surviving stream has its acks.
    let metrics = http_get(admin)?;
    let survivors: Vec<Arc<StreamStats>> = live.into_iter().map(|(s, _)| s).collect();
    Ok(summary(a, &metrics, &survivors, &killed, in_flight_killed, rss, t0.elapsed().as_secs_f64()))
}

/// The soak's JSON: what the streams sent and saw acked against what the learner counted, the
/// memory curve, and the checks.
fn summary(
    a: &SoakArgs,
    metrics: &str,
    survivors: &[Arc<StreamStats>],
    killed: &[Arc<StreamStats>],
    in_flight_killed: u64,
    rss: Vec<serde_json::Value>,
    seconds: f64,
) -> serde_json::Value {
    let counted = counter(metrics, "socialflow_learner_transitions_received_total")
        + counter(metrics, "socialflow_learner_transitions_dropped_total");
    let updates = counter(metrics, "socialflow_learner_updates_total");
    let all = || survivors.iter().chain(killed);
    let sent: u64 = all().map(|s| s.sent.load(Ordering::Relaxed)).sum();
    let acked: u64 = all().map(|s| s.acked.load(Ordering::Relaxed)).sum();
    let mut errors: BTreeMap<String, u64> = BTreeMap::new();
    for s in survivors {
        for (k, v) in lock(&s.errors).iter() {
            *errors.entry(k.clone()).or_default() += v;
        }
    }
    let lost = sent as f64 - counted;
    // Memory once the replay is full (it grows with the replay until then).
    let full = a.replay_capacity as f64;
    let steady: Vec<f64> = rss
        .iter()
        .skip_while(|p| p[2].as_f64().is_none_or(|n| n < full))
        .filter_map(|p| p[1].as_f64())
        .collect();
    let growth = match (steady.first(), steady.last()) {
        (Some(f), Some(l)) if *f > 0.0 && steady.len() >= 2 => l / f - 1.0,
        _ => f64::NAN,
    };
    let checks = json!({
        "no_rpc_errors_on_surviving_streams": errors.is_empty(),
        "learner_counted_every_acked_transition": counted >= acked as f64,
        "lost_within_killed_in_flight": lost <= in_flight_killed as f64,
        "rss_flat_within_10_percent_once_the_replay_is_full": growth.abs() <= 0.10,
    });
    json!({
        "streams": a.streams, "seconds": seconds, "kill_every_s": a.kill_every_s, "kills": killed.len(),
        "batch": a.batch, "samples_per_insert": a.samples_per_insert, "replay_capacity": a.replay_capacity,
        "sent": sent, "acked": acked, "learner_counted": counted, "lost": lost, "in_flight_at_kills": in_flight_killed,
        "transitions_per_s": acked as f64 / seconds, "updates": updates,
        "errors_on_surviving_streams": errors, "rss_mb_and_replay": rss, "rss_growth_once_full": growth, "checks": checks,
    })
}

/// A GET of the learner's /metrics over a plain socket (no HTTP client dependency).
fn http_get(url: &str) -> Result<String> {
    use std::io::{Read, Write};
    let rest = url.strip_prefix("http://").context("http url")?;
    let (host, path) =
        rest.split_once('/').map(|(h, p)| (h, format!("/{p}"))).unwrap_or((rest, "/".into()));
    let mut s =
        std::net::TcpStream::connect(host).with_context(|| format!("connecting to {host}"))?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    write!(s, "GET {path} HTTP/1.0\r\nHost: {host}\r\n\r\n")?;
    let mut out = String::new();
    s.read_to_string(&mut out)?;
    Ok(out)
}
