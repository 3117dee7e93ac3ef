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

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::case::random_case;
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
}

impl RowStep {
    /// The step ended the agent's episode by a failure or its destination: no bootstrapping
    /// from the next observation. Timeouts are not terminal.
    pub fn terminal(&self) -> bool {
        self.ended.is_some_and(|t| t != Termination::Timeout)
    }
}

struct Slot {
    env: Env,
    observer: Observer,
    rng: ChaCha8Rng,
    episodes: u32,
    finished: Vec<EpisodeMetrics>,
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
}

impl VecEnv {
    pub fn new(map: Arc<Map>, sim: Arc<SimConfig>, cfg: VecEnvConfig) -> Self {
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
                finished: Vec::new(),
            })
            .collect();
        let rows = cfg.n_envs * max_agents;
        let mut v = Self {
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
        };
        let (spec_len, mode, vehicles) = (v.spec.len, v.cfg.mode, v.cfg.vehicles);
        v.slots
            .par_iter_mut()
            .zip(v.obs.par_chunks_mut(max_agents * spec_len))
            .zip(v.alive.par_chunks_mut(max_agents))
            .zip(v.background.par_chunks_mut(max_agents))
            .for_each(|(((s, obs), alive), bg)| {
                s.reset(mode, vehicles);
                s.observe(obs, alive, bg, spec_len);
            });
        v
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

    /// Per row: what the last step did.
    pub fn row_steps(&self) -> &[RowStep] {
        &self.steps
    }

    /// The observation that follows row `r`'s last step: the observation at the end of that
    /// step if the agent's episode ended on it (the bootstrap observation of a timeout; the row
    /// itself is already reset), else its current row.
    pub fn next_observation(&self, r: usize) -> &[f32] {
        let len = self.spec.len;
        let src = if self.steps[r].ended.is_some() { &self.final_obs } else { &self.obs };
        &src[r * len..(r + 1) * len]
    }

    /// Decision steps taken, summed over environments, and learner steps taken.
    pub fn counters(&self) -> (u64, u64) {
        (self.env_steps, self.agent_steps)
    }

    /// Drains the metrics of episodes finished since the last call.
    pub fn take_finished(&mut self) -> Vec<EpisodeMetrics> {
        self.slots.iter_mut().flat_map(|s| s.finished.drain(..)).collect()
    }

    /// Steps every environment; `actions` has one entry per row. Finished episodes are
    /// scored and replaced by fresh random ones before observing.
    pub fn step(&mut self, actions: &[Action]) {
        assert_eq!(actions.len(), self.alive.len(), "one action per observation row");
        let (spec_len, max_agents, mode, vehicles) = (self.spec.len, self.max_agents, self.cfg.mode, self.cfg.vehicles);
        let learners_only = matches!(mode, Mode::Ego { .. });
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
                let n = s.env.len();
                let stepped = s.env.agents().iter().filter(|a| a.alive && a.role == Role::Learner).count() as u64;
                s.env.step(&acts[..n]).expect("a live episode with one action per agent");
                s.record(steps, finals, alive, spec_len);
                if s.env.done() {
                    s.finished.push(EpisodeMetrics::from_outcomes(s.env.outcomes(), learners_only));
                    s.reset(mode, vehicles);
                }
                s.observe(obs, alive, bg, spec_len);
                stepped
            })
            .sum();
        self.env_steps += self.slots.len() as u64;
        self.agent_steps += agent_steps;
    }
}

impl Slot {
    /// Fills per-row step results and final observations of rows that ended.
    fn record(&mut self, steps: &mut [RowStep], finals: &mut [f32], alive: &[f32], spec_len: usize) {
        let mut prepared = false;
        for (i, st) in steps.iter_mut().enumerate() {
            *st = RowStep::default();
            if alive[i] == 0.0 || i >= self.env.len() {
                continue;
            }
            st.stepped = true;
            st.rewards = self.env.rewards()[i];
            if self.env.ended_now()[i] {
                st.ended = self.env.agents()[i].termination;
                if !prepared {
                    self.observer.prepare(&self.env);
                    prepared = true;
                }
                self.observer.write(&self.env, i, &mut finals[i * spec_len..(i + 1) * spec_len]);
            }
        }
    }

    fn reset(&mut self, mode: Mode, vehicles: (u32, u32)) {
        let n = self.rng.random_range(vehicles.0..=vehicles.1) as usize;
        let case = random_case(&self.env.map, &mut self.rng, self.episodes, n);
        self.episodes += 1;
        self.env.reset(&case, mode, None).expect("generated cases are valid for their map");
    }

    fn observe(&mut self, obs: &mut [f32], alive: &mut [f32], bg: &mut [f32], spec_len: usize) {
        self.observer.prepare(&self.env);
        for (i, ((row, live), back)) in obs.chunks_mut(spec_len).zip(alive.iter_mut()).zip(bg.iter_mut()).enumerate() {
            let a = self.env.agents().get(i);
            if a.is_some_and(|a| a.alive && a.role == Role::Learner) {
                self.observer.write(&self.env, i, row);
                *live = 1.0;
                *back = 0.0;
            } else if a.is_some_and(|a| a.alive && a.role == Role::Background && a.controller == Controller::External) {
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
