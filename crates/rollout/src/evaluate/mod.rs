//! Running one cell of an evaluation grid: `cases x seeds` episodes of stored cases with the
//! cell's ego and flow, in batched simulators.
//!
//! Owns: the per-scenario policy cache ([`Runners`]), a cell's simulator settings and actors,
//! [`run_cell`], the grid's flows and egos ([`Resolved`]); what acts in a cell ([`Policy`],
//! [`FlowDef`], [`EgoDef`], [`check_cell`]) is in `policies`, the side-by-side GIF of one case
//! ([`render_gif`]) in `gif`. `socialflow eval`
//! (embedded) and the worker (an evaluation job's cells) both call these, so the same cell
//! gives the same numbers wherever it runs; a training job's validation runs its generated
//! cases through the same settings ([`run_cases`]). Must not: find jobs (callers hand over configs and
//! weights) or write results.
//!
//! Actions: ego policies act with their mean action (the IDM driver in the ego's seat with
//! the zero residual, so exactly as IDM drives); learned flows and the adversary sample, each
//! episode from its own draws (keyed by seed, case, step, agent and role), so an episode's
//! draws do not depend on `envs` or the other cases (since 2026-12-07; before, one stream per
//! seed ran through the batch). Learned policies' batched inference still rounds the last bits
//! of an action by batch size, so their episodes agree across `envs` in outcome, not bit for bit.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use sf_job::config::JobKind;
use sf_job::eval::{Cell, EvalEpisode};
use sf_job::{JobId, PolicyVersion, SvoGaussian};
use sf_sim::case::CaseFile;
use sf_sim::env::Controller;
use sf_sim::obs::MapSegments;
use sf_sim::vec_env::{EpisodeSpec, VecEnv};
use sf_sim::{Map, Mode, SimConfig};

use crate::drive::{self, Actor, Drivers};
use crate::inference::PolicyRunner;
use crate::setup;

mod gif;
pub mod mine;
mod policies;
pub mod view;

pub use gif::render_gif;
pub use policies::{check_cell, from_frozen, from_frozen_with, EgoDef, FlowDef, Policy};

