//! Fuzzing of the TOML config parsers (property tests, stable Rust, deterministic, bounded for CI).
//!
//! What is fuzzed: [`JobConfig::from_toml`] and [`EvalConfig::from_toml`] (with
//! [`is_eval_toml`], which tells them apart on submission) on arbitrary strings, on TOML-ish
//! token soup, and on mutations of every shipped job and eval config under `configs/` (a line
//! dropped or duplicated, a number replaced by one of -1, 0, 1e308, -1e308, nan, inf,
//! 18446744073709551615, 9223372036854775807 (i64::MAX, TOML's largest integer) or 1.5, a
//! string value emptied, the text truncated at a random byte; one to three edits per case, eval
//! and job configs drawn equally often). The ladder's rung files and `configs/learner.toml` belong to
//! the CLI and the learner and are not parsed here.
//!
//! What is asserted: nothing panics or hangs; an error's message is non-empty; when the only
//! edit replaced the whole value of a `key = number` line and the config is refused, the
//! message names that key (parse errors quote the line, validation errors name the field); a
//! config that is accepted survives its resolved TOML (`to_toml` -> `from_toml`) unchanged, and
//! an accepted eval config expands into its cells.
//!
//! Cases: 1024 per property (fixed seed, no persistence file); well under a second in all in the
//! debug profile.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use proptest::prelude::*;
use proptest::sample::Index;
use proptest::test_runner::{Config as ProptestConfig, RngSeed};
use sf_job::eval::{is_eval_toml, EvalConfig};
use sf_job::JobConfig;

/// Deterministic and bounded for CI: a fixed seed and `cases` cases, no regression files
/// written into the crate. `PROPTEST_CASES` and `PROPTEST_RNG_SEED` override both for a longer
/// local run.
fn config(cases: u32) -> ProptestConfig {
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse().ok());
    ProptestConfig {
        cases: env("PROPTEST_CASES").map_or(cases, |c: u64| c as u32),
        rng_seed: RngSeed::Fixed(env("PROPTEST_RNG_SEED").unwrap_or(0x50c1_a1f1)),
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    Job,
    Eval,
}

#[derive(Debug)]
struct Shipped {
    /// Relative to `configs/`.
    name: String,
    text: String,
    kind: Kind,
}

fn configs_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../configs")
}

fn collect(dir: &Path, root: &Path, out: &mut Vec<Shipped>) {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("configs/ is readable")
        .map(|e| e.expect("directory entry").path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            collect(&p, root, out);
            continue;
        }
        if p.extension().and_then(|e| e.to_str()) != Some("toml") {
            continue;
        }
        let name =
            p.strip_prefix(root).expect("under configs/").to_string_lossy().replace('\\', "/");
        // Learner deployment settings and the ladder's rung files have their own parsers
        // (socialflow-learner, socialflow-cli).
        if name == "learner.toml" || (name.starts_with("ladder/") && name.matches('/').count() == 1)
        {
            continue;
        }
        let text = std::fs::read_to_string(&p).expect("config is readable");
        let kind = if is_eval_toml(&text) { Kind::Eval } else { Kind::Job };
        out.push(Shipped { name, text, kind });
    }
}

/// Every shipped job and eval config, in a fixed order.
fn shipped() -> &'static [Shipped] {
    static FILES: OnceLock<Vec<Shipped>> = OnceLock::new();
    FILES.get_or_init(|| {
        let root = configs_dir();
        let mut out = Vec::new();
        collect(&root, &root, &mut out);
        out
    })
}

/// Parses with the parser `kind` names and checks what comes back: an error has a message;
/// an accepted config survives its resolved TOML and (eval) expands into cells. Returns the
/// error message, if any.
fn parse(kind: Kind, text: &str) -> Result<Option<String>, TestCaseError> {
    let err = match kind {
        Kind::Job => match JobConfig::from_toml(text) {
            Ok(c) => {
                let again = JobConfig::from_toml(&c.to_toml());
                prop_assert!(
                    again.as_ref().is_ok_and(|a| *a == c),
                    "resolved TOML of an accepted job config does not round-trip: {:?}",
                    again.err()
                );
                let _ = (
                    c.deps(),
                    c.deps_by_name(),
                    c.coordinator(),
                    c.curve_every_steps(),
                    c.action_dim(),
                );
                None
            }
            Err(e) => Some(e.to_string()),
        },
        Kind::Eval => match EvalConfig::from_toml(text) {
            Ok(c) => {
                let again = EvalConfig::from_toml(&c.to_toml());
                prop_assert!(
                    again.as_ref() == Ok(&c),
                    "resolved TOML of an accepted eval config does not round-trip: {:?}",
                    again.err()
                );
                prop_assert!(!c.cells().is_empty());
                let _ = c.all_scenarios();
                None
            }
            Err(e) => Some(e.to_string()),
        },
    };
    if let Some(m) = &err {
        prop_assert!(!m.trim().is_empty(), "empty error message");
    }
    Ok(err)
}

