//! The hand-over probe: where does SAC's objective move a cloned actor, and why?
//!
//! On a direct-action job, a clone of IDM reaches IDM's level with its mean action and the SAC
//! phase then takes it off the road within a few hundred updates, whatever was done to the
//! critic (docs/ladder/l3-roundabout-direct/). This probe replays that hand-over offline on
//! the IDM demonstrator's transitions ([`super::critic::collect`], IDM's noise-free action in
//! every state): the job's own schedule (cloning, critic alone), then SAC updates on the same
//! fixed data, and at the hand-over and every `every` updates after it, on held-out states:
//!
//! - per action component (the speed reference, the steer): how far the actor's mean and the
//!   averaged actor's mean are from IDM's action, and the actor's spread;
//! - the critic's gradient `dQ/da` at the actor's mean: its size per component and how often it
//!   points further from IDM's action than the mean already is;
//! - along each component, where the critic puts its best action on a grid around IDM's
//!   (the other component at IDM's), and how much higher it rates it;
//! - `Q(s, mean) - Q(s, a_IDM)` and how often IDM's action is rated at least as high (the rows
//!   a Q-filtered cloning term would keep);
//! - closed loop: the averaged actor's mean action driven on fresh cases among the job's
//!   traffic (success, safety, speed, collision), so the offline fall can be set beside the
//!   online one, with a GIF of the first failing episode at chosen points.
//!
//! Owns: [`HandoverSettings`], [`HandoverPoint`], [`run`]. Must not: touch the service or write
//! files other than the GIFs asked for (the command prints the points as JSON lines).

use std::path::PathBuf;
use std::sync::Arc;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use sf_job::JobConfig;
use sf_rollout::evaluate::{self, render_gif, EgoDef, EvalError, FlowDef, Policy, Runners};
use sf_rollout::setup;
use sf_sac::replay::Batch;
use sf_sac::Sac;
use sf_sim::case::CaseFile;
use sf_sim::Map;

use super::critic::{ProbeData, ProbeError};

/// Offsets from IDM's action tried along each component, in action units ([-1, 1] each).
const AXIS_GRID: [f32; 17] = [
    -0.4, -0.35, -0.3, -0.25, -0.2, -0.15, -0.1, -0.05, 0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35,
    0.4,
];

/// What the probe runs after the job's cloning and critic-only updates.
#[derive(Clone, Debug)]
pub struct HandoverSettings {
    /// SAC updates after the hand-over.
    pub sac_updates: u64,
    /// Updates between measurements.
    pub every: u64,
    /// Held-out rows measured (the first ones; all when fewer).
    pub rows: usize,
    /// Closed-loop episodes per measurement (0: none).
    pub episodes: u32,
    pub seed: u64,
    /// Where to write a GIF of the first closed-loop episode that fails, at the measurements
    /// `gif_at` updates after the hand-over (`handover-<updates>.gif`).
    pub gif_dir: Option<PathBuf>,
    pub gif_at: Vec<u64>,
}

/// One measurement; per-component arrays are in the action's order (speed reference, steer).
#[derive(Clone, Debug, Serialize)]
pub struct HandoverPoint {
    pub updates: u64,
    /// Updates since the actor started following SAC's objective (0 at the hand-over).
    pub since_handover: u64,
    pub alpha: f32,
    /// Mean |mean action - IDM's| of the actor, per component.
    pub gap: Vec<f64>,
    /// Mean (mean action - IDM's) of the actor, per component (the drift's sign).
    pub bias: Vec<f64>,
    /// Mean |mean action - IDM's| of the Polyak-averaged actor (what validation drives).
    pub gap_averaged: Vec<f64>,
    /// The actor's mean log-std per component.
    pub log_std: Vec<f64>,
    /// Mean dQ/da at the actor's mean, and mean |dQ/da|, per component.
    pub grad: Vec<f64>,
    pub grad_abs: Vec<f64>,
    /// Share of rows whose dQ/da points further from IDM's action than the mean already is
    /// (rows whose mean is within 0.01 of IDM's left out of the share).
    pub grad_away: Vec<f64>,
    /// Along each component (the other at IDM's): mean offset of the grid's best action from
    /// IDM's, mean |offset|, and mean Q(best) - Q(IDM's).
    pub axis_best: Vec<f64>,
    pub axis_best_abs: Vec<f64>,
    pub axis_gain: Vec<f64>,
    /// Mean Q(s, mean) - Q(s, a_IDM), and the share of rows with Q(s, a_IDM) >= Q(s, mean).
    pub q_mean_minus_idm: f64,
    pub idm_rated_higher: f64,
    /// Closed loop, mean action: the Polyak-averaged actor (what the job validates and, with
    /// `act_with_average`, acts with) and the actor itself; `None` without episodes.
    pub averaged: Option<Scored>,
    pub actor: Option<Scored>,
}

