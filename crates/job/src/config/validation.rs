//! `[validation]` (held-out selection of the actor during training) and `[coordinator]` (CoPO's
//! Stage 2): the optional sections, their defaults and their checks. Must not: read other
//! sections than the job's kind.

use serde::{Deserialize, Serialize};

use super::{bad, ConfigError, JobConfig, JobKind};

/// A held-out evaluation of the training actor (mean action) every `every_updates` updates on
/// `episodes` generated cases per scenario, drawn once from `seed` like the training episodes
/// (the job's vehicle range and `env.conflict_share`) and the same at every point, so points
/// are paired. The job's final policy (`policy.bpk`) is the best-scoring actor (success, then
/// safety; the earlier on ties); `validation.csv` holds every point. The checkpoint, and so
/// `train.init_job` continuations, keep the last SAC state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ValidationSection {
    pub every_updates: u64,
    /// Generated cases per scenario.
    pub episodes: u32,
    /// Seeds the cases: keep it apart from evaluation's (the ladder's generated cases use 2026).
    pub seed: u64,
    /// Simulators stepped together.
    pub envs: usize,
    /// Seeds the test cases: generated like the validation cases but from this seed, and
    /// scored once, at the end, with the kept actor and the IDM driver. They select nothing,
    /// so the side-by-side a finished job reports is on cases apart from those that chose its
    /// actor. Default: `seed + 1`; must differ from `seed`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub test_seed: Option<u64>,
    /// Test cases per scenario (default: `episodes`); 0 skips the test.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub test_episodes: Option<u32>,
}

impl Default for ValidationSection {
    fn default() -> Self {
        Self {
            every_updates: 500,
            episodes: 100,
            seed: 0x76_616c,
            envs: 25,
            test_seed: None,
            test_episodes: None,
        }
    }
}

impl ValidationSection {
    /// The seed of the test cases.
    pub fn test_seed(&self) -> u64 {
        self.test_seed.unwrap_or(self.seed.wrapping_add(1))
    }

    /// Test cases per scenario (0: no test).
    pub fn test_episodes(&self) -> u32 {
        self.test_episodes.unwrap_or(self.episodes)
    }
}

/// CoPO's Stage-2 coordinator: the cross-entropy method over a Gaussian on the SVO, per
/// scenario, each candidate SVO scored by the frozen Stage-1 flow's mean individual reward
/// with every agent at that SVO (generated cases of the job's vehicle range).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CoordinatorSection {
    /// CEM iterations per scenario; 0 leaves the flow at Stage 1 (SVOs uniform in [0, 90]).
    pub iterations: u32,
    /// Candidate SVOs per iteration.
    pub population: u32,
    /// Episodes scoring each candidate.
    pub episodes: u32,
    /// Fraction of the candidates the Gaussian is refitted to.
    pub elite_frac: f32,
    /// Simulators stepped together while scoring.
    pub envs: usize,
}

impl Default for CoordinatorSection {
    fn default() -> Self {
        Self { iterations: 6, population: 12, episodes: 1, elite_frac: 0.25, envs: 12 }
    }
}

impl JobConfig {
    /// The optional `[coordinator]` (CoPO Stage 2) and `[validation]` sections.
    pub(super) fn validate_sections(&self) -> Result<(), ConfigError> {
        if let Some(c) = &self.coordinator {
            if self.kind != JobKind::Copo {
                return bad(
                    "coordinator",
                    format!("only copo jobs fit a Stage-2 coordinator, not {}", self.kind.as_str()),
                );
            }
            if c.iterations > 1000 {
                return bad(
                    "coordinator.iterations",
                    format!("{} must be at most 1000", c.iterations),
                );
            }
            for (f, v) in
                [("coordinator.population", c.population), ("coordinator.episodes", c.episodes)]
            {
                if v == 0 || v > 10_000 {
                    return bad(f, format!("{v} must be in 1..=10000"));
                }
            }
            if !(c.elite_frac > 0.0 && c.elite_frac <= 1.0) {
                return bad(
                    "coordinator.elite_frac",
                    format!("{} must be in (0, 1]", c.elite_frac),
                );
            }
            if c.envs == 0 || c.envs > 256 {
                return bad("coordinator.envs", format!("{} must be in 1..=256", c.envs));
            }
        }
        if let Some(v) = &self.validation {
            if !(self.kind == JobKind::Ego || self.kind.multi_agent()) {
                return bad(
                    "validation",
                    format!(
                        "selects drivers by success: ego and flow jobs only, not {} (an adversary)",
                        self.kind.as_str()
                    ),
                );
            }
            if v.every_updates == 0 {
                return bad("validation.every_updates", "must be positive");
            }
            if v.episodes == 0 || v.episodes > 10_000 {
                return bad("validation.episodes", format!("{} must be in 1..=10000", v.episodes));
            }
            if v.envs == 0 || v.envs > 256 {
                return bad("validation.envs", format!("{} must be in 1..=256", v.envs));
            }
            if v.test_seed() == v.seed {
                return bad(
                    "validation.test_seed",
                    format!("{} is the validation seed: the test cases must be apart from the cases that select the actor", v.seed),
                );
            }
            if v.test_episodes() > 10_000 {
                return bad(
                    "validation.test_episodes",
                    format!("{} must be in 0..=10000", v.test_episodes()),
                );
            }
        }
        Ok(())
    }
}
