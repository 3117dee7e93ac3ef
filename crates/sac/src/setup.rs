//! A job config (`sf_job::JobConfig`) resolved into the simulator, network and SAC configs.
//!
//! Owns: the one mapping from job-config sections to `SimConfig`, `NetConfig`, `SacConfig`
//! and the rate limiter, shared by the learner and the workers so both build the same shapes.
//! Must not: read files.

use sf_job::config::{Device, Encoder, NetPreset, SacSection, SvoSeen};
use sf_job::JobConfig;
use sf_nn::device::DeviceKind;
use sf_nn::{EncoderKind, NetConfig, SvoInput};
use sf_sim::config::SvoVisibility;
use sf_sim::env::Controller;
use sf_sim::{Layout, Mode, ObsSpec, SimConfig};

use crate::{RateLimiterConfig, SacConfig};

/// The network of the job's ego policy.
pub fn net_config(job: &JobConfig) -> NetConfig {
    let mut n = match job.net.preset {
        NetPreset::Paper => NetConfig::paper(),
        NetPreset::Compact => NetConfig::compact(),
        NetPreset::Fast => NetConfig::fast(),
    };
    if let Some(e) = job.net.encoder {
        n.encoder = match e {
            Encoder::EgoFrame => EncoderKind::EgoFrame,
            Encoder::QueryCentric => EncoderKind::QueryCentric,
        };
    }
    if let Some(w) = job.net.width {
        n.d_model = w;
        n.set_hidden = w;
        n.head_hidden = 2 * w;
    }
    n.svo = match job.kind.svo_seen() {
        SvoSeen::None => SvoInput::None,
        SvoSeen::Own => SvoInput::Own,
        SvoSeen::All => SvoInput::All,
    };
    n
}

/// How the job's simulators run: every vehicle a learner for a flow, one ego among IDM cars
/// otherwise.
pub fn mode(job: &JobConfig) -> Mode {
    if job.kind.multi_agent() {
        Mode::MultiAgent
    } else if job.env.background_job.is_some() {
        Mode::Ego { background: Controller::External }
    } else {
        Mode::Ego { background: Controller::Idm }
    }
}

/// The reward a transition carries for this job.
pub fn reward(job: &JobConfig, r: &sf_sim::env::Rewards) -> f32 {
    if job.kind.composed_reward() {
        r.composed
    } else {
        r.individual
    }
}

/// Simulator settings: digest defaults with the observation layout the encoder reads.
pub fn sim_config(job: &JobConfig) -> SimConfig {
    let mut s = SimConfig::default();
    s.obs.layout = match net_config(job).encoder {
        EncoderKind::EgoFrame => Layout::EgoFrame,
        EncoderKind::QueryCentric => Layout::QueryCentric,
    };
    s.obs.svo = match job.kind.svo_seen() {
        // A frozen flow in the background may read SVOs; every network zeroes the SVO channels
        // it does not consume (`ObsBatch::from_rows`), so the ego still sees none.
        SvoSeen::None if job.env.background_job.is_some() => SvoVisibility::All,
        SvoSeen::None => SvoVisibility::None,
        SvoSeen::Own => SvoVisibility::Own,
        SvoSeen::All => SvoVisibility::All,
    };
    s
}

pub fn obs_spec(job: &JobConfig) -> ObsSpec {
    ObsSpec::new(&sim_config(job).obs)
}

pub fn sac_config(job: &JobConfig) -> SacConfig {
    sac_from_section(&job.sac)
}

/// A job config's `[sac]` section as the SAC crate's config.
pub fn sac_from_section(s: &SacSection) -> SacConfig {
    SacConfig {
        gamma: s.gamma,
        tau: s.tau,
        lr_actor: s.lr_actor,
        lr_critic: s.lr_critic,
        lr_alpha: s.lr_alpha,
        batch_size: s.batch_size,
        initial_alpha: s.initial_alpha,
        target_entropy: None,
        reward_scale: s.reward_scale,
        warmup_steps: s.warmup_steps,
        seed: s.seed,
        device: device_kind(s.device),
        reuse_critic_features: true,
    }
}

pub fn device_kind(d: Device) -> DeviceKind {
    match d {
        Device::Cpu => DeviceKind::Cpu,
        Device::Ndarray => DeviceKind::Ndarray,
        Device::Cuda => DeviceKind::Cuda,
    }
}

/// The replay ratio as a rate limiter. `min_size` is the fill before the first update; the
/// error buffer lets one worker batch in at a time without blocking on itself.
pub fn rate_limiter(job: &JobConfig, min_size: u64) -> RateLimiterConfig {
    let spi = job.train.samples_per_insert;
    let batch = job.worker.batch_transitions as f64;
    RateLimiterConfig { samples_per_insert: spi, min_size_to_sample: min_size.max(1), error_buffer: (spi * batch).max(spi).max(1.0) * 2.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(kind: &str) -> JobConfig {
        JobConfig::from_toml(&format!("name = \"t\"\nkind = \"{kind}\"\n[env]\nscenarios = [\"merge\"]\n[sac]\nwarmup_steps = 10\n[train]\nenv_steps = 100\n")).expect("valid")
    }

    /// The network consumes exactly the SVO channels the observation fills, per flow.
    #[test]
    fn each_kind_sees_and_is_rewarded_as_the_paper_says() {
        let r = sf_sim::env::Rewards { individual: 1.0, composed: 2.0, failmaker: 3.0 };
        for (kind, svo, vis, multi, composed) in [
            ("ego", SvoInput::None, SvoVisibility::None, false, false),
            ("macad", SvoInput::None, SvoVisibility::None, true, false),
            ("copo", SvoInput::Own, SvoVisibility::Own, true, true),
            ("socialcomm", SvoInput::All, SvoVisibility::All, true, true),
        ] {
            let j = job(kind);
            assert_eq!(net_config(&j).svo, svo, "{kind}");
            assert_eq!(sim_config(&j).obs.svo, vis, "{kind}");
            assert_eq!(mode(&j) == Mode::MultiAgent, multi, "{kind}");
            assert_eq!(reward(&j, &r), if composed { 2.0 } else { 1.0 }, "{kind}");
        }
    }
}

#[cfg(test)]
mod defaults {
    use super::*;

    /// The paper's table (gamma 0.9, batch 128, Adam 1e-4 / 5e-4 / 1e-4, tau 0.005, alpha 1).
    #[test]
    fn sac_defaults_are_the_papers() {
        let c = SacConfig::default();
        assert_eq!((c.gamma, c.tau, c.batch_size, c.initial_alpha, c.reward_scale), (0.9, 0.005, 128, 1.0, 1.0));
        assert_eq!((c.lr_actor, c.lr_critic, c.lr_alpha), (1e-4, 5e-4, 1e-4));
        assert_eq!((c.warmup_steps, c.target_entropy, c.reuse_critic_features), (30_000, None, true));
    }
}
