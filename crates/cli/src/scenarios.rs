//! Regenerating the shipped scenario and case files (`gen-scenarios`, `gen-cases`); loading
//! them by name is `sf_embedded::Ctx`, shared with the lab.

use std::path::Path;

use anyhow::{Context, Result};
use sf_sim::case::{self, DEFAULT_VEHICLES};
use sf_sim::scenarios::{self, SCENARIOS};
use sf_sim::Map;

pub use sf_embedded::Ctx;

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
