//! `socialflow pipeline <dir>`: submits a directory of job configs as one graph, dependencies
//! first, and follows it to the end; rerun, it resumes where it stopped.
//!
//! Owns: name-based references between the configs of a directory (`env.background_from =
//! "<job name>"`, turned into `env.background_job = <id>` at submission), the submission order,
//! reuse of jobs the learner already has under the same name (unless they failed or were
//! cancelled), and the final summary. Must not: schedule (the learner runs queued jobs in order
//! once their dependency has succeeded).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;
use sf_job::{JobConfig, JobState};

use crate::remote::{self, Conn, JobsClient};
use crate::train::{runtime, Embedded};

#[derive(Args, Debug)]
pub struct PipelineArgs {
    /// Directory of job configs (`*.toml`), e.g. configs/paper-small.
    pub dir: PathBuf,
    /// Run on an embedded learner with this many workers instead of a remote one.
    #[arg(long)]
    pub embedded: Option<usize>,
    /// Embedded: job store and artifacts (rerun with the same directory to resume).
    #[arg(long, default_value = "runs/pipeline")]
    pub data_dir: PathBuf,
    #[command(flatten)]
    pub conn: Conn,
}

/// The configs of a pipeline directory in submission order (every job after its dependency).
pub fn load(dir: &Path) -> Result<Vec<(PathBuf, JobConfig, String)>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading pipeline directory {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{} holds no job configs (*.toml)", dir.display());
    }
    let mut jobs: BTreeMap<String, (PathBuf, JobConfig, String)> = BTreeMap::new();
    for f in files {
        let text = std::fs::read_to_string(&f).with_context(|| format!("reading {}", f.display()))?;
        let cfg = JobConfig::from_toml(&text).with_context(|| f.display().to_string())?;
        if let Some((other, _, _)) = jobs.get(&cfg.name) {
            bail!("{} and {} both name their job `{}`", other.display(), f.display(), cfg.name);
        }
        jobs.insert(cfg.name.clone(), (f, cfg, text));
    }
    for (path, cfg, _) in jobs.values() {
        if let Some(dep) = &cfg.env.background_from {
            match jobs.get(dep) {
                None => bail!("{}: env.background_from names `{dep}`, which no config in {} defines", path.display(), dir.display()),
                Some((_, d, _)) if !d.kind.multi_agent() => bail!("{}: env.background_from names `{dep}`, an ego job, not a flow", path.display()),
                Some(_) => {}
            }
        }
    }
    // Flows (no dependency) first, then the jobs that depend on them, each group by name.
    let (mut first, mut then): (Vec<_>, Vec<_>) = jobs.into_values().partition(|(_, c, _)| c.env.background_from.is_none());
    first.append(&mut then);
    Ok(first)
}

/// Submits what the learner does not have yet; returns (name, job id) in submission order.
async fn submit_all(c: &mut JobsClient, jobs: &[(PathBuf, JobConfig, String)]) -> Result<Vec<(String, u64)>> {
    let existing = remote::list(c).await?;
    let mut ids: BTreeMap<String, u64> = BTreeMap::new();
    let mut out = Vec::new();
    for (path, cfg, _) in jobs {
        let reuse = existing.iter().filter(|j| j.name == cfg.name && !matches!(j.state, JobState::Failed | JobState::Cancelled)).max_by_key(|j| j.id);
        let id = match reuse {
            Some(j) => {
                eprintln!("{}: job {} ({}) already on the learner", cfg.name, j.id, j.state.as_str());
                j.id
            }
            None => {
                let mut cfg = cfg.clone();
                if let Some(dep) = cfg.env.background_from.take() {
                    cfg.env.background_job = Some(*ids.get(&dep).with_context(|| format!("{}: dependency `{dep}` was not submitted", path.display()))?);
                }
                let j = remote::submit(c, cfg.to_toml()).await.with_context(|| path.display().to_string())?;
                eprintln!("{}: submitted as job {}", cfg.name, j.id);
                j.id
            }
        };
        ids.insert(cfg.name.clone(), id);
        out.push((cfg.name.clone(), id));
    }
    Ok(out)
}

/// Polls until every job is final; prints one JSON line per job; fails if any did not succeed.
async fn follow(c: &mut JobsClient, ids: &[(String, u64)]) -> Result<()> {
    loop {
        let all = remote::list(c).await?;
        let mine: Vec<_> = ids.iter().filter_map(|(_, id)| all.iter().find(|j| j.id == *id)).collect();
        if mine.len() == ids.len() && mine.iter().all(|j| j.state.is_final()) {
            let mut bad = Vec::new();
            for j in &mine {
                println!("{}", json!({"name": j.name, "job_id": j.id, "state": j.state.as_str(), "message": j.message, "artifact_dir": j.artifact_dir, "progress": j.progress}));
                if j.state != JobState::Succeeded {
                    bad.push(format!("{} ({})", j.name, j.state.as_str()));
                }
            }
            if !bad.is_empty() {
                bail!("pipeline jobs did not succeed: {}", bad.join(", "));
            }
            return Ok(());
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

pub fn run(scenarios_dir: PathBuf, a: PipelineArgs) -> Result<()> {
    let jobs = load(&a.dir)?;
    runtime()?.block_on(async move {
        match a.embedded {
            Some(0) => bail!("--embedded needs at least one worker"),
            Some(n) => {
                let emb = Embedded::start(a.data_dir.clone(), scenarios_dir, n).await?;
                let mut c = emb.client().await?;
                let r = async {
                    let ids = submit_all(&mut c, &jobs).await?;
                    tokio::select! {
                        r = follow(&mut c, &ids) => r.map(Some),
                        _ = sf_svc::signal::terminate() => Ok(None),
                    }
                }
                .await;
                emb.stop().await?;
                match r? {
                    Some(()) => Ok(()),
                    None => {
                        eprintln!("interrupted: the running job is checkpointed; run the same command to resume");
                        Ok(())
                    }
                }
            }
            None => {
                let mut c = remote::connect(&a.conn).await?;
                let ids = submit_all(&mut c, &jobs).await?;
                follow(&mut c, &ids).await
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_small_graph_submits_flows_before_the_egos_that_need_them() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/paper-small");
        let jobs = load(&dir).expect("a valid pipeline");
        let pos = |n: &str| jobs.iter().position(|(_, c, _)| c.name == n).unwrap_or_else(|| panic!("{n} missing"));
        for k in ["macad", "copo", "socialcomm"] {
            assert!(pos(&format!("flow-{k}")) < pos(&format!("ego-{k}")), "{k}");
            assert_eq!(jobs[pos(&format!("ego-{k}"))].1.env.background_from.as_deref(), Some(format!("flow-{k}").as_str()));
        }
        assert!(jobs[pos("ego-idm")].1.env.background_from.is_none());
    }
}
