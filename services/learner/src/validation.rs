//! Policy selection by a held-out evaluation during training (a job's `[validation]`), and
//! the test that reports the selected policy on cases apart from those that selected it.
//!
//! Owns: the job's validation cases and test cases (generated once from the section's `seed`
//! and `test_seed`, like the training episodes), scoring a training actor on them in the job's
//! own setting (an ego with its mean action among IDM or its frozen flow; a flow driving every
//! vehicle with sampled actions, as flows act in evaluations), and which point is best
//! ([`ValidationPoint::better_than`], [`BestPolicy`]). Must not: write files or touch the SAC
//! state (the trainer does both), nor let the test cases choose anything (they are scored only
//! once the actor is chosen), nor pick cases the final evaluation grid uses.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sf_job::config::ValidationSection;
use sf_job::{Frozen, JobConfig};
use sf_rollout::evaluate::{self, EgoDef, FlowDef, Policy, Runners};
use sf_rollout::setup;
use sf_sim::{Case, Map};

use crate::error::LearnerError;

/// One validation of the training actor: the means over every scenario's cases.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ValidationPoint {
    pub updates: u64,
    pub env_steps: u64,
    pub episodes: u32,
    #[serde(flatten)]
    pub scores: sf_sim::Scores,
    pub collision: f32,
    /// Seconds the validation took.
    pub took_s: f32,
}

impl ValidationPoint {
    pub const CSV_HEADER: &'static str =
        "updates,env_steps,episodes,success,safety,collision,speed,took_s";

    pub fn csv_row(&self) -> String {
        format!(
            "{},{},{},{},{},{},{},{:.2}",
            self.updates,
            self.env_steps,
            self.episodes,
            self.scores.success,
            self.scores.safety,
            self.collision,
            self.scores.speed,
            self.took_s
        )
    }

    /// Higher success, then higher safety; a tie keeps the earlier point.
    pub fn better_than(&self, other: &Self) -> bool {
        self.scores.success > other.scores.success
            || (self.scores.success == other.scores.success
                && self.scores.safety > other.scores.safety)
    }
}

/// The best-scoring actor so far: its weights in `best_policy.bpk` and its point in
/// `best_policy.json` beside them, written in that order so the point on disk always
/// describes the bytes on disk (a restart reads both back).
pub struct BestPolicy {
    dir: PathBuf,
    pub point: Option<ValidationPoint>,
}

impl BestPolicy {
    const WEIGHTS: &'static str = "best_policy.bpk";
    const POINT: &'static str = "best_policy.json";

    /// The best so far of a job directory (none for a fresh job).
    pub fn load(dir: &Path) -> Result<Self, LearnerError> {
        let p = dir.join(Self::POINT);
        let point = match std::fs::read_to_string(&p) {
            Ok(text) if dir.join(Self::WEIGHTS).exists() => Some(
                serde_json::from_str(&text)
                    .map_err(|source| LearnerError::StateFile { path: p, source })?,
            ),
            Ok(_) => None,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(source) => return Err(LearnerError::Io { action: "reading", path: p, source }),
        };
        Ok(Self { dir: dir.to_path_buf(), point })
    }

    /// Keeps `weights` if `point` beats the best so far; whether it did.
    pub fn offer(&mut self, point: &ValidationPoint, weights: &[u8]) -> Result<bool, LearnerError> {
        if self.point.as_ref().is_some_and(|b| !point.better_than(b)) {
            return Ok(false);
        }
        crate::artifacts::write_atomic(&self.dir.join(Self::WEIGHTS), weights)?;
        crate::artifacts::write_atomic(
            &self.dir.join(Self::POINT),
            serde_json::to_string(point)?.as_bytes(),
        )?;
        self.point = Some(point.clone());
        Ok(true)
    }

    /// The best actor's weights and point, if any was kept.
    pub fn take(&self) -> Result<Option<(Vec<u8>, ValidationPoint)>, LearnerError> {
        let Some(point) = self.point.clone() else { return Ok(None) };
        let bytes = crate::artifacts::read(&self.dir.join(Self::WEIGHTS))?;
        Ok(Some((bytes, point)))
    }
}

