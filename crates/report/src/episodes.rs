//! The evaluation's result files: one row per evaluated episode (`episodes.csv`, read gzipped as
//! `episodes.csv.gz` too: committed results are stored so) and the grid's metadata (`meta.json`).
//!
//! Owns: [`EpisodeRow`] and its CSV line format, the validating reader [`read_episodes`] (a bad
//! line is named by its number and field), [`EpisodesWriter`] (whole cells appended and synced,
//! so a cell is stored whole or not at all), [`Meta`] and [`read_meta`]. Must not: compute
//! statistics or draw anything (the report does).
//!
//! Three formats are read: [`EPISODES_HEADER`] (with the lane-change share and the closed-road
//! share, written since 2026-11-29), [`EPISODES_HEADER_V2`] (with the lane-change share only,
//! 2026-11-28) and [`EPISODES_HEADER_V1`] (neither: older results). A file keeps the format it
//! was started in, so appending to an older file never mixes rows.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sf_job::eval::{Cell, EvalConfig, EvalEpisode};

pub const EPISODES_HEADER: &str =
    "experiment,ego,flow,scenario,svo_deg,vehicles,case,seed,success,safety,speed,collision,lane_change,road_closed";

/// The header of files written before the closed-road share was recorded (2026-11-28).
pub const EPISODES_HEADER_V2: &str =
    "experiment,ego,flow,scenario,svo_deg,vehicles,case,seed,success,safety,speed,collision,lane_change";

/// The header of files written before the lane-change share was recorded.
pub const EPISODES_HEADER_V1: &str =
    "experiment,ego,flow,scenario,svo_deg,vehicles,case,seed,success,safety,speed,collision";

/// Which of the three line formats a file holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// 14 fields, the last two the lane-change and closed-road shares (each empty when not
    /// recorded).
    Current,
    /// 13 fields, the last the lane-change share.
    V2,
    /// 12 fields, no lane-change share.
    V1,
}

impl Format {
    fn of_header(h: &str) -> Option<Self> {
        match h {
            EPISODES_HEADER => Some(Self::Current),
            EPISODES_HEADER_V2 => Some(Self::V2),
            EPISODES_HEADER_V1 => Some(Self::V1),
            _ => None,
        }
    }

    fn header(self) -> &'static str {
        match self {
            Self::Current => EPISODES_HEADER,
            Self::V2 => EPISODES_HEADER_V2,
            Self::V1 => EPISODES_HEADER_V1,
        }
    }

    /// Fields per line: the header's.
    fn fields(self) -> usize {
        self.header().split(',').count()
    }
}

/// One evaluated episode: the cell it belongs to and what the episode measured. `cell.ego` is
/// empty when the flow was evaluated on its own.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeRow {
    pub cell: Cell,
    pub ep: EvalEpisode,
    /// Which replicate of the graph (trained from scratch with its own seed) the episode
    /// belongs to when several result sets are reported together; 0 in a single set. Not a
    /// column of `episodes.csv`: a results directory holds one replicate.
    pub replicate: u32,
}

impl EpisodeRow {
    /// An evaluated episode of `cell`.
    pub fn new(cell: &Cell, e: &EvalEpisode) -> Self {
        Self { cell: cell.clone(), ep: *e, replicate: 0 }
    }

    /// The cell the episode belongs to.
    pub fn cell(&self) -> Cell {
        self.cell.clone()
    }

    /// The row as a line of [`EPISODES_HEADER`]'s format.
    pub fn to_csv(&self) -> String {
        self.to_csv_in(Format::Current)
    }

    /// The row as a line of `format` (V2 drops the closed-road share, V1 the lane-change share
    /// too).
    pub fn to_csv_in(&self, format: Format) -> String {
        let (c, e) = (&self.cell, &self.ep);
        let o = |v: Option<String>| v.unwrap_or_default();
        let line = format!(
            "{},{},{},{},{},{},{},{},{},{},{},{}",
            c.experiment,
            c.ego,
            c.flow,
            c.scenario,
            o(c.svo_deg.map(|v| v.to_string())),
            o(c.vehicles.map(|v| v.to_string())),
            e.case,
            e.seed,
            e.scores.success,
            e.scores.safety,
            e.scores.speed,
            e.collision
        );
        let lane_change = o(e.lane_change.map(|v| v.to_string()));
        match format {
            Format::Current => {
                format!("{line},{lane_change},{}", o(e.road_closed.map(|v| v.to_string())))
            }
            Format::V2 => format!("{line},{lane_change}"),
            Format::V1 => line,
        }
    }

