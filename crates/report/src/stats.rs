//! The t-statistics every result rests on: [`Summary`] (mean with a Student-t 95% confidence
//! interval), [`paired_t_test`], [`one_sample_t_test`] and [`welch_t_test`], with their one error
//! type. Owns: the arithmetic of one test over the values a caller passes. Must not: choose the
//! unit of analysis, correct for several tests ([`crate::inference`] does) or read files.

use serde::{Deserialize, Serialize};
use statrs::distribution::{ContinuousCDF, StudentsT};

/// Mean and 95% confidence half-width of a sample.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub n: usize,
    pub mean: f64,
    pub std: f64,
    /// Half-width of the two-sided 95% Student-t interval (0 for n < 2).
    pub ci95: f64,
}

impl Summary {
    pub fn of(xs: &[f64]) -> Self {
        let n = xs.len();
        if n == 0 {
            return Self { n, mean: f64::NAN, std: f64::NAN, ci95: f64::NAN };
        }
        let mean = xs.iter().sum::<f64>() / n as f64;
        if n < 2 {
            return Self { n, mean, std: 0.0, ci95: 0.0 };
        }
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let std = var.sqrt();
        let ci95 = t_quantile(0.975, (n - 1) as f64) * std / (n as f64).sqrt();
        Self { n, mean, std, ci95 }
    }
}

fn t_quantile(p: f64, df: f64) -> f64 {
    StudentsT::new(0.0, 1.0, df).map(|t| t.inverse_cdf(p)).unwrap_or(f64::NAN)
}

/// Result of a paired two-sided t-test.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairedT {
    pub n: usize,
    pub mean_diff: f64,
    /// Standard error of `mean_diff` (0 without variance).
    pub se: f64,
    pub t: f64,
    pub p_value: f64,
}

/// Errors of the statistics API.
#[derive(Debug, PartialEq)]
pub enum StatsError {
    LengthMismatch(usize, usize),
    TooFew(usize),
}

impl std::fmt::Display for StatsError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::LengthMismatch(a, b) => write!(f, "paired samples differ in length: {a} vs {b}"),
            Self::TooFew(n) => write!(f, "a paired t-test needs at least 2 pairs, got {n}"),
        }
    }
}

impl std::error::Error for StatsError {}

/// Paired two-sided t-test of `a - b`. Identical samples give t = 0 and p = 1.
pub fn paired_t_test(a: &[f64], b: &[f64]) -> Result<PairedT, StatsError> {
    if a.len() != b.len() {
        return Err(StatsError::LengthMismatch(a.len(), b.len()));
    }
    let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    one_sample_t_test(&d)
}

/// Two-sided one-sample t-test of `mean(d) = 0`: the paired test on the differences `d`
/// (e.g. per-episode-start differences already averaged over the start's seeds).
pub fn one_sample_t_test(d: &[f64]) -> Result<PairedT, StatsError> {
    let n = d.len();
    if n < 2 {
        return Err(StatsError::TooFew(n));
    }
    let s = Summary::of(d);
    if s.std == 0.0 {
        let p = if s.mean == 0.0 { 1.0 } else { 0.0 };
        let t = if s.mean == 0.0 { 0.0 } else { s.mean.signum() * f64::INFINITY };
        return Ok(PairedT { n, mean_diff: s.mean, se: 0.0, t, p_value: p });
    }
    let se = s.std / (n as f64).sqrt();
    let t = s.mean / se;
    let dist = StudentsT::new(0.0, 1.0, (n - 1) as f64).map_err(|_| StatsError::TooFew(n))?;
    let p_value = 2.0 * (1.0 - dist.cdf(t.abs()));
    Ok(PairedT { n, mean_diff: s.mean, se, t, p_value })
}

/// Result of Welch's two-sided t-test (unequal variances) of `mean(a) - mean(b)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WelchT {
    pub n_a: usize,
    pub n_b: usize,
    pub mean_diff: f64,
    /// Standard error of `mean_diff`.
    pub se: f64,
    pub t: f64,
    /// Welch-Satterthwaite degrees of freedom.
    pub df: f64,
    pub p_value: f64,
}

