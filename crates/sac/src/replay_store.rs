//! The replay on disk: written beside a job's checkpoint in segments, read back on resume.
//!
//! Owns: the segment file format and the segment directory (`<job>/replay/`). Each checkpoint
//! appends one segment holding the transitions inserted since the previous one, so a checkpoint
//! writes only what is new; segments whose transitions have all left the FIFO are deleted. A
//! segment stores every distinct observation row once (an agent's next observation is usually
//! the observation of its following transition) as f16, then per transition two row indices,
//! the action, reward, terminal flag, map id, (format 2) the steps it spans and (format 3, only
//! for a replay holding oracle labels) the IDM label, NaN where a row has none; format 1
//! segments (one-step transitions) and 2 are still read, and a replay without labels still
//! writes format 2. A CRC-32 closes the file, which is written to
//! a temporary name and renamed, so a crash leaves whole segments only. What a crash loses:
//! the transitions since the last checkpoint, which the job's counters (written after the
//! segment) do not count either, so workers collect them again. Must not: know about jobs,
//! networks or the service; hold the replay's lock while writing (callers snapshot first).

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use half::f16;

use crate::replay::{Replay, ReplayError, Stored};

const MAGIC: &[u8; 8] = b"SFREPLAY";
const VERSION: u32 = 2;
/// Format 2 plus each transition's oracle label (`act_dim` f32, NaN for none).
const VERSION_LABELLED: u32 = 3;
/// The first format: one-step transitions, no per-transition step counts.
const VERSION_ONE_STEP: u32 = 1;

#[derive(Debug, thiserror::Error)]
pub enum ReplayStoreError {
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("replay segment {path}: {reason}")]
    Corrupt { path: String, reason: String },
    #[error("replay segment {path} holds {got} (obs floats, action dims); the job has {want:?}")]
    Shape { path: String, got: String, want: (usize, usize) },
    /// The replay refused one of the segment's transitions (a non-finite value, a wrong shape).
    #[error("replay segment {path}: {source}")]
    Refused { path: String, source: ReplayError },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ReplayStoreError + '_ {
    move |source| ReplayStoreError::Io { path: path.display().to_string(), source }
}

/// A fast non-cryptographic hash of a row's bits (FNV-style over 64-bit words): SipHash made a
/// full snapshot of 10^6 transitions hash-bound. Collisions only cost a comparison.
fn row_hash(row: &[f16]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for c in row.chunks(4) {
        let w =
            c.iter().enumerate().fold(0u64, |w, (i, v)| w | (u64::from(v.to_bits()) << (16 * i)));
        h = (h ^ w).wrapping_mul(0x0000_0100_0000_01b3);
        h ^= h >> 29;
    }
    h
}

/// Transitions `[first, first + count)` of a replay, observations deduplicated.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Segment {
    pub first: u64,
    pub obs_len: usize,
    pub act_dim: usize,
    /// Distinct observation rows, `rows x obs_len`.
    pub rows: Vec<f16>,
    pub obs_row: Vec<u32>,
    pub next_row: Vec<u32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub terminals: Vec<bool>,
    pub map_ids: Vec<u32>,
    /// Decision steps each transition spans.
    pub steps: Vec<u8>,
    /// `len x act_dim` oracle labels (NaN: none), or empty when the replay holds none.
    pub oracle: Vec<f32>,
}

impl Segment {
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// The transitions the replay holds from insertion number `from` (or its oldest, if later)
    /// to its newest. Run under the replay's lock; it copies and hashes, no IO.
    pub fn snapshot(r: &Replay, from: u64) -> Self {
        let first = from.max(r.oldest());
        let (ol, ad) = (r.obs_len(), r.act_dim());
        let mut s = Segment { first, obs_len: ol, act_dim: ad, ..Default::default() };
        let mut index: HashMap<u64, Vec<u32>> = HashMap::new();
        let mut row_of = |rows: &mut Vec<f16>, row: &[f16]| -> u32 {
            let bucket = index.entry(row_hash(row)).or_default();
            for &k in bucket.iter() {
                let at = k as usize * ol;
                if rows[at..at + ol].iter().zip(row).all(|(a, b)| a.to_bits() == b.to_bits()) {
                    return k;
                }
            }
            let k = (rows.len() / ol) as u32;
            rows.extend_from_slice(row);
            bucket.push(k);
            k
        };
        let labelled = r.is_labelled();
        for k in first..r.inserted() {
            let Some(t) = r.get(k) else { continue };
            if labelled {
                match t.oracle.len() {
                    0 => s.oracle.extend(std::iter::repeat_n(f32::NAN, ad)),
                    _ => s.oracle.extend_from_slice(t.oracle),
                }
            }
            let o = row_of(&mut s.rows, t.obs);
            let n = row_of(&mut s.rows, t.next_obs);
            s.obs_row.push(o);
            s.next_row.push(n);
            s.actions.extend_from_slice(t.action);
            s.rewards.push(t.reward);
            s.terminals.push(t.terminal);
            s.map_ids.push(t.map_id);
            s.steps.push(t.steps);
        }
        s
    }

