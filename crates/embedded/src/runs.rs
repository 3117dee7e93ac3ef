//! Finished jobs in a learner's data directory (`jobs/<id>-<name>/`), as `socialflow eval` and
//! the ladder find them.
//!
//! Owns: [`find_job`] (by pinned id, else the newest of a name with a final policy) and
//! [`load_job`]. Must not: write into the directory (the learner owns it).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use sf_job::JobId;
use sf_rollout::evaluate::Policy;

/// Every `jobs/<id>-<name>/` directory of a learner's data directory as `(id, name, dir)`.
fn job_dirs(runs: &Path) -> Result<Vec<(JobId, String, PathBuf)>> {
    let jobs = runs.join("jobs");
    let mut out = Vec::new();
    for e in
        std::fs::read_dir(&jobs).with_context(|| format!("reading {}", jobs.display()))?.flatten()
    {
        let file = e.file_name().to_string_lossy().to_string();
        if let Some((id, name)) = file
            .split_once('-')
            .and_then(|(id, name)| Some((JobId::new(id.parse().ok()?), name.to_string())))
        {
            out.push((id, name, e.path()));
        }
    }
    Ok(out)
}

/// The job a flow or ego names: by `job_id` if pinned, else the newest `jobs/<id>-<name>/`
/// with a final policy.
pub fn find_job(runs: &Path, name: &str, id: Option<JobId>) -> Result<Policy> {
    let dirs = job_dirs(runs)?;
    let dir = match id {
        Some(id) => {
            dirs.into_iter().find(|(i, _, _)| *i == id).map(|(_, _, d)| d).with_context(|| {
                format!("job {id} has no directory under {}", runs.join("jobs").display())
            })?
        }
        None => {
            let best = dirs
                .into_iter()
                .filter(|(_, n, dir)| n == name && dir.join("policy.bpk").exists())
                .max_by_key(|(id, _, _)| *id);
            best.map(|(_, _, d)| d).with_context(|| {
                format!("no finished job named `{name}` under {}", runs.join("jobs").display())
            })?
        }
    };
    load_job(&dir)
}

pub fn load_job(dir: &Path) -> Result<Policy> {
    Policy::load(dir).map_err(anyhow::Error::msg)
}
