//! The worker registry: who is registered, when each was last heard from, and forgetting the
//! silent ones.
//!
//! Owns: [`Workers`] (ids issued once per learner start, last-seen times, the `workers`
//! gauge, the training job each works for) and the sharing of workers between training jobs
//! running side by side ([`Workers::assign`] gives a worker the job with the fewest workers,
//! [`Workers::rebalance`] moves one off a job holding more than its share). Every call from a
//! worker (heartbeat, assignment, transitions, evaluation results) touches it; the scheduler
//! prunes it once a tick so the gauge falls even when no worker calls. Must not: know what a
//! job is beyond its id, or leases (the evaluation job asks [`Workers::live`] whom to keep
//! leases for).

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use prometheus_client::metrics::gauge::Gauge;
use sf_job::eval::ScriptedSeats;
use sf_job::{JobId, WorkerId};
use sf_service::sync::lock;

use crate::error::LearnerError;

struct WorkerInfo {
    name: String,
    last_seen: Instant,
    /// The scripted drivers it seats in evaluation cells.
    seats: ScriptedSeats,
    /// The training job it was last assigned, until it is moved or asks again.
    job: Option<JobId>,
}

/// Registered workers, forgotten after `timeout` without a call.
pub struct Workers {
    map: Mutex<HashMap<WorkerId, WorkerInfo>>,
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

    pub fn register(&self, name: &str, seats: ScriptedSeats) -> WorkerId {
        let id = WorkerId::new(self.next.fetch_add(1, Ordering::Relaxed));
        let mut w = lock(&self.map);
        w.insert(
            id,
            WorkerInfo { name: name.to_string(), last_seen: Instant::now(), seats, job: None },
        );
        self.gauge.set(w.len() as i64);
        tracing::info!(worker_id = id.get(), name, "worker registered");
        id
    }

    /// The scripted egos worker `id` registered as seating (none if it is unknown).
    pub fn seats(&self, id: WorkerId) -> ScriptedSeats {
        lock(&self.map).get(&id).map(|w| w.seats).unwrap_or_default()
    }