/// Welch's two-sided t-test of `mean(a) - mean(b)` for two independent samples. Two samples
/// without variance give p = 1 if their means are equal and 0 otherwise.
pub fn welch_t_test(a: &[f64], b: &[f64]) -> Result<WelchT, StatsError> {
    let (sa, sb) = (Summary::of(a), Summary::of(b));
    if sa.n < 2 || sb.n < 2 {
        return Err(StatsError::TooFew(sa.n.min(sb.n)));
    }
    let (va, vb) = (sa.std * sa.std / sa.n as f64, sb.std * sb.std / sb.n as f64);
    let mean_diff = sa.mean - sb.mean;
    let se = (va + vb).sqrt();
    if se == 0.0 {
        let p_value = if mean_diff == 0.0 { 1.0 } else { 0.0 };
        let t = if mean_diff == 0.0 { 0.0 } else { mean_diff.signum() * f64::INFINITY };
        return Ok(WelchT {
            n_a: sa.n,
            n_b: sb.n,
            mean_diff,
            se,
            t,
            df: (sa.n + sb.n - 2) as f64,
            p_value,
        });
    }
    let t = mean_diff / se;
    let df = (va + vb).powi(2) / (va * va / (sa.n - 1) as f64 + vb * vb / (sb.n - 1) as f64);
    let dist = StudentsT::new(0.0, 1.0, df).map_err(|_| StatsError::TooFew(sa.n.min(sb.n)))?;
    let p_value = 2.0 * (1.0 - dist.cdf(t.abs()));
    Ok(WelchT { n_a: sa.n, n_b: sb.n, mean_diff, se, t, df, p_value })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ci_matches_t_table() {
        // n = 10, std 1: half-width = t_{0.975, 9} / sqrt(10) = 2.262157 / 3.162278.
        let xs: Vec<f64> = (0..10).map(|i| if i % 2 == 0 { 1.0 } else { -1.0 }).collect();
        let s = Summary::of(&xs);
        let std = (10.0f64 / 9.0).sqrt();
        assert!((s.std - std).abs() < 1e-12);
        assert!((s.ci95 - 2.262157 * std / 10f64.sqrt()).abs() < 1e-5, "{}", s.ci95);
    }

    #[test]
    fn paired_t_matches_reference() {
        // Differences [1, 0, 1, 1, 2]: t = 3.16228, df = 4, two-sided p = 0.034 (scipy.stats.ttest_rel).
        let a = [2.0, 2.0, 4.0, 5.0, 7.0];
        let b = [1.0, 2.0, 3.0, 4.0, 5.0];
        let r = paired_t_test(&a, &b).expect("valid");
        assert!((r.t - 3.162278).abs() < 1e-5, "{}", r.t);
        assert!((r.p_value - 0.034109).abs() < 1e-4, "{}", r.p_value);
        assert_eq!(paired_t_test(&a, &a).expect("valid").p_value, 1.0);
        assert_eq!(paired_t_test(&a, &b[..3]), Err(StatsError::LengthMismatch(5, 3)));
    }

    #[test]
    fn welch_t_matches_reference() {
        // Means 3 and 5, variances 2.5 each, n = 5 each: t = -2, df = 8, two-sided p = 0.0805
        // (scipy.stats.ttest_ind(a, b, equal_var=False)).
        let w =
            welch_t_test(&[1.0, 2.0, 3.0, 4.0, 5.0], &[3.0, 4.0, 5.0, 6.0, 7.0]).expect("valid");
        assert!((w.t + 2.0).abs() < 1e-12 && (w.df - 8.0).abs() < 1e-9, "{w:?}");
        assert!((w.p_value - 0.08052).abs() < 1e-4, "{}", w.p_value);
        assert_eq!(welch_t_test(&[1.0, 1.0], &[1.0, 1.0]).expect("valid").p_value, 1.0);
        assert_eq!(welch_t_test(&[1.0], &[1.0, 2.0]), Err(StatsError::TooFew(1)));
    }
}
