//! Who acts in a decision step of batched simulators: the ego rows, the externally driven
//! background rows and the SocialCommAdv adversary, each with one batched inference over every
//! scenario's environments.
//!
//! Owns: [`Drivers`] (the actor of each role: uniform, the IDM demonstrator, or a policy),
//! [`decide`] (the adversary's message first, communicated before anyone drives, then the
//! driving actions as the roles chose them), [`apply`] (steps the environments with them, adding
//! the IDM driver's action for roles whose actions are residuals) and [`run_episodes`] (stored
//! episodes to their end). Shared by rollout workers and evaluation, so both run a flow the same
//! way. Must not: record transitions or choose which role is being trained.

use rand::Rng;
use rand_distr::StandardNormal;
use sf_sim::metrics::EpisodeMetrics;
use sf_sim::vec_env::VecEnv;
use sf_sim::Action;

use crate::inference::PolicyRunner;
use crate::setup::adversary_svo_deg;

/// How one role acts.
#[derive(Clone, Copy)]
pub enum Actor<'a> {
    /// Uniform in [-1, 1] (warm-up).
    Random,
    /// The IDM demonstrator ([`VecEnv::demo_actions`]) with Gaussian noise of this standard
    /// deviation per component, clipped to [-1, 1] (the IDM warm-up). Driving roles only.
    /// For a role whose actions are IDM residuals it acts with the residual: the noise alone.
    Demo { noise: f32, residual: bool },
    /// A policy: sampled, or its mean action when `deterministic` (evaluation).
    Policy { runner: &'a PolicyRunner, deterministic: bool },
}

impl<'a> Actor<'a> {
    pub fn sampled(runner: &'a PolicyRunner) -> Self {
        Self::Policy { runner, deterministic: false }
    }

    pub fn mean(runner: &'a PolicyRunner) -> Self {
        Self::Policy { runner, deterministic: true }
    }

    /// Its actions are residuals on the IDM driver's ([`apply`] adds the driver's action).
    pub fn idm_residual(&self) -> bool {
        match self {
            Actor::Random => false,
            Actor::Demo { residual, .. } => *residual,
            Actor::Policy { runner, .. } => runner.idm_residual(),
        }
    }
}

/// The actor of each role. Rows flagged `alive` (the ego, or every learner of a Stage-1 flow)
/// are driven by `alive`; rows flagged `background` by `background`; `adversary`, if any,
/// reads the `alive` rows (the ego's observation) and tells the background its SVO.
#[derive(Clone, Copy)]
pub struct Drivers<'a> {
    pub alive: Actor<'a>,
    pub background: Option<Actor<'a>>,
    pub adversary: Option<Actor<'a>>,
}

/// The actions of one step, per environment batch (one per scenario).
#[derive(Default)]
pub struct Decision {
    /// Row indices of live `alive` rows and of live externally driven background rows.
    pub alive_rows: Vec<Vec<usize>>,
    pub background_rows: Vec<Vec<usize>>,
    /// Two floats per row of `alive_rows` / `background_rows`.
    pub alive_actions: Vec<Vec<f32>>,
    pub background_actions: Vec<Vec<f32>>,
    /// One float per row of `alive_rows` when there is an adversary (its raw action).
    pub adversary_actions: Vec<Vec<f32>>,
    /// Observations that went through a policy this step.
    pub inferred_rows: usize,
    /// The `alive` / `background` actions are residuals on the IDM driver's.
    pub alive_residual: bool,
    pub background_residual: bool,
}

fn flagged(flags: &[f32]) -> Vec<usize> {
    (0..flags.len()).filter(|&r| flags[r] == 1.0).collect()
}

/// `dim` actions per listed row of every batch, one inference for all of them.
fn act(venvs: &[VecEnv], rows: &[Vec<usize>], actor: Actor, dim: usize, rng: &mut impl Rng) -> (Vec<Vec<f32>>, usize) {
    let n: usize = rows.iter().map(Vec::len).sum();
    let flat = match actor {
        Actor::Random => (0..n * dim).map(|_| rng.random_range(-1.0..1.0)).collect(),
        Actor::Demo { noise, residual } => {
            assert_eq!(dim, 2, "the IDM demonstrator drives; it has no other action");
            let mut a: Vec<f32> = if residual { vec![0.0; n * dim] } else { venvs.iter().zip(rows).flat_map(|(v, rs)| v.demo_actions(rs)).collect() };
            for x in &mut a {
                let e: f32 = rng.sample(StandardNormal);
                *x = (*x + noise * e).clamp(-1.0, 1.0);
            }
            a
        }
        Actor::Policy { .. } if n == 0 => Vec::new(),
        Actor::Policy { runner, deterministic } => {
            let len = venvs.first().map_or(0, |v| v.spec.len);
            let mut obs = Vec::with_capacity(n * len);
            let mut ids = Vec::with_capacity(n);
            for (k, (v, rs)) in venvs.iter().zip(rows).enumerate() {
                for &r in rs {
                    obs.extend_from_slice(&v.observations()[r * len..(r + 1) * len]);
                    ids.push(k as u32);
                }
            }
            let a = if deterministic { runner.mean(&obs, &ids) } else { runner.sample(&obs, &ids, rng) };
            assert_eq!(a.len(), n * dim, "policy action size differs from its role's");
            a
        }
    };
    let mut out = Vec::with_capacity(rows.len());
    let mut at = 0;
    for rs in rows {
        out.push(flat[at..at + rs.len() * dim].to_vec());
        at += rs.len() * dim;
    }
    (out, if matches!(actor, Actor::Policy { .. }) { n } else { 0 })
}

