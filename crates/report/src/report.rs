//! The reproduction report: per-episode results in, tables, statistics and figures out.
//!
//! Owns: [`build`], which turns stored per-episode results and the grid's metadata
//! ([`crate::episodes`]) into `report.md` and a
//! self-contained `report.html` (figures embedded) with every experiment the results hold:
//! flow quality (tables, radar charts), the SVO and density sweeps, adversary degradation,
//! cross-validation heatmaps (medals per column, grey diagonal) and zero-shot bar charts with
//! 95 % intervals and paired t-tests. The paper's numbers are printed beside ours where the
//! paper gives them in its text; which rows each of the paper's findings is tested on
//! ([`crate::findings`] decides the verdict). Must not: run simulations or define the result
//! files' format.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::episodes::{file_err, EpisodeRow, FileError, Meta};
use crate::findings::Check;
use crate::plot::{self, Bar, Mark, Series};
use crate::{paired_t_test, Summary};

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error(transparent)]
    Plot(#[from] plot::PlotError),
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
const METRICS: [(&str, Metric); 3] = [("Success", |r| r.ep.scores.success), ("Safety", |r| r.ep.scores.safety), ("Speed", |r| r.ep.scores.speed)];

fn summary(rows: &[&EpisodeRow], m: Metric) -> Summary {
    Summary::of(&rows.iter().map(|r| m(r) as f64).collect::<Vec<_>>())
}

/// "= 1.23e-2", or "< 1e-15" below what [`fmt_p`] prints (after a "p").
fn p_is(p: f64) -> String {
    match fmt_p(p) {
        s if s.starts_with('<') => s,
        s => format!("= {s}"),
    }
}

fn pct(s: Summary) -> String {
    if s.n == 0 {
        "-".into()
    } else {
        format!("{:.1} ± {:.1}", 100.0 * s.mean, 100.0 * s.ci95)
    }
}

/// Paired t-test of metric `m` between two row sets, paired on the same episode start
/// (replicate, scenario, SVO, vehicles, case, seed) and the dimension that is not compared: with
/// `same_flow` two egos are compared on the same flow; otherwise two flows with the same ego
/// (pooled rows of several egos pair each ego with itself, never with another ego).
fn paired_on(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric, same_flow: bool) -> Option<crate::PairedT> {
    let (x, y) = pairs(a, b, m, same_flow);
    paired_t_test(&x, &y).ok()
}

/// The metric's values of `a` and `b` on the episode starts they share (see [`paired_on`]).
fn pairs(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric, same_flow: bool) -> (Vec<f64>, Vec<f64>) {
    let key = |r: &EpisodeRow| (r.replicate, if same_flow { r.cell.flow.clone() } else { r.cell.ego.clone() }, r.cell.scenario.clone(), r.cell.svo_deg, r.cell.vehicles, r.ep.case, r.ep.seed);
    let bm: BTreeMap<_, f64> = b.iter().map(|r| (key(r), m(r) as f64)).collect();
    let (mut x, mut y) = (Vec::new(), Vec::new());
    for r in a {
        if let Some(v) = bm.get(&key(r)) {
            x.push(m(r) as f64);
            y.push(*v);
        }
    }
    (x, y)
}

/// Per-episode-start differences `a - b` of two flows (see [`paired_across_flows`]).
fn diffs_across_flows(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric) -> Vec<f64> {
    let (x, y) = pairs(a, b, m, false);
    x.iter().zip(&y).map(|(p, q)| p - q).collect()
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
    /// The paper's findings this result set can test, each with its test, effect and p-value
    /// (over every replicate when there are several).
    pub checks: Vec<Check>,
    /// With several replicates: each replicate's own findings, in replicate order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub replicates: Vec<Findings>,
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

/// What every section of the report reads.
struct Ctx<'a> {
    rows: &'a [EpisodeRow],
    meta: &'a Meta,
    out: &'a Path,
    /// Scenarios in the paper's order.
    scen_pref: Vec<String>,
}

/// Builds `report.md`, `report.html` and the figures in `out` from `episodes` and `meta`.
pub fn build(rows: &[EpisodeRow], meta: &Meta, out: &Path) -> Result<Findings, ReportError> {
    build_doc(rows, meta, out, Vec::new())
}

/// The report of several replicates of one graph (each trained from scratch with its own seed,
/// evaluated on the same grid, `meta`): each replicate's own report in `out/run-<k>/`
/// (k from 1), and in `out` the report of all their episodes together, in which paired tests
/// pair episodes within a replicate (the same start under two flows or egos of the same
/// replicate) and the findings table shows every replicate's effect and p beside the pooled
/// one. One set is [`build`].
pub fn build_replicates(sets: &[Vec<EpisodeRow>], meta: &Meta, out: &Path) -> Result<Findings, ReportError> {
    if sets.len() == 1 {
        return build(&sets[0], meta, out);
    }
    let mut each = Vec::with_capacity(sets.len());
    let mut pooled = Vec::with_capacity(sets.iter().map(Vec::len).sum());
    for (k, rows) in sets.iter().enumerate() {
        each.push(build(rows, meta, &out.join(format!("run-{}", k + 1)))?);
        pooled.extend(rows.iter().map(|r| EpisodeRow { replicate: k as u32, ..r.clone() }));
    }
    build_doc(&pooled, meta, out, each)
}

fn build_doc(rows: &[EpisodeRow], meta: &Meta, out: &Path, replicates: Vec<Findings>) -> Result<Findings, ReportError> {
    std::fs::create_dir_all(out).map_err(|e| file_err(out, e))?;
    let mut doc = Doc { md: String::new(), html: String::new(), dir: out.to_path_buf() };
    let mut found = Findings { episodes: rows.len(), ..Findings::default() };
    doc.h(1, "socialflow: reproduction report");
    let over = match replicates.len() {
        0 => String::new(),
        n => format!(
            ", over {n} replicates of the graph (each trained from scratch with its own seed; each replicate's own report in run-1/ .. run-{n}/; paired tests pair episodes within a replicate)"
        ),
    };
    doc.p(&format!("{} evaluated episodes ({} stored cases x {} seeds per cell{over}). Values are percent, mean ± 95 % confidence half-width (Student t); p-values from paired two-sided t-tests over the same (case, seed) pairs. Stars: **** p < 0.0001, *** p < 0.001, ** p < 0.01, * p < 0.05.", rows.len(), meta.cases, meta.seeds));
    let ctx = Ctx { rows, meta, out, scen_pref: ["intersection", "bottleneck", "merge", "roundabout"].iter().map(|s| s.to_string()).collect() };
    for section in [flow_quality, svo_sweep, density, adversary, cross] {
        section(&ctx, &mut doc, &mut found)?;
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
        doc.p("Each finding in the paper's direction; effect: mean paired difference in points, positive where the paper says it should be; verdict at p < 0.05 with its direction (a significant effect the other way reads \"opposite\").");
        if !replicates.is_empty() {
            doc.p("Effect, p and verdict over every replicate's episodes, then each run's own; \"every run\": the verdict when all runs reach the same one, else \"runs disagree\". A \"-\": that run did not test the claim (the zero-shot comparisons are against each run's own two nearest egos).");
        }
        let mut head: Vec<String> = ["Finding", "Test", "Effect (points)", "p", "Here"].map(String::from).into();
        head.extend((1..=replicates.len()).map(|k| format!("Run {k}: effect, p")));
        if !replicates.is_empty() {
            head.push("Every run".into());
        }
        let table: Vec<Vec<String>> = found
            .checks
            .iter()
            .map(|c| {
                let mut row = vec![c.claim.clone(), c.test.clone(), format!("{:+.1}", c.effect_points), fmt_p(c.p_value), c.verdict.as_str().into()];
                let runs: Vec<Option<&Check>> = replicates.iter().map(|f| f.checks.iter().find(|r| r.key == c.key)).collect();
                row.extend(runs.iter().map(|r| match r {
                    Some(r) => format!("{:+.1}, {} ({})", r.effect_points, fmt_p(r.p_value), r.verdict.as_str()),
                    None => "-".into(),
                }));
                if !runs.is_empty() {
                    row.push(match runs.iter().map(|r| r.map(|r| r.verdict)).collect::<Option<Vec<_>>>() {
                        Some(v) if v.windows(2).all(|w| w[0] == w[1]) => v[0].as_str().into(),
                        Some(_) => "runs disagree".into(),
                        None => "-".into(),
                    });
                }
                row
            })
            .collect();
        doc.table(&head, &table);
    }
    found.replicates = replicates;
    let md_path = out.join("report.md");
    std::fs::write(&md_path, &doc.md).map_err(|e| file_err(&md_path, e))?;
    let html = format!("<!doctype html><html><head><meta charset=\"utf-8\"><title>socialflow report</title><style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}table{{border-collapse:collapse;margin:1em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;font-size:13px}}img{{max-width:100%}}</style></head><body>{}</body></html>", doc.html);
    let html_path = out.join("report.html");
    std::fs::write(&html_path, html).map_err(|e| file_err(&html_path, e))?;
    Ok(found)
}

/// Flow quality: a table and a radar chart per scenario; SocialComm against every other flow.
fn flow_quality(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let fq = by(rows, |r| r.cell.experiment == "flow_quality");
    if !fq.is_empty() {
        found.experiments.push("flow_quality".into());
        doc.h(2, "Flow quality (every vehicle driven by the flow)");
        let flows = order(fq.iter().map(|r| r.cell.flow.clone()), &meta.flows);
        let scen = order(fq.iter().map(|r| r.cell.scenario.clone()), &ctx.scen_pref);
        let mut head = vec!["Flow".to_string(), "Scenario".into()];
        head.extend(METRICS.iter().map(|(n, _)| n.to_string()));
        let mut table = Vec::new();
        for f in &flows {
            for s in &scen {
                let cell = by(rows, |r| r.cell.experiment == "flow_quality" && &r.cell.flow == f && &r.cell.scenario == s);
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
                    let cell = by(rows, |r| r.cell.experiment == "flow_quality" && &r.cell.flow == f && &r.cell.scenario == s);
                    (f.clone(), METRICS.iter().enumerate().map(|(k, (_, m))| (k as f64, summary(&cell, *m).mean)).collect())
                })
                .collect();
            let file = format!("flow-quality-{s}.png");
            let ser: Vec<Series> = series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
            plot::radar(&ctx.out.join(&file), &format!("Flow quality, {s}"), &METRICS.iter().map(|(n, _)| n.to_string()).collect::<Vec<_>>(), &ser)?;
            doc.figure(&file, &format!("Success, Safety and Speed of each flow in {s} (radar; 1 = 100 %)"))?;
        }
        // The paper: SocialComm beats CoPO, MACAD and IDM as a flow, most in dense merge.
        if flows.iter().any(|f| f == "SocialComm") {
            // A flow's rows, in merge (`Some(true)`), elsewhere (`Some(false)`) or everywhere.
            let fq = |flow: &str, merge: Option<bool>| by(rows, |r| r.cell.experiment == "flow_quality" && r.cell.flow == flow && merge.is_none_or(|m| (r.cell.scenario == "merge") == m));
            for other in flows.iter().filter(|f| *f != "SocialComm") {
                if let Some(t) = paired_across_flows(&fq("SocialComm", None), &fq(other, None), |r| r.ep.scores.success) {
                    found.checks.push(Check::from_paired(format!("SocialComm flow succeeds more often than {other} (flow quality, all scenarios)"), &format!("success, SocialComm - {other}"), &t));
                }
                let (sc_merge, other_merge) = (fq("SocialComm", Some(true)), fq(other, Some(true)));
                if let Some(t) = paired_across_flows(&sc_merge, &other_merge, |r| r.ep.scores.success) {
                    found.checks.push(Check::from_paired(format!("SocialComm flow succeeds more often than {other} in merge"), &format!("success, SocialComm - {other}"), &t));
                }
                // "Most in dense merge": SocialComm's per-start advantage in merge against its
                // advantage in the other scenarios (independent starts, so Welch's test).
                let in_merge = diffs_across_flows(&sc_merge, &other_merge, |r| r.ep.scores.success);
                let elsewhere = diffs_across_flows(&fq("SocialComm", Some(false)), &fq(other, Some(false)), |r| r.ep.scores.success);
                if let Ok(w) = crate::welch_t_test(&in_merge, &elsewhere) {
                    found.checks.push(Check::from_welch(
                        format!("SocialComm's advantage over {other} is larger in merge than elsewhere"),
                        &format!("success difference SocialComm - {other} per episode start, merge vs the other scenarios"),
                        &w,
                    ));
                }
            }
        }
    }
    Ok(())
}

