//! The trainer thread of the running job: SAC updates at the rate the limiter allows, policy
//! publishing, learning-curve points, checkpoints and the job's artifacts.
//!
//! Owns: [`run`], which builds (or restores) the SAC state, loops `sample -> update ->
//! publish` until the job has all its transitions and its owed updates, is cancelled, or the
//! learner shuts down, and then writes the final checkpoint and artifacts. All tensor work of
//! the learner happens here, never on the async runtime.
//!
//! Artifacts in the job directory: `config.toml` (resolved), `checkpoint/` (SAC state),
//! `state.json` (counters, policy version, curve), `curve.csv`, `curve.png`, `policy.bpk`
//! (the final actor) with `policy.json` (its version); CoPO jobs then fit their Stage-2
//! coordinator on that final actor and add `coordinator.json`. `tensorboard/` holds event files
//! with the curve's scalars and more (losses, alpha, rates, policy lag). With `train.persist_replay`
//! (the default) `replay/` holds the replay in segments, one per checkpoint, read back on
//! resume (or carried into a continuation, `train.init_replay`); the scheduler deletes it once
//! the job has succeeded and no unfinished job carries it. With `[validation]`,
//! `validation.csv` holds the held-out evaluation's points and `best_policy.bpk`/`.json` the
//! best actor so far, which becomes `policy.bpk` (`policy.json` then says
//! `"selected_by": "validation"` and at which update).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sf_job::PolicyVersion;
use sf_report::plot::{line_chart, Series};
use sf_report::tensorboard::EventWriter;
use sf_sac::rate_limiter::RateLimitError;
use sf_sac::replay_store::{ReplayStore, Segment};
use sf_sac::CurvePoint;
use sf_sac::{checkpoint, Batch, Sac};
use sf_sim::obs::MapSegments;
use sf_sim::Map;
use tokio::sync::oneshot;

use crate::artifacts::{self, write_atomic};
use crate::deps::InitDep;
use crate::error::LearnerError;
use crate::job::{ActiveJob, Counters, StopReason};
use crate::slot::Outcome;
use crate::validation::{BestPolicy, ValidationPoint, Validator};
use curve::CurveRecorder;
use outputs::{fit_coordinator, keep_actor, validate, write_final_policy};
use sf_service::sync::lock;

mod curve;
mod outputs;

/// What survives a restart besides the SAC checkpoint.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct TrainState {
    pub counters: Counters,
    pub policy_version: PolicyVersion,
    pub curve: Vec<CurvePoint>,
    /// `[validation]`: every point so far.
    #[serde(default)]
    pub validation: Vec<ValidationPoint>,
    /// `train.init_replay`: transitions carried in from the continued job's replay at the
    /// start. The replay numbers them before the job's own, so its insertion numbers run to
    /// `carried + counters.env_steps`.
    #[serde(default)]
    pub carried: u64,
}

impl TrainState {
    /// Transitions the job's replay has numbered: the carried ones, then its own.
    fn replay_inserted(&self) -> u64 {
        self.carried + self.counters.env_steps
    }
}

/// The marker a continuation's copy leaves in the new job's directory (`continuation::seed`);
/// the trainer adds the state it restored at the job's first start.
pub const CONTINUED_FROM: &str = "continued_from.json";

pub fn state_path(dir: &Path) -> PathBuf {
    dir.join("state.json")
}

/// Reads `state.json` if the job has one (a resumed job).
pub fn load_state(dir: &Path) -> Result<Option<TrainState>, LearnerError> {
    let p = state_path(dir);
    if !p.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&p).map_err(artifacts::io_error("reading", &p))?;
    serde_json::from_str(&text)
        .map(Some)
        .map_err(|source| LearnerError::StateFile { path: p, source })
}

pub struct TrainerInput {
    pub job: Arc<ActiveJob>,
    pub maps: Vec<Arc<Map>>,
    /// Each map's segments, as ingest checked the observations against them.
    pub segs: Vec<Arc<MapSegments>>,
    pub dir: PathBuf,
    pub resume: Option<TrainState>,
    /// `train.init_job`: its checkpoint and final policy are the SAC state a fresh job starts
    /// from.
    pub(crate) init: Option<InitDep>,
    /// With `[validation]`: the final weights of the job's frozen policies (`job.frozen`, in
    /// order), which validation episodes run with. Empty otherwise.
    pub frozen_weights: Vec<Arc<Vec<u8>>>,
}

