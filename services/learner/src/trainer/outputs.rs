//! What a training job writes besides its checkpoint: the kept actors
//! (`train.keep_actors_at`), each validation point and the best actor so far, the final policy
//! (`policy.bpk` and `policy.json`, with the held-out and test scores) and CoPO's Stage-2
//! coordinator. Must not: decide when these happen (the trainer's loop does) or touch the SAC
//! state.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use sf_job::{PolicyRequest, PolicyVersion};
use sf_report::tensorboard::EventWriter;
use sf_rollout::setup;
use sf_sac::Sac;
use sf_sim::obs::MapSegments;
use sf_sim::Map;

use super::TrainState;
use crate::artifacts::{self, write_atomic};
use crate::error::LearnerError;
use crate::job::ActiveJob;
use crate::validation::{BestPolicy, Validator};

/// Writes the job's final policy (`policy.bpk`, `policy.json`) and returns its weights: the
/// best validated actor with `[validation]` (`policy.json` then has its validation point and,
/// as `idm`, the IDM driver's on the same held-out cases), else the averaged actor with
/// `sac.actor_average_tau`, else the version just published. `policy.json`'s `version` names
/// the job's final policy either way.
pub(super) fn write_final_policy(
    job: &ActiveJob,
    sac: &Sac,
    validator: Option<&mut (Validator, BestPolicy)>,
    dir: &Path,
) -> Result<Vec<u8>, LearnerError> {
    let last = job
        .latest()
        .ok_or(LearnerError::NoPolicyVersion { job_id: job.id, version: PolicyRequest::Latest })?;
    let validated = match validator {
        Some((v, best)) => match best.take()? {
            Some((bytes, p)) => {
                let idm = v.score_idm()?;
                // The kept actor and the IDM driver on the test cases, which chose nothing.
                let test = v.test(&bytes, p.updates)?;
                Some((bytes, p, idm, test))
            }
            None => None,
        },
        None => None,
    };
    let (weights, meta) = match validated {
        Some((bytes, p, idm, test)) => {
            tracing::info!(
                job_id = job.id.get(),
                updates = p.updates,
                success = p.scores.success,
                idm_success = idm.scores.success,
                test_success = test.as_ref().map(|t| t.policy.scores.success),
                test_idm_success = test.as_ref().map(|t| t.idm.scores.success),
                last_updates = sac.updates,
                "final policy: the best validated actor"
            );
            (
                bytes,
                serde_json::json!({"version": last.version, "updates": p.updates, "selected_by": "validation", "validation": p, "idm": idm, "test": test}),
            )
        }
        None if sac.actor_avg.is_some() => {
            let bytes = sac.selected_actor_bytes().map_err(|source| LearnerError::Weights {
                action: "serialising the averaged actor",
                source,
            })?;
            (
                bytes,
                serde_json::json!({"version": last.version, "updates": sac.updates, "selected_by": "average"}),
            )
        }
        None => (
            last.weights.to_vec(),
            serde_json::json!({"version": last.version, "updates": sac.updates}),
        ),
    };
    write_atomic(&dir.join("policy.bpk"), &weights)?;
    write_atomic(&dir.join("policy.json"), meta.to_string().as_bytes())?;
    Ok(weights)
}

/// `train.keep_actors_at`: the actor validation would score, as `kept/actor-<updates>.bpk`.
pub(super) fn keep_actor(job: &ActiveJob, sac: &Sac, dir: &Path) -> Result<(), LearnerError> {
    let weights = sac
        .selected_actor_bytes()
        .map_err(|source| LearnerError::Weights { action: "serialising the actor", source })?;
    let kept = dir.join("kept");
    artifacts::create_dir(&kept)?;
    write_atomic(&kept.join(format!("actor-{}.bpk", sac.updates)), &weights)?;
    tracing::info!(job_id = job.id.get(), updates = sac.updates, "actor kept");
    Ok(())
}

