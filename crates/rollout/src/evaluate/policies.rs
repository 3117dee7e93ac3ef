//! What acts in an evaluation cell: a finished job's [`Policy`] (its config resolved once), the
//! flow ([`FlowDef`]: IDM or a learned background with its adversary) and the ego ([`EgoDef`]),
//! built from a learner's frozen policies ([`from_frozen`]), and whether an ego and a flow fit
//! together ([`check_cell`]). Must not: run episodes (the parent module does) or find jobs.

use std::path::Path;
use std::sync::Arc;

use sf_job::config::JobKind;
use sf_job::eval::{Cell, ScriptedEgo};
use sf_job::{Frozen, FrozenRole, JobConfig, SvoGaussian};
use sf_sim::config::MessageProbe;
use sf_sim::SimConfig;

use super::{io, EvalError};
use crate::setup;

/// A finished job's final policy, with its job config resolved once ([`Policy::resolved`]).
#[derive(Clone)]
pub struct Policy {
    /// Identifies the policy in caches and messages (a job id or an artifact directory).
    pub key: String,
    pub cfg: JobConfig,
    pub weights: Arc<Vec<u8>>,
    /// A CoPO flow past Stage 2: per scenario, the coordinator's SVO Gaussian.
    pub svo_gaussians: Vec<(String, SvoGaussian)>,
    /// `cfg` resolved on its own (no background): the network, the observation layout and the
    /// simulator settings the policy acts with. Private, so it always matches `cfg`.
    resolved: Arc<setup::ResolvedJob>,
}

impl Policy {
    /// A policy of job config `cfg` with actor `weights`; resolves `cfg` once.
    pub fn new(
        key: String,
        cfg: JobConfig,
        weights: Arc<Vec<u8>>,
        svo_gaussians: Vec<(String, SvoGaussian)>,
    ) -> Self {
        let resolved = Arc::new(setup::resolve(&cfg, None));
        Self { key, cfg, weights, svo_gaussians, resolved }
    }

    /// The policy's job config resolved on its own (no background job).
    pub fn resolved(&self) -> &setup::ResolvedJob {
        &self.resolved
    }

    /// A finished job's final policy from its artifact directory (`config.toml`, `policy.bpk`,
    /// and `coordinator.json` for a CoPO flow past Stage 2). Errors name the file.
    pub fn load(dir: &Path) -> Result<Self, EvalError> {
        let path = dir.join("config.toml");
        let text = std::fs::read_to_string(&path).map_err(io("reading", &path))?;
        let cfg = JobConfig::from_toml(&text)
            .map_err(|source| EvalError::JobFile { path: path.clone(), source })?;
        let path = dir.join("policy.bpk");
        let weights = std::fs::read(&path).map_err(io("reading (is the job finished?)", &path))?;
        let coordinator = crate::coordinator::CoordinatorFile::load(dir)?;
        let svo_gaussians = coordinator
            .map(|c| c.scenarios.into_iter().map(|s| (s.scenario, s.gaussian)).collect())
            .unwrap_or_default();
        Ok(Self::new(dir.display().to_string(), cfg, Arc::new(weights), svo_gaussians))
    }
}

/// What drives a flow: IDM, or a learned background (with its adversary for SocialCommAdv).
#[derive(Clone)]
// A handful per grid, built once: boxing the policies would buy nothing.
#[allow(clippy::large_enum_variant)]
pub enum FlowDef {
    Idm,
    /// The noise-matched IDM flow (an evaluation grid's `job = "idm-noise"`): every vehicle the
    /// IDM driver plus a learned flow's sampling noise of standard deviation `std` on each
    /// component of the lateral residual action ([`crate::drive::Actor::IdmNoise`]), so "a learned flow beats
    /// IDM" can be told apart from "noise beats IDM".
    IdmNoise {
        std: f32,
    },
    /// `messages`: an evaluation probe's constants in place of the SVOs observers are told (off
    /// unless an evaluation grid's flow asks for it).
    Learned {
        background: Policy,
        adversary: Option<Policy>,
        messages: MessageProbe,
    },
}

impl FlowDef {
    /// A learned flow as it was trained (no message probe).
    pub fn learned(background: Policy, adversary: Option<Policy>) -> Self {
        Self::Learned { background, adversary, messages: MessageProbe::default() }
    }

    /// The flow's message probe on `sim` (nothing for IDM, whose drivers read no messages).
    pub fn probe(&self, sim: &mut SimConfig) {
        if let Self::Learned { messages, .. } = self {
            sim.obs.messages = *messages;
        }
    }
}

