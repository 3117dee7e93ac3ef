//! One simulated episode: vehicles on a map, stepped at the decision rate.
//!
//! Owns: [`Env`] (reset from a [`Case`], [`Env::step`] with sub-steps, collisions through
//! parry2d, the failure and success rules, rewards with SVO composition, per-agent outcomes).
//! Must not: allocate in `step` once warmed up, iterate over hash maps, or use any randomness
//! (a case plus the actions fully determine the trajectory). Observations live in `obs`.
//!
//! Agent indices are stable for an episode: agent `i` is `case.vehicles[i]`, and agent 0 is
//! the ego in ego mode. Terminated agents stay in the list (`alive == false`) but are removed
//! from the world: they neither collide nor are observed.

use std::sync::Arc;

use parry2d::math::{Pose, Vector};
use parry2d::query::details::{intersection_test_cuboid_cuboid, intersection_test_cuboid_segment};
use parry2d::shape::{Cuboid, Segment};
use serde::{Deserialize, Serialize};

use crate::case::Case;
use crate::config::SimConfig;
use crate::geom::{self, Frame, P2};
use crate::idm::{idm_accel, pure_pursuit_steer};
use crate::map::Map;
use crate::vehicle::{Action, Pid, VehicleParams, VehicleState};

/// Who computes a vehicle's controls.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Controller {
    /// Actions come from the caller (a learned or scripted policy).
    External,
    /// The rule-based IDM driver with a pure-pursuit path follower.
    Idm,
}

/// Whether an agent's episode end matters for the episode's end.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Role {
    Learner,
    Background,
}

/// How the episode's vehicles are controlled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Every vehicle is a learner driven by external actions.
    MultiAgent,
    /// Agent 0 is the (external) learner; the others are background with this controller.
    Ego { background: Controller },
    /// Every vehicle is driven by IDM and scored (the all-IDM flow).
    AllIdm,
}

/// Why an agent's episode ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Termination {
    Collision,
    OffRoad,
    OffRoute,
    WrongLane,
    Destination,
    Timeout,
}

impl Termination {
    /// The name in files and Python (`collision`, `off-road`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Collision => "collision",
            Self::OffRoad => "off-road",
            Self::OffRoute => "off-route",
            Self::WrongLane => "wrong-lane",
            Self::Destination => "destination",
            Self::Timeout => "timeout",
        }
    }

    pub fn is_failure(self) -> bool {
        matches!(self, Self::Collision | Self::OffRoad | Self::OffRoute | Self::WrongLane)
    }
}

/// The rewards of one agent for one decision step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rewards {
    /// `R_i = w1 (2 v / v_max - 1) - w2 * failure`.
    pub individual: f32,
    /// `cos(c) R_i + sin(c) mean(R_j)` over other external agents within the radius.
    pub composed: f32,
    /// FailMaker background: `cos(c) R_i' + sin(c) R_ego` with no collision penalty in `R_i'`.
    pub failmaker: f32,
}

/// The outcome of one agent's episode.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AgentOutcome {
    pub role: Role,
    pub success: bool,
    pub termination: Option<Termination>,
    /// Mean over its steps of clip(v / v_max, 0, 1).
    pub speed_ratio: f32,
    pub steps: u32,
    /// The vehicle's centre was more than half its route's lane width off the route at some
    /// decision step: it changed lanes (or left the road).
    #[serde(default)]
    pub left_lane: bool,
    /// It timed out with standing vehicles closing the road ahead of it
    /// ([`Env::road_closed_ahead`]); set by [`Env::outcomes`], false from [`Agent::outcome`].
    #[serde(default)]
    pub road_closed: bool,
}

