//! What the kernel benchmarks share: opening the device (exit code 2 when there is no adapter:
//! nothing to measure) and timing a closure as the best of a few repeats after a warm-up.

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

/// Seconds of the fastest of `repeats` runs of `f`, after one warm-up run.
pub fn best_of(repeats: usize, mut f: impl FnMut()) -> f64 {
    f();
    (0..repeats)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// The middle of a table row: CPU and GPU samples per second over `n` samples and the GPU / CPU
/// ratio, from the two timings in seconds.
pub fn rates(n: usize, cpu_s: f64, gpu_s: f64) -> String {
    format!(
        "{:>14.0} {:>14.0} {:>8.2}",
        n as f64 / cpu_s,
        n as f64 / gpu_s,
        cpu_s / gpu_s
    )
}
