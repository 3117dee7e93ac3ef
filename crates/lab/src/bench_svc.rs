//! `socialflow bench ingest` and `bench e2e`: the service's throughput over loopback gRPC.
//!
//! `ingest`: m synthetic senders stream pre-built, valid batches to an embedded learner whose
//! job never samples (warm-up = replay capacity), so the number is the learner's ingest rate
//! (decode, validate, rate limiter, copy into replay). `e2e`: a real job with m in-process
//! workers; rates are measured after the warm-up, while the learner trains.
//!
//! Owns: [`SvcBenchArgs`], the synthetic senders and the rate sampling. Must not: bypass the
//! service (everything goes through the learner's gRPC API, as a worker's data does).

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use serde_json::json;
use sf_embedded::{runtime, Ctx, Embedded};
use sf_job::{JobConfig, TransitionBatch};
use sf_proto::pb;
use sf_proto::pb::experience_service_client::ExperienceServiceClient;
use sf_service::auth::AttachToken;
use sf_service::client::{submit, JobsClient};
use tokio_stream::StreamExt;

#[derive(Args, Debug)]
pub struct SvcBenchArgs {
    #[arg(long, default_value_t = 4)]
    workers: usize,
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Job config for `e2e` (its budget is raised so the job outlives the measurement).
    #[arg(long, default_value = "configs/bench/service.toml")]
    config: PathBuf,
    /// `e2e`: override the job's replay ratio (a small value measures unthrottled workers).
    #[arg(long)]
    samples_per_insert: Option<f64>,
    /// Transitions per batch for `ingest`.
    #[arg(long, default_value_t = 256)]
    batch: usize,
    #[arg(long)]
    json: bool,
}

fn tmp_dir(tag: &str) -> PathBuf {
    std::env::temp_dir().join(format!("socialflow-bench-{tag}-{}", std::process::id()))
}

const INGEST_JOB: &str = r#"
name = "bench-ingest"
[env]
scenarios = ["roundabout"]
[sac]
warmup_steps = 400000
[train]
env_steps = 1000000000000
replay_capacity = 400000
samples_per_insert = 0.0001
max_policy_lag = 1000000000
publish_every_updates = 1000000
checkpoint_every_s = 100000
"#;

