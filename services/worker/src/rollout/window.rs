//! The window of transition batches sent and not yet acknowledged, sized to the link.
//!
//! Owns: [`Window`], which the rollout thread takes a slot of before sending a batch and each
//! acknowledgement gives back. Each acknowledgement is also a round-trip sample (acknowledgements
//! come in the order batches were sent). The window grows by one batch for an acknowledgement
//! that came back about as fast as the fastest recent one while the sender had been waiting for
//! a slot (the link's delay binds: each batch more in flight carries a batch more per round trip,
//! up to the bandwidth-delay product), and shrinks by one for one that came back much slower
//! (batches queue at the learner, its rate limiter or the transport: more in flight would only
//! add policy lag). It lives between 2 batches (or the cap, if lower) and the cap (the
//! `--in-flight-batches` flag, which bounds what a worker's death loses); a fixed window stays at
//! the cap. Must not: do network IO or know what a batch holds.
//!
//! (Climbing the acknowledged rate instead, a step kept only if the next round's rate rose 5 %,
//! was measured on 2026-12-07 and grew too slowly across 100 ms: `docs/results/reliability.md`.)

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex};
use std::time::{Duration, Instant};

use sf_service::sync::lock;

use super::Control;

/// Round-trip samples the fastest-recent figure is taken over: long enough (minutes of
/// acknowledgements) that sustained queueing does not become the new normal at once.
const RTT_SAMPLES: usize = 1024;
/// The smallest window an adaptive one has.
const FLOOR: u32 = 2;

/// An acknowledgement about as fast as the fastest recent one: no queue on the way.
fn fast(rtt: Duration, min: Duration) -> bool {
    rtt <= min.mul_f64(1.25) + Duration::from_millis(1)
}

/// One much slower: batches queue somewhere.
fn slow(rtt: Duration, min: Duration) -> bool {
    rtt > min * 2 + Duration::from_millis(5)
}

struct State {
    cap: u32,
    adaptive: bool,
    limit: u32,
    in_flight: u32,
    /// When each batch in flight was sent, oldest first.
    sent_at: VecDeque<Instant>,
    /// The last round trips, newest last.
    rtts: VecDeque<Duration>,
    /// The sender waited for a slot since the window last changed.
    waited: bool,
}

impl State {
    /// A batch sent at `now`.
    fn send(&mut self, now: Instant) {
        self.in_flight += 1;
        self.sent_at.push_back(now);
    }

    /// The oldest batch in flight acknowledged at `now`.
    fn ack(&mut self, now: Instant) {
        self.in_flight = self.in_flight.saturating_sub(1);
        let Some(sent) = self.sent_at.pop_front() else { return };
        let rtt = now.saturating_duration_since(sent);
        if self.rtts.len() == RTT_SAMPLES {
            self.rtts.pop_front();
        }
        self.rtts.push_back(rtt);
        let min = self.rtts.iter().min().copied().unwrap_or(rtt);
        if !self.adaptive {
            return;
        }
        if fast(rtt, min) && self.waited && self.limit < self.cap {
            self.limit += 1;
            self.waited = false;
        } else if slow(rtt, min) && self.limit > FLOOR.min(self.cap) {
            self.limit -= 1;
            self.waited = false;
        }
    }
}

/// Batches the rollout thread may have in flight (see the module header).
pub struct Window {
    state: Mutex<State>,
    changed: Condvar,
}

impl Window {
    /// A window capped at `cap` batches; `adaptive` starts it at 2 and sizes it to the link,
    /// otherwise it stays at `cap`.
    pub fn new(cap: u32, adaptive: bool) -> Self {
        let cap = cap.max(1);
        Self {
            state: Mutex::new(State {
                cap,
                adaptive,
                limit: if adaptive { FLOOR.min(cap) } else { cap },
                in_flight: 0,
                sent_at: VecDeque::new(),
                rtts: VecDeque::with_capacity(RTT_SAMPLES),
                waited: false,
            }),
            changed: Condvar::new(),
        }
    }

