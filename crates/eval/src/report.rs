//! The reproduction report: per-episode results in, tables, statistics and figures out.
//!
//! Owns: the per-episode results file format ([`EpisodeRow`], `episodes.csv`) and its
//! validating reader, the evaluation's metadata file (`meta.json`: which flow each ego was
//! trained in, which ego is "ours"), and [`build`], which turns them into `report.md` and a
//! self-contained `report.html` (figures embedded) with every experiment the results hold:
//! flow quality (tables, radar charts), the SVO and density sweeps, adversary degradation,
//! cross-validation heatmaps (medals per column, grey diagonal) and zero-shot bar charts with
//! 95 % intervals and paired t-tests. The paper's numbers are printed beside ours where the
//! paper gives them in its text. Must not: run simulations.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sf_job::eval::{Cell, EvalConfig, EvalEpisode};

use crate::plot::{self, Bar, Mark, Series};
use crate::{paired_t_test, Summary};

pub const EPISODES_HEADER: &str = "experiment,ego,flow,scenario,svo_deg,vehicles,case,seed,success,safety,speed,collision";

/// One evaluated episode. `ego` is empty when the flow was evaluated on its own.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeRow {
    pub experiment: String,
    pub ego: String,
    pub flow: String,
    pub scenario: String,
    pub svo_deg: Option<u32>,
    pub vehicles: Option<usize>,
    pub case: u32,
    pub seed: u32,
    pub success: f32,
    pub safety: f32,
    pub speed: f32,
    pub collision: f32,
}

impl EpisodeRow {
    /// An evaluated episode of `cell`.
    pub fn new(cell: &Cell, e: &EvalEpisode) -> Self {
        Self {
            experiment: cell.experiment.clone(),
            ego: cell.ego.clone(),
            flow: cell.flow.clone(),
            scenario: cell.scenario.clone(),
            svo_deg: cell.svo_deg,
            vehicles: cell.vehicles,
            case: e.case,
            seed: e.seed,
            success: e.success,
            safety: e.safety,
            speed: e.speed,
            collision: e.collision,
        }
    }

    /// The cell the episode belongs to.
    pub fn cell(&self) -> Cell {
        Cell { experiment: self.experiment.clone(), ego: self.ego.clone(), flow: self.flow.clone(), scenario: self.scenario.clone(), svo_deg: self.svo_deg, vehicles: self.vehicles }
    }

    pub fn to_csv(&self) -> String {
        let o = |v: Option<String>| v.unwrap_or_default();
        format!(
            "{},{},{},{},{},{},{},{},{},{},{},{}",
            self.experiment,
            self.ego,
            self.flow,
            self.scenario,
            o(self.svo_deg.map(|v| v.to_string())),
            o(self.vehicles.map(|v| v.to_string())),
            self.case,
            self.seed,
            self.success,
            self.safety,
            self.speed,
            self.collision
        )
    }

    fn parse(line: &str) -> Result<Self, String> {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 12 {
            return Err(format!("{} fields, expected 12", f.len()));
        }
        let num =
            |i: usize, what: &str| f[i].parse::<f32>().map_err(|_| format!("{what} `{}` is not a number", f[i])).and_then(|v| if v.is_finite() { Ok(v) } else { Err(format!("{what} is not finite")) });
        let opt = |i: usize, what: &str| if f[i].is_empty() { Ok(None) } else { f[i].parse::<u64>().map(Some).map_err(|_| format!("{what} `{}` is not an integer", f[i])) };
        Ok(Self {
            experiment: f[0].into(),
            ego: f[1].into(),
            flow: f[2].into(),
            scenario: f[3].into(),
            svo_deg: opt(4, "svo_deg")?.map(|v| v as u32),
            vehicles: opt(5, "vehicles")?.map(|v| v as usize),
            case: f[6].parse().map_err(|_| format!("case `{}` is not an integer", f[6]))?,
            seed: f[7].parse().map_err(|_| format!("seed `{}` is not an integer", f[7]))?,
            success: num(8, "success")?,
            safety: num(9, "safety")?,
            speed: num(10, "speed")?,
            collision: num(11, "collision")?,
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{path}: {reason}")]
    File { path: String, reason: String },
    #[error(transparent)]
    Plot(#[from] plot::PlotError),
}

fn file_err(path: &Path, reason: impl std::fmt::Display) -> ReportError {
    ReportError::File { path: path.display().to_string(), reason: reason.to_string() }
}

/// Reads `episodes.csv`; a missing file is an empty result set.
pub fn read_episodes(path: &Path) -> Result<Vec<EpisodeRow>, ReportError> {
    if !path.exists() {
        return Ok(Vec::new());
    }
    let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e))?;
    let mut lines = text.lines();
    match lines.next() {
        Some(h) if h == EPISODES_HEADER => {}
        Some(h) => return Err(file_err(path, format!("header `{h}` is not `{EPISODES_HEADER}`"))),
        None => return Ok(Vec::new()),
    }
    lines.enumerate().filter(|(_, l)| !l.is_empty()).map(|(i, l)| EpisodeRow::parse(l).map_err(|e| file_err(path, format!("line {}: {e}", i + 2)))).collect()
}

/// What the report needs to know besides the episodes.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Meta {
    /// Ego name -> the flow (by name) it was trained in; its cell in that column is grey.
    pub trained_in: BTreeMap<String, String>,
    /// The ego the paper proposes (RARL/SocialCommAdv), compared by paired t-tests.
    pub ours: Option<String>,
    /// Flow and ego names in display order.
    pub flows: Vec<String>,
    pub egos: Vec<String>,
    pub cases: u32,
    pub seeds: u32,
}

impl Meta {
    /// What a report of `cfg`'s grid needs to know.
    pub fn of(cfg: &EvalConfig) -> Self {
        Self {
            trained_in: cfg.egos.iter().filter_map(|e| e.trained_in.clone().map(|t| (e.name.clone(), t))).collect(),
            ours: cfg.ours.clone(),
            flows: cfg.flows.iter().map(|f| f.name.clone()).collect(),
            egos: cfg.egos.iter().map(|f| f.name.clone()).collect(),
            cases: cfg.cases,
            seeds: cfg.seeds,
        }
    }
}

/// Appends whole cells to an `episodes.csv` (the header first if the file is new or empty):
/// one write per cell, so a cell is stored whole or not at all.
pub struct EpisodesWriter {
    file: std::fs::File,
    path: PathBuf,
}

impl EpisodesWriter {
    pub fn open(path: &Path) -> Result<Self, ReportError> {
        let mut file = std::fs::OpenOptions::new().create(true).append(true).open(path).map_err(|e| file_err(path, e))?;
        let empty = file.metadata().map_err(|e| file_err(path, e))?.len() == 0;
        if empty {
            use std::io::Write;
            writeln!(file, "{EPISODES_HEADER}").map_err(|e| file_err(path, e))?;
        }
        Ok(Self { file, path: path.to_path_buf() })
    }

