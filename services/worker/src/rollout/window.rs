//! The window of transition batches sent and not yet acknowledged, sized to the link.
//!
//! Owns: [`Window`], which the rollout thread takes a slot of before sending a batch and each
//! acknowledgement gives back. The window is twice the link's bandwidth-delay product, measured
//! as BBR measures it: each acknowledgement (they come in the order batches were sent) gives a
//! round-trip sample and a delivery-rate sample (batches acknowledged since that batch was sent,
//! over the time since the acknowledgement that preceded its sending); the window is
//! `2 x (the fastest delivery rate of the last ~10 round trips) x (the shortest recent round
//! trip)`, the shortest round trip measured afresh with one batch in flight when it has
//! not been seen for 10 s (BBR's ProbeRTT: otherwise a queue the window built would become the
//! round trip and grow the window). While the window binds, each round trip's rate sample is the window over the
//! round trip, so the window doubles per round trip until something else binds (the learner, its
//! rate limiter, the link's bandwidth or the worker's own simulation); there the rate stops rising
//! and the window rests at twice what that rate needs. One slow round trip changes nothing (the
//! rate is a maximum, the round trip a minimum), and a window that shrank because the learner
//! slowed for a while grows back in a few round trips. It lives between 2 batches (or the cap, if
//! lower) and the cap (the `--in-flight-batches` flag, which bounds what a worker's death loses);
//! a fixed window stays at the cap. Must not: do network IO or know what a batch holds.
//!
//! (Measured on 2026-12-07 and replaced, `docs/results/reliability.md`: a rule that grew the
//! window by one for a round trip within 1.25x of the fastest and shrank it for one over 2x stalled
//! at 2-4 batches in a third of the delayed rows; a rule that climbed the acknowledged rate, a step
//! kept only if the next round's rate rose 5 %, grew too slowly across 100 ms.)

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex};
use std::time::{Duration, Instant};

use sf_service::sync::lock;

use super::Control;

/// The smallest window an adaptive one has.
const FLOOR: u32 = 2;
/// The window over the bandwidth-delay product: room for the rate to double per round trip while
/// the window binds, and for a round trip's jitter once it does not.
const GAIN: f64 = 2.0;
/// Round trips the delivery-rate maximum is taken over (BBR's ten)...
const RATE_ROUND_TRIPS: u32 = 10;
/// ... but never less than this, so a sub-millisecond loopback does not follow every burst.
const RATE_HORIZON_MIN: Duration = Duration::from_secs(1);
/// How long the shortest round trip stands without being seen again. Then the window drops to
/// one batch for one round trip (BBR's ProbeRTT), so a queue the window itself built cannot
/// become the new shortest round trip and grow the window further, and a link whose delay rose
/// is measured again.
const MIN_RTT_EXPIRY: Duration = Duration::from_secs(10);

/// A batch in flight: when it was sent, its place in the sending order, and the delivery count
/// and time then.
struct Sent {
    at: Instant,
    index: u64,
    delivered: u64,
    delivered_at: Instant,
}

struct State {
    cap: u32,
    adaptive: bool,
    limit: u32,
    in_flight: u32,
    /// Batches sent so far.
    sent_count: u64,
    /// Each batch in flight, oldest first.
    sent: VecDeque<Sent>,
    /// Batches acknowledged so far, and when the last was (or when sending resumed after the
    /// window emptied, so idle time is not counted as the link's).
    delivered: u64,
    delivered_at: Instant,
    /// The shortest round trip seen since it was last measured afresh, and when it was seen.
    min_rtt: Option<(Duration, Instant)>,
    /// While the window is at one batch to measure the round trip afresh: the first batch sent
    /// since (with none of ours ahead of it), whose acknowledgement gives the new shortest
    /// round trip.
    probing_from: Option<u64>,
    /// Delivery-rate samples (when, batches per second) that can still be the maximum: newest
    /// last, rates falling from front to back.
    rates: VecDeque<(Instant, f64)>,
}

impl State {
    fn new(cap: u32, adaptive: bool, now: Instant) -> Self {
        let cap = cap.max(1);
        Self {
            cap,
            adaptive,
            limit: if adaptive { FLOOR.min(cap) } else { cap },
            in_flight: 0,
            sent_count: 0,
            sent: VecDeque::new(),
            delivered: 0,
            delivered_at: now,
            min_rtt: None,
            probing_from: None,
            rates: VecDeque::new(),
        }
    }

