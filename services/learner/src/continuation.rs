//! Continuing a run from its job directory (`train.continue_from`): a stopped or finished job's
//! directory, whether left by this learner, another one, or copied and committed, whose whole
//! SAC state a new job takes over as if it had written it itself.
//!
//! Owns: the check at submission ([`check`]: the directory holds a checkpoint and a
//! `state.json`, and its job has this job's kind, network, observation layout and scenarios
//! and fewer transitions than this job asks for) and the copy into the new job's directory when
//! it first starts ([`seed`]). After the copy the job resumes from its own directory like any
//! restarted job (`trainer::start_state`): actor, critic, target, optimizer moments, alpha,
//! update counter and RNG from `checkpoint/`; counters, curve and validation points from
//! `state.json`; the best validated actor and the kept actors. The replay comes too when the
//! directory has one; without it the job refills its replay with the continued policy
//! (`sac.warmup_steps` transitions, the scheduler's `fill`) before updating again.
//! Must not: change the source directory (it may be another job's, or committed), or start
//! anything.

use std::path::{Path, PathBuf};

use sf_job::JobConfig;
use sf_rollout::setup;

use crate::error::LearnerError;
use crate::trainer;

/// The files a continuation takes over; `state.json` is copied last, so a copy cut short
/// leaves no `state.json` and is made again at the next start.
const FILES: &[&str] =
    &["published_version", "best_policy.bpk", "best_policy.json", "curve.csv", "validation.csv"];
/// The directories a continuation takes over (flat: files only). `replay/` is linked where the
/// file system allows (segments are never rewritten in place), else copied.
const DIRS: &[&str] = &["checkpoint", "kept", "replay"];

fn refuse(reason: String) -> LearnerError {
    LearnerError::Continuation { reason }
}

/// The source directory of `cfg`'s `train.continue_from`, if it names one.
pub fn source(cfg: &JobConfig) -> Option<PathBuf> {
    cfg.train.continue_from.as_deref().map(PathBuf::from)
}

/// Refuses a `train.continue_from` that the job could not continue: a directory without a
/// checkpoint or state, of another kind, network, observation layout or set of scenarios, or
/// one that already has the transitions this job asks for. Blocking (reads small files).
pub fn check(cfg: &JobConfig) -> Result<(), LearnerError> {
    let Some(from) = source(cfg) else { return Ok(()) };
    let shown = from.display();
    let needed = ["config.toml", "state.json", "checkpoint/state.json"];
    let theirs = job_dir_config(&from, &needed, "config.toml, state.json, checkpoint/", refuse)?;
    if theirs.kind != cfg.kind {
        return Err(refuse(format!(
            "{shown} is a {} job, this one {}",
            theirs.kind.as_str(),
            cfg.kind.as_str()
        )));
    }
    // A stored transition names its map by its index in `env.scenarios`.
    if theirs.env.scenarios != cfg.env.scenarios {
        return Err(refuse(format!(
            "{shown} trains on scenarios {:?}, this job on {:?} (same scenarios, same order)",
            theirs.env.scenarios, cfg.env.scenarios
        )));
    }
    let (mine, other) = (setup::resolve(cfg, None), setup::resolve(&theirs, None));
    if !other.net.same_network(&mine.net) {
        return Err(refuse(format!(
            "{shown} has network {:?}, this job {:?}",
            other.net, mine.net
        )));
    }
    if other.obs != mine.obs {
        return Err(refuse(format!(
            "{shown} observes with {:?}, this job with {:?}",
            other.obs, mine.obs
        )));
    }
    let st =
        trainer::load_state(&from)?.ok_or_else(|| refuse(format!("{shown} has no state.json")))?;
    if st.counters.env_steps >= cfg.train.env_steps {
        return Err(LearnerError::JobConfig(sf_job::ConfigError::Field {
            field: "train.env_steps",
            reason: format!(
                "{} is not more than the {} transitions {shown} already has: nothing to continue",
                cfg.train.env_steps, st.counters.env_steps
            ),
        }));
    }
    Ok(())
}

/// The job config of job directory `from` (on the learner's host), which must hold the files
/// `needed` (`what` says what a job directory has); `refuse` makes the error, naming the field
/// that named the directory. Blocking.
pub(crate) fn job_dir_config(
    from: &Path,
    needed: &[&str],
    what: &str,
    refuse: fn(String) -> LearnerError,
) -> Result<JobConfig, LearnerError> {
    let shown = from.display();
    if !from.is_dir() {
        return Err(refuse(format!("{shown} is not a directory on the learner's host")));
    }
    if let Some(missing) = needed.iter().find(|n| !from.join(n).is_file()) {
        return Err(refuse(format!("{shown} has no {missing} (a job directory: {what})")));
    }
    let text = std::fs::read_to_string(from.join("config.toml"))
        .map_err(|e| refuse(format!("reading {shown}/config.toml: {e}")))?;
    JobConfig::from_toml(&text).map_err(|e| refuse(format!("{shown}/config.toml: {e}")))
}

/// Copies the source's state into `dir` (the new job's directory) unless `dir` already has a
/// `state.json` (a continuation that has run before resumes from its own). Returns whether
/// the job now starts from a copied state, and whether a replay came with it. Blocking.
pub fn seed(cfg: &JobConfig, dir: &Path) -> Result<Option<Seeded>, LearnerError> {
    let Some(from) = source(cfg) else { return Ok(None) };
    if trainer::state_path(dir).exists() {
        return Ok(None);
    }
    let io = |action: &'static str, path: &Path| {
        let path = path.to_path_buf();
        move |source| LearnerError::Io { action, path, source }
    };
    std::fs::create_dir_all(dir).map_err(io("creating", dir))?;
    for d in DIRS {
        let (src, dst) = (from.join(d), dir.join(d));
        if !src.is_dir() {
            continue;
        }
        if dst.exists() {
            std::fs::remove_dir_all(&dst).map_err(io("removing", &dst))?;
        }
        std::fs::create_dir_all(&dst).map_err(io("creating", &dst))?;
        for e in std::fs::read_dir(&src).map_err(io("reading", &src))? {
            let p = e.map_err(io("reading", &src))?.path();
            if !p.is_file() {
                continue;
            }
            let to = dst.join(p.file_name().unwrap_or_default());
            if *d != "replay" || std::fs::hard_link(&p, &to).is_err() {
                std::fs::copy(&p, &to).map_err(io("copying", &p))?;
            }
        }
    }
    for f in FILES {
        let p = from.join(f);
        if p.is_file() {
            std::fs::copy(&p, dir.join(f)).map_err(io("copying", &p))?;
        }
    }
    let replay = dir.join("replay").is_dir()
        && std::fs::read_dir(dir.join("replay")).map(|mut r| r.next().is_some()).unwrap_or(false);
    let marker = serde_json::json!({"from": from.display().to_string(), "replay": replay});
    crate::artifacts::write_atomic(
        &dir.join(trainer::CONTINUED_FROM),
        marker.to_string().as_bytes(),
    )?;
    let st = from.join("state.json");
    std::fs::copy(&st, trainer::state_path(dir)).map_err(io("copying", &st))?;
    Ok(Some(Seeded { replay }))
}

/// A continuation's first start.
#[derive(Clone, Copy, Debug)]
pub struct Seeded {
    /// The source's replay came with it (else the job refills its replay).
    pub replay: bool,
}
