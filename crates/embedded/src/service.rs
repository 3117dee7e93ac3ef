//! The service in one process: a learner on loopback ports the OS chooses, with a random token,
//! and N workers connected to it over gRPC exactly as in a deployment; the async runtime the
//! commands run it on.
//!
//! Owns: [`Embedded`] (start, a job-API client, stop) and [`runtime`]. Must not: decide what the
//! learner or the workers do (`sf_learner`, `sf_worker`) or submit jobs itself.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result};
use prometheus_client::registry::Registry;
use rand::Rng;
use sf_learner::{LearnerConfig, RunningLearner};
use sf_service::auth::Token;
use sf_service::client::JobsClient;
use sf_worker::{WorkerConfig, WorkerMetrics};
use tokio::sync::watch;

use crate::client;
use crate::dirs::Ctx;

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
        Self::start_with(data_dir, dirs, n, None).await
    }

    /// As [`Embedded::start`], with the learner's `max_running_jobs` (unset: the cores).
    pub async fn start_with(
        data_dir: PathBuf,
        dirs: &Ctx,
        n: usize,
        max_running_jobs: Option<usize>,
    ) -> Result<Self> {
        let (scenarios_dir, cases_dir) = (dirs.scenarios.clone(), dirs.cases.clone());
        let secret: String =
            (0..32).map(|_| format!("{:x}", rand::rng().random_range(0..16u8))).collect();
        let token = Token::new(&secret, "embedded").context("embedded token")?;
        let cfg = LearnerConfig {
            grpc_addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            admin_addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            data_dir,
            scenarios_dir: scenarios_dir.clone(),
            cases_dir: cases_dir.clone(),
            max_running_jobs,
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
                in_flight_batches: sf_worker::DEFAULT_IN_FLIGHT_BATCHES,
                adaptive_window: true,
            };
            let metrics = WorkerMetrics::register(&mut Registry::default());
            workers.push(tokio::spawn(sf_worker::run(wc, metrics, stop_rx.clone())));
        }
        Ok(Self { learner, url, token, stop_workers, workers })
    }

    pub async fn client(&self) -> Result<JobsClient> {
        client::jobs_client(
            sf_service::tls::endpoint(&self.url, &Default::default())?,
            &self.url,
            Some(self.token.clone()),
        )
        .await
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
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")
}