    /// A batch sent at `now`.
    fn send(&mut self, now: Instant) {
        if self.in_flight == 0 {
            self.delivered_at = now;
        }
        self.in_flight += 1;
        self.sent.push_back(Sent {
            at: now,
            index: self.sent_count,
            delivered: self.delivered,
            delivered_at: self.delivered_at,
        });
        self.sent_count += 1;
    }

    /// The shortest recent round trip.
    fn min_rtt(&self) -> Option<Duration> {
        self.min_rtt.map(|(d, _)| d)
    }

    /// The fastest recent delivery rate, in batches per second.
    fn max_rate(&self) -> Option<f64> {
        self.rates.front().map(|&(_, r)| r)
    }

    /// The oldest batch in flight acknowledged at `now`.
    fn ack(&mut self, now: Instant) {
        self.in_flight = self.in_flight.saturating_sub(1);
        let Some(sent) = self.sent.pop_front() else { return };
        self.delivered += 1;
        self.delivered_at = now;
        let rtt = now.saturating_duration_since(sent.at);
        self.round_trip(rtt, sent.index, now);
        let interval = now.saturating_duration_since(sent.delivered_at);
        if !interval.is_zero() {
            let rate = (self.delivered - sent.delivered) as f64 / interval.as_secs_f64();
            while self.rates.back().is_some_and(|&(_, r)| r <= rate) {
                self.rates.pop_back();
            }
            self.rates.push_back((now, rate));
        }
        let Some(min_rtt) = self.min_rtt() else { return };
        let horizon = (min_rtt * RATE_ROUND_TRIPS).max(RATE_HORIZON_MIN);
        while self.rates.len() > 1
            && self.rates.front().is_some_and(|&(t, _)| now.saturating_duration_since(t) > horizon)
        {
            self.rates.pop_front();
        }
        if !self.adaptive {
            return;
        }
        if self.probing_from.is_some() {
            // One batch at a time: the probe's batch waits behind none of ours.
            self.limit = 1;
        } else if let Some(rate) = self.max_rate() {
            let bdp = rate * min_rtt.as_secs_f64();
            let want = (GAIN * bdp).ceil().min(f64::from(self.cap)) as u32;
            self.limit = want.clamp(FLOOR.min(self.cap), self.cap);
        }
    }

    /// A round-trip sample of the batch sent `index`-th: a new shortest, the end of a probe, or
    /// the start of one when the shortest has stood too long.
    fn round_trip(&mut self, rtt: Duration, index: u64, now: Instant) {
        match (self.min_rtt, self.probing_from) {
            (_, Some(from)) if index >= from => {
                self.min_rtt = Some((rtt, now));
                self.probing_from = None;
            }
            (_, Some(_)) => {}
            (Some((min, _)), None) if rtt <= min => self.min_rtt = Some((rtt, now)),
            (Some((_, seen)), None) if now.saturating_duration_since(seen) > MIN_RTT_EXPIRY => {
                if self.adaptive {
                    self.probing_from = Some(self.sent_count);
                } else {
                    self.min_rtt = Some((rtt, now));
                }
            }
            (Some(_), None) => {}
            (None, None) => self.min_rtt = Some((rtt, now)),
        }
    }
}

/// Batches the rollout thread may have in flight (see the module header).
pub struct Window {
    state: Mutex<State>,
    changed: Condvar,
}

/// What the window is sized from, for the worker's metrics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinkEstimate {
    /// The shortest of the recent round trips.
    pub min_rtt: Duration,
    /// The fastest recent delivery rate, batches per second.
    pub acked_batches_per_s: f64,
}

impl Window {
    /// A window capped at `cap` batches; `adaptive` starts it at 2 and sizes it to the link,
    /// otherwise it stays at `cap`.
    pub fn new(cap: u32, adaptive: bool) -> Self {
        Self {
            state: Mutex::new(State::new(cap, adaptive, Instant::now())),
            changed: Condvar::new(),
        }
    }

