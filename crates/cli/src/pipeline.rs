//! `socialflow pipeline <dir>`: submits a directory of job configs as one graph, dependencies
//! first, and follows it to the end; rerun, it resumes where it stopped. With `--eval` it then
//! submits an evaluation grid on the trained jobs (the learner's workers share its cells) and
//! with `--report` builds the report from its results: the paper's experiments from one command.
//!
//! Owns: name-based references between the configs of a directory (`env.background_from`,
//! `env.ego_from`, `train.init_from` = "<job name>", turned into the `*_job = <id>` fields at
//! submission), the submission order (dependencies first: a topological order),
//! reuse of jobs the learner already has under the same name (unless they failed or were
//! cancelled), replicates side by side (`--seeds 5,6`: the graph once per seed, each job
//! renamed `<name>-seed<N>`, the grid evaluated once per replicate and reported together),
//! and the final summary. Must not: schedule (the learner runs queued jobs once their
//! dependencies have succeeded, several at once where it has the cores and the workers).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::json;
use sf_embedded::{runtime, Embedded};
use sf_job::eval::EvalConfig;
use sf_job::{JobConfig, JobId, JobState};

use crate::remote::{self, Conn, JobsClient};

#[derive(Args, Debug)]
pub struct PipelineArgs {
    /// Directory of job configs (`*.toml`), e.g. configs/paper-small.
    pub dir: PathBuf,
    /// Run on an embedded learner with this many workers instead of a remote one.
    #[arg(long)]
    pub embedded: Option<usize>,
    /// Embedded: job store and artifacts (rerun with the same directory to resume).
    #[arg(long, default_value = "runs/pipeline")]
    pub data_dir: PathBuf,
    /// An evaluation grid (configs/eval/) to submit once every job of the graph has succeeded;
    /// a job of the grid's name already on the learner is reused (a rerun resumes it).
    #[arg(long)]
    pub eval: Option<PathBuf>,
    /// With `--eval`: build the report from the evaluation's results into this directory (the
    /// learner's artifact directory must be on this machine, as with `--embedded`).
    #[arg(long, requires = "eval")]
    pub report: Option<PathBuf>,
    /// Train every job of the graph with this seed (`sac.seed`: network initialisation,
    /// sampling and the training episodes) instead of its config's: a replicate of the graph
    /// from scratch. The evaluation grid keeps its own seeds, so replicates meet the same
    /// episodes. Use a fresh `--data-dir` per replicate.
    #[arg(long, conflicts_with = "seeds")]
    pub seed: Option<u64>,
    /// Replicates side by side on one learner: the graph once per seed (jobs renamed
    /// `<name>-seed<N>`), trained together where the learner runs several jobs at once; with
    /// `--eval`, the grid once per replicate and `--report` over all of them.
    #[arg(long, value_delimiter = ',', num_args = 1..)]
    pub seeds: Vec<u64>,
    /// Embedded: training jobs the learner runs at once (default: the machine's cores).
    #[arg(long, env = "SOCIALFLOW_MAX_RUNNING_JOBS")]
    pub max_running_jobs: Option<usize>,
    /// Override a setting of every job config of the graph (repeatable): `--set
    /// validation.every_updates=500`; validated like the files and recorded in each job's
    /// stored config.
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    pub set: Vec<String>,
    #[command(flatten)]
    pub conn: Conn,
}

