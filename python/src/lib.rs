//! `socialflow._socialflow`: the native half of the Python package.
//!
//! Owns: [`Core`] (K simulators of one scenario stepped together, with the background flow
//! driven inside Rust: IDM, or a finished flow job's frozen policy with CoPO's coordinator or
//! SocialCommAdv's adversary; in ego mode Python drives agent 0 of every simulator, in
//! multi-agent mode every vehicle), [`LoadedPolicy`] (a finished job's kept actor, Rust
//! inference of its mean action), [`evaluate`] (a Python policy over stored cases x seeds
//! through `sf_rollout::evaluate::run_stored`, the loop of `socialflow eval`'s cells),
//! [`view_episode`] / [`view_index`] (one of those episodes replayed with the same seat into a
//! viewer page, and the mined pages' index: `EvalResult.mine`) and the conversions to NumPy. Must not: re-implement the simulator, the flows or inference (it
//! calls `sf_sim` and `sf_rollout`), or hold the GIL while simulators step.
//!
//! [`client`] is the job API's half (`socialflow.client`).
//!
//! Errors: bad arguments raise `ValueError` naming the argument; missing files `OSError`.
//! The Gymnasium / PettingZoo classes are Python (`python/socialflow/`).

mod client;

use std::cell::RefCell;
use std::sync::Arc;

use numpy::{
    PyArray1, PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sf_rollout::drive::{self, Actor};
use sf_rollout::evaluate::view;
use sf_rollout::evaluate::{Episodes, FlowDef, FlowSetup, Policy, Runners, Setting, StoredEpisode};
use sf_rollout::inference::PolicyRunner;
use sf_sim::obs::{MapSegments, ObsSpec, AGENT_CTX};
use sf_sim::vec_env::{EpisodeSpec, VecEnv, VecEnvConfig};
use sf_sim::{CaseFile, DriveAction, Layout, Map, Mode, SvoVisibility, Termination};

/// The stored evaluation cases, compiled in (`configs/cases/`), so the package needs no files.
const CASES: [(&str, &str); 4] = [
    ("intersection", include_str!("../../configs/cases/intersection.v1.json")),
    ("bottleneck", include_str!("../../configs/cases/bottleneck.v1.json")),
    ("merge", include_str!("../../configs/cases/merge.v1.json")),
    ("roundabout", include_str!("../../configs/cases/roundabout.v1.json")),
];

/// Terminations in the order of the codes `step` returns (-1: still driving).
const TERMINATIONS: [Termination; 6] = [
    Termination::Collision,
    Termination::OffRoad,
    Termination::OffRoute,
    Termination::WrongLane,
    Termination::Destination,
    Termination::Timeout,
];

fn bad(arg: &str, msg: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(format!("{arg}: {msg}"))
}

/// A built-in scenario's map and stored cases.
fn scenario(name: &str) -> PyResult<(Arc<Map>, CaseFile)> {
    let file = sf_sim::scenarios::build(name).ok_or_else(|| {
        bad(
            "scenario",
            format!(
                "unknown scenario `{name}` (expected one of {})",
                sf_sim::scenarios::SCENARIOS.join(", ")
            ),
        )
    })?;
    let map = Map::from_file(&file, name).map_err(|e| bad("scenario", e))?;
    let text = CASES
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, t)| *t)
        .ok_or_else(|| bad("scenario", format!("no stored cases for `{name}`")))?;
    let cases = CaseFile::from_json(text, &format!("{name}.v1.json (built in)"), &map)
        .map_err(|e| bad("scenario", e))?;
    Ok((Arc::new(map), cases))
}

/// `None` or `"idm"`: the IDM flow; otherwise a finished flow job's artifact directory.
fn flow_def(flow: Option<&str>) -> PyResult<FlowDef> {
    match flow {
        None | Some("idm") => Ok(FlowDef::Idm),
        Some(dir) => {
            let path = std::path::Path::new(dir);
            if !path.join("config.toml").exists() {
                return Err(PyOSError::new_err(format!("flow: `{dir}` is neither `idm` nor a job's artifact directory (no config.toml there)")));
            }
            FlowDef::load(path).map_err(|e| bad("flow", e))
        }
    }
}

/// Zeroes the SVO channels of an ego's observation row (an ego policy is not told SVOs; a
/// learned flow's simulator writes them for the background's sake).
fn hide_svo(spec: &ObsSpec, row: &mut [f32]) {
    row[spec.ego_ctx.start] = 0.0;
    for j in 0..spec.neighbours {
        row[spec.agents_ctx.start + j * AGENT_CTX + 4] = 0.0;
    }
}

/// Which reward the rows carry.
#[derive(Clone, Copy, PartialEq)]
enum Reward {
    Individual,
    Composed,
}

