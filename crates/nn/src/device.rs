//! Device selection: the one place that turns configuration into a burn [`Device`].

pub use burn::tensor::Device;
use serde::{Deserialize, Serialize};

/// Where tensors live.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DeviceKind {
    /// burn's pure-Rust CPU backend (`flex`) with SIMD, rayon and AVX-512 dispatch.
    #[default]
    Cpu,
    /// An NVIDIA GPU (needs the `cuda` feature).
    Cuda,
    /// burn's deprecated `ndarray` CPU backend (needs the `ndarray` or `openblas` feature);
    /// kept for backend measurements.
    Ndarray,
}

#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("device `{0}` needs a build with the `{0}` feature of socialflow-nn")]
    NotBuilt(&'static str),
}

/// The inference device of a kind (no autodiff).
pub fn device(kind: DeviceKind) -> Result<Device, DeviceError> {
    match kind {
        DeviceKind::Cpu => Ok(Device::flex()),
        #[cfg(feature = "cuda")]
        DeviceKind::Cuda => Ok(Device::cuda(0)),
        #[cfg(not(feature = "cuda"))]
        DeviceKind::Cuda => Err(DeviceError::NotBuilt("cuda")),
        #[cfg(feature = "ndarray")]
        DeviceKind::Ndarray => Ok(Device::ndarray()),
        #[cfg(not(feature = "ndarray"))]
        DeviceKind::Ndarray => Err(DeviceError::NotBuilt("ndarray")),
    }
}

/// The training device of a kind (autodiff enabled).
pub fn train_device(kind: DeviceKind) -> Result<Device, DeviceError> {
    Ok(device(kind)?.autodiff())
}
