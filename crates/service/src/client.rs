//! The job API as a typed client: what `socialflow submit | status | watch | cancel | download`,
//! `pipeline` and the Python package's `socialflow.client` call.
//!
//! Owns: [`JobsClient`] and [`connect`], one function per `JobService` call (each unary call
//! with a deadline), [`Watch`] (a job's progress until it ends) and [`download`] (a job's files
//! into a directory that `socialflow.load_policy` and `socialflow eval` read as a job
//! directory). Errors keep the gRPC code ([`ClientError::Status`]) so that callers can tell a
//! bad config from a missing job from an unreachable learner. Must not: print, draw progress or
//! retry (callers decide).

use std::path::{Path, PathBuf};
use std::time::Duration;

use sf_job::{JobId, JobRecord, JobState, Progress};
use sf_proto::pb;
use sf_proto::pb::job_service_client::JobServiceClient;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};
use tonic::Code;

use crate::auth::{AttachToken, Token};

pub type JobsClient = JobServiceClient<InterceptedService<Channel, AttachToken>>;

/// How long a unary call may take.
pub const CALL_TIMEOUT: Duration = Duration::from_secs(30);

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("connecting to the learner at {url}: {source}")]
    Connect { url: String, source: tonic::transport::Error },
    /// The learner answered with an error status.
    #[error("{what}: {message} ({})", crate::error::code_label(*code))]
    Status { what: String, code: Code, message: String },
    #[error("{what}: {source}")]
    Wire { what: String, source: sf_proto::WireError },
    #[error("writing {path}: {source}")]
    Write { path: PathBuf, source: std::io::Error },
}

impl ClientError {
    /// The gRPC code of a status the learner answered, if it answered one.
    pub fn code(&self) -> Option<Code> {
        match self {
            Self::Status { code, .. } => Some(*code),
            _ => None,
        }
    }
}

type Result<T> = std::result::Result<T, ClientError>;

fn status(what: impl Into<String>) -> impl FnOnce(tonic::Status) -> ClientError {
    let what = what.into();
    move |s| ClientError::Status { what, code: s.code(), message: s.message().to_string() }
}

fn wire(what: impl Into<String>) -> impl FnOnce(sf_proto::WireError) -> ClientError {
    let what = what.into();
    move |source| ClientError::Wire { what, source }
}

fn deadline<T>(msg: T) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    r.set_timeout(CALL_TIMEOUT);
    r
}

/// A job-API client on `endpoint` (see [`crate::tls::endpoint`]) with `token`.
pub async fn connect(endpoint: Endpoint, url: &str, token: Option<Token>) -> Result<JobsClient> {
    let ch = endpoint
        .connect()
        .await
        .map_err(|source| ClientError::Connect { url: url.to_string(), source })?;
    Ok(JobServiceClient::with_interceptor(ch, AttachToken::new(token))
        .max_decoding_message_size(crate::MAX_MESSAGE_BYTES))
}

/// A job as JSON for scripts: what `socialflow status --json` prints and Python's client returns
/// (with `config_toml` where the call carried it).
pub fn job_json(j: &JobRecord) -> serde_json::Value {
    let mut v = serde_json::json!({
        "job_id": j.id, "name": j.name, "state": j.state.as_str(), "message": j.message,
        "artifact_dir": j.artifact_dir, "progress": j.progress,
    });
    if !j.config_toml.is_empty() {
        v["config_toml"] = j.config_toml.clone().into();
    }
    v
}

/// Queues a job config or evaluation grid (TOML text).
pub async fn submit(c: &mut JobsClient, config_toml: String) -> Result<JobRecord> {
    let j = c
        .submit_job(deadline(pb::SubmitJobRequest { config_toml }))
        .await
        .map_err(status("submitting the job"))?
        .into_inner();
    sf_proto::job_from_wire(&j).map_err(wire("the submitted job"))
}

/// One job with its config.
pub async fn get(c: &mut JobsClient, job_id: JobId) -> Result<JobRecord> {
    let what = format!("getting job {job_id}");
    let j = c
        .get_job(deadline(pb::GetJobRequest { job_id: job_id.get() }))
        .await
        .map_err(status(what.clone()))?
        .into_inner();
    sf_proto::job_from_wire(&j).map_err(wire(what))
}

