//! The SIMD MLP kernels (`core/src/mlp/simd.rs`, AVX2 + FMA and AVX-512F) against the
//! `matrixmultiply` path and the plain per-row reference, forward and backward, and their
//! backward against finite differences, on odd shapes (1, 3, 15, 16, 17, 31, 64 units; batches that are not a multiple
//! of the kernels' 6-row tiles or 64-row chunks).
//!
//! The two paths round differently (one FMA per step against a multiply and an add, sums split
//! differently), so outputs are compared within `1e-5` of the sum of the absolute values of the
//! terms that make them (the same pass run on `|W|`, `|x|` and `|dL/dy|`), the usual bound on a
//! float dot product's rounding.
//!
//! On a CPU without AVX2 and FMA (AVX-512F) there is nothing to compare for those kernels, and
//! their tests are reported as ignored with the reason (unless `MSTH_REQUIRE_AVX2=1`,
//! `MSTH_REQUIRE_AVX512=1`): this binary runs on `msth-testkit`'s harness.

use msth_core::mlp::{MlpActivations, MlpKernels, MlpLayout};
use msth_core::rng::Rng;
use msth_testkit::{Need, Tests};

fn main() -> std::process::ExitCode {
    let need = |kind: &str, kernels: MlpKernels, what: &'static str| {
        Need::new(kind, move || {
            if kernels.available() {
                Ok(())
            } else {
                Err(format!("this CPU has no {what} (or is not x86_64)"))
            }
        })
    };
    let avx2 = need("avx2", MlpKernels::Avx2, "AVX2 and FMA");
    let avx512 = need("avx512", MlpKernels::Avx512, "AVX-512F");
    let mut tests = Tests::new(file!());
    for (need, kernels, name) in [
        (&avx2, MlpKernels::Avx2, "avx2"),
        (&avx512, MlpKernels::Avx512, "avx512"),
    ] {
        tests = tests
            .needs(
                &[need],
                &format!("{name}_forward_matches_gemm_and_reference"),
                move || forward_matches_gemm_and_reference(kernels),
            )
            .needs(
                &[need],
                &format!("{name}_backward_matches_gemm"),
                move || backward_matches_gemm(kernels),
            )
            .needs(
                &[need],
                &format!("{name}_backward_matches_finite_differences"),
                move || backward_matches_finite_differences(kernels),
            );
    }
    tests.run()
}

/// Relative tolerance against the sum of the absolute terms.
const REL: f64 = 1e-5;

/// The shapes: every width of 1, 3, 15, 16, 17, 31, 64 as an input, a hidden layer and an
/// output, with one or two hidden layers, plus the training ones.
fn shapes() -> Vec<Vec<usize>> {
    let widths = [1, 3, 15, 16, 17, 31, 64];
    let mut s = vec![
        vec![24, 64, 16],
        vec![32, 64, 16],
        vec![31, 64, 64, 3],
        vec![10, 16, 1],
        vec![3, 16, 16, 1],
    ];
    for (a, &fi) in widths.iter().enumerate() {
        for (b, &h) in widths.iter().enumerate() {
            let fo = widths[(a + 2 * b) % widths.len()];
            s.push(vec![fi, h, fo]);
            if (a + b) % 3 == 0 {
                s.push(vec![fi, h, widths[(a + b) % widths.len()], fo]);
            }
        }
    }
    s
}

/// Batch sizes: below, at and above the 6- and 8-row tiles and the 64-row chunks.
const BATCHES: [usize; 6] = [1, 5, 6, 13, 64, 131];

fn random(rng: &mut Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect()
}

fn abs(v: &[f32]) -> Vec<f32> {
    v.iter().map(|x| x.abs()).collect()
}

/// `|fast - slow| <= REL * scale` element by element.
fn assert_close(fast: &[f32], slow: &[f32], scale: &[f32], what: &str) {
    assert_eq!(fast.len(), slow.len(), "{what}: lengths");
    for (i, ((&f, &s), &sc)) in fast.iter().zip(slow).zip(scale).enumerate() {
        let tol = REL * sc as f64 + 1e-30;
        assert!(
            ((f - s) as f64).abs() <= tol,
            "{what}[{i}]: {f} vs {s} (scale {sc}, tolerance {tol:e})"
        );
    }
}

/// Every layer's output, fast path against the `matrixmultiply` path, and the output against
/// [`MlpLayout::forward_reference`] row by row.
fn forward_matches_gemm_and_reference(kernels: MlpKernels) {
    let mut rng = Rng::new(11);
    for dims in shapes() {
        let mlp = MlpLayout::new(&dims);
        let mut p = vec![0f32; mlp.num_params];
        mlp.init(&mut p, &mut rng);
        let p_abs = abs(&p);
        for n in BATCHES {
            let x = random(&mut rng, n * dims[0]);
            let (mut fast, mut slow, mut scale) = Default::default();
            mlp.forward_with(kernels, &p, &x, n, &mut fast);
            mlp.forward_with(MlpKernels::Gemm, &p, &x, n, &mut slow);
            // The sum of the absolute terms of every output (ReLU does not change a bound of
            // non-negative terms).
            mlp.forward_with(MlpKernels::Gemm, &p_abs, &abs(&x), n, &mut scale);
            let (fast, slow, scale): (&MlpActivations, &MlpActivations, &MlpActivations) =
                (&fast, &slow, &scale);
            for k in 0..mlp.num_layers() {
                assert_close(
                    &fast.acts[k],
                    &slow.acts[k],
                    &scale.acts[k],
                    &format!("{dims:?} n {n} layer {k}"),
                );
            }
            let out = mlp.output(fast);
            let sc = mlp.output(scale);
            let fo = mlp.output_dim();
            for r in 0..n {
                let reference = mlp.forward_reference(&p, &x[r * dims[0]..(r + 1) * dims[0]]);
                assert_close(
                    &out[r * fo..(r + 1) * fo],
                    &reference,
                    &sc[r * fo..(r + 1) * fo],
                    &format!("{dims:?} n {n} row {r} against the reference"),
                );
            }
        }
    }
}

