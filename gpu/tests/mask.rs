//! The mask kernels against `msth_core`'s CPU mask (`DenseGrid3` + sigmoid) on whatever adapter
//! exists: forward values, backward gradients on both atomic paths, and the backward against
//! central finite differences of a loss computed through the CPU reference.
//!
//! Tolerances: forward |gpu - cpu| <= 1e-6 per value (the GPU's `exp` is not correctly
//! rounded); backward |gpu - cpu| <= 1e-5 * sum|contributions| + 1e-7 per entry (atomics add
//! in any order); finite differences (h = 1e-2, f64 loss of f32 CPU values)
//! |gpu - fd| <= 1e-3 * max(1, |fd|).
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`), and
//! [`main`] lists every test.

mod common;

use msth_core::activation::sigmoid;
use msth_core::grid::DenseGrid3;
use msth_core::rng::Rng;
use msth_gpu::hashgrid::AtomicMode;
use msth_gpu::mask::MaskKernels;
use msth_gpu::GpuError;
use msth_testkit::Tests;

use common::{device, gpu_need, modes};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "mask_forward_and_backward_match_the_cpu",
            mask_forward_and_backward_match_the_cpu,
        )
        .needs(
            &[&gpu],
            "mask_backward_matches_finite_differences_of_the_cpu_reference",
            mask_backward_matches_finite_differences_of_the_cpu_reference,
        )
        .needs(
            &[&gpu],
            "mask_bad_input_is_an_error",
            mask_bad_input_is_an_error,
        )
        .run()
}

fn points(n: usize, rng: &mut Rng) -> Vec<[f32; 4]> {
    let mut p: Vec<[f32; 4]> = (0..n)
        .map(|_| [rng.f32(), rng.f32(), rng.f32(), rng.f32()])
        .collect();
    p.extend([
        [0.0; 4],
        [1.0; 4],
        [0.5, 0.25, 0.75, 0.0],
        [-0.5, 1.5, f32::NAN, 0.0],
    ]);
    p
}

const GRID: DenseGrid3 = DenseGrid3 { res: 9 };

fn cpu_m(logits: &[f32], p: &[f32; 4]) -> f32 {
    sigmoid(GRID.sample(logits, p))
}

fn mask_forward_and_backward_match_the_cpu() {
    let dev = device();
    let mut rng = Rng::new(5);
    let logits: Vec<f32> = (0..GRID.num_params())
        .map(|_| rng.range_f32(-4.0, 4.0))
        .collect();
    let pts = points(3000, &mut rng);
    let cpu: Vec<f32> = pts.iter().map(|p| cpu_m(&logits, p)).collect();
    let d_m: Vec<f32> = (0..pts.len()).map(|_| rng.range_f32(-1.0, 1.0)).collect();
    let mut ref_grad = vec![0f32; GRID.num_params()];
    let mut abs_sum = vec![0f32; GRID.num_params()];
    for (i, p) in pts.iter().enumerate() {
        let d = d_m[i] * cpu[i] * (1.0 - cpu[i]);
        GRID.backward(p, d, &mut ref_grad);
        GRID.backward(p, d.abs(), &mut abs_sum);
    }
    for mode in modes(&dev) {
        let k = MaskKernels::new(&dev, mode).unwrap();
        let gpu = k.forward_host(&dev, GRID, &logits, &pts).unwrap();
        let mut worst = 0f32;
        for (i, (a, b)) in gpu.iter().zip(&cpu).enumerate() {
            assert!(
                (a - b).abs() <= 1e-6,
                "point {i} {:?}: gpu {a} cpu {b}",
                pts[i]
            );
            worst = worst.max((a - b).abs());
        }
        println!("mask forward {mode:?}: worst |gpu - cpu| {worst:.2e}");
        // The backward from the CPU's m, so that only the scatter is compared.
        let grad = k.backward_host(&dev, GRID, &pts, &cpu, &d_m).unwrap();
        let mut worst = 0f32;
        for e in 0..GRID.num_params() {
            let tol = 1e-5 * abs_sum[e] + 1e-7;
            let err = (grad[e] - ref_grad[e]).abs();
            assert!(
                err <= tol,
                "{mode:?}: entry {e}: gpu {} cpu {}",
                grad[e],
                ref_grad[e]
            );
            worst = worst.max(err / tol);
        }
        println!("mask backward {mode:?}: worst error / tolerance {worst:.3}");
    }
}

fn mask_backward_matches_finite_differences_of_the_cpu_reference() {
    let dev = device();
    let mut rng = Rng::new(9);
    let logits: Vec<f32> = (0..GRID.num_params())
        .map(|_| rng.range_f32(-2.0, 2.0))
        .collect();
    let pts = points(60, &mut rng);
    let weights: Vec<f32> = (0..pts.len()).map(|_| rng.range_f32(-1.0, 1.0)).collect();
    let loss = |l: &[f32]| -> f64 {
        pts.iter()
            .zip(&weights)
            .map(|(p, w)| *w as f64 * cpu_m(l, p) as f64)
            .sum()
    };
    for mode in modes(&dev) {
        let k = MaskKernels::new(&dev, mode).unwrap();
        let m = k.forward_host(&dev, GRID, &logits, &pts).unwrap();
        let grad = k.backward_host(&dev, GRID, &pts, &m, &weights).unwrap();
        let touched: Vec<usize> = (0..grad.len()).filter(|&e| grad[e] != 0.0).collect();
        assert!(touched.len() > 20);
        let h = 1e-2f32;
        let mut worst = 0f64;
        for _ in 0..30 {
            let e = touched[rng.below(touched.len() as u64) as usize];
            let mut l = logits.clone();
            l[e] = logits[e] + h;
            let up = loss(&l);
            l[e] = logits[e] - h;
            let down = loss(&l);
            let fd = (up - down) / (2.0 * h as f64);
            let err = (grad[e] as f64 - fd).abs();
            assert!(
                err <= 1e-3 * fd.abs().max(1.0),
                "{mode:?}: entry {e}: gpu {} finite difference {fd}",
                grad[e]
            );
            worst = worst.max(err);
        }
        println!("mask finite differences {mode:?}: worst |gpu - fd| {worst:.2e}");
    }
}

fn mask_bad_input_is_an_error() {
    let dev = device();
    let k = MaskKernels::new(&dev, AtomicMode::CompareExchange).unwrap();
    let e = k
        .forward_host(&dev, GRID, &[0.0; 3], &[[0.5; 4]])
        .unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
    let e = k
        .forward_host(&dev, DenseGrid3 { res: 1 }, &[0.0], &[[0.5; 4]])
        .unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
    let e = k
        .backward_host(&dev, GRID, &[[0.5; 4]; 2], &[0.5], &[1.0, 1.0])
        .unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
}
