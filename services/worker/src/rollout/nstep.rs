//! n-step returns on the worker: each agent's latest steps, summed before they are sent.
//!
//! Owns: [`NStep`], one window per observation row of every simulator. A step enters its row's
//! window; the window's oldest step leaves as one transition once it spans `n` steps, and
//! every step in the window leaves when the agent's episode ends (by any end, a cut included)
//! or when the acting policy changes ([`NStep::flush`]), each spanning the steps it saw. A
//! transition's reward is `sum_k gamma^k r_(t+k)` over its span, its next observation the one
//! after its last step, and it is terminal when that step ended the episode by a failure or
//! the destination (the learner then bootstraps with `gamma^steps`, or not at all). With
//! `n = 1` every step leaves at once, unchanged. Must not: batch or send (the writer does),
//! or decide who acts.

use std::collections::VecDeque;

use sf_job::Transition;

struct Pending {
    obs: Vec<f32>,
    action: Vec<f32>,
    /// IDM's action in `obs`'s state, if the job records it (empty otherwise).
    oracle: Vec<f32>,
    /// Discounted reward summed so far.
    reward: f32,
    steps: u8,
}

#[derive(Default)]
struct Window {
    pending: VecDeque<Pending>,
    /// The observation after the window's latest step (what a flush bootstraps from).
    next_obs: Vec<f32>,
    map_id: u32,
}

/// Per-row windows of the last `n` steps (see the module header).
pub struct NStep {
    n: u8,
    gamma: f32,
    /// `windows[k][r]`: row `r` of simulator `k`.
    windows: Vec<Vec<Window>>,
}

impl NStep {
    /// `n >= 1` steps per transition, discounted by `gamma`.
    pub fn new(n: u8, gamma: f32) -> Self {
        Self { n: n.max(1), gamma, windows: Vec::new() }
    }

