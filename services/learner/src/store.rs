//! The job store: an embedded redb database that survives restarts.
//!
//! Owns: [`Store`] (jobs by id as JSON records, the id counter) and where a job's artifact
//! directory is: always `<data dir>/jobs/<id>-<name>`, stored relative to the data directory and
//! read back against the directory the store is opened in, so a data directory that was moved or
//! restored elsewhere keeps its jobs (stores written with absolute paths read the same way).
//! Every write is one committed transaction, so a crash leaves either the old or the new record.
//! Reads are served from the records this store has read or written (it is the file's only
//! writer), so they keep working while the disk refuses writes; an I/O error that poisons the
//! database is a [`StoreError::Storage`] (redb's `io::Error` kept as its source), and
//! [`Store::reopen`] opens the file again once the disk takes writes. Calls block on disk IO:
//! async code calls them through `spawn_blocking`.
//! Must not: hold training state (checkpoints live in each job's artifact directory).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, RwLock};

use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use sf_job::{now_unix_ms, JobId, JobRecord, JobState, Progress};
use sf_service::sync::{lock, read, write};

/// Jobs by id: the key is the bare number ([`JobId::get`]), as stores have always written it.
const JOBS: TableDefinition<u64, &[u8]> = TableDefinition::new("jobs");
const META: TableDefinition<&str, u64> = TableDefinition::new("meta");

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("job store {path}: {reason}")]
    Db { path: String, reason: String },
    /// The disk refused a read or write (full, read-only, failing): nothing was changed, and
    /// the database must be reopened ([`Store::reopen`]) once the disk takes writes again.
    /// `source`: redb's `io::Error` when it gave one (`None` for redb's "previous I/O error",
    /// a closed database and a store closed after an earlier fault). The variant itself is the
    /// classification (`storage::is_storage_fault`), whatever the error's kind.
    #[error("job store {path}: storage: {reason}")]
    Storage { path: String, reason: String, source: Option<std::io::Error> },
    #[error("job store record {id} is corrupt: {reason}")]
    Corrupt { id: JobId, reason: String },
}

pub struct Store {
    /// `None` between a failed reopen and the next one.
    db: RwLock<Option<Database>>,
    path: PathBuf,
    /// The data directory the artifact directories are read against.
    data_dir: PathBuf,
    /// Every record, as last committed.
    records: Mutex<BTreeMap<JobId, JobRecord>>,
}

/// Where job `id` (`name`) keeps its artifacts, relative to the data directory.
fn relative_artifact_dir(id: JobId, name: &str) -> PathBuf {
    Path::new("jobs").join(format!("{id}-{name}"))
}

impl Store {
    /// Opens (or creates) the database file `path` of data directory `data_dir` and reads every
    /// record.
    pub fn open(path: &Path, data_dir: &Path) -> Result<Self, StoreError> {
        let s = Self {
            db: RwLock::new(None),
            path: path.to_path_buf(),
            data_dir: data_dir.to_path_buf(),
            records: Mutex::new(BTreeMap::new()),
        };
        s.reopen()?;
        Ok(s)
    }

    /// Opens the database file again (after a [`StoreError::Storage`]) and reads every record
    /// back. On error the store stays closed: writes fail, reads keep answering.
    pub fn reopen(&self) -> Result<(), StoreError> {
        // Locks in the writers' order: the records, then the database.
        let mut records = lock(&self.records);
        let mut db = write(&self.db);
        // The file is locked while open: the old handle goes first.
        *db = None;
        let fresh = Database::create(&self.path).map_err(|e| self.err(e))?;
        let w = fresh.begin_write().map_err(|e| self.err(e))?;
        {
            w.open_table(JOBS).map_err(|e| self.err(e))?;
            w.open_table(META).map_err(|e| self.err(e))?;
        }
        w.commit().map_err(|e| self.err(e))?;
        let mut read_back = BTreeMap::new();
        {
            let r = fresh.begin_read().map_err(|e| self.err(e))?;
            let t = r.open_table(JOBS).map_err(|e| self.err(e))?;
            for item in t.iter().map_err(|e| self.err(e))? {
                let (k, v) = item.map_err(|e| self.err(e))?;
                let id = JobId::new(k.value());
                read_back.insert(id, self.decode(id, v.value())?);
            }
        }
        *records = read_back;
        *db = Some(fresh);
        Ok(())
    }

    /// `e` on this store's file: a [`StoreError::Storage`] (with redb's `io::Error` as its
    /// source) when the disk refused a read or write, else a [`StoreError::Db`].
    fn err(&self, e: impl Into<redb::Error>) -> StoreError {
        let (path, e) = (self.path.display().to_string(), e.into());
        let reason = e.to_string();
        match e {
            redb::Error::Io(io) => StoreError::Storage { path, reason, source: Some(io) },
            redb::Error::PreviousIo | redb::Error::DatabaseClosed => {
                StoreError::Storage { path, reason, source: None }
            }
            _ => StoreError::Db { path, reason },
        }
    }

