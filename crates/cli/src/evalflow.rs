//! `socialflow eval-flow`: a flow's Success, Safety and Speed over the stored cases.
//!
//! The all-IDM flow needs nothing; a learned flow (MACAD, CoPO Stage 1, SocialComm) is read
//! from a finished job's artifact directory (`config.toml` + `policy.bpk`) and drives every
//! vehicle of the stored case, actions sampled with the seed (or the mean with
//! `--deterministic`).

use anyhow::{bail, Context, Result};
use clap::Args;
use rayon::prelude::*;
use serde_json::json;
use sf_eval::Summary;
use sf_sim::metrics::EpisodeMetrics;
use sf_sim::{Env, Mode, SimConfig};

use crate::scenarios::Ctx;
use crate::Flow;

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
}

/// The environment mode of a flow that needs no trained policy.
pub fn flow_mode(flow: Flow) -> Result<Mode> {
    match flow {
        Flow::Idm => Ok(Mode::AllIdm),
        other => bail!("flow `{other:?}` needs a trained policy, which this build cannot load yet (only `idm` runs without one)"),
    }
}

/// A learned flow loaded from a job's artifacts, ready to drive one map: its simulator settings,
/// the map's segments and the policy (built once, reused by every episode).
struct LearnedFlow {
    sim: std::sync::Arc<SimConfig>,
    segments: std::sync::Arc<sf_sim::obs::MapSegments>,
    runner: sf_sac::inference::PolicyRunner,
}

impl LearnedFlow {
    /// The config of a flow job's artifact directory (refused if it is not a flow).
    fn config(dir: &std::path::Path) -> Result<sf_job::JobConfig> {
        let cfg = dir.join("config.toml");
        let text = std::fs::read_to_string(&cfg).with_context(|| format!("reading {}", cfg.display()))?;
        let job = sf_job::JobConfig::from_toml(&text).with_context(|| cfg.display().to_string())?;
        if !job.kind.multi_agent() {
            bail!("{} is a `{}` job, not a Stage-1 traffic flow", dir.display(), job.kind.as_str());
        }
        Ok(job)
    }

    fn load(dir: &std::path::Path, job: sf_job::JobConfig, map: &sf_sim::Map) -> Result<Self> {
        let p = dir.join("policy.bpk");
        let weights = std::fs::read(&p).with_context(|| format!("reading {} (did the job succeed?)", p.display()))?;
        let sim = std::sync::Arc::new(sf_sac::setup::sim_config(&job, None));
        let segments = std::sync::Arc::new(sf_sim::obs::MapSegments::build(map, sim.obs.segment_points));
        let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?;
        let runner = sf_sac::inference::PolicyRunner::from_bytes(&sf_sac::setup::net_config(&job), &sf_sac::setup::obs_spec(&job), sim.dt_s, &[&segments], &weights, 0, &device)
            .with_context(|| format!("loading {}", p.display()))?;
        Ok(Self { sim, segments, runner })
    }

    /// One episode of a stored case with every vehicle driven by the policy, every agent's SVO
    /// set to `svo_deg` if given; returns the metrics and the mean individual reward per
    /// agent-step.
    fn episode(&self, map: &std::sync::Arc<sf_sim::Map>, case: &sf_sim::Case, vehicles: Option<usize>, seed: u64, deterministic: bool, svo_deg: Option<f32>) -> Result<(EpisodeMetrics, f32)> {
        use rand::SeedableRng;
        let mut env = Env::new(map.clone(), self.sim.clone());
        env.reset(case, Mode::MultiAgent, vehicles).context("resetting a stored case")?;
        if let Some(svo) = svo_deg {
            for i in 0..env.len() {
                env.set_svo(i, svo);
            }
        }
        let mut obs = sf_sim::Observer::with_segments(self.segments.clone(), &self.sim);
        let (mut reward_sum, mut reward_n, mut first) = (0.0f64, 0u64, true);
        let len = obs.spec.len;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut rows = Vec::new();
        let mut ids = Vec::new();
        let runner = &self.runner;
        env.run_episode(
            |env, actions| {
                obs.prepare(env);
                rows.clear();
                ids.clear();
                for (i, a) in env.agents().iter().enumerate() {
                    if a.alive && a.role == sf_sim::Role::Learner {
                        let start = rows.len();
                        rows.resize(start + len, 0.0);
                        obs.write(env, i, &mut rows[start..]);
                        ids.push(i);
                    }
                }
                if ids.is_empty() {
                    return;
                }
                let zeros = vec![0u32; ids.len()];
                let act = if deterministic { runner.mean(&rows, &zeros) } else { runner.sample(&rows, &zeros, &mut rng) };
                for (j, &i) in ids.iter().enumerate() {
                    actions[i] = sf_sim::Action { ref_speed: act[2 * j], steer: act[2 * j + 1] };
                }
            },
            |env| {
                // Called once after the reset (no rewards yet), then after every step: count the
                // agents that acted on that step (still alive, or ended on it).
                if std::mem::take(&mut first) {
                    return;
                }
                for (i, (a, r)) in env.agents().iter().zip(env.rewards()).enumerate() {
                    if a.alive || env.ended_now().get(i).copied().unwrap_or(false) {
                        reward_sum += r.individual as f64;
                        reward_n += 1;
                    }
                }
            },
        )?;
        Ok((EpisodeMetrics::from_outcomes(env.outcomes(), false), (reward_sum / reward_n.max(1) as f64) as f32))
    }
}

