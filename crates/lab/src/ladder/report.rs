//! The rung's report: per-seed summaries (paired policy-vs-IDM statistics, the curve checks of
//! the gate), `summary.md`, and the curve and validation charts. Must not: train or evaluate
//! (the parent module does, and hands over the rows and curves).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Context, Result};
use sf_report::plot::{line_chart, Series};

use super::{Gate, Row, Rung, SeedSummary};

pub(super) fn mean(xs: impl Iterator<Item = f32>) -> f64 {
    let (s, n) = xs.fold((0.0, 0usize), |(s, n), x| (s + x as f64, n + 1));
    if n == 0 {
        0.0
    } else {
        s / n as f64
    }
}

pub(super) fn summarise(
    train_seed: u64,
    dir: &Path,
    rows: &[Row],
    g: &Gate,
    updates: u64,
    wall_s: f64,
    judged: &str,
) -> Result<SeedSummary> {
    // `judged`: the driver whose rows the gate judges against the IDM ego's (`policy`, or a
    // scripted driver's name).
    let pol: Vec<&Row> = rows.iter().filter(|r| r.driver == judged).collect();
    let idm: Vec<&Row> = rows.iter().filter(|r| r.driver == "idm").collect();
    let (cases, p_value) = paired_by_case(&pol, &idm);
    let mut per_scenario = BTreeMap::new();
    for s in pol.iter().map(|r| r.scenario.clone()).collect::<std::collections::BTreeSet<_>>() {
        let m = |v: &[&Row]| mean(v.iter().filter(|r| r.scenario == s).map(|r| r.success));
        let v = [m(&pol), m(&idm)];
        per_scenario.insert(s, v);
    }
    let mut s = SeedSummary {
        train_seed,
        job_dir: dir.display().to_string(),
        episodes: pol.len(),
        cases,
        success: mean(pol.iter().map(|r| r.success)),
        idm_success: mean(idm.iter().map(|r| r.success)),
        collision: mean(pol.iter().map(|r| r.collision)),
        idm_collision: mean(idm.iter().map(|r| r.collision)),
        other_failures: mean(pol.iter().map(|r| r.other_failure)),
        speed: mean(pol.iter().map(|r| r.speed)),
        idm_speed: mean(idm.iter().map(|r| r.speed)),
        lane_change: mean(pol.iter().map(|r| r.lane_change)),
        p_value,
        per_scenario,
        updates,
        selected_updates: None,
        wall_s,
        passed: true,
        failed_checks: Vec::new(),
    };
    let mut fail = |ok: bool, what: String| {
        if !ok {
            s.failed_checks.push(what);
        }
    };
    if let Some(v) = g.min_success {
        fail(s.success >= v, format!("success {:.3} < {v}", s.success));
    }
    if let Some(v) = g.min_success_gain {
        fail(
            s.success - s.idm_success >= v,
            format!("success gain over IDM {:+.3} < {v}", s.success - s.idm_success),
        );
    }
    if let Some(v) = g.min_collision_drop {
        fail(
            s.idm_collision - s.collision >= v,
            format!("collision drop {:+.3} < {v}", s.idm_collision - s.collision),
        );
    }
    if let Some(v) = g.max_other_failures {
        fail(s.other_failures <= v, format!("other failures {:.3} > {v}", s.other_failures));
    }
    if let Some(v) = g.max_p {
        fail(
            s.p_value <= v && s.success > s.idm_success,
            format!(
                "p = {:.3e} (policy {:.3} vs IDM {:.3}), need p <= {v} in the policy's favour",
                s.p_value, s.success, s.idm_success
            ),
        );
    }
    if let Some(v) = g.min_speed_gain {
        let gain = if s.idm_speed > 0.0 { s.speed / s.idm_speed - 1.0 } else { f64::INFINITY };
        fail(
            gain >= v,
            format!(
                "speed {:.3} is {:+.1} % of the IDM ego's {:.3}, need {:+.0} %",
                s.speed,
                100.0 * gain,
                s.idm_speed,
                100.0 * v
            ),
        );
    }
    if let Some(v) = g.min_lane_change {
        fail(s.lane_change >= v, format!("lane change in {:.3} of episodes < {v}", s.lane_change));
    }
    s.passed = s.failed_checks.is_empty();
    Ok(s)
}

