//! `socialflow eval <config>`: the paper's evaluation grid over stored cases and seeds, run in
//! this process.
//!
//! Owns: finding the grid's trained jobs by name in a learner's data directory (the config's
//! `runs`), running the cells not yet stored (`sf_rollout::evaluate::run_cell`, the code a worker
//! runs for an evaluation job's cells) and appending them to `episodes.csv` in the config's
//! `out`; `socialflow report`. A rerun skips cells already stored and appends the rest, so
//! nothing stored is lost (a stored cell whose episode count is not what the config now asks,
//! e.g. after its `sizes` changed, is kept and warned about, not rerun). The grid itself
//! (`sf_job::eval::EvalConfig`, each cell sized by `EvalConfig::size_of`) is shared with the
//! learner's evaluation jobs (`socialflow submit` of the same file), which spread the cells over
//! workers. Must not: compute statistics or draw (`sf_report::report` does).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use sf_embedded::runs::find_job;
use sf_job::config::JobKind;
use sf_job::eval::{Cell, EvalConfig};
use sf_report::episodes::{EpisodeRow, EpisodesWriter, Meta};
use sf_rollout::evaluate::{self, CellSize, FlowDef, Runners};

use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Evaluation config (TOML), e.g. configs/eval/paper-small.toml.
    pub config: PathBuf,
    /// Override the config's `out` directory.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Override the config's `runs` directory (the same grid on another replicate's jobs).
    #[arg(long)]
    pub runs: Option<PathBuf>,
    /// Failure mining once the grid is evaluated: `worst=N` replays the N worst stored episodes
    /// of every cell (lowest success, then most collisions) into viewer pages under
    /// `<out>/mined/`, with `index.html` listing them by outcome (collision, off-road, ...,
    /// road closed, timeout).
    #[arg(long, value_name = "worst=N")]
    pub mine: Option<String>,
    /// Rows per inference call of the learned policies: a number (what every result evaluated
    /// since 2026-12-08 used is the default), with which a stored episode ends the same at any
    /// `envs`, thread or worker count; or `all`, one call per step (faster where many rows step
    /// together, and episodes then depend on `envs`).
    #[arg(long, value_name = "N|all", value_parser = parse_inference_rows,
          default_value_t = InferenceRows(Some(evaluate::EVAL_INFERENCE_ROWS)))]
    pub inference_rows: InferenceRows,
}

/// `--inference-rows`: a fixed width, or one call per step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InferenceRows(pub Option<usize>);

impl std::fmt::Display for InferenceRows {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            Some(n) => write!(f, "{n}"),
            None => f.write_str("all"),
        }
    }
}

fn parse_inference_rows(s: &str) -> Result<InferenceRows, String> {
    if s == "all" {
        return Ok(InferenceRows(None));
    }
    match s.parse::<usize>() {
        Ok(n) if n > 0 => Ok(InferenceRows(Some(n))),
        _ => Err(format!("`{s}` is neither a positive number of rows nor `all`")),
    }
}

/// Reads and validates an evaluation config file.
pub fn load(path: &Path) -> Result<EvalConfig> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    EvalConfig::from_toml(&text).with_context(|| path.display().to_string())
}

fn flow_def(runs: &Path, f: &sf_job::eval::Named) -> Result<FlowDef> {
    if f.is_idm() {
        return Ok(FlowDef::Idm);
    }
    if f.is_idm_noise() {
        return Ok(FlowDef::IdmNoise { std: f.noise_std() });
    }
    let t = find_job(runs, &f.job, f.job_id)?;
    let messages = f.messages;
    match t.cfg.kind {
        JobKind::Ego => bail!("`{}` ({}) is an ego job, not a flow", f.job, t.key),
        JobKind::SocialcommAdv => {
            let bg_id = t
                .cfg
                .env
                .background_job
                .with_context(|| format!("{}: a socialcomm-adv job without its flow", t.key))?;
            let bg = find_job(runs, "", Some(bg_id))?;
            Ok(FlowDef::Learned { background: bg, adversary: Some(t), messages })
        }
        _ => Ok(FlowDef::Learned { background: t, adversary: None, messages }),
    }
}

