//! A single-process SAC training loop for an ego policy among background traffic.
//!
//! Owns: [`train_ego`], which steps batched simulators with the current policy (uniform random
//! actions during warm-up), pushes every learner transition into the replay buffer, runs
//! updates at a fixed replay ratio and reports a learning curve. It is what the learner's
//! trainer thread and the embedded mode build on. Must not: do IO; callers write curves.

use std::sync::Arc;
use std::time::Instant;

use burn::tensor::{Tensor, TensorData};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use sf_sim::env::Controller;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Map, Mode, SimConfig};

use crate::replay::{Replay, Transition};
use crate::sac::{Losses, Sac};

/// What to train on and for how long.
#[derive(Clone, Debug)]
pub struct EgoRun {
    /// One batch of environments per map; map `k` is map id `k` of the SAC's segment tables.
    pub maps: Vec<Arc<Map>>,
    pub envs_per_map: usize,
    pub vehicles: (u32, u32),
    pub background: Controller,
    /// Learner transitions to collect.
    pub env_steps: u64,
    /// Updates per collected transition.
    pub updates_per_step: f64,
    pub replay_capacity: usize,
    /// A curve point every this many collected transitions.
    pub report_every: u64,
    /// The acting policy is refreshed from the learner after this many updates (policy lag).
    pub policy_refresh_updates: u64,
    /// Finished episodes averaged in each curve point.
    pub window: usize,
    pub seed: u64,
}

/// One point of a learning curve.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CurvePoint {
    pub env_steps: u64,
    pub updates: u64,
    pub episodes: u64,
    pub success: f32,
    pub safety: f32,
    pub speed: f32,
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
            self.success,
            self.safety,
            self.speed,
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

/// Trains `sac` on ego episodes; calls `on_point` for every curve point and returns them all.
pub fn train_ego(sim: &Arc<SimConfig>, sac: &mut Sac, run: &EgoRun, mut on_point: impl FnMut(&CurvePoint)) -> Vec<CurvePoint> {
    let mut venvs: Vec<VecEnv> = run
        .maps
        .iter()
        .enumerate()
        .map(|(k, m)| {
            VecEnv::new(
                Arc::clone(m),
                Arc::clone(sim),
                VecEnvConfig { n_envs: run.envs_per_map, mode: Mode::Ego { background: run.background }, vehicles: run.vehicles, seed: run.seed.wrapping_add(k as u64 * 1000) },
            )
        })
        .collect();
    let spec = sac.spec.clone();
    let a_dim = sac.net.action_dim;
    let mut replay = Replay::new(run.replay_capacity, spec.len, a_dim);
    let mut rng = ChaCha8Rng::seed_from_u64(run.seed ^ 0x5eed);
    let mut curve = Vec::new();
    let mut recent: std::collections::VecDeque<sf_sim::metrics::EpisodeMetrics> = Default::default();
    let mut steps = 0u64;
    let mut episodes = 0u64;
    let mut update_debt = 0.0f64;
    let mut last = Losses::default();
    let mut next_report = run.report_every;
    let start = Instant::now();
    let mut batch = crate::replay::Batch::default();
    let (mut policy, mut table) = sac.policy();
    let mut refreshed_at = sac.updates;
    while steps < run.env_steps {
        if sac.updates >= refreshed_at + run.policy_refresh_updates.max(1) {
            (policy, table) = sac.policy();
            refreshed_at = sac.updates;
        }
        for (k, v) in venvs.iter_mut().enumerate() {
            // Actions for live learner rows.
            let rows: Vec<usize> = (0..v.alive().len()).filter(|&r| v.alive()[r] == 1.0).collect();
            let mut actions = vec![Action::default(); v.alive().len()];
            if steps < sac.cfg.warmup_steps {
                for &r in &rows {
                    actions[r] = Action { ref_speed: rng.random_range(-1.0..1.0), steer: rng.random_range(-1.0..1.0), idm_accel: None };
                }
            } else if !rows.is_empty() {
                let mut obs = Vec::with_capacity(rows.len() * spec.len);
                for &r in &rows {
                    obs.extend_from_slice(&v.observations()[r * spec.len..(r + 1) * spec.len]);
                }
                let ids = vec![k as u32; rows.len()];
                let ob = sac.obs_batch(&obs, &ids);
                let eps: Vec<f32> = (0..rows.len() * a_dim).map(|_| rng.sample(StandardNormal)).collect();
                let eps = Tensor::<2>::from_data(TensorData::new(eps, [rows.len(), a_dim]), &sac.plain);
                let (a, _) = policy.sample(&ob, table.as_ref(), eps);
                let a: Vec<f32> = a.into_data().try_to_vec().expect("actions are f32");
                for (j, &r) in rows.iter().enumerate() {
                    actions[r] = Action { ref_speed: a[j * a_dim], steer: a[j * a_dim + 1], idm_accel: None };
                }
            }
            let before = v.observations().to_vec();
            v.step(&actions);
            for &r in &rows {
                let st = v.row_steps()[r];
                if !st.stepped {
                    continue;
                }
                let act = [actions[r].ref_speed, actions[r].steer];
                replay
                    .push(Transition {
                        obs: &before[r * spec.len..(r + 1) * spec.len],
                        action: &act,
                        reward: st.rewards.individual,
                        next_obs: v.next_observation(r),
                        terminal: st.terminal(),
                        map_id: k as u32,
                    })
                    .expect("simulator observations are finite and well-shaped");
                steps += 1;
                if steps >= sac.cfg.warmup_steps {
                    update_debt += run.updates_per_step;
                }
            }
            for m in v.take_finished() {
                episodes += 1;
                recent.push_back(m);
                if recent.len() > run.window {
                    recent.pop_front();
                }
            }
        }
        while update_debt >= 1.0 && replay.len() >= sac.cfg.batch_size {
            replay.sample_into(&mut rng, sac.cfg.batch_size, &mut batch).expect("non-empty replay");
            last = sac.update(&batch);
            update_debt -= 1.0;
        }
        if steps >= next_report {
            next_report += run.report_every;
            let n = recent.len().max(1) as f32;
            let p = CurvePoint {
                env_steps: steps,
                updates: sac.updates,
                episodes,
                success: recent.iter().map(|m| m.success).sum::<f32>() / n,
                safety: recent.iter().map(|m| m.safety).sum::<f32>() / n,
                speed: recent.iter().map(|m| m.speed).sum::<f32>() / n,
                critic_loss: last.critic,
                actor_loss: last.actor,
                alpha: last.alpha,
                entropy: last.entropy,
                wall_s: start.elapsed().as_secs_f64(),
                ..CurvePoint::default()
            };
            on_point(&p);
            curve.push(p);
        }
    }
    curve
}