    /// The window's size now, in batches.
    pub fn limit(&self) -> u32 {
        lock(&self.state).limit
    }

    /// One acknowledgement arrived (for the oldest batch in flight).
    pub fn grant(&self) {
        lock(&self.state).ack(Instant::now());
        self.changed.notify_all();
    }

    /// Waits for a slot and marks a batch sent; `false` if `stop` turned true first.
    pub(super) fn take(&self, control: &Mutex<Control>) -> bool {
        let mut s = lock(&self.state);
        loop {
            if s.in_flight < s.limit {
                s.send(Instant::now());
                return true;
            }
            s.waited = true;
            if lock(control).stop {
                return false;
            }
            s = self
                .changed
                .wait_timeout(s, Duration::from_millis(100))
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn control() -> Mutex<Control> {
        Mutex::new(Control { warmup: false, policy: None, stop: false })
    }

    /// A link with a propagation round trip of `rtt` and a bottleneck (the learner, or the
    /// link's bandwidth) that takes `service` per batch, fed by a sender that always has a batch
    /// ready: each acknowledgement at `max(sent + rtt, previous ack + service)`, a batch sent as
    /// soon as the window has a slot. Returns the window after `acks` acknowledgements and the
    /// acknowledged batches per second over the last quarter.
    fn run(w: &Window, rtt: Duration, service: Duration, acks: usize) -> (u32, f64) {
        let t0 = Instant::now();
        let (mut now, mut last_ack) = (t0, t0);
        let mut flight: VecDeque<Instant> = VecDeque::new();
        let mut times = Vec::with_capacity(acks);
        for _ in 0..acks {
            loop {
                let mut s = lock(&w.state);
                if s.in_flight >= s.limit {
                    break;
                }
                s.send(now);
                flight.push_back(now);
            }
            lock(&w.state).waited = true;
            let sent = flight.pop_front().expect("a batch in flight");
            now = (sent + rtt).max(last_ack + service);
            last_ack = now;
            lock(&w.state).ack(now);
            times.push(now);
        }
        let q = acks / 4;
        let span = times[acks - 1].duration_since(times[acks - 1 - q]).as_secs_f64();
        (w.limit(), q as f64 / span)
    }

    #[test]
    fn a_delay_bound_link_grows_the_window_to_its_cap() {
        let w = Window::new(16, true);
        assert_eq!(w.limit(), 2);
        // 50 ms round trips, a bottleneck at 1,000 batches/s: 16 in flight carry 320/s.
        let (limit, rate) = run(&w, Duration::from_millis(50), Duration::from_millis(1), 4000);
        assert_eq!(limit, 16);
        assert!(rate > 300.0, "{rate} batches/s");
    }

    #[test]
    fn where_the_bottleneck_binds_the_window_stays_small() {
        let w = Window::new(16, true);
        // 1 ms round trips, a bottleneck at 100 batches/s: 2 in flight already carry it.
        let (limit, rate) = run(&w, Duration::from_millis(1), Duration::from_millis(10), 4000);
        assert!(limit <= 3, "window {limit}");
        assert!(rate > 95.0, "{rate} batches/s");
    }

    #[test]
    fn a_fixed_window_stays_at_its_cap_and_blocks_there() {
        let w = Window::new(3, false);
        let (limit, _) = run(&w, Duration::from_millis(1), Duration::from_micros(100), 500);
        assert_eq!(limit, 3);
        let (w, c) = (Window::new(3, false), control());
        for _ in 0..3 {
            assert!(w.take(&c));
        }
        c.lock().expect("control").stop = true;
        assert!(!w.take(&c), "a full window gives no slot; stop ends the wait");
    }

    #[test]
    fn without_waiting_for_slots_the_window_does_not_grow() {
        let (w, c) = (Window::new(16, true), control());
        for _ in 0..200 {
            assert!(w.take(&c));
            w.grant();
        }
        assert_eq!(w.limit(), 2, "one batch at a time never needs a wider window");
    }
}
