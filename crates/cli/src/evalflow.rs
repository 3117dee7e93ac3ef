//! `socialflow eval-flow`: a flow's Success, Safety and Speed over the stored cases.
//!
//! The all-IDM flow needs nothing; a learned flow (MACAD, CoPO Stage 1, SocialComm) is read
//! from a finished job's artifact directory (`config.toml` + `policy.bpk`) and drives every
//! vehicle of the stored case, actions sampled with the seed (or the mean with
//! `--deterministic`); a CoPO flow with a fitted coordinator runs as Stage 2 (SVOs redrawn
//! from its Gaussian every step) unless `--stage1`. Also `copo-coordinator`, CoPO Stage 2 on
//! a finished CoPO flow.

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use rayon::prelude::*;
use serde_json::json;
use sf_report::stats::Summary;
use sf_rollout::coordinator::CoordinatorFile;
use sf_rollout::drive::{Actor, Drivers};
use sf_sim::metrics::EpisodeMetrics;
use sf_sim::vec_env::{EpisodeSpec, VecEnv};
use sf_sim::{Env, Mode, SimConfig};

use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct EvalFlowArgs {
    /// A flow that needs no trained policy (`idm`).
    #[arg(long, value_enum, required_unless_present = "policy", conflicts_with = "policy")]
    flow: Option<Flow>,
    /// A trained flow: the artifact directory of a finished flow job.
    #[arg(long)]
    policy: Option<std::path::PathBuf>,
    /// Mean actions instead of samples (learned flows).
    #[arg(long)]
    deterministic: bool,
    /// A CoPO flow past Stage 2: keep the cases' SVOs instead of its coordinator's Gaussian.
    #[arg(long)]
    stage1: bool,
    #[arg(long)]
    scenario: String,
    /// Number of stored cases to run (the first N).
    #[arg(long, default_value_t = 200)]
    cases: u32,
    #[arg(long, default_value_t = 10)]
    seeds: u32,
    /// Override the number of vehicles per case (density sweep); default: the case's own.
    #[arg(long)]
    vehicles: Option<usize>,
    #[arg(long)]
    json: bool,
    /// Score only the ego's seat (agent 0), driven by this driver among the flow, instead of
    /// every vehicle; `--json` then also lists every episode. `idm`: the IDM driver (what the
    /// Python package's `evaluate` gives for a zero acceleration residual).
    #[arg(long, value_enum)]
    ego: Option<EgoDriver>,
    /// Simulators stepped together with `--ego` (a learned flow's samples depend on it).
    #[arg(long, default_value_t = 16)]
    envs: usize,
}

/// A driver for the ego's seat that needs no trained policy.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum EgoDriver {
    Idm,
}

/// Traffic flows selectable on the command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Flow {
    Idm,
    Macad,
    Copo,
    Socialcomm,
    Failmaker,
    Socialcommadv,
}

/// The environment mode of a flow that needs no trained policy.
pub fn flow_mode(flow: Flow) -> Result<Mode> {
    match flow {
        Flow::Idm => Ok(Mode::AllIdm),
        other => bail!("flow `{other:?}` needs a trained policy, which this build cannot load yet (only `idm` runs without one)"),
    }
}

/// A learned flow loaded from a job's artifacts, ready to drive one map: its simulator settings,
/// the policy (built once, reused by every episode) and, for a CoPO flow past Stage 2, its
/// coordinator.
struct LearnedFlow {
    sim: std::sync::Arc<SimConfig>,
    runner: sf_rollout::inference::PolicyRunner,
    coordinator: Option<CoordinatorFile>,
}

impl LearnedFlow {
    /// The config of a flow job's artifact directory (refused if it is not a flow).
    fn config(dir: &std::path::Path) -> Result<sf_job::JobConfig> {
        let cfg = dir.join("config.toml");
        let text =
            std::fs::read_to_string(&cfg).with_context(|| format!("reading {}", cfg.display()))?;
        let job = sf_job::JobConfig::from_toml(&text).with_context(|| cfg.display().to_string())?;
        if !job.kind.multi_agent() {
            bail!("{} is a `{}` job, not a Stage-1 traffic flow", dir.display(), job.kind.as_str());
        }
        Ok(job)
    }

