//! Replay buffer for fixed-shape observations: FIFO ring, uniform sampling, f16 storage.
//!
//! Owns: [`Replay`] and [`Batch`]. Every agent's transitions go into the one buffer
//! (parameter sharing). Observations are stored as f16 (positions are normalised to about
//! [-1, 1], so the error is below 3 cm at 50 m; segment ids are exact below 2048), actions,
//! rewards and flags as f32. Memory grows with use up to the capacity. Must not: do IO.

use half::f16;
use rand::Rng;

/// One transition as pushed by a rollout.
#[derive(Clone, Copy, Debug)]
pub struct Transition<'a> {
    pub obs: &'a [f32],
    pub action: &'a [f32],
    pub reward: f32,
    pub next_obs: &'a [f32],
    /// True when the episode ended for this agent by a failure or its destination
    /// (timeouts are not terminal for bootstrapping).
    pub terminal: bool,
    /// Index of the map the observation refers to (query-centric segment ids).
    pub map_id: u32,
}

/// A sampled minibatch, rows in sampling order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Batch {
    pub obs: Vec<f32>,
    pub next_obs: Vec<f32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub terminals: Vec<f32>,
    pub map_ids: Vec<u32>,
}

impl Batch {
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ReplayError {
    #[error("transition field `{field}` has {got} values, expected {want}")]
    Shape { field: &'static str, got: usize, want: usize },
    #[error("transition field `{0}` holds a non-finite value")]
    NotFinite(&'static str),
    #[error("cannot sample from an empty replay buffer")]
    Empty,
}

/// Fixed-capacity FIFO replay of transitions with observations of `obs_len` floats.
pub struct Replay {
    capacity: usize,
    obs_len: usize,
    act_dim: usize,
    obs: Vec<f16>,
    next_obs: Vec<f16>,
    actions: Vec<f32>,
    rewards: Vec<f32>,
    terminals: Vec<f32>,
    map_ids: Vec<u32>,
    len: usize,
    head: usize,
    inserted: u64,
    /// Insertion number of the first transition this buffer stored (a restored buffer keeps
    /// numbering where its job was).
    offset: u64,
}

/// One stored transition, borrowed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stored<'a> {
    pub obs: &'a [f16],
    pub next_obs: &'a [f16],
    pub action: &'a [f32],
    pub reward: f32,
    pub terminal: bool,
    pub map_id: u32,
}

impl Replay {
    pub fn new(capacity: usize, obs_len: usize, act_dim: usize) -> Self {
        assert!(capacity > 0, "replay capacity must be positive");
        Self::numbered_from(capacity, obs_len, act_dim, 0)
    }

    /// An empty buffer whose first transition gets insertion number `first` (restoring a job's
    /// replay: numbers match the job's transition count).
    pub fn numbered_from(capacity: usize, obs_len: usize, act_dim: usize, first: u64) -> Self {
        assert!(capacity > 0, "replay capacity must be positive");
        Self {
            capacity,
            obs_len,
            act_dim,
            obs: Vec::new(),
            next_obs: Vec::new(),
            actions: Vec::new(),
            rewards: Vec::new(),
            terminals: Vec::new(),
            map_ids: Vec::new(),
            len: 0,
            head: 0,
            inserted: first,
            offset: first,
        }
    }

    pub fn obs_len(&self) -> usize {
        self.obs_len
    }

    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// Renumbers the held transitions so that the newest is `inserted - 1` (a restore that
    /// found fewer transitions than its job counted). Contents and order do not change.
    pub fn renumber(&mut self, inserted: u64) {
        let shift = inserted.wrapping_sub(self.inserted);
        self.offset = self.offset.wrapping_add(shift);
        self.inserted = inserted;
    }

    /// Insertion number of the oldest transition held.
    pub fn oldest(&self) -> u64 {
        self.inserted - self.len as u64
    }

    /// The transition with insertion number `k`, if still held.
    pub fn get(&self, k: u64) -> Option<Stored<'_>> {
        if k < self.oldest() || k >= self.inserted {
            return None;
        }
        let i = ((k - self.offset) % self.capacity as u64) as usize;
        let o = i * self.obs_len;
        Some(Stored {
            obs: &self.obs[o..o + self.obs_len],
            next_obs: &self.next_obs[o..o + self.obs_len],
            action: &self.actions[i * self.act_dim..(i + 1) * self.act_dim],
            reward: self.rewards[i],
            terminal: self.terminals[i] != 0.0,
            map_id: self.map_ids[i],
        })
    }

    /// Bytes one stored transition takes.
    pub fn bytes_per_transition(&self) -> usize {
        2 * self.obs_len * std::mem::size_of::<f16>() + self.act_dim * 4 + 4 + 4 + 4
    }

    /// Bytes the buffer takes when full.
    pub fn bytes_at_capacity(&self) -> usize {
        self.capacity * self.bytes_per_transition()
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Transitions ever inserted (including evicted ones, and for a restored buffer those
    /// before its first).
    pub fn inserted(&self) -> u64 {
        self.inserted
    }

    /// Validates and stores a transition, evicting the oldest when full.
    pub fn push(&mut self, t: Transition<'_>) -> Result<(), ReplayError> {
        let check = |field, got: usize, want| if got == want { Ok(()) } else { Err(ReplayError::Shape { field, got, want }) };
        check("obs", t.obs.len(), self.obs_len)?;
        check("next_obs", t.next_obs.len(), self.obs_len)?;
        check("action", t.action.len(), self.act_dim)?;
        for (field, v) in [("obs", t.obs), ("next_obs", t.next_obs), ("action", t.action), ("reward", std::slice::from_ref(&t.reward))] {
            if !v.iter().all(|x| x.is_finite()) {
                return Err(ReplayError::NotFinite(field));
            }
        }
        let i = self.head;
        let to16 = |s: &[f32]| s.iter().map(|&x| f16::from_f32(x)).collect::<Vec<_>>();
        if self.len < self.capacity && i == self.len {
            self.obs.extend(to16(t.obs));
            self.next_obs.extend(to16(t.next_obs));
            self.actions.extend_from_slice(t.action);
            self.rewards.push(t.reward);
            self.terminals.push(t.terminal as u8 as f32);
            self.map_ids.push(t.map_id);
            self.len += 1;
        } else {
            let o = i * self.obs_len;
            for (dst, &x) in self.obs[o..o + self.obs_len].iter_mut().zip(t.obs) {
                *dst = f16::from_f32(x);
            }
            for (dst, &x) in self.next_obs[o..o + self.obs_len].iter_mut().zip(t.next_obs) {
                *dst = f16::from_f32(x);
            }
            self.actions[i * self.act_dim..(i + 1) * self.act_dim].copy_from_slice(t.action);
            self.rewards[i] = t.reward;
            self.terminals[i] = t.terminal as u8 as f32;
            self.map_ids[i] = t.map_id;
        }
        self.head = (self.head + 1) % self.capacity;
        self.inserted += 1;
        Ok(())
    }

    /// Stores a transition whose observations are already half floats (the wire format), so
    /// ingest copies instead of converting. Same checks and eviction as [`Replay::push`].
    #[allow(clippy::too_many_arguments)]
    pub fn push_f16(&mut self, obs: &[f16], action: &[f32], reward: f32, next_obs: &[f16], terminal: bool, map_id: u32) -> Result<(), ReplayError> {
        let check = |field, got: usize, want| if got == want { Ok(()) } else { Err(ReplayError::Shape { field, got, want }) };
        check("obs", obs.len(), self.obs_len)?;
        check("next_obs", next_obs.len(), self.obs_len)?;
        check("action", action.len(), self.act_dim)?;
        if !obs.iter().all(|x| x.is_finite()) {
            return Err(ReplayError::NotFinite("obs"));
        }
        if !next_obs.iter().all(|x| x.is_finite()) {
            return Err(ReplayError::NotFinite("next_obs"));
        }
        if !(action.iter().all(|x| x.is_finite()) && reward.is_finite()) {
            return Err(ReplayError::NotFinite("action or reward"));
        }
        let i = self.head;
        if self.len < self.capacity && i == self.len {
            self.obs.extend_from_slice(obs);
            self.next_obs.extend_from_slice(next_obs);
            self.actions.extend_from_slice(action);
            self.rewards.push(reward);
            self.terminals.push(terminal as u8 as f32);
            self.map_ids.push(map_id);
            self.len += 1;
        } else {
            let o = i * self.obs_len;
            self.obs[o..o + self.obs_len].copy_from_slice(obs);
            self.next_obs[o..o + self.obs_len].copy_from_slice(next_obs);
            self.actions[i * self.act_dim..(i + 1) * self.act_dim].copy_from_slice(action);
            self.rewards[i] = reward;
            self.terminals[i] = terminal as u8 as f32;
            self.map_ids[i] = map_id;
        }
        self.head = (self.head + 1) % self.capacity;
        self.inserted += 1;
        Ok(())
    }

    /// Uniformly samples `n` transitions (with replacement) into `out`, reusing its buffers.
    pub fn sample_into(&self, rng: &mut impl Rng, n: usize, out: &mut Batch) -> Result<(), ReplayError> {
        if self.len == 0 {
            return Err(ReplayError::Empty);
        }
        out.obs.clear();
        out.next_obs.clear();
        out.actions.clear();
        out.rewards.clear();
        out.terminals.clear();
        out.map_ids.clear();
        for _ in 0..n {
            let i = rng.random_range(0..self.len);
            let o = i * self.obs_len;
            out.obs.extend(self.obs[o..o + self.obs_len].iter().map(|x| x.to_f32()));
            out.next_obs.extend(self.next_obs[o..o + self.obs_len].iter().map(|x| x.to_f32()));
            out.actions.extend_from_slice(&self.actions[i * self.act_dim..(i + 1) * self.act_dim]);
            out.rewards.push(self.rewards[i]);
            out.terminals.push(self.terminals[i]);
            out.map_ids.push(self.map_ids[i]);
        }
        Ok(())
    }

    pub fn sample(&self, rng: &mut impl Rng, n: usize) -> Result<Batch, ReplayError> {
        let mut b = Batch::default();
        self.sample_into(rng, n, &mut b)?;
        Ok(b)
    }
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;

    fn t(v: f32, obs: &[f32; 3]) -> Transition<'_> {
        Transition { obs, action: &[0.5, -0.5], reward: v, next_obs: obs, terminal: v > 2.0, map_id: 1 }
    }

    #[test]
    fn fifo_eviction_and_sampling() {
        let mut r = Replay::new(3, 3, 2);
        for k in 0..5 {
            let o = [k as f32, 0.25, -1.0];
            r.push(t(k as f32, &o)).expect("push");
        }
        assert_eq!((r.len(), r.inserted()), (3, 5));
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let b = r.sample(&mut rng, 300).expect("sample");
        // Only the three newest survive; each is drawn, and rows stay consistent.
        let mut seen = [0; 5];
        for i in 0..b.len() {
            let k = b.rewards[i] as usize;
            seen[k] += 1;
            assert_eq!(b.obs[i * 3], k as f32);
            assert_eq!(b.terminals[i], (k > 2) as u8 as f32);
            assert_eq!(&b.actions[i * 2..i * 2 + 2], &[0.5, -0.5]);
        }
        assert_eq!(&seen[..2], &[0, 0]);
        assert!(seen[2] > 50 && seen[3] > 50 && seen[4] > 50, "{seen:?}");
        assert_eq!(r.bytes_per_transition(), 2 * 3 * 2 + 8 + 12);
    }

    #[test]
    fn half_float_pushes_store_the_same_rows() {
        let mut a = Replay::new(2, 3, 2);
        let mut b = Replay::new(2, 3, 2);
        for k in 0..3 {
            let o = [k as f32, 0.5, -0.25];
            a.push(t(k as f32, &o)).expect("push");
            let h: Vec<f16> = o.iter().map(|&x| f16::from_f32(x)).collect();
            b.push_f16(&h, &[0.5, -0.5], k as f32, &h, k as f32 > 2.0, 1).expect("push_f16");
        }
        let mut r1 = ChaCha8Rng::seed_from_u64(3);
        let mut r2 = ChaCha8Rng::seed_from_u64(3);
        assert_eq!(a.sample(&mut r1, 20), b.sample(&mut r2, 20));
        assert_eq!(b.push_f16(&[f16::NAN; 3], &[0.0, 0.0], 0.0, &[f16::ZERO; 3], false, 0), Err(ReplayError::NotFinite("obs")));
        assert_eq!(b.inserted(), 3);
    }

    #[test]
    fn transitions_are_found_by_insertion_number_across_wraparound() {
        let mut r = Replay::numbered_from(3, 3, 2, 100);
        for k in 0..5 {
            let o = [k as f32, 0.25, -1.0];
            r.push(t(k as f32, &o)).expect("push");
        }
        assert_eq!((r.oldest(), r.inserted()), (102, 105));
        assert!(r.get(101).is_none() && r.get(105).is_none());
        for k in 102..105 {
            let s = r.get(k).expect("held");
            assert_eq!((s.obs[0].to_f32(), s.reward), ((k - 100) as f32, (k - 100) as f32));
        }
    }

    #[test]
    fn bad_transitions_are_refused_and_change_nothing() {
        let mut r = Replay::new(4, 3, 2);
        let o = [0.0; 3];
        assert_eq!(r.push(Transition { obs: &[0.0; 2], ..t(0.0, &o) }), Err(ReplayError::Shape { field: "obs", got: 2, want: 3 }));
        assert_eq!(r.push(Transition { reward: f32::NAN, ..t(0.0, &o) }), Err(ReplayError::NotFinite("reward")));
        assert_eq!(r.len(), 0);
        assert_eq!(r.sample(&mut ChaCha8Rng::seed_from_u64(0), 1), Err(ReplayError::Empty));
    }
}
