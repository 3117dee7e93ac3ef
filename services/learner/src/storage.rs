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
//!
//! A fault is recognised by the errors' types, not their messages: an `io::Error` of a storage
//! kind or errno anywhere in the source chain (every write of a job keeps its `io::Error` as a
//! source: artifact files through `artifacts::write`/`write_atomic`, the checkpoint, the replay's
//! segments, the job store, an evaluation's `episodes.csv` through `sf_report::episodes`'s
//! `FileError`), a [`StoreError::Storage`] (redb's I/O errors, a closed store) or a
//! [`LearnerError::StorageFault`].

use std::io;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::gauge::Gauge;
use sf_service::sync::lock;

use crate::error::LearnerError;
use crate::store::StoreError;

/// The first repeat of a fault is logged after this, then after twice as long, up to
/// [`MAX_LOG_EVERY`].
const FIRST_LOG_EVERY: Duration = Duration::from_secs(10);
const MAX_LOG_EVERY: Duration = Duration::from_secs(300);

/// Errno values of storage faults on Linux: EIO, ENOSPC, EROFS, EDQUOT.
const STORAGE_ERRNOS: [i32; 4] = [5, 28, 30, 122];

/// Whether `e` (or any error in its source chain) is the disk refusing reads or writes, as
/// opposed to a defect or bad input: such a job pauses instead of failing. Decided by the
/// errors' types alone (the module header): an error whose text merely names a full disk (a
/// worker's failed cell, a message built from another error's text) is not a storage fault.
pub fn is_storage_fault(e: &(dyn std::error::Error + 'static)) -> bool {
    let mut cur = Some(e);
    while let Some(err) = cur {
        if err.downcast_ref::<io::Error>().is_some_and(is_storage_io)
            || matches!(err.downcast_ref::<StoreError>(), Some(StoreError::Storage { .. }))
            || matches!(err.downcast_ref::<LearnerError>(), Some(LearnerError::StorageFault { .. }))
        {
            return true;
        }
        cur = err.source();
    }
    false
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
    use sf_report::episodes::FileError;

    #[test]
    fn disk_errors_are_storage_faults_and_others_are_not() {
        assert!(is_storage_fault(&io::Error::from_raw_os_error(28)));
        assert!(is_storage_fault(&io::Error::from(io::ErrorKind::ReadOnlyFilesystem)));
        assert!(is_storage_fault(&io::Error::from(io::ErrorKind::StorageFull)));
        assert!(!is_storage_fault(&io::Error::from(io::ErrorKind::NotFound)));
        assert!(!is_storage_fault(&io::Error::from(io::ErrorKind::PermissionDenied)));
    }

    /// Every way a job's write reaches the disk, its `io::Error` wrapped as that path wraps it:
    /// a full disk (ENOSPC), a quota (EDQUOT), a read-only (EROFS) or failing (EIO) file system
    /// is a storage fault by the typed source alone.
    #[test]
    fn each_write_path_is_a_storage_fault_by_its_typed_source() {
        use sf_sac::checkpoint::CheckpointError;
        use sf_sac::replay_store::ReplayStoreError;
        for errno in STORAGE_ERRNOS {
            let e = || io::Error::from_raw_os_error(errno);
            let paths = [
                // `artifacts::write`/`write_atomic`: config.toml, published_version, state.json,
                // curve.csv, validation.csv, policy.bpk/.json, best_policy.*, coordinator.json,
                // an evaluation's meta.json.
                LearnerError::Io {
                    action: "writing",
                    path: "jobs/1-a/curve.tmp".into(),
                    source: e(),
                },
                LearnerError::Io {
                    action: "renaming",
                    path: "jobs/1-a/state.json".into(),
                    source: e(),
                },
                // `sf_sac::checkpoint::save` (module and optimizer records are encoded to bytes
                // in memory and written with std::fs).
                LearnerError::SaveCheckpoint(CheckpointError::Io {
                    path: "jobs/1-a/.checkpoint.tmp/actor.bpk".into(),
                    source: e(),
                }),
                // `ReplayStore::append`, a replay segment.
                LearnerError::Replay {
                    action: "writing",
                    source: ReplayStoreError::Io {
                        path: "jobs/1-a/replay/seg.tmp".into(),
                        source: e(),
                    },
                },
                // The job store (redb's `io::Error` kept: `store::tests`).
                LearnerError::Store(StoreError::Storage {
                    path: "jobs.redb".into(),
                    reason: "I/O error".into(),
                    source: Some(e()),
                }),
                // A resumed job's reads: a failing disk pauses it too.
                LearnerError::Checkpoint {
                    action: "restoring",
                    path: "jobs/1-a/checkpoint".into(),
                    source: CheckpointError::Io { path: "state.json".into(), source: e() },
                },
            ];
            for p in &paths {
                assert!(is_storage_fault(p), "errno {errno}: {p}");
            }
        }
        // Faults known by their type without an io::Error: a poisoned or closed job store, and
        // a refusal because of a fault already recorded.
        let poisoned = LearnerError::Store(StoreError::Storage {
            path: "jobs.redb".into(),
            reason: "Previous I/O error occurred. Please close and re-open the database.".into(),
            source: None,
        });
        assert!(is_storage_fault(&poisoned));
        assert!(is_storage_fault(&LearnerError::StorageFault { cause: "writing x".into() }));
    }

    /// An evaluation's `episodes.csv` (`sf_report::episodes`) keeps the file system's
    /// `io::Error` as its source: a storage errno there is a fault; other io errors, and bad
    /// content whose text quotes a full disk, are not.
    #[test]
    fn episodes_csv_is_a_storage_fault_by_its_source() {
        let file = |reason: &str, io: Option<io::Error>| {
            LearnerError::Episodes(FileError {
                path: "jobs/2-e/episodes.csv".into(),
                reason: reason.into(),
                io,
            })
        };
        for errno in STORAGE_ERRNOS {
            let e = file("appending", Some(io::Error::from_raw_os_error(errno)));
            assert!(is_storage_fault(&e), "{e}");
        }
        for (reason, io) in [
            ("not found", Some(io::Error::from_raw_os_error(2))),
            ("permission denied", Some(io::Error::from_raw_os_error(13))),
            ("No space left on device (os error 28)", None),
            ("header `No space left on device (os error 28)` is not an episodes.csv header; not appending", None),
            ("line 3: success `Read-only file system` is not a number", None),
        ] {
            let e = file(reason, io);
            assert!(!is_storage_fault(&e), "{e}");
        }
    }

    /// A full device through the learner's own writers, end to end: `artifacts::write` (every
    /// artifact file) and `EpisodesWriter::open` (an evaluation's `episodes.csv`, the header
    /// written into a new file).
    #[cfg(target_os = "linux")]
    #[test]
    fn a_full_device_is_a_storage_fault_through_the_real_writers() {
        let full = Path::new("/dev/full");
        if !full.exists() {
            eprintln!("SKIPPED, no /dev/full: a full device through the real writers");
            return;
        }
        let e = crate::artifacts::write(full, b"x").expect_err("/dev/full takes no write");
        assert!(is_storage_fault(&e), "{e}");
        assert!(e.to_string().contains("/dev/full"), "the message names the file: {e}");
        match sf_report::episodes::EpisodesWriter::open(full) {
            Ok(_) => panic!("/dev/full took the episodes.csv header"),
            Err(e) => {
                let e = LearnerError::from(e);
                assert!(is_storage_fault(&e), "{e}");
            }
        }
    }

    /// Classification no longer depends on text: errors whose message merely names a full disk,
    /// a read-only file system or redb's poisoned state are not storage faults.
    #[test]
    fn a_message_that_names_a_full_disk_is_not_a_storage_fault() {
        let texts = [
            // An io::Error made from text (no errno, kind Other).
            LearnerError::Io {
                action: "writing",
                path: "x".into(),
                source: io::Error::other("No space left on device (os error 28)"),
            },
            // A worker's disk is not the learner's.
            LearnerError::CellFailed {
                cell: "idm/merge".into(),
                worker: sf_job::WorkerId::new(1),
                error: "writing /tmp/x: No space left on device (os error 28)".into(),
            },
            LearnerError::Store(StoreError::Db {
                path: "jobs.redb".into(),
                reason: "Previous I/O error occurred; Read-only file system".into(),
            }),
            LearnerError::BadEvalConfig {
                field: "egos.job",
                name: "Disk quota exceeded".into(),
                reason: "Input/output error".into(),
            },
        ];
        for e in &texts {
            assert!(!is_storage_fault(e), "{e}");
        }
        assert!(!is_storage_fault(&io::Error::other("No space left on device")));
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
