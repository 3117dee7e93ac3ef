//! The critic probe: does a job's critic learn which states lead to failure?
//!
//! Drives the job's ego with its IDM demonstrator (the warm-up's actor, noise and braking
//! segments) among the job's traffic ([`collect`], also the hand-over probe's data; IDM's
//! noise-free action is recorded in every state), labels every transition "a failure within `horizon`
//! decision steps", trains the job's SAC on the first 80 % of the episodes with the actor
//! frozen after cloning (policy evaluation only), then scores the critic on the held-out 20 %:
//! the AUROC of `-Q(s, a)` for the label, and the error on failure rows (whose target is
//! exactly the scaled failure reward).
//! Separates "the representation cannot see it" from "RL does not find it".
//!
//! Owns: [`collect`], [`train_and_score`], [`auroc`]. Must not: touch the service or files.

use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use sf_job::JobConfig;
use sf_rollout::drive::{self, Actor, Drivers};
use sf_rollout::setup;
use sf_sac::replay::{Batch, Replay, ReplayError, Transition};
use sf_sac::Sac;
use sf_sim::env::{Controller, Mode};
use sf_sim::obs::MapSegments;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::Map;

/// What failed collecting or training on the probe's transitions.
#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    /// The replay refused a transition or a sample (the replay's error names the field).
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// The hand-over probe's closed-loop episodes could not run (the reason named).
    #[error("closed-loop episodes: {0}")]
    Eval(String),
}

/// Demonstrator transitions with their failure labels, split by episode.
pub struct ProbeData {
    pub train: Replay,
    /// Held-out rows: observation, action, map id and IDM's noise-free action (`oracle`); the
    /// failure label and whether the row itself failed beside them.
    pub test: Batch,
    pub test_labels: Vec<bool>,
    pub test_failed: Vec<bool>,
    pub failure_episodes: usize,
    pub episodes: usize,
}

struct Pending {
    obs: Vec<f32>,
    action: Vec<f32>,
    reward: f32,
    next_obs: Vec<f32>,
    terminal: bool,
    map_id: u32,
    failed: bool,
    /// IDM's noise-free action in the row's state (direct action; zeros for residual kinds).
    oracle: Vec<f32>,
}

