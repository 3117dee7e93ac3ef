//! The rung's episodes: who sits in the ego's seat ([`Driver`]: the trained policy, the IDM
//! driver, or IDM with MOBIL's lane changes), its rows on every evaluated case and seed
//! ([`evaluate`], paired across drivers: the same cases, seeds and batch) and its GIFs.
//!
//! Must not: judge the rows (the gate is `report`'s) or train anything.

use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use sf_rollout::drive::{self, Actor, Drivers};
use sf_rollout::evaluate::{EgoDef, FlowDef, Policy, Runners};
use sf_sim::env::{Controller, Mode};
use sf_sim::metrics::EpisodeMetrics;
use sf_sim::vec_env::{EpisodeSpec, VecEnv};
use sf_sim::{CaseFile, DriveAction, Map, SimConfig};

use super::{Row, RungEval};

/// Who drives the ego's seat in a rung's episodes.
#[derive(Clone, Copy)]
pub(super) enum Driver<'a> {
    /// A trained policy: its mean action (sampled actions with `eval.sampled`).
    Policy(&'a Policy),
    /// The IDM driver (an acceleration residual of zero: IDM exactly), the rung's baseline.
    Idm,
    /// IDM with MOBIL's lane changes (`sf_sim::mobil`), a scripted reference that steers
    /// (`socialflow ladder --scripted idm-mobil`).
    IdmMobil,
}

impl Driver<'_> {
    /// Its name in `episodes.csv`'s `driver` column.
    pub(super) fn name(self) -> &'static str {
        match self {
            Self::Policy(_) => "policy",
            Self::Idm => "idm",
            Self::IdmMobil => sf_job::eval::IDM_MOBIL,
        }
    }
}

/// The evaluation episodes of one scenario with `driver` in the ego's seat among IDM cars.
pub(super) fn evaluate(
    e: &RungEval,
    train_seed: u64,
    map: &Arc<Map>,
    cases: &CaseFile,
    driver: Driver,
    runners: &mut Runners,
) -> Result<Vec<Row>> {
    let n = e.cases as usize;
    if n > cases.cases.len() {
        bail!("eval.cases: {n} exceeds the {} stored cases of {}", cases.cases.len(), map.name);
    }
    let policy = match driver {
        Driver::Policy(p) => Some(p),
        Driver::Idm | Driver::IdmMobil => None,
    };
    let sim = Arc::new(match policy {
        Some(p) => p.resolved().sim.clone(),
        None => SimConfig::default(),
    });
    let runner =
        policy.map(|p| runners.get(p, map, &sim)).transpose().map_err(anyhow::Error::msg)?;
    let drivers = Drivers {
        alive: match (&runner, driver) {
            (Some(r), _) if e.sampled => Actor::sampled(r),
            (Some(r), _) => Actor::mean(r),
            (None, Driver::IdmMobil) => Actor::Mobil(sf_sim::mobil::MobilParams::default()),
            (None, _) => Actor::Demo { noise: 0.0, action: DriveAction::IdmAccelResidual },
        },
        background: None,
        adversary: None,
    };
    let vehicles = |c: usize| {
        if e.vehicles.is_empty() {
            None
        } else {
            Some(e.vehicles[c % e.vehicles.len()])
        }
    };
    let mut rows = Vec::new();
    for seed in 0..e.seeds {
        let eps: Vec<EpisodeSpec> = (0..n)
            .map(|c| EpisodeSpec {
                case: cases.cases[c].clone(),
                vehicles: vehicles(c),
                svo_deg: None,
                tag: (seed as u64) << 32 | c as u64,
            })
            .collect();
        let mut v = VecEnv::from_episodes(
            Arc::clone(map),
            Arc::clone(&sim),
            Mode::Ego { background: Controller::Idm },
            e.envs,
            eps,
        )
        .map_err(anyhow::Error::msg)?;
        let mut done: Vec<Option<EpisodeMetrics>> = vec![None; n];
        for (tag, m) in drive::run_episodes(&mut v, &drivers, |_, _| {}) {
            done[(tag & 0xffff_ffff) as usize] = Some(m);
        }
        for (c, m) in done.into_iter().enumerate() {
            let m = m.with_context(|| format!("case {c} did not finish"))?;
            rows.push(Row {
                train_seed,
                driver: driver.name(),
                scenario: map.name.clone(),
                case: cases.cases[c].id,
                seed,
                vehicles: vehicles(c)
                    .unwrap_or(cases.cases[c].vehicles.len())
                    .min(cases.cases[c].vehicles.len()),
                success: m.scores.success,
                collision: m.collision,
                other_failure: m.off_road + m.off_route + m.wrong_lane,
                timeout: m.timeout,
                speed: m.scores.speed,
                lane_change: m.lane_change,
            });
        }
    }
    Ok(rows)
}

/// `eval.gifs` episodes of `map`'s first cases with `driver` in the ego's seat among IDM cars,
/// one GIF each into `dir` (`gif-<scenario>-case-<c>.gif` for a policy, with `-idm` or
/// `-idm-mobil` before `.gif` for the scripted drivers).
pub(super) fn render_gifs(
    e: &RungEval,
    map: &Arc<Map>,
    cases: &CaseFile,
    driver: Driver,
    runners: &mut Runners,
    dir: &Path,
) -> Result<()> {
    let (ego, suffix) = match driver {
        Driver::Policy(p) => (EgoDef::Learned(p.clone()), String::new()),
        Driver::Idm => (EgoDef::Idm, format!("-{}", driver.name())),
        Driver::IdmMobil => (EgoDef::IdmMobil, format!("-{}", driver.name())),
    };
    for c in 0..e.gifs.min(cases.cases.len() as u32) {
        let path = dir.join(format!("gif-{}-case-{c}{suffix}.gif", map.name));
        sf_rollout::evaluate::render_gif(
            Some(("ego", &ego)),
            &[("IDM", &FlowDef::Idm)],
            c,
            map,
            cases,
            runners,
            &path,
            sf_job::eval::Gifs::DEFAULT_SIZE_PX,
        )
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("rendering {}", path.display()))?;
    }
    Ok(())
}
