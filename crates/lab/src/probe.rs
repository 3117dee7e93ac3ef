//! `socialflow probe <job.toml>`: probes of a job config on its IDM demonstrator's data.
//! `--kind critic` ([`critic`]): can its critic tell, from demonstrator data alone, which states
//! lead to a failure? `--kind handover` ([`handover`]): where does SAC's objective move the
//! job's clone of IDM once the actor follows it, per action component, and why?
//!
//! Owns: [`ProbeArgs`] and the command (read the job, collect, train, print JSON lines).
//! Must not: change the job's settings (beyond the critic probe's frozen actor) or write
//! files; the probes themselves are their modules'.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use sf_embedded::Ctx;
use sf_job::JobConfig;
use sf_rollout::setup;
use sf_sac::Sac;

pub mod critic;
pub mod handover;

/// Which probe runs.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProbeKind {
    Critic,
    Handover,
}

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
    /// The probe: `critic` (failure prediction) or `handover` (the clone under SAC).
    #[arg(long, value_enum, default_value = "critic")]
    pub kind: ProbeKind,
    /// Hand-over probe: SAC updates after the job's cloning and critic-only updates.
    #[arg(long, default_value_t = 1_000)]
    pub sac_updates: u64,
    /// Hand-over probe: updates between measurements.
    #[arg(long, default_value_t = 100)]
    pub every: u64,
    /// Hand-over probe: held-out rows measured.
    #[arg(long, default_value_t = 2_000)]
    pub rows: usize,
    /// Hand-over probe: closed-loop episodes per measurement (0: none).
    #[arg(long, default_value_t = 100)]
    pub episodes: u32,
    /// Hand-over probe: a directory for GIFs of the first failing closed-loop episode.
    #[arg(long)]
    pub gif_dir: Option<PathBuf>,
    /// Hand-over probe: the measurements (updates after the hand-over) that write a GIF.
    #[arg(long, value_delimiter = ',', default_value = "0,100,500")]
    pub gif_at: Vec<u64>,
}

pub fn run(dirs: &Ctx, a: ProbeArgs) -> Result<()> {
    let text =
        std::fs::read_to_string(&a.job).with_context(|| format!("reading {}", a.job.display()))?;
    let job = JobConfig::from_toml(&text).with_context(|| a.job.display().to_string())?;
    anyhow::ensure!(
        a.transitions >= 1000 && a.horizon >= 1,
        "--transitions must be at least 1000 and --horizon at least 1"
    );
    let r = setup::resolve(&job, None);
    if a.kind == ProbeKind::Handover {
        // Refused before any data is collected.
        anyhow::ensure!(
            r.net.action == sf_sim::vehicle::DriveAction::Direct,
            "--kind handover needs a job with the direct action (env.action = \"direct\"): IDM's \
             action is the clone's reference"
        );
        anyhow::ensure!(
            job.kind == sf_job::config::JobKind::Ego && job.env.background_job.is_none(),
            "--kind handover drives the clone among IDM cars: give it an ego job without \
             env.background_job"
        );
        anyhow::ensure!(a.every >= 1, "--every must be at least 1");
    }
    let maps = job.env.scenarios.iter().map(|s| dirs.map(s)).collect::<Result<Vec<_>>>()?;
    let data = critic::collect(&job, &maps, a.transitions, a.horizon, a.seed)
        .map_err(anyhow::Error::msg)?;
    let segs = critic::segments(&maps, &job);
    let seg_refs: Vec<_> = segs.iter().collect();
    let mut sac = Sac::new(r.sac, r.net, r.obs, r.sim.dt_s, &seg_refs)?;
    if a.kind == ProbeKind::Handover {
        let settings = handover::HandoverSettings {
            sac_updates: a.sac_updates,
            every: a.every,
            rows: a.rows,
            episodes: a.episodes,
            seed: a.seed,
            gif_dir: a.gif_dir.clone(),
            gif_at: a.gif_at.clone(),
        };
        if let Some(d) = &a.gif_dir {
            std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
        }
        handover::run(&mut sac, &data, &job, &maps, &settings, |p| {
            println!("{}", serde_json::json!({"job": a.job.display().to_string(), "point": p}));
        })
        .map_err(anyhow::Error::msg)?;
        return Ok(());
    }
    let score =
        critic::train_and_score(&mut sac, &data, a.updates, a.seed).map_err(anyhow::Error::msg)?;
    println!(
        "{}",
        serde_json::json!({"job": a.job.display().to_string(), "horizon": a.horizon, "score": score})
    );
    Ok(())
}
