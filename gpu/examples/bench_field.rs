//! Benchmark of the whole main field on the device ([`msth_gpu::field::GpuField`]: hash grids,
//! mask, blend, density MLP, SH, colour MLP, forward and backward) against core's CPU field
//! (`msth_core::field::FieldLayout`, one thread) in the same run, at the demo (fast preset) and
//! paper configurations: samples per second of the forward, the backward, and both (what a
//! training step spends on the main field), and the GPU / CPU ratio.
//!
//! Two sample orders: `rays` (48 samples along each ray, consecutive in memory, one time per
//! ray: the order training evaluates them in) and `random` (uniform in the cube and in time: no
//! two neighbours share a table row, the cache's worst case).
//!
//! `cargo run --release -p msth-gpu --example bench_field [SAMPLES] [REPEATS]` (default 262144
//! samples on the GPU, 3 repeats, the best counts; the CPU runs 16384 samples). Any adapter is
//! used (lavapipe included: pass fewer samples there). The GPU figures time every kernel's
//! dispatch and completion with all buffers resident (no upload, no read-back); each kernel
//! still submits and waits on its own.

mod common;

use msth_core::field::{FieldScratch, ModelLayout};
use msth_core::rng::Rng;
use msth_core::sh::{sh4, SH_COEFFS};
use msth_gpu::field::{FieldKernels, GpuField};
use msth_gpu::hashgrid::AtomicMode;
use msth_gpu::presets::{reference_model, REFERENCE_PRESETS};
use msth_gpu::GpuError;

use common::{best_of, open_device};

const CPU_SAMPLES: usize = 16384;
const PER_RAY: usize = 48;

/// `n` samples as `(x, y, z, t)`: along rays (`rays`) or uniform.
fn points(n: usize, rays: bool, rng: &mut Rng) -> Vec<f32> {
    let mut p = Vec::with_capacity(4 * n);
    while p.len() < 4 * n {
        if rays {
            let o = [rng.f32(), rng.f32(), rng.f32()];
            let d = [
                rng.range_f32(-1.0, 1.0),
                rng.range_f32(-1.0, 1.0),
                rng.range_f32(-1.0, 1.0),
            ];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-6);
            let t = rng.f32();
            for s in 0..PER_RAY {
                let u = 0.6 * s as f32 / PER_RAY as f32;
                for a in 0..3 {
                    p.push((o[a] + u * d[a] / l).clamp(0.0, 1.0));
                }
                p.push(t);
            }
        } else {
            p.extend([rng.f32(), rng.f32(), rng.f32(), rng.f32()]);
        }
    }
    p.truncate(4 * n);
    p
}

fn main() -> Result<(), GpuError> {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(262_144);
    let repeats: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(3);
    let dev = open_device("bench_field")?;
    let mode = AtomicMode::best(&dev);
    let kernels = FieldKernels::new(&dev, mode)?;
    println!(
        "adapter: {}; gradient adds: {mode:?}; {n} samples on the GPU, {} on the CPU (one thread), best of {repeats}",
        dev.adapter_name(),
        n.min(CPU_SAMPLES)
    );
    println!(
        "{:<14} {:<8} {:>13} {:>13} {:>13} {:>13} {:>8}",
        "config", "order", "gpu fwd/s", "gpu bwd/s", "gpu both/s", "cpu both/s", "gpu/cpu"
    );
    let mut rng = Rng::new(5);
    for (name, preset) in REFERENCE_PRESETS {
        let model = ModelLayout::new(&reference_model(preset));
        let field = &model.field;
        let mut params = model.init_params(3);
        for r in [&field.encoding.h3, &field.encoding.h4]
            .into_iter()
            .flatten()
            .map(|(_, r)| r)
        {
            for v in &mut params[r.clone()] {
                *v = rng.range_f32(-0.3, 0.3);
            }
        }
        if let Some((_, r)) = &field.encoding.mask {
            for v in &mut params[r.clone()] {
                *v = rng.range_f32(-3.0, 3.0);
            }
        }
        let gpu_field = GpuField::new(field)?;
        let bufs = gpu_field.buffers(&dev, n)?;
        // The paper's flat buffer (134 MB) exceeds a 128 MiB binding limit (lavapipe's).
        let p_b = match dev.buffer_f32("params", &params) {
            Ok(b) => b,
            Err(e @ GpuError::Limit { .. }) => {
                println!("{name}: refused by this adapter: {e}");
                continue;
            }
            Err(e) => return Err(e),
        };
        let grad_b = dev.zeros_f32("grad", params.len())?;
        for rays in [true, false] {
            let pts = points(n, rays, &mut rng);
            let dirs: Vec<f32> = (0..n)
                .flat_map(|i| {
                    let a = i as f32 * 0.618;
                    [a.cos() * 0.6, a.sin() * 0.6, 0.8]
                })
                .collect();
            let d_sigma: Vec<f32> = (0..n).map(|_| rng.range_f32(-0.1, 0.1)).collect();
            let d_rgb: Vec<f32> = (0..3 * n).map(|_| rng.range_f32(-1.0, 1.0)).collect();

            // CPU, one thread, on the first CPU_SAMPLES samples.
            let m = n.min(CPU_SAMPLES);
            let mut sh = vec![0f32; m * SH_COEFFS];
            for i in 0..m {
                sh4(
                    [dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]],
                    &mut sh[i * SH_COEFFS..(i + 1) * SH_COEFFS],
                );
            }
            let mut s = FieldScratch::default();
            let mut grad = vec![0f32; params.len()];
            let cpu = best_of(repeats, || {
                field.forward(&params, &pts[..4 * m], &sh, &|i| i, m, &mut s);
                field.backward(
                    &params,
                    &pts[..4 * m],
                    m,
                    &mut s,
                    &d_sigma[..m],
                    &d_rgb[..3 * m],
                    &mut grad,
                );
            });

            // GPU, every buffer resident.
            let pts_b = dev.buffer_f32("points", &pts)?;
            let dirs_b = dev.buffer_f32("dirs", &dirs)?;
            let ds_b = dev.buffer_f32("d sigma", &d_sigma)?;
            let dr_b = dev.buffer_f32("d rgb", &d_rgb)?;
            let mut err = Ok(());
            let fwd = best_of(repeats, || {
                if let Err(e) = gpu_field.forward(&dev, &kernels, &p_b, &pts_b, &dirs_b, n, &bufs) {
                    err = Err(e);
                }
            });
            err?;
            let mut err = Ok(());
            let bwd = best_of(repeats, || {
                if let Err(e) = gpu_field.backward(
                    &dev, &kernels, &p_b, &pts_b, n, &bufs, &ds_b, &dr_b, None, &grad_b,
                ) {
                    err = Err(e);
                }
            });
            err?;
            let rate = |secs: f64, count: usize| count as f64 / secs;
            println!(
                "{:<14} {:<8} {:>13.0} {:>13.0} {:>13.0} {:>13.0} {:>8.1}",
                format!("{name} ({:?})", field.encoding.blend),
                if rays { "rays" } else { "random" },
                rate(fwd, n),
                rate(bwd, n),
                rate(fwd + bwd, n),
                rate(cpu, m),
                rate(fwd + bwd, n) / rate(cpu, m)
            );
        }
    }
    Ok(())
}
