//! `socialflow learn-ego`: trains an ego policy with SAC among IDM traffic in one process and
//! writes its learning curve (CSV + PNG), its configuration and a final checkpoint.
//! `socialflow plot-curves` overlays the curves of several runs.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;
use sf_eval::plot::{line_chart, Series};
use sf_nn::NetConfig;
use sf_sac::ego::{train_ego, CurvePoint, EgoRun};
use sf_sac::{checkpoint, Sac, SacConfig};
use sf_sim::obs::MapSegments;
use sf_sim::{Controller, Layout, SimConfig};

use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct LearnArgs {
    /// Scenarios to train on at once (comma-separated).
    #[arg(long = "scenario", value_delimiter = ',', default_value = "roundabout")]
    train_scenarios: Vec<String>,
    #[arg(long, default_value_t = 2)]
    vehicles_min: u32,
    #[arg(long, default_value_t = 4)]
    vehicles_max: u32,
    /// Learner transitions to collect.
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
    #[arg(long, default_value_t = 8)]
    envs: usize,
    /// `ego-frame` or `query-centric`.
    #[arg(long, value_parser = Layout::parse, default_value = "query-centric")]
    encoder: Layout,
    /// Token width; the DeepSets use the same width, the heads twice it.
    #[arg(long, default_value_t = 64)]
    width: usize,
    /// Updates per collected transition.
    #[arg(long, default_value_t = 0.25)]
    ratio: f64,
    #[arg(long, default_value_t = 2_000)]
    warmup: u64,
    #[arg(long, default_value_t = 50.0)]
    reward_scale: f32,
    #[arg(long, default_value_t = 128)]
    batch: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long)]
    out: PathBuf,
}

pub fn run(ctx: &Ctx, a: LearnArgs) -> Result<()> {
    if a.vehicles_min == 0 || a.vehicles_min > a.vehicles_max {
        bail!("--vehicles-min must be in 1..=--vehicles-max");
    }
    let mut sim = SimConfig::default();
    sim.obs.layout = a.encoder;
    let sim = Arc::new(sim);
    let maps = a.train_scenarios.iter().map(|s| ctx.map(s)).collect::<Result<Vec<_>>>()?;
    let segs: Vec<MapSegments> = maps.iter().map(|m| MapSegments::build(m, sim.obs.segment_points)).collect();
    let seg_refs: Vec<&MapSegments> = segs.iter().collect();
    let net = NetConfig { encoder: a.encoder, d_model: a.width, set_hidden: a.width, head_hidden: 2 * a.width, ..NetConfig::fast() };
    let cfg = SacConfig { warmup_steps: a.warmup, reward_scale: a.reward_scale, batch_size: a.batch, seed: a.seed, ..SacConfig::default() };
    let spec = sf_sim::ObsSpec::new(&sim.obs);
    let mut sac = Sac::new(cfg.clone(), net.clone(), spec, sim.dt_s, &seg_refs)?;
    let run = EgoRun {
        maps,
        envs_per_map: a.envs,
        vehicles: (a.vehicles_min, a.vehicles_max),
        background: Controller::Idm,
        env_steps: a.steps,
        updates_per_step: a.ratio,
        replay_capacity: 1_000_000,
        report_every: (a.steps / 50).max(100),
        policy_refresh_updates: 10,
        window: 100,
        seed: a.seed,
    };
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let config = json!({"args": format!("{a:?}"), "sac": cfg, "net": net, "sim_obs": sim.obs});
    std::fs::write(a.out.join("config.json"), serde_json::to_string_pretty(&config)?)?;
    let csv_path = a.out.join("curve.csv");
    let mut csv = std::fs::File::create(&csv_path).with_context(|| format!("creating {}", csv_path.display()))?;
    writeln!(csv, "{}", CurvePoint::CSV_HEADER)?;
    let mut write_err = None;
    let curve = train_ego(&sim, &mut sac, &run, |p| {
        eprintln!(
            "steps {:>7} updates {:>6} episodes {:>5} success {:.2} safety {:.2} speed {:.2} alpha {:.3} {:.0}s",
            p.env_steps, p.updates, p.episodes, p.success, p.safety, p.speed, p.alpha, p.wall_s
        );
        if let Err(e) = writeln!(csv, "{}", p.csv_row()) {
            write_err.get_or_insert(e);
        }
    });
    if let Some(e) = write_err {
        return Err(e).context("writing curve.csv");
    }
    checkpoint::save(&sac, &a.out.join("checkpoint"))?;
    let label = a.encoder.as_str();
    plot(&a.out.join("curve.png"), &format!("ego SAC in {} ({label})", a.train_scenarios.join("+")), &[(label, &curve)])?;
    let last = curve.last().copied().unwrap_or_default();
    println!("{}", json!({"out": a.out, "env_steps": last.env_steps, "updates": last.updates, "success": last.success, "safety": last.safety, "speed": last.speed, "wall_s": last.wall_s}));
    Ok(())
}

fn plot(path: &std::path::Path, title: &str, runs: &[(&str, &Vec<CurvePoint>)]) -> Result<()> {
    let mut series = Vec::new();
    for (name, c) in runs {
        series.push(Series { name, points: c.iter().map(|p| (p.env_steps as f64, p.success as f64)).collect() });
    }
    line_chart(path, title, "learner transitions", "success (last 100 episodes)", &series, Some((0.0, 1.0)), (800, 500))?;
    Ok(())
}

#[derive(Args, Debug)]
pub struct PlotArgs {
    /// `name=path/to/curve.csv` pairs.
    #[arg(required = true)]
    runs: Vec<String>,
    #[arg(long, default_value = "success")]
    column: String,
    #[arg(long)]
    title: Option<String>,
    #[arg(long)]
    out: PathBuf,
}

pub fn plot_curves(a: PlotArgs) -> Result<()> {
    let mut series = Vec::new();
    let mut names = Vec::new();
    for r in &a.runs {
        let Some((name, path)) = r.split_once('=') else { bail!("run `{r}` must be NAME=PATH") };
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {path}"))?;
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().context("empty curve file")?.split(',').collect();
        let col = header.iter().position(|h| *h == a.column).with_context(|| format!("{path} has no column `{}`", a.column))?;
        let mut pts = Vec::new();
        for (k, l) in lines.enumerate() {
            let f: Vec<&str> = l.split(',').collect();
            let x: f64 = f.first().and_then(|v| v.parse().ok()).with_context(|| format!("{path} line {}: bad env_steps", k + 2))?;
            let y: f64 = f.get(col).and_then(|v| v.parse().ok()).with_context(|| format!("{path} line {}: bad {}", k + 2, a.column))?;
            pts.push((x, y));
        }
        names.push(name.to_string());
        series.push(pts);
    }
    let s: Vec<Series> = names.iter().zip(series).map(|(n, p)| Series { name: n, points: p }).collect();
    let unit = matches!(a.column.as_str(), "success" | "safety" | "speed");
    line_chart(&a.out, a.title.as_deref().unwrap_or(&a.column), "learner transitions", &a.column, &s, unit.then_some((0.0, 1.0)), (800, 500))?;
    eprintln!("wrote {}", a.out.display());
    Ok(())
}