    fn load(dir: &std::path::Path, job: &sf_job::JobConfig, map: &sf_sim::Map) -> Result<Self> {
        let p = dir.join("policy.bpk");
        let weights = std::fs::read(&p)
            .with_context(|| format!("reading {} (did the job succeed?)", p.display()))?;
        let r = sf_rollout::setup::resolve(job, None);
        let sim = std::sync::Arc::new(r.sim);
        let segments = sf_sim::obs::MapSegments::build(map, sim.obs.segment_points);
        let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?;
        let runner = sf_rollout::inference::PolicyRunner::from_bytes(
            &r.net,
            &r.obs,
            sim.dt_s,
            &[&segments],
            &weights,
            sf_job::PolicyVersion::new(0),
            &device,
        )
        .with_context(|| format!("loading {}", p.display()))?;
        let coordinator = CoordinatorFile::load(dir).map_err(anyhow::Error::msg)?;
        Ok(Self { sim, runner, coordinator })
    }
}

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// A finished CoPO Stage-1 job's artifact directory (the frozen policy).
    #[arg(long)]
    policy: std::path::PathBuf,
    /// Scenarios to fit (default: every scenario of the job).
    #[arg(long)]
    scenario: Vec<String>,
    #[arg(long, default_value_t = 6)]
    iterations: u32,
    /// Candidate SVOs per iteration.
    #[arg(long, default_value_t = 12)]
    population: u32,
    /// Generated episodes scoring each candidate.
    #[arg(long, default_value_t = 1)]
    episodes: u32,
    #[arg(long, default_value_t = 0.25)]
    elite: f32,
    /// Simulators stepped together.
    #[arg(long, default_value_t = 12)]
    envs: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where to write the fitted Gaussians (default: `<policy>/coordinator.json`, which ego
    /// jobs and evaluation read).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
}

/// CoPO Stage 2 on a finished CoPO flow (what a CoPO job does by itself after Stage 1):
/// fits each scenario's SVO Gaussian by the cross-entropy method, each candidate scored by the
/// frozen Stage-1 flow's mean individual reward with every agent at that SVO.
pub fn coordinator(ctx: &Ctx, a: CoordinatorArgs) -> Result<()> {
    use sf_rollout::coordinator::{fit_scenario, FitSettings, ScenarioFit};
    let job = LearnedFlow::config(&a.policy)?;
    if job.kind != sf_job::config::JobKind::Copo {
        bail!(
            "{} is a `{}` job; the coordinator is fitted on a CoPO Stage-1 flow",
            a.policy.display(),
            job.kind.as_str()
        );
    }
    if a.population == 0
        || a.iterations == 0
        || a.episodes == 0
        || a.envs == 0
        || !(a.elite > 0.0 && a.elite <= 1.0)
    {
        bail!("--population, --iterations, --episodes and --envs must be positive and --elite in (0, 1]");
    }
    let scenarios =
        if a.scenario.is_empty() { job.env.scenarios.clone() } else { a.scenario.clone() };
    let mut fits = Vec::new();
    for (k, scenario) in scenarios.iter().enumerate() {
        let map = ctx.map(scenario)?;
        let flow = LearnedFlow::load(&a.policy, &job, &map)?;
        let settings = FitSettings {
            iterations: a.iterations,
            population: a.population,
            episodes: a.episodes,
            elite_frac: a.elite,
            envs: a.envs,
            vehicles: (job.env.vehicles_min, job.env.vehicles_max),
            seed: a.seed ^ k as u64,
        };
        let (coord, history) = fit_scenario(&map, &flow.sim, &flow.runner, &settings, |l| {
            eprintln!(
                "{scenario} iteration {}: mean {:.1} deg, std {:.1} deg, mean reward {:.4}",
                l.iteration, l.mean_deg, l.std_deg, l.mean_reward
            );
        })
        .map_err(anyhow::Error::msg)?;
        fits.push(ScenarioFit { scenario: scenario.clone(), gaussian: coord.gaussian(), history });
    }
    let file = CoordinatorFile { scenarios: fits };
    let out = a.out.unwrap_or_else(|| a.policy.join(CoordinatorFile::FILE));
    let text = serde_json::to_string_pretty(&file)?;
    std::fs::write(&out, &text).with_context(|| format!("writing {}", out.display()))?;
    println!("{}", serde_json::to_string(&file)?);
    Ok(())
}

