//! A job's text parsed once: [`JobSpec`], a training job or an evaluation grid.
//!
//! Owns: the one decision which of the two a TOML text is (its top-level `kind`: `"eval"` is
//! an evaluation grid, any other kind or none a training job; see [`crate::eval::is_eval_toml`])
//! and [`SpecError`], which keeps the refusing parser's own message (it names the field).
//! Callers that take submitted or stored text (the learner's submit and scheduler, the CLI's
//! `submit` and `pipeline`) parse it here and match on the result instead of asking
//! `is_eval_toml` and then parsing again. Must not: validate beyond what
//! [`JobConfig::from_toml`] and [`EvalConfig::from_toml`] do, or resolve anything.

use crate::config::{ConfigError, DepRole, JobConfig};
use crate::eval::{is_eval_toml, EvalConfig, EvalConfigError};
use crate::ids::JobId;

/// A submitted or stored job: what it runs, parsed and validated.
#[derive(Clone, Debug, PartialEq)]
// One per job, parsed once and kept: boxing the larger config would buy nothing.
#[allow(clippy::large_enum_variant)]
pub enum JobSpec {
    /// A training job (`kind` = ego, a flow, or an adversary).
    Train(JobConfig),
    /// An evaluation grid (`kind = "eval"`).
    Eval(EvalConfig),
}

/// A text that is neither a valid training job nor a valid evaluation grid; the message is the
/// refusing parser's (it names the field).
#[derive(Debug, thiserror::Error)]
pub enum SpecError {
    #[error(transparent)]
    Train(#[from] ConfigError),
    #[error(transparent)]
    Eval(#[from] EvalConfigError),
}

impl JobSpec {
    /// Parses and validates `text` as the kind it declares.
    pub fn from_toml(text: &str) -> Result<Self, SpecError> {
        if is_eval_toml(text) {
            Ok(Self::Eval(EvalConfig::from_toml(text)?))
        } else {
            Ok(Self::Train(JobConfig::from_toml(text)?))
        }
    }

    /// The job's name.
    pub fn name(&self) -> &str {
        match self {
            Self::Train(c) => &c.name,
            Self::Eval(c) => &c.name,
        }
    }

    /// The jobs (by id) this one must wait for; an evaluation grid's jobs have all succeeded
    /// before it is accepted, so it waits for none.
    pub fn deps(&self) -> Vec<(DepRole, JobId)> {
        match self {
            Self::Train(c) => c.deps(),
            Self::Eval(_) => Vec::new(),
        }
    }

    /// The training job, if this is one.
    pub fn train(&self) -> Option<&JobConfig> {
        match self {
            Self::Train(c) => Some(c),
            Self::Eval(_) => None,
        }
    }

    pub fn is_eval(&self) -> bool {
        matches!(self, Self::Eval(_))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const JOB: &str = "name = \"j\"\n[env]\nscenarios = [\"merge\"]\nbackground_job = 3\n[sac]\nwarmup_steps = 100\n[train]\nenv_steps = 1000\n";
    const GRID: &str = "kind = \"eval\"\nname = \"g\"\nscenarios = [\"merge\"]\ncases = 2\nseeds = 1\nflows = [{ name = \"IDM\", job = \"idm\" }]\negos = [{ name = \"E\", job = \"ego-a\" }]\n[experiments]\nflow_quality = [\"IDM\"]\n";

    #[test]
    fn the_kind_decides_and_each_parser_keeps_its_message() {
        let j = JobSpec::from_toml(JOB).expect("a training job");
        assert_eq!(
            (j.name(), j.is_eval(), j.deps()),
            ("j", false, vec![(DepRole::Background, JobId::new(3))])
        );
        assert_eq!(j.train().map(|c| c.train.env_steps), Some(1000));
        let g = JobSpec::from_toml(GRID).expect("a grid");
        assert_eq!(
            (g.name(), g.is_eval(), g.deps(), g.train().is_none()),
            ("g", true, vec![], true)
        );
        // A grid with a bad field is refused by the grid's parser, not taken for a bad job.
        let e = JobSpec::from_toml(
            &GRID.replace("flow_quality = [\"IDM\"]", "flow_quality = [\"Nope\"]"),
        )
        .expect_err("unknown flow");
        assert!(matches!(e, SpecError::Eval(_)) && e.to_string().contains("Nope"), "{e}");
        let e = JobSpec::from_toml(&JOB.replace("env_steps = 1000", "env_steps = 0"))
            .expect_err("no steps");
        assert!(matches!(e, SpecError::Train(_)) && e.to_string().contains("env_steps"), "{e}");
        assert!(matches!(JobSpec::from_toml("not toml ["), Err(SpecError::Train(_))));
    }
}
