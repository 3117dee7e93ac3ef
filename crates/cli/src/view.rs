//! `socialflow view` (one stored episode of an evaluation grid as a browser page) and failure
//! mining (`socialflow eval ... --mine worst=N`: the worst stored episodes of every cell replayed
//! into pages, with an index sorted by outcome).
//!
//! Owns: choosing which episodes to replay, naming the pages and writing them with the index.
//! The replay and the page are `sf_rollout::evaluate::view`'s; the grid's names are resolved as
//! `eval` resolves them (`crate::eval::resolve`). Must not: run cells or change `episodes.csv`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use sf_job::eval::Cell;
use sf_report::episodes::EpisodeRow;
use sf_rollout::evaluate::view::{self, IndexRow, StoredRow};
use sf_rollout::evaluate::Runners;

use crate::eval::{load, resolve, runs_and_out, Grid};
use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct ViewArgs {
    /// Evaluation config (TOML) whose grid holds the episode, e.g. configs/eval/paper-small.toml.
    pub config: PathBuf,
    /// The cell, as `episodes.csv` and `eval`'s log write it:
    /// `experiment|ego|flow|scenario|svo_deg|vehicles` (empty fields stay empty), e.g.
    /// `cross|RL/IDM|SocialComm|merge||`.
    #[arg(long)]
    pub cell: String,
    /// The stored case's id (`episodes.csv`'s `case`).
    #[arg(long)]
    pub case: u32,
    /// The evaluation seed (`episodes.csv`'s `seed`).
    #[arg(long, default_value_t = 0)]
    pub seed: u32,
    /// The page to write (default: `<out>/view/<cell>-case<case>-seed<seed>.html`).
    #[arg(long)]
    pub page: Option<PathBuf>,
    /// Override the config's `runs` directory.
    #[arg(long)]
    pub runs: Option<PathBuf>,
    /// Override the config's `out` directory (where the stored episode is looked up).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// What `--mine` asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MineSpec {
    /// Episodes per cell.
    pub worst: usize,
}

impl MineSpec {
    pub fn parse(s: &str) -> Result<Self> {
        let n = s.strip_prefix("worst=").with_context(|| {
            format!("--mine `{s}`: expected `worst=N` (the N worst episodes of every cell)")
        })?;
        let worst: usize = n
            .parse()
            .with_context(|| format!("--mine `{s}`: N must be a positive whole number"))?;
        if worst == 0 {
            bail!("--mine `{s}`: N must be at least 1");
        }
        Ok(Self { worst })
    }
}

/// A cell key as a file name: letters, digits, `-` and `_` kept, the rest `_`.
fn file_stem(cell: &Cell, case: u32, seed: u32) -> String {
    let key: String = cell
        .key()
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' })
        .collect();
    format!("{key}-case{case}-seed{seed}")
}

/// The stored rows of `out`'s episodes file, if it has one.
fn stored_rows(out: &Path) -> Result<Vec<EpisodeRow>> {
    let path = sf_report::episodes::episodes_file(out);
    if !path.exists() {
        return Ok(Vec::new());
    }
    sf_report::episodes::read_episodes(&path).with_context(|| format!("reading {}", path.display()))
}

