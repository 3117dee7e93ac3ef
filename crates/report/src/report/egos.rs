//! The egos' experiments: adversary degradation, cross-validation heatmaps, zero-shot transfer
//! and the trained egos against the IDM driver in their seat, with the paper's ego findings
//! tested on them (over stored cases, [`super::units`]: the cross-validation's starts are a
//! case under 4 flows, the adversary's pooled starts a case under 4 egos).

use std::collections::BTreeMap;

use super::units::{case_columns, paired, paired_across_flows, summary, CaseTest};
use super::{
    by, fmt_p, holm_family, order, p_holm, p_is, paper_adversary, pct, stars, Ctx, Doc, Findings,
    ReportError, METRICS,
};
use crate::episodes::EpisodeRow;
use crate::findings::Check;
use crate::inference;
use crate::plot::{self, Bar, Mark};

/// Draws of the drop ratio's bootstrap, and its fixed seed (the report is reproducible).
const RATIO_DRAWS: usize = 4000;
const RATIO_SEED: u64 = 20261127;

/// Adversary degradation: egos trained in non-adversarial flows under each adversary.
pub(super) fn adversary(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let ad = by(rows, |r| r.cell.experiment == "adversary");
    if ad.is_empty() {
        return Ok(());
    }
    found.experiments.push("adversary".into());
    doc.h(2, "Effect of adversaries on egos trained in non-adversarial flows");
    let egos = order(ad.iter().map(|r| r.cell.ego.clone()), &meta.egos);
    let flows = order(ad.iter().map(|r| r.cell.flow.clone()), &meta.flows);
    let scen = order(ad.iter().map(|r| r.cell.scenario.clone()), &ctx.scen_pref);
    for (mname, m) in [METRICS[0], METRICS[2]] {
        let paper = paper_adversary(mname);
        let mut head = vec!["Ego".to_string(), "Scenario".into()];
        head.extend(flows.iter().cloned());
        head.push("p, second vs first flow (Holm over this table)".into());
        head.push("paper (SC / SCA / FM)".into());
        let mut table = Vec::new();
        let mut tests = Vec::new();
        for e in &egos {
            for s in &scen {
                let cell = |f: &String| {
                    by(rows, |r| {
                        r.cell.experiment == "adversary"
                            && &r.cell.ego == e
                            && &r.cell.flow == f
                            && &r.cell.scenario == s
                    })
                };
                let base = flows.first().map(|f| summary(&cell(f), m).mean).unwrap_or(f64::NAN);
                let mut row = vec![e.clone(), s.clone()];
                for (k, f) in flows.iter().enumerate() {
                    let v = summary(&cell(f), m);
                    row.push(if k == 0 {
                        pct(v)
                    } else {
                        format!("{} ({:+.1})", pct(v), 100.0 * (v.mean - base))
                    });
                }
                tests.push(if flows.len() >= 2 {
                    paired_across_flows(&cell(&flows[1]), &cell(&flows[0]), m).map(|t| t.t.p_value)
                } else {
                    None
                });
                row.push(String::new());
                row.push(
                    paper
                        .get(&(e.as_str(), s.as_str()))
                        .map(|v| format!("{:.1} / {:.1} / {:.1}", v[0], v[1], v[2]))
                        .unwrap_or_else(|| "-".into()),
                );
                table.push(row);
            }
        }
        for ((row, p), a) in table.iter_mut().zip(&tests).zip(holm_family(&tests)) {
            let at = row.len() - 2;
            row[at] = match (p, a) {
                (Some(p), Some(a)) => format!("{} {}", p_holm(*p, a), stars(a)),
                _ => "-".into(),
            };
        }
        doc.p(&format!("{mname} (percent; in parentheses the change from the first flow):"));
        doc.table(&head, &table);
    }
    if flows.len() >= 3 {
        adversary_findings(ctx, doc, found, &flows);
    }
    Ok(())
}