/// Byte ranges of the numbers and of the basic strings (`"..."`) outside comments.
fn tokens(text: &str) -> (Vec<Range<usize>>, Vec<Range<usize>>) {
    let b = text.as_bytes();
    let (mut numbers, mut strings) = (Vec::new(), Vec::new());
    let mut i = 0;
    let ident = |c: u8| c.is_ascii_alphanumeric() || c == b'_' || c == b'-';
    while i < b.len() {
        let c = b[i];
        if c == b'#' {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if c == b'"' {
            let start = i;
            i += 1;
            while i < b.len() && b[i] != b'"' && b[i] != b'\n' {
                i += if b[i] == b'\\' { 2 } else { 1 };
            }
            if i < b.len() && b[i] == b'"' {
                strings.push(start..i + 1);
            }
            i += 1;
        } else if c.is_ascii_digit()
            || ((c == b'-' || c == b'+') && b.get(i + 1).is_some_and(u8::is_ascii_digit))
        {
            let start = i;
            i += 1;
            while i < b.len() && (ident(b[i]) || b[i] == b'.' || b[i] == b'+') {
                i += 1;
            }
            numbers.push(start..i);
        } else if ident(c) {
            while i < b.len() && ident(b[i]) {
                i += 1;
            }
        } else {
            i += 1;
        }
    }
    (numbers, strings)
}

/// The key of a `key = <number>` line whose whole value is the number at `r`.
fn sole_key(text: &str, r: &Range<usize>) -> Option<String> {
    let line_start = text[..r.start].rfind('\n').map_or(0, |k| k + 1);
    let line_end = text[r.end..].find('\n').map_or(text.len(), |k| r.end + k);
    let (key, eq) = text[line_start..r.start].split_once('=')?;
    let key = key.trim();
    let rest = text[r.end..line_end].trim();
    let simple =
        !key.is_empty() && key.bytes().all(|c| c.is_ascii_alphanumeric() || c == b'_' || c == b'-');
    (simple && eq.trim().is_empty() && (rest.is_empty() || rest.starts_with('#')))
        .then(|| key.to_string())
}

/// Replacement numbers: extremes of every type the configs use. TOML integers are i64, so
/// u64::MAX is a parse error and i64::MAX is the largest count a config can actually carry.
const NUMBERS: [&str; 9] = [
    "-1",
    "0",
    "1e308",
    "-1e308",
    "nan",
    "inf",
    "18446744073709551615",
    "9223372036854775807",
    "1.5",
];

#[derive(Clone, Debug)]
enum Edit {
    DropLine(Index),
    DuplicateLine(Index),
    Number(Index, usize),
    EmptyString(Index),
    Truncate(Index),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        1 => any::<Index>().prop_map(Edit::DropLine),
        1 => any::<Index>().prop_map(Edit::DuplicateLine),
        3 => (any::<Index>(), 0..NUMBERS.len()).prop_map(|(i, v)| Edit::Number(i, v)),
        1 => any::<Index>().prop_map(Edit::EmptyString),
        1 => any::<Index>().prop_map(Edit::Truncate),
    ]
}

/// Applies one edit; returns the key whose whole numeric value it replaced, if it did that.
fn apply(text: &mut String, e: &Edit) -> Option<String> {
    match e {
        Edit::DropLine(i) | Edit::DuplicateLine(i) => {
            let mut lines: Vec<&str> = text.split_inclusive('\n').collect();
            if lines.is_empty() {
                return None;
            }
            let k = i.index(lines.len());
            if matches!(e, Edit::DropLine(_)) {
                lines.remove(k);
            } else {
                let dup = if lines[k].ends_with('\n') {
                    lines[k].to_string()
                } else {
                    format!("\n{}", lines[k])
                };
                *text = format!("{}{}{}", lines[..=k].concat(), dup, lines[k + 1..].concat());
                return None;
            }
            *text = lines.concat();
            None
        }
        Edit::Number(i, v) => {
            let (numbers, _) = tokens(text);
            if numbers.is_empty() {
                return None;
            }
            let r = numbers[i.index(numbers.len())].clone();
            let key = sole_key(text, &r);
            text.replace_range(r, NUMBERS[*v]);
            key
        }
        Edit::EmptyString(i) => {
            let (_, strings) = tokens(text);
            if !strings.is_empty() {
                text.replace_range(strings[i.index(strings.len())].clone(), "\"\"");
            }
            None
        }
        Edit::Truncate(i) => {
            let mut k = i.index(text.len() + 1);
            while !text.is_char_boundary(k) {
                k -= 1;
            }
            text.truncate(k);
            None
        }
    }
}

