//! The rollout loop's adder: what leaves the rollout thread, and when.
//!
//! Owns: [`TransitionWriter`] (batching of the job's transitions and finished episodes, version
//! stamping, sending through the bounded channel), each batch after a slot of the
//! [`super::window::Window`] of batches in flight is taken. Steps pass through the n-step windows (`super::nstep`) on
//! their way in. Invariant: every batch holds transitions of one acting policy version (or the
//! warm-up) and is stamped with it (a version change flushes the windows first); a batch is
//! sent only after a window slot is taken. Must not: do network IO (the session streams what the
//! channel carries), or decide who acts (the environment loop does).

use std::ops::ControlFlow;
use std::sync::{Arc, Mutex};

use anyhow::bail;
use sf_job::{ActedBy, Ends, EpisodeResult, JobConfig, Transition, TransitionBatch};
use sf_proto::pb;
use sf_rollout::setup;
use sf_sim::vec_env::VecEnv;
use tokio::sync::mpsc;

use super::nstep::NStep;
use super::window::Window;
use super::{Control, STREAM_CLOSED};
use crate::metrics::WorkerMetrics;

/// The rollout loop's adder: packs the job's transitions and finished episodes into batches,
/// one acting policy version per batch, and sends each when it is full (or when the version
/// changes), after taking a window slot. `Break` from a method: `stop` was set while waiting for a
/// window slot.
pub struct TransitionWriter {
    batch: TransitionBatch,
    /// Each agent's steps not yet summed into a transition (`sac.n_step`).
    nstep: NStep,
    /// Version of the policy that acted for the batch's transitions (`None` before the first step).
    acted_by: Option<ActedBy>,
    /// Transitions that make a batch full (`worker.batch_transitions`).
    full_at: usize,
    control: Arc<Mutex<Control>>,
    window: Arc<Window>,
    tx: mpsc::Sender<pb::TransitionBatch>,
    metrics: WorkerMetrics,
}

impl TransitionWriter {
    /// Fills `batch` (empty, with the job's shapes) up to `full_at` transitions.
    pub(super) fn new(
        batch: TransitionBatch,
        nstep: NStep,
        full_at: usize,
        control: Arc<Mutex<Control>>,
        window: Arc<Window>,
        tx: mpsc::Sender<pb::TransitionBatch>,
        metrics: WorkerMetrics,
    ) -> Self {
        Self { batch, nstep, acted_by: None, full_at, control, window, tx, metrics }
    }

    /// The coming step is acted by `acted_by`: the previous actor's pending n-step windows are
    /// flushed into the batch, and a batch holding another actor's transitions is sent first.
    pub(super) fn stamp(&mut self, acted_by: ActedBy) -> anyhow::Result<ControlFlow<()>> {
        if self.acted_by.is_some_and(|a| a != acted_by) {
            let batch = &mut self.batch;
            self.nstep.flush(&mut |t| batch.push_transition(t));
        }
        if let Some(held) = self.acted_by.filter(|&a| a != acted_by && self.batch.count > 0) {
            if self.send(held)?.is_break() {
                return Ok(ControlFlow::Break(()));
            }
        }
        self.acted_by = Some(acted_by);
        Ok(ControlFlow::Continue(()))
    }

    /// One step of every simulator: its simulated steps, the `rows`' transitions (`before`: each
    /// simulator's observations before the step; `actions`, and `oracle` when the job records
    /// IDM's labels: `act_dim` floats per row) and the episodes that finished.
    pub(super) fn add(
        &mut self,
        venvs: &mut [VecEnv],
        before: &[Vec<f32>],
        rows: &[Vec<usize>],
        actions: &[Vec<f32>],
        oracle: Option<&[Vec<f32>]>,
        job: &JobConfig,
    ) {
        let (len, act_dim) = (self.batch.obs_len, self.batch.action_dim);
        for (k, v) in venvs.iter_mut().enumerate() {
            self.batch.sim_steps += v.n_envs() as u64;
            self.metrics.env_steps.inc_by(v.n_envs() as u64);
            for (j, &r) in rows[k].iter().enumerate() {
                let st = v.row_steps()[r];
                if !st.stepped {
                    continue;
                }
                let step = Transition {
                    obs: &before[k][r * len..(r + 1) * len],
                    action: &actions[k][j * act_dim..(j + 1) * act_dim],
                    reward: setup::reward(job, &st.rewards),
                    next_obs: v.next_observation(r),
                    terminal: st.terminal(),
                    steps: 1,
                    map_id: k as u32,
                    oracle: oracle.map_or(&[][..], |o| &o[k][j * act_dim..(j + 1) * act_dim]),
                };
                let batch = &mut self.batch;
                self.nstep.step(k, r, step, st.ended.is_some() || st.truncated, &mut |t| {
                    batch.push_transition(t)
                });
            }
            for m in v.take_finished() {
                self.metrics.episodes.inc();
                self.batch.episodes.push(EpisodeResult {
                    scenario_index: k as u32,
                    scores: m.scores,
                    ends: Ends {
                        collision: m.collision,
                        off_road: m.off_road,
                        off_route: m.off_route,
                        wrong_lane: m.wrong_lane,
                        timeout: m.timeout,
                    },
                });
            }
        }
    }

    /// Sends the batch if it holds `worker.batch_transitions` transitions.
    pub(super) fn send_if_full(&mut self) -> anyhow::Result<ControlFlow<()>> {
        if self.batch.count >= self.full_at {
            return self.send(self.acted_by.unwrap_or_default());
        }
        Ok(ControlFlow::Continue(()))
    }

