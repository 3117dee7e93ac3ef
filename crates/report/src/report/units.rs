//! The unit of analysis: a distinct episode start.
//!
//! Owns: how episodes become the values every mean, interval and test of the report is computed
//! on. A unit is one stored start (scenario, SVO, vehicles, case) of one cell (ego, flow); its
//! seeds, and in a report over several replicates its replicates, are averaged first. The IDM
//! flow and every policy's mean action are deterministic, so two seeds of a start can be the
//! same episode: counted as one unit it cannot narrow an interval. Paired comparisons pair two
//! cells' episodes on the same (replicate, seed, start), take the differences, and average them
//! per start. Must not: decide verdicts ([`crate::findings`]) or lay out the report.

use std::collections::BTreeMap;

use crate::episodes::EpisodeRow;
use crate::{one_sample_t_test, PairedT, Summary};

pub(crate) type Metric = fn(&EpisodeRow) -> f32;

/// A start of one cell: (ego, flow, scenario, SVO, vehicles, case).
type Unit = (String, String, String, Option<u32>, Option<usize>, u32);

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

/// Means of `values` grouped by key, in key order.
fn group_means<K: Ord>(values: impl IntoIterator<Item = (K, f64)>) -> Vec<f64> {
    group_mean_map(values).into_values().collect()
}

/// The metric of each distinct start among `rows` (seeds and replicates averaged).
pub(crate) fn unit_values(rows: &[&EpisodeRow], m: Metric) -> Vec<f64> {
    group_means(rows.iter().map(|r| (unit(r), m(r) as f64)))
}

/// Mean and 95 % interval over the distinct starts of `rows`.
pub(crate) fn summary(rows: &[&EpisodeRow], m: Metric) -> Summary {
    Summary::of(&unit_values(rows, m))
}

/// Per-start differences `a - b` of the metric: episodes paired on the same (replicate, seed,
/// scenario, SVO, vehicles, case) and on the dimension that is not compared (with `same_flow`
/// two egos on the same flow; otherwise two flows with the same ego, so pooled rows of several
/// egos pair each ego with itself), then averaged per start.
pub(crate) fn unit_diffs(
    a: &[&EpisodeRow],
    b: &[&EpisodeRow],
    m: Metric,
    same_flow: bool,
) -> Vec<f64> {
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
                (other(r), r.cell.scenario.clone(), r.cell.svo_deg, r.cell.vehicles, r.ep.case),
                m(r) as f64 - v,
            )
        })
    });
    group_means(diffs)
}

/// Two egos on the same starts of the same flows.
pub(crate) fn paired(a: &[&EpisodeRow], b: &[&EpisodeRow], m: Metric) -> Option<PairedT> {
    one_sample_t_test(&unit_diffs(a, b, m, true)).ok()
}

/// Two flows on the same starts with the same ego.
pub(crate) fn paired_across_flows(
    a: &[&EpisodeRow],
    b: &[&EpisodeRow],
    m: Metric,
) -> Option<PairedT> {
    one_sample_t_test(&unit_diffs(a, b, m, false)).ok()
}

/// Per start (ego, scenario, case) with the same ego: the metric under each of `flows`' rows,
/// for starts every flow ran (for a bootstrap that resamples whole starts).
pub(crate) fn unit_columns<const N: usize>(flows: [&[&EpisodeRow]; N], m: Metric) -> Vec<[f64; N]> {
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
    per[0]
        .keys()
        .filter_map(|k| {
            per.iter()
                .map(|p| p.get(k).copied())
                .collect::<Option<Vec<f64>>>()
                .and_then(|v| <[f64; N]>::try_from(v).ok())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use sf_job::eval::{Cell, EvalEpisode};

    fn row(flow: &str, case: u32, seed: u32, replicate: u32, success: f32) -> EpisodeRow {
        EpisodeRow {
            cell: Cell {
                experiment: "flow_quality".into(),
                ego: String::new(),
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
            replicate,
        }
    }

    /// A deterministic cell evaluated under two seeds (and in two replicates) repeats each
    /// episode: the interval is the one of its distinct starts, not narrower.
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
        let (a, b) = (
            summary(&once.iter().collect::<Vec<_>>(), |r| r.ep.scores.success),
            summary(&repeated.iter().collect::<Vec<_>>(), |r| r.ep.scores.success),
        );
        assert_eq!(a, b, "80 copies of 20 starts are 20 units");
        assert_eq!(b.n, 20);
        // Paired: the differences of two repeated cells are tested over the 20 starts.
        let other: Vec<EpisodeRow> = repeated
            .iter()
            .map(|r| EpisodeRow {
                cell: Cell { flow: "X".into(), ..r.cell.clone() },
                ep: EvalEpisode { scores: sf_job::Scores { success: 1.0, ..r.ep.scores }, ..r.ep },
                ..r.clone()
            })
            .collect();
        let t = paired_across_flows(
            &other.iter().collect::<Vec<_>>(),
            &repeated.iter().collect::<Vec<_>>(),
            |r| r.ep.scores.success,
        )
        .expect("a test");
        assert_eq!(t.n, 20);
    }

    /// Seeds that change the episode are averaged within their start: the start is the unit.
    #[test]
    fn seeds_are_averaged_within_a_start() {
        let rows: Vec<EpisodeRow> =
            (0..10).flat_map(|c| [row("F", c, 0, 0, 1.0), row("F", c, 1, 0, 0.0)]).collect();
        let v = unit_values(&rows.iter().collect::<Vec<_>>(), |r| r.ep.scores.success);
        assert_eq!(v, vec![0.5; 10]);
        let cols = unit_columns(
            [
                &rows.iter().collect::<Vec<_>>()[..],
                &rows.iter().filter(|r| r.ep.case < 5).collect::<Vec<_>>()[..],
            ],
            |r| r.ep.scores.success,
        );
        assert_eq!(cols.len(), 5, "starts every column ran");
    }
}