/// The paper's adversary findings: egos succeed less under the first adversary, the second
/// degrades them more; the ratio of the two drops with a bootstrap interval where it is defined;
/// what the grid can detect against the paper's effects.
fn adversary_findings(ctx: &Ctx, doc: &mut Doc, found: &mut Findings, flows: &[String]) {
    let success = METRICS[0].1;
    let pooled =
        |f: &String| by(ctx.rows, |r| r.cell.experiment == "adversary" && &r.cell.flow == f);
    let (base, first, second) = (pooled(&flows[0]), pooled(&flows[1]), pooled(&flows[2]));
    let mean = |rows: &[&EpisodeRow]| 100.0 * summary(rows, success).mean;
    let (sc, sca, fm) = (mean(&base), mean(&first), mean(&second));
    let first_drop = paired_across_flows(&base, &first, success);
    if let Some(t) = &first_drop {
        found.checks.push(Check::from_paired(
            format!("Egos succeed less in {} than in {} (pooled)", flows[1], flows[0]),
            &format!("success, {} - {}", flows[0], flows[1]),
            &t.t,
            t.starts,
        ));
    }
    if let Some(t) = paired_across_flows(&first, &second, success) {
        let claim = format!(
            "{} degrades egos more than {} (pooled success {} {sc:.1}, {} {sca:.1}, {} {fm:.1})",
            flows[2], flows[1], flows[0], flows[1], flows[2]
        );
        let key = format!("{} degrades egos more than {}", flows[2], flows[1]);
        found.checks.push(
            Check::from_paired(
                claim,
                &format!("success, {} - {}", flows[1], flows[2]),
                &t.t,
                t.starts,
            )
            .keyed(key),
        );
    }
    // The paper: FailMaker costs egos about ten times what SocialCommAdv costs them. A ratio is
    // only given where its denominator, the first drop, is significantly positive.
    let second_drop = paired_across_flows(&base, &second, success);
    let drop = |t: &Option<CaseTest>| {
        t.map(|t| {
            format!(
                "{:+.1} points (raw p {}, {} stored cases)",
                100.0 * t.t.mean_diff,
                fmt_p(t.t.p_value),
                t.t.n
            )
        })
        .unwrap_or_else(|| "-".into())
    };
    let denominator_holds =
        first_drop.is_some_and(|t| t.t.mean_diff > 0.0 && t.t.p_value < crate::findings::ALPHA);
    let units = case_columns([&base[..], &first[..], &second[..]], success);
    let ratio = match inference::bootstrap_ratio(&units, RATIO_DRAWS, RATIO_SEED) {
        Some(r) if denominator_holds => format!(
            "drop ratio {:.1}x (95 % cluster-bootstrap interval {:.1}x to {:.1}x, resampling {} stored cases, {} draws; the first drop is not positive in {:.0} % of draws)",
            r.ratio,
            r.lo,
            r.hi,
            units.len(),
            r.draws,
            100.0 * r.undefined_share
        ),
        _ => "no drop ratio: the first drop is not significantly positive, so a ratio over it would be noise".into(),
    };
    doc.p(&format!(
        "Drops from {} (pooled over egos and scenarios): under {} {}, under {} {}; {ratio}. The paper: 2.4 and 53.8 points.",
        flows[0],
        flows[1],
        drop(&first_drop),
        flows[2],
        drop(&second_drop)
    ));
    // Power: the stored cases a paired test of this grid's spread needs to see the paper's
    // effects.
    let paper = paper_adversary("Success");
    let paper_mean =
        |k: usize| paper.values().map(|v| v[k]).sum::<f64>() / paper.len().max(1) as f64;
    let lines: Vec<String> = [(&first_drop, paper_mean(0) - paper_mean(1), flows[1].as_str()), (&second_drop, paper_mean(0) - paper_mean(2), flows[2].as_str())]
        .iter()
        .filter_map(|(t, effect, name)| {
            let CaseTest { t, starts } = t.as_ref()?;
            let sd = 100.0 * t.se * (t.n as f64).sqrt();
            let need = inference::units_needed(*effect, sd)?;
            Some(format!(
                "{name}'s drop: this grid has {} stored cases ({starts} starts; minimum detectable effect {:.1} points at 80 % power); the paper's {effect:.1} points need about {need} stored cases at this spread (sd {sd:.1} points per case, its starts averaged)",
                t.n,
                inference::mde(100.0 * t.se, (t.n.max(2) - 1) as f64)
            ))
        })
        .collect();
    if !lines.is_empty() {
        doc.p(&format!("Power: {}.", lines.join("; ")));
    }
}

