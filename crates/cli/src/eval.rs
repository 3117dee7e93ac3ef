//! `socialflow eval <config>`: the paper's evaluation grid over stored cases and seeds.
//!
//! Owns: the evaluation config ([`EvalConfig`]: where the trained jobs are, which flows and ego
//! policies, which experiments), expanding experiments into cells (ego or none x flow x
//! scenario x SVO / density variant), running each cell's `cases x seeds` episodes in batched
//! simulators ([`sf_sim::vec_env::VecEnv::from_episodes`], roles decided by `sf_sac::drive`),
//! and the per-episode results file (`episodes.csv`) that a report is rebuilt from. A rerun
//! skips cells already stored and appends the rest, so nothing stored is lost. Must not:
//! compute statistics or draw (`sf_eval::report` does).
//!
//! Actions: ego policies act with their mean action; learned flows and the adversary sample,
//! one random stream per seed (the seed is the stream's seed), so the same policies, cases and
//! seeds give the same numbers.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Deserialize;
use sf_eval::report::{EpisodeRow, EPISODES_HEADER};
use sf_job::config::JobKind;
use sf_job::JobConfig;
use sf_sac::drive::{self, Actor, Drivers};
use sf_sac::inference::PolicyRunner;
use sf_sac::setup;
use sf_sim::env::Controller;
use sf_sim::obs::MapSegments;
use sf_sim::vec_env::{EpisodeSpec, VecEnv};
use sf_sim::{Map, Mode, SimConfig};