/// TOML-ish token soup: the shipped configs' keys, section headers and value shapes.
fn toml_soup() -> impl Strategy<Value = String> {
    #[rustfmt::skip]
    const VOCAB: &[&str] = &[
        "\n", " = ", "=", "[env]", "[sac]", "[train]", "[net]", "[worker]", "[coordinator]", "[experiments]", "[[x]]", "kind", "\"eval\"", "\"ego\"", "\"copo\"", "name", "scenarios",
        "[\"merge\"]", "env_steps", "warmup_steps", "replay_capacity", "batch_size", "gamma", "vehicles_min", "vehicles_max", "cases", "seeds", "envs", "flows", "egos", "values",
        "svo_sweep", "density", "vehicles", "{ name = \"IDM\", job = \"idm\" }", "flow_quality", "[\"IDM\"]", "\"", "'", "{", "}", "[", "]", ",", ".", "#", "0", "1", "-1", "1e308",
        "nan", "inf", "18446744073709551615", "9223372036854775807", "1.5", "true", "\"\"", "\"\\u0000\"", "1979-05-27",
    ];
    prop::collection::vec(prop::sample::select(VOCAB), 0..64).prop_map(|t| t.concat())
}

#[test]
fn every_shipped_config_parses() {
    let files = shipped();
    let evals = files.iter().filter(|f| f.kind == Kind::Eval).count();
    assert!(
        evals >= 4 && files.len() - evals >= 40,
        "found {} job and {evals} eval configs under configs/",
        files.len() - evals
    );
    for f in files {
        let err = match f.kind {
            Kind::Job => JobConfig::from_toml(&f.text).err().map(|e| e.to_string()),
            Kind::Eval => EvalConfig::from_toml(&f.text).err().map(|e| e.to_string()),
        };
        assert_eq!(err, None, "configs/{}", f.name);
    }
}

proptest! {
    #![proptest_config(config(1024))]

    /// Arbitrary strings: an error with a message, or (never, in practice) a valid config.
    #[test]
    fn arbitrary_strings_never_panic(s in prop::collection::vec(any::<char>(), 0..256).prop_map(String::from_iter)) {
        let _ = is_eval_toml(&s);
        parse(Kind::Job, &s)?;
        parse(Kind::Eval, &s)?;
    }

    /// Token soup that reaches the deserialiser and the validation more often.
    #[test]
    fn toml_soup_never_panics(s in toml_soup()) {
        let _ = is_eval_toml(&s);
        parse(Kind::Job, &s)?;
        parse(Kind::Eval, &s)?;
    }

    /// Mutated shipped configs: no panic, a message on refusal, and a refused single numeric
    /// replacement names its key.
    #[test]
    fn mutated_shipped_configs_are_refused_clearly(eval in any::<bool>(), file in any::<Index>(), edits in prop::collection::vec(edit(), 1..=3)) {
        let kind = if eval { Kind::Eval } else { Kind::Job };
        let files: Vec<&Shipped> = shipped().iter().filter(|f| f.kind == kind).collect();
        let f = files[file.index(files.len())];
        let mut text = f.text.clone();
        let keys: Vec<Option<String>> = edits.iter().map(|e| apply(&mut text, e)).collect();
        let err = parse(f.kind, &text)?;
        // Also what a submission does first: tell an eval grid from a job, then parse as that.
        let kind = if is_eval_toml(&text) { Kind::Eval } else { Kind::Job };
        parse(kind, &text)?;
        if let ([Some(key)], Some(msg)) = (keys.as_slice(), &err) {
            prop_assert!(msg.contains(key.as_str()), "configs/{} with `{}` replaced: `{}` does not name it", f.name, key, msg);
        }
    }
}
