//! The paper's findings as tests: each claim with the test that decides it, the direction and
//! size of the measured effect, its p-value and the verdict.
//!
//! Owns: [`Check`], [`Verdict`] and the one rule that turns a test into a verdict (the effect is
//! signed so that positive is the paper's direction; the Holm-adjusted p < [`ALPHA`] decides,
//! [`adjust`] over the report's family of findings; a significant effect against the claim is
//! "opposite" where the reverse of every comparison the claim needs is shown and "refuted" where
//! only some are, see [`Against`]), claims that need several comparisons at once
//! ([`Check::all_of`]), and the verdict across training runs with the run as the unit
//! ([`across_runs`], [`RunsVerdict`]; the runs' pooled estimate is descriptive and never decides
//! it). Must not: read result files, pick which rows to compare (the report does), choose the
//! unit of a test (the report's stored case) or draw anything.

use serde::Serialize;

use crate::inference::{self, RandomEffects};
use crate::stats::{PairedT, WelchT};

/// Significance level of every verdict (after the family's Holm correction).
pub const ALPHA: f64 = 0.05;

/// What the measurement says about a claim.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Verdict {
    /// The effect points the paper's way and the adjusted p < ALPHA.
    Holds,
    /// The effect points the other way and the adjusted p < ALPHA, and every comparison the
    /// claim needs goes the other way: the claim is reversed.
    Opposite,
    /// A claim that needs several comparisons ([`Check::all_of`]): one of them goes the other
    /// way with adjusted p < ALPHA (its p corrected over the parts), but not every one is shown
    /// to: the claim is false, its reverse is not shown (e.g. "largest in merge" where merge is
    /// below one scenario and above another).
    Refuted,
    /// Adjusted p >= ALPHA (or no variance): this result set cannot tell.
    NotSignificant,
}

impl Verdict {
    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Holds => "holds",
            Verdict::Opposite => "opposite (significant)",
            Verdict::Refuted => "refuted (significant)",
            Verdict::NotSignificant => "not significant",
        }
    }

    /// The one rule: the sign of the effect and p < [`ALPHA`]; against the claim, what the
    /// test shows ([`Against`]).
    fn of(effect: f64, p: f64, against: Against) -> Verdict {
        match p {
            p if p.is_finite() && p < ALPHA && effect > 0.0 => Verdict::Holds,
            p if p.is_finite() && p < ALPHA && effect < 0.0 => match against {
                Against::Reverses => Verdict::Opposite,
                Against::Refutes => Verdict::Refuted,
            },
            _ => Verdict::NotSignificant,
        }
    }
}

/// What a significant effect against a claim shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Against {
    /// The reverse of the claim: its one comparison, or every comparison it needs, goes the
    /// other way.
    Reverses,
    /// Only that the claim is false: some of the comparisons it needs go the other way.
    Refutes,
}

/// One of the paper's claims, tested on this result set. The unit of every test is a stored
/// case (a start's seeds averaged first, then the case's starts under several flows, egos or
/// SVOs), so `n` counts cases, not starts or episodes.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Check {
    /// The claim in the paper's direction, e.g. "SocialComm flow succeeds more often than CoPO".
    pub claim: String,
    /// The test that decides it, e.g. "paired t, two-sided, 80 stored cases (320 episode
    /// starts): success, ...".
    pub test: String,
    /// Mean paired difference in percentage points; positive is the paper's direction.
    pub effect_points: f64,
    /// Units (stored cases) the test used.
    pub n: usize,
    /// Distinct episode starts averaged into those cases.
    pub starts: usize,
    /// Standard error of the effect, in points, and the test's degrees of freedom.
    pub se_points: f64,
    pub df: f64,
    /// The test's own p-value.
    pub p_value: f64,
    /// Holm-adjusted within the family the check is reported in ([`adjust`]); equal to
    /// `p_value` until then.
    pub p_adjusted: f64,
    /// Decided on `p_adjusted`.
    pub verdict: Verdict,
    /// What a significant effect against the claim would show.
    pub against: Against,
    /// What identifies the claim across result sets (replicates of a graph): the claim itself
    /// unless the claim quotes measured values (see [`Check::keyed`]).
    #[serde(skip)]
    pub key: String,
}

impl Check {
    /// A claim decided by a paired t-test over stored cases whose `mean_diff` is positive in
    /// the claim's direction (`what` names the compared quantity, e.g. "success, SocialComm -
    /// CoPO"); `starts`: the distinct episode starts its case values average.
    pub fn from_paired(claim: impl Into<String>, what: &str, t: &PairedT, starts: usize) -> Check {
        let test =
            format!("paired t, two-sided, {} stored cases ({starts} episode starts): {what}", t.n);
        Check::decide(
            claim.into(),
            test,
            Estimate {
                mean_diff: t.mean_diff,
                se: t.se,
                df: (t.n.max(2) - 1) as f64,
                n: t.n,
                starts,
                p_value: t.p_value,
            },
            Against::Reverses,
        )
    }