use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Evaluation config (TOML), e.g. configs/eval/paper-small.toml.
    pub config: PathBuf,
    /// Override the config's `out` directory.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// A named flow: `idm`, or the job whose final policy it is.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Named {
    pub name: String,
    pub job: String,
    /// Egos: the flow (by name) the ego was trained in; its cell is grey in the heatmaps.
    #[serde(default)]
    pub trained_in: Option<String>,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SvoSweep {
    pub flows: Vec<String>,
    /// Number of SVO values, evenly spaced over [0, 90] deg.
    pub values: usize,
    pub scenarios: Vec<String>,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Density {
    pub scenario: String,
    pub flows: Vec<String>,
    pub vehicles: Vec<usize>,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Adversary {
    pub egos: Vec<String>,
    pub flows: Vec<String>,
}

/// GIFs of the same stored case with one ego under several flows, side by side.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gifs {
    pub ego: String,
    pub flows: Vec<String>,
    pub scenarios: Vec<String>,
    #[serde(default)]
    pub case: u32,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Experiments {
    pub gifs: Option<Gifs>,
    /// Flows evaluated on their own (every vehicle of the case driven by the flow).
    pub flow_quality: Vec<String>,
    /// Every ego in each of these flows (the paper: the four non-adversarial ones).
    pub cross_validation: Vec<String>,
    pub svo_sweep: Option<SvoSweep>,
    pub density: Option<Density>,
    pub adversary: Option<Adversary>,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalConfig {
    /// Data directory of the learner (or embedded pipeline) that trained the jobs.
    pub runs: PathBuf,
    /// Where `episodes.csv` (and by default the report) go.
    pub out: PathBuf,
    pub scenarios: Vec<String>,
    /// The first N stored cases of each scenario.
    pub cases: u32,
    pub seeds: u32,
    /// Episodes stepped together.
    #[serde(default = "d_envs")]
    pub envs: usize,
    pub flows: Vec<Named>,
    pub egos: Vec<Named>,
    /// The ego the paper proposes; the report tests it against the others.
    #[serde(default)]
    pub ours: Option<String>,
    #[serde(default)]
    pub experiments: Experiments,
}
fn d_envs() -> usize {
    32
}

impl EvalConfig {
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let c: Self = toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.to_string().trim_end()))?;
        c.validate().with_context(|| path.display().to_string())?;
        Ok(c)
    }

    fn validate(&self) -> Result<()> {
        if self.cases == 0 || self.seeds == 0 || self.envs == 0 {
            bail!("eval config fields `cases`, `seeds` and `envs` must be positive");
        }
        if self.scenarios.is_empty() {
            bail!("eval config field `scenarios`: list at least one");
        }
        let flows: BTreeSet<&str> = self.flows.iter().map(|f| f.name.as_str()).collect();
        let egos: BTreeSet<&str> = self.egos.iter().map(|f| f.name.as_str()).collect();
        if flows.len() != self.flows.len() || egos.len() != self.egos.len() {
            bail!("eval config fields `flows` / `egos`: names must be unique");
        }
        for n in self.flows.iter().chain(&self.egos).map(|f| f.name.as_str()).chain(self.scenarios.iter().map(String::as_str)) {
            if n.is_empty() || n.contains([',', '|', '\n']) {
                bail!("eval config: name `{n}` must be non-empty without ',' or '|'");
            }
        }
        if let Some(o) = self.ours.as_ref().filter(|o| !egos.contains(o.as_str())) {
            bail!("eval config field `ours`: `{o}` is not one of `egos`");
        }
        for e in &self.egos {
            if let Some(t) = e.trained_in.as_ref().filter(|t| !flows.contains(t.as_str())) {
                bail!("eval config field `egos.trained_in` of `{}`: `{t}` is not one of `flows`", e.name);
            }
        }
        let e = &self.experiments;
        let mut need_flows: Vec<(&str, &String)> = e.flow_quality.iter().map(|f| ("experiments.flow_quality", f)).collect();
        need_flows.extend(e.cross_validation.iter().map(|f| ("experiments.cross_validation", f)));
        let mut need_egos: Vec<(&str, &String)> = Vec::new();
        if let Some(s) = &e.svo_sweep {
            need_flows.extend(s.flows.iter().map(|f| ("experiments.svo_sweep.flows", f)));
            if s.values < 2 {
                bail!("eval config field `experiments.svo_sweep.values`: at least 2");
            }
        }
        if let Some(d) = &e.density {
            need_flows.extend(d.flows.iter().map(|f| ("experiments.density.flows", f)));
            if d.vehicles.is_empty() || d.vehicles.contains(&0) {
                bail!("eval config field `experiments.density.vehicles`: positive vehicle counts");
            }
        }
        if let Some(g) = &e.gifs {
            need_flows.extend(g.flows.iter().map(|f| ("experiments.gifs.flows", f)));
            need_egos.push(("experiments.gifs.ego", &g.ego));
        }
        if let Some(a) = &e.adversary {
            need_flows.extend(a.flows.iter().map(|f| ("experiments.adversary.flows", f)));
            need_egos.extend(a.egos.iter().map(|f| ("experiments.adversary.egos", f)));
        }
        for (field, f) in need_flows {
            if !flows.contains(f.as_str()) {
                bail!("eval config field `{field}`: `{f}` is not one of `flows`");
            }
        }
        for (field, f) in need_egos {
            if !egos.contains(f.as_str()) {
                bail!("eval config field `{field}`: `{f}` is not one of `egos`");
            }
        }
        Ok(())
    }
}

/// One cell of the grid: `cases x seeds` episodes.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Cell {
    experiment: String,
    ego: String,
    flow: String,
    scenario: String,
    /// SVO sweep: every agent's SVO; density: vehicles per case. Empty otherwise.
    svo_deg: Option<u32>,
    vehicles: Option<usize>,
}

impl Cell {
    /// The cell a stored episode belongs to.
    fn of(r: &EpisodeRow) -> Self {
        Self { experiment: r.experiment.clone(), ego: r.ego.clone(), flow: r.flow.clone(), scenario: r.scenario.clone(), svo_deg: r.svo_deg, vehicles: r.vehicles }
    }

    fn key(&self) -> String {
        format!("{}|{}|{}|{}|{}|{}", self.experiment, self.ego, self.flow, self.scenario, opt(self.svo_deg), opt(self.vehicles))
    }
}

