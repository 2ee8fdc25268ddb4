//! The hash-grid kernels against `msth_core::grid`'s CPU reference on whatever adapter exists
//! (Mesa's lavapipe in CI): forward features for 3D and 4D grids with dense and hashed levels
//! and per-axis resolutions, inputs on vertices and outside the unit cube; backward gradients
//! through both atomic paths (native f32 atomics where the adapter has them, the
//! compare-exchange loop always, forced), under heavy contention, and against central finite
//! differences of a loss computed through the CPU reference.
//!
//! Tolerances (tables and gradients of magnitude <= 1):
//! - forward: |gpu - cpu| <= 2e-6 + 2 eps sum_a (scale_a + 0.5) per feature of a level (same
//!   operation order, but the GPU may fuse `x * scale + 0.5` into one multiply-add, as NVIDIA's
//!   compiler does, rounding the scaled position once where the CPU rounds twice: each axis'
//!   interpolation weight moves by up to eps (scale_a + 0.5), and the value by up to twice
//!   that per axis for tables in [-1, 1]; the lower corner can differ at a cell boundary where
//!   both cells give the same value);
//! - backward: |gpu - cpu| <= 1e-5 * sum|contributions| + 1e-6 per entry (atomics add in any
//!   order; f32 rounding grows with the number and size of the terms summed);
//! - finite differences: |gpu - fd| <= 1e-3 per entry (the loss is linear in the table, so
//!   the difference quotient is exact up to f64-summed f32 rounding).
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`), and
//! [`main`] lists every test.

mod common;

use msth_core::grid::{GridConfig, GridLayout};
use msth_core::rng::Rng;
use msth_gpu::hashgrid::{AtomicMode, HashGridKernels};
use msth_gpu::GpuError;
use msth_testkit::Tests;

use common::{device, gpu_need, modes};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "forward_matches_the_cpu_reference",
            forward_matches_the_cpu_reference,
        )
        .needs(
            &[&gpu],
            "backward_matches_the_cpu_reference_on_both_atomic_paths",
            backward_matches_the_cpu_reference_on_both_atomic_paths,
        )
        .needs(
            &[&gpu],
            "backward_under_contention_loses_no_update",
            backward_under_contention_loses_no_update,
        )
        .needs(
            &[&gpu],
            "backward_matches_finite_differences_of_the_cpu_reference",
            backward_matches_finite_differences_of_the_cpu_reference,
        )
        .needs(
            &[&gpu],
            "bad_input_is_an_error_not_a_panic",
            bad_input_is_an_error_not_a_panic,
        )
        .run()
}

/// Grids with coarse dense levels, fine hashed ones, and different resolutions per axis.
fn grids() -> Vec<GridLayout> {
    let shapes = [
        (3, 2, vec![4.0, 6.0, 3.0], vec![64.0, 90.0, 40.0]),
        (4, 2, vec![4.0, 4.0, 4.0, 2.0], vec![64.0, 64.0, 64.0, 10.0]),
        (3, 8, vec![4.0; 3], vec![48.0; 3]),
        (4, 1, vec![3.0, 4.0, 5.0, 2.0], vec![40.0, 50.0, 60.0, 30.0]),
        (4, 4, vec![4.0, 4.0, 4.0, 3.0], vec![32.0, 32.0, 32.0, 12.0]),
    ];
    shapes
        .into_iter()
        .map(|(dims, f, base, finest)| {
            let c = GridConfig {
                levels: 6,
                features_per_level: f,
                log2_table_size: 10,
                base_resolution: base,
                finest_resolution: finest,
            };
            assert_eq!(c.dims(), dims);
            c.validate("test grid").unwrap();
            let g = GridLayout::new(&c);
            assert!(g.levels.iter().any(|l| l.dense) && g.levels.iter().any(|l| !l.dense));
            g
        })
        .collect()
}

/// Random points plus the awkward ones: vertices of a level, the cube's corners, outside it,
/// NaN and infinities (clamped as on the CPU).
fn points(g: &GridLayout, n: usize, rng: &mut Rng) -> Vec<[f32; 4]> {
    let mut p: Vec<[f32; 4]> = (0..n)
        .map(|_| [rng.f32(), rng.f32(), rng.f32(), rng.f32()])
        .collect();
    let s = g.levels[1].scale;
    p.push([
        (2.0 - 0.5) / s[0],
        (3.0 - 0.5) / s[1],
        (1.0 - 0.5) / s[2],
        0.5,
    ]);
    p.push([0.0; 4]);
    p.push([1.0; 4]);
    p.push([-0.25, 1.5, 0.5, 2.0]);
    p.push([f32::NAN, 0.5, f32::INFINITY, f32::NEG_INFINITY]);
    p
}

fn random_table(g: &GridLayout, rng: &mut Rng) -> Vec<f32> {
    (0..g.num_params)
        .map(|_| rng.range_f32(-1.0, 1.0))
        .collect()
}

fn reference_backward(g: &GridLayout, pts: &[[f32; 4]], d: &[f32]) -> Vec<f32> {
    let k = g.output_dim();
    let mut grad = vec![0f32; g.num_params];
    for (i, p) in pts.iter().enumerate() {
        g.backward_point_reference(p, &d[i * k..(i + 1) * k], &mut grad);
    }
    grad
}

fn forward_matches_the_cpu_reference() {
    let dev = device();
    let k = HashGridKernels::new(&dev, AtomicMode::CompareExchange).unwrap();
    let mut rng = Rng::new(7);
    for g in grids() {
        let table = random_table(&g, &mut rng);
        let pts = points(&g, 2000, &mut rng);
        let gpu = k.forward_host(&dev, &g, &table, &pts).unwrap();
        let dim = g.output_dim();
        assert_eq!(gpu.len(), pts.len() * dim);
        // Per level: 2e-6, plus what one rounding of each axis' scaled position can move the
        // interpolated value (|d value / d weight_a| <= 2 max|table| = 2).
        let tol: Vec<f32> = g
            .levels
            .iter()
            .map(|l| {
                let pos: f32 = l.scale[..g.dims].iter().map(|s| s + 0.5).sum();
                2e-6 + 2.0 * f32::EPSILON * pos
            })
            .collect();
        let mut worst = 0f32;
        for (i, p) in pts.iter().enumerate() {
            let cpu = g.encode_point_reference(&table, p);
            for (j, (a, b)) in gpu[i * dim..(i + 1) * dim].iter().zip(&cpu).enumerate() {
                let e = (a - b).abs();
                let t = tol[j / g.features];
                assert!(
                    e <= t,
                    "dims {} F {}: point {i} {p:?} feature {j}: gpu {a} cpu {b} (tolerance {t:.2e})",
                    g.dims,
                    g.features
                );
                worst = worst.max(e / t);
            }
        }
        println!(
            "forward dims {} F {}: {} points, worst error / tolerance {worst:.3}",
            g.dims,
            g.features,
            pts.len()
        );
    }
}

fn check_grad(g: &GridLayout, gpu: &[f32], cpu: &[f32], abs_sum: &[f32], what: &str) -> f32 {
    let mut worst = 0f32;
    for e in 0..g.num_params {
        let err = (gpu[e] - cpu[e]).abs();
        let tol = 1e-5 * abs_sum[e] + 1e-6;
        assert!(
            err <= tol,
            "{what}: entry {e}: gpu {} cpu {} (sum of |terms| {})",
            gpu[e],
            cpu[e],
            abs_sum[e]
        );
        worst = worst.max(err / tol);
    }
    worst
}

fn backward_matches_the_cpu_reference_on_both_atomic_paths() {
    let dev = device();
    for mode in modes(&dev) {
        let k = HashGridKernels::new(&dev, mode).unwrap();
        let mut rng = Rng::new(11);
        for g in grids() {
            let pts = points(&g, 3000, &mut rng);
            let d: Vec<f32> = (0..pts.len() * g.output_dim())
                .map(|_| rng.range_f32(-1.0, 1.0))
                .collect();
            let gpu = k.backward_host(&dev, &g, &pts, &d).unwrap();
            let cpu = reference_backward(&g, &pts, &d);
            let abs: Vec<f32> = d.iter().map(|v| v.abs()).collect();
            let abs_sum = reference_backward(&g, &pts, &abs);
            assert!(cpu.iter().filter(|v| **v != 0.0).count() > 100);
            let worst = check_grad(&g, &gpu, &cpu, &abs_sum, &format!("{mode:?}"));
            println!(
                "backward {mode:?} dims {} F {}: worst error / tolerance {worst:.3}",
                g.dims, g.features
            );
        }
    }
}

fn backward_under_contention_loses_no_update() {
    // 20,000 samples at one point: every invocation of a level adds into the same 2^D rows.
    let dev = device();
    let g = &grids()[1];
    let n = 20_000;
    let pts = vec![[0.3, 0.6, 0.2, 0.7]; n];
    let d = vec![1.0f32; n * g.output_dim()];
    let cpu_one = reference_backward(g, &pts[..1], &d[..g.output_dim()]);
    for mode in modes(&dev) {
        let k = HashGridKernels::new(&dev, mode).unwrap();
        let gpu = k.backward_host(&dev, g, &pts, &d).unwrap();
        for e in 0..g.num_params {
            let want = cpu_one[e] as f64 * n as f64;
            let err = (gpu[e] as f64 - want).abs();
            // n additions of a value <= 1 in f32: relative rounding at most about n * 2^-24.
            assert!(
                err <= 2e-3 * want.abs() + 1e-6,
                "{mode:?}: entry {e}: gpu {} expected {want}",
                gpu[e]
            );
        }
    }
}

fn backward_matches_finite_differences_of_the_cpu_reference() {
    let dev = device();
    let mut rng = Rng::new(23);
    for g in grids() {
        let table = random_table(&g, &mut rng);
        let pts = points(&g, 40, &mut rng);
        let dim = g.output_dim();
        let weights: Vec<f32> = (0..pts.len() * dim)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        // loss = sum_i sum_k weights_ik * features_ik(table), through the CPU reference.
        let loss = |t: &[f32]| -> f64 {
            let mut s = 0f64;
            for (i, p) in pts.iter().enumerate() {
                let f = g.encode_point_reference(t, p);
                for j in 0..dim {
                    s += weights[i * dim + j] as f64 * f[j] as f64;
                }
            }
            s
        };
        for mode in modes(&dev) {
            let k = HashGridKernels::new(&dev, mode).unwrap();
            let gpu = k.backward_host(&dev, &g, &pts, &weights).unwrap();
            let touched: Vec<usize> = (0..g.num_params).filter(|&e| gpu[e] != 0.0).collect();
            assert!(touched.len() > 50);
            let mut picks: Vec<usize> = (0..24)
                .map(|_| touched[rng.below(touched.len() as u64) as usize])
                .collect();
            // and a few entries no sample reached (gradient exactly 0)
            picks.extend((0..4).map(|_| rng.below(g.num_params as u64) as usize));
            let h = 0.25f32;
            let mut worst = 0f64;
            for e in picks {
                let mut t = table.clone();
                t[e] = table[e] + h;
                let up = loss(&t);
                t[e] = table[e] - h;
                let down = loss(&t);
                let fd = (up - down) / (2.0 * h as f64);
                let err = (gpu[e] as f64 - fd).abs();
                assert!(
                    err <= 1e-3,
                    "{mode:?} dims {} F {}: entry {e}: gpu {} finite difference {fd}",
                    g.dims,
                    g.features,
                    gpu[e]
                );
                worst = worst.max(err);
            }
            println!(
                "finite differences {mode:?} dims {} F {}: worst |gpu - fd| {worst:.2e}",
                g.dims, g.features
            );
        }
    }
}

fn bad_input_is_an_error_not_a_panic() {
    let dev = device();
    let k = HashGridKernels::new(&dev, AtomicMode::CompareExchange).unwrap();
    let g = &grids()[0];
    let short = vec![0f32; g.num_params - 1];
    let e = k.forward_host(&dev, g, &short, &[[0.5; 4]]).unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
    let e = k
        .backward_host(&dev, g, &[[0.5; 4]; 2], &[0.0; 3])
        .unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
    // A points buffer too small for the sample count.
    let grid = msth_gpu::hashgrid::GpuGrid::new(g, 0).unwrap();
    let t = dev.zeros_f32("table", g.num_params).unwrap();
    let p = dev.zeros_f32("points", 4).unwrap();
    let out = dev.zeros_f32("features", 10 * g.output_dim()).unwrap();
    let e = k.forward(&dev, &grid, &t, &p, 10, &out).unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
    // Native atomics where the device lacks them.
    if !dev.has_float_atomics() {
        let e = HashGridKernels::new(&dev, AtomicMode::NativeF32)
            .err()
            .expect("refused");
        assert!(matches!(e, GpuError::MissingFeature(_)), "{e}");
    }
    // No samples: nothing to do, no error.
    assert!(k
        .forward_host(&dev, g, &vec![0.0; g.num_params], &[])
        .unwrap()
        .is_empty());
}
