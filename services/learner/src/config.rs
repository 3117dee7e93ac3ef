//! The learner's deployment settings: [`LearnerConfig`], read from TOML (`configs/learner.toml`,
//! unknown fields refused), overridden by flags and `SOCIALFLOW_*` variables in [`crate::cmd`],
//! and validated (paths exist, TLS files go together, a client CA only with TLS) before any
//! port is bound. Must not: bind ports or open the store.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Context;
use serde::{Deserialize, Serialize};

/// The learner's deployment settings (`configs/learner.toml`).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LearnerConfig {
    pub grpc_addr: SocketAddr,
    pub admin_addr: SocketAddr,
    /// Job store (`jobs.redb`) and per-job artifact directories (`jobs/<id>-<name>/`).
    pub data_dir: PathBuf,
    /// Scenario files `<name>.json`.
    pub scenarios_dir: PathBuf,
    /// Stored evaluation cases `<name>.v<N>.json` (evaluation jobs).
    pub cases_dir: PathBuf,
    pub max_message_bytes: usize,
    /// Seconds a worker may go without a heartbeat before it is forgotten.
    pub worker_timeout_s: u64,
    /// Seconds the trainers get to write their checkpoints on shutdown.
    pub shutdown_grace_s: u64,
    /// Training jobs that may run at once, each on its own trainer thread with its own replay
    /// and rate limiter (never more than there are live workers: each needs one). Unset: the
    /// machine's cores.
    pub max_running_jobs: Option<usize>,
    /// PEM certificate chain and key: serve TLS only (both or neither).
    pub tls_cert_file: Option<PathBuf>,
    pub tls_key_file: Option<PathBuf>,
    /// With TLS: accept only clients whose certificate this CA signed (mutual TLS).
    pub tls_client_ca_file: Option<PathBuf>,
    /// Without TLS, a bearer token from a peer that is not on loopback is refused unless this is
    /// set (a private network the operator trusts: compose, a cluster's pod network).
    pub allow_plaintext_token: bool,
}

impl Default for LearnerConfig {
    fn default() -> Self {
        Self {
            grpc_addr: SocketAddr::from(([0, 0, 0, 0], 50051)),
            admin_addr: SocketAddr::from(([0, 0, 0, 0], 9090)),
            data_dir: PathBuf::from("runs/learner"),
            scenarios_dir: PathBuf::from("configs/scenarios"),
            cases_dir: PathBuf::from("configs/cases"),
            max_message_bytes: sf_service::MAX_MESSAGE_BYTES,
            worker_timeout_s: 30,
            shutdown_grace_s: 120,
            max_running_jobs: None,
            tls_cert_file: None,
            tls_key_file: None,
            tls_client_ca_file: None,
            allow_plaintext_token: false,
        }
    }
}

impl LearnerConfig {
    /// How many training jobs may run at once: `max_running_jobs`, else the machine's cores.
    pub fn running_job_limit(&self) -> usize {
        self.max_running_jobs
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
            .max(1)
    }

    pub fn from_toml(text: &str, origin: &str) -> anyhow::Result<Self> {
        let c: Self = toml::from_str(text).with_context(|| format!("learner config {origin}"))?;
        c.validate().with_context(|| format!("learner config {origin}"))?;
        Ok(c)
    }

    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.max_message_bytes >= 1 << 16,
            "field `max_message_bytes`: {} is below 65536",
            self.max_message_bytes
        );
        anyhow::ensure!(self.worker_timeout_s > 0, "field `worker_timeout_s` must be positive");
        anyhow::ensure!(
            self.max_running_jobs != Some(0),
            "field `max_running_jobs`: 0 would run no job (leave it out for the machine's cores)"
        );
        anyhow::ensure!(
            self.scenarios_dir.is_dir(),
            "field `scenarios_dir`: {} is not a directory",
            self.scenarios_dir.display()
        );
        anyhow::ensure!(
            self.cases_dir.is_dir(),
            "field `cases_dir`: {} is not a directory",
            self.cases_dir.display()
        );
        match (&self.tls_cert_file, &self.tls_key_file) {
            (Some(c), Some(k)) => {
                anyhow::ensure!(
                    c.is_file(),
                    "field `tls_cert_file`: {} is not a file",
                    c.display()
                );
                anyhow::ensure!(k.is_file(), "field `tls_key_file`: {} is not a file", k.display());
            }
            (None, None) => {}
            _ => anyhow::bail!("fields `tls_cert_file` and `tls_key_file` go together"),
        }
        if let Some(ca) = &self.tls_client_ca_file {
            anyhow::ensure!(self.tls_cert_file.is_some(), "field `tls_client_ca_file` needs `tls_cert_file` and `tls_key_file` (mutual TLS is TLS)");
            anyhow::ensure!(
                ca.is_file(),
                "field `tls_client_ca_file`: {} is not a file",
                ca.display()
            );
        }
        Ok(())
    }
}