    /// Records a call from worker `id`; refused when it is not (or no longer) registered.
    pub fn touch(&self, id: WorkerId) -> Result<(), LearnerError> {
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
    pub fn live(&self) -> BTreeSet<WorkerId> {
        lock(&self.map).keys().copied().collect()
    }

    /// Gives worker `id` the job among `jobs` (the running training jobs that take workers)
    /// with the fewest other live workers, the lowest id among equals; `None` (and no job
    /// recorded) when there is none.
    pub fn assign(&self, id: WorkerId, jobs: &[JobId]) -> Option<JobId> {
        let mut w = lock(&self.map);
        let loads = loads(&w, jobs, Some(id));
        let pick = least_loaded(&loads);
        if let Some(info) = w.get_mut(&id) {
            info.job = pick;
        }
        pick
    }

    /// Whether worker `id`, sending for job `job`, should move to another of `jobs` to even out
    /// the workers per job: when `job` holds more than one worker above the least served job.
    /// If so the worker is recorded on the job it should take at once (so that its fellows on
    /// `job` stay) and that job is returned.
    pub fn rebalance(&self, id: WorkerId, job: JobId, jobs: &[JobId]) -> Option<JobId> {
        let mut w = lock(&self.map);
        let info = w.get_mut(&id)?;
        if info.job != Some(job) {
            // An older session's batch (or one from before a restart): recorded, not moved.
            info.job = Some(job);
        }
        let loads = loads(&w, jobs, None);
        let to = least_loaded(&loads)?;
        let here = loads.get(&job).copied().unwrap_or(0);
        if to == job || here <= loads[&to] + 1 {
            return None;
        }
        // Counted on the job it is to take, so that its fellows on `job` stay.
        if let Some(info) = w.get_mut(&id) {
            info.job = Some(to);
        }
        tracing::info!(
            worker_id = id.get(),
            from = job.get(),
            to = to.get(),
            "worker moves to even out the running jobs"
        );
        Some(to)
    }

    /// Live workers per job of `jobs`.
    pub fn per_job(&self, jobs: &[JobId]) -> BTreeMap<JobId, usize> {
        loads(&lock(&self.map), jobs, None)
    }

    /// Forgets workers silent for longer than the timeout and updates the gauge.
    pub fn prune(&self) {
        self.prune_locked(&mut lock(&self.map), None);
    }

    fn prune_locked(&self, w: &mut HashMap<WorkerId, WorkerInfo>, keep: Option<WorkerId>) {
        let before = w.len();
        w.retain(|wid, info| {
            let stay = Some(*wid) == keep || info.last_seen.elapsed() < self.timeout;
            if !stay {
                tracing::info!(worker_id = wid.get(), name = %info.name, "worker timed out");
            }
            stay
        });
        if w.len() != before {
            self.gauge.set(w.len() as i64);
        }
    }
}

/// Workers per job of `jobs` (every one listed, zero included), `except` not counted.
fn loads(
    w: &HashMap<WorkerId, WorkerInfo>,
    jobs: &[JobId],
    except: Option<WorkerId>,
) -> BTreeMap<JobId, usize> {
    let mut n: BTreeMap<JobId, usize> = jobs.iter().map(|&j| (j, 0)).collect();
    for job in w.iter().filter(|(wid, _)| Some(**wid) != except).filter_map(|(_, i)| i.job) {
        if let Some(c) = n.get_mut(&job) {
            *c += 1;
        }
    }
    n
}

/// The job with the fewest workers, the lowest id among equals.
fn least_loaded(loads: &BTreeMap<JobId, usize>) -> Option<JobId> {
    loads.iter().min_by_key(|(&j, &n)| (n, j)).map(|(&j, _)| j)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn silent_workers_are_forgotten_and_refused_while_callers_stay() {
        let gauge = Gauge::default();
        let w = Workers::new(0, Duration::from_millis(50), gauge.clone());
        let idm_only = ScriptedSeats { idm: true, mobil: false };
        let (a, b) = (w.register("a", idm_only), w.register("b", ScriptedSeats::default()));
        assert!(
            a.get() >= 1 && b.get() == a.get() + 1,
            "ids start at 1 and are never reused: {a} {b}"
        );
        assert_eq!((w.seats(a), w.seats(b)), (idm_only, ScriptedSeats::default()), "as registered");
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

    #[test]
    fn workers_spread_over_running_jobs_and_move_when_a_job_starts_or_ends() {
        let w = Workers::new(1, Duration::from_secs(60), Gauge::default());
        let ids: Vec<WorkerId> =
            (0..3).map(|k| w.register(&format!("w{k}"), ScriptedSeats::default())).collect();
        let (j10, j11) = (JobId::new(10), JobId::new(11));
        // One job: everyone on it.
        for &id in &ids {
            assert_eq!(w.assign(id, &[j10]), Some(j10));
        }
        assert_eq!(w.per_job(&[j10]), BTreeMap::from([(j10, 3)]));
        // A second job starts: the first sender moves, the next ones stay (3 vs 0 -> 2 vs 1).
        assert_eq!(w.rebalance(ids[0], j10, &[j10, j11]), Some(j11), "3 on 10, 0 on 11");
        assert_eq!(w.rebalance(ids[1], j10, &[j10, j11]), None, "2 on 10, 1 moving to 11");
        assert_eq!(w.rebalance(ids[2], j10, &[j10, j11]), None);
        assert_eq!(w.assign(ids[0], &[j10, j11]), Some(j11), "the mover takes the empty job");
        assert_eq!(w.per_job(&[j10, j11]), BTreeMap::from([(j10, 2), (j11, 1)]));
        // Job 10 ends: its workers ask again and both land on 11.
        assert_eq!(w.assign(ids[1], &[j11]), Some(j11));
        assert_eq!(w.assign(ids[2], &[j11]), Some(j11));
        assert_eq!(w.per_job(&[j11]), BTreeMap::from([(j11, 3)]));
        // Nothing runs: nothing is assigned.
        assert_eq!(w.assign(ids[0], &[]), None);
        assert_eq!(w.per_job(&[j11]), BTreeMap::from([(j11, 2)]));
        // A batch for a job the worker was not recorded on (a session from before): recorded.
        assert_eq!(w.rebalance(ids[0], j11, &[j11]), None);
        assert_eq!(w.per_job(&[j11]), BTreeMap::from([(j11, 3)]));
    }
}