pub fn run(ctx: &Ctx, a: EvalFlowArgs) -> Result<()> {
    if a.ego.is_some() {
        return run_ego_seat(ctx, &a);
    }
    let learned = a
        .policy
        .as_deref()
        .map(|dir| LearnedFlow::config(dir).map(|job| (dir, job)))
        .transpose()?;
    let flow_name = match (&learned, a.flow) {
        (Some((_, job)), _) => format!("{:?}", job.kind).to_lowercase(),
        (None, Some(f)) => format!("{f:?}").to_lowercase(),
        (None, None) => bail!("give --flow or --policy"),
    };
    let mode = match (&learned, a.flow) {
        (Some(_), _) => Mode::MultiAgent,
        (None, Some(f)) => flow_mode(f)?,
        (None, None) => bail!("give --flow or --policy"),
    };
    let map = ctx.map(&a.scenario)?;
    let cases = ctx.cases(&map)?;
    if a.cases as usize > cases.cases.len() {
        bail!(
            "--cases {} exceeds the {} stored cases of {}",
            a.cases,
            cases.cases.len(),
            a.scenario
        );
    }
    let cfg = std::sync::Arc::new(SimConfig::default());
    // A learned flow: the mean standard deviation of its sampling noise per action component,
    // over the rows it drove (every 4th step), the noise a noise-matched IDM flow should have.
    let mut std_sum: Vec<f64> = Vec::new();
    let mut std_rows = 0usize;
    let jobs: Vec<(usize, u32)> =
        (0..a.cases as usize).flat_map(|c| (0..a.seeds).map(move |s| (c, s))).collect();
    let results: Vec<EpisodeMetrics> = match learned {
        None => jobs
            .par_iter()
            .map(|&(c, _seed)| {
                // The all-IDM flow is deterministic: the seed only matters for stochastic flows.
                let mut env = Env::new(map.clone(), cfg.clone());
                env.reset(&cases.cases[c], mode, a.vehicles).context("resetting a stored case")?;
                env.run_episode(|_, _| {}, |_| {})?;
                Ok(EpisodeMetrics::from_outcomes(env.outcomes(), false))
            })
            .collect::<Result<_>>()?,
        Some((dir, job)) => {
            // Every vehicle driven by the flow; one sampling stream per seed, as in `eval`.
            let flow = LearnedFlow::load(dir, &job, &map)?;
            let gaussian = if a.stage1 {
                None
            } else {
                flow.coordinator.as_ref().and_then(|c| c.gaussian(&a.scenario))
            };
            let actor = if a.deterministic {
                Actor::mean(&flow.runner)
            } else {
                Actor::sampled(&flow.runner)
            };
            let drivers = Drivers { alive: actor, background: None, adversary: None };
            let mut out = Vec::with_capacity(jobs.len());
            for seed in 0..a.seeds {
                let eps = (0..a.cases as usize)
                    .map(|c| EpisodeSpec {
                        case: cases.cases[c].clone(),
                        vehicles: a.vehicles,
                        svo_deg: None,
                        tag: (seed as u64) << 32 | c as u64,
                    })
                    .collect();
                let mut v =
                    VecEnv::from_episodes(map.clone(), flow.sim.clone(), Mode::MultiAgent, 16, eps)
                        .map_err(anyhow::Error::msg)?;
                v.set_svo_gaussian(gaussian);
                let mut step = 0usize;
                let mut done = sf_rollout::drive::run_episodes(&mut v, &drivers, |v, _| {
                    step += 1;
                    if !step.is_multiple_of(4) {
                        return;
                    }
                    let len = v.spec.len;
                    let rows: Vec<usize> =
                        (0..v.alive().len()).filter(|&r| v.alive()[r] == 1.0).collect();
                    if rows.is_empty() {
                        return;
                    }
                    let obs: Vec<f32> = rows
                        .iter()
                        .flat_map(|&r| v.observations()[r * len..(r + 1) * len].iter().copied())
                        .collect();
                    let sd = flow.runner.std_dev(&obs, &vec![0u32; rows.len()]);
                    let dim = sd.len() / rows.len();
                    std_sum.resize(dim, 0.0);
                    for (k, x) in sd.iter().enumerate() {
                        std_sum[k % dim] += *x as f64;
                    }
                    std_rows += rows.len();
                });
                done.sort_by_key(|(tag, _)| *tag);
                out.extend(done.into_iter().map(|(_, m)| m));
            }
            out
        }
    };
    let col = |f: fn(&EpisodeMetrics) -> f32| {
        Summary::of(&results.iter().map(|m| f(m) as f64).collect::<Vec<_>>())
    };
    let (success, safety, speed) =
        (col(|m| m.scores.success), col(|m| m.scores.safety), col(|m| m.scores.speed));
    let failures = json!({
        "collision": col(|m| m.collision).mean,
        "off_road": col(|m| m.off_road).mean,
        "off_route": col(|m| m.off_route).mean,
        "wrong_lane": col(|m| m.wrong_lane).mean,
        "timeout": col(|m| m.timeout).mean,
        "destination": col(|m| m.destination).mean,
    });
    let action_std: Option<Vec<f64>> =
        (std_rows > 0).then(|| std_sum.iter().map(|s| s / std_rows as f64).collect());
    if a.json {
        let s = |x: Summary| json!({"mean": x.mean, "ci95": x.ci95});
        let out = json!({
            "flow": flow_name,
            "policy": a.policy,
            "scenario": a.scenario,
            "cases": a.cases,
            "seeds": a.seeds,
            "episodes": results.len(),
            "success": s(success),
            "safety": s(safety),
            "speed": s(speed),
            "failures": failures,
            "action_std": action_std,
        });
        println!("{out}");
    } else {
        let p = |x: Summary| format!("{:5.1}% +- {:.1}", 100.0 * x.mean, 100.0 * x.ci95);
        println!("{flow_name} flow in {} over {} episodes", a.scenario, results.len());
        println!("  success {}\n  safety  {}\n  speed   {}", p(success), p(safety), p(speed));
        println!("  failures {failures}");
        if let Some(sd) = &action_std {
            println!("  sampling noise (std before tanh, per action component) {sd:.3?}");
        }
    }
    Ok(())
}

