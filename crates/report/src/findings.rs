//! The paper's findings as tests: each claim with the test that decides it, the direction and
//! size of the measured effect, its p-value and the verdict.
//!
//! Owns: [`Check`], [`Verdict`] and the one rule that turns a paired test into a verdict (the
//! effect is signed so that positive is the paper's direction; p < [`ALPHA`] decides). Must
//! not: read result files, pick which rows to compare (the report does) or draw anything.

use serde::Serialize;

use crate::{PairedT, WelchT};

/// Significance level of every verdict.
pub const ALPHA: f64 = 0.05;

/// What the measurement says about a claim.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Verdict {
    /// The effect points the paper's way and p < ALPHA.
    Holds,
    /// The effect points the other way and p < ALPHA: the claim is contradicted here.
    Opposite,
    /// p >= ALPHA (or no variance): this result set cannot tell.
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
}

/// One of the paper's claims, tested on this result set.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Check {
    /// The claim in the paper's direction, e.g. "SocialComm flow succeeds more often than CoPO".
    pub claim: String,
    /// The test that decides it, e.g. "paired t (two-sided) over 1600 episode starts: success".
    pub test: String,
    /// Mean paired difference in percentage points; positive is the paper's direction.
    pub effect_points: f64,
    /// Pairs the test used.
    pub n: usize,
    pub p_value: f64,
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
        Check::decide(claim.into(), format!("paired t, two-sided, {} episode starts: {what}", t.n), t.mean_diff, t.n, t.p_value)
    }

    /// A claim decided by Welch's t-test between two independent samples whose `mean_diff` is
    /// positive in the claim's direction (`what` names the two samples).
    pub fn from_welch(claim: impl Into<String>, what: &str, t: &WelchT) -> Check {
        Check::decide(claim.into(), format!("Welch t, two-sided, {} vs {} values: {what}", t.n_a, t.n_b), t.mean_diff, t.n_a + t.n_b, t.p_value)
    }

    /// The one rule: the sign of the effect and p < [`ALPHA`].
    fn decide(claim: String, test: String, mean_diff: f64, n: usize, p_value: f64) -> Check {
        let effect_points = 100.0 * mean_diff;
        let verdict = match p_value {
            p if p.is_finite() && p < ALPHA && effect_points > 0.0 => Verdict::Holds,
            p if p.is_finite() && p < ALPHA && effect_points < 0.0 => Verdict::Opposite,
            _ => Verdict::NotSignificant,
        };
        Check { key: claim.clone(), claim, test, effect_points, n, p_value, verdict }
    }

    /// The same check identified by `key` instead of its claim: for a claim whose text quotes
    /// measured values, which differ between result sets.
    pub fn keyed(self, key: impl Into<String>) -> Check {
        Check { key: key.into(), ..self }
    }

    pub fn holds(&self) -> bool {
        self.verdict == Verdict::Holds
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(mean_diff: f64, p_value: f64) -> PairedT {
        PairedT { n: 400, mean_diff, t: 0.0, p_value }
    }

    /// The verdict follows the effect's sign and the p-value: a strong effect the other way is
    /// reported as such, not folded into "does not hold".
    #[test]
    fn verdict_has_a_direction() {
        let c = Check::from_paired("A beats B", "success, A - B", &t(0.12, 1e-6));
        assert_eq!((c.verdict, c.n), (Verdict::Holds, 400));
        assert!((c.effect_points - 12.0).abs() < 1e-9 && c.test.contains("400 episode starts") && c.test.contains("A - B"), "{c:?}");
        assert_eq!(Check::from_paired("A beats B", "x", &t(-0.08, 4e-11)).verdict, Verdict::Opposite);
        assert_eq!(Check::from_paired("A beats B", "x", &t(-0.0015, 0.94)).verdict, Verdict::NotSignificant);
        assert_eq!(Check::from_paired("A beats B", "x", &t(0.3, 0.05)).verdict, Verdict::NotSignificant, "p must be below 0.05");
        assert_eq!(Check::from_paired("A beats B", "x", &t(0.3, f64::NAN)).verdict, Verdict::NotSignificant);
        assert!(!Check::from_paired("A beats B", "x", &t(-0.08, 4e-11)).holds());
        let w = WelchT { n_a: 40, n_b: 120, mean_diff: 0.1, t: 3.0, df: 60.0, p_value: 0.004 };
        let c = Check::from_welch("larger in merge", "merge vs others", &w);
        assert_eq!((c.verdict, c.n), (Verdict::Holds, 160));
        assert!(c.test.starts_with("Welch t") && c.test.contains("40 vs 120"), "{c:?}");
    }
}