/// One vehicle's full state.
#[derive(Clone, Debug)]
pub struct Agent {
    pub state: VehicleState,
    pub route: u32,
    /// Arc length of the projection onto the route.
    pub s_m: f32,
    /// Route segment holding the projection.
    pub seg: usize,
    pub lateral_m: f32,
    pub svo_deg: f32,
    pub controller: Controller,
    pub role: Role,
    pub alive: bool,
    pub termination: Option<Termination>,
    pub zone_entered: bool,
    pub zone_passed: bool,
    pub steps: u32,
    speed_ratio_sum: f32,
    pid: Pid,
    ref_speed_mps: f32,
    steer_rad: f32,
    /// External agents driving as IDM with this residual on its acceleration (`Action::idm_accel`).
    idm_accel_residual: Option<f32>,
    /// `Action::lateral`: the offset (m, left positive) the followed path moves towards, and
    /// where it is now (rate-limited, updated every sub-step). Zero for everyone else.
    lateral_target_m: f32,
    lateral_offset_m: f32,
    /// Whether |lateral_m| has exceeded half its route's lane width at a decision step: it left
    /// its lane ([`AgentOutcome::left_lane`]).
    left_lane: bool,
    /// The case's speed cap for this vehicle (`CaseVehicle::max_speed_mps`), else the vehicle's.
    max_speed_mps: f32,
    collided: bool,
    /// IDM: bumper gap and leader speed along the route, updated every sub-step.
    leader: Option<(f32, f32)>,
    /// History ring: `[x, y, theta, v]` per decision step; `hist_head` is the newest.
    hist: Vec<[f32; 4]>,
    hist_head: usize,
}

impl Agent {
    /// History frame `k` steps back (0 = current), world coordinates `[x, y, theta, v]`.
    #[inline]
    pub fn history(&self, k: usize) -> [f32; 4] {
        let h = self.hist.len();
        self.hist[(self.hist_head + h - k.min(h - 1)) % h]
    }

    fn push_history(&mut self) {
        self.hist_head = (self.hist_head + 1) % self.hist.len();
        let s = &self.state;
        self.hist[self.hist_head] = [s.x_m, s.y_m, s.theta_rad, s.speed_mps];
    }

    /// Where the `idm-residual-lateral` action has its followed path go, m left of the route
    /// (its target), and where the path is now; zero for every other driver.
    pub fn lateral_target_m(&self) -> f32 {
        self.lateral_target_m
    }

    pub fn lateral_offset_m(&self) -> f32 {
        self.lateral_offset_m
    }

    pub fn frame(&self) -> Frame {
        Frame::new(self.state.pos(), self.state.theta_rad)
    }

    pub fn outcome(&self) -> AgentOutcome {
        AgentOutcome {
            role: self.role,
            success: self.zone_passed && !self.termination.is_some_and(Termination::is_failure),
            termination: self.termination,
            speed_ratio: if self.steps > 0 {
                self.speed_ratio_sum / self.steps as f32
            } else {
                0.0
            },
            steps: self.steps,
            left_lane: self.left_lane,
            road_closed: false,
        }
    }
}

/// Errors from misuse of the environment API.
#[derive(Debug, thiserror::Error)]
pub enum EnvError {
    #[error("case {case}: {field}: {reason}")]
    BadCase { case: u32, field: String, reason: String },
    #[error("step called on a finished episode; call reset first")]
    Finished,
    #[error("step got {got} actions for {want} agents")]
    ActionCount { got: usize, want: usize },
}

/// A single episode of one scenario.
#[derive(Clone)]
pub struct Env {
    pub map: Arc<Map>,
    pub cfg: Arc<SimConfig>,
    agents: Vec<Agent>,
    step_idx: u32,
    done: bool,
    rewards: Vec<Rewards>,
    ended_now: Vec<bool>,
    /// Per observer: the ego's SVO it is told (Stage 2 adversary), in degrees.
    seen_ego_svo: Vec<Option<f32>>,
    box_full: Cuboid,
    box_road: Cuboid,
    poses: Vec<Pose>,
    alive_before: Vec<bool>,
    /// Scratch for the composed reward's nearest neighbours: (squared distance, index).
    reward_cand: Vec<(f32, u32)>,
}