fn opt<T: ToString>(v: Option<T>) -> String {
    v.map(|x| x.to_string()).unwrap_or_default()
}

fn cells(c: &EvalConfig) -> Vec<Cell> {
    let cell = |experiment: &str, ego: &str, flow: &str, scenario: &str, svo_deg, vehicles| Cell { experiment: experiment.into(), ego: ego.into(), flow: flow.into(), scenario: scenario.into(), svo_deg, vehicles };
    let e = &c.experiments;
    let mut out = Vec::new();
    for f in &e.flow_quality {
        for s in &c.scenarios {
            out.push(cell("flow_quality", "", f, s, None, None));
        }
    }
    for ego in &c.egos {
        for f in &e.cross_validation {
            for s in &c.scenarios {
                out.push(cell("cross", &ego.name, f, s, None, None));
            }
        }
    }
    if let Some(sw) = &e.svo_sweep {
        for f in &sw.flows {
            for s in &sw.scenarios {
                for k in 0..sw.values {
                    let svo = (90.0 * k as f64 / (sw.values - 1) as f64).round() as u32;
                    out.push(cell("svo_sweep", "", f, s, Some(svo), None));
                }
            }
        }
    }
    if let Some(d) = &e.density {
        for f in &d.flows {
            for &n in &d.vehicles {
                out.push(cell("density", "", f, &d.scenario, None, Some(n)));
            }
        }
    }
    if let Some(a) = &e.adversary {
        // The same numbers as the cross-validation's cells when both run; stored once each.
        for ego in &a.egos {
            for f in &a.flows {
                for s in &c.scenarios {
                    out.push(cell("adversary", ego, f, s, None, None));
                }
            }
        }
    }
    out
}

/// A finished job's artifacts found by name in a learner's data directory.
#[derive(Clone)]
struct Trained {
    cfg: JobConfig,
    weights: Arc<Vec<u8>>,
    dir: PathBuf,
    /// A CoPO flow's Stage-2 coordinator (`coordinator.json`), if it was fitted.
    coordinator: Option<sf_sac::coordinator::CoordinatorFile>,
}

/// Every `jobs/<id>-<name>/` directory of a learner's data directory as `(id, name, dir)`.
fn job_dirs(runs: &Path) -> Result<Vec<(u64, String, PathBuf)>> {
    let jobs = runs.join("jobs");
    let mut out = Vec::new();
    for e in std::fs::read_dir(&jobs).with_context(|| format!("reading {}", jobs.display()))?.flatten() {
        let file = e.file_name().to_string_lossy().to_string();
        if let Some((id, name)) = file.split_once('-').and_then(|(id, name)| Some((id.parse::<u64>().ok()?, name.to_string()))) {
            out.push((id, name, e.path()));
        }
    }
    Ok(out)
}

/// The newest `jobs/<id>-<name>/` with a final policy.
fn find_job(runs: &Path, name: &str) -> Result<Trained> {
    let best = job_dirs(runs)?.into_iter().filter(|(_, n, dir)| n == name && dir.join("policy.bpk").exists()).max_by_key(|(id, _, _)| *id);
    let (_, _, dir) = best.with_context(|| format!("no finished job named `{name}` under {}", runs.join("jobs").display()))?;
    load_job(&dir)
}

fn find_job_by_id(runs: &Path, id: u64) -> Result<Trained> {
    match job_dirs(runs)?.into_iter().find(|(i, _, _)| *i == id) {
        Some((_, _, dir)) => load_job(&dir),
        None => bail!("job {id} has no directory under {}", runs.join("jobs").display()),
    }
}

