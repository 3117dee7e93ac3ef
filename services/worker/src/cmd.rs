//! The `socialflow-worker` command line and process wiring (admin port, signals).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use clap::Parser;
use prometheus_client::registry::Registry;
use sf_service::conn::LearnerConn;
use tokio::sync::watch;

use crate::client::{WorkerConfig, DEFAULT_IN_FLIGHT_BATCHES};
use crate::metrics::WorkerMetrics;

#[derive(Parser, Debug, Clone)]
#[command(name = "socialflow-worker", about = "A stateless socialflow rollout worker")]
pub struct WorkerArgs {
    #[command(flatten)]
    pub conn: LearnerConn,
    /// Name in the learner's logs (default: the host name).
    #[arg(long, env = "SOCIALFLOW_WORKER_NAME")]
    pub name: Option<String>,
    /// Admin HTTP port (metrics, health); none if unset.
    #[arg(long, env = "SOCIALFLOW_ADMIN_ADDR")]
    pub admin_addr: Option<SocketAddr>,
    #[arg(long, env = "SOCIALFLOW_SCENARIOS_DIR", default_value = "configs/scenarios")]
    pub scenarios_dir: PathBuf,
    /// Stored evaluation cases (evaluation jobs' cells). Not `--cases-dir`: `socialflow worker`
    /// already has that global flag.
    #[arg(long, env = "SOCIALFLOW_CASES_DIR", default_value = "configs/cases")]
    pub eval_cases_dir: PathBuf,
    /// Deadline of each unary call, seconds.
    #[arg(long, default_value_t = 10)]
    pub rpc_timeout_s: u64,
    /// Longest reconnect delay, seconds.
    #[arg(long, default_value_t = 10)]
    pub max_backoff_s: u64,
    /// Transition batches sent and not yet acknowledged, at most: the cap of the window that
    /// carries ingest across a slow link (throughput is at most the window's batches per round
    /// trip). The window sizes itself to the link between 2 and this cap (twice the measured
    /// bandwidth-delay product: the fastest recent acknowledged rate times the shortest recent
    /// round trip); more is more lost if the worker dies.
    #[arg(long, env = "SOCIALFLOW_IN_FLIGHT_BATCHES", default_value_t = DEFAULT_IN_FLIGHT_BATCHES)]
    pub in_flight_batches: u32,
    /// Keep the window at `--in-flight-batches` instead of sizing it to the link.
    #[arg(long, env = "SOCIALFLOW_FIXED_WINDOW")]
    pub fixed_window: bool,
    #[arg(long, env = "SOCIALFLOW_LOG_JSON")]
    pub log_json: bool,
}

impl WorkerArgs {
    pub fn resolve(&self) -> anyhow::Result<WorkerConfig> {
        anyhow::ensure!(
            self.conn.learner.starts_with("http://") || self.conn.learner.starts_with("https://"),
            "--learner `{}` must start with http:// or https://",
            self.conn.learner
        );
        anyhow::ensure!(
            self.scenarios_dir.is_dir(),
            "--scenarios-dir {} is not a directory",
            self.scenarios_dir.display()
        );
        anyhow::ensure!(
            self.eval_cases_dir.is_dir(),
            "--eval-cases-dir {} is not a directory",
            self.eval_cases_dir.display()
        );
        anyhow::ensure!(self.rpc_timeout_s > 0, "--rpc-timeout-s must be positive");
        anyhow::ensure!(
            (1..=64).contains(&self.in_flight_batches),
            "--in-flight-batches {} is not in 1..=64",
            self.in_flight_batches
        );
        let token = self.conn.token()?;
        let name = self
            .name
            .clone()
            .or_else(|| std::env::var("HOSTNAME").ok())
            .or_else(|| std::fs::read_to_string("/etc/hostname").ok().map(|s| s.trim().to_string()))
            .unwrap_or_else(|| "worker".into());
        Ok(WorkerConfig {
            learner_url: self.conn.learner.clone(),
            name,
            scenarios_dir: self.scenarios_dir.clone(),
            cases_dir: self.eval_cases_dir.clone(),
            token: Some(token),
            rpc_timeout: Duration::from_secs(self.rpc_timeout_s),
            max_backoff: Duration::from_secs(self.max_backoff_s.max(1)),
            threads: 0,
            tls: self.conn.tls(),
            in_flight_batches: self.in_flight_batches,
            adaptive_window: !self.fixed_window,
        })
    }
}

pub async fn run(args: WorkerArgs) -> anyhow::Result<()> {
    sf_service::logging::init(args.log_json);
    let cfg = args.resolve()?;
    let mut reg = Registry::default();
    let metrics = WorkerMetrics::register(&mut reg);
    if let Some(addr) = args.admin_addr {
        let m = metrics.clone();
        let bound = sf_service::admin::serve(
            addr,
            Arc::new(reg),
            Arc::new(AtomicBool::new(true)),
            Arc::new(move || m.common.refresh()),
        )
        .await?;
        tracing::info!(admin = %bound, "admin server");
    }
    let (stop_tx, stop_rx) = watch::channel(false);
    tokio::spawn(async move {
        sf_service::signal::terminate().await;
        let _ = stop_tx.send(true);
    });
    crate::run(cfg, metrics, stop_rx).await
}
