//! Whether the data directory takes writes.
//!
//! Owns: which errors are storage faults ([`is_storage_fault`]: a full disk, a quota, a
//! read-only or failing file system, or a job store poisoned by one), [`StorageHealth`] (the
//! fault's cause and since when, the log line about it: once at ERROR, then at most once per
//! doubling back-off; the `socialflow_learner_storage_ok` gauge and the readiness a fault
//! withholds) and [`probe`], which says when the disk takes writes again. Must not: decide what
//! a job does about a fault (the scheduler stops starting jobs, a trainer stops at its last
//! checkpoint and its job stays RUNNING) or reopen the job store (the learner's recovery task
//! does, after a probe succeeds).

use std::io;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use sf_service::sync::lock;

use crate::store::StoreError;

/// The first repeat of a fault is logged after this, then after twice as long, up to
/// [`MAX_LOG_EVERY`].
const FIRST_LOG_EVERY: Duration = Duration::from_secs(10);
const MAX_LOG_EVERY: Duration = Duration::from_secs(300);

/// Errno values of storage faults on Linux: EIO, ENOSPC, EROFS, EDQUOT.
const STORAGE_ERRNOS: [i32; 4] = [5, 28, 30, 122];

/// Messages of storage faults whose `io::Error` did not survive as a source (flattened into a
/// string by a library on the way).
const STORAGE_MESSAGES: [&str; 5] = [
    "No space left on device",
    "Disk quota exceeded",
    "Read-only file system",
    "Input/output error",
    "Previous I/O error",
];

/// Whether `e` (or any error in its source chain) is the disk refusing reads or writes, as
/// opposed to a defect or bad input: such a job pauses instead of failing.
pub fn is_storage_fault(e: &(dyn std::error::Error + 'static)) -> bool {
    let mut cur = Some(e);
    while let Some(err) = cur {
        if err.downcast_ref::<io::Error>().is_some_and(is_storage_io)
            || matches!(err.downcast_ref::<StoreError>(), Some(StoreError::Storage { .. }))
        {
            return true;
        }
        cur = err.source();
    }
    let text = e.to_string();
    STORAGE_MESSAGES.iter().any(|m| text.contains(m))
}

fn is_storage_io(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::StorageFull
            | io::ErrorKind::ReadOnlyFilesystem
            | io::ErrorKind::QuotaExceeded
    ) || e.raw_os_error().is_some_and(|n| STORAGE_ERRNOS.contains(&n))
}

/// Whether `dir` takes a write: 1 MiB written, synced and removed.
pub fn probe(dir: &Path) -> io::Result<()> {
    use std::io::Write;
    let p = dir.join(".storage-probe");
    let r = (|| {
        let mut f = std::fs::File::create(&p)?;
        f.write_all(&vec![0u8; 1 << 20])?;
        f.sync_all()
    })();
    let _ = std::fs::remove_file(&p);
    r
}

struct Fault {
    cause: String,
    since: Instant,
    next_log: Instant,
    log_every: Duration,
    /// Faults seen since the last log line.
    unlogged: u64,
}

/// The data directory's health as the learner last saw it.
pub struct StorageHealth {
    fault: Mutex<Option<Fault>>,
    /// The admin port's readiness: false while a fault lasts.
    ready: Arc<AtomicBool>,
    ok: Gauge,
    faults: Counter,
}

impl StorageHealth {
    /// `ready`: the readiness the admin port serves; `ok` and `faults`: the
    /// `socialflow_learner_storage_ok` gauge and `socialflow_learner_storage_faults_total`.
    pub fn new(ready: Arc<AtomicBool>, ok: Gauge, faults: Counter) -> Self {
        ok.set(1);
        Self { fault: Mutex::new(None), ready, ok, faults }
    }

    pub fn healthy(&self) -> bool {
        lock(&self.fault).is_none()
    }

    /// The cause of the fault that lasts, if one does.
    pub fn cause(&self) -> Option<String> {
        lock(&self.fault).as_ref().map(|f| f.cause.clone())
    }

    /// Records a storage fault (`cause`: the error as text). Readiness goes false; the first
    /// fault is logged at ERROR with its cause, repeats at most once per back-off (10 s,
    /// doubling to 5 min) with how many were seen meanwhile.
    pub fn fault(&self, cause: &str) {
        self.faults.inc();
        self.ok.set(0);
        self.ready.store(false, Ordering::Release);
        let now = Instant::now();
        let mut f = lock(&self.fault);
        match &mut *f {
            None => {
                tracing::error!(cause, "the data directory refuses writes: no job starts, the running one stops at its last checkpoint and resumes when the disk takes writes again");
                *f = Some(Fault {
                    cause: cause.to_string(),
                    since: now,
                    next_log: now + FIRST_LOG_EVERY,
                    log_every: FIRST_LOG_EVERY,
                    unlogged: 0,
                });
            }
            Some(x) => {
                x.unlogged += 1;
                x.cause = cause.to_string();
                if now >= x.next_log {
                    tracing::warn!(
                        cause,
                        for_s = x.since.elapsed().as_secs(),
                        repeats = x.unlogged,
                        "the data directory still refuses writes"
                    );
                    x.log_every = (x.log_every * 2).min(MAX_LOG_EVERY);
                    x.next_log = now + x.log_every;
                    x.unlogged = 0;
                }
            }
        }
    }

    /// The disk takes writes again (a probe succeeded and the store reopened).
    pub fn recovered(&self) {
        if let Some(f) = lock(&self.fault).take() {
            tracing::info!(
                after_s = f.since.elapsed().as_secs(),
                "the data directory takes writes again: jobs resume"
            );
        }
        self.ok.set(1);
        self.ready.store(true, Ordering::Release);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disk_errors_are_storage_faults_and_others_are_not() {
        let full = io::Error::from_raw_os_error(28);
        assert!(is_storage_fault(&full));
        assert!(is_storage_fault(&io::Error::from(io::ErrorKind::ReadOnlyFilesystem)));
        assert!(!is_storage_fault(&io::Error::from(io::ErrorKind::NotFound)));
        assert!(!is_storage_fault(&io::Error::from(io::ErrorKind::PermissionDenied)));
        // Through a chain of sources, and as a poisoned store.
        let wrapped = crate::LearnerError::Io {
            action: "writing",
            path: "x".into(),
            source: io::Error::from_raw_os_error(28),
        };
        assert!(is_storage_fault(&wrapped));
        let store = crate::LearnerError::Store(StoreError::Storage {
            path: "jobs.redb".into(),
            reason: "Previous I/O error occurred".into(),
        });
        assert!(is_storage_fault(&store));
        let other = crate::LearnerError::Store(StoreError::Db {
            path: "jobs.redb".into(),
            reason: "table missing".into(),
        });
        assert!(!is_storage_fault(&other));
    }

    #[test]
    fn a_fault_withholds_readiness_until_recovery() {
        let ready = Arc::new(AtomicBool::new(true));
        let h = StorageHealth::new(Arc::clone(&ready), Gauge::default(), Counter::default());
        assert!(h.healthy());
        h.fault("No space left on device");
        h.fault("No space left on device");
        assert!(!h.healthy() && !ready.load(Ordering::Acquire));
        assert_eq!((h.ok.get(), h.faults.get()), (0, 2));
        assert_eq!(h.cause().as_deref(), Some("No space left on device"));
        h.recovered();
        assert!(h.healthy() && ready.load(Ordering::Acquire) && h.ok.get() == 1);
    }
}
