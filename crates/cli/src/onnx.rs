//! `socialflow export-onnx`: a finished job's actor (its deterministic action) as an ONNX
//! model, plus a check file of stored observations with burn's actions for them, so a runtime
//! can be compared with burn (`tests/python/check_onnx.py` does it with onnxruntime).

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use rand::SeedableRng;
use serde_json::json;
use sf_rollout::drive::{self, Actor, Drivers};
use sf_rollout::evaluate::Policy;
use sf_rollout::inference::PolicyRunner;
use sf_rollout::setup;
use sf_sim::obs::MapSegments;
use sf_sim::vec_env::{EpisodeSpec, VecEnv};
use sf_sim::{DriveAction, Mode};

use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct ExportOnnxArgs {
    /// A finished job's artifact directory (`config.toml`, `policy.bpk`).
    job: PathBuf,
    /// Where to write the model.
    #[arg(long)]
    out: PathBuf,
    /// Also write this many observations from the job's scenarios (stored cases, every
    /// vehicle driven by the IDM driver) with burn's actions for them to `<out>.check.json`
    /// (0: none).
    #[arg(long, default_value_t = 100)]
    check: usize,
}

pub fn run(ctx: &Ctx, a: ExportOnnxArgs) -> Result<()> {
    let policy = Policy::load(&a.job).map_err(anyhow::Error::msg)?;
    let cfg = &policy.cfg;
    let setup::ResolvedJob { net, obs: spec, sim, .. } = setup::resolve(cfg, None);
    let sim = Arc::new(sim);
    let maps = cfg.env.scenarios.iter().map(|s| ctx.map(s)).collect::<Result<Vec<_>>>()?;
    let segments: Vec<MapSegments> =
        maps.iter().map(|m| MapSegments::build(m, sim.obs.segment_points)).collect();
    let device = sf_nn::device::device(sf_nn::device::DeviceKind::Cpu)?;
    let runner = PolicyRunner::from_bytes(
        &net,
        &spec,
        sim.dt_s,
        &segments.iter().collect::<Vec<_>>(),
        &policy.weights,
        sf_job::PolicyVersion::new(0),
        &device,
    )
    .with_context(|| format!("loading {}/policy.bpk", a.job.display()))?;
    let doc = format!(
        "socialflow {} job `{}`: deterministic action tanh(mean), action `{}` ({} floats), layout {}; map_id indexes env.scenarios = {:?}",
        cfg.kind.as_str(),
        cfg.name,
        net.action.as_str(),
        net.action_dim,
        spec.layout.as_str(),
        cfg.env.scenarios
    );
    let bytes = runner.export_onnx(env!("CARGO_PKG_VERSION"), &doc).map_err(anyhow::Error::msg)?;
    std::fs::write(&a.out, &bytes).with_context(|| format!("writing {}", a.out.display()))?;
    let mut out = json!({"model": a.out, "bytes": bytes.len(), "inputs": sf_nn::onnx::input_names(&spec), "opset": sf_nn::onnx::OPSET});
    if a.check > 0 {
        let path = PathBuf::from(format!("{}.check.json", a.out.display()));
        let (rows, map_ids) = observations(ctx, cfg, &sim, a.check)?;
        let actions = runner.mean(&rows, &map_ids);
        let mut inputs = serde_json::Map::new();
        let b = map_ids.len();
        for (name, r, shape) in spec.blocks() {
            let data: Vec<f32> =
                rows.chunks_exact(spec.len).flat_map(|row| row[r.clone()].to_vec()).collect();
            let mut dims = vec![b];
            dims.extend(shape);
            inputs.insert(name.into(), json!({"shape": dims, "data": data}));
        }
        if spec.layout == sf_sim::Layout::QueryCentric {
            inputs
                .insert("map_id".into(), json!({"shape": [b], "data": map_ids, "dtype": "int64"}));
        }
        let check =
            json!({"inputs": inputs, "action": {"shape": [b, net.action_dim], "data": actions}});
        std::fs::write(&path, serde_json::to_string(&check)?)
            .with_context(|| format!("writing {}", path.display()))?;
        out["check"] = json!(path);
        out["observations"] = json!(b);
    }
    println!("{out}");
    Ok(())
}

/// `n` observation rows spread over the job's scenarios: stored cases with every vehicle a
/// learner driven by the IDM demonstrator, a live row every fifth step. Returns the rows and
/// each row's map index (its scenario's position in `env.scenarios`).
fn observations(
    ctx: &Ctx,
    cfg: &sf_job::JobConfig,
    sim: &Arc<sf_sim::SimConfig>,
    n: usize,
) -> Result<(Vec<f32>, Vec<u32>)> {
    let scenarios = &cfg.env.scenarios;
    if scenarios.is_empty() {
        bail!("the job lists no scenarios");
    }
    let per = n.div_ceil(scenarios.len());
    let (mut rows, mut ids) = (Vec::new(), Vec::new());
    let drivers = Drivers {
        alive: Actor::Demo { noise: 0.0, action: DriveAction::Direct },
        background: None,
        adversary: None,
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    for (k, s) in scenarios.iter().enumerate() {
        let map = ctx.map(s)?;
        let cases = ctx.cases(&map)?;
        let eps = cases
            .cases
            .iter()
            .take(8)
            .enumerate()
            .map(|(i, c)| EpisodeSpec {
                case: c.clone(),
                vehicles: None,
                svo_deg: None,
                tag: i as u64,
            })
            .collect();
        let mut v =
            VecEnv::from_episodes(Arc::clone(&map), Arc::clone(sim), Mode::MultiAgent, 4, eps)
                .map_err(anyhow::Error::msg)?;
        let (mut taken, mut step) = (0, 0);
        while taken < per && !v.is_finished() && rows.len() < n * v.spec.len {
            if step % 5 == 0 {
                let len = v.spec.len;
                for r in (0..v.alive().len()).filter(|&r| v.alive()[r] == 1.0).take(4) {
                    if taken < per && ids.len() < n {
                        rows.extend_from_slice(&v.observations()[r * len..(r + 1) * len]);
                        ids.push(k as u32);
                        taken += 1;
                    }
                }
            }
            let venvs = std::slice::from_mut(&mut v);
            let d = drive::decide(venvs, &drivers, &mut rng);
            drive::apply(venvs, &d);
            step += 1;
        }
    }
    Ok((rows, ids))
}