/// Loads the map and stored cases of every scenario the grid runs in.
pub fn load_maps(
    ctx: &Ctx,
    cfg: &EvalConfig,
) -> Result<BTreeMap<String, (Arc<sf_sim::Map>, sf_sim::CaseFile)>> {
    let mut maps = BTreeMap::new();
    for s in cfg.all_scenarios() {
        let m = ctx.map(&s)?;
        let c = ctx.cases(&m)?;
        maps.insert(s, (m, c));
    }
    Ok(maps)
}

/// A grid's names resolved in its trained runs (every flow and ego found and fitting its
/// cells), with the maps and stored cases of its scenarios: what running cells and replaying
/// episodes need.
pub struct Grid {
    pub cfg: EvalConfig,
    pub resolved: evaluate::Resolved,
    pub maps: BTreeMap<String, (Arc<sf_sim::Map>, sf_sim::CaseFile)>,
}

/// Resolves the grid of `cfg` (read from `config`) in `runs`.
pub fn resolve(ctx: &Ctx, config: &Path, cfg: EvalConfig, runs: &Path) -> Result<Grid> {
    // Everything named must exist, and every cell's ego and flow fit, before anything runs.
    let mut grid = evaluate::Resolved::default();
    for f in &cfg.flows {
        grid.flows.insert(
            f.name.clone(),
            flow_def(runs, f).with_context(|| format!("flow `{}`", f.name))?,
        );
    }
    for e in &cfg.egos {
        if let Some(s) = e.scripted() {
            grid.egos.insert(e.name.clone(), s.into());
            continue;
        }
        let t = find_job(runs, &e.job, e.job_id).with_context(|| format!("ego `{}`", e.name))?;
        // A probe places a Stage-1 flow's actor in the ego's seat, zero-shot.
        let stage1_flow =
            matches!(t.cfg.kind, JobKind::Macad | JobKind::Copo | JobKind::Socialcomm);
        match (e.flow_actor, t.cfg.kind) {
            (false, JobKind::Ego) => {}
            (true, _) if stage1_flow => {}
            (true, k) => bail!("ego `{}`: `flow_actor = true` needs a Stage-1 flow job (macad, copo, socialcomm), job `{}` is a {} job", e.name, e.job, k.as_str()),
            (false, k) => bail!("ego `{}`: job `{}` is a {} job (a flow's actor in the ego's seat needs `flow_actor = true`)", e.name, e.job, k.as_str()),
        }
        grid.egos.insert(e.name.clone(), evaluate::EgoDef::Learned(t));
    }
    grid.check(&cfg.cells()).map_err(anyhow::Error::msg)?;
    let maps = load_maps(ctx, &cfg)?;
    cfg.check_stored_cases(|s| maps.get(s).map_or(0, |(_, c)| c.cases.len()))
        .with_context(|| config.display().to_string())?;
    Ok(Grid { cfg, resolved: grid, maps })
}

/// The config's `runs` and `out`, or the flags that override them.
pub fn runs_and_out(
    config: &Path,
    cfg: &EvalConfig,
    runs: Option<PathBuf>,
    out: Option<PathBuf>,
) -> Result<(PathBuf, PathBuf)> {
    let runs = runs.or(cfg.runs.clone()).with_context(|| format!("{}: field `runs` (or --runs: the data directory of the trained jobs) is needed to evaluate here", config.display()))?;
    let out = out.or(cfg.out.clone()).with_context(|| {
        format!("{}: field `out` (or --out) is needed to evaluate here", config.display())
    })?;
    Ok((runs, out))
}

