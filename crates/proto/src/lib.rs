//! The `socialflow.v1` wire format.
//!
//! Owns: the code generated from `proto/socialflow/v1/socialflow.proto` (module [`pb`]) and
//! the only conversions between wire messages and the domain types of `sf_job` (training
//! assignments and batches, evaluation cells and their episodes). Decoding
//! validates: enum values, shapes (every array holds `count` rows of the declared widths),
//! finiteness, size caps. Must not: hold service logic. Other crates pass domain types
//! between their modules; wire types appear only at their gRPC edges (the learner's tonic
//! service, the worker's session and the rollout thread's outgoing batches).

use half::f16;
use sf_job::eval::{Cell, EvalEpisode, EvalWork, ScriptedEgo};
use sf_job::{
    ActedBy, Assignment, Ends, EpisodeResult, Frozen, FrozenRole, JobId, JobRecord, JobState,
    Learning, PolicyRequest, PolicyVersion, Progress, Scores, TransitionBatch,
};

#[allow(clippy::all, missing_docs)]
pub mod pb {
    tonic::include_proto!("socialflow.v1");
}

/// The encoded `FileDescriptorSet` of `socialflow.v1`, for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("socialflow_descriptor");

/// A wire message that does not decode into a valid domain value.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("field `{field}`: {reason}")]
pub struct WireError {
    pub field: &'static str,
    pub reason: String,
}

fn wire<T>(field: &'static str, reason: impl Into<String>) -> Result<T, WireError> {
    Err(WireError { field, reason: reason.into() })
}

pub fn state_to_wire(s: JobState) -> pb::JobState {
    match s {
        JobState::Queued => pb::JobState::Queued,
        JobState::Running => pb::JobState::Running,
        JobState::Succeeded => pb::JobState::Succeeded,
        JobState::Failed => pb::JobState::Failed,
        JobState::Cancelled => pb::JobState::Cancelled,
    }
}

pub fn state_from_wire(v: i32) -> Result<JobState, WireError> {
    match pb::JobState::try_from(v) {
        Ok(pb::JobState::Queued) => Ok(JobState::Queued),
        Ok(pb::JobState::Running) => Ok(JobState::Running),
        Ok(pb::JobState::Succeeded) => Ok(JobState::Succeeded),
        Ok(pb::JobState::Failed) => Ok(JobState::Failed),
        Ok(pb::JobState::Cancelled) => Ok(JobState::Cancelled),
        Ok(pb::JobState::Unspecified) | Err(_) => wire("state", format!("{v} is not a job state")),
    }
}

pub fn progress_to_wire(job_id: JobId, state: JobState, progress: &Progress) -> pb::JobProgress {
    let p = &progress.learning;
    pb::JobProgress {
        job_id: job_id.get(),
        state: state_to_wire(state) as i32,
        env_steps: p.env_steps,
        target_env_steps: progress.target_env_steps,
        updates: p.updates,
        policy_version: progress.policy_version.get(),
        episodes: p.episodes,
        success: p.scores.success,
        safety: p.scores.safety,
        speed: p.scores.speed,
        critic_loss: p.critic_loss,
        actor_loss: p.actor_loss,
        alpha: p.alpha,
        env_steps_per_s: progress.env_steps_per_s,
        wall_s: p.wall_s,
        dropped_stale: progress.dropped_stale,
        validation: progress.validation.map(|v| pb::ValidationProgress {
            updates: v.updates,
            success: v.success,
            best_updates: v.best_updates,
            best_success: v.best_success,
        }),
    }
}

pub fn progress_from_wire(p: &pb::JobProgress) -> Result<(JobState, Progress), WireError> {
    Ok((
        state_from_wire(p.state)?,
        Progress {
            learning: Learning {
                env_steps: p.env_steps,
                updates: p.updates,
                episodes: p.episodes,
                scores: Scores { success: p.success, safety: p.safety, speed: p.speed },
                critic_loss: p.critic_loss,
                actor_loss: p.actor_loss,
                alpha: p.alpha,
                wall_s: p.wall_s,
            },
            target_env_steps: p.target_env_steps,
            policy_version: p.policy_version.into(),
            env_steps_per_s: p.env_steps_per_s,
            dropped_stale: p.dropped_stale,
            validation: p.validation.as_ref().map(validation_from_wire).transpose()?,
        },
    ))
}

