//! A job config (`sf_job::JobConfig`) resolved once into everything that runs it.
//!
//! Owns: [`resolve`], the one mapping from job-config sections to a [`ResolvedJob`] (the
//! simulator config, the network, the observation layout, the SAC config and the mode), shared
//! by the learner, the workers, evaluation and the CLI so all build the same shapes; the
//! per-transition reward and the adversary's SVO ([`reward`], [`adversary_svo_deg`]); the rate
//! limiter (the device kind is `sf_sac::device_kind`). Callers take the resolved value's fields
//! instead of deriving them one by one. Must not: read files.

use sf_job::config::{JobKind, NetPreset, RewardNeighbours};
use sf_job::JobConfig;
use sf_nn::NetConfig;
use sf_sim::config::SvoVisibility;
use sf_sim::env::Controller;
use sf_sim::{Mode, ObsSpec, SimConfig};

use sf_sac::{RateLimiterConfig, SacConfig};

/// A job config resolved: everything that runs the job or one of its policies.
#[derive(Clone, Debug)]
pub struct ResolvedJob {
    /// The simulators its episodes run in (observation layout, SVO visibility and range).
    pub sim: SimConfig,
    /// The network of its policy.
    pub net: NetConfig,
    /// The observation layout that network reads (the same whatever the background).
    pub obs: ObsSpec,
    /// Its `[sac]` section, which is the SAC config.
    pub sac: SacConfig,
    /// Who drives what in its simulators.
    pub mode: Mode,
}

/// Resolves `job`. `background` is the config of the job named in `env.background_job` (the
/// frozen flow), whose kind decides what the background's observations must carry and whose
/// `env.svo_range_deg` the background's SVOs are drawn from; it changes `sim` only.
pub fn resolve(job: &JobConfig, background: Option<&JobConfig>) -> ResolvedJob {
    ResolvedJob {
        sim: sim_config(job, background),
        net: net_config(job),
        obs: obs_spec(job),
        sac: job.sac.clone(),
        mode: mode(job),
    }
}

/// The network of the job's ego policy.
fn net_config(job: &JobConfig) -> NetConfig {
    let mut n = match job.net.preset {
        NetPreset::Paper => NetConfig::paper(),
        NetPreset::Compact => NetConfig::compact(),
        NetPreset::Fast => NetConfig::fast(),
    };
    if let Some(e) = job.net.encoder {
        n.encoder = e;
    }
    if let Some(w) = job.net.width {
        n.d_model = w;
        n.set_hidden = w;
        n.head_hidden = 2 * w;
    }
    n.svo = job.kind.svo_seen();
    n.ego_flag = job.kind == JobKind::Failmaker;
    n.action_dim = job.action_dim();
    n.action = if job.kind.drives() { job.env.action } else { sf_sim::DriveAction::Direct };
    if let Some(p) = job.net.pose_layers {
        n.pose_layers = p;
    }
    n.ego_skip = job.net.ego_skip;
    n.critic_layer_norm = job.net.critic_layer_norm;
    n.squash_mean_twice = job.net.squash_mean_twice;
    if let Some(m) = job.net.log_std_min {
        n.log_std_min = m;
    }
    // A demonstrator's warm-up: the first policy is as spread as the demonstrator.
    if job.sac.warmup_policy == sf_job::config::WarmupPolicy::Idm {
        n.init_log_std = job.sac.bc_log_std(n.log_std_min);
    }
    n
}

/// How the job's simulators run: every vehicle a learner for a Stage-1 flow; otherwise agent 0
/// is the ego (the learner of ego jobs, the frozen ego of RARL phases, whose episode decides
/// the episode's end) among IDM cars or an externally driven background.
fn mode(job: &JobConfig) -> Mode {
    if job.kind.multi_agent() {
        Mode::MultiAgent
    } else if job.env.background_job.is_some() || job.kind == JobKind::Failmaker {
        Mode::Ego { background: Controller::External }
    } else {
        Mode::Ego { background: Controller::Idm }
    }
}

