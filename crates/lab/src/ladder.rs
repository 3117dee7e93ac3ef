//! `socialflow ladder <rung.toml>`: one rung of the learning ladder. Trains the rung's job once
//! per training seed (embedded learner and workers, reusing a finished job of the same name in
//! `--data-dir`), evaluates each final policy with its mean action (or, `eval.sampled`, its
//! sampled actions) on the stored cases against the IDM driver in the ego's seat (the same
//! episodes, paired), checks the rung's gate and writes the curves, episodes and a summary to
//! `--out`. With `--scripted idm-mobil` it trains nothing and judges IDM with MOBIL's lane
//! changes in the policy's seat instead (a reference for rungs that need steering).
//!
//! Owns: the rung file format ([`Rung`]), the paired ego-vs-IDM evaluation and the gate.
//! Must not: change how jobs train (it submits ordinary job configs) or how episodes run
//! (`sf_rollout::drive`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use sf_embedded::client::watch;
use sf_embedded::runs::{find_job, load_job};
use sf_embedded::{runtime, Ctx, Embedded};
use sf_job::{JobConfig, JobState};
use sf_rollout::evaluate::{Policy, Runners};
use sf_service::client::{list, submit};
use sf_sim::vec_env::{CaseDraw, SlowLeader};
use sf_sim::{CaseFile, Map, SimConfig};

mod episodes;
mod report;

use episodes::{evaluate, render_gifs, Driver};

use report::{
    check_curve, plot_curves, plot_validation, read_curve, selected_updates, summarise, summary_md,
    CurvePt,
};

#[derive(Args, Debug)]
pub struct LadderArgs {
    /// The rung (TOML), e.g. configs/ladder/l3-roundabout.toml.
    pub rung: PathBuf,
    /// Job store of the embedded learner; a finished job of a seed's name there is reused.
    #[arg(long, default_value = "runs/ladder")]
    pub data_dir: PathBuf,
    /// Where the curves, episodes and summary go (default docs/ladder/<rung name>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Training seeds (default: the rung's).
    #[arg(long, value_delimiter = ',')]
    pub seeds: Option<Vec<u64>>,
    /// Rollout workers in this process.
    #[arg(long, default_value_t = 2)]
    pub workers: usize,
    /// Evaluate the jobs already trained; train nothing.
    #[arg(long)]
    pub eval_only: bool,
    /// Put a scripted driver in the policy's seat instead of training: `idm-mobil` (IDM with
    /// MOBIL's lane changes). Its episodes, the IDM ego's and the gate's verdict (without the
    /// curve check: there is no curve) go to `--out`.
    #[arg(long, conflicts_with_all = ["seeds", "eval_only"])]
    pub scripted: Option<String>,
    /// Override a setting of the rung's job config (repeatable): `--set sac.lr_actor=1e-4`;
    /// validated like the file and recorded in each seed's stored config.
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    pub set: Vec<String>,
}

/// A rung of the ladder: a job, its training seeds, an evaluation and a gate.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rung {
    /// L0 ... L5.
    pub rung: String,
    pub name: String,
    /// The job config, relative to the rung file.
    pub job: PathBuf,
    pub seeds: Vec<u64>,
    pub eval: RungEval,
    pub gate: Gate,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RungEval {
    pub scenarios: Vec<String>,
    /// The first N stored cases of each scenario.
    pub cases: u32,
    pub seeds: u32,
    /// Vehicles per case (ego first), cycled over the cases: case i keeps
    /// `vehicles[i % len]` of its stored vehicles. Empty: as stored.
    #[serde(default)]
    pub vehicles: Vec<usize>,
    #[serde(default = "d_envs")]
    pub envs: usize,
    /// Evaluate on `cases` generated cases per scenario instead of the stored ones.
    #[serde(default)]
    pub generate: Option<Generate>,
    /// Drive the policy's sampled actions (what its training curve measures) instead of its
    /// mean action; the IDM driver's episodes are the same either way.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub sampled: bool,
    /// GIFs of the first `gifs` evaluated cases of the first scenario: each seed's policy
    /// (`seed-<s>/gif-<scenario>-case-<c>.gif`) and the IDM ego (`gif-<scenario>-case-<c>-idm.gif`).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub gifs: u32,
}

