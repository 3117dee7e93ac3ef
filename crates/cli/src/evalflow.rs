//! `socialflow eval-flow`: a flow's Success, Safety and Speed over the stored cases.

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
    #[arg(long, value_enum)]
    flow: Flow,
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

pub fn run(ctx: &Ctx, a: EvalFlowArgs) -> Result<()> {
    let mode = flow_mode(a.flow)?;
    let map = ctx.map(&a.scenario)?;
    let cases = ctx.cases(&map)?;
    if a.cases as usize > cases.cases.len() {
        bail!("--cases {} exceeds the {} stored cases of {}", a.cases, cases.cases.len(), a.scenario);
    }
    let cfg = std::sync::Arc::new(SimConfig::default());
    let jobs: Vec<(usize, u32)> = (0..a.cases as usize).flat_map(|c| (0..a.seeds).map(move |s| (c, s))).collect();
    let results: Vec<EpisodeMetrics> = jobs
        .par_iter()
        .map(|&(c, _seed)| {
            // The all-IDM flow is deterministic: the seed only matters for stochastic flows.
            let mut env = Env::new(map.clone(), cfg.clone());
            env.reset(&cases.cases[c], mode, a.vehicles).context("resetting a stored case")?;
            env.run_episode(|_, _| {}, |_| {})?;
            Ok(EpisodeMetrics::from_outcomes(env.outcomes(), false))
        })
        .collect::<Result<_>>()?;
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
            "flow": format!("{:?}", a.flow).to_lowercase(),
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
        println!("{:?} flow in {} over {} episodes", a.flow, a.scenario, results.len());
        println!("  success {}\n  safety  {}\n  speed   {}", p(success), p(safety), p(speed));
        println!("  failures {failures}");
    }
    Ok(())
}
