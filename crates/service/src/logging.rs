//! Logging set-up: `tracing` with a `RUST_LOG` filter, human or JSON lines on stderr; for the
//! commands that run a learner in their own process, a quiet terminal and the full log in a
//! file.
//!
//! Owns: [`init`] (the services: everything at INFO on stderr) and [`init_embedded`] (`train`,
//! `pipeline --embedded`, `ladder`: warnings and errors on the terminal, every INFO line in the
//! run's log file). Must not: decide what a command prints as its result or progress.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{fmt, EnvFilter, Layer};

/// Installs the global subscriber once; later calls are no-ops. `json` selects JSON lines.
pub fn init(json: bool) {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    // Colour only on a terminal: logs redirected to files stay greppable.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let b = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(ansi);
    let _ = if json { b.json().try_init() } else { b.try_init() };
}

/// Why [`init_embedded`] could not set logging up.
#[derive(Debug, thiserror::Error)]
pub enum LoggingError {
    #[error("--log-level `{level}`: {reason}")]
    Level { level: String, reason: String },
}

/// The set-up of a command that runs the learner and its workers in its own process: the
/// terminal gets `terminal` (a `RUST_LOG`-style filter; by default `RUST_LOG` if set, else
/// warnings and errors, so a user sees the progress display and what went wrong, not the
/// service's chatter) and `file` gets every INFO line, appended (a resumed run's log goes on).
/// The file and its directory are made at the first line, so a command refused before it logs
/// anything (an invalid config) leaves nothing behind.
pub fn init_embedded(terminal: Option<&str>, file: &Path) -> Result<(), LoggingError> {
    let term = match terminal {
        Some(level) => EnvFilter::try_new(level)
            .map_err(|e| LoggingError::Level { level: level.into(), reason: e.to_string() })?,
        None => EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn")),
    };
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let _ = tracing_subscriber::registry()
        .with(fmt::layer().with_writer(std::io::stderr).with_ansi(ansi).with_filter(term))
        .with(
            fmt::layer()
                .with_writer(LazyFile::new(file))
                .with_ansi(false)
                .with_filter(EnvFilter::new("info")),
        )
        .try_init();
    Ok(())
}

/// A log file opened (with its directory) at the first write. If it cannot be opened, the
/// terminal is told once and the lines are dropped: logging never stops a run.
struct LazyFile {
    path: PathBuf,
    file: Mutex<Option<File>>,
    failed: AtomicBool,
}

impl LazyFile {
    fn new(path: &Path) -> Self {
        Self { path: path.to_path_buf(), file: Mutex::new(None), failed: AtomicBool::new(false) }
    }

    fn open(&self) -> std::io::Result<File> {
        if let Some(dir) = self.path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::OpenOptions::new().create(true).append(true).open(&self.path)
    }
}

impl Write for &LazyFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let mut f = crate::sync::lock(&self.file);
        if f.is_none() && !self.failed.load(Ordering::Relaxed) {
            match self.open() {
                Ok(file) => *f = Some(file),
                Err(e) => {
                    self.failed.store(true, Ordering::Relaxed);
                    eprintln!("cannot write the log file {}: {e}", self.path.display());
                }
            }
        }
        match f.as_mut() {
            Some(file) => file.write(buf),
            None => Ok(buf.len()),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        crate::sync::lock(&self.file).as_mut().map_or(Ok(()), |f| f.flush())
    }
}

impl<'a> fmt::MakeWriter<'a> for LazyFile {
    type Writer = &'a LazyFile;

    fn make_writer(&'a self) -> Self::Writer {
        self
    }
}
