//! Batched stepping of many environments in parallel (rayon), for rollout workers.
//!
//! Owns: [`VecEnv`]: K environments on one map, one observation batch
//! `[K * max_agents, spec.len]` reused every step (no per-step allocation once warm),
//! random resets from a seeded generator per environment, finished-episode metrics.
//! Must not: choose actions. Environment `k`'s agent `i` is row `k * max_agents + i`;
//! rows of absent or ended agents are zero with `alive = 0`. In `Mode::Ego` with an
//! externally driven background (a frozen learned flow), live background agents' rows are
//! observed too and flagged in [`VecEnv::background`] (their actions come from the caller).
//!
//! Run inside a rayon pool of the wanted size (`ThreadPool::install`); results do not depend
//! on the thread count.

use std::sync::Arc;

use rand::seq::index::sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::case::{random_case, Case, CaseVehicle, SvoGaussian, SVO_RANGE_DEG};
use crate::config::SimConfig;
use crate::env::{Controller, Env, Mode, Rewards, Role, Termination};
use crate::map::Map;
use crate::metrics::EpisodeMetrics;
use crate::obs::{MapSegments, ObsSpec, Observer};
use crate::vehicle::Action;

/// What a [`VecEnv`] runs.
#[derive(Clone, Debug)]
pub struct VecEnvConfig {
    pub n_envs: usize,
    pub mode: Mode,
    /// Vehicles per episode, inclusive range.
    pub vehicles: (u32, u32),
    pub seed: u64,
}

/// What happened to one observation row on the last step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RowStep {
    /// The row held a live learner before the step.
    pub stepped: bool,
    pub rewards: Rewards,
    /// Set when the agent's episode ended on this step.
    pub ended: Option<Termination>,
    /// The episode ended on this step (its learners are done) while this row's agent was still
    /// driving: a cut, not a terminal state (externally driven background rows).
    pub truncated: bool,
    /// The agent's episode ended on this step and counts as a success (see `sf_sim::env`).
    pub success: bool,
}

impl RowStep {
    /// The step ended the agent's episode by a failure or its destination: no bootstrapping
    /// from the next observation. Timeouts are not terminal.
    pub fn terminal(&self) -> bool {
        self.ended.is_some_and(|t| t != Termination::Timeout)
    }
}

/// How random cases are drawn beyond their vehicle count (training resets, validation and
/// generated evaluation cases); the default draws every case as [`random_case`] does.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CaseDraw {
    /// The share of cases in which the IDM driver in agent 0's seat collides.
    pub conflict_share: Option<f32>,
    /// Cases with a slow vehicle ahead of agent 0 in its lane.
    pub slow_leader: Option<SlowLeader>,
}

/// A slow vehicle ahead of the ego in its lane (the ladder's lane-change rung): with
/// probability `share` a case puts agent 0 on a spawn point in the first half of its lane's
/// spawn points and a vehicle capped at `speed_mps` one to three spawn points (7.5-22.5 m)
/// ahead of it on the same lane and route; the case's other vehicles start off that lane.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlowLeader {
    pub share: f32,
    pub speed_mps: f32,
}

impl SlowLeader {
    /// Why these numbers cannot be used (naming the field), if they cannot.
    pub fn check(&self, vehicle_max_speed_mps: f32) -> Result<(), String> {
        if !(self.share.is_finite() && (0.0..=1.0).contains(&self.share)) {
            return Err(format!("share: {} must be in [0, 1]", self.share));
        }
        if !(self.speed_mps.is_finite()
            && self.speed_mps >= 0.0
            && self.speed_mps < vehicle_max_speed_mps)
        {
            return Err(format!("speed_mps: {} must be in [0, {vehicle_max_speed_mps}) m/s (a vehicle slower than the others)", self.speed_mps));
        }
        Ok(())
    }
}