/// A job's validation cases and the policies they run with.
pub struct Validator {
    pub section: ValidationSection,
    cfg: JobConfig,
    /// An ego job's flow (IDM, or its frozen flow); `None` for a flow job, which drives
    /// every vehicle itself.
    flow: Option<FlowDef>,
    cases: Vec<(Arc<Map>, Vec<Case>)>,
    /// The test cases (`test_seed`); empty with `test_episodes = 0`.
    test: Vec<(Arc<Map>, Vec<Case>)>,
    runners: Runners,
}

/// The kept actor and the IDM driver in its seat on the test cases, which selected nothing.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TestScores {
    /// The seed the test cases were generated from (`validation.test_seed`).
    pub seed: u64,
    /// Always false: the test cases choose nothing.
    pub used_for_selection: bool,
    pub policy: ValidationPoint,
    pub idm: ValidationPoint,
}

impl Validator {
    /// `frozen` and `weights`: the policies the job acts with (an ego job's background flow),
    /// `weights[i]` belonging to `frozen[i]`.
    pub fn new(
        section: ValidationSection,
        cfg: &JobConfig,
        maps: &[Arc<Map>],
        frozen: &[Frozen],
        weights: &[Arc<Vec<u8>>],
    ) -> Result<Self, LearnerError> {
        let flow =
            if cfg.kind.is_flow() { None } else { Some(evaluate::from_frozen(frozen, weights)?.0) };
        let sim =
            Arc::new(setup::resolve(cfg, flow.as_ref().and_then(FlowDef::background_config)).sim);
        let vehicles = (cfg.env.vehicles_min, cfg.env.vehicles_max);
        let draw = |seed: u64, episodes: u32| -> Vec<(Arc<Map>, Vec<Case>)> {
            if episodes == 0 {
                return Vec::new();
            }
            maps.iter()
                .enumerate()
                .map(|(k, map)| {
                    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ ((k as u64) << 32));
                    let cases = sf_sim::vec_env::draw_cases(
                        map,
                        &sim,
                        &mut rng,
                        episodes,
                        vehicles,
                        cfg.case_draw(),
                    );
                    (Arc::clone(map), cases)
                })
                .collect()
        };
        let cases = draw(section.seed, section.episodes);
        let test = draw(section.test_seed(), section.test_episodes());
        let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?;
        Ok(Self { section, cfg: cfg.clone(), flow, cases, test, runners: Runners::new(device) })
    }

    /// The kept actor `weights` (selected at `updates`) and the IDM driver in its seat on the
    /// test cases; `None` with `test_episodes = 0`.
    pub fn test(
        &mut self,
        weights: &[u8],
        updates: u64,
    ) -> Result<Option<TestScores>, LearnerError> {
        if self.test.is_empty() {
            return Ok(None);
        }
        let policy = self.policy(weights, &format!("test@{updates}"));
        let (flow, ego) = self.seat(&policy);
        let (idm_flow, idm_ego) = self.idm_seat();
        let test = std::mem::take(&mut self.test);
        let scored = self
            .run_on(&test, &flow, ego.as_ref(), updates, 0)
            .and_then(|p| Ok((p, self.run_on(&test, &idm_flow, idm_ego.as_ref(), 0, 0)?)));
        self.test = test;
        self.runners.forget(&policy.key);
        let (policy, idm) = scored?;
        Ok(Some(TestScores {
            seed: self.section.test_seed(),
            used_for_selection: false,
            policy,
            idm,
        }))
    }

    fn policy(&self, weights: &[u8], key: &str) -> Policy {
        Policy::new(key.to_string(), self.cfg.clone(), Arc::new(weights.to_vec()), Vec::new())
    }

    /// Where a learned `policy` of the job acts: in the ego's seat among the job's flow, or as
    /// the flow itself.
    fn seat(&self, policy: &Policy) -> (FlowDef, Option<EgoDef>) {
        match &self.flow {
            Some(flow) => (flow.clone(), Some(EgoDef::Learned(policy.clone()))),
            None => (FlowDef::learned(policy.clone(), None), None),
        }
    }

    /// The IDM driver in the job's seat: an ego job's IDM ego among its flow, a flow job's
    /// all-IDM flow.
    fn idm_seat(&self) -> (FlowDef, Option<EgoDef>) {
        match &self.flow {
            Some(flow) => (flow.clone(), Some(EgoDef::Idm)),
            None => (FlowDef::Idm, None),
        }
    }

    /// Scores the actor `weights` (mean action) on every scenario's cases.
    pub fn score(
        &mut self,
        weights: &[u8],
        updates: u64,
        env_steps: u64,
    ) -> Result<ValidationPoint, LearnerError> {
        let policy = self.policy(weights, &format!("validation@{updates}"));
        let (flow, ego) = self.seat(&policy);
        let cases = std::mem::take(&mut self.cases);
        let point = self.run_on(&cases, &flow, ego.as_ref(), updates, env_steps);
        self.cases = cases;
        self.runners.forget(&policy.key);
        point
    }

    /// The IDM driver in the job's seat on the same cases, the score a learned policy is read
    /// against: an ego job's IDM ego among its flow, a flow job's all-IDM flow.
    pub fn score_idm(&mut self) -> Result<ValidationPoint, LearnerError> {
        let (flow, ego) = self.idm_seat();
        let cases = std::mem::take(&mut self.cases);
        let point = self.run_on(&cases, &flow, ego.as_ref(), 0, 0);
        self.cases = cases;
        point
    }

    fn run_on(
        &mut self,
        case_sets: &[(Arc<Map>, Vec<Case>)],
        flow: &FlowDef,
        ego: Option<&EgoDef>,
        updates: u64,
        env_steps: u64,
    ) -> Result<ValidationPoint, LearnerError> {
        let t = std::time::Instant::now();
        let mut rows = Vec::new();
        for (map, cases) in case_sets {
            rows.extend(evaluate::run_cases(
                map,
                cases,
                1,
                self.section.envs,
                flow,
                ego,
                &mut self.runners,
            )?);
        }
        let n = rows.len().max(1) as f32;
        let mean = |f: fn(&sf_job::eval::EvalEpisode) -> f32| rows.iter().map(f).sum::<f32>() / n;
        Ok(ValidationPoint {
            updates,
            env_steps,
            episodes: rows.len() as u32,
            scores: sf_job::Scores::mean(rows.iter().map(|r| r.scores)),
            collision: mean(|r| r.collision),
            took_s: t.elapsed().as_secs_f32(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pt(updates: u64, success: f32, safety: f32) -> ValidationPoint {
        ValidationPoint {
            updates,
            scores: sf_job::Scores { success, safety, speed: 0.0 },
            ..Default::default()
        }
    }

    #[test]
    fn better_means_success_then_safety_and_ties_keep_the_earlier() {
        assert!(pt(2, 0.9, 0.1).better_than(&pt(1, 0.8, 1.0)));
        assert!(pt(2, 0.9, 0.95).better_than(&pt(1, 0.9, 0.9)));
        assert!(!pt(2, 0.9, 0.9).better_than(&pt(1, 0.9, 0.9)), "a tie keeps the earlier point");
        assert!(!pt(2, 0.7, 1.0).better_than(&pt(1, 0.8, 0.0)));
    }

    #[test]
    fn best_policy_keeps_the_best_weights_with_their_point_across_a_restart() {
        let dir = std::env::temp_dir().join(format!("sf-best-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        let mut b = BestPolicy::load(&dir).expect("fresh");
        assert!(b.take().expect("none").is_none());
        assert!(b.offer(&pt(500, 0.6, 0.7), b"first").expect("kept"));
        assert!(b.offer(&pt(1000, 0.8, 0.8), b"second").expect("kept"));
        assert!(!b.offer(&pt(1500, 0.7, 1.0), b"third").expect("not kept"));
        assert!(!b.offer(&pt(2000, 0.8, 0.8), b"tie").expect("a tie is not kept"));
        let again = BestPolicy::load(&dir).expect("restart");
        let (bytes, point) = again.take().expect("read").expect("kept");
        assert_eq!((bytes.as_slice(), point.updates), (&b"second"[..], 1000));
        std::fs::write(dir.join("best_policy.json"), "{not json").expect("corrupt");
        let e = BestPolicy::load(&dir).err().expect("a corrupt point is refused");
        assert!(e.to_string().contains("best_policy.json"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