    /// A write transaction on the open database.
    fn begin_write(&self) -> Result<redb::WriteTransaction, StoreError> {
        match &*read(&self.db) {
            Some(db) => db.begin_write().map_err(|e| self.err(e)),
            None => Err(StoreError::Storage {
                path: self.path.display().to_string(),
                reason: "closed after a storage error; it reopens when the disk takes writes"
                    .into(),
                source: None,
            }),
        }
    }

    /// A stored record with its artifact directory under this store's data directory, whatever
    /// the record says (a relative path, or an absolute one from where the data lived before).
    fn decode(&self, id: JobId, bytes: &[u8]) -> Result<JobRecord, StoreError> {
        let mut rec: JobRecord = serde_json::from_slice(bytes)
            .map_err(|e| StoreError::Corrupt { id, reason: e.to_string() })?;
        rec.artifact_dir =
            self.data_dir.join(relative_artifact_dir(rec.id, &rec.name)).display().to_string();
        Ok(rec)
    }

    /// The bytes stored for `rec`: its artifact directory relative to the data directory.
    fn encode(rec: &JobRecord) -> Vec<u8> {
        let stored = JobRecord {
            artifact_dir: relative_artifact_dir(rec.id, &rec.name).display().to_string(),
            ..rec.clone()
        };
        serde_json::to_vec(&stored).expect("job records serialise")
    }

    /// Creates a queued job with the next id, its artifact directory `<data dir>/jobs/<id>-<name>`.
    pub fn create(
        &self,
        name: &str,
        config_toml: &str,
        target_env_steps: u64,
    ) -> Result<JobRecord, StoreError> {
        // The records' lock is held across the transaction: writes happen one at a time and
        // the kept records are always the committed ones.
        let mut records = lock(&self.records);
        let w = self.begin_write()?;
        let rec;
        {
            let mut meta = w.open_table(META).map_err(|e| self.err(e))?;
            let next =
                meta.get("next_id").map_err(|e| self.err(e))?.map(|g| g.value()).unwrap_or(1);
            meta.insert("next_id", next + 1).map_err(|e| self.err(e))?;
            let id = JobId::new(next);
            let now = now_unix_ms();
            rec = JobRecord {
                id,
                name: name.to_string(),
                state: JobState::Queued,
                config_toml: config_toml.to_string(),
                message: String::new(),
                created_unix_ms: now,
                updated_unix_ms: now,
                progress: Progress { target_env_steps, ..Progress::default() },
                artifact_dir: self
                    .data_dir
                    .join(relative_artifact_dir(id, name))
                    .display()
                    .to_string(),
            };
            let bytes = Self::encode(&rec);
            w.open_table(JOBS)
                .map_err(|e| self.err(e))?
                .insert(id.get(), bytes.as_slice())
                .map_err(|e| self.err(e))?;
        }
        w.commit().map_err(|e| self.err(e))?;
        records.insert(rec.id, rec.clone());
        Ok(rec)
    }

    /// The job's record (from memory: the store keeps every record loaded; writes go through).
    pub fn get(&self, id: JobId) -> Option<JobRecord> {
        lock(&self.records).get(&id).cloned()
    }

    /// Every job, oldest first.
    pub fn list(&self) -> Vec<JobRecord> {
        lock(&self.records).values().cloned().collect()
    }

