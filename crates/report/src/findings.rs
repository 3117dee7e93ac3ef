//! The paper's findings as tests: each claim with the test that decides it, the direction and
//! size of the measured effect, its p-value and the verdict.
//!
//! Owns: [`Check`], [`Verdict`] and the one rule that turns a test into a verdict (the effect is
//! signed so that positive is the paper's direction; the Holm-adjusted p < [`ALPHA`] decides,
//! [`adjust`] over the report's family of findings), claims that need several comparisons at
//! once ([`Check::all_of`]), and the verdict across training runs with the run as the unit
//! ([`across_runs`], [`RunsVerdict`]). Must not: read result files, pick which rows to compare
//! (the report does) or draw anything.

use serde::Serialize;

use crate::inference::{self, RandomEffects};
use crate::{PairedT, WelchT};

/// Significance level of every verdict (after the family's Holm correction).
pub const ALPHA: f64 = 0.05;

/// What the measurement says about a claim.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Verdict {
    /// The effect points the paper's way and the adjusted p < ALPHA.
    Holds,
    /// The effect points the other way and the adjusted p < ALPHA: the claim is contradicted.
    Opposite,
    /// Adjusted p >= ALPHA (or no variance): this result set cannot tell.
    NotSignificant,
}

impl Verdict {
    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Holds => "holds",
            Verdict::Opposite => "opposite (significant)",
            Verdict::NotSignificant => "not significant",
        }
    }

    /// The one rule: the sign of the effect and p < [`ALPHA`].
    fn of(effect: f64, p: f64) -> Verdict {
        match p {
            p if p.is_finite() && p < ALPHA && effect > 0.0 => Verdict::Holds,
            p if p.is_finite() && p < ALPHA && effect < 0.0 => Verdict::Opposite,
            _ => Verdict::NotSignificant,
        }
    }
}

/// One of the paper's claims, tested on this result set. The unit of every test is a distinct
/// episode start (its seeds averaged first), so `n` counts starts, not episodes.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Check {
    /// The claim in the paper's direction, e.g. "SocialComm flow succeeds more often than CoPO".
    pub claim: String,
    /// The test that decides it, e.g. "paired t (two-sided) over 160 episode starts: success".
    pub test: String,
    /// Mean paired difference in percentage points; positive is the paper's direction.
    pub effect_points: f64,
    /// Units (distinct episode starts) the test used.
    pub n: usize,
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
    /// What identifies the claim across result sets (replicates of a graph): the claim itself
    /// unless the claim quotes measured values (see [`Check::keyed`]).
    #[serde(skip)]
    pub key: String,
}

impl Check {
    /// A claim decided by a paired t-test whose `mean_diff` is positive in the claim's direction
    /// (`what` names the compared quantity, e.g. "success, SocialComm - CoPO").
    pub fn from_paired(claim: impl Into<String>, what: &str, t: &PairedT) -> Check {
        let test = format!("paired t, two-sided, {} episode starts: {what}", t.n);
        Check::decide(
            claim.into(),
            test,
            t.mean_diff,
            t.se,
            (t.n.max(2) - 1) as f64,
            t.n,
            t.p_value,
        )
    }

    /// A claim decided by Welch's t-test between two independent samples whose `mean_diff` is
    /// positive in the claim's direction (`what` names the two samples).
    pub fn from_welch(claim: impl Into<String>, what: &str, t: &WelchT) -> Check {
        let test = format!("Welch t, two-sided, {} vs {} episode starts: {what}", t.n_a, t.n_b);
        Check::decide(claim.into(), test, t.mean_diff, t.se, t.df, t.n_a + t.n_b, t.p_value)
    }

    /// A claim that needs every one of several comparisons (e.g. "larger in merge than in each
    /// other scenario", "better than every other ego"): an intersection-union test. While every
    /// part points the claim's way the decisive part is the one with the largest p (the claim
    /// holds only if all do); otherwise it is the part that points most strongly the other way.
    /// The check carries the decisive part's effect, error and p. `None` without parts.
    pub fn all_of(claim: impl Into<String>, parts: &[(String, Check)]) -> Option<Check> {
        let all_positive = parts.iter().all(|(_, c)| c.effect_points > 0.0);
        let (label, d) = if all_positive {
            parts.iter().max_by(|a, b| a.1.p_value.total_cmp(&b.1.p_value))?
        } else {
            parts.iter().min_by(|a, b| a.1.effect_points.total_cmp(&b.1.effect_points))?
        };
        let each: Vec<String> = parts
            .iter()
            .map(|(l, c)| format!("{l} {:+.1} (p {:.2e})", c.effect_points, c.p_value))
            .collect();
        let test = format!("every one of {} comparisons must hold (intersection-union); decisive: {label}; {}; all: {}", parts.len(), d.test, each.join(", "));
        Some(Check::decide(
            claim.into(),
            test,
            d.effect_points / 100.0,
            d.se_points / 100.0,
            d.df,
            d.n,
            d.p_value,
        ))
    }

