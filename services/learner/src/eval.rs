//! The running evaluation job: an evaluation grid's cells shared by the workers.
//!
//! Owns: [`EvalJob`] — the grid's cells and the policies each needs, which cells are queued,
//! leased (to which worker) and stored, the job's `episodes.csv` (a cell appended whole when a
//! worker's results pass the checks) and its progress; resolving a grid's flow and ego names
//! to this learner's succeeded jobs ([`resolve_names`], [`resolve_policies`]). A lease ends when
//! the worker pushes the cell, asks for another, or is forgotten for missing heartbeats; its
//! cell goes back to the queue. A restarted learner resumes a RUNNING evaluation from the
//! cells its `episodes.csv` holds. Its directory: `config.toml` (pinned), `meta.json`,
//! `episodes.csv`, the GIFs. Data under a slot, like `job.rs`'s `ActiveJob`: the scheduler
//! starts and follows it, `experience.rs` leases its cells and stores their results. Must not:
//! run simulations (workers do; the GIFs are drawn by the scheduler on a blocking thread once
//! every cell is stored).

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use sf_job::config::JobKind;
use sf_job::eval::{Cell, EvalConfig, EvalEpisode, EvalWork, ScriptedEgo, ScriptedSeats};
use sf_job::{CellId, Frozen, FrozenRole, JobId, JobRecord, JobState, Progress, WorkerId};
use sf_report::episodes::{EpisodeRow, EpisodesWriter, Meta};
use sf_rollout::evaluate::{EgoDef, Resolved};
use tokio::sync::Notify;

use crate::error::LearnerError;
use crate::job::StopReason;
use crate::metrics::LearnerMetrics;
use sf_service::sync::lock;

/// Pins every flow and ego of `cfg` to a job id: the newest succeeded job of its name, or the
/// id it already names (which must have succeeded). Errors name the field.
pub fn resolve_names(cfg: &mut EvalConfig, jobs: &[JobRecord]) -> Result<(), LearnerError> {
    let pin = |field: &'static str, n: &mut sf_job::eval::Named| -> Result<(), LearnerError> {
        let bad =
            |reason: String| LearnerError::BadEvalConfig { field, name: n.name.clone(), reason };
        if n.is_scripted() {
            n.job_id = None;
            return Ok(());
        }
        let found = match n.job_id {
            Some(id) => jobs
                .iter()
                .find(|r| r.id == id)
                .ok_or_else(|| bad(format!("job {id} does not exist")))?,
            None => jobs
                .iter()
                .filter(|r| r.name == n.job && r.state == JobState::Succeeded)
                .max_by_key(|r| r.id)
                .ok_or_else(|| {
                    bad(format!("this learner has no succeeded job named `{}`", n.job))
                })?,
        };
        if found.state != JobState::Succeeded {
            return Err(bad(format!(
                "job {} is {}, not succeeded",
                found.id,
                found.state.as_str()
            )));
        }
        n.job_id = Some(found.id);
        Ok(())
    };
    for f in cfg.flows.iter_mut() {
        pin("flows.job", f)?;
    }
    for e in cfg.egos.iter_mut() {
        pin("egos.job", e)?;
    }
    Ok(())
}

/// A stored job's parsed config, as the learner keeps it ([`crate::jobs::Jobs::spec`]).
pub type Specs<'a> = &'a dyn Fn(&JobRecord) -> Result<Arc<sf_job::JobSpec>, LearnerError>;

/// Per flow its frozen policies, per ego its frozen policy, and the grid resolved for checks.
pub type GridPolicies = (BTreeMap<String, Vec<Frozen>>, BTreeMap<String, Frozen>, Resolved);