fn load_job(dir: &Path) -> Result<Trained> {
    let text = std::fs::read_to_string(dir.join("config.toml")).with_context(|| format!("reading {}/config.toml", dir.display()))?;
    let cfg = JobConfig::from_toml(&text).with_context(|| format!("{}/config.toml", dir.display()))?;
    let weights = std::fs::read(dir.join("policy.bpk")).with_context(|| format!("reading {}/policy.bpk", dir.display()))?;
    let coordinator = sf_sac::coordinator::CoordinatorFile::load(dir).map_err(anyhow::Error::msg)?;
    Ok(Trained { cfg, weights: Arc::new(weights), dir: dir.to_path_buf(), coordinator })
}

/// What drives a flow: IDM, or a learned background (with its adversary for SocialCommAdv).
enum FlowDef {
    Idm,
    Learned { background: Trained, adversary: Option<Trained>, kind: JobKind },
}

fn flow_def(runs: &Path, job: &str) -> Result<FlowDef> {
    if job == "idm" {
        return Ok(FlowDef::Idm);
    }
    let t = find_job(runs, job)?;
    match t.cfg.kind {
        JobKind::Ego => bail!("`{job}` ({}) is an ego job, not a flow", t.dir.display()),
        JobKind::SocialcommAdv => {
            let bg_id = t.cfg.env.background_job.with_context(|| format!("{}: a socialcomm-adv job without its flow", t.dir.display()))?;
            let bg = find_job_by_id(runs, bg_id)?;
            Ok(FlowDef::Learned { background: bg, adversary: Some(t), kind: JobKind::SocialcommAdv })
        }
        k => Ok(FlowDef::Learned { background: t, adversary: None, kind: k }),
    }
}

/// Policies for one scenario, loaded once per run.
struct Runners {
    device: sf_nn::device::Device,
    segments: BTreeMap<String, Arc<MapSegments>>,
    cache: BTreeMap<(String, String), Arc<PolicyRunner>>,
}

impl Runners {
    fn get(&mut self, t: &Trained, scenario: &str, sim: &SimConfig) -> Result<Arc<PolicyRunner>> {
        let key = (t.dir.display().to_string(), scenario.to_string());
        if let Some(r) = self.cache.get(&key) {
            return Ok(Arc::clone(r));
        }
        let segs = self.segments.get(scenario).context("scenario segments")?;
        let r = PolicyRunner::from_bytes(&setup::net_config(&t.cfg), &setup::obs_spec(&t.cfg), sim.dt_s, &[segs.as_ref()], &t.weights, 0, &self.device).with_context(|| format!("loading {}/policy.bpk", t.dir.display()))?;
        let r = Arc::new(r);
        self.cache.insert(key, Arc::clone(&r));
        Ok(r)
    }
}

/// The policies acting in a cell.
struct Acting {
    ego: Option<Arc<PolicyRunner>>,
    background: Option<Arc<PolicyRunner>>,
    adversary: Option<Arc<PolicyRunner>>,
    /// CoPO Stage 2: the flow's SVOs are redrawn from its coordinator's Gaussian every step
    /// (not in cells that fix every SVO, the SVO sweep).
    svo_gaussian: Option<sf_sim::SvoGaussian>,
}

impl Acting {
    /// The ego acts with its mean; flows and the adversary sample.
    fn drivers(&self) -> Drivers<'_> {
        match (&self.ego, &self.background) {
            (Some(e), bg) => Drivers { alive: Actor::mean(e), background: bg.as_deref().map(Actor::sampled), adversary: self.adversary.as_deref().map(Actor::sampled) },
            (None, Some(f)) => Drivers { alive: Actor::sampled(f), background: None, adversary: None },
            // The all-IDM flow: its vehicles' controllers ignore these actions.
            (None, None) => Drivers { alive: Actor::Random, background: None, adversary: None },
        }
    }
}