fn validation_from_wire(
    v: &pb::ValidationProgress,
) -> Result<sf_job::ValidationProgress, WireError> {
    for (field, x) in [
        ("JobProgress.validation.success", v.success),
        ("JobProgress.validation.best_success", v.best_success),
    ] {
        if !(0.0..=1.0).contains(&x) {
            return wire(field, format!("{x} is not in [0, 1]"));
        }
    }
    Ok(sf_job::ValidationProgress {
        updates: v.updates,
        success: v.success,
        best_updates: v.best_updates,
        best_success: v.best_success,
    })
}

pub fn job_to_wire(j: &JobRecord) -> pb::Job {
    pb::Job {
        job_id: j.id.get(),
        name: j.name.clone(),
        state: state_to_wire(j.state) as i32,
        config_toml: j.config_toml.clone(),
        message: j.message.clone(),
        created_unix_ms: j.created_unix_ms,
        updated_unix_ms: j.updated_unix_ms,
        progress: Some(progress_to_wire(j.id, j.state, &j.progress)),
        artifact_dir: j.artifact_dir.clone(),
    }
}

pub fn job_from_wire(j: &pb::Job) -> Result<JobRecord, WireError> {
    let progress = match &j.progress {
        Some(p) => progress_from_wire(p)?.1,
        None => Progress::default(),
    };
    Ok(JobRecord {
        id: j.job_id.into(),
        name: j.name.clone(),
        state: state_from_wire(j.state)?,
        config_toml: j.config_toml.clone(),
        message: j.message.clone(),
        created_unix_ms: j.created_unix_ms,
        updated_unix_ms: j.updated_unix_ms,
        progress,
        artifact_dir: j.artifact_dir.clone(),
    })
}

pub fn assignment_to_wire(a: &Assignment) -> pb::Assignment {
    pb::Assignment {
        job_id: a.job_id.get(),
        config_toml: a.config_toml.clone(),
        scenario_index: a.scenario_index,
        seed: a.seed,
        policy_version: a.policy_version.get(),
        obs_len: a.obs_len,
        action_dim: a.action_dim,
        warmup: a.warmup,
        frozen: a.frozen.iter().map(frozen_to_wire).collect(),
    }
}

fn frozen_to_wire(f: &Frozen) -> pb::FrozenPolicy {
    pb::FrozenPolicy {
        role: match f.role {
            FrozenRole::Background => pb::FrozenRole::Background,
            FrozenRole::Ego => pb::FrozenRole::Ego,
            FrozenRole::Adversary => pb::FrozenRole::Adversary,
        } as i32,
        job_id: f.job_id.get(),
        config_toml: f.config_toml.clone(),
        svo_gaussians: f
            .svo_gaussians
            .iter()
            .map(|(s, g)| pb::ScenarioSvo {
                scenario: s.clone(),
                mean_deg: g.mean_deg,
                std_deg: g.std_deg,
            })
            .collect(),
    }
}

fn frozen_from_wire(f: &pb::FrozenPolicy) -> Result<Frozen, WireError> {
    let role = match pb::FrozenRole::try_from(f.role) {
        Ok(pb::FrozenRole::Background) => FrozenRole::Background,
        Ok(pb::FrozenRole::Ego) => FrozenRole::Ego,
        Ok(pb::FrozenRole::Adversary) => FrozenRole::Adversary,
        _ => {
            return wire(
                "assignment.frozen.role",
                format!("{} is not a frozen-policy role", f.role),
            )
        }
    };
    if f.job_id == 0 || f.config_toml.is_empty() {
        return wire("assignment.frozen.job_id", "a frozen policy names its job and config");
    }
    let mut svo_gaussians = Vec::with_capacity(f.svo_gaussians.len());
    for g in &f.svo_gaussians {
        let gauss = sf_job::SvoGaussian { mean_deg: g.mean_deg, std_deg: g.std_deg };
        if g.scenario.is_empty() {
            return wire("assignment.frozen.svo_gaussians.scenario", "must be set");
        }
        gauss.validate().map_err(|e| WireError {
            field: "assignment.frozen.svo_gaussians",
            reason: e.to_string(),
        })?;
        svo_gaussians.push((g.scenario.clone(), gauss));
    }
    Ok(Frozen { role, job_id: f.job_id.into(), config_toml: f.config_toml.clone(), svo_gaussians })
}