/// K simulators of one scenario, stepped together; see the module header.
#[pyclass(module = "socialflow._socialflow")]
pub struct Core {
    map: Arc<Map>,
    cases: CaseFile,
    flow: FlowSetup,
    /// Every vehicle a Python agent (PettingZoo), or Python drives agent 0 (Gymnasium).
    multi: bool,
    action: DriveAction,
    vehicles: (u32, u32),
    n_envs: usize,
    conflict_share: Option<f32>,
    reward: Reward,
    /// Ego mode among a learned flow: SVO channels zeroed in what Python sees.
    hide_svo: bool,
    segments: usize,
    venv: VecEnv,
    /// The flow's (and adversary's) sampling stream, reseeded by `reset(seed)`.
    rng: ChaCha8Rng,
    next_seed: u64,
    renderer: Option<sf_sim::render::Renderer>,
}

impl Core {
    /// The rows Python sees: agent 0 of every simulator, or every row.
    fn rows(&self) -> Vec<usize> {
        if self.multi {
            (0..self.venv.alive().len()).collect()
        } else {
            (0..self.n_envs).map(|k| k * self.venv.max_agents).collect()
        }
    }

    fn copy_row(&self, src: &[f32], out: &mut [f32]) {
        out.copy_from_slice(src);
        if self.hide_svo {
            hide_svo(&self.venv.spec, out);
        }
    }

    fn observation<'py>(&self, py: Python<'py>) -> PyResult<Observation<'py>> {
        let len = self.venv.spec.len;
        let rows = self.rows();
        let mut obs = vec![0f32; rows.len() * len];
        for (j, &r) in rows.iter().enumerate() {
            self.copy_row(
                &self.venv.observations()[r * len..(r + 1) * len],
                &mut obs[j * len..(j + 1) * len],
            );
        }
        let alive: Vec<bool> = rows.iter().map(|&r| self.venv.alive()[r] == 1.0).collect();
        Ok((PyArray1::from_vec(py, obs).reshape([rows.len(), len])?, PyArray1::from_vec(py, alive)))
    }
}

/// Observation rows and their `alive` flags.
type Observation<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray1<bool>>);

/// One evaluated episode: `(case, seed, success, safety, speed, collision, lane_change,
/// road_closed)`.
type EpisodeRow = (u32, u32, f32, f32, f32, f32, Option<f32>, Option<f32>);

/// What one `step` returns, per row Python sees.
type StepOut<'py> = (
    Bound<'py, PyArray2<f32>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<f32>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<i8>>,
    Bound<'py, PyArray1<i64>>,
    Bound<'py, PyArray2<f32>>,
);