    pub fn append(&mut self, rows: &[EpisodeRow]) -> Result<(), ReportError> {
        use std::io::Write;
        let text: String = rows.iter().map(|r| r.to_csv() + "\n").collect();
        self.file.write_all(text.as_bytes()).and_then(|()| self.file.sync_data()).map_err(|e| file_err(&self.path, e))
    }
}

pub fn read_meta(path: &Path) -> Result<Meta, ReportError> {
    let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e))?;
    serde_json::from_str(&text).map_err(|e| file_err(path, e))
}

/// Significance stars of a p-value, as the paper marks them.
pub fn stars(p: f64) -> &'static str {
    match p {
        p if p < 1e-4 => "****",
        p if p < 1e-3 => "***",
        p if p < 1e-2 => "**",
        p if p < 0.05 => "*",
        _ => "n.s.",
    }
}

/// A p-value as text; below what a double's `1 - cdf` resolves it reads "< 1e-15".
pub fn fmt_p(p: f64) -> String {
    if p < 1e-15 {
        "< 1e-15".into()
    } else {
        format!("{p:.2e}")
    }
}

type Metric = fn(&EpisodeRow) -> f32;
const METRICS: [(&str, Metric); 3] = [("Success", |r| r.success), ("Safety", |r| r.safety), ("Speed", |r| r.speed)];

fn summary(rows: &[&EpisodeRow], m: Metric) -> Summary {
    Summary::of(&rows.iter().map(|r| m(r) as f64).collect::<Vec<_>>())
}

fn pct(s: Summary) -> String {
    if s.n == 0 {
        "-".into()
    } else {
        format!("{:.1} ± {:.1}", 100.0 * s.mean, 100.0 * s.ci95)
    }
}

/// Paired t-test of metric `m` between two row sets, paired on the same episode start
/// (scenario, SVO, vehicles, case, seed) and the dimension that is not compared: with
/// `same_flow` two egos are compared on the same flow; otherwise two flows with the same ego
/// (pooled rows of several egos pair each ego with itself, never with another ego).
fn paired_on(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric, same_flow: bool) -> Option<crate::PairedT> {
    let key = |r: &EpisodeRow| (if same_flow { r.flow.clone() } else { r.ego.clone() }, r.scenario.clone(), r.svo_deg, r.vehicles, r.case, r.seed);
    let bm: BTreeMap<_, f64> = b.iter().map(|r| (key(r), m(r) as f64)).collect();
    let (mut x, mut y) = (Vec::new(), Vec::new());
    for r in a {
        if let Some(v) = bm.get(&key(r)) {
            x.push(m(r) as f64);
            y.push(*v);
        }
    }
    paired_t_test(&x, &y).ok()
}

/// Two egos on the same episodes of the same flows.
fn paired(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric) -> Option<crate::PairedT> {
    paired_on(a, b, m, true)
}

/// Two flows on the same episode starts.
fn paired_across_flows(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric) -> Option<crate::PairedT> {
    paired_on(a, b, m, false)
}

