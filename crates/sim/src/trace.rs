//! An episode as data a browser draws: the map's geometry once, each agent's role, route and
//! SVO, then every step's vehicles (pose, speed, whether alive, why it ended, reward) and the
//! neighbours the focus agent observed.
//!
//! Owns: [`Trace`] (serde, the viewer page's JSON), [`Trace::new`] at an episode's reset and
//! [`Trace::push`] after each step. Must not: choose actions, run policies or write HTML (the
//! viewer page is `sf_rollout::evaluate::view`'s); it only reads an [`Env`].

use serde::{Deserialize, Serialize};

use crate::env::{Env, Role};
use crate::geom::P2;
use crate::map::Map;
use crate::metrics::EpisodeMetrics;
use crate::obs::Observer;

/// The map as the viewer draws it (metres, world frame).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct MapGeometry {
    pub min: P2,
    pub max: P2,
    /// Lane centre lines and their widths.
    pub lanes: Vec<(f32, Vec<P2>)>,
    /// Road edges (polylines).
    pub edges: Vec<Vec<P2>>,
    /// The scenario's interaction zone (polygon; may be empty).
    pub zone: Vec<P2>,
}

/// One agent of the episode: what does not change while it drives.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct AgentInfo {
    /// Who drives it, as the caller names it (`ego`, `learned flow (macad)`, `IDM`, ...).
    pub role: String,
    /// Whether its outcome is scored (the simulator's learner role).
    pub scored: bool,
    /// Its route's points (metres).
    pub route: Vec<P2>,
}

/// Every agent's state after one step (index = agent).
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct StepState {
    /// `[x_m, y_m, heading_rad, speed_mps]` per agent.
    pub pose: Vec<[f32; 4]>,
    pub alive: Vec<bool>,
    /// Why an agent has ended (`collision`, `off-road`, ..., `destination`), if it has.
    pub ended: Vec<Option<String>>,
    /// Its SVO this step (degrees; CoPO's coordinator may redraw it every step).
    pub svo_deg: Vec<f32>,
    /// The individual reward of the decision step that led here (0 at the reset).
    pub reward: Vec<f32>,
    /// The neighbours the focus agent observed in this state (nearest first).
    pub observed: Vec<u32>,
}

/// One episode, step by step; `steps[0]` is the reset.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Trace {
    pub scenario: String,
    /// Seconds per decision step.
    pub dt_s: f32,
    pub vehicle_length_m: f32,
    pub vehicle_width_m: f32,
    pub map: MapGeometry,
    pub agents: Vec<AgentInfo>,
    /// The agent whose observed neighbours are recorded (the ego in an ego episode).
    pub focus: u32,
    pub steps: Vec<StepState>,
    /// The episode's metrics as the simulator scored it, once it has ended.
    pub metrics: Option<EpisodeMetrics>,
}

impl Trace {
    /// Starts a trace at `env`'s reset state. `role_of(i, role)` names agent `i`'s driver;
    /// `focus` is the agent whose observations are followed, `observer` finds its neighbours as
    /// its observation does.
    pub fn new(
        env: &Env,
        focus: usize,
        role_of: impl Fn(usize, Role) -> String,
        observer: &mut Observer,
    ) -> Self {
        let map: &Map = &env.map;
        let agents = env
            .agents()
            .iter()
            .enumerate()
            .map(|(i, a)| AgentInfo {
                role: role_of(i, a.role),
                scored: a.role == Role::Learner,
                route: map
                    .routes
                    .get(a.route as usize)
                    .map(|r| r.points.clone())
                    .unwrap_or_default(),
            })
            .collect();
        let mut t = Self {
            scenario: map.name.clone(),
            dt_s: env.cfg.dt_s,
            vehicle_length_m: env.cfg.vehicle.length_m,
            vehicle_width_m: env.cfg.vehicle.width_m,
            map: MapGeometry {
                min: map.boundary.min,
                max: map.boundary.max,
                lanes: map.lanes.iter().map(|l| (l.width_m, l.centre.clone())).collect(),
                edges: map.edges.clone(),
                zone: map.zone.clone(),
            },
            agents,
            focus: focus as u32,
            steps: Vec::new(),
            metrics: None,
        };
        t.push(env, observer);
        t
    }

    /// Records `env`'s state (the reset's, then after each step) with the focus agent's
    /// neighbours as `observer` finds them.
    pub fn push(&mut self, env: &Env, observer: &mut Observer) {
        let agents = env.agents();
        let first = self.steps.is_empty();
        let focus = self.focus as usize;
        let observed = if agents.get(focus).is_some_and(|a| a.alive) {
            observer.neighbours(env, focus).into_iter().map(|j| j as u32).collect()
        } else {
            Vec::new()
        };
        self.steps.push(StepState {
            pose: agents
                .iter()
                .map(|a| [a.state.x_m, a.state.y_m, a.state.theta_rad, a.state.speed_mps])
                .collect(),
            alive: agents.iter().map(|a| a.alive).collect(),
            ended: agents.iter().map(|a| a.termination.map(|t| t.as_str().to_string())).collect(),
            svo_deg: agents.iter().map(|a| a.svo_deg).collect(),
            reward: if first {
                vec![0.0; agents.len()]
            } else {
                env.rewards().iter().map(|r| r.individual).collect()
            },
            observed,
        });
    }
}