/// Cross-validation heatmaps and zero-shot bars; "ours" against every other trained ego.
pub(super) fn cross(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let cv = by(rows, |r| r.cell.experiment == "cross");
    if cv.is_empty() {
        return Ok(());
    }
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
                .map(|e| {
                    flows
                        .iter()
                        .map(|f| {
                            summary(
                                &by(rows, |r| {
                                    r.cell.experiment == "cross"
                                        && &r.cell.ego == e
                                        && &r.cell.flow == f
                                        && &r.cell.scenario == s
                                }),
                                m,
                            )
                            .mean
                        })
                        .collect()
                })
                .collect();
            let marks = medals(&egos, &flows, &values, &meta.trained_in, meta.idm_ego.as_ref());
            let file = format!("cross-{}-{s}.png", mname.to_lowercase());
            plot::heatmap(
                &ctx.out.join(&file),
                &format!("{mname}, {s}"),
                &egos,
                &flows,
                &values,
                &marks,
            )?;
            doc.figure(&file, &format!("Cross-validation {mname} in {s}"))?;
        }
    }
    zero_shot(ctx, doc, found, &egos, &scen)?;
    if let Some(idm) = meta.idm_ego.as_ref().filter(|e| egos.contains(e)) {
        against_idm_ego(ctx, doc, found, idm, &egos, &scen);
    }
    Ok(())
}

/// Zero-shot bars: each ego pooled over the evaluation flows, per scenario; ours against every
/// other trained ego (one family per metric), and "ours transfers best" as the claim that it
/// beats each of them.
fn zero_shot(
    ctx: &Ctx,
    doc: &mut Doc,
    found: &mut Findings,
    egos: &[String],
    scen: &[String],
) -> Result<(), ReportError> {
    let meta = ctx.meta;
    doc.h(2, "Zero-shot transfer");
    for (mname, m) in [METRICS[0], METRICS[2]] {
        let mut groups = Vec::new();
        // (scenario, other ego, test) for every comparison of ours.
        let mut tests = Vec::new();
        for s in scen {
            let pooled = |e: &String| {
                by(ctx.rows, |r| {
                    r.cell.experiment == "cross" && &r.cell.ego == e && &r.cell.scenario == s
                })
            };
            groups.push(
                egos.iter()
                    .map(|e| {
                        let v = summary(&pooled(e), m);
                        Bar { mean: v.mean, ci95: v.ci95, stars: String::new() }
                    })
                    .collect::<Vec<Bar>>(),
            );
            if let Some(ours) = meta.ours.as_ref().filter(|o| egos.contains(o)) {
                // Among the trained egos: the IDM driver has its own section below.
                for e in egos.iter().filter(|e| *e != ours && Some(*e) != meta.idm_ego.as_ref()) {
                    if let Some(t) = paired(&pooled(ours), &pooled(e), m) {
                        tests.push((s.clone(), e.clone(), t));
                    }
                }
            }
        }
        let adj = holm_family(&tests.iter().map(|(_, _, t)| Some(t.t.p_value)).collect::<Vec<_>>());
        let mut lines = Vec::new();
        for ((s, e, t), a) in tests.iter().zip(&adj) {
            let a = a.unwrap_or(f64::NAN);
            let (si, k) = (
                scen.iter().position(|x| x == s).unwrap_or(0),
                egos.iter().position(|x| x == e).unwrap_or(0),
            );
            groups[si][k].stars = stars(a).to_string();
            lines.push(format!(
                "{s}: ours - {e} {mname} = {:+.1} points ({} stored cases from {} (flow, case) starts), p {} {}",
                100.0 * t.t.mean_diff,
                t.t.n,
                t.starts,
                p_holm(t.t.p_value, a),
                stars(a)
            ));
        }
        if let (Some(ours), "Success") = (meta.ours.as_ref(), mname) {
            for s in scen {
                let parts: Vec<(String, Check)> = tests
                    .iter()
                    .filter(|(ts, _, _)| ts == s)
                    .map(|(_, e, t)| {
                        (
                            format!("vs {e}"),
                            Check::from_paired(
                                "",
                                &format!("success, {ours} - {e}, pooled over evaluation flows"),
                                &t.t,
                                t.starts,
                            ),
                        )
                    })
                    .collect();
                if let Some(c) = Check::all_of(
                    format!("{ours} transfers best in {s} (success above every other trained ego)"),
                    &parts,
                ) {
                    found.checks.push(c);
                }
            }
        }
        let file = format!("zero-shot-{}.png", mname.to_lowercase());
        plot::grouped_bars(
            &ctx.out.join(&file),
            &format!("Zero-shot {mname} (pooled over evaluation flows)"),
            &mname.to_lowercase(),
            scen,
            egos,
            &groups,
        )?;
        doc.figure(&file, &format!("{mname} of each ego pooled over the evaluation flows, 95 % intervals over stored cases; stars: paired t-test over stored cases of ours against each other trained ego, Holm over the figure's tests"))?;
        for l in lines {
            doc.p(&l);
        }
    }
    Ok(())
}

