//! The whole training step on the device ([`msth_gpu::step::GpuStep`]) against the CPU
//! trainer's (`msth_core::pipeline::train_chunk`) on the same rays and the same random numbers:
//! the loss sums and the gradient of every named parameter slice, for
//! - the built-in scene's set-up: a box, linear spacing, a random background per ray;
//! - a stage's: contraction, spacing linear in disparity, the last sample as the background.
//!
//! Each with proposal annealing (`a` = 0.5, so `w^a` is exercised), distortion, interlevel,
//! per-sample mask and free-space losses on, and trained-looking parameters (tables U(-0.3, 0.3), mask logits
//! U(-3, 3)).
//!
//! Tolerances: loss sums within 1e-4 relative (the colour and mask terms) and 2e-3 (distortion
//! and interlevel: sums over resampled intervals); each slice's gradient within 5e-3 of its
//! largest CPU entry (measured on lavapipe: 1.4e-3 at worst, `field.h3` of the stage). Why looser than the kernel tests: the device's inverse CDF sums the
//! proposal weights in a tree, the CPU front to back, so the resampled positions differ in
//! their last bits, and every downstream value with them (the kernel tests start from equal
//! positions). The step's own arithmetic is checked kernel by kernel in the other test
//! binaries; this test checks that the chain computes what the CPU step computes.
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`).

mod common;

use glam::Vec3;
use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::pipeline::{free_space_point, train_chunk_with, StepSettings, TimedRay, Workspace};
use msth_core::rng::Rng;
use msth_gpu::step::{GpuStep, HostBatch};
use msth_testkit::Tests;

use common::{device, gpu_need};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "step_matches_the_cpu_step_in_a_box_on_random_backgrounds",
            || step_matches_cpu(box_model(), true, false),
        )
        .needs(
            &[&gpu],
            "step_matches_the_cpu_step_on_a_contracted_stage_coarse_to_fine",
            || step_matches_cpu(stage_model(), false, true),
        )
        .needs(
            &[&gpu],
            "step_bad_input_is_an_error",
            step_bad_input_is_an_error,
        )
        .run()
}

fn box_model() -> ModelConfig {
    common::box_model(40, 20)
}

fn stage_model() -> ModelConfig {
    common::stage_model(40, 20, (0.2, 60.0))
}

/// Trained-looking parameters: hash tables U(-0.3, 0.3), mask logits U(-3, 3), the rest as
/// initialised.
fn params(cfg: &ModelConfig, seed: u64) -> Vec<f32> {
    let layout = ModelLayout::new(cfg);
    let mut p = layout.init_params(seed);
    let mut rng = Rng::new(seed + 1);
    for e in &layout.params.entries {
        let (lo, hi) = if e.name.ends_with(".mask") {
            (-3.0, 3.0)
        } else if e.name.contains(".h3") || e.name.contains(".h4") {
            (-0.3, 0.3)
        } else {
            continue;
        };
        for v in &mut p[e.range()] {
            *v = rng.range_f32(lo, hi);
        }
    }
    p
}

/// Rays from a ring of cameras 4 units out, towards points near the centre, at random times.
fn rays(n: usize, rng: &mut Rng) -> Vec<TimedRay> {
    (0..n)
        .map(|_| {
            let a = rng.range_f32(0.0, std::f32::consts::TAU);
            let origin = Vec3::new(4.0 * a.cos(), 4.0 * a.sin(), rng.range_f32(0.5, 1.5));
            let aim = Vec3::new(
                rng.range_f32(-0.8, 0.8),
                rng.range_f32(-0.8, 0.8),
                rng.range_f32(0.0, 1.5),
            );
            TimedRay {
                origin,
                dir: (aim - origin).normalize(),
                time: rng.f32(),
            }
        })
        .collect()
}

/// One step on the device against the CPU step; `ramp`: with the coarse-to-fine factor at 60%
/// of the main field's levels (one level partly on, the finer ones off).
fn step_matches_cpu(cfg: ModelConfig, random_backgrounds: bool, ramp: bool) {
    let dev = device();
    let layout = ModelLayout::new(&cfg);
    let p = params(&cfg, 5);
    let n = 48;
    let mut rng = Rng::new(9);
    let rays = rays(n, &mut rng);
    let targets: Vec<[f32; 3]> = (0..n).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
    let bgs: Vec<[f32; 3]> = (0..n).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
    let backgrounds = random_backgrounds.then_some(&bgs[..]);
    let step = StepSettings {
        anneal: 0.5,
        interlevel_weight: 1.0,
        distortion_weight: 0.01,
        loss_scale: 1.0 / n as f32,
        sample_mask_weight: 0.005,
        free_space_weight: 0.5,
        active_levels: ramp.then_some(0.6 * cfg.field.encoding.grid3.levels as f32),
        proposal_levels: ramp.then_some(0.6 * cfg.proposal.encoding.grid3.levels as f32),
    };

    // The CPU step draws one proposal jitter per ray, then one resampling jitter per ray, then
    // one free-space point per ray.
    let stream = Rng::stream(3, 7);
    let mut draw = stream.clone();
    let jp: Vec<f32> = (0..n).map(|_| draw.f32()).collect();
    let jm: Vec<f32> = (0..n).map(|_| draw.f32()).collect();
    let jitters: Vec<(f32, f32)> = jp.into_iter().zip(jm).collect();
    let free: Vec<[f32; 4]> = (0..n).map(|_| free_space_point(&mut draw)).collect();

    // Every third ray is spared the per-sample mask loss, as the trainer spares rays through
    // pixels that change over time.
    let mask_weights: Vec<f32> = (0..n).map(|i| (i % 3 != 0) as u8 as f32).collect();

    let mut grad_cpu = vec![0f32; p.len()];
    let mut ws = Workspace::default();
    let cpu = train_chunk_with(
        &cfg,
        &layout,
        &p,
        &mut grad_cpu,
        &rays,
        &targets,
        backgrounds,
        Some(&mask_weights),
        &step,
        &mut stream.clone(),
        &mut ws,
        None,
    );

    let mut gpu_step = GpuStep::new(&dev, &cfg, &p, None, n).unwrap();
    let batch = HostBatch {
        rays: &rays,
        targets: &targets,
        backgrounds,
        jitters: Some(&jitters),
        free_points: Some(&free),
        mask_weights: Some(&mask_weights),
    };
    gpu_step.gradients(&dev, &batch, &step).unwrap();
    let gpu = gpu_step.losses(&dev).unwrap();
    let grad = gpu_step.gradient(&dev).unwrap();

    for (name, g, c, tol) in [
        ("colour", gpu.sq_err, cpu.sq_err, 1e-4),
        ("sample mask", gpu.sample_mask, cpu.sample_mask, 1e-4),
        ("free space", gpu.free_space, cpu.free_space, 1e-4),
        ("distortion", gpu.distortion, cpu.distortion, 2e-3),
        ("interlevel", gpu.interlevel, cpu.interlevel, 2e-3),
    ] {
        println!("loss {name}: gpu {g:.6e} cpu {c:.6e}");
        assert!(
            c > 0.0,
            "{name}: the CPU loss is 0, the test exercises nothing"
        );
        assert!(
            (g - c).abs() <= tol * c.abs(),
            "{name}: gpu {g} cpu {c} (tolerance {tol} relative)"
        );
    }
    assert_eq!(
        (gpu.rays, gpu.field_samples, gpu.proposal_samples),
        (cpu.rays, cpu.field_samples, cpu.proposal_samples)
    );
    for e in &layout.params.entries {
        let r = e.range();
        let scale = grad_cpu[r.clone()].iter().fold(0f32, |a, v| a.max(v.abs()));
        assert!(scale > 0.0, "{}: no gradient on the CPU", e.name);
        let worst = r
            .clone()
            .map(|i| (grad[i] - grad_cpu[i]).abs())
            .fold(0f32, f32::max);
        println!(
            "{:<28} worst |gpu - cpu| = {:.2e} of the slice maximum {scale:.3e}",
            e.name,
            worst / scale
        );
        assert!(
            worst <= 5e-3 * scale,
            "{}: worst |gpu - cpu| {worst} against a slice maximum of {scale}",
            e.name
        );
    }
}

/// Wrong parameter counts, batches beyond the adapter's limits or larger than the buffers, and
/// mismatched lengths are errors that say what is wrong.
fn step_bad_input_is_an_error() {
    let dev = device();
    let cfg = box_model();
    let p = params(&cfg, 1);
    let e = GpuStep::new(&dev, &cfg, &p[1..], None, 8)
        .err()
        .expect("a parameter short");
    assert!(e.to_string().contains("parameters for a model"), "{e}");
    // A batch whose buffers exceed the adapter's limits: refused before anything is allocated,
    // the limit named.
    let e = GpuStep::new(&dev, &cfg, &p, None, 1 << 22)
        .err()
        .expect("2^22 rays: 8 GB for one buffer");
    assert!(e.to_string().contains("max_"), "{e}");
    let mut step = GpuStep::new(&dev, &cfg, &p, None, 8).unwrap();
    let mut rng = Rng::new(2);
    let r = rays(9, &mut rng);
    let t = [[0.5f32; 3]; 9];
    let settings = StepSettings {
        anneal: 1.0,
        interlevel_weight: 1.0,
        distortion_weight: 0.0,
        loss_scale: 1.0 / 9.0,
        sample_mask_weight: 0.0,
        free_space_weight: 0.0,
        active_levels: None,
        proposal_levels: None,
    };
    let batch = |n: usize, m: usize| HostBatch {
        rays: &r[..n],
        targets: &t[..m],
        backgrounds: None,
        jitters: None,
        free_points: None,
        mask_weights: None,
    };
    let e = step
        .gradients(&dev, &batch(9, 9), &settings)
        .expect_err("9 rays in buffers for 8");
    assert!(e.to_string().contains("1 to 8"), "{e}");
    let e = step
        .gradients(&dev, &batch(4, 3), &settings)
        .expect_err("4 rays, 3 targets");
    assert!(e.to_string().contains("need 4 targets"), "{e}");
    let free_space = StepSettings {
        free_space_weight: 0.1,
        active_levels: None,
        proposal_levels: None,
        ..settings
    };
    let e = step
        .gradients(&dev, &batch(4, 4), &free_space)
        .expect_err("the free-space loss without its points");
    assert!(
        e.to_string().contains("free-space loss needs 4 points"),
        "{e}"
    );
    step.gradients(&dev, &batch(4, 4), &settings).unwrap();
    let l = step.losses(&dev).unwrap();
    assert_eq!(l.rays, 4);
    assert!(l.sq_err.is_finite() && l.interlevel.is_finite());
}