#[pymethods]
impl Core {
    #[new]
    #[pyo3(signature = (scenario_name, flow=None, vehicles=(8, 20), layout=None, action="direct", num_envs=1, seed=0, conflict_share=None, multi_agent=false, reward="individual", policy=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        scenario_name: &str,
        flow: Option<&str>,
        vehicles: (u32, u32),
        layout: Option<&str>,
        action: &str,
        num_envs: usize,
        seed: u64,
        conflict_share: Option<f32>,
        multi_agent: bool,
        reward: &str,
        policy: Option<PyRef<'_, LoadedPolicy>>,
    ) -> PyResult<Self> {
        let (map, cases) = scenario(scenario_name)?;
        let action = DriveAction::parse(action).map_err(|e| bad("action", e))?;
        let mut layout = layout.map(Layout::parse).transpose().map_err(|e| bad("layout", e))?;
        if let Some(p) = &policy {
            if multi_agent {
                return Err(bad("policy", "observes as one ego: not in a multi-agent environment"));
            }
            layout = Some(p.fits(action, layout)?);
        }
        if vehicles.0 == 0 || vehicles.0 > vehicles.1 {
            return Err(bad(
                "vehicles",
                format!(
                    "({}, {}) is not a range of at least one vehicle (min <= max)",
                    vehicles.0, vehicles.1
                ),
            ));
        }
        if vehicles.1 as usize > map.spawns.len() {
            return Err(bad(
                "vehicles",
                format!(
                    "{} exceeds the {} spawn points of {scenario_name}",
                    vehicles.1,
                    map.spawns.len()
                ),
            ));
        }
        if !(1..=4096).contains(&num_envs) {
            return Err(bad("num_envs", format!("{num_envs} is not in 1..=4096")));
        }
        if let Some(p) = conflict_share.filter(|p| !(0.0..=1.0).contains(p)) {
            return Err(bad("conflict_share", format!("{p} is not a probability")));
        }
        let reward = match reward {
            "individual" => Reward::Individual,
            "composed" => Reward::Composed,
            other => {
                return Err(bad(
                    "reward",
                    format!("unknown reward `{other}` (expected `individual` or `composed`)"),
                ))
            }
        };
        let def = flow_def(flow)?;
        let mut runners = Runners::new(
            sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)
                .map_err(|e| PyOSError::new_err(e.to_string()))?,
        );
        let mut setup =
            FlowSetup::new(&def, &map, layout, &mut runners).map_err(|e| bad("flow", e))?;
        if multi_agent {
            if !matches!(def, FlowDef::Idm) {
                return Err(bad("flow", "a multi-agent environment drives every vehicle from Python: leave the flow out"));
            }
            let mut sim = (*setup.sim).clone();
            // Every agent sees the others' SVOs when they are rewarded for them.
            sim.obs.svo =
                if reward == Reward::Composed { SvoVisibility::All } else { SvoVisibility::None };
            setup.sim = Arc::new(sim);
            setup.mode = Mode::MultiAgent;
        }
        if let Some(p) = &policy {
            setup.sim = Arc::new(sf_rollout::evaluate::ego_sim(&def, &p.policy));
        }
        let hide_svo = !multi_agent && !matches!(def, FlowDef::Idm);
        let segments = MapSegments::build(&map, setup.sim.obs.segment_points).len();
        let venv = VecEnv::new(
            Arc::clone(&map),
            Arc::clone(&setup.sim),
            VecEnvConfig { n_envs: num_envs, mode: setup.mode, vehicles, seed },
        );
        Ok(Self {
            map,
            cases,
            flow: setup,
            multi: multi_agent,
            action,
            vehicles,
            n_envs: num_envs,
            conflict_share,
            reward,
            hide_svo,
            segments,
            venv,
            rng: ChaCha8Rng::seed_from_u64(seed),
            next_seed: seed.wrapping_add(1),
            renderer: None,
        })
    }

    /// Observation blocks: `{name: (start, stop, shape)}` of the flat row.
    fn spec<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (name, r, shape) in self.venv.spec.blocks() {
            d.set_item(name, (r.start, r.end, shape))?;
        }
        Ok(d)
    }

    #[getter]
    fn obs_len(&self) -> usize {
        self.venv.spec.len
    }

    #[getter]
    fn action_dim(&self) -> usize {
        self.action.dim()
    }

    /// The action kind Python's actions drive (`"direct"`, `"idm-residual-lateral"`, ...).
    #[getter]
    fn action(&self) -> &'static str {
        self.action.as_str()
    }

    #[getter]
    fn max_agents(&self) -> usize {
        self.venv.max_agents
    }

    #[getter]
    fn num_envs(&self) -> usize {
        self.n_envs
    }

    /// Map segments of the scenario (query-centric `seg_id` values are below it).
    #[getter]
    fn segments(&self) -> usize {
        self.segments
    }

    #[getter]
    fn num_cases(&self) -> usize {
        self.cases.cases.len()
    }

    #[getter]
    fn layout(&self) -> &'static str {
        self.flow.sim.obs.layout.as_str()
    }

    #[getter]
    fn dt_s(&self) -> f32 {
        self.flow.sim.dt_s
    }

    /// Starts new episodes in every simulator: random cases drawn from `seed` (the next seed
    /// when `None`), or stored `cases` (one index per simulator; each runs once, then the
    /// simulator idles until the next reset). Returns `(obs [rows, len], alive [rows])`.
    #[pyo3(signature = (seed=None, cases=None))]
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seed: Option<u64>,
        cases: Option<Vec<usize>>,
    ) -> PyResult<Observation<'py>> {
        let seed = seed.unwrap_or(self.next_seed);
        self.next_seed = seed.wrapping_add(1);
        let (map, sim, mode, n) =
            (Arc::clone(&self.map), Arc::clone(&self.flow.sim), self.flow.mode, self.n_envs);
        let venv = match cases {
            None => {
                let (vehicles, share) = (self.vehicles, self.conflict_share);
                let v = py.detach(move || {
                    let v = VecEnv::new(map, sim, VecEnvConfig { n_envs: n, mode, vehicles, seed });
                    match share {
                        Some(p) => v.with_conflicts(p),
                        None => v,
                    }
                });
                Ok(v)
            }
            Some(idx) => {
                if idx.len() != n {
                    return Err(bad(
                        "cases",
                        format!("{} case indices for {n} simulators (one each)", idx.len()),
                    ));
                }
                let mut eps = Vec::with_capacity(n);
                for (k, &c) in idx.iter().enumerate() {
                    let case = self.cases.cases.get(c).ok_or_else(|| {
                        bad(
                            "case",
                            format!(
                                "{c} is not a stored case of {} (0..{})",
                                self.map.name,
                                self.cases.cases.len()
                            ),
                        )
                    })?;
                    eps.push(EpisodeSpec {
                        case: case.clone(),
                        vehicles: None,
                        svo_deg: None,
                        tag: seed << 32 | k as u64,
                    });
                }
                py.detach(move || VecEnv::from_episodes(map, sim, mode, n, eps))
                    .map_err(|e| bad("cases", e))
            }
        }?;
        self.venv = venv;
        self.venv.set_svo_gaussian(self.flow.svo_gaussian);
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        self.observation(py)
    }

    /// One decision step. `actions`: `[rows, action_dim]` (rows of agents not alive are
    /// ignored). Returns `(obs, alive, reward, terminated, truncated, success, termination,
    /// final_rows, final_obs)`: per row, the reward of this step, whether its episode ended by
    /// a failure or its destination (terminated) or by the time limit or the episode's end
    /// (truncated), whether it succeeded, the termination code (index into
    /// `TERMINATIONS`, -1 while driving), and for the rows that ended their last observation
    /// (`final_obs[i]` belongs to row `final_rows[i]`; `obs` already holds the next episode's
    /// first observation for simulators that reset).
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray2<'py, f32>,
    ) -> PyResult<StepOut<'py>> {
        let rows = self.rows();
        let dim = self.action.dim();
        if actions.shape() != [rows.len(), dim] {
            return Err(bad(
                "actions",
                format!("shape {:?}, expected ({}, {dim})", actions.shape(), rows.len()),
            ));
        }
        let given = actions.as_slice().map_err(|e| bad("actions", e))?;
        if let Some(x) = given.iter().find(|x| !x.is_finite()) {
            return Err(bad("actions", format!("{x} is not a finite number")));
        }
        // The actions of live rows, in the order `drive::decide` lists them.
        let total = self.venv.alive().len();
        let mut by_row = vec![None; total];
        for (j, &r) in rows.iter().enumerate() {
            by_row[r] = Some(j);
        }
        let live: Vec<f32> = (0..total)
            .filter(|&r| self.venv.alive()[r] == 1.0)
            .flat_map(|r| {
                by_row[r].map_or(vec![0.0; dim], |j| given[j * dim..(j + 1) * dim].to_vec())
            })
            .collect();
        let (flow, venv, rng, action) = (&self.flow, &mut self.venv, &mut self.rng, self.action);
        py.detach(|| {
            let act = move |_: &[f32], _: usize| live.clone();
            let drivers = flow.drivers(Actor::External { act: &act, action });
            let venvs = std::slice::from_mut(venv);
            let d = drive::decide(venvs, &drivers, rng);
            drive::apply(venvs, &d);
            venv.take_finished();
        });
        let len = self.venv.spec.len;
        let steps = self.venv.row_steps();
        let n = rows.len();
        let (mut reward, mut terminated, mut truncated, mut success, mut code) =
            (vec![0f32; n], vec![false; n], vec![false; n], vec![false; n], vec![-1i8; n]);
        let (mut final_rows, mut final_obs) = (Vec::new(), Vec::new());
        for (j, &r) in rows.iter().enumerate() {
            let st = &steps[r];
            reward[j] = match self.reward {
                Reward::Individual => st.rewards.individual,
                Reward::Composed => st.rewards.composed,
            };
            if let Some(t) = st.ended {
                terminated[j] = st.terminal();
                truncated[j] = t == Termination::Timeout;
                success[j] = st.success;
                code[j] = TERMINATIONS.iter().position(|&x| x == t).map_or(-1, |i| i as i8);
            }
            truncated[j] |= st.truncated;
            if st.ended.is_some() || st.truncated {
                final_rows.push(j as i64);
                let at = final_obs.len();
                final_obs.resize(at + len, 0.0);
                self.copy_row(self.venv.next_observation(r), &mut final_obs[at..]);
            }
        }
        let (obs, alive) = self.observation(py)?;
        let k = final_rows.len();
        Ok((
            obs,
            alive,
            PyArray1::from_vec(py, reward),
            PyArray1::from_vec(py, terminated),
            PyArray1::from_vec(py, truncated),
            PyArray1::from_vec(py, success),
            PyArray1::from_vec(py, code),
            PyArray1::from_vec(py, final_rows),
            PyArray1::from_vec(py, final_obs).reshape([k, len])?,
        ))
    }

    /// The IDM driver's choice for every row Python sees, as the paper's normalised
    /// `[reference speed, steer]` (zeros for rows not alive): a demonstrator for the `direct`
    /// action. For the `idm-accel-residual` action the IDM driver is simply zero.
    fn idm_action<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let rows = self.rows();
        let mut out = vec![0f32; rows.len() * 2];
        for (j, &r) in rows.iter().enumerate() {
            if self.venv.alive()[r] == 1.0 {
                let a = self.venv.demo_action(r);
                out[j * 2] = a.ref_speed;
                out[j * 2 + 1] = a.steer;
            }
        }
        PyArray1::from_vec(py, out).reshape([rows.len(), 2])
    }

    /// IDM with MOBIL's lane changes for every row Python sees, as the `idm-residual-lateral`
    /// action `[acceleration residual, lateral target]` (`sf_sim::mobil`; zeros for rows not
    /// alive): a demonstrator that steers. Zeros while it keeps its lane, so only for the
    /// lateral action is it more than the IDM driver.
    fn mobil_action<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let rows = self.rows();
        let params = sf_sim::mobil::MobilParams::default();
        let mut out = vec![0f32; rows.len() * 2];
        for (j, &r) in rows.iter().enumerate() {
            if self.venv.alive()[r] == 1.0 {
                out[j * 2..j * 2 + 2].copy_from_slice(&self.venv.mobil_action(r, &params));
            }
        }
        PyArray1::from_vec(py, out).reshape([rows.len(), 2])
    }

    /// Vehicles in simulator `k`'s episode (agents `0..n`).
    fn vehicles_in(&self, k: usize) -> PyResult<usize> {
        if k >= self.n_envs {
            return Err(bad("k", format!("{k} is not a simulator index (0..{})", self.n_envs)));
        }
        Ok(self.venv.env(k).len())
    }

    /// An RGB frame `[H, W, 3]` of simulator `k` (vehicles coloured by SVO).
    #[pyo3(signature = (k=0, size_px=480))]
    fn render<'py>(
        &mut self,
        py: Python<'py>,
        k: usize,
        size_px: u32,
    ) -> PyResult<Bound<'py, PyArray3<u8>>> {
        if k >= self.n_envs {
            return Err(bad("k", format!("{k} is not a simulator index (0..{})", self.n_envs)));
        }
        if !(32..=4096).contains(&size_px) {
            return Err(bad("size_px", format!("{size_px} is not in 32..=4096")));
        }
        if self.renderer.as_ref().is_none_or(|r| r.size().0.max(r.size().1) != size_px) {
            self.renderer = Some(
                sf_sim::render::Renderer::new(&self.map, size_px, sf_sim::render::ColourBy::Svo)
                    .map_err(|e| bad("render", e))?,
            );
        }
        let Some(r) = self.renderer.as_ref() else { return Err(bad("render", "no renderer")) };
        let pm = r.frame(self.venv.env(k));
        let (w, h) = (pm.width() as usize, pm.height() as usize);
        let rgb: Vec<u8> = pm.data().chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
        PyArray1::from_vec(py, rgb).reshape([h, w, 3])
    }
}

