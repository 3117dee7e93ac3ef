//! The native half of `socialflow.client`: the learner's job API over gRPC.
//!
//! Owns: [`JobClient`] (one connection and a runtime of its own; every call releases the GIL
//! while it waits) and [`JobWatch`] (a job's progress, one change per call). The calls are
//! `sf_service::client`'s, on tonic's stubs generated from `proto/` at build time: nothing here
//! knows the wire format. Must not: parse configs or records into Python objects (records cross
//! as JSON text; `socialflow/client.py` decodes them and gives the documented API).
//!
//! Errors: a learner's status becomes `ValueError` (INVALID_ARGUMENT: a bad config or file
//! name), `LookupError` (NOT_FOUND), `PermissionError` (a missing or wrong token),
//! `ConnectionError` (unreachable, UNAVAILABLE), `TimeoutError` (DEADLINE_EXCEEDED),
//! `RuntimeError` otherwise; all carry the learner's message.

use std::path::PathBuf;

use pyo3::exceptions::{
    PyConnectionError, PyLookupError, PyOSError, PyPermissionError, PyRuntimeError, PyTimeoutError,
    PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::PyBytes;
use sf_job::JobId;
use sf_service::auth::Token;
use sf_service::client::{self, ClientError, JobsClient};
use sf_service::tls::ClientTls;
use tokio::runtime::Runtime;
use tonic::Code;

fn py_err(e: ClientError) -> PyErr {
    let msg = e.to_string();
    match (&e, e.code()) {
        (ClientError::Connect { .. }, _) | (_, Some(Code::Unavailable)) => {
            PyConnectionError::new_err(msg)
        }
        (ClientError::Write { .. }, _) => PyOSError::new_err(msg),
        (_, Some(Code::InvalidArgument)) => PyValueError::new_err(msg),
        (_, Some(Code::NotFound)) => PyLookupError::new_err(msg),
        (_, Some(Code::Unauthenticated | Code::PermissionDenied)) => {
            PyPermissionError::new_err(msg)
        }
        (_, Some(Code::DeadlineExceeded)) => PyTimeoutError::new_err(msg),
        _ => PyRuntimeError::new_err(msg),
    }
}

/// A connection to a learner's job API.
#[pyclass(module = "socialflow._socialflow")]
pub struct JobClient {
    rt: std::sync::Arc<Runtime>,
    c: JobsClient,
}

#[pymethods]
impl JobClient {
    #[new]
    #[pyo3(signature = (url, token=None, token_file=None, tls_ca_file=None, tls_client_cert_file=None, tls_client_key_file=None))]
    fn new(
        py: Python<'_>,
        url: &str,
        token: Option<&str>,
        token_file: Option<PathBuf>,
        tls_ca_file: Option<PathBuf>,
        tls_client_cert_file: Option<PathBuf>,
        tls_client_key_file: Option<PathBuf>,
    ) -> PyResult<Self> {
        let token = match (token, &token_file) {
            (Some(_), Some(_)) => {
                return Err(PyValueError::new_err("token, token_file: give one, not both"))
            }
            (Some(t), None) => Some(
                Token::new(t, "token").map_err(|e| PyValueError::new_err(format!("token: {e}")))?,
            ),
            (None, Some(f)) => Some(
                Token::load(sf_service::auth::TOKEN_ENV, Some(f))
                    .map_err(|e| PyValueError::new_err(format!("token_file: {e}")))?,
            ),
            // The variable the command line reads, if it is set; else no token.
            (None, None) => Token::load(sf_service::auth::TOKEN_ENV, None).ok(),
        };
        let identity = match (tls_client_cert_file, tls_client_key_file) {
            (Some(c), Some(k)) => Some((c, k)),
            (None, None) => None,
            _ => {
                return Err(PyValueError::new_err(
                    "tls_client_cert_file, tls_client_key_file: give both or neither",
                ))
            }
        };
        let tls = ClientTls { ca_file: tls_ca_file, identity };
        let endpoint = sf_service::tls::endpoint(url, &tls)
            .map_err(|e| PyValueError::new_err(format!("url: {e:#}")))?;
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| PyRuntimeError::new_err(format!("starting the client's runtime: {e}")))?;
        let c = py.detach(|| rt.block_on(client::connect(endpoint, url, token))).map_err(py_err)?;
        Ok(Self { rt: std::sync::Arc::new(rt), c })
    }

    /// Queues a job config or evaluation grid (TOML text); the job as JSON.
    fn submit(&mut self, py: Python<'_>, config_toml: String) -> PyResult<String> {
        let (rt, c) = (&self.rt, &mut self.c);
        let j = py.detach(|| rt.block_on(client::submit(c, config_toml))).map_err(py_err)?;
        Ok(client::job_json(&j).to_string())
    }

    /// One job, with its config, as JSON.
    fn job(&mut self, py: Python<'_>, job_id: u64) -> PyResult<String> {
        let (rt, c) = (&self.rt, &mut self.c);
        let j = py.detach(|| rt.block_on(client::get(c, JobId::from(job_id)))).map_err(py_err)?;
        Ok(client::job_json(&j).to_string())
    }

    /// Every job, newest first, as a JSON list.
    fn jobs(&mut self, py: Python<'_>) -> PyResult<String> {
        let (rt, c) = (&self.rt, &mut self.c);
        let all = py.detach(|| rt.block_on(client::list(c))).map_err(py_err)?;
        Ok(serde_json::Value::Array(all.iter().map(client::job_json).collect()).to_string())
    }

    /// Cancels a queued or running job; the job as JSON.
    fn cancel(&mut self, py: Python<'_>, job_id: u64) -> PyResult<String> {
        let (rt, c) = (&self.rt, &mut self.c);
        let j =
            py.detach(|| rt.block_on(client::cancel(c, JobId::from(job_id)))).map_err(py_err)?;
        Ok(client::job_json(&j).to_string())
    }

    /// One file of the job's artifact directory.
    fn file<'py>(
        &mut self,
        py: Python<'py>,
        job_id: u64,
        name: &str,
    ) -> PyResult<Bound<'py, PyBytes>> {
        let (rt, c) = (&self.rt, &mut self.c);
        let b = py
            .detach(|| rt.block_on(client::file(c, JobId::from(job_id), name)))
            .map_err(py_err)?;
        Ok(PyBytes::new(py, &b))
    }

    /// A succeeded job's files into `dir`; the names written.
    fn download(&mut self, py: Python<'_>, job_id: u64, dir: PathBuf) -> PyResult<Vec<String>> {
        let (rt, c) = (&self.rt, &mut self.c);
        py.detach(|| rt.block_on(client::download(c, JobId::from(job_id), &dir))).map_err(py_err)
    }

    /// Opens the job's progress stream.
    fn watch(&mut self, py: Python<'_>, job_id: u64) -> PyResult<JobWatch> {
        let (rt, c) = (&self.rt, &mut self.c);
        let w = py
            .detach(|| rt.block_on(client::Watch::open(c, JobId::from(job_id))))
            .map_err(py_err)?;
        Ok(JobWatch { rt: std::sync::Arc::clone(&self.rt), w })
    }
}

/// A job's progress stream.
#[pyclass(module = "socialflow._socialflow")]
pub struct JobWatch {
    rt: std::sync::Arc<Runtime>,
    w: client::Watch,
}

#[pymethods]
impl JobWatch {
    /// The next change as JSON (`state` and `progress`), or `None` after the final one.
    fn next(&mut self, py: Python<'_>) -> PyResult<Option<String>> {
        let (rt, w) = (&self.rt, &mut self.w);
        let n = py.detach(|| rt.block_on(w.next())).map_err(py_err)?;
        Ok(n.map(|(state, p)| {
            serde_json::json!({"state": state.as_str(), "progress": p}).to_string()
        }))
    }
}
