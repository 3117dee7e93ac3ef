//! Starting a job from another job's weights (`train.warm_start_from`), of the same kind or
//! another one with the same network sizes: a SocialComm flow from a competent MACAD flow.
//!
//! Owns: the check at submission ([`check`]: the directory holds a checkpoint, its job's
//! network has this job's sizes and action and its observation layout is this job's) and the
//! load when the job first starts ([`start`]: `sf_sac::checkpoint::warm_start_across`, which
//! zeroes the weights that read context channels the source did not consume, and
//! `warm_started_from.json` in the job directory naming the source, its kind and the SHA-256
//! of the actor and critic as loaded). Unlike a continuation (`continuation.rs`) nothing else
//! comes along: the job's replay, counters, curve, seed and update counter are its own.
//! Must not: change the source directory, or run for a job that resumes its own checkpoint.

use std::path::{Path, PathBuf};

use sf_job::JobConfig;
use sf_rollout::setup;
use sf_sac::checkpoint;
use sf_sac::sac::Sac;

use crate::artifacts::write_atomic;
use crate::error::LearnerError;

/// The marker a warm-started job directory keeps beside its checkpoint.
pub const WARM_STARTED_FROM: &str = "warm_started_from.json";

fn refuse(reason: String) -> LearnerError {
    LearnerError::WarmStart { reason }
}

/// The source directory of `cfg`'s `train.warm_start_from`, if it names one.
pub fn source(cfg: &JobConfig) -> Option<PathBuf> {
    cfg.train.warm_start_from.as_deref().map(PathBuf::from)
}

/// The source's job config, read from its directory.
fn source_config(from: &Path) -> Result<JobConfig, LearnerError> {
    let needed = ["config.toml", "checkpoint/state.json", "checkpoint/actor.bpk"];
    crate::continuation::job_dir_config(from, &needed, "config.toml and checkpoint/", refuse)
}

/// Refuses a `train.warm_start_from` whose weights would not load into this job's network or
/// would read its observations differently: no checkpoint, other sizes or action, another
/// observation layout. Blocking (reads small files).
pub fn check(cfg: &JobConfig) -> Result<(), LearnerError> {
    let Some(from) = source(cfg) else { return Ok(()) };
    let theirs = source_config(&from)?;
    let shown = from.display();
    let (mine, other) = (setup::resolve(cfg, None), setup::resolve(&theirs, None));
    if !mine.net.same_shapes(&other.net) {
        return Err(refuse(format!(
            "{shown} ({} job) has network {:?}, this job {:?}: only the SVO inputs and the ego flag may differ",
            theirs.kind.as_str(),
            other.net,
            mine.net
        )));
    }
    if other.obs != mine.obs {
        return Err(refuse(format!(
            "{shown} observes with {:?}, this job with {:?}",
            other.obs, mine.obs
        )));
    }
    Ok(())
}

/// Loads the source's weights into `sac` (a job starting for the first time) and writes the
/// marker. Blocking.
pub fn start(sac: &mut Sac, cfg: &JobConfig, dir: &Path) -> Result<(), LearnerError> {
    let Some(from) = source(cfg) else { return Ok(()) };
    let theirs = source_config(&from)?;
    let ckpt = from.join("checkpoint");
    let net = checkpoint::warm_start_across(sac, &ckpt).map_err(|source| {
        LearnerError::Checkpoint { action: "warm-starting from", path: ckpt.clone(), source }
    })?;
    let digest = |bytes: Result<Vec<u8>, sf_nn::weights::WeightsError>| {
        bytes.map(|b| sf_nn::weights::sha256_hex(&b)).map_err(|source| LearnerError::Weights {
            action: "serialising the warm-started state",
            source,
        })
    };
    let marker = serde_json::json!({
        "from": from.display().to_string(),
        "kind": theirs.kind.as_str(),
        "svo": net.svo,
        "ego_flag": net.ego_flag,
        "actor_sha256": digest(sac.actor_bytes())?,
        "critic_sha256": digest(sf_nn::weights::to_bytes(&sac.critic))?,
    });
    crate::artifacts::create_dir(dir)?;
    write_atomic(&dir.join(WARM_STARTED_FROM), marker.to_string().as_bytes())
}