fn cpu() -> PyResult<sf_nn::device::Device> {
    sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)
        .map_err(|e| PyOSError::new_err(e.to_string()))
}

/// A finished job's kept actor (`policy.bpk` with its `config.toml`): batched Rust inference of
/// its deterministic (mean) action, the action `socialflow eval` drives with. Query-centric
/// actors read map segments, so they act in one scenario (`scenario`, or the job's only one).
#[pyclass(name = "Policy", module = "socialflow._socialflow", frozen)]
struct LoadedPolicy {
    policy: Policy,
    job_dir: String,
    action: DriveAction,
    layout: Layout,
    obs_len: usize,
    action_dim: usize,
    scenario: Option<String>,
    /// Boxed: the runner's tensors are aligned beyond what a Python object's storage gives.
    runner: Option<Box<PolicyRunner>>,
}

impl LoadedPolicy {
    /// Its layout, once `action` and `layout` (the caller's) are checked against its own.
    fn fits(&self, action: DriveAction, layout: Option<Layout>) -> PyResult<Layout> {
        if action != self.action {
            return Err(bad(
                "action",
                format!(
                    "`{}` given, but the policy drives with `{}`",
                    action.as_str(),
                    self.action.as_str()
                ),
            ));
        }
        if layout.is_some_and(|l| l != self.layout) {
            return Err(bad(
                "layout",
                format!("the policy reads the `{}` layout", self.layout.as_str()),
            ));
        }
        Ok(self.layout)
    }
}