    /// The bytes of the segment file (CRC-32 last).
    pub fn encode(&self) -> Vec<u8> {
        let rows = self.rows.len() / self.obs_len.max(1);
        let mut b =
            Vec::with_capacity(48 + self.rows.len() * 2 + self.len() * (17 + 4 * self.act_dim));
        b.extend_from_slice(MAGIC);
        let version = if self.oracle.is_empty() { VERSION } else { VERSION_LABELLED };
        for v in [version, self.obs_len as u32, self.act_dim as u32] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&self.first.to_le_bytes());
        b.extend_from_slice(&(self.len() as u64).to_le_bytes());
        b.extend_from_slice(&(rows as u64).to_le_bytes());
        self.rows.iter().for_each(|v| b.extend_from_slice(&v.to_bits().to_le_bytes()));
        self.obs_row
            .iter()
            .chain(&self.next_row)
            .for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
        self.actions
            .iter()
            .chain(&self.rewards)
            .for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
        b.extend(self.terminals.iter().map(|&t| t as u8));
        self.map_ids.iter().for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
        b.extend_from_slice(&self.steps);
        self.oracle.iter().for_each(|v| b.extend_from_slice(&v.to_le_bytes()));
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }

    /// Parses and checks a segment file's bytes (`path` names it in errors).
    pub fn decode(bytes: &[u8], path: &Path) -> Result<Self, ReplayStoreError> {
        let bad = |reason: &str| ReplayStoreError::Corrupt {
            path: path.display().to_string(),
            reason: reason.to_string(),
        };
        if bytes.len() < 48 || &bytes[..8] != MAGIC {
            return Err(bad("not a socialflow replay segment"));
        }
        let (body, tail) = bytes.split_at(bytes.len() - 4);
        if crc32fast::hash(body)
            != u32::from_le_bytes(tail.try_into().map_err(|_| bad("truncated"))?)
        {
            return Err(bad("checksum mismatch (a torn or altered file)"));
        }
        let mut at = 8;
        let mut take = |n: usize| -> Result<&[u8], ReplayStoreError> {
            let s = body.get(at..at + n).ok_or_else(|| bad("truncated"))?;
            at += n;
            Ok(s)
        };
        let u32_at = |s: &[u8]| u32::from_le_bytes([s[0], s[1], s[2], s[3]]);
        let u64_of =
            |s: &[u8]| u64::from_le_bytes([s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]]);
        let version = u32_at(take(4)?);
        if !(VERSION_ONE_STEP..=VERSION_LABELLED).contains(&version) {
            return Err(bad(&format!(
                "format version {version}; this build reads {VERSION_ONE_STEP} to {VERSION_LABELLED}"
            )));
        }
        let obs_len = u32_at(take(4)?) as usize;
        let act_dim = u32_at(take(4)?) as usize;
        let first = u64_of(take(8)?);
        let count = usize::try_from(u64_of(take(8)?)).map_err(|_| bad("count"))?;
        let rows = usize::try_from(u64_of(take(8)?)).map_err(|_| bad("rows"))?;
        let need = rows
            .checked_mul(obs_len)
            .and_then(|r| r.checked_mul(2))
            .ok_or_else(|| bad("row count overflows"))?;
        let rows_v: Vec<f16> = take(need)?
            .chunks_exact(2)
            .map(|c| f16::from_bits(u16::from_le_bytes([c[0], c[1]])))
            .collect();
        let u32s = |s: &[u8]| s.chunks_exact(4).map(u32_at).collect::<Vec<u32>>();
        let f32s = |s: &[u8]| {
            s.chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect::<Vec<f32>>()
        };
        let n4 = count.checked_mul(4).ok_or_else(|| bad("count overflows"))?;
        let obs_row = u32s(take(n4)?);
        let next_row = u32s(take(n4)?);
        let actions = f32s(take(n4.checked_mul(act_dim).ok_or_else(|| bad("count overflows"))?)?);
        let rewards = f32s(take(n4)?);
        let terminals: Vec<bool> = take(count)?.iter().map(|&t| t != 0).collect();
        let map_ids = u32s(take(n4)?);
        let steps =
            if version == VERSION_ONE_STEP { vec![1; count] } else { take(count)?.to_vec() };
        if steps.contains(&0) {
            return Err(bad("a transition spanning 0 steps"));
        }
        let oracle = if version == VERSION_LABELLED {
            f32s(take(n4.checked_mul(act_dim).ok_or_else(|| bad("count overflows"))?)?)
        } else {
            Vec::new()
        };
        if at != body.len() {
            return Err(bad("trailing bytes"));
        }
        if obs_row.iter().chain(&next_row).any(|&r| r as usize >= rows) {
            return Err(bad("a row index past the rows"));
        }
        Ok(Segment {
            first,
            obs_len,
            act_dim,
            rows: rows_v,
            obs_row,
            next_row,
            actions,
            rewards,
            terminals,
            map_ids,
            steps,
            oracle,
        })
    }

    /// Pushes transitions with insertion numbers below `upto` into `r` (in order).
    /// Returns how many it pushed.
    pub fn push_into(&self, r: &mut Replay, upto: u64) -> Result<u64, ReplayError> {
        let (ol, ad) = (self.obs_len, self.act_dim);
        let mut n = 0;
        for i in 0..self.len() {
            let k = self.first + i as u64;
            if k < r.inserted() {
                continue;
            }
            if k >= upto {
                break;
            }
            let row = |j: u32| &self.rows[j as usize * ol..(j as usize + 1) * ol];
            r.push_f16(Stored {
                obs: row(self.obs_row[i]),
                next_obs: row(self.next_row[i]),
                action: &self.actions[i * ad..(i + 1) * ad],
                reward: self.rewards[i],
                terminal: self.terminals[i],
                steps: self.steps[i],
                map_id: self.map_ids[i],
                // NaN: the row was stored without a label.
                oracle: self
                    .oracle
                    .get(i * ad..(i + 1) * ad)
                    .filter(|l| !l.iter().any(|x| x.is_nan()))
                    .unwrap_or(&[]),
            })?;
            n += 1;
        }
        Ok(n)
    }
}

