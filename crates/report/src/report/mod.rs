//! The reproduction report: per-episode results in, tables, statistics and figures out.
//!
//! Owns: [`build`] and [`build_replicates`], which turn stored per-episode results and the
//! grid's metadata ([`crate::episodes`]) into `report.md` and `report.html` (figures as files
//! beside both, referenced by name, never embedded) with every experiment the results hold: flow
//! quality, the SVO and density sweeps ([`flows`]), adversary degradation, cross-validation
//! heatmaps, zero-shot transfer and the trained egos against the IDM driver ([`egos`]); the
//! findings table (each run's family Holm-corrected, the training run as the unit across runs)
//! and the power of each finding.
//! Every mean, interval and test is over stored cases ([`units`]: a start's seeds averaged,
//! then a case's starts under several flows, egos or SVOs). The paper's numbers
//! are printed beside ours where the paper gives them in its text. Must not: run simulations,
//! define the result files' format or decide a verdict ([`crate::findings`] does).

mod egos;
mod flows;
mod units;

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::episodes::{file_err, io_err, EpisodeRow, FileError, Meta};
use crate::findings::{self, AcrossRuns, Check};
use crate::inference;
use crate::plot;
use crate::stats::Summary;
pub use egos::medals;
use units::Metric;

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

const METRICS: [(&str, Metric); 3] = [
    ("Success", |r| r.ep.scores.success),
    ("Safety", |r| r.ep.scores.safety),
    ("Speed", |r| r.ep.scores.speed),
];

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

/// "1.23e-2 (Holm 4.56e-2)": a raw p-value and its family's adjusted one.
fn p_holm(p: f64, adjusted: f64) -> String {
    format!("{} (Holm {})", fmt_p(p), fmt_p(adjusted))
}

/// The paper's Table "Effects of adversaries" (success and speed, percent): ego -> scenario -> (SC, SCA, FM).
fn paper_adversary(metric: &str) -> BTreeMap<(&'static str, &'static str), [f64; 3]> {
    let success: [(&str, [[f64; 3]; 4]); 4] = [
        ("RL/IDM", [[76.5, 74.8, 55.2], [52.0, 50.8, 20.6], [64.5, 62.8, 9.2], [75.0, 72.8, 19.6]]),
        (
            "RL/MACAD",
            [[83.6, 82.6, 52.1], [75.2, 73.6, 4.6], [71.2, 69.6, 9.1], [73.6, 71.6, 29.6]],
        ),
        (
            "RL/CoPO",
            [[81.6, 78.8, 51.0], [71.6, 69.8, 6.5], [70.1, 66.2, 10.0], [82.1, 80.8, 21.0]],
        ),
        (
            "RL/SocialComm",
            [[87.2, 85.2, 51.4], [91.2, 85.2, 2.4], [84.8, 80.2, 8.4], [87.8, 84.7, 17.0]],
        ),
    ];
    let speed: [(&str, [[f64; 3]; 4]); 4] = [
        (
            "RL/IDM",
            [[47.4, 46.4, 37.3], [58.6, 57.5, 34.5], [51.6, 51.2, 15.1], [38.3, 38.3, 20.2]],
        ),
        (
            "RL/MACAD",
            [[49.8, 49.7, 36.1], [74.3, 73.9, 24.3], [54.7, 54.2, 17.6], [39.4, 39.6, 25.1]],
        ),
        (
            "RL/CoPO",
            [[49.3, 47.6, 34.9], [71.4, 70.0, 27.7], [55.6, 53.5, 19.4], [42.9, 42.3, 22.9]],
        ),
        (
            "RL/SocialComm",
            [[52.1, 51.0, 36.5], [81.5, 78.5, 24.3], [60.9, 59.4, 16.8], [43.4, 42.5, 19.9]],
        ),
    ];
    let table = if metric == "Speed" { speed } else { success };
    let scen = ["intersection", "bottleneck", "merge", "roundabout"];
    table
        .iter()
        .flat_map(|(ego, rows)| scen.iter().zip(rows).map(move |(s, v)| ((*ego, *s), *v)))
        .collect()
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
        let _ = write!(
            self.html,
            "<table><tr>{}</tr>",
            head.iter().map(|h| format!("<th>{}</th>", esc(h))).collect::<String>()
        );
        for r in rows {
            let _ = write!(
                self.html,
                "<tr>{}</tr>",
                r.iter().map(|c| format!("<td>{}</td>", esc(c))).collect::<String>()
            );
        }
        self.html.push_str("</table>\n");
    }

    /// A paragraph that is one link.
    fn link(&mut self, text: &str, href: &str) {
        self.links("", &[(text.to_string(), href.to_string())]);
    }

    /// A paragraph: `label:` and its links, comma separated.
    fn links(&mut self, label: &str, links: &[(String, String)]) {
        let head = if label.is_empty() { String::new() } else { format!("{label}: ") };
        let md: Vec<String> = links.iter().map(|(t, h)| format!("[{t}]({h})")).collect();
        let _ = writeln!(self.md, "{head}{}\n", md.join(", "));
        let html: Vec<String> = links
            .iter()
            .map(|(t, h)| format!("<a href=\"{}\">{}</a>", esc_attr(h), esc(t)))
            .collect();
        let _ = writeln!(self.html, "<p>{}{}</p>", esc(&head), html.join(", "));
    }

    /// A figure already written to `self.dir/<file>`: linked from markdown, referenced by its
    /// file name from HTML (the report's directory keeps the HTML and its figures together, so
    /// the page stays small and a figure is stored once).
    fn figure(&mut self, file: &str, caption: &str) -> Result<(), ReportError> {
        let path = self.dir.join(file);
        if !path.is_file() {
            return Err(file_err(&path, "figure missing beside the report").into());
        }
        let _ = writeln!(self.md, "![{caption}]({file})\n");
        let _ = writeln!(
            self.html,
            "<figure><img src=\"{}\" alt=\"{}\"><figcaption>{}</figcaption></figure>",
            esc_attr(file),
            esc(caption),
            esc(caption)
        );
        Ok(())
    }
}