/// The configs of a pipeline directory in submission order (every job after its dependency),
/// each with the `--set` overrides `sets` written in.
pub fn load(dir: &Path, sets: &[String]) -> Result<Vec<(PathBuf, JobConfig, String)>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading pipeline directory {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{} holds no job configs (*.toml)", dir.display());
    }
    let mut jobs: BTreeMap<String, (PathBuf, JobConfig, String)> = BTreeMap::new();
    for f in files {
        let text =
            std::fs::read_to_string(&f).with_context(|| format!("reading {}", f.display()))?;
        let (text, cfg) = remote::with_overrides(&f, &text, sets)?;
        if let Some((other, _, _)) = jobs.get(&cfg.name) {
            bail!("{} and {} both name their job `{}`", other.display(), f.display(), cfg.name);
        }
        jobs.insert(cfg.name.clone(), (f, cfg, text));
    }
    for (path, cfg, _) in jobs.values() {
        for (role, dep) in cfg.deps_by_name() {
            let Some((_, d, _)) = jobs.get(dep) else {
                bail!(
                    "{}: {} names `{dep}`, which no config in {} defines",
                    path.display(),
                    role.field(),
                    dir.display()
                );
            };
            if let Err(why) = role.accepts(cfg.kind, d.kind) {
                bail!("{}: {} names `{dep}`, which {why}", path.display(), role.field());
            }
        }
    }
    // Dependencies first; among jobs ready at the same time, by name.
    let mut order = Vec::with_capacity(jobs.len());
    let mut placed = std::collections::BTreeSet::new();
    while order.len() < jobs.len() {
        let ready: Vec<String> = jobs
            .iter()
            .filter(|(n, (_, c, _))| {
                !placed.contains(*n) && c.deps_by_name().iter().all(|(_, d)| placed.contains(*d))
            })
            .map(|(n, _)| n.clone())
            .collect();
        if ready.is_empty() {
            let left: Vec<&String> = jobs.keys().filter(|n| !placed.contains(*n)).collect();
            bail!("{}: the jobs {left:?} depend on each other in a cycle", dir.display());
        }
        for n in ready {
            placed.insert(n.clone());
            order.push(n);
        }
    }
    Ok(order.into_iter().filter_map(|n| jobs.remove(&n)).collect())
}

/// Submits what the learner does not have yet; returns (name, job id) in submission order.
async fn submit_all(
    c: &mut JobsClient,
    jobs: &[(PathBuf, JobConfig, String)],
) -> Result<Vec<(String, JobId)>> {
    let existing = remote::list(c).await?;
    let mut ids: BTreeMap<String, JobId> = BTreeMap::new();
    let mut out = Vec::new();
    for (path, cfg, _) in jobs {
        let reuse = existing
            .iter()
            .filter(|j| {
                j.name == cfg.name && !matches!(j.state, JobState::Failed | JobState::Cancelled)
            })
            .max_by_key(|j| j.id);
        let id = match reuse {
            Some(j) => {
                eprintln!(
                    "{}: job {} ({}) already on the learner",
                    cfg.name,
                    j.id,
                    j.state.as_str()
                );
                j.id
            }
            None => {
                let mut cfg = cfg.clone();
                cfg.resolve_names(|n| ids.get(n).copied())
                    .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
                let j = remote::submit(c, cfg.to_toml())
                    .await
                    .with_context(|| path.display().to_string())?;
                eprintln!("{}: submitted as job {}", cfg.name, j.id);
                j.id
            }
        };
        ids.insert(cfg.name.clone(), id);
        out.push((cfg.name.clone(), id));
    }
    Ok(out)
}

/// Submits an evaluation grid (or reuses the learner's evaluation job of its name); its id.
async fn submit_grid(c: &mut JobsClient, path: &Path, cfg: &EvalConfig) -> Result<JobId> {
    // Newest first: the first of its name that is an evaluation.
    for j in remote::list(c).await?.into_iter().filter(|j| {
        j.name == cfg.name && !matches!(j.state, JobState::Failed | JobState::Cancelled)
    }) {
        let full = remote::get(c, j.id).await?;
        if sf_job::JobSpec::from_toml(&full.config_toml).is_ok_and(|s| s.is_eval()) {
            eprintln!(
                "{}: evaluation job {} ({}) already on the learner",
                cfg.name,
                full.id,
                full.state.as_str()
            );
            return Ok(full.id);
        }
    }
    let j = remote::submit(c, cfg.to_toml()).await.with_context(|| path.display().to_string())?;
    eprintln!("{}: submitted as evaluation job {} ({} cells)", cfg.name, j.id, cfg.cells().len());
    Ok(j.id)
}

