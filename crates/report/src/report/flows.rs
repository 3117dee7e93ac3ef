//! The flows' experiments: flow quality (tables, radar charts), the SVO sweep and the density
//! sweep, and the paper's flow findings tested on them (over stored cases, [`super::units`]).

use std::collections::BTreeSet;

use super::units::{case_diffs, paired_across_flows, summary};
use super::{by, holm_family, order, pct, stars, Ctx, Doc, Findings, ReportError, METRICS};
use crate::findings::Check;
use crate::plot::{self, Series};

/// Flow quality: a table and a radar chart per scenario; SocialComm against every other flow.
pub(super) fn flow_quality(
    ctx: &Ctx,
    doc: &mut Doc,
    found: &mut Findings,
) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let fq = by(rows, |r| r.cell.experiment == "flow_quality");
    if !fq.is_empty() {
        found.experiments.push("flow_quality".into());
        doc.h(2, "Flow quality (every vehicle driven by the flow)");
        let flows = order(fq.iter().map(|r| r.cell.flow.clone()), &meta.flows);
        let scen = order(fq.iter().map(|r| r.cell.scenario.clone()), &ctx.scen_pref);
        let mut head = vec!["Flow".to_string(), "Scenario".into()];
        head.extend(METRICS.iter().map(|(n, _)| n.to_string()));
        // The lane-change share, where every flow-quality episode recorded it (results written
        // since 2026-11-28): the vehicles that can steer show here whether they leave their lane.
        let lane_change = fq.iter().all(|r| r.ep.lane_change.is_some());
        if lane_change {
            head.push("Left its lane".into());
        }
        let mut table = Vec::new();
        for f in &flows {
            for s in &scen {
                let cell = by(rows, |r| {
                    r.cell.experiment == "flow_quality"
                        && &r.cell.flow == f
                        && &r.cell.scenario == s
                });
                let mut row = vec![f.clone(), s.clone()];
                row.extend(METRICS.iter().map(|(_, m)| pct(summary(&cell, *m))));
                if lane_change {
                    row.push(pct(summary(&cell, |r| r.ep.lane_change.unwrap_or(0.0))));
                }
                table.push(row);
            }
        }
        doc.table(&head, &table);
        if lane_change {
            doc.p("*Left its lane*: the share of the flow's vehicles that left their route's lane at some point in the episode (a lane change, a cut-in or drifting out of it), mean with its 95 % CI over stored cases.");
        }
        for s in &scen {
            let series: Vec<(String, Vec<(f64, f64)>)> = flows
                .iter()
                .map(|f| {
                    let cell = by(rows, |r| {
                        r.cell.experiment == "flow_quality"
                            && &r.cell.flow == f
                            && &r.cell.scenario == s
                    });
                    (
                        f.clone(),
                        METRICS
                            .iter()
                            .enumerate()
                            .map(|(k, (_, m))| (k as f64, summary(&cell, *m).mean))
                            .collect(),
                    )
                })
                .collect();
            let file = format!("flow-quality-{s}.png");
            let ser: Vec<Series> =
                series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
            plot::radar(
                &ctx.out.join(&file),
                &format!("Flow quality, {s}"),
                &METRICS.iter().map(|(n, _)| n.to_string()).collect::<Vec<_>>(),
                &ser,
            )?;
            doc.figure(
                &file,
                &format!("Success, Safety and Speed of each flow in {s} (radar; 1 = 100 %)"),
            )?;
        }
        // The paper: SocialComm beats CoPO, MACAD and IDM as a flow, most in dense merge.
        if flows.iter().any(|f| f == "SocialComm") {
            // A flow's rows, in merge (`Some(true)`) or everywhere.
            let fq = |flow: &str, merge: Option<bool>| {
                by(rows, |r| {
                    r.cell.experiment == "flow_quality"
                        && r.cell.flow == flow
                        && merge.is_none_or(|m| (r.cell.scenario == "merge") == m)
                })
            };
            for other in flows.iter().filter(|f| *f != "SocialComm") {
                if let Some(t) =
                    paired_across_flows(&fq("SocialComm", None), &fq(other, None), |r| {
                        r.ep.scores.success
                    })
                {
                    found.checks.push(Check::from_paired(format!("SocialComm flow succeeds more often than {other} (flow quality, all scenarios)"), &format!("success, SocialComm - {other}"), &t.t, t.starts));
                }
                let (sc_merge, other_merge) = (fq("SocialComm", Some(true)), fq(other, Some(true)));
                if let Some(t) =
                    paired_across_flows(&sc_merge, &other_merge, |r| r.ep.scores.success)
                {
                    found.checks.push(Check::from_paired(
                        format!("SocialComm flow succeeds more often than {other} in merge"),
                        &format!("success, SocialComm - {other}"),
                        &t.t,
                        t.starts,
                    ));
                }
                // "Most in dense merge": SocialComm's per-case advantage in merge against its
                // advantage in each other scenario (their stored cases are different, so
                // Welch's test); the claim needs every one (intersection-union).
                let in_merge = case_diffs(&sc_merge, &other_merge, |r| r.ep.scores.success, false);
                let parts: Vec<(String, Check)> = scen
                    .iter()
                    .filter(|s| *s != "merge")
                    .filter_map(|s| {
                        let in_s = |f: &str| by(rows, |r| r.cell.experiment == "flow_quality" && r.cell.flow == f && &r.cell.scenario == s);
                        let there = case_diffs(&in_s("SocialComm"), &in_s(other), |r| r.ep.scores.success, false);
                        let w = crate::stats::welch_t_test(&in_merge.values, &there.values).ok()?;
                        Some((format!("merge vs {s}"), Check::from_welch("", &format!("success difference SocialComm - {other} per case, merge vs {s}"), &w, in_merge.starts + there.starts)))
                    })
                    .collect();
                if let Some(c) = Check::all_of(format!("SocialComm's advantage over {other} is larger in merge than in each other scenario"), &parts) {
                    found.checks.push(c);
                }
            }
        }
    }
    Ok(())
}