/// Scores the current actor on the validation cases, keeps it if it is the best so far and
/// records the point (curve, TensorBoard, log).
pub(super) fn validate(
    job: &ActiveJob,
    sac: &Sac,
    v: &mut Validator,
    best: &mut BestPolicy,
    st: &mut TrainState,
    tb: Option<&mut EventWriter>,
) -> Result<(), LearnerError> {
    let weights = sac
        .selected_actor_bytes()
        .map_err(|source| LearnerError::Weights { action: "serialising the actor", source })?;
    let p = v.score(&weights, sac.updates, job.progress().learning.env_steps)?;
    let kept = best.offer(&p, &weights)?;
    if let Some(b) = &best.point {
        job.record_validation(p.updates, p.scores.success, (b.updates, b.scores.success));
    }
    tracing::info!(
        job_id = job.id.get(),
        updates = p.updates,
        success = p.scores.success,
        safety = p.scores.safety,
        collision = p.collision,
        took_s = p.took_s,
        best = kept,
        "validation"
    );
    if let Some(w) = tb {
        let scalars = [
            ("validation/success", p.scores.success as f64),
            ("validation/safety", p.scores.safety as f64),
            ("validation/collision", p.collision as f64),
            ("validation/speed", p.scores.speed as f64),
        ];
        if let Err(e) = w.scalars(p.env_steps, &scalars) {
            tracing::warn!(job_id = job.id.get(), error = %e, "writing TensorBoard events");
        }
    }
    st.validation.push(p);
    Ok(())
}

/// CoPO Stage 2: fits the coordinator's Gaussian of every scenario of the job on its frozen
/// final policy and writes `coordinator.json` (what ego jobs and evaluation read).
pub(super) fn fit_coordinator(
    job: &ActiveJob,
    maps: &[Arc<Map>],
    segs: &[Arc<MapSegments>],
    resolved: &setup::ResolvedJob,
    c: &sf_job::config::CoordinatorSection,
    weights: &[u8],
    dir: &Path,
) -> Result<(), LearnerError> {
    use sf_rollout::coordinator::{fit_scenario, CoordinatorFile, FitSettings, ScenarioFit};
    let cfg = &job.cfg;
    let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?;
    let sim = Arc::new(resolved.sim.clone());
    let t = Instant::now();
    let mut fits = Vec::new();
    for (k, (map, seg)) in maps.iter().zip(segs).enumerate() {
        let scenario = &cfg.env.scenarios[k];
        let runner = sf_rollout::inference::PolicyRunner::from_bytes(
            &resolved.net,
            &resolved.obs,
            sim.dt_s,
            &[&**seg],
            weights,
            PolicyVersion::new(0),
            &device,
        )
        .map_err(|source| LearnerError::Weights { action: "loading the final policy", source })?;
        let settings = FitSettings {
            iterations: c.iterations,
            population: c.population,
            episodes: c.episodes,
            elite_frac: c.elite_frac,
            envs: c.envs,
            vehicles: (cfg.env.vehicles_min, cfg.env.vehicles_max),
            seed: cfg.sac.seed ^ 0x636f_6f72 ^ k as u64,
        };
        let (coord, history) = fit_scenario(map, &sim, &runner, &settings, |l| {
            tracing::info!(job_id = job.id.get(), scenario = %scenario, iteration = l.iteration, mean_deg = l.mean_deg, std_deg = l.std_deg, mean_reward = l.mean_reward, "coordinator");
        })
        .map_err(|source| LearnerError::FitCoordinator { scenario: scenario.clone(), source })?;
        fits.push(ScenarioFit { scenario: scenario.clone(), gaussian: coord.gaussian(), history });
    }
    let file = CoordinatorFile { scenarios: fits };
    write_atomic(
        &dir.join(CoordinatorFile::FILE),
        serde_json::to_string_pretty(&file)?.as_bytes(),
    )?;
    tracing::info!(
        job_id = job.id.get(),
        s = t.elapsed().as_secs_f32(),
        "CoPO Stage 2: coordinator fitted"
    );
    Ok(())
}
