//! `socialflow train <config>`: the learner and N workers in this process, talking gRPC over
//! loopback exactly as in a deployment, with a progress bar. Also the `learner` and `worker`
//! subcommands (the service binaries' entry points, for a one-binary image). The embedded set-up
//! itself is `sf_embedded::Embedded`, shared with the lab's service benchmarks and ladder.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;
use sf_embedded::{runtime, Embedded};
use sf_job::JobState;

use crate::remote;
use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Job config (TOML), e.g. configs/quickstart.toml.
    pub config: PathBuf,
    /// Rollout workers in this process.
    #[arg(long, default_value_t = 2)]
    pub workers: usize,
    /// Job store and artifacts; rerunning with the same directory resumes an interrupted job.
    #[arg(long, default_value = "runs/embedded")]
    pub data_dir: PathBuf,
    /// No progress bar (logs only).
    #[arg(long)]
    pub quiet: bool,
    /// Continue the run in this job directory (a stopped or finished job's, copied or
    /// committed) instead of starting from scratch: sets `train.continue_from`; the config's
    /// `train.env_steps` is the run's total. Rerun with the same data directory, it resumes.
    #[arg(long, value_name = "JOB_DIR")]
    pub continue_from: Option<PathBuf>,
    /// Start from the weights of this job directory (its `checkpoint/`), which may be of
    /// another kind with the same network sizes (a MACAD flow's into a SocialComm job): sets
    /// `train.warm_start_from`. Rerun with the same data directory, it resumes.
    #[arg(long, value_name = "JOB_DIR", conflicts_with = "continue_from")]
    pub warm_start_from: Option<PathBuf>,
    /// Override a setting of the config (repeatable): `--set sac.seed=12`; validated like
    /// the file and recorded in the job's stored config.
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    pub set: Vec<String>,
}

pub fn run(dirs: &Ctx, a: TrainArgs) -> Result<()> {
    let text = std::fs::read_to_string(&a.config)
        .with_context(|| format!("reading {}", a.config.display()))?;
    // The learner is in this process: a source directory as an absolute path of this host,
    // written in as one more override so that the config is validated with it (an absolute
    // path is not TOML, so it is read as a string).
    let abs = |from: &PathBuf, flag: &str| {
        std::fs::canonicalize(from)
            .map(|p| p.display().to_string())
            .with_context(|| format!("{flag} {}", from.display()))
    };
    let mut sets = a.set.clone();
    if let Some(from) = &a.continue_from {
        sets.push(format!("train.continue_from={}", abs(from, "--continue-from")?));
    }
    if let Some(from) = &a.warm_start_from {
        sets.push(format!("train.warm_start_from={}", abs(from, "--warm-start-from")?));
    }
    let (text, cfg) = crate::remote::with_overrides(&a.config, &text, &sets)?;
    if a.workers == 0 {
        bail!("--workers must be at least 1");
    }
    // The device before any port: a cuda job on a machine without a GPU stops here.
    sf_nn::device::device(sf_sac::device_kind(cfg.sac.device))
        .with_context(|| format!("{}: field `sac.device`", a.config.display()))?;
    runtime()?.block_on(async move {
        let emb = Embedded::start(a.data_dir.clone(), dirs, a.workers).await?;
        let mut c = emb.client().await?;
        let mut existing = None;
        for j in remote::list(&mut c).await?.into_iter().filter(|j| j.name == cfg.name && !j.state.is_final()) {
            let full = remote::get(&mut c, j.id).await?;
            if full.config_toml == text {
                existing = Some(full);
                break;
            }
        }
        let job = match existing {
            Some(j) => {
                eprintln!("resuming job {} ({}) from {}", j.id, j.name, j.artifact_dir);
                j
            }
            None => remote::submit(&mut c, text.clone()).await?,
        };
        let learner = std::sync::Arc::clone(&emb.learner.learner);
        let watched = tokio::select! {
            r = remote::watch(&mut c, job.id, a.quiet) => Watched::Ended(r),
            _ = sf_service::signal::terminate() => Watched::Interrupted,
            cause = storage_fault(&learner) => Watched::StorageFault(cause),
        };
        emb.stop().await?;
        let checkpoint = checkpoint_line(Path::new(&job.artifact_dir));
        let r = match watched {
            Watched::Ended(r) => r,
            Watched::Interrupted => {
                eprintln!("interrupted: job {} {checkpoint}; run the same command to resume", job.id);
                return Ok(());
            }
            Watched::StorageFault(cause) => {
                bail!("job {} stopped: the data directory {} refuses writes ({cause}); job {} {checkpoint}; free space and run the same command to resume", job.id, a.data_dir.display(), job.id)
            }
        };
        let (state, p) = r?;
        let held_out = held_out(Path::new(&job.artifact_dir));
        if let Some(h) = &held_out {
            eprintln!("{}", held_out_table(h));
        }
        println!("{}", json!({"job_id": job.id, "name": job.name, "state": state.as_str(), "artifact_dir": job.artifact_dir, "progress": p, "held_out": held_out}));
        if state != JobState::Succeeded {
            bail!("job {} ended {}", job.id, state.as_str());
        }
        Ok(())
    })
}