/// The reward a transition carries for this job: the adversary's is exactly `-R_ego` (the
/// learner applies `sac.reward_scale` to every reward alike).
pub fn reward(job: &JobConfig, r: &sf_sim::env::Rewards) -> f32 {
    match job.kind {
        JobKind::Failmaker => r.failmaker,
        JobKind::SocialcommAdv => -r.individual,
        k if k.composed_reward() => r.composed,
        _ => r.individual,
    }
}

/// The adversary's action in [-1, 1] as the SVO it communicates, degrees in [0, 90].
pub fn adversary_svo_deg(action: f32) -> f32 {
    (action.clamp(-1.0, 1.0) + 1.0) * 45.0
}

/// Simulator settings: digest defaults with the observation layout the encoder reads.
/// `background` is the config of the job named in `env.background_job` (the frozen flow), which
/// decides what the background's observations must carry and where their SVOs are drawn from.
fn sim_config(job: &JobConfig, background: Option<&JobConfig>) -> SimConfig {
    let mut s = SimConfig::default();
    let svo_owner = background.unwrap_or(job);
    let background = background.map(|b| b.kind);
    s.obs.layout = net_config(job).encoder;
    s.obs.svo = match job.kind.svo_seen() {
        // A frozen flow in the background may read SVOs; every network zeroes the SVO channels
        // it does not consume (`ObsBatch::from_rows`), so the ego still sees none.
        SvoVisibility::None if background.is_some() => SvoVisibility::All,
        seen => seen,
    };
    if let Some(n) = job.env.max_neighbours {
        s.obs.max_neighbours = n;
    }
    if let Some(n) = job.env.max_segments {
        s.obs.max_segments = n;
    }
    if job.env.reward_neighbours == RewardNeighbours::Observed {
        s.reward.neighbour_radius_m = s.obs.radius_m;
        s.reward.max_neighbours = Some(s.obs.max_neighbours);
    }
    // FailMaker's agents tell the ego apart and carry c in [-90, 90] as their SVO.
    if job.kind == JobKind::Failmaker || background == Some(JobKind::Failmaker) {
        s.obs.ego_flag = true;
        s.svo_range_deg = [-90.0, 90.0];
    }
    // A flow job's own range (e.g. a FailMaker whose every vehicle wants the ego to lose), also
    // where it is the background.
    if let Some(r) = svo_owner.env.svo_range_deg {
        s.svo_range_deg = r;
    }
    s
}

/// The observation layout (independent of the background: only SVO and flag values vary).
fn obs_spec(job: &JobConfig) -> ObsSpec {
    ObsSpec::new(&sim_config(job, None).obs)
}