#[pymethods]
impl LoadedPolicy {
    #[new]
    #[pyo3(signature = (job_dir, scenario=None))]
    fn new(job_dir: &str, scenario: Option<&str>) -> PyResult<Self> {
        let dir = std::path::Path::new(job_dir);
        if !dir.join("config.toml").exists() {
            return Err(PyOSError::new_err(format!(
                "job_dir: `{job_dir}` is not a job's artifact directory (no config.toml there)"
            )));
        }
        let policy = Policy::load(dir).map_err(|e| match e {
            sf_rollout::evaluate::EvalError::Io { .. } => {
                PyOSError::new_err(format!("job_dir: {e}"))
            }
            e => bad("job_dir", e),
        })?;
        if !policy.cfg.kind.drives() {
            return Err(bad(
                "job_dir",
                format!("a {} job's actor does not drive a vehicle", policy.cfg.kind.as_str()),
            ));
        }
        let resolved = sf_rollout::setup::resolve(&policy.cfg, None);
        let bound = match scenario {
            Some(s) => Some(s.to_string()),
            None => match policy.cfg.env.scenarios.as_slice() {
                [only] => Some(only.clone()),
                _ => None,
            },
        };
        let layout = resolved.obs.layout;
        let build = |maps: &[&MapSegments]| -> PyResult<PolicyRunner> {
            PolicyRunner::from_bytes(
                &resolved.net,
                &resolved.obs,
                resolved.sim.dt_s,
                maps,
                &policy.weights,
                sf_job::PolicyVersion::new(0),
                &cpu()?,
            )
            .map_err(|e| bad("job_dir", format!("{}: {e}", dir.join("policy.bpk").display())))
        };
        let runner = match (&bound, layout) {
            (Some(name), _) => {
                let (map, _) = crate::scenario(name)?;
                Some(Box::new(build(&[&MapSegments::build(
                    &map,
                    resolved.sim.obs.segment_points,
                )])?))
            }
            (None, Layout::EgoFrame) => Some(Box::new(build(&[])?)),
            (None, _) => None,
        };
        Ok(Self {
            job_dir: job_dir.to_string(),
            action: resolved.net.action,
            action_dim: resolved.net.action_dim,
            obs_len: resolved.obs.len,
            layout,
            scenario: bound,
            runner,
            policy,
        })
    }