/// The policies behind a grid whose names are pinned ([`resolve_names`]): per flow the frozen
/// policies a worker gets (none for IDM; background and adversary for SocialCommAdv, as a
/// training job's background gets them: [`crate::deps::flow_frozen`]), per ego its frozen policy, and
/// the same as [`Resolved`] for checks and GIFs (with weights if `weights`: file IO, call off
/// the runtime). `spec` gives a stored job's parsed config ([`crate::jobs::Jobs::spec`]), so nothing
/// here parses a job's text again. Refuses an ego that is not an ego job and a flow that is.
pub fn resolve_policies(
    cfg: &EvalConfig,
    jobs: &[JobRecord],
    weights: bool,
    spec: Specs<'_>,
) -> Result<GridPolicies, LearnerError> {
    let find = |id: JobId| {
        jobs.iter()
            .find(|r| r.id == id && r.state == JobState::Succeeded)
            .ok_or(LearnerError::NotSucceeded { job_id: id })
    };
    // A frozen policy's config: its job's spec, parsed when the job was stored.
    let train_cfg = |rec: &JobRecord| -> Result<sf_job::JobConfig, LearnerError> {
        spec(rec)?.train().cloned().ok_or_else(|| LearnerError::BadEvalConfig {
            field: "job",
            name: rec.name.clone(),
            reason: format!("job {} is an evaluation, not a policy", rec.id),
        })
    };
    let from_frozen = |fz: &[Frozen], w: &[Arc<Vec<u8>>]| {
        sf_rollout::evaluate::from_frozen_with(fz, w, |f| train_cfg(find(f.job_id)?))
    };
    let pinned = |n: &sf_job::eval::Named| -> Result<&JobRecord, LearnerError> {
        let id = n.job_id.ok_or_else(|| LearnerError::NotPinned { name: n.name.clone() })?;
        find(id).map_err(|e| LearnerError::Grid { name: n.name.clone(), source: Box::new(e) })
    };
    // Each policy's final weights, or nothing when only the configs are checked.
    let load = |fz: &[Frozen]| -> Result<Vec<Arc<Vec<u8>>>, LearnerError> {
        fz.iter()
            .map(|f| {
                if !weights {
                    return Ok(Arc::new(Vec::new()));
                }
                crate::artifacts::read_final(
                    Path::new(&find(f.job_id)?.artifact_dir),
                    f.job_id,
                    "policy.bpk",
                )
                .map(Arc::new)
            })
            .collect()
    };
    let mut grid = Resolved::default();
    let mut flows = BTreeMap::new();
    for f in &cfg.flows {
        let fz = if f.is_idm() {
            Vec::new()
        } else {
            let rec = pinned(f)?;
            crate::deps::flow_frozen(rec, &train_cfg(rec)?, |id| find(id).cloned())?
        };
        let (flow, _) = from_frozen(&fz, &load(&fz)?)?;
        if flow.kind() == Some(JobKind::Ego) {
            return Err(LearnerError::BadEvalConfig {
                field: "flows.job",
                name: f.name.clone(),
                reason: format!("job {} is an ego job, not a flow", fz[0].job_id),
            });
        }
        flows.insert(f.name.clone(), fz);
        grid.flows.insert(f.name.clone(), flow);
    }
    let mut egos = BTreeMap::new();
    for e in &cfg.egos {
        // A scripted driver: no policy travels, the work item says so
        // (`EvalWork::scripted_ego`).
        if let Some(s) = e.scripted() {
            grid.egos.insert(e.name.clone(), s.into());
            continue;
        }
        let r = pinned(e)?;
        let fz = Frozen::new(FrozenRole::Ego, r.id, r.config_toml.clone());
        let (_, ego) = from_frozen(std::slice::from_ref(&fz), &load(std::slice::from_ref(&fz))?)?;
        let p = ego.ok_or_else(|| LearnerError::NoEgoPolicy { name: e.name.clone() })?;
        if p.cfg.kind != JobKind::Ego {
            return Err(LearnerError::BadEvalConfig {
                field: "egos.job",
                name: e.name.clone(),
                reason: format!("job {} is a {} job, not an ego policy", r.id, p.cfg.kind.as_str()),
            });
        }
        egos.insert(e.name.clone(), fz);
        grid.egos.insert(e.name.clone(), EgoDef::Learned(p));
    }
    Ok((flows, egos, grid))
}