/// The replay ratio as a rate limiter. `min_size` is the fill before the first update; the
/// error buffer lets one worker batch in at a time without blocking on itself.
pub fn rate_limiter(job: &JobConfig, min_size: u64) -> RateLimiterConfig {
    let spi = job.train.samples_per_insert;
    let batch = job.worker.batch_transitions as f64;
    RateLimiterConfig {
        samples_per_insert: spi,
        min_size_to_sample: min_size.max(1),
        error_buffer: (spi * batch).max(spi).max(1.0) * 2.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(kind: &str) -> JobConfig {
        let deps = match kind {
            "failmaker" => "ego_job = 1\n",
            "socialcomm-adv" => "ego_job = 1\nbackground_job = 2\n",
            _ => "",
        };
        JobConfig::from_toml(&format!("name = \"t\"\nkind = \"{kind}\"\n[env]\nscenarios = [\"merge\"]\n{deps}[sac]\nwarmup_steps = 10\n[train]\nenv_steps = 100\n")).expect("valid")
    }

    /// The network consumes exactly the SVO channels the observation fills, per flow.
    #[test]
    fn each_kind_sees_and_is_rewarded_as_the_paper_says() {
        let r = sf_sim::env::Rewards { individual: 1.0, composed: 2.0, failmaker: 3.0 };
        for (kind, svo, vis, multi, want) in [
            ("ego", SvoVisibility::None, SvoVisibility::None, false, 1.0),
            ("macad", SvoVisibility::None, SvoVisibility::None, true, 1.0),
            ("copo", SvoVisibility::Own, SvoVisibility::Own, true, 2.0),
            ("socialcomm", SvoVisibility::All, SvoVisibility::All, true, 2.0),
            ("failmaker", SvoVisibility::Own, SvoVisibility::Own, false, 3.0),
            ("socialcomm-adv", SvoVisibility::None, SvoVisibility::All, false, -1.0),
        ] {
            let j = job(kind);
            let flow = job("socialcomm");
            let bg = (kind == "socialcomm-adv").then_some(&flow);
            assert_eq!(net_config(&j).svo, svo, "{kind}");
            assert_eq!(sim_config(&j, bg).obs.svo, vis, "{kind}");
            assert_eq!(mode(&j) == Mode::MultiAgent, multi, "{kind}");
            assert_eq!(reward(&j, &r), want, "{kind}");
            assert_eq!(
                net_config(&j).action_dim,
                if kind == "socialcomm-adv" { 1 } else { 2 },
                "{kind}"
            );
            assert_eq!(net_config(&j).ego_flag, kind == "failmaker", "{kind}");
        }
    }

    /// FailMaker's background tells the ego apart and draws c from [-90, 90], also when an ego
    /// trains against it; other flows keep [0, 90] and no flag.
    #[test]
    fn failmaker_observations_flag_the_ego_and_widen_the_svo_range() {
        let ego = job("ego");
        let (socialcomm, failmaker) = (job("socialcomm"), job("failmaker"));
        for (bg, flag, lo) in
            [(None, false, 0.0), (Some(&socialcomm), false, 0.0), (Some(&failmaker), true, -90.0)]
        {
            let s = sim_config(&ego, bg);
            assert_eq!(
                (s.obs.ego_flag, s.svo_range_deg[0]),
                (flag, lo),
                "{:?}",
                bg.map(|b| b.kind)
            );
        }
        let s = sim_config(&failmaker, None);
        assert_eq!((s.obs.ego_flag, s.svo_range_deg), (true, [-90.0, 90.0]));
        // A FailMaker whose every vehicle wants the ego to lose: its own range, also as a
        // background.
        let mut hostile = failmaker.clone();
        hostile.env.svo_range_deg = Some([-90.0, -90.0]);
        assert_eq!(sim_config(&hostile, None).svo_range_deg, [-90.0, -90.0]);
        assert_eq!(sim_config(&ego, Some(&hostile)).svo_range_deg, [-90.0, -90.0]);
        assert_eq!(adversary_svo_deg(-1.0), 0.0);
        assert_eq!(adversary_svo_deg(1.0), 90.0);
    }

    /// `resolve` is the parts together; the background changes the simulator only.
    #[test]
    fn resolve_is_the_parts_and_the_background_changes_only_the_simulator() {
        let ego = job("ego");
        let failmaker = job("failmaker");
        let (plain, with_bg) = (resolve(&ego, None), resolve(&ego, Some(&failmaker)));
        assert_eq!(
            (&plain.net, &plain.obs, plain.mode),
            (&net_config(&ego), &obs_spec(&ego), mode(&ego))
        );
        assert_eq!((&with_bg.net, &with_bg.obs), (&plain.net, &plain.obs));
        assert!(with_bg.sim.obs.ego_flag && !plain.sim.obs.ego_flag);
        assert_eq!(plain.sac, ego.sac);
    }
}

#[cfg(test)]
mod defaults {
    use super::*;

    /// The paper's table (gamma 0.9, batch 128, Adam 1e-4 / 5e-4 / 1e-4, tau 0.005, alpha 1,
    /// reward scale 50), and a job's `[sac]` section is what SAC runs with.
    #[test]
    fn sac_defaults_are_the_papers() {
        let c = SacConfig::default();
        assert_eq!(
            (c.gamma, c.tau, c.batch_size, c.initial_alpha, c.reward_scale),
            (0.9, 0.005, 128, 1.0, 50.0)
        );
        assert_eq!((c.lr_actor, c.lr_critic, c.lr_alpha), (1e-4, 5e-4, 1e-4));
        assert_eq!(
            (c.warmup_steps, c.target_entropy, c.reuse_critic_features),
            (30_000, None, true)
        );
    }
}