    fn parse(line: &str, format: Format) -> Result<Self, RowError> {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != format.fields() {
            return Err(RowError::Fields { found: f.len(), expected: format.fields() });
        }
        let int =
            |i: usize, what: &'static str| RowError::NotAnInteger { what, text: f[i].to_string() };
        let num = |i: usize, what: &'static str| {
            let v = f[i]
                .parse::<f32>()
                .map_err(|_| RowError::NotANumber { what, text: f[i].to_string() })?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(RowError::NotFinite { what })
            }
        };
        // A share that may be unrecorded: an empty or absent field is `None`.
        let share = |i: usize, what: &'static str| match f.get(i) {
            None | Some(&"") => Ok(None),
            Some(_) => num(i, what).map(Some),
        };
        let opt = |i: usize, what: &'static str| {
            if f[i].is_empty() {
                Ok(None)
            } else {
                f[i].parse::<u64>().map(Some).map_err(|_| int(i, what))
            }
        };
        let cell = Cell {
            experiment: f[0].into(),
            ego: f[1].into(),
            flow: f[2].into(),
            scenario: f[3].into(),
            svo_deg: opt(4, "svo_deg")?.map(|v| v as u32),
            vehicles: opt(5, "vehicles")?.map(|v| v as usize),
        };
        let ep = EvalEpisode {
            case: f[6].parse().map_err(|_| int(6, "case"))?,
            seed: f[7].parse().map_err(|_| int(7, "seed"))?,
            scores: sf_job::Scores {
                success: num(8, "success")?,
                safety: num(9, "safety")?,
                speed: num(10, "speed")?,
            },
            collision: num(11, "collision")?,
            lane_change: share(12, "lane_change")?,
            road_closed: share(13, "road_closed")?,
        };
        Ok(Self { cell, ep, replicate: 0 })
    }
}

/// Why a line of `episodes.csv` does not parse.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RowError {
    #[error("{found} fields, expected {expected}")]
    Fields { found: usize, expected: usize },
    #[error("{what} `{text}` is not a number")]
    NotANumber { what: &'static str, text: String },
    #[error("{what} is not finite")]
    NotFinite { what: &'static str },
    #[error("{what} `{text}` is not an integer")]
    NotAnInteger { what: &'static str, text: String },
}

/// A results file that cannot be read or written, naming the file and what is wrong with it;
/// where the file system refused, its `io::Error` is the source (so a service can tell a full
/// disk from a bad file by type).
#[derive(Debug, thiserror::Error)]
#[error("{path}: {reason}")]
pub struct FileError {
    pub path: String,
    pub reason: String,
    #[source]
    pub io: Option<std::io::Error>,
}

/// A file whose content is wrong (no `io::Error` behind it).
pub(crate) fn file_err(path: &Path, reason: impl std::fmt::Display) -> FileError {
    FileError { path: path.display().to_string(), reason: reason.to_string(), io: None }
}

/// A file the file system would not read or write: the `io::Error` is kept as the source.
pub(crate) fn io_err(path: &Path, e: std::io::Error) -> FileError {
    FileError { path: path.display().to_string(), reason: e.to_string(), io: Some(e) }
}

/// The gzipped form of a stored result file: `episodes.csv` -> `episodes.csv.gz`.
pub fn gz_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".gz");
    PathBuf::from(name)
}

/// The gzipped file stored in place of `plain` (committed results are gzipped): `Some` when
/// `plain` is absent, names no `.gz` itself, and `plain.gz` exists. The one test of "stored
/// gzipped" that reading, finding and refusing to append share.
pub fn stored_gzipped(plain: &Path) -> Option<PathBuf> {
    let gz = gz_path(plain);
    (plain.extension().is_none_or(|e| e != "gz") && !plain.exists() && gz.exists()).then_some(gz)
}

/// Where a results directory keeps its episodes: `episodes.csv`, or `episodes.csv.gz` when only
/// that is stored; `episodes.csv` when neither exists.
pub fn episodes_file(dir: &Path) -> PathBuf {
    let plain = dir.join("episodes.csv");
    stored_gzipped(&plain).unwrap_or(plain)
}

