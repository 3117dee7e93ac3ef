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
    /// Any GPU through burn's wgpu backend (Vulkan on Linux; WGSL shaders compiled by naga)
    /// (needs the `wgpu` feature; builds from the package registries alone, unlike `cuda`).
    Wgpu,
    /// burn's deprecated `ndarray` CPU backend (needs the `ndarray` or `openblas` feature);
    /// kept for backend measurements.
    Ndarray,
}

#[derive(Clone, Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("device `{0}` needs a build with the `{0}` feature of socialflow-nn")]
    NotBuilt(&'static str),
    #[error("device `{0}` is built in but unusable here (no GPU or driver?): {1}")]
    Unavailable(&'static str, String),
}

/// The inference device of a kind (no autodiff).
pub fn device(kind: DeviceKind) -> Result<Device, DeviceError> {
    match kind {
        DeviceKind::Cpu => Ok(Device::flex()),
        #[cfg(feature = "cuda")]
        DeviceKind::Cuda => {
            static PROBE: std::sync::OnceLock<Result<(), DeviceError>> = std::sync::OnceLock::new();
            probe(&PROBE, "cuda", || Device::cuda(0))
        }
        #[cfg(not(feature = "cuda"))]
        DeviceKind::Cuda => Err(DeviceError::NotBuilt("cuda")),
        #[cfg(feature = "wgpu")]
        DeviceKind::Wgpu => {
            static PROBE: std::sync::OnceLock<Result<(), DeviceError>> = std::sync::OnceLock::new();
            probe(&PROBE, "wgpu", || Device::wgpu(burn::tensor::DeviceKind::DefaultDevice))
        }
        #[cfg(not(feature = "wgpu"))]
        DeviceKind::Wgpu => Err(DeviceError::NotBuilt("wgpu")),
        #[cfg(feature = "ndarray")]
        DeviceKind::Ndarray => Ok(Device::ndarray()),
        #[cfg(not(feature = "ndarray"))]
        DeviceKind::Ndarray => Err(DeviceError::NotBuilt("ndarray")),
    }
}

/// A GPU device after a round trip of one small tensor: burn initialises its GPU runtimes
/// lazily and panics deep inside on a machine without the GPU or its driver; this turns that into
/// an error at the first look (before a learner binds its ports or a job is accepted). Checked
/// once per process and kind (`once`).
#[cfg(any(feature = "cuda", feature = "wgpu"))]
fn probe(
    once: &'static std::sync::OnceLock<Result<(), DeviceError>>,
    name: &'static str,
    make: fn() -> Device,
) -> Result<Device, DeviceError> {
    let r = once.get_or_init(|| {
        let quiet = std::panic::take_hook();
        std::panic::set_hook(Box::new(|_| {}));
        let r = std::panic::catch_unwind(|| {
            let d = make();
            let t = burn::tensor::Tensor::<1>::from_data(
                burn::tensor::TensorData::new(vec![1.0f32, 2.0], [2]),
                &d,
            );
            t.into_data().try_to_vec::<f32>().map(|v| v.len()).unwrap_or(0)
        });
        std::panic::set_hook(quiet);
        match r {
            Ok(2) => Ok(()),
            Ok(n) => Err(DeviceError::Unavailable(
                name,
                format!("a test tensor came back with {n} values"),
            )),
            Err(p) => Err(DeviceError::Unavailable(
                name,
                p.downcast_ref::<String>()
                    .cloned()
                    .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| format!("{name} initialisation panicked")),
            )),
        }
    });
    r.clone().map(|()| make())
}

/// The training device of a kind (autodiff enabled).
pub fn train_device(kind: DeviceKind) -> Result<Device, DeviceError> {
    Ok(device(kind)?.autodiff())
}

/// Keeps freed memory in the process instead of returning it to the kernel after every
/// tensor: burn allocates and frees many large buffers per update and per inference batch, and
/// glibc's defaults turn each into mmap/munmap plus page faults (measured: ~1.5x on SAC
/// updates). Every binary that runs the networks calls it first thing in `main`, before any
/// thread starts.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator thresholds; it is called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_TOP_PAD, 64 << 20);
    }
}
