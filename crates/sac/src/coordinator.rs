//! CoPO's Stage-2 global coordinator: a Gaussian over the SVO that a scenario's agents are
//! given, fitted by the cross-entropy method to maximise the flow's mean individual reward
//! with the Stage-1 policy frozen.
//!
//! Owns: [`Coordinator`] (mean and deviation in degrees, candidate proposals clamped to
//! [0, 90], the elite update with a floor on the deviation). Must not: run episodes (callers
//! score candidates).

use rand::Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

/// SVO range of CoPO's agents, degrees (the simulator's).
pub use sf_sim::case::SVO_RANGE_DEG;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Coordinator {
    pub mean_deg: f32,
    pub std_deg: f32,
    /// The deviation never drops below this (keeps exploring).
    pub min_std_deg: f32,
}

impl Default for Coordinator {
    /// Uniform-ish start: centred, wide.
    fn default() -> Self {
        Self { mean_deg: 45.0, std_deg: 30.0, min_std_deg: 2.0 }
    }
}

impl Coordinator {
    /// `n` candidate SVOs drawn from the Gaussian, clamped to the SVO range.
    pub fn propose(&self, rng: &mut impl Rng, n: usize) -> Vec<f32> {
        let d = Normal::new(self.mean_deg, self.std_deg.max(1e-3)).expect("a positive deviation");
        (0..n).map(|_| d.sample(rng).clamp(SVO_RANGE_DEG.0, SVO_RANGE_DEG.1)).collect()
    }

    /// Refits to the best `elite_frac` of the candidates by score (higher is better).
    pub fn update(&mut self, candidates: &[f32], scores: &[f32], elite_frac: f32) {
        assert_eq!(candidates.len(), scores.len(), "one score per candidate");
        if candidates.is_empty() {
            return;
        }
        let mut idx: Vec<usize> = (0..candidates.len()).collect();
        idx.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]));
        let k = ((candidates.len() as f32 * elite_frac).ceil() as usize).clamp(1, candidates.len());
        let elite: Vec<f32> = idx[..k].iter().map(|&i| candidates[i]).collect();
        let mean = elite.iter().sum::<f32>() / k as f32;
        let var = elite.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / k as f32;
        self.mean_deg = mean;
        self.std_deg = var.sqrt().max(self.min_std_deg);
    }
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;

    /// A constructed case where cooperative SVOs near 60 deg pay best: the mean moves there.
    #[test]
    fn the_mean_moves_toward_the_better_svo() {
        let mut c = Coordinator::default();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let start = (c.mean_deg - 60.0).abs();
        for _ in 0..8 {
            let cand = c.propose(&mut rng, 16);
            assert!(cand.iter().all(|v| (0.0..=90.0).contains(v)));
            let scores: Vec<f32> = cand.iter().map(|v| -(v - 60.0).powi(2)).collect();
            c.update(&cand, &scores, 0.25);
        }
        assert!((c.mean_deg - 60.0).abs() < 5.0 && (c.mean_deg - 60.0).abs() < start, "{c:?}");
        assert!(c.std_deg >= c.min_std_deg);
    }
}
