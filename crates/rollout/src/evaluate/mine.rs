//! Failure mining: the worst stored episodes of every cell of a grid replayed into viewer pages
//! ([`super::view`]), with `index.html` sorted by outcome and `cells.json` (what `socialflow
//! report` links per cell). Shared by `socialflow eval --mine` and evaluation jobs with
//! `mine_worst` (the learner mines when every cell is stored).
//!
//! Owns: which episodes are a cell's worst, the pages' file names, the index and `cells.json`.
//! Must not: run cells, or read or write `episodes.csv` (callers hand the stored rows in).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use sf_job::eval::{Cell, EvalEpisode};
use sf_sim::case::CaseFile;
use sf_sim::Map;

use super::view::{self, IndexRow, StoredRow};
use super::{io, EvalError, Resolved, Runners};

/// A grid's scenarios by name: the map and its stored cases.
pub type Maps = BTreeMap<String, (Arc<Map>, CaseFile)>;

/// A cell key as a file name: letters, digits, `-` and `_` kept, the rest `_`.
pub fn file_stem(cell: &Cell, case: u32, seed: u32) -> String {
    let key: String = cell
        .key()
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' })
        .collect();
    format!("{key}-case{case}-seed{seed}")
}

/// The `worst` episodes of each cell among `rows`: lowest success first, then most collisions,
/// then slowest; ties by case and seed.
pub fn worst_per_cell(rows: &[(Cell, EvalEpisode)], worst: usize) -> Vec<&(Cell, EvalEpisode)> {
    let mut by_cell: BTreeMap<String, Vec<&(Cell, EvalEpisode)>> = BTreeMap::new();
    for r in rows {
        by_cell.entry(r.0.key()).or_default().push(r);
    }
    let mut out = Vec::new();
    for (_, mut v) in by_cell {
        v.sort_by(|(_, a), (_, b)| {
            let key = |e: &EvalEpisode| (e.scores.success, -e.collision, e.scores.speed);
            key(a)
                .partial_cmp(&key(b))
                .unwrap_or(std::cmp::Ordering::Equal)
                .then((a.case, a.seed).cmp(&(b.case, b.seed)))
        });
        out.extend(v.into_iter().take(worst));
    }
    out
}

/// Replays one episode of `cell` (stored case id `case_id`, `seed`) of `grid` into the page
/// `path`; the index row that links it as `href`. `stored`: the episode's stored row, which the
/// page and the row say the replay agrees with or not.
#[allow(clippy::too_many_arguments)]
pub fn write_episode(
    grid: &Resolved,
    maps: &Maps,
    cell: &Cell,
    case_id: u32,
    seed: u32,
    stored: Option<&EvalEpisode>,
    path: &Path,
    href: String,
    runners: &mut Runners,
) -> Result<IndexRow, EvalError> {
    let (map, cases) = maps.get(&cell.scenario).ok_or_else(|| {
        EvalError::Misfit(format!("scenario `{}` is not in the grid", cell.scenario))
    })?;
    let case_index = cases.cases.iter().position(|c| c.id == case_id).ok_or_else(|| {
        EvalError::Misfit(format!(
            "case {case_id} is not among the {} stored cases of {}",
            cases.cases.len(),
            cell.scenario
        ))
    })?;
    let (flow, ego) = grid.cell(cell)?;
    let trace =
        view::record(cell, map, cases, case_index, seed, flow, ego, runners).map_err(|e| {
            EvalError::Run(format!("replaying case {case_id} seed {seed} of {}: {e}", cell.key()))
        })?;
    let metrics = trace.metrics.ok_or_else(|| {
        EvalError::Run(format!("the replay of case {case_id} seed {seed} has no metrics"))
    })?;
    let stored = stored.map(|e| StoredRow {
        success: e.scores.success,
        safety: e.scores.safety,
        speed: e.scores.speed,
        collision: e.collision,
        road_closed: e.road_closed,
    });
    let key = cell.key();
    let title = format!("{key} - case {case_id}, seed {seed}");
    let html = view::page(&trace, &title, stored.as_ref())?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(io("creating", dir))?;
    }
    std::fs::write(path, html).map_err(io("writing", path))?;
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

/// What a mining wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct Mined {
    /// `<out>/mined/index.html`.
    pub index: PathBuf,
    pub pages: usize,
    /// Pages whose replay ends as its stored row.
    pub agree: usize,
}

/// Failure mining over `rows`, the stored episodes of `out` (those of `grid`'s `cells` are
/// mined): the pages of each cell's `worst` episodes under `<out>/mined/`, `index.html` sorted by
/// outcome (worst first, [`view::OUTCOMES`]), then success, and `cells.json`.
#[allow(clippy::too_many_arguments)]
pub fn mine(
    grid: &Resolved,
    maps: &Maps,
    cells: &[Cell],
    rows: &[(Cell, EvalEpisode)],
    out: &Path,
    worst: usize,
    runners: &mut Runners,
) -> Result<Mined, EvalError> {
    let cells: std::collections::BTreeSet<&Cell> = cells.iter().collect();
    let rows: Vec<(Cell, EvalEpisode)> =
        rows.iter().filter(|(c, _)| cells.contains(c)).cloned().collect();
    if rows.is_empty() {
        return Err(EvalError::Misfit(format!(
            "{}: no stored episodes of this grid to mine",
            out.display()
        )));
    }
    let dir = out.join("mined");
    let picked = worst_per_cell(&rows, worst);
    let mut index = Vec::with_capacity(picked.len());
    for (cell, ep) in picked {
        let name = format!("{}.html", file_stem(cell, ep.case, ep.seed));
        let path = dir.join(&name);
        index.push(write_episode(
            grid,
            maps,
            cell,
            ep.case,
            ep.seed,
            Some(ep),
            &path,
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
        "{worst} worst episodes per cell ({agree} of {} replays end as stored)",
        index.len()
    );
    let path = dir.join("index.html");
    std::fs::write(&path, view::index(&title, &index)?).map_err(io("writing", &path))?;
    // Per cell, what `socialflow report` links.
    let mut by_cell: BTreeMap<String, Vec<serde_json::Value>> = BTreeMap::new();
    for r in &index {
        by_cell.entry(r.cell.clone()).or_default().push(serde_json::json!({
            "href": r.href, "outcome": r.outcome, "case": r.case, "seed": r.seed,
            "success": r.metrics.scores.success,
        }));
    }
    let cells_path = dir.join("cells.json");
    let text = serde_json::to_string_pretty(&by_cell)
        .map_err(|e| EvalError::Run(format!("cells.json: {e}")))?;
    std::fs::write(&cells_path, text).map_err(io("writing", &cells_path))?;
    Ok(Mined { index: path, pages: index.len(), agree })
}

#[cfg(test)]
mod tests {
    use super::*;

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
