//! The rollout thread: K simulators spread over every scenario of the job, stepped in parallel
//! with one batched CPU inference per step, transitions packed into batches stamped with the
//! acting policy version.
//!
//! Owns: [`spawn`] and the loop it runs. The session hands it new policy weights and the
//! warm-up flag through [`Control`]; it hands back wire batches through a bounded channel, so a
//! back-pressured stream stops the simulators instead of growing memory. Must not: do network
//! IO itself.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use anyhow::{bail, Context};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sf_job::config::{JobKind, WarmupPolicy};
use sf_job::{Ends, EpisodeResult, FrozenRole, JobConfig, TransitionBatch};
use sf_proto::pb;
use sf_sac::drive::{self, Actor, Drivers};
use sf_sac::inference::PolicyRunner;
use sf_sac::setup;
use sf_sim::obs::MapSegments;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::Map;
use tokio::sync::mpsc;

use crate::WorkerMetrics;
use sf_svc::sync::lock;

const STREAM_CLOSED: &str = "the transition stream closed";

/// What the session tells the rollout thread.
pub struct Control {
    pub warmup: bool,
    /// Latest weights `(version, bytes)`; the thread rebuilds its actor when the version changes.
    pub policy: Option<(u64, Vec<u8>)>,
    pub stop: bool,
}

/// Batches the rollout thread may send before the learner acknowledges one: bounds the data in
/// flight, and so its policy lag, when the learner's rate limiter holds workers back.
pub struct Credits {
    n: Mutex<u32>,
    changed: std::sync::Condvar,
}

impl Credits {
    pub fn new(n: u32) -> Self {
        Self { n: Mutex::new(n), changed: std::sync::Condvar::new() }
    }

    /// One acknowledgement arrived.
    pub fn grant(&self) {
        *lock(&self.n) += 1;
        self.changed.notify_all();
    }

    /// Waits for a credit; `false` if `stop` turned true first.
    fn take(&self, control: &Mutex<Control>) -> bool {
        let mut n = lock(&self.n);
        loop {
            if *n > 0 {
                *n -= 1;
                return true;
            }
            if lock(control).stop {
                return false;
            }
            n = self.changed.wait_timeout(n, std::time::Duration::from_millis(100)).unwrap_or_else(|p| p.into_inner()).0;
        }
    }
}

pub struct RolloutSpec {
    pub job: JobConfig,
    /// Frozen policies the job acts with: role, config and weights.
    pub frozen: Vec<(FrozenRole, JobConfig, Vec<u8>)>,
    /// Per scenario: the CoPO coordinator's Gaussian the background's SVOs are redrawn from
    /// every step (`None`: the cases' SVOs).
    pub svo_gaussians: Vec<Option<sf_sim::SvoGaussian>>,
    /// The job's scenarios in config order (index = map id).
    pub maps: Vec<Arc<Map>>,
    pub worker_id: u64,
    pub job_id: u64,
    pub seed: u64,
    pub obs_len: usize,
    pub threads: usize,
}

/// Starts the rollout thread. It ends when `control.stop` is set or the channel closes.
pub fn spawn(spec: RolloutSpec, control: Arc<Mutex<Control>>, credits: Arc<Credits>, tx: mpsc::Sender<pb::TransitionBatch>, metrics: WorkerMetrics) -> anyhow::Result<std::thread::JoinHandle<()>> {
    let bg_kind = spec.frozen.iter().find(|(r, _, _)| *r == FrozenRole::Background).map(|(_, c, _)| c.kind);
    let resolved = setup::resolve(&spec.job, bg_kind);
    if resolved.obs.len != spec.obs_len {
        bail!("the learner expects {}-float observations; this worker's build makes {}", spec.obs_len, resolved.obs.len);
    }
    std::thread::Builder::new()
        .name(format!("rollout-{}", spec.worker_id))
        .spawn(move || {
            let stop = Arc::clone(&control);
            if let Err(e) = rollout(spec, resolved, control, &credits, tx, metrics) {
                // The session closes the stream when it ends; only other failures are errors.
                if lock(&stop).stop || e.to_string() == STREAM_CLOSED {
                    tracing::debug!(error = %format!("{e:#}"), "rollout thread stopped");
                } else {
                    tracing::error!(error = %format!("{e:#}"), "rollout thread failed");
                }
            }
        })
        .context("spawning the rollout thread")
}

