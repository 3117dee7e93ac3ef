//! TensorBoard event files: scalar summaries that `tensorboard --logdir` (and W&B's importer)
//! read.
//!
//! Owns: [`EventWriter`] and the few messages of TensorBoard's `event.proto` / `summary.proto`
//! it writes, as prost structs with TensorBoard's field numbers (`Event.wall_time = 1`,
//! `step = 2`, `file_version = 3`, `summary = 5`; `Summary.value = 1`; `Summary.Value.tag = 1`,
//! `simple_value = 2`), framed as TFRecords (little-endian u64 length, masked CRC-32C of the
//! length, payload, masked CRC-32C of the payload). Must not: know what the scalars mean
//! (callers name them) or write anything but whole records.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use prost::Message;

/// `tensorboard.Event` (the fields socialflow writes).
#[derive(Clone, PartialEq, prost::Message)]
pub struct Event {
    #[prost(double, tag = "1")]
    pub wall_time: f64,
    #[prost(int64, tag = "2")]
    pub step: i64,
    #[prost(string, optional, tag = "3")]
    pub file_version: Option<String>,
    #[prost(message, optional, tag = "5")]
    pub summary: Option<Summary>,
}

/// `tensorboard.Summary`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Summary {
    #[prost(message, repeated, tag = "1")]
    pub value: Vec<SummaryValue>,
}

/// `tensorboard.Summary.Value` with a `simple_value`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct SummaryValue {
    #[prost(string, tag = "1")]
    pub tag: String,
    #[prost(float, optional, tag = "2")]
    pub simple_value: Option<f32>,
}

fn masked_crc(bytes: &[u8]) -> u32 {
    let c = crc32c::crc32c(bytes);
    (c.rotate_right(15)).wrapping_add(0xa282_ead8)
}

/// One TFRecord around `payload`.
pub fn record(payload: &[u8]) -> Vec<u8> {
    let len = (payload.len() as u64).to_le_bytes();
    let mut out = Vec::with_capacity(payload.len() + 16);
    out.extend_from_slice(&len);
    out.extend_from_slice(&masked_crc(&len).to_le_bytes());
    out.extend_from_slice(payload);
    out.extend_from_slice(&masked_crc(payload).to_le_bytes());
    out
}