pub fn run(ctx: &Ctx, a: EvalArgs) -> Result<()> {
    let cfg = load(&a.config)?;
    // `--mine` over the grid's own `mine_worst`.
    let mine = match a.mine.as_deref() {
        Some(spec) => Some(crate::view::MineSpec::parse(spec)?),
        None => cfg.mine_worst.map(|worst| crate::view::MineSpec { worst }),
    };
    let (runs, out) = runs_and_out(&a.config, &cfg, a.runs, a.out)?;
    let Grid { cfg, resolved: grid, maps } = resolve(ctx, &a.config, cfg, &runs)?;
    let all = cfg.cells();
    let mut runners = Runners::new(sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?)
        .with_inference_rows(a.inference_rows.0);
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let meta_path = out.join("meta.json");
    std::fs::write(&meta_path, serde_json::to_string_pretty(&Meta::of(&cfg))?)
        .with_context(|| format!("writing {}", meta_path.display()))?;
    let path = out.join("episodes.csv");
    if let Some(gz) = sf_report::episodes::stored_gzipped(&path) {
        bail!("{} is stored gzipped: gunzip it to add cells to it", gz.display());
    }
    let stored = sf_report::episodes::read_episodes(&path)
        .with_context(|| format!("reading {}", path.display()))?;
    let mut have: BTreeMap<Cell, u64> = BTreeMap::new();
    for r in &stored {
        *have.entry(r.cell()).or_default() += 1;
    }
    for cell in all.iter().filter(|c| have.get(c).is_some_and(|&n| n != cfg.episodes_of(c))) {
        let (cases, seeds) = cfg.size_of(cell);
        eprintln!(
            "warning: cell {} is stored in {} with {} episodes, the config now asks {} ({cases} cases x {seeds} seeds); keeping the stored ones (remove its rows to rerun it)",
            cell.key(),
            path.display(),
            have[cell],
            cfg.episodes_of(cell)
        );
    }
    let todo: Vec<Cell> = all.into_iter().filter(|c| !have.contains_key(c)).collect();
    let per_cell: BTreeSet<u64> = todo.iter().map(|c| cfg.episodes_of(c)).collect();
    let each = match (per_cell.first(), per_cell.last()) {
        (Some(lo), Some(hi)) if lo == hi => format!("{lo} episodes each"),
        (Some(lo), Some(hi)) => format!(
            "{} episodes ({lo} to {hi} per cell)",
            todo.iter().map(|c| cfg.episodes_of(c)).sum::<u64>()
        ),
        _ => "no episodes".to_string(),
    };
    eprintln!("{} cells to run ({} stored), {each}", todo.len(), have.len());
    let mut file = EpisodesWriter::open(&path)?;
    let progress =
        sf_embedded::client::EpisodesBar::new(todo.iter().map(|c| cfg.episodes_of(c)).sum());
    for (k, cell) in todo.iter().enumerate() {
        let (n_cases, n_seeds) = cfg.size_of(cell);
        let size = CellSize { cases: n_cases, seeds: n_seeds, envs: cfg.envs };
        let (map, cases) = maps.get(&cell.scenario).context("scenario loaded")?;
        let t = std::time::Instant::now();
        let (flow, ego) = grid.cell(cell).map_err(anyhow::Error::msg)?;
        let eps = evaluate::run_cell(cell, size, map, cases, flow, ego, &mut runners)
            .map_err(anyhow::Error::msg)
            .with_context(|| format!("cell {}", cell.key()))?;
        let rows: Vec<EpisodeRow> = eps.iter().map(|e| EpisodeRow::new(cell, e)).collect();
        file.append(&rows)?;
        let s =
            rows.iter().map(|r| r.ep.scores.success as f64).sum::<f64>() / rows.len().max(1) as f64;
        progress.line(format!(
            "[{}/{}] {:<64} success {:5.1}%  ({:.1} s)",
            k + 1,
            todo.len(),
            cell.key(),
            100.0 * s,
            t.elapsed().as_secs_f64()
        ));
        progress.bar.inc(rows.len() as u64);
    }
    progress.bar.finish_and_clear();
    eprintln!("wrote {}", path.display());
    if let Some(g) = &cfg.experiments.gifs {
        for p in grid.render_gifs(g, &out, &maps, &mut runners).map_err(anyhow::Error::msg)? {
            eprintln!("wrote {}", p.display());
        }
    }
    if let Some(spec) = mine {
        let grid = Grid { cfg, resolved: grid, maps };
        let index = crate::view::mine(&grid, &out, spec, &mut runners)?;
        eprintln!("wrote {}", index.display());
    }
    Ok(())
}

#[derive(Args, Debug)]
pub struct ReportArgs {
    /// A results directory written by `socialflow eval` (`episodes.csv`, `meta.json`); several
    /// are replicates of one graph evaluated on the same grid (their own reports go to
    /// `<out>/run-1`, `<out>/run-2`, ..., the pooled one to `<out>`).
    #[arg(required = true, num_args = 1..)]
    pub results: Vec<PathBuf>,
    /// Where `report.md`, `report.html` and the figures go.
    #[arg(long, default_value = "report")]
    pub out: PathBuf,
}

