//! Following a job through the job API: a client with its token and the progress display
//! (`socialflow train`, `submit --watch`, `watch`, the ladder's jobs).
//!
//! Owns: [`jobs_client`], [`bar`], [`show`], [`watch`]. Must not: define the calls (they are
//! `sf_service::client`'s) or decide what a job's end means for a command.

use anyhow::{anyhow, Result};
use indicatif::{ProgressBar, ProgressStyle};
use sf_job::{JobId, JobState, Progress};
use sf_service::auth::Token;
use sf_service::client::{JobsClient, Watch};

/// A job-API client for the learner at `url` (`endpoint`), sending `token` with every call.
pub async fn jobs_client(
    endpoint: tonic::transport::Endpoint,
    url: &str,
    token: Option<Token>,
) -> Result<JobsClient> {
    Ok(sf_service::client::connect(endpoint, url, token).await?)
}

/// A progress bar over learner transitions.
pub fn bar(target: u64) -> ProgressBar {
    let pb = ProgressBar::new(target);
    pb.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} steps  {msg}")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb
}

pub fn show(pb: &ProgressBar, state: JobState, progress: &Progress) {
    let p = &progress.learning;
    pb.set_length(progress.target_env_steps.max(1));
    pb.set_position(p.env_steps);
    pb.set_message(format!(
        "{} | updates {} | v{} | {:.0} steps/s | success {:.2} safety {:.2} speed {:.2} (last {} episodes)",
        state.as_str(),
        p.updates,
        progress.policy_version,
        progress.env_steps_per_s,
        p.scores.success,
        p.scores.safety,
        p.scores.speed,
        p.episodes.min(100)
    ));
}

/// Follows a job until it reaches a final state; returns that state and the last progress.
pub async fn watch(c: &mut JobsClient, job_id: JobId, quiet: bool) -> Result<(JobState, Progress)> {
    let mut w = Watch::open(c, job_id).await?;
    let pb = if quiet { ProgressBar::hidden() } else { bar(1) };
    let mut last = None;
    while let Some((state, p)) = w.next().await? {
        show(&pb, state, &p);
        last = Some((state, p));
    }
    pb.finish();
    last.ok_or_else(|| anyhow!("the learner ended the watch of job {job_id} without progress"))
}