/// Simulator settings, mode and acting policies of a cell.
fn cell_setup(cell: &Cell, flow: &FlowDef, ego: Option<&Trained>, runners: &mut Runners) -> Result<(Arc<SimConfig>, Mode, Acting)> {
    // The layout comes from whichever job acts; what the background's observations carry from the flow.
    let bg_kind = match flow {
        FlowDef::Idm => None,
        FlowDef::Learned { background, .. } => Some(background.cfg.kind),
    };
    let (sim, mode) = match (ego, flow) {
        (Some(e), FlowDef::Idm) => (setup::sim_config(&e.cfg, None), Mode::Ego { background: Controller::Idm }),
        (Some(e), FlowDef::Learned { .. }) => (setup::sim_config(&e.cfg, bg_kind), Mode::Ego { background: Controller::External }),
        (None, FlowDef::Idm) => (SimConfig::default(), Mode::AllIdm),
        (None, FlowDef::Learned { background, kind, .. }) => {
            if !kind.multi_agent() {
                bail!("flow `{}` ({}) needs an ego to act against; evaluate it with an ego", cell.flow, kind.as_str());
            }
            (setup::sim_config(&background.cfg, None), Mode::MultiAgent)
        }
    };
    if let (Some(e), FlowDef::Learned { background, .. }) = (ego, flow) {
        if setup::obs_spec(&e.cfg).layout != setup::obs_spec(&background.cfg).layout {
            bail!("ego `{}` and flow `{}` observe in different layouts", cell.ego, cell.flow);
        }
    }
    let ego = ego.map(|e| runners.get(e, &cell.scenario, &sim)).transpose()?;
    let (background, adversary) = match flow {
        FlowDef::Idm => (None, None),
        FlowDef::Learned { background, adversary, .. } => (Some(runners.get(background, &cell.scenario, &sim)?), adversary.as_ref().map(|a| runners.get(a, &cell.scenario, &sim)).transpose()?),
    };
    let svo_gaussian = match flow {
        FlowDef::Learned { background, .. } if cell.svo_deg.is_none() => background.coordinator.as_ref().and_then(|c| c.gaussian(&cell.scenario)),
        _ => None,
    };
    Ok((Arc::new(sim), mode, Acting { ego, background, adversary, svo_gaussian }))
}

/// An episode's tag: its case index and seed (the simulator's per-episode draws, such as CoPO
/// Stage 2's SVOs, follow the tag, so each seed gets its own).
fn episode_tag(seed: u32, case: usize) -> u64 {
    (seed as u64) << 32 | case as u64
}

/// Runs one cell; rows in (case, seed) order.
fn run_cell(cell: &Cell, cfg: &EvalConfig, map: &Arc<Map>, cases: &sf_sim::CaseFile, flows: &BTreeMap<String, FlowDef>, egos: &BTreeMap<String, Trained>, runners: &mut Runners) -> Result<Vec<EpisodeRow>> {
    let flow = flows.get(&cell.flow).with_context(|| format!("flow `{}`", cell.flow))?;
    let ego = if cell.ego.is_empty() { None } else { Some(egos.get(&cell.ego).with_context(|| format!("ego `{}`", cell.ego))?) };
    let (sim, mode, acting) = cell_setup(cell, flow, ego, runners)?;
    let n_cases = cfg.cases as usize;
    if n_cases > cases.cases.len() {
        bail!("eval config field `cases`: {} exceeds the {} stored cases of {}", n_cases, cases.cases.len(), cell.scenario);
    }
    let mut rows = Vec::with_capacity(n_cases * cfg.seeds as usize);
    for seed in 0..cfg.seeds {
        let eps: Vec<EpisodeSpec> = (0..n_cases).map(|c| EpisodeSpec { case: cases.cases[c].clone(), vehicles: cell.vehicles, svo_deg: cell.svo_deg.map(|s| s as f32), tag: episode_tag(seed, c) }).collect();
        let mut v = VecEnv::from_episodes(Arc::clone(map), Arc::clone(&sim), mode, cfg.envs, eps).map_err(anyhow::Error::msg)?;
        v.set_svo_gaussian(acting.svo_gaussian);
        let mut rng = ChaCha8Rng::seed_from_u64(seed as u64);
        let mut done: Vec<Option<sf_sim::metrics::EpisodeMetrics>> = vec![None; n_cases];
        for (tag, m) in drive::run_episodes(&mut v, &acting.drivers(), &mut rng, |_, _| {}) {
            done[(tag & 0xffff_ffff) as usize] = Some(m);
        }
        for (c, m) in done.into_iter().enumerate() {
            let m = m.with_context(|| format!("case {c} did not finish"))?;
            rows.push(EpisodeRow {
                experiment: cell.experiment.clone(),
                ego: cell.ego.clone(),
                flow: cell.flow.clone(),
                scenario: cell.scenario.clone(),
                svo_deg: cell.svo_deg,
                vehicles: cell.vehicles,
                case: cases.cases[c].id,
                seed,
                success: m.success,
                safety: m.safety,
                speed: m.speed,
                collision: m.collision,
            });
        }
    }
    Ok(rows)
}