/// The IDM driver's steer for agent `a`: pure pursuit toward the point of its route
/// `max(1.5 s x speed, 4 m)` ahead, moved `a.lateral_offset_m` to the left of the route there
/// (zero but for the `idm-residual-lateral` action). The IDM controller recomputes it every
/// sub-step; the demonstrator ([`Env::demo_action`]) holds it for a decision step.
fn route_steer_rad(map: &Map, vp: &VehicleParams, a: &Agent) -> f32 {
    let route = &map.routes[a.route as usize];
    let look = (1.5 * a.state.speed_mps).max(4.0);
    let (mut target, heading) = geom::point_at(&route.points, &route.cum_m, a.s_m + look);
    if a.lateral_offset_m != 0.0 {
        let (s, c) = heading.sin_cos();
        target = [target[0] - s * a.lateral_offset_m, target[1] + c * a.lateral_offset_m];
    }
    pure_pursuit_steer(vp.wheelbase_m, a.frame().to_local(target))
}

/// `offset_m` moved towards `target_m` by at most `rate_mps * dt_s`.
pub fn lateral_step(offset_m: f32, target_m: f32, rate_mps: f32, dt_s: f32) -> f32 {
    let max = rate_mps * dt_s;
    offset_m + (target_m - offset_m).clamp(-max, max)
}

/// IDM's acceleration `a_idm` moved by a residual `r` in [-1, 1] towards full braking (r = -1:
/// `-max`) or full acceleration (r = +1: `+max`), linearly on each side; `None` or 0 is IDM
/// exactly. (A plain offset `a_idm + 5 r` could not brake at full speed on a free road, where
/// IDM still commands ~4.7 m/s^2 towards its desired 12 m/s.)
pub fn residual_accel(a_idm: f32, r: Option<f32>, max_mps2: f32) -> f32 {
    match r {
        None => a_idm,
        Some(r) if r < 0.0 => a_idm + r * (a_idm + max_mps2),
        Some(r) => a_idm + r * (max_mps2 - a_idm),
    }
}

impl Env {
    pub fn new(map: Arc<Map>, cfg: Arc<SimConfig>) -> Self {
        let v = &cfg.vehicle;
        let half = Vector::new(v.length_m / 2.0, v.width_m / 2.0);
        Self {
            box_full: Cuboid::new(half),
            box_road: Cuboid::new(half * cfg.off_road_box_scale),
            map,
            cfg,
            agents: Vec::new(),
            step_idx: 0,
            done: true,
            rewards: Vec::new(),
            ended_now: Vec::new(),
            seen_ego_svo: Vec::new(),
            poses: Vec::new(),
            alive_before: Vec::new(),
            reward_cand: Vec::new(),
        }
    }