/// Why an evaluation (or a policy's loading) could not go on. Messages name the file, job,
/// cell or field.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A file could not be read or created.
    #[error("{action} {}: {source}", path.display())]
    Io { action: &'static str, path: std::path::PathBuf, source: std::io::Error },
    /// A scenario's map does not load.
    #[error("scenario `{name}`: {source}")]
    Scenario { name: String, source: sf_sim::map::MapError },
    /// A scenario's stored cases do not load or do not fit its map.
    #[error("cases of `{name}` ({}): {source}", path.display())]
    Cases { name: String, path: std::path::PathBuf, source: sf_sim::case::CaseError },
    /// A finished job's `config.toml` does not parse or validate.
    #[error("{}: {source}", path.display())]
    JobFile { path: std::path::PathBuf, source: sf_job::ConfigError },
    /// A frozen policy's config text does not parse or validate.
    #[error("config of job {job_id}: {source}")]
    FrozenConfig { job_id: JobId, source: sf_job::ConfigError },
    /// A CoPO job's `coordinator.json` does not load.
    #[error(transparent)]
    Coordinator(#[from] crate::coordinator::CoordinatorError),
    /// A job's config is valid but lacks what evaluating it needs.
    #[error("{0}")]
    Invalid(String),
    /// What was asked for does not fit together (ego and flow, cells, sizes, names).
    #[error("{0}")]
    Misfit(String),
    /// A policy's weights do not load into its network.
    #[error("loading the policy of {key}: {source}")]
    Weights { key: String, source: sf_nn::weights::WeightsError },
    /// The episodes of a cell do not fit its simulators.
    #[error(transparent)]
    Episodes(#[from] sf_sim::vec_env::VecEnvError),
    /// Drawing a frame or writing the GIF failed.
    #[error(transparent)]
    Render(#[from] sf_sim::render::RenderError),
    /// A grid's GIF could not be rendered.
    #[error("rendering {}: {source}", path.display())]
    Gif { path: std::path::PathBuf, source: Box<EvalError> },
    /// Simulating or drawing failed.
    #[error("{0}")]
    Run(String),
}

fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> EvalError + 'a {
    move |source| EvalError::Io { action, path: path.to_path_buf(), source }
}

/// A scenario's map (`<scenarios_dir>/<name>.json`) and its stored evaluation cases
/// (`<cases_dir>/<name>.v<CASES_VERSION>.json`).
pub fn load_scenario(
    scenarios_dir: &Path,
    cases_dir: &Path,
    name: &str,
) -> Result<(Arc<Map>, CaseFile), EvalError> {
    let map = Map::load(&scenarios_dir.join(format!("{name}.json")))
        .map_err(|source| EvalError::Scenario { name: name.to_string(), source })?;
    let path = cases_dir.join(format!("{name}.v{}.json", sf_sim::case::CASES_VERSION));
    let cases = CaseFile::load(&path, &map).map_err(|source| EvalError::Cases {
        name: name.to_string(),
        path: path.clone(),
        source,
    })?;
    Ok((Arc::new(map), cases))
}

/// Rows per inference call of every policy evaluation runs ([`PolicyRunner::with_fixed_width`]):
/// a stored episode's actions, and so its outcome, are then the same at any `envs`, thread or
/// worker count. Changing it changes every evaluated episode with a learned policy in its last
/// bits (the cost of widths 8-64 against one call per step: `docs/usage.md`).
pub const EVAL_INFERENCE_ROWS: usize = 64;

/// Policies built for one scenario, loaded once and reused by every cell.
pub struct Runners {
    device: sf_nn::device::Device,
    segments: BTreeMap<String, Arc<MapSegments>>,
    cache: BTreeMap<(String, String), Arc<PolicyRunner>>,
    inference_rows: Option<usize>,
}

impl Runners {
    /// Runners that infer in calls of [`EVAL_INFERENCE_ROWS`] rows.
    pub fn new(device: sf_nn::device::Device) -> Self {
        Self {
            device,
            segments: BTreeMap::new(),
            cache: BTreeMap::new(),
            inference_rows: Some(EVAL_INFERENCE_ROWS),
        }
    }

    /// The same with another width, or `None` for one call per step (episodes then depend on
    /// the batch width; measurements of the width's cost compare the two).
    pub fn with_inference_rows(mut self, rows: Option<usize>) -> Self {
        self.inference_rows = rows;
        self.cache.clear();
        self
    }

    fn segments(&mut self, map: &Map) -> Arc<MapSegments> {
        Arc::clone(self.segments.entry(map.name.clone()).or_insert_with(|| {
            Arc::new(MapSegments::build(map, SimConfig::default().obs.segment_points))
        }))
    }

    /// The runner of `p` on `map` (built once, then cached).
    pub fn get(
        &mut self,
        p: &Policy,
        map: &Map,
        sim: &SimConfig,
    ) -> Result<Arc<PolicyRunner>, EvalError> {
        let key = (p.key.clone(), map.name.clone());
        if let Some(r) = self.cache.get(&key) {
            return Ok(Arc::clone(r));
        }
        let segs = self.segments(map);
        let own = p.resolved();
        let r = PolicyRunner::from_bytes(
            &own.net,
            &own.obs,
            sim.dt_s,
            &[segs.as_ref()],
            &p.weights,
            PolicyVersion::new(0),
            &self.device,
        )
        .map_err(|source| EvalError::Weights { key: p.key.clone(), source })?;
        let r = Arc::new(match self.inference_rows {
            Some(rows) => r.with_fixed_width(rows),
            None => r,
        });
        self.cache.insert(key, Arc::clone(&r));
        Ok(r)
    }

    /// Drops every cached runner of the policy `key` (one that will not act again, such as a
    /// training actor once validated).
    pub fn forget(&mut self, key: &str) {
        self.cache.retain(|(k, _), _| k != key);
    }
}

/// The policies acting in a cell.
struct Acting {
    ego: Seat,
    background: Option<Arc<PolicyRunner>>,
    adversary: Option<Arc<PolicyRunner>>,
    /// The noise-matched IDM flow's noise ([`FlowDef::IdmNoise`]), in place of a policy.
    noise: Option<f32>,
    /// CoPO Stage 2: the flow's SVOs are redrawn from its coordinator's Gaussian every step
    /// (not in cells that fix every SVO, the SVO sweep).
    svo_gaussian: Option<SvoGaussian>,
}

/// A cell's ego seat, built.
enum Seat {
    /// No ego: the flow drives every vehicle.
    Empty,
    Idm,
    IdmMobil,
    Policy(Arc<PolicyRunner>),
}

impl Acting {
    /// The ego acts with its mean (the IDM driver with the zero residual); flows and the
    /// adversary sample.
    fn drivers(&self) -> Drivers<'_> {
        let (background, adversary) = (
            self.background.as_deref().map(Actor::sampled).or(self.noise.map(noise_actor)),
            self.adversary.as_deref().map(Actor::sampled),
        );
        match (&self.ego, &self.background) {
            (Seat::Policy(e), _) => Drivers { alive: Actor::mean(e), background, adversary },
            (Seat::Idm, _) => Drivers { alive: IDM_EGO, background, adversary },
            (Seat::IdmMobil, _) => Drivers {
                alive: Actor::Mobil(sf_sim::mobil::MobilParams::default()),
                background,
                adversary,
            },
            (Seat::Empty, Some(f)) => {
                Drivers { alive: Actor::sampled(f), background: None, adversary: None }
            }
            // The noise-matched IDM flow drives every vehicle; the all-IDM flow's controllers
            // ignore the actions they are given.
            (Seat::Empty, None) => Drivers {
                alive: self.noise.map_or(Actor::Random { dim: 2 }, noise_actor),
                background: None,
                adversary: None,
            },
        }
    }
}

/// The noise-matched IDM flow's vehicles: the IDM driver plus noise of standard deviation `std`
/// on both components of the lateral residual.
fn noise_actor(std: f32) -> Actor<'static> {
    Actor::IdmNoise { std, action: sf_sim::DriveAction::IdmResidualLateral }
}

