//! A job config (`sf_job::JobConfig`) resolved into the simulator, network and SAC configs.
//!
//! Owns: the one mapping from job-config sections to `SimConfig`, `NetConfig`, `SacConfig`
//! and the rate limiter, shared by the learner and the workers so both build the same shapes.
//! Must not: read files.

use sf_job::config::{Device, Encoder, NetPreset};
use sf_job::JobConfig;
use sf_nn::device::DeviceKind;
use sf_nn::{EncoderKind, NetConfig};
use sf_sim::{Layout, ObsSpec, SimConfig};

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
    n
}

/// Simulator settings: digest defaults with the observation layout the encoder reads.
pub fn sim_config(job: &JobConfig) -> SimConfig {
    let mut s = SimConfig::default();
    s.obs.layout = match net_config(job).encoder {
        EncoderKind::EgoFrame => Layout::EgoFrame,
        EncoderKind::QueryCentric => Layout::QueryCentric,
    };
    s
}

pub fn obs_spec(job: &JobConfig) -> ObsSpec {
    ObsSpec::new(&sim_config(job).obs)
}

pub fn sac_config(job: &JobConfig) -> SacConfig {
    let s = &job.sac;
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
