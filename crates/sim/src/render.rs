//! Rendering of frames (PNG) and episodes (animated GIF).
//!
//! Owns: [`Renderer`] (world-to-pixel transform, drawing of road surface, lane centre-lines,
//! edges, the interaction zone, routes, vehicles coloured by role or SVO, history tails) and
//! the GIF encoder loop. Must not: step the simulator; callers pass environments to draw.

use std::io::Write;

pub use tiny_skia::Pixmap;
use tiny_skia::{
    Color, FillRule, LineCap, LineJoin, Paint, PathBuilder, Stroke, StrokeDash, Transform,
};

use crate::env::{Env, Role};
use crate::geom::P2;
use crate::map::Map;

/// How vehicles are coloured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColourBy {
    /// Ego green, background blue, other learners orange.
    Role,
    /// Hue from the SVO: 0 deg red (egoistic) to 90 deg blue (altruistic); negative purple.
    Svo,
}

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error("cannot allocate a {0}x{1} image")]
    Size(u32, u32),
    #[error("cannot write image: {0}")]
    Io(#[from] std::io::Error),
    #[error("cannot encode image: {0}")]
    Encode(String),
}

/// Draws one map at a fixed scale.
pub struct Renderer {
    min: P2,
    px_per_m: f32,
    width: u32,
    height: u32,
    background: Pixmap,
    pub colour_by: ColourBy,
}

fn rgba(r: u8, g: u8, b: u8, a: u8) -> Paint<'static> {
    let mut p = Paint::default();
    p.set_color(Color::from_rgba8(r, g, b, a));
    p.anti_alias = true;
    p
}

impl Renderer {
    /// A renderer whose longer side is `max_px` pixels.
    pub fn new(map: &Map, max_px: u32, colour_by: ColourBy) -> Result<Self, RenderError> {
        let (w_m, h_m) =
            (map.boundary.max[0] - map.boundary.min[0], map.boundary.max[1] - map.boundary.min[1]);
        let px_per_m = max_px as f32 / w_m.max(h_m);
        let (width, height) = ((w_m * px_per_m).ceil() as u32, (h_m * px_per_m).ceil() as u32);
        let mut r = Self {
            min: map.boundary.min,
            px_per_m,
            width,
            height,
            background: Pixmap::new(width, height).ok_or(RenderError::Size(width, height))?,
            colour_by,
        };
        r.background = r.draw_map(map)?;
        Ok(r)
    }

    fn px(&self, p: P2) -> (f32, f32) {
        (
            (p[0] - self.min[0]) * self.px_per_m,
            self.height as f32 - (p[1] - self.min[1]) * self.px_per_m,
        )
    }

    fn path(&self, pts: &[P2], close: bool) -> Option<tiny_skia::Path> {
        let mut pb = PathBuilder::new();
        for (k, p) in pts.iter().enumerate() {
            let (x, y) = self.px(*p);
            if k == 0 {
                pb.move_to(x, y)
            } else {
                pb.line_to(x, y)
            }
        }
        if close {
            pb.close();
        }
        pb.finish()
    }

    fn stroke(&self, width_m: f32, dash: bool) -> Stroke {
        Stroke {
            width: (width_m * self.px_per_m).max(1.0),
            line_cap: LineCap::Round,
            line_join: LineJoin::Round,
            dash: if dash { StrokeDash::new(vec![6.0, 6.0], 0.0) } else { None },
            ..Stroke::default()
        }
    }

    fn draw_map(&self, map: &Map) -> Result<Pixmap, RenderError> {
        let mut pm = Pixmap::new(self.width, self.height)
            .ok_or(RenderError::Size(self.width, self.height))?;
        pm.fill(Color::from_rgba8(34, 85, 51, 255));
        let t = Transform::identity();
        for l in &map.lanes {
            if let Some(p) = self.path(&l.centre, false) {
                pm.stroke_path(
                    &p,
                    &rgba(70, 70, 75, 255),
                    &Stroke { line_cap: LineCap::Butt, ..self.stroke(l.width_m + 0.1, false) },
                    t,
                    None,
                );
            }
        }
        if let Some(p) = self.path(&map.zone, true) {
            pm.fill_path(&p, &rgba(255, 210, 0, 45), FillRule::EvenOdd, t, None);
            pm.stroke_path(&p, &rgba(255, 210, 0, 160), &self.stroke(0.3, true), t, None);
        }
        for l in &map.lanes {
            if let Some(p) = self.path(&l.centre, false) {
                pm.stroke_path(&p, &rgba(200, 200, 200, 90), &self.stroke(0.15, true), t, None);
            }
        }
        for e in &map.edges {
            if let Some(p) = self.path(e, false) {
                pm.stroke_path(&p, &rgba(245, 245, 245, 255), &self.stroke(0.35, false), t, None);
            }
        }
        Ok(pm)
    }

