//! One point of a training curve: what a job's `curve.csv` holds.
//!
//! Owns: [`CurvePoint`] (rolling success, safety, speed and how episodes ended, the last
//! update's losses, the critic's loss statistics since the previous point) and its CSV row.
//! Must not: compute the rolling statistics (the learner's trainer does) or do IO.

use serde::{Deserialize, Serialize};

/// One point of a learning curve.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CurvePoint {
    pub env_steps: u64,
    pub updates: u64,
    pub episodes: u64,
    #[serde(flatten)]
    pub scores: sf_sim::Scores,
    /// The last update's single-batch losses.
    pub critic_loss: f32,
    pub actor_loss: f32,
    pub alpha: f32,
    pub entropy: f32,
    pub wall_s: f64,
    /// Rolling fractions of how episodes ended (same window as `success`).
    pub ends: sf_job::Ends,
    /// Mean critic loss over the updates since the previous point, and its median.
    pub critic_loss_mean: f32,
    pub critic_loss_median: f32,
    pub q_mean: f32,
}

impl CurvePoint {
    /// Header of the curve CSV files (`curve.csv`).
    pub const CSV_HEADER: &'static str =
        "env_steps,updates,episodes,success,safety,speed,critic_loss,actor_loss,alpha,entropy,wall_s,collision,off_road,off_route,wrong_lane,timeout,critic_loss_mean,critic_loss_median,q_mean";

    /// One CSV row (no newline) in [`CurvePoint::CSV_HEADER`] order.
    pub fn csv_row(&self) -> String {
        let e = &self.ends;
        format!(
            "{},{},{},{},{},{},{},{},{},{},{:.1},{},{},{},{},{},{},{},{}",
            self.env_steps,
            self.updates,
            self.episodes,
            self.scores.success,
            self.scores.safety,
            self.scores.speed,
            self.critic_loss,
            self.actor_loss,
            self.alpha,
            self.entropy,
            self.wall_s,
            e.collision,
            e.off_road,
            e.off_route,
            e.wrong_lane,
            e.timeout,
            self.critic_loss_mean,
            self.critic_loss_median,
            self.q_mean
        )
    }
}
