//! The `socialflow` command line: argument parsing and dispatch to the library crates.
//!
//! Owns: the CLI contract (subcommand names, flags and JSON output fields that scripts read).
//! The lab commands (`ladder`, `probe`, `bench ...`, `plot-curves`) keep their names here, with
//! their arguments and implementations in `sf_lab`; only this dispatch uses `sf_lab`.
//! Must not: hold simulator or training logic; each subcommand is a thin layer over a library.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

mod eval;
mod evalflow;
mod onnx;
mod pipeline;
mod remote;
mod render;
mod scenarios;
mod train;
mod view;

/// Zero-shot transfer of driving policies via socially adversarial traffic flow.
#[derive(Parser, Debug)]
#[command(name = "socialflow", version, about)]
struct Cli {
    /// Directory holding the scenario files (`<name>.json`).
    #[arg(long, global = true, default_value = "configs/scenarios", env = "SOCIALFLOW_SCENARIOS")]
    scenarios: PathBuf,
    /// Directory holding the evaluation case files (`<name>.v1.json`).
    #[arg(long, global = true, default_value = "configs/cases", env = "SOCIALFLOW_CASES")]
    cases_dir: PathBuf,
    /// The terminal's log filter for the commands that run a learner in this process (`train`,
    /// `pipeline --embedded`, `ladder`), whose full log goes to `<data dir>/socialflow.log`:
    /// `warn` by default (or `RUST_LOG`), `info` for every line, `RUST_LOG` syntax.
    #[arg(long, global = true, value_name = "FILTER")]
    log_level: Option<String>,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Trains a job embedded in this process: the learner and N workers over loopback gRPC.
    Train(train::TrainArgs),
    #[command(flatten)]
    Remote(remote::RemoteCmd),
    /// Submits a directory of job configs as one graph (dependencies first) and follows it;
    /// rerun, it resumes where it stopped.
    Pipeline(pipeline::PipelineArgs),
    /// One rung of the learning ladder: trains its ego job per seed, evaluates each policy
    /// against the IDM driver on the same stored cases and checks the rung's gate.
    Ladder(sf_lab::ladder::LadderArgs),
    /// Probes of a job on its IDM demonstrator's data: `--kind critic` scores how well its
    /// critic predicts failures on held-out episodes (AUROC, failure-row error); `--kind
    /// handover` follows a direct-action clone into SAC's updates (drift from IDM's action, the
    /// critic's gradient and best action per component, closed-loop success).
    Probe(sf_lab::probe::ProbeArgs),
    /// Writes a finished job's actor (its deterministic action) as an ONNX model, with a check
    /// file of stored observations and burn's actions for them.
    ExportOnnx(onnx::ExportOnnxArgs),
    /// Runs the learner service (same as the `socialflow-learner` binary).
    Learner(sf_learner::cmd::LearnerArgs),
    /// Runs a rollout worker (same as the `socialflow-worker` binary).
    Worker(sf_worker::cmd::WorkerArgs),
    /// Benchmarks.
    Bench {
        #[command(subcommand)]
        what: sf_lab::bench::BenchCmd,
    },
    /// The paper's evaluation grid (egos x flows x scenarios, sweeps) over stored cases and
    /// seeds; per-episode results appended to `<out>/episodes.csv` (a rerun skips stored cells).
    Eval(eval::EvalArgs),
    /// Builds the reproduction report (markdown and HTML, charts beside them) from `eval` results.
    Report(eval::ReportArgs),
    /// One stored episode of an evaluation grid, replayed into a self-contained browser page
    /// (play, pause, scrub; roles, SVOs, observed neighbours; metrics beside the stored row).
    View(view::ViewArgs),
    /// Success, Safety and Speed of a traffic flow over the stored evaluation cases.
    EvalFlow(evalflow::EvalFlowArgs),
    /// CoPO Stage 2: fits a scenario's SVO Gaussian on a frozen CoPO Stage-1 flow (CEM).
    CopoCoordinator(evalflow::CoordinatorArgs),
    /// Overlays learning curves (CSV) of several runs in one PNG.
    PlotCurves(sf_lab::plot::PlotArgs),
    /// Renders a frame (PNG) or an episode (GIF).
    Render(render::RenderArgs),
    /// Writes the four scenario files from their builders.
    GenScenarios {
        #[arg(long, default_value = "configs/scenarios")]
        out: PathBuf,
    },
    /// Writes the evaluation case files (200 per scenario by default).
    GenCases {
        #[arg(long, default_value = "configs/cases")]
        out: PathBuf,
        #[arg(long, default_value_t = 200)]
        n: u32,
        #[arg(long, default_value_t = 20221)]
        seed: u64,
    },
}

pub fn main() -> ExitCode {
    sf_nn::device::tune_allocator();
    let cli = Cli::parse();
    // One logging set-up for every command; the services' own `--log-json` (and
    // SOCIALFLOW_LOG_JSON, which the container images set) chooses JSON lines.
    let json = match &cli.cmd {
        Cmd::Learner(a) => a.log_json,
        Cmd::Worker(a) => a.log_json,
        _ => false,
    };
    // The commands with a learner in this process: progress on the terminal, the log in a file.
    let log_file = match &cli.cmd {
        Cmd::Train(a) => Some(a.data_dir.join("socialflow.log")),
        Cmd::Pipeline(a) if a.embedded.is_some() => Some(a.data_dir.join("socialflow.log")),
        Cmd::Ladder(a) => Some(a.data_dir.join("socialflow.log")),
        _ => None,
    };
    match &log_file {
        Some(f) => {
            if let Err(e) = sf_service::logging::init_embedded(cli.log_level.as_deref(), f) {
                eprintln!("error: {e}");
                return ExitCode::FAILURE;
            }
        }
        None => sf_service::logging::init(json),
    }
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    let ctx = scenarios::Ctx { scenarios: cli.scenarios, cases: cli.cases_dir };
    match cli.cmd {
        Cmd::Train(a) => train::run(&ctx, a),
        Cmd::Remote(c) => remote::run(c),
        Cmd::Pipeline(a) => pipeline::run(&ctx, a),
        Cmd::Ladder(a) => sf_lab::ladder::run(&ctx, a),
        Cmd::Probe(a) => sf_lab::probe::run(&ctx, a),
        Cmd::ExportOnnx(a) => onnx::run(&ctx, a),
        Cmd::Learner(a) => train::learner(a),
        Cmd::Worker(a) => train::worker(a),
        Cmd::Bench { what } => sf_lab::bench::run(&ctx, what),
        Cmd::Eval(a) => eval::run(&ctx, a),
        Cmd::Report(a) => eval::report(a),
        Cmd::View(a) => view::run(&ctx, a),
        Cmd::EvalFlow(a) => evalflow::run(&ctx, a),
        Cmd::CopoCoordinator(a) => evalflow::coordinator(&ctx, a),
        Cmd::Render(a) => render::run(&ctx, a),
        Cmd::PlotCurves(a) => sf_lab::plot::run(a),
        Cmd::GenScenarios { out } => scenarios::gen_scenarios(&out),
        Cmd::GenCases { out, n, seed } => scenarios::gen_cases(&ctx, &out, n, seed),
    }
    .context("socialflow")
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    /// Catches clashing or malformed argument definitions at test time, not at a user's run.
    #[test]
    fn cli_definition_is_consistent() {
        super::Cli::command().debug_assert();
    }
}
