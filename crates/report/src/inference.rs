//! Inference over several tests: a family-wise correction, the combination of replicates'
//! estimates, the power of a test and a cluster bootstrap.
//!
//! Owns: [`holm`] (Holm-Bonferroni adjusted p-values of one family), [`random_effects`]
//! (DerSimonian-Laird combination of per-replicate estimates with its heterogeneity, and a
//! Hartung-Knapp-Sidik-Jonkman interval: t with k - 1 degrees of freedom, because with two or
//! three training runs the normal interval treats an estimated between-run variance resting on
//! one or two degrees of freedom as known),
//! [`mde`] (the minimum detectable effect of a t-test at a given power) and
//! [`bootstrap_ratio`] (a percentile interval for a ratio of two mean drops, resampling whole
//! clusters). Must not: know episodes, cells or the report's layout; callers pass numbers.

use rand::{Rng, SeedableRng};
use serde::Serialize;
use statrs::distribution::{ContinuousCDF, Normal, StudentsT};

/// Holm-Bonferroni adjusted p-values of one family, in the input's order. Non-finite p-values
/// are not members of the family (they stay as they are and do not count in its size).
/// Rejecting where the adjusted p is below alpha controls the family-wise error rate at alpha.
pub fn holm(ps: &[f64]) -> Vec<f64> {
    let mut idx: Vec<usize> = (0..ps.len()).filter(|&i| ps[i].is_finite()).collect();
    idx.sort_by(|&a, &b| ps[a].total_cmp(&ps[b]));
    let m = idx.len();
    let mut out = ps.to_vec();
    let mut running = 0.0f64;
    for (rank, &i) in idx.iter().enumerate() {
        running = running.max(((m - rank) as f64 * ps[i]).min(1.0));
        out[i] = running;
    }
    out
}

/// The replicates' estimates combined with a DerSimonian-Laird random-effects model: the
/// between-replicate variance `tau2` is estimated from Cochran's Q and widens the interval when
/// the replicates disagree more than their own errors explain. The interval and p are
/// Hartung-Knapp-Sidik-Jonkman's (HKSJ): the variance of the estimate is scaled by the weighted
/// spread of the replicates about it, and the quantile is Student's t with k - 1 degrees of
/// freedom. The scale is floored at 1 (the modification of Knapp and Hartung, recommended by
/// Röver, Knapp and Friede 2015 for few replicates): unfloored, two replicates that happen to
/// agree would give an interval narrower than their own errors, down to zero width.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RandomEffects {
    /// Replicates combined.
    pub k: usize,
    pub estimate: f64,
    /// Standard error of `estimate` (HKSJ): `sqrt(max(1, hksj_scale) / sum w)`, with `w` the
    /// random-effects weights `1 / (se_i^2 + tau2)`.
    pub se: f64,
    /// Degrees of freedom of the interval and p: k - 1.
    pub df: f64,
    /// Half-width of the 95 % interval of `estimate`: `t(0.975, k - 1) * se`.
    pub ci95: f64,
    /// Two-sided p of `estimate` against 0 (Student t, k - 1 degrees of freedom).
    pub p_value: f64,
    /// The HKSJ scale before its floor: `sum w (y_i - estimate)^2 / (k - 1)`.
    pub hksj_scale: f64,
    /// The DerSimonian-Laird standard error `sqrt(1 / sum w)` and its normal 95 % half-width
    /// (the interval this report printed before 2026-12-06), for comparison.
    pub se_dl: f64,
    pub ci95_z: f64,
    /// Cochran's Q and its p-value (chi-squared, k - 1 df): do the replicates differ?
    pub q: f64,
    pub q_p_value: f64,
    /// Share of the variation due to heterogeneity, max(0, (Q - df) / Q), in [0, 1].
    pub i2: f64,
    /// Between-replicate variance.
    pub tau2: f64,
}

