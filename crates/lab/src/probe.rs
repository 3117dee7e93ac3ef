//! `socialflow probe <job.toml>`: the critic probe ([`critic`]) on a job config: can its
//! critic tell, from demonstrator data alone, which states lead to a failure?
//!
//! Owns: [`ProbeArgs`] and the command (read the job, collect, train, print one JSON line).
//! Must not: change the job's settings or write files; the probe itself is [`critic`]'s.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use sf_embedded::Ctx;
use sf_job::JobConfig;
use sf_rollout::setup;
use sf_sac::Sac;

pub mod critic;

#[derive(Args, Debug)]
pub struct ProbeArgs {
    /// An ego job config (its observation, network, SAC settings and traffic are probed).
    pub job: PathBuf,
    /// Demonstrator transitions to collect (80 % of the episodes train, 20 % are held out).
    #[arg(long, default_value_t = 40_000)]
    pub transitions: usize,
    /// Updates (the job's cloning updates, then the critic alone).
    #[arg(long, default_value_t = 3_000)]
    pub updates: u64,
    /// A failure within this many decision steps is a positive.
    #[arg(long, default_value_t = 4)]
    pub horizon: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn run(dirs: &Ctx, a: ProbeArgs) -> Result<()> {
    let text =
        std::fs::read_to_string(&a.job).with_context(|| format!("reading {}", a.job.display()))?;
    let job = JobConfig::from_toml(&text).with_context(|| a.job.display().to_string())?;
    anyhow::ensure!(
        a.transitions >= 1000 && a.horizon >= 1,
        "--transitions must be at least 1000 and --horizon at least 1"
    );
    let maps = job.env.scenarios.iter().map(|s| dirs.map(s)).collect::<Result<Vec<_>>>()?;
    let data = critic::collect(&job, &maps, a.transitions, a.horizon, a.seed)
        .map_err(anyhow::Error::msg)?;
    let segs = critic::segments(&maps, &job);
    let seg_refs: Vec<_> = segs.iter().collect();
    let r = setup::resolve(&job, None);
    let mut sac = Sac::new(r.sac, r.net, r.obs, r.sim.dt_s, &seg_refs)?;
    let score =
        critic::train_and_score(&mut sac, &data, a.updates, a.seed).map_err(anyhow::Error::msg)?;
    println!(
        "{}",
        serde_json::json!({"job": a.job.display().to_string(), "horizon": a.horizon, "score": score})
    );
    Ok(())
}