impl FlowDef {
    /// The kind of job the flow is (SocialCommAdv when it has an adversary); `None` for IDM.
    pub fn kind(&self) -> Option<JobKind> {
        match self {
            Self::Idm | Self::IdmNoise { .. } => None,
            Self::Learned { adversary: Some(_), .. } => Some(JobKind::SocialcommAdv),
            Self::Learned { background, .. } => Some(background.cfg.kind),
        }
    }

    /// The config of the flow job whose policy drives the background; `None` for IDM.
    pub fn background_config(&self) -> Option<&JobConfig> {
        match self {
            Self::Idm | Self::IdmNoise { .. } => None,
            Self::Learned { background, .. } => Some(&background.cfg),
        }
    }

    /// The noise-matched IDM flow's noise standard deviation; `None` for the other flows.
    pub fn noise_std(&self) -> Option<f32> {
        match self {
            Self::IdmNoise { std } => Some(*std),
            _ => None,
        }
    }
}

impl FlowDef {
    /// A flow from a finished flow job's artifact directory. A SocialCommAdv job brings the
    /// SocialComm flow it was trained against (`env.background_job`), found beside it in the
    /// same `jobs/` directory (`<id>-<name>/`).
    pub fn load(dir: &Path) -> Result<Self, EvalError> {
        let p = Policy::load(dir)?;
        match p.cfg.kind {
            JobKind::Ego => {
                Err(EvalError::Misfit(format!("{} is an ego job, not a flow", dir.display())))
            }
            JobKind::SocialcommAdv => {
                let id = p.cfg.env.background_job.ok_or_else(|| {
                    EvalError::Invalid(format!(
                        "{}: a socialcomm-adv job without its flow (env.background_job)",
                        dir.display()
                    ))
                })?;
                let jobs = dir.parent().ok_or_else(|| {
                    EvalError::Misfit(format!("{} has no parent directory", dir.display()))
                })?;
                let entries = std::fs::read_dir(jobs).map_err(io("reading", jobs))?;
                let bg = entries
                    .flatten()
                    .map(|e| e.path())
                    .find(|d| {
                        d.file_name()
                            .and_then(|n| n.to_str())
                            .and_then(|n| n.split_once('-'))
                            .is_some_and(|(i, _)| i.parse::<u64>() == Ok(id.get()))
                    })
                    .ok_or_else(|| {
                        EvalError::Misfit(format!(
                            "{}: its flow, job {id}, has no directory in {}",
                            dir.display(),
                            jobs.display()
                        ))
                    })?;
                Ok(Self::learned(Policy::load(&bg)?, Some(p)))
            }
            _ => Ok(Self::learned(p, None)),
        }
    }
}

/// Who drives a cell's ego seat: a trained ego policy (its mean action), the IDM driver (an
/// evaluation grid's `job = "idm"` ego: the zero residual every trained ego starts from, the
/// baseline they are tested against), or IDM with MOBIL's lane changes (`job = "idm-mobil"`,
/// [`sf_sim::mobil`]: a reference driver that steers).
#[derive(Clone)]
// A handful per grid, built once: boxing the policy would buy nothing.
#[allow(clippy::large_enum_variant)]
pub enum EgoDef {
    Idm,
    IdmMobil,
    Learned(Policy),
}

impl From<ScriptedEgo> for EgoDef {
    /// The seat of a grid's scripted ego (`job = "idm"` or `"idm-mobil"`).
    fn from(s: ScriptedEgo) -> Self {
        match s {
            ScriptedEgo::Idm => Self::Idm,
            ScriptedEgo::IdmMobil => Self::IdmMobil,
        }
    }
}

impl EgoDef {
    /// A work item's ego seat: its scripted driver (the wire's `ego_idm`, `ego_mobil`), else
    /// its EGO policy if it has one.
    pub fn of_work(
        ego: Option<Policy>,
        scripted: Option<ScriptedEgo>,
    ) -> Result<Option<Self>, EvalError> {
        match (ego, scripted) {
            (Some(_), Some(_)) => Err(EvalError::Misfit(
                "a scripted driver and an ego policy both given for the ego's seat".into(),
            )),
            (None, Some(s)) => Ok(Some(s.into())),
            (ego, None) => Ok(ego.map(Self::Learned)),
        }
    }

