//! `socialflow train <config>`: the learner and N workers in this process, talking gRPC over
//! loopback exactly as in a deployment, with a progress bar. Also the `learner` and `worker`
//! subcommands (the service binaries' entry points, for a one-binary image) and the embedded
//! set-up the service benchmarks use.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use prometheus_client::registry::Registry;
use rand::Rng;
use serde_json::json;
use sf_job::{JobConfig, JobState};
use sf_learner::{LearnerConfig, RunningLearner};
use sf_service::auth::Token;
use sf_worker::{WorkerConfig, WorkerMetrics};
use tokio::sync::watch;

use crate::remote;
use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Job config (TOML), e.g. configs/quickstart.toml.
    pub config: PathBuf,
    /// Rollout workers in this process.
    #[arg(long, default_value_t = 2)]
    pub workers: usize,
    /// Job store and artifacts; rerunning with the same directory resumes an interrupted job.
    #[arg(long, default_value = "runs/embedded")]
    pub data_dir: PathBuf,
    /// No progress bar (logs only).
    #[arg(long)]
    pub quiet: bool,
}

/// A learner and its workers in this process.
pub struct Embedded {
    pub learner: RunningLearner,
    pub url: String,
    pub token: Token,
    stop_workers: watch::Sender<bool>,
    workers: Vec<tokio::task::JoinHandle<Result<()>>>,
}

impl Embedded {
    /// Starts a learner on loopback ports chosen by the OS and `n` workers connected to it.
    pub async fn start(data_dir: PathBuf, dirs: &Ctx, n: usize) -> Result<Self> {
        let (scenarios_dir, cases_dir) = (dirs.scenarios.clone(), dirs.cases.clone());
        let secret: String = (0..32).map(|_| format!("{:x}", rand::rng().random_range(0..16u8))).collect();
        let token = Token::new(&secret, "embedded").context("embedded token")?;
        let cfg = LearnerConfig {
            grpc_addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            admin_addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            data_dir,
            scenarios_dir: scenarios_dir.clone(),
            cases_dir: cases_dir.clone(),
            ..LearnerConfig::default()
        };
        let learner = sf_learner::start(cfg, token.clone()).await?;
        let url = format!("http://{}", learner.grpc_addr);
        let (stop_workers, stop_rx) = watch::channel(false);
        let mut workers = Vec::new();
        for k in 0..n {
            let wc = WorkerConfig {
                learner_url: url.clone(),
                name: format!("embedded-{k}"),
                scenarios_dir: scenarios_dir.clone(),
                cases_dir: cases_dir.clone(),
                token: Some(token.clone()),
                rpc_timeout: Duration::from_secs(30),
                max_backoff: Duration::from_secs(2),
                threads: 0,
                tls: Default::default(),
            };
            let metrics = WorkerMetrics::register(&mut Registry::default());
            workers.push(tokio::spawn(sf_worker::run(wc, metrics, stop_rx.clone())));
        }
        Ok(Self { learner, url, token, stop_workers, workers })
    }

    pub async fn client(&self) -> Result<remote::JobsClient> {
        remote::jobs_client(sf_service::tls::endpoint(&self.url, &Default::default())?, &self.url, Some(self.token.clone())).await
    }

    /// Stops the workers, then the learner (checkpointing a running job).
    pub async fn stop(self) -> Result<()> {
        let _ = self.stop_workers.send(true);
        for w in self.workers {
            let _ = tokio::time::timeout(Duration::from_secs(10), w).await;
        }
        self.learner.shutdown().await
    }
}

pub fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("starting the async runtime")
}

pub fn run(dirs: &Ctx, a: TrainArgs) -> Result<()> {
    let text = std::fs::read_to_string(&a.config).with_context(|| format!("reading {}", a.config.display()))?;
    let cfg = JobConfig::from_toml(&text).with_context(|| a.config.display().to_string())?;
    if a.workers == 0 {
        bail!("--workers must be at least 1");
    }
    // The device before any port: a cuda job on a machine without a GPU stops here.
    sf_nn::device::device(sf_sac::device_kind(cfg.sac.device)).with_context(|| format!("{}: field `sac.device`", a.config.display()))?;
    runtime()?.block_on(async move {
        let emb = Embedded::start(a.data_dir.clone(), dirs, a.workers).await?;
        let mut c = emb.client().await?;
        let mut existing = None;
        for j in remote::list(&mut c).await?.into_iter().filter(|j| j.name == cfg.name && !j.state.is_final()) {
            let full = remote::get(&mut c, j.id).await?;
            if full.config_toml == text {
                existing = Some(full);
                break;
            }
        }
        let job = match existing {
            Some(j) => {
                eprintln!("resuming job {} ({}) from {}", j.id, j.name, j.artifact_dir);
                j
            }
            None => remote::submit(&mut c, text.clone()).await?,
        };
        let watched = tokio::select! {
            r = remote::watch(&mut c, job.id, a.quiet) => Some(r),
            _ = sf_service::signal::terminate() => None,
        };
        emb.stop().await?;
        let Some(r) = watched else {
            eprintln!("interrupted: job {} is checkpointed; run the same command to resume", job.id);
            return Ok(());
        };
        let (state, p) = r?;
        println!("{}", json!({"job_id": job.id, "name": job.name, "state": state.as_str(), "artifact_dir": job.artifact_dir, "progress": p}));
        if state != JobState::Succeeded {
            bail!("job {} ended {}", job.id, state.as_str());
        }
        Ok(())
    })
}

pub fn learner(a: sf_learner::cmd::LearnerArgs) -> Result<()> {
    runtime()?.block_on(sf_learner::cmd::run(a))
}

pub fn worker(a: sf_worker::cmd::WorkerArgs) -> Result<()> {
    runtime()?.block_on(sf_worker::cmd::run(a))
}
