//! `msth bench ...`: the benchmarks and their reports, one module tree behind one boundary.
//!
//! - this file: `msth bench step`, the cost of one full training step (proposal and field,
//!   forward, backward and Adam) at the demo (fast preset) and paper configurations, reported as
//!   field samples per second, with three same-run baselines: the same step on one worker
//!   thread, the plain reference hash encoding against the batched one, and the MLPs'
//!   forward + backward on `matrixmultiply` against the SIMD kernels;
//! - [`play`]: `msth bench play` (streamed playback, CPU and GPU);
//! - [`layers`]: `msth bench layers` (held-out PSNR against bytes of each prefix of the
//!   progressive layers);
//! - [`stream`]: `msth bench stream` (progressive layers over a throttled link: time to first
//!   picture, layers and stalls on a changing link);
//! - [`tradeoff`], [`tradeoff_report`], [`tradeoff_plot`]: `msth bench tradeoff` (size, quality
//!   and training time over model settings; tables and plots);
//! - [`ablation`]: `msth bench ablation` (the paper's ablations).
//!
//! The boundary: the tree is compiled only with the cli's `bench` feature (on by default;
//! `cargo build -p msth-cli --no-default-features` builds `msth` without it and without
//! `plotters`). From the rest of the cli it uses only the dataset arguments ([`crate::data`]),
//! the playback reuse and backend options ([`crate::play`]) and the held-out PSNR of a
//! quantised model ([`crate::export`]); nothing outside this tree uses it but [`crate::run`]
//! (and the re-exports `msth_cli::{bench_tradeoff, tradeoff_plot}` for `tests/`).

pub mod ablation;
pub mod layers;
pub mod play;
pub mod stream;
pub mod tradeoff;
pub mod tradeoff_plot;
pub(crate) mod tradeoff_report;

use std::time::Instant;

use anyhow::Result;
use clap::{Args, Subcommand};
use glam::Vec3;

use msth_core::config::{Background, ModelConfig, Preset};
use msth_core::field::ModelLayout;
use msth_core::mlp::{MlpActivations, MlpKernels};
use msth_core::pipeline::TimedRay;
use msth_core::rng::Rng;
use msth_core::SceneBounds;
use msth_trainer::device::TrainDevice;
use msth_trainer::train::{TrainSettings, Trainer};

#[derive(Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    what: BenchKind,
}

#[derive(Subcommand)]
enum BenchKind {
    /// One full training step at the demo and paper configurations.
    Step {
        /// Timed steps per configuration (after 2 warm-up steps).
        #[arg(long, default_value_t = 5)]
        reps: usize,
        /// Rays per step (default: the preset's batch).
        #[arg(long)]
        batch_rays: Option<usize>,
        /// Only this configuration: demo | paper.
        #[arg(long)]
        only: Option<String>,
        /// Write the results as JSON here.
        #[arg(long)]
        json: Option<std::path::PathBuf>,
        /// `cpu`, or `gpu`: the step on a GPU adapter (software ones included), with the CPU
        /// step (all threads) timed in the same run as the baseline.
        #[arg(long, default_value = "cpu")]
        device: String,
    },
    /// Playback of a .msth file over loopback HTTP: time to first frame against the full
    /// download, incremental against full rendering (FPS and PSNR).
    Play(play::BenchPlayArgs),
    /// Streaming over a throttled loopback link: time to first picture of a layered file
    /// against the same model without layers, and real-time playback on a changing link
    /// (layers drawn, stalls; see `docs/streaming.md`).
    Stream(stream::BenchStreamArgs),
    /// Quality against bytes of progressive layers: held-out PSNR of every prefix of a layered
    /// export, one curve per checkpoint.
    Layers(layers::BenchLayersArgs),
    /// The accuracy / cost trade-off: a one-factor-at-a-time sweep around a preset, plus the
    /// presets; tables and plots with the Pareto fronts (see `docs/tradeoff.md`).
    Tradeoff(Box<tradeoff::TradeoffArgs>),
    /// The paper's ablation: 4D only, h3 + h4, mt, mst, mst + uncertainty + MINE, each with
    /// uniform and dynamics-aware sampling; table, JSON and mask pictures.
    Ablation(ablation::AblationArgs),
}

