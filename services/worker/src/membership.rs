//! Who this worker is to the learner: registration and the heartbeats that keep it alive.
//!
//! Owns: [`register`] (`Register`, the id and heartbeat interval, clamped to 0.2–30 s) and
//! [`Heartbeats`], a task that sends `Heartbeat` every interval on a connection of its own (on
//! the session's, a transition stream the learner is not reading — its rate limiter holds
//! inserts — fills HTTP/2's connection window and starves them). NOT_FOUND (the learner forgot
//! this worker) or three failures in a row stop it and make [`Heartbeats::failed`] ready;
//! dropping it stops the task. Must not: end the session itself (the session selects on
//! `failed`), or keep the registration (the session loop in `lib.rs` does, dropping it after an
//! error).

use std::time::Duration;

use sf_job::WorkerId;
use sf_proto::pb;
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tonic::Code;

use crate::client::{connect, req, status_err, Client, WorkerConfig};
use crate::metrics::WorkerMetrics;

/// What the learner gave this worker when it registered.
#[derive(Clone, Copy, Debug)]
pub struct Registration {
    pub worker_id: WorkerId,
    pub heartbeat_every: Duration,
}

/// Registers this worker under `cfg.name`.
pub async fn register(
    client: &mut Client,
    cfg: &WorkerConfig,
    metrics: &WorkerMetrics,
) -> anyhow::Result<Registration> {
    let reg = client
        .register(req(
            pb::RegisterRequest {
                name: cfg.name.clone(),
                runs_idm_ego: true,
                runs_mobil_ego: true,
            },
            cfg.rpc_timeout,
        ))
        .await
        .map_err(|s| status_err("Register", s, metrics))?
        .into_inner();
    metrics.common.rpc("Register", Code::Ok);
    tracing::info!(worker_id = reg.worker_id, learner = %cfg.learner_url, "registered");
    Ok(Registration {
        worker_id: reg.worker_id.into(),
        heartbeat_every: Duration::from_millis(reg.heartbeat_interval_ms.clamp(200, 30_000) as u64),
    })
}

/// Heartbeats on the side of a session. Dropping it stops them.
pub struct Heartbeats {
    task: JoinHandle<()>,
    /// Turns true when heartbeats fail; closed if the task is gone.
    failed: watch::Receiver<bool>,
}

impl Heartbeats {
    /// Connects and starts sending heartbeats for `me`.
    pub async fn spawn(
        cfg: &WorkerConfig,
        me: Registration,
        metrics: &WorkerMetrics,
    ) -> anyhow::Result<Self> {
        let (failed_tx, failed) = watch::channel(false);
        let mut client = connect(cfg).await?;
        let (worker_id, every, t) = (me.worker_id, me.heartbeat_every, cfg.rpc_timeout);
        let metrics = metrics.clone();
        let task = tokio::spawn(async move {
            let mut fails = 0;
            loop {
                tokio::time::sleep(every).await;
                match client
                    .heartbeat(req(pb::HeartbeatRequest { worker_id: worker_id.get() }, t))
                    .await
                {
                    Ok(_) => {
                        metrics.common.rpc("Heartbeat", Code::Ok);
                        fails = 0
                    }
                    Err(s) => {
                        metrics.common.rpc("Heartbeat", s.code());
                        fails += 1;
                        if s.code() == Code::NotFound || fails >= 3 {
                            let _ = failed_tx.send(true);
                            return;
                        }
                    }
                }
            }
        });
        Ok(Self { task, failed })
    }

    /// Ready once heartbeats have failed (or their task is gone). Cancel-safe: for `select!`.
    pub async fn failed(&mut self) {
        let _ = self.failed.changed().await;
    }
}

impl Drop for Heartbeats {
    fn drop(&mut self) {
        self.task.abort();
    }
}
