//! One point of a training curve: what a job's `curve.csv` holds.
//!
//! Owns: [`CurvePoint`] (the job's `sf_job::Learning` at that point, i.e. counters, rolling
//! success, safety and speed and the last update's losses, as its progress reports them; plus
//! how episodes ended, the entropy and the critic's loss statistics since the previous point)
//! and its CSV row.
//! Must not: compute the rolling statistics (the learner's trainer does) or do IO.

use serde::{Deserialize, Serialize};

/// One point of a learning curve.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CurvePoint {
    /// Counters, rolling scores and the last update's losses, as the job's progress has them.
    #[serde(flatten)]
    pub learning: sf_job::Learning,
    pub entropy: f32,
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
        let (l, e) = (&self.learning, &self.ends);
        format!(
            "{},{},{},{},{},{},{},{},{},{},{:.1},{},{},{},{},{},{},{},{}",
            l.env_steps,
            l.updates,
            l.episodes,
            l.scores.success,
            l.scores.safety,
            l.scores.speed,
            l.critic_loss,
            l.actor_loss,
            l.alpha,
            self.entropy,
            l.wall_s,
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

#[cfg(test)]
mod tests {
    use super::*;

    /// `state.json` curves written before the fold (flat fields) still read; the CSV row keeps
    /// its column order.
    #[test]
    fn old_points_read_and_rows_keep_their_order() {
        let old = r#"{"env_steps":2000,"updates":400,"episodes":50,"success":0.75,"safety":0.5,"speed":0.25,"critic_loss":3.0,"actor_loss":-1.0,"alpha":0.1,"entropy":0.5,"wall_s":20.0,"ends":{"collision":0.25,"off_road":0.0,"off_route":0.0,"wrong_lane":0.0,"timeout":0.0},"critic_loss_mean":2.5,"critic_loss_median":2.0,"q_mean":-4.0}"#;
        let p: CurvePoint = serde_json::from_str(old).expect("an old curve point");
        assert_eq!(
            (p.learning.env_steps, p.learning.updates, p.learning.episodes),
            (2000, 400, 50)
        );
        assert_eq!(p.learning.scores.success, 0.75);
        assert_eq!(
            p.csv_row(),
            "2000,400,50,0.75,0.5,0.25,3,-1,0.1,0.5,20.0,0.25,0,0,0,0,2.5,2,-4"
        );
        assert_eq!(p.csv_row().split(',').count(), CurvePoint::CSV_HEADER.split(',').count());
    }
}