/// Every job, newest first, without configs (`get` has them).
pub async fn list(c: &mut JobsClient) -> Result<Vec<JobRecord>> {
    let r = c.list_jobs(deadline(pb::ListJobsRequest {})).await.map_err(status("listing jobs"))?;
    r.into_inner()
        .jobs
        .iter()
        .map(|j| sf_proto::job_from_wire(j).map_err(wire("a listed job")))
        .collect()
}

/// Cancels a queued or running job; a finished one comes back unchanged.
pub async fn cancel(c: &mut JobsClient, job_id: JobId) -> Result<JobRecord> {
    let what = format!("cancelling job {job_id}");
    let j = c
        .cancel_job(deadline(pb::CancelJobRequest { job_id: job_id.get() }))
        .await
        .map_err(status(what.clone()))?
        .into_inner();
    sf_proto::job_from_wire(&j).map_err(wire(what))
}

/// One file of a job's artifact directory (names: the learner's `GetJobFile` list).
pub async fn file(c: &mut JobsClient, job_id: JobId, name: &str) -> Result<Vec<u8>> {
    let r = c
        .get_job_file(deadline(pb::GetJobFileRequest {
            job_id: job_id.get(),
            name: name.to_string(),
        }))
        .await
        .map_err(status(format!("fetching {name} of job {job_id}")))?;
    Ok(r.into_inner().content)
}

/// A job's progress as the learner reports it, until it ends.
pub struct Watch {
    job_id: JobId,
    stream: tonic::Streaming<pb::JobProgress>,
    done: bool,
}

impl Watch {
    pub async fn open(c: &mut JobsClient, job_id: JobId) -> Result<Self> {
        let stream = c
            .watch_job(pb::WatchJobRequest { job_id: job_id.get() })
            .await
            .map_err(status(format!("watching job {job_id}")))?
            .into_inner();
        Ok(Self { job_id, stream, done: false })
    }

    /// The next change; `None` after the one that carried a final state.
    pub async fn next(&mut self) -> Result<Option<(JobState, Progress)>> {
        if self.done {
            return Ok(None);
        }
        let what = format!("watching job {}", self.job_id);
        let Some(m) = self.stream.message().await.map_err(status(what.clone()))? else {
            self.done = true;
            return Ok(None);
        };
        let (state, p) = sf_proto::progress_from_wire(&m).map_err(wire(what))?;
        self.done = state.is_final();
        Ok(Some((state, p)))
    }
}

/// The files [`download`] fetches for each kind of job: (name, needed).
fn download_list(eval: bool) -> &'static [(&'static str, bool)] {
    if eval {
        &[("config.toml", false), ("episodes.csv", true), ("meta.json", false)]
    } else {
        &[
            ("config.toml", true),
            ("policy.bpk", true),
            ("policy.json", true),
            ("curve.csv", false),
            ("validation.csv", false),
            ("coordinator.json", false),
        ]
    }
}

/// Fetches a finished job's files into `dir` (created): a training job's config, final actor
/// and curves, or an evaluation's results, each written beside and renamed into place. The
/// names written, in order. A job that did not succeed is refused (its files are incomplete).
pub async fn download(c: &mut JobsClient, job_id: JobId, dir: &Path) -> Result<Vec<String>> {
    let job = get(c, job_id).await?;
    if job.state != JobState::Succeeded {
        return Err(ClientError::Status {
            what: format!("downloading job {job_id}"),
            code: Code::FailedPrecondition,
            message: format!("job {job_id} is {}, not succeeded", job.state.as_str()),
        });
    }
    let eval = sf_job::JobSpec::from_toml(&job.config_toml).is_ok_and(|s| s.is_eval());
    std::fs::create_dir_all(dir)
        .map_err(|source| ClientError::Write { path: dir.to_path_buf(), source })?;
    let mut written = Vec::new();
    for &(name, needed) in download_list(eval) {
        let bytes = match file(c, job_id, name).await {
            Ok(b) => b,
            Err(e) if !needed && e.code() == Some(Code::NotFound) => continue,
            Err(e) => return Err(e),
        };
        let path = dir.join(name);
        let part = dir.join(format!(".{name}.part"));
        std::fs::write(&part, &bytes)
            .and_then(|()| std::fs::rename(&part, &path))
            .map_err(|source| ClientError::Write { path, source })?;
        written.push(name.to_string());
    }
    Ok(written)
}
