//! CoPO's Stage-2 global coordinator: a Gaussian over the SVO that a scenario's agents are
//! given, fitted by the cross-entropy method to maximise the flow's mean individual reward
//! with the Stage-1 policy frozen.
//!
//! Owns: [`Coordinator`] (mean and deviation in degrees, candidate proposals clamped to
//! [0, 90], the elite update with a floor on the deviation), [`fit_scenario`] (scores
//! candidates by running the frozen flow through `crate::drive` on generated cases) and
//! [`CoordinatorFile`] (`coordinator.json` in a CoPO job's artifact directory: the Gaussians
//! an ego job's background and evaluation redraw SVOs from). Must not: train the flow.

use std::path::Path;
use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use sf_sim::case::{random_case, SvoGaussianError};
use sf_sim::vec_env::{EpisodeSpec, VecEnv, VecEnvError};
use sf_sim::{Map, Mode, SimConfig, SvoGaussian};

use crate::drive::{run_episodes, Actor, Drivers};
use crate::inference::PolicyRunner;

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

impl Coordinator {
    pub fn gaussian(&self) -> SvoGaussian {
        SvoGaussian { mean_deg: self.mean_deg, std_deg: self.std_deg }
    }
}

/// One CEM iteration, after its update.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IterationLog {
    pub iteration: u32,
    pub mean_deg: f32,
    pub std_deg: f32,
    /// Mean individual reward per agent-step over the iteration's candidates.
    pub mean_reward: f32,
    /// The best candidate's score.
    pub best_reward: f32,
}

/// The fitted coordinator of one scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScenarioFit {
    pub scenario: String,
    pub gaussian: SvoGaussian,
    pub history: Vec<IterationLog>,
}

/// `coordinator.json`: a CoPO job's Stage-2 Gaussians, one per scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoordinatorFile {
    pub scenarios: Vec<ScenarioFit>,
}

/// What failed reading a [`CoordinatorFile`] or running [`fit_scenario`]; names the file,
/// scenario or setting.
#[derive(Debug, thiserror::Error)]
pub enum CoordinatorError {
    #[error("reading {path}: {source}")]
    Read { path: String, source: std::io::Error },
    #[error("{path}: {source}")]
    Parse { path: String, source: serde_json::Error },
    #[error("{path}: scenario {scenario}: {source}")]
    Gaussian { path: String, scenario: String, source: SvoGaussianError },
    #[error("coordinator settings out of range: {0:?}")]
    Settings(FitSettings),
    /// The generated episodes do not fit the map.
    #[error(transparent)]
    Episodes(#[from] VecEnvError),
}

impl CoordinatorFile {
    pub const FILE: &'static str = "coordinator.json";

    /// The file of a job's artifact directory, if it has one (a CoPO flow past Stage 2).
    pub fn load(dir: &Path) -> Result<Option<Self>, CoordinatorError> {
        let p = dir.join(Self::FILE);
        if !p.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&p)
            .map_err(|source| CoordinatorError::Read { path: p.display().to_string(), source })?;
        let f: Self = serde_json::from_str(&text)
            .map_err(|source| CoordinatorError::Parse { path: p.display().to_string(), source })?;
        for s in &f.scenarios {
            s.gaussian.validate().map_err(|source| CoordinatorError::Gaussian {
                path: p.display().to_string(),
                scenario: s.scenario.clone(),
                source,
            })?;
        }
        Ok(Some(f))
    }

    pub fn gaussian(&self, scenario: &str) -> Option<SvoGaussian> {
        self.scenarios.iter().find(|s| s.scenario == scenario).map(|s| s.gaussian)
    }
}

/// How [`fit_scenario`] searches.
#[derive(Clone, Debug)]
pub struct FitSettings {
    pub iterations: u32,
    pub population: u32,
    pub episodes: u32,
    pub elite_frac: f32,
    pub envs: usize,
    /// Vehicles per generated case, inclusive.
    pub vehicles: (u32, u32),
    pub seed: u64,
}

/// CoPO Stage 2 on one scenario: the cross-entropy method over the SVO Gaussian, each
/// candidate SVO given to every agent of `episodes` generated cases, driven by the frozen
/// flow (`runner`, sampled; its map index 0 is `map`), scored by the mean individual reward
/// per agent-step. `progress` sees every iteration.
pub fn fit_scenario(
    map: &Arc<Map>,
    sim: &Arc<SimConfig>,
    runner: &PolicyRunner,
    s: &FitSettings,
    mut progress: impl FnMut(&IterationLog),
) -> Result<(Coordinator, Vec<IterationLog>), CoordinatorError> {
    if s.population == 0
        || s.episodes == 0
        || s.envs == 0
        || s.vehicles.0 == 0
        || s.vehicles.0 > s.vehicles.1
        || !(s.elite_frac > 0.0 && s.elite_frac <= 1.0)
    {
        return Err(CoordinatorError::Settings(s.clone()));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
    let mut coord = Coordinator::default();
    let mut history = Vec::new();
    let (pop, eps) = (s.population as usize, s.episodes as usize);
    let drivers = Drivers { alive: Actor::sampled(runner), background: None, adversary: None };
    let mut case_id = 0u32;
    for iteration in 0..s.iterations {
        let cand = coord.propose(&mut rng, pop);
        let mut specs = Vec::with_capacity(pop * eps);
        for (p, &svo) in cand.iter().enumerate() {
            for e in 0..eps {
                let n = rng.random_range(s.vehicles.0..=s.vehicles.1) as usize;
                specs.push(EpisodeSpec {
                    case: random_case(map, &mut rng, case_id, n),
                    vehicles: None,
                    svo_deg: Some(svo),
                    tag: (p * eps + e) as u64,
                });
                case_id += 1;
            }
        }
        let mut v = VecEnv::from_episodes(
            Arc::clone(map),
            Arc::clone(sim),
            Mode::MultiAgent,
            s.envs,
            specs,
        )?;
        let (mut sum, mut count) = (vec![0f64; pop], vec![0u64; pop]);
        run_episodes(&mut v, &drivers, |v, tags| {
            for (r, st) in v.row_steps().iter().enumerate().filter(|(_, st)| st.stepped) {
                if let Some(t) = tags[r / v.max_agents] {
                    sum[t as usize / eps] += st.rewards.individual as f64;
                    count[t as usize / eps] += 1;
                }
            }
        });
        let scores: Vec<f32> =
            sum.iter().zip(&count).map(|(s, &n)| (s / n.max(1) as f64) as f32).collect();
        coord.update(&cand, &scores, s.elite_frac);
        let log = IterationLog {
            iteration,
            mean_deg: coord.mean_deg,
            std_deg: coord.std_deg,
            mean_reward: scores.iter().sum::<f32>() / scores.len() as f32,
            best_reward: scores.iter().copied().fold(f32::NEG_INFINITY, f32::max),
        };
        progress(&log);
        history.push(log);
    }
    Ok((coord, history))
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