    /// What names it in a cell run outside a grid ([`run_cases`]): the policy's key, or `idm`.
    pub fn key(&self) -> String {
        match self {
            Self::Idm => "idm".into(),
            Self::IdmMobil => "idm-mobil".into(),
            Self::Learned(p) => p.key.clone(),
        }
    }
}

/// The ego and flow of a cell from the frozen policies of an evaluation job's work item and
/// their fetched weights (`weights[i]` belongs to `policies[i]`), each config parsed from the
/// text it travelled with (a worker's view).
pub fn from_frozen(
    policies: &[Frozen],
    weights: &[Arc<Vec<u8>>],
) -> Result<(FlowDef, Option<Policy>), EvalError> {
    from_frozen_with(policies, weights, |f| {
        JobConfig::from_toml(&f.config_toml)
            .map_err(|source| EvalError::FrozenConfig { job_id: f.job_id, source })
    })
}

/// [`from_frozen`] with each policy's config from `config` (the learner's: the configs it
/// parsed once when the jobs were stored), failing with the caller's error type.
pub fn from_frozen_with<E: From<EvalError>>(
    policies: &[Frozen],
    weights: &[Arc<Vec<u8>>],
    config: impl Fn(&Frozen) -> Result<JobConfig, E>,
) -> Result<(FlowDef, Option<Policy>), E> {
    if policies.len() != weights.len() {
        return Err(EvalError::Misfit(format!(
            "{} policies but {} weights",
            policies.len(),
            weights.len()
        ))
        .into());
    }
    let (mut ego, mut background, mut adversary) = (None, None, None);
    for (f, w) in policies.iter().zip(weights) {
        let cfg = config(f)?;
        let slot = match f.role {
            FrozenRole::Ego => &mut ego,
            FrozenRole::Background => &mut background,
            FrozenRole::Adversary => &mut adversary,
        };
        if slot
            .replace(Policy::new(f.job_id.to_string(), cfg, Arc::clone(w), f.svo_gaussians.clone()))
            .is_some()
        {
            return Err(EvalError::Misfit(format!("two policies in the role {:?}", f.role)).into());
        }
    }
    let flow = match background {
        Some(background) => FlowDef::learned(background, adversary),
        None if adversary.is_some() => {
            return Err(EvalError::Misfit("an adversary without the flow it talks to".into()).into())
        }
        None => FlowDef::Idm,
    };
    Ok((flow, ego))
}

/// Whether `ego` (or none) can be evaluated in `flow`: an ego is an ego job observing in the
/// flow's layout; a flow on its own is a Stage-1 flow that drives every vehicle.
pub fn check_cell(cell: &Cell, flow: &FlowDef, ego: Option<&EgoDef>) -> Result<(), EvalError> {
    if cell.ego.is_empty() != ego.is_none() {
        return Err(EvalError::Misfit(format!(
            "cell {} names ego `{}` but {} given",
            cell.key(),
            cell.ego,
            if ego.is_some() { "an ego is" } else { "none is" }
        )));
    }
    let ego = match ego {
        // The scripted drivers ignore what they observe: they fit every flow.
        Some(EgoDef::Idm | EgoDef::IdmMobil) => return Ok(()),
        Some(EgoDef::Learned(p)) => Some(p),
        None => None,
    };
    if let Some(e) = ego {
        // A Stage-1 flow's actor may sit in the ego's seat (`flow_actor`, a probe); the
        // observation is one layout for every kind, each network reads the channels it consumes.
        if !matches!(
            e.cfg.kind,
            JobKind::Ego | JobKind::Macad | JobKind::Copo | JobKind::Socialcomm
        ) {
            return Err(EvalError::Misfit(format!(
                "ego `{}` is a {} job, not an ego policy (or a Stage-1 flow's actor)",
                cell.ego,
                e.cfg.kind.as_str()
            )));
        }
    }
    match (ego, flow) {
        (None, FlowDef::Learned { .. }) => {
            let kind = flow.kind().unwrap_or_default();
            if !kind.multi_agent() {
                return Err(EvalError::Misfit(format!(
                    "flow `{}` ({}) needs an ego to act against; evaluate it with an ego",
                    cell.flow,
                    kind.as_str()
                )));
            }
        }
        (Some(e), FlowDef::Learned { background, .. }) => {
            if e.resolved().obs.layout != background.resolved().obs.layout {
                return Err(EvalError::Misfit(format!(
                    "ego `{}` and flow `{}` observe in different layouts",
                    cell.ego, cell.flow
                )));
            }
        }
        (_, FlowDef::Idm | FlowDef::IdmNoise { .. }) => {}
    }
    Ok(())
}
