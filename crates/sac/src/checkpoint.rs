//! Checkpoints of the SAC state: weights, target, optimizer states, alpha, counters, RNG.
//!
//! Owns: the on-disk layout of a checkpoint directory and its atomic replacement (everything
//! is written into a sibling temporary directory, then renamed over the old one), and the
//! restore that continues training exactly. Must not: save the replay buffer (too large; a
//! restored learner refills it) or run during an update.
//!
//! Layout: `actor.bpk`, `critic.bpk`, `target.bpk`, `log_alpha.bpk`, `opt_actor.bpk`,
//! `opt_critic.bpk`, `opt_alpha.bpk`, `state.json`, and `actor_avg.bpk` with
//! `sac.actor_average_tau`.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::Bytes;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sf_nn::weights;

use crate::sac::Sac;

/// Version of the checkpoint layout.
pub const CHECKPOINT_VERSION: u32 = 1;

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct State {
    version: u32,
    updates: u64,
    rng_seed: [u8; 32],
    rng_word_pos: u128,
    /// The SAC settings the run had, for the reader's information: a restored run takes its
    /// settings from its job config, so this is never read back (older checkpoints' fields
    /// stay readable whatever the config struct became).
    sac: serde_json::Value,
    net: sf_nn::NetConfig,
}

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("checkpoint {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("checkpoint {path}: cannot encode or decode {what}: {reason}")]
    Record { path: String, what: &'static str, reason: String },
    #[error("checkpoint {path}: state.json: {reason}")]
    State { path: String, reason: String },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
    move |source| CheckpointError::Io { path: path.display().to_string(), source }
}

fn rec_err<'a>(path: &'a Path, what: &'static str) -> impl FnOnce(String) -> CheckpointError + 'a {
    move |reason| CheckpointError::Record { path: path.display().to_string(), what, reason }
}

/// `m`'s record; the error names `what` in checkpoint `dir`.
fn module_bytes<M: Module + Clone>(
    m: &M,
    dir: &Path,
    what: &'static str,
) -> Result<Vec<u8>, CheckpointError> {
    weights::to_bytes(m).map_err(|e| rec_err(dir, what)(e.to_string()))
}

/// `o`'s state; the error names `what` in checkpoint `dir`.
fn opt_bytes(
    o: &burn::optim::ModuleOptimizer,
    dir: &Path,
    what: &'static str,
) -> Result<Vec<u8>, CheckpointError> {
    o.into_bytes().map(|b| b.to_vec()).map_err(|e| rec_err(dir, what)(format!("{e:?}")))
}

/// `bytes` loaded into `m`; the error names `what` in checkpoint `dir`.
fn load_module<M: Module>(
    m: M,
    bytes: Vec<u8>,
    dir: &Path,
    what: &'static str,
) -> Result<M, CheckpointError> {
    weights::from_bytes(m, &bytes).map_err(|e| rec_err(dir, what)(e.to_string()))
}

/// Writes `sac` into `dir` atomically: readers see either the old or the new checkpoint.
pub fn save(sac: &Sac, dir: &Path) -> Result<(), CheckpointError> {
    let tmp = sibling(dir, "tmp");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(io(&tmp))?;
    }
    std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
    let files = [
        ("actor.bpk", module_bytes(&sac.actor, dir, "actor")),
        ("critic.bpk", module_bytes(&sac.critic, dir, "critic")),
        ("target.bpk", module_bytes(&sac.target, dir, "target critic")),
        ("log_alpha.bpk", module_bytes(&sac.log_alpha, dir, "log alpha")),
        ("opt_actor.bpk", opt_bytes(&sac.opt_actor, dir, "actor optimizer")),
        ("opt_critic.bpk", opt_bytes(&sac.opt_critic, dir, "critic optimizer")),
        ("opt_alpha.bpk", opt_bytes(&sac.opt_alpha, dir, "alpha optimizer")),
    ];
    let avg =
        sac.actor_avg.as_ref().map(|a| ("actor_avg.bpk", module_bytes(a, dir, "averaged actor")));
    for (name, bytes) in files.into_iter().chain(avg) {
        let bytes = bytes?;
        let p = tmp.join(name);
        std::fs::write(&p, bytes).map_err(io(&p))?;
    }
    let state = State {
        version: CHECKPOINT_VERSION,
        updates: sac.updates,
        rng_seed: sac.rng.get_seed(),
        rng_word_pos: sac.rng.get_word_pos(),
        sac: serde_json::to_value(&sac.cfg).map_err(|e| CheckpointError::State {
            path: dir.display().to_string(),
            reason: e.to_string(),
        })?,
        net: sac.net.clone(),
    };
    let p = tmp.join("state.json");
    let text = serde_json::to_string_pretty(&state).map_err(|e| CheckpointError::State {
        path: p.display().to_string(),
        reason: e.to_string(),
    })?;
    std::fs::write(&p, text).map_err(io(&p))?;
    // Swap: old -> .old, tmp -> dir, drop .old.
    let old = sibling(dir, "old");
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(io(&old))?;
    }
    if dir.exists() {
        std::fs::rename(dir, &old).map_err(io(dir))?;
    }
    std::fs::rename(&tmp, dir).map_err(io(dir))?;
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(io(&old))?;
    }
    Ok(())
}

