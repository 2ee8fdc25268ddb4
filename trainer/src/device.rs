//! Where the training step runs: the CPU (rayon workers over chunks) or a GPU through wgpu
//! (`msth_gpu::step::GpuStep`: the whole step on the device, the ray batch drawn on the CPU).
//!
//! Both compute the same step from the same random numbers: the GPU step takes each ray's two
//! jitters from the CPU trainer's per-chunk streams ([`host_draws`]), so a seed draws the same
//! samples on either device, and the results differ only by rounding (`gpu/tests/step.rs`).
//! Checkpoints hold the same parameters and Adam state whichever device wrote them, so a run
//! moves between devices on `--resume`.

use std::fmt;
use std::str::FromStr;

use msth_core::pipeline::{free_space_point, TimedRay};
use msth_core::rng::Rng;
use msth_gpu::device::ComputeDevice;
use msth_gpu::step::GpuStep;
use msth_gpu::{AdapterPolicy, GpuError};

/// Where `msth train` runs its steps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TrainDevice {
    /// A hardware GPU adapter when there is one (or a software one with `MSTH_GPU_SOFTWARE=1`),
    /// else the CPU.
    Auto,
    #[default]
    Cpu,
    /// A GPU adapter, software ones (lavapipe) included; an error when there is none.
    Gpu,
}

impl FromStr for TrainDevice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "auto" => Ok(TrainDevice::Auto),
            "cpu" => Ok(TrainDevice::Cpu),
            "gpu" => Ok(TrainDevice::Gpu),
            _ => Err(format!("`{s}` is not a device: auto, cpu or gpu")),
        }
    }
}

impl fmt::Display for TrainDevice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            TrainDevice::Auto => "auto",
            TrainDevice::Cpu => "cpu",
            TrainDevice::Gpu => "gpu",
        })
    }
}

/// Why the GPU step could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("--device gpu: no GPU adapter found ({0}); install a Vulkan driver (e.g. Mesa's lavapipe: mesa-vulkan-drivers) or train with --device cpu")]
    NoAdapter(String),
    #[error("training on the GPU (--device cpu trains on the CPU)")]
    Gpu(#[from] GpuError),
    #[error("--device gpu: {0}; train with --device cpu")]
    Unsupported(String),
}

/// A model in training on a GPU.
pub struct GpuTraining {
    pub dev: ComputeDevice,
    pub step: GpuStep,
    /// The parameters and Adam state on the host are older than the device's.
    pub stale: bool,
}

/// Opens the adapter `device` asks for: `Ok(None)` for the CPU (asked for, or `auto` without a
/// hardware adapter), an error for `gpu` without an adapter.
pub fn open(device: TrainDevice) -> Result<Option<ComputeDevice>, DeviceError> {
    let policy = match device {
        TrainDevice::Cpu => return Ok(None),
        TrainDevice::Auto => AdapterPolicy::automatic(),
        TrainDevice::Gpu => AdapterPolicy::any(),
    };
    match ComputeDevice::open(policy) {
        Ok(d) => Ok(Some(d)),
        Err(GpuError::NoAdapter(_)) if device == TrainDevice::Auto => Ok(None),
        Err(GpuError::NoAdapter(why)) => Err(DeviceError::NoAdapter(why)),
        Err(e) => Err(DeviceError::Gpu(e)),
    }
}

/// The random stream of chunk `chunk` of step `step`: the CPU trainer's chunks draw from it, and
/// [`host_draws`] draws the GPU step's numbers from it.
pub fn chunk_stream(seed: u64, step: u64, chunk: usize) -> Rng {
    Rng::stream(seed, (step << 20) | chunk as u64)
}

/// The random numbers the CPU trainer draws for a batch, chunk by chunk from [`chunk_stream`]:
/// per ray the proposal edges' jitter and the resampling's (within a chunk first one proposal
/// jitter per ray, then one resampling jitter per ray), then, when `free_space`, one
/// free-space point per ray (`msth_core::pipeline::free_space_point`; empty otherwise).
pub fn host_draws(
    rays: &[TimedRay],
    chunk: usize,
    seed: u64,
    step: u64,
    free_space: bool,
) -> (Vec<(f32, f32)>, Vec<[f32; 4]>) {
    let chunk = chunk.max(1);
    let mut jitters = Vec::with_capacity(rays.len());
    let mut points = Vec::new();
    for (c, part) in rays.chunks(chunk).enumerate() {
        let mut rng = chunk_stream(seed, step, c);
        let first: Vec<f32> = part.iter().map(|_| rng.f32()).collect();
        jitters.extend(first.into_iter().map(|p| (p, rng.f32())));
        if free_space {
            points.extend(part.iter().map(|_| free_space_point(&mut rng)));
        }
    }
    (jitters, points)
}