    /// Takes a window slot, stamps the batch with `acted_by` and sends it.
    fn send(&mut self, acted_by: ActedBy) -> anyhow::Result<ControlFlow<()>> {
        if !self.window.take(&self.control) {
            return Ok(ControlFlow::Break(()));
        }
        self.batch.acted_by = acted_by;
        let msg = sf_proto::batch_to_wire(&self.batch);
        self.metrics.transitions_sent.inc_by(self.batch.count as u64);
        self.metrics.batches_sent.inc();
        self.batch.clear();
        if self.tx.blocking_send(msg).is_err() {
            bail!(STREAM_CLOSED);
        }
        Ok(ControlFlow::Continue(()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use prometheus_client::registry::Registry;
    use sf_service::sync::lock;

    fn writer(
        credits: u32,
        full_at: usize,
    ) -> (TransitionWriter, mpsc::Receiver<pb::TransitionBatch>, Arc<Mutex<Control>>) {
        let control = Arc::new(Mutex::new(Control { warmup: false, policy: None, stop: false }));
        let (tx, rx) = mpsc::channel(8);
        let metrics = WorkerMetrics::register(&mut Registry::default());
        // A fixed window of `credits` slots (none free for 0: its one slot is taken here).
        let window = Arc::new(Window::new(credits.max(1), false));
        if credits == 0 {
            assert!(window.take(&control));
        }
        let w = TransitionWriter::new(
            TransitionBatch::new(7.into(), 3.into(), 2, 1),
            NStep::new(1, 0.9),
            full_at,
            Arc::clone(&control),
            window,
            tx,
            metrics,
        );
        (w, rx, control)
    }

    fn v(version: u64) -> ActedBy {
        ActedBy::Policy(std::num::NonZeroU64::new(version).expect("versions start at 1"))
    }

    fn push(w: &mut TransitionWriter) {
        w.batch.push(&[0.0, 1.0], &[0.5], 1.0, &[1.0, 2.0], false, 0);
    }

    #[test]
    fn a_batch_holds_one_version_and_is_stamped_with_it() -> anyhow::Result<()> {
        let (mut w, mut rx, _control) = writer(8, 100);
        assert!(w.stamp(ActedBy::Warmup)?.is_continue());
        push(&mut w);
        push(&mut w);
        assert!(w.stamp(ActedBy::Warmup)?.is_continue());
        assert!(rx.try_recv().is_err(), "same version: nothing sent");
        assert!(w.stamp(v(5))?.is_continue());
        let sent = rx.try_recv()?;
        assert_eq!((sent.policy_version, sent.count, sent.job_id, sent.worker_id), (0, 2, 7, 3));
        push(&mut w);
        assert!(w.stamp(v(6))?.is_continue());
        assert_eq!(rx.try_recv()?.policy_version, 5);
        // An empty batch is not sent when the version changes.
        assert!(w.stamp(v(7))?.is_continue());
        assert!(rx.try_recv().is_err());
        Ok(())
    }

    /// With n-step windows, a version change flushes the previous actor's pending steps into
    /// its own batch before that batch is sent.
    #[test]
    fn a_policy_change_flushes_pending_n_step_windows_into_the_old_batch() -> anyhow::Result<()> {
        let (mut w, mut rx, _control) = writer(8, 100);
        w.nstep = NStep::new(3, 0.5);
        assert!(w.stamp(v(4))?.is_continue());
        let batch = &mut w.batch;
        for reward in [1.0, 2.0] {
            let step = Transition {
                obs: &[0.0, 1.0],
                action: &[0.5],
                reward,
                next_obs: &[1.0, 2.0],
                terminal: false,
                steps: 1,
                map_id: 0,
                oracle: &[],
            };
            w.nstep.step(0, 0, step, false, &mut |t| batch.push_transition(t));
        }
        assert_eq!((w.batch.count, w.nstep.pending()), (0, 2), "the window holds both steps");
        assert!(w.stamp(v(5))?.is_continue());
        let sent = rx.try_recv()?;
        assert_eq!(
            (sent.policy_version, sent.count, sent.steps.as_slice(), sent.rewards.as_slice()),
            (4, 2, &[2u8, 1][..], &[2.0f32, 2.0][..])
        );
        assert_eq!(w.nstep.pending(), 0);
        Ok(())
    }

    #[test]
    fn a_full_batch_is_sent_counted_and_cleared() -> anyhow::Result<()> {
        let (mut w, mut rx, _control) = writer(8, 2);
        assert!(w.stamp(v(4))?.is_continue());
        push(&mut w);
        assert!(w.send_if_full()?.is_continue());
        assert!(rx.try_recv().is_err());
        push(&mut w);
        assert!(w.send_if_full()?.is_continue());
        let sent = rx.try_recv()?;
        assert_eq!((sent.policy_version, sent.count), (4, 2));
        assert_eq!(
            (w.metrics.transitions_sent.get(), w.metrics.batches_sent.get(), w.batch.count),
            (2, 1, 0)
        );
        Ok(())
    }

    #[test]
    fn with_the_window_full_a_stop_breaks_before_sending() -> anyhow::Result<()> {
        let (mut w, mut rx, control) = writer(0, 1);
        lock(&control).stop = true;
        assert!(w.stamp(ActedBy::Warmup)?.is_continue());
        push(&mut w);
        assert!(w.send_if_full()?.is_break());
        assert!(rx.try_recv().is_err());
        assert_eq!(w.metrics.batches_sent.get(), 0);
        Ok(())
    }

    #[test]
    fn a_closed_channel_is_the_stream_closing() -> anyhow::Result<()> {
        let (mut w, rx, _control) = writer(1, 1);
        drop(rx);
        assert!(w.stamp(ActedBy::Warmup)?.is_continue());
        push(&mut w);
        let e = w.send_if_full().err().map(|e| e.to_string());
        assert_eq!(e.as_deref(), Some(STREAM_CLOSED));
        Ok(())
    }
}