    /// A claim decided by Welch's t-test between two independent samples of stored cases whose
    /// `mean_diff` is positive in the claim's direction (`what` names the two samples);
    /// `starts`: the distinct episode starts both samples' case values average.
    pub fn from_welch(claim: impl Into<String>, what: &str, t: &WelchT, starts: usize) -> Check {
        let test = format!(
            "Welch t, two-sided, {} vs {} stored cases ({starts} episode starts): {what}",
            t.n_a, t.n_b
        );
        Check::decide(
            claim.into(),
            test,
            Estimate {
                mean_diff: t.mean_diff,
                se: t.se,
                df: t.df,
                n: t.n_a + t.n_b,
                starts,
                p_value: t.p_value,
            },
            Against::Reverses,
        )
    }

    /// A claim that needs every one of several comparisons (e.g. "larger in merge than in each
    /// other scenario", "better than every other ego"): an intersection-union test.
    ///
    /// While every part points the claim's way, the decisive part is the one with the largest
    /// p: the claim holds only if every part does. Otherwise the claim can only be refuted: the
    /// decisive part is the one against the claim with the smallest p, and since it was chosen
    /// for being the strongest, its p is multiplied by the number of parts (Bonferroni, a union
    /// test that some part goes the other way). A significant result against the claim is
    /// "opposite" only where every part goes the other way and the largest of their own p (the
    /// intersection-union test of the reversed claim) is no larger than that corrected p, so the
    /// reverse is shown at the same level; otherwise it is "refuted". The check carries the
    /// decisive part's effect, error and (corrected) p. `None` without parts.
    pub fn all_of(claim: impl Into<String>, parts: &[(String, Check)]) -> Option<Check> {
        let all_for = parts.iter().all(|(_, c)| c.effect_points > 0.0);
        let m = parts.len();
        let ((label, d), p_value, against) = if all_for {
            let d = parts.iter().max_by(|a, b| a.1.p_value.total_cmp(&b.1.p_value))?;
            (d, d.1.p_value, Against::Reverses)
        } else {
            let d = parts.iter().filter(|(_, c)| c.effect_points <= 0.0).min_by(|a, b| {
                a.1.p_value
                    .total_cmp(&b.1.p_value)
                    .then(a.1.effect_points.total_cmp(&b.1.effect_points))
            })?;
            let p_refutes = (m as f64 * d.1.p_value).min(1.0);
            let p_reverses = parts
                .iter()
                .all(|(_, c)| c.effect_points < 0.0)
                .then(|| parts.iter().map(|(_, c)| c.p_value).fold(0.0f64, f64::max));
            let against = match p_reverses {
                Some(p) if p <= p_refutes => Against::Reverses,
                _ => Against::Refutes,
            };
            (d, p_refutes, against)
        };
        let each: Vec<String> = parts
            .iter()
            .map(|(l, c)| format!("{l} {:+.1} (p {:.2e})", c.effect_points, c.p_value))
            .collect();
        let rule = if all_for {
            "the weakest part".to_string()
        } else {
            format!("the strongest part against the claim, its p x {m} (Bonferroni over the parts)")
        };
        let test = format!(
            "every one of {m} comparisons must hold (intersection-union); decisive: {label} ({rule}); {}; all: {}",
            d.test,
            each.join(", ")
        );
        Some(Check::decide(
            claim.into(),
            test,
            Estimate {
                mean_diff: d.effect_points / 100.0,
                se: d.se_points / 100.0,
                df: d.df,
                n: d.n,
                starts: d.starts,
                p_value,
            },
            against,
        ))
    }

    fn decide(claim: String, test: String, e: Estimate, against: Against) -> Check {
        let effect_points = 100.0 * e.mean_diff;
        let verdict = Verdict::of(effect_points, e.p_value, against);
        Check {
            key: claim.clone(),
            claim,
            test,
            effect_points,
            n: e.n,
            starts: e.starts,
            se_points: 100.0 * e.se,
            df: e.df,
            p_value: e.p_value,
            p_adjusted: e.p_value,
            verdict,
            against,
        }
    }

    /// The same check identified by `key` instead of its claim: for a claim whose text quotes
    /// measured values, which differ between result sets.
    pub fn keyed(self, key: impl Into<String>) -> Check {
        Check { key: key.into(), ..self }
    }