/// Runs the demonstrator for at least `transitions` ego transitions over the job's scenarios.
pub fn collect(
    job: &JobConfig,
    maps: &[Arc<Map>],
    transitions: usize,
    horizon: usize,
    seed: u64,
) -> Result<ProbeData, ProbeError> {
    let setup::ResolvedJob { sim, net, .. } = setup::resolve(job, None);
    let sim = Arc::new(sim);
    let per_map = 8;
    let mut venvs: Vec<VecEnv> = maps
        .iter()
        .enumerate()
        .map(|(k, m)| {
            VecEnv::new(
                Arc::clone(m),
                Arc::clone(&sim),
                VecEnvConfig {
                    n_envs: per_map,
                    mode: Mode::Ego { background: Controller::Idm },
                    vehicles: (job.env.vehicles_min, job.env.vehicles_max),
                    seed: seed.wrapping_add(k as u64 * 7919),
                },
            )
        })
        .collect();
    let len = venvs[0].spec.len;
    let drivers = Drivers {
        alive: Actor::Demo { noise: job.sac.warmup_noise, action: net.action },
        background: None,
        adversary: None,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut brakes = (job.sac.warmup_brake_prob > 0.0 || job.sac.warmup_lane_change_prob > 0.0)
        .then(|| {
            drive::WarmupSegments::new(
                job.sac.warmup_brake_prob,
                job.sac.warmup_lane_change_prob,
                &venvs,
            )
        });
    // Per environment row: the episode in progress.
    let mut open: Vec<Vec<Vec<Pending>>> =
        venvs.iter().map(|v| (0..v.alive().len()).map(|_| Vec::new()).collect()).collect();
    let mut episodes: Vec<Vec<Pending>> = Vec::new();
    let mut n = 0;
    while n < transitions {
        let before: Vec<Vec<f32>> = venvs.iter().map(|v| v.observations().to_vec()).collect();
        let mut d = drive::decide(&mut venvs, &drivers, &mut rng);
        if let Some(b) = brakes.as_mut() {
            b.overlay(&mut d, &mut rng);
        }
        let labels = drive::oracle_labels(&venvs, &d.alive_rows, net.action);
        drive::apply(&mut venvs, &d);
        if let Some(b) = brakes.as_mut() {
            b.after_step(&venvs);
        }
        let dim = net.action_dim;
        for (k, v) in venvs.iter_mut().enumerate() {
            for (j, &r) in d.alive_rows[k].iter().enumerate() {
                let st = v.row_steps()[r];
                if !st.stepped {
                    continue;
                }
                let failed = st.ended.is_some_and(|t| t.is_failure());
                open[k][r].push(Pending {
                    obs: before[k][r * len..(r + 1) * len].to_vec(),
                    action: d.alive_actions[k][j * dim..(j + 1) * dim].to_vec(),
                    reward: setup::reward(job, &st.rewards),
                    next_obs: v.next_observation(r).to_vec(),
                    terminal: st.terminal(),
                    map_id: k as u32,
                    failed,
                    oracle: labels[k][j * dim..(j + 1) * dim].to_vec(),
                });
                n += 1;
                if st.ended.is_some() {
                    episodes.push(std::mem::take(&mut open[k][r]));
                }
            }
            v.take_finished();
        }
    }
    let n_train = episodes.len() * 4 / 5;
    // The training rows carry IDM's labels where the job clones towards them.
    let labelled = job.sac.bc_target == sf_job::config::BcTarget::Oracle;
    let total: usize = episodes.iter().map(Vec::len).sum();
    let mut train = Replay::new(total.max(1), len, net.action_dim);
    let mut test = Batch::default();
    let (mut test_labels, mut test_failed) = (Vec::new(), Vec::new());
    let failure_episodes = episodes.iter().filter(|e| e.last().is_some_and(|p| p.failed)).count();
    for (i, ep) in episodes.iter().enumerate() {
        let fail_at = ep.iter().position(|p| p.failed);
        for (t, p) in ep.iter().enumerate() {
            if i < n_train {
                train.push(Transition {
                    obs: &p.obs,
                    action: &p.action,
                    reward: p.reward,
                    next_obs: &p.next_obs,
                    terminal: p.terminal,
                    steps: 1,
                    map_id: p.map_id,
                    oracle: if labelled { &p.oracle } else { &[] },
                })?;
            } else {
                test.obs.extend_from_slice(&p.obs);
                test.next_obs.extend_from_slice(&p.next_obs);
                test.actions.extend_from_slice(&p.action);
                test.rewards.push(p.reward);
                test.terminals.push(p.terminal as u8 as f32);
                test.steps.push(1);
                test.map_ids.push(p.map_id);
                test.oracle.extend_from_slice(&p.oracle);
                test_labels.push(fail_at.is_some_and(|f| f >= t && f - t < horizon));
                test_failed.push(p.failed);
            }
        }
    }
    Ok(ProbeData {
        train,
        test,
        test_labels,
        test_failed,
        failure_episodes,
        episodes: episodes.len(),
    })
}

/// What the probe measured.
#[derive(Clone, Debug, Serialize)]
pub struct ProbeScore {
    pub updates: u64,
    pub train_transitions: usize,
    pub test_transitions: usize,
    pub test_positives: usize,
    pub episodes: usize,
    pub failure_episodes: usize,
    /// AUROC of `-min(Q1, Q2)(s, a)` for "failure within the horizon" on the held-out rows.
    pub auroc: f64,
    /// RMSE of Q on held-out rows that failed (target: the scaled failure-step reward, exact).
    pub failure_rmse: f64,
    /// That RMSE relative to |target| (0: exact; 1: as if the failure were not predicted).
    pub failure_rmse_rel: f64,
    pub updates_per_s: f64,
}

/// Trains `sac` (cloning updates as configured, then the critic alone) for `updates` updates
/// on the training split and scores its critic on the held-out rows.
pub fn train_and_score(
    sac: &mut Sac,
    data: &ProbeData,
    updates: u64,
    seed: u64,
) -> Result<ProbeScore, ProbeError> {
    sac.cfg.critic_pretrain_updates = u64::MAX / 2;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x70_726f_6265);
    let mut batch = Batch::default();
    let t = std::time::Instant::now();
    for _ in 0..updates {
        data.train.sample_into(&mut rng, sac.cfg.batch_size, &mut batch)?;
        sac.update(&batch);
    }
    let updates_per_s = updates as f64 / t.elapsed().as_secs_f64().max(1e-9);
    let q = sac.q_min(&data.test.obs, &data.test.actions, &data.test.map_ids);
    let scores: Vec<f32> = q.iter().map(|v| -v).collect();
    let (mut se, mut se_ref, mut nf) = (0.0f64, 0.0f64, 0usize);
    for (i, &failed) in data.test_failed.iter().enumerate() {
        if failed {
            let target = (data.test.rewards[i] * sac.cfg.reward_scale) as f64;
            se += (q[i] as f64 - target).powi(2);
            se_ref += target.powi(2);
            nf += 1;
        }
    }
    let rmse = if nf > 0 { (se / nf as f64).sqrt() } else { f64::NAN };
    let rmse_ref = if nf > 0 { (se_ref / nf as f64).sqrt() } else { f64::NAN };
    Ok(ProbeScore {
        updates,
        train_transitions: data.train.len(),
        test_transitions: data.test.len(),
        test_positives: data.test_labels.iter().filter(|&&l| l).count(),
        episodes: data.episodes,
        failure_episodes: data.failure_episodes,
        auroc: auroc(&scores, &data.test_labels),
        failure_rmse: rmse,
        failure_rmse_rel: rmse / rmse_ref,
        updates_per_s,
    })
}