/// `count` cases numbered from 0, drawn one after another from one `rng` (as [`draw_case`]):
/// held-out validation and evaluation sets, reproducible from the rng's seed.
pub fn draw_cases(
    map: &Arc<Map>,
    sim: &Arc<SimConfig>,
    rng: &mut impl Rng,
    count: u32,
    vehicles: (u32, u32),
    draw: CaseDraw,
) -> Vec<Case> {
    (0..count).map(|id| draw_case(map, sim, rng, id, vehicles, draw)).collect()
}

/// A random case with a vehicle count uniform in `vehicles`; with `draw.conflict_share =
/// Some(p)`, with probability p one in which the IDM driver in agent 0's seat ends by a
/// collision (tried up to 200 draws, then the last draw is taken); with `draw.slow_leader`,
/// with its probability a case with a slow vehicle ahead of agent 0 ([`SlowLeader`]).
pub fn draw_case(
    map: &Arc<Map>,
    sim: &Arc<SimConfig>,
    rng: &mut impl Rng,
    id: u32,
    vehicles: (u32, u32),
    draw: CaseDraw,
) -> Case {
    let want_conflict = draw.conflict_share.is_some_and(|p| rng.random::<f32>() < p);
    let n = rng.random_range(vehicles.0..=vehicles.1) as usize;
    if let Some(slow) = draw.slow_leader {
        if rng.random::<f32>() < slow.share {
            if let Some(case) = slow_leader_case(map, rng, id, n, slow.speed_mps) {
                return case;
            }
        }
    }
    let mut case = random_case(map, rng, id, n);
    if want_conflict {
        for _ in 0..200 {
            if idm_ego_collides(map, sim, &case) {
                break;
            }
            let n = rng.random_range(vehicles.0..=vehicles.1) as usize;
            case = random_case(map, rng, id, n);
        }
    }
    case
}

/// Spawn points that start the same lane as spawn `k` (spawn points of one first lane share
/// their route list), in order along it.
fn same_lane(map: &Map, k: usize) -> Vec<usize> {
    let mut lane: Vec<usize> =
        (0..map.spawns.len()).filter(|&j| map.spawns[j].routes == map.spawns[k].routes).collect();
    lane.sort_by(|&a, &b| map.spawns[a].s_m.total_cmp(&map.spawns[b].s_m));
    lane
}

/// A case of `n` vehicles (at least 2) with a slow leader ahead of agent 0 ([`SlowLeader`]);
/// `None` if the map has no lane with room for one.
fn slow_leader_case(
    map: &Map,
    rng: &mut impl Rng,
    id: u32,
    n: usize,
    speed_mps: f32,
) -> Option<Case> {
    let starts: Vec<(usize, Vec<usize>)> = (0..map.spawns.len())
        .filter_map(|k| {
            let lane = same_lane(map, k);
            let at = lane.iter().position(|&j| j == k)?;
            let ahead: Vec<usize> = lane[at + 1..].iter().copied().take(3).collect();
            (2 * at < lane.len() && !ahead.is_empty()).then_some((k, ahead))
        })
        .collect();
    if starts.is_empty() {
        return None;
    }
    let (ego, ahead) = &starts[rng.random_range(0..starts.len())];
    let lead = ahead[rng.random_range(0..ahead.len())];
    let routes = &map.spawns[*ego].routes;
    let route = routes[rng.random_range(0..routes.len())];
    let mut vehicles = vec![
        CaseVehicle {
            spawn: *ego as u32,
            route,
            svo_deg: rng.random_range(SVO_RANGE_DEG.0..=SVO_RANGE_DEG.1),
            max_speed_mps: None,
        },
        CaseVehicle {
            spawn: lead as u32,
            route,
            svo_deg: rng.random_range(SVO_RANGE_DEG.0..=SVO_RANGE_DEG.1),
            max_speed_mps: Some(speed_mps),
        },
    ];
    let lane = same_lane(map, *ego);
    let others: Vec<usize> = (0..map.spawns.len()).filter(|j| !lane.contains(j)).collect();
    let k = n.max(2).saturating_sub(2).min(others.len());
    for j in sample(rng, others.len(), k) {
        let sp = &map.spawns[others[j]];
        let route = sp.routes[rng.random_range(0..sp.routes.len())];
        vehicles.push(CaseVehicle {
            spawn: others[j] as u32,
            route,
            svo_deg: rng.random_range(SVO_RANGE_DEG.0..=SVO_RANGE_DEG.1),
            max_speed_mps: None,
        });
    }
    Some(Case { id, vehicles })
}