fn is_zero(n: &u32) -> bool {
    *n == 0
}

/// Generated evaluation cases: vehicle counts uniform in `vehicles`, with probability
/// `conflict_share` a case in which the IDM ego collides, and with `slow_leader` a slow
/// vehicle ahead of the ego (`sf_sim::vec_env::draw_case`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Generate {
    pub vehicles: [u32; 2],
    #[serde(default)]
    pub conflict_share: f32,
    pub seed: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slow_leader: Option<SlowLeader>,
}

impl Generate {
    fn draw(&self) -> CaseDraw {
        CaseDraw { conflict_share: Some(self.conflict_share), slow_leader: self.slow_leader }
    }
}

fn d_envs() -> usize {
    40
}

/// What every training seed's policy must reach (fields left out are not checked).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Gate {
    /// Success over all evaluated episodes.
    pub min_success: Option<f64>,
    /// Success minus the IDM ego's on the same episodes.
    pub min_success_gain: Option<f64>,
    /// The IDM ego's collision rate minus the policy's.
    pub min_collision_drop: Option<f64>,
    /// Failures other than collisions (off road, off route, wrong lane).
    pub max_other_failures: Option<f64>,
    /// Paired t-test of success against the IDM ego.
    pub max_p: Option<f64>,
    /// Mean speed over the IDM ego's, minus 1 (0.2: at least 20 % faster).
    pub min_speed_gain: Option<f64>,
    /// The share of episodes in which the ego left its route's lane (a lane change).
    pub min_lane_change: Option<f64>,
    /// The training curve's rolling success at every point from `curve_from_updates` updates on.
    pub curve_min_success: Option<f64>,
    pub curve_from_updates: u64,
    /// The training curve reaches `curve_reach_success` within `curve_reach_updates` updates.
    pub curve_reach_success: Option<f64>,
    pub curve_reach_updates: u64,
}

impl Rung {
    pub fn load(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let r: Rung = toml::from_str(&text).with_context(|| format!("{}", path.display()))?;
        if r.seeds.is_empty() {
            bail!("{}: `seeds` is empty", path.display());
        }
        if r.eval.scenarios.is_empty() || r.eval.cases == 0 || r.eval.seeds == 0 || r.eval.envs == 0
        {
            bail!("{}: `eval` needs scenarios and positive cases, seeds and envs", path.display());
        }
        if let Some(g) = &r.eval.generate {
            if g.vehicles[0] == 0
                || g.vehicles[0] > g.vehicles[1]
                || !(0.0..=1.0).contains(&g.conflict_share)
            {
                bail!("{}: `eval.generate` needs 1 <= vehicles[0] <= vehicles[1] and conflict_share in [0, 1]", path.display());
            }
            if let Some(Err(why)) = g
                .slow_leader
                .map(|s| s.check(sf_sim::vehicle::VehicleParams::default().max_speed_mps))
            {
                bail!("{}: `eval.generate.slow_leader.{why}", path.display());
            }
        }
        if r.eval.vehicles.contains(&0) {
            bail!("{}: `eval.vehicles` entries must be positive", path.display());
        }
        Ok(r)
    }
}

/// One evaluated episode of the ladder: a policy (or the IDM ego) on a case and seed.
#[derive(Clone, Debug, Serialize)]
struct Row {
    train_seed: u64,
    driver: &'static str,
    scenario: String,
    case: u32,
    seed: u32,
    vehicles: usize,
    success: f32,
    collision: f32,
    other_failure: f32,
    timeout: f32,
    speed: f32,
    lane_change: f32,
}

impl Row {
    const HEADER: &'static str = "train_seed,driver,scenario,case,seed,vehicles,success,collision,other_failure,timeout,speed,lane_change";

    fn csv(&self) -> String {
        format!(
            "{},{},{},{},{},{},{},{},{},{},{},{}",
            self.train_seed,
            self.driver,
            self.scenario,
            self.case,
            self.seed,
            self.vehicles,
            self.success,
            self.collision,
            self.other_failure,
            self.timeout,
            self.speed,
            self.lane_change
        )
    }
}

