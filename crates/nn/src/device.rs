//! Device selection: the one place that turns configuration into a burn [`Device`].

use burn::tensor::Device;
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
}

#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("device `cuda` needs a build with the `cuda` feature (cargo build --features sf-nn/cuda)")]
    CudaNotBuilt,
}

/// The inference device of a kind (no autodiff).
pub fn device(kind: DeviceKind) -> Result<Device, DeviceError> {
    match kind {
        DeviceKind::Cpu => Ok(Device::flex()),
        #[cfg(feature = "cuda")]
        DeviceKind::Cuda => Ok(Device::cuda(0)),
        #[cfg(not(feature = "cuda"))]
        DeviceKind::Cuda => Err(DeviceError::CudaNotBuilt),
    }
}

/// The training device of a kind (autodiff enabled).
pub fn train_device(kind: DeviceKind) -> Result<Device, DeviceError> {
    Ok(device(kind)?.autodiff())
}