/// Whether the IDM driver in agent 0's seat (every vehicle IDM) ends its episode of `case` by
/// a collision.
pub fn idm_ego_collides(map: &Arc<Map>, sim: &Arc<SimConfig>, case: &Case) -> bool {
    let mut e = Env::new(Arc::clone(map), Arc::clone(sim));
    if e.reset(case, Mode::AllIdm, None).is_err() {
        return false;
    }
    let idle = vec![Action::default(); e.len()];
    while !e.done() && e.agents()[0].alive {
        if e.step(&idle).is_err() {
            return false;
        }
    }
    e.agents()[0].termination == Some(Termination::Collision)
}

/// Stored episodes that [`VecEnv::from_episodes`] refuses.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum VecEnvError {
    /// A case does not fit the map (`field` inside the case, as [`Case::check`] names it).
    #[error("case {case}: {field}: {reason}")]
    Case { case: u32, field: String, reason: String },
}

/// One stored episode to run (evaluation): a case, optionally truncated to `vehicles`, with
/// every agent's SVO set to `svo_deg` if given; `tag` comes back with its metrics.
#[derive(Clone, Debug)]
pub struct EpisodeSpec {
    pub case: Case,
    pub vehicles: Option<usize>,
    pub svo_deg: Option<f32>,
    pub tag: u64,
}

struct Slot {
    env: Env,
    observer: Observer,
    rng: ChaCha8Rng,
    episodes: u32,
    /// Tag of the running episode (a counter for random resets).
    tag: u64,
    /// Queue mode: no episode left for this slot; its rows are zero.
    idle: bool,
    finished: Vec<(u64, EpisodeMetrics)>,
}

/// K environments stepped together.
pub struct VecEnv {
    cfg: VecEnvConfig,
    slots: Vec<Slot>,
    pub spec: ObsSpec,
    pub max_agents: usize,
    obs: Vec<f32>,
    alive: Vec<f32>,
    /// 1 where the row holds a live externally driven background agent's observation.
    background: Vec<f32>,
    /// Per row, the last step's outcome (see [`RowStep`]) and the final observation of rows
    /// that ended on it (before any reset).
    steps: Vec<RowStep>,
    final_obs: Vec<f32>,
    env_steps: u64,
    agent_steps: u64,
    /// Stored episodes still to run (evaluation); `None`: endless random resets (training).
    queue: Option<std::collections::VecDeque<EpisodeSpec>>,
    /// CoPO Stage 2: every flow-driven agent's SVO is redrawn from this at every reset and
    /// after every step (`None`: SVOs stay as the case gives them).
    svo_gaussian: Option<SvoGaussian>,
    /// [`VecEnv::with_conflicts`], [`VecEnv::with_slow_leader`].
    draw: CaseDraw,
}

impl VecEnv {
    /// Runs the given stored episodes, `n_envs` at a time, each exactly once, in order: a slot
    /// that finishes takes the next one (slots in index order, so results do not depend on
    /// thread timing). Rows of slots with nothing left stay zero; [`VecEnv::is_finished`] tells
    /// when all are done and [`VecEnv::take_finished_tagged`] returns their metrics by tag.
    pub fn from_episodes(
        map: Arc<Map>,
        sim: Arc<SimConfig>,
        mode: Mode,
        n_envs: usize,
        episodes: Vec<EpisodeSpec>,
    ) -> Result<Self, VecEnvError> {
        for e in &episodes {
            e.case.check(&map).map_err(|(field, reason)| VecEnvError::Case {
                case: e.case.id,
                field,
                reason,
            })?;
        }
        let most = episodes
            .iter()
            .map(|e| e.vehicles.unwrap_or(usize::MAX).min(e.case.vehicles.len()))
            .max()
            .unwrap_or(1);
        let cfg = VecEnvConfig {
            n_envs: n_envs.max(1),
            mode,
            vehicles: (1, most.max(1) as u32),
            seed: 0,
        };
        let mut v = Self::build(map, sim, cfg);
        v.queue = Some(episodes.into());
        for s in &mut v.slots {
            s.idle = true;
        }
        v.refill();
        Ok(v)
    }

