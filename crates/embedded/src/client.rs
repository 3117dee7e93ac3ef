//! Following a job through the job API: a client with its token and the progress display
//! (`socialflow train`, `submit --watch`, `watch`, the ladder's jobs).
//!
//! Owns: [`jobs_client`], [`bar`], [`show`], [`line`], [`watch`]: on a terminal a progress bar
//! (transitions, ETA, updates, rolling and held-out success), elsewhere (a log file, CI) one
//! line per validation, or per tenth of the job for jobs without one. Must not: define the calls
//! (they are `sf_service::client`'s) or decide what a job's end means for a command.

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
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} steps, eta {eta}  {msg}",
        )
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
        "{} | updates {} | v{} | {:.0} steps/s | success {:.2} safety {:.2} speed {:.2} (last {} episodes){}",
        state.as_str(),
        p.updates,
        progress.policy_version,
        progress.env_steps_per_s,
        p.scores.success,
        p.scores.safety,
        p.scores.speed,
        p.episodes.min(100),
        held_out(progress)
    ));
}

/// ` | held-out 0.74 (best 0.76 at 21000)` once the job has validated, else nothing.
fn held_out(progress: &Progress) -> String {
    progress.validation.map_or_else(String::new, |v| {
        format!(" | held-out {:.3} (best {:.3} at {})", v.success, v.best_success, v.best_updates)
    })
}

/// One line of progress for a log (not a terminal): transitions, updates, an estimate of the
/// time left from the job's own pace, rolling and held-out success.
pub fn line(job_id: JobId, state: JobState, progress: &Progress) -> String {
    let p = &progress.learning;
    let target = progress.target_env_steps.max(1);
    let eta = (p.env_steps > 0 && p.env_steps < target).then(|| {
        let left_s = p.wall_s * (target - p.env_steps) as f64 / p.env_steps as f64;
        format!(", eta {}m", (left_s / 60.0).ceil())
    });
    format!(
        "job {job_id} {}: {}/{} transitions ({:.0} %){}, updates {}, success {:.3} (last {} episodes){}",
        state.as_str(),
        p.env_steps,
        target,
        100.0 * p.env_steps as f64 / target as f64,
        eta.unwrap_or_default(),
        p.updates,
        p.scores.success,
        p.episodes.min(100),
        held_out(progress)
    )
}

/// Follows a job until it reaches a final state; returns that state and the last progress.
pub async fn watch(c: &mut JobsClient, job_id: JobId, quiet: bool) -> Result<(JobState, Progress)> {
    let mut w = Watch::open(c, job_id).await?;
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let pb = if quiet || !terminal { ProgressBar::hidden() } else { bar(1) };
    let mut last: Option<(JobState, Progress)> = None;
    while let Some((state, p)) = w.next().await? {
        show(&pb, state, &p);
        if !quiet && !terminal {
            // A line per validation; a job without one, a line per tenth of its transitions.
            let tenth = |q: &Progress| q.learning.env_steps * 10 / q.target_env_steps.max(1);
            let new = match (last.as_ref().map(|l| &l.1), p.validation) {
                (None, _) => true,
                (Some(l), Some(v)) => l.validation.map(|lv| lv.updates) != Some(v.updates),
                (Some(l), None) => tenth(l) != tenth(&p),
            };
            if new {
                eprintln!("{}", line(job_id, state, &p));
            }
        }
        last = Some((state, p));
    }
    pb.finish();
    last.ok_or_else(|| anyhow!("the learner ended the watch of job {job_id} without progress"))
}