pub fn eval_work_to_wire(w: &EvalWork) -> pb::EvalAssignment {
    let c = &w.cell;
    pb::EvalAssignment {
        job_id: w.job_id.get(),
        cell_id: w.cell_id.get(),
        cell: Some(pb::EvalCell {
            experiment: c.experiment.clone(),
            ego: c.ego.clone(),
            flow: c.flow.clone(),
            scenario: c.scenario.clone(),
            svo_deg: c.svo_deg,
            vehicles: c.vehicles.map(|v| v as u32),
        }),
        cases: w.cases,
        seeds: w.seeds,
        envs: w.envs,
        policies: w.policies.iter().map(frozen_to_wire).collect(),
        ego_idm: w.scripted_ego.is_some(),
        ego_mobil: w.scripted_ego == Some(ScriptedEgo::IdmMobil),
    }
}

pub fn eval_work_from_wire(w: &pb::EvalAssignment) -> Result<EvalWork, WireError> {
    if w.job_id == 0 {
        return wire("eval.job_id", "must be set");
    }
    let Some(c) = &w.cell else { return wire("eval.cell", "must be set") };
    if c.flow.is_empty() || c.scenario.is_empty() || c.experiment.is_empty() {
        return wire("eval.cell", "experiment, flow and scenario must be set");
    }
    if w.cases == 0 || w.seeds == 0 || w.envs == 0 {
        return wire("eval.cases", "cases, seeds and envs must be positive");
    }
    if c.svo_deg.is_some_and(|s| s > 90) {
        return wire(
            "eval.cell.svo_deg",
            format!("{} is not in [0, 90]", c.svo_deg.unwrap_or_default()),
        );
    }
    let cell = Cell {
        experiment: c.experiment.clone(),
        ego: c.ego.clone(),
        flow: c.flow.clone(),
        scenario: c.scenario.clone(),
        svo_deg: c.svo_deg,
        vehicles: c.vehicles.map(|v| v as usize),
    };
    let policies = w.policies.iter().map(frozen_from_wire).collect::<Result<Vec<_>, _>>()?;
    // Who sits in the ego's seat: a cell that names an ego gets exactly one of the IDM
    // driver and an EGO policy; a cell without one (a flow on its own) gets neither.
    let ego_policy = policies.iter().any(|p| p.role == FrozenRole::Ego);
    if w.ego_mobil && !w.ego_idm {
        return wire(
            "eval.ego_mobil",
            "MOBIL's lane changes need the IDM driver (ego_idm) in the seat",
        );
    }
    match (cell.ego.is_empty(), w.ego_idm, ego_policy) {
        (true, false, false) | (false, true, false) | (false, false, true) => {}
        (true, _, _) => {
            return wire("eval.cell.ego", "a cell without an ego gets no EGO policy and no IDM ego")
        }
        (false, true, true) => {
            return wire(
                "eval.ego_idm",
                format!("the IDM driver and an EGO policy both given for ego `{}`", cell.ego),
            )
        }
        (false, false, false) => {
            return wire(
                "eval.policies",
                format!("ego `{}` has no EGO policy and is not the IDM driver", cell.ego),
            )
        }
    }
    Ok(EvalWork {
        job_id: w.job_id.into(),
        cell_id: w.cell_id.into(),
        cell,
        cases: w.cases,
        seeds: w.seeds,
        envs: w.envs,
        policies,
        scripted_ego: match (w.ego_idm, w.ego_mobil) {
            (false, _) => None,
            (true, false) => Some(ScriptedEgo::Idm),
            (true, true) => Some(ScriptedEgo::IdmMobil),
        },
    })
}

pub fn eval_episode_to_wire(e: &EvalEpisode) -> pb::EvalEpisode {
    pb::EvalEpisode {
        case_id: e.case,
        seed: e.seed,
        success: e.scores.success,
        safety: e.scores.safety,
        speed: e.scores.speed,
        collision: e.collision,
        lane_change: e.lane_change,
        road_closed: e.road_closed,
    }
}

/// Decodes and validates one episode's metrics.
pub fn eval_episode_from_wire(e: &pb::EvalEpisode) -> Result<EvalEpisode, WireError> {
    let ep = EvalEpisode {
        case: e.case_id,
        seed: e.seed,
        scores: Scores { success: e.success, safety: e.safety, speed: e.speed },
        collision: e.collision,
        lane_change: e.lane_change,
        road_closed: e.road_closed,
    };
    ep.validate().map_err(|e| WireError { field: "episodes", reason: e.to_string() })?;
    Ok(ep)
}

