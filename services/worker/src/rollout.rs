//! The rollout thread: K simulators spread over every scenario of the job, stepped in parallel
//! with one batched CPU inference per step, transitions packed into batches stamped with the
//! acting policy version.
//!
//! Owns: [`Rollout`], the session's handle on the thread (it hands new policy weights and the
//! warm-up flag through [`Control`], a [`Window`] slot back per acknowledgement, and stops the
//! thread on drop); [`spawn`] and the environment loop it runs (who acts in which role, the
//! simulator steps). What leaves the thread is `writer`'s: its `TransitionWriter` batches,
//! stamps and sends through a bounded channel, so a back-pressured stream stops the simulators
//! instead of growing memory. Must not: do network IO itself.

mod nstep;
mod window;
mod writer;

pub use window::{LinkEstimate, Window};
use writer::TransitionWriter;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sf_job::config::{BcTarget, JobKind, WarmupPolicy};
use sf_job::{
    ActedBy, Assignment, FrozenRole, JobConfig, JobId, PolicyVersion, TransitionBatch, WorkerId,
};
use sf_nn::device::Device;
use sf_proto::pb;
use sf_rollout::drive::{self, Actor};
use sf_rollout::inference::PolicyRunner;
use sf_rollout::setup;
use sf_sim::obs::MapSegments;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Map, Mode, ObsSpec, SimConfig};
use tokio::sync::mpsc;

use crate::metrics::WorkerMetrics;
use sf_service::sync::lock;

const STREAM_CLOSED: &str = "the transition stream closed";

/// What the session tells the rollout thread.
pub struct Control {
    pub warmup: bool,
    /// Latest weights `(version, bytes)`; the thread rebuilds its actor when the version changes.
    pub policy: Option<(PolicyVersion, Vec<u8>)>,
    pub stop: bool,
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
    pub worker_id: WorkerId,
    pub job_id: JobId,
    pub seed: u64,
    pub obs_len: usize,
    pub threads: usize,
}

impl RolloutSpec {
    /// What an assignment's rollout runs: its job, frozen policies and maps, and (CoPO Stage 2
    /// in the background) each scenario's coordinator Gaussian, if it has one.
    pub fn for_assignment(
        asg: &Assignment,
        job: JobConfig,
        frozen: Vec<(FrozenRole, JobConfig, Vec<u8>)>,
        maps: Vec<Arc<Map>>,
        worker_id: WorkerId,
        threads: usize,
    ) -> Self {
        let bg = asg.frozen.iter().find(|f| f.role == FrozenRole::Background);
        let svo_gaussians: Vec<_> =
            job.env.scenarios.iter().map(|s| bg.and_then(|f| f.svo_gaussian(s))).collect();
        let redrawn = svo_gaussians.iter().flatten().count();
        if redrawn > 0 {
            tracing::info!(worker_id = worker_id.get(), "CoPO Stage 2: background SVOs redrawn every step from the coordinator's Gaussians in {redrawn} scenario(s)");
        }
        Self {
            job,
            frozen,
            svo_gaussians,
            maps,
            worker_id,
            job_id: asg.job_id,
            seed: asg.seed,
            obs_len: asg.obs_len as usize,
            threads,
        }
    }
}

/// The session's handle on a running rollout thread. Dropping it stops the thread.
pub struct Rollout {
    control: Arc<Mutex<Control>>,
    window: Arc<Window>,
    thread: std::thread::JoinHandle<()>,
}

impl Rollout {
    /// Starts the thread acting with `policy` (`None`: warm-up actions until weights come) and
    /// a window of unacknowledged batches capped at `in_flight_batches` (sized to the link
    /// when `adaptive`); returns the batches it sends.
    pub fn start(
        spec: RolloutSpec,
        warmup: bool,
        policy: Option<(PolicyVersion, Vec<u8>)>,
        in_flight_batches: u32,
        adaptive: bool,
        metrics: &WorkerMetrics,
    ) -> anyhow::Result<(Self, mpsc::Receiver<pb::TransitionBatch>)> {
        let control = Arc::new(Mutex::new(Control { warmup, policy, stop: false }));
        let (batch_tx, batch_rx) = mpsc::channel::<pb::TransitionBatch>(2);
        let window = Arc::new(Window::new(in_flight_batches, adaptive));
        let thread =
            spawn(spec, Arc::clone(&control), Arc::clone(&window), batch_tx, metrics.clone())?;
        Ok((Self { control, window, thread }, batch_rx))
    }