    /// Queue mode: every stored episode has run.
    pub fn is_finished(&self) -> bool {
        self.queue.as_ref().is_some_and(|q| q.is_empty()) && self.slots.iter().all(|s| s.idle)
    }

    /// Drains `(tag, metrics)` of episodes finished since the last call.
    pub fn take_finished_tagged(&mut self) -> Vec<(u64, EpisodeMetrics)> {
        self.slots.iter_mut().flat_map(|s| s.finished.drain(..)).collect()
    }

    /// Queue mode: idle slots start the next stored episodes, in slot order.
    fn refill(&mut self) {
        let Some(q) = self.queue.as_mut() else { return };
        let (len, per, mode) = (self.spec.len, self.max_agents, self.cfg.mode);
        for (k, s) in self.slots.iter_mut().enumerate().filter(|(_, s)| s.idle) {
            let (obs, alive, bg) = (
                &mut self.obs[k * per * len..(k + 1) * per * len],
                &mut self.alive[k * per..(k + 1) * per],
                &mut self.background[k * per..(k + 1) * per],
            );
            match q.pop_front() {
                Some(ep) => {
                    s.env
                        .reset(&ep.case, mode, ep.vehicles)
                        .expect("stored cases were checked against the map");
                    if let Some(svo) = ep.svo_deg {
                        for i in 0..s.env.len() {
                            s.env.set_svo(i, svo);
                        }
                    }
                    // A stored episode's random draws depend on its tag, not on its slot.
                    s.rng = ChaCha8Rng::seed_from_u64(
                        ep.tag.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x5356_4f47,
                    );
                    if ep.svo_deg.is_none() {
                        s.redraw_svos(self.svo_gaussian, mode);
                    }
                    s.tag = ep.tag;
                    s.idle = false;
                    s.observe(obs, alive, bg, len);
                }
                None => {
                    obs.fill(0.0);
                    alive.fill(0.0);
                    bg.fill(0.0);
                }
            }
        }
    }

    pub fn new(map: Arc<Map>, sim: Arc<SimConfig>, cfg: VecEnvConfig) -> Self {
        let mut v = Self::build(map, sim, cfg);
        let (spec_len, mode, vehicles, max_agents) =
            (v.spec.len, v.cfg.mode, v.cfg.vehicles, v.max_agents);
        v.slots
            .par_iter_mut()
            .zip(v.obs.par_chunks_mut(max_agents * spec_len))
            .zip(v.alive.par_chunks_mut(max_agents))
            .zip(v.background.par_chunks_mut(max_agents))
            .for_each(|(((s, obs), alive), bg)| {
                s.reset(mode, vehicles, CaseDraw::default());
                s.observe(obs, alive, bg, spec_len);
            });
        v
    }

    /// Random resets (from now on, and of every running episode now) draw, with probability
    /// `share`, only cases in which the IDM driver in agent 0's seat collides ([`draw_case`]):
    /// a training distribution rich in the conflicts IDM does not yield in.
    pub fn with_conflicts(mut self, share: f32) -> Self {
        self.draw.conflict_share = Some(share);
        self.redraw()
    }

    /// Random resets (from now on, and of every running episode now) put a slow vehicle ahead
    /// of agent 0 in `slow.share` of the cases ([`SlowLeader`]).
    pub fn with_slow_leader(mut self, slow: SlowLeader) -> Self {
        self.draw.slow_leader = Some(slow);
        self.redraw()
    }