/// Trains `sac` on `data` with the job's schedule and measures the hand-over; calls `emit`
/// with every point as it is measured.
pub fn run(
    sac: &mut Sac,
    data: &ProbeData,
    job: &JobConfig,
    maps: &[Arc<Map>],
    s: &HandoverSettings,
    mut emit: impl FnMut(&HandoverPoint),
) -> Result<Vec<HandoverPoint>, ProbeError> {
    let handover = sac.cfg.bc_updates + sac.cfg.critic_pretrain_updates;
    let test = held_out(&data.test, s.rows, sac.spec.len, sac.net.action_dim);
    let mut loop_ = ClosedLoop::new(job, maps, s.episodes, s.seed);
    let gif_path = |since: u64| {
        s.gif_dir
            .as_ref()
            .filter(|_| s.gif_at.contains(&since))
            .map(|d| d.join(format!("handover-{since}.gif")))
    };
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0x68_616e_646f);
    let mut batch = Batch::default();
    let mut points = Vec::new();
    let end = handover + s.sac_updates;
    let every = s.every.max(1);
    while sac.updates <= end {
        if sac.updates >= handover && (sac.updates - handover).is_multiple_of(every) {
            let gif = gif_path(sac.updates - handover);
            let p = measure(sac, &test, handover, &mut loop_, gif)?;
            emit(&p);
            points.push(p);
        }
        if sac.updates == end {
            break;
        }
        data.train.sample_into(&mut rng, sac.cfg.batch_size, &mut batch)?;
        sac.update(&batch);
    }
    Ok(points)
}

/// The first `rows` held-out rows with their IDM labels.
fn held_out(test: &Batch, rows: usize, len: usize, a_dim: usize) -> Batch {
    let n = test.len().min(rows);
    Batch {
        obs: test.obs[..n * len].to_vec(),
        actions: test.actions[..n * a_dim].to_vec(),
        map_ids: test.map_ids[..n].to_vec(),
        oracle: test.oracle[..n * a_dim].to_vec(),
        ..Batch::default()
    }
}

fn measure(
    sac: &Sac,
    t: &Batch,
    handover: u64,
    loop_: &mut ClosedLoop,
    gif: Option<PathBuf>,
) -> Result<HandoverPoint, ProbeError> {
    let a_dim = sac.net.action_dim;
    let n = t.map_ids.len();
    let idm = &t.oracle;
    let (mean, log_std) = sac.action_dist(&t.obs, &t.map_ids, false);
    let (mean_avg, _) = sac.action_dist(&t.obs, &t.map_ids, true);
    let grad = sac.q_action_gradient(&t.obs, &mean, &t.map_ids);
    let per = |f: &dyn Fn(usize, usize) -> f64| -> Vec<f64> {
        (0..a_dim).map(|k| (0..n).map(|i| f(i, k)).sum::<f64>() / n.max(1) as f64).collect()
    };
    let at = |v: &[f32], i: usize, k: usize| v[i * a_dim + k] as f64;
    let gap = per(&|i, k| (at(&mean, i, k) - at(idm, i, k)).abs());
    let bias = per(&|i, k| at(&mean, i, k) - at(idm, i, k));
    let gap_averaged = per(&|i, k| (at(&mean_avg, i, k) - at(idm, i, k)).abs());
    let log_std_m = per(&|i, k| at(&log_std, i, k));
    let grad_m = per(&|i, k| at(&grad, i, k));
    let grad_abs = per(&|i, k| at(&grad, i, k).abs());
    let grad_away = (0..a_dim)
        .map(|k| {
            let (mut away, mut counted) = (0usize, 0usize);
            for i in 0..n {
                let d = at(&mean, i, k) - at(idm, i, k);
                if d.abs() > 0.01 {
                    counted += 1;
                    away += (d * at(&grad, i, k) > 0.0) as usize;
                }
            }
            away as f64 / counted.max(1) as f64
        })
        .collect();
    // Every action set the critic rates, encoded once: the mean, IDM's, then along each
    // component (the other at IDM's) IDM's action moved by each grid offset.
    let mut sets: Vec<Vec<f32>> = vec![mean.clone(), idm.clone()];
    for k in 0..a_dim {
        for &d in &AXIS_GRID {
            let mut acts = idm.clone();
            for row in acts.chunks_exact_mut(a_dim) {
                row[k] = (row[k] + d).clamp(-1.0, 1.0);
            }
            sets.push(acts);
        }
    }
    let set_refs: Vec<&[f32]> = sets.iter().map(Vec::as_slice).collect();
    let q = sac.q_min_each(&t.obs, &set_refs, &t.map_ids);
    let (q_mean, q_idm) = (&q[0], &q[1]);
    let nn = n.max(1) as f64;
    let q_mean_minus_idm = q_mean.iter().zip(q_idm).map(|(a, b)| (a - b) as f64).sum::<f64>() / nn;
    let idm_rated_higher = q_mean.iter().zip(q_idm).filter(|(a, b)| b >= a).count() as f64 / nn;
    let (mut axis_best, mut axis_best_abs, mut axis_gain) = (vec![], vec![], vec![]);
    for along in q[2..].chunks_exact(AXIS_GRID.len()) {
        // Row i's best offset on the grid along this component, and its Q.
        let mut best = vec![(0.0f32, f32::NEG_INFINITY); n];
        for (&d, qs) in AXIS_GRID.iter().zip(along) {
            for (b, &v) in best.iter_mut().zip(qs) {
                if v > b.1 {
                    *b = (d, v);
                }
            }
        }
        axis_best.push(best.iter().map(|b| b.0 as f64).sum::<f64>() / nn);
        axis_best_abs.push(best.iter().map(|b| b.0.abs() as f64).sum::<f64>() / nn);
        axis_gain.push(best.iter().zip(q_idm).map(|(b, q)| (b.1 - q) as f64).sum::<f64>() / nn);
    }
    let bytes = |w: Result<Vec<u8>, sf_nn::weights::WeightsError>| {
        w.map_err(|e| ProbeError::Eval(format!("the actor's weights: {e}")))
    };
    let averaged =
        loop_.score(sac, bytes(sac.selected_actor_bytes())?, "averaged", gif.as_ref())?;
    let actor = loop_.score(sac, bytes(sac.actor_bytes())?, "actor", gif.as_ref())?;
    Ok(HandoverPoint {
        updates: sac.updates,
        since_handover: sac.updates - handover,
        alpha: sac.alpha(),
        gap,
        bias,
        gap_averaged,
        log_std: log_std_m,
        grad: grad_m,
        grad_abs,
        grad_away,
        axis_best,
        axis_best_abs,
        axis_gain,
        q_mean_minus_idm,
        idm_rated_higher,
        averaged,
        actor,
    })
}