    /// Mean actions `[n, action_dim]` for observations `[n, obs_len]` (float32) of the job's
    /// observation format (`make_ego(..., layout=policy.layout, action=policy.action)`).
    fn __call__<'py>(
        &self,
        py: Python<'py>,
        obs: PyReadonlyArray2<'py, f32>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let runner = self.runner.as_ref().ok_or_else(|| {
            bad(
                "scenario",
                format!(
                    "this actor reads the {} layout's map segments and its job trained on {} scenarios: load it with load_policy(job_dir, scenario=...) for the scenario it acts in",
                    self.layout.as_str(),
                    self.policy.cfg.env.scenarios.len()
                ),
            )
        })?;
        let [n, len] = [obs.shape()[0], obs.shape()[1]];
        if len != self.obs_len {
            return Err(bad(
                "obs",
                format!("rows of {len} floats, expected {} (this job's observation)", self.obs_len),
            ));
        }
        let rows = obs.as_slice().map_err(|e| bad("obs", e))?.to_vec();
        if rows.iter().any(|v| !v.is_finite()) {
            return Err(bad("obs", "holds NaN or infinite values"));
        }
        let out = py.detach(|| runner.mean(&rows, &vec![0; n]));
        PyArray1::from_vec(py, out).reshape([n, self.action_dim])
    }

    /// The action kind its output drives (`"direct"`, `"idm-accel-residual"`, ...).
    #[getter]
    fn action(&self) -> &'static str {
        self.action.as_str()
    }
    /// The observation layout it reads (`"ego-frame"` or `"query-centric"`).
    #[getter]
    fn layout(&self) -> &'static str {
        self.layout.as_str()
    }
    #[getter]
    fn obs_len(&self) -> usize {
        self.obs_len
    }
    #[getter]
    fn action_dim(&self) -> usize {
        self.action_dim
    }
    /// The scenario it acts in (`None`: unbound, evaluation only).
    #[getter]
    fn scenario(&self) -> Option<String> {
        self.scenario.clone()
    }
    #[getter]
    fn job_dir(&self) -> &str {
        &self.job_dir
    }
    /// The job's name and kind (`config.toml`).
    #[getter]
    fn name(&self) -> &str {
        &self.policy.cfg.name
    }
    #[getter]
    fn kind(&self) -> &'static str {
        self.policy.cfg.kind.as_str()
    }
    /// The scenarios the job trained on.
    #[getter]
    fn scenarios(&self) -> Vec<String> {
        self.policy.cfg.env.scenarios.clone()
    }

    fn __repr__(&self) -> String {
        format!(
            "socialflow.Policy(job_dir={:?}, name={:?}, kind={:?}, action={:?}, layout={:?}, scenario={:?})",
            self.job_dir,
            self.policy.cfg.name,
            self.policy.cfg.kind.as_str(),
            self.action.as_str(),
            self.layout.as_str(),
            self.scenario
        )
    }
}

