//! Charts as PNG: line charts (learning curves, sweeps), heatmaps with medals, grouped bars with
//! 95 % intervals and significance marks, radar charts. Drawn with plotters and an embedded font
//! so they render the same on a machine without fonts.

use std::path::Path;

use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

#[derive(Debug, thiserror::Error)]
#[error("cannot draw {path}: {reason}")]
pub struct PlotError {
    pub path: String,
    pub reason: String,
}

/// One named series of (x, y) points.
pub struct Series<'a> {
    pub name: &'a str,
    pub points: Vec<(f64, f64)>,
}

fn ensure_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // Registration only fails for an unparsable font, which the embedded one is not.
        let _ = register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// Draws series on shared axes into a PNG of `size` pixels.
pub fn line_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
    y_range: Option<(f64, f64)>,
    size: (u32, u32),
) -> Result<(), PlotError> {
    ensure_font();
    let err = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    let pts = series.iter().flat_map(|s| s.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) =
        (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if !x0.is_finite() {
        return Err(err(&"no points to draw"));
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    let (y0, y1) =
        y_range.unwrap_or(if y1 > y0 { (y0, y1 + 0.05 * (y1 - y0)) } else { (y0 - 1.0, y1 + 1.0) });
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(56)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .label_style(("sans-serif", 14))
        .draw()
        .map_err(|e| err(&e))?;
    for (k, s) in series.iter().enumerate() {
        let colour = Palette99::pick(k).to_rgba();
        chart
            .draw_series(LineSeries::new(s.points.iter().copied(), colour.stroke_width(2)))
            .map_err(|e| err(&e))?
            .label(s.name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// A heatmap cell's decoration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mark {
    None,
    /// In-distribution (the ego's training flow): grey, not ranked.
    Diagonal,
    Gold,
    Silver,
    Copper,
}

/// A matrix of values in [0, 1]; `marks[r][c]` decorates each cell. Values print as percent.
pub fn heatmap(
    path: &Path,
    title: &str,
    rows: &[String],
    cols: &[String],
    values: &[Vec<f64>],
    marks: &[Vec<Mark>],
) -> Result<(), PlotError> {
    ensure_font();
    let err = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    let (cw, ch, left, top) = (130i32, 44i32, 190i32, 70i32);
    let size =
        ((left + cw * cols.len() as i32 + 20) as u32, (top + ch * rows.len() as i32 + 20) as u32);
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    root.draw(&Text::new(title.to_string(), (12, 10), ("sans-serif", 20))).map_err(|e| err(&e))?;
    for (c, name) in cols.iter().enumerate() {
        root.draw(&Text::new(
            name.clone(),
            (left + c as i32 * cw + 6, top - 24),
            ("sans-serif", 14),
        ))
        .map_err(|e| err(&e))?;
    }
    for (r, name) in rows.iter().enumerate() {
        let y = top + r as i32 * ch;
        root.draw(&Text::new(name.clone(), (10, y + ch / 2 - 8), ("sans-serif", 14)))
            .map_err(|e| err(&e))?;
        for c in 0..cols.len() {
            let x = left + c as i32 * cw;
            let v = values.get(r).and_then(|row| row.get(c)).copied().unwrap_or(f64::NAN);
            let mark = marks.get(r).and_then(|row| row.get(c)).copied().unwrap_or(Mark::None);
            let fill = match mark {
                Mark::Diagonal => RGBColor(200, 200, 200),
                _ if v.is_finite() => {
                    let t = v.clamp(0.0, 1.0);
                    RGBColor((255.0 - 200.0 * t) as u8, (255.0 - 120.0 * t) as u8, 255)
                }
                _ => RGBColor(240, 240, 240),
            };
            root.draw(&Rectangle::new([(x, y), (x + cw - 2, y + ch - 2)], fill.filled()))
                .map_err(|e| err(&e))?;
            let border = match mark {
                Mark::Gold => Some(RGBColor(212, 175, 55)),
                Mark::Silver => Some(RGBColor(150, 150, 160)),
                Mark::Copper => Some(RGBColor(184, 115, 51)),
                _ => None,
            };
            if let Some(b) = border {
                root.draw(&Rectangle::new(
                    [(x + 1, y + 1), (x + cw - 3, y + ch - 3)],
                    b.stroke_width(4),
                ))
                .map_err(|e| err(&e))?;
            }
            let label = if v.is_finite() { format!("{:.1}", 100.0 * v) } else { "-".into() };
            root.draw(&Text::new(label, (x + cw / 2 - 18, y + ch / 2 - 8), ("sans-serif", 16)))
                .map_err(|e| err(&e))?;
        }
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// One bar: mean, 95 % half-width, and a significance mark drawn above it ("", "*", "**", "***").
#[derive(Clone, Debug)]
pub struct Bar {
    pub mean: f64,
    pub ci95: f64,
    pub stars: String,
}

/// Grouped bars with error bars: `groups[g]` has one bar per name in `series` (values in [0, 1]).
pub fn grouped_bars(
    path: &Path,
    title: &str,
    y_label: &str,
    group_names: &[String],
    series: &[String],
    groups: &[Vec<Bar>],
) -> Result<(), PlotError> {
    ensure_font();
    let err = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    let n_s = series.len().max(1);
    let width = (120 + group_names.len() * (n_s * 26 + 40)).max(520) as u32;
    let root = BitMapBackend::new(path, (width, 440)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let x_max = group_names.len() as f64;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(0.0..x_max.max(1.0), 0.0..1.15)
        .map_err(|e| err(&e))?;
    let names = group_names.to_vec();
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(group_names.len().max(1) * 2 + 1)
        .x_label_formatter(&move |x: &f64| {
            let k = (*x - 0.5).round();
            if (x - 0.5 - k).abs() < 1e-6 && k >= 0.0 {
                names.get(k as usize).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        })
        .y_desc(y_label)
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(|e| err(&e))?;
    let bw = 0.8 / n_s as f64;
    for (si, name) in series.iter().enumerate() {
        let colour = Palette99::pick(si).to_rgba();
        let rects = groups
            .iter()
            .enumerate()
            .filter_map(|(g, bars)| bars.get(si).map(|b| (g, b)))
            .map(|(g, b)| {
                let x = g as f64 + 0.1 + si as f64 * bw;
                Rectangle::new([(x, 0.0), (x + bw * 0.9, b.mean.clamp(0.0, 1.0))], colour.filled())
            });
        chart
            .draw_series(rects)
            .map_err(|e| err(&e))?
            .label(name.as_str())
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], colour.filled()));
        for (g, bars) in groups.iter().enumerate() {
            let Some(b) = bars.get(si) else { continue };
            let xc = g as f64 + 0.1 + si as f64 * bw + bw * 0.45;
            let (lo, hi) = ((b.mean - b.ci95).max(0.0), (b.mean + b.ci95).min(1.0));
            chart
                .draw_series(std::iter::once(PathElement::new(
                    vec![(xc, lo), (xc, hi)],
                    BLACK.stroke_width(1),
                )))
                .map_err(|e| err(&e))?;
            if !b.stars.is_empty() {
                chart
                    .draw_series(std::iter::once(Text::new(
                        b.stars.clone(),
                        (xc - bw * 0.3, hi + 0.06),
                        ("sans-serif", 14),
                    )))
                    .map_err(|e| err(&e))?;
            }
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

/// A radar chart: one polygon per series over the named axes (values in [0, 1]).
pub fn radar(
    path: &Path,
    title: &str,
    axes: &[String],
    series: &[Series<'_>],
) -> Result<(), PlotError> {
    ensure_font();
    let err = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    let root = BitMapBackend::new(path, (520, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    root.draw(&Text::new(title.to_string(), (12, 10), ("sans-serif", 20))).map_err(|e| err(&e))?;
    let (cx, cy, r) = (230.0f64, 250.0f64, 170.0f64);
    let n = axes.len().max(3);
    let at = |k: usize, v: f64| {
        let a = -std::f64::consts::FRAC_PI_2 + 2.0 * std::f64::consts::PI * k as f64 / n as f64;
        ((cx + r * v * a.cos()) as i32, (cy + r * v * a.sin()) as i32)
    };
    for ring in [0.25, 0.5, 0.75, 1.0] {
        let mut pts: Vec<(i32, i32)> = (0..n).map(|k| at(k, ring)).collect();
        pts.push(at(0, ring));
        root.draw(&PathElement::new(pts, RGBColor(210, 210, 210).stroke_width(1)))
            .map_err(|e| err(&e))?;
    }
    for (k, name) in axes.iter().enumerate() {
        root.draw(&PathElement::new(
            vec![at(k, 0.0), at(k, 1.0)],
            RGBColor(180, 180, 180).stroke_width(1),
        ))
        .map_err(|e| err(&e))?;
        let (x, y) = at(k, 1.12);
        root.draw(&Text::new(name.clone(), (x - 24, y - 8), ("sans-serif", 14)))
            .map_err(|e| err(&e))?;
    }
    for (si, s) in series.iter().enumerate() {
        let colour = Palette99::pick(si).to_rgba();
        let mut pts: Vec<(i32, i32)> =
            s.points.iter().enumerate().map(|(k, &(_, v))| at(k, v.clamp(0.0, 1.0))).collect();
        if let Some(&first) = pts.first() {
            pts.push(first);
        }
        root.draw(&PathElement::new(pts, colour.stroke_width(2))).map_err(|e| err(&e))?;
        root.draw(&Rectangle::new(
            [(420, 60 + 20 * si as i32), (434, 72 + 20 * si as i32)],
            colour.filled(),
        ))
        .map_err(|e| err(&e))?;
        root.draw(&Text::new(s.name.to_string(), (440, 58 + 20 * si as i32), ("sans-serif", 13)))
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_a_png() {
        let p = std::env::temp_dir().join(format!("sf-plot-{}.png", std::process::id()));
        let s = [
            Series { name: "a", points: vec![(0.0, 0.1), (1.0, 0.5), (2.0, 0.4)] },
            Series { name: "b", points: vec![(0.0, 0.2), (2.0, 0.9)] },
        ];
        line_chart(&p, "test", "x", "y", &s, Some((0.0, 1.0)), (400, 300)).expect("draw");
        let bytes = std::fs::read(&p).expect("png");
        assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 1000);
        let _ = std::fs::remove_file(&p);
        assert!(line_chart(&p, "empty", "x", "y", &[], None, (100, 100)).is_err());
    }
}