/// Runs the job on a thread of its own (`trainer-<id>`); its [`Outcome`] comes through the
/// receiver. A panic fails the job with its message.
pub fn spawn(input: TrainerInput) -> Result<oneshot::Receiver<Outcome>, LearnerError> {
    let (tx, rx) = oneshot::channel();
    std::thread::Builder::new()
        .name(format!("trainer-{}", input.job.id))
        .spawn(move || {
            // A panic is a defect, but it must not leave the job without its cause.
            let out = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(input)))
                .unwrap_or_else(|p| {
                    let why = p
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_else(|| "no message".into());
                    Outcome::Failed(format!("the trainer panicked: {why}"))
                });
            let _ = tx.send(out);
        })
        .map_err(LearnerError::SpawnTrainer)?;
    Ok(rx)
}

/// Runs the job to an [`Outcome`]. Blocking; call on a dedicated thread.
pub fn run(input: TrainerInput) -> Outcome {
    match train(input) {
        Ok(o) => o,
        Err(e) if crate::storage::is_storage_fault(&e) => Outcome::Paused(e.to_string()),
        Err(e) => Outcome::Failed(e.to_string()),
    }
}

fn train(input: TrainerInput) -> Result<Outcome, LearnerError> {
    let TrainerInput { job, maps, segs, dir, resume, init, frozen_weights } = input;
    let cfg = &job.cfg;
    let resolved = Arc::clone(&job.resolved);
    let seg_refs: Vec<&MapSegments> = segs.iter().map(|s| &**s).collect();
    let mut sac = Sac::new(
        resolved.sac.clone(),
        resolved.net.clone(),
        resolved.obs.clone(),
        resolved.sim.dt_s,
        &seg_refs,
    )
    .map_err(LearnerError::BuildSac)?;
    let mut st = resume.unwrap_or_default();
    let resumed = start_state(&job, &mut sac, &dir, init.as_ref(), &st)?;
    artifacts::create_dir(&dir)?;
    write_atomic(&dir.join("config.toml"), cfg.to_toml().as_bytes())?;
    // The replay comes back before the first policy is published, i.e. before any worker
    // can push.
    let mut persist = if cfg.train.persist_replay {
        Some(restore_replay(&job, &dir, resumed, init.as_ref(), &mut st)?)
    } else {
        None
    };
    // TensorBoard scalars beside curve.csv (a new event file per start; TensorBoard reads all).
    let mut tb = EventWriter::create(&dir.join("tensorboard"))
        .map_err(|e| tracing::warn!(job_id = job.id.get(), error = %e, "no TensorBoard event file"))
        .ok();
    let mut validator = match &cfg.validation {
        Some(v) => Some((
            Validator::new(v.clone(), cfg, &maps, &job.frozen, &frozen_weights)?,
            BestPolicy::load(&dir)?,
        )),
        None => None,
    };
    if let (Some((_, best)), Some(last)) = (&validator, st.validation.last()) {
        if let Some(b) = &best.point {
            job.record_validation(last.updates, last.scores.success, (b.updates, b.scores.success));
        }
    }
    let mut publisher = Publisher::new(&job, &dir, st.policy_version);
    publisher.publish(&sac)?;
    job.record_update(sac.updates, Default::default());

    let mut rng = ChaCha8Rng::seed_from_u64(cfg.sac.seed ^ 0x7261_6e64 ^ sac.updates);
    let mut batch = Batch::default();
    let mut curve = CurveRecorder::new(cfg.curve_every_steps(), st.counters.env_steps);
    let mut last_ckpt = Instant::now();
    let mut last_loss = Default::default();
    let outcome = loop {
        if let Some(why) = job.stop_reason() {
            break match why {
                StopReason::Cancelled => Outcome::Cancelled,
                StopReason::Shutdown => Outcome::Shutdown,
            };
        }
        if job.is_complete() && !job.limiter.can_sample() {
            break Outcome::Succeeded;
        }
        match job.limiter.sample(Duration::from_millis(100)) {
            Ok(()) => {
                let sampled = {
                    let r = lock(&job.replay);
                    // The cloning updates of `sac.bc_from_warmup` draw from the warm-up's rows
                    // (the whole replay once those are evicted).
                    match cfg.sac.sample_before(sac.updates).map(|b| b + st.carried) {
                        Some(before) => r
                            .sample_before_into(&mut rng, cfg.sac.batch_size, before, &mut batch)
                            .or_else(|_| r.sample_into(&mut rng, cfg.sac.batch_size, &mut batch)),
                        None => r.sample_into(&mut rng, cfg.sac.batch_size, &mut batch),
                    }
                };
                if sampled.is_ok() {
                    last_loss = sac.update(&batch);
                    curve.after_update(&last_loss);
                    job.record_update(sac.updates, last_loss);
                    if sac.updates.is_multiple_of(cfg.train.publish_every_updates) {
                        publisher.publish(&sac)?;
                    }
                    if cfg.train.keep_actors_at.contains(&sac.updates) {
                        keep_actor(&job, &sac, &dir)?;
                    }
                    if let Some((v, best)) = validator
                        .as_mut()
                        .filter(|(v, _)| sac.updates.is_multiple_of(v.section.every_updates))
                    {
                        validate(&job, &sac, v, best, &mut st, tb.as_mut())?;
                    }
                }
            }
            Err(RateLimitError::Timeout(_)) => {}
            Err(RateLimitError::Closed) => continue,
            Err(e) => return Err(e.into()),
        }
        curve.record(&job, &last_loss, publisher.version, &mut st, &mut tb);
        if last_ckpt.elapsed() >= Duration::from_secs(cfg.train.checkpoint_every_s) {
            save(&job, &sac, &dir, &mut st, publisher.version, &mut persist)?;
            last_ckpt = Instant::now();
        }
    };
    if outcome == Outcome::Succeeded {
        // The last actor is a candidate too.
        if let Some((v, best)) = validator
            .as_mut()
            .filter(|_| st.validation.last().is_none_or(|p| p.updates < sac.updates))
        {
            validate(&job, &sac, v, best, &mut st, tb.as_mut())?;
        }
        publisher.publish(&sac)?;
        // The final save writes the replay's last segment: a continuation may carry it
        // (`train.init_replay`). The scheduler deletes it once no unfinished job does.
    }
    save(&job, &sac, &dir, &mut st, publisher.version, &mut persist)?;
    if outcome == Outcome::Succeeded {
        let weights = write_final_policy(&job, &sac, validator.as_mut(), &dir)?;
        if let Some(c) = cfg.coordinator() {
            fit_coordinator(&job, &maps, &segs, &resolved, &c, &weights, &dir)?;
        }
    }
    Ok(outcome)
}