/// The ego's seat taken by `policy` (a finished job's actor from `load_policy`, driven in Rust,
/// or a callable `[n, obs_len] float32 -> [n, action_dim] float32`) among `flow` in
/// `scenario_name`, as `socialflow eval`'s cells seat a policy: `body` gets the setting, the
/// drivers, the scenario's stored cases and the flow, and runs what it runs. An exception the
/// callable raised (or a wrong shape it returned) is raised after the run, the run's own result
/// dropped. What [`evaluate`] and [`view_episode`] share.
#[allow(clippy::too_many_arguments)]
fn with_ego_seat<R>(
    py: Python<'_>,
    policy: &Bound<'_, PyAny>,
    scenario_name: &str,
    flow: Option<&str>,
    layout: Option<&str>,
    action: &str,
    svo_deg: Option<f32>,
    body: impl FnOnce(&Setting, &drive::Drivers, &CaseFile, &FlowDef, &str) -> PyResult<R>,
) -> PyResult<R> {
    if !policy.is_callable() {
        return Err(bad("policy", "is not callable"));
    }
    let (map, stored) = scenario(scenario_name)?;
    let action = DriveAction::parse(action).map_err(|e| bad("action", e))?;
    let mut layout = layout.map(Layout::parse).transpose().map_err(|e| bad("layout", e))?;
    // A loaded job's actor drives in Rust, as in `socialflow eval`, with its own action and
    // layout.
    let loaded = policy.extract::<PyRef<'_, LoadedPolicy>>().ok();
    if let Some(p) = &loaded {
        layout = Some(p.fits(action, layout)?);
    }
    if let Some(s) = svo_deg.filter(|s| !(0.0..=90.0).contains(s)) {
        return Err(bad("svo_deg", format!("{s} is not in [0, 90]")));
    }
    let def = flow_def(flow)?;
    let mut runners = Runners::new(cpu()?);
    let mut setup = FlowSetup::new(&def, &map, layout, &mut runners).map_err(|e| bad("flow", e))?;
    if let Some(p) = &loaded {
        setup.sim = Arc::new(sf_rollout::evaluate::ego_sim(&def, &p.policy));
    }
    let runner = loaded
        .as_ref()
        .map(|p| runners.get(&p.policy, &map, &setup.sim))
        .transpose()
        .map_err(|e| bad("policy", e))?;
    let ego_label = match &loaded {
        Some(p) => format!("ego (learned, {} job {})", p.policy.cfg.kind.as_str(), p.job_dir),
        None => "ego (the Python policy)".to_string(),
    };
    let spec = ObsSpec::new(&setup.sim.obs);
    let (len, dim, hide) = (spec.len, action.dim(), !matches!(def, FlowDef::Idm));
    let failed: RefCell<Option<PyErr>> = RefCell::new(None);
    let act = |obs: &[f32], n: usize| -> Vec<f32> {
        if failed.borrow().is_some() {
            return vec![0.0; n * dim];
        }
        let mut rows = obs.to_vec();
        if hide {
            rows.chunks_exact_mut(len).for_each(|r| hide_svo(&spec, r));
        }
        let call = || -> PyResult<Vec<f32>> {
            let arr = PyArray1::from_vec(py, rows).reshape([n, len])?;
            let out = policy.call1((arr,))?;
            let out: PyReadonlyArray2<f32> = out.extract().map_err(|_| {
                bad("policy", format!("must return a float32 array of shape ({n}, {dim})"))
            })?;
            if out.shape() != [n, dim] {
                return Err(bad(
                    "policy",
                    format!("returned shape {:?}, expected ({n}, {dim})", out.shape()),
                ));
            }
            Ok(out.as_slice().map_err(|e| bad("policy", e))?.to_vec())
        };
        call().unwrap_or_else(|e| {
            *failed.borrow_mut() = Some(e);
            vec![0.0; n * dim]
        })
    };
    let ego = match &runner {
        Some(r) => Actor::mean(r),
        None => Actor::External { act: &act, action },
    };
    let drivers = setup.drivers(ego);
    let at =
        Setting { map: &map, sim: &setup.sim, mode: setup.mode, svo_gaussian: setup.svo_gaussian };
    let out = body(&at, &drivers, &stored, &def, &ego_label);
    if let Some(e) = failed.into_inner() {
        return Err(e);
    }
    out
}

/// Runs `policy` (a callable `[n, obs_len] float32 -> [n, action_dim] float32`) in the ego's
/// seat over the first `cases` stored cases x `seeds` among the flow, through the loop of
/// `socialflow eval`'s cells. Returns `(case, seed, success, safety, speed, collision,
/// lane_change, road_closed)` per episode in (seed, case) order.
#[pyfunction]
#[pyo3(signature = (policy, scenario_name, flow=None, layout=None, action="direct", cases=200, seeds=10, envs=16, vehicles=None, svo_deg=None))]
#[allow(clippy::too_many_arguments)]
fn evaluate(
    py: Python<'_>,
    policy: Bound<'_, PyAny>,
    scenario_name: &str,
    flow: Option<&str>,
    layout: Option<&str>,
    action: &str,
    cases: usize,
    seeds: u32,
    envs: usize,
    vehicles: Option<usize>,
    svo_deg: Option<f32>,
) -> PyResult<Vec<EpisodeRow>> {
    if seeds == 0 || !(1..=4096).contains(&envs) {
        return Err(bad(
            "seeds/envs",
            format!("seeds {seeds} and envs {envs} must be positive (envs at most 4096)"),
        ));
    }
    let run = |at: &Setting, drivers: &drive::Drivers, stored: &CaseFile, _: &FlowDef, _: &str| {
        if cases == 0 || cases > stored.cases.len() {
            return Err(bad(
                "cases",
                format!(
                    "{cases} is not in 1..={} (the stored cases of {scenario_name})",
                    stored.cases.len()
                ),
            ));
        }
        let episodes = Episodes { cases: &stored.cases[..cases], seeds, envs, vehicles, svo_deg };
        sf_rollout::evaluate::run_stored(
            at.map,
            at.sim,
            at.mode,
            at.svo_gaussian,
            &episodes,
            drivers,
        )
        .map_err(|e| bad("evaluate", e))
    };
    let rows = with_ego_seat(py, &policy, scenario_name, flow, layout, action, svo_deg, run)?;
    Ok(rows
        .into_iter()
        .map(|r| {
            let s = r.scores;
            let (lane_change, road_closed) = (r.lane_change, r.road_closed);
            (r.case, r.seed, s.success, s.safety, s.speed, r.collision, lane_change, road_closed)
        })
        .collect())
}

