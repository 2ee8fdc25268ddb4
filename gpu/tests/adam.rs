//! The Adam kernel against the trainer's `msth_trainer::adam::Adam::update` on whatever adapter
//! exists: 12 steps over a buffer of 40,003 parameters (a partial last workgroup) with two mask
//! slices (the mask loss fused into their update, learning-rate scales 10 and 1), gradients
//! spanning zero, tiny, ordinary and clamped (1e20) magnitudes, the trainer's decaying learning
//! rate; then a resume from the downloaded state.
//!
//! Tolerance ("bit-close"): after every step, parameters and both moments within 4 units in the
//! last place (ulp) of the magnitude that made them (a parameter: its value plus the sizes of the
//! steps it took; `m`: its old and new values plus a tenth of the gradient, plus beta1 times the
//! previous step's scale, since earlier steps' roundings decay by beta1; `v`: its value plus
//! beta2 times the previous step's scale, likewise), or
//! 1e-9 absolute. The operations are the CPU's in the same order; the differences come from the
//! GPU fusing multiply-adds, its division and square root (Vulkan allows 2.5 and ~2 ulp), and its
//! `exp` in the mask slices' sigmoid. The test prints the fraction of bit-identical values (on
//! lavapipe: 99% of them, the others within 1.3 ulp; on an NVIDIA H200, which fuses
//! multiply-adds, an `m` 4.6 ulp and a `v` 4.05 ulp from the CPU's, measured against their own
//! step's terms alone).
//! The mask loss: relative 1e-5.
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`), and
//! [`main`] lists every test.

mod common;

use msth_core::rng::Rng;
use msth_gpu::adam::{AdamHyper, AdamKernel, GpuAdam, MaskSlice, MAX_GRADIENT};
use msth_gpu::GpuError;
use msth_testkit::Tests;

use common::{device, gpu_need};
use msth_trainer::adam::{Adam, AdamConfig, ScaledSlice};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "adam_matches_the_trainer_step_for_step",
            adam_matches_the_trainer_step_for_step,
        )
        .needs(
            &[&gpu],
            "adam_bad_input_is_an_error",
            adam_bad_input_is_an_error,
        )
        .run()
}

const N: usize = 40_003;

fn masks() -> Vec<ScaledSlice> {
    vec![
        ScaledSlice {
            range: 1_000..5_000,
            weight: 0.5,
            lr_scale: 10.0,
            decay: 0.0,
        },
        ScaledSlice {
            range: 30_016..31_000,
            weight: 1.0,
            lr_scale: 1.0,
            decay: 0.0,
        },
        // Weight decay without a mask loss (the trainer's `grid_decay` slices).
        ScaledSlice {
            range: 20_000..25_000,
            weight: 0.0,
            lr_scale: 1.0,
            decay: 0.37,
        },
    ]
}

fn gpu_masks() -> Vec<MaskSlice> {
    masks()
        .into_iter()
        .map(|s| MaskSlice {
            range: s.range,
            weight: s.weight,
            lr_scale: s.lr_scale,
            decay: s.decay,
        })
        .collect()
}

fn gradient(rng: &mut Rng) -> Vec<f32> {
    (0..N)
        .map(|i| match i % 7 {
            0 => 0.0,
            1 => rng.range_f32(-1e-12, 1e-12),
            2 => rng.range_f32(-1e20, 1e20),
            3 => rng.range_f32(-100.0, 100.0),
            _ => rng.range_f32(-1.0, 1.0),
        })
        .collect()
}

/// Worst distance in ulp of `scale` (the magnitude of the terms that made the value), and the
/// count of bit-identical values; panics past the tolerance.
fn compare(what: &str, step: u64, gpu: &[f32], cpu: &[f32], scale: &[f32]) -> (f32, usize) {
    let (mut worst, mut same) = (0f32, 0);
    for (i, (&g, &c)) in gpu.iter().zip(cpu).enumerate() {
        if g.to_bits() == c.to_bits() {
            same += 1;
            continue;
        }
        let ulp = (scale[i] * f32::EPSILON).max(f32::MIN_POSITIVE);
        let err = (g - c).abs();
        assert!(
            err <= 4.0 * ulp || err <= 1e-9,
            "step {step}: {what}[{i}]: gpu {g} cpu {c} ({} ulp of {})",
            err / ulp,
            scale[i]
        );
        if err > 1e-9 {
            worst = worst.max(err / ulp);
        }
    }
    (worst, same)
}

fn adam_matches_the_trainer_step_for_step() {
    assert_eq!(MAX_GRADIENT, msth_trainer::adam::MAX_GRADIENT);
    let dev = device();
    let kernel = AdamKernel::new(&dev).unwrap();
    let cfg = AdamConfig::default();
    let hyper = AdamHyper {
        beta1: cfg.beta1,
        beta2: cfg.beta2,
        eps: cfg.eps,
    };
    let mut rng = Rng::new(21);
    let mut p_cpu: Vec<f32> = (0..N).map(|_| rng.range_f32(-2.0, 2.0)).collect();
    let mut cpu = Adam::new(N);
    let mut gpu = GpuAdam::new(&dev, N).unwrap();
    let params = dev.buffer_f32("params", &p_cpu).unwrap();
    let grad = dev.zeros_f32("grad", N).unwrap();
    let steps = 12u64;
    let (mut p_prev, mut m_prev) = (p_cpu.clone(), cpu.m.clone());
    // Every step's rounding stays in the parameter: the sum of the steps' sizes so far.
    let mut p_path = vec![0f32; N];
    let mut m_hist = vec![0f32; N];
    let mut v_hist = vec![0f32; N];
    let (mut worst, mut same, mut total) = (0f32, 0usize, 0usize);
    for s in 0..steps {
        let lr = cfg.lr_at_fraction(s as f32 / (steps - 1) as f32);
        let g = gradient(&mut rng);
        let loss_cpu = cpu.update(&cfg, lr, &mut p_cpu, &g, &masks());
        dev.write_f32(&grad, &g).unwrap();
        gpu.update(&dev, &kernel, &hyper, lr, &params, &grad, &gpu_masks())
            .unwrap();
        let loss_gpu = gpu.mask_loss(&dev).unwrap();
        assert!(
            (loss_gpu - loss_cpu).abs() <= 1e-5 * loss_cpu.abs(),
            "step {s}: mask loss gpu {loss_gpu} cpu {loss_cpu}"
        );
        let p_gpu = dev.read_f32(&params, N).unwrap();
        let (m, v, step) = gpu.state(&dev).unwrap();
        assert_eq!(step, cpu.step);
        // Scales: a parameter's value and the steps it took; a moment's old and new values and
        // its share of the (clamped) gradient.
        for i in 0..N {
            p_path[i] += (p_cpu[i] - p_prev[i]).abs();
        }
        let p_scale: Vec<f32> = (0..N).map(|i| p_cpu[i].abs() + p_path[i]).collect();
        // A moment also carries the roundings of earlier steps, decayed by beta1 each step.
        let m_scale: Vec<f32> = (0..N)
            .map(|i| {
                cpu.m[i].abs()
                    + m_prev[i].abs()
                    + 0.1 * g[i].abs().min(MAX_GRADIENT)
                    + cfg.beta1 * m_hist[i]
            })
            .collect();
        m_hist.clone_from(&m_scale);
        // Likewise `v`, whose roundings decay by beta2.
        let v_scale: Vec<f32> = (0..N)
            .map(|i| cpu.v[i].abs() + cfg.beta2 * v_hist[i])
            .collect();
        v_hist.clone_from(&v_scale);
        for (what, a, b, sc) in [
            ("p", &p_gpu, &p_cpu, &p_scale),
            ("m", &m, &cpu.m, &m_scale),
            ("v", &v, &cpu.v, &v_scale),
        ] {
            let (w, n) = compare(what, s, a, b, sc);
            worst = worst.max(w);
            same += n;
            total += N;
        }
        p_prev.clone_from(&p_cpu);
        m_prev.clone_from(&cpu.m);
    }
    println!(
        "adam: {steps} steps, {:.2}% of parameters and moments bit-identical, worst {worst:.2} ulp",
        100.0 * same as f64 / total as f64
    );
    // A run resumed from the downloaded state (as from a checkpoint) goes on identically.
    let (m, v, step) = gpu.state(&dev).unwrap();
    let mut resumed = GpuAdam::with_state(&dev, &m, &v, step).unwrap();
    let params2 = dev
        .buffer_f32("params", &dev.read_f32(&params, N).unwrap())
        .unwrap();
    let g = gradient(&mut rng);
    dev.write_f32(&grad, &g).unwrap();
    for (adam, p) in [(&mut gpu, &params), (&mut resumed, &params2)] {
        adam.update(&dev, &kernel, &hyper, 1e-3, p, &grad, &gpu_masks())
            .unwrap();
    }
    assert_eq!(
        dev.read_f32(&params, N).unwrap(),
        dev.read_f32(&params2, N).unwrap()
    );
    assert_eq!(gpu.state(&dev).unwrap(), resumed.state(&dev).unwrap());
}

fn adam_bad_input_is_an_error() {
    let dev = device();
    let kernel = AdamKernel::new(&dev).unwrap();
    let hyper = AdamHyper {
        beta1: 0.9,
        beta2: 0.99,
        eps: 1e-15,
    };
    let mut adam = GpuAdam::new(&dev, 100).unwrap();
    let small = dev.zeros_f32("small", 50).unwrap();
    let ok = dev.zeros_f32("ok", 100).unwrap();
    let bad_slice = [MaskSlice {
        range: 90..101,
        weight: 1.0,
        lr_scale: 1.0,
        decay: 0.0,
    }];
    for e in [
        adam.update(&dev, &kernel, &hyper, 1e-2, &small, &ok, &[])
            .unwrap_err(),
        adam.update(&dev, &kernel, &hyper, 1e-2, &ok, &ok, &bad_slice)
            .unwrap_err(),
        GpuAdam::with_state(&dev, &[0.0; 3], &[0.0; 2], 1)
            .err()
            .unwrap(),
    ] {
        assert!(matches!(e, GpuError::Input(_)), "{e}");
    }
    assert_eq!(adam.step(), 0, "a refused update does not count");
}