/// A whole text file, gunzipped when its name ends in `.gz`.
fn read_text(path: &Path) -> Result<String, FileError> {
    use std::io::Read as _;
    let bytes = std::fs::read(path).map_err(|e| io_err(path, e))?;
    if path.extension().is_some_and(|e| e == "gz") {
        let mut text = String::new();
        flate2::read::GzDecoder::new(bytes.as_slice())
            .read_to_string(&mut text)
            .map_err(|e| io_err(path, e))?;
        Ok(text)
    } else {
        String::from_utf8(bytes).map_err(|e| file_err(path, format!("not UTF-8 text: {e}")))
    }
}

/// Reads `episodes.csv`, or `episodes.csv.gz` (gunzipped) when the path names it or when the plain
/// file is absent and the gzipped one is stored; a missing file is an empty result set.
pub fn read_episodes(path: &Path) -> Result<Vec<EpisodeRow>, FileError> {
    let path = stored_gzipped(path).unwrap_or_else(|| path.to_path_buf());
    if !path.exists() {
        return Ok(Vec::new());
    }
    let path = path.as_path();
    let text = read_text(path)?;
    let mut lines = text.lines();
    let format = match lines.next() {
        None => return Ok(Vec::new()),
        Some(h) => Format::of_header(h).ok_or_else(|| {
            file_err(
                path,
                format!("header `{h}` is neither `{EPISODES_HEADER}` nor `{EPISODES_HEADER_V1}`"),
            )
        })?,
    };
    lines
        .enumerate()
        .filter(|(_, l)| !l.is_empty())
        .map(|(i, l)| {
            EpisodeRow::parse(l, format).map_err(|e| file_err(path, format!("line {}: {e}", i + 2)))
        })
        .collect()
}

/// What the report needs to know besides the episodes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Meta {
    /// Ego name -> the flow (by name) it was trained in; its cell in that column is grey.
    pub trained_in: BTreeMap<String, String>,
    /// The ego the paper proposes (RARL/SocialCommAdv), compared by paired t-tests.
    pub ours: Option<String>,
    /// The IDM driver in the ego's seat (an ego of `job = "idm"`), which every trained ego is
    /// tested against.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub idm_ego: Option<String>,
    /// Flow and ego names in display order.
    pub flows: Vec<String>,
    pub egos: Vec<String>,
    pub cases: u32,
    pub seeds: u32,
    /// Experiments whose cells run another number of stored cases and seeds than the grid's
    /// (`[sizes]` of the eval config): experiment -> [cases, seeds].
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub sizes: BTreeMap<String, [u32; 2]>,
}

impl Meta {
    /// "20 stored cases x 2 seeds per cell; adversary: 200 x 2".
    pub fn sizes_text(&self) -> String {
        let mut t = format!("{} stored cases x {} seeds per cell", self.cases, self.seeds);
        for (e, [c, s]) in &self.sizes {
            t.push_str(&format!("; {e}: {c} x {s}"));
        }
        t
    }

    /// What a report of `cfg`'s grid needs to know.
    pub fn of(cfg: &EvalConfig) -> Self {
        Self {
            trained_in: cfg
                .egos
                .iter()
                .filter_map(|e| e.trained_in.clone().map(|t| (e.name.clone(), t)))
                .collect(),
            ours: cfg.ours.clone(),
            idm_ego: cfg.egos.iter().find(|e| e.is_idm()).map(|e| e.name.clone()),
            flows: cfg.flows.iter().map(|f| f.name.clone()).collect(),
            egos: cfg.egos.iter().map(|f| f.name.clone()).collect(),
            cases: cfg.cases,
            seeds: cfg.seeds,
            sizes: cfg
                .sizes
                .iter()
                .map(|(e, o)| {
                    (e.clone(), [o.cases.unwrap_or(cfg.cases), o.seeds.unwrap_or(cfg.seeds)])
                })
                .collect(),
        }
    }
}

/// Appends whole cells to an `episodes.csv` (the header first if the file is new or empty):
/// one write per cell, so a cell is stored whole or not at all. A file started in the older
/// format ([`EPISODES_HEADER_V1`]) is continued in it; one with any other header is refused
/// rather than appended to.
pub struct EpisodesWriter {
    file: std::fs::File,
    path: PathBuf,
    format: Format,
}