/// The paper's Table "Effects of adversaries" (success and speed, percent): ego -> scenario -> (SC, SCA, FM).
fn paper_adversary(metric: &str) -> BTreeMap<(&'static str, &'static str), [f64; 3]> {
    let success: [(&str, [[f64; 3]; 4]); 4] = [
        ("RL/IDM", [[76.5, 74.8, 55.2], [52.0, 50.8, 20.6], [64.5, 62.8, 9.2], [75.0, 72.8, 19.6]]),
        ("RL/MACAD", [[83.6, 82.6, 52.1], [75.2, 73.6, 4.6], [71.2, 69.6, 9.1], [73.6, 71.6, 29.6]]),
        ("RL/CoPO", [[81.6, 78.8, 51.0], [71.6, 69.8, 6.5], [70.1, 66.2, 10.0], [82.1, 80.8, 21.0]]),
        ("RL/SocialComm", [[87.2, 85.2, 51.4], [91.2, 85.2, 2.4], [84.8, 80.2, 8.4], [87.8, 84.7, 17.0]]),
    ];
    let speed: [(&str, [[f64; 3]; 4]); 4] = [
        ("RL/IDM", [[47.4, 46.4, 37.3], [58.6, 57.5, 34.5], [51.6, 51.2, 15.1], [38.3, 38.3, 20.2]]),
        ("RL/MACAD", [[49.8, 49.7, 36.1], [74.3, 73.9, 24.3], [54.7, 54.2, 17.6], [39.4, 39.6, 25.1]]),
        ("RL/CoPO", [[49.3, 47.6, 34.9], [71.4, 70.0, 27.7], [55.6, 53.5, 19.4], [42.9, 42.3, 22.9]]),
        ("RL/SocialComm", [[52.1, 51.0, 36.5], [81.5, 78.5, 24.3], [60.9, 59.4, 16.8], [43.4, 42.5, 19.9]]),
    ];
    let table = if metric == "Speed" { speed } else { success };
    let scen = ["intersection", "bottleneck", "merge", "roundabout"];
    table.iter().flat_map(|(ego, rows)| scen.iter().zip(rows).map(move |(s, v)| ((*ego, *s), *v))).collect()
}

/// Markdown and HTML written side by side.
struct Doc {
    md: String,
    html: String,
    dir: PathBuf,
}

impl Doc {
    fn h(&mut self, level: usize, text: &str) {
        let _ = writeln!(self.md, "\n{} {text}\n", "#".repeat(level));
        let _ = writeln!(self.html, "<h{level}>{}</h{level}>", esc(text));
    }

    fn p(&mut self, text: &str) {
        let _ = writeln!(self.md, "{text}\n");
        let _ = writeln!(self.html, "<p>{}</p>", esc(text));
    }

    fn table(&mut self, head: &[String], rows: &[Vec<String>]) {
        let _ = writeln!(self.md, "| {} |", head.join(" | "));
        let _ = writeln!(self.md, "|{}", "---|".repeat(head.len()));
        for r in rows {
            let _ = writeln!(self.md, "| {} |", r.join(" | "));
        }
        self.md.push('\n');
        let _ = write!(self.html, "<table><tr>{}</tr>", head.iter().map(|h| format!("<th>{}</th>", esc(h))).collect::<String>());
        for r in rows {
            let _ = write!(self.html, "<tr>{}</tr>", r.iter().map(|c| format!("<td>{}</td>", esc(c))).collect::<String>());
        }
        self.html.push_str("</table>\n");
    }