    /// One acknowledgement arrived: the thread may send one more batch.
    pub fn grant(&self) {
        self.window.grant();
    }

    /// The window of unacknowledged batches now.
    pub fn window(&self) -> u32 {
        self.window.limit()
    }

    /// The round trip and acknowledged rate the window is sized from.
    pub fn link_estimate(&self) -> Option<LinkEstimate> {
        self.window.estimate()
    }

    pub fn is_finished(&self) -> bool {
        self.thread.is_finished()
    }

    /// Whether the thread has been handed weights yet.
    pub fn has_policy(&self) -> bool {
        lock(&self.control).policy.is_some()
    }

    /// New weights, acting at once (the warm-up is over).
    pub fn act_with(&self, version: PolicyVersion, weights: Vec<u8>) {
        let mut c = lock(&self.control);
        c.policy = Some((version, weights));
        c.warmup = false;
    }

    /// The warm-up is over: the weights held act.
    pub fn end_warmup(&self) {
        lock(&self.control).warmup = false;
    }
}

impl Drop for Rollout {
    fn drop(&mut self) {
        lock(&self.control).stop = true;
    }
}

/// Starts the rollout thread. It ends when `control.stop` is set or the channel closes.
pub fn spawn(
    spec: RolloutSpec,
    control: Arc<Mutex<Control>>,
    window: Arc<Window>,
    tx: mpsc::Sender<pb::TransitionBatch>,
    metrics: WorkerMetrics,
) -> anyhow::Result<std::thread::JoinHandle<()>> {
    let background =
        spec.frozen.iter().find(|(r, _, _)| *r == FrozenRole::Background).map(|(_, c, _)| c);
    let resolved = setup::resolve(&spec.job, background);
    if resolved.obs.len != spec.obs_len {
        bail!(
            "the learner expects {}-float observations; this worker's build makes {}",
            spec.obs_len,
            resolved.obs.len
        );
    }
    std::thread::Builder::new()
        .name(format!("rollout-{}", spec.worker_id))
        .spawn(move || {
            let stop = Arc::clone(&control);
            if let Err(e) = rollout(spec, resolved, control, window, tx, metrics) {
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

/// The environment loop: act, step, hand the job's transitions to the writer.
fn rollout(
    spec: RolloutSpec,
    resolved: setup::ResolvedJob,
    control: Arc<Mutex<Control>>,
    window: Arc<Window>,
    tx: mpsc::Sender<pb::TransitionBatch>,
    metrics: WorkerMetrics,
) -> anyhow::Result<()> {
    let job = &spec.job;
    let setup::ResolvedJob { sim, net, obs: obs_spec, mode, .. } = resolved;
    let sim = Arc::new(sim);
    let device =
        sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).context("inference device")?;
    let segs: Vec<MapSegments> =
        spec.maps.iter().map(|m| MapSegments::build(m, sim.obs.segment_points)).collect();
    let seg_refs: Vec<&MapSegments> = segs.iter().collect();
    let mut venvs = envs(&spec, &sim, mode);
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed ^ 0x726f_6c6c);
    let len = obs_spec.len;
    let frozen = FrozenRunners::load(&spec.frozen, &obs_spec, sim.dt_s, &seg_refs, &device)?;
    let kind = job.kind;
    if kind == JobKind::Failmaker || kind == JobKind::SocialcommAdv {
        anyhow::ensure!(
            frozen.ego.is_some(),
            "a {} job needs its frozen ego policy",
            kind.as_str()
        );
    }
    let act_dim = job.action_dim();
    let seat = drive::Seat::for_job(kind);
    // Who plays the job's own role until the warm-up ends.
    let warm_actor = match job.sac.warmup_policy {
        WarmupPolicy::Idm if kind.drives() => {
            Actor::Demo { noise: job.sac.warmup_noise, action: net.action }
        }
        _ => Actor::Random { dim: act_dim },
    };
    // Braking and lane-change segments overlay the warm-up actions of the rows the job drives.
    let mut brakes = ((job.sac.warmup_brake_prob > 0.0 || job.sac.warmup_lane_change_prob > 0.0)
        && kind.drives())
    .then(|| {
        let segments = drive::WarmupSegments::new(
            job.sac.warmup_brake_prob,
            job.sac.warmup_lane_change_prob,
            &venvs,
        );
        // FailMaker drives the background: its own vehicles brake and change lanes.
        if kind == JobKind::Failmaker {
            segments.on_background()
        } else {
            segments
        }
    });
    let mut runner: Option<PolicyRunner> = None;
    let nstep = nstep::NStep::new(job.sac.n_step, job.sac.gamma);
    let mut writer = TransitionWriter::new(
        TransitionBatch::new(spec.job_id, spec.worker_id, len, act_dim),
        nstep,
        job.worker.batch_transitions,
        Arc::clone(&control),
        window,
        tx,
        metrics.clone(),
    );
    loop {
        let (stop, warmup, new_policy) = {
            let c = lock(&control);
            let newer = c
                .policy
                .as_ref()
                .filter(|(v, _)| runner.as_ref().is_none_or(|r| r.version != *v))
                .cloned();
            (c.stop, c.warmup, newer)
        };
        if stop {
            return Ok(());
        }
        if let Some((v, bytes)) = new_policy {
            runner = Some(
                PolicyRunner::from_bytes(&net, &obs_spec, sim.dt_s, &seg_refs, &bytes, v, &device)
                    .with_context(|| format!("loading policy version {v}"))?,
            );
            metrics.policy_version.set(v.get() as i64);
        }
        let acting = match (&runner, warmup) {
            (Some(r), false) => Some(r),
            _ => None,
        };
        // The job's own policy plays its role (in the warm-up too with `warmup_policy =
        // "policy"`); frozen policies the others.
        let Some(own) = own_actor(job.sac.warmup_policy, acting, runner.as_ref(), warm_actor)
        else {
            // A continuation's warm-up waits for its policy rather than act otherwise.
            std::thread::sleep(Duration::from_millis(20));
            continue;
        };
        let acted_by =
            acting.map_or(ActedBy::Warmup, |r| sf_proto::acted_by_from_wire(r.version.get()));
        if writer.stamp(acted_by)?.is_break() {
            return Ok(());
        }
        let (f_bg, f_ego, f_adv) = (
            frozen.background.as_ref().map(Actor::sampled),
            frozen.ego.as_ref().map(Actor::sampled),
            frozen.adversary.as_ref().map(Actor::sampled),
        );
        let drivers = seat.drivers(own, f_bg, f_ego, f_adv);
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
        let (trained_rows, trained_actions) = seat.trained(&d);
        // IDM's action in each trained row's state, before the step moves it
        // (`sac.bc_target = "oracle"`).
        let oracle = (job.sac.bc_target == BcTarget::Oracle)
            .then(|| drive::oracle_labels(&venvs, trained_rows, net.action));
        drive::apply(&mut venvs, &d);
        if let Some(b) = brakes.as_mut() {
            b.after_step(&venvs);
        }
        writer.add(&mut venvs, &before, trained_rows, trained_actions, oracle.as_deref(), job);
        if writer.send_if_full()?.is_break() {
            return Ok(());
        }
    }
}

/// Every scenario of the job, environments split evenly; map id = scenario index.
fn envs(spec: &RolloutSpec, sim: &Arc<SimConfig>, mode: Mode) -> Vec<VecEnv> {
    let job = &spec.job;
    let per_map = job.worker.envs.div_ceil(spec.maps.len()).max(1);
    let mut venvs: Vec<VecEnv> = spec
        .maps
        .iter()
        .enumerate()
        .map(|(k, m)| {
            let seed = spec.seed.wrapping_add(k as u64 * 0x9e37_79b9);
            VecEnv::new(
                Arc::clone(m),
                Arc::clone(sim),
                VecEnvConfig {
                    n_envs: per_map,
                    mode,
                    vehicles: (job.env.vehicles_min, job.env.vehicles_max),
                    seed,
                },
            )
        })
        .collect();
    if let Some(share) = job.env.conflict_share {
        venvs = venvs.into_iter().map(|v| v.with_conflicts(share)).collect();
    }
    if let Some(slow) = job.env.slow_leader {
        venvs = venvs.into_iter().map(|v| v.with_slow_leader(slow)).collect();
    }
    for (v, g) in venvs.iter_mut().zip(&spec.svo_gaussians) {
        v.set_svo_gaussian(*g);
    }
    venvs
}

/// Who plays the job's own role this step: its policy once the warm-up is over (`acting`); in
/// the warm-up `warm` (the IDM demonstrator, or random actions), or with `warmup_policy =
/// "policy"` the policy itself, and `None` (wait) while that policy has not arrived: its
/// warm-up must not fall back to actions of another kind.
fn own_actor<'a>(
    warmup_policy: WarmupPolicy,
    acting: Option<&'a PolicyRunner>,
    runner: Option<&'a PolicyRunner>,
    warm: Actor<'a>,
) -> Option<Actor<'a>> {
    match (acting, runner, warmup_policy) {
        (Some(r), _, _) | (None, Some(r), WarmupPolicy::Policy) => Some(Actor::sampled(r)),
        (None, None, WarmupPolicy::Policy) => None,
        _ => Some(warm),
    }
}