/// How watching an embedded job ended.
enum Watched {
    Ended(Result<(JobState, sf_job::Progress)>),
    Interrupted,
    StorageFault(String),
}

/// Resolves with the cause once the embedded learner's data directory refuses writes.
async fn storage_fault(learner: &sf_learner::Learner) -> String {
    loop {
        if let Some(cause) = learner.storage_fault() {
            return cause;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

/// What a job's directory holds to resume from, as its `state.json` (written with each
/// checkpoint) says: never a checkpoint that was not written.
fn checkpoint_line(artifact_dir: &Path) -> String {
    let state = std::fs::read_to_string(artifact_dir.join("state.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok());
    match state
        .as_ref()
        .and_then(|v| Some((v["counters"]["env_steps"].as_u64()?, v["policy_version"].as_u64()?)))
    {
        Some((steps, version)) if artifact_dir.join("checkpoint").exists() => {
            format!("is checkpointed at {steps} environment steps (policy version {version})")
        }
        _ => "has no checkpoint yet (it starts from the beginning)".to_string(),
    }
}

/// The final policy's and the IDM driver's scores on held-out cases (its `policy.json`, when
/// the job has `[validation]`): the test cases, which selected nothing, or for a job finished
/// before they existed the validation cases, which chose the policy (`used_for_selection`).
pub fn held_out(artifact_dir: &Path) -> Option<serde_json::Value> {
    let text = std::fs::read_to_string(artifact_dir.join("policy.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    let scores = |p: &serde_json::Value| json!({"success": p["success"], "collision": p["collision"], "speed": p["speed"]});
    let t = &v["test"];
    if t["policy"].is_object() && t["idm"].is_object() {
        return Some(
            json!({"cases": "test", "cases_seed": t["seed"], "used_for_selection": false, "episodes": t["policy"]["episodes"], "policy": scores(&t["policy"]), "idm": scores(&t["idm"])}),
        );
    }
    (v["validation"].is_object() && v["idm"].is_object()).then(|| json!({"cases": "validation", "used_for_selection": true, "episodes": v["validation"]["episodes"], "policy": scores(&v["validation"]), "idm": scores(&v["idm"])}))
}

/// [`held_out`] as a table for the terminal.
fn held_out_table(h: &serde_json::Value) -> String {
    let row = |name: &str, p: &serde_json::Value| {
        let f = |k: &str| p[k].as_f64().map_or_else(|| "-".to_string(), |x| format!("{x:.3}"));
        format!("  {name:<16} {:>8} {:>10} {:>7}", f("success"), f("collision"), f("speed"))
    };
    let head = format!("  {:<16} {:>8} {:>10} {:>7}", "", "success", "collision", "speed");
    let which = if h["used_for_selection"] == false {
        format!("test cases, seed {}: they chose nothing", h["cases_seed"])
    } else {
        "validation cases: they chose the policy".to_string()
    };
    format!(
        "the same {} held-out episodes ({which}):\n{head}\n{}\n{}",
        h["episodes"],
        row("learned policy", &h["policy"]),
        row("IDM driver", &h["idm"])
    )
}

pub fn learner(a: sf_learner::cmd::LearnerArgs) -> Result<()> {
    runtime()?.block_on(sf_learner::cmd::run(a))
}

pub fn worker(a: sf_worker::cmd::WorkerArgs) -> Result<()> {
    runtime()?.block_on(sf_worker::cmd::run(a))
}
