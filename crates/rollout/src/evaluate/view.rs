//! Browser viewer pages of stored episodes: [`record`] replays one episode of a cell as the cell
//! runs it (the parent's `replay_episode`) into an [`sf_sim::trace::Trace`], [`record_with`] one
//! run with drivers chosen outside (the Python package's `EvalResult.mine`); [`page`] makes it a
//! self-contained HTML page (the trace as JSON beside a canvas player: play / pause / scrub,
//! every vehicle drawn with its role and SVO, the focus agent's route and observed neighbours,
//! per-agent reward and end on hover, the episode's metrics beside the stored row's); [`index`]
//! lists pages in a sortable table. No server and no network: the page holds everything.
//!
//! Must not: decide what a cell runs (`cell_setup` does) or score (the simulator's metrics come
//! with the trace).

use std::sync::Arc;

use serde::Serialize;
use sf_job::eval::Cell;
use sf_sim::case::CaseFile;
use sf_sim::metrics::EpisodeMetrics;
use sf_sim::trace::Trace;
use sf_sim::{Map, Observer, Role};

use super::{EgoDef, EvalError, FlowDef, Runners, Setting, StoredEpisode};
use crate::drive::Drivers;

/// The player page; `__TITLE__`, `__TRACE__` and `__STORED__` are filled in by [`page`].
const PAGE: &str = include_str!("viewer.html");
/// The index page; `__TITLE__` and `__ROWS__` are filled in by [`index`].
const INDEX: &str = include_str!("viewer_index.html");

/// Who drives the background of `flow`, as the viewer labels it.
pub fn flow_role(flow: &FlowDef) -> String {
    match flow {
        FlowDef::Idm => "IDM".into(),
        FlowDef::IdmNoise { std } => format!("IDM + noise (std {std})"),
        FlowDef::Learned { background, adversary: None, .. } => {
            format!("learned flow ({})", background.cfg.kind.as_str())
        }
        FlowDef::Learned { background, adversary: Some(_), .. } => format!(
            "learned flow ({}) told SVOs by an adversary (socialcomm-adv)",
            background.cfg.kind.as_str()
        ),
    }
}

/// Who drives the ego seat.
fn ego_role(name: &str, ego: &EgoDef) -> String {
    match ego {
        EgoDef::Idm => format!("ego `{name}` (the IDM driver)"),
        EgoDef::IdmMobil => format!("ego `{name}` (IDM with MOBIL lane changes)"),
        EgoDef::Learned(p) => format!("ego `{name}` (learned, {})", p.key),
    }
}

/// Replays case `case_index` (its position among the scenario's stored cases) at evaluation seed
/// `seed` as `cell` runs it, recording every step. The focus agent is agent 0: the ego in an ego
/// cell, the first flow vehicle otherwise.
#[allow(clippy::too_many_arguments)]
pub fn record(
    cell: &Cell,
    map: &Arc<Map>,
    cases: &CaseFile,
    case_index: usize,
    seed: u32,
    flow: &FlowDef,
    ego: Option<&EgoDef>,
    runners: &mut Runners,
) -> Result<Trace, EvalError> {
    let mut rec = Recorder::new(map, ego.map(|e| ego_role(&cell.ego, e)), flow_role(flow));
    let metrics = super::replay_episode(
        cell,
        map,
        cases,
        case_index,
        seed,
        flow,
        ego,
        runners,
        |env, sim| rec.push(env, sim),
    )?;
    rec.finish(metrics)
}

/// Replays one stored episode with `drivers` chosen outside (a Python policy in the ego's seat,
/// say) as [`super::run_stored`] runs it, recording every step. The focus agent is agent 0,
/// labelled `ego_label` when it sits in an ego's seat; every other vehicle is the flow of
/// `flow` ([`flow_role`]).
pub fn record_with(
    at: &Setting,
    episode: &StoredEpisode,
    drivers: &Drivers,
    ego_label: Option<String>,
    flow: &FlowDef,
) -> Result<Trace, EvalError> {
    let mut rec = Recorder::new(at.map, ego_label, flow_role(flow));
    let metrics = super::replay_stored(at, episode, drivers, |env, sim| rec.push(env, sim))?;
    rec.finish(metrics)
}

/// A trace being recorded, state by state, with its roles' labels.
struct Recorder<'a> {
    map: &'a Arc<Map>,
    ego_label: Option<String>,
    background: String,
    trace: Option<Trace>,
    observer: Option<Observer>,
}

impl<'a> Recorder<'a> {
    fn new(map: &'a Arc<Map>, ego_label: Option<String>, background: String) -> Self {
        Self { map, ego_label, background, trace: None, observer: None }
    }

    fn push(&mut self, env: &sf_sim::Env, sim: &sf_sim::SimConfig) {
        let o = self.observer.get_or_insert_with(|| Observer::new(self.map, sim));
        match self.trace.as_mut() {
            Some(t) => t.push(env, o),
            None => {
                let (ego, background) = (&self.ego_label, &self.background);
                let role_of = |i, role| match (ego, i, role) {
                    (Some(e), 0, Role::Learner) => e.clone(),
                    _ => background.clone(),
                };
                self.trace = Some(Trace::new(env, 0, role_of, o));
            }
        }
    }

