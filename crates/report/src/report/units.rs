//! The unit of analysis: a stored case.
//!
//! Owns: how episodes become the values every mean, interval and test of the report is computed
//! on. The grid reuses one stored case (its scenario and number: routes, initial poses, SVOs) in
//! many cells: under every flow and ego, under each SVO of the sweep and each vehicle count of
//! the density sweep. Outcomes of one case correlate across those cells (the intraclass
//! correlation within a case reached 0.41 in the committed report), so the stored case, not the
//! cell's start, is the independent unit of every test. Values are built in two stages:
//!
//! 1. A start, one cell's episodes on one stored case (ego, flow, scenario, SVO, vehicles, case),
//!    averages its seeds and, in a report over several replicates, its replicates. The IDM flow
//!    and every mean action are deterministic, so two seeds of a start can be the same episode:
//!    counted once, it cannot narrow an interval.
//! 2. A stored case (scenario, case) averages its starts: the same case under 4 flows, 4 egos
//!    or 10 SVOs of one test is one value, so copying it into more cells cannot narrow an
//!    interval either.
//!
//! Paired comparisons pair two cells' episodes on the same (replicate, seed, start), take the
//! differences and average them per start, then per case; the test is a t over the cases
//! (cases - 1 degrees of freedom), and the Welch tests, the intersection-union parts, the
//! minimum detectable effects, the power lines and the drop ratio's bootstrap (which resamples
//! whole cases) all take these per-case values.
//!
//! Why aggregation to the case rather than a cluster-robust (by case) variance: on this grid
//! every case appears in every cell of a test (a balanced design), where the t-test over case
//! means is exact and is the test of a mixed model with a random case effect; its mean is the
//! cells' mean; and anyone can recompute it with one group-by and a one-sample t
//! (`tests/report_stats_check.py` does). A sandwich variance over 20 cases per scenario is
//! biased low and would need small-sample corrections (CR2, Satterthwaite degrees of freedom)
//! before its intervals could be trusted. One method is used everywhere.
//!
//! Must not: decide verdicts ([`crate::findings`]) or lay out the report.

use std::collections::BTreeMap;

use crate::episodes::EpisodeRow;
use crate::stats::{one_sample_t_test, PairedT, Summary};

pub(crate) type Metric = fn(&EpisodeRow) -> f32;

/// A start of one cell: (ego, flow, scenario, SVO, vehicles, case).
type Unit = (String, String, String, Option<u32>, Option<usize>, u32);

/// A stored case: (scenario, case). Every cell that runs the scenario reuses it.
type Case = (String, u32);

/// A start with the same ego under several flows: (ego, scenario, SVO, vehicles, case).
type EgoStart = (String, String, Option<u32>, Option<usize>, u32);

fn unit(r: &EpisodeRow) -> Unit {
    (
        r.cell.ego.clone(),
        r.cell.flow.clone(),
        r.cell.scenario.clone(),
        r.cell.svo_deg,
        r.cell.vehicles,
        r.ep.case,
    )
}

/// The mean of `values` per key.
fn group_mean_map<K: Ord>(values: impl IntoIterator<Item = (K, f64)>) -> BTreeMap<K, f64> {
    let mut acc: BTreeMap<K, (f64, usize)> = BTreeMap::new();
    for (k, v) in values {
        let e = acc.entry(k).or_insert((0.0, 0));
        e.0 += v;
        e.1 += 1;
    }
    acc.into_iter().map(|(k, (s, n))| (k, s / n as f64)).collect()
}

/// One value per stored case, and how many distinct starts were averaged into them.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct CaseValues {
    /// In case order (scenario, case).
    pub values: Vec<f64>,
    pub starts: usize,
}

/// The two stages: `values` averaged per start (their seeds and replicates), then the starts
/// averaged per stored case (`case_of` names a start's case).
fn per_case<S: Ord>(
    values: impl IntoIterator<Item = (S, f64)>,
    case_of: impl Fn(&S) -> Case,
) -> CaseValues {
    let starts = group_mean_map(values);
    let n = starts.len();
    let cases = group_mean_map(starts.into_iter().map(|(s, v)| (case_of(&s), v)));
    CaseValues { values: cases.into_values().collect(), starts: n }
}

/// The metric of each stored case among `rows` (seeds and replicates averaged per start, then
/// starts per case).
pub(crate) fn case_values(rows: &[&EpisodeRow], m: Metric) -> CaseValues {
    per_case(rows.iter().map(|r| (unit(r), m(r) as f64)), |u| (u.2.clone(), u.5))
}