/// The closed loop's numbers for one actor at one point: success, safety (no failure: an
/// episode that is safe but not a success timed out), speed score, collision rate, and the GIF
/// of its first failing episode if one was asked for.
#[derive(Clone, Debug, Serialize)]
pub struct Scored {
    pub success: f64,
    pub safety: f64,
    pub speed: f64,
    pub collision: f64,
    pub episodes: usize,
    pub gif: Option<String>,
}

/// Fresh cases among IDM traffic (the ego jobs this probe is for) on the job's first scenario,
/// each actor scored on the same ones with its mean action.
struct ClosedLoop {
    job: JobConfig,
    map: Option<Arc<Map>>,
    cases: CaseFile,
    runners: Runners,
}

impl ClosedLoop {
    fn new(job: &JobConfig, maps: &[Arc<Map>], episodes: u32, seed: u64) -> Self {
        let sim = Arc::new(setup::resolve(job, None).sim);
        let map = maps.first().filter(|_| episodes > 0).cloned();
        let cases = map.as_ref().map_or_else(Vec::new, |m| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6c6f_6f70);
            sf_sim::vec_env::draw_cases(
                m,
                &sim,
                &mut rng,
                episodes,
                (job.env.vehicles_min, job.env.vehicles_max),
                job.case_draw(),
            )
        });
        let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)
            .expect("the CPU device is always there");
        let cases = CaseFile {
            format_version: 1,
            scenario: map.as_ref().map_or_else(String::new, |m| m.name.clone()),
            generator_seed: seed,
            cases,
        };
        Self { job: job.clone(), map, cases, runners: Runners::new(device) }
    }

    /// Drives `weights` (the actor `which`) on the cases; a GIF beside `gif` (its name with
    /// `which` added) of the first failing episode.
    fn score(
        &mut self,
        sac: &Sac,
        weights: Vec<u8>,
        which: &str,
        gif: Option<&PathBuf>,
    ) -> Result<Option<Scored>, ProbeError> {
        let Some(map) = &self.map else { return Ok(None) };
        let eval = |e: EvalError| ProbeError::Eval(e.to_string());
        let key = format!("handover-{which}@{}", sac.updates);
        let policy = Policy::new(key.clone(), self.job.clone(), Arc::new(weights), Vec::new());
        let ego = EgoDef::Learned(policy);
        let rows = evaluate::run_cases(
            map,
            &self.cases.cases,
            1,
            25,
            &FlowDef::Idm,
            Some(&ego),
            &mut self.runners,
        )
        .map_err(eval)?;
        let failed = rows.iter().position(|r| r.scores.success < 1.0);
        let gif = match (gif, failed) {
            (Some(path), Some(i)) => {
                let path = path.with_file_name(format!(
                    "{}-{which}.gif",
                    path.file_stem().and_then(|x| x.to_str()).unwrap_or("handover")
                ));
                let case = rows[i].case;
                let flows = [("idm", &FlowDef::Idm)];
                let ego = Some(("probe", &ego));
                render_gif(ego, &flows, case, map, &self.cases, &mut self.runners, &path, 480)
                    .map_err(eval)?;
                Some(path.display().to_string())
            }
            _ => None,
        };
        self.runners.forget(&key);
        let n = rows.len().max(1) as f64;
        let mean = |f: &dyn Fn(&sf_job::eval::EvalEpisode) -> f32| {
            rows.iter().map(|r| f(r) as f64).sum::<f64>() / n
        };
        Ok(Some(Scored {
            success: mean(&|r| r.scores.success),
            safety: mean(&|r| r.scores.safety),
            speed: mean(&|r| r.scores.speed),
            collision: mean(&|r| r.collision),
            episodes: rows.len(),
            gif,
        }))
    }
}