/// The SVO sweep: success against SVO per scenario; SocialComm against the other flow.
pub(super) fn svo_sweep(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
    let (rows, meta) = (ctx.rows, ctx.meta);
    let sw = by(rows, |r| r.cell.experiment == "svo_sweep");
    if !sw.is_empty() {
        found.experiments.push("svo_sweep".into());
        doc.h(2, "SVO sweep (all agents share one SVO)");
        let flows = order(sw.iter().map(|r| r.cell.flow.clone()), &meta.flows);
        let scen = order(sw.iter().map(|r| r.cell.scenario.clone()), &ctx.scen_pref);
        let mut tests = Vec::new();
        for s in &scen {
            let series: Vec<(String, Vec<(f64, f64)>)> = flows
                .iter()
                .map(|f| {
                    let svos: BTreeSet<u32> = sw
                        .iter()
                        .filter(|r| &r.cell.flow == f && &r.cell.scenario == s)
                        .filter_map(|r| r.cell.svo_deg)
                        .collect();
                    (
                        f.clone(),
                        svos.into_iter()
                            .map(|v| {
                                (
                                    v as f64,
                                    summary(
                                        &by(rows, |r| {
                                            r.cell.experiment == "svo_sweep"
                                                && &r.cell.flow == f
                                                && &r.cell.scenario == s
                                                && r.cell.svo_deg == Some(v)
                                        }),
                                        |r| r.ep.scores.success,
                                    )
                                    .mean,
                                )
                            })
                            .collect(),
                    )
                })
                .collect();
            let file = format!("svo-sweep-{s}.png");
            let ser: Vec<Series> =
                series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
            plot::line_chart(
                &ctx.out.join(&file),
                &format!("Success vs SVO, {s}"),
                "SVO (deg)",
                "success",
                &ser,
                Some((0.0, 1.0)),
                (640, 400),
            )?;
            doc.figure(
                &file,
                &format!("Flow success rate when every agent has the same SVO, {s}"),
            )?;
            if flows.len() == 2 {
                let a = by(rows, |r| {
                    r.cell.experiment == "svo_sweep"
                        && r.cell.flow == flows[1]
                        && &r.cell.scenario == s
                });
                let b = by(rows, |r| {
                    r.cell.experiment == "svo_sweep"
                        && r.cell.flow == flows[0]
                        && &r.cell.scenario == s
                });
                if let Some(t) = paired_across_flows(&a, &b, |r| r.ep.scores.success) {
                    tests.push((s.clone(), t));
                }
            }
        }
        // One family: the sweep's scenarios.
        let adj = holm_family(&tests.iter().map(|(_, t)| Some(t.t.p_value)).collect::<Vec<_>>());
        for ((s, t), a) in tests.iter().zip(adj) {
            let a = a.unwrap_or(f64::NAN);
            doc.p(&format!(
                "{s}: {} - {} success = {:+.1} points over all SVOs ({} stored cases from {} starts, a case's SVOs averaged), p = {} {}",
                flows[1],
                flows[0],
                100.0 * t.t.mean_diff,
                t.t.n,
                t.starts,
                super::p_holm(t.t.p_value, a),
                stars(a)
            ));
            if flows[1] == "SocialComm" {
                found.checks.push(Check::from_paired(
                    format!("SocialComm beats {} over the SVO sweep in {s}", flows[0]),
                    &format!("success, SocialComm - {}", flows[0]),
                    &t.t,
                    t.starts,
                ));
            }
        }
    }
    Ok(())
}

/// The density sweep: success against vehicles per case.
pub(super) fn density(ctx: &Ctx, doc: &mut Doc, found: &mut Findings) -> Result<(), ReportError> {
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
                let ns: BTreeSet<usize> = de
                    .iter()
                    .filter(|r| &r.cell.flow == f)
                    .filter_map(|r| r.cell.vehicles)
                    .collect();
                (
                    f.clone(),
                    ns.into_iter()
                        .map(|n| {
                            (
                                n as f64,
                                summary(
                                    &by(rows, |r| {
                                        r.cell.experiment == "density"
                                            && &r.cell.flow == f
                                            && r.cell.vehicles == Some(n)
                                    }),
                                    |r| r.ep.scores.success,
                                )
                                .mean,
                            )
                        })
                        .collect(),
                )
            })
            .collect();
        let ser: Vec<Series> =
            series.iter().map(|(n, p)| Series { name: n, points: p.clone() }).collect();
        plot::line_chart(
            &ctx.out.join("density.png"),
            &format!("Success vs vehicles, {scen}"),
            "vehicles per case",
            "success",
            &ser,
            Some((0.0, 1.0)),
            (640, 400),
        )?;
        doc.figure("density.png", &format!("Flow success rate by number of vehicles in {scen}"))?;
        let mut table = Vec::new();
        for (f, pts) in &series {
            table.push(
                std::iter::once(f.clone())
                    .chain(pts.iter().map(|(n, v)| format!("{n}: {:.1}", 100.0 * v)))
                    .collect(),
            );
        }
        let width = table.iter().map(Vec::len).max().unwrap_or(1);
        let head: Vec<String> = std::iter::once("Flow".to_string())
            .chain((1..width).map(|k| format!("density {k}")))
            .collect();
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
