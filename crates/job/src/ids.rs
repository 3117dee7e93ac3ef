//! Typed ids that cross processes.
//!
//! Owns: [`WorkerId`], the number a learner gives a worker when it registers, as a type of its
//! own, so that it cannot be passed where a job id or a version is meant. Stored and written as
//! the bare number (`serde(transparent)`), so files and the wire format stay as they were.
//! Must not: know the wire format: the gRPC edges convert (`From<u64>` and
//! [`WorkerId::get`]).

use std::fmt;

use serde::{Deserialize, Serialize};

/// A worker, as the learner that registered it numbers it (ids are issued once per learner
/// start).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize,
)]
#[serde(transparent)]
pub struct WorkerId(u64);

impl WorkerId {
    pub const fn new(id: u64) -> Self {
        Self(id)
    }

    /// The number, for the wire, logs and metrics.
    pub const fn get(self) -> u64 {
        self.0
    }
}

impl From<u64> for WorkerId {
    fn from(id: u64) -> Self {
        Self(id)
    }
}

impl fmt::Display for WorkerId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.fmt(f)
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
}
