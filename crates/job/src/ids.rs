//! Typed ids that cross processes.
//!
//! Owns: [`WorkerId`], the number a learner gives a worker when it registers, [`JobId`], the
//! number a learner gives a job when it accepts it, and [`PolicyVersion`], a job's counter of
//! published actor weights, and [`CellId`], a cell's place in an evaluation job's grid, each as
//! a type of its own, so that one cannot be passed where
//! another is meant. Stored and written as the bare number (`serde(transparent)`), so files and
//! the wire format stay as they were.
//! Must not: know the wire format: the gRPC edges convert (`From<u64>` and `get`).

use std::fmt;

use serde::{Deserialize, Serialize};

/// A `u64` newtype that crosses processes: serialised as the bare number, `new`, `get` (for
/// the wire, the store's keys, logs and metrics), `From<u64>` and `Display`.
macro_rules! typed_id {
    ($(#[$doc:meta])* $name:ident) => {
        $(#[$doc])*
        #[derive(
            Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize,
        )]
        #[serde(transparent)]
        pub struct $name(u64);

        impl $name {
            pub const fn new(id: u64) -> Self {
                Self(id)
            }

            /// The number, for the wire, the store's keys, files, logs and metrics.
            pub const fn get(self) -> u64 {
                self.0
            }
        }

        impl From<u64> for $name {
            fn from(id: u64) -> Self {
                Self(id)
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                self.0.fmt(f)
            }
        }
    };
}

typed_id!(
    /// A worker, as the learner that registered it numbers it (ids are issued once per learner
    /// start).
    WorkerId
);

typed_id!(
    /// A job, as the learner that accepted it numbers it (ids start at 1 and are never reused by
    /// a job store; they name job directories, `jobs/<id>-<name>`, and dependencies in job
    /// configs).
    JobId
);

typed_id!(
    /// A published policy's version: a job's counter of published actor weights. Published
    /// versions start at 1; 0 (the default) is a job that has published none yet, and on the
    /// wire the warm-up's actions or "the latest policy" ([`crate::ActedBy`],
    /// [`crate::PolicyRequest`]).
    PolicyVersion
);

typed_id!(
    /// A cell of an evaluation job: its index in the job's list of cells
    /// ([`crate::eval::EvalConfig::cells`]), which a worker's results name.
    CellId
);

impl CellId {
    /// The cell at `index` of the grid's list.
    pub fn of_index(index: usize) -> Self {
        Self(index as u64)
    }

    /// Its index in the grid's list of cells, if this platform can hold it.
    pub fn index(self) -> Option<usize> {
        usize::try_from(self.0).ok()
    }
}

impl PolicyVersion {
    /// The version published after this one.
    #[must_use]
    pub const fn next(self) -> Self {
        Self(self.0 + 1)
    }

    /// Policy lag: how many versions `older` is behind this one (0 if it is not behind).
    pub const fn lag_of(self, older: Self) -> u64 {
        self.0.saturating_sub(older.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A worker id is written as its bare number, so old files and messages read the same.
    #[test]
    fn a_worker_id_serialises_as_its_number() {
        let id = WorkerId::new(42);
        assert_eq!(serde_json::to_string(&id).expect("json"), "42");
        assert_eq!(serde_json::from_str::<WorkerId>("42").expect("json"), id);
        assert_eq!(id.to_string(), "42");
    }

    /// A job id is written as its bare number, so stored records, job configs (`init_job = 3`)
    /// and messages read the same.
    #[test]
    fn a_job_id_serialises_as_its_number() {
        let id = JobId::new(42);
        assert_eq!(serde_json::to_string(&id).expect("json"), "42");
        assert_eq!(serde_json::from_str::<JobId>("42").expect("json"), id);
        assert_eq!(id.to_string(), "42");
        #[derive(Debug, PartialEq, Serialize, Deserialize)]
        struct Train {
            init_job: Option<JobId>,
        }
        let t = Train { init_job: Some(JobId::new(3)) };
        assert_eq!(toml::to_string(&t).expect("toml"), "init_job = 3\n");
        assert_eq!(toml::from_str::<Train>("init_job = 3").expect("toml"), t);
    }

    /// A cell id is its index in the grid's list, written as the bare number.
    #[test]
    fn a_cell_id_is_its_index() {
        let c = CellId::of_index(5);
        assert_eq!((c.get(), c.index(), c.to_string()), (5, Some(5), "5".to_string()));
        assert_eq!(serde_json::to_string(&c).expect("json"), "5");
        assert_eq!(serde_json::from_str::<CellId>("5").expect("json"), c);
    }

    /// A policy version is written as its bare number (`state.json`, `policy.json`, progress),
    /// and 0 stays "none published yet".
    #[test]
    fn a_policy_version_serialises_as_its_number() {
        let v = PolicyVersion::new(7);
        assert_eq!(serde_json::to_string(&v).expect("json"), "7");
        assert_eq!(serde_json::from_str::<PolicyVersion>("7").expect("json"), v);
        assert_eq!(v.to_string(), "7");
        assert_eq!(PolicyVersion::default(), PolicyVersion::new(0));
        assert_eq!(
            (v.next().get(), v.lag_of(PolicyVersion::new(5)), v.lag_of(v.next())),
            (8, 2, 0)
        );
    }
}
