//! What a finished job gives the jobs that depend on it.
//!
//! Owns: [`JobDeps`] and [`job_deps`] (a starting training job's frozen policies,
//! their final weights when `[validation]` runs episodes with them, and the job a RARL phase
//! continues from), [`flow_frozen`] (how a finished flow drives a background: itself, its
//! SocialComm flow and itself as the adversary for SocialCommAdv, a CoPO coordinator's
//! Gaussians) and [`check_dep`] (whether a job can serve another in a role). Configs come
//! parsed ([`Jobs::spec`]); the
//! frozen text only travels on to workers. Must not: schedule, or decide a job's state.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use sf_job::config::JobKind;
use sf_job::{DepRole, Frozen, FrozenRole, JobConfig, JobId, JobRecord, JobState};
use sf_rollout::setup;

use crate::artifacts::read_final;
use crate::error::LearnerError;
use crate::jobs::Jobs;

/// What a starting training job takes from its dependencies.
pub(crate) struct JobDeps {
    /// The frozen policies its workers act with (background, ego, adversary).
    pub frozen: Vec<Frozen>,
    /// `frozen`'s final weights, in order, when the job validates (`[validation]`); else empty.
    pub frozen_weights: Vec<Arc<Vec<u8>>>,
    /// `train.init_job`: a continuation starts from its checkpoint's critic and its final
    /// policy (`sf_sac::checkpoint::warm_start`).
    pub init: Option<InitDep>,
}

/// The finished job a continuation starts from: its id and artifact directory.
pub(crate) struct InitDep {
    pub job_id: JobId,
    pub dir: PathBuf,
}

/// The dependencies of training job `cfg` among `jobs`: every one must have succeeded with a
/// final policy; the error names the field.
pub(crate) async fn job_deps(jobs: &Jobs, cfg: &JobConfig) -> Result<JobDeps, LearnerError> {
    let mut frozen = Vec::new();
    // Each frozen policy's artifact directory, for validation's weights.
    let mut dirs: HashMap<JobId, PathBuf> = HashMap::new();
    let mut init = None;
    for (role, dep) in cfg.deps() {
        let d = jobs.get(dep).map_err(|e| LearnerError::DependencyLookup {
            dep,
            field: role.field(),
            source: e.into(),
        })?;
        if d.state != JobState::Succeeded || !Path::new(&d.artifact_dir).join("policy.bpk").exists()
        {
            return Err(LearnerError::NoFinalPolicy {
                dep,
                field: role.field(),
                state: d.state.as_str(),
            });
        }
        match role {
            DepRole::Init => {
                init = Some(InitDep { job_id: dep, dir: PathBuf::from(&d.artifact_dir) })
            }
            DepRole::Ego => {
                dirs.insert(dep, PathBuf::from(&d.artifact_dir));
                frozen.push(Frozen::new(FrozenRole::Ego, dep, d.config_toml));
            }
            DepRole::Background => {
                let spec = jobs.spec(&d)?;
                let flow_cfg = spec
                    .train()
                    .ok_or_else(|| LearnerError::Dependency {
                        field: role.field(),
                        dep,
                        reason: "is an evaluation, not a training job".into(),
                    })?
                    .clone();
                let all = jobs.list();
                let fz = {
                    let jobs = all.clone();
                    tokio::task::spawn_blocking(move || {
                        flow_frozen(&d, &flow_cfg, |id| {
                            jobs.iter()
                                .find(|r| r.id == id)
                                .cloned()
                                .ok_or(LearnerError::JobNotFound { job_id: id })
                        })
                    })
                    .await??
                };
                for f in &fz {
                    if let Some(r) = all.iter().find(|r| r.id == f.job_id) {
                        dirs.insert(f.job_id, PathBuf::from(&r.artifact_dir));
                    }
                }
                frozen.extend(fz);
            }
        }
    }
    // `[validation]` runs episodes with the frozen policies the workers fetch.
    let mut frozen_weights = Vec::new();
    if cfg.validation.is_some() {
        for f in &frozen {
            let job_id = f.job_id;
            let dir = dirs.get(&job_id).cloned().ok_or(LearnerError::JobNotFound { job_id })?;
            let bytes = tokio::task::spawn_blocking(move || read_final(&dir, job_id, "policy.bpk"))
                .await
                .map_err(|source| LearnerError::Task { task: "policy reading task", source })?;
            frozen_weights.push(Arc::new(bytes?));
        }
    }
    Ok(JobDeps { frozen, frozen_weights, init })
}

/// The frozen policies with which a finished flow job `rec` drives the background, for a
/// training job or an evaluation: a SocialCommAdv job brings its SocialComm flow (`find` looks it
/// up) as the background and itself as the adversary; any other flow drives itself, with a CoPO
/// coordinator's Gaussians if it has fitted them (Stage 2). `cfg` is `rec`'s parsed config
/// ([`Jobs::spec`]). Blocking file IO (`coordinator.json`).
pub(crate) fn flow_frozen(
    rec: &JobRecord,
    cfg: &JobConfig,
    find: impl Fn(JobId) -> Result<JobRecord, LearnerError>,
) -> Result<Vec<Frozen>, LearnerError> {
    if cfg.kind == JobKind::SocialcommAdv {
        let flow =
            cfg.env.background_job.ok_or(LearnerError::NoBackgroundFlow { job_id: rec.id })?;
        let f = find(flow).map_err(|e| LearnerError::BackgroundFlow {
            flow,
            job_id: rec.id,
            source: Box::new(e),
        })?;
        return Ok(vec![
            Frozen::new(FrozenRole::Background, flow, f.config_toml),
            Frozen::new(FrozenRole::Adversary, rec.id, rec.config_toml.clone()),
        ]);
    }
    let mut f = Frozen::new(FrozenRole::Background, rec.id, rec.config_toml.clone());
    if let Some(c) = sf_rollout::coordinator::CoordinatorFile::load(Path::new(&rec.artifact_dir))
        .map_err(LearnerError::Coordinator)?
    {
        f.svo_gaussians = c.scenarios.into_iter().map(|s| (s.scenario, s.gaussian)).collect();
    }
    Ok(vec![f])
}

/// Whether job `dep_id` (config `dep`) can serve `job` in `role`: its kind (`DepRole::accepts`),
/// for `train.init_job` the same network, and the same observation layout. The error names the
/// field and the job.
pub(crate) fn check_dep(
    job: &JobConfig,
    role: DepRole,
    dep_id: JobId,
    dep: &JobConfig,
) -> Result<(), LearnerError> {
    let refuse =
        |reason: String| LearnerError::Dependency { field: role.field(), dep: dep_id, reason };
    role.accepts(job.kind, dep.kind).map_err(|e| refuse(e.to_string()))?;
    let (mine, theirs) = (setup::resolve(job, None), setup::resolve(dep, None));
    if role == DepRole::Init && !theirs.net.same_network(&mine.net) {
        return Err(refuse(format!(
            "has network {:?}; a job starts only from one of its own kind and network",
            theirs.net
        )));
    }
    if theirs.obs.layout != mine.obs.layout {
        return Err(refuse(format!(
            "observes in the {:?} layout, this job in {:?}",
            theirs.obs.layout, mine.obs.layout
        )));
    }
    Ok(())
}
