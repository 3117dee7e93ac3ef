//! A job's artifact directory as files: the helpers every part writes and reads it with.
//!
//! Owns: [`write_atomic`] (written beside, then renamed over: a reader never sees half a file),
//! [`create_dir`], [`write`] and [`read`] (errors name the action and the path),
//! [`read_final`] (a finished job's `policy.bpk` / `policy.json`: what workers, validation and
//! evaluation grids get of a frozen policy), and what clients may read of a directory
//! (`GetJobFile`): [`READABLE`] and [`read_job_file`]. All blocking: call off the async runtime.
//! Must not: decide what a job writes or when (the trainer, validation and the evaluation job
//! do), or read a client's name that is not in [`READABLE`] (a name is never joined to a path
//! unless it is one of them, so `../` cannot escape the directory).

use std::path::Path;

use sf_job::JobId;

use crate::error::LearnerError;

/// The files of a job directory a client may fetch: the resolved config, the final and best
/// actors with their metadata, the curves, CoPO's coordinator, the counters, and an
/// evaluation's results.
pub const READABLE: [&str; 12] = [
    "config.toml",
    "policy.bpk",
    "policy.json",
    "best_policy.bpk",
    "best_policy.json",
    "curve.csv",
    "curve.png",
    "validation.csv",
    "coordinator.json",
    "state.json",
    "episodes.csv",
    "meta.json",
];

/// The error of `action` ("reading", "writing", ...) on `path`.
pub(crate) fn io_error(
    action: &'static str,
    path: &Path,
) -> impl FnOnce(std::io::Error) -> LearnerError {
    let path = path.to_path_buf();
    move |source| LearnerError::Io { action, path, source }
}

/// Creates `dir` and its parents.
pub(crate) fn create_dir(dir: &Path) -> Result<(), LearnerError> {
    std::fs::create_dir_all(dir).map_err(io_error("creating", dir))
}

/// Writes `bytes` to `path` in place.
pub(crate) fn write(path: &Path, bytes: &[u8]) -> Result<(), LearnerError> {
    std::fs::write(path, bytes).map_err(io_error("writing", path))
}

/// Writes `bytes` beside `path`, then renames the copy over it.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), LearnerError> {
    let tmp = path.with_extension("tmp");
    write(&tmp, bytes)?;
    std::fs::rename(&tmp, path).map_err(io_error("renaming", path))
}

/// The content of `path`.
pub(crate) fn read(path: &Path) -> Result<Vec<u8>, LearnerError> {
    std::fs::read(path).map_err(io_error("reading", path))
}

/// A file of finished job `job_id`'s artifact directory `dir` (`policy.bpk`, `policy.json`).
pub(crate) fn read_final(dir: &Path, job_id: JobId, name: &str) -> Result<Vec<u8>, LearnerError> {
    std::fs::read(dir.join(name)).map_err(|source| LearnerError::FinalPolicy { job_id, source })
}

/// `name` if it is one of [`READABLE`].
pub(crate) fn readable(name: &str) -> Result<&'static str, LearnerError> {
    READABLE.iter().find(|&&n| n == name).copied().ok_or_else(|| LearnerError::UnknownJobFile {
        name: name.to_string(),
        readable: READABLE.join(", "),
    })
}

/// The content of file `name` ([`readable`]) of job `job_id`'s artifact directory `dir`, if it
/// fits in a reply under `limit` bytes.
pub(crate) fn read_job_file(
    dir: &Path,
    job_id: JobId,
    name: &'static str,
    limit: u64,
) -> Result<Vec<u8>, LearnerError> {
    let path = dir.join(name);
    let len = match std::fs::metadata(&path) {
        Ok(m) => m.len(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(LearnerError::NoJobFile { job_id, name });
        }
        Err(source) => return Err(LearnerError::Io { action: "reading", path, source }),
    };
    // The reply carries a few bytes besides the content.
    if len + 1024 > limit {
        return Err(LearnerError::JobFileTooLarge { job_id, name, bytes: len, limit });
    }
    read(&path)
}
