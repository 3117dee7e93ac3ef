//! `socialflow render`: a PNG of one frame or a GIF of one episode of a stored case.

use std::fs::File;
use std::io::BufWriter;
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use sf_sim::render::{write_png, ColourBy, GifWriter, Renderer};
use sf_sim::{Env, SimConfig};

use crate::evalflow::{flow_mode, Flow};
use crate::scenarios::Ctx;

#[derive(Args, Debug)]
pub struct RenderArgs {
    #[arg(long)]
    scenario: String,
    #[arg(long, value_enum, default_value = "idm")]
    flow: Flow,
    #[arg(long, default_value_t = 0)]
    case: u32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output file: `.gif` renders the episode, `.png` one frame (`--step`).
    #[arg(long)]
    out: PathBuf,
    /// For PNG output: the decision step to draw.
    #[arg(long, default_value_t = 0)]
    step: u32,
    /// Colour vehicles by SVO instead of role.
    #[arg(long)]
    by_svo: bool,
    /// Longer image side in pixels.
    #[arg(long, default_value_t = 640)]
    size: u32,
}

pub fn run(ctx: &Ctx, a: RenderArgs) -> Result<()> {
    let mode = flow_mode(a.flow)?;
    let map = ctx.map(&a.scenario)?;
    let cases = ctx.cases(&map)?;
    let Some(case) = cases.cases.get(a.case as usize) else {
        bail!("case {} does not exist ({} stored for {})", a.case, cases.cases.len(), a.scenario);
    };
    let cfg = Arc::new(SimConfig::default());
    let mut env = Env::new(map.clone(), cfg);
    env.reset(case, mode, None)?;
    let r = Renderer::new(&map, a.size, if a.by_svo { ColourBy::Svo } else { ColourBy::Role })?;
    let ext = a.out.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    let file = File::create(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let mut out = BufWriter::new(file);
    match ext.as_str() {
        "gif" => {
            let (w, h) = r.size();
            let mut gif = GifWriter::new(&mut out, w, h, 10)?;
            let mut err = None;
            env.run_episode(
                |_, _| {},
                |e| {
                    if err.is_none() {
                        err = gif.push(&r.frame(e)).err();
                    }
                },
            )?;
            if let Some(e) = err {
                return Err(e.into());
            }
        }
        "png" => {
            let mut frame = None;
            env.run_episode(
                |_, _| {},
                |e| {
                    if e.step_index() == a.step {
                        frame = Some(r.frame(e));
                    }
                },
            )?;
            let Some(f) = frame else { bail!("the episode ended before step {}", a.step) };
            write_png(&f, &mut out)?;
        }
        other => bail!("--out must end in .gif or .png, not `.{other}`"),
    }
    eprintln!("wrote {}", a.out.display());
    Ok(())
}