    fn redraw(mut self) -> Self {
        let (mode, vehicles, draw) = (self.cfg.mode, self.cfg.vehicles, self.draw);
        self.redo_live_slots(|s| s.reset(mode, vehicles, draw));
        self
    }

    /// Runs `f` on every slot with an episode, then observes it again.
    fn redo_live_slots(&mut self, f: impl Fn(&mut Slot) + Sync + Send) {
        let (spec_len, max_agents) = (self.spec.len, self.max_agents);
        self.slots
            .par_iter_mut()
            .zip(self.obs.par_chunks_mut(max_agents * spec_len))
            .zip(self.alive.par_chunks_mut(max_agents))
            .zip(self.background.par_chunks_mut(max_agents))
            .filter(|(((s, _), _), _)| !s.idle)
            .for_each(|(((s, obs), alive), bg)| {
                f(s);
                s.observe(obs, alive, bg, spec_len);
            });
    }

    fn build(map: Arc<Map>, sim: Arc<SimConfig>, cfg: VecEnvConfig) -> Self {
        let base = Observer::new(&map, &sim);
        let segments: Arc<MapSegments> = Arc::clone(&base.segments);
        let spec = base.spec.clone();
        let max_agents = (cfg.vehicles.1 as usize).min(map.spawns.len()).max(1);
        let slots = (0..cfg.n_envs)
            .map(|k| Slot {
                env: Env::new(Arc::clone(&map), Arc::clone(&sim)),
                observer: Observer::with_segments(Arc::clone(&segments), &sim),
                rng: ChaCha8Rng::seed_from_u64(cfg.seed.wrapping_add(k as u64 * 0x9E37_79B9)),
                episodes: 0,
                tag: 0,
                idle: false,
                finished: Vec::new(),
            })
            .collect();
        let rows = cfg.n_envs * max_agents;
        Self {
            obs: vec![0.0; rows * spec.len],
            alive: vec![0.0; rows],
            background: vec![0.0; rows],
            steps: vec![RowStep::default(); rows],
            final_obs: vec![0.0; rows * spec.len],
            spec,
            max_agents,
            cfg,
            slots,
            env_steps: 0,
            agent_steps: 0,
            queue: None,
            svo_gaussian: None,
            draw: CaseDraw::default(),
        }
    }

    /// Observation rows, `[n_envs * max_agents, spec.len]` flattened.
    pub fn observations(&self) -> &[f32] {
        &self.obs
    }

    /// 1 where the row holds a live learner's observation.
    pub fn alive(&self) -> &[f32] {
        &self.alive
    }

    /// 1 where the row holds a live externally driven background agent's observation
    /// (`Mode::Ego { background: Controller::External }`; all zero otherwise).
    pub fn background(&self) -> &[f32] {
        &self.background
    }

    pub fn n_envs(&self) -> usize {
        self.slots.len()
    }

    pub fn env(&self, k: usize) -> &Env {
        &self.slots[k].env
    }

    /// The tag of environment `k`'s running stored episode (`None` when idle).
    pub fn tag(&self, k: usize) -> Option<u64> {
        self.slots.get(k).filter(|s| !s.idle).map(|s| s.tag)
    }

    /// CoPO Stage 2: from now on, every agent the flow drives (all agents, or every
    /// background agent in `Mode::Ego`) gets an SVO drawn from `g` at every reset and after
    /// every step, before it observes; the running episodes are redrawn and re-observed at
    /// once. `None` keeps the cases' SVOs. Draws come from each environment's own generator.
    pub fn set_svo_gaussian(&mut self, g: Option<SvoGaussian>) {
        self.svo_gaussian = g;
        let mode = self.cfg.mode;
        self.redo_live_slots(|s| s.redraw_svos(g, mode));
    }