/// The IDM driver in the ego's seat: the demonstrator with no noise, as a zero residual.
const IDM_EGO: Actor<'static> =
    Actor::Demo { noise: 0.0, action: sf_sim::DriveAction::IdmAccelResidual };

/// The simulator a learned ego acts in among `flow`: its own observation settings (layout,
/// neighbour and segment caps), what the flow's observations carry, and the flow's probe.
pub fn ego_sim(flow: &FlowDef, ego: &Policy) -> SimConfig {
    let mut sim = setup::resolve(&ego.cfg, flow.background_config()).sim;
    flow.probe(&mut sim);
    sim
}

/// Simulator settings, mode and acting policies of a cell.
fn cell_setup(
    cell: &Cell,
    map: &Map,
    flow: &FlowDef,
    ego: Option<&EgoDef>,
    runners: &mut Runners,
) -> Result<(Arc<SimConfig>, Mode, Acting), EvalError> {
    check_cell(cell, flow, ego)?;
    let ego = match ego {
        // The scripted drivers observe in the flow's settings, as `eval-flow --ego idm` runs
        // the IDM driver.
        Some(scripted @ (EgoDef::Idm | EgoDef::IdmMobil)) => {
            let f = FlowSetup::new(flow, map, None, runners)?;
            let svo_gaussian = f.svo_gaussian.filter(|_| cell.svo_deg.is_none());
            return Ok((
                f.sim,
                f.mode,
                Acting {
                    ego: if matches!(scripted, EgoDef::Idm) { Seat::Idm } else { Seat::IdmMobil },
                    background: f.background,
                    adversary: f.adversary,
                    noise: flow.noise_std(),
                    svo_gaussian,
                },
            ));
        }
        Some(EgoDef::Learned(p)) => Some(p),
        None => None,
    };
    // The layout comes from whichever job acts; what the background's observations carry from the flow.
    let (sim, mode) = match (ego, flow) {
        (Some(e), FlowDef::Idm) => (ego_sim(flow, e), Mode::Ego { background: Controller::Idm }),
        (Some(e), FlowDef::Learned { .. } | FlowDef::IdmNoise { .. }) => {
            (ego_sim(flow, e), Mode::Ego { background: Controller::External })
        }
        (None, FlowDef::Idm) => (SimConfig::default(), Mode::AllIdm),
        // Every vehicle a learner driven by the IDM driver plus noise, as a Stage-1 flow's.
        (None, FlowDef::IdmNoise { .. }) => (SimConfig::default(), Mode::MultiAgent),
        (None, FlowDef::Learned { background, .. }) => {
            let mut sim = background.resolved().sim.clone();
            flow.probe(&mut sim);
            (sim, Mode::MultiAgent)
        }
    };
    let ego = ego.map(|e| runners.get(e, map, &sim)).transpose()?;
    let (background, adversary) = match flow {
        FlowDef::Idm | FlowDef::IdmNoise { .. } => (None, None),
        FlowDef::Learned { background, adversary, .. } => (
            Some(runners.get(background, map, &sim)?),
            adversary.as_ref().map(|a| runners.get(a, map, &sim)).transpose()?,
        ),
    };
    let svo_gaussian = match flow {
        FlowDef::Learned { background, .. } if cell.svo_deg.is_none() => {
            background.svo_gaussians.iter().find(|(s, _)| *s == cell.scenario).map(|(_, g)| *g)
        }
        _ => None,
    };
    let ego = ego.map_or(Seat::Empty, Seat::Policy);
    let noise = flow.noise_std();
    Ok((Arc::new(sim), mode, Acting { ego, background, adversary, noise, svo_gaussian }))
}