/// Starts a new run from another run's checkpoint (a RARL phase continuing the previous one of
/// its side): weights, target, alpha and optimizer states are restored; this run's SAC
/// settings are kept (as [`restore`] does) and its update counter starts at 0.
///
/// `kept_actor` (the other run's final policy, `policy.bpk`: with `[validation]` the actor it
/// kept, not its last) replaces the actor and the averaged actor. This is the one rule of a
/// continuation: it goes on with exactly the policy that every job depending on the other run
/// (an adversary trained against it, an evaluation) acted with.
pub fn warm_start(
    sac: &mut Sac,
    dir: &Path,
    kept_actor: Option<&[u8]>,
) -> Result<(), CheckpointError> {
    // Decoded first, so that nothing is changed on error.
    let kept = match kept_actor {
        Some(bytes) => {
            let err = |e: sf_nn::weights::WeightsError| CheckpointError::Record {
                path: dir.display().to_string(),
                what: "the kept actor (policy.bpk)",
                reason: e.to_string(),
            };
            let actor = weights::from_bytes(sac.actor.clone(), bytes).map_err(err)?;
            let avg = sac
                .actor_avg
                .clone()
                .map(|avg| weights::from_bytes(avg, bytes).map_err(err))
                .transpose()?;
            Some((actor, avg))
        }
        None => None,
    };
    restore(sac, dir)?;
    if let Some((actor, avg)) = kept {
        sac.actor = actor;
        sac.actor_avg = avg;
    }
    sac.updates = 0;
    Ok(())
}

fn sibling(dir: &Path, suffix: &str) -> PathBuf {
    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "checkpoint".into());
    dir.with_file_name(format!(".{name}.{suffix}"))
}

/// Starts a new run from another kind's checkpoint (a SocialComm flow from a MACAD flow's
/// weights): weights, target, alpha and optimizer states as [`warm_start`] restores them, into
/// a network of the same sizes that may consume context channels the source's did not (SVOs,
/// the ego flag). The weights that read those channels never learned (their input was zero)
/// and are set to zero ([`sf_nn::Actor::silence_new_context`]), so the run starts acting and
/// valuing exactly as the source did. The run keeps its own RNG and starts at update 0.
/// Returns the source's network. Nothing is changed on error.
pub fn warm_start_across(sac: &mut Sac, dir: &Path) -> Result<sf_nn::NetConfig, CheckpointError> {
    let from = load(sac, dir, Fit::SameShapes)?;
    let to = sac.net.clone();
    sac.actor = sac.actor.clone().silence_new_context(&from, &to);
    sac.critic = sac.critic.clone().silence_new_context(&from, &to);
    sac.target = sac.target.clone().silence_new_context(&from, &to);
    sac.actor_avg = sac.actor_avg.take().map(|a| a.silence_new_context(&from, &to));
    sac.updates = 0;
    Ok(from)
}