/// One seed's verdict.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct SeedSummary {
    train_seed: u64,
    job_dir: String,
    episodes: usize,
    /// Stored cases the paired test is over (its unit; absent in summaries written before).
    #[serde(default)]
    cases: usize,
    success: f64,
    idm_success: f64,
    collision: f64,
    idm_collision: f64,
    other_failures: f64,
    speed: f64,
    idm_speed: f64,
    /// Share of the policy's episodes with a lane change (absent in summaries written before
    /// it was measured).
    #[serde(default)]
    lane_change: f64,
    p_value: f64,
    per_scenario: BTreeMap<String, [f64; 2]>,
    updates: u64,
    /// With `[validation]`: the update whose actor became the final policy.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    selected_updates: Option<u64>,
    wall_s: f64,
    passed: bool,
    failed_checks: Vec<String>,
}

pub fn run(dirs: &Ctx, a: LadderArgs) -> Result<()> {
    let rung = Rung::load(&a.rung)?;
    let job_path = a.rung.parent().unwrap_or(Path::new(".")).join(&rung.job);
    let text = std::fs::read_to_string(&job_path)
        .with_context(|| format!("reading {}", job_path.display()))?;
    let text =
        sf_job::overrides::apply(&text, &a.set).with_context(|| job_path.display().to_string())?;
    let base = JobConfig::from_toml(&text).with_context(|| {
        format!("{}{}", job_path.display(), if a.set.is_empty() { "" } else { " with --set" })
    })?;
    if base.kind != sf_job::config::JobKind::Ego {
        bail!("{}: a rung trains an ego job, not a {} job", job_path.display(), base.kind.as_str());
    }
    let out = a.out.clone().unwrap_or_else(|| PathBuf::from("docs/ladder").join(&rung.name));
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let seeds = a.seeds.clone().unwrap_or_else(|| rung.seeds.clone());
    let maps = rung_cases(dirs, &rung)?;
    if let Some(name) = &a.scripted {
        return run_scripted(&rung, &maps, name, &out);
    }

    // 1. Train (or find) one job per seed.
    let mut jobs = Vec::new();
    for &seed in &seeds {
        let mut cfg = base.clone();
        cfg.name = format!("{}-s{seed}", base.name);
        cfg.sac.seed = seed;
        jobs.push((seed, trained_policy(dirs, &a, &cfg)?));
    }

    // 2. Evaluate each against the IDM ego on the same episodes.
    let mut rows = Vec::new();
    let mut summaries = Vec::new();
    let mut runners = Runners::new(
        sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).map_err(anyhow::Error::msg)?,
    );
    let mut curves = Vec::new();
    // The IDM ego does not depend on the training seed: its episodes run once.
    let mut idm = Vec::new();
    for (map, cases) in &maps {
        idm.extend(evaluate(&rung.eval, 0, map, cases, Driver::Idm, &mut runners)?);
    }
    if let Some((map, cases)) = maps.first() {
        render_gifs(&rung.eval, map, cases, Driver::Idm, &mut runners, &out)?;
    }
    for (seed, policy) in &jobs {
        let (summary, curve, mine) =
            evaluate_seed(&rung, *seed, policy, &maps, &idm, &mut runners, &out)?;
        summaries.push(summary);
        curves.push((*seed, curve));
        rows.extend(mine);
    }

    // 3. Write episodes, summary and curves, keeping the seeds of earlier runs into `out` that
    // this run did not redo (a rung run seed by seed adds up to one summary).
    let ran: BTreeSet<u64> = summaries.iter().map(|s| s.train_seed).collect();
    let (kept, kept_rows) = earlier_seeds(&out, &rung, &ran)?;
    for s in kept {
        curves.push((
            s.train_seed,
            read_curve(&out.join(format!("seed-{}", s.train_seed)).join("curve.csv"))?,
        ));
        summaries.push(s);
    }
    summaries.sort_by_key(|s| s.train_seed);
    curves.sort_by_key(|c| c.0);
    let lines = kept_rows.into_iter().chain(rows.iter().map(Row::csv));
    let csv: String =
        std::iter::once(Row::HEADER.to_string()).chain(lines).map(|l| l + "\n").collect();
    std::fs::write(out.join("episodes.csv"), csv)?;
    let passed = summaries.iter().all(|s| s.passed);
    let json = serde_json::json!({"rung": rung.rung, "name": rung.name, "gate": rung.gate, "eval": rung.eval, "passed": passed, "seeds": summaries});
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&json)?)?;
    std::fs::write(out.join("summary.md"), summary_md(&rung, &summaries, passed))?;
    plot_curves(&out, &rung, &curves)?;
    plot_validation(&out, &rung, &summaries)?;
    println!(
        "{}",
        serde_json::json!({"rung": rung.rung, "name": rung.name, "passed": passed, "out": out.display().to_string()})
    );
    print!("{}", summary_md(&rung, &summaries, passed));
    Ok(())
}

