//! The worker registry: who is registered, when each was last heard from, and forgetting the
//! silent ones.
//!
//! Owns: [`Workers`] (ids issued once per learner start, last-seen times, the `workers`
//! gauge). Every call from a worker (heartbeat, assignment, transitions, evaluation results)
//! touches it; the scheduler prunes it once a tick so the gauge falls even when no worker
//! calls. Must not: know about jobs or leases (the evaluation job asks [`Workers::live`] whom
//! to keep leases for).

use std::collections::{BTreeSet, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use prometheus_client::metrics::gauge::Gauge;
use sf_service::sync::lock;

use crate::error::LearnerError;

struct WorkerInfo {
    name: String,
    last_seen: Instant,
    /// It runs evaluation cells with the IDM driver in the ego's seat.
    runs_idm_ego: bool,
}

/// Registered workers, forgotten after `timeout` without a call.
pub struct Workers {
    map: Mutex<HashMap<u64, WorkerInfo>>,
    next: AtomicU64,
    timeout: Duration,
    gauge: Gauge,
}

impl Workers {
    /// Ids start at `first_id` (distinct across learner starts, so a worker registered with an
    /// earlier learner is not mistaken for a new one).
    pub fn new(first_id: u64, timeout: Duration, gauge: Gauge) -> Self {
        Self {
            map: Mutex::new(HashMap::new()),
            next: AtomicU64::new(first_id.max(1)),
            timeout,
            gauge,
        }
    }

    pub fn register(&self, name: &str, runs_idm_ego: bool) -> u64 {
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let mut w = lock(&self.map);
        w.insert(
            id,
            WorkerInfo { name: name.to_string(), last_seen: Instant::now(), runs_idm_ego },
        );
        self.gauge.set(w.len() as i64);
        tracing::info!(worker_id = id, name, "worker registered");
        id
    }

    /// Whether worker `id` registered as running IDM-ego evaluation cells.
    pub fn runs_idm_ego(&self, id: u64) -> bool {
        lock(&self.map).get(&id).is_some_and(|w| w.runs_idm_ego)
    }

    /// Records a call from worker `id`; refused when it is not (or no longer) registered.
    pub fn touch(&self, id: u64) -> Result<(), LearnerError> {
        let mut w = lock(&self.map);
        self.prune_locked(&mut w, Some(id));
        match w.get_mut(&id) {
            Some(info) => {
                info.last_seen = Instant::now();
                Ok(())
            }
            None => Err(LearnerError::WorkerNotRegistered { worker_id: id }),
        }
    }

    /// Workers not yet forgotten for missing heartbeats.
    pub fn live(&self) -> BTreeSet<u64> {
        lock(&self.map).keys().copied().collect()
    }

    /// Forgets workers silent for longer than the timeout and updates the gauge.
    pub fn prune(&self) {
        self.prune_locked(&mut lock(&self.map), None);
    }

    fn prune_locked(&self, w: &mut HashMap<u64, WorkerInfo>, keep: Option<u64>) {
        let before = w.len();
        w.retain(|wid, info| {
            let stay = Some(*wid) == keep || info.last_seen.elapsed() < self.timeout;
            if !stay {
                tracing::info!(worker_id = *wid, name = %info.name, "worker timed out");
            }
            stay
        });
        if w.len() != before {
            self.gauge.set(w.len() as i64);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn silent_workers_are_forgotten_and_refused_while_callers_stay() {
        let gauge = Gauge::default();
        let w = Workers::new(0, Duration::from_millis(50), gauge.clone());
        let (a, b) = (w.register("a", true), w.register("b", false));
        assert!(a >= 1 && b == a + 1, "ids start at 1 and are never reused: {a} {b}");
        assert!(w.runs_idm_ego(a) && !w.runs_idm_ego(b), "what each worker registered with");
        assert_eq!(gauge.get(), 2);
        std::thread::sleep(Duration::from_millis(80));
        // `a` calls after the timeout: it stays (its own call keeps it), `b` goes.
        w.touch(a).expect("a calls");
        assert_eq!(w.live(), BTreeSet::from([a]));
        assert_eq!(gauge.get(), 1);
        let e = w.touch(b).expect_err("b was forgotten");
        assert!(e.to_string().contains(&format!("worker {b} is not registered")), "{e}");
        std::thread::sleep(Duration::from_millis(80));
        w.prune();
        assert!(w.live().is_empty());
        assert_eq!(gauge.get(), 0, "the gauge falls with no worker calling");
    }
}