/// Replays one stored episode of `evaluate`'s (stored case id `case`, evaluation seed `seed`)
/// with `policy` in the ego's seat, as `evaluate` ran it, into a self-contained browser page
/// (the page of `socialflow view`). `stored`: the episode's row from `evaluate` (`success`,
/// `safety`, `speed`, `collision`, `road_closed`), shown beside the replay with whether they
/// agree. Returns `(html, outcome, metrics_json, agrees)`: the page, the outcome class
/// (`collision`, `off-road`, `off-route`, `wrong-lane`, `road-closed`, `timeout` or `success`),
/// the replay's metrics as JSON and whether the replay ended as `stored` says (`None` without
/// one).
#[pyfunction]
#[pyo3(signature = (policy, scenario_name, case, seed, flow=None, layout=None, action="direct", vehicles=None, svo_deg=None, title="", stored=None))]
#[allow(clippy::too_many_arguments)]
fn view_episode(
    py: Python<'_>,
    policy: Bound<'_, PyAny>,
    scenario_name: &str,
    case: u32,
    seed: u32,
    flow: Option<&str>,
    layout: Option<&str>,
    action: &str,
    vehicles: Option<usize>,
    svo_deg: Option<f32>,
    title: &str,
    stored: Option<Bound<'_, PyDict>>,
) -> PyResult<(String, String, String, Option<bool>)> {
    let stored = stored.map(|d| stored_row(&d)).transpose()?;
    let run =
        |at: &Setting, drivers: &drive::Drivers, cases: &CaseFile, def: &FlowDef, ego: &str| {
            let case_index = cases.cases.iter().position(|c| c.id == case).ok_or_else(|| {
                bad(
                    "case",
                    format!(
                        "{case} is not among the {} stored cases of {scenario_name}",
                        cases.cases.len()
                    ),
                )
            })?;
            let episode =
                StoredEpisode { cases: &cases.cases, case_index, seed, vehicles, svo_deg };
            view::record_with(at, &episode, drivers, Some(ego.to_string()), def)
                .map_err(|e| bad("view_episode", e))
        };
    let trace = with_ego_seat(py, &policy, scenario_name, flow, layout, action, svo_deg, run)?;
    let metrics = trace.metrics.ok_or_else(|| bad("view_episode", "the replay has no metrics"))?;
    let html = view::page(&trace, title, stored.as_ref()).map_err(|e| bad("view_episode", e))?;
    let json = serde_json::to_string(&metrics).map_err(|e| bad("view_episode", e))?;
    let agrees = stored.as_ref().map(|s| s.agrees(&metrics));
    Ok((html, view::outcome_class(&metrics).to_string(), json, agrees))
}

/// An episode row's stored scores (a dict of `evaluate`'s columns); `ValueError` names a
/// missing or non-numeric one.
fn stored_row(d: &Bound<'_, PyDict>) -> PyResult<view::StoredRow> {
    let num = |k: &str| -> PyResult<Option<f32>> {
        match d.get_item(k)? {
            None => Ok(None),
            Some(v) if v.is_none() => Ok(None),
            Some(v) => v
                .extract::<f32>()
                .map(Some)
                .map_err(|_| bad("stored", format!("`{k}` is not a number: {v}"))),
        }
    };
    let need = |k: &str| num(k)?.ok_or_else(|| bad("stored", format!("has no `{k}`")));
    Ok(view::StoredRow {
        success: need("success")?,
        safety: need("safety")?,
        speed: need("speed")?,
        collision: need("collision")?,
        road_closed: num("road_closed")?,
    })
}

/// The index page of mined episodes (`socialflow eval --mine`'s `mined/index.html`): `rows_json`
/// a JSON list of rows with `href`, `cell`, `experiment`, `ego`, `flow`, `scenario`, `svo_deg`,
/// `vehicles`, `case`, `seed`, `outcome`, `metrics` and `replay_agrees`, in the order to show.
#[pyfunction]
fn view_index(title: &str, rows_json: &str) -> PyResult<String> {
    let rows: Vec<serde_json::Value> =
        serde_json::from_str(rows_json).map_err(|e| bad("rows_json", e))?;
    view::index(title, &rows).map_err(|e| bad("view_index", e))
}

/// The built-in scenarios.
#[pyfunction]
fn scenarios() -> Vec<&'static str> {
    sf_sim::scenarios::SCENARIOS.to_vec()
}

/// Names of the termination codes `Core.step` returns.
#[pyfunction]
fn terminations() -> Vec<&'static str> {
    TERMINATIONS.iter().map(|t| t.as_str()).collect()
}

/// A job config's TOML text with `section.key=value` overrides written in (the command line's
/// `--set`); `ValueError` names a malformed override. The result is validated where it is
/// submitted, like any config.
#[pyfunction]
fn apply_overrides(text: &str, sets: Vec<String>) -> PyResult<String> {
    sf_job::overrides::apply(text, &sets).map_err(|e| PyValueError::new_err(e.to_string()))
}

#[pymodule]
fn _socialflow(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Core>()?;
    m.add_class::<LoadedPolicy>()?;
    m.add_class::<client::JobClient>()?;
    m.add_class::<client::JobWatch>()?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(view_episode, m)?)?;
    m.add_function(wrap_pyfunction!(view_index, m)?)?;
    m.add_function(wrap_pyfunction!(scenarios, m)?)?;
    m.add_function(wrap_pyfunction!(terminations, m)?)?;
    m.add_function(wrap_pyfunction!(apply_overrides, m)?)?;
    Ok(())
}