#[derive(Args, Debug)]
pub struct CoordinatorArgs {
    /// A finished CoPO Stage-1 job's artifact directory (the frozen policy).
    #[arg(long)]
    policy: std::path::PathBuf,
    #[arg(long)]
    scenario: String,
    #[arg(long, default_value_t = 10)]
    iterations: u32,
    /// Candidate SVOs per iteration (one episode each, on successive stored cases).
    #[arg(long, default_value_t = 16)]
    population: u32,
    #[arg(long, default_value_t = 0.25)]
    elite: f32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Where to write the fitted Gaussian (default: `<policy>/coordinator-<scenario>.json`).
    #[arg(long)]
    out: Option<std::path::PathBuf>,
}

/// CoPO Stage 2: fits the scenario's SVO Gaussian by the cross-entropy method, each candidate
/// scored by the frozen Stage-1 flow's mean individual reward with every agent at that SVO.
pub fn coordinator(ctx: &Ctx, a: CoordinatorArgs) -> Result<()> {
    use rand::SeedableRng;
    let job = LearnedFlow::config(&a.policy)?;
    if job.kind != sf_job::config::JobKind::Copo {
        bail!("{} is a `{:?}` job; the coordinator is fitted on a CoPO Stage-1 flow", a.policy.display(), job.kind);
    }
    if a.population == 0 || a.iterations == 0 || !(a.elite > 0.0 && a.elite <= 1.0) {
        bail!("--population and --iterations must be positive and --elite in (0, 1]");
    }
    let map = ctx.map(&a.scenario)?;
    let cases = ctx.cases(&map)?;
    let flow = LearnedFlow::load(&a.policy, job, &map)?;
    let mut coord = sf_sac::coordinator::Coordinator::default();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    let mut history = Vec::new();
    let mut case_k = 0usize;
    for it in 0..a.iterations {
        let cand = coord.propose(&mut rng, a.population as usize);
        let mut scores = Vec::with_capacity(cand.len());
        for &svo in &cand {
            let case = &cases.cases[case_k % cases.cases.len()];
            let (_, r) = flow.episode(&map, case, None, a.seed ^ case_k as u64, false, Some(svo))?;
            scores.push(r);
            case_k += 1;
        }
        coord.update(&cand, &scores, a.elite);
        let mean_score = scores.iter().sum::<f32>() / scores.len() as f32;
        eprintln!("iteration {it}: mean {:.1} deg, std {:.1} deg, mean reward {mean_score:.4}", coord.mean_deg, coord.std_deg);
        history.push(json!({"iteration": it, "mean_deg": coord.mean_deg, "std_deg": coord.std_deg, "mean_reward": mean_score}));
    }
    let out = a.out.unwrap_or_else(|| a.policy.join(format!("coordinator-{}.json", a.scenario)));
    let v = json!({"scenario": a.scenario, "mean_deg": coord.mean_deg, "std_deg": coord.std_deg, "history": history});
    std::fs::write(&out, serde_json::to_string_pretty(&v)?).with_context(|| format!("writing {}", out.display()))?;
    println!("{v}");
    Ok(())
}

pub fn run(ctx: &Ctx, a: EvalFlowArgs) -> Result<()> {
    let learned = a.policy.as_deref().map(|dir| LearnedFlow::config(dir).map(|job| (dir, job))).transpose()?;
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
        bail!("--cases {} exceeds the {} stored cases of {}", a.cases, cases.cases.len(), a.scenario);
    }
    let cfg = std::sync::Arc::new(SimConfig::default());
    let jobs: Vec<(usize, u32)> = (0..a.cases as usize).flat_map(|c| (0..a.seeds).map(move |s| (c, s))).collect();
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
            let flow = LearnedFlow::load(dir, job, &map)?;
            jobs.iter().map(|&(c, seed)| Ok(flow.episode(&map, &cases.cases[c], a.vehicles, 1_000_003 * c as u64 + seed as u64, a.deterministic, None)?.0)).collect::<Result<_>>()?
        }
    };
    let col = |f: fn(&EpisodeMetrics) -> f32| Summary::of(&results.iter().map(|m| f(m) as f64).collect::<Vec<_>>());
    let (success, safety, speed) = (col(|m| m.success), col(|m| m.safety), col(|m| m.speed));
    let failures = json!({
        "collision": col(|m| m.collision).mean,
        "off_road": col(|m| m.off_road).mean,
        "off_route": col(|m| m.off_route).mean,
        "wrong_lane": col(|m| m.wrong_lane).mean,
        "timeout": col(|m| m.timeout).mean,
        "destination": col(|m| m.destination).mean,
    });
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
        });
        println!("{out}");
    } else {
        let p = |x: Summary| format!("{:5.1}% +- {:.1}", 100.0 * x.mean, 100.0 * x.ci95);
        println!("{flow_name} flow in {} over {} episodes", a.scenario, results.len());
        println!("  success {}\n  safety  {}\n  speed   {}", p(success), p(safety), p(speed));
        println!("  failures {failures}");
    }
    Ok(())
}