/// The SVO sweep: success against SVO per scenario; SocialComm against the other flow.
fn svo_sweep(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let sw = by(rows, |r| r.cell.experiment == "svo_sweep");
    if !sw.is_empty() {
        found.experiments.push("svo_sweep".into());
        doc.h(2, "SVO sweep (all agents share one SVO)");
        let flows = order(sw.iter().map(|r| r.cell.flow.clone()), &meta.flows);
        let scen = order(sw.iter().map(|r| r.cell.scenario.clone()), &ctx.scen_pref);
        for s in &scen {
            let series: Vec<(String, Vec<(f64, f64)>)> = flows
                .iter()
                .map(|f| {
                    let svos: BTreeSet<u32> = sw.iter().filter(|r| &r.cell.flow == f && &r.cell.scenario == s).filter_map(|r| r.cell.svo_deg).collect();
                    (
                        f.clone(),
                        svos.into_iter()
                            .map(|v| {
                                (
                                    v as f64,
                                    summary(&by(rows, |r| r.cell.experiment == "svo_sweep" && &r.cell.flow == f && &r.cell.scenario == s && r.cell.svo_deg == Some(v)), |r| r.ep.scores.success).mean,
                                )
                            })
                            .collect(),
                    )
                })
                .collect();
            let file = format!("svo-sweep-{s}.png");
            let ser: Vec<Series> = series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
            plot::line_chart(&ctx.out.join(&file), &format!("Success vs SVO, {s}"), "SVO (deg)", "success", &ser, Some((0.0, 1.0)), (640, 400))?;
            doc.figure(&file, &format!("Flow success rate when every agent has the same SVO, {s}"))?;
            if flows.len() == 2 {
                let a = by(rows, |r| r.cell.experiment == "svo_sweep" && r.cell.flow == flows[1] && &r.cell.scenario == s);
                let b = by(rows, |r| r.cell.experiment == "svo_sweep" && r.cell.flow == flows[0] && &r.cell.scenario == s);
                if let Some(t) = paired_across_flows(&a, &b, |r| r.ep.scores.success) {
                    doc.p(&format!("{s}: {} - {} success = {:+.1} points over all SVOs, p = {} {}", flows[1], flows[0], 100.0 * t.mean_diff, fmt_p(t.p_value), stars(t.p_value)));
                    if flows[1] == "SocialComm" {
                        found.checks.push(Check::from_paired(format!("SocialComm beats {} over the SVO sweep in {s}", flows[0]), &format!("success, SocialComm - {}", flows[0]), &t));
                    }
                }
            }
        }
    }
    Ok(())
}

