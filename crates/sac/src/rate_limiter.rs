//! A Reverb-style sample-to-insert rate limiter: updates per inserted environment step.
//!
//! Owns: [`RateLimiterConfig`] (validated so that no setting can deadlock) and
//! [`RateLimiter`] (counters behind a mutex with condition variables; blocking waits with
//! deadlines; `close` wakes every waiter). Must not: know what is inserted or sampled.
//!
//! With `spi` = samples per insert, `m` = minimum inserts before sampling and `e` = error
//! buffer, `diff = inserts * spi - samples` must stay within `[m * spi - e, m * spi + e]` once
//! `m` inserts have happened: sampling waits when it would go below, inserting waits when it
//! would go above. Before `m` inserts, inserting is always allowed and sampling never is.

use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RateLimiterConfig {
    /// Updates per inserted environment step (the replay ratio).
    pub samples_per_insert: f64,
    /// Inserts before the first sample (warm-up).
    pub min_size_to_sample: u64,
    /// Slack around the target ratio, in samples.
    pub error_buffer: f64,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RateLimitError {
    #[error("rate limiter field `{field}`: {reason}")]
    Invalid { field: &'static str, reason: String },
    #[error("timed out waiting to {0}")]
    Timeout(&'static str),
    #[error("rate limiter closed")]
    Closed,
}

impl RateLimiterConfig {
    /// Refuses settings that could deadlock or never sample.
    pub fn validate(&self, capacity: u64) -> Result<(), RateLimitError> {
        let bad = |field, reason: String| Err(RateLimitError::Invalid { field, reason });
        if !(self.samples_per_insert.is_finite() && self.samples_per_insert > 0.0) {
            return bad(
                "samples_per_insert",
                format!("{} must be a positive number", self.samples_per_insert),
            );
        }
        if self.min_size_to_sample < 1 {
            return bad("min_size_to_sample", "must be at least 1".into());
        }
        if self.min_size_to_sample > capacity {
            return bad(
                "min_size_to_sample",
                format!(
                    "{} exceeds the replay capacity {capacity}: sampling could never start",
                    self.min_size_to_sample
                ),
            );
        }
        let need = self.samples_per_insert.max(1.0);
        if !(self.error_buffer.is_finite() && self.error_buffer >= need) {
            return bad("error_buffer", format!("{} must be at least max(1, samples_per_insert) = {need}, or inserts and samples can block each other forever", self.error_buffer));
        }
        Ok(())
    }
}

#[derive(Debug, Default)]
struct Counts {
    inserts: u64,
    samples: u64,
    closed: bool,
}

/// Thread-safe limiter shared by the inserting side (workers) and the sampling side (trainer).
#[derive(Debug)]
pub struct RateLimiter {
    cfg: RateLimiterConfig,
    counts: Mutex<Counts>,
    changed: Condvar,
}

impl RateLimiter {
    pub fn new(cfg: RateLimiterConfig, capacity: u64) -> Result<Self, RateLimitError> {
        cfg.validate(capacity)?;
        Ok(Self { cfg, counts: Mutex::new(Counts::default()), changed: Condvar::new() })
    }

    /// Restores counters (after a checkpoint); waiters are woken.
    pub fn restore(&self, inserts: u64, samples: u64) {
        let mut c = self.lock();
        c.inserts = inserts;
        c.samples = samples;
        self.changed.notify_all();
    }

    fn lock(&self) -> MutexGuard<'_, Counts> {
        self.counts.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn bounds(&self) -> (f64, f64) {
        let centre = self.cfg.min_size_to_sample as f64 * self.cfg.samples_per_insert;
        (centre - self.cfg.error_buffer, centre + self.cfg.error_buffer)
    }

    fn diff(&self, c: &Counts) -> f64 {
        c.inserts as f64 * self.cfg.samples_per_insert - c.samples as f64
    }

    /// Whether `n` inserts may happen now.
    pub fn can_insert(&self, n: u64) -> bool {
        let c = self.lock();
        self.insert_ok(&c, n)
    }

    fn insert_ok(&self, c: &Counts, n: u64) -> bool {
        c.inserts + n <= self.cfg.min_size_to_sample
            || self.diff(c) + n as f64 * self.cfg.samples_per_insert <= self.bounds().1
    }

    /// Whether one sample (update) may happen now.
    pub fn can_sample(&self) -> bool {
        let c = self.lock();
        self.sample_ok(&c)
    }

    fn sample_ok(&self, c: &Counts) -> bool {
        c.inserts >= self.cfg.min_size_to_sample && self.diff(c) - 1.0 >= self.bounds().0
    }

    fn wait(
        &self,
        what: &'static str,
        timeout: Duration,
        ok: impl Fn(&Counts) -> bool,
        apply: impl FnOnce(&mut Counts),
    ) -> Result<(), RateLimitError> {
        let deadline = Instant::now() + timeout;
        let mut c = self.lock();
        loop {
            if c.closed {
                return Err(RateLimitError::Closed);
            }
            if ok(&c) {
                apply(&mut c);
                self.changed.notify_all();
                return Ok(());
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(RateLimitError::Timeout(what));
            }
            c = self.changed.wait_timeout(c, deadline - now).unwrap_or_else(|p| p.into_inner()).0;
        }
    }

    /// Blocks until `n` inserts are allowed, then records them.
    pub fn insert(&self, n: u64, timeout: Duration) -> Result<(), RateLimitError> {
        self.wait("insert", timeout, |c| self.insert_ok(c, n), |c| c.inserts += n)
    }

    /// Blocks until one sample is allowed, then records it.
    pub fn sample(&self, timeout: Duration) -> Result<(), RateLimitError> {
        self.wait("sample", timeout, |c| self.sample_ok(c), |c| c.samples += 1)
    }

    /// Wakes every waiter with [`RateLimitError::Closed`].
    pub fn close(&self) {
        self.lock().closed = true;
        self.changed.notify_all();
    }

    /// (inserts, samples) so far.
    pub fn counts(&self) -> (u64, u64) {
        let c = self.lock();
        (c.inserts, c.samples)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    fn cfg(spi: f64, min: u64, e: f64) -> RateLimiterConfig {
        RateLimiterConfig { samples_per_insert: spi, min_size_to_sample: min, error_buffer: e }
    }

    #[test]
    fn refuses_settings_that_deadlock() {
        assert!(matches!(
            cfg(4.0, 10, 2.0).validate(100),
            Err(RateLimitError::Invalid { field: "error_buffer", .. })
        ));
        assert!(matches!(
            cfg(1.0, 200, 2.0).validate(100),
            Err(RateLimitError::Invalid { field: "min_size_to_sample", .. })
        ));
        assert!(matches!(
            cfg(0.0, 10, 2.0).validate(100),
            Err(RateLimitError::Invalid { field: "samples_per_insert", .. })
        ));
        assert!(cfg(1.0, 10, 1.0).validate(100).is_ok());
    }

    #[test]
    fn blocks_sampling_before_min_size_and_inserting_when_ahead() {
        let t = Duration::from_millis(20);
        let r = RateLimiter::new(cfg(1.0, 5, 2.0), 100).expect("valid");
        assert_eq!(r.sample(t), Err(RateLimitError::Timeout("sample")));
        for _ in 0..5 {
            r.insert(1, t).expect("warm-up inserts are free");
        }
        // diff = 5, bounds [3, 7]: two more inserts fit, the third waits for a sample.
        r.insert(2, t).expect("within the error buffer");
        assert_eq!(r.insert(1, t), Err(RateLimitError::Timeout("insert")));
        r.sample(t).expect("sampling allowed");
        r.insert(1, t).expect("a sample made room");
        // Sampling drains down to the lower bound, then waits.
        for _ in 0..4 {
            r.sample(t).expect("ahead of the ratio");
        }
        assert_eq!(r.sample(t), Err(RateLimitError::Timeout("sample")));
        assert_eq!(r.counts(), (8, 5));
    }

    #[test]
    fn a_blocked_sampler_is_released_by_an_insert_and_close_wakes_all() {
        let r = Arc::new(RateLimiter::new(cfg(2.0, 1, 2.0), 10).expect("valid"));
        let r2 = Arc::clone(&r);
        let waiter = std::thread::spawn(move || r2.sample(Duration::from_secs(10)));
        std::thread::sleep(Duration::from_millis(30));
        assert!(!waiter.is_finished(), "sampler must wait for the first insert");
        r.insert(1, Duration::from_secs(1)).expect("insert");
        assert_eq!(waiter.join().expect("join"), Ok(()));
        let r3 = Arc::clone(&r);
        let blocked = std::thread::spawn(move || loop {
            if let Err(e) = r3.sample(Duration::from_secs(10)) {
                return e;
            }
        });
        std::thread::sleep(Duration::from_millis(30));
        r.close();
        assert_eq!(blocked.join().expect("join"), RateLimitError::Closed);
    }
}
