//! `socialflow bench sac`: SAC updates/s and actor inference observations/s.
//!
//! Sizes: `paper` and `compact` are the paper's ego-frame network at the reference script's
//! sizes (`../shared/bench/sac_torch.py`); `default` is our default query-centric network at
//! the paper's observation content. Batches are real observations from the simulator.
//! `--profile` adds the update's roofline (`profile`: FLOPs counted from the configs, the FMA
//! peak, the stages timed alone; `docs/results/roofline.md`).
//!
//! Owns: [`SacArgs`], the size presets and the timed loops. Must not: change the update or the
//! networks it measures (it calls `sf_sac::Sac` and `sf_rollout::inference` as training does).

use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde_json::json;
use sf_embedded::Ctx;
use sf_nn::NetConfig;
use sf_rollout::inference::PolicyRunner;
use sf_sac::{Replay, Sac, SacConfig, Transition};
use sf_sim::obs::MapSegments;
use sf_sim::policy::route_follower;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Layout, Mode, SimConfig};

mod profile;

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Size {
    Paper,
    Compact,
    Default,
}

#[derive(Args, Debug)]
pub struct SacArgs {
    #[arg(long, value_enum, default_value = "default")]
    size: Size,
    /// Seconds spent timing updates (inference gets a third of it, half with shared histories).
    #[arg(long, default_value_t = 20.0)]
    seconds: f64,
    #[arg(long, default_value_t = 128)]
    batch: usize,
    /// Tensor device (`ndarray` needs a build with `--features sf-nn/ndarray` or `sf-nn/openblas`).
    #[arg(long, value_enum, default_value = "cpu")]
    device: DeviceArg,
    #[arg(long)]
    json: bool,
    /// Benchmark a job config's observation, network and SAC settings instead of `--size`
    /// (e.g. configs/ladder/jobs/l4-ego-idm.toml).
    #[arg(long)]
    job: Option<std::path::PathBuf>,
    /// Which updates to time: full SAC updates, the behaviour-cloning updates of
    /// `sac.bc_updates`, or the critic-only updates of `sac.critic_pretrain_updates`.
    #[arg(long, value_enum, default_value = "full")]
    phase: Phase,
    /// Also report the update against this CPU's limit: FLOPs by stage and network part
    /// (counted from the configs), achieved GFLOP/s beside a measured FMA peak, and the
    /// update's stages timed one by one beside its matrix products alone (`profile` in the
    /// JSON, a summary on stderr).
    #[arg(long)]
    profile: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Phase {
    Full,
    Cloning,
    Critic,
}

impl Phase {
    /// `(bc_updates, critic_pretrain_updates)` that keep every timed update in this phase.
    fn schedule(self) -> (u64, u64) {
        const ALWAYS: u64 = 1 << 40;
        match self {
            Phase::Full => (0, 0),
            Phase::Cloning => (ALWAYS, 0),
            Phase::Critic => (0, ALWAYS),
        }
    }
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum DeviceArg {
    Cpu,
    Ndarray,
    Cuda,
    Wgpu,
}

/// The observation and network configuration of a benchmark size.
pub fn size_config(size: Size) -> (SimConfig, NetConfig) {
    let mut sim = SimConfig::default();
    // The reference script's caps: other agents, static polylines, points per polyline.
    let mut ego_frame = |neighbours, polylines, points| {
        sim.obs.layout = Layout::EgoFrame;
        sim.obs.max_neighbours = neighbours;
        sim.obs.max_polylines = polylines;
        sim.obs.polyline_points = points;
    };
    let net = match size {
        Size::Paper => {
            ego_frame(20, 40, 25);
            NetConfig::paper()
        }
        Size::Compact => {
            ego_frame(16, 16, 10);
            NetConfig::compact()
        }
        Size::Default => NetConfig::fast(),
    };
    (sim, net)
}

fn sac_device(d: DeviceArg) -> sf_job::config::Device {
    match d {
        DeviceArg::Cpu => sf_job::config::Device::Cpu,
        DeviceArg::Ndarray => sf_job::config::Device::Ndarray,
        DeviceArg::Cuda => sf_job::config::Device::Cuda,
        DeviceArg::Wgpu => sf_job::config::Device::Wgpu,
    }
}

pub fn run(ctx: &Ctx, a: SacArgs) -> Result<()> {
    let job = match &a.job {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            Some(sf_job::JobConfig::from_toml(&text).with_context(|| p.display().to_string())?)
        }
        None => None,
    };
    let (sim, net) = match &job {
        Some(j) => {
            let r = sf_rollout::setup::resolve(j, None);
            (r.sim, r.net)
        }
        None => size_config(a.size),
    };
    let sim = Arc::new(sim);
    let map = ctx.map("intersection")?;
    let mut venv = VecEnv::new(
        map.clone(),
        sim.clone(),
        VecEnvConfig { n_envs: 4, mode: Mode::MultiAgent, vehicles: (20, 20), seed: 1 },
    );
    let spec = venv.spec.clone();
    let replay = fill_replay(&mut venv, &sim, net.action_dim, 4 * a.batch)?;
    let segs = MapSegments::build(&map, sim.obs.segment_points);
    // paper and compact follow the reference update exactly (fresh critic features).
    let reuse = matches!(a.size, Size::Default);
    // Every timed update in the chosen phase (by default past the job's cloning and
    // critic-only updates: full updates).
    let (bc_updates, critic_pretrain_updates) = a.phase.schedule();
    let cfg = match &job {
        Some(j) => SacConfig {
            batch_size: a.batch,
            device: sac_device(a.device),
            bc_updates,
            critic_pretrain_updates,
            ..j.sac.clone()
        },
        None => SacConfig {
            batch_size: a.batch,
            reuse_critic_features: reuse,
            device: sac_device(a.device),
            reward_scale: 1.0,
            bc_updates,
            critic_pretrain_updates,
            ..SacConfig::default()
        },
    };
    let reuse = cfg.reuse_critic_features;
    let mut sac = Sac::new(cfg, net.clone(), spec.clone(), sim.dt_s, &[&segs])?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batches: Vec<_> =
        (0..4).map(|_| replay.sample(&mut rng, a.batch)).collect::<Result<_, _>>()?;
    let cpu_start = profile::process_cpu_s();
    let mut times = time_updates(&mut sac, &batches, a.seconds);
    let update_cpu_s = (profile::process_cpu_s() - cpu_start) / times.len() as f64;
    let updates_timed = times.len();
    // The first and the last tenth of the timed updates: an update that slows as training goes
    // on shows here, not in the median.
    // Sorting a tenth in place leaves the other tenth and the whole's median as they are.
    let tenth = (updates_timed / 10).max(1);
    let first_tenth = median(&mut times[..tenth]);
    let last_tenth = median(&mut times[updates_timed - tenth..]);
    let update_median = median(&mut times);