pub fn run(a: BenchArgs) -> Result<()> {
    match a.what {
        BenchKind::Step {
            reps,
            batch_rays,
            only,
            json,
            device,
        } => {
            let device: TrainDevice = device.parse().map_err(anyhow::Error::msg)?;
            if device == TrainDevice::Gpu {
                step_gpu(reps, batch_rays, only.as_deref(), json)
            } else {
                step(reps, batch_rays, only.as_deref(), json)
            }
        }
        BenchKind::Play(a) => play::run(a),
        BenchKind::Stream(a) => stream::run(a),
        BenchKind::Layers(a) => layers::run(a),
        BenchKind::Tradeoff(a) => tradeoff::run(*a),
        BenchKind::Ablation(a) => ablation::run(a).map(|_| ()),
    }
}

/// The step bench's configurations, or the one whose name starts with `only`.
fn configurations(only: Option<&str>) -> impl Iterator<Item = (&'static str, Preset)> + '_ {
    [
        ("demo (fast preset)", Preset::Fast),
        ("paper (2^19 rows/level)", Preset::Paper),
    ]
    .into_iter()
    .filter(move |(name, _)| only.is_none_or(|o| name.starts_with(o)))
}

fn settings(preset: Preset, batch: Option<usize>) -> TrainSettings {
    let model = ModelConfig::preset(
        preset,
        SceneBounds::dnerf_default(),
        Background::Color { rgb: [1.0; 3] },
        24,
    );
    let mut s = TrainSettings::for_model(preset, model);
    if let Some(b) = batch {
        s.batch_rays = b;
    }
    s.checkpoint_every = 0;
    s
}

/// Rays from a ring of cameras through the D-NeRF box, at random times.
fn rays(n: usize, seed: u64) -> (Vec<TimedRay>, Vec<[f32; 3]>) {
    let mut rng = Rng::new(seed);
    let mut r = Vec::with_capacity(n);
    let mut t = Vec::with_capacity(n);
    for _ in 0..n {
        let az = rng.f32() * std::f32::consts::TAU;
        let o = Vec3::new(4.0 * az.cos(), 4.0 * az.sin(), 1.0);
        let target = Vec3::new(
            rng.range_f32(-1.0, 1.0),
            rng.range_f32(-1.0, 1.0),
            rng.range_f32(-1.0, 1.0),
        );
        r.push(TimedRay {
            origin: o,
            dir: (target - o).normalize(),
            time: rng.f32(),
        });
        t.push([rng.f32(), rng.f32(), rng.f32()]);
    }
    (r, t)
}

struct StepResult {
    secs: f64,
    field_samples: usize,
    proposal_samples: usize,
    rays: usize,
}

fn time_steps(s: &TrainSettings, reps: usize) -> Result<StepResult> {
    time_steps_on(s, reps, TrainDevice::Cpu).map(|(r, _)| r)
}

/// Times `reps` steps on `device` (after 2 warm-up steps; every step reads its losses back, as
/// training does); also returns the line naming the device.
fn time_steps_on(
    s: &TrainSettings,
    reps: usize,
    device: TrainDevice,
) -> Result<(StepResult, String)> {
    let mut trainer = Trainer::new(s.clone()).map_err(anyhow::Error::msg)?;
    let line = trainer.use_device(device)?;
    let (r, t) = rays(s.batch_rays, 1);
    for _ in 0..2 {
        trainer.step_on(&r, &t, None, None)?;
    }
    let start = Instant::now();
    let mut fs = 0;
    let mut ps = 0;
    for _ in 0..reps {
        let l = trainer.step_on(&r, &t, None, None)?;
        fs += l.field_samples;
        ps += l.proposal_samples;
    }
    Ok((
        StepResult {
            secs: start.elapsed().as_secs_f64(),
            field_samples: fs,
            proposal_samples: ps,
            rays: reps * s.batch_rays,
        },
        line,
    ))
}

/// `msth bench step --device gpu`: the step on the GPU against the CPU step (all threads) in
/// the same run, at the demo and paper configurations. A configuration the adapter's limits
/// refuse is reported as such (the limit named) and the next one runs.
fn step_gpu(
    reps: usize,
    batch: Option<usize>,
    only: Option<&str>,
    json: Option<std::path::PathBuf>,
) -> Result<()> {
    let threads = rayon::current_num_threads();
    println!("msth bench step --device gpu: one full training step (proposal + field, forward + backward + Adam, losses read back), against the CPU step on {threads} threads");
    let mut rows = Vec::new();
    for (name, preset) in configurations(only) {
        let s = settings(preset, batch);
        let (gpu, line) = match time_steps_on(&s, reps, TrainDevice::Gpu) {
            Ok(r) => r,
            Err(e) => {
                println!("{name:<26} GPU: {e:#}");
                rows.push(serde_json::json!({"config": name, "gpu_error": format!("{e:#}")}));
                continue;
            }
        };
        let cpu = time_steps(&s, reps.div_ceil(2))?;
        let gps = gpu.field_samples as f64 / gpu.secs;
        let cps = cpu.field_samples as f64 / cpu.secs;
        println!(
            "{name:<26} batch {:>6} rays x {}+{} samples  GPU: {:>9.1} ms/step {:>11.0} field samples/s  | CPU: {:>9.1} ms/step {:>10.0} samples/s  | GPU / CPU {:.2}x  ({line})",
            s.batch_rays,
            s.model.sampler.num_proposal_samples,
            s.model.sampler.num_samples,
            gpu.secs / reps as f64 * 1e3,
            gps,
            cpu.secs / reps.div_ceil(2) as f64 * 1e3,
            cps,
            gps / cps
        );
        rows.push(serde_json::json!({
            "config": name, "device": line, "cpu_threads": threads, "batch_rays": s.batch_rays,
            "gpu_ms_per_step": gpu.secs / reps as f64 * 1e3, "gpu_field_samples_per_sec": gps,
            "cpu_ms_per_step": cpu.secs / reps.div_ceil(2) as f64 * 1e3, "cpu_field_samples_per_sec": cps,
            "gpu_over_cpu": gps / cps,
        }));
    }
    if let Some(p) = json {
        std::fs::write(&p, serde_json::to_vec_pretty(&rows)?)?;
        println!("wrote {}", p.display());
    }
    Ok(())
}

fn step(
    reps: usize,
    batch: Option<usize>,
    only: Option<&str>,
    json: Option<std::path::PathBuf>,
) -> Result<()> {
    let threads = rayon::current_num_threads();
    println!("msth bench step: one full training step (proposal + field, forward + backward + Adam), {threads} threads");
    let mut rows = Vec::new();
    for (name, preset) in configurations(only) {
        let s = settings(preset, batch);
        let layout = ModelLayout::new(&s.model);
        let all = time_steps(&s, reps)?;
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()?
            .install(|| time_steps(&s, reps.div_ceil(2)))?;
        let sps = all.field_samples as f64 / all.secs;
        let sps1 = one.field_samples as f64 / one.secs;
        println!(
            "{name:<26} params {:>10}  batch {:>6} rays x {}+{} samples: {:>8.1} ms/step  {:>9.0} field samples/s  {:>9.0} proposal samples/s  {:>7.0} rays/s  | 1 thread: {:>9.0} samples/s, speed-up {:.2}x",
            layout.params.total,
            s.batch_rays,
            s.model.sampler.num_proposal_samples,
            s.model.sampler.num_samples,
            all.secs / reps as f64 * 1e3,
            sps,
            all.proposal_samples as f64 / all.secs,
            all.rays as f64 / all.secs,
            sps1,
            sps / sps1
        );
        rows.push(serde_json::json!({
            "config": name, "threads": threads, "params": layout.params.total, "batch_rays": s.batch_rays,
            "proposal_samples_per_ray": s.model.sampler.num_proposal_samples, "samples_per_ray": s.model.sampler.num_samples,
            "ms_per_step": all.secs / reps as f64 * 1e3, "field_samples_per_sec": sps,
            "proposal_samples_per_sec": all.proposal_samples as f64 / all.secs, "rays_per_sec": all.rays as f64 / all.secs,
            "one_thread_field_samples_per_sec": sps1, "thread_speedup": sps / sps1,
        }));
    }
    // Kernel baseline: reference vs batched hash encoding of the demo field's 4D grid.
    let s = settings(Preset::Fast, None);
    let layout = ModelLayout::new(&s.model);
    let params = layout.init_params(0);
    let (g, range) = layout
        .field
        .encoding
        .h4
        .as_ref()
        .expect("fast preset has a 4D grid");
    let table = &params[range.clone()];
    let mut rng = Rng::new(3);
    let n = 1 << 16;
    let pts: Vec<f32> = (0..n * 4).map(|_| rng.f32()).collect();
    let mut out = vec![0f32; n * g.output_dim()];
    let t = Instant::now();
    g.encode(table, &pts, 4, &mut out, g.output_dim(), 0);
    let fast = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut acc = 0f32;
    for i in 0..n {
        acc += g.encode_point_reference(table, &pts[i * 4..i * 4 + 4])[0];
    }
    let reference = t.elapsed().as_secs_f64();
    println!(
        "4D hash encoding, {n} points, 1 thread: batched {:.0} points/s, reference {:.0} points/s, ratio {:.2}x (checksum {acc:.3})",
        n as f64 / fast,
        n as f64 / reference,
        reference / fast
    );
    rows.push(serde_json::json!({"kernel": "hash4d_encode", "batched_points_per_sec": n as f64 / fast, "reference_points_per_sec": n as f64 / reference, "ratio": reference / fast}));
    mlp_kernels(&s, &layout, &params, &mut rows);
    if let Some(p) = json {
        std::fs::write(&p, serde_json::to_vec_pretty(&rows)?)?;
        println!("wrote {}", p.display());
    }
    Ok(())
}

/// Kernel baseline: forward + backward of the demo model's three MLPs (the field's density and
/// colour MLPs on one chunk's field samples, the proposal's density MLP on its proposal samples;
/// the input gradients the training step asks for) on `matrixmultiply`
/// ([`MlpKernels::Gemm`]) against the SIMD kernels ([`MlpKernels::best`]; where that is
/// AVX-512, the AVX2 ones as well), one thread, best of 20 runs each, in ns per row.
fn mlp_kernels(
    s: &TrainSettings,
    layout: &ModelLayout,
    params: &[f32],
    rows: &mut Vec<serde_json::Value>,
) {
    let best = MlpKernels::best();
    let chunk = s.chunk_rays;
    let sampler = &s.model.sampler;
    let field = &layout.field;
    let mlps = [
        ("density", &field.density, chunk * sampler.num_samples, 0),
        (
            "colour",
            &field.color,
            chunk * sampler.num_samples,
            msth_core::sh::SH_COEFFS,
        ),
        (
            "proposal",
            &layout.proposal.field.density,
            chunk * sampler.num_proposal_samples,
            0,
        ),
    ];
    let mut rng = Rng::new(4);
    let (mut total_gemm, mut total_best) = (0.0, 0.0);
    for (name, (mlp, range), n, from) in mlps {
        let p = &params[range.clone()];
        let x: Vec<f32> = (0..n * mlp.input_dim())
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let d: Vec<f32> = (0..n * mlp.output_dim())
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let time = |kernels: MlpKernels| {
            let mut acts = MlpActivations::default();
            let mut grad = vec![0f32; mlp.num_params];
            let mut dx = vec![0f32; n * (mlp.input_dim() - from)];
            let mut best_secs = f64::MAX;
            for _ in 0..20 {
                let t = Instant::now();
                mlp.forward_with(kernels, p, &x, n, &mut acts);
                mlp.backward_partial_with(
                    kernels,
                    p,
                    &x,
                    n,
                    &mut acts,
                    &d,
                    &mut grad,
                    Some((from, &mut dx)),
                );
                best_secs = best_secs.min(t.elapsed().as_secs_f64());
            }
            best_secs / n as f64 * 1e9
        };
        let (gemm, fast) = (time(MlpKernels::Gemm), time(best));
        // Where AVX-512 is the best, the AVX2 kernels too, for the record.
        let avx2 = (best == MlpKernels::Avx512 && MlpKernels::Avx2.available())
            .then(|| time(MlpKernels::Avx2));
        total_gemm += gemm * n as f64;
        total_best += fast * n as f64;
        println!(
            "MLP {name} {:?}, {n} rows, forward + backward, 1 thread: matrixmultiply {gemm:.1} ns/row, {best:?} kernels {fast:.1} ns/row, ratio {:.2}x{}",
            mlp.dims,
            gemm / fast,
            avx2.map_or(String::new(), |t| format!(" (Avx2 kernels {t:.1} ns/row)"))
        );
        rows.push(serde_json::json!({"kernel": format!("mlp_{name}"), "dims": mlp.dims, "rows": n, "kernels": format!("{best:?}"), "gemm_ns_per_row": gemm, "simd_ns_per_row": fast, "ratio": gemm / fast, "avx2_ns_per_row": avx2}));
    }
    println!(
        "MLPs of one chunk, forward + backward: matrixmultiply {:.2} ms, {best:?} kernels {:.2} ms, ratio {:.2}x",
        total_gemm * 1e-6,
        total_best * 1e-6,
        total_gemm / total_best
    );
}