/// After the graph: submits the grids (one per replicate), follows them and builds the report
/// over all of their results.
async fn evaluate(
    c: &mut JobsClient,
    grids: &[(PathBuf, EvalConfig)],
    report: Option<&Path>,
) -> Result<()> {
    let mut ids = Vec::new();
    for (path, cfg) in grids {
        ids.push((cfg.name.clone(), submit_grid(c, path, cfg).await?));
    }
    follow(c, &ids).await?;
    let Some(out) = report else { return Ok(()) };
    let all = remote::list(c).await?;
    let mut results = Vec::new();
    for (_, id) in &ids {
        let j = all
            .iter()
            .find(|j| j.id == *id)
            .with_context(|| format!("evaluation job {id} is gone"))?;
        let dir = PathBuf::from(&j.artifact_dir);
        if !sf_report::episodes::episodes_file(&dir).exists() {
            bail!("the results of evaluation job {id} ({}) are not on this machine: run `socialflow report` where they are", dir.display());
        }
        results.push(dir);
    }
    crate::eval::report(crate::eval::ReportArgs { results, out: out.to_path_buf() })
}

/// Polls until every job is final, showing their progress ([`sf_embedded::client::Board`]: bars
/// on a terminal, a line per start, validation and end elsewhere); then prints one JSON line per
/// job; fails if any did not succeed.
async fn follow(c: &mut JobsClient, ids: &[(String, JobId)]) -> Result<()> {
    let mut board = sf_embedded::client::Board::new(ids.len());
    loop {
        let all = remote::list(c).await?;
        let mine: Vec<_> =
            ids.iter().filter_map(|(_, id)| all.iter().find(|j| j.id == *id)).collect();
        for j in &mine {
            board.update(&j.name, j.id, j.state, &j.progress);
        }
        if mine.len() == ids.len() && mine.iter().all(|j| j.state.is_final()) {
            board.finish();
            let mut bad = Vec::new();
            for j in &mine {
                println!(
                    "{}",
                    json!({"name": j.name, "job_id": j.id, "state": j.state.as_str(), "message": j.message, "artifact_dir": j.artifact_dir, "progress": j.progress, "held_out": crate::train::held_out(Path::new(&j.artifact_dir))})
                );
                if j.state != JobState::Succeeded {
                    bad.push(format!("{} ({})", j.name, j.state.as_str()));
                }
            }
            if !bad.is_empty() {
                bail!("pipeline jobs did not succeed: {}", bad.join(", "));
            }
            return Ok(());
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

/// Sets `sac.seed` of every job (the `--seed` replicate).
pub fn reseed(jobs: &mut [(PathBuf, JobConfig, String)], seed: u64) {
    for (_, cfg, _) in jobs {
        cfg.sac.seed = seed;
    }
}

/// A replicate's name for a job or grid of the graph.
fn replicate_name(name: &str, seed: u64) -> String {
    format!("{name}-seed{seed}")
}

/// The graph's replicate with seed `seed`, beside others on one learner: every job reseeded
/// and renamed, and its references to other jobs of the graph renamed with it.
pub fn replicate(
    jobs: &[(PathBuf, JobConfig, String)],
    seed: u64,
) -> Vec<(PathBuf, JobConfig, String)> {
    let mut out = jobs.to_vec();
    reseed(&mut out, seed);
    for (_, cfg, _) in &mut out {
        cfg.name = replicate_name(&cfg.name, seed);
        for dep in [&mut cfg.env.background_from, &mut cfg.env.ego_from, &mut cfg.train.init_from] {
            if let Some(n) = dep.as_mut() {
                *n = replicate_name(n, seed);
            }
        }
    }
    out
}

/// The grid for replicate `seed`: the same cells on that replicate's jobs.
fn replicate_grid(grid: &EvalConfig, seed: u64) -> EvalConfig {
    let mut g = grid.clone();
    g.name = replicate_name(&g.name, seed);
    for n in g.flows.iter_mut().chain(g.egos.iter_mut()).filter(|n| !n.is_scripted()) {
        n.job = replicate_name(&n.job, seed);
    }
    g
}

pub fn run(dirs: &crate::scenarios::Ctx, a: PipelineArgs) -> Result<()> {
    let mut jobs = load(&a.dir, &a.set)?;
    if let Some(seed) = a.seed {
        reseed(&mut jobs, seed);
    }
    // The grid is checked before anything is submitted.
    let grid = match &a.eval {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            let cfg = EvalConfig::from_toml(&text).with_context(|| p.display().to_string())?;
            Some((p.clone(), cfg))
        }
        None => None,
    };
    let seeds = a.seeds.clone();
    let mut unique = seeds.clone();
    unique.sort_unstable();
    unique.dedup();
    if unique.len() != seeds.len() {
        bail!("--seeds {seeds:?}: name each seed once");
    }
    let (jobs, grids): (Vec<_>, Vec<_>) = if seeds.is_empty() {
        (jobs, grid.into_iter().collect())
    } else {
        let all = seeds.iter().flat_map(|&s| replicate(&jobs, s)).collect();
        let grids = grid
            .iter()
            .flat_map(|(p, g)| seeds.iter().map(|&s| (p.clone(), replicate_grid(g, s))))
            .collect();
        (all, grids)
    };
    runtime()?.block_on(async move {
        match a.embedded {
            Some(0) => bail!("--embedded needs at least one worker"),
            Some(n) => {
                let emb =
                    Embedded::start_with(a.data_dir.clone(), dirs, n, a.max_running_jobs).await?;
                let mut c = emb.client().await?;
                let r = async {
                    let ids = submit_all(&mut c, &jobs).await?;
                    let all = async {
                        follow(&mut c, &ids).await?;
                        evaluate(&mut c, &grids, a.report.as_deref()).await
                    };
                    tokio::select! {
                        r = all => r.map(Some),
                        _ = sf_service::signal::terminate() => Ok(None),
                    }
                }
                .await;
                emb.stop().await?;
                match r? {
                    Some(()) => Ok(()),
                    None => {
                        eprintln!("interrupted: the running jobs are checkpointed; run the same command to resume");
                        Ok(())
                    }
                }
            }
            None => {
                let mut c = remote::connect(&a.conn).await?;
                let ids = submit_all(&mut c, &jobs).await?;
                follow(&mut c, &ids).await?;
                evaluate(&mut c, &grids, a.report.as_deref()).await
            }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_small_graph_submits_flows_before_the_egos_that_need_them() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/paper-small");
        let jobs = load(&dir, &[]).expect("a valid pipeline");
        let pos = |n: &str| {
            jobs.iter().position(|(_, c, _)| c.name == n).unwrap_or_else(|| panic!("{n} missing"))
        };
        for k in ["macad", "copo", "socialcomm"] {
            assert!(pos(&format!("flow-{k}")) < pos(&format!("ego-{k}")), "{k}");
            assert_eq!(
                jobs[pos(&format!("ego-{k}"))].1.env.background_from.as_deref(),
                Some(format!("flow-{k}").as_str())
            );
        }
        assert!(jobs[pos("ego-idm")].1.env.background_from.is_none());
        // RARL, three rounds per arm, both arms from `ego-idm`: each phase after the frozen side it
        // acts against and after the phase it continues (`train.init_from`).
        let arms = [
            [
                "ego-idm",
                "failmaker-1",
                "ego-failmaker-1",
                "failmaker-2",
                "ego-failmaker-2",
                "flow-failmaker",
                "ego-failmaker",
            ],
            [
                "ego-idm",
                "socialcomm-adv-1",
                "ego-socialcomm-adv-1",
                "socialcomm-adv-2",
                "ego-socialcomm-adv-2",
                "flow-socialcomm-adv",
                "ego-socialcomm-adv",
            ],
        ];
        for chain in &arms {
            for w in chain.windows(2) {
                assert!(pos(w[0]) < pos(w[1]), "{} before {}", w[0], w[1]);
            }
            for round in 0..3 {
                let (ego_before, adv, ego) =
                    (chain[2 * round], chain[2 * round + 1], chain[2 * round + 2]);
                let (a, e) = (&jobs[pos(adv)].1, &jobs[pos(ego)].1);
                assert_eq!(
                    a.env.ego_from.as_deref(),
                    Some(ego_before),
                    "{adv} acts against the previous ego"
                );
                assert_eq!(
                    e.env.background_from.as_deref(),
                    Some(adv),
                    "{ego} drives among this round's adversary"
                );
                assert_eq!(
                    e.train.init_from.as_deref(),
                    Some(ego_before),
                    "{ego} continues the previous ego"
                );
                let prev_adv = (round > 0).then(|| chain[2 * round - 1]);
                assert_eq!(
                    a.train.init_from.as_deref(),
                    prev_adv,
                    "{adv} continues its arm's previous adversary"
                );
                assert_eq!(
                    e.sac.warmup_policy,
                    sf_job::config::WarmupPolicy::Policy,
                    "{ego} warms up with the policy it continues"
                );
            }
        }
        // The SocialCommAdv adversary acts in the frozen SocialComm flow in every round.
        for adv in ["socialcomm-adv-1", "socialcomm-adv-2", "flow-socialcomm-adv"] {
            assert_eq!(
                jobs[pos(adv)].1.env.background_from.as_deref(),
                Some("flow-socialcomm"),
                "{adv}"
            );
            assert!(pos("flow-socialcomm") < pos(adv), "flow-socialcomm before {adv}");
        }
        assert_eq!(jobs[pos("socialcomm-adv-1")].1.env.ego_from.as_deref(), Some("ego-idm"));
        assert_eq!(jobs[pos("ego-socialcomm-adv-1")].1.train.init_from.as_deref(), Some("ego-idm"));
        assert_eq!(jobs[pos("ego-failmaker-1")].1.train.init_from.as_deref(), Some("ego-idm"));
        // No other ego continues a job: the six above are all of Stage 2's ego phases.
        let rarl_egos: Vec<&JobConfig> = jobs
            .iter()
            .map(|(_, c, _)| c)
            .filter(|c| c.kind == sf_job::config::JobKind::Ego && c.train.init_from.is_some())
            .collect();
        assert_eq!(rarl_egos.len(), 6, "three ego phases per arm");
        for c in rarl_egos {
            assert_eq!(c.sac.warmup_policy, sf_job::config::WarmupPolicy::Policy, "{}", c.name);
        }
    }

    /// The paper graph chains five rounds: every phase continues its side's previous phase.
    #[test]
    fn the_paper_graph_alternates_rarl_phases_in_order() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/paper");
        let jobs = load(&dir, &[]).expect("a valid pipeline");
        let pos = |n: &str| {
            jobs.iter().position(|(_, c, _)| c.name == n).unwrap_or_else(|| panic!("{n} missing"))
        };
        let chain = [
            "ego-idm",
            "failmaker-1",
            "ego-failmaker-1",
            "failmaker-2",
            "ego-failmaker-2",
            "failmaker-3",
            "ego-failmaker-3",
            "failmaker-4",
            "ego-failmaker-4",
            "flow-failmaker",
            "ego-failmaker",
        ];
        for w in chain.windows(2) {
            assert!(pos(w[0]) < pos(w[1]), "{} before {}", w[0], w[1]);
        }
        assert_eq!(jobs[pos("failmaker-3")].1.train.init_from.as_deref(), Some("failmaker-2"));
        assert_eq!(jobs[pos("failmaker-3")].1.env.ego_from.as_deref(), Some("ego-failmaker-2"));
    }

    /// A replicate changes the seed of every job and nothing else; what is submitted carries it.
    #[test]
    fn a_replicate_reseeds_every_job_and_only_the_seed() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/paper-small");
        let before = load(&dir, &[]).expect("a valid pipeline");
        let mut after = before.clone();
        reseed(&mut after, 7);
        assert_eq!(before.len(), after.len());
        for ((_, b, _), (_, a, _)) in before.iter().zip(&after) {
            assert_ne!(
                b.sac.seed, 7,
                "{}: the configs must not already use the test's seed",
                b.name
            );
            assert_eq!(a.sac.seed, 7, "{}", a.name);
            // What is submitted (`to_toml`) carries the seed.
            assert_eq!(
                JobConfig::from_toml(&a.to_toml()).expect("parses").sac.seed,
                7,
                "{}",
                a.name
            );
            let mut a = a.clone();
            a.sac.seed = b.sac.seed;
            assert_eq!(a.to_toml(), b.to_toml(), "{}: only the seed changes", b.name);
        }
    }

    #[test]
    fn a_dependency_cycle_is_refused() {
        let dir = std::env::temp_dir().join(format!("sf-cycle-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let job = |name: &str, init: &str| {
            format!("name = \"{name}\"\n[env]\nscenarios = [\"merge\"]\n[sac]\nwarmup_steps = 10\n[train]\nenv_steps = 100\ninit_from = \"{init}\"\n")
        };
        std::fs::write(dir.join("a.toml"), job("a", "b")).expect("write");
        std::fs::write(dir.join("b.toml"), job("b", "a")).expect("write");
        let e = load(&dir, &[]).expect_err("a cycle");
        assert!(e.to_string().contains("cycle"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Replicates side by side: distinct names, each replicate's references stay inside it,
    /// only the seed and names differ from the graph, and the grid follows its replicate.
    #[test]
    fn replicates_rename_their_jobs_and_references_and_differ_only_in_seed() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let jobs = load(&root.join("configs/paper-small"), &[]).expect("a valid pipeline");
        let (r5, r6) = (replicate(&jobs, 5), replicate(&jobs, 6));
        let names: std::collections::BTreeSet<&str> =
            r5.iter().chain(&r6).map(|(_, c, _)| c.name.as_str()).collect();
        assert_eq!(names.len(), 2 * jobs.len(), "every job name is distinct across replicates");
        for ((_, orig, _), (_, c, _)) in jobs.iter().zip(&r5) {
            assert_eq!(c.name, format!("{}-seed5", orig.name));
            assert_eq!(c.sac.seed, 5);
            for ((role, d), (_, od)) in c.deps_by_name().into_iter().zip(orig.deps_by_name()) {
                assert_eq!(d, format!("{od}-seed5"), "{}: {}", c.name, role.field());
                assert!(r5.iter().any(|(_, x, _)| x.name == d), "{d} is in the replicate");
            }
            let mut back = c.clone();
            back.name = orig.name.clone();
            back.sac.seed = orig.sac.seed;
            back.env.background_from = orig.env.background_from.clone();
            back.env.ego_from = orig.env.ego_from.clone();
            back.train.init_from = orig.train.init_from.clone();
            assert_eq!(back.to_toml(), orig.to_toml(), "{}: only seed and names change", c.name);
        }
        let text = std::fs::read_to_string(root.join("configs/eval/paper-small.toml"))
            .expect("the paper-small grid");
        let grid = EvalConfig::from_toml(&text).expect("valid grid");
        let g6 = replicate_grid(&grid, 6);
        assert_eq!(g6.name, format!("{}-seed6", grid.name));
        for (a, b) in grid.flows.iter().chain(&grid.egos).zip(g6.flows.iter().chain(&g6.egos)) {
            let want = if a.is_idm() { a.job.clone() } else { format!("{}-seed6", a.job) };
            assert_eq!(b.job, want);
            assert!(b.is_idm() || r6.iter().any(|(_, c, _)| c.name == b.job), "{}", b.job);
        }
        assert!(EvalConfig::from_toml(&g6.to_toml()).is_ok(), "the replicate's grid is valid");
    }
}
