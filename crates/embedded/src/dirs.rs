//! Where the commands find their data files: scenarios and evaluation cases by name.
//!
//! Owns: [`Ctx`], the two directories and the file names inside them. Must not: build or
//! regenerate the files (`socialflow gen-scenarios` and `gen-cases` do).

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{bail, Result};
use sf_sim::case::{self, CaseFile};
use sf_sim::scenarios::SCENARIOS;
use sf_sim::Map;

/// Where the command finds its data files.
pub struct Ctx {
    pub scenarios: PathBuf,
    pub cases: PathBuf,
}

impl Ctx {
    pub fn map(&self, name: &str) -> Result<Arc<Map>> {
        if !SCENARIOS.contains(&name) {
            bail!("unknown scenario `{name}` (expected one of {})", SCENARIOS.join(", "));
        }
        let path = self.scenarios.join(format!("{name}.json"));
        Ok(Arc::new(Map::load(&path)?))
    }

    pub fn cases(&self, map: &Map) -> Result<CaseFile> {
        let path = self.cases.join(format!("{}.v{}.json", map.name, case::CASES_VERSION));
        Ok(CaseFile::load(&path, map)?)
    }
}