/// Replays one episode of `cell` (stored case id `case_id`, `seed`) into the page `path`; the
/// index row that links it as `href`.
#[allow(clippy::too_many_arguments)]
fn write_episode(
    grid: &Grid,
    cell: &Cell,
    case_id: u32,
    seed: u32,
    stored: Option<&EpisodeRow>,
    path: &Path,
    href: String,
    runners: &mut Runners,
) -> Result<IndexRow> {
    let (map, cases) = grid
        .maps
        .get(&cell.scenario)
        .with_context(|| format!("scenario `{}` is not in the grid", cell.scenario))?;
    let case_index = cases.cases.iter().position(|c| c.id == case_id).with_context(|| {
        format!(
            "case {case_id} is not among the {} stored cases of {}",
            cases.cases.len(),
            cell.scenario
        )
    })?;
    let (flow, ego) = grid.resolved.cell(cell).map_err(anyhow::Error::msg)?;
    let trace = view::record(cell, map, cases, case_index, seed, flow, ego, runners)
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("replaying case {case_id} seed {seed} of {}", cell.key()))?;
    let metrics = trace.metrics.context("the replay has no metrics")?;
    let stored = stored.map(|r| StoredRow {
        success: r.ep.scores.success,
        safety: r.ep.scores.safety,
        speed: r.ep.scores.speed,
        collision: r.ep.collision,
        road_closed: r.ep.road_closed,
    });
    let key = cell.key();
    let title = format!("{key} - case {case_id}, seed {seed}");
    let html = view::page(&trace, &title, stored.as_ref()).map_err(anyhow::Error::msg)?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(path, html).with_context(|| format!("writing {}", path.display()))?;
    Ok(IndexRow {
        href,
        cell: key,
        experiment: cell.experiment.clone(),
        ego: cell.ego.clone(),
        flow: cell.flow.clone(),
        scenario: cell.scenario.clone(),
        svo_deg: cell.svo_deg,
        vehicles: cell.vehicles,
        case: case_id,
        seed,
        outcome: view::outcome_class(&metrics).to_string(),
        metrics,
        replay_agrees: stored.map(|s| s.agrees(&metrics)),
    })
}

/// `socialflow view`: one episode's page.
pub fn run(ctx: &Ctx, a: ViewArgs) -> Result<()> {
    let cfg = load(&a.config)?;
    let (runs, out) = runs_and_out(&a.config, &cfg, a.runs, a.out)?;
    let grid = resolve(ctx, &a.config, cfg, &runs)?;
    let cells = grid.cfg.cells();
    let Some(cell) = cells.iter().find(|c| c.key() == a.cell) else {
        let near: Vec<String> = cells
            .iter()
            .map(Cell::key)
            .filter(|k| a.cell.split('|').filter(|p| !p.is_empty()).all(|p| k.contains(p)))
            .take(8)
            .collect();
        bail!(
            "--cell `{}` is not a cell of {} (`experiment|ego|flow|scenario|svo_deg|vehicles`); {}",
            a.cell,
            a.config.display(),
            if near.is_empty() {
                format!("its first cell is `{}`", cells.first().map(Cell::key).unwrap_or_default())
            } else {
                format!("cells that contain its parts: {}", near.join(", "))
            }
        );
    };
    let rows = stored_rows(&out)?;
    let stored =
        rows.iter().find(|r| r.cell == *cell && r.ep.case == a.case && r.ep.seed == a.seed);
    let page = a.page.unwrap_or_else(|| {
        out.join("view").join(format!("{}.html", file_stem(cell, a.case, a.seed)))
    });
    let mut runners = Runners::new(sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?);
    let href = page.file_name().map(|f| f.to_string_lossy().to_string()).unwrap_or_default();
    let row = write_episode(&grid, cell, a.case, a.seed, stored, &page, href, &mut runners)?;
    eprintln!(
        "{}: {} (success {:.3}, collision {:.3}){}",
        page.display(),
        row.outcome,
        row.metrics.scores.success,
        row.metrics.collision,
        match row.replay_agrees {
            Some(true) => ", as stored",
            Some(false) => ", NOT as stored",
            None => ", not in the episodes file",
        }
    );
    println!("{}", page.display());
    Ok(())
}

/// The `worst` episodes of each cell among `rows`: lowest success first, then most collisions,
/// then slowest; ties by case and seed.
fn worst_per_cell(rows: &[EpisodeRow], worst: usize) -> Vec<&EpisodeRow> {
    let mut by_cell: BTreeMap<String, Vec<&EpisodeRow>> = BTreeMap::new();
    for r in rows {
        by_cell.entry(r.cell.key()).or_default().push(r);
    }
    let mut out = Vec::new();
    for (_, mut v) in by_cell {
        v.sort_by(|a, b| {
            let key = |r: &EpisodeRow| (r.ep.scores.success, -r.ep.collision, r.ep.scores.speed);
            key(a)
                .partial_cmp(&key(b))
                .unwrap_or(std::cmp::Ordering::Equal)
                .then((a.ep.case, a.ep.seed).cmp(&(b.ep.case, b.ep.seed)))
        });
        out.extend(v.into_iter().take(worst));
    }
    out
}