/// How a checkpoint's network must fit the one it is loaded into.
#[derive(Clone, Copy, PartialEq)]
enum Fit {
    /// The same network ([`sf_nn::NetConfig::same_network`]): a continuation; its RNG too.
    SameNetwork,
    /// The same sizes ([`sf_nn::NetConfig::same_shapes`]): a warm start across kinds; the
    /// run's own RNG stays.
    SameShapes,
}

/// Restores a checkpoint into `sac`, which must have been built with the same network and
/// observation layout (the usual case: the same job config); `sac` keeps its own SAC settings
/// (the job config is their one source). Nothing is changed on error.
pub fn restore(sac: &mut Sac, dir: &Path) -> Result<(), CheckpointError> {
    load(sac, dir, Fit::SameNetwork).map(|_| ())
}

/// [`restore`] with the network fit `fit`; returns the checkpoint's network.
fn load(sac: &mut Sac, dir: &Path, fit: Fit) -> Result<sf_nn::NetConfig, CheckpointError> {
    let read = |name: &str| {
        let p = dir.join(name);
        std::fs::read(&p).map_err(io(&p))
    };
    let p = dir.join("state.json");
    let text = std::fs::read_to_string(&p).map_err(io(&p))?;
    let state: State = serde_json::from_str(&text).map_err(|e| CheckpointError::State {
        path: dir.display().to_string(),
        reason: e.to_string(),
    })?;
    if state.version != CHECKPOINT_VERSION {
        return Err(CheckpointError::State {
            path: dir.display().to_string(),
            reason: format!(
                "version {} is not supported (this build reads {CHECKPOINT_VERSION})",
                state.version
            ),
        });
    }
    let fits = match fit {
        Fit::SameNetwork => state.net.same_network(&sac.net),
        Fit::SameShapes => sac.net.same_shapes(&state.net),
    };
    if !fits {
        return Err(CheckpointError::State {
            path: dir.display().to_string(),
            reason: format!("network {:?} differs from the configured {:?}", state.net, sac.net),
        });
    }
    let actor = load_module(sac.actor.clone(), read("actor.bpk")?, dir, "actor")?;
    let critic = load_module(sac.critic.clone(), read("critic.bpk")?, dir, "critic")?;
    let target = load_module(sac.target.clone(), read("target.bpk")?, dir, "target critic")?;
    let log_alpha = load_module(sac.log_alpha.clone(), read("log_alpha.bpk")?, dir, "log alpha")?;
    // A checkpoint without an averaged actor (written without `sac.actor_average_tau`) starts
    // the average at the restored actor.
    let actor_avg = match &sac.actor_avg {
        Some(avg) if dir.join("actor_avg.bpk").exists() => {
            Some(load_module(avg.clone(), read("actor_avg.bpk")?, dir, "averaged actor")?)
        }
        Some(_) => Some(actor.valid()),
        None => None,
    };
    let opt =
        |name: &str| -> Result<Bytes, CheckpointError> { Ok(Bytes::from_bytes_vec(read(name)?)) };
    let fresh = || burn::optim::AdamConfig::new().init();
    let opt_actor = fresh()
        .from_bytes(opt("opt_actor.bpk")?)
        .map_err(|e| rec_err(dir, "actor optimizer")(format!("{e:?}")))?;
    let opt_critic = fresh()
        .from_bytes(opt("opt_critic.bpk")?)
        .map_err(|e| rec_err(dir, "critic optimizer")(format!("{e:?}")))?;
    let opt_alpha = fresh()
        .from_bytes(opt("opt_alpha.bpk")?)
        .map_err(|e| rec_err(dir, "alpha optimizer")(format!("{e:?}")))?;
    let mut rng = <ChaCha8Rng as rand::SeedableRng>::from_seed(state.rng_seed);
    rng.set_word_pos(state.rng_word_pos);
    sac.actor = actor;
    sac.critic = critic;
    sac.target = target;
    sac.actor_avg = actor_avg;
    sac.log_alpha = log_alpha;
    sac.opt_actor = opt_actor;
    sac.opt_critic = opt_critic;
    sac.opt_alpha = opt_alpha;
    if fit == Fit::SameNetwork {
        sac.rng = rng;
    }
    sac.updates = state.updates;
    Ok(state.net)
}