/// The paired test of `a`'s success against `b`'s with the stored case as the unit: each
/// (scenario, case)'s success averaged over its evaluation seeds for either driver, then a
/// paired t-test over the cases both drove. A deterministic driver gives the same episode under
/// every seed, and a second seed of it is not a second observation: counted per episode it
/// would halve the variance's denominator. Returns the number of cases and the two-sided p (1
/// when the two never differ, so there is nothing to test).
pub(super) fn paired_by_case(a: &[&Row], b: &[&Row]) -> (usize, f64) {
    fn by_case<'r>(rows: &[&'r Row]) -> BTreeMap<(&'r str, u32), f64> {
        let mut m: BTreeMap<(&str, u32), (f64, usize)> = BTreeMap::new();
        for r in rows {
            let e = m.entry((r.scenario.as_str(), r.case)).or_default();
            *e = (e.0 + r.success as f64, e.1 + 1);
        }
        m.into_iter().map(|(k, (s, n))| (k, s / n as f64)).collect()
    }
    let (ma, mb) = (by_case(a), by_case(b));
    let (xs, ys): (Vec<f64>, Vec<f64>) =
        ma.iter().filter_map(|(k, &x)| mb.get(k).map(|&y| (x, y))).unzip();
    let p = match sf_report::stats::paired_t_test(&xs, &ys) {
        Ok(t) => t.p_value,
        // Identical outcomes everywhere: no difference to test.
        Err(_) => 1.0,
    };
    (xs.len(), p)
}

/// The update at which a job's final policy was selected by its validation (`policy.json`),
/// `None` when the final policy is the last actor.
pub(super) fn selected_updates(dir: &Path) -> Result<Option<u64>> {
    let path = dir.join("policy.json");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| path.display().to_string())?;
    Ok(v.get("selected_by")
        .and_then(|b| (b == "validation").then(|| v.get("updates")?.as_u64()))
        .flatten())
}

/// The gate's checks on the training curve.
pub(super) fn check_curve(s: &mut SeedSummary, g: &Gate, curve: &[CurvePt], window: usize) {
    let learner: Vec<&CurvePt> = learner_points(curve, window).collect();
    if let Some(v) = g.curve_min_success {
        let after: Vec<f64> =
            learner.iter().filter(|p| p[0] >= g.curve_from_updates as f64).map(|p| p[1]).collect();
        let low = after.iter().copied().fold(f64::INFINITY, f64::min);
        if after.is_empty() || low < v {
            s.failed_checks.push(format!(
                "curve success from {} updates on: min {:.3} < {v}",
                g.curve_from_updates,
                if after.is_empty() { 0.0 } else { low }
            ));
        }
    }
    if let Some(v) = g.curve_reach_success {
        if !learner.iter().any(|p| p[0] <= g.curve_reach_updates as f64 && p[1] >= v) {
            s.failed_checks.push(format!(
                "curve success never reached {v} within {} updates",
                g.curve_reach_updates
            ));
        }
    }
    s.passed = s.failed_checks.is_empty();
}

/// The curve points whose rolling window (the job's last `window` episodes) holds only
/// episodes driven by the learned policy: after the first update, and at least `window`
/// episodes after the warm-up's last point. Before that the window holds the warm-up's
/// episodes, which an IDM warm-up's demonstrator drove, not the policy.
pub(super) fn learner_points(curve: &[CurvePt], window: usize) -> impl Iterator<Item = &CurvePt> {
    let warmup_episodes = curve.iter().filter(|p| p[0] == 0.0).map(|p| p[3]).fold(0.0, f64::max);
    curve.iter().filter(move |p| p[0] > 0.0 && p[3] >= warmup_episodes + window as f64)
}

pub(super) fn summary_md(r: &Rung, seeds: &[SeedSummary], passed: bool) -> String {
    let mut m = String::new();
    let _ = writeln!(
        m,
        "## {} `{}`: {}\n",
        r.rung,
        r.name,
        if passed { "PASSED" } else { "NOT PASSED" }
    );
    if r.eval.sampled {
        let _ = writeln!(
            m,
            "The policies drove their sampled actions (`eval.sampled`), not their mean action.\n"
        );
    }
    let _ = writeln!(m, "| seed | updates | success | IDM ego | collision | IDM coll. | other fail. | speed | IDM speed | lane change | p (paired by case) | gate |");
    let _ = writeln!(m, "|---|---|---|---|---|---|---|---|---|---|---|---|");
    for s in seeds {
        let _ = writeln!(
            m,
            "| {} | {}{} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {} | {} |",
            s.train_seed,
            s.updates,
            s.selected_updates.map(|u| format!(" (policy of {u})")).unwrap_or_default(),
            s.success,
            s.idm_success,
            s.collision,
            s.idm_collision,
            s.other_failures,
            s.speed,
            s.idm_speed,
            s.lane_change,
            sf_report::report::fmt_p(s.p_value),
            if s.passed { "pass".to_string() } else { s.failed_checks.join("; ") }
        );
    }
    if let Some(s) = seeds.first() {
        let _ = writeln!(
            m,
            "\n{} episodes per seed over {} cases: the rung's evaluation cases, apart from the validation cases that kept each actor (they chose nothing); p is a paired t-test over the cases (each case's success averaged over its evaluation seeds).",
            s.episodes, s.cases
        );
    }
    let _ = writeln!(m, "\nPer scenario, success policy / IDM ego:\n");
    for s in seeds {
        let per: Vec<String> =
            s.per_scenario.iter().map(|(k, [p, i])| format!("{k} {p:.3} / {i:.3}")).collect();
        let _ = writeln!(m, "- seed {}: {}", s.train_seed, per.join(", "));
    }
    m
}