/// Failure mining over `out`'s stored episodes: the pages of each cell's worst episodes and
/// `mined/index.html`, sorted by outcome (worst first), then success. Returns the index's path.
pub fn mine(grid: &Grid, out: &Path, spec: MineSpec, runners: &mut Runners) -> Result<PathBuf> {
    let rows = stored_rows(out)?;
    let cells: std::collections::BTreeSet<Cell> = grid.cfg.cells().into_iter().collect();
    let rows: Vec<EpisodeRow> = rows.into_iter().filter(|r| cells.contains(&r.cell)).collect();
    if rows.is_empty() {
        bail!("{}: no stored episodes of this grid to mine", out.display());
    }
    let dir = out.join("mined");
    let picked = worst_per_cell(&rows, spec.worst);
    eprintln!("mining {} episodes ({} per cell) into {}", picked.len(), spec.worst, dir.display());
    let mut index = Vec::with_capacity(picked.len());
    for r in picked {
        let stem = file_stem(&r.cell, r.ep.case, r.ep.seed);
        let name = format!("{stem}.html");
        index.push(write_episode(
            grid,
            &r.cell,
            r.ep.case,
            r.ep.seed,
            Some(r),
            &dir.join(&name),
            name,
            runners,
        )?);
    }
    let rank =
        |o: &str| view::OUTCOMES.iter().position(|x| *x == o).unwrap_or(view::OUTCOMES.len());
    index.sort_by(|a, b| {
        rank(&a.outcome)
            .cmp(&rank(&b.outcome))
            .then(a.metrics.scores.success.total_cmp(&b.metrics.scores.success))
            .then(a.href.cmp(&b.href))
    });
    let agree = index.iter().filter(|r| r.replay_agrees == Some(true)).count();
    let title = format!(
        "{} worst episodes per cell ({agree} of {} replays end as stored)",
        spec.worst,
        index.len()
    );
    let path = dir.join("index.html");
    std::fs::write(&path, view::index(&title, &index).map_err(anyhow::Error::msg)?)
        .with_context(|| format!("writing {}", path.display()))?;
    // Per cell, what `socialflow report` links (`mined/cells.json`).
    let mut cells: BTreeMap<String, Vec<serde_json::Value>> = BTreeMap::new();
    for r in &index {
        cells.entry(r.cell.clone()).or_default().push(serde_json::json!({
            "href": r.href, "outcome": r.outcome, "case": r.case, "seed": r.seed,
            "success": r.metrics.scores.success,
        }));
    }
    let cells_path = dir.join("cells.json");
    std::fs::write(&cells_path, serde_json::to_string_pretty(&cells)?)
        .with_context(|| format!("writing {}", cells_path.display()))?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mine_specs_are_read_or_refused_by_name() {
        assert_eq!(MineSpec::parse("worst=3").expect("ok"), MineSpec { worst: 3 });
        for bad in ["worst=0", "worst=x", "best=3", "3"] {
            let e = MineSpec::parse(bad).expect_err(bad).to_string();
            assert!(e.contains("--mine") && e.contains(bad), "{e}");
        }
    }

    #[test]
    fn page_names_keep_only_safe_characters() {
        let c = Cell {
            experiment: "cross".into(),
            ego: "RL/IDM".into(),
            flow: "Social Comm".into(),
            scenario: "merge".into(),
            svo_deg: Some(30),
            vehicles: None,
        };
        assert_eq!(file_stem(&c, 12, 1), "cross_RL_IDM_Social_Comm_merge_30_-case12-seed1");
    }
}