/// One stored episode of `cell` run alone as its cell runs it: the same settings and policies,
/// case `case_index` of `cases` with the cell's vehicles and SVO, and the draws of (seed, case)
/// (its tag). `on_state(env, sim)` sees the reset state and the state after every step. Returns
/// the simulator's metrics of the episode. GIFs and viewer pages are drawn from it, so they show
/// what the cell measures.
#[allow(clippy::too_many_arguments)]
fn replay_episode(
    cell: &Cell,
    map: &Arc<Map>,
    cases: &CaseFile,
    case_index: usize,
    seed: u32,
    flow: &FlowDef,
    ego: Option<&EgoDef>,
    runners: &mut Runners,
    on_state: impl FnMut(&sf_sim::Env, &SimConfig),
) -> Result<sf_sim::metrics::EpisodeMetrics, EvalError> {
    let (sim, mode, acting) = cell_setup(cell, map, flow, ego, runners)?;
    let episode = StoredEpisode {
        cases: &cases.cases,
        case_index,
        seed,
        vehicles: cell.vehicles,
        svo_deg: cell.svo_deg.map(|s| s as f32),
    };
    let setting = Setting { map, sim: &sim, mode, svo_gaussian: acting.svo_gaussian };
    replay_stored(&setting, &episode, &acting.drivers(), on_state)
}

/// Where stored episodes run: the map, the simulator settings the policies observe with, the
/// mode and CoPO's Gaussian for the scenario (what [`run_stored`] takes besides the episodes).
#[derive(Clone, Copy)]
pub struct Setting<'a> {
    pub map: &'a Arc<Map>,
    pub sim: &'a Arc<SimConfig>,
    pub mode: Mode,
    pub svo_gaussian: Option<SvoGaussian>,
}

/// One episode of [`Episodes`]: case `case_index` of `cases` at evaluation seed `seed`.
#[derive(Clone, Copy)]
pub struct StoredEpisode<'a> {
    pub cases: &'a [sf_sim::Case],
    pub case_index: usize,
    pub seed: u32,
    pub vehicles: Option<usize>,
    pub svo_deg: Option<f32>,
}