    /// Applies `f` to the stored record in one transaction and returns the result; `None` if
    /// the job does not exist. `updated_unix_ms` is set. On error nothing changed.
    pub fn update(
        &self,
        id: JobId,
        f: impl FnOnce(&mut JobRecord),
    ) -> Result<Option<JobRecord>, StoreError> {
        let mut records = lock(&self.records);
        let Some(mut rec) = records.get(&id).cloned() else {
            return Ok(None);
        };
        let w = self.begin_write()?;
        f(&mut rec);
        rec.updated_unix_ms = now_unix_ms();
        let bytes = Self::encode(&rec);
        w.open_table(JOBS)
            .map_err(|e| self.err(e))?
            .insert(id.get(), bytes.as_slice())
            .map_err(|e| self.err(e))?;
        w.commit().map_err(|e| self.err(e))?;
        records.insert(id, rec.clone());
        Ok(Some(rec))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jobs_survive_reopening_and_ids_keep_rising() {
        let dir = std::env::temp_dir().join(format!("sf-store-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("tmp");
        let path = dir.join("jobs.redb");
        {
            let s = Store::open(&path, &dir).expect("open");
            let a = s.create("a", "cfg-a", 10).expect("create");
            let b = s.create("b", "cfg-b", 20).expect("create");
            assert_eq!((a.id, b.id), (JobId::new(1), JobId::new(2)));
            assert_eq!(Path::new(&b.artifact_dir), dir.join("jobs/2-b"));
            s.update(JobId::new(1), |r| {
                r.state = JobState::Running;
                r.progress.learning.updates = 5;
            })
            .expect("update");
            assert!(s.update(JobId::new(99), |_| {}).expect("update").is_none());
        }
        let s = Store::open(&path, &dir).expect("reopen");
        let all = s.list();
        assert_eq!(all.len(), 2);
        assert_eq!(all[0].state, JobState::Running);
        assert_eq!(all[0].progress.learning.updates, 5);
        assert_eq!(all[1].config_toml, "cfg-b");
        assert_eq!(s.create("c", "x", 1).expect("create").id, JobId::new(3));
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A data directory moved elsewhere keeps its jobs' artifact directories, including a store
    /// written before paths were relative (an absolute path to where the data used to be).
    #[test]
    fn a_moved_data_directory_finds_its_artifacts_where_it_is_now() {
        let base = std::env::temp_dir().join(format!("sf-store-moved-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&base);
        let (old, new) = (base.join("old"), base.join("new"));
        std::fs::create_dir_all(&old).expect("tmp");
        {
            let s = Store::open(&old.join("jobs.redb"), &old).expect("open");
            s.create("kept", "cfg", 10).expect("create");
            // A record as stores wrote it before: the absolute path of the old directory.
            let legacy = JobRecord {
                artifact_dir: old.join("jobs/2-legacy").display().to_string(),
                ..s.create("legacy", "cfg", 10).expect("create")
            };
            let w = s.begin_write().expect("write");
            w.open_table(JOBS)
                .expect("table")
                .insert(2, serde_json::to_vec(&legacy).expect("json").as_slice())
                .expect("insert");
            w.commit().expect("commit");
        }
        std::fs::rename(&old, &new).expect("move the data directory");
        let s = Store::open(&new.join("jobs.redb"), &new).expect("open the moved store");
        let dirs: Vec<PathBuf> = s.list().iter().map(|r| PathBuf::from(&r.artifact_dir)).collect();
        assert_eq!(dirs, vec![new.join("jobs/1-kept"), new.join("jobs/2-legacy")]);
        let updated = s
            .update(JobId::new(2), |r| r.message = "touched".into())
            .expect("update")
            .expect("job 2");
        assert_eq!(Path::new(&updated.artifact_dir), new.join("jobs/2-legacy"));
        // What is stored now is relative to the data directory.
        let db = read(&s.db);
        let r = db.as_ref().expect("open").begin_read().expect("read");
        let raw: JobRecord = serde_json::from_slice(
            r.open_table(JOBS).expect("table").get(2).expect("get").expect("job 2").value(),
        )
        .expect("json");
        assert_eq!(raw.artifact_dir, "jobs/2-legacy");
        let _ = std::fs::remove_dir_all(&base);
    }

    /// redb's I/O errors, and a store closed after one, are storage faults by their type (the
    /// `io::Error` kept as the source of a [`StoreError::Storage`]), not by their text; other
    /// database errors are not, whatever their text says.
    #[test]
    fn a_storage_error_keeps_its_io_error_and_is_a_storage_fault_by_type() {
        use crate::storage::is_storage_fault;
        use crate::LearnerError;
        use std::error::Error as _;
        let dir = std::env::temp_dir().join(format!("sf-store-fault-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("tmp");
        let s = Store::open(&dir.join("jobs.redb"), &dir).expect("open");
        let id = s.create("a", "cfg", 1).expect("create").id;

        let full =
            LearnerError::Store(s.err(redb::Error::Io(std::io::Error::from_raw_os_error(28))));
        let kept = full
            .source()
            .and_then(|store| store.source())
            .and_then(|io| io.downcast_ref::<std::io::Error>())
            .and_then(std::io::Error::raw_os_error);
        assert_eq!(kept, Some(28), "the io::Error survives as a source: {full}");
        let message = format!(
            "job store {}: storage: I/O error: {}",
            dir.join("jobs.redb").display(),
            std::io::Error::from_raw_os_error(28)
        );
        assert_eq!(full.to_string(), message, "the message is unchanged");
        assert!(is_storage_fault(&full), "{full}");
        assert!(is_storage_fault(&LearnerError::Store(s.err(redb::Error::PreviousIo))));
        assert!(is_storage_fault(&LearnerError::Store(s.err(redb::Error::DatabaseClosed))));
        // Any I/O error poisons redb's file: it is reopened after a probe, whatever the kind.
        let denied = s.err(redb::Error::Io(std::io::ErrorKind::PermissionDenied.into()));
        assert!(is_storage_fault(&LearnerError::Store(denied)));

        let other = LearnerError::Store(s.err(redb::Error::TableDoesNotExist("jobs".into())));
        assert!(!is_storage_fault(&other), "{other}");
        let text_only = LearnerError::Store(StoreError::Db {
            path: "jobs.redb".into(),
            reason: "Previous I/O error occurred: No space left on device (os error 28)".into(),
        });
        assert!(!is_storage_fault(&text_only), "{text_only}");

        // A store closed after a fault refuses writes as a storage fault until it reopens.
        *write(&s.db) = None;
        let closed = s.update(id, |_| {}).expect_err("a closed store refuses writes");
        assert!(is_storage_fault(&LearnerError::Store(closed)));
        s.reopen().expect("reopen");
        assert!(s.update(id, |_| {}).expect("update").is_some());
        drop(s);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
