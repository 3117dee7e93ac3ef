//! The running job's learning curve: [`CurveRecorder`] adds a point every `every` learner
//! transitions (`curve.csv` and `state.json` through [`TrainState`]) with the rollout
//! statistics and the losses since the previous point, and writes the same plus rates and
//! policy lag as TensorBoard scalars. Must not: write files itself or touch the SAC state; the
//! trainer saves what it records.

use sf_report::tensorboard::EventWriter;
use sf_sac::{CurvePoint, Losses};

use super::TrainState;
use crate::job::ActiveJob;

/// The learning curve: a point every `every` learner transitions (`curve.csv`, `state.json`)
/// with the rollout statistics and the losses, and the same plus rates and policy lag as
/// TensorBoard scalars.
pub(super) struct CurveRecorder {
    every: u64,
    next_point: u64,
    /// Critic losses and the Q mean's sum of the updates since the previous point.
    recent_losses: Vec<f32>,
    recent_q: f64,
    /// (wall_s, updates, env_steps) at the previous point: the rates between points.
    last_rates: Option<(f64, u64, u64)>,
}

impl CurveRecorder {
    pub(super) fn new(every: u64, env_steps: u64) -> Self {
        Self {
            every,
            next_point: (env_steps / every + 1) * every,
            recent_losses: Vec::new(),
            recent_q: 0.0,
            last_rates: None,
        }
    }

    pub(super) fn after_update(&mut self, loss: &Losses) {
        self.recent_losses.push(loss.critic);
        self.recent_q += loss.q_mean as f64;
    }

    /// Whether the job's progress at `env_steps` has passed a point that should be written.
    /// Points passed while the rolling episode window holds no episode (at the start and after
    /// a resume, until the first episode ends) are skipped, not written with success 0: nothing
    /// was measured there. The losses keep accumulating into the next written point.
    fn due(&mut self, env_steps: u64, window_episodes: usize) -> bool {
        if env_steps < self.next_point {
            return false;
        }
        if window_episodes == 0 {
            while env_steps >= self.next_point {
                self.next_point += self.every;
            }
            return false;
        }
        true
    }

    /// Adds the points the job's progress has passed (none most of the time).
    pub(super) fn record(
        &mut self,
        job: &ActiveJob,
        last_loss: &Losses,
        version: sf_job::PolicyVersion,
        st: &mut TrainState,
        tb: &mut Option<EventWriter>,
    ) {
        let progress = job.progress();
        let p = progress.learning;
        if !self.due(p.env_steps, job.window_episodes()) {
            return;
        }
        let n = self.recent_losses.len().max(1);
        let (mean, q) = (
            self.recent_losses.iter().map(|&l| l as f64).sum::<f64>() / n as f64,
            self.recent_q / n as f64,
        );
        self.recent_losses.sort_by(f32::total_cmp);
        let median = self.recent_losses.get(self.recent_losses.len() / 2).copied().unwrap_or(0.0);
        let ends = job.ends();
        self.recent_losses.clear();
        self.recent_q = 0.0;
        while p.env_steps >= self.next_point {
            st.curve.push(CurvePoint {
                learning: sf_job::Learning {
                    env_steps: self.next_point.min(p.env_steps),
                    critic_loss: last_loss.critic,
                    actor_loss: last_loss.actor,
                    alpha: last_loss.alpha,
                    ..p
                },
                entropy: last_loss.entropy,
                ends,
                critic_loss_mean: mean as f32,
                critic_loss_median: median,
                q_mean: q as f32,
            });
            self.next_point += self.every;
        }
        let Some(w) = tb.as_mut() else { return };
        let (updates_per_s, transitions_per_s) = match self.last_rates {
            Some((t, u, e)) if p.wall_s > t => {
                ((p.updates - u) as f64 / (p.wall_s - t), (p.env_steps - e) as f64 / (p.wall_s - t))
            }
            _ => (f64::NAN, f64::NAN),
        };
        self.last_rates = Some((p.wall_s, p.updates, p.env_steps));
        let lag = job.take_mean_lag().unwrap_or(f64::NAN);
        let scalars = [
            ("rollout/success", p.scores.success as f64),
            ("rollout/safety", p.scores.safety as f64),
            ("rollout/speed", p.scores.speed as f64),
            ("ends/collision", ends.collision as f64),
            ("ends/off_road", ends.off_road as f64),
            ("ends/off_route", ends.off_route as f64),
            ("ends/wrong_lane", ends.wrong_lane as f64),
            ("ends/timeout", ends.timeout as f64),
            ("loss/critic", last_loss.critic as f64),
            ("loss/critic_mean", mean),
            ("loss/actor", last_loss.actor as f64),
            ("sac/alpha", last_loss.alpha as f64),
            ("sac/entropy", last_loss.entropy as f64),
            ("sac/q_mean", q),
            ("rate/updates_per_s", updates_per_s),
            ("rate/transitions_per_s", transitions_per_s),
            ("policy/lag_versions", lag),
            ("policy/version", version.get() as f64),
            ("policy/dropped_stale", progress.dropped_stale as f64),
        ];
        if let Err(e) = w.scalars(p.env_steps, &scalars) {
            tracing::warn!(job_id = job.id.get(), error = %e, "writing TensorBoard events; no more for this run");
            *tb = None;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::CurveRecorder;

    /// Until an episode ends (at the start, and after a resume) the rolling window is empty:
    /// the points passed meanwhile are skipped (they used to be written with success 0), later
    /// ones keep their places on the grid of `every` transitions.
    #[test]
    fn curve_points_wait_for_an_episode_in_the_window() {
        let mut c = CurveRecorder::new(100, 1_000);
        assert_eq!(c.next_point, 1_100);
        assert!(!c.due(1_050, 0), "not yet at a point");
        assert!(!c.due(1_250, 0), "points passed with an empty window are skipped");
        assert_eq!(c.next_point, 1_300, "1,100 and 1,200 skipped, the grid kept");
        assert!(!c.due(1_299, 4));
        assert!(c.due(1_300, 4), "a point with episodes in the window is written");
    }
}
