//! The learner's one running slot: a training job or an evaluation job, never both.
//!
//! Owns: [`Slot`], which holds the [`Running`] job the handlers, the scheduler and shutdown
//! look at. Must not: start or stop jobs (the scheduler fills and clears it, the job itself
//! stops on request) or know how either kind runs.

use std::sync::{Arc, RwLock};

use sf_service::sync::{read, write};

use crate::eval::EvalJob;
use crate::job::ActiveJob;

/// What occupies the slot.
#[derive(Clone)]
pub enum Running {
    Train(Arc<ActiveJob>),
    Eval(Arc<EvalJob>),
}

/// The running job, if any.
#[derive(Default)]
pub struct Slot(RwLock<Option<Running>>);

impl Slot {
    /// The running training job.
    pub fn train(&self) -> Option<Arc<ActiveJob>> {
        match &*read(&self.0) {
            Some(Running::Train(j)) => Some(Arc::clone(j)),
            _ => None,
        }
    }

    /// The running evaluation job.
    pub fn eval(&self) -> Option<Arc<EvalJob>> {
        match &*read(&self.0) {
            Some(Running::Eval(e)) => Some(Arc::clone(e)),
            _ => None,
        }
    }

    pub fn busy(&self) -> bool {
        read(&self.0).is_some()
    }

    /// Live progress of job `id` if it is the running one.
    pub fn progress(&self, id: u64) -> Option<sf_job::Progress> {
        match &*read(&self.0) {
            Some(Running::Train(j)) if j.id == id => Some(j.progress()),
            Some(Running::Eval(e)) if e.id == id => Some(e.progress()),
            _ => None,
        }
    }

    /// Puts `job` in the slot (the scheduler starts a job only when it is empty).
    pub fn fill(&self, job: Running) {
        *write(&self.0) = Some(job);
    }

    pub fn clear(&self) {
        *write(&self.0) = None;
    }
}
