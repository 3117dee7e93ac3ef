//! The transition stream of a session: one `PushTransitions` call carrying the rollout
//! thread's batches, and its acknowledgements.
//!
//! Owns: [`stream`] and [`SessionEnd`], how a session that did not fail ended. Each
//! acknowledgement gives the rollout thread a credit and lets the [`PolicyClient`] follow the
//! learner's version. The session ends when the learner ends the
//! job (FAILED_PRECONDITION: the next session starts at once), the stream or the rollout thread
//! stops, or heartbeats fail. Must not: touch simulators or tensors (the rollout thread's), or
//! retry (the session loop in `lib.rs` does).

use sf_proto::pb;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

use crate::client::{status_err, Client};
use crate::membership::Heartbeats;
use crate::metrics::WorkerMetrics;
use crate::policy::PolicyClient;
use crate::rollout::Rollout;

/// Why a session ended.
#[derive(Debug)]
pub enum SessionEnd {
    /// The job stopped running: ask for a new assignment at once.
    JobEnded,
    /// Shutdown requested.
    Stop,
}

/// Streams `batches` and follows the acknowledgements until the session ends.
pub async fn stream(
    client: &mut Client,
    batches: mpsc::Receiver<pb::TransitionBatch>,
    rollout: &Rollout,
    policy: &mut PolicyClient<'_>,
    heartbeats: &mut Heartbeats,
    metrics: &WorkerMetrics,
) -> anyhow::Result<SessionEnd> {
    let mut acks = client
        .push_transitions(ReceiverStream::new(batches))
        .await
        .map_err(|s| status_err("PushTransitions", s, metrics))?
        .into_inner();
    loop {
        let ack = tokio::select! {
            a = acks.message() => a,
            _ = heartbeats.failed() => anyhow::bail!("heartbeats failed"),
        };
        let ack = match ack {
            Ok(Some(a)) => a,
            Ok(None) => {
                if rollout.is_finished() {
                    anyhow::bail!("the rollout thread stopped");
                }
                anyhow::bail!("the learner closed the transition stream")
            }
            Err(s) if s.code() == Code::FailedPrecondition => {
                metrics.common.rpc("PushTransitions", s.code());
                tracing::info!(job_id = policy.job_id().get(), reason = s.message(), "job ended");
                return Ok(SessionEnd::JobEnded);
            }
            Err(s) => return Err(status_err("PushTransitions", s, metrics)),
        };
        metrics.common.rpc("PushTransitions", Code::Ok);
        rollout.grant();
        metrics.in_flight_window.set(i64::from(rollout.window()));
        if let Some(e) = rollout.link_estimate() {
            metrics.link_min_rtt_seconds.set(e.min_rtt.as_secs_f64());
            metrics.link_acked_batches_per_second.set(e.acked_batches_per_s);
        }
        policy.follow(&ack, rollout).await?;
    }
}
