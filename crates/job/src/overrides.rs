//! Settings from the command line: `--set section.key=value` on a job's TOML text.
//!
//! Owns: [`apply`], which parses each override, writes its value into the text's table (the
//! value read as TOML, or as a string when it is not TOML: `--set sac.device=cpu`), and
//! returns the new text for the caller to validate like any file (a misspelt key or a bad value
//! is refused by the config's own checks, naming the field). The text that comes back is what
//! a job stores as its config, so what was overridden is on record.
//! Must not: validate the config (`JobConfig::from_toml` / `JobSpec::from_toml` do) or know
//! which keys exist.

/// Why an override could not be applied.
#[derive(Debug, thiserror::Error)]
pub enum OverrideError {
    #[error("--set `{set}`: expected section.key=value (e.g. sac.seed=3)")]
    Syntax { set: String },
    #[error("--set `{set}`: `{at}` is a {found}, not a section")]
    NotATable { set: String, at: String, found: &'static str },
    #[error("the config is not valid TOML: {0}")]
    Text(String),
}

/// `text` with every `section.key=value` of `sets` written into it, in order (a later one wins).
/// Keys may nest (`validation.every_updates`, `a.b.c`) and missing sections are created; a key
/// at the top level (`name=x`) needs no section.
pub fn apply(text: &str, sets: &[String]) -> Result<String, OverrideError> {
    if sets.is_empty() {
        return Ok(text.to_string());
    }
    let mut table: toml::Table = text.parse().map_err(|e| OverrideError::Text(format!("{e}")))?;
    for set in sets {
        let syntax = || OverrideError::Syntax { set: set.clone() };
        let (path, raw) = set.split_once('=').ok_or_else(syntax)?;
        let keys: Vec<&str> = path.trim().split('.').map(str::trim).collect();
        if keys.iter().any(|k| k.is_empty()) {
            return Err(syntax());
        }
        let value = parse_value(raw.trim());
        let (last, sections) = keys.split_last().ok_or_else(syntax)?;
        let mut at = &mut table;
        for (i, k) in sections.iter().enumerate() {
            let entry =
                at.entry(k.to_string()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
            at = match entry {
                toml::Value::Table(t) => t,
                other => {
                    return Err(OverrideError::NotATable {
                        set: set.clone(),
                        at: keys[..=i].join("."),
                        found: other.type_str(),
                    })
                }
            };
        }
        at.insert(last.to_string(), value);
    }
    toml::to_string(&table).map_err(|e| OverrideError::Text(e.to_string()))
}

/// A value as TOML (`3`, `0.5`, `true`, `"x"`, `[1, 2]`, `{ a = 1 }`), else the raw text as a
/// string.
fn parse_value(raw: &str) -> toml::Value {
    format!("v = {raw}")
        .parse::<toml::Table>()
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(raw.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::JobConfig;

    const JOB: &str = "# a comment\nname = \"j\"\n[env]\nscenarios = [\"merge\"]\n[sac]\nseed = 1\n[train]\nenv_steps = 1000\n";

    fn set(s: &[&str]) -> Vec<String> {
        s.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn overrides_write_typed_values_into_sections_and_the_config_validates_them() {
        let text = apply(
            JOB,
            &set(&[
                "sac.seed=12",
                "sac.device=cpu",
                "env.scenarios=[\"merge\", \"roundabout\"]",
                "validation.every_updates=500",
                "name=renamed",
                "sac.seed=13",
            ]),
        )
        .expect("applies");
        let cfg = JobConfig::from_toml(&text).expect("valid");
        assert_eq!(cfg.sac.seed, 13, "a later override wins");
        assert_eq!(cfg.name, "renamed");
        assert_eq!(cfg.env.scenarios, ["merge", "roundabout"]);
        assert_eq!(cfg.validation.as_ref().map(|v| v.every_updates), Some(500));
        assert_eq!(apply(JOB, &[]).expect("nothing to do"), JOB, "no override keeps the text");
    }

    #[test]
    fn bad_overrides_are_refused_naming_the_override_or_the_field() {
        for (s, want) in [
            ("sac.seed", "expected section.key=value"),
            ("sac..seed=1", "expected section.key=value"),
            ("=1", "expected section.key=value"),
            ("name.x=1", "`name` is a string, not a section"),
        ] {
            let e = apply(JOB, &set(&[s])).expect_err(s).to_string();
            assert!(e.contains(want) && e.contains(s), "{s}: {e}");
        }
        // What the override writes is checked like the file: the config names the field.
        for (s, field) in [("sac.seeed=3", "seeed"), ("train.env_steps=-5", "env_steps")] {
            let text = apply(JOB, &set(&[s])).expect("written");
            let e = JobConfig::from_toml(&text).expect_err(s).to_string();
            assert!(e.contains(field), "{s}: {e}");
        }
    }
}
