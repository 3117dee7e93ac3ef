//! Evaluation cases: who spawns where, on which route, with which SVO.
//!
//! Owns: [`Case`], the seeded generator used both for the stored evaluation sets and for
//! random training resets, the versioned case file ([`CaseFile`]) with its validating
//! loader, and [`SvoGaussian`] (a per-scenario SVO distribution). Must not: step vehicles. A case plus a seed fully determines an episode.

use std::path::Path;

use rand::seq::index::sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::Distribution;
use serde::{Deserialize, Serialize};

use crate::map::Map;

/// Version of the case file format and generator; bump when either changes.
pub const CASES_VERSION: u32 = 1;
/// Vehicles per episode, inclusive (digest).
pub const DEFAULT_VEHICLES: (u32, u32) = (8, 20);
/// SVO range of a case, degrees; flows with other ranges map it linearly.
pub const SVO_RANGE_DEG: (f32, f32) = (0.0, 90.0);

/// A Gaussian over the SVO (CoPO's Stage-2 coordinator, per scenario), degrees. Draws are
/// clamped to [`SVO_RANGE_DEG`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SvoGaussian {
    pub mean_deg: f32,
    pub std_deg: f32,
}

impl SvoGaussian {
    /// Checks the parameters; names the field.
    pub fn validate(&self) -> Result<(), SvoGaussianError> {
        if !self.mean_deg.is_finite()
            || !(SVO_RANGE_DEG.0..=SVO_RANGE_DEG.1).contains(&self.mean_deg)
        {
            return Err(SvoGaussianError::Mean { mean_deg: self.mean_deg });
        }
        if !self.std_deg.is_finite() || self.std_deg < 0.0 {
            return Err(SvoGaussianError::Std { std_deg: self.std_deg });
        }
        Ok(())
    }

    pub fn sample(&self, rng: &mut impl Rng) -> f32 {
        let z: f32 = rand_distr::StandardNormal.sample(rng);
        (self.mean_deg + self.std_deg * z).clamp(SVO_RANGE_DEG.0, SVO_RANGE_DEG.1)
    }
}

/// An [`SvoGaussian`] whose parameters are out of range; names the field and its value.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum SvoGaussianError {
    #[error("mean_deg {mean_deg} must lie in [0, 90]")]
    Mean { mean_deg: f32 },
    #[error("std_deg {std_deg} must be finite and >= 0")]
    Std { std_deg: f32 },
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CaseVehicle {
    pub spawn: u32,
    pub route: u32,
    pub svo_deg: f32,
    /// A slow vehicle: its speed never exceeds this (m/s; the ladder's lane-change rung puts
    /// one ahead of the ego). Absent: the vehicle's own limit. Files without it are unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_speed_mps: Option<f32>,
}

/// One evaluation case; vehicle 0 is the ego in ego mode.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Case {
    pub id: u32,
    pub vehicles: Vec<CaseVehicle>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CaseFile {
    pub format_version: u32,
    pub scenario: String,
    pub generator_seed: u64,
    pub cases: Vec<Case>,
}

#[derive(Debug, thiserror::Error)]
pub enum CaseError {
    #[error("cannot read case file {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("case file {path} is not valid JSON for the case format: {source}")]
    Parse { path: String, source: serde_json::Error },
    #[error("case file {path}: {field}: {reason}")]
    Invalid { path: String, field: String, reason: String },
}

/// Draws a random case with `n_vehicles` (capped at the number of spawn points).
pub fn random_case(map: &Map, rng: &mut impl Rng, id: u32, n_vehicles: usize) -> Case {
    let n = n_vehicles.min(map.spawns.len());
    let spawns = sample(rng, map.spawns.len(), n);
    let vehicles = spawns
        .iter()
        .map(|s| {
            let sp = &map.spawns[s];
            let route = sp.routes[rng.random_range(0..sp.routes.len())];
            let svo_deg = rng.random_range(SVO_RANGE_DEG.0..=SVO_RANGE_DEG.1);
            CaseVehicle { spawn: s as u32, route, svo_deg, max_speed_mps: None }
        })
        .collect();
    Case { id, vehicles }
}