/// The density sweep: success against vehicles per case.
fn density(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let de = by(rows, |r| r.cell.experiment == "density");
    if !de.is_empty() {
        found.experiments.push("density".into());
        doc.h(2, "Density sweep");
        let flows = order(de.iter().map(|r| r.cell.flow.clone()), &meta.flows);
        let scen = de[0].cell.scenario.clone();
        let series: Vec<(String, Vec<(f64, f64)>)> = flows
            .iter()
            .map(|f| {
                let ns: BTreeSet<usize> = de.iter().filter(|r| &r.cell.flow == f).filter_map(|r| r.cell.vehicles).collect();
                (
                    f.clone(),
                    ns.into_iter()
                        .map(|n| (n as f64, summary(&by(rows, |r| r.cell.experiment == "density" && &r.cell.flow == f && r.cell.vehicles == Some(n)), |r| r.ep.scores.success).mean))
                        .collect(),
                )
            })
            .collect();
        let ser: Vec<Series> = series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
        plot::line_chart(&ctx.out.join("density.png"), &format!("Success vs vehicles, {scen}"), "vehicles per case", "success", &ser, Some((0.0, 1.0)), (640, 400))?;
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
    Ok(())
}

/// Adversary degradation: egos trained in non-adversarial flows under each adversary.
fn adversary(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let ad = by(rows, |r| r.cell.experiment == "adversary");
    if !ad.is_empty() {
        found.experiments.push("adversary".into());
        doc.h(2, "Effect of adversaries on egos trained in non-adversarial flows");
        let egos = order(ad.iter().map(|r| r.cell.ego.clone()), &meta.egos);
        let flows = order(ad.iter().map(|r| r.cell.flow.clone()), &meta.flows);
        let scen = order(ad.iter().map(|r| r.cell.scenario.clone()), &ctx.scen_pref);
        for (mname, m) in [METRICS[0], METRICS[2]] {
            let paper = paper_adversary(mname);
            let mut head = vec!["Ego".to_string(), "Scenario".into()];
            head.extend(flows.iter().cloned());
            head.push("p (first vs second flow)".into());
            head.push("paper (SC / SCA / FM)".into());
            let mut table = Vec::new();
            for e in &egos {
                for s in &scen {
                    let cell = |f: &String| by(rows, |r| r.cell.experiment == "adversary" && &r.cell.ego == e && &r.cell.flow == f && &r.cell.scenario == s);
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
            let pooled = |f: &String| by(rows, |r| r.cell.experiment == "adversary" && &r.cell.flow == f);
            let (sc, sca, fm) =
                (summary(&pooled(&flows[0]), |r| r.ep.scores.success).mean, summary(&pooled(&flows[1]), |r| r.ep.scores.success).mean, summary(&pooled(&flows[2]), |r| r.ep.scores.success).mean);
            if let Some(t) = paired_across_flows(&pooled(&flows[0]), &pooled(&flows[1]), |r| r.ep.scores.success) {
                found.checks.push(Check::from_paired(format!("Egos succeed less in {} than in {} (pooled)", flows[1], flows[0]), &format!("success, {} - {}", flows[0], flows[1]), &t));
            }
            // The paper: FailMaker costs egos about 10x the success SocialCommAdv costs them.
            if let Some(t) = paired_across_flows(&pooled(&flows[1]), &pooled(&flows[2]), |r| r.ep.scores.success) {
                let ratio = if sc - sca > 0.0 { format!("{:.1}x", (sc - fm) / (sc - sca)) } else { "undefined (no drop under the first)".into() };
                let claim = format!(
                    "{} degrades egos more than {} (pooled success {} {:.1}, {} {:.1}, {} {:.1}; drop ratio {ratio}, paper ~10x)",
                    flows[2],
                    flows[1],
                    flows[0],
                    100.0 * sc,
                    flows[1],
                    100.0 * sca,
                    flows[2],
                    100.0 * fm
                );
                let key = format!("{} degrades egos more than {}", flows[2], flows[1]);
                found.checks.push(Check::from_paired(claim, &format!("success, {} - {}", flows[1], flows[2]), &t).keyed(key));
            }
        }
    }
    Ok(())
}

/// Cross-validation heatmaps and zero-shot bars; "ours" against the two nearest egos.
fn cross(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let cv = by(rows, |r| r.cell.experiment == "cross");
    if !cv.is_empty() {
        found.experiments.push("cross".into());
        doc.h(2, "Cross-validation: every ego in every flow");
        doc.p("Rows: ego policies; columns: evaluation flows. Grey: the ego's own training flow (not ranked). Gold, silver and copper frames: first, second and third of each column.");
        let egos = order(cv.iter().map(|r| r.cell.ego.clone()), &meta.egos);
        let flows = order(cv.iter().map(|r| r.cell.flow.clone()), &meta.flows);
        let scen = order(cv.iter().map(|r| r.cell.scenario.clone()), &ctx.scen_pref);
        for s in &scen {
            for (mname, m) in [METRICS[0], METRICS[2]] {
                let values: Vec<Vec<f64>> = egos
                    .iter()
                    .map(|e| flows.iter().map(|f| summary(&by(rows, |r| r.cell.experiment == "cross" && &r.cell.ego == e && &r.cell.flow == f && &r.cell.scenario == s), m).mean).collect())
                    .collect();
                let marks = medals(&egos, &flows, &values, &meta.trained_in, meta.idm_ego.as_ref());
                let file = format!("cross-{}-{s}.png", mname.to_lowercase());
                plot::heatmap(&ctx.out.join(&file), &format!("{mname}, {s}"), &egos, &flows, &values, &marks)?;
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
                let pooled = |e: &String| by(rows, |r| r.cell.experiment == "cross" && &r.cell.ego == e && &r.cell.scenario == s);
                let means: Vec<(String, Summary)> = egos.iter().map(|e| (e.clone(), summary(&pooled(e), m))).collect();
                let mut bars: Vec<Bar> = means.iter().map(|(_, v)| Bar { mean: v.mean, ci95: v.ci95, stars: String::new() }).collect();
                if let Some(ours) = meta.ours.as_ref().filter(|o| egos.contains(o)) {
                    let our_mean = means.iter().find(|(e, _)| e == ours).map(|(_, v)| v.mean).unwrap_or(f64::NAN);
                    // Among the trained egos: the IDM driver has its own section below.
                    let mut others: Vec<&(String, Summary)> = means.iter().filter(|(e, _)| e != ours && Some(e) != meta.idm_ego.as_ref()).collect();
                    others.sort_by(|a, b| (a.1.mean - our_mean).abs().total_cmp(&(b.1.mean - our_mean).abs()));
                    for (e, _) in others.into_iter().take(2) {
                        if let Some(t) = paired(&pooled(ours), &pooled(e), m) {
                            let k = egos.iter().position(|x| x == e).unwrap_or(0);
                            bars[k].stars = stars(t.p_value).to_string();
                            lines.push(format!("{s}: {ours} - {e} {mname} = {:+.1} points, p = {} {}", 100.0 * t.mean_diff, fmt_p(t.p_value), stars(t.p_value)));
                            if mname == "Success" {
                                found.checks.push(Check::from_paired(
                                    format!("{ours} transfers better than {e} in {s} (success)"),
                                    &format!("success, {ours} - {e}, pooled over evaluation flows"),
                                    &t,
                                ));
                            }
                        }
                    }
                }
                groups.push(bars);
            }
            let file = format!("zero-shot-{}.png", mname.to_lowercase());
            plot::grouped_bars(&ctx.out.join(&file), &format!("Zero-shot {mname} (pooled over evaluation flows)"), &mname.to_lowercase(), &scen, &egos, &groups)?;
            doc.figure(&file, &format!("{mname} of each ego pooled over the evaluation flows, 95 % intervals; stars: paired t-test of ours against the two nearest"))?;
            for l in lines {
                doc.p(&l);
            }
        }
        if let Some(idm) = meta.idm_ego.as_ref().filter(|e| egos.contains(e)) {
            against_idm_ego(ctx, doc, found, idm, &egos, &scen);
        }
    }
    Ok(())
}

/// Every trained ego against the IDM driver in its seat, on the same cross-validation episode
/// starts (flow, scenario, case, seed): per scenario and pooled, with one check per ego.
fn against_idm_ego(ctx: &Ctx, doc: &mut Doc, found: &mut Findings, idm: &String, egos: &[String], scen: &[String]) {
    let success = METRICS[0].1;
    let cells = |e: &String, s: Option<&String>| by(ctx.rows, |r| r.cell.experiment == "cross" && &r.cell.ego == e && s.is_none_or(|s| &r.cell.scenario == s));
    doc.h(2, "Trained egos against the IDM driver in their seat");
    doc.p(&format!(
        "Success in percent over the cross-validation cells (every evaluation flow); in brackets the paired difference to `{idm}` (the IDM driver, the zero residual every trained ego starts from) on the same episode starts and its p-value. The last column pools every scenario."
    ));
    let mut head = vec!["Ego".to_string()];
    head.extend(scen.iter().cloned());
    head.push("all scenarios".into());
    let scopes: Vec<Option<&String>> = scen.iter().map(Some).chain([None]).collect();
    let mean = |rows: &[&EpisodeRow]| if rows.is_empty() { "-".to_string() } else { format!("{:.1}", 100.0 * summary(rows, success).mean) };
    let mut table = vec![std::iter::once(idm.clone()).chain(scopes.iter().map(|s| mean(&cells(idm, *s)))).collect::<Vec<_>>()];
    for e in egos.iter().filter(|e| *e != idm) {
        let mut line = vec![e.clone()];
        for s in &scopes {
            let (a, b) = (cells(e, *s), cells(idm, *s));
            let t = paired(&a, &b, success);
            line.push(match &t {
                Some(t) => format!("{} ({:+.1}, p {})", mean(&a), 100.0 * t.mean_diff, p_is(t.p_value)),
                None => mean(&a),
            });
            if let (None, Some(t)) = (s, t) {
                found.checks.push(Check::from_paired(
                    format!("{e} succeeds more often than the IDM driver in its seat (cross-validation, all flows and scenarios)"),
                    &format!("success, {e} - {idm}"),
                    &t,
                ));
            }
        }
        table.push(line);
    }
    doc.table(&head, &table);
}

/// Grey for an ego's own training flow; gold, silver, copper for the best three of each column,
/// `unranked` (a baseline) left out of the ranking.
pub fn medals(egos: &[String], flows: &[String], values: &[Vec<f64>], trained_in: &BTreeMap<String, String>, unranked: Option<&String>) -> Vec<Vec<Mark>> {
    let mut marks = vec![vec![Mark::None; flows.len()]; egos.len()];
    for (c, f) in flows.iter().enumerate() {
        let mut ranked: Vec<(usize, f64)> = Vec::new();
        for (r, e) in egos.iter().enumerate() {
            if trained_in.get(e) == Some(f) {
                marks[r][c] = Mark::Diagonal;
            } else if Some(e) == unranked {
                // A baseline (the IDM driver in the ego's seat) is shown, not ranked.
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
    use sf_job::eval::{Cell, EvalEpisode};

    fn row(experiment: &str, ego: &str, flow: &str, case: u32, seed: u32, success: f32) -> EpisodeRow {
        EpisodeRow {
            cell: Cell { experiment: experiment.into(), ego: ego.into(), flow: flow.into(), scenario: "merge".into(), svo_deg: None, vehicles: None },
            ep: EvalEpisode { case, seed, scores: sf_job::Scores { success, safety: success, speed: 0.5 }, collision: 0.0 },
            replicate: 0,
        }
    }

    /// `row` with the cell changed by `f` (sweeps set the SVO or the vehicle count).
    fn with_cell(mut r: EpisodeRow, f: impl FnOnce(&mut Cell)) -> EpisodeRow {
        f(&mut r.cell);
        r
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
        let t = paired_across_flows(&xr, &yr, |r| r.ep.scores.success).expect("a test");
        assert_eq!(t.n, 40, "one pair per ego and episode start");
        assert!(t.mean_diff.abs() < 1e-12 && t.p_value > 0.9, "{t:?}");
        // Two egos on the same flow still pair across egos.
        let a: Vec<&EpisodeRow> = x.iter().filter(|r| r.cell.ego == "A").collect();
        let b: Vec<&EpisodeRow> = x.iter().filter(|r| r.cell.ego == "B").collect();
        let t = paired(&a, &b, |r| r.ep.scores.success).expect("a test");
        assert_eq!(t.n, 20);
    }

    #[test]
    fn medals_skip_the_diagonal_and_rank_each_column() {
        let egos: Vec<String> = ["A", "B", "C", "D"].iter().map(|s| s.to_string()).collect();
        let flows: Vec<String> = ["X", "Y"].iter().map(|s| s.to_string()).collect();
        let values = vec![vec![0.9, 0.1], vec![0.5, 0.2], vec![0.7, 0.3], vec![0.6, 0.4]];
        let trained: BTreeMap<String, String> = [("A".to_string(), "X".to_string())].into();
        let m = medals(&egos, &flows, &values, &trained, None);
        assert_eq!(m[0][0], Mark::Diagonal, "A's own flow is grey though it is the best");
        assert_eq!((m[2][0], m[3][0], m[1][0]), (Mark::Gold, Mark::Silver, Mark::Copper));
        assert_eq!((m[3][1], m[2][1], m[1][1], m[0][1]), (Mark::Gold, Mark::Silver, Mark::Copper, Mark::None));
        // A baseline row is not ranked: the next ego takes its medal.
        let m = medals(&egos, &flows, &values, &trained, Some(&egos[3]));
        assert_eq!((m[2][1], m[1][1], m[0][1], m[3][1]), (Mark::Gold, Mark::Silver, Mark::Copper, Mark::None));
    }

    #[test]
    fn stars_follow_the_paper() {
        assert_eq!((stars(1e-5), stars(5e-4), stars(5e-3), stars(0.03), stars(0.2)), ("****", "***", "**", "*", "n.s."));
        assert_eq!((fmt_p(0.0), fmt_p(0.0123)), ("< 1e-15".to_string(), "1.23e-2".to_string()));
    }

    /// Replicates pair within themselves: the same (case, seed) in two replicates are different
    /// episodes. Here each replicate's SocialComm beats CoPO by ~10 points on every start while
    /// the replicates' values are opposite, so pairing across them would see +-90 points.
    #[test]
    fn replicates_pair_within_themselves_and_report_each_run() {
        let set = |rep: u32| {
            let mut rows = Vec::new();
            for case in 0..16 {
                let base = if (case % 2 == 0) == (rep == 0) { 1.0 } else { 0.0 };
                let jitter = (case % 3) as f32 * 0.01;
                rows.push(row("flow_quality", "", "SocialComm", case, 0, base));
                rows.push(row("flow_quality", "", "CoPO", case, 0, base - 0.1 - jitter));
                // The adversary claim quotes measured values, which differ between replicates.
                for (flow, v) in [("SocialComm", 0.7), ("SocialCommAdv", 0.6 - 0.1 * rep as f32), ("FailMaker", 0.2)] {
                    rows.push(row("adversary", "RL/IDM", flow, case, 0, v + jitter));
                }
            }
            rows
        };
        let meta = Meta { flows: vec!["CoPO".into(), "SocialComm".into(), "SocialCommAdv".into(), "FailMaker".into()], cases: 16, seeds: 1, ..Meta::default() };
        let out = std::env::temp_dir().join(format!("sf-report-replicates-{}", std::process::id()));
        let f = build_replicates(&[set(0), set(1)], &meta, &out).expect("report");
        let copo = f.checks.iter().find(|c| c.claim == "SocialComm flow succeeds more often than CoPO (flow quality, all scenarios)").expect("flow check");
        assert_eq!(copo.n, 32, "both replicates' starts");
        assert!(copo.holds() && (copo.effect_points - 11.0).abs() < 1.0, "{copo:?}");
        assert_eq!(f.replicates.len(), 2);
        for (k, r) in f.replicates.iter().enumerate() {
            assert_eq!(r.episodes, 16 * 5, "run {k}");
            assert!(out.join(format!("run-{}", k + 1)).join("report.md").exists(), "run {k}'s own report");
        }
        let md = std::fs::read_to_string(out.join("report.md")).expect("md");
        assert!(md.contains("over 2 replicates") && md.contains("| Run 1: effect, p | Run 2: effect, p | Every run |"), "{md}");
        let fm = md.lines().find(|l| l.starts_with("| FailMaker degrades egos more")).expect("adversary row");
        assert!(!fm.contains("| - |") && fm.contains("3.3x"), "each run's check is found by its key although its claim differs: {fm}");
        assert!(fm.ends_with("| holds |"), "both runs hold: {fm}");
        assert_ne!(f.replicates[0].checks.iter().find(|c| c.key.starts_with("FailMaker")).map(|c| &c.claim), f.replicates[1].checks.iter().find(|c| c.key.starts_with("FailMaker")).map(|c| &c.claim));
        let _ = std::fs::remove_dir_all(&out);
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
                    rows.push(row("cross", "IDM ego", flow, case, seed, 0.45 + fb + noise * 0.5));
                }
                rows.push(row("flow_quality", "", "SocialComm", case, seed, 0.7 + noise));
                rows.push(row("flow_quality", "", "CoPO", case, seed, 0.4 + noise));
                for (flow, v) in [("SocialComm", 0.7), ("SocialCommAdv", 0.6), ("FailMaker", 0.2)] {
                    rows.push(row("adversary", "RL/IDM", flow, case, seed, v + noise));
                }
                for svo in [0, 45, 90] {
                    for (flow, v) in [("CoPO", 0.4), ("SocialComm", 0.7)] {
                        rows.push(with_cell(row("svo_sweep", "", flow, case, seed, v + noise), |c| c.svo_deg = Some(svo)));
                    }
                }
                for n in [4, 8] {
                    rows.push(with_cell(row("density", "", "SocialComm", case, seed, 0.9 - n as f32 * 0.05), |c| c.vehicles = Some(n)));
                }
            }
        }
        let meta = Meta {
            trained_in: [("RL/IDM".to_string(), "IDM".to_string()), ("RL/SocialComm".to_string(), "SocialComm".to_string())].into(),
            ours: Some("RARL/SocialCommAdv".into()),
            flows: vec!["IDM".into(), "CoPO".into(), "SocialComm".into(), "SocialCommAdv".into(), "FailMaker".into()],
            egos: vec!["RL/IDM".into(), "RL/SocialComm".into(), "RARL/SocialCommAdv".into(), "IDM ego".into()],
            idm_ego: Some("IDM ego".into()),
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
        let beats = f.checks.iter().find(|c| c.claim.contains("better than RL/SocialComm")).expect("a zero-shot check");
        assert!(beats.holds() && beats.p_value < 1e-4, "{beats:?}");
        // FailMaker (0.2) degrades far more than SocialCommAdv (0.6) from SocialComm (0.7): a tested
        // finding with its direction, not a bare comparison of means.
        let fm = f.checks.iter().find(|c| c.claim.starts_with("FailMaker degrades egos more")).expect("the adversary check");
        assert!(fm.holds() && (fm.effect_points - 40.0).abs() < 1.0 && fm.claim.contains("5.0x"), "{fm:?}");
        let copo = f.checks.iter().find(|c| c.claim == "SocialComm flow succeeds more often than CoPO (flow quality, all scenarios)").expect("flow check");
        assert!(copo.holds() && copo.test.starts_with("paired t"), "{copo:?}");
        assert!(md.contains("| Finding | Test | Effect (points) | p | Here |"), "the findings table names test, effect and p");
        // Against the IDM driver in the ego's seat: one check per trained ego, with its direction.
        let vs_idm = |e: &str| f.checks.iter().find(|c| c.claim.starts_with(&format!("{e} succeeds more often than the IDM driver"))).unwrap_or_else(|| panic!("{e} vs the IDM ego"));
        assert!(vs_idm("RL/SocialComm").holds() && (vs_idm("RL/SocialComm").effect_points - 15.0).abs() < 1e-3, "{:?}", vs_idm("RL/SocialComm"));
        assert_eq!(vs_idm("RL/IDM").verdict, crate::findings::Verdict::Opposite, "0.30 vs 0.45 on every start");
        assert_eq!(f.checks.iter().filter(|c| c.claim.contains("than the IDM driver")).count(), 3, "the IDM ego is not tested against itself");
        assert!(!f.checks.iter().any(|c| c.claim.contains("better than IDM ego")), "ours is compared with trained egos only");
        assert!(md.contains("Trained egos against the IDM driver in their seat") && md.contains("| IDM ego | 49.4 | 49.4 |") && md.contains("(+15.0, p < 1e-15)"), "{md}");
        let _ = std::fs::remove_dir_all(&out);
    }
}