pub fn assignment_from_wire(a: &pb::Assignment) -> Result<Assignment, WireError> {
    if a.job_id == 0 {
        return wire("assignment.job_id", "must be set");
    }
    if a.obs_len == 0 || a.action_dim == 0 {
        return wire("assignment.obs_len", "observation length and action size must be positive");
    }
    Ok(Assignment {
        job_id: a.job_id.into(),
        config_toml: a.config_toml.clone(),
        scenario_index: a.scenario_index,
        seed: a.seed,
        policy_version: a.policy_version.into(),
        obs_len: a.obs_len,
        action_dim: a.action_dim,
        warmup: a.warmup,
        frozen: a.frozen.iter().map(frozen_from_wire).collect::<Result<_, _>>()?,
    })
}

fn f16_to_bytes(v: &[f16]) -> Vec<u8> {
    let mut out = Vec::with_capacity(v.len() * 2);
    for x in v {
        out.extend_from_slice(&x.to_bits().to_le_bytes());
    }
    out
}

fn f16_from_bytes(field: &'static str, b: &[u8], want: usize) -> Result<Vec<f16>, WireError> {
    // `want` is the peer's count x obs_len (up to (2^32 - 1)^2): its byte count may overflow.
    let Some(want_bytes) = want.checked_mul(2) else {
        return wire(
            "count",
            format!("count x obs_len ({want}) half floats overflow a byte count"),
        );
    };
    if b.len() != want_bytes {
        return wire(
            field,
            format!("{} bytes, expected {} ({} half floats)", b.len(), want_bytes, want),
        );
    }
    Ok(b.chunks_exact(2).map(|c| f16::from_bits(u16::from_le_bytes([c[0], c[1]]))).collect())
}

pub fn batch_to_wire(b: &TransitionBatch) -> pb::TransitionBatch {
    pb::TransitionBatch {
        job_id: b.job_id.get(),
        worker_id: b.worker_id.get(),
        policy_version: acted_by_to_wire(b.acted_by),
        count: b.count as u32,
        obs_len: b.obs_len as u32,
        action_dim: b.action_dim as u32,
        obs_f16: f16_to_bytes(&b.obs),
        next_obs_f16: f16_to_bytes(&b.next_obs),
        actions: b.actions.clone(),
        rewards: b.rewards.clone(),
        terminals: b.terminals.iter().map(|&t| t as u8).collect(),
        // One-step batches leave the field empty (what older learners and workers know).
        steps: if b.steps.iter().all(|&s| s == 1) { Vec::new() } else { b.steps.clone() },
        map_ids: b.map_ids.clone(),
        oracle_actions: b.oracle_actions.clone(),
        episodes: b
            .episodes
            .iter()
            .map(|e| pb::EpisodeResult {
                scenario_index: e.scenario_index,
                success: e.scores.success,
                safety: e.scores.safety,
                speed: e.scores.speed,
                collision: e.ends.collision,
                off_road: e.ends.off_road,
                off_route: e.ends.off_route,
                wrong_lane: e.ends.wrong_lane,
                timeout: e.ends.timeout,
            })
            .collect(),
        sim_steps: b.sim_steps,
    }
}

/// The wire spells warm-up actions as policy version 0.
pub fn acted_by_from_wire(version: u64) -> ActedBy {
    std::num::NonZeroU64::new(version).map_or(ActedBy::Warmup, ActedBy::Policy)
}

pub fn acted_by_to_wire(a: ActedBy) -> u64 {
    a.version().map_or(0, PolicyVersion::get)
}

/// The wire spells "the latest policy" as version 0.
pub fn policy_request_from_wire(version: u64) -> PolicyRequest {
    std::num::NonZeroU64::new(version).map_or(PolicyRequest::Latest, PolicyRequest::Version)
}

/// A `GetPolicy` request for `job_id`.
pub fn get_policy_to_wire(job_id: JobId, which: PolicyRequest) -> pb::GetPolicyRequest {
    pb::GetPolicyRequest {
        job_id: job_id.get(),
        version: which.version().map_or(0, PolicyVersion::get),
    }
}

