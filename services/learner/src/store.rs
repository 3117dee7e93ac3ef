//! The job store: an embedded redb database that survives restarts.
//!
//! Owns: [`Store`] (jobs by id as JSON records, the id counter). Every write is one committed
//! transaction, so a crash leaves either the old or the new record. Calls block on disk IO:
//! async code calls them through `spawn_blocking`. Must not: hold training state (checkpoints
//! live in each job's artifact directory).

use std::path::Path;

use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use sf_job::{now_unix_ms, JobRecord, JobState, Progress};

const JOBS: TableDefinition<u64, &[u8]> = TableDefinition::new("jobs");
const META: TableDefinition<&str, u64> = TableDefinition::new("meta");

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("job store {path}: {reason}")]
    Db { path: String, reason: String },
    #[error("job store record {id} is corrupt: {reason}")]
    Corrupt { id: u64, reason: String },
}

pub struct Store {
    db: Database,
    path: String,
}

impl Store {
    /// Opens (or creates) the database file.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        let p = path.display().to_string();
        let db = Database::create(path).map_err(|e| StoreError::Db { path: p.clone(), reason: e.to_string() })?;
        let s = Self { db, path: p };
        let w = s.db.begin_write().map_err(|e| s.err(e))?;
        {
            w.open_table(JOBS).map_err(|e| s.err(e))?;
            w.open_table(META).map_err(|e| s.err(e))?;
        }
        w.commit().map_err(|e| s.err(e))?;
        Ok(s)
    }

    fn err(&self, e: impl std::fmt::Display) -> StoreError {
        StoreError::Db { path: self.path.clone(), reason: e.to_string() }
    }

    /// Creates a queued job with the next id; `artifact_dir(id)` names its directory.
    pub fn create(&self, name: &str, config_toml: &str, target_env_steps: u64, artifact_dir: impl Fn(u64) -> String) -> Result<JobRecord, StoreError> {
        let w = self.db.begin_write().map_err(|e| self.err(e))?;
        let rec;
        {
            let mut meta = w.open_table(META).map_err(|e| self.err(e))?;
            let id = meta.get("next_id").map_err(|e| self.err(e))?.map(|g| g.value()).unwrap_or(1);
            meta.insert("next_id", id + 1).map_err(|e| self.err(e))?;
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
                artifact_dir: artifact_dir(id),
            };
            let bytes = serde_json::to_vec(&rec).expect("job records serialise");
            w.open_table(JOBS).map_err(|e| self.err(e))?.insert(id, bytes.as_slice()).map_err(|e| self.err(e))?;
        }
        w.commit().map_err(|e| self.err(e))?;
        Ok(rec)
    }

    pub fn get(&self, id: u64) -> Result<Option<JobRecord>, StoreError> {
        let r = self.db.begin_read().map_err(|e| self.err(e))?;
        let t = r.open_table(JOBS).map_err(|e| self.err(e))?;
        match t.get(id).map_err(|e| self.err(e))? {
            None => Ok(None),
            Some(g) => serde_json::from_slice(g.value()).map(Some).map_err(|e| StoreError::Corrupt { id, reason: e.to_string() }),
        }
    }

    /// Every job, oldest first.
    pub fn list(&self) -> Result<Vec<JobRecord>, StoreError> {
        let r = self.db.begin_read().map_err(|e| self.err(e))?;
        let t = r.open_table(JOBS).map_err(|e| self.err(e))?;
        let mut out = Vec::new();
        for item in t.iter().map_err(|e| self.err(e))? {
            let (k, v) = item.map_err(|e| self.err(e))?;
            let id = k.value();
            out.push(serde_json::from_slice(v.value()).map_err(|e| StoreError::Corrupt { id, reason: e.to_string() })?);
        }
        Ok(out)
    }

    /// Applies `f` to the stored record in one transaction and returns the result; `None` if
    /// the job does not exist. `updated_unix_ms` is set.
    pub fn update(&self, id: u64, f: impl FnOnce(&mut JobRecord)) -> Result<Option<JobRecord>, StoreError> {
        let w = self.db.begin_write().map_err(|e| self.err(e))?;
        let out;
        {
            let mut t = w.open_table(JOBS).map_err(|e| self.err(e))?;
            let cur: Option<JobRecord> = match t.get(id).map_err(|e| self.err(e))? {
                None => None,
                Some(g) => Some(serde_json::from_slice(g.value()).map_err(|e| StoreError::Corrupt { id, reason: e.to_string() })?),
            };
            let Some(mut rec) = cur else {
                return Ok(None);
            };
            f(&mut rec);
            rec.updated_unix_ms = now_unix_ms();
            let bytes = serde_json::to_vec(&rec).expect("job records serialise");
            t.insert(id, bytes.as_slice()).map_err(|e| self.err(e))?;
            out = rec;
        }
        w.commit().map_err(|e| self.err(e))?;
        Ok(Some(out))
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
            let s = Store::open(&path).expect("open");
            let a = s.create("a", "cfg-a", 10, |id| format!("jobs/{id}")).expect("create");
            let b = s.create("b", "cfg-b", 20, |id| format!("jobs/{id}")).expect("create");
            assert_eq!((a.id, b.id), (1, 2));
            s.update(1, |r| {
                r.state = JobState::Running;
                r.progress.learning.updates = 5;
            })
            .expect("update");
            assert!(s.update(99, |_| {}).expect("update").is_none());
        }
        let s = Store::open(&path).expect("reopen");
        let all = s.list().expect("list");
        assert_eq!(all.len(), 2);
        assert_eq!(all[0].state, JobState::Running);
        assert_eq!(all[0].progress.learning.updates, 5);
        assert_eq!(all[1].config_toml, "cfg-b");
        assert_eq!(s.create("c", "x", 1, |id| id.to_string()).expect("create").id, 3);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