/// Builds the report from stored results; prints the findings as JSON.
pub fn report(a: ReportArgs) -> Result<()> {
    let mut sets = Vec::with_capacity(a.results.len());
    let mut meta: Option<(PathBuf, sf_report::episodes::Meta)> = None;
    for dir in &a.results {
        let episodes = sf_report::episodes::episodes_file(dir);
        let rows = sf_report::episodes::read_episodes(&episodes)?;
        if rows.is_empty() {
            bail!(
                "{} holds no evaluated episodes (run `socialflow eval` first)",
                episodes.display()
            );
        }
        let m = sf_report::episodes::read_meta(&dir.join("meta.json"))?;
        match &meta {
            Some((first, m0)) if *m0 != m => bail!("{} and {} were not evaluated on the same grid (their meta.json differ): replicates must share one", first.display(), dir.display()),
            Some(_) => {}
            None => meta = Some((dir.clone(), m)),
        }
        sets.push(rows);
    }
    let Some((_, meta)) = meta else { bail!("no results directory given") };
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    // Episode GIFs of the first replicate.
    for e in std::fs::read_dir(&a.results[0])
        .with_context(|| format!("reading {}", a.results[0].display()))?
        .flatten()
    {
        let name = e.file_name().to_string_lossy().to_string();
        if name.starts_with("gif-") && name.ends_with(".gif") {
            std::fs::copy(e.path(), a.out.join(&name))
                .with_context(|| format!("copying {name}"))?;
        }
    }
    // Failure mining's pages of the first replicate (`eval --mine`), which the report links.
    let mined = a.results[0].join("mined");
    if mined.join("cells.json").is_file() {
        let to = a.out.join("mined");
        std::fs::create_dir_all(&to).with_context(|| format!("creating {}", to.display()))?;
        for e in std::fs::read_dir(&mined)
            .with_context(|| format!("reading {}", mined.display()))?
            .flatten()
        {
            if e.path().is_file() {
                std::fs::copy(e.path(), to.join(e.file_name()))
                    .with_context(|| format!("copying {}", e.path().display()))?;
            }
        }
    }
    let f = sf_report::report::build_replicates(&sets, &meta, &a.out)?;
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
        let c = load(&p).expect("valid");
        let cells = c.cells();
        let count = |e: &str| cells.iter().filter(|c| c.experiment == e).count();
        assert_eq!(
            count("cross"),
            7 * 4 * 4,
            "6 trained egos and the IDM driver x 4 flows x 4 scenarios"
        );
        assert_eq!(count("svo_sweep"), 2 * 4 * 10);
        assert_eq!(count("density"), 4 * 6);
        let keys: BTreeSet<String> = cells.iter().map(Cell::key).collect();
        assert_eq!(keys.len(), cells.len(), "cells are distinct");
        let svos: BTreeSet<u32> = cells.iter().filter_map(|c| c.svo_deg).collect();
        assert_eq!(
            svos.into_iter().collect::<Vec<_>>(),
            vec![0, 10, 20, 30, 40, 50, 60, 70, 80, 90]
        );
        // The flows-only grid: the same flow cells, no ego.
        let p =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/eval/paper-small-flows.toml");
        let flows = load(&p).expect("valid").cells();
        assert!(flows.iter().all(|c| c.ego.is_empty()), "no ego cells");
        let flow_keys: BTreeSet<String> = flows.iter().map(Cell::key).collect();
        let full_flow_keys: BTreeSet<String> =
            cells.iter().filter(|c| c.ego.is_empty()).map(Cell::key).collect();
        assert_eq!(flow_keys, full_flow_keys, "the flows-only grid is the full grid's flow cells");
        // The paper's grid: 200 cases x 10 seeds, the same experiments.
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/eval/paper.toml");
        let paper = load(&p).expect("valid");
        assert_eq!((paper.cases, paper.seeds), (200, 10));
        assert_eq!(paper.cells(), cells, "the paper grid has the paper-small grid's cells");
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../configs/eval/paper-small-flow-quality-200x10.toml");
        let fq = load(&p).expect("valid");
        assert_eq!((fq.cases, fq.seeds), (200, 10));
        assert_eq!(
            fq.cells(),
            cells.iter().filter(|c| c.experiment == "flow_quality").cloned().collect::<Vec<_>>()
        );
    }
}
