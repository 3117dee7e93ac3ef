//! Evaluation jobs: the config of an evaluation grid, its cells, and what one cell's episodes
//! return.
//!
//! Owns: [`EvalConfig`] (`kind = "eval"`: which flows and ego policies, which experiments, how
//! many stored cases and seeds, grid-wide or per experiment ([`SizeOverride`]); validated with
//! errors that name the field), the expansion of its experiments into [`Cell`]s
//! ([`EvalConfig::cells`]) and each cell's size ([`EvalConfig::size_of`]), the work a worker is handed for one
//! cell ([`EvalWork`]) and the metrics of one evaluated episode ([`EvalEpisode`]). Both
//! `socialflow eval` (embedded) and the learner's evaluation jobs (cells shared by workers)
//! expand the same config into the same cells. Must not: run simulations (`sf_rollout::evaluate`
//! does) or know the results file (`sf_report::report` does).

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use sf_sim::config::MessageProbe;

use crate::ids::{CellId, JobId};
use crate::record::Frozen;

/// A config that is not a valid evaluation grid; the message names the field.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{0}")]
pub struct EvalConfigError(pub String);

fn bad<T>(msg: impl Into<String>) -> Result<T, EvalConfigError> {
    Err(EvalConfigError(msg.into()))
}

/// The reserved job name of IDM with MOBIL's lane changes in the ego's seat.
pub const IDM_MOBIL: &str = "idm-mobil";
/// The reserved job name of the noise-matched IDM flow: the IDM driver plus a learned flow's
/// sampling noise on each component of the lateral residual (`noise_std`).
pub const IDM_NOISE: &str = "idm-noise";
/// `noise_std` of an `idm-noise` flow by default: the standard deviation the learned flows'
/// cloning term pulls their log-std to (`ln 0.3`).
pub const DEFAULT_FLOW_NOISE_STD: f32 = 0.3;

/// A scripted driver in an evaluation cell's ego seat (an ego of `job = "idm"` or
/// `job = "idm-mobil"`): no policy travels for it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScriptedEgo {
    /// The IDM driver (lane keeping).
    Idm,
    /// IDM with MOBIL's lane changes.
    IdmMobil,
}

/// Which scripted egos a worker can seat (what it registered with); cells with another
/// scripted ego are never leased to it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ScriptedSeats {
    pub idm: bool,
    pub mobil: bool,
}

impl ScriptedSeats {
    /// Every scripted ego.
    pub const ALL: Self = Self { idm: true, mobil: true };

    /// Whether a cell with this ego seat can go to the worker (a cell without a scripted ego
    /// always can).
    pub fn runs(self, ego: Option<ScriptedEgo>) -> bool {
        match ego {
            None => true,
            Some(ScriptedEgo::Idm) => self.idm,
            Some(ScriptedEgo::IdmMobil) => self.mobil,
        }
    }
}

/// A named flow (`idm`, or the job whose final policy it is) or ego policy.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Named {
    pub name: String,
    /// The job's name (the newest succeeded job of that name), or `idm`: the IDM flow, or as an
    /// ego the IDM driver in the ego's seat (the zero residual: what every trained ego starts
    /// from); or, as an ego only, `idm-mobil`: IDM with MOBIL's lane changes, a reference driver
    /// that steers.
    pub job: String,
    /// Pins the job by id. The learner fills it in when it accepts an evaluation job, so the
    /// job evaluates what existed at submission.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job_id: Option<JobId>,
    /// Egos: the flow (by name) the ego was trained in; its cell is grey in the heatmaps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trained_in: Option<String>,
    /// Learned flows, a probe: constants in place of the SVOs its observers are told (`{
    /// neighbours_deg = 45 }`: every neighbour's; `{ told_ego_deg = 0 }`: the ego's, a
    /// constant-message adversary). `socialflow eval` only.
    #[serde(default, skip_serializing_if = "MessageProbe::is_off")]
    pub messages: MessageProbe,
    /// Egos, a probe: the job is a Stage-1 flow (MACAD, CoPO, SocialComm) whose actor drives
    /// in the ego's seat, zero-shot. `socialflow eval` only.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub flow_actor: bool,
    /// `job = "idm-noise"` flows only: the standard deviation of the noise on each action
    /// component, in (0, 3] (default [`DEFAULT_FLOW_NOISE_STD`]). `socialflow eval` only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_std: Option<f32>,
}

impl Named {
    pub fn is_idm(&self) -> bool {
        self.job == "idm"
    }

    /// IDM with MOBIL's lane changes in the ego's seat.
    pub fn is_idm_mobil(&self) -> bool {
        self.job == IDM_MOBIL
    }

    /// The noise-matched IDM flow (`job = "idm-noise"`).
    pub fn is_idm_noise(&self) -> bool {
        self.job == IDM_NOISE
    }

    /// An `idm-noise` flow's noise standard deviation.
    pub fn noise_std(&self) -> f32 {
        self.noise_std.unwrap_or(DEFAULT_FLOW_NOISE_STD)
    }

