//! What the kernel benchmarks share: opening the device (exit code 2 when there is no adapter:
//! nothing to measure) and timing a closure as the best of a few repeats after a warm-up of at
//! least 0.3 s.

use std::time::Instant;

use msth_gpu::device::ComputeDevice;
use msth_gpu::{AdapterPolicy, GpuError};

/// Any adapter (lavapipe included); without one, says so and exits with code 2.
pub fn open_device(bench: &str) -> Result<ComputeDevice, GpuError> {
    match ComputeDevice::open(AdapterPolicy::any()) {
        Ok(d) => Ok(d),
        Err(e @ GpuError::NoAdapter(_)) => {
            eprintln!("{bench}: no GPU adapter, nothing to measure: {e}");
            std::process::exit(2);
        }
        Err(e) => Err(e),
    }
}

/// Seconds of the fastest of `repeats` runs of `f`, after warming up: `f` runs again and again
/// for at least [`WARM_UP_SECONDS`] (and at least twice). A GPU idles at low clocks while the
/// CPU side of a benchmark runs, and takes tens of milliseconds of load to reach its boost
/// clock: with a single warm-up run, the figures of one kernel varied 5x between two runs on an
/// NVIDIA H200.
pub fn best_of(repeats: usize, mut f: impl FnMut()) -> f64 {
    let start = Instant::now();
    let mut runs = 0;
    while runs < 2 || start.elapsed().as_secs_f64() < WARM_UP_SECONDS {
        f();
        runs += 1;
    }
    (0..repeats)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// How long [`best_of`] keeps the device busy before timing.
pub const WARM_UP_SECONDS: f64 = 0.3;

/// The middle of a table row: CPU and GPU samples per second over `n` samples and the GPU / CPU
/// ratio, from the two timings in seconds.
#[allow(dead_code)] // not every benchmark prints this row
pub fn rates(n: usize, cpu_s: f64, gpu_s: f64) -> String {
    format!(
        "{:>14.0} {:>14.0} {:>8.2}",
        n as f64 / cpu_s,
        n as f64 / gpu_s,
        cpu_s / gpu_s
    )
}