    /// Tells background agents of environment `k` within the observation radius of the ego
    /// (agent 0) that the ego's SVO is `svo_deg[k]` (the adversary's message; `None`: the
    /// genuine one), everyone else the genuine SVO, and rewrites the externally driven
    /// background rows so their observations carry it. Agents' own SVOs and what they see of
    /// each other are unchanged.
    pub fn communicate_ego_svo(&mut self, svo_deg: &[Option<f32>]) {
        assert_eq!(svo_deg.len(), self.slots.len(), "one message per environment");
        let (spec_len, max_agents) = (self.spec.len, self.max_agents);
        self.slots
            .par_iter_mut()
            .zip(self.obs.par_chunks_mut(max_agents * spec_len))
            .zip(self.background.par_chunks(max_agents))
            .zip(svo_deg.par_iter())
            .for_each(|(((s, obs), bg), &msg)| {
                let env = &mut s.env;
                let Some(ego) = env.agents().first().filter(|a| a.alive).map(|a| a.state.pos())
                else {
                    return;
                };
                let r2 = env.cfg.obs.radius_m * env.cfg.obs.radius_m;
                for i in 1..env.len() {
                    let near = crate::geom::dist2(env.agents()[i].state.pos(), ego) <= r2;
                    env.set_seen_ego_svo(i, msg.filter(|_| near));
                }
                s.observer.prepare(&s.env);
                for (i, row) in
                    obs.chunks_mut(spec_len).enumerate().filter(|&(i, _)| bg.get(i) == Some(&1.0))
                {
                    s.observer.write(&s.env, i, row);
                }
            });
    }

    /// The IDM demonstrator's action ([`Env::demo_action`]) of row `r`'s agent, normalised.
    pub fn demo_action(&self, r: usize) -> Action {
        self.slots[r / self.max_agents].env.demo_action(r % self.max_agents)
    }

    /// Row `r`'s agent's `idm-residual-lateral` action under MOBIL ([`crate::mobil::action`]).
    pub fn mobil_action(&self, r: usize, p: &crate::mobil::MobilParams) -> [f32; 2] {
        crate::mobil::action(&self.slots[r / self.max_agents].env, r % self.max_agents, p)
    }

    /// Per row: what the last step did.
    pub fn row_steps(&self) -> &[RowStep] {
        &self.steps
    }

    /// The observation that follows row `r`'s last step: the observation at the end of that
    /// step if the agent's episode ended on it (the bootstrap observation of a timeout; the row
    /// itself is already reset), else its current row.
    pub fn next_observation(&self, r: usize) -> &[f32] {
        let len = self.spec.len;
        let src = if self.steps[r].ended.is_some() || self.steps[r].truncated {
            &self.final_obs
        } else {
            &self.obs
        };
        &src[r * len..(r + 1) * len]
    }

    /// Decision steps taken, summed over environments, and learner steps taken.
    pub fn counters(&self) -> (u64, u64) {
        (self.env_steps, self.agent_steps)
    }

    /// Drains the metrics of episodes finished since the last call.
    pub fn take_finished(&mut self) -> Vec<EpisodeMetrics> {
        self.slots.iter_mut().flat_map(|s| s.finished.drain(..).map(|(_, m)| m)).collect()
    }

    /// Steps every environment; `actions` has one entry per row. Finished episodes are
    /// scored and replaced by fresh random ones before observing.
    pub fn step(&mut self, actions: &[Action]) {
        assert_eq!(actions.len(), self.alive.len(), "one action per observation row");
        let (spec_len, max_agents, mode, vehicles) =
            (self.spec.len, self.max_agents, self.cfg.mode, self.cfg.vehicles);
        let learners_only = matches!(mode, Mode::Ego { .. });
        let queued = self.queue.is_some();
        let svo_gaussian = self.svo_gaussian;
        let draw = self.draw;
        let agent_steps: u64 = self
            .slots
            .par_iter_mut()
            .zip(self.obs.par_chunks_mut(max_agents * spec_len))
            .zip(self.alive.par_chunks_mut(max_agents))
            .zip(self.background.par_chunks_mut(max_agents))
            .zip(actions.par_chunks(max_agents))
            .zip(self.steps.par_chunks_mut(max_agents))
            .zip(self.final_obs.par_chunks_mut(max_agents * spec_len))
            .map(|((((((s, obs), alive), bg), acts), steps), finals)| {
                if s.idle {
                    steps.fill(RowStep::default());
                    return 0;
                }
                let n = s.env.len();
                let stepped =
                    s.env.agents().iter().filter(|a| a.alive && a.role == Role::Learner).count()
                        as u64;
                s.env.step(&acts[..n]).expect("a live episode with one action per agent");
                s.record(steps, finals, alive, bg, spec_len);
                if s.env.done() {
                    s.finished.push((
                        s.tag,
                        // Stored episodes (evaluation) say whether a timeout was walled in;
                        // training's endless resets skip the corridor test.
                        EpisodeMetrics::from_outcomes(s.env.outcomes_judged(queued), learners_only),
                    ));
                    if queued {
                        s.idle = true;
                        return stepped;
                    }
                    s.reset(mode, vehicles, draw);
                }
                s.redraw_svos(svo_gaussian, mode);
                s.observe(obs, alive, bg, spec_len);
                stepped
            })
            .sum();
        self.env_steps += self.slots.len() as u64;
        self.agent_steps += agent_steps;
        self.refill();
    }
}