    pub fn holds(&self) -> bool {
        self.verdict == Verdict::Holds
    }

    /// The smallest true effect (points) this test detects with 80 % power at a two-sided 5 %.
    pub fn mde_points(&self) -> f64 {
        inference::mde(self.se_points, self.df)
    }
}

/// A test's numbers, in fractions (not points), as [`Check::decide`] takes them.
struct Estimate {
    mean_diff: f64,
    se: f64,
    df: f64,
    n: usize,
    starts: usize,
    p_value: f64,
}

/// Holm-Bonferroni over one family of checks (a report's findings): sets each `p_adjusted`
/// and decides every verdict on it.
pub fn adjust(checks: &mut [Check]) {
    let adj = inference::holm(&checks.iter().map(|c| c.p_value).collect::<Vec<_>>());
    for (c, p) in checks.iter_mut().zip(adj) {
        c.p_adjusted = p;
        c.verdict = Verdict::of(c.effect_points, p, c.against);
    }
}

/// What the training runs together say about a claim: the training run is the unit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RunsVerdict {
    /// Every run holds (each at its own family's Holm-adjusted 5 %).
    Holds,
    /// Every run is significant the other way and shows the reverse ([`Verdict::Opposite`]).
    Opposite,
    /// Every run is significant against the claim, and at least one only refutes it
    /// ([`Verdict::Refuted`]): the claim fails in every run, its reverse is not shown in all.
    Refuted,
    /// Some runs hold and others are significant the other way.
    Conflict,
    /// Significant in some runs only, all in one direction.
    NotReplicated,
    /// Significant in no run.
    NotSignificant,
    /// Not every run tested the claim.
    Untested,
}

impl RunsVerdict {
    pub fn as_str(self) -> &'static str {
        match self {
            RunsVerdict::Holds => "holds in every run",
            RunsVerdict::Opposite => "opposite in every run",
            RunsVerdict::Refuted => "refuted in every run",
            RunsVerdict::Conflict => "runs conflict",
            RunsVerdict::NotReplicated => "not replicated",
            RunsVerdict::NotSignificant => "not significant",
            RunsVerdict::Untested => "not tested in every run",
        }
    }

    /// The replication rule over the runs' (corrected) verdicts.
    pub fn of(runs: &[Option<Verdict>]) -> RunsVerdict {
        let Some(v) = runs.iter().copied().collect::<Option<Vec<Verdict>>>() else {
            return RunsVerdict::Untested;
        };
        let count = |w: Verdict| v.iter().filter(|v| **v == w).count();
        let (n, holds, opposite) = (v.len(), count(Verdict::Holds), count(Verdict::Opposite));
        let against = opposite + count(Verdict::Refuted);
        if n == 0 {
            RunsVerdict::Untested
        } else if holds == n {
            RunsVerdict::Holds
        } else if opposite == n {
            RunsVerdict::Opposite
        } else if against == n {
            RunsVerdict::Refuted
        } else if holds > 0 && against > 0 {
            RunsVerdict::Conflict
        } else if holds + against == 0 {
            RunsVerdict::NotSignificant
        } else {
            RunsVerdict::NotReplicated
        }
    }
}

/// One claim across the training runs: each run's own check, the runs' estimates combined by a
/// random-effects model (between-run variance included, a Hartung-Knapp-Sidik-Jonkman interval,
/// [`inference::random_effects`]) and the replication verdict. The verdict is the replication
/// rule alone: the combined estimate describes the runs and decides nothing.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AcrossRuns {
    pub key: String,
    /// Each run's check (after its family's correction); `None` where the run did not test it.
    pub runs: Vec<Option<Check>>,
    /// In points; `None` unless every run tested the claim (and there are at least two).
    /// Descriptive: the runs share their stored cases, so their estimates are not independent.
    pub combined: Option<RandomEffects>,
    pub verdict: RunsVerdict,
}

