//! What a finished job gives the jobs that depend on it.
//!
//! Owns: [`InitDep`] (the finished job a continuation starts from), [`flow_frozen`] (how a finished flow drives a background: itself, its
//! SocialComm flow and itself as the adversary for SocialCommAdv, a CoPO coordinator's
//! Gaussians) and [`check_dep`] (whether a job can serve another in a role; for
//! `train.init_replay`, whether its replay can be carried) and [`replays_to_release`] (the
//! finished jobs whose replay no unfinished job carries any more): rules over job records, which
//! the job table and the scheduler apply; the frozen text only travels on to workers. Must not:
//! read the job table (the scheduler gathers a starting job's dependencies, `scheduler::job_deps`),
//! schedule, or decide a job's state.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use sf_job::config::JobKind;
use sf_job::{DepRole, Frozen, FrozenRole, JobConfig, JobId, JobRecord, JobState};
use sf_rollout::setup;

use crate::error::LearnerError;

/// The finished job a continuation starts from: its id and artifact directory.
pub(crate) struct InitDep {
    pub job_id: JobId,
    pub dir: PathBuf,
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
    if role == DepRole::Init && job.train.init_replay {
        // A stored transition names its map by its index in `env.scenarios`.
        if dep.env.scenarios != job.env.scenarios {
            return Err(refuse(format!(
                "trains on scenarios {:?}; train.init_replay carries its replay only into a job on the same scenarios, in the same order ({:?})",
                dep.env.scenarios, job.env.scenarios
            )));
        }
        if !dep.train.persist_replay {
            return Err(refuse(
                "does not write its replay (train.persist_replay = false), so train.init_replay has none to carry"
                    .into(),
            ));
        }
    }
    if theirs.obs.layout != mine.obs.layout {
        return Err(refuse(format!(
            "observes in the {:?} layout, this job in {:?}",
            theirs.obs.layout, mine.obs.layout
        )));
    }
    Ok(())
}

/// The artifact directories of succeeded jobs whose `replay/` may go: no queued or running job
/// carries it (`train.init_replay` with `train.init_job` naming it). `spec` parses a record's
/// config (`None`: unreadable, which carries nothing). A job's replay outlives it only for such a
/// continuation: a finished job never resumes.
pub(crate) fn replays_to_release(
    all: &[JobRecord],
    spec: impl Fn(&JobRecord) -> Option<Arc<sf_job::JobSpec>>,
) -> Vec<PathBuf> {
    let carried: Vec<JobId> = all
        .iter()
        .filter(|r| !r.state.is_final())
        .filter_map(|r| {
            let s = spec(r)?;
            let cfg = s.train()?;
            cfg.train.init_replay.then_some(cfg.train.init_job).flatten()
        })
        .collect();
    all.iter()
        .filter(|r| r.state == JobState::Succeeded && !carried.contains(&r.id))
        .map(|r| PathBuf::from(&r.artifact_dir))
        .filter(|d| d.join("replay").exists())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use sf_job::JobSpec;

    fn cfg(extra_train: &str, scenarios: &str) -> JobConfig {
        JobConfig::from_toml(&format!(
            "name = \"t\"\n[env]\nscenarios = {scenarios}\n[sac]\nwarmup_steps = 100\n[train]\nenv_steps = 1000\n{extra_train}"
        ))
        .expect("valid config")
    }

    #[test]
    fn a_replay_is_carried_only_between_jobs_on_the_same_scenarios_that_write_it() {
        let id = JobId::new(1);
        let cont = cfg("init_job = 1\ninit_replay = true\n", "[\"merge\", \"bottleneck\"]");
        let same = cfg("", "[\"merge\", \"bottleneck\"]");
        check_dep(&cont, DepRole::Init, id, &same).expect("same scenarios");
        let e = check_dep(&cont, DepRole::Init, id, &cfg("", "[\"bottleneck\", \"merge\"]"))
            .expect_err("other order");
        assert!(e.to_string().contains("train.init_job") && e.to_string().contains("scenarios"));
        let e = check_dep(
            &cont,
            DepRole::Init,
            id,
            &cfg("persist_replay = false\n", "[\"merge\", \"bottleneck\"]"),
        )
        .expect_err("no replay on disk");
        assert!(e.to_string().contains("persist_replay"), "{e}");
        // Without the carry, scenarios may differ.
        let plain = cfg("init_job = 1\n", "[\"merge\"]");
        check_dep(&plain, DepRole::Init, id, &same).expect("no carry");
    }

    #[test]
    fn a_finished_jobs_replay_goes_once_no_unfinished_job_carries_it() {
        let root = std::env::temp_dir().join(format!("sf-release-{}", std::process::id()));
        let rec = |id: u64, state: JobState, train: &str| {
            let dir = root.join(format!("job-{id}"));
            std::fs::create_dir_all(dir.join("replay")).expect("replay dir");
            JobRecord {
                id: JobId::new(id),
                name: format!("j{id}"),
                state,
                config_toml: cfg(train, "[\"merge\"]").to_toml(),
                message: String::new(),
                created_unix_ms: 0,
                updated_unix_ms: 0,
                progress: Default::default(),
                artifact_dir: dir.display().to_string(),
            }
        };
        let source = rec(1, JobState::Succeeded, "");
        let other = rec(2, JobState::Succeeded, "");
        let carrier = rec(3, JobState::Queued, "init_job = 1\ninit_replay = true\n");
        let plain = rec(4, JobState::Running, "init_job = 2\n");
        let spec = |r: &JobRecord| JobSpec::from_toml(&r.config_toml).ok().map(Arc::new);
        let go = replays_to_release(&[source.clone(), other.clone(), carrier.clone(), plain], spec);
        assert_eq!(go, vec![PathBuf::from(&other.artifact_dir)], "job 1 is carried by job 3");
        let mut done = carrier;
        done.state = JobState::Succeeded;
        let go = replays_to_release(&[source.clone(), done.clone()], spec);
        assert_eq!(go.len(), 2, "nothing carries either any more: {go:?}");
        std::fs::remove_dir_all(root.join("job-1").join("replay")).expect("rm");
        let go = replays_to_release(&[source, done], spec);
        assert_eq!(go.len(), 1, "a deleted replay is not listed again");
        let _ = std::fs::remove_dir_all(&root);
    }
}
