//! Bounded exponential backoff with jitter for reconnecting clients.

use std::time::Duration;

#[derive(Clone, Debug)]
pub struct Backoff {
    initial: Duration,
    max: Duration,
    current: Duration,
    state: u64,
}

impl Backoff {
    pub fn new(initial: Duration, max: Duration) -> Self {
        Self {
            initial,
            max,
            current: initial,
            state: 0x9e37_79b9_7f4a_7c15 ^ std::process::id() as u64,
        }
    }

    /// The next delay: doubles up to `max`, with up to 25 % jitter below it.
    pub fn next_delay(&mut self) -> Duration {
        self.state ^= self.state << 13;
        self.state ^= self.state >> 7;
        self.state ^= self.state << 17;
        let jitter = (self.state % 1000) as f64 / 4000.0;
        let d = self.current.mul_f64(1.0 - jitter);
        self.current = (self.current * 2).min(self.max);
        d
    }

    pub fn reset(&mut self) {
        self.current = self.initial;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn delays_grow_and_stay_bounded() {
        let mut b = Backoff::new(Duration::from_millis(100), Duration::from_secs(2));
        let ds: Vec<Duration> = (0..10).map(|_| b.next_delay()).collect();
        assert!(ds[0] <= Duration::from_millis(100) && ds[0] >= Duration::from_millis(75));
        assert!(ds.iter().all(|d| *d <= Duration::from_secs(2)));
        assert!(ds[9] >= Duration::from_millis(1500));
        b.reset();
        assert!(b.next_delay() <= Duration::from_millis(100));
    }
}