/// What is wrong with a TFRecord stream, and at which byte its record starts.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("truncated record {what} at byte {at}")]
    Truncated { what: &'static str, at: usize },
    #[error("{what} CRC mismatch in the record at byte {at}")]
    Crc { what: &'static str, at: usize },
    #[error("record at byte {at} is longer than this machine can address")]
    Length { at: usize },
    #[error("event in the record at byte {at}: {source}")]
    Event { at: usize, source: prost::DecodeError },
}

/// Parses TFRecords back into events, checking both CRCs (tests, and a reader for tools).
pub fn read_events(bytes: &[u8]) -> Result<Vec<Event>, RecordError> {
    let mut out = Vec::new();
    let mut at = 0;
    let cut = |what, at| move || RecordError::Truncated { what, at };
    while at < bytes.len() {
        let head = bytes.get(at..at + 12).ok_or_else(cut("header", at))?;
        let (len_bytes, len_crc) = head.split_at(8);
        if masked_crc(len_bytes).to_le_bytes() != len_crc {
            return Err(RecordError::Crc { what: "length", at });
        }
        let len_u64 =
            u64::from_le_bytes(len_bytes.try_into().map_err(|_| RecordError::Length { at })?);
        let len = usize::try_from(len_u64).map_err(|_| RecordError::Length { at })?;
        let end = at
            .checked_add(16)
            .and_then(|e| e.checked_add(len))
            .ok_or(RecordError::Length { at })?;
        let payload = bytes.get(at + 12..end - 4).ok_or_else(cut("payload", at))?;
        let crc = bytes.get(end - 4..end).ok_or_else(cut("CRC", at))?;
        if masked_crc(payload).to_le_bytes() != crc {
            return Err(RecordError::Crc { what: "payload", at });
        }
        out.push(Event::decode(payload).map_err(|source| RecordError::Event { at, source })?);
        at = end;
    }
    Ok(out)
}

/// Appends scalar events to one `events.out.tfevents.<secs>.<host>` file in a directory.
/// Each call to [`EventWriter::scalars`] writes and flushes whole records, so a crash loses at
/// most the call in progress; a restarted job opens a new file beside the old ones, which
/// TensorBoard reads together.
pub struct EventWriter {
    path: PathBuf,
    out: BufWriter<File>,
}

fn now_s() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

impl EventWriter {
    /// Creates the directory and a new event file with its `brain.Event:2` header.
    pub fn create(dir: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let host = std::fs::read_to_string("/etc/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "socialflow".into());
        let t = now_s();
        let mut name = format!("events.out.tfevents.{}.{host}", t as u64);
        // Two writers in the same second (a quick restart) get distinct files.
        let mut k = 0;
        while dir.join(&name).exists() {
            k += 1;
            name = format!("events.out.tfevents.{}.{host}.{k}", t as u64);
        }
        let path = dir.join(name);
        let mut w = Self { out: BufWriter::new(File::create(&path)?), path };
        let head = Event {
            wall_time: t,
            step: 0,
            file_version: Some("brain.Event:2".into()),
            summary: None,
        };
        w.write(&head)?;
        Ok(w)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn write(&mut self, e: &Event) -> std::io::Result<()> {
        self.out.write_all(&record(&e.encode_to_vec()))?;
        self.out.flush()
    }

    /// One event at `step` holding every finite `(tag, value)`.
    pub fn scalars(&mut self, step: u64, values: &[(&str, f64)]) -> std::io::Result<()> {
        let value: Vec<SummaryValue> = values
            .iter()
            .filter(|(_, v)| v.is_finite())
            .map(|(t, v)| SummaryValue { tag: t.to_string(), simple_value: Some(*v as f32) })
            .collect();
        if value.is_empty() {
            return Ok(());
        }
        let e = Event {
            wall_time: now_s(),
            step: step as i64,
            file_version: None,
            summary: Some(Summary { value }),
        };
        self.write(&e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[allow(clippy::manual_rotate)]
    fn crc32c_matches_the_tfrecord_reference() {
        // CRC-32C("123456789") = 0xE3069283 (the Castagnoli check value).
        assert_eq!(crc32c::crc32c(b"123456789"), 0xE306_9283);
        // Masking as TensorFlow's crc32c::Mask writes it (the reference, not our rotate).
        let c = 0xE306_9283u32;
        assert_eq!(masked_crc(b"123456789"), ((c >> 15) | (c << 17)).wrapping_add(0xa282_ead8));
    }

    #[test]
    fn events_round_trip_and_damage_is_detected() {
        let dir = std::env::temp_dir().join(format!("sf-tb-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut w = EventWriter::create(&dir).expect("writer");
        w.scalars(10, &[("train/success", 0.5), ("train/nan", f64::NAN)]).expect("write");
        w.scalars(20, &[("train/success", 0.75)]).expect("write");
        let bytes = std::fs::read(w.path()).expect("read");
        let ev = read_events(&bytes).expect("parse");
        assert_eq!(ev.len(), 3);
        assert_eq!(ev[0].file_version.as_deref(), Some("brain.Event:2"));
        let s = ev[1].summary.as_ref().expect("summary");
        assert_eq!(
            (ev[1].step, s.value.len(), s.value[0].tag.as_str(), s.value[0].simple_value),
            (10, 1, "train/success", Some(0.5))
        );
        let mut bad = bytes.clone();
        let n = bad.len();
        bad[n - 6] ^= 0xff;
        assert!(read_events(&bad).is_err());
        assert!(read_events(&bytes[..bytes.len() - 1]).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