/// One stored episode run alone with `drivers`, with the draws [`run_stored`] gives it among
/// the others (its tag: seed and case index). `on_state(env, sim)` sees the reset state and the
/// state after every step. Returns the simulator's metrics of the episode.
pub fn replay_stored(
    at: &Setting,
    episode: &StoredEpisode,
    drivers: &Drivers,
    mut on_state: impl FnMut(&sf_sim::Env, &SimConfig),
) -> Result<sf_sim::metrics::EpisodeMetrics, EvalError> {
    let (map, sim, i) = (at.map, at.sim, episode.case_index);
    let case = episode.cases.get(i).ok_or_else(|| {
        EvalError::Misfit(format!(
            "case {i} is not stored for {} ({} cases)",
            map.name,
            episode.cases.len()
        ))
    })?;
    let spec = episode_spec(case, i, episode.seed, episode.vehicles, episode.svo_deg);
    let mut v = VecEnv::from_episodes(Arc::clone(map), Arc::clone(sim), at.mode, 1, vec![spec])?;
    v.set_svo_gaussian(at.svo_gaussian);
    on_state(v.env(0), sim);
    let done = drive::run_episodes(&mut v, drivers, |v, _| on_state(v.env(0), sim));
    done.into_iter()
        .next()
        .map(|(_, m)| m)
        .ok_or_else(|| EvalError::Run(format!("case {i} of {} did not finish", map.name)))
}

/// Stored case `case` (index `case_index` among its scenario's) at evaluation seed `seed`, as
/// every stored episode is set up: one place, so a replay gets the draws its row had.
fn episode_spec(
    case: &sf_sim::Case,
    case_index: usize,
    seed: u32,
    vehicles: Option<usize>,
    svo_deg: Option<f32>,
) -> EpisodeSpec {
    EpisodeSpec { case: case.clone(), vehicles, svo_deg, tag: episode_tag(seed, case_index) }
}

/// An episode's tag: its case index and seed (the simulator's per-episode draws, such as CoPO
/// Stage 2's SVOs, follow the tag, so each seed gets its own).
fn episode_tag(seed: u32, case: usize) -> u64 {
    (seed as u64) << 32 | case as u64
}

/// How many episodes a cell runs and how many are stepped together.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CellSize {
    /// The first N stored cases of the scenario.
    pub cases: u32,
    pub seeds: u32,
    pub envs: usize,
}

/// Runs one cell on `map` (the cell's scenario) over its stored `cases`; episodes in (seed,
/// case) order.
pub fn run_cell(
    cell: &Cell,
    size: CellSize,
    map: &Arc<Map>,
    cases: &CaseFile,
    flow: &FlowDef,
    ego: Option<&EgoDef>,
    runners: &mut Runners,
) -> Result<Vec<EvalEpisode>, EvalError> {
    if map.name != cell.scenario {
        return Err(EvalError::Misfit(format!(
            "cell of scenario `{}` given the map `{}`",
            cell.scenario, map.name
        )));
    }
    let n_cases = size.cases as usize;
    if n_cases > cases.cases.len() {
        return Err(EvalError::Misfit(format!(
            "eval config field `cases`: {} exceeds the {} stored cases of {}",
            n_cases,
            cases.cases.len(),
            cell.scenario
        )));
    }
    let (sim, mode, acting) = cell_setup(cell, map, flow, ego, runners)?;
    let episodes = Episodes {
        cases: &cases.cases[..n_cases],
        seeds: size.seeds,
        envs: size.envs,
        vehicles: cell.vehicles,
        svo_deg: cell.svo_deg.map(|s| s as f32),
    };
    run_stored(map, &sim, mode, acting.svo_gaussian, &episodes, &acting.drivers())
}

