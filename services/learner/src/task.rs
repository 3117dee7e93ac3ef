//! Blocking work from async code.
//!
//! Owns: [`blocking`], the shared way the learner's async code runs store IO, file IO and decoding
//! on a blocking thread. Must not: run tensor work (the trainer thread does) or pick a status
//! (a panicked task is [`LearnerError::Join`], mapped in `error.rs`).

use crate::error::LearnerError;

/// Runs `f` on a blocking thread.
pub(crate) async fn blocking<T, E>(
    f: impl FnOnce() -> Result<T, E> + Send + 'static,
) -> Result<T, LearnerError>
where
    T: Send + 'static,
    E: Into<LearnerError> + Send + 'static,
{
    tokio::task::spawn_blocking(f).await.map_err(LearnerError::Join)?.map_err(Into::into)
}