    /// The window's size now, in batches.
    pub fn limit(&self) -> u32 {
        lock(&self.state).limit
    }

    /// The round trip and delivery rate the window is sized from; `None` before the first
    /// acknowledgement.
    pub fn estimate(&self) -> Option<LinkEstimate> {
        let s = lock(&self.state);
        Some(LinkEstimate { min_rtt: s.min_rtt()?, acked_batches_per_s: s.max_rate()? })
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

    /// A simulated link, in simulated time: a propagation round trip of `rtt` plus, for every
    /// `stall_every`-th batch (0: none), a one-off delay of `stall` (a learner busy for a moment,
    /// a round trip through a loaded host); a bottleneck (the learner, or the link's bandwidth)
    /// that takes `service` per batch; a sender that has a batch ready every `produce` (zero:
    /// always) and sends it as soon as the window has a slot. Each acknowledgement comes at
    /// `max(sent + rtt (+ stall), previous ack + service)`.
    struct Link {
        rtt: Duration,
        service: Duration,
        produce: Duration,
        stall_every: usize,
        stall: Duration,
    }

    impl Link {
        fn new(rtt_ms: u64, service_us: u64) -> Self {
            Self {
                rtt: Duration::from_millis(rtt_ms),
                service: Duration::from_micros(service_us),
                produce: Duration::ZERO,
                stall_every: 0,
                stall: Duration::ZERO,
            }
        }

        /// Runs `acks` acknowledgements through the window `w`; returns the window at the end,
        /// the window after each acknowledgement of the last half, and the acknowledged batches
        /// per second over the last half.
        fn run(&self, w: &mut State, acks: usize) -> (u32, Vec<u32>, f64) {
            let t0 = Instant::now();
            let (mut clock, mut last_ack, mut ready) = (t0, t0, t0);
            // When each batch in flight arrives at the bottleneck's queue, oldest first.
            let mut flight: VecDeque<Instant> = VecDeque::new();
            let (mut times, mut limits, mut sent) = (Vec::with_capacity(acks), Vec::new(), 0usize);
            while times.len() < acks {
                let due = flight.front().map(|&arrive| arrive.max(last_ack + self.service));
                if w.in_flight < w.limit && due.is_none_or(|d| ready <= d) {
                    clock = clock.max(ready);
                    w.send(clock);
                    let stalled = self.stall_every > 0 && sent % self.stall_every == 0 && sent > 0;
                    flight.push_back(
                        clock + self.rtt + if stalled { self.stall } else { Duration::ZERO },
                    );
                    sent += 1;
                    ready = clock + self.produce;
                    continue;
                }
                let due = due.expect("a full window has a batch in flight");
                flight.pop_front();
                clock = due;
                last_ack = due;
                w.ack(due);
                times.push(due);
                if times.len() > acks / 2 {
                    limits.push(w.limit);
                }
            }
            let half = acks / 2;
            let span = times[acks - 1].duration_since(times[half]).as_secs_f64();
            (w.limit, limits, (acks - 1 - half) as f64 / span)
        }
    }

    /// The share of `limits` under `n`.
    fn share_under(limits: &[u32], n: u32) -> f64 {
        limits.iter().filter(|&&l| l < n).count() as f64 / limits.len().max(1) as f64
    }

    fn window(cap: u32) -> State {
        State::new(cap, true, Instant::now())
    }

    #[test]
    fn a_delay_bound_link_grows_the_window_to_its_cap() {
        // 100 ms round trips (50 ms one way), a bottleneck at 1,000 batches/s: 32 in flight
        // carry 320/s, which only the cap bounds.
        let mut w = window(32);
        assert_eq!(w.limit, 2);
        let (limit, limits, rate) = Link::new(100, 1_000).run(&mut w, 4000);
        assert_eq!(limit, 32);
        assert!(
            share_under(&limits, 32) < 0.02,
            "under the cap {:.3} of the time",
            share_under(&limits, 32)
        );
        assert!(rate > 300.0, "{rate} batches/s");
    }

    #[test]
    fn the_window_reaches_its_cap_within_a_few_round_trips() {
        // Doubling per round trip: from 2 to 32 in about four round trips, not 30.
        let mut w = window(32);
        let (limit, _, _) = Link::new(200, 1_000).run(&mut w, 2 + 4 + 8 + 16 + 32);
        assert_eq!(limit, 32);
    }

    #[test]
    fn where_the_bottleneck_binds_the_window_rests_near_twice_its_need() {
        // 1 ms round trips, a bottleneck at 100 batches/s: one batch in flight already carries
        // it, so the window stays at the floor.
        let mut w = window(32);
        let (limit, _, rate) = Link::new(1, 10_000).run(&mut w, 4000);
        assert!(limit <= 3, "window {limit}");
        assert!(rate > 95.0, "{rate} batches/s");
        // 50 ms round trips, a bottleneck at 200 batches/s: 10 in flight carry it; the window
        // rests at about twice that, not at the cap.
        let mut w = window(64);
        let (limit, _, rate) = Link::new(50, 5_000).run(&mut w, 4000);
        assert!((10..=30).contains(&limit), "window {limit}");
        assert!(rate > 190.0, "{rate} batches/s");
    }

    #[test]
    fn slow_round_trips_now_and_then_do_not_shrink_the_window() {
        // What stalled the rule before this one: every 50th batch takes 300 ms longer (a busy
        // learner, a loaded host), and the batches behind it wait. The window stays near its
        // cap and carries what a window fixed at the cap carries over the same link.
        let link =
            Link { stall_every: 50, stall: Duration::from_millis(300), ..Link::new(100, 1_000) };
        let mut w = window(32);
        let (_, limits, rate) = link.run(&mut w, 6000);
        let mut fixed = State::new(32, false, Instant::now());
        let (_, _, fixed_rate) = link.run(&mut fixed, 6000);
        assert!(
            share_under(&limits, 24) < 0.05,
            "under 24 {:.3} of the time",
            share_under(&limits, 24)
        );
        assert!(rate > 0.9 * fixed_rate, "{rate} batches/s, a fixed 32: {fixed_rate}");
    }

    #[test]
    fn a_queue_the_window_built_does_not_become_the_round_trip() {
        // The bottleneck binds over a 1 ms link for 60 s (6,000 batches at 100/s): every round
        // trip but the first waits behind a batch. The shortest round trip is measured afresh
        // every 10 s with the window at its floor, so the queue never grows the window.
        let mut w = window(32);
        let (_, limits, rate) = Link::new(1, 10_000).run(&mut w, 6000);
        let largest = limits.iter().max().copied().unwrap_or_default();
        assert!(largest <= 3, "window {largest}");
        assert!(rate > 95.0, "{rate} batches/s");
    }

    #[test]
    fn a_sender_slower_than_the_link_keeps_the_window_small() {
        // A batch every 100 ms over 50 ms round trips: one in flight at a time suffices, so
        // the window stays near the floor (a bigger one would only risk more on a worker's
        // death).
        let link = Link { produce: Duration::from_millis(100), ..Link::new(50, 1_000) };
        let mut w = window(32);
        let (limit, _, rate) = link.run(&mut w, 400);
        assert!(limit <= 3, "window {limit}");
        assert!(rate > 9.5, "{rate} batches/s");
    }

    #[test]
    fn a_fixed_window_stays_at_its_cap_and_blocks_there() {
        let mut s = State::new(3, false, Instant::now());
        let (limit, _, _) = Link::new(1, 100).run(&mut s, 500);
        assert_eq!(limit, 3);
        let (w, c) = (Window::new(3, false), control());
        for _ in 0..3 {
            assert!(w.take(&c));
        }
        c.lock().expect("control").stop = true;
        assert!(!w.take(&c), "a full window gives no slot; stop ends the wait");
    }

    #[test]
    fn the_estimate_follows_the_acknowledgements() {
        let (w, c) = (Window::new(8, true), control());
        assert_eq!(w.estimate(), None);
        assert!(w.take(&c));
        std::thread::sleep(Duration::from_millis(5));
        w.grant();
        let e = w.estimate().expect("an estimate after an acknowledgement");
        assert!(e.min_rtt >= Duration::from_millis(5), "{e:?}");
        assert!(e.acked_batches_per_s > 0.0 && e.acked_batches_per_s <= 200.0, "{e:?}");
    }
}