impl Slot {
    /// Draws a new SVO from `g` for every agent the flow drives (not the ego of `Mode::Ego`).
    fn redraw_svos(&mut self, g: Option<SvoGaussian>, mode: Mode) {
        let Some(g) = g else { return };
        let first = usize::from(matches!(mode, Mode::Ego { .. }));
        for i in first..self.env.len() {
            let svo = g.sample(&mut self.rng);
            self.env.set_svo(i, svo);
        }
    }

    /// Fills per-row step results (learner and externally driven background rows) and the
    /// final observations of rows that ended, or were cut by the episode's end.
    fn record(
        &mut self,
        steps: &mut [RowStep],
        finals: &mut [f32],
        alive: &[f32],
        bg: &[f32],
        spec_len: usize,
    ) {
        let mut prepared = false;
        let done = self.env.done();
        for (i, st) in steps.iter_mut().enumerate() {
            *st = RowStep::default();
            if (alive[i] == 0.0 && bg[i] == 0.0) || i >= self.env.len() {
                continue;
            }
            st.stepped = true;
            st.rewards = self.env.rewards()[i];
            let ended = self.env.ended_now()[i];
            st.truncated = done && !ended;
            if ended || st.truncated {
                st.ended = if ended { self.env.agents()[i].termination } else { None };
                st.success = ended && self.env.agents()[i].outcome().success;
                if !prepared {
                    self.observer.prepare(&self.env);
                    prepared = true;
                }
                self.observer.write(&self.env, i, &mut finals[i * spec_len..(i + 1) * spec_len]);
            }
        }
    }

    fn reset(&mut self, mode: Mode, vehicles: (u32, u32), draw: CaseDraw) {
        let case =
            draw_case(&self.env.map, &self.env.cfg, &mut self.rng, self.episodes, vehicles, draw);
        self.tag = self.episodes as u64;
        self.episodes += 1;
        self.env.reset(&case, mode, None).expect("generated cases are valid for their map");
    }

    fn observe(&mut self, obs: &mut [f32], alive: &mut [f32], bg: &mut [f32], spec_len: usize) {
        self.observer.prepare(&self.env);
        for (i, ((row, live), back)) in
            obs.chunks_mut(spec_len).zip(alive.iter_mut()).zip(bg.iter_mut()).enumerate()
        {
            let a = self.env.agents().get(i);
            if a.is_some_and(|a| a.alive && a.role == Role::Learner) {
                self.observer.write(&self.env, i, row);
                *live = 1.0;
                *back = 0.0;
            } else if a.is_some_and(|a| {
                a.alive && a.role == Role::Background && a.controller == Controller::External
            }) {
                self.observer.write(&self.env, i, row);
                *live = 0.0;
                *back = 1.0;
            } else if *live != 0.0 || *back != 0.0 {
                row.fill(0.0);
                *live = 0.0;
                *back = 0.0;
            }
        }
    }
}