/// The worst episodes of each cell, if failure mining left them beside the report
/// (`mined/cells.json`, written by `socialflow eval --mine`): a line per cell linking each
/// episode's viewer page, and the index.
fn mined_section(doc: &mut Doc, out: &Path) -> Result<(), ReportError> {
    let path = out.join("mined").join("cells.json");
    if !path.is_file() {
        return Ok(());
    }
    let text = std::fs::read_to_string(&path).map_err(|e| io_err(&path, e))?;
    let cells: BTreeMap<String, Vec<MinedEpisode>> = serde_json::from_str(&text)
        .map_err(|e| file_err(&path, format!("not the mined cells' JSON: {e}")))?;
    doc.h(2, "Worst episodes per cell");
    doc.p("Each cell's worst stored episodes, replayed into browser pages (play, pause, scrub; who drives each vehicle, what the focus agent observed): lowest success first, then most collisions. All of them, sortable by outcome: mined/index.html.");
    doc.link("all mined episodes", "mined/index.html");
    for (cell, eps) in &cells {
        let links: Vec<(String, String)> = eps
            .iter()
            .map(|e| {
                (
                    format!("{} (case {}, seed {})", e.outcome, e.case, e.seed),
                    format!("mined/{}", e.href),
                )
            })
            .collect();
        doc.links(cell, &links);
    }
    Ok(())
}

