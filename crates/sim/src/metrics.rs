//! Episode metrics: Success, Safety, Speed and the failure breakdown.
//!
//! Owns: [`Scores`] (the paper's three metrics, embedded wherever they travel together) and
//! [`EpisodeMetrics`] (one episode, averaged over the agents it scores). Must not:
//! compute confidence intervals or tests (that is the eval crate). Flow evaluation scores every agent; ego evaluation only
//! the learner (agent 0).

use serde::{Deserialize, Serialize};

use crate::env::{AgentOutcome, Role, Termination};

/// The paper's three metrics: Success (reached the destination), Safety (no failure
/// termination) and Speed (mean speed over the speed limit), each a fraction in [0, 1] or a mean
/// of such fractions. Serialised flat, so records that embed it keep their field names.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Scores {
    pub success: f32,
    pub safety: f32,
    pub speed: f32,
}

impl Scores {
    /// The mean of each metric over `scores` (zeros for none), summed in `f32` in order.
    pub fn mean(scores: impl IntoIterator<Item = Scores>) -> Scores {
        let (mut sum, mut n) = (Scores::default(), 0u32);
        for s in scores {
            sum.success += s.success;
            sum.safety += s.safety;
            sum.speed += s.speed;
            n += 1;
        }
        if n == 0 {
            return sum;
        }
        let n = n as f32;
        Scores { success: sum.success / n, safety: sum.safety / n, speed: sum.speed / n }
    }
}

/// One episode's scores, each a mean over the scored agents, in [0, 1].
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EpisodeMetrics {
    pub agents: u32,
    #[serde(flatten)]
    pub scores: Scores,
    pub collision: f32,
    pub off_road: f32,
    pub off_route: f32,
    pub wrong_lane: f32,
    pub timeout: f32,
    pub destination: f32,
    /// The share of scored agents that left their route's lane at some point
    /// ([`AgentOutcome::left_lane`]).
    #[serde(default)]
    pub lane_change: f32,
    /// The share of scored agents that timed out with standing vehicles closing the road ahead
    /// ([`AgentOutcome::road_closed`]): blocked, not merely slow. Judged in stored episodes
    /// (evaluation) only; 0 in training's metrics.
    #[serde(default)]
    pub road_closed: f32,
}

impl EpisodeMetrics {
    /// Scores an episode; `learners_only` keeps agents with the learner role (ego evaluation).
    pub fn from_outcomes(
        outcomes: impl IntoIterator<Item = AgentOutcome>,
        learners_only: bool,
    ) -> Self {
        let mut m = Self::default();
        for o in outcomes {
            if learners_only && o.role != Role::Learner {
                continue;
            }
            m.agents += 1;
            m.scores.success += o.success as u32 as f32;
            m.scores.safety += !o.termination.is_some_and(Termination::is_failure) as u32 as f32;
            m.scores.speed += o.speed_ratio;
            m.lane_change += o.left_lane as u32 as f32;
            m.road_closed += o.road_closed as u32 as f32;
            match o.termination {
                Some(Termination::Collision) => m.collision += 1.0,
                Some(Termination::OffRoad) => m.off_road += 1.0,
                Some(Termination::OffRoute) => m.off_route += 1.0,
                Some(Termination::WrongLane) => m.wrong_lane += 1.0,
                Some(Termination::Timeout) => m.timeout += 1.0,
                Some(Termination::Destination) => m.destination += 1.0,
                None => {}
            }
        }
        if m.agents > 0 {
            let n = m.agents as f32;
            for v in [
                &mut m.scores.success,
                &mut m.scores.safety,
                &mut m.scores.speed,
                &mut m.collision,
                &mut m.off_road,
                &mut m.off_route,
                &mut m.wrong_lane,
                &mut m.timeout,
                &mut m.destination,
                &mut m.lane_change,
                &mut m.road_closed,
            ] {
                *v /= n;
            }
        }
        m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn o(role: Role, success: bool, t: Termination, speed: f32) -> AgentOutcome {
        AgentOutcome {
            role,
            success,
            termination: Some(t),
            speed_ratio: speed,
            steps: 10,
            left_lane: false,
            road_closed: t == Termination::Timeout,
        }
    }

    #[test]
    fn episode_means_and_learner_filter() {
        let outs = [
            o(Role::Learner, true, Termination::Destination, 0.8),
            o(Role::Background, false, Termination::Collision, 0.2),
        ];
        let m = EpisodeMetrics::from_outcomes(outs, false);
        assert_eq!(m.agents, 2);
        assert!(
            (m.scores.success - 0.5).abs() < 1e-6
                && (m.scores.safety - 0.5).abs() < 1e-6
                && (m.collision - 0.5).abs() < 1e-6
        );
        assert!((m.scores.speed - 0.5).abs() < 1e-6);
        let e = EpisodeMetrics::from_outcomes(outs, true);
        assert_eq!((e.agents, e.scores.success, e.scores.safety), (1, 1.0, 1.0));
    }

    #[test]
    fn road_closed_is_the_share_of_scored_agents_blocked_at_their_timeout() {
        let outs = [
            o(Role::Learner, false, Termination::Timeout, 0.1),
            o(Role::Background, false, Termination::Timeout, 0.1),
            o(Role::Background, true, Termination::Destination, 0.9),
            o(Role::Background, false, Termination::Collision, 0.3),
        ];
        assert_eq!(EpisodeMetrics::from_outcomes(outs, false).road_closed, 0.5);
        assert_eq!(EpisodeMetrics::from_outcomes(outs, true).road_closed, 1.0);
        assert_eq!(EpisodeMetrics::from_outcomes(outs[2..].to_vec(), false).road_closed, 0.0);
    }

    #[test]
    fn scores_average_field_by_field_and_none_average_to_zero() {
        let a = Scores { success: 1.0, safety: 1.0, speed: 0.5 };
        let b = Scores { success: 0.0, safety: 0.5, speed: 0.25 };
        assert_eq!(Scores::mean([a, b]), Scores { success: 0.5, safety: 0.75, speed: 0.375 });
        assert_eq!(Scores::mean([]), Scores::default());
    }
}