/// Combines per-replicate `(estimate, standard error)` pairs; `None` for fewer than two or a
/// non-finite value. A zero standard error (a deterministic comparison) is floored at a
/// millionth of the largest one, so such a replicate weighs heavily but finitely. The
/// replicates are taken as independent: where they share their units (training runs evaluated
/// on the same stored cases), the interval leaves that shared sampling error out.
pub fn random_effects(est: &[(f64, f64)]) -> Option<RandomEffects> {
    let k = est.len();
    if k < 2 || est.iter().any(|(e, s)| !e.is_finite() || !s.is_finite()) {
        return None;
    }
    let floor = est.iter().map(|(_, s)| *s).fold(0.0f64, f64::max).max(1e-12) * 1e-6;
    let var: Vec<f64> = est.iter().map(|(_, s)| s.max(floor).powi(2)).collect();
    let w: Vec<f64> = var.iter().map(|v| 1.0 / v).collect();
    let sw: f64 = w.iter().sum();
    let fixed = est.iter().zip(&w).map(|((e, _), w)| w * e).sum::<f64>() / sw;
    let q: f64 = est.iter().zip(&w).map(|((e, _), w)| w * (e - fixed).powi(2)).sum();
    let df = (k - 1) as f64;
    let c = sw - w.iter().map(|w| w * w).sum::<f64>() / sw;
    let tau2 = if c > 0.0 { ((q - df) / c).max(0.0) } else { 0.0 };
    let wr: Vec<f64> = var.iter().map(|v| 1.0 / (v + tau2)).collect();
    let swr: f64 = wr.iter().sum();
    let estimate = est.iter().zip(&wr).map(|((e, _), w)| w * e).sum::<f64>() / swr;
    let se_dl = 1.0 / swr.sqrt();
    let hksj_scale =
        est.iter().zip(&wr).map(|((e, _), w)| w * (e - estimate).powi(2)).sum::<f64>() / df;
    let se = (hksj_scale.max(1.0) / swr).sqrt();
    let t = StudentsT::new(0.0, 1.0, df).ok()?;
    let p_value = 2.0 * (1.0 - t.cdf((estimate / se).abs()));
    let chi2 = statrs::distribution::ChiSquared::new(df).ok()?;
    let q_p_value = 1.0 - chi2.cdf(q);
    let i2 = if q > 0.0 { ((q - df) / q).max(0.0) } else { 0.0 };
    Some(RandomEffects {
        k,
        estimate,
        se,
        df,
        ci95: t.inverse_cdf(0.975) * se,
        p_value,
        hksj_scale,
        se_dl,
        ci95_z: 1.959964 * se_dl,
        q,
        q_p_value,
        i2,
        tau2,
    })
}

/// Two-sided significance level and power at which [`mde`] is computed.
pub const MDE_ALPHA: f64 = 0.05;
pub const MDE_POWER: f64 = 0.8;

/// The smallest true effect a two-sided t-test at level [`MDE_ALPHA`] detects with probability
/// [`MDE_POWER`], given the standard error of its estimate and its degrees of freedom:
/// `(t(1 - alpha/2) + t(power)) * se`.
pub fn mde(se: f64, df: f64) -> f64 {
    if !(se.is_finite() && df.is_finite() && df > 0.0) {
        return f64::NAN;
    }
    match StudentsT::new(0.0, 1.0, df) {
        Ok(t) => (t.inverse_cdf(1.0 - MDE_ALPHA / 2.0) + t.inverse_cdf(MDE_POWER)) * se,
        Err(_) => f64::NAN,
    }
}

/// Units (e.g. stored cases) a paired test needs to detect `effect` at the level and
/// power of [`mde`], given the standard deviation of one unit's difference (normal
/// approximation, rounded up).
pub fn units_needed(effect: f64, sd: f64) -> Option<u64> {
    if !(effect.is_finite() && sd.is_finite() && effect != 0.0) {
        return None;
    }
    let normal = Normal::new(0.0, 1.0).ok()?;
    let z = normal.inverse_cdf(1.0 - MDE_ALPHA / 2.0) + normal.inverse_cdf(MDE_POWER);
    Some(((z * sd / effect).powi(2)).ceil() as u64)
}

/// A percentile bootstrap of `(mean(base) - mean(b)) / (mean(base) - mean(a))`, the drop under
/// `b` in units of the drop under `a`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RatioInterval {
    pub ratio: f64,
    pub lo: f64,
    pub hi: f64,
    /// Share of draws in which the denominator (the drop under `a`) is not positive: the ratio
    /// is undefined there and the interval is over the other draws.
    pub undefined_share: f64,
    pub draws: usize,
}

