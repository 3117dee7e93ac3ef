//! What a session works on: the learner's assignment and the job it names.
//!
//! Owns: [`next_assignment`] (`GetAssignment` until a training job comes, running the
//! evaluation cells handed out meanwhile, waiting the learner's `retry_after_ms` clamped to
//! 0.1–10 s while there is nothing) and [`load_job`] (the job's config and its scenarios' maps).
//! Failed heartbeats end the wait. Must not: fetch the training job's policies or start its
//! rollout (the session does that next), or keep anything past the session.

use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use sf_job::{Assignment, JobConfig, WorkerId};
use sf_proto::pb;
use sf_sim::Map;
use tonic::Code;

use crate::client::{req, status_err, Client, WorkerConfig};
use crate::evalcell::Cells;
use crate::membership::Heartbeats;
use crate::metrics::WorkerMetrics;

/// A training job's assignment; evaluation cells handed out before it are run on the way.
pub async fn next_assignment(
    client: &mut Client,
    cfg: &WorkerConfig,
    worker_id: WorkerId,
    heartbeats: &mut Heartbeats,
    metrics: &WorkerMetrics,
) -> anyhow::Result<Assignment> {
    let t = cfg.rpc_timeout;
    let mut cells = Cells::new(cfg);
    loop {
        let r = client
            .get_assignment(req(pb::GetAssignmentRequest { worker_id: worker_id.get() }, t))
            .await
            .map_err(|s| status_err("GetAssignment", s, metrics))?
            .into_inner();
        metrics.common.rpc("GetAssignment", Code::Ok);
        if let (true, Some(a)) = (r.has_assignment, r.assignment) {
            return sf_proto::assignment_from_wire(&a).context("assignment from the learner");
        }
        if let (true, Some(w)) = (r.has_assignment, r.eval) {
            let work =
                sf_proto::eval_work_from_wire(&w).context("evaluation cell from the learner")?;
            tokio::select! {
                r = cells.run(client, worker_id, work, t, metrics) => r?,
                _ = heartbeats.failed() => anyhow::bail!("heartbeats failed while running an evaluation cell"),
            }
            continue;
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_millis(r.retry_after_ms.clamp(100, 10_000) as u64)) => {}
            _ = heartbeats.failed() => anyhow::bail!("heartbeats failed while waiting for an assignment"),
        }
    }
}

/// The assignment's job config and its scenarios' maps in config order (index = map id).
pub fn load_job(
    cfg: &WorkerConfig,
    worker_id: WorkerId,
    asg: &Assignment,
) -> anyhow::Result<(JobConfig, Vec<Arc<Map>>)> {
    let job = JobConfig::from_toml(&asg.config_toml).context("job config in the assignment")?;
    tracing::info!(worker_id = worker_id.get(), job_id = asg.job_id.get(), scenarios = ?job.env.scenarios, policy_version = asg.policy_version.get(), warmup = asg.warmup, "assignment");
    let maps = job
        .env
        .scenarios
        .iter()
        .map(|s| {
            Map::load(&cfg.scenarios_dir.join(format!("{s}.json")))
                .map(Arc::new)
                .with_context(|| format!("scenario `{s}`"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok((job, maps))
}
