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
    /// HTTP/2 receive windows sized by hyper's bandwidth-delay estimates (the default): ingest
    /// across a link is at most a window per round trip, and these grow with the link. With
    /// `false`, the fixed windows below.
    pub http2_adaptive_window: bool,
    /// A fixed HTTP/2 receive window per stream, KiB (with `http2_adaptive_window = false`):
    /// how much a worker may send on its transition stream before the learner reads it.
    pub http2_stream_window_kib: u32,
    /// A fixed HTTP/2 receive window per connection (all its streams), KiB; at least the
    /// stream's.
    pub http2_connection_window_kib: u32,
}

/// HTTP/2 windows, KiB: the smallest (the protocol's 64 KiB) and the largest (2^31 - 1 bytes).
const WINDOW_KIB: std::ops::RangeInclusive<u32> = 64..=2_097_151;

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
            http2_adaptive_window: true,
            http2_stream_window_kib: 8 << 10,
            http2_connection_window_kib: 32 << 10,
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
        for (field, kib) in [
            ("http2_stream_window_kib", self.http2_stream_window_kib),
            ("http2_connection_window_kib", self.http2_connection_window_kib),
        ] {
            anyhow::ensure!(
                WINDOW_KIB.contains(&kib),
                "field `{field}`: {kib} is not in {}..={} (KiB: HTTP/2's 64 KiB to 2 GiB)",
                WINDOW_KIB.start(),
                WINDOW_KIB.end()
            );
        }
        anyhow::ensure!(
            self.http2_connection_window_kib >= self.http2_stream_window_kib,
            "field `http2_connection_window_kib`: {} is below `http2_stream_window_kib` ({}): one stream could never fill its window",
            self.http2_connection_window_kib,
            self.http2_stream_window_kib
        );
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

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(extra: &str) -> anyhow::Result<LearnerConfig> {
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../..");
        let text = format!("scenarios_dir = \"{root}/configs/scenarios\"\ncases_dir = \"{root}/configs/cases\"\n{extra}");
        LearnerConfig::from_toml(&text, "test")
    }

    #[test]
    fn http2_windows_are_checked_by_field() {
        let c = parse("").expect("defaults");
        assert_eq!((c.http2_stream_window_kib, c.http2_connection_window_kib), (8192, 32768));
        assert!(c.http2_adaptive_window);
        for (extra, field) in [
            ("http2_stream_window_kib = 16", "http2_stream_window_kib"),
            ("http2_connection_window_kib = 4000000", "http2_connection_window_kib"),
            ("http2_stream_window_kib = 4096\nhttp2_connection_window_kib = 1024", "is below"),
        ] {
            let e = format!("{:#}", parse(extra).expect_err(extra));
            assert!(e.contains(field), "{extra}: {e}");
        }
        assert!(!parse("http2_adaptive_window = false").expect("fixed").http2_adaptive_window);
    }
}
