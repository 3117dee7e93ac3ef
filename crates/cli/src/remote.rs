//! `socialflow submit | status | watch | cancel`: the job API from the command line, and the
//! progress display shared with the embedded `train`.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use clap::Subcommand;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use sf_job::{JobRecord, JobState, Progress};
use sf_proto::pb;
use sf_proto::pb::job_service_client::JobServiceClient;
use sf_service::auth::{AttachToken, Token};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

pub type JobsClient = JobServiceClient<InterceptedService<Channel, AttachToken>>;

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
    },
    /// One job, or all jobs newest first.
    Status {
        job_id: Option<u64>,
        #[command(flatten)]
        conn: Conn,
        #[arg(long)]
        json: bool,
    },
    /// Follows a job's progress until it ends.
    Watch {
        job_id: u64,
        #[command(flatten)]
        conn: Conn,
    },
    /// Cancels a queued or running job.
    Cancel {
        job_id: u64,
        #[command(flatten)]
        conn: Conn,
    },
}

/// A job-API client for `conn` with its token.
pub async fn connect(conn: &Conn) -> Result<JobsClient> {
    jobs_client(conn.endpoint()?, &conn.learner, Some(conn.token()?)).await
}

pub async fn jobs_client(
    endpoint: tonic::transport::Endpoint,
    url: &str,
    token: Option<Token>,
) -> Result<JobsClient> {
    let ch =
        endpoint.connect().await.with_context(|| format!("connecting to the learner at {url}"))?;
    Ok(JobServiceClient::with_interceptor(ch, AttachToken::new(token))
        .max_decoding_message_size(sf_service::MAX_MESSAGE_BYTES))
}

fn deadline<T>(msg: T) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    r.set_timeout(Duration::from_secs(30));
    r
}

fn status_err(s: tonic::Status) -> anyhow::Error {
    anyhow!("{} ({})", s.message(), sf_service::error::code_label(s.code()))
}

pub async fn submit(c: &mut JobsClient, config_toml: String) -> Result<JobRecord> {
    let j = c
        .submit_job(deadline(pb::SubmitJobRequest { config_toml }))
        .await
        .map_err(status_err)
        .context("submitting the job")?
        .into_inner();
    Ok(sf_proto::job_from_wire(&j)?)
}

/// One job with its config.
pub async fn get(c: &mut JobsClient, job_id: u64) -> Result<JobRecord> {
    let j = c
        .get_job(deadline(pb::GetJobRequest { job_id }))
        .await
        .map_err(status_err)
        .with_context(|| format!("getting job {job_id}"))?
        .into_inner();
    Ok(sf_proto::job_from_wire(&j)?)
}

/// Every job, newest first, without configs (`get` has them).
pub async fn list(c: &mut JobsClient) -> Result<Vec<JobRecord>> {
    let r = c
        .list_jobs(deadline(pb::ListJobsRequest {}))
        .await
        .map_err(status_err)
        .context("listing jobs")?
        .into_inner();
    r.jobs.iter().map(|j| sf_proto::job_from_wire(j).map_err(Into::into)).collect()
}

pub fn job_json(j: &JobRecord) -> serde_json::Value {
    json!({
        "job_id": j.id, "name": j.name, "state": j.state.as_str(), "message": j.message,
        "artifact_dir": j.artifact_dir, "progress": j.progress,
    })
}

/// A progress bar over learner transitions.
pub fn bar(target: u64) -> ProgressBar {
    let pb = ProgressBar::new(target);
    pb.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} steps  {msg}")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb
}

pub fn show(pb: &ProgressBar, state: JobState, progress: &Progress) {
    let p = &progress.learning;
    pb.set_length(progress.target_env_steps.max(1));
    pb.set_position(p.env_steps);
    pb.set_message(format!(
        "{} | updates {} | v{} | {:.0} steps/s | success {:.2} safety {:.2} speed {:.2} (last {} episodes)",
        state.as_str(),
        p.updates,
        progress.policy_version,
        progress.env_steps_per_s,
        p.scores.success,
        p.scores.safety,
        p.scores.speed,
        p.episodes.min(100)
    ));
}

/// Follows a job until it reaches a final state; returns that state and the last progress.
pub async fn watch(c: &mut JobsClient, job_id: u64, quiet: bool) -> Result<(JobState, Progress)> {
    let mut stream = c
        .watch_job(pb::WatchJobRequest { job_id })
        .await
        .map_err(status_err)
        .with_context(|| format!("watching job {job_id}"))?
        .into_inner();
    let pb = if quiet { ProgressBar::hidden() } else { bar(1) };
    let mut last = None;
    while let Some(m) = stream
        .message()
        .await
        .map_err(status_err)
        .with_context(|| format!("watching job {job_id}"))?
    {
        let (state, p) = sf_proto::progress_from_wire(&m)?;
        show(&pb, state, &p);
        last = Some((state, p));
        if state.is_final() {
            break;
        }
    }
    pb.finish();
    last.ok_or_else(|| anyhow!("the learner ended the watch of job {job_id} without progress"))
}

pub fn run(cmd: RemoteCmd) -> Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(async move {
        match cmd {
            RemoteCmd::Submit { config, conn, watch: w } => {
                let text = std::fs::read_to_string(&config)
                    .with_context(|| format!("reading {}", config.display()))?;
                // Checked here first, so a bad file is named before any connection.
                sf_job::JobSpec::from_toml(&text).with_context(|| config.display().to_string())?;
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
                let j = c
                    .cancel_job(deadline(pb::CancelJobRequest { job_id }))
                    .await
                    .map_err(status_err)?
                    .into_inner();
                println!("{}", job_json(&sf_proto::job_from_wire(&j)?));
                Ok(())
            }
        }
    })
}
