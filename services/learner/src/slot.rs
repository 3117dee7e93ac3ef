//! The learner's running jobs: several training jobs side by side, or one evaluation job alone.
//!
//! Owns: [`Slots`], which hold the [`Running`] jobs the handlers, the scheduler and shutdown
//! look at, and the rule for what may start next ([`Slots::admits`]): training jobs up to the
//! limit (each needs a worker of its own, so no more than there are live workers), an
//! evaluation only when nothing runs (its cells go to idle workers, and a worker in a training
//! session is never idle), and nothing beside an evaluation. Must not: start or stop jobs (the
//! scheduler fills and clears the slots, the job itself stops on request) or know how either
//! kind runs. Also owns [`Outcome`], how a running job of either kind ended.

use std::collections::BTreeMap;
use std::sync::{Arc, RwLock};

use prometheus_client::metrics::gauge::Gauge;
use sf_job::JobId;
use sf_service::sync::{read, write};

use crate::eval::EvalJob;
use crate::job::{ActiveJob, StopReason};

/// How a running job ended (a training job's trainer, or an evaluation's last cell).
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    Succeeded,
    Cancelled,
    /// Learner shutdown: checkpoint written, the job stays RUNNING and resumes on next start.
    Shutdown,
    /// The disk refused a write (`storage::is_storage_fault`): the job stays RUNNING at its last
    /// good checkpoint and resumes from it when the disk takes writes again.
    Paused(String),
    Failed(String),
}

/// What occupies a slot.
#[derive(Clone)]
pub enum Running {
    Train(Arc<ActiveJob>),
    Eval(Arc<EvalJob>),
}

impl Running {
    /// Asks the job to stop (it ends with the first reason asked for a training job, the last
    /// for an evaluation).
    pub fn request_stop(&self, why: StopReason) {
        match self {
            Running::Train(j) => j.request_stop(why),
            Running::Eval(e) => e.request_stop(why),
        }
    }

    pub fn progress(&self) -> sf_job::Progress {
        match self {
            Running::Train(j) => j.progress(),
            Running::Eval(e) => e.progress(),
        }
    }
}

/// What the scheduler wants to start.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Train,
    Eval,
}

/// The running jobs by id.
pub struct Slots {
    jobs: RwLock<BTreeMap<JobId, Running>>,
    /// Training jobs that may run at once.
    limit: usize,
    gauge: Gauge,
}

impl Slots {
    pub fn new(limit: usize, gauge: Gauge) -> Self {
        Self { jobs: RwLock::new(BTreeMap::new()), limit: limit.max(1), gauge }
    }

    /// The running job `id`.
    pub fn get(&self, id: JobId) -> Option<Running> {
        read(&self.jobs).get(&id).cloned()
    }

    /// Every running job.
    pub fn all(&self) -> Vec<Running> {
        read(&self.jobs).values().cloned().collect()
    }

    /// The running training job `id`.
    pub fn train(&self, id: JobId) -> Option<Arc<ActiveJob>> {
        match read(&self.jobs).get(&id) {
            Some(Running::Train(j)) => Some(Arc::clone(j)),
            _ => None,
        }
    }

    /// Every running training job, by id.
    pub fn trains(&self) -> Vec<Arc<ActiveJob>> {
        read(&self.jobs)
            .values()
            .filter_map(|r| match r {
                Running::Train(j) => Some(Arc::clone(j)),
                Running::Eval(_) => None,
            })
            .collect()
    }

    /// The running evaluation job.
    pub fn eval(&self) -> Option<Arc<EvalJob>> {
        read(&self.jobs).values().find_map(|r| match r {
            Running::Eval(e) => Some(Arc::clone(e)),
            Running::Train(_) => None,
        })
    }

    pub fn is_empty(&self) -> bool {
        read(&self.jobs).is_empty()
    }

    /// Whether a job of `kind` may start now, with `workers` live workers.
    pub fn admits(&self, kind: Kind, workers: usize) -> bool {
        let jobs = read(&self.jobs);
        if jobs.values().any(|r| matches!(r, Running::Eval(_))) {
            return false;
        }
        match kind {
            Kind::Eval => jobs.is_empty(),
            Kind::Train => jobs.len() < self.limit.min(workers.max(1)),
        }
    }

    /// Live progress of job `id` if it is running.
    pub fn progress(&self, id: JobId) -> Option<sf_job::Progress> {
        read(&self.jobs).get(&id).map(Running::progress)
    }

    /// Puts `job` in a slot (the scheduler starts a job only when [`Slots::admits`] it).
    pub fn fill(&self, id: JobId, job: Running) {
        let mut jobs = write(&self.jobs);
        jobs.insert(id, job);
        self.gauge.set(jobs.len() as i64);
    }

    /// Frees job `id`'s slot; true if it held one.
    pub fn clear(&self, id: JobId) -> bool {
        let mut jobs = write(&self.jobs);
        let held = jobs.remove(&id).is_some();
        self.gauge.set(jobs.len() as i64);
        held
    }
}
