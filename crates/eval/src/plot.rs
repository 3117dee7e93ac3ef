//! Line charts as PNG (learning curves, sweeps), drawn with plotters and an embedded font so
//! they render the same on a machine without fonts.

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
pub fn line_chart(path: &Path, title: &str, x_label: &str, y_label: &str, series: &[Series<'_>], y_range: Option<(f64, f64)>, size: (u32, u32)) -> Result<(), PlotError> {
    ensure_font();
    let err = |e: &dyn std::fmt::Display| PlotError { path: path.display().to_string(), reason: e.to_string() };
    let pts = series.iter().flat_map(|s| s.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
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
    let (y0, y1) = y_range.unwrap_or_else(|| if y1 > y0 { (y0, y1 + 0.05 * (y1 - y0)) } else { (y0 - 1.0, y1 + 1.0) });
    let root = BitMapBackend::new(path, size).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(56)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(|e| err(&e))?;
    chart.configure_mesh().x_desc(x_label).y_desc(y_label).label_style(("sans-serif", 14)).draw().map_err(|e| err(&e))?;
    for (k, s) in series.iter().enumerate() {
        let colour = Palette99::pick(k).to_rgba();
        chart
            .draw_series(LineSeries::new(s.points.iter().copied(), colour.stroke_width(2)))
            .map_err(|e| err(&e))?
            .label(s.name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2)));
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).label_font(("sans-serif", 14)).draw().map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_a_png() {
        let p = std::env::temp_dir().join(format!("sf-plot-{}.png", std::process::id()));
        let s = [Series { name: "a", points: vec![(0.0, 0.1), (1.0, 0.5), (2.0, 0.4)] }, Series { name: "b", points: vec![(0.0, 0.2), (2.0, 0.9)] }];
        line_chart(&p, "test", "x", "y", &s, Some((0.0, 1.0)), (400, 300)).expect("draw");
        let bytes = std::fs::read(&p).expect("png");
        assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 1000);
        let _ = std::fs::remove_file(&p);
        assert!(line_chart(&p, "empty", "x", "y", &[], None, (100, 100)).is_err());
    }
}