/// Takes the first queued cell `eligible` says the asking worker can run; the others keep
/// their places.
fn take_first(queued: &mut VecDeque<usize>, eligible: impl Fn(usize) -> bool) -> Option<usize> {
    let k = queued.iter().position(|&c| eligible(c))?;
    queued.remove(k)
}

/// Adds the rows' success, safety and speed to the running sums (in that order).
fn add_scores(sums: &mut [f64; 3], rows: &[EpisodeRow]) {
    for r in rows {
        sums[0] += r.ep.scores.success as f64;
        sums[1] += r.ep.scores.safety as f64;
        sums[2] += r.ep.scores.speed as f64;
    }
}

struct State {
    queued: VecDeque<usize>,
    /// Cell -> (worker, since).
    leased: HashMap<usize, (WorkerId, Instant)>,
    stored: Vec<bool>,
    episodes: u64,
    sums: [f64; 3],
    writer: EpisodesWriter,
    /// Set by a worker that could not run a cell.
    failed: Option<String>,
}

impl State {
    fn stored_cells(&self) -> usize {
        self.stored.iter().filter(|s| **s).count()
    }
}

/// An evaluation job while it runs.
pub struct EvalJob {
    pub id: JobId,
    pub cfg: EvalConfig,
    pub dir: PathBuf,
    cells: Vec<Cell>,
    /// Per cell: the policies a worker acts with.
    work: Vec<Vec<Frozen>>,
    /// For the GIFs at the end.
    pub grid: Resolved,
    state: Mutex<State>,
    stop: Mutex<Option<StopReason>>,
    /// Every cell stored, a cell failed, or a stop was requested.
    pub changed: Notify,
    started: Instant,
    wall_s_before: f64,
    metrics: LearnerMetrics,
}

impl EvalJob {
    /// Builds the job from its pinned config `cfg` (job `rec`'s), the learner's job records and
    /// the cells its `episodes.csv` already holds (a resumed job); writes `meta.json`. Blocking
    /// file IO.
    pub fn open(
        rec: &JobRecord,
        cfg: EvalConfig,
        jobs: &[JobRecord],
        spec: Specs<'_>,
        metrics: LearnerMetrics,
    ) -> Result<Self, LearnerError> {
        let (flows, egos, grid) = resolve_policies(&cfg, jobs, true, spec)?;
        let cells = cfg.cells();
        grid.check(&cells)?;
        let work = cells
            .iter()
            .map(|c| {
                let mut p = flows.get(&c.flow).cloned().unwrap_or_default();
                if let Some(e) = egos.get(&c.ego) {
                    p.push(e.clone());
                }
                p
            })
            .collect();
        let dir = PathBuf::from(&rec.artifact_dir);
        crate::artifacts::create_dir(&dir)?;
        let meta = serde_json::to_string_pretty(&Meta::of(&cfg))?;
        crate::artifacts::write(&dir.join("meta.json"), meta.as_bytes())?;
        // The grid as it runs (names pinned to job ids), beside its results.
        crate::artifacts::write(&dir.join("config.toml"), rec.config_toml.as_bytes())?;
        let path = dir.join("episodes.csv");
        let rows = sf_report::episodes::read_episodes(&path)?;
        let have: BTreeSet<Cell> = rows.iter().map(EpisodeRow::cell).collect();
        let stored: Vec<bool> = cells.iter().map(|c| have.contains(c)).collect();
        let mut sums = [0.0; 3];
        add_scores(&mut sums, &rows);
        let queued = (0..cells.len()).filter(|&i| !stored[i]).collect::<VecDeque<_>>();
        let writer = EpisodesWriter::open(&path)?;
        metrics.eval_cells_pending.set(queued.len() as i64);
        let state = State {
            queued,
            leased: HashMap::new(),
            stored,
            episodes: rows.len() as u64,
            sums,
            writer,
            failed: None,
        };
        Ok(Self {
            id: rec.id,
            cfg,
            dir,
            cells,
            work,
            grid,
            state: Mutex::new(state),
            stop: Mutex::new(None),
            changed: Notify::new(),
            started: Instant::now(),
            wall_s_before: rec.progress.learning.wall_s,
            metrics,
        })
    }

