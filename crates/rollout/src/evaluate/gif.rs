//! GIFs of one stored case: each flow side by side, alone or around one ego ([`render_gif`]),
//! and a grid's configured GIFs ([`Resolved::render_gifs`]). Must not: decide what a cell runs
//! (the parent's `cell_setup` does, so a GIF shows what its cell measures).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use sf_job::eval::Cell;
use sf_sim::case::CaseFile;
use sf_sim::Map;

use super::{io, EgoDef, EvalError, FlowDef, Resolved, Runners};

/// One episode of stored case `case` with `ego` (its name and policy) under each of `flows`, or
/// each flow alone with no ego, rendered into a GIF at `path`: one panel per flow whose longer
/// side is `size_px`, side by side (stacked for maps more than twice as wide as tall).
#[allow(clippy::too_many_arguments)]
pub fn render_gif(
    ego: Option<(&str, &EgoDef)>,
    flows: &[(&str, &FlowDef)],
    case: u32,
    map: &Arc<Map>,
    cases: &CaseFile,
    runners: &mut Runners,
    path: &Path,
    size_px: u32,
) -> Result<(), EvalError> {
    use sf_sim::render::{panels, ColourBy, GifWriter, Renderer};
    if case as usize >= cases.cases.len() {
        return Err(EvalError::Misfit(format!(
            "experiments.gifs.case {case} is not stored for {}",
            map.name
        )));
    }
    let renderer = Renderer::new(map, size_px, ColourBy::Svo)?;
    let mut films = Vec::new();
    for (name, flow) in flows {
        let cell = Cell {
            experiment: "gif".into(),
            ego: ego.map_or_else(String::new, |(n, _)| n.into()),
            flow: name.to_string(),
            scenario: map.name.clone(),
            svo_deg: None,
            vehicles: None,
        };
        // Seed 0's episode of the case, as a cell runs it.
        let mut frames = Vec::new();
        super::replay_episode(
            &cell,
            map,
            cases,
            case as usize,
            0,
            flow,
            ego.map(|(_, e)| e),
            runners,
            |env, _| frames.push(renderer.frame(env)),
        )?;
        films.push(frames);
    }
    let len = films.iter().map(Vec::len).max().unwrap_or(0);
    let file = std::fs::File::create(path).map_err(io("creating", path))?;
    let mut out = Some(std::io::BufWriter::new(file));
    let mut gif: Option<GifWriter<_>> = None;
    for k in 0..len {
        let row: Vec<&sf_sim::render::Pixmap> =
            films.iter().filter_map(|f| f.get(k).or_else(|| f.last())).collect();
        let pm = panels(&row).ok_or_else(|| EvalError::Run("composing frames".into()))?;
        if let Some(o) = out.take() {
            gif = Some(GifWriter::new(o, pm.width(), pm.height(), 10)?);
        }
        if let Some(w) = gif.as_mut() {
            w.push(&pm)?;
        }
    }
    Ok(())
}

impl Resolved {
    /// The config's GIFs (`gif-<scenario>.gif` in `out`) not already there; the paths written.
    pub fn render_gifs(
        &self,
        g: &sf_job::eval::Gifs,
        out: &Path,
        maps: &BTreeMap<String, (Arc<Map>, CaseFile)>,
        runners: &mut Runners,
    ) -> Result<Vec<std::path::PathBuf>, EvalError> {
        let ego = if g.ego.is_empty() {
            None
        } else {
            Some(self.egos.get(&g.ego).map(|e| (g.ego.as_str(), e)).ok_or_else(|| {
                EvalError::Misfit(format!("experiments.gifs.ego `{}` is not in the grid", g.ego))
            })?)
        };
        let flows = g
            .flows
            .iter()
            .map(|f| {
                self.flows.get(f).map(|d| (f.as_str(), d)).ok_or_else(|| {
                    EvalError::Misfit(format!("experiments.gifs.flows: `{f}` is not in the grid"))
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut written = Vec::new();
        for s in &g.scenarios {
            let path = out.join(format!("gif-{s}.gif"));
            if path.exists() {
                continue;
            }
            let (map, cases) = maps
                .get(s)
                .ok_or_else(|| EvalError::Misfit(format!("scenario `{s}` is not loaded")))?;
            render_gif(ego, &flows, g.case, map, cases, runners, &path, g.size_px())
                .map_err(|e| EvalError::Gif { path: path.clone(), source: Box::new(e) })?;
            written.push(path);
        }
        Ok(written)
    }
}
