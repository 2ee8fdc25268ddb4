//! What the kernel tests share: the `gpu` need (a compute device can be opened), the device,
//! and the atomic paths to test on it. Each test binary uses part of it.
#![allow(dead_code)]

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
