//! `socialflow bench replay`: what persisting the replay costs. Fills a replay with real
//! simulator transitions (every vehicle a learner driven by the scripted route follower, as
//! `bench sim`), then measures a full write, an incremental checkpoint's write and a restore
//! through `sf_sac::replay_store`, with bytes per transition beside the in-memory f16 size.
//!
//! Owns: [`ReplayArgs`] and the timings. Must not: define the store's format (that is
//! `sf_sac::replay_store`) or leave what it writes behind (its directory is removed).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use serde_json::json;
use sf_embedded::Ctx;
use sf_sac::replay::{Replay, Transition};
use sf_sac::replay_store::{ReplayStore, Segment};
use sf_sim::policy::route_follower;
use sf_sim::vec_env::{VecEnv, VecEnvConfig};
use sf_sim::{Action, Mode, SimConfig};

#[derive(Args, Debug)]
pub struct ReplayArgs {
    /// Replay sizes to measure (each filled to capacity).
    #[arg(long, value_delimiter = ',', default_value = "100000,1000000")]
    transitions: Vec<usize>,
    #[arg(long, default_value = "intersection")]
    scenario: String,
    #[arg(long, default_value_t = 20)]
    vehicles: u32,
    /// Transitions new since the previous checkpoint, for the incremental write.
    #[arg(long, default_value_t = 20_000)]
    increment: usize,
    /// Scratch directory for the segments (removed afterwards).
    #[arg(long)]
    dir: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

/// Pushes `n` transitions of the scripted fleet into `r`.
fn fill(venv: &mut VecEnv, cfg: &SimConfig, r: &mut Replay, n: usize) -> Result<()> {
    let spec = venv.spec.clone();
    let rows = venv.alive().len();
    let mut actions = vec![Action::default(); rows];
    let mut pushed = 0;
    while pushed < n {
        let obs = venv.observations().to_vec();
        let alive = venv.alive().to_vec();
        for (k, act) in actions.iter_mut().enumerate() {
            if alive[k] != 0.0 {
                *act = route_follower(
                    &spec,
                    &obs[k * spec.len..(k + 1) * spec.len],
                    &cfg.vehicle,
                    2,
                    1.0,
                );
            }
        }
        venv.step(&actions);
        for (k, step) in venv.row_steps().iter().enumerate() {
            if !step.stepped || pushed >= n {
                continue;
            }
            let a = [actions[k].ref_speed, actions[k].steer];
            let next = venv.next_observation(k);
            r.push(Transition {
                obs: &obs[k * spec.len..(k + 1) * spec.len],
                action: &a,
                reward: 0.0,
                next_obs: next,
                terminal: step.terminal(),
                steps: 1,
                map_id: 0,
                oracle: &[],
            })
            .context("pushing a simulator transition")?;
            pushed += 1;
        }
    }
    Ok(())
}

pub fn run(ctx: &Ctx, a: ReplayArgs) -> Result<()> {
    let map = ctx.map(&a.scenario)?;
    let cfg = Arc::new(SimConfig::default());
    let vehicles = a.vehicles.min(map.spawns.len() as u32);
    let root = a.dir.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("socialflow-bench-replay-{}", std::process::id()))
    });
    for &n in &a.transitions {
        anyhow::ensure!(
            n > a.increment,
            "--transitions {n} must exceed --increment {}",
            a.increment
        );
        let mut venv = VecEnv::new(
            map.clone(),
            cfg.clone(),
            VecEnvConfig {
                n_envs: 8,
                mode: Mode::MultiAgent,
                vehicles: (vehicles, vehicles),
                seed: 11,
            },
        );
        let obs_len = venv.spec.len;
        let mut r = Replay::new(n, obs_len, 2);
        fill(&mut venv, &cfg, &mut r, n)?;
        let dir = root.join(format!("n{n}"));
        let _ = std::fs::remove_dir_all(&dir);
        let store = ReplayStore::new(&dir);
        // A full write (the first checkpoint of a resumed-from-nothing replay, or the worst case).
        let t = Instant::now();
        let seg = Segment::snapshot(&r, 0);
        let snapshot_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let full_bytes = store.append(&seg, r.oldest()).context("writing the full segment")?;
        let write_s = t.elapsed().as_secs_f64();
        let distinct_rows = seg.rows.len() / obs_len;
        drop(seg);
        // One checkpoint interval later: `increment` new transitions, evicting as many.
        let from = r.inserted();
        fill(&mut venv, &cfg, &mut r, a.increment)?;
        let t = Instant::now();
        let seg = Segment::snapshot(&r, from);
        let inc_bytes = store.append(&seg, r.oldest()).context("writing the increment")?;
        let inc_s = t.elapsed().as_secs_f64();
        drop(seg);
        // Resume: read everything back into a fresh replay.
        let t = Instant::now();
        let (back, _) = store.restore(n, obs_len, 2, r.inserted()).context("restoring")?;
        let restore_s = t.elapsed().as_secs_f64();
        anyhow::ensure!(
            back.len() == r.len() && back.get(r.inserted() - 1) == r.get(r.inserted() - 1),
            "the restored replay differs"
        );
        drop(back);
        let out = json!({
            "transitions": n,
            "scenario": a.scenario,
            "vehicles": vehicles,
            "obs_floats": obs_len,
            "memory_bytes_per_transition": r.bytes_per_transition(),
            "disk_bytes_per_transition": full_bytes as f64 / n as f64,
            "distinct_rows_per_transition": distinct_rows as f64 / n as f64,
            "full_write_bytes": full_bytes,
            "full_snapshot_s": snapshot_s,
            "full_write_s": write_s,
            "increment_transitions": a.increment,
            "increment_bytes": inc_bytes,
            "increment_checkpoint_s": inc_s,
            "restore_s": restore_s,
        });
        if a.json {
            println!("{out}");
        } else {
            println!("{}", serde_json::to_string_pretty(&out)?);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
    let _ = std::fs::remove_dir_all(&root);
    Ok(())
}