/// Decides the step: the adversary speaks first (its message reaches the background's
/// observations before they act), then every role drives.
pub fn decide(venvs: &mut [VecEnv], d: &Drivers, rng: &mut impl Rng) -> Decision {
    let alive_rows: Vec<Vec<usize>> = venvs.iter().map(|v| flagged(v.alive())).collect();
    let mut out = Decision { alive_rows, ..Decision::default() };
    if let Some(adv) = d.adversary {
        let (a, n) = act(venvs, &out.alive_rows, adv, 1, rng);
        out.inferred_rows += n;
        for ((v, rs), acts) in venvs.iter_mut().zip(&out.alive_rows).zip(&a) {
            // The ego is agent 0 of its environment: row k * max_agents.
            let mut msg = vec![None; v.n_envs()];
            for (&r, &x) in rs.iter().zip(acts) {
                msg[r / v.max_agents] = Some(adversary_svo_deg(x));
            }
            v.communicate_ego_svo(&msg);
        }
        out.adversary_actions = a;
    }
    out.background_rows = venvs.iter().map(|v| flagged(v.background())).collect();
    let (a, n) = act(venvs, &out.alive_rows, d.alive, 2, rng);
    out.alive_actions = a;
    out.alive_residual = d.alive.idm_residual();
    out.inferred_rows += n;
    if let Some(bg) = d.background {
        let (a, n) = act(venvs, &out.background_rows, bg, 2, rng);
        out.background_actions = a;
        out.background_residual = bg.idm_residual();
        out.inferred_rows += n;
    } else {
        out.background_actions = out.background_rows.iter().map(|rs| vec![0.0; rs.len() * 2]).collect();
    }
    out
}

/// Steps every batch with the decided driving actions (rows without one keep the default);
/// a residual role's action is added to the IDM driver's action in the state it was decided
/// in, and clipped to [-1, 1].
pub fn apply(venvs: &mut [VecEnv], d: &Decision) {
    for (k, v) in venvs.iter_mut().enumerate() {
        let mut acts = vec![Action::default(); v.alive().len()];
        for (rows, a, residual) in [(&d.alive_rows[k], &d.alive_actions[k], d.alive_residual), (&d.background_rows[k], &d.background_actions[k], d.background_residual)] {
            // The IDM driver's actions only for residual roles; others drive their action as is.
            let base = residual.then(|| v.demo_actions(rows));
            for (j, &r) in rows.iter().enumerate() {
                let c = |i: usize| (a[i] + base.as_ref().map_or(0.0, |b| b[i])).clamp(-1.0, 1.0);
                acts[r] = Action { ref_speed: c(j * 2), steer: c(j * 2 + 1) };
            }
        }
        v.step(&acts);
    }
}

/// Runs the stored episodes of `v` (`VecEnv::from_episodes`) to their end with `d`.
/// `after_step(v, tags)` sees every step's results (`VecEnv::row_steps`, the environments)
/// with the tags of the episodes that took it, per environment (`None`: idle). Returns every
/// episode's `(tag, metrics)` in the order they finished.
pub fn run_episodes(v: &mut VecEnv, d: &Drivers, rng: &mut impl Rng, mut after_step: impl FnMut(&VecEnv, &[Option<u64>])) -> Vec<(u64, EpisodeMetrics)> {
    let mut out = Vec::new();
    let venvs = std::slice::from_mut(v);
    while !venvs[0].is_finished() {
        let tags: Vec<Option<u64>> = (0..venvs[0].n_envs()).map(|k| venvs[0].tag(k)).collect();
        let decision = decide(venvs, d, rng);
        apply(venvs, &decision);
        after_step(&venvs[0], &tags);
        out.extend(venvs[0].take_finished_tagged());
    }
    out
}
