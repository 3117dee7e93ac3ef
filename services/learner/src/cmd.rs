//! The `socialflow-learner` command line: flags and environment overrides on top of the TOML
//! config, validation before any port is bound, SIGTERM/ctrl-c handling.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use sf_service::auth::Token;

use crate::config::LearnerConfig;

#[derive(Parser, Debug, Clone)]
#[command(
    name = "socialflow-learner",
    about = "The socialflow learner: job store, replay, SAC trainer, gRPC APIs"
)]
pub struct LearnerArgs {
    /// Learner config (TOML); flags and environment variables override its fields.
    #[arg(long, env = "SOCIALFLOW_LEARNER_CONFIG")]
    pub config: Option<PathBuf>,
    #[arg(long, env = "SOCIALFLOW_GRPC_ADDR")]
    pub grpc_addr: Option<SocketAddr>,
    #[arg(long, env = "SOCIALFLOW_ADMIN_ADDR")]
    pub admin_addr: Option<SocketAddr>,
    #[arg(long, env = "SOCIALFLOW_DATA_DIR")]
    pub data_dir: Option<PathBuf>,
    #[arg(long, env = "SOCIALFLOW_SCENARIOS_DIR")]
    pub scenarios_dir: Option<PathBuf>,
    /// Stored evaluation cases (evaluation jobs). Not `--cases-dir`: `socialflow learner`
    /// already has that global flag.
    #[arg(long, env = "SOCIALFLOW_CASES_DIR")]
    pub eval_cases_dir: Option<PathBuf>,
    /// File holding the bearer token (default: the SOCIALFLOW_TOKEN variable).
    #[arg(long, env = "SOCIALFLOW_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
    /// PEM certificate chain and key: serve TLS only.
    #[arg(long, env = "SOCIALFLOW_TLS_CERT_FILE", requires = "tls_key_file")]
    pub tls_cert_file: Option<PathBuf>,
    #[arg(long, env = "SOCIALFLOW_TLS_KEY_FILE", requires = "tls_cert_file")]
    pub tls_key_file: Option<PathBuf>,
    /// CA certificate (PEM): require client certificates it signed (mutual TLS).
    #[arg(long, env = "SOCIALFLOW_TLS_CLIENT_CA_FILE")]
    pub tls_client_ca_file: Option<PathBuf>,
    /// Accept the bearer token over plaintext from peers off loopback (a trusted private
    /// network only; prefer TLS).
    #[arg(long, env = "SOCIALFLOW_ALLOW_PLAINTEXT_TOKEN")]
    pub allow_plaintext_token: bool,
    /// Training jobs that may run at once (default: the machine's cores).
    #[arg(long, env = "SOCIALFLOW_MAX_RUNNING_JOBS")]
    pub max_running_jobs: Option<usize>,
    /// Log JSON lines (for containers).
    #[arg(long, env = "SOCIALFLOW_LOG_JSON")]
    pub log_json: bool,
}

impl LearnerArgs {
    /// The resolved config and token; nothing is bound yet.
    pub fn resolve(&self) -> anyhow::Result<(LearnerConfig, Token)> {
        let mut cfg = match &self.config {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .with_context(|| format!("reading learner config {}", p.display()))?;
                LearnerConfig::from_toml(&text, &p.display().to_string())?
            }
            None => LearnerConfig::default(),
        };
        if let Some(a) = self.grpc_addr {
            cfg.grpc_addr = a;
        }
        if let Some(a) = self.admin_addr {
            cfg.admin_addr = a;
        }
        if let Some(d) = &self.data_dir {
            cfg.data_dir = d.clone();
        }
        if let Some(n) = self.max_running_jobs {
            cfg.max_running_jobs = Some(n);
        }
        if let Some(d) = &self.scenarios_dir {
            cfg.scenarios_dir = d.clone();
        }
        if let Some(d) = &self.eval_cases_dir {
            cfg.cases_dir = d.clone();
        }
        if self.tls_cert_file.is_some() {
            cfg.tls_cert_file = self.tls_cert_file.clone();
            cfg.tls_key_file = self.tls_key_file.clone();
        }
        if self.tls_client_ca_file.is_some() {
            cfg.tls_client_ca_file = self.tls_client_ca_file.clone();
        }
        cfg.allow_plaintext_token |= self.allow_plaintext_token;
        cfg.validate()?;
        let token = Token::load(sf_service::auth::TOKEN_ENV, self.token_file.as_deref())?;
        Ok((cfg, token))
    }
}

/// The binary's whole life: resolve, start, wait for a signal, checkpoint and stop.
pub async fn run(args: LearnerArgs) -> anyhow::Result<()> {
    sf_service::logging::init(args.log_json);
    let (cfg, token) = args.resolve()?;
    let l = crate::start(cfg, token).await?;
    sf_service::signal::terminate().await;
    tracing::info!("termination requested");
    l.shutdown().await
}