/// A job's segment directory.
pub struct ReplayStore {
    dir: PathBuf,
}

/// One segment on disk: `seg-<first>-<end>.bin`, transitions `[first, end)`.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct SegmentFile {
    pub first: u64,
    pub end: u64,
    pub path: PathBuf,
}

impl ReplayStore {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }

    /// Segments on disk in order (temporary files of an interrupted write are ignored).
    pub fn segments(&self) -> Result<Vec<SegmentFile>, ReplayStoreError> {
        if !self.dir.exists() {
            return Ok(Vec::new());
        }
        let mut out = Vec::new();
        for e in std::fs::read_dir(&self.dir).map_err(io(&self.dir))? {
            let path = e.map_err(io(&self.dir))?.path();
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
            let Some(range) = name.strip_prefix("seg-").and_then(|r| r.strip_suffix(".bin")) else {
                continue;
            };
            let Some((a, b)) = range.split_once('-') else { continue };
            if let (Ok(first), Ok(end)) = (a.parse(), b.parse()) {
                out.push(SegmentFile { first, end, path });
            }
        }
        out.sort();
        Ok(out)
    }

    /// Where the next segment starts: the end of the newest one on disk (0 if none).
    pub fn next(&self) -> Result<u64, ReplayStoreError> {
        Ok(self.segments()?.last().map_or(0, |s| s.end))
    }

    /// Writes `seg` (if it holds anything) atomically, then deletes segments that end at or
    /// before `oldest` (every transition in them has left the FIFO). Returns bytes written.
    pub fn append(&self, seg: &Segment, oldest: u64) -> Result<u64, ReplayStoreError> {
        std::fs::create_dir_all(&self.dir).map_err(io(&self.dir))?;
        let mut written = 0;
        if !seg.is_empty() {
            let end = seg.first + seg.len() as u64;
            let path = self.dir.join(format!("seg-{:020}-{:020}.bin", seg.first, end));
            let tmp = path.with_extension("tmp");
            let bytes = seg.encode();
            let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
            f.write_all(&bytes).map_err(io(&tmp))?;
            f.sync_all().map_err(io(&tmp))?;
            std::fs::rename(&tmp, &path).map_err(io(&path))?;
            written = bytes.len() as u64;
        }
        for s in self.segments()? {
            if s.end <= oldest {
                std::fs::remove_file(&s.path).map_err(io(&s.path))?;
            }
        }
        Ok(written)
    }

    /// Reads the segments back into a new replay numbered like the job: the newest `capacity`
    /// of the transitions below `upto` (the job's counted transitions). Returns it with the
    /// insertion number the next [`ReplayStore::append`] must start from. Segments reaching
    /// past `upto` (written just before a crash; those transitions will come again) are deleted
    /// and their counted part is written again by the next append. If transitions are missing
    /// (a lost segment, persistence turned on mid-job), what was read is kept, renumbered to end
    /// at `upto`, and the directory starts over with a full write.
    pub fn restore(
        &self,
        capacity: usize,
        obs_len: usize,
        act_dim: usize,
        upto: u64,
    ) -> Result<(Replay, u64), ReplayStoreError> {
        let mut r = self.read(capacity, obs_len, act_dim, upto)?;
        let segs = self.segments()?;
        if r.inserted() < upto {
            r.renumber(upto);
            for s in &segs {
                std::fs::remove_file(&s.path).map_err(io(&s.path))?;
            }
            let oldest = r.oldest();
            return Ok((r, oldest));
        }
        let mut next = upto;
        for s in segs.iter().filter(|s| s.end > upto) {
            next = next.min(s.first.max(r.oldest()));
            std::fs::remove_file(&s.path).map_err(io(&s.path))?;
        }
        Ok((r, next))
    }

    /// Reads the newest `capacity` of the transitions below `upto` into a new replay numbered
    /// like the job, leaving the directory as it is (another job's replay, carried by a
    /// continuation). A replay that holds fewer than were counted (a lost segment) ends below
    /// `upto`: its [`Replay::inserted`] says where.
    pub fn read(
        &self,
        capacity: usize,
        obs_len: usize,
        act_dim: usize,
        upto: u64,
    ) -> Result<Replay, ReplayStoreError> {
        let segs = self.segments()?;
        // The window: the newest `capacity` transitions the segments hold below `upto`.
        let reach =
            segs.iter().filter(|s| s.first < upto).map(|s| s.end.min(upto)).max().unwrap_or(upto);
        let start = reach.saturating_sub(capacity as u64);
        let first =
            segs.iter().find(|s| s.end > start).map_or(reach, |s| s.first.max(start)).min(reach);
        let mut r = Replay::numbered_from(capacity, obs_len, act_dim, first);
        for s in segs.iter().filter(|s| s.end > first) {
            if s.first > r.inserted() || r.inserted() >= reach {
                break;
            }
            let bytes = std::fs::read(&s.path).map_err(io(&s.path))?;
            let seg = Segment::decode(&bytes, &s.path)?;
            if (seg.obs_len, seg.act_dim) != (obs_len, act_dim) {
                return Err(ReplayStoreError::Shape {
                    path: s.path.display().to_string(),
                    got: format!("({}, {})", seg.obs_len, seg.act_dim),
                    want: (obs_len, act_dim),
                });
            }
            seg.push_into(&mut r, reach).map_err(|source| ReplayStoreError::Refused {
                path: s.path.display().to_string(),
                source,
            })?;
        }
        Ok(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::replay::Transition;

    /// A replay of agents whose next observation is their following one (as rollouts give).
    fn filled(capacity: usize, n: u64) -> Replay {
        let mut r = Replay::new(capacity, 4, 2);
        for k in 0..n {
            let o = [k as f32, 0.5, -0.25, (k % 7) as f32];
            let nx = [(k + 1) as f32, 0.5, -0.25, ((k + 1) % 7) as f32];
            r.push(Transition {
                obs: &o,
                action: &[0.1, -(k as f32) / 100.0],
                reward: k as f32,
                next_obs: &nx,
                terminal: k % 5 == 4,
                steps: 1 + (k % 3) as u8,
                map_id: (k % 3) as u32,
                oracle: &[],
            })
            .expect("push");
        }
        r
    }

    fn same(a: &Replay, b: &Replay) {
        assert_eq!((a.oldest(), a.inserted(), a.len()), (b.oldest(), b.inserted(), b.len()));
        for k in a.oldest()..a.inserted() {
            assert_eq!(a.get(k), b.get(k), "transition {k}");
        }
    }

    fn scratch(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("sf-replay-store-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// A replay with oracle labels on some rows writes format 3 and reads back with every
    /// row's label, or its lack of one; a replay without labels still writes format 2.
    #[test]
    fn oracle_labels_round_trip_through_segments() {
        let plain = filled(50, 20);
        let seg = Segment::snapshot(&plain, 0);
        assert_eq!(u32::from_le_bytes(seg.encode()[8..12].try_into().expect("4 bytes")), VERSION);
        let mut r = Replay::new(50, 4, 2);
        for k in 0..20u64 {
            let o = [k as f32, 0.0, 0.0, 0.0];
            let label = [0.01 * k as f32, -0.5];
            r.push(Transition {
                obs: &o,
                action: &[0.0, 0.0],
                reward: k as f32,
                next_obs: &o,
                terminal: false,
                steps: 1,
                map_id: 0,
                // Rows 0-4 come before the first label; every third row after has none.
                oracle: if k < 5 || k % 3 == 0 { &[] } else { &label },
            })
            .expect("push");
        }
        let bytes = Segment::snapshot(&r, 0).encode();
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes")), VERSION_LABELLED);
        let seg = Segment::decode(&bytes, Path::new("labelled.bin")).expect("decode");
        let mut back = Replay::new(50, 4, 2);
        assert_eq!(seg.push_into(&mut back, u64::MAX).expect("push_into"), 20);
        same(&r, &back);
        assert_eq!(back.get(7).expect("held").oracle, &[0.07f32, -0.5][..]);
        assert!(
            back.get(6).expect("held").oracle.is_empty()
                && back.get(2).expect("held").oracle.is_empty()
        );
    }

    #[test]
    fn segments_round_trip_and_store_shared_rows_once() {
        let r = filled(100, 60);
        let seg = Segment::snapshot(&r, 0);
        assert_eq!(seg.len(), 60);
        // 60 transitions chain 61 distinct observations.
        assert_eq!(seg.rows.len() / 4, 61);
        let back = Segment::decode(&seg.encode(), Path::new("mem")).expect("decode");
        assert_eq!(back, seg);
        let mut bytes = seg.encode();
        bytes[60] ^= 1;
        assert!(matches!(
            Segment::decode(&bytes, Path::new("mem")),
            Err(ReplayStoreError::Corrupt { .. })
        ));
        assert!(Segment::decode(&bytes[..30], Path::new("mem")).is_err());
    }

    /// A job stored before n-step returns (format 1, no step counts) resumes with one-step
    /// transitions; a step count of 0 is a corrupt segment.
    #[test]
    fn format_one_segments_are_read_as_one_step_transitions() {
        let mut seg = Segment::snapshot(&filled(100, 20), 0);
        seg.steps = vec![1; seg.len()];
        let v2 = seg.encode();
        let mut v1 = v2[..v2.len() - 4 - seg.len()].to_vec();
        v1[8..12].copy_from_slice(&VERSION_ONE_STEP.to_le_bytes());
        let crc = crc32fast::hash(&v1);
        v1.extend_from_slice(&crc.to_le_bytes());
        assert_eq!(Segment::decode(&v1, Path::new("v1")).expect("format 1"), seg);
        seg.steps[3] = 0;
        let e = Segment::decode(&seg.encode(), Path::new("zero")).expect_err("zero steps");
        assert!(e.to_string().contains("0 steps"), "{e}");
    }

    #[test]
    fn checkpoints_append_segments_and_a_restore_rebuilds_the_fifo() {
        let dir = scratch("fifo");
        let store = ReplayStore::new(&dir);
        let mut r = Replay::new(50, 4, 2);
        let mut k = 0u64;
        // Four checkpoints of 30 transitions into a FIFO of 50: old segments are deleted.
        for _ in 0..4 {
            for _ in 0..30 {
                let o = [k as f32, 1.0, 0.0, 0.0];
                let nx = [(k + 1) as f32, 1.0, 0.0, 0.0];
                r.push(Transition {
                    obs: &o,
                    action: &[0.0, 1.0],
                    reward: 1.0,
                    next_obs: &nx,
                    terminal: false,
                    steps: 1,
                    map_id: 0,
                    oracle: &[],
                })
                .expect("push");
                k += 1;
            }
            let seg = Segment::snapshot(&r, store.next().expect("next"));
            assert_eq!(seg.len(), 30);
            store.append(&seg, r.oldest()).expect("append");
        }
        assert_eq!(
            store.segments().expect("list").iter().map(|s| (s.first, s.end)).collect::<Vec<_>>(),
            vec![(60, 90), (90, 120)]
        );
        let (back, next) = store.restore(50, 4, 2, 120).expect("restore");
        same(&r, &back);
        assert_eq!(next, 120);
        // Another job reads it (a carried replay): the newest it has room for, and the
        // directory stays as it is, even when asked for more than it holds.
        let before = store.segments().expect("list");
        let carried = store.read(20, 4, 2, 120).expect("read");
        assert_eq!((carried.oldest(), carried.inserted()), (100, 120));
        assert_eq!(carried.get(110), r.get(110));
        let short = store.read(50, 4, 2, 150).expect("read past the end");
        assert_eq!((short.oldest(), short.inserted()), (70, 120));
        assert_eq!(store.segments().expect("list"), before);
        // A job counted only 100 of them when it stopped: the segment reaching past is deleted
        // and its counted part is to be written again.
        let (back, next) = store.restore(50, 4, 2, 100).expect("restore");
        assert_eq!((back.oldest(), back.inserted(), next), (60, 100, 90));
        assert_eq!(back.get(70), r.get(70));
        assert!(store.segments().expect("list").iter().all(|s| s.first < 100));
        // A shape change is an error, not a silent mix.
        assert!(matches!(store.restore(50, 5, 2, 100), Err(ReplayStoreError::Shape { .. })));
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A continuation's carried replay (`train.init_replay`): the source's transitions renumbered
    /// `0..carried`, the job's own after them, all written to the job's own directory from 0,
    /// comes back whole on resume (up to `carried + own`).
    #[test]
    fn a_carried_replay_is_written_and_restored_as_the_jobs_own() {
        let (src_dir, dir) = (scratch("carry-src"), scratch("carry-own"));
        let src = ReplayStore::new(&src_dir);
        let theirs = filled(100, 70);
        src.append(&Segment::snapshot(&theirs, 0), theirs.oldest()).expect("source");
        let mut r = src.read(50, 4, 2, 70).expect("carried");
        let carried = r.len() as u64;
        r.renumber(carried);
        assert_eq!((carried, r.oldest(), r.inserted()), (50, 0, 50));
        assert_eq!(r.get(0).map(|t| t.reward), theirs.get(20).map(|t| t.reward));
        let o = [9.0, 9.0, 9.0, 9.0];
        for _ in 0..10 {
            r.push(Transition {
                obs: &o,
                action: &[0.0, 0.0],
                reward: -1.0,
                next_obs: &o,
                terminal: false,
                steps: 1,
                map_id: 0,
                oracle: &[],
            })
            .expect("own");
        }
        let own = ReplayStore::new(&dir);
        own.append(&Segment::snapshot(&r, 0), r.oldest()).expect("first checkpoint");
        let (back, next) = own.restore(50, 4, 2, carried + 10).expect("resume");
        same(&r, &back);
        assert_eq!(next, 60);
        assert_eq!(src.segments().expect("source").len(), 1, "the source is left as it was");
        let _ = std::fs::remove_dir_all(&src_dir);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_restored_fifo_wraps_like_the_original() {
        let dir = scratch("wrap");
        let store = ReplayStore::new(&dir);
        let r = filled(40, 97);
        store.append(&Segment::snapshot(&r, 0), r.oldest()).expect("append");
        let (back, next) = store.restore(40, 4, 2, 97).expect("restore");
        same(&r, &back);
        assert_eq!(next, 97);
        // A job that counts more than the segments hold keeps what they hold, renumbered, and
        // starts the directory over.
        let (short, next) = store.restore(40, 4, 2, 150).expect("restore");
        assert_eq!((short.len(), short.inserted(), next), (40, 150, 110));
        assert_eq!(short.get(149).map(|t| t.reward), r.get(96).map(|t| t.reward));
        assert!(store.segments().expect("list").is_empty());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
