//! Benchmark of the hash-grid kernels against the CPU in the same run: forward (features of a
//! batch of samples) and backward (scatter into a zeroed gradient) of the main field's 3D and 4D
//! grids at the demo (fast preset) and paper configurations, as samples per second and the
//! GPU / CPU ratio. The CPU figures are `msth_core::grid::GridLayout::encode` / `backward`, the
//! batched fast paths, on one thread; the GPU figures time the dispatch and its completion with
//! every buffer already on the device (no upload, no read-back).
//!
//! `cargo run --release -p msth-gpu --example bench_encode [SAMPLES] [REPEATS]`
//! (default 32768 samples, 3 repeats; the best repeat counts). Any adapter is used (lavapipe
//! included); the backward uses native f32 atomics where the adapter has them, else the
//! compare-exchange loop, and the compare-exchange loop always as a second row.

mod common;

use msth_core::grid::GridLayout;
use msth_core::rng::Rng;
use msth_gpu::hashgrid::{encoding_counts, AtomicMode, GpuGrid, HashGridKernels};
use msth_gpu::presets::{reference_model, REFERENCE_PRESETS};
use msth_gpu::GpuError;

use common::{best_of, open_device, rates};

fn main() -> Result<(), GpuError> {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(32768);
    let repeats: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(3);
    let dev = open_device("bench_encode")?;
    println!(
        "adapter: {}; f32 atomics: {}; {n} samples, best of {repeats}",
        dev.adapter_name(),
        dev.has_float_atomics()
    );
    let mut modes = vec![AtomicMode::best(&dev)];
    if modes[0] != AtomicMode::CompareExchange {
        modes.push(AtomicMode::CompareExchange);
    }
    let kernels: Vec<HashGridKernels> = modes
        .iter()
        .map(|m| HashGridKernels::new(&dev, *m))
        .collect::<Result<_, _>>()?;
    println!(
        "{:<22} {:<9} {:>14} {:>14} {:>8}  {:>7} {:>8}",
        "grid", "pass", "cpu samples/s", "gpu samples/s", "gpu/cpu", "B/smp", "atomics"
    );
    let mut rng = Rng::new(1);
    for (name, preset) in REFERENCE_PRESETS {
        let cfg = reference_model(preset);
        for (gname, gcfg) in [
            ("3D", &cfg.field.encoding.grid3),
            ("4D", &cfg.field.encoding.grid4),
        ] {
            let g = GridLayout::new(gcfg);
            let counts = encoding_counts(&g);
            let table: Vec<f32> = (0..g.num_params)
                .map(|_| rng.range_f32(-1e-2, 1e-2))
                .collect();
            let pts: Vec<[f32; 4]> = (0..n)
                .map(|_| [rng.f32(), rng.f32(), rng.f32(), rng.f32()])
                .collect();
            let flat: &[f32] = bytemuck::cast_slice(&pts);
            let dim = g.output_dim();
            let d: Vec<f32> = (0..n * dim).map(|_| rng.range_f32(-1.0, 1.0)).collect();
            let mut out = vec![0f32; n * dim];
            let cpu_fwd = best_of(repeats, || g.encode(&table, flat, 4, &mut out, dim, 0));
            let mut grad = vec![0f32; g.num_params];
            let cpu_bwd = best_of(repeats, || {
                grad.fill(0.0);
                g.backward(flat, 4, &d, dim, 0, &mut grad)
            });
            let grid = GpuGrid::new(&g, 0)?;
            let t_buf = dev.buffer_f32("table", &table)?;
            let p_buf = dev.buffer_f32("points", flat)?;
            let o_buf = dev.zeros_f32("features", n * dim)?;
            let d_buf = dev.buffer_f32("d features", &d)?;
            let g_buf = dev.zeros_f32("gradient", g.num_params)?;
            let mut err = Ok(());
            let gpu_fwd = best_of(repeats, || {
                if let Err(e) = kernels[0].forward(&dev, &grid, &t_buf, &p_buf, n, &o_buf) {
                    err = Err(e);
                }
            });
            err?;
            let label = format!("{name} {gname} ({} MiB)", counts.table_bytes >> 20);
            let row = |pass: &str, cpu: f64, gpu: f64, bytes: u64, atomics: u64| {
                println!(
                    "{label:<22} {pass:<9} {}  {bytes:>7} {atomics:>8}",
                    rates(n, cpu, gpu)
                );
            };
            row(
                "forward",
                cpu_fwd,
                gpu_fwd,
                counts.forward_table_bytes + counts.feature_bytes,
                0,
            );
            for k in &kernels {
                let mut err = Ok(());
                let gpu_bwd = best_of(repeats, || {
                    let r = dev
                        .clear(&g_buf)
                        .and_then(|_| k.backward(&dev, &grid, &p_buf, &d_buf, n, &g_buf));
                    if let Err(e) = r {
                        err = Err(e);
                    }
                });
                err?;
                let pass = match k.mode() {
                    AtomicMode::NativeF32 => "bwd f32",
                    AtomicMode::CompareExchange => "bwd cas",
                };
                row(pass, cpu_bwd, gpu_bwd, counts.feature_bytes, counts.atomics);
            }
        }
    }
    Ok(())
}
