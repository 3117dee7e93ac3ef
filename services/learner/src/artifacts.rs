//! What clients may read of a job's artifact directory (`GetJobFile`).
//!
//! Owns: [`READABLE`], the files a client may fetch by name, and [`Inner::job_file`], which
//! reads one off the async runtime. Must not: read anything not in the list (a name is never
//! joined to a path unless it is one of them, so `../` cannot escape the directory), or write.

use std::sync::Arc;

use sf_service::ServiceError;

use crate::{Inner, LearnerError};

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

impl Inner {
    /// The content of file `name` of job `job_id`'s artifact directory.
    pub(crate) async fn job_file(
        self: &Arc<Self>,
        job_id: u64,
        name: &str,
    ) -> Result<Vec<u8>, ServiceError> {
        let Some(&name) = READABLE.iter().find(|&&n| n == name) else {
            return Err(LearnerError::UnknownJobFile { name: name.to_string() }.into());
        };
        let rec = self.job(job_id).await?;
        let path = std::path::PathBuf::from(&rec.artifact_dir).join(name);
        let limit = self.cfg.max_message_bytes as u64;
        tokio::task::spawn_blocking(move || -> Result<Vec<u8>, LearnerError> {
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
            std::fs::read(&path).map_err(|source| LearnerError::Io {
                action: "reading",
                path,
                source,
            })
        })
        .await
        .map_err(LearnerError::from)?
        .map_err(Into::into)
    }
}
