//! `socialflow plot-curves`: overlays one column of several runs' `curve.csv` (or
//! `validation.csv`) files in one PNG, against the column named by `--x`.
//!
//! Owns: [`PlotArgs`] and reading the CSV columns. Must not: draw itself (`sf_report::plot`).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;
use sf_report::plot::{line_chart, Series};

#[derive(Args, Debug)]
pub struct PlotArgs {
    /// `name=path/to/curve.csv` pairs.
    #[arg(required = true)]
    runs: Vec<String>,
    #[arg(long, default_value = "success")]
    column: String,
    /// The x-axis column: `env_steps` (transitions the learner received) or `updates`.
    #[arg(long, default_value = "env_steps")]
    x: String,
    #[arg(long)]
    title: Option<String>,
    #[arg(long)]
    out: PathBuf,
}

pub fn run(a: PlotArgs) -> Result<()> {
    let mut series = Vec::new();
    let mut names = Vec::new();
    for r in &a.runs {
        let Some((name, path)) = r.split_once('=') else { bail!("run `{r}` must be NAME=PATH") };
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {path}"))?;
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().context("empty curve file")?.split(',').collect();
        let find = |name: &str| {
            header
                .iter()
                .position(|h| *h == name)
                .with_context(|| format!("{path} has no column `{name}`"))
        };
        let (xcol, col) = (find(&a.x)?, find(&a.column)?);
        let mut pts = Vec::new();
        for (k, l) in lines.enumerate() {
            let f: Vec<&str> = l.split(',').collect();
            let x: f64 = f
                .get(xcol)
                .and_then(|v| v.parse().ok())
                .with_context(|| format!("{path} line {}: bad {}", k + 2, a.x))?;
            let y: f64 = f
                .get(col)
                .and_then(|v| v.parse().ok())
                .with_context(|| format!("{path} line {}: bad {}", k + 2, a.column))?;
            pts.push((x, y));
        }
        names.push(name.to_string());
        series.push(pts);
    }
    let s: Vec<Series> =
        names.iter().zip(series).map(|(n, p)| Series { name: n, points: p }).collect();
    let unit = matches!(a.column.as_str(), "success" | "safety" | "speed");
    let x_label = if a.x == "env_steps" { "learner transitions" } else { a.x.as_str() };
    line_chart(
        &a.out,
        a.title.as_deref().unwrap_or(&a.column),
        x_label,
        &a.column,
        &s,
        unit.then_some((0.0, 1.0)),
        (800, 500),
    )?;
    eprintln!("wrote {}", a.out.display());
    Ok(())
}