/// One mined episode as `mined/cells.json` lists it.
#[derive(serde::Deserialize)]
struct MinedEpisode {
    href: String,
    outcome: String,
    case: u32,
    seed: u32,
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

/// Text for a double-quoted HTML attribute.
fn esc_attr(s: &str) -> String {
    esc(s).replace('"', "&quot;")
}

/// What the report found, for the caller's summary.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Findings {
    pub episodes: usize,
    pub experiments: Vec<String>,
    /// The paper's findings this result set can test, each with its test, effect, raw and
    /// Holm-adjusted p (the family: these checks) and verdict. Over several replicates, the
    /// tests of their episodes together (starts averaged over the replicates, then per stored
    /// case): conditional on these trained instances, not the headline (see `across`).
    pub checks: Vec<Check>,
    /// With several replicates: each replicate's own findings, in replicate order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub replicates: Vec<Findings>,
    /// With several replicates: each claim across them, the training run as the unit.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub across: Vec<AcrossRuns>,
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
pub fn build_replicates(
    sets: &[Vec<EpisodeRow>],
    meta: &Meta,
    out: &Path,
) -> Result<Findings, ReportError> {
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

fn build_doc(
    rows: &[EpisodeRow],
    meta: &Meta,
    out: &Path,
    replicates: Vec<Findings>,
) -> Result<Findings, ReportError> {
    std::fs::create_dir_all(out).map_err(|e| io_err(out, e))?;
    let mut doc = Doc { md: String::new(), html: String::new(), dir: out.to_path_buf() };
    let mut found = Findings { episodes: rows.len(), ..Findings::default() };
    doc.h(1, "socialflow: reproduction report");
    let over = match replicates.len() {
        0 => String::new(),
        n => format!(
            ", over {n} replicates of the graph (each trained from scratch with its own seed; each replicate's own report in run-1/ .. run-{n}/). Tables pool the replicates: a start's value is its mean over seeds and replicates, paired differences are taken within a replicate; the replicates were evaluated on the same stored cases"
        ),
    };
    doc.p(&format!(
        "{} evaluated episodes ({}{over}). Values are percent, mean ± 95 % confidence half-width (Student t) over stored cases: a start's seeds are averaged first, so an episode that repeats under another seed (the IDM flow and every mean action are deterministic) counts once; then a stored case's starts are averaged, so a case reused under several SVOs, flows or egos of one comparison counts once (its outcomes correlate across them). p-values: two-sided paired t-tests over the same stored cases, except the \"larger in merge\" comparisons (Welch t-tests between the stored cases of two scenarios). Each table's p-values are one family, Holm-corrected within it (\"Holm\"); stars (**** < 0.0001, *** < 0.001, ** < 0.01, * < 0.05) mark the corrected p.",
        rows.len(),
        meta.sizes_text()
    ));
    let ctx = Ctx {
        rows,
        meta,
        out,
        scen_pref: ["intersection", "bottleneck", "merge", "roundabout"]
            .iter()
            .map(|s| s.to_string())
            .collect(),
    };
    for section in
        [flows::flow_quality, flows::svo_sweep, flows::density, egos::adversary, egos::cross]
    {
        section(&ctx, &mut doc, &mut found)?;
    }
    findings::adjust(&mut found.checks);

    // Episode GIFs placed in `out` by the caller (`gif-<scenario>.gif`).
    let mut gifs: Vec<String> = std::fs::read_dir(out)
        .map_err(|e| io_err(out, e))?
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with("gif-") && n.ends_with(".gif"))
        .collect();
    gifs.sort();
    if !gifs.is_empty() {
        doc.h(2, "The same case under each flow");
        doc.p("One ego policy, one stored case, the flows side by side (left to right as in the evaluation config); vehicles coloured by SVO.");
        for g in gifs {
            let scen = g.trim_start_matches("gif-").trim_end_matches(".gif").to_string();
            doc.figure(&g, &format!("{scen}: the same case under each flow"))?;
        }
    }

    mined_section(&mut doc, out)?;

    if replicates.is_empty() {
        findings_table(&mut doc, &found.checks);
    } else {
        let runs: Vec<Vec<Check>> = replicates.iter().map(|f| f.checks.clone()).collect();
        found.across = findings::across_runs(&runs);
        across_table(&mut doc, &found.across);
    }
    found.replicates = replicates;
    let md_path = out.join("report.md");
    std::fs::write(&md_path, &doc.md).map_err(|e| io_err(&md_path, e))?;
    let html = format!("<!doctype html><html><head><meta charset=\"utf-8\"><title>socialflow report</title><style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}table{{border-collapse:collapse;margin:1em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;font-size:13px}}img{{max-width:100%}}</style></head><body>{}</body></html>", doc.html);
    let html_path = out.join("report.html");
    std::fs::write(&html_path, html).map_err(|e| io_err(&html_path, e))?;
    Ok(found)
}

const FAMILY_NOTE: &str = "The family: every finding of this table, Holm-Bonferroni at a family-wise 5 %; the verdict is decided on the adjusted p. \"opposite\": significant the other way, the reverse of the claim shown (for a claim that needs several comparisons, every one goes the other way); \"refuted\": a claim that needs several comparisons (\"in each other scenario\", \"every other ego\", an intersection-union test) has one going the other way significantly, its p multiplied by the number of comparisons since it is the strongest of them, while the others do not all follow: the claim is false, its reverse is not shown. Effect: mean paired difference in points over stored cases, positive where the paper says it should be (for a refuted claim, the refuting comparison's). MDE: the smallest true effect this test detects with 80 % power at a two-sided 5 % (before the correction), from its standard error: a \"not significant\" with an MDE above the paper's effect says this grid cannot see it.";

/// One result set's findings: effect, raw and adjusted p, MDE, verdict.
fn findings_table(doc: &mut Doc, checks: &[Check]) {
    if checks.is_empty() {
        return;
    }
    doc.h(2, "The paper's findings at this budget");
    doc.p(FAMILY_NOTE);
    let head: Vec<String> =
        ["Finding", "Test", "Effect (points)", "p", "p (Holm)", "MDE (points)", "Verdict"]
            .map(String::from)
            .into();
    let table: Vec<Vec<String>> = checks
        .iter()
        .map(|c| {
            vec![
                c.claim.clone(),
                c.test.clone(),
                format!("{:+.1}", c.effect_points),
                fmt_p(c.p_value),
                fmt_p(c.p_adjusted),
                format!("{:.1}", c.mde_points()),
                c.verdict.as_str().into(),
            ]
        })
        .collect();
    doc.table(&head, &table);
}

/// The findings over several training runs: each run's own (Holm within the run), the runs'
/// estimates combined by random effects, and the verdict with the run as the unit.
fn across_table(doc: &mut Doc, across: &[AcrossRuns]) {
    let Some(k) = across.first().map(|a| a.runs.len()) else { return };
    doc.h(2, "The paper's findings across training runs");
    doc.p(&format!(
        "A claim about a method is a claim across training runs, so the verdict takes the run as the unit: \"holds in every run\" needs each run's own test to hold after its family's correction (an intersection-union rule, level 5 %); \"opposite in every run\": each run shows the reverse; \"refuted in every run\": each run is significant against the claim, not every one reversing it; \"runs conflict\": significant both ways; \"not replicated\": significant in some runs only. This rule is the verdict. Each run: effect, raw p, Holm-adjusted p within that run's findings, MDE. Pooled (descriptive, it decides no verdict): the runs' estimates combined by a DerSimonian-Laird random-effects model (between-run variance included) with a Hartung-Knapp-Sidik-Jonkman 95 % interval (Student t with {} degree(s) of freedom, the variance scaled by the runs' spread about the estimate, the scale floored at 1), and I² (the share of the variation that is between runs). The {k} runs were evaluated on the same stored cases (and the deterministic IDM episodes are the same in each), so their estimates are not independent: even this interval leaves their shared case-sampling error out. With {k} runs the between-run variance rests on {} degree(s) of freedom: a verdict from {k} runs is weak evidence; more training seeds are what would make it strong.",
        k.saturating_sub(1),
        k.saturating_sub(1)
    ));
    doc.p(FAMILY_NOTE);
    let mut head: Vec<String> = vec!["Finding".into()];
    head.extend((1..=k).map(|r| format!("Run {r}: effect, p (Holm), MDE")));
    head.extend(
        [
            "Verdict (runs as the unit)",
            "Pooled, descriptive: effect ± 95 % (HKSJ, t with k - 1 df), I²",
        ]
        .map(String::from),
    );
    let table: Vec<Vec<String>> = across
        .iter()
        .map(|a| {
            // A claim that quotes measured values differs between runs: its key names it.
            let claims: Vec<&String> = a.runs.iter().flatten().map(|c| &c.claim).collect();
            let claim = if claims.windows(2).all(|w| w[0] == w[1]) {
                claims.first().map(|c| c.to_string()).unwrap_or_else(|| a.key.clone())
            } else {
                a.key.clone()
            };
            let mut row = vec![claim];
            row.extend(a.runs.iter().map(|c| match c {
                Some(c) => format!(
                    "{:+.1}, {}, MDE {:.1}: {}",
                    c.effect_points,
                    p_holm(c.p_value, c.p_adjusted),
                    c.mde_points(),
                    c.verdict.as_str()
                ),
                None => "-".into(),
            }));
            row.push(a.verdict.as_str().into());
            row.push(match &a.combined {
                Some(re) => {
                    format!("{:+.1} ± {:.1}, I² {:.0} %", re.estimate, re.ci95, 100.0 * re.i2)
                }
                None => "-".into(),
            });
            row
        })
        .collect();
    doc.table(&head, &table);
}

/// Holm-adjusted p-values of one table's family, in the order of `ps` (`None`: no test).
fn holm_family(ps: &[Option<f64>]) -> Vec<Option<f64>> {
    let raw: Vec<f64> = ps.iter().map(|p| p.unwrap_or(f64::NAN)).collect();
    inference::holm(&raw).into_iter().zip(ps).map(|(a, p)| p.map(|_| a)).collect()
}

#[cfg(test)]
mod tests {
    use super::units::{paired, paired_across_flows};
    use super::*;
    use crate::plot::Mark;
    use sf_job::eval::{Cell, EvalEpisode};