    /// A scripted driver or flow (`idm`, `idm-mobil`, `idm-noise`), not a stored job.
    pub fn is_scripted(&self) -> bool {
        self.scripted().is_some() || self.is_idm_noise()
    }

    /// As an ego: the scripted driver it names, if any.
    pub fn scripted(&self) -> Option<ScriptedEgo> {
        match self.job.as_str() {
            "idm" => Some(ScriptedEgo::Idm),
            IDM_MOBIL => Some(ScriptedEgo::IdmMobil),
            _ => None,
        }
    }

    /// Whether the entry asks for an evaluation probe (a message constant or a flow's actor in
    /// the ego's seat), which only `socialflow eval` runs.
    pub fn is_probe(&self) -> bool {
        !self.messages.is_off() || self.flow_actor
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SvoSweep {
    pub flows: Vec<String>,
    /// Number of SVO values, evenly spaced over [0, 90] deg.
    pub values: usize,
    pub scenarios: Vec<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Density {
    pub scenario: String,
    pub flows: Vec<String>,
    pub vehicles: Vec<usize>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Adversary {
    pub egos: Vec<String>,
    pub flows: Vec<String>,
}

/// GIFs of the same stored case with one ego under several flows, side by side; with no `ego`
/// (or `ego = ""`), each flow alone, driving every vehicle (as flow quality runs it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gifs {
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub ego: String,
    pub flows: Vec<String>,
    pub scenarios: Vec<String>,
    #[serde(default)]
    pub case: u32,
    /// The longer side of each flow's panel in pixels (default [`Gifs::DEFAULT_SIZE_PX`]);
    /// panels of maps more than twice as wide as tall are stacked top to bottom, others placed
    /// side by side.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size_px: Option<u32>,
}

impl Gifs {
    pub const DEFAULT_SIZE_PX: u32 = 320;
    /// The accepted range of `size_px`.
    pub const SIZE_PX: std::ops::RangeInclusive<u32> = 64..=2048;

    /// The longer side of each panel in pixels.
    pub fn size_px(&self) -> u32 {
        self.size_px.unwrap_or(Self::DEFAULT_SIZE_PX)
    }
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Experiments {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gifs: Option<Gifs>,
    /// Flows evaluated on their own (every vehicle of the case driven by the flow).
    pub flow_quality: Vec<String>,
    /// Every ego in each of these flows (the paper: the four non-adversarial ones).
    pub cross_validation: Vec<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub svo_sweep: Option<SvoSweep>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub density: Option<Density>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub adversary: Option<Adversary>,
}

/// The experiments of a grid, as [`Cell::experiment`] names them (cross-validation's cells are
/// `cross`): the keys of [`EvalConfig::sizes`].
pub const EXPERIMENTS: [&str; 5] = ["flow_quality", "cross", "svo_sweep", "density", "adversary"];

/// A cell of a grid that asks for more stored cases than its scenario has.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("eval config field `{field}`: {cases} exceeds the {stored} stored cases of {scenario}")]
pub struct TooFewCases {
    pub field: String,
    pub cases: u32,
    pub stored: usize,
    pub scenario: String,
}

/// One experiment's own number of stored cases and seeds (`[sizes]` of an eval config); a
/// field left out is the grid-wide value.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SizeOverride {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cases: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seeds: Option<u32>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalConfig {
    /// Always `"eval"`: what tells an evaluation grid from a training job when one is submitted.
    pub kind: String,
    /// Shown in job lists and used for the artifact directory (default `eval`).
    #[serde(default = "d_name")]
    pub name: String,
    /// `socialflow eval` (embedded) only: the data directory of the learner (or embedded
    /// pipeline) that trained the jobs. A learner evaluates its own jobs and ignores it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runs: Option<PathBuf>,
    /// `socialflow eval` (embedded) only: where `episodes.csv`, `meta.json` and the GIFs go.
    /// A learner writes them to the job's artifact directory and ignores it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub out: Option<PathBuf>,
    pub scenarios: Vec<String>,
    /// The first N stored cases of each scenario, in every cell not sized by `sizes`.
    pub cases: u32,
    /// Seeds per stored case, in every cell not sized by `sizes`.
    pub seeds: u32,
    /// Experiment name (one of [`EXPERIMENTS`]) -> its own cases and/or seeds, e.g.
    /// `adversary = { cases = 200, seeds = 2 }`. Read through [`EvalConfig::size_of`].
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub sizes: BTreeMap<String, SizeOverride>,
    /// Episodes stepped together: how fast a cell runs, not how its episodes end (every draw is
    /// the episode's own and learned policies infer in fixed-width calls).
    #[serde(default = "d_envs")]
    pub envs: usize,
    pub flows: Vec<Named>,
    pub egos: Vec<Named>,
    /// The ego the paper proposes; the report tests it against the others.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ours: Option<String>,
    #[serde(default)]
    pub experiments: Experiments,
    /// Failure mining once every cell is stored: the N worst stored episodes of every cell
    /// replayed into viewer pages under `mined/`, with an index sorted by outcome (what
    /// `socialflow eval --mine worst=N` does). 1 to [`EvalConfig::MAX_MINE_WORST`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mine_worst: Option<usize>,
}

fn d_envs() -> usize {
    32
}

fn d_name() -> String {
    "eval".into()
}

/// Whether a submitted TOML text is an evaluation grid (`kind = "eval"`) rather than a job.
pub fn is_eval_toml(text: &str) -> bool {
    text.parse::<toml::Table>()
        .is_ok_and(|t| t.get("kind").and_then(|k| k.as_str()) == Some("eval"))
}

/// One cell of the grid: `cases x seeds` episodes ([`EvalConfig::size_of`]).
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Cell {
    pub experiment: String,
    /// Empty when the flow is evaluated on its own.
    pub ego: String,
    pub flow: String,
    pub scenario: String,
    /// SVO sweep: every agent's SVO. Empty otherwise.
    pub svo_deg: Option<u32>,
    /// Density sweep: vehicles per case. Empty otherwise.
    pub vehicles: Option<usize>,
}

impl Cell {
    /// The cell's identity in results files and logs.
    pub fn key(&self) -> String {
        let opt = |v: Option<String>| v.unwrap_or_default();
        format!(
            "{}|{}|{}|{}|{}|{}",
            self.experiment,
            self.ego,
            self.flow,
            self.scenario,
            opt(self.svo_deg.map(|v| v.to_string())),
            opt(self.vehicles.map(|v| v.to_string()))
        )
    }
}

/// An evaluated episode's metric outside [0, 1].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("episode (case {case}, seed {seed}): {metric} {value} is not in [0, 1]")]
pub struct MetricRangeError {
    pub case: u32,
    pub seed: u32,
    pub metric: &'static str,
    pub value: f32,
}

/// The metrics of one evaluated episode of a cell.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvalEpisode {
    /// The stored case's id.
    pub case: u32,
    pub seed: u32,
    pub scores: sf_sim::Scores,
    pub collision: f32,
    /// The share of the scored agents that left their route's lane at some point (a lane
    /// change, a cut-in, or drifting out of it); `None` where it was not recorded (results
    /// written before it was, and Python's `evaluate`).
    pub lane_change: Option<f32>,
    /// The share of the scored agents that timed out with standing vehicles closing the road
    /// ahead of them (`sf_sim::passage`); `None` where it was not recorded (results written
    /// before 2026-11-29, Python's `evaluate`).
    pub road_closed: Option<f32>,
}

impl EvalEpisode {
    /// Every metric is a fraction in [0, 1].
    pub fn validate(&self) -> Result<(), MetricRangeError> {
        for (metric, value) in [
            ("success", self.scores.success),
            ("safety", self.scores.safety),
            ("speed", self.scores.speed),
            ("collision", self.collision),
            ("lane_change", self.lane_change.unwrap_or(0.0)),
            ("road_closed", self.road_closed.unwrap_or(0.0)),
        ] {
            if !(0.0..=1.0).contains(&value) {
                return Err(MetricRangeError { case: self.case, seed: self.seed, metric, value });
            }
        }
        Ok(())
    }
}

/// One cell handed to a worker by an evaluation job.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalWork {
    pub job_id: JobId,
    /// The cell's index in the job's grid; results name it.
    pub cell_id: CellId,
    pub cell: Cell,
    pub cases: u32,
    pub seeds: u32,
    pub envs: u32,
    /// What acts in the cell: the ego (role `Ego`), the learned flow (`Background`, with a CoPO
    /// coordinator's Gaussians) and SocialCommAdv's adversary (`Adversary`). No `Background`:
    /// the IDM flow. Their weights are each job's final policy (GetPolicy, version 0).
    pub policies: Vec<Frozen>,
    /// A scripted driver sits in the ego's seat (an ego of `job = "idm"` or `"idm-mobil"`; no
    /// `Ego` policy then).
    pub scripted_ego: Option<ScriptedEgo>,
}

impl EvalConfig {
    pub fn from_toml(text: &str) -> Result<Self, EvalConfigError> {
        let c: Self = toml::from_str(text).map_err(|e| {
            EvalConfigError(format!(
                "eval config is not valid TOML for an evaluation: {}",
                e.to_string().trim_end()
            ))
        })?;
        c.validate()?;
        Ok(c)
    }