/// The frozen policies' actors, by role.
struct FrozenRunners {
    background: Option<PolicyRunner>,
    ego: Option<PolicyRunner>,
    adversary: Option<PolicyRunner>,
}

impl FrozenRunners {
    fn load(
        frozen: &[(FrozenRole, JobConfig, Vec<u8>)],
        obs_spec: &ObsSpec,
        dt_s: f32,
        seg_refs: &[&MapSegments],
        device: &Device,
    ) -> anyhow::Result<Self> {
        let len = obs_spec.len;
        let mut runners = Self { background: None, ego: None, adversary: None };
        for (role, cfg, bytes) in frozen {
            let fz = setup::resolve(cfg, None);
            anyhow::ensure!(
                fz.obs.len == len,
                "frozen {role:?} policy observations are {} floats, the job's {len}",
                fz.obs.len
            );
            let runner = PolicyRunner::from_bytes(
                &fz.net,
                obs_spec,
                dt_s,
                seg_refs,
                bytes,
                PolicyVersion::new(0),
                device,
            )
            .with_context(|| format!("loading the frozen {role:?} policy"))?;
            *match role {
                FrozenRole::Background => &mut runners.background,
                FrozenRole::Ego => &mut runners.ego,
                FrozenRole::Adversary => &mut runners.adversary,
            } = Some(runner);
        }
        Ok(runners)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A continuation warming up with its policy waits for that policy: before it arrives
    /// nothing else may act in its place (a random actor is the paper's direct action, which
    /// a one-number residual job cannot record). Other warm-ups act with their warm actor.
    #[test]
    fn a_policy_warm_up_waits_for_its_policy() {
        let demo = Actor::Demo { noise: 0.1, action: sf_sim::DriveAction::IdmAccelResidual };
        assert!(own_actor(WarmupPolicy::Policy, None, None, demo).is_none());
        assert!(matches!(own_actor(WarmupPolicy::Idm, None, None, demo), Some(Actor::Demo { .. })));
        assert!(matches!(
            own_actor(WarmupPolicy::Random, None, None, Actor::Random { dim: 2 }),
            Some(Actor::Random { dim: 2 })
        ));
    }
}