/// Bootstraps the ratio of two mean drops over `units` (each a cluster's `[base, a, b]` values,
/// e.g. a stored case's success under three flows), resampling whole units with replacement,
/// `draws` times with a fixed seed (the report is reproducible). `None` without units or with a
/// point estimate whose denominator is not positive.
pub fn bootstrap_ratio(units: &[[f64; 3]], draws: usize, seed: u64) -> Option<RatioInterval> {
    let n = units.len();
    let ratio_of = |sum: [f64; 3]| {
        let den = sum[0] - sum[1];
        (den > 0.0).then(|| (sum[0] - sum[2]) / den)
    };
    let total = units.iter().fold([0.0; 3], |acc, u| [acc[0] + u[0], acc[1] + u[1], acc[2] + u[2]]);
    let ratio = ratio_of(total)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut defined = Vec::with_capacity(draws);
    for _ in 0..draws {
        let mut sum = [0.0; 3];
        for _ in 0..n {
            let u = &units[rng.random_range(0..n)];
            for (s, v) in sum.iter_mut().zip(u) {
                *s += v;
            }
        }
        if let Some(r) = ratio_of(sum) {
            defined.push(r);
        }
    }
    if defined.is_empty() {
        return Some(RatioInterval {
            ratio,
            lo: f64::NAN,
            hi: f64::NAN,
            undefined_share: 1.0,
            draws,
        });
    }
    defined.sort_by(f64::total_cmp);
    let q = |p: f64| {
        defined[((p * (defined.len() - 1) as f64).round() as usize).min(defined.len() - 1)]
    };
    Some(RatioInterval {
        ratio,
        lo: q(0.025),
        hi: q(0.975),
        undefined_share: 1.0 - defined.len() as f64 / draws as f64,
        draws,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// statsmodels.stats.multitest.multipletests([0.01, 0.04, 0.03, 0.005], method="holm")
    /// gives [0.03, 0.06, 0.06, 0.02]; a NaN is left out of the family.
    #[test]
    fn holm_matches_the_reference() {
        let adj = holm(&[0.01, 0.04, 0.03, 0.005]);
        for (a, want) in adj.iter().zip([0.03, 0.06, 0.06, 0.02]) {
            assert!((a - want).abs() < 1e-12, "{adj:?}");
        }
        let adj = holm(&[0.01, f64::NAN, 0.04]);
        assert!(
            (adj[0] - 0.02).abs() < 1e-12 && adj[1].is_nan() && (adj[2] - 0.04).abs() < 1e-12,
            "{adj:?}"
        );
        assert_eq!(holm(&[0.9, 0.8]), vec![1.0, 1.0], "capped at 1");
        assert_eq!(holm(&[0.45, 0.4]), vec![0.8, 0.8], "monotone in the ordered p");
    }

    /// Two replicates that agree give the fixed-effect estimate (tau2 = 0); two that disagree
    /// strongly get a wide interval that covers zero, and a high I2.
    #[test]
    fn random_effects_widen_when_replicates_disagree() {
        let agree = random_effects(&[(5.0, 1.0), (5.5, 1.0)]).expect("two");
        assert_eq!(agree.tau2, 0.0);
        assert!(
            (agree.estimate - 5.25).abs() < 1e-12 && (agree.se_dl - 0.5f64.sqrt()).abs() < 1e-12,
            "{agree:?}"
        );
        // Q = 0.125: the unfloored HKSJ scale would shrink the interval; floored at 1 it is the
        // DerSimonian-Laird error with t(1): p = 2 (1 - T1(5.25 / 0.7071)) = 0.0852.
        assert!(
            (agree.hksj_scale - 0.125).abs() < 1e-12 && (agree.se - agree.se_dl).abs() < 1e-12,
            "{agree:?}"
        );
        assert!((agree.p_value - 0.08523).abs() < 1e-4 && agree.i2 == 0.0, "{agree:?}");
        let disagree = random_effects(&[(-5.3, 1.0), (3.7, 1.0)]).expect("two");
        // Q = 40.5, C = 1, tau2 = 39.5: se = sqrt((1 + 39.5) / 2).
        assert!(
            (disagree.q - 40.5).abs() < 1e-9 && (disagree.tau2 - 39.5).abs() < 1e-9,
            "{disagree:?}"
        );
        assert!(
            (disagree.se_dl - 20.25f64.sqrt()).abs() < 1e-9
                && disagree.p_value > 0.5
                && disagree.i2 > 0.95,
            "{disagree:?}"
        );
        assert!(disagree.q_p_value < 1e-8);
        assert!(random_effects(&[(1.0, 1.0)]).is_none());
        assert!(random_effects(&[(1.0, 1.0), (f64::NAN, 1.0)]).is_none());
    }

    /// Two runs (k = 2), by hand. Estimates 2.1 and 3.1 points with standard errors 0.72 and
    /// 0.75: w = 1/0.5184 = 1.92901 and 1/0.5625 = 1.77778, sum 3.70679; the fixed estimate
    /// (2.1 w1 + 3.1 w2) / 3.70679 = 2.57960; Q = w1 0.47960^2 + w2 0.52040^2 = 0.92516 < 1, so
    /// tau2 = 0 and the weights stay. DerSimonian-Laird: se 1/sqrt(3.70679) = 0.51940, z
    /// half-width 1.95996 x 0.51940 = 1.01800. HKSJ: scale Q / (k - 1) = 0.92516, floored at 1,
    /// se 0.51940, t(0.975, 1) = 12.70620, half-width 6.59959, 6.48 times the z interval;
    /// p = 2 (1 - T1(2.57960 / 0.51940)) = 2 (1 - T1(4.96651)) = 0.12649.
    #[test]
    fn hksj_interval_of_two_runs_matches_the_hand_computation() {
        let re = random_effects(&[(2.1, 0.72), (3.1, 0.75)]).expect("two runs");
        let near = |a: f64, b: f64, tol: f64| (a - b).abs() < tol;
        assert_eq!((re.k, re.df, re.tau2), (2, 1.0, 0.0), "{re:?}");
        assert!(near(re.estimate, 2.57960, 1e-5) && near(re.q, 0.92516, 1e-5), "{re:?}");
        assert!(near(re.se_dl, 0.51940, 1e-5) && near(re.ci95_z, 1.01800, 1e-5), "{re:?}");
        assert!(near(re.hksj_scale, 0.92516, 1e-5) && near(re.se, 0.51940, 1e-5), "{re:?}");
        assert!(near(re.ci95, 6.59959, 1e-4), "{re:?}");
        assert!(re.ci95 > 6.0 * re.ci95_z, "wider than the z interval: {re:?}");
        assert!(near(re.p_value, 0.12649, 1e-4), "{re:?}");
        // Runs that disagree beyond their errors: tau2 > 0 and the scale above 1 is kept. With
        // equal errors 1, estimates -5.3 and 3.7: tau2 = 39.5, w = 1/40.5 each, estimate -0.8,
        // scale (4.5^2 + 4.5^2) / 40.5 = 1, se sqrt(40.5 / 2) = 4.5, half-width 12.7062 x 4.5.
        let re = random_effects(&[(-5.3, 1.0), (3.7, 1.0)]).expect("two runs");
        assert!(near(re.hksj_scale, 1.0, 1e-9) && near(re.se, 4.5, 1e-9), "{re:?}");
        assert!(near(re.ci95, 12.70620 * 4.5, 1e-3) && re.ci95 > re.ci95_z, "{re:?}");
        // Unequal errors, disagreeing: the scale is computed, not assumed. Estimates 0 and 10,
        // errors 1 and 3: the estimate, scale and error against their definitions at the
        // estimated tau2.
        let re = random_effects(&[(0.0, 1.0), (10.0, 3.0)]).expect("two runs");
        let (w1, w2) = (1.0 / (1.0 + re.tau2), 1.0 / (9.0 + re.tau2));
        let mu = 10.0 * w2 / (w1 + w2);
        let scale = (w1 * mu * mu + w2 * (10.0 - mu).powi(2)) / 1.0;
        assert!(near(re.estimate, mu, 1e-9) && near(re.hksj_scale, scale, 1e-9), "{re:?}");
        assert!(near(re.se, (scale.max(1.0) / (w1 + w2)).sqrt(), 1e-9), "{re:?}");
    }

    /// n = 100 pairs with sd 1: se 0.1, (t(0.975, 99) 1.98422 + t(0.8, 99) 0.84519) * 0.1 = 0.28294; the normal
    /// approximation needs 79 units for an effect of 0.3157 with sd 1 (z 1.96 + 0.8416).
    #[test]
    fn mde_and_units_needed() {
        assert!((mde(0.1, 99.0) - 0.28294).abs() < 1e-4, "{}", mde(0.1, 99.0));
        assert!(mde(0.1, 0.0).is_nan());
        assert_eq!(units_needed(0.3157, 1.0), Some(79));
        assert_eq!(units_needed(0.0, 1.0), None);
    }

    /// A drop of 10 under `b` against 2 under `a` is a ratio of 5; without a drop under `a` no
    /// ratio is given; a noisy denominator leaves many draws undefined.
    #[test]
    fn bootstrap_ratio_of_drops() {
        let units: Vec<[f64; 3]> =
            (0..50).map(|i| [0.8, 0.78 + 0.0001 * (i % 3) as f64, 0.7]).collect();
        let r = bootstrap_ratio(&units, 500, 1).expect("a drop");
        assert!(
            (r.ratio - 0.1 / 0.0199).abs() < 0.2
                && r.lo <= r.ratio
                && r.ratio <= r.hi
                && r.undefined_share == 0.0,
            "{r:?}"
        );
        assert!(bootstrap_ratio(&[[0.5, 0.6, 0.2]], 10, 1).is_none(), "no drop under a");
        let coin: Vec<[f64; 3]> = (0..40)
            .map(|i| [0.5, if i % 2 == 0 { 0.45 } else { 0.55 }, 0.1])
            .chain([[0.5, 0.49, 0.1]])
            .collect();
        let r = bootstrap_ratio(&coin, 1000, 3).expect("a tiny drop");
        assert!(
            r.undefined_share > 0.2,
            "a drop indistinguishable from zero leaves many draws undefined: {r:?}"
        );
    }
}