    fn row(
        experiment: &str,
        ego: &str,
        flow: &str,
        case: u32,
        seed: u32,
        success: f32,
    ) -> EpisodeRow {
        EpisodeRow {
            cell: Cell {
                experiment: experiment.into(),
                ego: ego.into(),
                flow: flow.into(),
                scenario: "merge".into(),
                svo_deg: None,
                vehicles: None,
            },
            ep: EvalEpisode {
                case,
                seed,
                scores: sf_job::Scores { success, safety: success, speed: 0.5 },
                collision: 0.0,
                lane_change: None,
                road_closed: None,
            },
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
        let (xr, yr): (Vec<&EpisodeRow>, Vec<&EpisodeRow>) =
            (x.iter().collect(), y.iter().collect());
        let t = paired_across_flows(&xr, &yr, |r| r.ep.scores.success).expect("a test");
        assert_eq!(
            (t.t.n, t.starts),
            (20, 40),
            "one pair per ego and episode start, two starts per stored case"
        );
        assert!(t.t.mean_diff.abs() < 1e-12 && t.t.p_value > 0.9, "{t:?}");
        // Two egos on the same flow still pair across egos.
        let a: Vec<&EpisodeRow> = x.iter().filter(|r| r.cell.ego == "A").collect();
        let b: Vec<&EpisodeRow> = x.iter().filter(|r| r.cell.ego == "B").collect();
        let t = paired(&a, &b, |r| r.ep.scores.success).expect("a test");
        assert_eq!(t.t.n, 20);
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
        assert_eq!(
            (m[3][1], m[2][1], m[1][1], m[0][1]),
            (Mark::Gold, Mark::Silver, Mark::Copper, Mark::None)
        );
        // A baseline row is not ranked: the next ego takes its medal.
        let m = medals(&egos, &flows, &values, &trained, Some(&egos[3]));
        assert_eq!(
            (m[2][1], m[1][1], m[0][1], m[3][1]),
            (Mark::Gold, Mark::Silver, Mark::Copper, Mark::None)
        );
    }

    #[test]
    fn stars_follow_the_paper() {
        assert_eq!(
            (stars(1e-5), stars(5e-4), stars(5e-3), stars(0.03), stars(0.2)),
            ("****", "***", "**", "*", "n.s.")
        );
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
                for (flow, v) in [
                    ("SocialComm", 0.7),
                    ("SocialCommAdv", 0.6 - 0.1 * rep as f32),
                    ("FailMaker", 0.2),
                ] {
                    rows.push(row("adversary", "RL/IDM", flow, case, 0, v + jitter));
                }
            }
            rows
        };
        let meta = Meta {
            flows: vec![
                "CoPO".into(),
                "SocialComm".into(),
                "SocialCommAdv".into(),
                "FailMaker".into(),
            ],
            cases: 16,
            seeds: 1,
            ..Meta::default()
        };
        let out = std::env::temp_dir().join(format!("sf-report-replicates-{}", std::process::id()));
        let f = build_replicates(&[set(0), set(1)], &meta, &out).expect("report");
        let copo = f
            .checks
            .iter()
            .find(|c| {
                c.claim
                    == "SocialComm flow succeeds more often than CoPO (flow quality, all scenarios)"
            })
            .expect("flow check");
        assert_eq!(copo.n, 16, "the 16 stored cases, each averaged over both replicates");
        assert!(copo.holds() && (copo.effect_points - 11.0).abs() < 1.0, "{copo:?}");
        assert_eq!(f.replicates.len(), 2);
        for (k, r) in f.replicates.iter().enumerate() {
            assert_eq!(r.episodes, 16 * 5, "run {k}");
            assert!(
                out.join(format!("run-{}", k + 1)).join("report.md").exists(),
                "run {k}'s own report"
            );
        }
        let md = std::fs::read_to_string(out.join("report.md")).expect("md");
        assert!(
            md.contains("over 2 replicates")
                && md.contains("| Finding | Run 1: effect, p (Holm), MDE | Run 2: effect, p (Holm), MDE | Verdict (runs as the unit) | Pooled, descriptive: effect ± 95 % (HKSJ, t with k - 1 df), I² |")
                && md.contains("evaluated on the same stored cases"),
            "{md}"
        );
        let fm = md
            .lines()
            .find(|l| l.starts_with("| FailMaker degrades egos more"))
            .expect("adversary row");
        assert!(
            !fm.contains("| - |"),
            "each run's check is found by its key although its claim differs: {fm}"
        );
        assert!(fm.contains("| holds in every run |"), "both runs hold: {fm}");
        // Run 1 drops 10 points under SocialCommAdv, run 2 20: ratios 5 and 2.5, each with its interval.
        let run = |k: usize| {
            std::fs::read_to_string(out.join(format!("run-{k}")).join("report.md"))
                .expect("run report")
        };
        assert!(
            run(1).contains("drop ratio 5.0x") && run(2).contains("drop ratio 2.5x"),
            "{}",
            run(1)
        );
        assert_ne!(
            f.replicates[0]
                .checks
                .iter()
                .find(|c| c.key.starts_with("FailMaker"))
                .map(|c| &c.claim),
            f.replicates[1]
                .checks
                .iter()
                .find(|c| c.key.starts_with("FailMaker"))
                .map(|c| &c.claim)
        );
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
                    rows.push(row(
                        "cross",
                        "RARL/SocialCommAdv",
                        flow,
                        case,
                        seed,
                        0.8 + fb + noise,
                    ));
                    rows.push(row("cross", "RL/IDM", flow, case, seed, 0.3 + fb + noise));
                    rows.push(row(
                        "cross",
                        "RL/SocialComm",
                        flow,
                        case,
                        seed,
                        0.6 + fb + noise * 0.5,
                    ));
                    rows.push(row("cross", "IDM ego", flow, case, seed, 0.45 + fb + noise * 0.5));
                }
                rows.push(row("flow_quality", "", "SocialComm", case, seed, 0.7 + noise));
                rows.push(row("flow_quality", "", "CoPO", case, seed, 0.4 + noise));
                for (flow, v) in [("SocialComm", 0.7), ("SocialCommAdv", 0.6), ("FailMaker", 0.2)] {
                    rows.push(row("adversary", "RL/IDM", flow, case, seed, v + noise));
                }
                for svo in [0, 45, 90] {
                    for (flow, v) in [("CoPO", 0.4), ("SocialComm", 0.7)] {
                        rows.push(with_cell(
                            row("svo_sweep", "", flow, case, seed, v + noise),
                            |c| c.svo_deg = Some(svo),
                        ));
                    }
                }
                for n in [4, 8] {
                    rows.push(with_cell(
                        row("density", "", "SocialComm", case, seed, 0.9 - n as f32 * 0.05),
                        |c| c.vehicles = Some(n),
                    ));
                }
            }
        }
        let meta = Meta {
            trained_in: [
                ("RL/IDM".to_string(), "IDM".to_string()),
                ("RL/SocialComm".to_string(), "SocialComm".to_string()),
            ]
            .into(),
            ours: Some("RARL/SocialCommAdv".into()),
            flows: vec![
                "IDM".into(),
                "CoPO".into(),
                "SocialComm".into(),
                "SocialCommAdv".into(),
                "FailMaker".into(),
            ],
            egos: vec![
                "RL/IDM".into(),
                "RL/SocialComm".into(),
                "RARL/SocialCommAdv".into(),
                "IDM ego".into(),
            ],
            idm_ego: Some("IDM ego".into()),
            cases: 12,
            seeds: 2,
            sizes: BTreeMap::new(),
        };
        let out = std::env::temp_dir().join(format!("sf-report-{}", std::process::id()));
        let f = build(&rows, &meta, &out).expect("report");
        assert_eq!(f.experiments, ["flow_quality", "svo_sweep", "density", "adversary", "cross"]);
        let md = std::fs::read_to_string(out.join("report.md")).expect("md");
        assert!(!md.contains("Left its lane"), "no lane-change column where none was recorded");
        for needle in [
            "Cross-validation",
            "cross-success-merge.png",
            "zero-shot-success.png",
            "64.5 / 62.8 / 9.2",
            "svo-sweep-merge.png",
            "density.png",
        ] {
            assert!(md.contains(needle), "{needle} missing from the report");
        }
        let html = std::fs::read_to_string(out.join("report.html")).expect("html");
        assert!(
            !html.contains("data:") && html.contains("<img src=\"cross-success-merge.png\""),
            "figures are referenced by file name, not embedded"
        );
        for needle in ["cross-success-merge.png", "zero-shot-success.png", "density.png"] {
            assert!(out.join(needle).is_file(), "{needle} is written beside report.html");
        }
        let best = f
            .checks
            .iter()
            .find(|c| c.claim.starts_with("RARL/SocialCommAdv transfers best in merge"))
            .expect("a zero-shot check");
        assert!(
            best.holds() && best.p_value < 1e-4 && best.test.contains("decisive: vs RL/SocialComm"),
            "the nearer of the two others decides: {best:?}"
        );
        // FailMaker (0.2) degrades far more than SocialCommAdv (0.6) from SocialComm (0.7): a tested
        // finding with its direction, not a bare comparison of means.
        let fm = f
            .checks
            .iter()
            .find(|c| c.claim.starts_with("FailMaker degrades egos more"))
            .expect("the adversary check");
        assert!(fm.holds() && (fm.effect_points - 40.0).abs() < 1.0, "{fm:?}");
        assert!(
            md.contains("drop ratio 5.0x (95 % cluster-bootstrap interval")
                && md.contains("resampling 12 stored cases"),
            "a significant first drop gives a ratio with its interval"
        );
        let copo = f
            .checks
            .iter()
            .find(|c| {
                c.claim
                    == "SocialComm flow succeeds more often than CoPO (flow quality, all scenarios)"
            })
            .expect("flow check");
        assert!(copo.holds() && copo.test.starts_with("paired t"), "{copo:?}");
        assert!(
            md.contains(
                "| Finding | Test | Effect (points) | p | p (Holm) | MDE (points) | Verdict |"
            ),
            "the findings table names test, effect, raw and adjusted p"
        );
        // Against the IDM driver in the ego's seat: one check per trained ego, with its direction.
        let vs_idm = |e: &str| {
            f.checks
                .iter()
                .find(|c| {
                    c.claim.starts_with(&format!("{e} succeeds more often than the IDM driver"))
                })
                .unwrap_or_else(|| panic!("{e} vs the IDM ego"))
        };
        assert!(
            vs_idm("RL/SocialComm").holds()
                && (vs_idm("RL/SocialComm").effect_points - 15.0).abs() < 1e-3,
            "{:?}",
            vs_idm("RL/SocialComm")
        );
        assert_eq!(
            vs_idm("RL/IDM").verdict,
            crate::findings::Verdict::Opposite,
            "0.30 vs 0.45 on every start"
        );
        assert_eq!(
            f.checks.iter().filter(|c| c.claim.contains("than the IDM driver")).count(),
            3,
            "the IDM ego is not tested against itself"
        );
        assert!(!best.test.contains("IDM ego"), "ours is compared with trained egos only");
        assert!(
            md.contains("Trained egos against the IDM driver in their seat")
                && md.contains("| IDM ego | 49.4 | 49.4 |")
                && md.contains("(+15.0, p < 1e-15, Holm < 1e-15)"),
            "{md}"
        );
        let _ = std::fs::remove_dir_all(&out);
    }

    /// Rows of the flow-quality experiment in one scenario: SocialComm at `sc`, `other` at `o`,
    /// with a little per-case spread.
    fn flows_in(scenario: &str, sc: f32, other: &str, o: f32) -> Vec<EpisodeRow> {
        (0..30)
            .flat_map(|case| {
                let j = (case % 5) as f32 * 0.02;
                [
                    row("flow_quality", "", "SocialComm", case, 0, sc + j),
                    row("flow_quality", "", other, case, 0, o + j + (case % 3) as f32 * 0.01),
                ]
            })
            .map(|r| with_cell(r, |c| c.scenario = scenario.into()))
            .collect()
    }

    /// Flow-quality episodes that recorded the lane-change share get a column with its mean per
    /// flow and scenario (here 0.25 for SocialComm, 0 for CoPO).
    #[test]
    fn the_lane_change_share_is_tabled_where_recorded() {
        let meta = Meta {
            flows: vec!["CoPO".into(), "SocialComm".into()],
            cases: 30,
            seeds: 1,
            ..Meta::default()
        };
        let out = std::env::temp_dir().join(format!("sf-report-lanes-{}", std::process::id()));
        let rows: Vec<EpisodeRow> = flows_in("merge", 0.8, "CoPO", 0.5)
            .into_iter()
            .map(|mut r| {
                r.ep.lane_change = Some(if r.cell.flow == "SocialComm" { 0.25 } else { 0.0 });
                r
            })
            .collect();
        build(&rows, &meta, &out).expect("report");
        let md = std::fs::read_to_string(out.join("report.md")).expect("md");
        assert!(md.contains("| Left its lane |"), "{md}");
        let sc =
            md.lines().find(|l| l.starts_with("| SocialComm | merge |")).expect("SocialComm's row");
        assert!(sc.trim_end().ends_with("| 25.0 ± 0.0 |"), "{sc}");
        let _ = std::fs::remove_dir_all(&out);
    }

    /// "Larger in merge" is tested against each other scenario: a larger advantage in merge
    /// than in two scenarios but not in the third does not hold; larger than all three does.
    #[test]
    fn larger_in_merge_needs_every_other_scenario() {
        let meta = Meta {
            flows: vec!["CoPO".into(), "SocialComm".into()],
            cases: 30,
            seeds: 1,
            ..Meta::default()
        };
        let out = std::env::temp_dir().join(format!("sf-report-merge-{}", std::process::id()));
        let claim =
            "SocialComm's advantage over CoPO is larger in merge than in each other scenario";
        let mut rows = flows_in("merge", 0.8, "CoPO", 0.5);
        rows.extend(flows_in("intersection", 0.7, "CoPO", 0.6));
        rows.extend(flows_in("roundabout", 0.7, "CoPO", 0.6));
        let both = rows.clone();
        rows.extend(flows_in("bottleneck", 0.9, "CoPO", 0.4));
        let f = build(&rows, &meta, &out).expect("report");
        let c = f.checks.iter().find(|c| c.claim == claim).expect("the merge check");
        assert_eq!(
            c.verdict,
            crate::findings::Verdict::Refuted,
            "bottleneck's advantage is larger, intersection's and roundabout's smaller: refuted, not reversed: {c:?}"
        );
        assert!(
            c.test.contains("decisive: merge vs bottleneck")
                && c.test.starts_with("every one of 3 comparisons"),
            "{c:?}"
        );
        let mut rows = both;
        rows.extend(flows_in("bottleneck", 0.65, "CoPO", 0.6));
        let f = build(&rows, &meta, &out).expect("report");
        let c = f.checks.iter().find(|c| c.claim == claim).expect("the merge check");
        assert!(c.holds() && c.test.contains("Welch t"), "{c:?}");
        let md = std::fs::read_to_string(out.join("report.md")).expect("md");
        assert!(
            md.contains("except the \"larger in merge\" comparisons (Welch"),
            "the header says which tests are not paired"
        );
        let _ = std::fs::remove_dir_all(&out);
    }

    /// Without a significant drop under SocialCommAdv no ratio is printed, only both drops.
    #[test]
    fn no_ratio_over_a_drop_that_is_not_significant() {
        let mut rows = Vec::new();
        for case in 0..30 {
            let noise = if case % 2 == 0 { 0.05 } else { -0.05 };
            for (flow, v) in
                [("SocialComm", 0.7), ("SocialCommAdv", 0.7 + noise), ("FailMaker", 0.3)]
            {
                rows.push(row("adversary", "RL/IDM", flow, case, 0, v + (case % 4) as f32 * 0.03));
            }
        }
        let meta = Meta {
            flows: vec!["SocialComm".into(), "SocialCommAdv".into(), "FailMaker".into()],
            cases: 30,
            seeds: 1,
            ..Meta::default()
        };
        let out = std::env::temp_dir().join(format!("sf-report-ratio-{}", std::process::id()));
        build(&rows, &meta, &out).expect("report");
        let md = std::fs::read_to_string(out.join("report.md")).expect("md");
        assert!(
            md.contains("no drop ratio: the first drop is not significantly positive")
                && !md.contains("x (95 % cluster-bootstrap"),
            "{md}"
        );
        assert!(md.contains("under FailMaker +40.0 points"), "both drops are reported: {md}");
        assert!(
            md.contains("Power: SocialCommAdv's drop: this grid has 30 stored cases (30 starts;"),
            "{md}"
        );
        let _ = std::fs::remove_dir_all(&out);
    }
}