/// The SAC state a run starts from: the job's own checkpoint when it has one (a resumed job;
/// returns true), else `train.init_job`'s last checkpoint with its final policy as the actor
/// (the actor its adversary attacked: `sf_sac::checkpoint::warm_start`) when it names one, else
/// `train.warm_start_from`'s weights (`warm_start.rs`), else fresh weights.
fn start_state(
    job: &ActiveJob,
    sac: &mut Sac,
    dir: &Path,
    init: Option<&InitDep>,
    st: &TrainState,
) -> Result<bool, LearnerError> {
    let ckpt = dir.join("checkpoint");
    if ckpt.exists() {
        checkpoint::restore(sac, &ckpt).map_err(|source| LearnerError::Checkpoint {
            action: "restoring",
            path: ckpt.clone(),
            source,
        })?;
        tracing::info!(
            job_id = job.id.get(),
            updates = sac.updates,
            env_steps = st.counters.env_steps,
            "resumed from checkpoint"
        );
        record_continuation(sac, dir)?;
        return Ok(true);
    }
    if let Some(InitDep { job_id, dir: init }) = init {
        let kept = artifacts::read_final(init, *job_id, "policy.bpk")?;
        let ckpt = init.join("checkpoint");
        checkpoint::warm_start(sac, &ckpt, Some(&kept)).map_err(|source| {
            LearnerError::Checkpoint { action: "starting from", path: ckpt.clone(), source }
        })?;
        tracing::info!(job_id = job.id.get(), from = %init.display(), "started from another job's critic and final policy");
    } else if let Some(from) = crate::warm_start::source(&job.cfg) {
        crate::warm_start::start(sac, &job.cfg, dir)?;
        tracing::info!(job_id = job.id.get(), from = %from.display(), "warm-started from another job's weights");
    }
    Ok(false)
}

