//! Who acts in a decision step of batched simulators: the ego rows, the externally driven
//! background rows and the SocialCommAdv adversary, each with one batched inference over every
//! scenario's environments.
//!
//! Owns: [`Drivers`] (the actor of each role: uniform, the IDM demonstrator, IDM with MOBIL's
//! lane changes, or a policy), [`decide`] (the adversary's message first, communicated before
//! anyone drives, then the driving actions as the roles chose them), [`apply`] (steps the
//! environments with them, adding the IDM driver's action for roles whose actions are
//! residuals) and [`run_episodes`] (stored episodes to their end). Shared by rollout workers and
//! evaluation, so both run a flow the same way. Where a step's random draws (sampled policy
//! actions, noise, uniform warm-up actions) come from is [`Draws`]: one stream in row order for
//! training, per episode for stored episodes, so an evaluated episode's draws are a function of
//! its case, seed, step and agents alone, whatever the batch width or thread count. Must not: record
//! transitions or choose which role is being trained.

use rand::{Rng, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use sf_job::config::JobKind;
use sf_sim::metrics::EpisodeMetrics;
use sf_sim::vec_env::VecEnv;
use sf_sim::{Action, DriveAction};

use crate::inference::PolicyRunner;
use crate::setup::adversary_svo_deg;

/// How one role acts.
#[derive(Clone, Copy)]
pub enum Actor<'a> {
    /// Uniform in [-1, 1], `dim` floats (warm-up); driving roles read them as the paper's action.
    Random { dim: usize },
    /// The IDM demonstrator ([`VecEnv::demo_action`]) expressed as `action` (for residual
    /// kinds: zero) with Gaussian noise of this standard deviation per component, clipped to
    /// [-1, 1] (the IDM warm-up; a noise of 0 draws no random numbers). Driving roles only.
    Demo { noise: f32, action: DriveAction },
    /// The IDM driver with a learned flow's sampling noise, for a residual `action` (zero is
    /// IDM): each component `tanh(std * e)` with `e` standard normal, what a tanh-squashed
    /// Gaussian policy with a zero mean and this standard deviation samples. The noise-matched
    /// IDM flow of evaluation grids (`job = "idm-noise"`). Driving roles only.
    IdmNoise { std: f32, action: DriveAction },
    /// IDM with MOBIL's lane changes ([`sf_sim::mobil::action`]) as an `idm-residual-lateral`
    /// action: the lane MOBIL chooses, a zero residual once there (a reference driver that
    /// steers). Driving roles only.
    Mobil(sf_sim::mobil::MobilParams),
    /// A policy: sampled, or its mean action when `deterministic` (evaluation).
    Policy { runner: &'a PolicyRunner, deterministic: bool },
    /// Actions chosen outside (a Python policy, or actions handed in by an environment's
    /// caller): `act(rows, n)` gets the `n` observation rows of the role, flattened, and returns
    /// `n * action.dim()` floats. It must not fail: a caller that can fail records its error
    /// and returns zeros.
    External { act: &'a dyn Fn(&[f32], usize) -> Vec<f32>, action: DriveAction },
}

impl<'a> Actor<'a> {
    pub fn sampled(runner: &'a PolicyRunner) -> Self {
        Self::Policy { runner, deterministic: false }
    }

    pub fn mean(runner: &'a PolicyRunner) -> Self {
        Self::Policy { runner, deterministic: true }
    }

    /// How its action vector moves a vehicle ([`apply`] turns it into the vehicle's command).
    pub fn drive_action(&self) -> DriveAction {
        match self {
            Actor::Random { .. } => DriveAction::Direct,
            Actor::Demo { action, .. } | Actor::IdmNoise { action, .. } => *action,
            Actor::Mobil(_) => DriveAction::IdmResidualLateral,
            Actor::Policy { runner, .. } => runner.net().action,
            Actor::External { action, .. } => *action,
        }
    }

    /// Floats per action.
    pub fn dim(&self) -> usize {
        match self {
            Actor::Random { dim } => *dim,
            Actor::Demo { action, .. } | Actor::IdmNoise { action, .. } => action.dim(),
            Actor::Mobil(_) => DriveAction::IdmResidualLateral.dim(),
            Actor::Policy { runner, .. } => runner.net().action_dim,
            Actor::External { action, .. } => action.dim(),
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

/// Where a training job's own policy sits among a step's drivers, by the job's kind: the
/// `alive` rows for ego and Stage-1 flow jobs, the background for FailMaker (its frozen ego
/// drives the `alive` row), the SVO message for SocialCommAdv (the adversary reads the frozen
/// ego's observation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Seat {
    Alive,
    Background,
    Adversary,
}

impl Seat {
    pub fn for_job(kind: JobKind) -> Self {
        match kind {
            JobKind::Failmaker => Self::Background,
            JobKind::SocialcommAdv => Self::Adversary,
            _ => Self::Alive,
        }
    }

    /// `own` in this seat and the frozen policies (`background`, `ego`, `adversary`) in the
    /// others; a RARL job's frozen ego that is missing drives randomly.
    pub fn drivers<'a>(
        self,
        own: Actor<'a>,
        background: Option<Actor<'a>>,
        ego: Option<Actor<'a>>,
        adversary: Option<Actor<'a>>,
    ) -> Drivers<'a> {
        let ego = ego.unwrap_or(Actor::Random { dim: 2 });
        match self {
            Self::Alive => Drivers { alive: own, background, adversary },
            Self::Background => Drivers { alive: ego, background: Some(own), adversary: None },
            Self::Adversary => Drivers { alive: ego, background, adversary: Some(own) },
        }
    }

    /// The rows the job learns from, per environment batch, and the actions its policy took
    /// there.
    pub fn trained(self, d: &Decision) -> (&[Vec<usize>], &[Vec<f32>]) {
        match self {
            Self::Alive => (&d.alive_rows, &d.alive_actions),
            Self::Background => (&d.background_rows, &d.background_actions),
            Self::Adversary => (&d.alive_rows, &d.adversary_actions),
        }
    }
}

/// The actions of one step, per environment batch (one per scenario).
#[derive(Default)]
pub struct Decision {
    /// Row indices of live `alive` rows and of live externally driven background rows.
    pub alive_rows: Vec<Vec<usize>>,
    pub background_rows: Vec<Vec<usize>>,
    /// `alive_action.dim()` / `background_action.dim()` floats per row of `alive_rows` /
    /// `background_rows`.
    pub alive_actions: Vec<Vec<f32>>,
    pub background_actions: Vec<Vec<f32>>,
    /// One float per row of `alive_rows` when there is an adversary (its raw action).
    pub adversary_actions: Vec<Vec<f32>>,
    /// Observations that went through a policy this step.
    pub inferred_rows: usize,
    /// How the `alive` / `background` actions move their vehicles.
    pub alive_action: DriveAction,
    pub background_action: DriveAction,
}

fn flagged(flags: &[f32]) -> Vec<usize> {
    (0..flags.len()).filter(|&r| flags[r] == 1.0).collect()
}

/// The listed rows' observations, flattened, and each row's map (batch) index.
fn gather(venvs: &[VecEnv], rows: &[Vec<usize>], n: usize) -> (Vec<f32>, Vec<u32>) {
    let len = venvs.first().map_or(0, |v| v.spec.len);
    let mut obs = Vec::with_capacity(n * len);
    let mut ids = Vec::with_capacity(n);
    for (k, (v, rs)) in venvs.iter().zip(rows).enumerate() {
        for &r in rs {
            obs.extend_from_slice(&v.observations()[r * len..(r + 1) * len]);
            ids.push(k as u32);
        }
    }
    (obs, ids)
}

/// The IDM driver's action in the current state of every listed row, expressed as `action`
/// (`action.dim()` floats per row, per environment batch): the demonstrator's noise-free
/// action, and the oracle labels of `sac.bc_target = "oracle"`. Residual kinds are IDM at
/// zero: no IDM action to compute.
pub fn oracle_labels(venvs: &[VecEnv], rows: &[Vec<usize>], action: DriveAction) -> Vec<Vec<f32>> {
    venvs
        .iter()
        .zip(rows)
        .map(|(v, rs)| {
            if action == DriveAction::Direct {
                rs.iter().flat_map(|&r| action.demonstrator(v.demo_action(r))).collect()
            } else {
                vec![0.0; rs.len() * action.dim()]
            }
        })
        .collect()
}

/// Where a step's random numbers come from.
pub enum Draws<'r> {
    /// One stream, drawn in row order (batch by batch, row by row, component by component):
    /// training, where a job's stream is its own and no episode is replayed alone.
    Stream(&'r mut dyn RngCore),
    /// Each row's own stream, keyed by its episode's tag, the episode's step, the row's agent
    /// and the role that draws: a stored episode's draws do not depend on which other episodes
    /// share its steps (the batch width), nor on the order they run in.
    PerEpisode,
}

/// The roles that draw, so each role's per-episode draws are its own.
#[derive(Clone, Copy)]
enum Role {
    Adversary = 1,
    Alive = 2,
    Background = 3,
}

/// What one draw is: a standard normal, or uniform in [-1, 1).
#[derive(Clone, Copy)]
enum Draw {
    Normal,
    Uniform,
}

fn draw_one<R: Rng + ?Sized>(g: &mut R, what: Draw) -> f32 {
    match what {
        Draw::Normal => g.sample(StandardNormal),
        Draw::Uniform => g.random_range(-1.0..1.0),
    }
}

/// The stream of one row's draws in one step of a stored episode: ChaCha8 seeded with the
/// episode's tag, the step, the agent and the role laid side by side (a one-to-one key, so two
/// rows never share a stream).
fn row_stream(tag: u64, step: u32, agent: usize, role: Role) -> ChaCha8Rng {
    let mut seed = [0u8; 32];
    seed[..8].copy_from_slice(&tag.to_le_bytes());
    seed[8..12].copy_from_slice(&step.to_le_bytes());
    seed[12..20].copy_from_slice(&(agent as u64).to_le_bytes());
    seed[20] = role as u8;
    seed[24..].copy_from_slice(b"sf-draws");
    ChaCha8Rng::from_seed(seed)
}

/// `dim` draws per listed row, in row order.
fn draws(
    venvs: &[VecEnv],
    rows: &[Vec<usize>],
    dim: usize,
    what: Draw,
    role: Role,
    from: &mut Draws,
) -> Vec<f32> {
    let n: usize = rows.iter().map(Vec::len).sum();
    match from {
        Draws::Stream(rng) => (0..n * dim).map(|_| draw_one(&mut **rng, what)).collect(),
        Draws::PerEpisode => {
            let mut out = Vec::with_capacity(n * dim);
            for (v, rs) in venvs.iter().zip(rows) {
                for &r in rs {
                    let (slot, agent) = (r / v.max_agents, r % v.max_agents);
                    // A listed row is live, so its slot runs an episode (idle slots' rows are
                    // never flagged); u64::MAX keeps the key total all the same.
                    let tag = v.tag(slot).unwrap_or(u64::MAX);
                    let mut g = row_stream(tag, v.env(slot).step_index(), agent, role);
                    out.extend((0..dim).map(|_| draw_one(&mut g, what)));
                }
            }
            out
        }
    }
}

/// `actor.dim()` actions per listed row of every batch, one inference for all of them.
fn act(
    venvs: &[VecEnv],
    rows: &[Vec<usize>],
    actor: Actor,
    role: Role,
    from: &mut Draws,
) -> (Vec<Vec<f32>>, usize) {
    let n: usize = rows.iter().map(Vec::len).sum();
    let dim = actor.dim();
    let flat = match actor {
        Actor::Random { .. } => draws(venvs, rows, dim, Draw::Uniform, role, from),
        Actor::Demo { noise, action } => {
            let mut a: Vec<f32> = oracle_labels(venvs, rows, action).concat();
            // Noise-free demonstrations draw nothing, so the stream other roles sample from (a
            // learned flow's) is the one an outside actor with the same actions would leave.
            if noise > 0.0 {
                let e = draws(venvs, rows, dim, Draw::Normal, role, from);
                for (x, e) in a.iter_mut().zip(e) {
                    *x = (*x + noise * e).clamp(-1.0, 1.0);
                }
            }
            a
        }
        Actor::IdmNoise { std, .. } => draws(venvs, rows, dim, Draw::Normal, role, from)
            .into_iter()
            .map(|e| (std * e).tanh())
            .collect(),
        Actor::Mobil(p) => venvs
            .iter()
            .zip(rows)
            .flat_map(|(v, rs)| rs.iter().flat_map(move |&r| v.mobil_action(r, &p)))
            .collect(),
        Actor::Policy { .. } | Actor::External { .. } if n == 0 => Vec::new(),
        Actor::Policy { runner, deterministic } => {
            let (obs, ids) = gather(venvs, rows, n);
            let a = if deterministic {
                runner.mean(&obs, &ids)
            } else {
                runner.sample_with(&obs, &ids, draws(venvs, rows, dim, Draw::Normal, role, from))
            };
            assert_eq!(a.len(), n * dim, "policy action size differs from its role's");
            a
        }
        Actor::External { act, .. } => {
            let (obs, _) = gather(venvs, rows, n);
            let a = act(&obs, n);
            assert_eq!(
                a.len(),
                n * dim,
                "an external actor returned {} floats for {n} rows of {dim}",
                a.len()
            );
            a
        }
    };
    let mut out = Vec::with_capacity(rows.len());
    let mut at = 0;
    for rs in rows {
        out.push(flat[at..at + rs.len() * dim].to_vec());
        at += rs.len() * dim;
    }
    (out, if matches!(actor, Actor::Policy { .. } | Actor::External { .. }) { n } else { 0 })
}

/// Decides the step: the adversary speaks first (its message reaches the background's
/// observations before they act), then every role drives. Draws from `rng` in row order
/// ([`Draws::Stream`]).
pub fn decide(venvs: &mut [VecEnv], d: &Drivers, rng: &mut impl Rng) -> Decision {
    decide_drawing(venvs, d, &mut Draws::Stream(rng))
}

/// [`decide`] with the draws taken `from` where the caller says.
pub fn decide_drawing(venvs: &mut [VecEnv], d: &Drivers, from: &mut Draws) -> Decision {
    let alive_rows: Vec<Vec<usize>> = venvs.iter().map(|v| flagged(v.alive())).collect();
    let mut out = Decision { alive_rows, ..Decision::default() };
    if let Some(adv) = d.adversary {
        assert_eq!(adv.dim(), 1, "the adversary's action is one SVO");
        let (a, n) = act(venvs, &out.alive_rows, adv, Role::Adversary, from);
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
    let (a, n) = act(venvs, &out.alive_rows, d.alive, Role::Alive, from);
    out.alive_actions = a;
    out.alive_action = d.alive.drive_action();
    out.inferred_rows += n;
    if let Some(bg) = d.background {
        let (a, n) = act(venvs, &out.background_rows, bg, Role::Background, from);
        out.background_actions = a;
        out.background_action = bg.drive_action();
        out.inferred_rows += n;
    } else {
        out.background_actions =
            out.background_rows.iter().map(|rs| vec![0.0; rs.len() * 2]).collect();
    }
    out
}

/// Steps every batch with the decided driving actions (rows without one keep the default),
/// each turned into its vehicle's command by its role's [`DriveAction`]: an `idm-residual`
/// role's action is added to the IDM driver's action in the state it was decided in.
pub fn apply(venvs: &mut [VecEnv], d: &Decision) {
    for (k, v) in venvs.iter_mut().enumerate() {
        let mut acts = vec![Action::default(); v.alive().len()];
        for (rows, a, kind) in [
            (&d.alive_rows[k], &d.alive_actions[k], d.alive_action),
            (&d.background_rows[k], &d.background_actions[k], d.background_action),
        ] {
            let dim = kind.dim();
            assert_eq!(
                a.len(),
                rows.len() * dim,
                "{} action floats for {} rows of {kind:?} (alive {:?}, background {:?})",
                a.len(),
                rows.len(),
                d.alive_action,
                d.background_action
            );
            for (j, &r) in rows.iter().enumerate() {
                // The IDM driver's action only where the kind adds to it.
                let demo = kind.needs_demo().then(|| v.demo_action(r));
                acts[r] = kind.command(&a[j * dim..(j + 1) * dim], demo);
            }
        }
        v.step(&acts);
    }
}

/// Segments in a demonstrator's warm-up that show what IDM never does. Braking: with
/// probability `brake_prob` per step a driving row starts holding its action's first component
/// (the speed or acceleration residual) at a value drawn from U(-1, -0.2) for 4 to 12 decision
/// steps, so the data shows what braking early buys (and costs). Lane changes (actions with a
/// lateral component, `idm-residual-lateral`): with probability `lane_change_prob` per step a
/// row starts holding its lateral target at -1 or +1 (one lane right or left) for 8 to 20
/// decision steps (2-5 s, enough to move one lane at the default rate). The segments go to the
/// rows the job drives: the `alive` rows, or with [`WarmupSegments::on_background`] the
/// background's (FailMaker's own vehicles). State per row, cleared when the row's episode ends.
pub struct WarmupSegments {
    brake_prob: f32,
    lane_change_prob: f32,
    background: bool,
    /// Per batch, per row: the braking and the lane-change segment.
    brake: Vec<Vec<Held>>,
    lateral: Vec<Vec<Held>>,
}

/// One row's warm-up segment: a value held for a number of steps.
#[derive(Clone, Copy, Debug, Default)]
struct Held {
    left: u32,
    value: f32,
}

impl Held {
    /// Starts a segment with probability `prob` when none runs (`start` draws its length and
    /// value) and returns the value held this step, if any.
    fn step<R: Rng + ?Sized>(
        &mut self,
        prob: f32,
        rng: &mut R,
        start: impl FnOnce(&mut R) -> (u32, f32),
    ) -> Option<f32> {
        if self.left == 0 && prob > 0.0 && rng.random::<f32>() < prob {
            (self.left, self.value) = start(rng);
        }
        (self.left > 0).then(|| {
            self.left -= 1;
            self.value
        })
    }
}

impl WarmupSegments {
    pub fn new(brake_prob: f32, lane_change_prob: f32, venvs: &[VecEnv]) -> Self {
        let rows = || venvs.iter().map(|v| vec![Held::default(); v.alive().len()]).collect();
        Self { brake_prob, lane_change_prob, background: false, brake: rows(), lateral: rows() }
    }

    /// Overlay the background rows instead of the `alive` ones.
    pub fn on_background(mut self) -> Self {
        self.background = true;
        self
    }

    /// Overrides the decided `alive` actions of rows in a segment (call between [`decide`]
    /// and [`apply`]; the recorded action is then the one applied): braking holds the first
    /// action number at -1..-0.2 for 4-12 steps, a lane change the lateral one at +-1 for 8-20.
    pub fn overlay(&mut self, d: &mut Decision, rng: &mut impl Rng) {
        let (all_rows, all_actions, kind) = if self.background {
            (&d.background_rows, &mut d.background_actions, d.background_action)
        } else {
            (&d.alive_rows, &mut d.alive_actions, d.alive_action)
        };
        let dim = kind.dim();
        let lateral = kind == sf_sim::DriveAction::IdmResidualLateral;
        for (k, (rows, actions)) in all_rows.iter().zip(all_actions.iter_mut()).enumerate() {
            for (j, &r) in rows.iter().enumerate() {
                if let Some(v) = self.brake[k][r].step(self.brake_prob, rng, |g| {
                    (g.random_range(4..=12), g.random_range(-1.0..-0.2))
                }) {
                    actions[j * dim] = v;
                }
                if !lateral {
                    continue;
                }
                if let Some(v) = self.lateral[k][r].step(self.lane_change_prob, rng, |g| {
                    (g.random_range(8..=20), if g.random::<bool>() { 1.0 } else { -1.0 })
                }) {
                    actions[j * dim + 1] = v;
                }
            }
        }
    }

    /// Ends the segments of rows whose episode ended in the last step (call after [`apply`]).
    pub fn after_step(&mut self, venvs: &[VecEnv]) {
        for (k, v) in venvs.iter().enumerate() {
            for (r, st) in v.row_steps().iter().enumerate() {
                if st.ended.is_some() {
                    self.brake[k][r] = Held::default();
                    self.lateral[k][r] = Held::default();
                }
            }
        }
    }
}

/// Runs the stored episodes of `v` (`VecEnv::from_episodes`) to their end with `d`, every
/// random draw the episode's own ([`Draws::PerEpisode`]): an episode draws the same at any
/// batch width. `after_step(v, tags)` sees every step's results (`VecEnv::row_steps`, the
/// environments) with the tags of the episodes that took it, per environment (`None`: idle).
/// Returns every episode's `(tag, metrics)` in the order they finished.
pub fn run_episodes(
    v: &mut VecEnv,
    d: &Drivers,
    mut after_step: impl FnMut(&VecEnv, &[Option<u64>]),
) -> Vec<(u64, EpisodeMetrics)> {
    let mut out = Vec::new();
    let venvs = std::slice::from_mut(v);
    while !venvs[0].is_finished() {
        let tags: Vec<Option<u64>> = (0..venvs[0].n_envs()).map(|k| venvs[0].tag(k)).collect();
        let decision = decide_drawing(venvs, d, &mut Draws::PerEpisode);
        apply(venvs, &decision);
        after_step(&venvs[0], &tags);
        out.extend(venvs[0].take_finished_tagged());
    }
    out
}
