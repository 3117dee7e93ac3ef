//! Read-only views of a [`Sac`]'s critic and actor on rows of observations: what probes and
//! diagnostics ask of a training state without training it.
//!
//! Owns: `min(Q1, Q2)(s, a)` on rows ([`Sac::q_min`], [`Sac::q_min_each`] for several action
//! sets), its gradient with respect to the action
//! ([`Sac::q_action_gradient`]) and the actor's mean action and spread ([`Sac::action_dist`]). Must not:
//! change weights, optimizer state or the noise RNG (a probe that reads a state between updates
//! leaves the run it reads exactly as it was).

use burn::module::Module;
use burn::tensor::{Tensor, TensorData};

use crate::sac::Sac;

/// Rows handled per forward pass.
const CHUNK: usize = 256;

impl Sac {
    /// `min(Q1, Q2)(s, a)` of the online critic for rows of observations and actions, in
    /// chunks on the plain device (the critic probe, diagnostics).
    pub fn q_min(&self, obs: &[f32], actions: &[f32], map_ids: &[u32]) -> Vec<f32> {
        self.q_min_each(obs, &[actions], map_ids).pop().unwrap_or_default()
    }

    /// [`Sac::q_min`] for several sets of actions on the same rows (each `[rows x
    /// action_dim]`), one result per set: the critic's encoder runs once per chunk of rows,
    /// only its heads once per set.
    pub fn q_min_each(
        &self,
        obs: &[f32],
        action_sets: &[&[f32]],
        map_ids: &[u32],
    ) -> Vec<Vec<f32>> {
        let (len, a_dim) = (self.spec.len, self.net.action_dim);
        let critic = self.critic.valid();
        let table = self.seg_plain.as_ref().map(|s| critic.enc.segment_table(s));
        let mut out: Vec<Vec<f32>> =
            action_sets.iter().map(|_| Vec::with_capacity(map_ids.len())).collect();
        for start in (0..map_ids.len()).step_by(CHUNK) {
            let end = (start + CHUNK).min(map_ids.len());
            let ob = self.batch_on(&obs[start * len..end * len], &map_ids[start..end], &self.plain);
            let f = critic.enc.forward(&ob, table.as_ref());
            for (actions, q) in action_sets.iter().zip(&mut out) {
                let a = Tensor::<2>::from_data(
                    TensorData::new(
                        actions[start * a_dim..end * a_dim].to_vec(),
                        [end - start, a_dim],
                    ),
                    &self.plain,
                );
                let (q1, q2) = critic.heads(f.clone(), a);
                q.extend(
                    q1.min_pair(q2).into_data().try_to_vec::<f32>().expect("Q values are f32"),
                );
            }
        }
        out
    }

    /// `d min(Q1, Q2)(s, a) / d a` of the online critic, row by row (`[rows x action_dim]`,
    /// row-major): the direction SAC's actor loss moves an action in, before the entropy
    /// term. Computed on a copy of the critic; the state is not changed.
    pub fn q_action_gradient(&self, obs: &[f32], actions: &[f32], map_ids: &[u32]) -> Vec<f32> {
        let (len, a_dim) = (self.spec.len, self.net.action_dim);
        let critic = self.critic.clone();
        let mut out = Vec::with_capacity(map_ids.len() * a_dim);
        for start in (0..map_ids.len()).step_by(CHUNK) {
            let end = (start + CHUNK).min(map_ids.len());
            // The table is built per chunk: its graph is consumed by the chunk's backward.
            let table = self.seg_ad.as_ref().map(|s| critic.enc.segment_table(s));
            let ob = self.batch_on(&obs[start * len..end * len], &map_ids[start..end], &self.ad);
            let a = Tensor::<2>::from_data(
                TensorData::new(actions[start * a_dim..end * a_dim].to_vec(), [end - start, a_dim]),
                &self.ad,
            )
            .require_grad();
            let (q1, q2) = critic.forward(&ob, table.as_ref(), a.clone());
            // Rows are independent, so the sum's gradient is each row's own.
            let grads = q1.min_pair(q2).sum().backward();
            let g = a.grad(&grads).expect("the action takes part in Q");
            out.extend(g.into_data().try_to_vec::<f32>().expect("gradients are f32"));
        }
        out
    }

    /// The actor's mean action `tanh(mu(s))` (what validation drives with) and its log-std
    /// before the squash, row by row (`[rows x action_dim]` each); the Polyak-averaged actor's
    /// with `averaged` where the job keeps one, else the actor's.
    pub fn action_dist(
        &self,
        obs: &[f32],
        map_ids: &[u32],
        averaged: bool,
    ) -> (Vec<f32>, Vec<f32>) {
        let len = self.spec.len;
        let actor = match (&self.actor_avg, averaged) {
            (Some(avg), true) => avg.clone(),
            _ => self.actor.valid(),
        };
        let table = self.seg_plain.as_ref().map(|s| actor.enc.segment_table(s));
        let n = map_ids.len() * self.net.action_dim;
        let (mut means, mut log_stds) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for start in (0..map_ids.len()).step_by(CHUNK) {
            let end = (start + CHUNK).min(map_ids.len());
            let ob = self.batch_on(&obs[start * len..end * len], &map_ids[start..end], &self.plain);
            let (m, s) = actor.dist(&ob, table.as_ref());
            means.extend(m.tanh().into_data().try_to_vec::<f32>().expect("actions are f32"));
            log_stds.extend(s.into_data().try_to_vec::<f32>().expect("log-stds are f32"));
        }
        (means, log_stds)
    }
}