/// Every claim any run tested, in the order first seen, across `runs` (each run's checks after
/// [`adjust`]).
pub fn across_runs(runs: &[Vec<Check>]) -> Vec<AcrossRuns> {
    let mut keys: Vec<&str> = Vec::new();
    for c in runs.iter().flatten() {
        if !keys.contains(&c.key.as_str()) {
            keys.push(&c.key);
        }
    }
    keys.into_iter()
        .map(|key| {
            let each: Vec<Option<Check>> =
                runs.iter().map(|r| r.iter().find(|c| c.key == key).cloned()).collect();
            let est: Option<Vec<(f64, f64)>> =
                each.iter().map(|c| c.as_ref().map(|c| (c.effect_points, c.se_points))).collect();
            let combined = est.and_then(|e| inference::random_effects(&e));
            let verdict = RunsVerdict::of(
                &each.iter().map(|c| c.as_ref().map(|c| c.verdict)).collect::<Vec<_>>(),
            );
            AcrossRuns { key: key.to_string(), runs: each, combined, verdict }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(mean_diff: f64, p_value: f64) -> PairedT {
        PairedT { n: 400, mean_diff, se: 0.01, t: 0.0, p_value }
    }

    /// The verdict follows the effect's sign and the p-value: a strong effect the other way is
    /// reported as such, not folded into "does not hold".
    #[test]
    fn verdict_has_a_direction() {
        let c = Check::from_paired("A beats B", "success, A - B", &t(0.12, 1e-6), 1600);
        assert_eq!((c.verdict, c.n, c.starts), (Verdict::Holds, 400, 1600));
        assert!(
            (c.effect_points - 12.0).abs() < 1e-9
                && c.test.contains("400 stored cases (1600 episode starts)")
                && c.test.contains("A - B"),
            "{c:?}"
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(-0.08, 4e-11), 400).verdict,
            Verdict::Opposite
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(-0.0015, 0.94), 400).verdict,
            Verdict::NotSignificant
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(0.3, 0.05), 400).verdict,
            Verdict::NotSignificant,
            "p must be below 0.05"
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(0.3, f64::NAN), 400).verdict,
            Verdict::NotSignificant
        );
        assert!(!Check::from_paired("A beats B", "x", &t(-0.08, 4e-11), 400).holds());
        let w = WelchT {
            n_a: 40,
            n_b: 120,
            mean_diff: 0.1,
            se: 0.03,
            t: 3.0,
            df: 60.0,
            p_value: 0.004,
        };
        let c = Check::from_welch("larger in merge", "merge vs others", &w, 160);
        assert_eq!((c.verdict, c.n), (Verdict::Holds, 160));
        assert!(
            c.test.starts_with("Welch t") && c.test.contains("40 vs 120 stored cases"),
            "{c:?}"
        );
    }

    /// Holm over the family decides the verdicts: a p of 0.03 holds alone, not among three.
    #[test]
    fn holm_decides_the_family_verdicts() {
        let mut fam = vec![
            Check::from_paired("a", "x", &t(0.1, 0.03), 400),
            Check::from_paired("b", "x", &t(0.1, 0.01), 400),
            Check::from_paired("c", "x", &t(-0.1, 0.001), 400),
        ];
        assert!(fam[0].holds(), "uncorrected");
        adjust(&mut fam);
        assert_eq!(fam.iter().map(|c| c.p_adjusted).collect::<Vec<_>>(), vec![0.03, 0.02, 0.003]);
        assert_eq!(
            fam.iter().map(|c| c.verdict).collect::<Vec<_>>(),
            vec![Verdict::Holds, Verdict::Holds, Verdict::Opposite]
        );
        let mut fam = vec![
            Check::from_paired("a", "x", &t(0.1, 0.03), 400),
            Check::from_paired("b", "x", &t(0.1, 0.02), 400),
            Check::from_paired("c", "x", &t(0.1, 0.2), 400),
        ];
        adjust(&mut fam);
        assert_eq!(fam[0].verdict, Verdict::NotSignificant, "0.03 x 2 = 0.06: {fam:?}");
        assert!((fam[0].p_value - 0.03).abs() < 1e-12, "the raw p is kept");
    }

    /// Two runs with strong opposite effects never give "holds", however the pooled mean falls;
    /// the combined interval covers zero and the heterogeneity is reported.
    #[test]
    fn opposite_runs_do_not_hold() {
        let run = |d: f64| {
            vec![Check::from_paired(
                "SVO sweep",
                "x",
                &PairedT { n: 200, mean_diff: d, se: 0.01, t: d / 0.01, p_value: 1e-9 },
                200,
            )]
        };
        let a = across_runs(&[run(-0.053), run(0.037)]);
        assert_eq!(a.len(), 1);
        assert_eq!(a[0].verdict, RunsVerdict::Conflict);
        let re = a[0].combined.expect("combined");
        assert!(re.estimate.abs() < re.ci95 && re.i2 > 0.9, "{re:?}");
        let b = across_runs(&[run(0.05), run(0.04)]);
        assert_eq!(b[0].verdict, RunsVerdict::Holds);
        assert_eq!(
            RunsVerdict::of(&[Some(Verdict::Holds), Some(Verdict::NotSignificant)]),
            RunsVerdict::NotReplicated
        );
        assert_eq!(RunsVerdict::of(&[Some(Verdict::Holds), None]), RunsVerdict::Untested);
        assert_eq!(
            RunsVerdict::of(&[Some(Verdict::NotSignificant); 2]),
            RunsVerdict::NotSignificant
        );
    }

    /// Against the claim in every run: "opposite in every run" only where every run shows the
    /// reverse; where a run only refutes it, "refuted in every run"; refuted in one run only
    /// is not replicated, and refuted beside a run that holds is a conflict.
    #[test]
    fn refuted_and_opposite_runs_are_told_apart() {
        use Verdict::{Holds, NotSignificant, Opposite, Refuted};
        let of = |v: &[Verdict]| RunsVerdict::of(&v.iter().map(|v| Some(*v)).collect::<Vec<_>>());
        assert_eq!(of(&[Opposite, Opposite]), RunsVerdict::Opposite);
        assert_eq!(of(&[Refuted, Refuted]), RunsVerdict::Refuted);
        assert_eq!(of(&[Opposite, Refuted]), RunsVerdict::Refuted);
        assert_eq!(of(&[Refuted, NotSignificant]), RunsVerdict::NotReplicated);
        assert_eq!(of(&[Refuted, Holds]), RunsVerdict::Conflict);
        assert_eq!(RunsVerdict::Refuted.as_str(), "refuted in every run");
        assert_eq!(Refuted.as_str(), "refuted (significant)");
    }

    /// "Better than every other": holds only when every comparison holds; one clear loss
    /// refutes it (its p corrected over the parts), and only every part going the other way
    /// reverses it.
    #[test]
    fn all_of_is_an_intersection_union_test() {
        let c = |d: f64, p: f64| Check::from_paired("x", "y", &t(d, p), 400);
        let all = Check::all_of("best", &[("A".into(), c(0.1, 1e-4)), ("B".into(), c(0.05, 0.01))])
            .expect("parts");
        assert!(
            all.holds() && (all.p_value - 0.01).abs() < 1e-12 && all.test.contains("decisive: B"),
            "{all:?}"
        );
        let lost =
            Check::all_of("best", &[("A".into(), c(0.1, 1e-4)), ("B".into(), c(-0.07, 1e-3))])
                .expect("parts");
        assert_eq!(lost.verdict, Verdict::Refuted, "A is still above: refuted, not reversed");
        assert!(
            (lost.effect_points + 7.0).abs() < 1e-9
                && (lost.p_value - 2e-3).abs() < 1e-12
                && lost
                    .test
                    .contains("decisive: B (the strongest part against the claim, its p x 2"),
            "{lost:?}"
        );
        // "Largest in merge" as the review found it: above roundabout, about level with
        // intersection, clearly below bottleneck. Refuted, and the refuting part's p x 3.
        let merge = Check::all_of(
            "largest in merge",
            &[
                ("vs intersection".into(), c(0.010, 0.778)),
                ("vs bottleneck".into(), c(-0.145, 2.31e-4)),
                ("vs roundabout".into(), c(0.109, 2.58e-3)),
            ],
        )
        .expect("parts");
        assert_eq!(merge.verdict, Verdict::Refuted);
        assert!((merge.p_value - 6.93e-4).abs() < 1e-12, "{merge:?}");
        // Every part the other way, each at least as clearly as the corrected decisive p: the
        // reverse is shown.
        let reversed =
            Check::all_of("best", &[("A".into(), c(-0.1, 2e-4)), ("B".into(), c(-0.05, 3e-4))])
                .expect("parts");
        assert_eq!((reversed.verdict, reversed.against), (Verdict::Opposite, Against::Reverses));
        assert!(
            (reversed.p_value - 4e-4).abs() < 1e-12 && (reversed.effect_points + 10.0).abs() < 1e-9
        );
        // Every part the other way, but one only weakly: refuted by A, the reverse not shown.
        let weak =
            Check::all_of("best", &[("A".into(), c(-0.1, 1e-5)), ("B".into(), c(-0.01, 0.6))])
                .expect("parts");
        assert_eq!(weak.verdict, Verdict::Refuted);
        // Adjusted over a family, the check keeps what it can show.
        let mut fam = vec![weak.clone(), c(0.1, 0.001)];
        adjust(&mut fam);
        assert_eq!(fam[0].verdict, Verdict::Refuted);
        // A single part is a plain comparison: against it, the claim is reversed.
        let one = Check::all_of("best", &[("A".into(), c(-0.1, 1e-5))]).expect("a part");
        assert_eq!((one.verdict, one.p_value), (Verdict::Opposite, 1e-5));
        assert!(Check::all_of("best", &[]).is_none());
    }
}