    /// One decision step `s` of row `r` of simulator `k` (`ended`: the agent's episode ended
    /// on it, by any end, a cut included); what leaves goes to `out`.
    pub fn step(
        &mut self,
        k: usize,
        r: usize,
        s: Transition<'_>,
        ended: bool,
        out: &mut impl FnMut(Transition<'_>),
    ) {
        if self.n == 1 {
            out(Transition { steps: 1, ..s });
            return;
        }
        if self.windows.len() <= k {
            self.windows.resize_with(k + 1, Vec::new);
        }
        let rows = &mut self.windows[k];
        if rows.len() <= r {
            rows.resize_with(r + 1, Window::default);
        }
        let w = &mut rows[r];
        w.pending.push_back(Pending {
            obs: s.obs.to_vec(),
            action: s.action.to_vec(),
            oracle: s.oracle.to_vec(),
            reward: 0.0,
            steps: 0,
        });
        for p in &mut w.pending {
            p.reward += self.gamma.powi(i32::from(p.steps)) * s.reward;
            p.steps += 1;
        }
        w.map_id = s.map_id;
        if ended {
            for p in w.pending.drain(..) {
                out(Transition {
                    obs: &p.obs,
                    action: &p.action,
                    oracle: &p.oracle,
                    reward: p.reward,
                    next_obs: s.next_obs,
                    terminal: s.terminal,
                    map_id: s.map_id,
                    steps: p.steps,
                });
            }
            return;
        }
        if w.pending.front().is_some_and(|p| p.steps >= self.n) {
            if let Some(p) = w.pending.pop_front() {
                out(Transition {
                    obs: &p.obs,
                    action: &p.action,
                    oracle: &p.oracle,
                    reward: p.reward,
                    next_obs: s.next_obs,
                    terminal: false,
                    map_id: s.map_id,
                    steps: p.steps,
                });
            }
        }
        if !w.pending.is_empty() {
            w.next_obs.clear();
            w.next_obs.extend_from_slice(s.next_obs);
        }
    }

    /// Every pending step leaves, spanning what it has seen and bootstrapping from its row's
    /// latest observation (the acting policy changes: a batch holds one policy's actions).
    pub fn flush(&mut self, out: &mut impl FnMut(Transition<'_>)) {
        for w in self.windows.iter_mut().flatten() {
            for p in w.pending.drain(..) {
                out(Transition {
                    obs: &p.obs,
                    action: &p.action,
                    oracle: &p.oracle,
                    reward: p.reward,
                    next_obs: &w.next_obs,
                    terminal: false,
                    map_id: w.map_id,
                    steps: p.steps,
                });
            }
        }
    }

    /// Steps waiting in windows.
    #[cfg(test)]
    pub fn pending(&self) -> usize {
        self.windows.iter().flatten().map(|w| w.pending.len()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq)]
    struct Out {
        obs: f32,
        reward: f32,
        next_obs: f32,
        terminal: bool,
        steps: u8,
    }

    fn run(n: u8, steps: &[(f32, f32, bool, bool)], flush_after: Option<usize>) -> Vec<Out> {
        let mut ns = NStep::new(n, 0.5);
        let mut got = Vec::new();
        let mut out = |s: Transition<'_>| {
            // A step's oracle label leaves with the transition that starts at it.
            assert_eq!(s.oracle, &[10.0 * s.obs[0]]);
            got.push(Out {
                obs: s.obs[0],
                reward: s.reward,
                next_obs: s.next_obs[0],
                terminal: s.terminal,
                steps: s.steps,
            })
        };
        for (t, &(reward, next, ended, terminal)) in steps.iter().enumerate() {
            let (obs, oracle) = ([t as f32], [10.0 * t as f32]);
            ns.step(
                1,
                2,
                Transition {
                    obs: &obs,
                    action: &[0.0],
                    reward,
                    next_obs: &[next],
                    terminal,
                    steps: 1,
                    map_id: 0,
                    oracle: &oracle,
                },
                ended,
                &mut out,
            );
            if flush_after == Some(t) {
                ns.flush(&mut out);
            }
        }
        assert_eq!(ns.pending(), 0, "every step left");
        got
    }

    /// Rewards 1, 2, 4, 8 with gamma 0.5: a 3-step window sums 1 + 1 + 1 = 3 from step 0 and
    /// 2 + 2 + 2 = 6 from step 1; the episode's end (a collision) flushes the rest with the
    /// spans they saw, terminal.
    #[test]
    fn windows_sum_discounted_rewards_and_end_with_the_episode() {
        let got = run(
            3,
            &[
                (1.0, 1.0, false, false),
                (2.0, 2.0, false, false),
                (4.0, 3.0, false, false),
                (8.0, 4.0, true, true),
            ],
            None,
        );
        assert_eq!(
            got,
            vec![
                Out { obs: 0.0, reward: 3.0, next_obs: 3.0, terminal: false, steps: 3 },
                Out { obs: 1.0, reward: 2.0 + 2.0 + 2.0, next_obs: 4.0, terminal: true, steps: 3 },
                Out { obs: 2.0, reward: 4.0 + 4.0, next_obs: 4.0, terminal: true, steps: 2 },
                Out { obs: 3.0, reward: 8.0, next_obs: 4.0, terminal: true, steps: 1 },
            ]
        );
    }

    /// A timeout ends the episode without being terminal: the rest leave bootstrapping from the
    /// final observation; a policy change flushes the window the same way.
    #[test]
    fn cuts_and_policy_changes_leave_short_non_terminal_spans() {
        let got = run(4, &[(1.0, 1.0, false, false), (1.0, 2.0, true, false)], None);
        assert_eq!(
            got,
            vec![
                Out { obs: 0.0, reward: 1.5, next_obs: 2.0, terminal: false, steps: 2 },
                Out { obs: 1.0, reward: 1.0, next_obs: 2.0, terminal: false, steps: 1 }
            ]
        );
        let got = run(
            4,
            &[(1.0, 1.0, false, false), (1.0, 2.0, false, false), (1.0, 3.0, true, true)],
            Some(0),
        );
        assert_eq!(
            got,
            vec![
                Out { obs: 0.0, reward: 1.0, next_obs: 1.0, terminal: false, steps: 1 },
                Out { obs: 1.0, reward: 1.5, next_obs: 3.0, terminal: true, steps: 2 },
                Out { obs: 2.0, reward: 1.0, next_obs: 3.0, terminal: true, steps: 1 },
            ]
        );
    }

    /// n = 1 passes every step through unchanged, as before n-step returns.
    #[test]
    fn one_step_passes_through() {
        let got = run(1, &[(1.0, 1.0, false, false), (2.0, 2.0, true, true)], Some(0));
        assert_eq!(
            got,
            vec![
                Out { obs: 0.0, reward: 1.0, next_obs: 1.0, terminal: false, steps: 1 },
                Out { obs: 1.0, reward: 2.0, next_obs: 2.0, terminal: true, steps: 1 }
            ]
        );
    }
}