/// Mean and 95 % interval over the stored cases of `rows`.
pub(crate) fn summary(rows: &[&EpisodeRow], m: Metric) -> Summary {
    Summary::of(&case_values(rows, m).values)
}

/// Per-case differences `a - b` of the metric: episodes paired on the same (replicate, seed,
/// scenario, SVO, vehicles, case) and on the dimension that is not compared (with `same_flow`
/// two egos on the same flow; otherwise two flows with the same ego, so pooled rows of several
/// egos pair each ego with itself), averaged per start, then per stored case.
pub(crate) fn case_diffs(
    a: &[&EpisodeRow],
    b: &[&EpisodeRow],
    m: Metric,
    same_flow: bool,
) -> CaseValues {
    let other = |r: &EpisodeRow| if same_flow { r.cell.flow.clone() } else { r.cell.ego.clone() };
    let key = |r: &EpisodeRow| {
        (
            r.replicate,
            r.ep.seed,
            other(r),
            r.cell.scenario.clone(),
            r.cell.svo_deg,
            r.cell.vehicles,
            r.ep.case,
        )
    };
    let bm: BTreeMap<_, f64> = b.iter().map(|r| (key(r), m(r) as f64)).collect();
    let diffs = a.iter().filter_map(|r| {
        bm.get(&key(r)).map(|v| {
            (
                (r.cell.scenario.clone(), r.ep.case, other(r), r.cell.svo_deg, r.cell.vehicles),
                m(r) as f64 - v,
            )
        })
    });
    per_case(diffs, |s| (s.0.clone(), s.1))
}

/// A paired test over stored cases, and the distinct starts its case values average.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct CaseTest {
    /// `n` counts stored cases.
    pub t: PairedT,
    pub starts: usize,
}

fn test_of(d: CaseValues) -> Option<CaseTest> {
    one_sample_t_test(&d.values).ok().map(|t| CaseTest { t, starts: d.starts })
}

/// Two egos on the same starts of the same flows.
pub(crate) fn paired(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric) -> Option<CaseTest> {
    test_of(case_diffs(a, b, m, true))
}

/// Two flows on the same starts with the same ego.
pub(crate) fn paired_across_flows(
    a: &[&EpisodeRow],
    b: &[&EpisodeRow],
    m: Metric,
) -> Option<CaseTest> {
    test_of(case_diffs(a, b, m, false))
}