/// `--scripted`: the rung's episodes with a scripted driver in the policy's seat, paired with
/// the IDM ego's, judged by the gate (no curve: the curve check is not made), into `out`
/// (`episodes.csv` with both drivers' rows, `summary.json`, `summary.md`, GIFs of both).
fn run_scripted(rung: &Rung, maps: &[(Arc<Map>, CaseFile)], name: &str, out: &Path) -> Result<()> {
    let driver = match name {
        sf_job::eval::IDM_MOBIL => Driver::IdmMobil,
        _ => bail!(
            "--scripted: `{name}` is not a scripted driver (expected `{}`)",
            sf_job::eval::IDM_MOBIL
        ),
    };
    let mut runners = Runners::new(
        sf_nn::device::device(sf_nn::device::DeviceKind::Cpu).map_err(anyhow::Error::msg)?,
    );
    let mut rows = Vec::new();
    for (map, cases) in maps {
        rows.extend(evaluate(&rung.eval, 0, map, cases, driver, &mut runners)?);
        rows.extend(evaluate(&rung.eval, 0, map, cases, Driver::Idm, &mut runners)?);
    }
    if let Some((map, cases)) = maps.first() {
        for d in [driver, Driver::Idm] {
            render_gifs(&rung.eval, map, cases, d, &mut runners, out)?;
        }
    }
    let s = summarise(0, Path::new(name), &rows, &rung.gate, 0, 0.0, driver.name())?;
    let lines = std::iter::once(Row::HEADER.to_string()).chain(rows.iter().map(Row::csv));
    std::fs::write(out.join("episodes.csv"), lines.map(|l| l + "\n").collect::<String>())?;
    let passed = s.passed;
    let json = serde_json::json!({"rung": rung.rung, "name": rung.name, "scripted": name, "gate": rung.gate, "eval": rung.eval, "passed": passed, "seeds": [&s]});
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&json)?)?;
    let md = format!(
        "The scripted driver `{name}` in the policy's seat (no training; the gate without its \
         curve check). Seed 0 stands for the driver.\n\n{}",
        summary_md(rung, std::slice::from_ref(&s), passed)
    );
    std::fs::write(out.join("summary.md"), &md)?;
    print!("{md}");
    Ok(())
}

/// The rung's scenarios with the cases it evaluates on: the stored ones, or with
/// `eval.generate` cases drawn from its seed (the same for every scenario's generator).
fn rung_cases(dirs: &Ctx, rung: &Rung) -> Result<Vec<(Arc<Map>, CaseFile)>> {
    let mut maps: Vec<_> = rung
        .eval
        .scenarios
        .iter()
        .map(|s| {
            sf_rollout::evaluate::load_scenario(&dirs.scenarios, &dirs.cases, s)
                .map_err(anyhow::Error::msg)
        })
        .collect::<Result<_>>()?;
    if let Some(g) = &rung.eval.generate {
        let sim = Arc::new(SimConfig::default());
        for (map, cases) in &mut maps {
            let mut rng = ChaCha8Rng::seed_from_u64(g.seed);
            cases.cases = sf_sim::vec_env::draw_cases(
                map,
                &sim,
                &mut rng,
                rung.eval.cases,
                (g.vehicles[0], g.vehicles[1]),
                g.draw(),
            );
        }
    }
    Ok(maps)
}

