//! `socialflow bench ...`: measurements with JSON output for scripts.
//!
//! Owns: the `bench` subcommands ([`BenchCmd`]) and `bench sim` (simulator throughput with a
//! scripted policy); the others are in `bench_*`. Must not: change what it measures (every
//! number comes from the library code that runs in production) or write into a job store.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use serde_json::json;
use sf_embedded::Ctx;
use sf_sim::policy::route_follower;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Layout, Mode, SimConfig};

#[derive(Subcommand, Debug)]
pub enum BenchCmd {
    /// Simulator throughput: every vehicle a learning agent driven by a fixed cheap policy
    /// that reads its observation; observations built for every agent on every step.
    Sim(SimArgs),
    /// SAC update and actor inference speed of a network size on real observations.
    Sac(crate::bench_sac::SacArgs),
    /// Transitions per second a learner ingests over loopback gRPC from m synthetic senders.
    Ingest(crate::bench_svc::SvcBenchArgs),
    /// Environment steps and updates per second of a real job with m in-process workers.
    E2e(crate::bench_svc::SvcBenchArgs),
    /// Bytes per transition and the time to checkpoint and restore a persisted replay.
    Replay(crate::bench_replay::ReplayArgs),
    /// Many worker streams against one learner process for minutes, optionally killing one
    /// every N seconds: RPC errors, transition accounting, learner memory.
    Soak(crate::bench_soak::SoakArgs),
}

#[derive(Args, Debug)]
pub struct SimArgs {
    #[arg(long, default_value = "intersection")]
    scenario: String,
    #[arg(long, default_value_t = 20)]
    vehicles: u32,
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Environments stepped together (default: 8 per thread).
    #[arg(long)]
    envs: Option<usize>,
    /// `ego-frame` or `query-centric`.
    #[arg(long, value_parser = Layout::parse, default_value = "query-centric")]
    layout: Layout,
    #[arg(long)]
    json: bool,
}

pub fn run(ctx: &Ctx, cmd: BenchCmd) -> Result<()> {
    match cmd {
        BenchCmd::Sim(a) => sim(ctx, a),
        BenchCmd::Sac(a) => crate::bench_sac::run(ctx, a),
        BenchCmd::Ingest(a) => crate::bench_svc::ingest(ctx, a),
        BenchCmd::E2e(a) => crate::bench_svc::e2e(ctx, a),
        BenchCmd::Replay(a) => crate::bench_replay::run(ctx, a),
        BenchCmd::Soak(a) => crate::bench_soak::run(ctx, a),
    }
}

fn sim(ctx: &Ctx, a: SimArgs) -> Result<()> {
    let map = ctx.map(&a.scenario)?;
    let mut cfg = SimConfig::default();
    cfg.obs.layout = a.layout;
    let cfg = Arc::new(cfg);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(a.threads.max(1))
        .build()
        .context("building the thread pool")?;
    let n_envs = a.envs.unwrap_or(8 * a.threads.max(1));
    let vehicles = a.vehicles.min(map.spawns.len() as u32);
    let result = pool.install(|| {
        let mut venv = VecEnv::new(
            map.clone(),
            cfg.clone(),
            VecEnvConfig {
                n_envs,
                mode: Mode::MultiAgent,
                vehicles: (vehicles, vehicles),
                seed: 7,
            },
        );
        let rows = venv.alive().len();
        let mut actions = vec![Action::default(); rows];
        let spec = venv.spec.clone();
        let start = Instant::now();
        let mut steps = 0u64;
        while start.elapsed().as_secs_f64() < a.seconds {
            for _ in 0..10 {
                let obs = venv.observations();
                for (r, act) in actions.iter_mut().enumerate() {
                    if venv.alive()[r] != 0.0 {
                        *act = route_follower(
                            &spec,
                            &obs[r * spec.len..(r + 1) * spec.len],
                            &cfg.vehicle,
                            2,
                            1.0,
                        );
                    }
                }
                venv.step(&actions);
                steps += 1;
            }
        }
        let secs = start.elapsed().as_secs_f64();
        let (env_steps, agent_steps) = venv.counters();
        let finished = venv.take_finished();
        let success = finished.iter().map(|m| m.scores.success as f64).sum::<f64>()
            / finished.len().max(1) as f64;
        (secs, steps, env_steps, agent_steps, finished.len(), success, spec)
    });
    let (secs, _steps, env_steps, agent_steps, episodes, success, spec) = result;
    let out = json!({
        "scenario": a.scenario,
        "vehicles": vehicles,
        "threads": a.threads,
        "envs": n_envs,
        "layout": serde_json::to_value(cfg.obs.layout)?,
        "seconds": secs,
        "agent_steps_per_s": agent_steps as f64 / secs,
        "env_steps_per_s": env_steps as f64 / secs,
        "episodes": episodes,
        "episode_success_of_scripted_policy": success,
        "obs_floats": spec.len,
        "obs_bytes_f32": spec.bytes_f32(),
        "obs_bytes_f16": spec.len * 2,
    });
    if a.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(())
}