/// Decodes and validates a batch (shapes, finiteness, flags).
pub fn batch_from_wire(m: pb::TransitionBatch) -> Result<TransitionBatch, WireError> {
    if m.job_id == 0 {
        return wire("job_id", "must be set");
    }
    let n = m.count as usize;
    let want = n
        .checked_mul(m.obs_len as usize)
        .ok_or(WireError { field: "count", reason: "count x obs_len overflows".into() })?;
    let obs = f16_from_bytes("obs_f16", &m.obs_f16, want)?;
    let next_obs = f16_from_bytes("next_obs_f16", &m.next_obs_f16, want)?;
    let mut terminals = Vec::with_capacity(m.terminals.len());
    for (i, &t) in m.terminals.iter().enumerate() {
        match t {
            0 => terminals.push(false),
            1 => terminals.push(true),
            _ => return wire("terminals", format!("byte {i} is {t}, expected 0 or 1")),
        }
    }
    let steps = if m.steps.is_empty() { vec![1; n] } else { m.steps };
    let b = TransitionBatch {
        job_id: m.job_id.into(),
        worker_id: m.worker_id.into(),
        acted_by: acted_by_from_wire(m.policy_version),
        count: n,
        obs_len: m.obs_len as usize,
        action_dim: m.action_dim as usize,
        obs,
        next_obs,
        actions: m.actions,
        rewards: m.rewards,
        terminals,
        steps,
        map_ids: m.map_ids,
        oracle_actions: m.oracle_actions,
        episodes: m
            .episodes
            .iter()
            .map(|e| EpisodeResult {
                scenario_index: e.scenario_index,
                scores: Scores { success: e.success, safety: e.safety, speed: e.speed },
                ends: Ends {
                    collision: e.collision,
                    off_road: e.off_road,
                    off_route: e.off_route,
                    wrong_lane: e.wrong_lane,
                    timeout: e.timeout,
                },
            })
            .collect(),
        sim_steps: m.sim_steps,
    };
    b.validate().map_err(|e| WireError { field: "batch", reason: e.to_string() })?;
    Ok(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_batch_round_trips_and_bad_ones_are_named() {
        let mut b = TransitionBatch::new(3.into(), 4.into(), 2, 2);
        b.push(&[0.5, -1.25], &[0.1, 0.2], 1.0, &[0.25, 2.0], true, 1);
        b.episodes.push(EpisodeResult {
            scenario_index: 1,
            scores: Scores { success: 1.0, safety: 1.0, speed: 0.5 },
            ends: Ends { collision: 0.25, timeout: 0.5, ..Ends::default() },
        });
        let back = batch_from_wire(batch_to_wire(&b)).expect("round trip");
        assert_eq!(back, b);

        let mut m = batch_to_wire(&b);
        m.obs_f16.pop();
        assert_eq!(batch_from_wire(m).expect_err("short").field, "obs_f16");
        let mut m = batch_to_wire(&b);
        m.terminals[0] = 7;
        assert_eq!(batch_from_wire(m).expect_err("flag").field, "terminals");
        let mut m = batch_to_wire(&b);
        m.rewards[0] = f32::NAN;
        let e = batch_from_wire(m).expect_err("nan");
        assert!(e.reason.contains("rewards"), "{e}");
        // n-step transitions carry their spans; one-step batches send none and decode to 1s.
        assert!(batch_to_wire(&b).steps.is_empty());
        b.steps[0] = 3;
        assert_eq!(batch_to_wire(&b).steps, vec![3]);
        assert_eq!(batch_from_wire(batch_to_wire(&b)).expect("n-step round trip"), b);
        let mut m = batch_to_wire(&b);
        m.steps = vec![3, 1];
        assert!(batch_from_wire(m).expect_err("steps shape").reason.contains("steps"));
        let mut m = batch_to_wire(&b);
        m.steps = vec![0];
        assert!(batch_from_wire(m).expect_err("zero steps").reason.contains("steps"));
        let mut m = batch_to_wire(&b);
        m.obs_f16[0..2].copy_from_slice(&f16::NAN.to_bits().to_le_bytes());
        assert!(batch_from_wire(m).expect_err("nan obs").reason.contains("obs_f16"));
        // Oracle labels travel with their batch; a short column is named.
        b.oracle_actions = vec![0.5, -0.25];
        assert_eq!(batch_from_wire(batch_to_wire(&b)).expect("labelled round trip"), b);
        let mut m = batch_to_wire(&b);
        m.oracle_actions.pop();
        assert!(batch_from_wire(m).expect_err("labels shape").reason.contains("oracle_actions"));
    }

    /// The wire's version 0 means warm-up data in a batch and "the latest" in a policy
    /// request; the domain keeps the two apart.
    #[test]
    fn version_zero_decodes_to_warm_up_or_latest_by_message() {
        use std::num::NonZeroU64;
        let five = NonZeroU64::new(5).expect("non-zero");
        assert_eq!(
            (acted_by_from_wire(0), acted_by_from_wire(5)),
            (ActedBy::Warmup, ActedBy::Policy(five))
        );
        assert_eq!(
            (acted_by_to_wire(ActedBy::Warmup), acted_by_to_wire(ActedBy::Policy(five))),
            (0, 5)
        );
        assert_eq!(
            (policy_request_from_wire(0), policy_request_from_wire(5)),
            (PolicyRequest::Latest, PolicyRequest::Version(five))
        );
        for which in [PolicyRequest::Latest, PolicyRequest::Version(five)] {
            let m = get_policy_to_wire(9.into(), which);
            assert_eq!((m.job_id, policy_request_from_wire(m.version)), (9, which));
        }
        let mut b = TransitionBatch::new(1.into(), 2.into(), 1, 1);
        b.push(&[0.0], &[0.0], 0.0, &[0.0], false, 0);
        for acted_by in [ActedBy::Warmup, ActedBy::Policy(five)] {
            b.acted_by = acted_by;
            assert_eq!(batch_from_wire(batch_to_wire(&b)).expect("valid").acted_by, acted_by);
        }
    }

    /// Regression (found by `tests/fuzz.rs`): shape fields whose byte count overflows 64 bits
    /// are refused, not a multiplication overflow panic.
    #[test]
    fn huge_shapes_are_refused_without_overflow() {
        let mut b = TransitionBatch::new(3.into(), 4.into(), 2, 2);
        b.push(&[0.5, -1.25], &[0.1, 0.2], 1.0, &[0.25, 2.0], true, 1);
        let mut m = batch_to_wire(&b);
        (m.count, m.obs_len, m.action_dim) = (u32::MAX, u32::MAX, u32::MAX);
        assert_eq!(batch_from_wire(m).expect_err("huge shape").field, "count");
    }

    #[test]
    fn an_assignment_carries_its_frozen_policies_and_coordinator_gaussians() {
        let mut bg = Frozen::new(FrozenRole::Background, 2.into(), "name = \"flow\"".into());
        bg.svo_gaussians =
            vec![("merge".into(), sf_job::SvoGaussian { mean_deg: 45.0, std_deg: 4.5 })];
        let a = Assignment {
            job_id: 5.into(),
            config_toml: "name = \"ego\"".into(),
            scenario_index: 0,
            seed: 9,
            policy_version: 3.into(),
            obs_len: 10,
            action_dim: 2,
            warmup: false,
            frozen: vec![bg, Frozen::new(FrozenRole::Ego, 4.into(), "name = \"e\"".into())],
        };
        let back = assignment_from_wire(&assignment_to_wire(&a)).expect("round trip");
        assert_eq!(back, a);
        assert_eq!(back.frozen[0].svo_gaussian("merge").map(|g| g.mean_deg), Some(45.0));
        assert_eq!(back.frozen[0].svo_gaussian("intersection"), None);
        let mut m = assignment_to_wire(&a);
        m.frozen[0].svo_gaussians[0].mean_deg = 120.0;
        assert_eq!(
            assignment_from_wire(&m).expect_err("out of range").field,
            "assignment.frozen.svo_gaussians"
        );
        let mut m = assignment_to_wire(&a);
        m.frozen[0].svo_gaussians[0].std_deg = f32::NAN;
        assert!(assignment_from_wire(&m).is_err());
    }

    #[test]
    fn an_eval_cell_round_trips_and_bad_metrics_are_named() {
        let w = EvalWork {
            job_id: 3.into(),
            cell_id: 17.into(),
            cell: Cell {
                experiment: "svo_sweep".into(),
                ego: String::new(),
                flow: "CoPO".into(),
                scenario: "merge".into(),
                svo_deg: Some(40),
                vehicles: None,
            },
            cases: 20,
            seeds: 2,
            envs: 40,
            policies: vec![Frozen::new(FrozenRole::Background, 2.into(), "name = \"flow\"".into())],
            scripted_ego: None,
        };
        assert_eq!(eval_work_from_wire(&eval_work_to_wire(&w)), Ok(w.clone()));
        // Who sits in the ego's seat: exactly one of the IDM driver and an EGO policy when the
        // cell names an ego, neither when it does not.
        let idm_ego = EvalWork {
            cell: Cell {
                experiment: "cross".into(),
                ego: "IDM ego".into(),
                svo_deg: None,
                ..w.cell.clone()
            },
            scripted_ego: Some(ScriptedEgo::Idm),
            ..w.clone()
        };
        assert_eq!(eval_work_from_wire(&eval_work_to_wire(&idm_ego)), Ok(idm_ego.clone()));
        let mobil_ego = EvalWork { scripted_ego: Some(ScriptedEgo::IdmMobil), ..idm_ego.clone() };
        let m = eval_work_to_wire(&mobil_ego);
        assert!(m.ego_idm && m.ego_mobil);
        assert_eq!(eval_work_from_wire(&m), Ok(mobil_ego));
        let mut m = eval_work_to_wire(&idm_ego);
        m.ego_idm = false;
        m.ego_mobil = true;
        assert_eq!(eval_work_from_wire(&m).expect_err("MOBIL alone").field, "eval.ego_mobil");
        let mut m = eval_work_to_wire(&idm_ego);
        m.policies.push(frozen_to_wire(&Frozen::new(
            FrozenRole::Ego,
            5.into(),
            "name = \"e\"".into(),
        )));
        assert_eq!(eval_work_from_wire(&m).expect_err("both").field, "eval.ego_idm");
        m.ego_idm = false;
        assert!(eval_work_from_wire(&m).is_ok(), "a learned ego");
        m.policies.pop();
        assert_eq!(eval_work_from_wire(&m).expect_err("no ego at all").field, "eval.policies");
        let mut m = eval_work_to_wire(&w);
        m.ego_idm = true;
        assert_eq!(
            eval_work_from_wire(&m).expect_err("an IDM ego in a flow-only cell").field,
            "eval.cell.ego"
        );
        let mut m = eval_work_to_wire(&w);
        m.cell = None;
        assert_eq!(eval_work_from_wire(&m).expect_err("no cell").field, "eval.cell");
        let mut m = eval_work_to_wire(&w);
        m.seeds = 0;
        assert!(eval_work_from_wire(&m).is_err());
        let e = EvalEpisode {
            case: 4,
            seed: 1,
            scores: Scores { success: 1.0, safety: 0.5, speed: 0.7 },
            collision: 0.0,
            lane_change: Some(0.25),
            road_closed: Some(1.0),
        };
        assert_eq!(eval_episode_from_wire(&eval_episode_to_wire(&e)), Ok(e));
        // A worker that predates the lane-change share leaves it unset: read as not recorded.
        let mut m = eval_episode_to_wire(&e);
        m.lane_change = None;
        assert_eq!(eval_episode_from_wire(&m), Ok(EvalEpisode { lane_change: None, ..e }));
        m.lane_change = Some(2.0);
        assert!(eval_episode_from_wire(&m).expect_err("range").reason.contains("lane_change"));
        let mut m = eval_episode_to_wire(&e);
        m.road_closed = None;
        assert_eq!(eval_episode_from_wire(&m), Ok(EvalEpisode { road_closed: None, ..e }));
        m.road_closed = Some(-0.5);
        assert!(eval_episode_from_wire(&m).expect_err("range").reason.contains("road_closed"));
        let mut m = eval_episode_to_wire(&e);
        m.speed = f32::NAN;
        assert_eq!(eval_episode_from_wire(&m).expect_err("nan").field, "episodes");
        m.speed = 1.5;
        assert!(eval_episode_from_wire(&m).expect_err("range").reason.contains("speed"));
    }

    #[test]
    fn unknown_job_states_are_refused() {
        assert!(state_from_wire(99).is_err());
        assert!(state_from_wire(0).is_err());
        assert_eq!(state_from_wire(state_to_wire(JobState::Running) as i32), Ok(JobState::Running));
    }
}