    fn decide(
        claim: String,
        test: String,
        mean_diff: f64,
        se: f64,
        df: f64,
        n: usize,
        p_value: f64,
    ) -> Check {
        let effect_points = 100.0 * mean_diff;
        let verdict = Verdict::of(effect_points, p_value);
        Check {
            key: claim.clone(),
            claim,
            test,
            effect_points,
            n,
            se_points: 100.0 * se,
            df,
            p_value,
            p_adjusted: p_value,
            verdict,
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

/// Holm-Bonferroni over one family of checks (a report's findings): sets each `p_adjusted`
/// and decides every verdict on it.
pub fn adjust(checks: &mut [Check]) {
    let adj = inference::holm(&checks.iter().map(|c| c.p_value).collect::<Vec<_>>());
    for (c, p) in checks.iter_mut().zip(adj) {
        c.p_adjusted = p;
        c.verdict = Verdict::of(c.effect_points, p);
    }
}

/// What the training runs together say about a claim: the training run is the unit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RunsVerdict {
    /// Every run holds (each at its own family's Holm-adjusted 5 %).
    Holds,
    /// Every run is significant the other way.
    Opposite,
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
        let (holds, opposite) = (
            v.iter().filter(|v| **v == Verdict::Holds).count(),
            v.iter().filter(|v| **v == Verdict::Opposite).count(),
        );
        match (holds, opposite) {
            _ if v.is_empty() => RunsVerdict::Untested,
            (h, 0) if h == v.len() => RunsVerdict::Holds,
            (0, o) if o == v.len() => RunsVerdict::Opposite,
            (h, o) if h > 0 && o > 0 => RunsVerdict::Conflict,
            (0, 0) => RunsVerdict::NotSignificant,
            _ => RunsVerdict::NotReplicated,
        }
    }
}

/// One claim across the training runs: each run's own check, the runs' estimates combined by a
/// random-effects model (between-run variance included) and the replication verdict.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AcrossRuns {
    pub key: String,
    /// Each run's check (after its family's correction); `None` where the run did not test it.
    pub runs: Vec<Option<Check>>,
    /// In points; `None` unless every run tested the claim (and there are at least two).
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
        let c = Check::from_paired("A beats B", "success, A - B", &t(0.12, 1e-6));
        assert_eq!((c.verdict, c.n), (Verdict::Holds, 400));
        assert!(
            (c.effect_points - 12.0).abs() < 1e-9
                && c.test.contains("400 episode starts")
                && c.test.contains("A - B"),
            "{c:?}"
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(-0.08, 4e-11)).verdict,
            Verdict::Opposite
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(-0.0015, 0.94)).verdict,
            Verdict::NotSignificant
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(0.3, 0.05)).verdict,
            Verdict::NotSignificant,
            "p must be below 0.05"
        );
        assert_eq!(
            Check::from_paired("A beats B", "x", &t(0.3, f64::NAN)).verdict,
            Verdict::NotSignificant
        );
        assert!(!Check::from_paired("A beats B", "x", &t(-0.08, 4e-11)).holds());
        let w = WelchT {
            n_a: 40,
            n_b: 120,
            mean_diff: 0.1,
            se: 0.03,
            t: 3.0,
            df: 60.0,
            p_value: 0.004,
        };
        let c = Check::from_welch("larger in merge", "merge vs others", &w);
        assert_eq!((c.verdict, c.n), (Verdict::Holds, 160));
        assert!(c.test.starts_with("Welch t") && c.test.contains("40 vs 120"), "{c:?}");
    }

    /// Holm over the family decides the verdicts: a p of 0.03 holds alone, not among three.
    #[test]
    fn holm_decides_the_family_verdicts() {
        let mut fam = vec![
            Check::from_paired("a", "x", &t(0.1, 0.03)),
            Check::from_paired("b", "x", &t(0.1, 0.01)),
            Check::from_paired("c", "x", &t(-0.1, 0.001)),
        ];
        assert!(fam[0].holds(), "uncorrected");
        adjust(&mut fam);
        assert_eq!(fam.iter().map(|c| c.p_adjusted).collect::<Vec<_>>(), vec![0.03, 0.02, 0.003]);
        assert_eq!(
            fam.iter().map(|c| c.verdict).collect::<Vec<_>>(),
            vec![Verdict::Holds, Verdict::Holds, Verdict::Opposite]
        );
        let mut fam = vec![
            Check::from_paired("a", "x", &t(0.1, 0.03)),
            Check::from_paired("b", "x", &t(0.1, 0.02)),
            Check::from_paired("c", "x", &t(0.1, 0.2)),
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

    /// "Better than every other": holds only when every comparison holds; one clear loss
    /// decides it the other way.
    #[test]
    fn all_of_is_an_intersection_union_test() {
        let c = |d: f64, p: f64| Check::from_paired("x", "y", &t(d, p));
        let all = Check::all_of("best", &[("A".into(), c(0.1, 1e-4)), ("B".into(), c(0.05, 0.01))])
            .expect("parts");
        assert!(
            all.holds() && (all.p_value - 0.01).abs() < 1e-12 && all.test.contains("decisive: B"),
            "{all:?}"
        );
        let lost =
            Check::all_of("best", &[("A".into(), c(0.1, 1e-4)), ("B".into(), c(-0.07, 1e-3))])
                .expect("parts");
        assert_eq!(lost.verdict, Verdict::Opposite);
        assert!(
            (lost.effect_points + 7.0).abs() < 1e-9 && lost.test.contains("decisive: B"),
            "{lost:?}"
        );
        assert!(Check::all_of("best", &[]).is_none());
    }
}