    fn colour(&self, i: usize, role: Role, svo_deg: f32) -> (u8, u8, u8) {
        match self.colour_by {
            ColourBy::Role => match (i, role) {
                (0, Role::Learner) => (50, 205, 50),
                (_, Role::Learner) => (255, 140, 0),
                _ => (0, 160, 255),
            },
            ColourBy::Svo => {
                if svo_deg < 0.0 {
                    (160, 32, 240)
                } else {
                    let t = (svo_deg / 90.0).clamp(0.0, 1.0);
                    ((230.0 * (1.0 - t) + 20.0) as u8, 60, (230.0 * t + 20.0) as u8)
                }
            }
        }
    }

    /// Draws the current state of `env` over the map: the live vehicles and those that ended on
    /// the last step (where they ended, so an episode's last frame shows how it ended). The ego
    /// of an ego episode (agent 0, the one learner among background vehicles) gets a thick green
    /// outline, whatever the colouring.
    pub fn frame(&self, env: &Env) -> Pixmap {
        let mut pm = self.background.clone();
        let t = Transform::identity();
        let vp = &env.cfg.vehicle;
        let agents = env.agents();
        let ego = agents.first().is_some_and(|a| a.role == Role::Learner)
            && agents.iter().any(|a| a.role == Role::Background);
        for (i, a) in agents.iter().enumerate() {
            if !a.alive && !env.ended_now().get(i).copied().unwrap_or(false) {
                continue;
            }
            let (r, g, b) = self.colour(i, a.role, a.svo_deg);
            let route = &env.map.routes[a.route as usize];
            if let Some(p) = self.path(&route.points[a.seg.min(route.points.len() - 1)..], false) {
                pm.stroke_path(&p, &rgba(r, g, b, 70), &self.stroke(0.25, false), t, None);
            }
            for k in 1..env.cfg.obs.history {
                let h = a.history(k);
                let (x, y) = self.px([h[0], h[1]]);
                let rad = (0.5 * self.px_per_m).max(1.0);
                if let Some(c) = PathBuilder::from_circle(x, y, rad) {
                    let alpha = (180.0 * (1.0 - k as f32 / env.cfg.obs.history as f32)) as u8;
                    pm.fill_path(&c, &rgba(r, g, b, alpha), FillRule::Winding, t, None);
                }
            }
            let f = a.frame();
            let (hl, hw) = (vp.length_m / 2.0, vp.width_m / 2.0);
            let corners = [[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]].map(|c| f.to_world(c));
            if let Some(p) = self.path(&corners, true) {
                pm.fill_path(&p, &rgba(r, g, b, 255), FillRule::Winding, t, None);
                let (outline, width_m) = if ego && i == 0 {
                    (rgba(50, 205, 50, 255), 0.6)
                } else {
                    (rgba(20, 20, 20, 255), 0.12)
                };
                pm.stroke_path(&p, &outline, &self.stroke(width_m, false), t, None);
            }
            let nose = [
                f.to_world([hl - 0.6, hw - 0.3]),
                f.to_world([hl - 0.1, 0.0]),
                f.to_world([hl - 0.6, -hw + 0.3]),
            ];
            if let Some(p) = self.path(&nose, true) {
                pm.fill_path(&p, &rgba(255, 255, 255, 220), FillRule::Winding, t, None);
            }
        }
        pm
    }

    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
}

/// Frames placed left to right with a 4-pixel white gap (comparisons of the same case under
/// different flows). `None` if there are no frames or a size is invalid.
pub fn side_by_side(frames: &[&Pixmap]) -> Option<Pixmap> {
    tile(frames, false)
}

/// Frames placed top to bottom with a 4-pixel white gap.
pub fn stacked(frames: &[&Pixmap]) -> Option<Pixmap> {
    tile(frames, true)
}

/// Frames of the same map composed for viewing: stacked if a frame is more than twice as wide
/// as tall (the bottleneck's long road), else side by side.
pub fn panels(frames: &[&Pixmap]) -> Option<Pixmap> {
    let f = frames.first()?;
    tile(frames, f.width() > 2 * f.height())
}

fn tile(frames: &[&Pixmap], down: bool) -> Option<Pixmap> {
    let gap = 4;
    let gaps = gap * frames.len().saturating_sub(1) as u32;
    let (w, h) = if down {
        (
            frames.iter().map(|f| f.width()).max()?,
            frames.iter().map(|f| f.height()).sum::<u32>() + gaps,
        )
    } else {
        (
            frames.iter().map(|f| f.width()).sum::<u32>() + gaps,
            frames.iter().map(|f| f.height()).max()?,
        )
    };
    let mut out = Pixmap::new(w, h)?;
    out.fill(tiny_skia::Color::WHITE);
    let mut at = 0i32;
    for f in frames {
        let (x, y) = if down { (0, at) } else { (at, 0) };
        out.draw_pixmap(
            x,
            y,
            f.as_ref(),
            &tiny_skia::PixmapPaint::default(),
            Transform::identity(),
            None,
        );
        at += (if down { f.height() } else { f.width() } + gap) as i32;
    }
    Some(out)
}