    pub fn cells(&self) -> usize {
        self.cells.len()
    }

    /// The episodes of every cell together (each cell's own cases x seeds).
    fn target_episodes(&self) -> u64 {
        self.cells.iter().map(|c| self.cfg.episodes_of(c)).sum()
    }

    pub fn progress(&self) -> Progress {
        let s = lock(&self.state);
        let n = s.episodes.max(1) as f64;
        Progress {
            learning: sf_job::Learning {
                env_steps: s.episodes,
                episodes: s.episodes,
                scores: sf_job::Scores {
                    success: (s.sums[0] / n) as f32,
                    safety: (s.sums[1] / n) as f32,
                    speed: (s.sums[2] / n) as f32,
                },
                wall_s: self.wall_s_before + self.started.elapsed().as_secs_f64(),
                ..Default::default()
            },
            target_env_steps: self.target_episodes(),
            ..Progress::default()
        }
    }

    /// Every cell is stored.
    pub fn is_complete(&self) -> bool {
        let s = lock(&self.state);
        s.stored_cells() == self.cells.len()
    }

    pub fn failure(&self) -> Option<String> {
        lock(&self.state).failed.clone()
    }

    pub fn request_stop(&self, why: StopReason) {
        *lock(&self.stop) = Some(why);
        self.changed.notify_one();
    }

    pub fn stop_reason(&self) -> Option<StopReason> {
        *lock(&self.stop)
    }

    /// The scripted driver in cell `c`'s ego seat, if any.
    fn scripted_ego(&self, c: usize) -> Option<ScriptedEgo> {
        self.cfg.ego(&self.cells[c].ego).and_then(sf_job::eval::Named::scripted)
    }

    /// The next queued cell for `worker` (not one with a scripted ego it does not seat).
    /// Leases of workers not in `live` (forgotten for missing heartbeats) and the worker's own
    /// earlier lease (it asks again, so it gave that cell up) go back to the queue first.
    /// `None`: nothing queued now for this worker (cells may still be leased to others).
    pub fn lease(
        &self,
        worker: WorkerId,
        live: &BTreeSet<WorkerId>,
        seats: ScriptedSeats,
    ) -> Option<EvalWork> {
        if self.stop_reason().is_some() {
            return None;
        }
        let mut s = lock(&self.state);
        if s.failed.is_some() {
            return None;
        }
        let gone: Vec<usize> = s
            .leased
            .iter()
            .filter(|(_, (w, _))| *w == worker || !live.contains(w))
            .map(|(c, _)| *c)
            .collect();
        for c in gone {
            if let Some((w, since)) = s.leased.remove(&c) {
                tracing::info!(job_id = self.id.get(), cell = %self.cells[c].key(), worker_id = w.get(), leased_s = since.elapsed().as_secs(), "cell returned to the queue");
                if w != worker {
                    self.metrics.eval_cells_reassigned.inc();
                }
                s.queued.push_front(c);
            }
        }
        let c = take_first(&mut s.queued, |c| seats.runs(self.scripted_ego(c)))?;
        s.leased.insert(c, (worker, Instant::now()));
        let (cell, scripted_ego) = (self.cells[c].clone(), self.scripted_ego(c));
        let (cases, seeds) = self.cfg.size_of(&cell);
        Some(EvalWork {
            job_id: self.id,
            cell_id: CellId::of_index(c),
            cell,
            cases,
            seeds,
            envs: self.cfg.envs as u32,
            policies: self.work[c].clone(),
            scripted_ego,
        })
    }