/// Runs `cases` chosen outside (a training job's generated validation cases, say) once per
/// seed, as a cell of `ego` (or the flow on its own) in `flow` would: the same settings, mode
/// and acting policies; episodes in (seed, case) order.
pub fn run_cases(
    map: &Arc<Map>,
    cases: &[sf_sim::Case],
    seeds: u32,
    envs: usize,
    flow: &FlowDef,
    ego: Option<&EgoDef>,
    runners: &mut Runners,
) -> Result<Vec<EvalEpisode>, EvalError> {
    let cell = Cell {
        experiment: String::new(),
        ego: ego.map(EgoDef::key).unwrap_or_default(),
        flow: flow.kind().map_or("idm", JobKind::as_str).to_string(),
        scenario: map.name.clone(),
        svo_deg: None,
        vehicles: None,
    };
    let (sim, mode, acting) = cell_setup(&cell, map, flow, ego, runners)?;
    run_stored(
        map,
        &sim,
        mode,
        acting.svo_gaussian,
        &Episodes { cases, seeds, envs, vehicles: None, svo_deg: None },
        &acting.drivers(),
    )
}

/// Stored episodes to run: every case once per seed.
pub struct Episodes<'a> {
    pub cases: &'a [sf_sim::Case],
    pub seeds: u32,
    /// Simulators stepped together.
    pub envs: usize,
    /// Vehicles per case (the case's own when `None`) and every agent's SVO (the case's own).
    pub vehicles: Option<usize>,
    pub svo_deg: Option<f32>,
}

/// Runs `episodes` with `drivers` and returns one row per episode in (seed, case) order. Every
/// random draw of an episode is its own (keyed by seed, case, step, agent and role:
/// [`drive::Draws::PerEpisode`]), so a row's draws do not depend on `envs` or the other cases. What a cell runs once its policies are chosen;
/// also the loop of an ego chosen outside ([`FlowSetup`]).
pub fn run_stored(
    map: &Arc<Map>,
    sim: &Arc<SimConfig>,
    mode: Mode,
    svo_gaussian: Option<SvoGaussian>,
    episodes: &Episodes,
    drivers: &Drivers,
) -> Result<Vec<EvalEpisode>, EvalError> {
    if episodes.envs == 0 || episodes.seeds == 0 {
        return Err(EvalError::Misfit("`envs` and `seeds` must be positive".into()));
    }
    let n_cases = episodes.cases.len();
    let mut rows = Vec::with_capacity(n_cases * episodes.seeds as usize);
    for seed in 0..episodes.seeds {
        let eps: Vec<EpisodeSpec> = episodes
            .cases
            .iter()
            .enumerate()
            .map(|(c, case)| episode_spec(case, c, seed, episodes.vehicles, episodes.svo_deg))
            .collect();
        let mut v =
            VecEnv::from_episodes(Arc::clone(map), Arc::clone(sim), mode, episodes.envs, eps)?;
        v.set_svo_gaussian(svo_gaussian);
        let mut done: Vec<Option<sf_sim::metrics::EpisodeMetrics>> = vec![None; n_cases];
        for (tag, m) in drive::run_episodes(&mut v, drivers, |_, _| {}) {
            done[(tag & 0xffff_ffff) as usize] = Some(m);
        }
        for (c, m) in done.into_iter().enumerate() {
            let m = m.ok_or_else(|| EvalError::Run(format!("case {c} did not finish")))?;
            rows.push(EvalEpisode {
                case: episodes.cases[c].id,
                seed,
                scores: m.scores,
                collision: m.collision,
                lane_change: Some(m.lane_change),
                road_closed: Some(m.road_closed),
            });
        }
    }
    Ok(rows)
}

/// A flow ready to drive around an ego chosen outside this crate (the IDM driver, or a Python
/// policy through [`Actor::External`]): the simulator settings the flow's policies observe
/// with, the mode, the flow's runners and CoPO's Gaussian for the scenario. The ego observes
/// in the flow's layout (a learned flow fixes it; the IDM flow takes `layout`).
pub struct FlowSetup {
    pub sim: Arc<SimConfig>,
    pub mode: Mode,
    background: Option<Arc<PolicyRunner>>,
    adversary: Option<Arc<PolicyRunner>>,
    /// The noise-matched IDM flow's noise.
    noise: Option<f32>,
    pub svo_gaussian: Option<SvoGaussian>,
}

