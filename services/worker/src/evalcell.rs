//! An evaluation job's cells on a worker: fetch the cell's policies, run its episodes
//! (`sf_rollout::evaluate::run_cell`, the code `socialflow eval` runs), push the results.
//!
//! Owns: [`Cells`], what one session keeps between cells — final policies by job (they never
//! change), the policies built per scenario, the maps and stored cases — and [`Cells::run`].
//! A cell that cannot run (its ego and flow do not fit, a case does not finish) is reported to
//! the learner, which fails the job; a problem of this worker (a missing scenario or case file,
//! an RPC failure) ends the session instead, so the cell goes to another worker. Must not: run
//! tensor code on the async runtime (cells run on a blocking task).

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use sf_job::eval::EvalWork;
use sf_job::{JobId, PolicyRequest, WorkerId};
use sf_proto::pb;
use sf_rollout::evaluate::{self, CellSize, Runners};
use tonic::Code;

use crate::client::{req, status_err, Client, WorkerConfig};
use crate::metrics::WorkerMetrics;

type Maps = BTreeMap<String, (Arc<sf_sim::Map>, sf_sim::CaseFile)>;

/// What a session keeps between evaluation cells.
pub struct Cells {
    scenarios_dir: std::path::PathBuf,
    cases_dir: std::path::PathBuf,
    weights: HashMap<JobId, Arc<Vec<u8>>>,
    /// Taken by the blocking task while a cell runs.
    state: Option<(Runners, Maps)>,
}

impl Cells {
    pub fn new(cfg: &WorkerConfig) -> Self {
        Self {
            scenarios_dir: cfg.scenarios_dir.clone(),
            cases_dir: cfg.cases_dir.clone(),
            weights: HashMap::new(),
            state: None,
        }
    }

    /// Runs one cell and pushes its episodes (or why it could not run).
    pub async fn run(
        &mut self,
        client: &mut Client,
        worker_id: WorkerId,
        w: EvalWork,
        t: Duration,
        metrics: &WorkerMetrics,
    ) -> anyhow::Result<()> {
        let started = Instant::now();
        let mut weights = Vec::with_capacity(w.policies.len());
        for p in &w.policies {
            if let std::collections::hash_map::Entry::Vacant(slot) = self.weights.entry(p.job_id) {
                let got = client
                    .get_policy(req(
                        sf_proto::get_policy_to_wire(p.job_id, PolicyRequest::Latest),
                        t,
                    ))
                    .await
                    .map_err(|s| status_err("GetPolicy", s, metrics))?
                    .into_inner();
                metrics.common.rpc("GetPolicy", Code::Ok);
                metrics.policy_fetches.inc();
                slot.insert(Arc::new(got.weights));
            }
            weights.push(Arc::clone(&self.weights[&p.job_id]));
        }
        let (mut runners, mut maps) = match self.state.take() {
            Some(s) => s,
            None => (
                Runners::new(
                    sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)
                        .map_err(|e| anyhow!("{e}"))?,
                ),
                Maps::new(),
            ),
        };
        if !maps.contains_key(&w.cell.scenario) {
            let (dir, cases) = (self.scenarios_dir.clone(), self.cases_dir.clone());
            let name = w.cell.scenario.clone();
            let loaded =
                tokio::task::spawn_blocking(move || evaluate::load_scenario(&dir, &cases, &name))
                    .await
                    .context("scenario loading task")?
                    .map_err(|e| anyhow!("{e}"))?;
            maps.insert(w.cell.scenario.clone(), loaded);
        }
        let work = w.clone();
        let (state, result) = tokio::task::spawn_blocking(move || {
            let r = (|| {
                let (flow, ego) = evaluate::from_frozen(&work.policies, &weights)?;
                let ego = evaluate::EgoDef::of_work(ego, work.scripted_ego)?;
                let (map, cases) = maps
                    .get(&work.cell.scenario)
                    .ok_or_else(|| evaluate::EvalError::Misfit("scenario not loaded".into()))?;
                let size =
                    CellSize { cases: work.cases, seeds: work.seeds, envs: work.envs as usize };
                evaluate::run_cell(&work.cell, size, map, cases, &flow, ego.as_ref(), &mut runners)
            })();
            ((runners, maps), r)
        })
        .await
        .context("evaluation task")?;
        self.state = Some(state);
        let (episodes, error) = match result {
            Ok(eps) => {
                (eps.iter().map(sf_proto::eval_episode_to_wire).collect::<Vec<_>>(), String::new())
            }
            Err(e) => {
                tracing::error!(job_id = w.job_id.get(), cell = %w.cell.key(), error = %e, "evaluation cell could not run");
                (Vec::new(), e.to_string())
            }
        };
        let n = episodes.len() as u64;
        let msg = pb::EvalResults {
            job_id: w.job_id.get(),
            worker_id: worker_id.get(),
            cell_id: w.cell_id.get(),
            episodes,
            error,
        };
        let ack = match client.push_eval_results(req(msg, t)).await {
            Ok(a) => a.into_inner(),
            // The job ended (finished by others, cancelled, failed): ask for the next assignment.
            Err(s) if s.code() == Code::FailedPrecondition => {
                metrics.common.rpc("PushEvalResults", s.code());
                tracing::info!(job_id = w.job_id.get(), reason = s.message(), "evaluation ended");
                return Ok(());
            }
            Err(s) => return Err(status_err("PushEvalResults", s, metrics)),
        };
        metrics.common.rpc("PushEvalResults", Code::Ok);
        metrics.eval_cells.inc();
        metrics.episodes.inc_by(n);
        tracing::info!(job_id = w.job_id.get(), cell = %w.cell.key(), episodes = n, stored = ack.stored, secs = started.elapsed().as_secs_f64(), "evaluation cell");
        Ok(())
    }
}
