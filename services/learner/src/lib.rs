//! The learner: owns all training state and serves the job and experience APIs.
//!
//! Owns: [`start`] (validates the [`LearnerConfig`] before any port is bound, opens the job
//! store, binds the gRPC and admin ports, spawns the scheduler's loop and its storage
//! recovery) and [`Learner`], the parts it composes — each a type with the fields it needs:
//!
//! - [`jobs::Jobs`]: the job table over the store (submit, get, list, cancel, files, parsed
//!   specs); `JobService`'s handlers call it.
//! - [`scheduler::Scheduler`]: starts jobs while the slots admit them, follows them, records
//!   their end; shutdown.
//! - [`experience::Experience`]: what workers call (assignment, policy, ingest, evaluation
//!   results); `ExperienceService`'s handlers call it.
//! - [`workers::Workers`]: the worker registry; [`slot::Slots`]: the running jobs (training
//!   [`job::ActiveJob`]s side by side, or one evaluation [`eval::EvalJob`] alone).
//!
//! Must not: expose wire types outside [`service`] (the gRPC edge) and `experience.rs` (the
//! batch it decodes), or pick a status for an error (`error.rs` maps each domain error to one).
//!
//! Shutdown ([`RunningLearner::shutdown`], SIGTERM in the binary): the running jobs are asked
//! to stop, their trainers write checkpoints, the jobs stay RUNNING in the store and resume on
//! the next start.

mod artifacts;
pub mod cmd;
pub mod config;
pub mod continuation;
mod deps;
mod error;
pub mod eval;
pub mod experience;
pub mod job;
pub mod jobs;
pub mod metrics;
pub mod scheduler;
pub mod service;
pub mod slot;
pub mod storage;
pub mod store;
mod task;
pub mod trainer;
pub mod validation;
pub mod warm_start;
pub mod workers;

use std::net::SocketAddr;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use prometheus_client::registry::Registry;
use sf_proto::pb::experience_service_server::ExperienceServiceServer;
use sf_proto::pb::job_service_server::JobServiceServer;
use sf_service::auth::{RequireToken, Token, Transport};
use tokio::sync::{oneshot, Notify};
use tonic::service::interceptor::InterceptedService;

pub use crate::config::LearnerConfig;
pub use crate::error::{IngestError, LearnerError};
use crate::experience::Experience;
use crate::jobs::{Jobs, Shared};
use crate::metrics::LearnerMetrics;
use crate::scheduler::Scheduler;
use crate::slot::Slots;
use crate::storage::StorageHealth;
use crate::store::Store;
use crate::workers::Workers;

/// The learner's parts, shared by the handlers, the scheduler and the jobs' completion tasks.
pub struct Learner {
    pub jobs: Arc<Jobs>,
    pub scheduler: Arc<Scheduler>,
    pub experience: Arc<Experience>,
    pub workers: Arc<Workers>,
    pub metrics: LearnerMetrics,
    /// Whether the data directory takes writes; while it does not, no job starts.
    pub storage: Arc<StorageHealth>,
}

impl Learner {
    /// Why the data directory refuses writes, while it does.
    pub fn storage_fault(&self) -> Option<String> {
        self.storage.cause()
    }
}

/// A started learner.
pub struct RunningLearner {
    pub learner: Arc<Learner>,
    pub grpc_addr: SocketAddr,
    pub admin_addr: SocketAddr,
    /// How long shutdown waits for the running jobs' checkpoints.
    shutdown_grace: Duration,
    stop_server: Option<oneshot::Sender<()>>,
    server: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
}

/// Rewrites tonic's OUT_OF_RANGE for oversized messages into the protocol's RESOURCE_EXHAUSTED
/// (trailers-only responses carry the status in headers).
fn size_status<B>(mut res: http::Response<B>) -> http::Response<B> {
    let h = res.headers_mut();
    let oversized = h.get("grpc-status").is_some_and(|v| v.as_bytes() == b"11")
        && h.get("grpc-message").is_some_and(|m| {
            m.to_str().is_ok_and(|m| {
                m.contains("message%20length%20too%20large")
                    || m.contains("message length too large")
            })
        });
    if oversized {
        h.insert("grpc-status", http::HeaderValue::from_static("8"));
    }
    res
}