/// Every trained ego against the IDM driver in its seat, on the same cross-validation episode
/// starts (flow, scenario, case, seed): per scenario and pooled, with one check per ego.
fn against_idm_ego(
    ctx: &Ctx,
    doc: &mut Doc,
    found: &mut Findings,
    idm: &String,
    egos: &[String],
    scen: &[String],
) {
    let success = METRICS[0].1;
    let cells = |e: &String, s: Option<&String>| {
        by(ctx.rows, |r| {
            r.cell.experiment == "cross"
                && &r.cell.ego == e
                && s.is_none_or(|s| &r.cell.scenario == s)
        })
    };
    doc.h(2, "Trained egos against the IDM driver in their seat");
    doc.p(&format!(
        "Success in percent over the cross-validation cells (every evaluation flow); in brackets the paired difference to `{idm}` (the IDM driver, the zero residual every trained ego starts from) on the same episode starts, tested over stored cases (a case's flows averaged), its p-value and the Holm-adjusted p over this table's tests. The last column pools every scenario."
    ));
    let mut head = vec!["Ego".to_string()];
    head.extend(scen.iter().cloned());
    head.push("all scenarios".into());
    let scopes: Vec<Option<&String>> = scen.iter().map(Some).chain([None]).collect();
    let mean = |rows: &[&EpisodeRow]| {
        if rows.is_empty() {
            "-".to_string()
        } else {
            format!("{:.1}", 100.0 * summary(rows, success).mean)
        }
    };
    let mut table = vec![std::iter::once(idm.clone())
        .chain(scopes.iter().map(|s| mean(&cells(idm, *s))))
        .collect::<Vec<_>>()];
    // (row, column, test) of every cell, corrected together.
    let mut tests = Vec::new();
    for e in egos.iter().filter(|e| *e != idm) {
        let mut line = vec![e.clone()];
        for s in &scopes {
            let (a, b) = (cells(e, *s), cells(idm, *s));
            line.push(mean(&a));
            if let Some(t) = paired(&a, &b, success) {
                tests.push((table.len(), line.len() - 1, t));
                if s.is_none() {
                    found.checks.push(Check::from_paired(
                        format!("{e} succeeds more often than the IDM driver in its seat (cross-validation, all flows and scenarios)"),
                        &format!("success, {e} - {idm}"),
                        &t.t,
                        t.starts,
                    ));
                }
            }
        }
        table.push(line);
    }
    let adj = holm_family(&tests.iter().map(|(_, _, t)| Some(t.t.p_value)).collect::<Vec<_>>());
    for ((r, c, t), a) in tests.iter().zip(adj) {
        let a = a.unwrap_or(f64::NAN);
        table[*r][*c] = format!(
            "{} ({:+.1}, p {}, Holm {})",
            table[*r][*c],
            100.0 * t.t.mean_diff,
            p_is(t.t.p_value),
            fmt_p(a)
        );
    }
    doc.table(&head, &table);
}

/// Grey for an ego's own training flow; gold, silver, copper for the best three of each column,
/// `unranked` (a baseline) left out of the ranking.
pub fn medals(
    egos: &[String],
    flows: &[String],
    values: &[Vec<f64>],
    trained_in: &BTreeMap<String, String>,
    unranked: Option<&String>,
) -> Vec<Vec<Mark>> {
    let mut marks = vec![vec![Mark::None; flows.len()]; egos.len()];
    for (c, f) in flows.iter().enumerate() {
        let mut ranked: Vec<(usize, f64)> = Vec::new();
        for (r, e) in egos.iter().enumerate() {
            if trained_in.get(e) == Some(f) {
                marks[r][c] = Mark::Diagonal;
            } else if Some(e) == unranked {
                // A baseline (the IDM driver in the ego's seat) is shown, not ranked.
            } else if let Some(v) =
                values.get(r).and_then(|row| row.get(c)).filter(|v| v.is_finite())
            {
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