/// One episode of `case` with the ego under each flow, rendered side by side into a GIF.
#[allow(clippy::too_many_arguments)]
fn render_gif(g: &Gifs, scenario: &str, map: &Arc<Map>, cases: &sf_sim::CaseFile, flows: &BTreeMap<String, FlowDef>, egos: &BTreeMap<String, Trained>, runners: &mut Runners, path: &Path) -> Result<()> {
    use sf_sim::render::{side_by_side, ColourBy, GifWriter, Renderer};
    let case = cases.cases.get(g.case as usize).with_context(|| format!("experiments.gifs.case {} is not stored for {scenario}", g.case))?;
    let renderer = Renderer::new(map, 320, ColourBy::Svo)?;
    let mut films = Vec::new();
    for f in &g.flows {
        let cell = Cell { experiment: "gif".into(), ego: g.ego.clone(), flow: f.clone(), scenario: scenario.into(), svo_deg: None, vehicles: None };
        let flow = flows.get(f).context("flow")?;
        let ego = egos.get(&g.ego).context("ego")?;
        let (sim, mode, acting) = cell_setup(&cell, flow, Some(ego), runners)?;
        let mut v = VecEnv::from_episodes(Arc::clone(map), sim, mode, 1, vec![EpisodeSpec { case: case.clone(), vehicles: None, svo_deg: None, tag: 0 }]).map_err(anyhow::Error::msg)?;
        v.set_svo_gaussian(acting.svo_gaussian);
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut frames = vec![renderer.frame(v.env(0))];
        drive::run_episodes(&mut v, &acting.drivers(), &mut rng, |v, _| frames.push(renderer.frame(v.env(0))));
        films.push(frames);
    }
    let len = films.iter().map(Vec::len).max().unwrap_or(0);
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let out = std::io::BufWriter::new(file);
    let mut gif: Option<GifWriter<_>> = None;
    let mut out = Some(out);
    for k in 0..len {
        let row: Vec<&sf_sim::render::Pixmap> = films.iter().filter_map(|f| f.get(k).or_else(|| f.last())).collect();
        let pm = side_by_side(&row).context("composing frames")?;
        if let Some(o) = out.take() {
            gif = Some(GifWriter::new(o, pm.width(), pm.height(), 10)?);
        }
        if let Some(w) = gif.as_mut() {
            w.push(&pm)?;
        }
    }
    Ok(())
}