/// A continuation's first start (`train.continue_from`): the marker the copy left gets the
/// state the job starts from, so where a run came from is on disk beside it: the update
/// counter and the SHA-256 of the actor and critic as restored (equal to the source
/// checkpoint's `actor.bpk` and `critic.bpk`).
fn record_continuation(sac: &Sac, dir: &Path) -> Result<(), LearnerError> {
    let p = dir.join(CONTINUED_FROM);
    let Ok(text) = std::fs::read_to_string(&p) else { return Ok(()) };
    let mut marker: serde_json::Value = serde_json::from_str(&text)
        .map_err(|source| LearnerError::StateFile { path: p.clone(), source })?;
    if marker.get("updates").is_some() {
        return Ok(());
    }
    let digest = |bytes: Result<Vec<u8>, sf_nn::weights::WeightsError>| {
        bytes.map(|b| sf_nn::weights::sha256_hex(&b)).map_err(|source| LearnerError::Weights {
            action: "serialising the restored state",
            source,
        })
    };
    marker["updates"] = sac.updates.into();
    marker["actor_sha256"] = digest(sac.actor_bytes())?.into();
    marker["critic_sha256"] = digest(sf_nn::weights::to_bytes(&sac.critic))?.into();
    write_atomic(&p, marker.to_string().as_bytes())
}

/// `train.persist_replay`: the replay's segment store, with a resumed job's replay read back
/// into the job (up to the transitions its counters say were on disk), or, for a new
/// continuation with `train.init_replay`, the continued job's replay carried in (numbered before
/// the job's own: `st.carried`) and written by the first checkpoint as the job's own.
fn restore_replay(
    job: &ActiveJob,
    dir: &Path,
    resumed: bool,
    init: Option<&InitDep>,
    st: &mut TrainState,
) -> Result<(ReplayStore, u64), LearnerError> {
    let store = ReplayStore::new(dir.join("replay"));
    if !resumed {
        return match init.filter(|_| job.cfg.train.init_replay) {
            Some(from) => carry_replay(job, from, st).map(|()| (store, 0)),
            None => Ok((store, 0)),
        };
    }
    let t = Instant::now();
    let (r, next) = store
        .restore(job.cfg.train.replay_capacity, job.obs_len, job.action_dim, st.replay_inserted())
        .map_err(|source| LearnerError::Replay { action: "restoring", source })?;
    tracing::info!(
        job_id = job.id.get(),
        transitions = r.len(),
        ms = t.elapsed().as_millis() as u64,
        "replay restored"
    );
    install_replay(job, r);
    Ok((store, next))
}

/// Makes `r` the job's replay (before any worker can push).
fn install_replay(job: &ActiveJob, r: sf_sac::Replay) {
    job.metrics.replay_size.set(r.len() as i64);
    *lock(&job.replay) = r;
}

/// `train.init_replay`: reads the newest `replay_capacity` transitions of the continued job's
/// replay (left as it is, for other continuations) into the job, numbered `0..carried`.
fn carry_replay(job: &ActiveJob, from: &InitDep, st: &mut TrainState) -> Result<(), LearnerError> {
    let refuse = |reason: String| LearnerError::Dependency {
        field: "train.init_replay",
        dep: from.job_id,
        reason,
    };
    let t = Instant::now();
    let theirs = load_state(&from.dir)?
        .ok_or_else(|| refuse(format!("has no state.json in {}", from.dir.display())))?;
    let replay = from.dir.join("replay");
    if !replay.exists() {
        return Err(refuse(format!(
            "has no replay in {} (deleted when it finished, before this job was queued?)",
            replay.display()
        )));
    }
    let mut r = ReplayStore::new(&replay)
        .read(job.cfg.train.replay_capacity, job.obs_len, job.action_dim, theirs.replay_inserted())
        .map_err(|source| LearnerError::Replay { action: "carrying", source })?;
    if r.is_empty() {
        return Err(refuse(format!("has an empty replay in {}", replay.display())));
    }
    let carried = r.len() as u64;
    r.renumber(carried);
    st.carried = carried;
    tracing::info!(
        job_id = job.id.get(),
        from = from.job_id.get(),
        transitions = carried,
        ms = t.elapsed().as_millis() as u64,
        "replay carried from the continued job"
    );
    install_replay(job, r);
    Ok(())
}

