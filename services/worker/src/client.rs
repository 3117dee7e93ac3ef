//! The worker's connection to the learner: its settings and the helpers every part calls with.
//!
//! Owns: [`WorkerConfig`] (what outlives a connection: the learner's address, the worker's
//! name, directories, deadlines, TLS, the in-flight window), [`Client`] (the experience
//! service's client with the token attached), [`connect`], [`req`] (every unary call gets the
//! deadline) and [`status_err`] (a refused call counted and turned into an error naming the
//! RPC). Must not: hold session state (a job, its policies or batches) or decide what a session
//! does next.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, Context};
use sf_proto::pb::experience_service_client::ExperienceServiceClient;
use sf_service::auth::{AttachToken, Token};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::Request;

use crate::metrics::WorkerMetrics;

/// What a worker connects with; it outlives every connection.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// `http://host:port` of the learner.
    pub learner_url: String,
    pub name: String,
    pub scenarios_dir: PathBuf,
    /// Stored evaluation cases (evaluation jobs).
    pub cases_dir: PathBuf,
    pub token: Option<Token>,
    /// Deadline of every unary call.
    pub rpc_timeout: Duration,
    pub max_backoff: Duration,
    /// Rayon threads for stepping simulators (0 = rayon's default).
    pub threads: usize,
    /// Trust root for an `https://` learner and the worker's client certificate (mutual TLS).
    pub tls: sf_service::tls::ClientTls,
    /// Transition batches sent and not yet acknowledged, at most (the window's cap).
    pub in_flight_batches: u32,
    /// Size the window to the link (from 2 up to the cap), else keep it at the cap.
    pub adaptive_window: bool,
}

/// The cap of the window of unacknowledged batches: 32 batches carry ingest across 100 ms one
/// way (`docs/results/reliability.md`) and bound what a worker's death loses (8,192
/// transitions at the default batch size); the window itself starts at 2 and sizes itself.
pub const DEFAULT_IN_FLIGHT_BATCHES: u32 = 32;

/// The experience service's client, its token attached to every call.
pub(crate) type Client = ExperienceServiceClient<InterceptedService<Channel, AttachToken>>;

/// Request `msg` with deadline `timeout`: every unary call has one.
pub(crate) fn req<T>(msg: T, timeout: Duration) -> Request<T> {
    let mut r = Request::new(msg);
    r.set_timeout(timeout);
    r
}

/// Connects to the learner at `cfg.learner_url` (TLS for `https://`).
pub(crate) async fn connect(cfg: &WorkerConfig) -> anyhow::Result<Client> {
    let ch = sf_service::tls::endpoint(&cfg.learner_url, &cfg.tls)?
        .connect()
        .await
        .with_context(|| format!("connecting to {}", cfg.learner_url))?;
    Ok(ExperienceServiceClient::with_interceptor(ch, AttachToken::new(cfg.token.clone()))
        .max_decoding_message_size(sf_service::MAX_MESSAGE_BYTES)
        .max_encoding_message_size(sf_service::MAX_MESSAGE_BYTES))
}

/// Counts refused call `what` and turns its status into an error naming the call and the code.
pub(crate) fn status_err(what: &str, s: tonic::Status, metrics: &WorkerMetrics) -> anyhow::Error {
    metrics.common.rpc(what, s.code());
    anyhow!("{what}: {} ({})", s.message(), sf_service::error::code_label(s.code()))
}
