//! Replay buffer for fixed-shape observations: FIFO ring, uniform sampling, f16 storage.
//!
//! Owns: [`Replay`] and [`Batch`]. Every agent's transitions go into the one buffer
//! (parameter sharing). Observations are stored as f16 (positions are normalised to about
//! [-1, 1], so the error is below 3 cm at 50 m; segment ids are exact below 2048), actions,
//! rewards and flags as f32; the IDM driver's action in each state (`sac.bc_target =
//! "oracle"`) as a column that exists once a labelled transition arrives, NaN for rows stored
//! without one. Memory grows with use up to the capacity. Must not: do IO.

use half::f16;
use rand::Rng;

/// One transition as pushed by a rollout (the type workers batch, `sf_job`'s).
pub use sf_job::Transition;

/// A sampled minibatch, rows in sampling order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Batch {
    pub obs: Vec<f32>,
    pub next_obs: Vec<f32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub terminals: Vec<f32>,
    /// Decision steps each row spans (see [`Transition::steps`]).
    pub steps: Vec<u8>,
    pub map_ids: Vec<u32>,
    /// Each row's oracle label (`act_dim` floats, NaN where the transition came without
    /// one), or empty when the buffer holds no labels.
    pub oracle: Vec<f32>,
}

impl Batch {
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    /// Each row's bootstrap factor in the TD target `r + f (min Q' - alpha log pi)`:
    /// `gamma^steps`, or 0 where the row ends its episode by a failure or its destination.
    pub fn bootstrap_discounts(&self, gamma: f32) -> Vec<f32> {
        self.terminals
            .iter()
            .zip(&self.steps)
            .map(|(&d, &n)| (1.0 - d) * gamma.powi(i32::from(n)))
            .collect()
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
    #[error("a transition spans at least one step; got 0")]
    ZeroSteps,
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
    steps: Vec<u8>,
    map_ids: Vec<u32>,
    /// Oracle labels, `act_dim` per slot (NaN: none), once `labelled`.
    oracle: Vec<f32>,
    /// A labelled transition was pushed: `oracle` keeps a label (or NaN) for every slot.
    labelled: bool,
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
    pub steps: u8,
    pub map_id: u32,
    /// The oracle label ([`Transition::oracle`]): `act_dim` floats, or empty for none (a
    /// stored row without one reads back empty).
    pub oracle: &'a [f32],
}

/// An oracle label is `act_dim` finite floats, or absent.
fn check_label(label: &[f32], act_dim: usize) -> Result<(), ReplayError> {
    if !label.is_empty() && label.len() != act_dim {
        return Err(ReplayError::Shape { field: "oracle", got: label.len(), want: act_dim });
    }
    if !label.iter().all(|x| x.is_finite()) {
        return Err(ReplayError::NotFinite("oracle"));
    }
    Ok(())
}

fn check_steps(steps: u8) -> Result<(), ReplayError> {
    if steps == 0 {
        return Err(ReplayError::ZeroSteps);
    }
    Ok(())
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
            steps: Vec::new(),
            map_ids: Vec::new(),
            oracle: Vec::new(),
            labelled: false,
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
        let label = self.oracle.get(i * self.act_dim..(i + 1) * self.act_dim).unwrap_or(&[]);
        Some(Stored {
            obs: &self.obs[o..o + self.obs_len],
            next_obs: &self.next_obs[o..o + self.obs_len],
            action: &self.actions[i * self.act_dim..(i + 1) * self.act_dim],
            reward: self.rewards[i],
            terminal: self.terminals[i] != 0.0,
            steps: self.steps[i],
            map_id: self.map_ids[i],
            oracle: if label.iter().any(|x| x.is_nan()) { &[] } else { label },
        })
    }

    /// Bytes one stored transition takes.
    pub fn bytes_per_transition(&self) -> usize {
        let labels = if self.labelled { self.act_dim * 4 } else { 0 };
        2 * self.obs_len * std::mem::size_of::<f16>() + self.act_dim * 4 + 4 + 4 + 1 + 4 + labels
    }