pub fn ingest(dirs: &Ctx, a: SvcBenchArgs) -> Result<()> {
    if a.workers == 0 || a.batch == 0 {
        bail!("--workers and --batch must be positive");
    }
    let dir = tmp_dir("ingest");
    let _ = std::fs::remove_dir_all(&dir);
    let out = runtime()?.block_on(async {
        let emb = Embedded::start(dir.clone(), dirs, 0).await?;
        let mut c = emb.client().await?;
        let job = submit(&mut c, INGEST_JOB.to_string()).await?;
        let ch = tonic::transport::Endpoint::from_shared(emb.url.clone())?.connect().await?;
        let mut exp = ExperienceServiceClient::with_interceptor(
            ch,
            AttachToken::new(Some(emb.token.clone())),
        )
        .max_encoding_message_size(sf_service::MAX_MESSAGE_BYTES);
        let wid = exp
            .register(pb::RegisterRequest { name: "bench".into(), ..Default::default() })
            .await?
            .into_inner()
            .worker_id;
        let asg = loop {
            let r =
                exp.get_assignment(pb::GetAssignmentRequest { worker_id: wid }).await?.into_inner();
            if let Some(asg) = r.assignment {
                break asg;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        };
        let obs_len = asg.obs_len as usize;
        let mut b = TransitionBatch::new(job.id, wid.into(), obs_len, 2);
        let row: Vec<f32> = (0..obs_len).map(|i| ((i % 97) as f32 / 97.0) - 0.5).collect();
        for k in 0..a.batch {
            b.push(&row, &[0.1, -0.2], k as f32 * 0.01, &row, k % 50 == 0, 0);
        }
        b.acted_by = sf_job::ActedBy::Policy(
            std::num::NonZeroU64::new(asg.policy_version).unwrap_or(std::num::NonZeroU64::MIN),
        );
        let msg = sf_proto::batch_to_wire(&b);
        let bytes = prost::Message::encoded_len(&msg);
        let accepted = Arc::new(AtomicU64::new(0));
        let start = Instant::now();
        let until = start + Duration::from_secs_f64(a.seconds);
        let mut tasks = Vec::new();
        for _ in 0..a.workers {
            let (mut exp, msg, accepted) = (exp.clone(), msg.clone(), Arc::clone(&accepted));
            tasks.push(tokio::spawn(async move {
                let (tx, rx) = tokio::sync::mpsc::channel(2);
                let mut acks = exp
                    .push_transitions(tokio_stream::wrappers::ReceiverStream::new(rx))
                    .await?
                    .into_inner();
                let sender = tokio::spawn(async move {
                    while Instant::now() < until {
                        if tx.send(msg.clone()).await.is_err() {
                            break;
                        }
                    }
                });
                while let Some(a) = acks.next().await {
                    accepted.fetch_add(a?.accepted as u64, Ordering::Relaxed);
                }
                let _ = sender.await;
                anyhow::Ok(())
            }));
        }
        for t in tasks {
            t.await.map_err(|e| anyhow!("sender task: {e}"))??;
        }
        let secs = start.elapsed().as_secs_f64();
        emb.stop().await?;
        let n = accepted.load(Ordering::Relaxed);
        anyhow::Ok(json!({
            "workers": a.workers, "seconds": secs, "batch_transitions": a.batch, "transitions": n,
            "transitions_per_s": n as f64 / secs, "batch_bytes": bytes,
            "mb_per_s": n as f64 / a.batch as f64 * bytes as f64 / secs / 1e6, "obs_len": obs_len,
        }))
    });
    let _ = std::fs::remove_dir_all(&dir);
    print(out?, a.json);
    Ok(())
}

pub fn e2e(dirs: &Ctx, a: SvcBenchArgs) -> Result<()> {
    if a.workers == 0 {
        bail!("--workers must be positive");
    }
    let text = std::fs::read_to_string(&a.config)
        .with_context(|| format!("reading {}", a.config.display()))?;
    let mut cfg = JobConfig::from_toml(&text).with_context(|| a.config.display().to_string())?;
    cfg.name = "bench-e2e".into();
    cfg.train.env_steps = 1 << 40;
    cfg.train.checkpoint_every_s = 100_000;
    if let Some(spi) = a.samples_per_insert {
        cfg.train.samples_per_insert = spi;
    }
    cfg.validate().context("job config after the benchmark's overrides")?;
    let dir = tmp_dir("e2e");
    let _ = std::fs::remove_dir_all(&dir);
    let out = runtime()?.block_on(async {
        let emb = Embedded::start(dir.clone(), dirs, a.workers).await?;
        let mut c = emb.client().await?;
        let job = submit(&mut c, cfg.to_toml()).await?;
        let get = |c: &mut JobsClient| {
            let mut c = c.clone();
            async move {
                anyhow::Ok(
                    sf_proto::job_from_wire(
                        &c.get_job(pb::GetJobRequest { job_id: job.id.get() }).await?.into_inner(),
                    )?
                    .progress,
                )
            }
        };
        // Past the warm-up: the learner trains and workers act with the policy.
        let warm_deadline = Instant::now() + Duration::from_secs(600);
        let p0 = loop {
            let p = get(&mut c).await?;
            if p.learning.updates > 0
                && p.learning.env_steps
                    > cfg.sac.warmup_steps + 2 * cfg.worker.batch_transitions as u64
            {
                break p;
            }
            if Instant::now() > warm_deadline {
                bail!("the job did not leave its warm-up within 600 s");
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        };
        let t0 = Instant::now();
        tokio::time::sleep(Duration::from_secs_f64(a.seconds)).await;
        let p1 = get(&mut c).await?;
        let secs = t0.elapsed().as_secs_f64();
        emb.stop().await?;
        anyhow::Ok(json!({
            "workers": a.workers, "seconds": secs,
            "env_steps_per_s": (p1.learning.env_steps - p0.learning.env_steps) as f64 / secs,
            "updates_per_s": (p1.learning.updates - p0.learning.updates) as f64 / secs,
            "samples_per_insert": cfg.train.samples_per_insert, "envs_per_worker": cfg.worker.envs,
            "dropped_stale": p1.dropped_stale, "policy_version": p1.policy_version,
        }))
    });
    let _ = std::fs::remove_dir_all(&dir);
    print(out?, a.json);
    Ok(())
}

fn print(v: serde_json::Value, as_json: bool) {
    if as_json {
        println!("{v}");
    } else {
        println!("{}", serde_json::to_string_pretty(&v).unwrap_or_default());
    }
}