/// The stored evaluation set of a scenario: `n_cases` cases, vehicle counts uniform in `vehicles`.
pub fn generate(map: &Map, n_cases: u32, seed: u64, vehicles: (u32, u32)) -> CaseFile {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let cases = (0..n_cases)
        .map(|id| {
            let n = rng.random_range(vehicles.0..=vehicles.1) as usize;
            random_case(map, &mut rng, id, n)
        })
        .collect();
    CaseFile {
        format_version: CASES_VERSION,
        scenario: map.name.clone(),
        generator_seed: seed,
        cases,
    }
}

impl Case {
    /// Checks the case against a map; `field` prefixes error locations.
    pub fn check(&self, map: &Map) -> Result<(), (String, String)> {
        if self.vehicles.is_empty() {
            return Err(("vehicles".into(), "a case needs at least one vehicle".into()));
        }
        let mut used = vec![false; map.spawns.len()];
        for (k, v) in self.vehicles.iter().enumerate() {
            let f = format!("vehicles[{k}]");
            let Some(sp) = map.spawns.get(v.spawn as usize) else {
                return Err((
                    format!("{f}.spawn"),
                    format!("spawn point {} does not exist", v.spawn),
                ));
            };
            if std::mem::replace(&mut used[v.spawn as usize], true) {
                return Err((
                    format!("{f}.spawn"),
                    format!("spawn point {} is used twice", v.spawn),
                ));
            }
            if !sp.routes.contains(&v.route) {
                return Err((
                    format!("{f}.route"),
                    format!("route {} does not start at spawn point {}", v.route, v.spawn),
                ));
            }
            if !(v.svo_deg.is_finite() && (-90.0..=90.0).contains(&v.svo_deg)) {
                return Err((format!("{f}.svo_deg"), format!("{} is not in [-90, 90]", v.svo_deg)));
            }
            if let Some(cap) = v.max_speed_mps.filter(|c| !(c.is_finite() && *c >= 0.0)) {
                return Err((
                    format!("{f}.max_speed_mps"),
                    format!("{cap} must be a speed >= 0 m/s"),
                ));
            }
        }
        Ok(())
    }
}

impl CaseFile {
    /// Loads and validates a case file against its scenario's map.
    pub fn load(path: &Path, map: &Map) -> Result<Self, CaseError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|source| CaseError::Io { path: p.clone(), source })?;
        Self::from_json(&text, &p, map)
    }

    /// Parses and validates a case file's text (`origin` names it in errors).
    pub fn from_json(text: &str, origin: &str, map: &Map) -> Result<Self, CaseError> {
        let p = origin.to_string();
        let f: CaseFile = serde_json::from_str(text)
            .map_err(|source| CaseError::Parse { path: p.clone(), source })?;
        let bad =
            |field: String, reason: String| CaseError::Invalid { path: p.clone(), field, reason };
        if f.format_version != CASES_VERSION {
            return Err(bad(
                "format_version".into(),
                format!("{} is not supported (this build reads {CASES_VERSION})", f.format_version),
            ));
        }
        if f.scenario != map.name {
            return Err(bad(
                "scenario".into(),
                format!("file is for `{}`, map is `{}`", f.scenario, map.name),
            ));
        }
        for (i, c) in f.cases.iter().enumerate() {
            c.check(map).map_err(|(field, reason)| bad(format!("cases[{i}].{field}"), reason))?;
        }
        Ok(f)
    }

    /// Writes the file (temporary file, then rename).
    pub fn write(&self, path: &Path) -> std::io::Result<()> {
        let text = serde_json::to_string(self).map_err(std::io::Error::other)?;
        let tmp = path.with_extension("json.tmp");
        std::fs::write(&tmp, text + "\n")?;
        std::fs::rename(tmp, path)
    }
}
