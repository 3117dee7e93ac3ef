//! `socialflow submit | status | watch | cancel | download`: the job API from the command line
//! (the calls are `sf_service::client`'s; the progress display, shared with the embedded
//! `train`, is `sf_embedded::client`'s).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::builder::TypedValueParser;
use clap::Subcommand;
use serde_json::json;
use sf_job::{JobId, JobState};

pub use sf_embedded::client::{jobs_client, watch};
pub use sf_service::client::{cancel, get, job_json, list, submit, JobsClient};

pub use sf_service::conn::LearnerConn as Conn;

#[derive(Subcommand, Debug)]
pub enum RemoteCmd {
    /// Submits a job config or an evaluation grid (`kind = "eval"`, configs/eval/) and prints
    /// the job.
    Submit {
        config: PathBuf,
        #[command(flatten)]
        conn: Conn,
        /// Then watch it until it ends.
        #[arg(long)]
        watch: bool,
        /// Override a setting of the config (repeatable): `--set sac.seed=12`; validated like
        /// the file and recorded in the job's stored config.
        #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
        set: Vec<String>,
    },
    /// One job, or all jobs newest first.
    Status {
        #[arg(value_parser = job_id_arg())]
        job_id: Option<JobId>,
        #[command(flatten)]
        conn: Conn,
        #[arg(long)]
        json: bool,
    },
    /// Follows a job's progress until it ends.
    Watch {
        #[arg(value_parser = job_id_arg())]
        job_id: JobId,
        #[command(flatten)]
        conn: Conn,
    },
    /// Cancels a queued or running job.
    Cancel {
        #[arg(value_parser = job_id_arg())]
        job_id: JobId,
        #[command(flatten)]
        conn: Conn,
    },
    /// Fetches a succeeded job's files into a directory: a training job's config, final actor
    /// and curves (a job directory `socialflow eval` and `socialflow.load_policy` read), or an
    /// evaluation's results.
    Download {
        #[arg(value_parser = job_id_arg())]
        job_id: JobId,
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        conn: Conn,
    },
}

/// `text` (the file `path`) with the `--set` overrides `sets` written in; errors name the file.
pub fn overridden(path: &Path, text: &str, sets: &[String]) -> Result<String> {
    sf_job::overrides::apply(text, sets).with_context(|| path.display().to_string())
}

/// How an error names a config read with overrides: the file, and the overrides if any.
pub fn with_sets(path: &Path, sets: &[String]) -> String {
    if sets.is_empty() {
        path.display().to_string()
    } else {
        format!("{} with --set {}", path.display(), sets.join(" --set "))
    }
}

/// A training job's config file with its `--set` overrides, as the text to submit and parsed.
pub fn with_overrides(
    path: &Path,
    text: &str,
    sets: &[String],
) -> Result<(String, sf_job::JobConfig)> {
    let text = overridden(path, text, sets)?;
    let cfg = sf_job::JobConfig::from_toml(&text).with_context(|| with_sets(path, sets))?;
    Ok((text, cfg))
}

/// A job id as given on the command line: the bare number, parsed (and refused) as before.
fn job_id_arg() -> impl TypedValueParser<Value = JobId> {
    clap::value_parser!(u64).map(JobId::new)
}

/// A job-API client for `conn` with its token.
pub async fn connect(conn: &Conn) -> Result<JobsClient> {
    jobs_client(conn.endpoint()?, &conn.learner, Some(conn.token()?)).await
}

pub fn run(cmd: RemoteCmd) -> Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(async move {
        match cmd {
            RemoteCmd::Submit { config, conn, watch: w, set } => {
                let text = std::fs::read_to_string(&config)
                    .with_context(|| format!("reading {}", config.display()))?;
                let text = overridden(&config, &text, &set)?;
                // Checked here first, so a bad file is named before any connection.
                sf_job::JobSpec::from_toml(&text).with_context(|| with_sets(&config, &set))?;
                let mut c = connect(&conn).await?;
                let j = submit(&mut c, text).await?;
                println!("{}", job_json(&j));
                if w {
                    let (state, _) = watch(&mut c, j.id, false).await?;
                    if state != JobState::Succeeded {
                        bail!("job {} ended {}", j.id, state.as_str());
                    }
                }
                Ok(())
            }
            RemoteCmd::Status { job_id, conn, json: as_json } => {
                let mut c = connect(&conn).await?;
                let jobs = match job_id {
                    Some(id) => vec![get(&mut c, id).await?],
                    None => list(&mut c).await?,
                };
                for j in &jobs {
                    if as_json {
                        println!("{}", job_json(j));
                    } else {
                        let p = &j.progress;
                        println!(
                            "{:>5}  {:<20} {:<10} {:>9}/{:<9} updates {:>7}  success {:.2}  {}",
                            j.id,
                            j.name,
                            j.state.as_str(),
                            p.learning.env_steps,
                            p.target_env_steps,
                            p.learning.updates,
                            p.learning.scores.success,
                            j.message
                        );
                    }
                }
                Ok(())
            }
            RemoteCmd::Watch { job_id, conn } => {
                let mut c = connect(&conn).await?;
                let (state, p) = watch(&mut c, job_id, false).await?;
                println!("{}", json!({"job_id": job_id, "state": state.as_str(), "progress": p}));
                Ok(())
            }
            RemoteCmd::Cancel { job_id, conn } => {
                let mut c = connect(&conn).await?;
                println!("{}", job_json(&cancel(&mut c, job_id).await?));
                Ok(())
            }
            RemoteCmd::Download { job_id, out, conn } => {
                let mut c = connect(&conn).await?;
                let files = sf_service::client::download(&mut c, job_id, &out).await?;
                println!("{}", json!({"job_id": job_id, "dir": out, "files": files}));
                Ok(())
            }
        }
    })
}
