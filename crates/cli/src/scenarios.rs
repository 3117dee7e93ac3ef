//! Loading scenarios and case files by name, and regenerating the shipped ones.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use sf_sim::case::{self, CaseFile, DEFAULT_VEHICLES};
use sf_sim::scenarios::{self, SCENARIOS};
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

pub fn gen_scenarios(out: &Path) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    for name in SCENARIOS {
        let file = scenarios::build(name).expect("every listed scenario has a builder");
        Map::from_file(&file, name)
            .with_context(|| format!("built scenario {name} does not validate"))?;
        let path = out.join(format!("{name}.json"));
        file.write(&path).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

pub fn gen_cases(ctx: &Ctx, out: &Path, n: u32, seed: u64) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    for (k, name) in SCENARIOS.iter().enumerate() {
        let map = ctx.map(name)?;
        let file = case::generate(&map, n, seed.wrapping_add(k as u64), DEFAULT_VEHICLES);
        let path = out.join(format!("{name}.v{}.json", case::CASES_VERSION));
        file.write(&path).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {} ({} cases)", path.display(), file.cases.len());
    }
    Ok(())
}