pub fn run(ctx: &Ctx, a: EvalArgs) -> Result<()> {
    let mut cfg = EvalConfig::load(&a.config)?;
    if let Some(o) = a.out {
        cfg.out = o;
    }
    // Everything named must exist before anything runs.
    let mut flows = BTreeMap::new();
    for f in &cfg.flows {
        flows.insert(f.name.clone(), flow_def(&cfg.runs, &f.job).with_context(|| format!("flow `{}`", f.name))?);
    }
    let mut egos = BTreeMap::new();
    for e in &cfg.egos {
        let t = find_job(&cfg.runs, &e.job).with_context(|| format!("ego `{}`", e.name))?;
        if t.cfg.kind != JobKind::Ego {
            bail!("ego `{}`: job `{}` is a {} job", e.name, e.job, t.cfg.kind.as_str());
        }
        egos.insert(e.name.clone(), t);
    }
    let mut scen: BTreeSet<String> = cfg.scenarios.iter().cloned().collect();
    if let Some(s) = &cfg.experiments.svo_sweep {
        scen.extend(s.scenarios.iter().cloned());
    }
    if let Some(d) = &cfg.experiments.density {
        scen.insert(d.scenario.clone());
    }
    if let Some(g) = &cfg.experiments.gifs {
        scen.extend(g.scenarios.iter().cloned());
    }
    let mut maps = BTreeMap::new();
    let mut runners = Runners { device: sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?, segments: BTreeMap::new(), cache: BTreeMap::new() };
    for s in &scen {
        let m = ctx.map(s)?;
        let c = ctx.cases(&m)?;
        runners.segments.insert(s.clone(), Arc::new(MapSegments::build(&m, SimConfig::default().obs.segment_points)));
        maps.insert(s.clone(), (m, c));
    }
    std::fs::create_dir_all(&cfg.out).with_context(|| format!("creating {}", cfg.out.display()))?;
    let meta = sf_eval::report::Meta {
        trained_in: cfg.egos.iter().filter_map(|e| e.trained_in.clone().map(|t| (e.name.clone(), t))).collect(),
        ours: cfg.ours.clone(),
        flows: cfg.flows.iter().map(|f| f.name.clone()).collect(),
        egos: cfg.egos.iter().map(|f| f.name.clone()).collect(),
        cases: cfg.cases,
        seeds: cfg.seeds,
    };
    let meta_path = cfg.out.join("meta.json");
    std::fs::write(&meta_path, serde_json::to_string_pretty(&meta)?).with_context(|| format!("writing {}", meta_path.display()))?;
    let path = cfg.out.join("episodes.csv");
    let stored = sf_eval::report::read_episodes(&path).with_context(|| format!("reading {}", path.display()))?;
    let have: BTreeSet<String> = stored.iter().map(|r| Cell::of(r).key()).collect();
    let todo: Vec<Cell> = cells(&cfg).into_iter().filter(|c| !have.contains(&c.key())).collect();
    eprintln!("{} cells to run ({} stored), {} episodes each", todo.len(), have.len(), cfg.cases * cfg.seeds);
    let new_file = !path.exists();
    let mut file = std::fs::OpenOptions::new().create(true).append(true).open(&path).with_context(|| format!("opening {}", path.display()))?;
    if new_file {
        writeln!(file, "{EPISODES_HEADER}")?;
    }
    for (k, cell) in todo.iter().enumerate() {
        let (map, cases) = maps.get(&cell.scenario).context("scenario loaded")?;
        let t = std::time::Instant::now();
        let rows = run_cell(cell, &cfg, map, cases, &flows, &egos, &mut runners).with_context(|| format!("cell {}", cell.key()))?;
        // One write per cell: a cell is stored whole or not at all.
        let text: String = rows.iter().map(|r| r.to_csv() + "\n").collect();
        file.write_all(text.as_bytes())?;
        file.flush()?;
        let s = rows.iter().map(|r| r.success as f64).sum::<f64>() / rows.len().max(1) as f64;
        eprintln!("[{}/{}] {:<64} success {:5.1}%  ({:.1} s)", k + 1, todo.len(), cell.key(), 100.0 * s, t.elapsed().as_secs_f64());
    }
    eprintln!("wrote {}", path.display());
    if let Some(g) = &cfg.experiments.gifs {
        for s in &g.scenarios {
            let gif = cfg.out.join(format!("gif-{s}.gif"));
            if gif.exists() {
                continue;
            }
            let (map, cases) = maps.get(s).context("scenario loaded")?;
            render_gif(g, s, map, cases, &flows, &egos, &mut runners, &gif).with_context(|| format!("rendering {}", gif.display()))?;
            eprintln!("wrote {}", gif.display());
        }
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct ReportArgs {
    /// A results directory written by `socialflow eval` (`episodes.csv`, `meta.json`).
    pub results: PathBuf,
    /// Where `report.md`, `report.html` and the figures go.
    #[arg(long, default_value = "report")]
    pub out: PathBuf,
}

/// Builds the report from stored results; prints the findings as JSON.
pub fn report(a: ReportArgs) -> Result<()> {
    let rows = sf_eval::report::read_episodes(&a.results.join("episodes.csv"))?;
    if rows.is_empty() {
        bail!("{} holds no evaluated episodes (run `socialflow eval` first)", a.results.join("episodes.csv").display());
    }
    let meta = sf_eval::report::read_meta(&a.results.join("meta.json"))?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    for e in std::fs::read_dir(&a.results).with_context(|| format!("reading {}", a.results.display()))?.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        if name.starts_with("gif-") && name.ends_with(".gif") {
            std::fs::copy(e.path(), a.out.join(&name)).with_context(|| format!("copying {name}"))?;
        }
    }
    let f = sf_eval::report::build(&rows, &meta, &a.out)?;
    println!("{}", serde_json::to_string(&f)?);
    eprintln!("wrote {}/report.md and report.html", a.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_eval_configs_are_valid_and_expand_to_the_papers_grid() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/eval/paper-small.toml");
        let c = EvalConfig::load(&p).expect("valid");
        let cells = cells(&c);
        let count = |e: &str| cells.iter().filter(|c| c.experiment == e).count();
        assert_eq!(count("cross"), 6 * 4 * 4, "6 egos x 4 flows x 4 scenarios");
        assert_eq!(count("svo_sweep"), 2 * 4 * 10);
        assert_eq!(count("density"), 4 * 6);
        let keys: BTreeSet<String> = cells.iter().map(Cell::key).collect();
        assert_eq!(keys.len(), cells.len(), "cells are distinct");
        let svos: BTreeSet<u32> = cells.iter().filter_map(|c| c.svo_deg).collect();
        assert_eq!(svos.into_iter().collect::<Vec<_>>(), vec![0, 10, 20, 30, 40, 50, 60, 70, 80, 90]);
        // The flows-only grid: the same flow cells, no ego.
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/eval/paper-small-flows.toml");
        let flows = super::cells(&EvalConfig::load(&p).expect("valid"));
        assert!(flows.iter().all(|c| c.ego.is_empty()), "no ego cells");
        let flow_keys: BTreeSet<String> = flows.iter().map(Cell::key).collect();
        let full_flow_keys: BTreeSet<String> = cells.iter().filter(|c| c.ego.is_empty()).map(Cell::key).collect();
        assert_eq!(flow_keys, full_flow_keys, "the flows-only grid is the full grid's flow cells");
    }

    #[test]
    fn bad_eval_configs_name_the_field() {
        let base = "runs = \"r\"\nout = \"o\"\nscenarios = [\"merge\"]\ncases = 2\nseeds = 1\nflows = [{ name = \"IDM\", job = \"idm\" }]\negos = []\n";
        let dir = std::env::temp_dir().join(format!("sf-evalcfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        for (extra, needle) in [("[experiments]\nflow_quality = [\"Nope\"]\n", "experiments.flow_quality"), ("ours = \"X\"\n", "ours"), ("", "")] {
            let text = if extra.starts_with("ours") { format!("{extra}{base}") } else { format!("{base}{extra}") };
            let p = dir.join("e.toml");
            std::fs::write(&p, text).expect("write");
            match EvalConfig::load(&p) {
                Ok(_) => assert!(needle.is_empty(), "{needle} accepted"),
                Err(e) => assert!(!needle.is_empty() && format!("{e:#}").contains(needle), "{e:#}"),
            }
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