/// Weight gradients (added to non-zero ones) and input gradients (all columns, the last ones,
/// none), fast path against the `matrixmultiply` path on the same forward activations.
fn backward_matches_gemm(kernels: MlpKernels) {
    let mut rng = Rng::new(12);
    for dims in shapes() {
        let mlp = MlpLayout::new(&dims);
        let mut p = vec![0f32; mlp.num_params];
        mlp.init(&mut p, &mut rng);
        let p_abs = abs(&p);
        let (fi, fo) = (dims[0], mlp.output_dim());
        for n in BATCHES {
            let x = random(&mut rng, n * fi);
            let d_out = random(&mut rng, n * fo);
            let grad0 = random(&mut rng, mlp.num_params);
            let mut acts = MlpActivations::default();
            mlp.forward_with(MlpKernels::Gemm, &p, &x, n, &mut acts);
            for from in [None, Some(0), Some(fi / 2), Some(fi)] {
                let cols = from.map_or(0, |f| fi - f);
                let run =
                    |kernels: MlpKernels, p: &[f32], x: &[f32], d_out: &[f32], grad0: &[f32]| {
                        let mut a = acts.clone();
                        let mut grad = grad0.to_vec();
                        let mut dx = vec![f32::NAN; n * cols];
                        mlp.backward_partial_with(
                            kernels,
                            p,
                            x,
                            n,
                            &mut a,
                            d_out,
                            &mut grad,
                            from.map(|f| (f, &mut dx[..])),
                        );
                        (grad, dx)
                    };
                let fast = run(kernels, &p, &x, &d_out, &grad0);
                let slow = run(MlpKernels::Gemm, &p, &x, &d_out, &grad0);
                // The sums of the absolute terms: the same pass on |W|, |x|, |dL/dy| and
                // |grad0|, gated by the same activations (the hidden ones are non-negative).
                let scale = run(
                    MlpKernels::Gemm,
                    &p_abs,
                    &abs(&x),
                    &abs(&d_out),
                    &abs(&grad0),
                );
                let what = format!("{dims:?} n {n} d_input from {from:?}");
                assert_close(&fast.0, &slow.0, &scale.0, &format!("{what}: weights"));
                assert_close(&fast.1, &slow.1, &scale.1, &format!("{what}: inputs"));
            }
        }
    }
}

/// The fast backward against central differences of the reference forward (in f64) on odd
/// shapes, as `mlp::tests::backward_matches_finite_differences` does for the default path.
fn backward_matches_finite_differences(kernels: MlpKernels) {
    for (seed, dims, n) in [
        (4, vec![6, 8, 8, 3], 5),
        (5, vec![17, 15, 3], 7),
        (6, vec![3, 17, 16, 1], 5),
        (7, vec![16, 31, 17], 8),
    ] {
        let mlp = MlpLayout::new(&dims);
        let mut rng = Rng::new(seed);
        let mut p = vec![0f32; mlp.num_params];
        mlp.init(&mut p, &mut rng);
        let (fi, fo) = (dims[0], mlp.output_dim());
        let x = random(&mut rng, n * fi);
        let wts = random(&mut rng, n * fo);
        let loss = |p: &[f32], x: &[f32]| -> f64 {
            let mut s = 0f64;
            for i in 0..n {
                let r = mlp.forward_reference(p, &x[i * fi..(i + 1) * fi]);
                for o in 0..fo {
                    s += r[o] as f64 * wts[i * fo + o] as f64;
                }
            }
            s
        };
        let mut acts = MlpActivations::default();
        mlp.forward_with(kernels, &p, &x, n, &mut acts);
        let mut grad = vec![0f32; mlp.num_params];
        let mut dx = vec![0f32; n * fi];
        mlp.backward_partial_with(
            kernels,
            &p,
            &x,
            n,
            &mut acts,
            &wts,
            &mut grad,
            Some((0, &mut dx)),
        );
        let h = 1e-3f32;
        let central = |f: &dyn Fn(&[f32]) -> f64, v: &[f32], i: usize| {
            let mut q = v.to_vec();
            q[i] += h;
            let lp = f(&q);
            q[i] -= 2.0 * h;
            let lm = f(&q);
            (lp - lm) / (2.0 * h as f64)
        };
        for i in 0..mlp.num_params {
            let fd = central(&|pp| loss(pp, &x), &p, i);
            assert!(
                (fd - grad[i] as f64).abs() < 2e-3,
                "{dims:?} w{i}: {fd} vs {}",
                grad[i]
            );
        }
        for i in 0..n * fi {
            let fd = central(&|xx| loss(&p, xx), &x, i);
            assert!(
                (fd - dx[i] as f64).abs() < 2e-3,
                "{dims:?} x{i}: {fd} vs {}",
                dx[i]
            );
        }
    }
}