/// Writes one frame as PNG.
pub fn write_png(pm: &Pixmap, out: &mut impl Write) -> Result<(), RenderError> {
    let bytes = pm.encode_png().map_err(|e| RenderError::Encode(e.to_string()))?;
    out.write_all(&bytes)?;
    Ok(())
}

/// Streams frames into an animated GIF.
pub struct GifWriter<W: Write> {
    enc: gif::Encoder<W>,
    delay_cs: u16,
}

impl<W: Write> GifWriter<W> {
    /// `delay_cs`: hundredths of a second per frame.
    pub fn new(out: W, width: u32, height: u32, delay_cs: u16) -> Result<Self, RenderError> {
        let to16 = |v: u32| u16::try_from(v).map_err(|_| RenderError::Size(width, height));
        let mut enc =
            gif::Encoder::new(out, to16(width)?, to16(height)?, &[]).map_err(encode_err)?;
        enc.set_repeat(gif::Repeat::Infinite).map_err(encode_err)?;
        Ok(Self { enc, delay_cs })
    }

    pub fn push(&mut self, pm: &Pixmap) -> Result<(), RenderError> {
        let mut data = pm.data().to_vec();
        let mut f =
            gif::Frame::from_rgba_speed(pm.width() as u16, pm.height() as u16, &mut data, 10);
        f.delay = self.delay_cs;
        self.enc.write_frame(&f).map_err(encode_err)
    }
}

/// The GIF encoder's error, with a failed write kept as its `io::Error` (a full disk stays a
/// storage fault to whoever reads the chain).
fn encode_err(e: gif::EncodingError) -> RenderError {
    match e {
        gif::EncodingError::Io(io) => RenderError::Io(io),
        e => RenderError::Encode(e.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wide_panels_stack_and_others_sit_side_by_side() {
        let (wide, tall) = (Pixmap::new(100, 20).expect("px"), Pixmap::new(50, 40).expect("px"));
        let s = panels(&[&wide, &wide]).expect("stacked");
        assert_eq!((s.width(), s.height()), (100, 44));
        let s = panels(&[&tall, &tall, &tall]).expect("side by side");
        assert_eq!((s.width(), s.height()), (158, 40));
        assert_eq!(side_by_side(&[&wide]).map(|p| (p.width(), p.height())), Some((100, 20)));
        assert!(panels(&[]).is_none());
    }

    /// Pixels of the ego's outline colour.
    fn green(pm: &Pixmap) -> usize {
        pm.pixels().iter().filter(|p| (p.red(), p.green(), p.blue()) == (50, 205, 50)).count()
    }

    /// The last frame of an ego episode shows the ego where it ended, outlined; a flow's frame
    /// outlines nobody.
    #[test]
    fn the_ego_is_outlined_and_drawn_where_its_episode_ended() {
        use crate::case::{Case, CaseVehicle};
        use crate::env::{Controller, Mode};
        let map = std::sync::Arc::new(
            Map::from_file(&crate::scenarios::bottleneck(), "bottleneck").expect("map"),
        );
        let spawn =
            |k: usize| map.spawns.iter().position(|s| s.routes.contains(&0)).expect("spawn") + k;
        let case = Case {
            id: 0,
            vehicles: [0, 3]
                .map(|k| CaseVehicle {
                    spawn: spawn(k) as u32,
                    route: 0,
                    svo_deg: 0.0,
                    max_speed_mps: None,
                })
                .to_vec(),
        };
        let r = Renderer::new(&map, 960, ColourBy::Svo).expect("renderer");
        let mut env = Env::new(map.clone(), std::sync::Arc::new(crate::SimConfig::default()));
        env.reset(&case, Mode::Ego { background: Controller::Idm }, None).expect("reset");
        assert!(green(&r.frame(&env)) > 0, "the ego is outlined");
        let idle = vec![crate::Action::default(); 2];
        while !env.done() {
            env.step(&idle).expect("step");
        }
        assert!(!env.agents()[0].alive);
        assert!(green(&r.frame(&env)) > 0, "the ego is drawn where it ended");
        env.reset(&case, Mode::MultiAgent, None).expect("reset");
        assert_eq!(green(&r.frame(&env)), 0, "no ego among learners only");
    }

    /// A writer on a full disk.
    struct Full;

    impl Write for Full {
        fn write(&mut self, _: &[u8]) -> std::io::Result<usize> {
            Err(std::io::Error::from_raw_os_error(28))
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    /// A GIF written to a full disk fails with the disk's `io::Error` as the source, not its
    /// text, so the service can pause the job instead of failing it.
    #[test]
    fn a_gif_on_a_full_disk_keeps_its_io_error() {
        let e = match GifWriter::new(Full, 8, 8, 10) {
            Err(e) => e,
            Ok(mut w) => w.push(&Pixmap::new(8, 8).expect("pixmap")).expect_err("no frame written"),
        };
        let io = match &e {
            RenderError::Io(io) => io,
            other => panic!("not an io error: {other}"),
        };
        assert_eq!(io.raw_os_error(), Some(28));
        assert!(std::error::Error::source(&e).is_some(), "{e}");
    }
}
