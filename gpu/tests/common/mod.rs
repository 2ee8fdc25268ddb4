//! What the kernel tests share: the `gpu` need (a compute device can be opened), the device,
//! and the atomic paths to test on it. Each test binary uses part of it.
#![allow(dead_code)]

use glam::Vec3;
use msth_core::config::{Background, ModelConfig, Preset};
use msth_core::sampling::Spacing;
use msth_core::scene::SceneBounds;
use msth_gpu::device::ComputeDevice;
use msth_gpu::hashgrid::AtomicMode;
use msth_gpu::{AdapterPolicy, GpuError};
use msth_testkit::Need;

/// The `gpu` need: "no adapter" is a missing need (the tests are reported as ignored, or fail
/// under `MSTH_REQUIRE_GPU=1`); any other error opening one fails the test.
pub fn gpu_need() -> Need {
    Need::new("gpu", || match ComputeDevice::open(AdapterPolicy::any()) {
        Ok(_) => Ok(()),
        Err(e @ GpuError::NoAdapter(_)) => Err(e.to_string()),
        Err(e) => panic!("{e}"),
    })
}

/// The device (the tests that call this run only where the gpu need is met).
pub fn device() -> ComputeDevice {
    ComputeDevice::open(AdapterPolicy::any()).expect("the adapter the gpu need found")
}

/// The atomic paths this device can run: the compare-exchange loop always (forced even where
/// native atomics exist), native f32 atomics where the adapter has them.
pub fn modes(dev: &ComputeDevice) -> Vec<AtomicMode> {
    let mut m = vec![AtomicMode::CompareExchange];
    if dev.has_float_atomics() {
        m.push(AtomicMode::NativeF32);
    } else {
        eprintln!(
            "SKIPPED native f32 atomics path: {} lacks SHADER_FLOAT32_ATOMIC (the compare-exchange path is tested)",
            dev.adapter_name()
        );
    }
    m
}

/// The built-in scene's set-up (a box, linear spacing, white) at the fast preset, with `np`
/// proposal and `nf` field samples per ray.
pub fn box_model(np: usize, nf: usize) -> ModelConfig {
    let mut cfg = ModelConfig::fast_on_white(10);
    cfg.sampler.set_samples(np, nf);
    cfg
}

/// A stage's set-up at the fast preset: contraction, spacing linear in disparity from `near` to
/// `far`, the last sample as the background.
pub fn stage_model(np: usize, nf: usize, (near, far): (f32, f32)) -> ModelConfig {
    let bounds = SceneBounds::Contracted {
        center: Vec3::new(0.0, 0.3, 0.9),
        radius: 2.0,
    };
    let mut cfg = ModelConfig::preset(Preset::Fast, bounds, Background::LastSample, 10);
    cfg.sampler.spacing = Spacing::LinDisp;
    cfg.sampler.near = near;
    cfg.sampler.far = far;
    cfg.sampler.set_samples(np, nf);
    cfg
}