/// One curve point as the ladder reads it: `[updates, rolling success, wall_s, episodes]`.
pub(super) type CurvePt = [f64; 4];

/// A job's `curve.csv`, read by column name.
pub(super) fn read_curve(path: &Path) -> Result<Vec<CurvePt>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let (idx, lines) = columns(path, &text, ["updates", "success", "wall_s", "episodes"])?;
    let mut out = Vec::new();
    for (i, l) in lines.enumerate() {
        let f: Vec<&str> = l.split(',').collect();
        let mut p = [0.0; 4];
        for (k, &c) in idx.iter().enumerate() {
            p[k] = f
                .get(c)
                .and_then(|v| v.parse().ok())
                .with_context(|| format!("{} line {}: column {c}", path.display(), i + 2))?;
        }
        out.push(p);
    }
    Ok(out)
}

/// The positions of `names` in the header of a CSV file's `text`, and the rows after it.
pub(super) fn columns<'t, const N: usize>(
    path: &Path,
    text: &'t str,
    names: [&str; N],
) -> Result<([usize; N], std::str::Lines<'t>)> {
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let mut idx = [0; N];
    for (i, name) in idx.iter_mut().zip(names) {
        *i = header
            .iter()
            .position(|h| *h == name)
            .with_context(|| format!("{}: no column `{name}`", path.display()))?;
    }
    Ok((idx, lines))
}

/// Rolling success against updates, one line per seed.
/// `validation.png`: every seed's held-out success against updates (jobs with `[validation]`;
/// nothing is drawn when no seed has a `validation.csv`).
pub(super) fn plot_validation(out: &Path, r: &Rung, seeds: &[SeedSummary]) -> Result<()> {
    let mut series = Vec::new();
    for s in seeds {
        let path = out.join(format!("seed-{}", s.train_seed)).join("validation.csv");
        if !path.exists() {
            continue;
        }
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {}", path.display()))?;
        let ([u, v], lines) = columns(&path, &text, ["updates", "success"])?;
        let points = lines
            .map(|l| {
                let f: Vec<&str> = l.split(',').collect();
                let num = |i: usize| {
                    f.get(i)
                        .and_then(|x| x.parse::<f64>().ok())
                        .with_context(|| format!("{}: bad row `{l}`", path.display()))
                };
                Ok((num(u)?, num(v)?))
            })
            .collect::<Result<Vec<_>>>()?;
        series.push((format!("seed {}", s.train_seed), points));
    }
    if series.is_empty() {
        return Ok(());
    }
    let series: Vec<Series> =
        series.iter().map(|(name, points)| Series { name, points: points.clone() }).collect();
    seed_chart(
        out,
        "validation.png",
        &format!("{} {}: held-out success (mean action)", r.rung, r.name),
        "validation success",
        &series,
    )
}

/// One line per training seed against updates, y in [0, 1], as `<out>/<file>`.
pub(super) fn seed_chart(
    out: &Path,
    file: &str,
    title: &str,
    y_label: &str,
    series: &[Series],
) -> Result<()> {
    line_chart(&out.join(file), title, "updates", y_label, series, Some((0.0, 1.0)), (800, 500))
        .map_err(|e| anyhow::anyhow!("drawing {file}: {e}"))
}

pub(super) fn plot_curves(out: &Path, r: &Rung, curves: &[(u64, Vec<CurvePt>)]) -> Result<()> {
    let names: Vec<String> = curves.iter().map(|(s, _)| format!("seed {s}")).collect();
    let series: Vec<Series> = curves
        .iter()
        .zip(&names)
        .map(|((_, c), name)| Series { name, points: c.iter().map(|p| (p[0], p[1])).collect() })
        .collect();
    seed_chart(
        out,
        "success.png",
        &format!("{} {}: rolling success", r.rung, r.name),
        "rolling success",
        &series,
    )
}