    /// Starts an episode from a case; `max_vehicles` truncates it (density sweeps use fewer).
    pub fn reset(
        &mut self,
        case: &Case,
        mode: Mode,
        max_vehicles: Option<usize>,
    ) -> Result<(), EnvError> {
        case.check(&self.map).map_err(|(field, reason)| EnvError::BadCase {
            case: case.id,
            field,
            reason,
        })?;
        let n = max_vehicles.map_or(case.vehicles.len(), |m| m.min(case.vehicles.len()));
        let h = self.cfg.obs.history;
        let [svo_lo, svo_hi] = self.cfg.svo_range_deg;
        self.agents.clear();
        for (i, cv) in case.vehicles[..n].iter().enumerate() {
            let sp = &self.map.spawns[cv.spawn as usize];
            let route = &self.map.routes[cv.route as usize];
            let pr =
                geom::project_range(&route.points, &route.cum_m, sp.pos, 0, route.points.len());
            let (controller, role) = match mode {
                Mode::MultiAgent => (Controller::External, Role::Learner),
                Mode::AllIdm => (Controller::Idm, Role::Learner),
                Mode::Ego { .. } if i == 0 => (Controller::External, Role::Learner),
                Mode::Ego { background } => (background, Role::Background),
            };
            let state = VehicleState {
                x_m: sp.pos[0],
                y_m: sp.pos[1],
                theta_rad: sp.heading_rad,
                speed_mps: 0.0,
            };
            let mut a = Agent {
                state,
                route: cv.route,
                s_m: pr.s_m,
                seg: pr.seg,
                lateral_m: pr.lateral_m,
                svo_deg: svo_lo + (svo_hi - svo_lo) * cv.svo_deg / 90.0,
                controller,
                role,
                alive: true,
                termination: None,
                zone_entered: false,
                zone_passed: false,
                steps: 0,
                speed_ratio_sum: 0.0,
                pid: Pid::default(),
                ref_speed_mps: 0.0,
                steer_rad: 0.0,
                idm_accel_residual: None,
                lateral_target_m: 0.0,
                lateral_offset_m: 0.0,
                left_lane: false,
                max_speed_mps: cv.max_speed_mps.map_or(self.cfg.vehicle.max_speed_mps, |v| {
                    v.min(self.cfg.vehicle.max_speed_mps)
                }),
                collided: false,
                leader: None,
                hist: vec![[state.x_m, state.y_m, state.theta_rad, 0.0]; h],
                hist_head: 0,
            };
            a.zone_entered = geom::point_in_polygon(state.pos(), &self.map.zone);
            self.agents.push(a);
        }
        self.step_idx = 0;
        self.done = false;
        self.rewards.clear();
        self.rewards.resize(n, Rewards::default());
        self.ended_now.clear();
        self.ended_now.resize(n, false);
        self.seen_ego_svo.clear();
        self.seen_ego_svo.resize(n, None);
        Ok(())
    }

    pub fn agents(&self) -> &[Agent] {
        &self.agents
    }

    pub fn len(&self) -> usize {
        self.agents.len()
    }

    pub fn is_empty(&self) -> bool {
        self.agents.is_empty()
    }

    pub fn done(&self) -> bool {
        self.done
    }

    /// Decision steps taken in this episode.
    pub fn step_index(&self) -> u32 {
        self.step_idx
    }

    /// Rewards of the last step, by agent.
    pub fn rewards(&self) -> &[Rewards] {
        &self.rewards
    }

    /// Which agents ended on the last step.
    pub fn ended_now(&self) -> &[bool] {
        &self.ended_now
    }

    /// Sets the SVO of the ego (agent 0) that `observer` is told, or `None` for the genuine one.
    pub fn set_seen_ego_svo(&mut self, observer: usize, svo_deg: Option<f32>) {
        if let Some(s) = self.seen_ego_svo.get_mut(observer) {
            *s = svo_deg;
        }
    }

    /// Sets agent `i`'s genuine SVO (flows with other SVO ranges remap the case's value).
    pub fn set_svo(&mut self, i: usize, svo_deg: f32) {
        if let Some(a) = self.agents.get_mut(i) {
            a.svo_deg = svo_deg;
        }
    }

    /// The SVO of agent `j` as observer `o` sees it: the genuine one, what a Stage 2 adversary
    /// tells `o` of the ego, or an evaluation probe's constant ([`crate::config::MessageProbe`]).
    #[inline]
    pub fn communicated_svo_deg(&self, o: usize, j: usize) -> f32 {
        if j != o {
            let probe = &self.cfg.obs.messages;
            if let Some(s) = probe.told_ego_deg.filter(|_| j == 0) {
                return s;
            }
            if let Some(s) = probe.neighbours_deg {
                return s;
            }
        }
        if j == 0 && o != 0 {
            if let Some(s) = self.seen_ego_svo[o] {
                return s;
            }
        }
        self.agents[j].svo_deg
    }

