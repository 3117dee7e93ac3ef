//! A rollout worker that keeps no training state.
//!
//! Owns: the worker's session loop ([`run`]): connect, register, take an assignment, fetch the
//! policy, stream transitions, follow new policy versions, and start over with bounded backoff
//! when the learner goes away or the job ends. `session` only composes the parts, one job each
//! (Acme's actor side): `membership` (`register`, `Heartbeats`), `assignment`
//! (`next_assignment`, `load_job`), `policy` (`FrozenPolicies`, `PolicyClient`: the variable
//! client), [`rollout`] (the environment loop on its own thread and its `TransitionWriter`, the
//! adder) and `stream` (`PushTransitions` and its acknowledgements); an evaluation job's cells
//! ([`evalcell`]), one per assignment. The toolbox every part uses stands below them: `client`
//! ([`WorkerConfig`], the client, `connect`, `req`, `status_err`) and [`metrics`]; nothing
//! imports from this file. Simulation and inference run on a dedicated rollout
//! thread or a blocking task (evaluation); the async side only moves bytes. Every unary call
//! has a deadline. What outlives one job: its config and name, metrics and its registration
//! (worker id, heartbeat interval), dropped after an error. Must not: keep a job, a policy or
//! transitions across sessions, or write to disk (everything comes from the learner).

mod assignment;
mod client;
pub mod cmd;
pub mod evalcell;
mod membership;
pub mod metrics;
mod policy;
pub mod rollout;
mod stream;

use std::time::Duration;

use sf_service::backoff::Backoff;
use tokio::sync::watch;

use crate::assignment::{load_job, next_assignment};
use crate::client::connect;
pub use crate::client::{WorkerConfig, DEFAULT_IN_FLIGHT_BATCHES};
use crate::membership::{register, Heartbeats, Registration};
pub use crate::metrics::WorkerMetrics;
use crate::policy::{FrozenPolicies, PolicyClient};
use crate::rollout::{Rollout, RolloutSpec};
use crate::stream::{stream, SessionEnd};

/// Runs sessions until `stop` turns true. Errors are logged and retried with backoff.
pub async fn run(
    cfg: WorkerConfig,
    metrics: WorkerMetrics,
    mut stop: watch::Receiver<bool>,
) -> anyhow::Result<()> {
    let mut backoff = Backoff::new(Duration::from_millis(200), cfg.max_backoff);
    // Registered id and heartbeat interval, kept from one job to the next (a new registration
    // per job would leave the learner a stale worker to time out); dropped after an error.
    let mut registration: Option<Registration> = None;
    loop {
        if *stop.borrow() {
            return Ok(());
        }
        metrics.sessions.inc();
        let r = tokio::select! {
            r = session(&cfg, &metrics, &mut registration) => r,
            _ = stop.changed() => Ok(SessionEnd::Stop),
        };
        match r {
            Ok(SessionEnd::Stop) => return Ok(()),
            Ok(SessionEnd::JobEnded) => backoff.reset(),
            Err(e) => {
                registration = None;
                let d = backoff.next_delay();
                tracing::warn!(error = %format!("{e:#}"), retry_ms = d.as_millis() as u64, "session ended");
                tokio::select! {
                    _ = tokio::time::sleep(d) => {}
                    _ = stop.changed() => return Ok(()),
                }
            }
        }
    }
}

/// One session: who this worker is, what to work on, the policies to act with, then the
/// transition stream until the job or the connection ends.
async fn session(
    cfg: &WorkerConfig,
    metrics: &WorkerMetrics,
    registration: &mut Option<Registration>,
) -> anyhow::Result<SessionEnd> {
    let mut client = connect(cfg).await?;
    let me = match *registration {
        Some(r) => r,
        None => *registration.insert(register(&mut client, cfg, metrics).await?),
    };
    let mut heartbeats = Heartbeats::spawn(cfg, me, metrics).await?;
    let asg = next_assignment(&mut client, cfg, me.worker_id, &mut heartbeats, metrics).await?;
    let (job, maps) = load_job(cfg, me.worker_id, &asg)?;
    let frozen =
        FrozenPolicies::fetch(&client, me.worker_id, &asg.frozen, cfg.rpc_timeout, metrics).await?;
    let mut policy =
        PolicyClient::new(&client, asg.job_id, asg.policy_version, cfg.rpc_timeout, metrics);
    // The policy acts from the first step after the warm-up, and in it too where the job's
    // warm-up is its own (continued) policy: without weights that warm-up could not start, and
    // no acknowledgement would ever come to fetch them.
    let acts_in_warmup = job.sac.warmup_policy == sf_job::config::WarmupPolicy::Policy;
    let first = if asg.warmup && !acts_in_warmup { None } else { Some(policy.latest().await?) };
    let spec =
        RolloutSpec::for_assignment(&asg, job, frozen.into_vec(), maps, me.worker_id, cfg.threads);
    let (rollout, batches) = Rollout::start(
        spec,
        asg.warmup,
        first,
        cfg.in_flight_batches,
        cfg.adaptive_window,
        metrics,
    )?;
    stream(&mut client, batches, &rollout, &mut policy, &mut heartbeats, metrics).await
}