/// Area under the ROC curve of `scores` (higher: more likely positive) for `labels`, by
/// ranks with ties averaged (the Mann-Whitney U statistic). NaN without both classes.
pub fn auroc(scores: &[f32], labels: &[bool]) -> f64 {
    let mut idx: Vec<usize> = (0..scores.len()).collect();
    idx.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
    let mut ranks = vec![0.0f64; scores.len()];
    let mut i = 0;
    while i < idx.len() {
        let mut j = i;
        while j + 1 < idx.len() && scores[idx[j + 1]] == scores[idx[i]] {
            j += 1;
        }
        let r = (i + j) as f64 / 2.0 + 1.0;
        for &k in &idx[i..=j] {
            ranks[k] = r;
        }
        i = j + 1;
    }
    let pos = labels.iter().filter(|&&l| l).count();
    let neg = labels.len() - pos;
    if pos == 0 || neg == 0 {
        return f64::NAN;
    }
    let sum_pos: f64 = ranks.iter().zip(labels).filter(|(_, &l)| l).map(|(r, _)| r).sum();
    (sum_pos - (pos * (pos + 1)) as f64 / 2.0) / (pos * neg) as f64
}

/// The maps' segments the job's SAC needs (query-centric observations index them).
pub fn segments(maps: &[Arc<Map>], job: &JobConfig) -> Vec<MapSegments> {
    let sim = setup::resolve(job, None).sim;
    maps.iter().map(|m| MapSegments::build(m, sim.obs.segment_points)).collect()
}

#[cfg(test)]
mod tests {
    use super::auroc;

    #[test]
    fn auroc_of_constructed_cases() {
        // Perfect separation, its reverse, and an uninformative constant.
        assert_eq!(auroc(&[0.1, 0.2, 0.8, 0.9], &[false, false, true, true]), 1.0);
        assert_eq!(auroc(&[0.9, 0.8, 0.2, 0.1], &[false, false, true, true]), 0.0);
        assert_eq!(auroc(&[0.5; 4], &[false, true, false, true]), 0.5);
        // One swapped pair out of 2 x 2: 3 of 4 pairs ordered.
        assert_eq!(auroc(&[0.1, 0.6, 0.5, 0.9], &[false, false, true, true]), 0.75);
        assert!(auroc(&[0.1, 0.2], &[true, true]).is_nan());
    }
}