    // Inference: the worker's step, 20 observations of one step through the worker's
    // `PolicyRunner` (batch building included): the live agents of the simulators' current step,
    // each agent's history encoded once for all its observers (query-centric), and the same rows
    // with a copy per observation for comparison.
    let (actor, _) = sac.policy();
    let device = sf_nn::device::device(sf_sac::device_kind(sac_device(a.device)))?;
    let version = sf_job::PolicyVersion::new(0);
    let runner = PolicyRunner::new(actor, &net, &spec, sim.dt_s, &[&segs], version, &device);
    let live: Vec<usize> =
        (0..venv.alive().len()).filter(|&r| venv.alive()[r] == 1.0).take(20).collect();
    anyhow::ensure!(live.len() == 20, "the benchmark step has only {} live agents", live.len());
    let rows: Vec<f32> = live
        .iter()
        .flat_map(|&r| venv.observations()[r * spec.len..(r + 1) * spec.len].iter().copied())
        .collect();
    let (infer_median, unshared_median, encoded) = time_inference(&runner, &rows, a.seconds / 6.0);
    let profile = if a.profile {
        let p = profile::report(&sac, &segs, &batches[0], update_median, a.phase)?;
        profile::print(&p, update_median);
        Some(p)
    } else {
        None
    };
    let mut out = json!({
        "size": match &a.job { Some(p) => p.display().to_string(), None => format!("{:?}", a.size).to_lowercase() },
        "batch": a.batch,
        "updates_per_s": 1.0 / update_median,
        "update_median_s": update_median,
        "update_cpu_s_mean": update_cpu_s,
        "updates_timed": updates_timed,
        "phase": format!("{:?}", a.phase).to_lowercase(),
        "update_first_tenth_median_s": first_tenth,
        "update_last_tenth_median_s": last_tenth,
        "inference_obs_per_s": 20.0 / infer_median,
        "inference_batch": 20,
        "inference_unshared_obs_per_s": 20.0 / unshared_median,
        "inference_histories_encoded": encoded,
        "encoder": net.encoder,
        "d_model": net.d_model,
        "set_hidden": net.set_hidden,
        "phi_layers": net.phi_layers,
        "reuse_critic_features": reuse,
        "obs_floats": spec.len,
        "replay_bytes_per_transition": replay.bytes_per_transition(),
        "threads": rayon::current_num_threads(),
        "device": format!("{:?}", a.device).to_lowercase(),
    });
    if let Some(p) = profile {
        out["profile"] = p;
    }
    if a.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}

/// A replay of at least `rows` real transitions: every agent of `venv` follows its route.
fn fill_replay(
    venv: &mut VecEnv,
    sim: &SimConfig,
    action_dim: usize,
    rows: usize,
) -> Result<Replay> {
    let spec = venv.spec.clone();
    let mut replay = Replay::new(100_000, spec.len, action_dim);
    let mut actions = vec![Action::default(); venv.alive().len()];
    while replay.len() < rows {
        let before = venv.observations().to_vec();
        let alive = venv.alive().to_vec();
        for (i, act) in actions.iter_mut().enumerate() {
            *act = route_follower(
                &spec,
                &before[i * spec.len..(i + 1) * spec.len],
                &sim.vehicle,
                2,
                0.8,
            );
        }
        venv.step(&actions);
        for i in (0..alive.len()).filter(|&i| alive[i] == 1.0) {
            let act = [actions[i].ref_speed, actions[i].steer];
            replay.push(Transition {
                obs: &before[i * spec.len..(i + 1) * spec.len],
                action: &act[..action_dim],
                reward: venv.row_steps()[i].rewards.individual,
                next_obs: &venv.observations()[i * spec.len..(i + 1) * spec.len],
                terminal: false,
                steps: 1,
                map_id: 0,
                oracle: &[],
            })?;
        }
    }
    Ok(replay)
}

/// Two untimed updates, then updates on `batches` in turn for `seconds` (at least 3): each
/// timed update's seconds, in order.
fn time_updates(sac: &mut Sac, batches: &[sf_sac::Batch], seconds: f64) -> Vec<f64> {
    for b in batches.iter().take(2) {
        sac.update(b);
    }
    let mut times = Vec::new();
    let start = Instant::now();
    while start.elapsed().as_secs_f64() < seconds || times.len() < 3 {
        let t = Instant::now();
        sac.update(&batches[times.len() % batches.len()]);
        times.push(t.elapsed().as_secs_f64());
    }
    times
}

/// Median times of one worker step's batch (built and run through the actor's mean) with each
/// agent's history encoded once and with a copy per observation, each timed for `seconds` (at
/// least 20 steps); and how many histories the shared batch encodes.
fn time_inference(runner: &PolicyRunner, rows: &[f32], seconds: f64) -> (f64, f64, usize) {
    let ids = vec![0u32; 20];
    let time = |shared: bool| {
        let mut inf = Vec::new();
        let start = Instant::now();
        while start.elapsed().as_secs_f64() < seconds || inf.len() < 20 {
            let t = Instant::now();
            let obs =
                if shared { runner.batch(rows, &ids) } else { runner.batch_unshared(rows, &ids) };
            let _ = runner.mean_of(&obs);
            inf.push(t.elapsed().as_secs_f64());
        }
        median(&mut inf)
    };
    let (shared, unshared) = (time(true), time(false));
    (shared, unshared, runner.batch(rows, &ids).histories.encoded_histories())
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
