//! Following a job through the job API: a client with its token and the progress display
//! (`socialflow train`, `submit --watch`, `watch`, the ladder's jobs) and of several jobs at once
//! (`pipeline`).
//!
//! Owns: [`jobs_client`], [`bar`], [`show`], [`line`], [`watch`], [`Board`], [`EpisodesBar`]: on a terminal a
//! progress bar per job (transitions, ETA, updates, rolling and held-out success), elsewhere (a
//! log file, CI) one line per validation, or per tenth of the job for jobs without one, and one
//! as a job starts or ends. Must not: define the calls (they are `sf_service::client`'s) or
//! decide what a job's end means for a command.

use anyhow::{anyhow, Result};
use std::collections::BTreeMap;

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
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
    ProgressBar::new(target).with_style(bar_style("", "steps"))
}

/// A bar counting `unit` (a job's steps, a grid's episodes), `lead` (a job's name, `{prefix}`)
/// before the elapsed time.
fn bar_style(lead: &str, unit: &str) -> ProgressStyle {
    ProgressStyle::with_template(&format!(
        "{lead}{{elapsed_precise}} [{{bar:30}}] {{pos}}/{{len}} {unit}, eta {{eta}}  {{msg}}"
    ))
    .map(|s| s.progress_chars("=> "))
    .unwrap_or_else(|_| ProgressStyle::default_bar())
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

/// Whether progress `p` in `state` is worth a line in a log after `last`: the first report, a
/// change of state, a new validation point, or (a job without validation) a new tenth of its
/// transitions.
fn worth_a_line(last: Option<&(JobState, Progress)>, state: JobState, p: &Progress) -> bool {
    let tenth = |q: &Progress| q.learning.env_steps * 10 / q.target_env_steps.max(1);
    match (last, p.validation) {
        (None, _) => true,
        (Some((s, _)), _) if *s != state => true,
        (Some((_, l)), Some(v)) => l.validation.map(|lv| lv.updates) != Some(v.updates),
        (Some((_, l)), None) => tenth(l) != tenth(p),
    }
}

/// Follows a job until it reaches a final state; returns that state and the last progress.
pub async fn watch(c: &mut JobsClient, job_id: JobId, quiet: bool) -> Result<(JobState, Progress)> {
    let mut w = Watch::open(c, job_id).await?;
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let pb = if quiet || !terminal { ProgressBar::hidden() } else { bar(1) };
    let mut last: Option<(JobState, Progress)> = None;
    while let Some((state, p)) = w.next().await? {
        show(&pb, state, &p);
        if !quiet && !terminal && worth_a_line(last.as_ref(), state, &p) {
            eprintln!("{}", line(job_id, state, &p));
        }
        last = Some((state, p));
    }
    pb.finish();
    last.ok_or_else(|| anyhow!("the learner ended the watch of job {job_id} without progress"))
}

/// The progress of several jobs followed together (`pipeline`): on a terminal a line counting
/// the jobs that ended, and a bar per job once it has left the queue (kept, with its final
/// state, when it ends); elsewhere ([`Board::lines`]) a line per validation of each job, or per
/// tenth of a job without one, and one as it starts and as it ends.
pub struct Board {
    multi: MultiProgress,
    ended: ProgressBar,
    bars: BTreeMap<JobId, ProgressBar>,
    last: BTreeMap<JobId, (JobState, Progress)>,
    lines: bool,
}

impl Board {
    /// A board for `jobs` jobs: bars on a terminal (stderr), lines elsewhere.
    pub fn new(jobs: usize) -> Self {
        let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
        Self::with(jobs, !terminal)
    }

    /// Lines (`lines`) or bars, whatever stderr is.
    pub fn with(jobs: usize, lines: bool) -> Self {
        let target =
            if lines { ProgressDrawTarget::hidden() } else { ProgressDrawTarget::stderr() };
        let multi = MultiProgress::with_draw_target(target);
        let ended = multi.add(ProgressBar::new(jobs as u64));
        ended.set_style(
            ProgressStyle::with_template("{elapsed_precise} {pos}/{len} jobs ended {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        Self { multi, ended, bars: BTreeMap::new(), last: BTreeMap::new(), lines }
    }

    /// Records job `id` (`name`) in `state` with progress `p`; returns the line a log gets for
    /// it, if any (already written to stderr when the board writes lines).
    pub fn update(
        &mut self,
        name: &str,
        id: JobId,
        state: JobState,
        p: &Progress,
    ) -> Option<String> {
        let last = self.last.get(&id);
        let line = worth_a_line(last, state, p)
            .then(|| format!("{name}: {}", line(id, state, p)))
            .filter(|_| state != JobState::Queued || last.is_none());
        if state != JobState::Queued && !self.bars.contains_key(&id) {
            let pb =
                self.multi.add(ProgressBar::new(1).with_style(bar_style("{prefix} ", "steps")));
            pb.set_prefix(name.to_string());
            self.bars.insert(id, pb);
        }
        if let Some(pb) = self.bars.get(&id) {
            show(pb, state, p);
            if state.is_final() && !pb.is_finished() {
                pb.abandon_with_message(format!("{name}: {}", state.as_str()));
            }
        }
        self.last.insert(id, (state, *p));
        let ended = self.last.values().filter(|(s, _)| s.is_final()).count();
        self.ended.set_position(ended as u64);
        if self.lines {
            if let Some(l) = &line {
                eprintln!("{l}");
            }
        }
        line
    }

    /// Leaves the bars as they are drawn.
    pub fn finish(&self) {
        self.ended.finish();
    }
}

/// An evaluation grid's progress (`eval`): on a terminal a bar over its episodes (done, ETA)
/// with each cell's line printed above it; elsewhere the cell lines alone.
pub struct EpisodesBar {
    pub bar: ProgressBar,
    terminal: bool,
}

impl EpisodesBar {
    pub fn new(episodes: u64) -> Self {
        let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
        let bar = if terminal { ProgressBar::new(episodes) } else { ProgressBar::hidden() };
        bar.set_style(bar_style("", "episodes"));
        Self { bar, terminal }
    }

    /// A line for the terminal or the log, above the bar where there is one.
    pub fn line(&self, l: String) {
        if self.terminal {
            self.bar.println(l);
        } else {
            eprintln!("{l}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sf_job::ValidationProgress;

    fn at(env_steps: u64, validated_at: Option<u64>) -> Progress {
        let mut p = Progress { target_env_steps: 1000, ..Progress::default() };
        p.learning.env_steps = env_steps;
        p.validation = validated_at.map(|updates| ValidationProgress {
            updates,
            success: 0.5,
            best_updates: updates,
            best_success: 0.5,
        });
        p
    }

    /// A log gets one line as each job is first seen, starts, validates and ends, and none for
    /// the polls in between; jobs are told apart by name.
    #[test]
    fn a_board_writes_a_line_per_start_validation_and_end_of_each_job() {
        let mut b = Board::with(2, true);
        let (a, z) = (JobId::new(1), JobId::new(2));
        let mut lines = Vec::new();
        let mut step = |name: &str, id, state, p: Progress| {
            lines.extend(b.update(name, id, state, &p));
        };
        step("ego", a, JobState::Queued, at(0, None));
        step("flow", z, JobState::Queued, at(0, None));
        step("ego", a, JobState::Queued, at(0, None));
        step("ego", a, JobState::Running, at(10, None));
        step("ego", a, JobState::Running, at(20, None));
        step("ego", a, JobState::Running, at(30, Some(100)));
        step("ego", a, JobState::Running, at(40, Some(100)));
        step("ego", a, JobState::Running, at(50, Some(200)));
        step("ego", a, JobState::Succeeded, at(1000, Some(200)));
        step("flow", z, JobState::Running, at(5, None));
        step("flow", z, JobState::Failed, at(5, None));
        let want = [
            "ego: job 1 queued",
            "flow: job 2 queued",
            "ego: job 1 running",
            "ego: job 1 running",
            "ego: job 1 running",
            "ego: job 1 succeeded",
            "flow: job 2 running",
            "flow: job 2 failed",
        ];
        assert_eq!(lines.len(), want.len(), "{lines:#?}");
        for (l, w) in lines.iter().zip(want) {
            assert!(l.starts_with(w), "{l:?} is not {w:?}...");
        }
        assert!(lines[3].contains("held-out 0.500 (best 0.500 at 100)"), "{}", lines[3]);
        assert_eq!(b.ended.position(), 2, "both jobs ended");
    }
}