    /// Agents' outcomes (meaningful once they have ended); an agent that timed out is also told
    /// whether standing vehicles closed the road ahead of it then (every timeout falls on the
    /// episode's last step, so this is the state it ended in).
    pub fn outcomes(&self) -> impl Iterator<Item = AgentOutcome> + '_ {
        self.outcomes_judged(true)
    }

    /// [`Env::outcomes`], with the corridor test run for timeouts only when `passage` (it is
    /// what evaluation reports; training's episode metrics leave `road_closed` false).
    pub fn outcomes_judged(&self, passage: bool) -> impl Iterator<Item = AgentOutcome> + '_ {
        self.agents.iter().enumerate().map(move |(i, a)| {
            let mut o = a.outcome();
            o.road_closed = passage
                && a.termination == Some(Termination::Timeout)
                && self.road_closed_ahead(i).is_some();
            o
        })
    }

    /// The distance along agent `i`'s route at which the other vehicles standing on the road now
    /// (live, or timed out with the episode) close every corridor a car fits through
    /// ([`crate::passage`] with its default rule), if any.
    pub fn road_closed_ahead(&self, i: usize) -> Option<f32> {
        let a = self.agents.get(i)?;
        let rule = crate::passage::PassageRule::default();
        let standing: Vec<crate::passage::Obstacle> = self
            .agents
            .iter()
            .enumerate()
            // Vehicles that timed out with the episode stand where they stopped.
            .filter(|&(j, b)| {
                j != i
                    && (b.alive || b.termination == Some(Termination::Timeout))
                    && b.state.speed_mps < rule.stopped_mps
            })
            .map(|(_, b)| crate::passage::Obstacle {
                pos: b.state.pos(),
                theta_rad: b.state.theta_rad,
            })
            .collect();
        crate::passage::closed_ahead(
            &self.map,
            &self.cfg,
            a.route,
            a.s_m,
            a.lateral_m,
            &standing,
            &rule,
        )
    }

    /// Advances one decision step. `actions[i]` drives agent `i` when its controller is
    /// external; other entries are ignored.
    pub fn step(&mut self, actions: &[Action]) -> Result<(), EnvError> {
        if self.done {
            return Err(EnvError::Finished);
        }
        if actions.len() != self.agents.len() {
            return Err(EnvError::ActionCount { got: actions.len(), want: self.agents.len() });
        }
        let cfg = Arc::clone(&self.cfg);
        let vp = &cfg.vehicle;
        let dt = cfg.dt_s / cfg.substeps as f32;
        let mut alive_before = std::mem::take(&mut self.alive_before);
        alive_before.clear();
        alive_before.extend(self.agents.iter().map(|a| a.alive));
        for (i, a) in self.agents.iter_mut().enumerate() {
            self.ended_now[i] = false;
            if a.alive && a.controller == Controller::External {
                let (v, d) = actions[i].decode(vp);
                a.ref_speed_mps = v;
                a.steer_rad = d;
                a.idm_accel_residual =
                    actions[i]
                        .idm_accel
                        .map(|r| if r.is_finite() { r.clamp(-1.0, 1.0) } else { 0.0 });
                a.lateral_target_m = match (a.idm_accel_residual, actions[i].lateral) {
                    (Some(_), Some(l)) if l.is_finite() => {
                        l.clamp(-1.0, 1.0) * cfg.lateral.max_offset_m
                    }
                    _ => 0.0,
                };
            }
        }
        self.find_leaders();
        for _ in 0..cfg.substeps {
            let map = &self.map;
            for a in self.agents.iter_mut().filter(|a| a.alive && !a.collided) {
                let accel = match (a.controller, a.idm_accel_residual) {
                    (Controller::External, None) => {
                        a.pid.command(vp, a.ref_speed_mps, a.state.speed_mps, dt)
                    }
                    (Controller::Idm, _) | (Controller::External, Some(_)) => {
                        if a.lateral_offset_m != a.lateral_target_m {
                            a.lateral_offset_m = lateral_step(
                                a.lateral_offset_m,
                                a.lateral_target_m,
                                cfg.lateral.rate_mps,
                                dt,
                            );
                        }
                        a.steer_rad = route_steer_rad(map, vp, a);
                        residual_accel(
                            idm_accel(&cfg.idm, a.state.speed_mps, a.leader),
                            a.idm_accel_residual,
                            vp.max_accel_mps2,
                        )
                    }
                };
                let v0 = a.state.speed_mps;
                a.state.step(vp, accel, a.steer_rad, dt);
                if a.state.speed_mps > a.max_speed_mps {
                    a.state.speed_mps = a.max_speed_mps;
                }
                a.s_m += 0.5 * (v0 + a.state.speed_mps) * dt;
                if let Some((gap, v_lead)) = a.leader.as_mut() {
                    *gap -= (a.state.speed_mps - *v_lead) * dt;
                }
            }
            self.detect_collisions();
        }
        self.step_idx += 1;
        self.apply_rules();
        self.compute_rewards(&alive_before);
        self.alive_before = alive_before;
        for (i, a) in self.agents.iter_mut().enumerate() {
            if a.alive && a.termination.is_some() {
                a.alive = false;
                self.ended_now[i] = true;
            }
        }
        let learners_left = self.agents.iter().any(|a| a.alive && a.role == Role::Learner);
        self.done = !learners_left || self.step_idx >= cfg.horizon;
        Ok(())
    }

    /// IDM leaders of the IDM-driven agents, residual drivers included (see [`Env::leader_of`]).
    fn find_leaders(&mut self) {
        for i in 0..self.agents.len() {
            let a = &self.agents[i];
            if a.alive && (a.controller == Controller::Idm || a.idm_accel_residual.is_some()) {
                self.agents[i].leader = self.leader_of(i);
            }
        }
    }

    /// Agent `i`'s IDM leader: the nearest live vehicle ahead on its remaining route (moved
    /// sideways by its lateral offset, zero but for `idm-residual-lateral`) within the
    /// look-ahead, as `(gap_m, speed along the route in m/s)`.
    fn leader_of(&self, i: usize) -> Option<(f32, f32)> {
        let p = &self.cfg.idm;
        let len = self.cfg.vehicle.length_m;
        let a = &self.agents[i];
        let route = &self.map.routes[a.route as usize];
        let hi = route.cum_m.partition_point(|&c| c <= a.s_m + p.look_ahead_m) + 1;
        let mut best: Option<(f32, f32)> = None;
        for (j, b) in self.agents.iter().enumerate() {
            if j == i
                || !b.alive
                || geom::dist2(a.state.pos(), b.state.pos()) > (p.look_ahead_m + len).powi(2)
            {
                continue;
            }
            let pr = geom::project_range(&route.points, &route.cum_m, b.state.pos(), a.seg, hi);
            let ahead = pr.s_m - a.s_m;
            if (pr.lateral_m - a.lateral_offset_m).abs() > p.lateral_tolerance_m || ahead <= 0.0 {
                continue;
            }
            let gap = ahead - len;
            if best.is_none_or(|(g, _)| gap < g) {
                let along = route.headings[pr.seg];
                best = Some((gap, b.state.speed_mps * (b.state.theta_rad - along).cos().max(0.0)));
            }
        }
        best
    }

    /// The IDM driver's choice for agent `i` now, as the paper's normalised action (the
    /// demonstrator of the IDM warm-up): pure-pursuit steer toward its route and the
    /// reference speed whose PID error equals IDM's acceleration (`v + a_idm / Kp`, clipped to
    /// [0, v_max]). Held for a whole decision step, it drives its route like the IDM
    /// controller, which recomputes both every sub-step.
    pub fn demo_action(&self, i: usize) -> Action {
        let a = &self.agents[i];
        let vp = &self.cfg.vehicle;
        let steer_rad = route_steer_rad(&self.map, vp, a);
        let accel = idm_accel(&self.cfg.idm, a.state.speed_mps, self.leader_of(i));
        let ref_speed_mps =
            (a.state.speed_mps + accel / vp.pid_kp.max(1e-3)).clamp(0.0, vp.max_speed_mps);
        Action::encode(vp, ref_speed_mps, steer_rad)
    }

    /// Marks every pair of overlapping boxes as collided (both freeze until removal).
    fn detect_collisions(&mut self) {
        let reach2 = {
            let v = &self.cfg.vehicle;
            v.length_m * v.length_m + v.width_m * v.width_m
        };
        self.poses.clear();
        self.poses.extend(
            self.agents
                .iter()
                .map(|a| Pose::new(Vector::new(a.state.x_m, a.state.y_m), a.state.theta_rad)),
        );
        let n = self.agents.len();
        for i in 0..n {
            if !self.agents[i].alive {
                continue;
            }
            for j in (i + 1)..n {
                if !self.agents[j].alive || (self.agents[i].collided && self.agents[j].collided) {
                    continue;
                }
                if geom::dist2(self.agents[i].state.pos(), self.agents[j].state.pos()) > reach2 {
                    continue;
                }
                let pos12 = self.poses[i].inv_mul(&self.poses[j]);
                if intersection_test_cuboid_cuboid(&pos12, &self.box_full, &self.box_full) {
                    for k in [i, j] {
                        let a = &mut self.agents[k];
                        a.collided = true;
                        a.state.speed_mps = 0.0;
                    }
                }
            }
        }
    }

    /// Whether agent `a`'s shrunk box touches a road edge.
    fn off_road(&self, a: &Agent) -> bool {
        let pose_inv =
            Pose::new(Vector::new(a.state.x_m, a.state.y_m), a.state.theta_rad).inverse();
        let reach = 0.5 * (self.cfg.vehicle.length_m + self.cfg.vehicle.width_m);
        let mut hit = false;
        self.map.edge_grid.for_each_near(a.state.pos(), reach, |k| {
            if hit {
                return;
            }
            let (p, q) = self.map.edge_segments[k];
            let seg = Segment::new(
                pose_inv * Vector::new(p[0], p[1]),
                pose_inv * Vector::new(q[0], q[1]),
            );
            hit = intersection_test_cuboid_segment(&Pose::IDENTITY, &self.box_road, &seg);
        });
        hit
    }

    /// Route progress, zone bookkeeping, failure and success rules, timeout.
    fn apply_rules(&mut self) {
        let cfg = Arc::clone(&self.cfg);
        let max_heading = cfg.wrong_lane_deg.to_radians();
        let timeout = self.step_idx >= cfg.horizon;
        for i in 0..self.agents.len() {
            if !self.agents[i].alive {
                continue;
            }
            let off_road = self.off_road(&self.agents[i]);
            let map = Arc::clone(&self.map);
            let a = &mut self.agents[i];
            a.push_history();
            a.steps += 1;
            a.speed_ratio_sum += (a.state.speed_mps / cfg.vehicle.max_speed_mps).clamp(0.0, 1.0);
            let route = &map.routes[a.route as usize];
            let lo = a.seg.saturating_sub(2);
            let pr = geom::project_range(&route.points, &route.cum_m, a.state.pos(), lo, a.seg + 8);
            a.seg = pr.seg;
            a.s_m = pr.s_m;
            a.lateral_m = pr.lateral_m;
            a.left_lane |= pr.lateral_m.abs() > 0.5 * route.width_m;
            let pos = a.state.pos();
            let in_zone = geom::point_in_polygon(pos, &map.zone);
            if in_zone {
                a.zone_entered = true;
            } else if a.zone_entered {
                a.zone_passed = true;
            }
            let wrong_lane = !map.in_junction(pos)
                && map
                    .nearest_lane_heading(pos, 4.0)
                    .is_some_and(|h| geom::wrap_angle(a.state.theta_rad - h).abs() > max_heading);
            a.termination = if a.collided {
                Some(Termination::Collision)
            } else if off_road {
                Some(Termination::OffRoad)
            } else if pr.lateral_m.abs() > cfg.off_route_m {
                Some(Termination::OffRoute)
            } else if wrong_lane {
                Some(Termination::WrongLane)
            } else if a.s_m >= route.length_m - cfg.destination_tolerance_m {
                if a.zone_entered {
                    a.zone_passed = true;
                }
                Some(Termination::Destination)
            } else if timeout {
                Some(Termination::Timeout)
            } else {
                None
            };
        }
    }

    fn compute_rewards(&mut self, alive_before: &[bool]) {
        let rc = &self.cfg.reward;
        let vmax = self.cfg.vehicle.max_speed_mps;
        let n = self.agents.len();
        let mut ego_r = 0.0;
        for i in 0..n {
            let a = &self.agents[i];
            let r = &mut self.rewards[i];
            *r = Rewards::default();
            if !alive_before[i] {
                continue;
            }
            let speed = rc.speed_weight * (2.0 * a.state.speed_mps / vmax - 1.0);
            let fail = a.termination.is_some_and(Termination::is_failure);
            r.individual = speed - if fail { rc.failure_penalty } else { 0.0 };
            // FailMaker's own term: no collision penalty.
            let own = speed
                - if fail && a.termination != Some(Termination::Collision) {
                    rc.failure_penalty
                } else {
                    0.0
                };
            r.failmaker = own;
            if i == 0 {
                ego_r = r.individual;
            }
        }
        let r2 = rc.neighbour_radius_m * rc.neighbour_radius_m;
        let cap = rc.max_neighbours.unwrap_or(usize::MAX);
        for i in 0..n {
            if !alive_before[i] {
                continue;
            }
            let me = self.agents[i].state.pos();
            let cand = &mut self.reward_cand;
            cand.clear();
            for (j, b) in self.agents.iter().enumerate() {
                if j != i && alive_before[j] {
                    let d2 = geom::dist2(me, b.state.pos());
                    if d2 <= r2 {
                        cand.push((d2, j as u32));
                    }
                }
            }
            if cap < cand.len() {
                crate::geom::nearest_first(cand, cap);
            }
            let (mut sum, mut cnt) = (0.0, 0u32);
            for &(_, j) in cand.iter() {
                let j = j as usize;
                if self.agents[j].controller == Controller::External {
                    sum += self.rewards[j].individual;
                    cnt += 1;
                }
            }
            let others = if cnt > 0 { sum / cnt as f32 } else { 0.0 };
            let c = self.agents[i].svo_deg.to_radians();
            let r = &mut self.rewards[i];
            r.composed = c.cos() * r.individual + c.sin() * others;
            let ego_term = if i == 0 { 0.0 } else { ego_r };
            r.failmaker = c.cos() * r.failmaker + c.sin() * ego_term;
        }
    }

    /// Runs the episode to its end: before each step `policy` fills one action per agent,
    /// after each step (and once after reset) `on_step` sees the environment.
    pub fn run_episode(
        &mut self,
        mut policy: impl FnMut(&Env, &mut [Action]),
        mut on_step: impl FnMut(&Env),
    ) -> Result<(), EnvError> {
        let mut actions = vec![Action::default(); self.agents.len()];
        on_step(self);
        while !self.done {
            policy(self, &mut actions);
            self.step(&actions)?;
            on_step(self);
        }
        Ok(())
    }

    /// Moves agent `i` to a pose (tests and tools that construct situations).
    pub fn place_agent(&mut self, i: usize, pos: P2, theta_rad: f32, speed_mps: f32) {
        let a = &mut self.agents[i];
        a.state = VehicleState { x_m: pos[0], y_m: pos[1], theta_rad, speed_mps };
        let route = &self.map.routes[a.route as usize];
        let pr = geom::project_range(&route.points, &route.cum_m, pos, 0, route.points.len());
        a.seg = pr.seg;
        a.s_m = pr.s_m;
        for k in 0..a.hist.len() {
            a.hist[k] = [pos[0], pos[1], theta_rad, speed_mps];
        }
    }
}