impl EpisodesWriter {
    pub fn open(path: &Path) -> Result<Self, FileError> {
        use std::io::{BufRead, Write};
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .read(true)
            .open(path)
            .map_err(|e| io_err(path, e))?;
        let empty = file.metadata().map_err(|e| io_err(path, e))?.len() == 0;
        let format = if empty {
            writeln!(file, "{EPISODES_HEADER}").map_err(|e| io_err(path, e))?;
            Format::Current
        } else {
            let mut header = String::new();
            std::io::BufReader::new(&file).read_line(&mut header).map_err(|e| io_err(path, e))?;
            let header = header.trim_end_matches(['\n', '\r']);
            Format::of_header(header).ok_or_else(|| {
                file_err(
                    path,
                    format!("header `{header}` is not an episodes.csv header; not appending"),
                )
            })?
        };
        Ok(Self { file, path: path.to_path_buf(), format })
    }

    pub fn append(&mut self, rows: &[EpisodeRow]) -> Result<(), FileError> {
        use std::io::Write;
        let text: String = rows.iter().map(|r| r.to_csv_in(self.format) + "\n").collect();
        self.file
            .write_all(text.as_bytes())
            .and_then(|()| self.file.sync_data())
            .map_err(|e| io_err(&self.path, e))
    }
}