/// Opens the store, binds both ports and starts serving and scheduling.
pub async fn start(cfg: LearnerConfig, token: Token) -> anyhow::Result<RunningLearner> {
    cfg.validate()?;
    std::fs::create_dir_all(cfg.data_dir.join("jobs"))
        .with_context(|| format!("creating {}", cfg.data_dir.display()))?;
    let store = Arc::new(Store::open(&cfg.data_dir.join("jobs.redb"), &cfg.data_dir)?);
    let mut registry = Registry::default();
    let metrics = LearnerMetrics::register(&mut registry);
    let grpc = tokio::net::TcpListener::bind(cfg.grpc_addr)
        .await
        .with_context(|| format!("binding gRPC port {}", cfg.grpc_addr))?;
    let grpc_addr = grpc.local_addr()?;
    let ready = Arc::new(AtomicBool::new(false));
    let m2 = metrics.clone();
    let admin_addr = sf_service::admin::serve(
        cfg.admin_addr,
        Arc::new(registry),
        Arc::clone(&ready),
        Arc::new(move || m2.common.refresh()),
    )
    .await?;
    let first_worker = (sf_job::now_unix_ms() % 1_000_000_000) * 1000;
    let slots = Arc::new(Slots::new(cfg.running_job_limit(), metrics.running_jobs.clone()));
    let workers = Arc::new(Workers::new(
        first_worker,
        Duration::from_secs(cfg.worker_timeout_s),
        metrics.workers.clone(),
    ));
    let storage = Arc::new(StorageHealth::new(
        Arc::clone(&ready),
        metrics.storage_ok.clone(),
        metrics.storage_faults.clone(),
    ));
    let (shutting_down, wake) = (Arc::new(AtomicBool::new(false)), Arc::new(Notify::new()));
    let shared = || Shared {
        slots: Arc::clone(&slots),
        storage: Arc::clone(&storage),
        shutting_down: Arc::clone(&shutting_down),
        wake: Arc::clone(&wake),
    };
    let jobs = Arc::new(Jobs::new(store, &cfg, shared()));
    let learner = Arc::new(Learner {
        scheduler: Arc::new(Scheduler::new(
            Arc::clone(&jobs),
            Arc::clone(&workers),
            metrics.clone(),
            cfg.data_dir.clone(),
            shared(),
        )),
        experience: Arc::new(Experience::new(
            Arc::clone(&jobs),
            Arc::clone(&slots),
            Arc::clone(&workers),
            Arc::clone(&storage),
        )),
        jobs,
        workers,
        metrics: metrics.clone(),
        storage,
    });
    let m3 = metrics.clone();
    let transport = match (cfg.tls_cert_file.is_some(), cfg.allow_plaintext_token) {
        (true, _) => Transport::Tls,
        (false, allow_remote) => Transport::Plaintext { allow_remote },
    };
    if transport == (Transport::Plaintext { allow_remote: false })
        && !cfg.grpc_addr.ip().is_loopback()
    {
        tracing::warn!(%grpc_addr, "serving plaintext: tokens from peers off loopback are refused (serve TLS, or set allow_plaintext_token on a trusted network)");
    }
    let auth =
        RequireToken::new(&token, move || m3.common.rpc("any", tonic::Code::Unauthenticated))
            .transport(transport);
    let max = cfg.max_message_bytes;
    let jobs = JobServiceServer::new(service::Jobs {
        jobs: Arc::clone(&learner.jobs),
        metrics: metrics.clone(),
    })
    .max_decoding_message_size(max)
    .max_encoding_message_size(max);
    let exp = ExperienceServiceServer::new(service::Experience {
        experience: Arc::clone(&learner.experience),
        metrics: metrics.clone(),
    })
    .max_decoding_message_size(max)
    .max_encoding_message_size(max);
    let (health_reporter, health) = tonic_health::server::health_reporter();
    health_reporter.set_serving::<JobServiceServer<service::Jobs>>().await;
    health_reporter.set_serving::<ExperienceServiceServer<service::Experience>>().await;
    // Reflection in both versions: `v1alpha` is what older clients (and some GUI clients) ask.
    let reflection_builder = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(sf_proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection = reflection_builder().build_v1().context("gRPC reflection service (v1)")?;
    let reflection_v1alpha =
        reflection_builder().build_v1alpha().context("gRPC reflection service (v1alpha)")?;
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let incoming = tokio_stream::wrappers::TcpListenerStream::new(grpc);
    // HTTP/2 receive windows: ingest across a link is at most a window per round trip; sized
    // to the link by default (BDP estimates), fixed on request (`docs/results/reliability.md`,
    // slow links).
    let mut builder = if cfg.http2_adaptive_window {
        tonic::transport::Server::builder().http2_adaptive_window(Some(true))
    } else {
        tonic::transport::Server::builder()
            .initial_stream_window_size(cfg.http2_stream_window_kib * 1024)
            .initial_connection_window_size(cfg.http2_connection_window_kib * 1024)
    };
    if let (Some(c), Some(k)) = (&cfg.tls_cert_file, &cfg.tls_key_file) {
        builder = builder
            .tls_config(sf_service::tls::server(c, k, cfg.tls_client_ca_file.as_deref())?)
            .context("TLS server configuration")?;
    }
    let server = tokio::spawn(
        builder
            .layer(tower::util::MapResponseLayer::new(size_status))
            .add_service(InterceptedService::new(jobs, auth.clone()))
            .add_service(InterceptedService::new(exp, auth))
            // Health and reflection answer without a token: Kubernetes' gRPC probes cannot send
            // one, and neither reveals more than the public schema and "serving".
            .add_service(health)
            .add_service(reflection)
            .add_service(reflection_v1alpha)
            .serve_with_incoming_shutdown(incoming, async {
                let _ = stop_rx.await;
            }),
    );
    // The scheduler's loop: forget silent workers, count each job's, start what may start.
    let l = Arc::clone(&learner);
    tokio::spawn(async move {
        loop {
            l.workers.prune();
            l.experience.count_workers_per_job();
            l.scheduler.schedule_once().await;
            if l.scheduler.shutting_down() {
                return;
            }
            l.scheduler.wait().await;
        }
    });
    tokio::spawn(Arc::clone(&learner.scheduler).recover_storage());
    ready.store(learner.storage.healthy(), std::sync::atomic::Ordering::Release);
    tracing::info!(%grpc_addr, %admin_addr, tls = cfg.tls_cert_file.is_some(), mutual_tls = cfg.tls_client_ca_file.is_some(), data_dir = %cfg.data_dir.display(), "learner serving");
    Ok(RunningLearner {
        learner,
        grpc_addr,
        admin_addr,
        shutdown_grace: Duration::from_secs(cfg.shutdown_grace_s),
        stop_server: Some(stop_tx),
        server,
    })
}

impl RunningLearner {
    /// Checkpoints the running jobs (they stay RUNNING) and stops serving.
    pub async fn shutdown(mut self) -> anyhow::Result<()> {
        self.learner.scheduler.stop_all(self.shutdown_grace).await;
        if let Some(tx) = self.stop_server.take() {
            let _ = tx.send(());
        }
        match tokio::time::timeout(Duration::from_secs(5), &mut self.server).await {
            Ok(Ok(Ok(()))) | Err(_) => Ok(()),
            Ok(Ok(Err(e))) => Err(e).context("gRPC server"),
            Ok(Err(e)) => Err(e).context("gRPC server task"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sf_job::JobConfig;
    use std::path::{Path, PathBuf};

    /// Every shipped config parses and validates: job configs as jobs, the learner's as such.
    #[test]
    fn every_shipped_config_file_is_valid() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let mut files: Vec<PathBuf> = std::fs::read_dir(root.join("configs"))
            .expect("configs/")
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "toml"))
            .collect();
        files.push(root.join("deploy/smoke-job.toml"));
        for sub in [
            "configs/paper-small",
            "configs/paper",
            "configs/ladder/jobs",
            "configs/ladder/l7-steering-adversary",
        ] {
            files.extend(
                std::fs::read_dir(root.join(sub))
                    .expect("pipeline dir")
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.extension().is_some_and(|x| x == "toml")),
            );
        }
        assert!(files.len() >= 3, "{files:?}");
        for f in files {
            let text = std::fs::read_to_string(&f).expect("readable");
            if f.file_name().is_some_and(|n| n == "learner.toml") {
                let c: LearnerConfig =
                    toml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
                assert!(c.max_message_bytes >= 1 << 16);
            } else {
                JobConfig::from_toml(&text).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            }
        }
    }
}
