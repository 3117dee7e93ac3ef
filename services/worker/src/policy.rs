//! Policy weights from the learner (`GetPolicy`), Acme's variable client: the frozen policies an
//! assignment acts with, fetched once, and the job's own policy, followed as acknowledgements
//! name newer versions.
//!
//! Owns: [`FrozenPolicies::fetch`] and [`PolicyClient`] (the version this worker holds, and
//! when to fetch the latest). Weights stay bytes here. Must not: build networks or run tensor
//! code (the rollout thread does), or keep weights past the session.

use std::time::Duration;

use anyhow::Context;
use sf_job::{Frozen, FrozenRole, JobConfig, JobId, PolicyRequest, PolicyVersion, WorkerId};
use sf_proto::pb;
use tonic::Code;

use crate::client::{req, status_err, Client};
use crate::metrics::WorkerMetrics;
use crate::rollout::Rollout;

/// The frozen policies an assignment acts with (background flow, ego, adversary): role, config
/// and final weights.
pub struct FrozenPolicies(Vec<(FrozenRole, JobConfig, Vec<u8>)>);

impl FrozenPolicies {
    /// Each frozen job's config, then its final weights, in the assignment's order.
    pub async fn fetch(
        client: &Client,
        worker_id: WorkerId,
        frozen: &[Frozen],
        t: Duration,
        metrics: &WorkerMetrics,
    ) -> anyhow::Result<Self> {
        let mut policies = Vec::with_capacity(frozen.len());
        for f in frozen {
            let fj = JobConfig::from_toml(&f.config_toml)
                .with_context(|| format!("config of frozen job {}", f.job_id))?;
            let mut c = client.clone();
            let p = c
                .get_policy(req(sf_proto::get_policy_to_wire(f.job_id, PolicyRequest::Latest), t))
                .await
                .map_err(|s| status_err("GetPolicy", s, metrics))?
                .into_inner();
            metrics.common.rpc("GetPolicy", Code::Ok);
            tracing::info!(worker_id = worker_id.get(), frozen_job = f.job_id.get(), role = ?f.role, version = p.version, "frozen policy");
            policies.push((f.role, fj, p.weights));
        }
        Ok(Self(policies))
    }

    pub fn into_vec(self) -> Vec<(FrozenRole, JobConfig, Vec<u8>)> {
        self.0
    }
}

/// The training job's own policy: the version this worker holds and the latest weights.
pub struct PolicyClient<'a> {
    client: Client,
    job_id: JobId,
    /// The version last fetched after an acknowledgement (at first the assignment's).
    held_version: PolicyVersion,
    rpc_timeout: Duration,
    metrics: &'a WorkerMetrics,
}

impl<'a> PolicyClient<'a> {
    pub fn new(
        client: &Client,
        job_id: JobId,
        held_version: PolicyVersion,
        rpc_timeout: Duration,
        metrics: &'a WorkerMetrics,
    ) -> Self {
        Self { client: client.clone(), job_id, held_version, rpc_timeout, metrics }
    }

    pub fn job_id(&self) -> JobId {
        self.job_id
    }

    /// The latest weights `(version, bytes)`. Does not change the held version.
    pub async fn latest(&self) -> anyhow::Result<(PolicyVersion, Vec<u8>)> {
        let mut c = self.client.clone();
        let p = c
            .get_policy(req(
                sf_proto::get_policy_to_wire(self.job_id, PolicyRequest::Latest),
                self.rpc_timeout,
            ))
            .await
            .map_err(|s| status_err("GetPolicy", s, self.metrics))?
            .into_inner();
        self.metrics.common.rpc("GetPolicy", Code::Ok);
        self.metrics.policy_fetches.inc();
        Ok((PolicyVersion::from(p.version), p.weights))
    }

    /// After an acknowledgement: out of the warm-up, a newer version than the one held (or the
    /// first weights) is fetched and acts at once; otherwise the weights the rollout holds act.
    pub async fn follow(&mut self, ack: &pb::PushAck, rollout: &Rollout) -> anyhow::Result<()> {
        let warm = ack.warmup;
        let latest = PolicyVersion::from(ack.latest_policy_version);
        let need = !warm && (latest > self.held_version || !rollout.has_policy());
        if need {
            let (v, w) = self.latest().await?;
            self.held_version = v;
            rollout.act_with(v, w);
        } else if !warm {
            rollout.end_warmup();
        }
        Ok(())
    }
}
