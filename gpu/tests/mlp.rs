//! The MLP kernels against `msth_core::mlp::MlpLayout` (with `msth_core::field`'s output
//! activations) and the SH kernel against `msth_core::sh::sh4`, on whatever adapter exists
//! (Mesa's lavapipe in CI), for the MLP shapes of the demo (fast preset) and paper models:
//! density `[levels x 2, 64, 16]` (trunc_exp on the density), colour `[31, 64, 64, 3]`
//! (sigmoid), proposal `[10, 16, 1]`; sample counts that leave the last tile partial.
//!
//! Tolerances, per value, from `A` = the same quantity computed by the CPU with every weight,
//! input and output gradient replaced by its absolute value (the sum of the magnitudes of the
//! terms, an upper bound: f32 sums in another order differ by at most ~ terms x 2^-24 x A):
//! - forward raw outputs: |gpu - cpu| <= 1e-5 A + 1e-6, activated outputs the same through the
//!   activation's slope (+ 2e-6 relative for the GPU's `exp`);
//! - backward weight and input gradients: |gpu - cpu| <= 1e-5 A + 1e-6 on both atomic paths;
//! - finite differences (central, h = 1e-3, f64 loss of core's f32 `forward_reference`):
//!   |gpu - fd| <= 2e-3 max(1, |fd|), skipping entries where a ReLU kink lies within 2e-3 (the
//!   central and second differences at 2e-3 and 1e-3 disagree beyond the tolerance), at most a
//!   quarter of them;
//! - SH: |gpu - cpu| <= 1e-6 (the same f32 constants; the GPU may fuse multiply-adds).
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`), and
//! [`main`] lists every test.

mod common;

use msth_core::activation::{sigmoid, sigmoid_grad_from_output, trunc_exp, trunc_exp_grad};
use msth_core::config::Preset;
use msth_core::field::ModelLayout;
use msth_core::mlp::{MlpActivations, MlpLayout};
use msth_core::rng::Rng;
use msth_core::sh::{sh4, SH_COEFFS};
use msth_gpu::hashgrid::AtomicMode;
use msth_gpu::mlp::{GpuMlp, MlpKernels, OutputActivation};
use msth_gpu::presets::{reference_model, REFERENCE_PRESETS};
use msth_gpu::sh::ShKernel;
use msth_gpu::GpuError;
use msth_testkit::Tests;

use common::{device, gpu_need, modes};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "mlp_forward_matches_the_cpu",
            mlp_forward_matches_the_cpu,
        )
        .needs(
            &[&gpu],
            "mlp_backward_matches_the_cpu_on_both_atomic_paths",
            mlp_backward_matches_the_cpu_on_both_atomic_paths,
        )
        .needs(
            &[&gpu],
            "mlp_backward_matches_finite_differences_of_the_cpu_reference",
            mlp_backward_matches_finite_differences_of_the_cpu_reference,
        )
        .needs(
            &[&gpu],
            "mlp_bad_input_is_an_error",
            mlp_bad_input_is_an_error,
        )
        .needs(&[&gpu], "sh_matches_the_cpu", sh_matches_the_cpu)
        .run()
}

/// One MLP of a preset model: its name, layout, activation and the first input column whose
/// gradient the field needs.
struct Case {
    name: String,
    layout: MlpLayout,
    act: OutputActivation,
    d_input_from: usize,
}

fn cases() -> Vec<Case> {
    let mut out = Vec::new();
    for (_, preset) in REFERENCE_PRESETS {
        let cfg = reference_model(preset);
        let m = ModelLayout::new(&cfg);
        out.push(Case {
            name: format!("{preset:?} density"),
            layout: m.field.density.0.clone(),
            act: OutputActivation::Density,
            d_input_from: 0,
        });
        out.push(Case {
            name: format!("{preset:?} colour"),
            layout: m.field.color.0.clone(),
            act: OutputActivation::Sigmoid,
            d_input_from: SH_COEFFS,
        });
        if preset == Preset::Fast {
            out.push(Case {
                name: "proposal density".into(),
                layout: m.proposal.field.density.0.clone(),
                act: OutputActivation::Density,
                d_input_from: 0,
            });
        }
    }
    out
}

fn weights(l: &MlpLayout, rng: &mut Rng) -> Vec<f32> {
    let mut w = vec![0f32; l.num_params];
    l.init(&mut w, rng);
    w
}

fn uniform(n: usize, rng: &mut Rng) -> Vec<f32> {
    (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect()
}

fn abs(v: &[f32]) -> Vec<f32> {
    v.iter().map(|x| x.abs()).collect()
}

/// The CPU's raw outputs of `n` rows.
fn cpu_raw(l: &MlpLayout, w: &[f32], x: &[f32], n: usize) -> Vec<f32> {
    let mut acts = MlpActivations::default();
    l.forward(w, x, n, &mut acts);
    l.output(&acts).to_vec()
}

fn activate(act: OutputActivation, o: usize, raw: f32) -> f32 {
    match act {
        OutputActivation::Identity => raw,
        OutputActivation::Sigmoid => sigmoid(raw),
        OutputActivation::Density if o == 0 => trunc_exp(raw),
        OutputActivation::Density => raw,
    }
}

fn mlp_forward_matches_the_cpu() {
    let dev = device();
    let k = MlpKernels::new(&dev, AtomicMode::CompareExchange).unwrap();
    let mut rng = Rng::new(11);
    for case in cases() {
        let l = &case.layout;
        let n = 700;
        let w = weights(l, &mut rng);
        let x = uniform(n * l.input_dim(), &mut rng);
        let mlp = GpuMlp::new(l, 0, case.act).unwrap();
        let (out, acts) = k.forward_host(&dev, &mlp, &w, &x).unwrap();
        let raw = cpu_raw(l, &w, &x, n);
        let bound = cpu_raw(l, &abs(&w), &abs(&x), n);
        let (fo, stride) = (l.output_dim(), mlp.acts_stride());
        let mut worst = 0f32;
        for s in 0..n {
            for o in 0..fo {
                let e = s * fo + o;
                let tol = 1e-5 * bound[e] + 1e-6;
                let g_raw = acts[s * stride + stride - fo + o];
                let err = (g_raw - raw[e]).abs();
                assert!(
                    err <= tol,
                    "{}: sample {s} output {o}: raw gpu {g_raw} cpu {}",
                    case.name,
                    raw[e]
                );
                worst = worst.max(err / tol);
                let want = activate(case.act, o, raw[e]);
                let slope = match case.act {
                    OutputActivation::Sigmoid => 0.25,
                    OutputActivation::Density if o == 0 => want * 1.01,
                    _ => 1.0,
                };
                let tol_out = slope * tol + 2e-6 * want.abs().max(1.0);
                assert!(
                    (out[e] - want).abs() <= tol_out,
                    "{}: sample {s} output {o}: gpu {} cpu {want}",
                    case.name,
                    out[e]
                );
            }
        }
        println!(
            "{} {:?}: forward worst error / tolerance {worst:.3}",
            case.name, l.dims
        );
    }
}

/// The CPU backward: `(weight gradient, input gradient of columns from..)` of `d_out` with
/// respect to the activated outputs, through the activation as `msth_core::field` does.
fn cpu_backward(case: &Case, w: &[f32], x: &[f32], n: usize, d_out: &[f32]) -> [Vec<f32>; 4] {
    let l = &case.layout;
    let fo = l.output_dim();
    let mut acts = MlpActivations::default();
    l.forward(w, x, n, &mut acts);
    let raw = l.output(&acts).to_vec();
    let d_raw: Vec<f32> = (0..n * fo)
        .map(|e| {
            let o = e % fo;
            match case.act {
                OutputActivation::Sigmoid => d_out[e] * sigmoid_grad_from_output(sigmoid(raw[e])),
                OutputActivation::Density if o == 0 => d_out[e] * trunc_exp_grad(raw[e]),
                _ => d_out[e],
            }
        })
        .collect();
    let cols = l.input_dim() - case.d_input_from;
    let run = |w: &[f32], x: &[f32], d: &[f32]| {
        let mut acts = MlpActivations::default();
        l.forward(w, x, n, &mut acts);
        let mut g = vec![0f32; l.num_params];
        let mut dx = vec![0f32; n * cols];
        l.backward_partial(
            w,
            x,
            n,
            &mut acts,
            d,
            &mut g,
            Some((case.d_input_from, &mut dx)),
        );
        (g, dx)
    };
    let (g, dx) = run(w, x, &d_raw);
    let (ga, dxa) = run(&abs(w), &abs(x), &abs(&d_raw));
    [g, dx, ga, dxa]
}

fn mlp_backward_matches_the_cpu_on_both_atomic_paths() {
    let dev = device();
    let mut rng = Rng::new(12);
    let kernels: Vec<MlpKernels> = modes(&dev)
        .into_iter()
        .map(|m| MlpKernels::new(&dev, m).unwrap())
        .collect();
    for case in cases() {
        let l = &case.layout;
        let n = 1000;
        let w = weights(l, &mut rng);
        let x = uniform(n * l.input_dim(), &mut rng);
        let d_out = uniform(n * l.output_dim(), &mut rng);
        let [g, dx, ga, dxa] = cpu_backward(&case, &w, &x, n, &d_out);
        let mlp = GpuMlp::new(l, 0, case.act).unwrap();
        for k in &kernels {
            let (gg, gdx) = k
                .backward_host(&dev, &mlp, &w, &x, &d_out, case.d_input_from)
                .unwrap();
            for (what, gpu, cpu, bound) in [("weight", &gg, &g, &ga), ("input", &gdx, &dx, &dxa)] {
                assert_eq!(gpu.len(), cpu.len());
                let mut worst = 0f32;
                for e in 0..cpu.len() {
                    let tol = 1e-5 * bound[e] + 1e-6;
                    let err = (gpu[e] - cpu[e]).abs();
                    assert!(
                        err <= tol,
                        "{} {:?}: {what} gradient {e}: gpu {} cpu {}",
                        case.name,
                        k.mode(),
                        gpu[e],
                        cpu[e]
                    );
                    worst = worst.max(err / tol);
                }
                println!(
                    "{} {:?} {:?}: {what} gradient worst error / tolerance {worst:.3}",
                    case.name,
                    l.dims,
                    k.mode()
                );
            }
        }
    }
}

fn mlp_backward_matches_finite_differences_of_the_cpu_reference() {
    let dev = device();
    let k = MlpKernels::new(&dev, AtomicMode::best(&dev)).unwrap();
    let mut rng = Rng::new(13);
    for case in cases() {
        let l = &case.layout;
        let (n, fi, fo) = (16, l.input_dim(), l.output_dim());
        let w = weights(l, &mut rng);
        let x = uniform(n * fi, &mut rng);
        let d_out = uniform(n * fo, &mut rng);
        // loss = sum d_out . activated outputs, in f64 over core's per-row reference.
        let loss = |w: &[f32], x: &[f32]| -> f64 {
            (0..n)
                .map(|s| {
                    let r = l.forward_reference(w, &x[s * fi..(s + 1) * fi]);
                    (0..fo)
                        .map(|o| d_out[s * fo + o] as f64 * activate(case.act, o, r[o]) as f64)
                        .sum::<f64>()
                })
                .sum()
        };
        let mlp = GpuMlp::new(l, 0, case.act).unwrap();
        let (gw, gx) = k
            .backward_host(&dev, &mlp, &w, &x, &d_out, case.d_input_from)
            .unwrap();
        let h = 2e-3f32;
        let (mut checked, mut kinks, mut worst) = (0, 0, 0f64);
        let mut check = |analytic: f32, at: &dyn Fn(f32) -> f64, what: String| {
            // Where the loss is smooth, central differences at h and h / 2 agree to O(h^2) and
            // second differences scale with the step (c_wide = 2 c_half + O(h^3)). A ReLU kink
            // at distance d < h breaks one of the two (the first by ~ slope change x d / 2h,
            // the second by ~ slope change x |1 - 3 d / h|).
            let f = [at(-h), at(-h / 2.0), at(0.0), at(h / 2.0), at(h)];
            let hh = h as f64;
            let wide = (f[4] - f[0]) / (2.0 * hh);
            let fd = (f[3] - f[1]) / hh;
            let c_half = (f[3] - 2.0 * f[2] + f[1]) / (hh / 2.0);
            let c_wide = (f[4] - 2.0 * f[2] + f[0]) / hh;
            let tol = 2e-3 * fd.abs().max(1.0);
            if (wide - fd).abs() > tol || (c_wide - 2.0 * c_half).abs() > tol {
                kinks += 1;
                return;
            }
            let err = (analytic as f64 - fd).abs();
            assert!(err <= tol, "{}: {what}: gpu {analytic} fd {fd}", case.name);
            worst = worst.max(err);
            checked += 1;
        };
        for _ in 0..40 {
            let e = rng.below(w.len() as u64) as usize;
            let at = |d: f32| {
                let mut ww = w.clone();
                ww[e] += d;
                loss(&ww, &x)
            };
            check(gw[e], &at, format!("weight {e}"));
        }
        let cols = fi - case.d_input_from;
        for _ in 0..20 {
            let (s, c) = (
                rng.below(n as u64) as usize,
                rng.below(cols as u64) as usize,
            );
            let e = s * fi + case.d_input_from + c;
            let at = |d: f32| {
                let mut xx = x.clone();
                xx[e] += d;
                loss(&w, &xx)
            };
            check(gx[s * cols + c], &at, format!("input {s},{c}"));
        }
        assert!(
            kinks * 4 <= checked + kinks,
            "{}: {kinks} of {} entries straddle a ReLU kink",
            case.name,
            checked + kinks
        );
        println!(
            "{}: finite differences: {checked} entries, worst |gpu - fd| {worst:.2e} ({kinks} skipped at kinks)",
            case.name
        );
    }
}

fn mlp_bad_input_is_an_error() {
    let dev = device();
    let k = MlpKernels::new(&dev, AtomicMode::CompareExchange).unwrap();
    let l = MlpLayout::new(&[4, 8, 2]);
    let mlp = GpuMlp::new(&l, 0, OutputActivation::Identity).unwrap();
    let w = vec![0.1f32; l.num_params];
    // Inputs not a whole number of rows, wrong weight count, wrong d_output count.
    for e in [
        k.forward_host(&dev, &mlp, &w, &[0.0; 6]).unwrap_err(),
        k.forward_host(&dev, &mlp, &w[1..], &[0.0; 8]).unwrap_err(),
        k.backward_host(&dev, &mlp, &w, &[0.0; 8], &[0.0; 3], 0)
            .unwrap_err(),
        k.backward_host(&dev, &mlp, &w, &[0.0; 8], &[0.0; 4], 4)
            .unwrap_err(),
    ] {
        assert!(matches!(e, GpuError::Input(_)), "{e}");
    }
    // Buffers too small for the sample count.
    let small = dev.zeros_f32("small", 4).unwrap();
    let wb = dev.buffer_f32("w", &w).unwrap();
    let e = k
        .forward(&dev, &mlp, &wb, &small, 2, &small, None)
        .unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
    // Wider than the kernels hold: the limit is named.
    let e = GpuMlp::new(&MlpLayout::new(&[4, 65, 2]), 0, OutputActivation::Identity).unwrap_err();
    assert!(e.to_string().contains("width"), "{e}");
}

fn sh_matches_the_cpu() {
    let dev = device();
    let k = ShKernel::new(&dev).unwrap();
    let mut rng = Rng::new(14);
    let mut dirs: Vec<[f32; 3]> = (0..2000)
        .map(|_| {
            let v = [
                rng.range_f32(-1.0, 1.0),
                rng.range_f32(-1.0, 1.0),
                rng.range_f32(-1.0, 1.0),
            ];
            let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-6);
            [v[0] / len, v[1] / len, v[2] / len]
        })
        .collect();
    dirs.extend([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]);
    let gpu = k.encode_host(&dev, &dirs).unwrap();
    let mut cpu = [0f32; SH_COEFFS];
    let (mut worst, mut exact) = (0f32, 0);
    for (i, d) in dirs.iter().enumerate() {
        sh4(*d, &mut cpu);
        for c in 0..SH_COEFFS {
            let err = (gpu[i * SH_COEFFS + c] - cpu[c]).abs();
            assert!(
                err <= 1e-6,
                "direction {d:?} coefficient {c}: gpu {} cpu {}",
                gpu[i * SH_COEFFS + c],
                cpu[c]
            );
            worst = worst.max(err);
            exact += (err == 0.0) as usize;
        }
    }
    println!(
        "sh: worst |gpu - cpu| {worst:.2e}, {exact} of {} values bit-identical",
        dirs.len() * SH_COEFFS
    );
    // Into the colour MLP's input rows (31 wide, SH first): the other columns stay.
    let n = dirs.len();
    let d = dev.buffer_f32("dirs", bytemuck::cast_slice(&dirs)).unwrap();
    let rows = dev.buffer_f32("rows", &vec![7.0; n * 31]).unwrap();
    k.encode(&dev, &d, n, &rows, 31, 0).unwrap();
    let back = dev.read_f32(&rows, n * 31).unwrap();
    for i in 0..n {
        assert_eq!(
            &back[i * 31..i * 31 + SH_COEFFS],
            &gpu[i * SH_COEFFS..(i + 1) * SH_COEFFS]
        );
        assert!(back[i * 31 + SH_COEFFS..(i + 1) * 31]
            .iter()
            .all(|&v| v == 7.0));
    }
    let e = k.encode(&dev, &d, n, &rows, 31, 16).unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
}