    /// Stores a worker's results for cell `cell_id` (blocking file IO). `Ok(false)`: the cell
    /// was already stored. The episodes must be exactly one per stored case and seed of the
    /// cell's size ([`EvalConfig::size_of`]); nothing is written otherwise.
    pub fn store(
        &self,
        worker: WorkerId,
        cell_id: CellId,
        episodes: &[EvalEpisode],
        error: &str,
    ) -> Result<bool, LearnerError> {
        let c = cell_id
            .index()
            .filter(|&c| c < self.cells.len())
            .ok_or(LearnerError::NoCell { job_id: self.id, cell_id })?;
        let cell = &self.cells[c];
        let mut s = lock(&self.state);
        if s.stored[c] {
            return Ok(false);
        }
        if !error.is_empty() {
            let failed = LearnerError::CellFailed { cell: cell.key(), worker, error: error.into() };
            s.failed = Some(failed.to_string());
            drop(s);
            self.changed.notify_one();
            return Err(failed);
        }
        let (want, n_seeds) = (self.cfg.episodes_of(cell) as usize, self.cfg.size_of(cell).1);
        let seeds: BTreeSet<(u32, u32)> = episodes.iter().map(|e| (e.case, e.seed)).collect();
        if episodes.len() != want
            || seeds.len() != want
            || episodes.iter().any(|e| e.seed >= n_seeds)
        {
            let reason = format!("{} episodes, expected {want} distinct (case, seed) pairs with seeds below {n_seeds}", episodes.len());
            return Err(LearnerError::BadCellResults { cell_id, reason });
        }
        if let Some(bad) = episodes.iter().find_map(|e| e.validate().err()) {
            return Err(LearnerError::BadCellResults { cell_id, reason: bad.to_string() });
        }
        let rows: Vec<EpisodeRow> = episodes.iter().map(|e| EpisodeRow::new(cell, e)).collect();
        s.writer.append(&rows)?;
        s.stored[c] = true;
        s.leased.remove(&c);
        s.episodes += rows.len() as u64;
        add_scores(&mut s.sums, &rows);
        // A cell that went back to the queue (its worker looked dead) and is now stored.
        s.queued.retain(|&q| q != c);
        self.metrics.eval_episodes.inc_by(rows.len() as u64);
        let stored = s.stored_cells();
        self.metrics.eval_cells_pending.set((self.cells.len() - stored) as i64);
        let done = stored == self.cells.len();
        drop(s);
        tracing::debug!(job_id = self.id.get(), cell = %cell.key(), worker_id = worker.get(), "cell stored");
        if done {
            self.changed.notify_one();
        }
        Ok(true)
    }
}

/// Loads the map and stored cases of every scenario the grid runs in (blocking file IO); each
/// cell's cases must be stored ([`EvalConfig::check_stored_cases`]).
pub fn load_maps(
    cfg: &EvalConfig,
    scenarios_dir: &Path,
    cases_dir: &Path,
) -> Result<BTreeMap<String, (Arc<sf_sim::Map>, sf_sim::CaseFile)>, LearnerError> {
    let mut maps = BTreeMap::new();
    for s in cfg.all_scenarios() {
        let (map, cases) = sf_rollout::evaluate::load_scenario(scenarios_dir, cases_dir, &s)?;
        maps.insert(s, (map, cases));
    }
    cfg.check_stored_cases(|s| {
        maps.get(s).map_or(0, |(_, c): &(_, sf_sim::CaseFile)| c.cases.len())
    })?;
    Ok(maps)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A worker that cannot run IDM-ego cells skips them and they stay queued, in order, for
    /// one that can.
    #[test]
    fn idm_ego_cells_wait_for_a_worker_that_runs_them() {
        let idm = |c: usize| c == 0 || c == 2;
        let mut q: VecDeque<usize> = [0, 1, 2, 3].into();
        assert_eq!(take_first(&mut q, |c| !idm(c)), Some(1));
        assert_eq!(take_first(&mut q, |c| !idm(c)), Some(3));
        assert_eq!(take_first(&mut q, |c| !idm(c)), None, "only IDM-ego cells are left");
        assert_eq!(q, VecDeque::from([0, 2]));
        assert_eq!(take_first(&mut q, |_| true), Some(0), "a capable worker takes them in order");
    }
}