/// Publishes the actor to workers under version numbers that are never issued twice, even
/// across a crash: the newest is written (`published_version`) before workers can see it, and
/// a restart continues above it (not above the checkpoint's).
struct Publisher<'a> {
    job: &'a ActiveJob,
    file: PathBuf,
    /// The last version published.
    version: PolicyVersion,
}

impl<'a> Publisher<'a> {
    fn new(job: &'a ActiveJob, dir: &Path, saved_version: PolicyVersion) -> Self {
        let file = dir.join("published_version");
        let issued = std::fs::read_to_string(&file)
            .ok()
            .and_then(|s| s.trim().parse::<u64>().ok())
            .map(PolicyVersion::new)
            .unwrap_or_default();
        Self { job, file, version: saved_version.max(issued) }
    }

    fn publish(&mut self, sac: &Sac) -> Result<(), LearnerError> {
        self.version = self.version.next();
        let bytes = sac
            .acting_actor_bytes()
            .map_err(|source| LearnerError::Weights { action: "serialising the actor", source })?;
        write_atomic(&self.file, self.version.to_string().as_bytes())?;
        self.job.publish(self.version, bytes);
        Ok(())
    }
}

/// A CSV file's text: the header, then one row per line.
fn csv(header: &str, rows: impl Iterator<Item = String>) -> String {
    let mut text = String::from(header);
    text.push('\n');
    for r in rows {
        text.push_str(&r);
        text.push('\n');
    }
    text
}

/// Checkpoint + state + curve files.
/// The replay's segment directory and the insertion number its next segment starts at.
type Persist = Option<(ReplayStore, u64)>;

fn save(
    job: &ActiveJob,
    sac: &Sac,
    dir: &Path,
    st: &mut TrainState,
    version: PolicyVersion,
    persist: &mut Persist,
) -> Result<(), LearnerError> {
    let t = Instant::now();
    st.counters = job.counters();
    st.policy_version = version;
    checkpoint::save(sac, &dir.join("checkpoint")).map_err(LearnerError::SaveCheckpoint)?;
    // The replay segment before state.json: the counters written next never count a
    // transition that is not on disk.
    let mut replay_bytes = 0;
    if let Some((store, next)) = persist.as_mut() {
        let (seg, oldest) = {
            let r = lock(&job.replay);
            (Segment::snapshot(&r, *next), r.oldest())
        };
        replay_bytes = store
            .append(&seg, oldest)
            .map_err(|source| LearnerError::Replay { action: "writing", source })?;
        *next = seg.first + seg.len() as u64;
    }
    write_atomic(&state_path(dir), serde_json::to_string(st)?.as_bytes())?;
    write_atomic(
        &dir.join("curve.csv"),
        csv(CurvePoint::CSV_HEADER, st.curve.iter().map(CurvePoint::csv_row)).as_bytes(),
    )?;
    if !st.validation.is_empty() {
        write_atomic(
            &dir.join("validation.csv"),
            csv(ValidationPoint::CSV_HEADER, st.validation.iter().map(ValidationPoint::csv_row))
                .as_bytes(),
        )?;
    }
    if st.curve.len() >= 2 {
        let pts: Vec<(f64, f64)> = st
            .curve
            .iter()
            .map(|p| (p.learning.env_steps as f64, p.learning.scores.success as f64))
            .collect();
        let safety: Vec<(f64, f64)> = st
            .curve
            .iter()
            .map(|p| (p.learning.env_steps as f64, p.learning.scores.safety as f64))
            .collect();
        let series =
            [Series { name: "success", points: pts }, Series { name: "safety", points: safety }];
        let title = format!("job {} ({})", job.id, job.cfg.name);
        if let Err(e) = line_chart(
            &dir.join("curve.png"),
            &title,
            "learner transitions",
            "rolling fraction of episodes",
            &series,
            Some((0.0, 1.0)),
            (800, 500),
        ) {
            tracing::warn!(error = %e, "could not draw curve.png");
        }
    }
    job.metrics.totals.checkpoints.inc();
    tracing::info!(
        job_id = job.id.get(),
        updates = sac.updates,
        policy_version = version.get(),
        replay_bytes,
        ms = t.elapsed().as_millis() as u64,
        "checkpoint written"
    );
    Ok(())
}