    /// The buffer holds oracle labels (some pushed transition carried one).
    pub fn is_labelled(&self) -> bool {
        self.labelled
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
        let check = |field, got: usize, want| {
            if got == want {
                Ok(())
            } else {
                Err(ReplayError::Shape { field, got, want })
            }
        };
        check("obs", t.obs.len(), self.obs_len)?;
        check("next_obs", t.next_obs.len(), self.obs_len)?;
        check("action", t.action.len(), self.act_dim)?;
        check_label(t.oracle, self.act_dim)?;
        for (field, v) in [
            ("obs", t.obs),
            ("next_obs", t.next_obs),
            ("action", t.action),
            ("reward", std::slice::from_ref(&t.reward)),
        ] {
            if !v.iter().all(|x| x.is_finite()) {
                return Err(ReplayError::NotFinite(field));
            }
        }
        check_steps(t.steps)?;
        let to16 = |s: &[f32]| s.iter().map(|&x| f16::from_f32(x)).collect::<Vec<_>>();
        let (obs, next_obs) = (to16(t.obs), to16(t.next_obs));
        self.store(Stored {
            obs: &obs,
            next_obs: &next_obs,
            action: t.action,
            reward: t.reward,
            terminal: t.terminal,
            steps: t.steps,
            map_id: t.map_id,
            oracle: t.oracle,
        });
        Ok(())
    }

    /// Stores a transition whose observations are already half floats (the wire format), so
    /// ingest copies instead of converting. Same checks and eviction as [`Replay::push`].
    pub fn push_f16(&mut self, t: Stored<'_>) -> Result<(), ReplayError> {
        let check = |field, got: usize, want| {
            if got == want {
                Ok(())
            } else {
                Err(ReplayError::Shape { field, got, want })
            }
        };
        check("obs", t.obs.len(), self.obs_len)?;
        check("next_obs", t.next_obs.len(), self.obs_len)?;
        check("action", t.action.len(), self.act_dim)?;
        if !t.obs.iter().all(|x| x.is_finite()) {
            return Err(ReplayError::NotFinite("obs"));
        }
        if !t.next_obs.iter().all(|x| x.is_finite()) {
            return Err(ReplayError::NotFinite("next_obs"));
        }
        if !(t.action.iter().all(|x| x.is_finite()) && t.reward.is_finite()) {
            return Err(ReplayError::NotFinite("action or reward"));
        }
        check_label(t.oracle, self.act_dim)?;
        check_steps(t.steps)?;
        self.store(t);
        Ok(())
    }

    /// Writes a checked transition at the head, evicting the oldest when full.
    fn store(&mut self, t: Stored<'_>) {
        let i = self.head;
        // The label column starts with the first labelled row, NaN for the rows before it.
        if !self.labelled && !t.oracle.is_empty() {
            self.oracle = vec![f32::NAN; self.actions.len()];
            self.labelled = true;
        }
        if self.labelled {
            let label = |k: usize| if t.oracle.is_empty() { f32::NAN } else { t.oracle[k] };
            if self.len < self.capacity && i == self.len {
                self.oracle.extend((0..self.act_dim).map(label));
            } else {
                for k in 0..self.act_dim {
                    self.oracle[i * self.act_dim + k] = label(k);
                }
            }
        }
        if self.len < self.capacity && i == self.len {
            self.obs.extend_from_slice(t.obs);
            self.next_obs.extend_from_slice(t.next_obs);
            self.actions.extend_from_slice(t.action);
            self.rewards.push(t.reward);
            self.terminals.push(t.terminal as u8 as f32);
            self.steps.push(t.steps);
            self.map_ids.push(t.map_id);
            self.len += 1;
        } else {
            let o = i * self.obs_len;
            self.obs[o..o + self.obs_len].copy_from_slice(t.obs);
            self.next_obs[o..o + self.obs_len].copy_from_slice(t.next_obs);
            self.actions[i * self.act_dim..(i + 1) * self.act_dim].copy_from_slice(t.action);
            self.rewards[i] = t.reward;
            self.terminals[i] = t.terminal as u8 as f32;
            self.steps[i] = t.steps;
            self.map_ids[i] = t.map_id;
        }
        self.head = (self.head + 1) % self.capacity;
        self.inserted += 1;
    }

    /// Uniformly samples `n` transitions (with replacement) into `out`, reusing its buffers.
    pub fn sample_into(
        &self,
        rng: &mut impl Rng,
        n: usize,
        out: &mut Batch,
    ) -> Result<(), ReplayError> {
        self.sample_before_into(rng, n, u64::MAX, out)
    }