impl FlowSetup {
    /// `layout`: the ego's wish; refused when a learned flow observes in another layout.
    pub fn new(
        flow: &FlowDef,
        map: &Map,
        layout: Option<sf_sim::Layout>,
        runners: &mut Runners,
    ) -> Result<Self, EvalError> {
        match flow {
            FlowDef::Idm | FlowDef::IdmNoise { .. } => {
                let mut sim = SimConfig::default();
                if let Some(l) = layout {
                    sim.obs.layout = l;
                }
                let noise = flow.noise_std();
                // The IDM flow's vehicles are the simulator's; the noisy one's act from outside.
                let background =
                    if noise.is_some() { Controller::External } else { Controller::Idm };
                Ok(Self {
                    sim: Arc::new(sim),
                    mode: Mode::Ego { background },
                    background: None,
                    adversary: None,
                    noise,
                    svo_gaussian: None,
                })
            }
            FlowDef::Learned { background, adversary, .. } => {
                let mut sim = setup::resolve(&background.cfg, Some(&background.cfg)).sim;
                flow.probe(&mut sim);
                if let Some(l) = layout.filter(|&l| l != sim.obs.layout) {
                    return Err(EvalError::Misfit(format!(
                        "the flow observes in the {} layout, not {}",
                        sim.obs.layout.as_str(),
                        l.as_str()
                    )));
                }
                let bg = runners.get(background, map, &sim)?;
                let adv = adversary.as_ref().map(|a| runners.get(a, map, &sim)).transpose()?;
                let svo_gaussian =
                    background.svo_gaussians.iter().find(|(s, _)| *s == map.name).map(|(_, g)| *g);
                Ok(Self {
                    sim: Arc::new(sim),
                    mode: Mode::Ego { background: Controller::External },
                    background: Some(bg),
                    adversary: adv,
                    noise: None,
                    svo_gaussian,
                })
            }
        }
    }

    /// The ego acts with `ego`; the flow and its adversary sample.
    pub fn drivers<'a>(&'a self, ego: Actor<'a>) -> Drivers<'a> {
        Drivers {
            alive: ego,
            background: self
                .background
                .as_deref()
                .map(Actor::sampled)
                .or(self.noise.map(noise_actor)),
            adversary: self.adversary.as_deref().map(Actor::sampled),
        }
    }
}

/// The flows and egos of an evaluation grid, found by whoever runs it.
#[derive(Clone, Default)]
pub struct Resolved {
    pub flows: BTreeMap<String, FlowDef>,
    pub egos: BTreeMap<String, EgoDef>,
}

impl Resolved {
    /// The flow and ego (if any) acting in `cell`.
    pub fn cell(&self, cell: &Cell) -> Result<(&FlowDef, Option<&EgoDef>), EvalError> {
        let flow = self
            .flows
            .get(&cell.flow)
            .ok_or_else(|| EvalError::Misfit(format!("flow `{}` is not in the grid", cell.flow)))?;
        let ego = if cell.ego.is_empty() {
            None
        } else {
            Some(self.egos.get(&cell.ego).ok_or_else(|| {
                EvalError::Misfit(format!("ego `{}` is not in the grid", cell.ego))
            })?)
        };
        Ok((flow, ego))
    }

    /// Every cell's ego and flow fit together (checked before anything runs).
    pub fn check(&self, cells: &[Cell]) -> Result<(), EvalError> {
        for c in cells {
            let (flow, ego) = self.cell(c)?;
            check_cell(c, flow, ego)
                .map_err(|e| EvalError::Misfit(format!("cell {}: {e}", c.key())))?;
        }
        Ok(())
    }
}