fn rollout(spec: RolloutSpec, resolved: setup::ResolvedJob, control: Arc<Mutex<Control>>, credits: &Credits, tx: mpsc::Sender<pb::TransitionBatch>, metrics: WorkerMetrics) -> anyhow::Result<()> {
    let job = &spec.job;
    let setup::ResolvedJob { sim, net, obs: obs_spec, mode, .. } = resolved;
    let sim = Arc::new(sim);
    let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).context("inference device")?;
    let segs: Vec<MapSegments> = spec.maps.iter().map(|m| MapSegments::build(m, sim.obs.segment_points)).collect();
    let seg_refs: Vec<&MapSegments> = segs.iter().collect();
    // Every scenario of the job, environments split evenly; map id = scenario index.
    let per_map = job.worker.envs.div_ceil(spec.maps.len()).max(1);
    let mut venvs: Vec<VecEnv> = spec
        .maps
        .iter()
        .enumerate()
        .map(|(k, m)| {
            let seed = spec.seed.wrapping_add(k as u64 * 0x9e37_79b9);
            VecEnv::new(Arc::clone(m), Arc::clone(&sim), VecEnvConfig { n_envs: per_map, mode, vehicles: (job.env.vehicles_min, job.env.vehicles_max), seed })
        })
        .collect();
    if let Some(share) = job.env.conflict_share {
        venvs = venvs.into_iter().map(|v| v.with_conflicts(share)).collect();
    }
    for (v, g) in venvs.iter_mut().zip(&spec.svo_gaussians) {
        v.set_svo_gaussian(*g);
    }
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed ^ 0x726f_6c6c);
    let len = obs_spec.len;
    let (mut frozen_bg, mut frozen_ego, mut frozen_adv) = (None, None, None);
    for (role, cfg, bytes) in &spec.frozen {
        let fz = setup::resolve(cfg, None);
        anyhow::ensure!(fz.obs.len == len, "frozen {role:?} policy observations are {} floats, the job's {len}", fz.obs.len);
        let runner = PolicyRunner::from_bytes(&fz.net, &obs_spec, sim.dt_s, &seg_refs, bytes, 0, &device).with_context(|| format!("loading the frozen {role:?} policy"))?;
        *match role {
            FrozenRole::Background => &mut frozen_bg,
            FrozenRole::Ego => &mut frozen_ego,
            FrozenRole::Adversary => &mut frozen_adv,
        } = Some(runner);
    }
    let kind = job.kind;
    if kind == JobKind::Failmaker || kind == JobKind::SocialcommAdv {
        anyhow::ensure!(frozen_ego.is_some(), "a {} job needs its frozen ego policy", kind.as_str());
    }
    let act_dim = job.action_dim();
    // Who plays the job's own role until the warm-up ends.
    let warm_actor = match job.sac.warmup_policy {
        WarmupPolicy::Idm if kind.drives() => Actor::Demo { noise: job.sac.warmup_noise, action: net.action },
        _ => Actor::Random { dim: act_dim },
    };
    // Braking segments overlay the warm-up actions of the `alive` rows: the job's own only
    // where it drives them (not FailMaker's background).
    let mut brakes = (job.sac.warmup_brake_prob > 0.0 && kind.drives() && kind != JobKind::Failmaker).then(|| drive::BrakeSegments::new(job.sac.warmup_brake_prob, &venvs));
    let mut runner: Option<PolicyRunner> = None;
    let mut batch = TransitionBatch::new(spec.job_id, spec.worker_id, len, act_dim);
    let mut batch_version = None;
    loop {
        let (stop, warmup, new_policy) = {
            let c = lock(&control);
            let newer = c.policy.as_ref().filter(|(v, _)| runner.as_ref().is_none_or(|r| r.version != *v)).cloned();
            (c.stop, c.warmup, newer)
        };
        if stop {
            return Ok(());
        }
        if let Some((v, bytes)) = new_policy {
            runner = Some(PolicyRunner::from_bytes(&net, &obs_spec, sim.dt_s, &seg_refs, &bytes, v, &device).with_context(|| format!("loading policy version {v}"))?);
            metrics.policy_version.set(v as i64);
        }
        let acting = match (&runner, warmup) {
            (Some(r), false) => Some(r),
            _ => None,
        };
        let version = acting.map_or(0, |r| r.version);
        if batch_version.is_some_and(|v| v != version) && batch.count > 0 {
            if !credits.take(&control) {
                return Ok(());
            }
            send(&mut batch, batch_version.unwrap_or(0), &tx, &metrics)?;
        }
        batch_version = Some(version);
        // The job's own policy plays its role; frozen policies the others.
        let own = acting.map_or(warm_actor, Actor::sampled);
        let (f_bg, f_ego, f_adv) = (frozen_bg.as_ref().map(Actor::sampled), frozen_ego.as_ref().map(Actor::sampled), frozen_adv.as_ref().map(Actor::sampled));
        let drivers = match kind {
            JobKind::Failmaker => Drivers { alive: f_ego.unwrap_or(Actor::Random { dim: 2 }), background: Some(own), adversary: None },
            JobKind::SocialcommAdv => Drivers { alive: f_ego.unwrap_or(Actor::Random { dim: 2 }), background: f_bg, adversary: Some(own) },
            _ => Drivers { alive: own, background: f_bg, adversary: f_adv },
        };
        let before: Vec<Vec<f32>> = venvs.iter().map(|v| v.observations().to_vec()).collect();
        let t = Instant::now();
        let mut d = drive::decide(&mut venvs, &drivers, &mut rng);
        if d.inferred_rows > 0 {
            metrics.inference_seconds.inc_by(t.elapsed().as_secs_f64());
            metrics.inference_obs.inc_by(d.inferred_rows as u64);
        }
        // Braking segments belong to the warm-up: once the policy acts they are dropped.
        if acting.is_some() {
            brakes = None;
        }
        if let Some(b) = brakes.as_mut() {
            b.overlay(&mut d, &mut rng);
        }
        drive::apply(&mut venvs, &d);
        if let Some(b) = brakes.as_mut() {
            b.after_step(&venvs);
        }
        // The rows the job learns from and the actions its policy took there.
        let (trained_rows, trained_actions) = match kind {
            JobKind::Failmaker => (&d.background_rows, &d.background_actions),
            JobKind::SocialcommAdv => (&d.alive_rows, &d.adversary_actions),
            _ => (&d.alive_rows, &d.alive_actions),
        };
        for (k, v) in venvs.iter_mut().enumerate() {
            batch.sim_steps += v.n_envs() as u64;
            metrics.env_steps.inc_by(v.n_envs() as u64);
            for (j, &r) in trained_rows[k].iter().enumerate() {
                let st = v.row_steps()[r];
                if !st.stepped {
                    continue;
                }
                let act = &trained_actions[k][j * act_dim..(j + 1) * act_dim];
                batch.push(&before[k][r * len..(r + 1) * len], act, setup::reward(job, &st.rewards), v.next_observation(r), st.terminal(), k as u32);
            }
            for m in v.take_finished() {
                metrics.episodes.inc();
                batch.episodes.push(EpisodeResult {
                    scenario_index: k as u32,
                    success: m.success,
                    safety: m.safety,
                    speed: m.speed,
                    ends: Ends { collision: m.collision, off_road: m.off_road, off_route: m.off_route, wrong_lane: m.wrong_lane, timeout: m.timeout },
                });
            }
        }
        if batch.count >= job.worker.batch_transitions {
            if !credits.take(&control) {
                return Ok(());
            }
            send(&mut batch, version, &tx, &metrics)?;
        }
    }
}

fn send(batch: &mut TransitionBatch, version: u64, tx: &mpsc::Sender<pb::TransitionBatch>, metrics: &WorkerMetrics) -> anyhow::Result<()> {
    batch.policy_version = version;
    let msg = sf_proto::batch_to_wire(batch);
    metrics.transitions_sent.inc_by(batch.count as u64);
    metrics.batches_sent.inc();
    batch.clear();
    if tx.blocking_send(msg).is_err() {
        bail!(STREAM_CLOSED);
    }
    Ok(())
}
