//! Benchmark of the MLP kernels against core's CPU MLP in the same run: forward (keeping the
//! activations, as training does) and backward (weight and input gradients) of the main field's
//! density and colour MLPs at the demo (fast preset) and paper configurations, as samples per
//! second and the GPU / CPU ratio. The CPU figures are `msth_core::mlp::MlpLayout::forward` /
//! `backward_partial` (matrixmultiply's SGEMM on whole batches, one thread); the GPU figures
//! time the dispatch and its completion with every buffer already on the device (no upload, no
//! read-back).
//!
//! `cargo run --release -p msth-gpu --example bench_mlp [SAMPLES] [REPEATS]`
//! (default 16384 samples, 3 repeats; the best repeat counts). Any adapter is used (lavapipe
//! included); the backward adds its weight gradients with native f32 atomics where the adapter
//! has them, else the compare-exchange loop.

mod common;

use msth_core::field::ModelLayout;
use msth_core::mlp::{MlpActivations, MlpLayout};
use msth_core::rng::Rng;
use msth_core::sh::SH_COEFFS;
use msth_gpu::hashgrid::AtomicMode;
use msth_gpu::mlp::{mlp_counts, GpuMlp, MlpKernels, OutputActivation, TILE};
use msth_gpu::presets::{reference_model, REFERENCE_PRESETS};
use msth_gpu::GpuError;

use common::{best_of, open_device, rates};

fn main() -> Result<(), GpuError> {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(16384);
    let repeats: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(3);
    let dev = open_device("bench_mlp")?;
    let mode = AtomicMode::best(&dev);
    println!(
        "adapter: {}; weight-gradient adds: {mode:?}; {n} samples, best of {repeats}",
        dev.adapter_name()
    );
    let kernels = MlpKernels::new(&dev, mode)?;
    println!(
        "{:<26} {:<9} {:>14} {:>14} {:>8}  {:>7} {:>6} {:>8}",
        "mlp", "pass", "cpu samples/s", "gpu samples/s", "gpu/cpu", "flops", "B/smp", "atomics"
    );
    let mut rng = Rng::new(1);
    for (name, preset) in REFERENCE_PRESETS {
        let cfg = reference_model(preset);
        let model = ModelLayout::new(&cfg);
        for (mname, l, act, from) in [
            (
                "density",
                &model.field.density.0,
                OutputActivation::Density,
                0,
            ),
            (
                "colour",
                &model.field.color.0,
                OutputActivation::Sigmoid,
                SH_COEFFS,
            ),
        ] {
            bench_one(
                &dev,
                &kernels,
                &format!("{name} {mname} {:?}", l.dims),
                l,
                act,
                from,
                n,
                repeats,
                &mut rng,
            )?;
        }
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn bench_one(
    dev: &msth_gpu::device::ComputeDevice,
    kernels: &MlpKernels,
    label: &str,
    l: &MlpLayout,
    act: OutputActivation,
    from: usize,
    n: usize,
    repeats: usize,
    rng: &mut Rng,
) -> Result<(), GpuError> {
    let counts = mlp_counts(l);
    let mut w = vec![0f32; l.num_params];
    l.init(&mut w, rng);
    let x: Vec<f32> = (0..n * l.input_dim())
        .map(|_| rng.range_f32(-1.0, 1.0))
        .collect();
    let d_out: Vec<f32> = (0..n * l.output_dim())
        .map(|_| rng.range_f32(-1.0, 1.0))
        .collect();
    let cols = l.input_dim() - from;
    // CPU: batched forward keeping the activations, then the backward of that forward.
    let mut acts = MlpActivations::default();
    let cpu_fwd = best_of(repeats, || l.forward(&w, &x, n, &mut acts));
    let mut grad = vec![0f32; l.num_params];
    let mut dx = vec![0f32; n * cols];
    let cpu_bwd = best_of(repeats, || {
        l.backward_partial(
            &w,
            &x,
            n,
            &mut acts,
            &d_out,
            &mut grad,
            Some((from, &mut dx)),
        )
    });
    // GPU, every buffer resident.
    let mlp = GpuMlp::new(l, 0, act)?;
    let w_buf = dev.buffer_f32("weights", &w)?;
    let x_buf = dev.buffer_f32("input", &x)?;
    let o_buf = dev.zeros_f32("output", n * l.output_dim())?;
    let a_buf = dev.zeros_f32("activations", n * mlp.acts_stride())?;
    let d_buf = dev.buffer_f32("d_output", &d_out)?;
    let g_buf = dev.zeros_f32("gradient", l.num_params)?;
    let dx_buf = dev.zeros_f32("d_input", n * cols)?;
    let mut err = Ok(());
    let gpu_fwd = best_of(repeats, || {
        if let Err(e) = kernels.forward(dev, &mlp, &w_buf, &x_buf, n, &o_buf, Some(&a_buf)) {
            err = Err(e);
        }
    });
    err?;
    let mut err = Ok(());
    let gpu_bwd = best_of(repeats, || {
        let r = kernels.backward(
            dev,
            &mlp,
            &w_buf,
            &x_buf,
            &a_buf,
            &d_buf,
            n,
            &g_buf,
            Some((from, &dx_buf)),
        );
        if let Err(e) = r {
            err = Err(e);
        }
    });
    err?;
    let row = |pass: &str, cpu: f64, gpu: f64, flops: u64, bytes: u64, atomics: f64| {
        println!(
            "{label:<26} {pass:<9} {}  {flops:>7} {bytes:>6} {atomics:>8.1}",
            rates(n, cpu, gpu)
        );
    };
    row(
        "forward",
        cpu_fwd,
        gpu_fwd,
        counts.forward_flops,
        counts.forward_bytes,
        0.0,
    );
    row(
        "backward",
        cpu_bwd,
        gpu_bwd,
        counts.backward_flops,
        counts.backward_bytes,
        counts.atomics_per_tile as f64 / TILE as f64,
    );
    Ok(())
}