    /// Like [`Replay::sample_into`], among the held transitions whose insertion number is
    /// below `before` only (the first ones a job took, e.g. its warm-up's). `Empty` if none of
    /// them is held any more.
    pub fn sample_before_into(
        &self,
        rng: &mut impl Rng,
        n: usize,
        before: u64,
        out: &mut Batch,
    ) -> Result<(), ReplayError> {
        let (first, end) = (self.oldest(), self.inserted.min(before));
        if end <= first {
            return Err(ReplayError::Empty);
        }
        out.obs.clear();
        out.next_obs.clear();
        out.actions.clear();
        out.rewards.clear();
        out.terminals.clear();
        out.steps.clear();
        out.map_ids.clear();
        out.oracle.clear();
        let all = end - first == self.len as u64;
        for _ in 0..n {
            // The whole buffer draws a position directly (as it always has, so seeded runs keep
            // their batches); a prefix draws an insertion number and finds its position.
            let i = if all {
                rng.random_range(0..self.len)
            } else {
                ((rng.random_range(first..end) - self.offset) % self.capacity as u64) as usize
            };
            let o = i * self.obs_len;
            out.obs.extend(self.obs[o..o + self.obs_len].iter().map(|x| x.to_f32()));
            out.next_obs.extend(self.next_obs[o..o + self.obs_len].iter().map(|x| x.to_f32()));
            out.actions.extend_from_slice(&self.actions[i * self.act_dim..(i + 1) * self.act_dim]);
            out.rewards.push(self.rewards[i]);
            out.terminals.push(self.terminals[i]);
            out.steps.push(self.steps[i]);
            out.map_ids.push(self.map_ids[i]);
            if self.labelled {
                out.oracle
                    .extend_from_slice(&self.oracle[i * self.act_dim..(i + 1) * self.act_dim]);
            }
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
        Transition {
            obs,
            action: &[0.5, -0.5],
            reward: v,
            next_obs: obs,
            terminal: v > 2.0,
            steps: 1,
            map_id: 1,
            oracle: &[],
        }
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
        assert_eq!(r.bytes_per_transition(), 2 * 3 * 2 + 8 + 13);
    }

    /// Sampling below an insertion number draws only those transitions still held, and says
    /// so when none is.
    #[test]
    fn sampling_a_prefix_draws_only_its_rows() {
        let mut r = Replay::new(4, 3, 2);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut b = Batch::default();
        for k in 0..3 {
            r.push(t(k as f32, &[k as f32, 0.0, 0.0])).expect("push");
        }
        r.sample_before_into(&mut rng, 200, 2, &mut b).expect("rows 0 and 1");
        let mut seen = [0; 3];
        b.rewards.iter().for_each(|&k| seen[k as usize] += 1);
        assert!(seen[0] > 50 && seen[1] > 50 && seen[2] == 0, "{seen:?}");
        assert!(b.obs.chunks(3).zip(&b.rewards).all(|(o, &k)| o[0] == k), "rows stay whole");
        // Three more: rows 0 and 1 are evicted (row 4 took position 0), so a prefix below 3
        // keeps only row 2.
        for k in 3..6 {
            r.push(t(k as f32, &[k as f32, 0.0, 0.0])).expect("push");
        }
        r.sample_before_into(&mut rng, 20, 3, &mut b).expect("row 2");
        assert!(b.rewards.iter().all(|&k| k == 2.0), "{:?}", b.rewards);
        assert_eq!(r.sample_before_into(&mut rng, 5, 2, &mut b), Err(ReplayError::Empty));
        // A restored buffer numbers from its job's count.
        let mut q = Replay::numbered_from(4, 3, 2, 10);
        for k in 0..4 {
            q.push(t(k as f32, &[k as f32, 0.0, 0.0])).expect("push");
        }
        q.sample_before_into(&mut rng, 50, 12, &mut b).expect("rows 10 and 11");
        assert!(b.rewards.iter().all(|&k| k < 2.0), "{:?}", b.rewards);
    }

    #[test]
    fn half_float_pushes_store_the_same_rows() {
        let mut a = Replay::new(2, 3, 2);
        let mut b = Replay::new(2, 3, 2);
        for k in 0..3 {
            let o = [k as f32, 0.5, -0.25];
            a.push(t(k as f32, &o)).expect("push");
            let h: Vec<f16> = o.iter().map(|&x| f16::from_f32(x)).collect();
            b.push_f16(Stored {
                obs: &h,
                next_obs: &h,
                action: &[0.5, -0.5],
                reward: k as f32,
                terminal: k as f32 > 2.0,
                steps: 1,
                map_id: 1,
                oracle: &[],
            })
            .expect("push_f16");
        }
        let mut r1 = ChaCha8Rng::seed_from_u64(3);
        let mut r2 = ChaCha8Rng::seed_from_u64(3);
        assert_eq!(a.sample(&mut r1, 20), b.sample(&mut r2, 20));
        assert_eq!(
            b.push_f16(Stored {
                obs: &[f16::NAN; 3],
                next_obs: &[f16::ZERO; 3],
                action: &[0.0, 0.0],
                reward: 0.0,
                terminal: false,
                steps: 1,
                map_id: 0,
                oracle: &[],
            }),
            Err(ReplayError::NotFinite("obs"))
        );
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
        assert_eq!(
            r.push(Transition { obs: &[0.0; 2], ..t(0.0, &o) }),
            Err(ReplayError::Shape { field: "obs", got: 2, want: 3 })
        );
        assert_eq!(
            r.push(Transition { reward: f32::NAN, ..t(0.0, &o) }),
            Err(ReplayError::NotFinite("reward"))
        );
        assert_eq!(r.push(Transition { steps: 0, ..t(0.0, &o) }), Err(ReplayError::ZeroSteps));
        assert_eq!(r.len(), 0);
        assert_eq!(r.sample(&mut ChaCha8Rng::seed_from_u64(0), 1), Err(ReplayError::Empty));
    }

    /// Oracle labels: the column starts with the first labelled row (NaN before it), rows
    /// keep their labels through sampling and eviction, bad labels are refused.
    #[test]
    fn oracle_labels_stay_with_their_rows() {
        let mut r = Replay::new(3, 3, 2);
        let o = [0.0; 3];
        r.push(t(0.0, &o)).expect("unlabelled");
        assert!(!r.is_labelled());
        let before = r.bytes_per_transition();
        assert!(r.sample(&mut ChaCha8Rng::seed_from_u64(0), 4).expect("sample").oracle.is_empty());
        for k in 1..5 {
            let label = [0.1 * k as f32, -0.1 * k as f32];
            r.push(Transition { oracle: &label, ..t(k as f32, &o) }).expect("labelled");
        }
        assert!(r.is_labelled());
        assert_eq!(r.bytes_per_transition(), before + 8);
        // Rows 2, 3, 4 are held; each row's label is 0.1 x its reward.
        let b = r.sample(&mut ChaCha8Rng::seed_from_u64(1), 30).expect("sample");
        assert_eq!(b.oracle.len(), 60);
        for (i, &reward) in b.rewards.iter().enumerate() {
            assert!((b.oracle[2 * i] - 0.1 * reward).abs() < 1e-6, "row {i}");
            assert!((b.oracle[2 * i + 1] + 0.1 * reward).abs() < 1e-6, "row {i}");
        }
        assert_eq!(r.get(4).expect("held").oracle, &[0.4f32, -0.4][..]);
        // A row pushed without a label reads back without one, and samples as NaN.
        r.push(t(9.0, &o)).expect("unlabelled again");
        assert!(r.get(5).expect("held").oracle.is_empty());
        let b = r.sample(&mut ChaCha8Rng::seed_from_u64(2), 30).expect("sample");
        let nan_rows = (0..b.len()).filter(|&i| b.oracle[2 * i].is_nan()).count();
        assert_eq!(nan_rows, b.rewards.iter().filter(|&&x| x == 9.0).count());
        assert_eq!(
            r.push(Transition { oracle: &[0.0], ..t(0.0, &o) }),
            Err(ReplayError::Shape { field: "oracle", got: 1, want: 2 })
        );
        assert_eq!(
            r.push(Transition { oracle: &[0.0, f32::NAN], ..t(0.0, &o) }),
            Err(ReplayError::NotFinite("oracle"))
        );
        // A labelled buffer of one-row capacity: the first push creates the column.
        let mut one = Replay::new(1, 3, 2);
        one.push(Transition { oracle: &[0.5, 0.5], ..t(1.0, &o) }).expect("first");
        assert_eq!(one.get(0).expect("held").oracle, &[0.5f32, 0.5][..]);
    }

    /// n-step targets: a row bootstraps with gamma^steps unless it ends its episode.
    #[test]
    fn n_step_rows_bootstrap_with_gamma_to_their_span() {
        let mut r = Replay::new(4, 3, 2);
        let o = [0.0; 3];
        for (steps, terminal) in [(1, false), (3, false), (3, true), (2, false)] {
            r.push(Transition { steps, terminal, reward: f32::from(steps), ..t(0.0, &o) })
                .expect("push");
        }
        let b = r.sample(&mut ChaCha8Rng::seed_from_u64(1), 64).expect("sample");
        let f = b.bootstrap_discounts(0.9);
        assert_eq!(f.len(), b.len());
        for (i, &fi) in f.iter().enumerate() {
            let want = match (b.steps[i], b.terminals[i] != 0.0) {
                (_, true) => 0.0,
                (1, false) => 0.9,
                (2, false) => 0.81,
                (3, false) => 0.729,
                other => panic!("unexpected row {other:?}"),
            };
            assert!((fi - want).abs() < 1e-6, "row {i}: {fi} vs {want}");
            assert_eq!(b.rewards[i], f32::from(b.steps[i]), "the row's fields stay together");
        }
    }
}