/// One training seed's job: its curve files copied into `out/seed-N`, its episodes (with the
/// IDM ego's, relabelled to this seed) and its summary against the gate.
#[allow(clippy::too_many_arguments)]
fn evaluate_seed(
    rung: &Rung,
    seed: u64,
    policy: &Policy,
    maps: &[(Arc<Map>, CaseFile)],
    idm: &[Row],
    runners: &mut Runners,
    out: &Path,
) -> Result<(SeedSummary, Vec<CurvePt>, Vec<Row>)> {
    let dir = &PathBuf::from(&policy.key);
    let seed_out = out.join(format!("seed-{seed}"));
    std::fs::create_dir_all(&seed_out)?;
    for f in ["curve.csv", "curve.png", "config.toml", "validation.csv"] {
        if dir.join(f).exists() {
            std::fs::copy(dir.join(f), seed_out.join(f))
                .with_context(|| format!("copying {f} of {}", dir.display()))?;
        }
    }
    let curve = read_curve(&dir.join("curve.csv"))?;
    let mut mine = Vec::new();
    for (map, cases) in maps {
        mine.extend(evaluate(&rung.eval, seed, map, cases, Driver::Policy(policy), runners)?);
    }
    mine.extend(idm.iter().map(|r| Row { train_seed: seed, ..r.clone() }));
    if let Some((map, cases)) = maps.first() {
        render_gifs(&rung.eval, map, cases, Driver::Policy(policy), runners, &seed_out)?;
    }
    let [updates, _, wall_s, _] = curve.last().copied().unwrap_or_default();
    let mut s = summarise(seed, dir, &mine, &rung.gate, updates as u64, wall_s, "policy")?;
    s.selected_updates = selected_updates(dir)?;
    check_curve(&mut s, &rung.gate, &curve, policy.cfg.train.window);
    Ok((s, curve, mine))
}

/// The seed summaries and episode lines already in `out` from earlier runs of the same rung,
/// except the seeds in `ran` (nothing when `out` holds no summary yet).
fn earlier_seeds(
    out: &Path,
    rung: &Rung,
    ran: &BTreeSet<u64>,
) -> Result<(Vec<SeedSummary>, Vec<String>)> {
    let path = out.join("summary.json");
    if !path.exists() {
        return Ok((Vec::new(), Vec::new()));
    }
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}", path.display()))?;
    if v["name"] != rung.name.as_str() {
        bail!(
            "{} belongs to rung `{}`, not `{}`: give another --out",
            path.display(),
            v["name"],
            rung.name
        );
    }
    let all: Vec<SeedSummary> = serde_json::from_value(v["seeds"].clone())
        .with_context(|| format!("{}: field `seeds`", path.display()))?;
    let kept: Vec<SeedSummary> = all.into_iter().filter(|s| !ran.contains(&s.train_seed)).collect();
    let keep: BTreeSet<u64> = kept.iter().map(|s| s.train_seed).collect();
    let episodes = out.join("episodes.csv");
    let lines = match std::fs::read_to_string(&episodes) {
        // Lines written before a column was added get it empty.
        Ok(t) => t
            .lines()
            .skip(1)
            .filter(|l| {
                l.split(',')
                    .next()
                    .and_then(|f| f.parse::<u64>().ok())
                    .is_some_and(|s| keep.contains(&s))
            })
            .map(|l| {
                l.to_string()
                    + &","
                        .repeat(Row::HEADER.split(',').count().saturating_sub(l.split(',').count()))
            })
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(e).with_context(|| format!("reading {}", episodes.display())),
    };
    Ok((kept, lines))
}

/// The final policy of the newest finished job named `cfg.name` in the data directory, found on
/// disk as `socialflow eval` finds its jobs (so no learner starts, and none resumes other
/// jobs, just to evaluate); otherwise, unless `--eval-only`, that job trained now.
fn trained_policy(dirs: &Ctx, a: &LadderArgs, cfg: &JobConfig) -> Result<Policy> {
    match find_job(&a.data_dir, &cfg.name, None) {
        Ok(p) => Ok(p),
        Err(e) if a.eval_only => Err(e),
        Err(_) => load_job(&train(dirs, a, cfg)?),
    }
}