    /// A figure already written to `self.dir/<file>`: linked from markdown, embedded in HTML.
    fn figure(&mut self, file: &str, caption: &str) -> Result<(), ReportError> {
        let path = self.dir.join(file);
        let bytes = std::fs::read(&path).map_err(|e| file_err(&path, e))?;
        let _ = writeln!(self.md, "![{caption}]({file})\n");
        let mime = if file.ends_with(".gif") { "image/gif" } else { "image/png" };
        let _ = writeln!(self.html, "<figure><img src=\"data:{mime};base64,{}\" alt=\"{}\"><figcaption>{}</figcaption></figure>", b64(&bytes), esc(caption), esc(caption));
        Ok(())
    }
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

fn b64(bytes: &[u8]) -> String {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// What the report found, for the caller's summary.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Findings {
    pub episodes: usize,
    pub experiments: Vec<String>,
    /// (claim, holds, p-value) checks of the paper's findings this result set can test.
    pub checks: Vec<(String, bool, Option<f64>)>,
}

fn by(rows: &[EpisodeRow], f: impl Fn(&EpisodeRow) -> bool) -> Vec<&EpisodeRow> {
    rows.iter().filter(|r| f(r)).collect()
}

fn order(names: impl IntoIterator<Item = String>, preferred: &[String]) -> Vec<String> {
    let set: BTreeSet<String> = names.into_iter().collect();
    let mut out: Vec<String> = preferred.iter().filter(|n| set.contains(*n)).cloned().collect();
    out.extend(set.into_iter().filter(|n| !preferred.contains(n)));
    out
}

/// Builds `report.md`, `report.html` and the figures in `out` from `episodes` and `meta`.
pub fn build(rows: &[EpisodeRow], meta: &Meta, out: &Path) -> Result<Findings, ReportError> {
    std::fs::create_dir_all(out).map_err(|e| file_err(out, e))?;
    let mut doc = Doc { md: String::new(), html: String::new(), dir: out.to_path_buf() };
    let mut found = Findings { episodes: rows.len(), ..Findings::default() };
    doc.h(1, "socialflow: reproduction report");
    doc.p(&format!("{} evaluated episodes ({} stored cases x {} seeds per cell). Values are percent, mean ± 95 % confidence half-width (Student t); p-values from paired two-sided t-tests over the same (case, seed) pairs. Stars: **** p < 0.0001, *** p < 0.001, ** p < 0.01, * p < 0.05.", rows.len(), meta.cases, meta.seeds));
    let scen_pref: Vec<String> = ["intersection", "bottleneck", "merge", "roundabout"].iter().map(|s| s.to_string()).collect();

    // Flow quality.
    let fq = by(rows, |r| r.experiment == "flow_quality");
    if !fq.is_empty() {
        found.experiments.push("flow_quality".into());
        doc.h(2, "Flow quality (every vehicle driven by the flow)");
        let flows = order(fq.iter().map(|r| r.flow.clone()), &meta.flows);
        let scen = order(fq.iter().map(|r| r.scenario.clone()), &scen_pref);
        let mut head = vec!["Flow".to_string(), "Scenario".into()];
        head.extend(METRICS.iter().map(|(n, _)| n.to_string()));
        let mut table = Vec::new();
        for f in &flows {
            for s in &scen {
                let cell = by(rows, |r| r.experiment == "flow_quality" && &r.flow == f && &r.scenario == s);
                let mut row = vec![f.clone(), s.clone()];
                row.extend(METRICS.iter().map(|(_, m)| pct(summary(&cell, *m))));
                table.push(row);
            }
        }
        doc.table(&head, &table);
        for s in &scen {
            let series: Vec<(String, Vec<(f64, f64)>)> = flows
                .iter()
                .map(|f| {
                    let cell = by(rows, |r| r.experiment == "flow_quality" && &r.flow == f && &r.scenario == s);
                    (f.clone(), METRICS.iter().enumerate().map(|(k, (_, m))| (k as f64, summary(&cell, *m).mean)).collect())
                })
                .collect();
            let file = format!("flow-quality-{s}.png");
            let ser: Vec<Series> = series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
            plot::radar(&out.join(&file), &format!("Flow quality, {s}"), &METRICS.iter().map(|(n, _)| n.to_string()).collect::<Vec<_>>(), &ser)?;
            doc.figure(&file, &format!("Success, Safety and Speed of each flow in {s} (radar; 1 = 100 %)"))?;
        }
        if let (true, true) = (flows.contains(&"SocialComm".to_string()), flows.contains(&"CoPO".to_string())) {
            let a = by(rows, |r| r.experiment == "flow_quality" && r.flow == "SocialComm");
            let b = by(rows, |r| r.experiment == "flow_quality" && r.flow == "CoPO");
            if let Some(t) = paired_across_flows(&a, &b, |r| r.success) {
                found.checks.push(("SocialComm flow succeeds more often than CoPO Stage 1 (flow quality, all scenarios)".into(), t.mean_diff > 0.0 && t.p_value < 0.05, Some(t.p_value)));
            }
        }
    }

    // SVO sweep.
    let sw = by(rows, |r| r.experiment == "svo_sweep");
    if !sw.is_empty() {
        found.experiments.push("svo_sweep".into());
        doc.h(2, "SVO sweep (all agents share one SVO)");
        let flows = order(sw.iter().map(|r| r.flow.clone()), &meta.flows);
        let scen = order(sw.iter().map(|r| r.scenario.clone()), &scen_pref);
        for s in &scen {
            let series: Vec<(String, Vec<(f64, f64)>)> = flows
                .iter()
                .map(|f| {
                    let svos: BTreeSet<u32> = sw.iter().filter(|r| &r.flow == f && &r.scenario == s).filter_map(|r| r.svo_deg).collect();
                    (
                        f.clone(),
                        svos.into_iter()
                            .map(|v| (v as f64, summary(&by(rows, |r| r.experiment == "svo_sweep" && &r.flow == f && &r.scenario == s && r.svo_deg == Some(v)), |r| r.success).mean))
                            .collect(),
                    )
                })
                .collect();
            let file = format!("svo-sweep-{s}.png");
            let ser: Vec<Series> = series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
            plot::line_chart(&out.join(&file), &format!("Success vs SVO, {s}"), "SVO (deg)", "success", &ser, Some((0.0, 1.0)), (640, 400))?;
            doc.figure(&file, &format!("Flow success rate when every agent has the same SVO, {s}"))?;
            if flows.len() == 2 {
                let a = by(rows, |r| r.experiment == "svo_sweep" && r.flow == flows[1] && &r.scenario == s);
                let b = by(rows, |r| r.experiment == "svo_sweep" && r.flow == flows[0] && &r.scenario == s);
                if let Some(t) = paired_across_flows(&a, &b, |r| r.success) {
                    doc.p(&format!("{s}: {} - {} success = {:+.1} points over all SVOs, p = {} {}", flows[1], flows[0], 100.0 * t.mean_diff, fmt_p(t.p_value), stars(t.p_value)));
                    if flows[1] == "SocialComm" {
                        found.checks.push((format!("SocialComm beats CoPO Stage 1 over the SVO sweep in {s}"), t.mean_diff > 0.0 && t.p_value < 0.05, Some(t.p_value)));
                    }
                }
            }
        }
    }

    // Density sweep.
    let de = by(rows, |r| r.experiment == "density");
    if !de.is_empty() {
        found.experiments.push("density".into());
        doc.h(2, "Density sweep");
        let flows = order(de.iter().map(|r| r.flow.clone()), &meta.flows);
        let scen = de[0].scenario.clone();
        let series: Vec<(String, Vec<(f64, f64)>)> = flows
            .iter()
            .map(|f| {
                let ns: BTreeSet<usize> = de.iter().filter(|r| &r.flow == f).filter_map(|r| r.vehicles).collect();
                (f.clone(), ns.into_iter().map(|n| (n as f64, summary(&by(rows, |r| r.experiment == "density" && &r.flow == f && r.vehicles == Some(n)), |r| r.success).mean)).collect())
            })
            .collect();
        let ser: Vec<Series> = series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
        plot::line_chart(&out.join("density.png"), &format!("Success vs vehicles, {scen}"), "vehicles per case", "success", &ser, Some((0.0, 1.0)), (640, 400))?;
        doc.figure("density.png", &format!("Flow success rate by number of vehicles in {scen}"))?;
        let mut table = Vec::new();
        for (f, pts) in &series {
            table.push(std::iter::once(f.clone()).chain(pts.iter().map(|(n, v)| format!("{n}: {:.1}", 100.0 * v))).collect());
        }
        let width = table.iter().map(Vec::len).max().unwrap_or(1);
        let head: Vec<String> = std::iter::once("Flow".to_string()).chain((1..width).map(|k| format!("density {k}"))).collect();
        let table: Vec<Vec<String>> = table
            .into_iter()
            .map(|mut r: Vec<String>| {
                r.resize(width, String::new());
                r
            })
            .collect();
        doc.table(&head, &table);
    }

    // Adversary degradation.
    let ad = by(rows, |r| r.experiment == "adversary");
    if !ad.is_empty() {
        found.experiments.push("adversary".into());
        doc.h(2, "Effect of adversaries on egos trained in non-adversarial flows");
        let egos = order(ad.iter().map(|r| r.ego.clone()), &meta.egos);
        let flows = order(ad.iter().map(|r| r.flow.clone()), &meta.flows);
        let scen = order(ad.iter().map(|r| r.scenario.clone()), &scen_pref);
        for (mname, m) in [METRICS[0], METRICS[2]] {
            let paper = paper_adversary(mname);
            let mut head = vec!["Ego".to_string(), "Scenario".into()];
            head.extend(flows.iter().cloned());
            head.push("p (first vs second flow)".into());
            head.push("paper (SC / SCA / FM)".into());
            let mut table = Vec::new();
            for e in &egos {
                for s in &scen {
                    let cell = |f: &String| by(rows, |r| r.experiment == "adversary" && &r.ego == e && &r.flow == f && &r.scenario == s);
                    let base = flows.first().map(|f| summary(&cell(f), m).mean).unwrap_or(f64::NAN);
                    let mut row = vec![e.clone(), s.clone()];
                    for (k, f) in flows.iter().enumerate() {
                        let v = summary(&cell(f), m);
                        row.push(if k == 0 { pct(v) } else { format!("{} ({:+.1})", pct(v), 100.0 * (v.mean - base)) });
                    }
                    let p = if flows.len() >= 2 { paired_across_flows(&cell(&flows[1]), &cell(&flows[0]), m).map(|t| format!("{} {}", fmt_p(t.p_value), stars(t.p_value))) } else { None };
                    row.push(p.unwrap_or_else(|| "-".into()));
                    row.push(paper.get(&(e.as_str(), s.as_str())).map(|v| format!("{:.1} / {:.1} / {:.1}", v[0], v[1], v[2])).unwrap_or_else(|| "-".into()));
                    table.push(row);
                }
            }
            doc.p(&format!("{mname} (percent; in parentheses the change from the first flow):"));
            doc.table(&head, &table);
        }
        if flows.len() >= 3 {
            let pooled = |f: &String| by(rows, |r| r.experiment == "adversary" && &r.flow == f);
            let (sc, sca, fm) = (summary(&pooled(&flows[0]), |r| r.success).mean, summary(&pooled(&flows[1]), |r| r.success).mean, summary(&pooled(&flows[2]), |r| r.success).mean);
            let p = paired_across_flows(&pooled(&flows[1]), &pooled(&flows[0]), |r| r.success).map(|t| t.p_value);
            found.checks.push((format!("Egos succeed less in {} than in {} (pooled)", flows[1], flows[0]), sca < sc && p.is_some_and(|p| p < 0.05), p));
            found.checks.push((
                format!("{} degrades egos more than {} (pooled success: {} {:.1}, {} {:.1}, {} {:.1})", flows[2], flows[1], flows[0], 100.0 * sc, flows[1], 100.0 * sca, flows[2], 100.0 * fm),
                sc - fm > sc - sca,
                None,
            ));
        }
    }

    // Cross-validation.
    let cv = by(rows, |r| r.experiment == "cross");
    if !cv.is_empty() {
        found.experiments.push("cross".into());
        doc.h(2, "Cross-validation: every ego in every flow");
        doc.p("Rows: ego policies; columns: evaluation flows. Grey: the ego's own training flow (not ranked). Gold, silver and copper frames: first, second and third of each column.");
        let egos = order(cv.iter().map(|r| r.ego.clone()), &meta.egos);
        let flows = order(cv.iter().map(|r| r.flow.clone()), &meta.flows);
        let scen = order(cv.iter().map(|r| r.scenario.clone()), &scen_pref);
        for s in &scen {
            for (mname, m) in [METRICS[0], METRICS[2]] {
                let values: Vec<Vec<f64>> =
                    egos.iter().map(|e| flows.iter().map(|f| summary(&by(rows, |r| r.experiment == "cross" && &r.ego == e && &r.flow == f && &r.scenario == s), m).mean).collect()).collect();
                let marks = medals(&egos, &flows, &values, &meta.trained_in);
                let file = format!("cross-{}-{s}.png", mname.to_lowercase());
                plot::heatmap(&out.join(&file), &format!("{mname}, {s}"), &egos, &flows, &values, &marks)?;
                doc.figure(&file, &format!("Cross-validation {mname} in {s}"))?;
            }
        }
        // Zero-shot bars: each ego pooled over the evaluation flows, per scenario; ours against
        // the two others with the nearest means.
        doc.h(2, "Zero-shot transfer");
        for (mname, m) in [METRICS[0], METRICS[2]] {
            let mut groups = Vec::new();
            let mut lines = Vec::new();
            for s in &scen {
                let pooled = |e: &String| by(rows, |r| r.experiment == "cross" && &r.ego == e && &r.scenario == s);
                let means: Vec<(String, Summary)> = egos.iter().map(|e| (e.clone(), summary(&pooled(e), m))).collect();
                let mut bars: Vec<Bar> = means.iter().map(|(_, v)| Bar { mean: v.mean, ci95: v.ci95, stars: String::new() }).collect();
                if let Some(ours) = meta.ours.as_ref().filter(|o| egos.contains(o)) {
                    let our_mean = means.iter().find(|(e, _)| e == ours).map(|(_, v)| v.mean).unwrap_or(f64::NAN);
                    let mut others: Vec<&(String, Summary)> = means.iter().filter(|(e, _)| e != ours).collect();
                    others.sort_by(|a, b| (a.1.mean - our_mean).abs().total_cmp(&(b.1.mean - our_mean).abs()));
                    for (e, _) in others.into_iter().take(2) {
                        if let Some(t) = paired(&pooled(ours), &pooled(e), m) {
                            let k = egos.iter().position(|x| x == e).unwrap_or(0);
                            bars[k].stars = stars(t.p_value).to_string();
                            lines.push(format!("{s}: {ours} - {e} {mname} = {:+.1} points, p = {} {}", 100.0 * t.mean_diff, fmt_p(t.p_value), stars(t.p_value)));
                            if mname == "Success" {
                                found.checks.push((format!("{ours} transfers better than {e} in {s} (success)"), t.mean_diff > 0.0 && t.p_value < 0.05, Some(t.p_value)));
                            }
                        }
                    }
                }
                groups.push(bars);
            }
            let file = format!("zero-shot-{}.png", mname.to_lowercase());
            plot::grouped_bars(&out.join(&file), &format!("Zero-shot {mname} (pooled over evaluation flows)"), &mname.to_lowercase(), &scen, &egos, &groups)?;
            doc.figure(&file, &format!("{mname} of each ego pooled over the evaluation flows, 95 % intervals; stars: paired t-test of ours against the two nearest"))?;
            for l in lines {
                doc.p(&l);
            }
        }
    }

    // Episode GIFs placed in `out` by the caller (`gif-<scenario>.gif`).
    let mut gifs: Vec<String> =
        std::fs::read_dir(out).map_err(|e| file_err(out, e))?.flatten().map(|e| e.file_name().to_string_lossy().to_string()).filter(|n| n.starts_with("gif-") && n.ends_with(".gif")).collect();
    gifs.sort();
    if !gifs.is_empty() {
        doc.h(2, "The same case under each flow");
        doc.p("One ego policy, one stored case, the flows side by side (left to right as in the evaluation config); vehicles coloured by SVO.");
        for g in gifs {
            let scen = g.trim_start_matches("gif-").trim_end_matches(".gif").to_string();
            doc.figure(&g, &format!("{scen}: the same case under each flow"))?;
        }
    }

    if !found.checks.is_empty() {
        doc.h(2, "The paper's findings at this budget");
        let table: Vec<Vec<String>> =
            found.checks.iter().map(|(c, ok, p)| vec![c.clone(), if *ok { "holds".into() } else { "does not hold".into() }, p.map(fmt_p).unwrap_or_else(|| "-".into())]).collect();
        doc.table(&["Finding".into(), "Here".into(), "p".into()], &table);
    }
    let md_path = out.join("report.md");
    std::fs::write(&md_path, &doc.md).map_err(|e| file_err(&md_path, e))?;
    let html = format!("<!doctype html><html><head><meta charset=\"utf-8\"><title>socialflow report</title><style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}table{{border-collapse:collapse;margin:1em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;font-size:13px}}img{{max-width:100%}}</style></head><body>{}</body></html>", doc.html);
    let html_path = out.join("report.html");
    std::fs::write(&html_path, html).map_err(|e| file_err(&html_path, e))?;
    Ok(found)
}

/// Grey for an ego's own training flow; gold, silver, copper for the best three of each column.
pub fn medals(egos: &[String], flows: &[String], values: &[Vec<f64>], trained_in: &BTreeMap<String, String>) -> Vec<Vec<Mark>> {
    let mut marks = vec![vec![Mark::None; flows.len()]; egos.len()];
    for (c, f) in flows.iter().enumerate() {
        let mut ranked: Vec<(usize, f64)> = Vec::new();
        for (r, e) in egos.iter().enumerate() {
            if trained_in.get(e) == Some(f) {
                marks[r][c] = Mark::Diagonal;
            } else if let Some(v) = values.get(r).and_then(|row| row.get(c)).filter(|v| v.is_finite()) {
                ranked.push((r, *v));
            }
        }
        ranked.sort_by(|a, b| b.1.total_cmp(&a.1));
        for ((r, _), m) in ranked.into_iter().zip([Mark::Gold, Mark::Silver, Mark::Copper]) {
            marks[r][c] = m;
        }
    }
    marks
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(experiment: &str, ego: &str, flow: &str, case: u32, seed: u32, success: f32) -> EpisodeRow {
        EpisodeRow {
            experiment: experiment.into(),
            ego: ego.into(),
            flow: flow.into(),
            scenario: "merge".into(),
            svo_deg: None,
            vehicles: None,
            case,
            seed,
            success,
            safety: success,
            speed: 0.5,
            collision: 0.0,
        }
    }

    #[test]
    fn rows_round_trip_and_bad_lines_name_the_line() {
        let r = EpisodeRow { svo_deg: Some(30), vehicles: Some(8), ..row("svo_sweep", "", "CoPO", 3, 1, 0.25) };
        assert_eq!(EpisodeRow::parse(&r.to_csv()), Ok(r.clone()));
        let dir = std::env::temp_dir().join(format!("sf-report-rows-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let p = dir.join("episodes.csv");
        std::fs::write(&p, format!("{EPISODES_HEADER}\n{}\ncross,a,b,merge,,,1,0,NaN,1,1,0\n", r.to_csv())).expect("write");
        let e = read_episodes(&p).expect_err("NaN").to_string();
        assert!(e.contains("line 3") && e.contains("success"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn flows_pooled_over_egos_pair_each_ego_with_itself() {
        // Ego A succeeds everywhere in both flows; ego B fails everywhere in both. Paired per
        // ego, the flows do not differ at all; paired across egos they would differ in every pair.
        let mut x = Vec::new();
        let mut y = Vec::new();
        for case in 0..20 {
            for (ego, s) in [("A", 1.0), ("B", 0.0)] {
                x.push(row("adversary", ego, "X", case, 0, s));
                y.push(row("adversary", ego, "Y", case, 0, if case == 0 { 1.0 - s } else { s }));
            }
        }
        let (xr, yr): (Vec<&EpisodeRow>, Vec<&EpisodeRow>) = (x.iter().collect(), y.iter().collect());
        let t = paired_across_flows(&xr, &yr, |r| r.success).expect("a test");
        assert_eq!(t.n, 40, "one pair per ego and episode start");
        assert!(t.mean_diff.abs() < 1e-12 && t.p_value > 0.9, "{t:?}");
        // Two egos on the same flow still pair across egos.
        let a: Vec<&EpisodeRow> = x.iter().filter(|r| r.ego == "A").collect();
        let b: Vec<&EpisodeRow> = x.iter().filter(|r| r.ego == "B").collect();
        let t = paired(&a, &b, |r| r.success).expect("a test");
        assert_eq!(t.n, 20);
    }

    #[test]
    fn medals_skip_the_diagonal_and_rank_each_column() {
        let egos: Vec<String> = ["A", "B", "C", "D"].iter().map(|s| s.to_string()).collect();
        let flows: Vec<String> = ["X", "Y"].iter().map(|s| s.to_string()).collect();
        let values = vec![vec![0.9, 0.1], vec![0.5, 0.2], vec![0.7, 0.3], vec![0.6, 0.4]];
        let trained: BTreeMap<String, String> = [("A".to_string(), "X".to_string())].into();
        let m = medals(&egos, &flows, &values, &trained);
        assert_eq!(m[0][0], Mark::Diagonal, "A's own flow is grey though it is the best");
        assert_eq!((m[2][0], m[3][0], m[1][0]), (Mark::Gold, Mark::Silver, Mark::Copper));
        assert_eq!((m[3][1], m[2][1], m[1][1], m[0][1]), (Mark::Gold, Mark::Silver, Mark::Copper, Mark::None));
    }

    #[test]
    fn stars_follow_the_paper() {
        assert_eq!((stars(1e-5), stars(5e-4), stars(5e-3), stars(0.03), stars(0.2)), ("****", "***", "**", "*", "n.s."));
        assert_eq!((fmt_p(0.0), fmt_p(0.0123)), ("< 1e-15".to_string(), "1.23e-2".to_string()));
    }

    /// A tiny stored result set builds the whole report, and a clearly better ego is found
    /// significantly better.
    #[test]
    fn a_tiny_result_set_builds_the_report() {
        let mut rows = Vec::new();
        for case in 0..12 {
            for seed in 0..2 {
                let noise = ((case * 7 + seed * 3) % 5) as f32 * 0.02;
                for (flow, fb) in [("IDM", 0.0), ("SocialComm", 0.05)] {
                    rows.push(row("cross", "RARL/SocialCommAdv", flow, case, seed, 0.8 + fb + noise));
                    rows.push(row("cross", "RL/IDM", flow, case, seed, 0.3 + fb + noise));
                    rows.push(row("cross", "RL/SocialComm", flow, case, seed, 0.6 + fb + noise * 0.5));
                }
                rows.push(row("flow_quality", "", "SocialComm", case, seed, 0.7 + noise));
                rows.push(row("flow_quality", "", "CoPO", case, seed, 0.4 + noise));
                for (flow, v) in [("SocialComm", 0.7), ("SocialCommAdv", 0.6), ("FailMaker", 0.2)] {
                    rows.push(row("adversary", "RL/IDM", flow, case, seed, v + noise));
                }
                for svo in [0, 45, 90] {
                    for (flow, v) in [("CoPO", 0.4), ("SocialComm", 0.7)] {
                        rows.push(EpisodeRow { svo_deg: Some(svo), ..row("svo_sweep", "", flow, case, seed, v + noise) });
                    }
                }
                for n in [4, 8] {
                    rows.push(EpisodeRow { vehicles: Some(n), ..row("density", "", "SocialComm", case, seed, 0.9 - n as f32 * 0.05) });
                }
            }
        }
        let meta = Meta {
            trained_in: [("RL/IDM".to_string(), "IDM".to_string()), ("RL/SocialComm".to_string(), "SocialComm".to_string())].into(),
            ours: Some("RARL/SocialCommAdv".into()),
            flows: vec!["IDM".into(), "CoPO".into(), "SocialComm".into(), "SocialCommAdv".into(), "FailMaker".into()],
            egos: vec!["RL/IDM".into(), "RL/SocialComm".into(), "RARL/SocialCommAdv".into()],
            cases: 12,
            seeds: 2,
        };
        let out = std::env::temp_dir().join(format!("sf-report-{}", std::process::id()));
        let f = build(&rows, &meta, &out).expect("report");
        assert_eq!(f.experiments, ["flow_quality", "svo_sweep", "density", "adversary", "cross"]);
        let md = std::fs::read_to_string(out.join("report.md")).expect("md");
        for needle in ["Cross-validation", "cross-success-merge.png", "zero-shot-success.png", "64.5 / 62.8 / 9.2", "svo-sweep-merge.png", "density.png"] {
            assert!(md.contains(needle), "{needle} missing from the report");
        }
        let html = std::fs::read_to_string(out.join("report.html")).expect("html");
        assert!(html.contains("data:image/png;base64,") && !html.contains("src=\"cross-"), "figures are embedded");
        let beats = f.checks.iter().find(|(c, _, _)| c.contains("better than RL/SocialComm")).expect("a zero-shot check");
        assert!(beats.1 && beats.2.is_some_and(|p| p < 1e-4), "{beats:?}");
        let _ = std::fs::remove_dir_all(&out);
    }
}
