//! `socialflow view` (one stored episode of an evaluation grid as a browser page) and failure
//! mining (`socialflow eval ... --mine worst=N`: the worst stored episodes of every cell replayed
//! into pages, with an index sorted by outcome).
//!
//! Owns: the commands' arguments and reading the stored rows they mine or replay. Which episodes
//! are mined, the pages' names, the index: `sf_rollout::evaluate::mine`; the replay and the
//! page: `sf_rollout::evaluate::view`; the grid's names are resolved as `eval` resolves them
//! (`crate::eval::resolve`). Must not: run cells or change `episodes.csv`.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use sf_job::eval::Cell;
use sf_report::episodes::EpisodeRow;
use sf_rollout::evaluate::{mine, Runners};

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

/// The stored rows of `out`'s episodes file, if it has one.
fn stored_rows(out: &Path) -> Result<Vec<EpisodeRow>> {
    let path = sf_report::episodes::episodes_file(out);
    if !path.exists() {
        return Ok(Vec::new());
    }
    sf_report::episodes::read_episodes(&path).with_context(|| format!("reading {}", path.display()))
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
        out.join("view").join(format!("{}.html", mine::file_stem(cell, a.case, a.seed)))
    });
    let mut runners = Runners::new(sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?);
    let href = page.file_name().map(|f| f.to_string_lossy().to_string()).unwrap_or_default();
    let row = mine::write_episode(
        &grid.resolved,
        &grid.maps,
        cell,
        a.case,
        a.seed,
        stored.map(|r| &r.ep),
        &page,
        href,
        &mut runners,
    )?;
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

/// Failure mining over `out`'s stored episodes ([`mine::mine`]); returns the index's path.
pub fn mine(grid: &Grid, out: &Path, spec: MineSpec, runners: &mut Runners) -> Result<PathBuf> {
    let rows: Vec<_> = stored_rows(out)?.into_iter().map(|r| (r.cell, r.ep)).collect();
    eprintln!(
        "mining the {} worst episodes of every cell into {}",
        spec.worst,
        out.join("mined").display()
    );
    let m =
        mine::mine(&grid.resolved, &grid.maps, &grid.cfg.cells(), &rows, out, spec.worst, runners)?;
    eprintln!("{} pages, {} of them replays that end as stored", m.pages, m.agree);
    Ok(m.index)
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
}