    /// The config with every default written out.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("an eval config always serialises to TOML")
    }

    /// The most episodes per cell `mine_worst` replays (each is a page of ~100 KB).
    pub const MAX_MINE_WORST: usize = 100;

    pub fn validate(&self) -> Result<(), EvalConfigError> {
        if let Some(n) = self.mine_worst.filter(|n| !(1..=Self::MAX_MINE_WORST).contains(n)) {
            return bad(format!(
                "eval config field `mine_worst`: {n} is not in 1..={} episodes per cell",
                Self::MAX_MINE_WORST
            ));
        }
        if self.kind != "eval" {
            return bad(format!("eval config field `kind`: `{}`, expected \"eval\"", self.kind));
        }
        if self.name.is_empty()
            || !self.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return bad("eval config field `name`: letters, digits, '-' and '_' only");
        }
        if self.cases == 0 || self.seeds == 0 || self.envs == 0 {
            return bad("eval config fields `cases`, `seeds` and `envs` must be positive");
        }
        for (experiment, size) in &self.sizes {
            if !EXPERIMENTS.contains(&experiment.as_str()) {
                return bad(format!(
                    "eval config field `sizes.{experiment}`: not an experiment ({})",
                    EXPERIMENTS.join(", ")
                ));
            }
            for (field, value) in [("cases", size.cases), ("seeds", size.seeds)] {
                if value == Some(0) {
                    return bad(format!(
                        "eval config field `sizes.{experiment}.{field}` must be positive"
                    ));
                }
            }
        }
        if self.scenarios.is_empty() {
            return bad("eval config field `scenarios`: list at least one");
        }
        let flows: BTreeSet<&str> = self.flows.iter().map(|f| f.name.as_str()).collect();
        let egos: BTreeSet<&str> = self.egos.iter().map(|f| f.name.as_str()).collect();
        if flows.len() != self.flows.len() || egos.len() != self.egos.len() {
            return bad("eval config fields `flows` / `egos`: names must be unique");
        }
        for n in self
            .flows
            .iter()
            .chain(&self.egos)
            .map(|f| f.name.as_str())
            .chain(self.scenarios.iter().map(String::as_str))
        {
            if n.is_empty() || n.contains([',', '|', '\n']) {
                return bad(format!(
                    "eval config: name `{n}` must be non-empty without ',' or '|'"
                ));
            }
        }
        // `job = "idm"` as an ego: the IDM driver in the ego's seat, the baseline every trained
        // ego is tested against. It was trained nowhere and is not the proposed method.
        if self.egos.iter().filter(|e| e.is_idm()).count() > 1 {
            return bad(
                "eval config field `egos`: at most one ego may be the IDM driver (`job = \"idm\"`)",
            );
        }
        if self.egos.iter().filter(|e| e.is_idm_mobil()).count() > 1 {
            return bad(format!("eval config field `egos`: at most one ego may be the MOBIL driver (`job = \"{IDM_MOBIL}\"`)"));
        }
        if let Some(n) = self.egos.iter().find(|n| n.is_idm_noise()) {
            return bad(format!("eval config field `egos.job` of `{}`: `{IDM_NOISE}` is a flow, not a driver of the ego's seat", n.name));
        }
        if let Some(n) =
            self.flows.iter().chain(&self.egos).find(|n| n.noise_std.is_some() && !n.is_idm_noise())
        {
            return bad(format!("eval config field `noise_std` of `{}`: only a `job = \"{IDM_NOISE}\"` flow has a noise", n.name));
        }
        if let Some(n) = self.flows.iter().find(|n| !(n.noise_std() > 0.0 && n.noise_std() <= 3.0))
        {
            return bad(format!(
                "eval config field `noise_std` of `{}`: {} is not in (0, 3]",
                n.name,
                n.noise_std()
            ));
        }
        if let Some(n) = self.flows.iter().find(|n| n.is_idm_mobil()) {
            return bad(format!("eval config field `flows.job` of `{}`: `{IDM_MOBIL}` drives the ego's seat only, not a flow", n.name));
        }
        if let Some(n) =
            self.flows.iter().chain(&self.egos).find(|n| n.is_scripted() && n.job_id.is_some())
        {
            return bad(format!("eval config field `job_id` of `{}`: `job = \"{}\"` is a scripted driver, not a stored job", n.name, n.job));
        }
        if let Some(e) = self.egos.iter().find(|e| e.is_scripted() && e.trained_in.is_some()) {
            return bad(format!("eval config field `egos.trained_in` of `{}`: the scripted driver `job = \"{}\"` was not trained in a flow", e.name, e.job));
        }
        if let Some(n) = self.flows.iter().find(|n| n.flow_actor) {
            return bad(format!(
                "eval config field `flow_actor` of flow `{}`: only an ego can be a flow's actor",
                n.name
            ));
        }
        if let Some(n) = self.egos.iter().find(|n| !n.messages.is_off()) {
            return bad(format!(
                "eval config field `messages` of ego `{}`: message probes belong to a learned flow",
                n.name
            ));
        }
        if let Some(n) = self
            .flows
            .iter()
            .chain(&self.egos)
            .find(|n| n.is_scripted() && (!n.messages.is_off() || n.flow_actor))
        {
            return bad(format!("eval config entry `{}`: a probe (`messages`, `flow_actor`) needs a learned job, not `job = \"{}\"`", n.name, n.job));
        }
        if let Some((n, (field, v))) =
            self.flows.iter().find_map(|n| n.messages.out_of_range().map(|o| (n, o)))
        {
            return bad(format!("eval config field `messages.{field}` of flow `{}`: {v} is not an SVO in [-90, 90] degrees", n.name));
        }
        if let Some(o) = self.ours.as_ref().filter(|o| !egos.contains(o.as_str())) {
            return bad(format!("eval config field `ours`: `{o}` is not one of `egos`"));
        }
        if let Some(o) = self.ours.as_ref().filter(|o| self.ego(o).is_some_and(Named::is_scripted))
        {
            return bad(format!(
                "eval config field `ours`: `{o}` is a scripted driver, not a trained ego"
            ));
        }
        for e in &self.egos {
            if let Some(t) = e.trained_in.as_ref().filter(|t| !flows.contains(t.as_str())) {
                return bad(format!(
                    "eval config field `egos.trained_in` of `{}`: `{t}` is not one of `flows`",
                    e.name
                ));
            }
        }
        let e = &self.experiments;
        let mut need_flows: Vec<(&str, &String)> =
            e.flow_quality.iter().map(|f| ("experiments.flow_quality", f)).collect();
        need_flows.extend(e.cross_validation.iter().map(|f| ("experiments.cross_validation", f)));
        let mut need_egos: Vec<(&str, &String)> = Vec::new();
        if let Some(s) = &e.svo_sweep {
            need_flows.extend(s.flows.iter().map(|f| ("experiments.svo_sweep.flows", f)));
            // SVOs are whole degrees in [0, 90]: more than 91 values would repeat cells (and an
            // unbounded count would make `cells()` below allocate without end).
            if !(2..=91).contains(&s.values) {
                return bad(format!("eval config field `experiments.svo_sweep.values`: {}, expected 2 to 91 (whole degrees in [0, 90])", s.values));
            }
        }
        if let Some(d) = &e.density {
            need_flows.extend(d.flows.iter().map(|f| ("experiments.density.flows", f)));
            if d.vehicles.is_empty() || d.vehicles.contains(&0) {
                return bad(
                    "eval config field `experiments.density.vehicles`: positive vehicle counts",
                );
            }
        }
        if let Some(g) = &e.gifs {
            if !Gifs::SIZE_PX.contains(&g.size_px()) {
                return bad(format!(
                    "eval config field `experiments.gifs.size_px`: {} is not in {}..={} pixels",
                    g.size_px(),
                    Gifs::SIZE_PX.start(),
                    Gifs::SIZE_PX.end()
                ));
            }
            need_flows.extend(g.flows.iter().map(|f| ("experiments.gifs.flows", f)));
            if !g.ego.is_empty() {
                need_egos.push(("experiments.gifs.ego", &g.ego));
            }
        }
        if let Some(a) = &e.adversary {
            need_flows.extend(a.flows.iter().map(|f| ("experiments.adversary.flows", f)));
            need_egos.extend(a.egos.iter().map(|f| ("experiments.adversary.egos", f)));
        }
        for (field, f) in need_flows {
            if !flows.contains(f.as_str()) {
                return bad(format!("eval config field `{field}`: `{f}` is not one of `flows`"));
            }
        }
        for (field, f) in need_egos {
            if !egos.contains(f.as_str()) {
                return bad(format!("eval config field `{field}`: `{f}` is not one of `egos`"));
            }
        }
        if self.cells().is_empty() {
            return bad("eval config field `experiments`: the grid has no cells");
        }
        Ok(())
    }

    /// Every scenario a cell or GIF of the grid runs in.
    pub fn all_scenarios(&self) -> BTreeSet<String> {
        let mut s: BTreeSet<String> = self.scenarios.iter().cloned().collect();
        let e = &self.experiments;
        if let Some(sw) = &e.svo_sweep {
            s.extend(sw.scenarios.iter().cloned());
        }
        if let Some(d) = &e.density {
            s.insert(d.scenario.clone());
        }
        if let Some(g) = &e.gifs {
            s.extend(g.scenarios.iter().cloned());
        }
        s
    }

    pub fn flow(&self, name: &str) -> Option<&Named> {
        self.flows.iter().find(|f| f.name == name)
    }

    pub fn ego(&self, name: &str) -> Option<&Named> {
        self.egos.iter().find(|f| f.name == name)
    }

    /// `(cases, seeds)` of `cell`: its experiment's entry in `sizes`, field by field, else the
    /// grid-wide `cases` and `seeds`.
    pub fn size_of(&self, cell: &Cell) -> (u32, u32) {
        let o = self.sizes.get(&cell.experiment).copied().unwrap_or_default();
        (o.cases.unwrap_or(self.cases), o.seeds.unwrap_or(self.seeds))
    }

    /// The episodes of `cell`: its cases times its seeds.
    pub fn episodes_of(&self, cell: &Cell) -> u64 {
        let (cases, seeds) = self.size_of(cell);
        cases as u64 * seeds as u64
    }

    /// The episodes of every cell of the grid together.
    pub fn episodes(&self) -> u64 {
        self.cells().iter().map(|c| self.episodes_of(c)).sum()
    }

    /// Every cell's cases against what its scenario has stored (`stored(scenario)`): the first
    /// cell that asks for more is named by the field that set its size (`cases`, or
    /// `sizes.<experiment>.cases`).
    pub fn check_stored_cases(&self, stored: impl Fn(&str) -> usize) -> Result<(), TooFewCases> {
        for cell in self.cells() {
            let (cases, have) = (self.size_of(&cell).0, stored(&cell.scenario));
            if cases as usize > have {
                let field = if self.sizes.get(&cell.experiment).is_some_and(|s| s.cases.is_some()) {
                    format!("sizes.{}.cases", cell.experiment)
                } else {
                    "cases".into()
                };
                return Err(TooFewCases { field, cases, stored: have, scenario: cell.scenario });
            }
        }
        Ok(())
    }

    /// The grid's cells in a fixed order (a cell's index is its id in an evaluation job).
    pub fn cells(&self) -> Vec<Cell> {
        let cell =
            |experiment: &str, ego: &str, flow: &str, scenario: &str, svo_deg, vehicles| Cell {
                experiment: experiment.into(),
                ego: ego.into(),
                flow: flow.into(),
                scenario: scenario.into(),
                svo_deg,
                vehicles,
            };
        let e = &self.experiments;
        let mut out = Vec::new();
        for f in &e.flow_quality {
            for s in &self.scenarios {
                out.push(cell("flow_quality", "", f, s, None, None));
            }
        }
        for ego in &self.egos {
            for f in &e.cross_validation {
                for s in &self.scenarios {
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
                    for s in &self.scenarios {
                        out.push(cell("adversary", ego, f, s, None, None));
                    }
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BASE: &str = "kind = \"eval\"\nscenarios = [\"merge\"]\ncases = 2\nseeds = 1\nflows = [{ name = \"IDM\", job = \"idm\" }]\negos = [{ name = \"E\", job = \"ego-a\" }]\n[experiments]\nflow_quality = [\"IDM\"]\n";

    #[test]
    fn bad_eval_configs_name_the_field() {
        assert!(EvalConfig::from_toml(BASE).is_ok());
        for (from, to, needle) in [
            ("flow_quality = [\"IDM\"]", "flow_quality = [\"Nope\"]", "experiments.flow_quality"),
            ("kind = \"eval\"", "kind = \"ego\"", "`kind`"),
            ("cases = 2", "cases = 0", "`cases`"),
            ("cases = 2", "cases = 2\nmine_worst = 0", "`mine_worst`: 0 is not in 1..=100"),
            ("cases = 2", "cases = 2\nmine_worst = 101", "`mine_worst`: 101"),
            ("name = \"E\", job = \"ego-a\"", "name = \"E\", job = \"idm\", trained_in = \"IDM\"", "`egos.trained_in` of `E`"),
            ("egos = [{ name = \"E\", job = \"ego-a\" }]", "ours = \"I\"\negos = [{ name = \"I\", job = \"idm\" }]", "`ours`: `I` is a scripted driver"),
            ("egos = [{ name = \"E\", job = \"ego-a\" }]", "ours = \"M\"\negos = [{ name = \"M\", job = \"idm-mobil\" }]", "`ours`: `M` is a scripted driver"),
            ("egos = [{ name = \"E\", job = \"ego-a\" }]", "egos = [{ name = \"M\", job = \"idm-mobil\" }, { name = \"N\", job = \"idm-mobil\" }]", "at most one ego may be the MOBIL driver"),
            ("{ name = \"IDM\", job = \"idm\" }", "{ name = \"IDM\", job = \"idm-mobil\" }", "`flows.job` of `IDM`: `idm-mobil` drives the ego's seat only"),
            ("name = \"E\", job = \"ego-a\"", "name = \"E\", job = \"idm-mobil\", job_id = 4", "`job_id` of `E`: `job = \"idm-mobil\"` is a scripted driver"),
            ("name = \"E\", job = \"ego-a\"", "name = \"E\", job = \"idm-mobil\", trained_in = \"IDM\"", "`egos.trained_in` of `E`"),
            ("name = \"E\", job = \"ego-a\"", "name = \"E\", job = \"idm-mobil\", flow_actor = true", "needs a learned job, not `job = \"idm-mobil\"`"),
            ("egos = [{ name = \"E\", job = \"ego-a\" }]", "egos = [{ name = \"I\", job = \"idm\" }, { name = \"J\", job = \"idm\" }]", "at most one ego may be the IDM driver"),
            ("{ name = \"IDM\", job = \"idm\" }", "{ name = \"IDM\", job = \"idm\", job_id = 3 }", "`job_id` of `IDM`"),
            ("flow_quality = [\"IDM\"]", "flow_quality = []", "no cells"),
            ("seeds = 1", "seeds = 1\nbogus = 3", "bogus"),
            ("{ name = \"IDM\", job = \"idm\" }", "{ name = \"IDM\", job = \"idm\", messages = { neighbours_deg = 45.0 } }", "needs a learned job"),
            ("{ name = \"IDM\", job = \"idm\" }", "{ name = \"IDM\", job = \"flow-sc\", messages = { told_ego_deg = 120.0 } }", "`messages.told_ego_deg` of flow `IDM`"),
            ("{ name = \"IDM\", job = \"idm\" }", "{ name = \"IDM\", job = \"flow-sc\", flow_actor = true }", "only an ego can be a flow's actor"),
            ("name = \"E\", job = \"ego-a\"", "name = \"E\", job = \"ego-a\", messages = { neighbours_deg = 45.0 }", "`messages` of ego `E`"),
            ("seeds = 1", "seeds = 1\nsizes = { adversry = { cases = 3 } }", "field `sizes.adversry`: not an experiment (flow_quality, cross, svo_sweep, density, adversary)"),
            ("seeds = 1", "seeds = 1\nsizes = { cross_validation = { seeds = 3 } }", "field `sizes.cross_validation`: not an experiment"),
            ("seeds = 1", "seeds = 1\nsizes = { adversary = { cases = 0 } }", "field `sizes.adversary.cases` must be positive"),
            ("seeds = 1", "seeds = 1\nsizes = { cross = { cases = 3, seeds = 0 } }", "field `sizes.cross.seeds` must be positive"),
            ("seeds = 1", "seeds = 1\nsizes = { cross = { envs = 3 } }", "envs"),
        ] {
            let text = BASE.replace(from, to);
            let e = EvalConfig::from_toml(&text).expect_err(needle);
            assert!(e.0.contains(needle), "{needle}: {e}");
        }
        assert!(is_eval_toml(BASE));
        assert!(!is_eval_toml("name = \"x\"\nkind = \"ego\"\n"));
        assert!(!is_eval_toml("not toml ["));
    }

    /// GIFs name an ego of the grid, or none (each flow alone); a misspelt ego is refused.
    #[test]
    fn gifs_take_an_ego_of_the_grid_or_none() {
        let gifs = |ego: &str| {
            format!(
                "{BASE}gifs = {{ {ego}flows = [\"IDM\"], scenarios = [\"merge\"], case = 3 }}\n"
            )
        };
        let alone = EvalConfig::from_toml(&gifs("")).expect("flows alone");
        let g = alone.experiments.gifs.as_ref().expect("gifs");
        assert_eq!((g.ego.as_str(), g.case), ("", 3));
        assert!(!alone.to_toml().contains("ego = \"\""), "an absent ego stays absent");
        assert_eq!(
            EvalConfig::from_toml(&gifs("ego = \"E\", "))
                .expect("an ego")
                .experiments
                .gifs
                .expect("gifs")
                .ego,
            "E"
        );
        let e = EvalConfig::from_toml(&gifs("ego = \"F\", ")).expect_err("unknown ego");
        assert!(e.0.contains("experiments.gifs.ego") && e.0.contains("`F`"), "{e}");
        // The panel size: 320 px unless given, given ones kept, absurd ones refused by name.
        assert_eq!(g.size_px(), Gifs::DEFAULT_SIZE_PX);
        assert!(!alone.to_toml().contains("size_px"), "an absent size stays absent");
        let big = EvalConfig::from_toml(&gifs("size_px = 960, ")).expect("960 px");
        assert_eq!(big.experiments.gifs.as_ref().map(Gifs::size_px), Some(960));
        for bad in ["size_px = 0, ", "size_px = 100000, "] {
            let e = EvalConfig::from_toml(&gifs(bad)).expect_err(bad);
            assert!(e.0.contains("experiments.gifs.size_px"), "{bad}: {e}");
        }
    }

    #[test]
    fn the_idm_driver_is_an_ego_of_the_grid() {
        let text = BASE.replace(
            "egos = [{ name = \"E\", job = \"ego-a\" }]",
            "egos = [{ name = \"E\", job = \"ego-a\" }, { name = \"IDM ego\", job = \"idm\" }]",
        );
        let c = EvalConfig::from_toml(&format!("{text}cross_validation = [\"IDM\"]\n"))
            .expect("an IDM ego");
        assert!(
            c.ego("IDM ego").is_some_and(Named::is_idm) && !c.ego("E").is_some_and(Named::is_idm)
        );
        let cross: Vec<String> =
            c.cells().into_iter().filter(|c| c.experiment == "cross").map(|c| c.ego).collect();
        assert_eq!(cross, ["E", "IDM ego"], "one cross cell per ego, the IDM driver's included");
    }

    /// The MOBIL driver is a scripted ego of a grid beside the IDM driver; a worker gets a cell
    /// with a scripted ego only if it seats that driver.
    #[test]
    fn the_mobil_driver_is_a_scripted_ego() {
        let text = BASE.replace(
            "egos = [{ name = \"E\", job = \"ego-a\" }]",
            "egos = [{ name = \"I\", job = \"idm\" }, { name = \"M\", job = \"idm-mobil\" }]",
        );
        let c = EvalConfig::from_toml(&format!("{text}cross_validation = [\"IDM\"]\n"))
            .expect("an IDM and a MOBIL ego");
        let m = c.ego("M").expect("MOBIL ego");
        assert!(m.is_idm_mobil() && m.is_scripted() && !m.is_idm() && !m.is_probe());
        assert_eq!(m.scripted(), Some(ScriptedEgo::IdmMobil));
        let i = c.ego("I").expect("IDM ego");
        assert!(i.is_scripted() && !i.is_idm_mobil() && i.scripted() == Some(ScriptedEgo::Idm));
        assert_eq!(c.ego("E"), None);
        let idm_only = ScriptedSeats { idm: true, mobil: false };
        assert!(idm_only.runs(None) && idm_only.runs(Some(ScriptedEgo::Idm)));
        assert!(!idm_only.runs(Some(ScriptedEgo::IdmMobil)));
        assert!(ScriptedSeats::ALL.runs(Some(ScriptedEgo::IdmMobil)));
        assert!(!ScriptedSeats::default().runs(Some(ScriptedEgo::Idm)));
    }

    /// Regression (found by `tests/fuzz.rs`): a huge SVO-sweep count was accepted by the
    /// parser and made validation expand the grid until memory ran out.
    #[test]
    fn svo_sweep_values_are_bounded() {
        let sweep = |values: &str| {
            format!("{BASE}svo_sweep = {{ flows = [\"IDM\"], values = {values}, scenarios = [\"merge\"] }}\n")
        };
        assert_eq!(
            EvalConfig::from_toml(&sweep("91")).expect("one value per degree").cells().len(),
            92
        );
        for v in ["1", "92", "9223372036854775807"] {
            let e = EvalConfig::from_toml(&sweep(v)).expect_err(v);
            assert!(e.0.contains("experiments.svo_sweep.values"), "{v}: {e}");
        }
    }

    /// `BASE` with cross-validation and adversary cells, and `[sizes]` appended.
    fn sized(sizes: &str) -> EvalConfig {
        let text = BASE.replace(
            "flows = [{ name = \"IDM\", job = \"idm\" }]",
            "flows = [{ name = \"IDM\", job = \"idm\" }, { name = \"Adv\", job = \"flow-adv\" }]",
        );
        EvalConfig::from_toml(&format!("{text}cross_validation = [\"IDM\"]\nadversary = {{ egos = [\"E\"], flows = [\"Adv\"] }}\n[sizes]\n{sizes}")).expect(sizes)
    }

    #[test]
    fn a_size_override_applies_to_its_experiments_cells_field_by_field() {
        let c = sized("adversary = { cases = 200, seeds = 3 }\ncross = { cases = 50 }\n");
        let size = |e: &str| {
            c.cells()
                .iter()
                .filter(|c| c.experiment == e)
                .map(|cell| c.size_of(cell))
                .collect::<BTreeSet<_>>()
                .into_iter()
                .collect::<Vec<_>>()
        };
        assert_eq!(size("flow_quality"), [(2, 1)], "no override: the grid-wide size");
        assert_eq!(size("cross"), [(50, 1)], "seeds left out: the grid-wide seeds");
        assert_eq!(size("adversary"), [(200, 3)]);
        let e = c.check_stored_cases(|_| 199).expect_err("the adversary cells need 200");
        assert_eq!((e.field.as_str(), e.cases), ("sizes.adversary.cases", 200), "{e}");
        assert!(
            c.check_stored_cases(|_| 200).is_ok(),
            "200 stored cases are the most any cell uses"
        );
        assert_eq!(c.episodes(), 2 + 50 + 600, "one cell per experiment");
        let plain = sized("");
        assert!(plain.sizes.is_empty());
        assert_eq!(plain.episodes(), 3 * 2);
        assert!(plain.check_stored_cases(|_| 2).is_ok());
        assert_eq!(plain.check_stored_cases(|_| 1).expect_err("2 cases").field, "cases");
        // An override of an experiment without cells changes nothing.
        let unused = sized("density = { cases = 900 }\n");
        assert_eq!(unused.episodes(), 3 * 2);
        assert!(unused.check_stored_cases(|_| 2).is_ok());
    }

    #[test]
    fn a_config_with_sizes_round_trips_through_its_resolved_toml() {
        let c = sized("adversary = { cases = 200, seeds = 3 }\ncross = { seeds = 4 }\n");
        let text = c.to_toml();
        let back = EvalConfig::from_toml(&text).expect(&text);
        assert_eq!(back, c);
        assert_eq!(back.sizes["cross"], SizeOverride { cases: None, seeds: Some(4) });
        assert!(!sized("").to_toml().contains("sizes"), "no `sizes` written when empty");
    }

    #[test]
    fn a_config_round_trips_through_its_resolved_toml() {
        let mut c = EvalConfig::from_toml(BASE).expect("valid");
        c.egos[0].job_id = Some(JobId::new(7));
        let back = EvalConfig::from_toml(&c.to_toml()).expect("valid");
        assert_eq!(back, c);
        assert_eq!(back.cells(), c.cells());
    }
}