/// Per stored case, the metric under each of `flows`' rows with the same ego (for a bootstrap
/// that resamples whole cases): each flow's starts (ego, scenario, SVO, vehicles, case) that
/// every flow ran, averaged per case.
pub(crate) fn case_columns<const N: usize>(flows: [&[&EpisodeRow]; N], m: Metric) -> Vec<[f64; N]> {
    let per: Vec<BTreeMap<EgoStart, f64>> = flows
        .iter()
        .map(|rows| {
            group_mean_map(rows.iter().map(|r| {
                (
                    (
                        r.cell.ego.clone(),
                        r.cell.scenario.clone(),
                        r.cell.svo_deg,
                        r.cell.vehicles,
                        r.ep.case,
                    ),
                    m(r) as f64,
                )
            }))
        })
        .collect();
    let complete = per[0].keys().filter_map(|k| {
        per.iter().map(|p| p.get(k).copied()).collect::<Option<Vec<f64>>>().map(|v| (k, v))
    });
    let mut acc: BTreeMap<Case, ([f64; N], usize)> = BTreeMap::new();
    for (k, v) in complete {
        let e = acc.entry((k.1.clone(), k.4)).or_insert(([0.0; N], 0));
        for (s, x) in e.0.iter_mut().zip(&v) {
            *s += x;
        }
        e.1 += 1;
    }
    acc.into_values().map(|(s, n)| s.map(|x| x / n as f64)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use sf_job::eval::{Cell, EvalEpisode};

    /// An episode of `ego` in `flow` on stored case `case` of `scenario` (SVO `svo`).
    #[allow(clippy::too_many_arguments)]
    fn episode(
        ego: &str,
        flow: &str,
        scenario: &str,
        svo: Option<u32>,
        case: u32,
        seed: u32,
        replicate: u32,
        success: f32,
    ) -> EpisodeRow {
        EpisodeRow {
            cell: Cell {
                experiment: "cross".into(),
                ego: ego.into(),
                flow: flow.into(),
                scenario: scenario.into(),
                svo_deg: svo,
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
            replicate,
        }
    }

    fn row(flow: &str, case: u32, seed: u32, replicate: u32, success: f32) -> EpisodeRow {
        episode("", flow, "merge", None, case, seed, replicate, success)
    }

    fn refs(rows: &[EpisodeRow]) -> Vec<&EpisodeRow> {
        rows.iter().collect()
    }

    const SUCCESS: Metric = |r| r.ep.scores.success;

    /// A deterministic cell evaluated under two seeds (and in two replicates) repeats each
    /// episode: the interval is the one of its distinct cases, not narrower.
    #[test]
    fn a_duplicated_episode_does_not_narrow_the_interval() {
        let once: Vec<EpisodeRow> =
            (0..20).map(|c| row("IDM", c, 0, 0, (c % 3) as f32 / 2.0)).collect();
        let repeated: Vec<EpisodeRow> = (0..20)
            .flat_map(|c| {
                (0..2).flat_map(move |s| {
                    (0..2).map(move |rep| row("IDM", c, s, rep, (c % 3) as f32 / 2.0))
                })
            })
            .collect();
        let (a, b) = (summary(&refs(&once), SUCCESS), summary(&refs(&repeated), SUCCESS));
        assert_eq!(a, b, "80 copies of 20 cases are 20 units");
        assert_eq!(b.n, 20);
        // Paired: the differences of two repeated cells are tested over the 20 cases.
        let other: Vec<EpisodeRow> = repeated
            .iter()
            .map(|r| EpisodeRow {
                cell: Cell { flow: "X".into(), ..r.cell.clone() },
                ep: EvalEpisode { scores: sf_job::Scores { success: 1.0, ..r.ep.scores }, ..r.ep },
                ..r.clone()
            })
            .collect();
        let t = paired_across_flows(&refs(&other), &refs(&repeated), SUCCESS).expect("a test");
        assert_eq!((t.t.n, t.starts), (20, 20));
    }

    /// Seeds that change the episode are averaged within their start, starts within their case.
    #[test]
    fn seeds_are_averaged_within_a_start() {
        let rows: Vec<EpisodeRow> =
            (0..10).flat_map(|c| [row("F", c, 0, 0, 1.0), row("F", c, 1, 0, 0.0)]).collect();
        let v = case_values(&refs(&rows), SUCCESS);
        assert_eq!(v, CaseValues { values: vec![0.5; 10], starts: 10 });
        let cols = case_columns(
            [&refs(&rows)[..], &rows.iter().filter(|r| r.ep.case < 5).collect::<Vec<_>>()[..]],
            SUCCESS,
        );
        assert_eq!(cols.len(), 5, "cases every column ran");
    }

    /// One stored case's outcomes copied into more cells (10 SVOs of the sweep, 4 flows of the
    /// cross-validation) are the same evidence as the case once: the same estimate, standard
    /// error, p and interval. Counted as starts, the copies would narrow the interval by about
    /// sqrt(10).
    #[test]
    fn a_case_copied_into_more_cells_does_not_narrow_the_interval() {
        let value = |c: u32, flow: &str| {
            let base = 0.3 + 0.05 * (c % 7) as f32;
            if flow == "SocialComm" {
                base + 0.02 * (c % 3) as f32
            } else {
                base
            }
        };
        let sweep = |svos: &[u32]| -> Vec<EpisodeRow> {
            let mut rows = Vec::new();
            for c in 0..20 {
                for &svo in svos {
                    for f in ["SocialComm", "CoPO"] {
                        for seed in 0..2 {
                            rows.push(episode("", f, "merge", Some(svo), c, seed, 0, value(c, f)));
                        }
                    }
                }
            }
            rows
        };
        let test = |rows: &[EpisodeRow]| {
            let a: Vec<&EpisodeRow> = rows.iter().filter(|r| r.cell.flow == "SocialComm").collect();
            let b: Vec<&EpisodeRow> = rows.iter().filter(|r| r.cell.flow == "CoPO").collect();
            paired_across_flows(&a, &b, SUCCESS).expect("a test")
        };
        let once = test(&sweep(&[0]));
        let ten = test(&sweep(&(0..10).map(|k| 10 * k).collect::<Vec<_>>()));
        assert_eq!((once.t.n, once.starts), (20, 20));
        assert_eq!((ten.t.n, ten.starts), (20, 200), "200 starts are 20 stored cases");
        assert_eq!(
            (ten.t.mean_diff, ten.t.se, ten.t.p_value),
            (once.t.mean_diff, once.t.se, once.t.p_value)
        );
        let starts: Vec<f64> = (0..20)
            .flat_map(|c| {
                std::iter::repeat_n((value(c, "SocialComm") - value(c, "CoPO")) as f64, 10)
            })
            .collect();
        let naive = one_sample_t_test(&starts).expect("the start-level test");
        assert!(
            once.t.se / naive.se > 3.0,
            "as starts the copies would narrow the interval: {} vs {}",
            once.t.se,
            naive.se
        );

        // Two egos on one case under 4 flows: the same as under one flow.
        let cross = |flows: &[&str]| -> Vec<EpisodeRow> {
            let mut rows = Vec::new();
            for c in 0..20 {
                for f in flows {
                    rows.push(episode("A", f, "merge", None, c, 0, 0, value(c, "SocialComm")));
                    rows.push(episode("B", f, "merge", None, c, 0, 0, value(c, "CoPO")));
                }
            }
            rows
        };
        let ego_test = |rows: &[EpisodeRow]| {
            let a: Vec<&EpisodeRow> = rows.iter().filter(|r| r.cell.ego == "A").collect();
            let b: Vec<&EpisodeRow> = rows.iter().filter(|r| r.cell.ego == "B").collect();
            (paired(&a, &b, SUCCESS).expect("a test"), summary(&a, SUCCESS))
        };
        let (one_flow, s1) = ego_test(&cross(&["IDM"]));
        let (four_flows, s4) = ego_test(&cross(&["IDM", "MACAD", "CoPO", "SocialComm"]));
        assert_eq!((four_flows.t.n, four_flows.starts), (20, 80));
        assert_eq!(four_flows.t, one_flow.t);
        assert_eq!(s4, s1, "a mean's interval is over cases too");
    }

    /// A case-level effect planted in constructed data is recovered: each of 60 cases (two
    /// scenarios) has its own shift of the A - B difference around a planted 8 points, shared by
    /// the case's 4 flows and 2 seeds, with episode noise on top. The estimate lies near 8 and
    /// the interval over cases covers it; the interval over the 240 starts would be too narrow
    /// for the case-to-case spread.
    #[test]
    fn a_planted_case_level_effect_is_recovered() {
        const PLANTED: f64 = 0.08;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(65);
        let mut rows = Vec::new();
        for scenario in ["merge", "roundabout"] {
            for c in 0..30 {
                let case_shift = rng.random_range(-0.15..0.15);
                let level = rng.random_range(0.3..0.6);
                for f in ["IDM", "MACAD", "CoPO", "SocialComm"] {
                    for seed in 0..2 {
                        let noise = rng.random_range(-0.02..0.02);
                        let b = level;
                        let a = level + PLANTED + case_shift + noise;
                        rows.push(episode("A", f, scenario, None, c, seed, 0, a as f32));
                        rows.push(episode("B", f, scenario, None, c, seed, 0, b as f32));
                    }
                }
            }
        }
        let a: Vec<&EpisodeRow> = rows.iter().filter(|r| r.cell.ego == "A").collect();
        let b: Vec<&EpisodeRow> = rows.iter().filter(|r| r.cell.ego == "B").collect();
        let t = paired(&a, &b, SUCCESS).expect("a test");
        assert_eq!((t.t.n, t.starts), (60, 240));
        let ci95 = Summary::of(&case_diffs(&a, &b, SUCCESS, true).values).ci95;
        assert!(
            (t.t.mean_diff - PLANTED).abs() < 0.03 && (t.t.mean_diff - PLANTED).abs() < ci95,
            "estimate {} ± {ci95} should cover the planted {PLANTED}",
            t.t.mean_diff
        );
        assert!(t.t.p_value < 1e-4, "{t:?}");
        // The same differences with each (flow, case) start taken as a unit.
        let per_start = Summary::of(
            &group_mean_map(a.iter().zip(&b).map(|(x, y)| {
                (
                    (x.cell.scenario.clone(), x.ep.case, x.cell.flow.clone()),
                    (x.ep.scores.success - y.ep.scores.success) as f64,
                )
            }))
            .into_values()
            .collect::<Vec<f64>>(),
        );
        assert!(
            per_start.ci95 < 0.6 * ci95,
            "the starts of one case are not independent: {} vs {ci95}",
            per_start.ci95
        );
    }
}