pub fn read_meta(path: &Path) -> Result<Meta, FileError> {
    let text = std::fs::read_to_string(path).map_err(|e| io_err(path, e))?;
    serde_json::from_str(&text).map_err(|e| file_err(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip_and_bad_lines_name_the_line() {
        let r = EpisodeRow::new(
            &Cell {
                experiment: "svo_sweep".into(),
                ego: String::new(),
                flow: "CoPO".into(),
                scenario: "merge".into(),
                svo_deg: Some(30),
                vehicles: Some(8),
            },
            &EvalEpisode {
                case: 3,
                seed: 1,
                scores: sf_job::Scores { success: 0.25, safety: 0.25, speed: 0.5 },
                collision: 0.0,
                lane_change: Some(0.5),
                road_closed: Some(0.25),
            },
        );
        assert_eq!(EpisodeRow::parse(&r.to_csv(), Format::Current), Ok(r.clone()));
        let unrecorded = EpisodeRow {
            ep: EvalEpisode { lane_change: None, road_closed: None, ..r.ep },
            ..r.clone()
        };
        assert_eq!(
            EpisodeRow::parse(&unrecorded.to_csv(), Format::Current),
            Ok(unrecorded.clone())
        );
        let v2 = EpisodeRow { ep: EvalEpisode { road_closed: None, ..r.ep }, ..r.clone() };
        assert_eq!(EpisodeRow::parse(&r.to_csv_in(Format::V2), Format::V2), Ok(v2));
        assert_eq!(EpisodeRow::parse(&r.to_csv_in(Format::V1), Format::V1), Ok(unrecorded));
        let dir = std::env::temp_dir().join(format!("sf-report-rows-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let p = dir.join("episodes.csv");
        std::fs::write(
            &p,
            format!("{EPISODES_HEADER}\n{}\ncross,a,b,merge,,,1,0,NaN,1,1,0,,\n", r.to_csv()),
        )
        .expect("write");
        let e = read_episodes(&p).expect_err("NaN").to_string();
        assert!(e.contains("line 3") && e.contains("success"), "{e}");
        // A 12-field line in a file of the current format is named with both counts.
        std::fs::write(&p, format!("{EPISODES_HEADER}\n{}\n", r.to_csv_in(Format::V1)))
            .expect("write");
        let e = read_episodes(&p).expect_err("short line").to_string();
        assert!(e.contains("line 2") && e.contains("12 fields, expected 14"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The same rows read back from a plain and a gzipped file (named or found beside the plain
    /// name); a corrupt `.gz` is an error naming the file.
    #[test]
    fn gzipped_episodes_read_as_plain() {
        use std::io::Write as _;
        let dir = std::env::temp_dir().join(format!("sf-report-gz-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        let text: String = std::iter::once(EPISODES_HEADER.to_string())
            .chain((0..5).map(|c| row(c, Some(0.25 * c as f32)).to_csv()))
            .map(|l| l + "\n")
            .collect();
        let plain_dir = dir.join("plain");
        std::fs::create_dir_all(&plain_dir).expect("dir");
        std::fs::write(plain_dir.join("episodes.csv"), &text).expect("write");
        let plain = read_episodes(&episodes_file(&plain_dir)).expect("plain");
        assert_eq!(plain.len(), 5);
        let gz = dir.join("episodes.csv.gz");
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
        enc.write_all(text.as_bytes()).expect("gzip");
        std::fs::write(&gz, enc.finish().expect("gzip")).expect("write");
        assert_eq!(episodes_file(&dir), gz);
        assert_eq!(read_episodes(&gz).expect("gz"), plain);
        assert_eq!(read_episodes(&dir.join("episodes.csv")).expect("gz beside"), plain);
        std::fs::write(&gz, b"\x1f\x8b\x08\x00 not gzip at all").expect("write");
        let e = read_episodes(&dir.join("episodes.csv")).expect_err("corrupt").to_string();
        assert!(e.contains("episodes.csv.gz"), "{e}");
        assert!(read_episodes(&dir.join("absent.csv")).expect("absent").is_empty());
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn row(case: u32, lane_change: Option<f32>) -> EpisodeRow {
        EpisodeRow::new(
            &Cell {
                experiment: "flow_quality".into(),
                ego: String::new(),
                flow: "MACAD".into(),
                scenario: "merge".into(),
                svo_deg: None,
                vehicles: None,
            },
            &EvalEpisode {
                case,
                seed: 0,
                scores: sf_job::Scores { success: 1.0, safety: 1.0, speed: 0.9 },
                collision: 0.0,
                lane_change,
                road_closed: lane_change.map(|v| 1.0 - v),
            },
        )
    }

    /// An evaluation resumed into a file of the older format appends in that format, so the
    /// stored rows stay readable; a new file gets the current header; a foreign file is refused
    /// and left as it was.
    #[test]
    fn appending_keeps_the_files_format_and_refuses_foreign_files() {
        let dir = std::env::temp_dir().join(format!("sf-report-append-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let old = dir.join("old.csv");
        std::fs::write(
            &old,
            format!("{EPISODES_HEADER_V1}\n{}\n", row(0, None).to_csv_in(Format::V1)),
        )
        .expect("write");
        EpisodesWriter::open(&old).expect("open").append(&[row(1, Some(1.0))]).expect("append");
        let rows = read_episodes(&old).expect("still readable");
        assert_eq!(
            rows.iter().map(|r| (r.ep.case, r.ep.lane_change)).collect::<Vec<_>>(),
            [(0, None), (1, None)]
        );
        // A file of 2026-11-28 (lane changes, no closed roads) keeps its 13 fields.
        let v2 = dir.join("v2.csv");
        std::fs::write(
            &v2,
            format!("{EPISODES_HEADER_V2}\n{}\n", row(0, Some(0.5)).to_csv_in(Format::V2)),
        )
        .expect("write");
        EpisodesWriter::open(&v2).expect("open").append(&[row(1, Some(1.0))]).expect("append");
        let rows = read_episodes(&v2).expect("still readable");
        assert_eq!(
            rows.iter().map(|r| (r.ep.lane_change, r.ep.road_closed)).collect::<Vec<_>>(),
            [(Some(0.5), None), (Some(1.0), None)]
        );

        let new = dir.join("new.csv");
        let mut w = EpisodesWriter::open(&new).expect("open");
        w.append(&[row(0, Some(0.5))]).expect("append");
        drop(w);
        EpisodesWriter::open(&new).expect("reopen").append(&[row(1, Some(0.0))]).expect("append");
        let rows = read_episodes(&new).expect("read");
        assert_eq!(
            rows.iter().map(|r| (r.ep.lane_change, r.ep.road_closed)).collect::<Vec<_>>(),
            [(Some(0.5), Some(0.5)), (Some(0.0), Some(1.0))]
        );
        assert!(std::fs::read_to_string(&new).expect("text").starts_with(EPISODES_HEADER));

        let foreign = dir.join("foreign.csv");
        std::fs::write(&foreign, "a,b,c\n1,2,3\n").expect("write");
        let e = EpisodesWriter::open(&foreign).err().expect("foreign header").to_string();
        assert!(e.contains("a,b,c") && e.contains("not appending"), "{e}");
        assert_eq!(std::fs::read_to_string(&foreign).expect("text"), "a,b,c\n1,2,3\n");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