    fn finish(self, metrics: EpisodeMetrics) -> Result<Trace, EvalError> {
        let mut t =
            self.trace.ok_or_else(|| EvalError::Run("the episode recorded no state".into()))?;
        t.metrics = Some(metrics);
        Ok(t)
    }
}

/// What the episodes file stored for the episode, shown beside the replay's metrics.
#[derive(Clone, Debug, Serialize)]
pub struct StoredRow {
    pub success: f32,
    pub safety: f32,
    pub speed: f32,
    pub collision: f32,
    pub road_closed: Option<f32>,
}

impl StoredRow {
    /// Whether the replay ended as the stored row says (success and collision shares within
    /// 1e-6): the viewer says so on the page.
    pub fn agrees(&self, m: &EpisodeMetrics) -> bool {
        (self.success - m.scores.success).abs() < 1e-6
            && (self.collision - m.collision).abs() < 1e-6
    }
}

/// Text placed inside HTML: `&`, `<`, `>` and `"` escaped.
pub fn escape_html(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// JSON placed inside a `<script>` element: `</` cannot end the element early.
fn script_json(v: &impl Serialize) -> Result<String, EvalError> {
    serde_json::to_string(v)
        .map(|s| s.replace("</", "<\\/"))
        .map_err(|e| EvalError::Run(format!("encoding the viewer's data: {e}")))
}

/// The viewer page of `trace`, titled `title`, with the stored row (if any) beside the replay
/// and whether the replay agrees with it ([`StoredRow::agrees`]).
pub fn page(trace: &Trace, title: &str, stored: Option<&StoredRow>) -> Result<String, EvalError> {
    let stored = stored.map(|row| {
        serde_json::json!({
            "row": row,
            "agrees": trace.metrics.as_ref().is_some_and(|m| row.agrees(m)),
        })
    });
    Ok(PAGE
        .replace("__TITLE__", &escape_html(title))
        .replace("__STORED__", &script_json(&stored)?)
        .replace("__TRACE__", &script_json(trace)?))
}

/// One row of the index: an episode, its outcome and its page (relative link).
#[derive(Clone, Debug, Serialize)]
pub struct IndexRow {
    pub href: String,
    /// The cell's key (`Cell::key`); its parts follow.
    pub cell: String,
    pub experiment: String,
    pub ego: String,
    pub flow: String,
    pub scenario: String,
    pub svo_deg: Option<u32>,
    pub vehicles: Option<usize>,
    pub case: u32,
    pub seed: u32,
    /// The episode's outcome class: `collision`, `off-road`, `off-route`, `wrong-lane`,
    /// `road-closed`, `timeout` or `success` (the first that any scored agent had, in that order).
    pub outcome: String,
    pub metrics: EpisodeMetrics,
    /// Whether the replay ended as the stored row says (`None`: no stored row).
    pub replay_agrees: Option<bool>,
}

/// The outcome class of an episode's metrics, worst first: the order the index sorts by.
pub const OUTCOMES: [&str; 7] =
    ["collision", "off-road", "off-route", "wrong-lane", "road-closed", "timeout", "success"];

/// The worst outcome any scored agent of the episode had ([`OUTCOMES`]' order).
pub fn outcome_class(m: &EpisodeMetrics) -> &'static str {
    let shares = [
        m.collision,
        m.off_road,
        m.off_route,
        m.wrong_lane,
        m.road_closed,
        m.timeout,
        m.scores.success,
    ];
    OUTCOMES.iter().zip(shares).find(|(_, s)| *s > 0.0).map_or("success", |(o, _)| *o)
}

/// The index page over `rows`, sorted as given (the page sorts by any column on a click).
pub fn index(title: &str, rows: &[impl Serialize]) -> Result<String, EvalError> {
    Ok(INDEX.replace("__TITLE__", &escape_html(title)).replace("__ROWS__", &script_json(&rows)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_outcome_class_is_the_worst_any_agent_had() {
        let mut m = EpisodeMetrics { agents: 4, ..Default::default() };
        m.scores.success = 0.5;
        m.timeout = 0.25;
        m.road_closed = 0.25;
        assert_eq!(outcome_class(&m), "road-closed");
        m.off_road = 0.25;
        assert_eq!(outcome_class(&m), "off-road");
        m.collision = 0.5;
        assert_eq!(outcome_class(&m), "collision");
        let ok = EpisodeMetrics {
            scores: sf_sim::Scores { success: 1.0, ..Default::default() },
            ..Default::default()
        };
        assert_eq!(outcome_class(&ok), "success");
    }

    #[test]
    fn script_text_cannot_close_its_element() {
        let s = script_json(&"</script><b>").expect("json");
        assert!(!s.contains("</"), "{s}");
        assert_eq!(escape_html("<a href=\"x\">&"), "&lt;a href=&quot;x&quot;&gt;&amp;");
    }
}