/// `eval-flow --ego idm`: the IDM driver in the ego's seat among the flow, over the stored
/// cases x seeds, through the same loop as an evaluation cell (`sf_rollout::evaluate::run_stored`).
fn run_ego_seat(ctx: &Ctx, a: &EvalFlowArgs) -> Result<()> {
    use sf_rollout::evaluate::{Episodes, FlowDef, FlowSetup, Runners};
    let flow = match (&a.policy, a.flow) {
        (Some(dir), _) => FlowDef::load(dir).map_err(anyhow::Error::msg)?,
        (None, Some(Flow::Idm)) => FlowDef::Idm,
        (None, Some(other)) => {
            bail!("flow `{other:?}` needs a trained policy: give its job directory with --policy")
        }
        (None, None) => bail!("give --flow or --policy"),
    };
    let map = ctx.map(&a.scenario)?;
    let cases = ctx.cases(&map)?;
    if a.cases as usize > cases.cases.len() {
        bail!(
            "--cases {} exceeds the {} stored cases of {}",
            a.cases,
            cases.cases.len(),
            a.scenario
        );
    }
    let mut runners = Runners::new(sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?);
    let setup = FlowSetup::new(&flow, &map, None, &mut runners).map_err(anyhow::Error::msg)?;
    let gaussian = if a.stage1 { None } else { setup.svo_gaussian };
    let drivers =
        setup.drivers(Actor::Demo { noise: 0.0, action: sf_sim::DriveAction::IdmAccelResidual });
    let episodes = Episodes {
        cases: &cases.cases[..a.cases as usize],
        seeds: a.seeds,
        envs: a.envs,
        vehicles: a.vehicles,
        svo_deg: None,
    };
    let rows = sf_rollout::evaluate::run_stored(
        &map, &setup.sim, setup.mode, gaussian, &episodes, &drivers,
    )
    .map_err(anyhow::Error::msg)?;
    let col = |f: fn(&sf_job::eval::EvalEpisode) -> f32| {
        Summary::of(&rows.iter().map(|r| f(r) as f64).collect::<Vec<_>>())
    };
    let (success, safety, speed, collision) = (
        col(|r| r.scores.success),
        col(|r| r.scores.safety),
        col(|r| r.scores.speed),
        col(|r| r.collision),
    );
    let flow_name = flow.kind().map_or("idm", |k| k.as_str());
    if a.json {
        let s = |x: Summary| json!({"mean": x.mean, "ci95": x.ci95});
        let episodes: Vec<_> =
            rows.iter().map(|r| json!({"case": r.case, "seed": r.seed, "success": r.scores.success, "safety": r.scores.safety, "speed": r.scores.speed, "collision": r.collision})).collect();
        let out = json!({
            "flow": flow_name,
            "policy": a.policy,
            "ego": "idm",
            "scenario": a.scenario,
            "cases": a.cases,
            "seeds": a.seeds,
            "envs": a.envs,
            "success": s(success),
            "safety": s(safety),
            "speed": s(speed),
            "collision": s(collision),
            "episodes": episodes,
        });
        println!("{out}");
    } else {
        let p = |x: Summary| format!("{:5.1}% +- {:.1}", 100.0 * x.mean, 100.0 * x.ci95);
        println!(
            "IDM ego among the {flow_name} flow in {} over {} episodes",
            a.scenario,
            rows.len()
        );
        println!(
            "  success {}\n  safety  {}\n  speed   {}\n  collision {}",
            p(success),
            p(safety),
            p(speed),
            p(collision)
        );
    }
    Ok(())
}