/// Trains `cfg` (or follows its unfinished job of the same name) on an embedded learner with
/// `--workers` workers; returns its artifact directory once it succeeded.
fn train(dirs: &Ctx, a: &LadderArgs, cfg: &JobConfig) -> Result<PathBuf> {
    let text = cfg.to_toml();
    runtime()?.block_on(async {
        let emb = Embedded::start(a.data_dir.clone(), dirs, a.workers.max(1)).await?;
        let mut c = emb.client().await?;
        let result = async {
            let running =
                list(&mut c).await?.into_iter().find(|j| j.name == cfg.name && !j.state.is_final());
            let job = match running {
                Some(j) => j,
                None => submit(&mut c, text).await?,
            };
            eprintln!("training {} (job {})", cfg.name, job.id);
            let (state, _) = watch(&mut c, job.id, false).await?;
            anyhow::ensure!(
                state == JobState::Succeeded,
                "job {} ({}) ended {}",
                job.id,
                cfg.name,
                state.as_str()
            );
            Ok(PathBuf::from(&job.artifact_dir))
        }
        .await;
        emb.stop().await?;
        result
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Asserts that one of `s`'s failed checks mentions `what`.
    fn assert_failed(s: &SeedSummary, what: &str) {
        assert!(s.failed_checks.iter().any(|c| c.contains(what)), "{:?}", s.failed_checks);
    }

    fn summary() -> SeedSummary {
        SeedSummary {
            train_seed: 0,
            job_dir: String::new(),
            episodes: 0,
            cases: 0,
            success: 0.0,
            idm_success: 0.0,
            collision: 0.0,
            idm_collision: 0.0,
            other_failures: 0.0,
            speed: 0.0,
            idm_speed: 0.0,
            lane_change: 0.0,
            p_value: 1.0,
            per_scenario: BTreeMap::new(),
            updates: 0,
            selected_updates: None,
            wall_s: 0.0,
            passed: false,
            failed_checks: Vec::new(),
        }
    }

    /// The curve checks count only points whose rolling window the policy drove: a
    /// demonstrator's warm-up at 0.95 does not reach a 0.90 gate for a policy at 0.5, and the
    /// first `window` episodes after the warm-up still hold the demonstrator's.
    #[test]
    fn curve_checks_ignore_the_warmup_episodes() {
        let gate = Gate {
            curve_reach_success: Some(0.9),
            curve_reach_updates: 10_000,
            curve_min_success: Some(0.8),
            curve_from_updates: 2_000,
            ..Default::default()
        };
        // [updates, success, wall_s, episodes]: warm-up to 150 episodes, then the policy.
        let warmup = [[0.0, 0.95, 1.0, 50.0], [0.0, 0.95, 2.0, 150.0]];
        let check = |tail: &[CurvePt]| {
            let curve: Vec<CurvePt> = warmup.iter().chain(tail).copied().collect();
            let mut s = summary();
            check_curve(&mut s, &gate, &curve, 100);
            s
        };
        let poor = check(&[
            [500.0, 0.93, 3.0, 200.0],
            [3_000.0, 0.5, 4.0, 400.0],
            [6_000.0, 0.5, 5.0, 700.0],
        ]);
        assert!(!poor.passed, "0.93 at 200 episodes is the warm-up's window");
        assert_failed(&poor, "never reached 0.9");
        assert_failed(&poor, "min 0.500");
        let good = check(&[
            [500.0, 0.6, 3.0, 200.0],
            [3_000.0, 0.92, 4.0, 400.0],
            [6_000.0, 0.91, 5.0, 700.0],
        ]);
        assert!(good.passed, "{:?}", good.failed_checks);
        let none = check(&[]);
        assert_eq!(none.failed_checks.len(), 2, "{:?}", none.failed_checks);
    }

    /// The lane-change rung's checks: speed over the IDM ego's as a ratio, the share of episodes
    /// with a lane change, and failures even when the IDM ego's success is 0.
    #[test]
    fn speed_gain_and_lane_change_are_gated() {
        let row = |driver: &'static str,
                   case: u32,
                   success: f32,
                   speed: f32,
                   lane_change: f32,
                   other_failure: f32| Row {
            train_seed: 0,
            driver,
            scenario: "bottleneck".into(),
            case,
            seed: 0,
            vehicles: 3,
            success,
            collision: 0.0,
            other_failure,
            timeout: 1.0 - success,
            speed,
            lane_change,
        };
        let gate = Gate {
            min_success_gain: Some(0.0),
            min_speed_gain: Some(0.2),
            min_lane_change: Some(0.5),
            max_other_failures: Some(0.05),
            min_collision_drop: Some(-0.1),
            ..Default::default()
        };
        let idm: Vec<Row> = (0..4).map(|c| row("idm", c, 0.0, 0.3, 0.0, 0.0)).collect();
        let run = |pol: Vec<Row>| {
            summarise(
                0,
                Path::new("."),
                &pol.into_iter().chain(idm.clone()).collect::<Vec<_>>(),
                &gate,
                0,
                0.0,
                "policy",
            )
            .expect("summary")
        };
        let good = run((0..4).map(|c| row("policy", c, 1.0, 0.9, 1.0, 0.0)).collect());
        assert!(good.passed && (good.lane_change - 1.0).abs() < 1e-9, "{:?}", good.failed_checks);
        let slow = run((0..4)
            .map(|c| row("policy", c, 0.0, 0.33, if c < 1 { 1.0 } else { 0.0 }, 0.0))
            .collect());
        assert_failed(&slow, "need +20 %");
        assert_failed(&slow, "lane change in 0.250");
        let reckless = run((0..4)
            .map(|c| row("policy", c, 0.25, 0.9, 1.0, if c > 0 { 1.0 } else { 0.0 }))
            .collect());
        assert!(
            reckless.failed_checks.iter().any(|c| c.contains("other failures 0.750")),
            "success above IDM's 0 is not enough: {:?}",
            reckless.failed_checks
        );
        // `--scripted`: the gate judges the named driver's rows, and only those.
        let rows: Vec<Row> = (0..4)
            .map(|c| row("idm-mobil", c, 1.0, 0.9, 1.0, 0.0))
            .chain((0..4).map(|c| row("policy", c, 0.0, 0.3, 0.0, 0.0)))
            .chain(idm.clone())
            .collect();
        let mobil = summarise(0, Path::new("."), &rows, &gate, 0, 0.0, "idm-mobil").expect("mobil");
        assert!(mobil.passed && mobil.episodes == 4, "{:?}", mobil.failed_checks);
        let policy = summarise(0, Path::new("."), &rows, &gate, 0, 0.0, "policy").expect("policy");
        assert!(!policy.passed && policy.success == 0.0);
    }

    /// The paired test takes the stored case as its unit: an evaluation seed that repeats
    /// another's episodes (what deterministic drivers give) leaves p as it was, and the summary
    /// counts cases, not episodes.
    #[test]
    fn a_repeated_evaluation_seed_leaves_the_paired_test_unchanged() {
        let row = |driver: &'static str, case: u32, seed: u32, success: f32| Row {
            train_seed: 0,
            driver,
            scenario: if case.is_multiple_of(2) { "merge".into() } else { "roundabout".into() },
            case,
            seed,
            vehicles: 3,
            success,
            collision: 1.0 - success,
            other_failure: 0.0,
            timeout: 0.0,
            speed: 0.9,
            lane_change: 0.0,
        };
        // The policy succeeds in 14 of 20 cases, IDM in 9: a difference a paired test sees.
        let one_seed = |seed: u32| -> Vec<Row> {
            (0..20)
                .flat_map(|c| {
                    [
                        row("policy", c, seed, if c % 10 < 7 { 1.0 } else { 0.0 }),
                        row("idm", c, seed, if c % 20 < 9 { 1.0 } else { 0.0 }),
                    ]
                })
                .collect()
        };
        let gate = Gate::default();
        let once =
            summarise(0, Path::new("."), &one_seed(0), &gate, 0, 0.0, "policy").expect("once");
        let twice_rows: Vec<Row> = one_seed(0).into_iter().chain(one_seed(1)).collect();
        let twice =
            summarise(0, Path::new("."), &twice_rows, &gate, 0, 0.0, "policy").expect("twice");
        assert!(
            once.p_value < 0.2 && once.p_value > 1e-6,
            "a test with something to see: {}",
            once.p_value
        );
        assert_eq!(twice.p_value, once.p_value, "the repeated seed is not a second observation");
        assert_eq!((once.cases, twice.cases), (20, 20));
        assert_eq!((once.episodes, twice.episodes), (20, 40));
    }
}
