//! Stability at the extremes (issue #8, part 2): the field math at densities from 0 to 1e8 (and
//! the `trunc_exp` ceiling), steps from 1e-8 to 1e3, rays that graze or miss the box, `t` exactly
//! 0 and 1 (and outside), tables from 2^10 to 2^24 rows, 1 to 32 levels, finest resolutions up to
//! 2^16 per axis, coordinates outside the unit cube.
//!
//! Every test asserts finite values and gradients *and* a sensible result (partition of unity,
//! the analytic alpha, the background for a miss, u64 reference index arithmetic, ...). Property
//! tests keep their case counts modest so the suite stays fast; `docs/stability.md` lists what is
//! covered and the bugs the suite found.

use glam::Vec3;
use msth_testkit::proptest_config;
use proptest::prelude::*;

use msth_core::activation::{sigmoid, softplus, softplus_grad, trunc_exp, trunc_exp_grad};
use msth_core::config::{Background, BlendMode, ModelConfig, Preset};
use msth_core::field::ModelLayout;
use msth_core::grid::{clamp_unit, GridConfig, GridLayout, PRIMES};
use msth_core::losses::{distortion, interlevel, mask_loss};
use msth_core::pipeline::{
    render_chunk, train_chunk, RenderOutput, StepSettings, TimedRay, Workspace,
};
use msth_core::render::{composite, weights, weights_backward};
use msth_core::rng::Rng;
use msth_core::sampling::{sample_pdf, Spacing};
use msth_core::{Ray, SceneBounds};

/// A value spread evenly in log space over `[lo, hi]`.
fn log_uniform(lo: f64, hi: f64) -> impl Strategy<Value = f32> {
    (lo.ln()..=hi.ln()).prop_map(|l| l.exp() as f32)
}

/// Densities from 0 to 1e8, with the ends themselves drawn often.
fn density() -> impl Strategy<Value = f32> {
    prop_oneof![
        1 => Just(0.0f32),
        1 => Just(1e8f32),
        1 => Just(1e-8f32),
        6 => log_uniform(1e-8, 1e8),
    ]
}

/// Step sizes from 1e-8 to 1e3, with the ends drawn often.
fn step() -> impl Strategy<Value = f32> {
    prop_oneof![
        1 => Just(1e-8f32),
        1 => Just(1e3f32),
        6 => log_uniform(1e-8, 1e3),
    ]
}

// ---------------------------------------------------------------------------------------------
// Volume rendering
// ---------------------------------------------------------------------------------------------

mod render {
    use super::*;

    /// Plain f64 reference of the weights: `(w, T_N)`.
    pub fn weights_f64(tau: &[f64]) -> (Vec<f64>, f64) {
        let mut sum = 0f64;
        let mut w = Vec::with_capacity(tau.len());
        for &t in tau {
            w.push((-sum).exp() * -(-t).exp_m1());
            sum += t;
        }
        (w, (-sum).exp())
    }

    /// `L = sum g_i w_i + g_T T_N` in f64 as a function of the optical depths.
    fn loss_f64(tau: &[f64], g: &[f32], g_t: f32) -> f64 {
        let (w, t) = weights_f64(tau);
        w.iter().zip(g).map(|(a, b)| a * *b as f64).sum::<f64>() + t * g_t as f64
    }

    /// `dL/dsigma_k = dL/dtau_k * delta_k`, with `dL/dtau_k` by central differences of the f64
    /// reference (an independent check of `weights_backward`'s closed form).
    fn d_sigma_fd(sig: &[f32], del: &[f32], g: &[f32], g_t: f32) -> Vec<f64> {
        let tau: Vec<f64> = sig
            .iter()
            .zip(del)
            .map(|(s, d)| *s as f64 * *d as f64)
            .collect();
        (0..tau.len())
            .map(|k| {
                let h = 1e-6 * tau[k].max(1.0);
                let mut p = tau.clone();
                p[k] = tau[k] + h;
                let lp = loss_f64(&p, g, g_t);
                p[k] = (tau[k] - h).max(0.0);
                let lm = loss_f64(&p, g, g_t);
                (lp - lm) / (tau[k] + h - p[k]) * del[k] as f64
            })
            .collect()
    }

    fn ray_samples() -> impl Strategy<Value = (Vec<f32>, Vec<f32>, Vec<f32>, f32)> {
        (1usize..48).prop_flat_map(|n| {
            (
                prop::collection::vec(density(), n),
                prop::collection::vec(step(), n),
                prop::collection::vec(-1.0f32..1.0, n),
                -1.0f32..1.0,
            )
        })
    }

    proptest! {
        #![proptest_config(proptest_config(256))]

        /// Any densities in [0, 1e8] and steps in [1e-8, 1e3]: weights in [0, 1] summing with the
        /// final transmittance to 1, matching an f64 reference, and a finite backward pass that
        /// matches finite differences of that reference.
        #[test]
        fn weights_are_a_partition_of_unity_and_backward_matches_fd(
            (sig, del, g, g_t) in ray_samples()
        ) {
            let n = sig.len();
            let mut w = vec![0f32; n];
            let t = weights(&sig, &del, &mut w);
            prop_assert!(t.is_finite() && (0.0..=1.0).contains(&t), "T_N {t}");
            prop_assert!(w.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)), "{w:?}");
            let sum: f32 = w.iter().sum::<f32>() + t;
            prop_assert!((sum - 1.0).abs() <= 1e-6 * n as f32 + 1e-6, "sum {sum}");
            let tau: Vec<f64> = sig.iter().zip(&del).map(|(s, d)| *s as f64 * *d as f64).collect();
            let (w_ref, t_ref) = weights_f64(&tau);
            for k in 0..n {
                prop_assert!(
                    (w[k] as f64 - w_ref[k]).abs() < 1e-5,
                    "w[{k}] {} vs {}", w[k], w_ref[k]
                );
            }
            prop_assert!((t as f64 - t_ref).abs() < 1e-5);

            let mut d_sigma = vec![0f32; n];
            weights_backward(&sig, &del, &w, t, &g, g_t, &mut d_sigma);
            let fd = d_sigma_fd(&sig, &del, &g, g_t);
            for k in 0..n {
                prop_assert!(d_sigma[k].is_finite());
                // |dL/dtau| <= 3; its f32 rounding is ~1e-6, scaled by the step.
                let tol = 2e-5 * del[k] as f64 + 1e-9;
                prop_assert!(
                    (d_sigma[k] as f64 - fd[k]).abs() <= tol,
                    "d_sigma[{k}] {} vs fd {} (sigma {}, delta {})",
                    d_sigma[k], fd[k], sig[k], del[k]
                );
            }
        }

        /// A single sample's alpha is `1 - exp(-sigma delta)` to f32 precision, from `tau = 1e-16`
        /// (`sigma = delta = 1e-8`) to `tau = 1e11` (alpha = 1 exactly).
        #[test]
        fn alpha_matches_the_analytic_value(s in density(), d in step()) {
            let mut w = [0f32];
            let t = weights(&[s], &[d], &mut w);
            let alpha = -(-(s as f64 * d as f64)).exp_m1();
            prop_assert!(
                (w[0] as f64 - alpha).abs() <= 1e-6 * alpha + 1e-30,
                "{} vs {alpha}", w[0]
            );
            prop_assert!((t as f64 - (1.0 - alpha)).abs() <= 1e-6);
            if s as f64 * d as f64 > 104.0 {
                prop_assert_eq!(w[0], 1.0);
                prop_assert_eq!(t, 0.0);
            }
        }

        /// Huge density with a tiny step: `sigma` in [1, 1e8] and `delta = tau / sigma` give the
        /// alpha of `tau`, whatever the split between the two.
        #[test]
        fn huge_density_tiny_step_gives_the_analytic_alpha(
            sigma in log_uniform(1.0, 1e8),
            tau in log_uniform(1e-6, 60.0),
        ) {
            let delta = tau / sigma;
            let mut w = [0f32];
            weights(&[sigma], &[delta], &mut w);
            let alpha = -(-(sigma as f64 * delta as f64)).exp_m1();
            prop_assert!((w[0] as f64 - alpha).abs() <= 1e-6 * alpha, "{} vs {alpha}", w[0]);
        }

        /// A wall (alpha = 1 exactly) takes all the remaining transmittance: the weights sum to 1,
        /// nothing behind it gets weight or gradient, the transmittance after it is 0, and the
        /// samples in front still get the exact gradient.
        #[test]
        fn alpha_one_exactly_stops_the_ray(
            front in prop::collection::vec((0.0f32..4.0, 0.01f32..0.5), 0..12),
            wall_delta in log_uniform(1e-5, 1e3),
            behind in prop::collection::vec((density(), step()), 0..12),
            g_t in -1.0f32..1.0,
        ) {
            let mut sig: Vec<f32> = front.iter().map(|p| p.0).collect();
            let mut del: Vec<f32> = front.iter().map(|p| p.1).collect();
            let k = sig.len();
            sig.push(1e8);
            del.push(wall_delta);
            sig.extend(behind.iter().map(|p| p.0));
            del.extend(behind.iter().map(|p| p.1));
            let n = sig.len();
            let mut w = vec![0f32; n];
            let t = weights(&sig, &del, &mut w);
            prop_assert_eq!(t, 0.0);
            let front_sum: f32 = w[..k].iter().sum();
            prop_assert!((front_sum + w[k] - 1.0).abs() < 1e-5);
            prop_assert!(w[k + 1..].iter().all(|&v| v == 0.0), "{w:?}");
            let g: Vec<f32> = (0..n).map(|i| ((i * 7 % 5) as f32 - 2.0) * 0.3).collect();
            let mut d_sigma = vec![0f32; n];
            weights_backward(&sig, &del, &w, t, &g, g_t, &mut d_sigma);
            prop_assert!(d_sigma[k..].iter().all(|&v| v == 0.0), "{:?}", &d_sigma[k..]);
            let fd = d_sigma_fd(&sig, &del, &g, g_t);
            for i in 0..k {
                prop_assert!(
                    (d_sigma[i] as f64 - fd[i]).abs() < 1e-5,
                    "{i}: {} vs {}", d_sigma[i], fd[i]
                );
            }
        }
    }

    /// Finite differences through `weights` + `composite` in f32 at near-saturated alphas
    /// (tau 9 to 16.5: alpha within 1e-4..7e-8 of 1), where the gradient is tiny but must keep its
    /// sign and size.
    #[test]
    fn backward_matches_fd_near_saturated_alpha() {
        let sig = [0.2f32, 18.0, 1.0, 28.0, 33.0, 3.0];
        let del = [0.5f32, 0.5, 0.5, 0.5, 0.5, 0.5];
        let rgb = [
            0.9, 0.1, 0.2, 0.3, 0.8, 0.1, 0.5, 0.5, 0.5, 0.1, 0.2, 0.9, 0.7, 0.7, 0.1, 0.0, 1.0,
            0.0,
        ];
        let bg = [1.0f32, 1.0, 1.0];
        let gc = [0.4f32, -0.9, 0.3];
        let loss = |s: &[f64]| -> f64 {
            let tau: Vec<f64> = s.iter().zip(&del).map(|(a, b)| a * *b as f64).collect();
            let (w, t) = weights_f64(&tau);
            (0..3)
                .map(|ch| {
                    let c: f64 = (0..6).map(|i| w[i] * rgb[i * 3 + ch] as f64).sum::<f64>()
                        + t * bg[ch] as f64;
                    c * gc[ch] as f64
                })
                .sum()
        };
        let mut w = [0f32; 6];
        let t = weights(&sig, &del, &mut w);
        let c = composite(&w, &rgb, t, bg);
        assert!(c.iter().all(|v| v.is_finite()));
        let d_w: Vec<f32> = (0..6)
            .map(|i| (0..3).map(|ch| gc[ch] * rgb[i * 3 + ch]).sum())
            .collect();
        let d_t: f32 = (0..3).map(|ch| gc[ch] * bg[ch]).sum();
        let mut d_sigma = [0f32; 6];
        weights_backward(&sig, &del, &w, t, &d_w, d_t, &mut d_sigma);
        let s64: Vec<f64> = sig.iter().map(|&v| v as f64).collect();
        for k in 0..6 {
            let h = 1e-4 * s64[k].max(1.0);
            let mut p = s64.clone();
            p[k] += h;
            let lp = loss(&p);
            p[k] -= 2.0 * h;
            let lm = loss(&p);
            let fd = (lp - lm) / (2.0 * h);
            let err = (fd - d_sigma[k] as f64).abs();
            assert!(
                err <= 1e-3 * fd.abs() + 1e-9,
                "sample {k}: backward {} vs fd {fd}",
                d_sigma[k]
            );
        }
        // Behind the second (alpha = 1 - e^-9) sample the gradients are at most e^-9 in size.
        assert!(d_sigma[2..].iter().all(|g| g.abs() < 2e-4), "{d_sigma:?}");
    }

    /// Densities that are not numbers at all (NaN, infinities, negatives) count as empty or as a
    /// wall, never as NaN.
    #[test]
    fn non_finite_densities_are_empty_or_walls() {
        let mut w = [0f32; 4];
        let t = weights(&[f32::NAN, -1.0, f32::INFINITY, 1.0], &[1.0; 4], &mut w);
        assert_eq!(w, [0.0, 0.0, 1.0, 0.0]);
        assert_eq!(t, 0.0);
        let mut d = [0f32; 4];
        weights_backward(
            &[f32::NAN, -1.0, f32::INFINITY, 1.0],
            &[1.0; 4],
            &w,
            t,
            &[1.0, -1.0, 0.5, 0.2],
            1.0,
            &mut d,
        );
        assert!(d.iter().all(|v| v.is_finite()), "{d:?}");
    }
}

// ---------------------------------------------------------------------------------------------
// Sampling, activations, losses
// ---------------------------------------------------------------------------------------------

mod sampling_and_losses {
    use super::*;

    fn any_weight() -> impl Strategy<Value = f32> {
        prop_oneof![
            Just(0.0f32),
            Just(1.0f32),
            Just(f32::MIN_POSITIVE),
            Just(1e-45f32),
            Just(f32::NAN),
            Just(f32::INFINITY),
            Just(-1.0f32),
            Just(1e30f32),
            log_uniform(1e-30, 1.0),
        ]
    }

    proptest! {
        #![proptest_config(proptest_config(256))]

        /// Inverse-CDF resampling from any weights (zero, subnormal, huge, NaN, infinite) gives
        /// sorted, finite positions inside `[0, 1]`.
        #[test]
        fn pdf_sampling_is_sorted_and_bounded_for_any_weights(
            w in prop::collection::vec(any_weight(), 1..40),
            padding in prop_oneof![Just(0.0f32), Just(0.01f32), Just(1e-30f32)],
            m in 1usize..40,
            seed in any::<u64>(),
            jitter in any::<bool>(),
        ) {
            let nb = w.len();
            let edges: Vec<f32> = (0..=nb).map(|k| k as f32 / nb as f32).collect();
            let mut out = vec![0f32; m];
            let mut rng = Rng::new(seed);
            sample_pdf(&edges, &w, padding, jitter.then_some(&mut rng), &mut out);
            prop_assert!(out.iter().all(|s| s.is_finite() && (0.0..=1.0).contains(s)), "{out:?}");
            prop_assert!(out.windows(2).all(|p| p[0] <= p[1]), "{out:?}");
        }

        /// The disparity spacing stays finite and monotone from a near plane of 1e-6 to a far
        /// plane of 1e8 units.
        #[test]
        fn lindisp_spacing_is_finite_and_monotone(
            near in log_uniform(1e-6, 1.0),
            far_factor in log_uniform(1.0001, 1e8),
            unit in log_uniform(1e-3, 1e3),
        ) {
            let far = near * far_factor;
            let mut prev = f32::NEG_INFINITY;
            for k in 0..=64 {
                let t = Spacing::LinDisp.t_of_s(k as f32 / 64.0, near * unit, far * unit, unit);
                prop_assert!(t.is_finite() && t >= prev, "{k}: {t} after {prev}");
                prev = t;
            }
        }

        /// Activations and their derivatives are finite for every finite input, and the density
        /// activation never exceeds `f32::MAX`.
        #[test]
        fn activations_are_finite_for_any_finite_input(
            x in prop::num::f32::NORMAL | prop::num::f32::ZERO | prop::num::f32::SUBNORMAL
        ) {
            prop_assert!(sigmoid(x).is_finite() && (0.0..=1.0).contains(&sigmoid(x)));
            prop_assert!(trunc_exp(x).is_finite() && trunc_exp(x) >= 0.0);
            prop_assert!(trunc_exp_grad(x).is_finite() && trunc_exp_grad(x) > 0.0);
            prop_assert!(softplus(x).is_finite() && softplus(x) >= 0.0);
            prop_assert!(softplus_grad(x).is_finite());
        }

        /// Distortion and interlevel losses with weights at the extremes (all on one interval as
        /// behind an alpha = 1 wall, all zero for a miss, tiny intervals of 1e-8) stay finite, and
        /// give zero loss and gradient for a ray without weight.
        #[test]
        fn losses_are_finite_at_extreme_weights(
            n in 1usize..24,
            np in 1usize..24,
            hot in any::<prop::sample::Index>(),
            tiny in any::<bool>(),
            scale in prop_oneof![Just(1.0f32), Just(1e-8f32), Just(1e3f32)],
        ) {
            let width = if tiny { 1e-8f32 } else { 1.0 };
            let s: Vec<f32> = (0..=n).map(|k| k as f32 / n as f32 * width).collect();
            let sp: Vec<f32> = (0..=np).map(|k| k as f32 / np as f32 * width).collect();
            for one_hot in [true, false] {
                let mut w = vec![0f32; n];
                if one_hot {
                    w[hot.index(n)] = 1.0;
                }
                let wp: Vec<f32> = (0..np).map(|k| if k == 0 { 1.0 } else { 0.0 }).collect();
                let mut dw = vec![0f32; n];
                let l = distortion(&s, &w, scale, &mut dw);
                prop_assert!(l.is_finite() && l >= 0.0 && dw.iter().all(|v| v.is_finite()));
                let mut dwp = vec![0f32; np];
                let li = interlevel(&s, &w, &sp, &wp, scale, &mut dwp);
                prop_assert!(li.is_finite() && li >= 0.0 && dwp.iter().all(|v| v.is_finite()));
                if !one_hot {
                    prop_assert_eq!(l, 0.0);
                    prop_assert_eq!(li, 0.0);
                    prop_assert!(dw.iter().all(|&v| v == 0.0));
                    prop_assert!(dwp.iter().all(|&v| v == 0.0));
                }
            }
        }
    }

    /// The mask loss with saturated logits: finite, in [0, 1], gradient finite.
    #[test]
    fn mask_loss_is_finite_at_saturated_logits() {
        let logits = [-1e30f32, -1e4, -100.0, 0.0, 100.0, 1e4, 1e30, f32::MAX];
        let mut g = [0f32; 8];
        let l = mask_loss(&logits, 1.0, &mut g);
        assert!(l.is_finite() && (0.0..=1.0).contains(&l));
        assert!(g.iter().all(|v| v.is_finite() && *v <= 0.0), "{g:?}");
    }
}

// ---------------------------------------------------------------------------------------------
// Scene mapping and the hash grids
// ---------------------------------------------------------------------------------------------

mod grids {
    use super::*;

    /// Any float, including NaN, infinities and subnormals.
    fn any_f32() -> impl Strategy<Value = f32> {
        prop::num::f32::ANY
    }

    /// The level geometry recomputed independently from method.md's formulas, in f64/u128.
    fn expected_geometry(cfg: &GridConfig, l: usize) -> (Vec<u32>, bool, usize) {
        let d = cfg.dims();
        let t = 1u128 << cfg.log2_table_size;
        let mut res = Vec::new();
        let mut dense_size = 1u128;
        for a in 0..d {
            let (b, f) = (
                cfg.base_resolution[a] as f64,
                cfg.finest_resolution[a] as f64,
            );
            let growth = if cfg.levels > 1 {
                ((f.ln() - b.ln()) / (cfg.levels as f64 - 1.0)).exp()
            } else {
                1.0
            };
            let scale = ((b * growth.powi(l as i32) - 1.0).max(0.0)) as f32;
            let r = (scale as f64).ceil() as u32 + 1;
            res.push(r);
            dense_size *= r as u128 + 1;
        }
        let dense = dense_size <= t;
        let rows = if dense {
            (dense_size as usize).div_ceil(8) * 8
        } else {
            t as usize
        };
        (res, dense, rows)
    }

    /// Rows a point reads on one level, computed with u64 arithmetic: dense levels as
    /// `sum c_a prod_{b<a} (res_b + 1)`, hashed levels as `XOR (c_a * prime_a mod 2^32) mod T`.
    /// Corner positions use the same f32 `x * scale + 0.5` as the grid (that is the definition).
    fn rows_u64(g: &GridLayout, l: usize, x: &[f32]) -> Vec<(u64, f32)> {
        let level = &g.levels[l];
        let d = g.dims;
        let mut out = Vec::new();
        for corner in 0..(1usize << d) {
            let mut idx = 0u64;
            let mut stride = 1u64;
            let mut h = 0u64;
            let mut w = 1f32;
            for a in 0..d {
                let p = clamp_unit(x[a]) * level.scale[a] + 0.5;
                let i = p.floor();
                let fr = p - i;
                let c = i as u64 + (corner >> a & 1) as u64;
                w *= if corner >> a & 1 == 1 { fr } else { 1.0 - fr };
                assert!(
                    c <= level.res[a] as u64,
                    "corner {c} beyond res {}",
                    level.res[a]
                );
                if level.dense {
                    // prod(res + 1) <= 2^24 here; on hashed levels it can exceed u64.
                    idx += c * stride;
                    stride *= level.res[a] as u64 + 1;
                }
                h ^= (c * PRIMES[a] as u64) & 0xffff_ffff;
            }
            let row = if level.dense {
                idx
            } else {
                h & (g.table_size as u64 - 1)
            };
            out.push((row, w));
        }
        out
    }

    /// Plain u64 reference encoding of one point.
    fn encode_u64(g: &GridLayout, table: &[f32], x: &[f32]) -> Vec<f32> {
        let mut out = vec![0f32; g.output_dim()];
        for (l, level) in g.levels.iter().enumerate() {
            for (row, w) in rows_u64(g, l, x) {
                assert!(
                    row < level.rows as u64,
                    "level {l}: row {row} of {}",
                    level.rows
                );
                for f in 0..g.features {
                    out[l * g.features + f] +=
                        w * table[level.offset + row as usize * g.features + f];
                }
            }
        }
        out
    }

    fn unit_point(d: usize) -> impl Strategy<Value = Vec<f32>> {
        prop::collection::vec(
            prop_oneof![
                1 => Just(0.0f32),
                1 => Just(1.0f32),
                1 => Just(1.0f32 - f32::EPSILON),
                1 => Just(1e-30f32),
                6 => 0.0f32..=1.0,
            ],
            d,
        )
    }

    fn random_table(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = Rng::new(seed);
        (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect()
    }

    /// Fast batched encoding and backward against the per-point reference for `pts`.
    fn check_fast_against_reference(g: &GridLayout, table: &[f32], pts: &[Vec<f32>]) {
        let d = g.dims;
        let e = g.output_dim();
        let flat: Vec<f32> = pts.iter().flat_map(|p| p.iter().copied()).collect();
        let mut out = vec![0f32; pts.len() * e];
        g.encode(table, &flat, d, &mut out, e, 0);
        let mut rng = Rng::new(99);
        let d_out: Vec<f32> = (0..out.len()).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let mut grad_fast = vec![0f32; g.num_params];
        g.backward(&flat, d, &d_out, e, 0, &mut grad_fast);
        let mut grad_ref = vec![0f32; g.num_params];
        for (i, p) in pts.iter().enumerate() {
            let r = g.encode_point_reference(table, p);
            let u = encode_u64(g, table, p);
            for k in 0..e {
                assert!(out[i * e + k].is_finite());
                assert!((out[i * e + k] - r[k]).abs() < 1e-5, "fast vs reference");
                assert!((u[k] - r[k]).abs() < 1e-5, "u64 vs reference at {p:?}");
            }
            g.backward_point_reference(p, &d_out[i * e..(i + 1) * e], &mut grad_ref);
        }
        let mut touched = 0;
        for (a, b) in grad_fast.iter().zip(&grad_ref) {
            assert!((a - b).abs() < 1e-4, "backward fast {a} vs reference {b}");
            touched += (*b != 0.0) as usize;
        }
        assert!(touched > 0);
    }

    proptest! {
        #![proptest_config(proptest_config(64))]

        /// Finest resolutions up to 2^16 per axis on 3D and 4D grids with 2^10..2^22 rows and up
        /// to 32 levels: the layout matches the formulas (dense exactly when `prod(res + 1) <= T`),
        /// every corner lies in `0..=res`, and the rows match u64 reference arithmetic.
        #[test]
        fn index_math_matches_u64_reference_up_to_2_16(
            d in 3usize..=4,
            levels in prop_oneof![Just(1usize), Just(32usize), 2usize..16],
            log2 in 10u32..=22,
            base in log_uniform(1.0, 64.0),
            finest_log2 in 6.0f64..=16.0,
            pts in prop::collection::vec(unit_point(4), 16),
        ) {
            let finest = (finest_log2.exp2() as f32).max(base);
            let cfg = GridConfig {
                levels,
                features_per_level: 1,
                log2_table_size: log2,
                base_resolution: vec![base; d],
                finest_resolution: vec![finest; d],
            };
            cfg.validate("t").unwrap();
            let g = GridLayout::new(&cfg);
            for (l, level) in g.levels.iter().enumerate() {
                let (res, dense, rows) = expected_geometry(&cfg, l);
                prop_assert_eq!(&level.res[..d], &res[..]);
                prop_assert_eq!(level.dense, dense);
                prop_assert_eq!(level.rows, rows);
                prop_assert!(level.rows <= g.table_size);
            }
            for p in &pts {
                let x = &p[..d];
                let mut from_grid = Vec::new();
                g.visit_rows(x, |l, r| from_grid.push((l, r as u64)));
                let mut from_u64 = Vec::new();
                for l in 0..levels {
                    from_u64.extend(rows_u64(&g, l, x).into_iter().map(|(r, _)| (l, r)));
                }
                prop_assert_eq!(from_grid, from_u64);
            }
        }

        /// Coordinates outside the unit cube (any float, NaN and infinities included) encode as
        /// their clamp into `[0, 1]` (NaN as 0), as grid.rs documents, on both paths.
        #[test]
        fn coordinates_outside_the_cube_are_clamped(
            x in prop::collection::vec(any_f32(), 4),
        ) {
            let cfg = GridConfig {
                levels: 6,
                features_per_level: 2,
                log2_table_size: 12,
                base_resolution: vec![4.0; 4],
                finest_resolution: vec![300.0, 300.0, 300.0, 50.0],
            };
            let g = GridLayout::new(&cfg);
            let table = random_table(g.num_params, 5);
            let clamped: Vec<f32> = x.iter().map(|&v| clamp_unit(v)).collect();
            prop_assert!(clamped.iter().all(|v| (0.0..=1.0).contains(v)));
            for (a, c) in x.iter().zip(&clamped) {
                if a.is_nan() {
                    prop_assert_eq!(*c, 0.0);
                }
            }
            let r = g.encode_point_reference(&table, &x);
            prop_assert_eq!(&r, &g.encode_point_reference(&table, &clamped));
            let mut out = vec![0f32; g.output_dim()];
            g.encode(&table, &x, 4, &mut out, g.output_dim(), 0);
            prop_assert!(out.iter().all(|v| v.is_finite()));
            for k in 0..out.len() {
                prop_assert!((out[k] - r[k]).abs() < 1e-5);
            }
        }

        /// Scene mapping of any world point (huge, NaN, infinite) lands in the unit cube, for a box
        /// and for the contraction.
        #[test]
        fn scene_mapping_lands_in_the_unit_cube(
            p in prop::collection::vec(any_f32(), 3),
        ) {
            let p = Vec3::new(p[0], p[1], p[2]);
            for b in [
                SceneBounds::dnerf_default(),
                SceneBounds::Contracted { center: Vec3::new(0.5, -1.0, 2.0), radius: 3.0 },
            ] {
                let u = b.to_unit(p);
                prop_assert!(
                    u.is_finite() && u.cmpge(Vec3::ZERO).all() && u.cmple(Vec3::ONE).all(),
                    "{b:?}: {p} -> {u}"
                );
            }
        }
    }

    /// Finest resolution 2^16 per axis on a 4D grid with 32 levels and 2^16 rows: fast and
    /// reference paths agree with the u64 reference at the corners of the cube and inside.
    #[test]
    fn finest_2_16_with_32_levels_fast_matches_reference() {
        for d in [3usize, 4] {
            let cfg = GridConfig {
                levels: 32,
                features_per_level: 2,
                log2_table_size: 16,
                base_resolution: vec![2.0; d],
                finest_resolution: vec![65536.0; d],
            };
            cfg.validate("t").unwrap();
            let g = GridLayout::new(&cfg);
            assert!(g.levels[0].dense && !g.levels[31].dense);
            assert_eq!(g.levels[31].res[0], 65536);
            let table = random_table(g.num_params, 1);
            let mut rng = Rng::new(2);
            let mut pts: Vec<Vec<f32>> = (0..200)
                .map(|_| (0..d).map(|_| rng.f32()).collect())
                .collect();
            pts.push(vec![0.0; d]);
            pts.push(vec![1.0; d]);
            pts.push((0..d).map(|a| (a % 2) as f32).collect());
            pts.push(vec![1.0 - f32::EPSILON; d]);
            check_fast_against_reference(&g, &table, &pts);
        }
    }

    /// `t` exactly 0 and 1 land on the first and last time cells: on a dense 4D level the time
    /// corner is `row / stride_t`, 0 and 1 at `t = 0`, `round(scale_t)` and one more (at most
    /// `res_t`) at `t = 1`; times outside `[0, 1]` read exactly what the ends read; nothing is read
    /// out of bounds on any level, fast or reference, for 1 frame and 10,000 frames.
    #[test]
    fn t_zero_and_one_land_on_the_first_and_last_time_cells() {
        for frames in [1usize, 2, 300, 10_000] {
            let finest_t = (frames as f32).max(2.0);
            let cfg = GridConfig {
                levels: 8,
                features_per_level: 2,
                log2_table_size: 14,
                base_resolution: vec![2.0, 2.0, 2.0, finest_t.min(15.0)],
                finest_resolution: vec![8.0, 8.0, 8.0, finest_t],
            };
            cfg.validate("t").unwrap();
            let g = GridLayout::new(&cfg);
            let table = random_table(g.num_params, frames as u64);
            let x = [0.3f32, 0.6, 0.9];
            for (l, level) in g.levels.iter().enumerate() {
                if !level.dense {
                    continue;
                }
                let st = level.stride[3] as usize;
                for (t, expect) in [(0.0f32, 0u32), (1.0, (level.scale[3] + 0.5).floor() as u32)] {
                    let mut time_corners = Vec::new();
                    g.visit_rows(&[x[0], x[1], x[2], t], |ll, r| {
                        if ll == l {
                            time_corners.push((r / st) as u32);
                        }
                    });
                    time_corners.sort();
                    time_corners.dedup();
                    assert_eq!(
                        time_corners,
                        vec![expect, expect + 1],
                        "frames {frames} l {l} t {t}"
                    );
                    assert!(expect < level.res[3], "time corner beyond res_t");
                }
            }
            let at = |t: f32| g.encode_point_reference(&table, &[x[0], x[1], x[2], t]);
            assert_eq!(at(-0.5), at(0.0));
            assert_eq!(at(f32::NAN), at(0.0));
            assert_eq!(at(1.5), at(1.0));
            assert_eq!(at(f32::INFINITY), at(1.0));
            // Continuity into the ends.
            let (a, b) = (at(1.0), at(1.0 - 1e-6));
            assert!(a.iter().zip(&b).all(|(p, q)| (p - q).abs() < 1e-2));
            let pts: Vec<Vec<f32>> = [0.0f32, 1.0, 1.0 - f32::EPSILON, 0.5]
                .iter()
                .map(|&t| vec![x[0], x[1], x[2], t])
                .collect();
            check_fast_against_reference(&g, &table, &pts);
        }
    }

    /// Tables of 2^24 rows (the maximum): a level of exactly 2^24 dense rows (256^3 corners) and
    /// the next resolution up, hashed into 2^24 rows. One feature keeps each table at 64 MiB.
    #[test]
    fn tables_of_2_24_rows_work_dense_and_hashed() {
        for (res, dense) in [(255.0f32, true), (256.0, false)] {
            let cfg = GridConfig {
                levels: 1,
                features_per_level: 1,
                log2_table_size: 24,
                base_resolution: vec![res; 3],
                finest_resolution: vec![res; 3],
            };
            cfg.validate("t").unwrap();
            let g = GridLayout::new(&cfg);
            assert_eq!(g.levels[0].dense, dense, "resolution {res}");
            assert_eq!(g.levels[0].rows, 1 << 24);
            // Row r holds r, exact in f32 up to 2^24.
            let table: Vec<f32> = (0..g.num_params).map(|r| r as f32).collect();
            let mut rng = Rng::new(7);
            let mut pts: Vec<Vec<f32>> = (0..2000)
                .map(|_| (0..3).map(|_| rng.f32()).collect())
                .collect();
            pts.push(vec![1.0; 3]);
            pts.push(vec![0.0; 3]);
            if dense {
                // x = 1: p = 254 + 0.5, corners 254 and 255 with weight 1/2 on every axis, rows
                // `k0 + 256 (k1 + 256 k2)`: the last row of the table is read.
                let last = g.encode_point_reference(&table, &[1.0; 3]);
                let expected: f64 = (0..8u32)
                    .map(|c| {
                        let k = |a: u32| 254 + (c >> a & 1) as u64;
                        (k(0) + 256 * (k(1) + 256 * k(2))) as f64
                    })
                    .sum::<f64>()
                    / 8.0;
                assert!((last[0] as f64 - expected).abs() / expected < 1e-6);
                let mut max_row = 0;
                g.visit_rows(&[1.0; 3], |_, r| max_row = max_row.max(r));
                assert_eq!(max_row, (1 << 24) - 1);
            }
            check_fast_against_reference(&g, &table, &pts);
        }
    }

    /// The largest configuration the validator accepts (32 levels, 2^24 rows, finest 2^20 on
    /// four axes) has a layout without overflow; its memory is not allocated.
    #[test]
    fn largest_valid_layout_does_not_overflow() {
        let cfg = GridConfig {
            levels: 32,
            features_per_level: 8,
            log2_table_size: 24,
            base_resolution: vec![1.0; 4],
            finest_resolution: vec![1_048_576.0; 4],
        };
        cfg.validate("t").unwrap();
        let g = GridLayout::new(&cfg);
        let mut expected = 0usize;
        for (l, level) in g.levels.iter().enumerate() {
            let (res, dense, rows) = expected_geometry(&cfg, l);
            assert_eq!(&level.res[..4], &res[..]);
            assert_eq!((level.dense, level.rows), (dense, rows));
            assert_eq!(level.offset, expected);
            expected += rows * 8;
        }
        assert_eq!(g.num_params, expected);
        for x in [[0.0f32; 4], [1.0; 4], [0.5; 4]] {
            g.visit_rows(&x, |l, r| assert!(r < g.levels[l].rows));
            for l in 0..32 {
                for (row, _) in rows_u64(&g, l, &x) {
                    assert!(row < g.levels[l].rows as u64);
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The pipeline: whole rays through both fields
// ---------------------------------------------------------------------------------------------

mod pipeline {
    use super::*;

    const HALF: f32 = 1.5;

    fn tiny_cfg(bg: [f32; 3], frames: usize) -> ModelConfig {
        tiny_cfg_in(SceneBounds::dnerf_default(), bg, frames)
    }

    fn tiny_cfg_in(bounds: SceneBounds, bg: [f32; 3], frames: usize) -> ModelConfig {
        let mut c =
            ModelConfig::preset(Preset::Fast, bounds, Background::Color { rgb: bg }, frames);
        for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
            enc.blend = BlendMode::Mt;
            enc.resize(3, 10, 32.0, 6);
            enc.grid3.base_resolution = vec![4.0; 3];
            enc.grid4.base_resolution[..3].copy_from_slice(&[4.0; 3]);
        }
        c.resize_mlps(8, 4);
        c.field.geo_features = 3;
        c.sampler.set_samples(16, 8);
        c.validate().unwrap();
        c
    }

    /// Parameters that make both fields a constant density `sigma` (through `trunc_exp`, so
    /// `log_sigma` of 88 or more is the activation's ceiling, about 1.65e38): 3D tables 1, 4D
    /// tables 0, density MLPs `out_0 = log_sigma`.
    fn constant_density(layout: &ModelLayout, log_sigma: f32, seed: u64) -> Vec<f32> {
        let mut p = layout.init_params(seed);
        for e in &layout.params.entries {
            let r = e.range();
            if e.name.ends_with(".h3") {
                p[r].fill(1.0);
            } else if e.name.ends_with(".h4") {
                p[r].fill(0.0);
            }
        }
        for (mlp, range) in [&layout.field.density, &layout.proposal.field.density] {
            let p = &mut p[range.clone()];
            p.fill(0.0);
            // Row-major `[dims[k], dims[k + 1]]` weights: entry (0, 0) of each layer.
            p[mlp.offsets[0]] = 1.0; // hidden_0 = enc_0 = 1
            p[mlp.offsets[1]] = log_sigma; // out_0 = hidden_0 * log_sigma
        }
        p
    }

    fn render(
        cfg: &ModelConfig,
        layout: &ModelLayout,
        p: &[f32],
        rays: &[TimedRay],
    ) -> RenderOutput {
        let mut out = RenderOutput::default();
        render_chunk(cfg, layout, p, rays, &mut Workspace::default(), &mut out);
        out
    }

    fn train(
        cfg: &ModelConfig,
        layout: &ModelLayout,
        p: &[f32],
        rays: &[TimedRay],
        targets: &[[f32; 3]],
    ) -> (f64, Vec<f32>) {
        let mut grad = vec![0f32; p.len()];
        let step = StepSettings {
            anneal: 0.5,
            interlevel_weight: 1.0,
            distortion_weight: 0.01,
            loss_scale: 1.0 / rays.len() as f32,
            sample_mask_weight: 0.0,
            free_space_weight: 0.0,
            active_levels: None,
            proposal_levels: None,
        };
        let l = train_chunk(
            cfg,
            layout,
            p,
            &mut grad,
            rays,
            targets,
            None,
            &step,
            &mut Rng::new(3),
            &mut Workspace::default(),
        );
        assert!(l.sq_err.is_finite() && l.interlevel.is_finite() && l.distortion.is_finite());
        (l.sq_err, grad)
    }

    /// A ray that certainly misses the box: outside on one axis and moving away from it (or
    /// parallel to it).
    fn missing_ray() -> impl Strategy<Value = TimedRay> {
        (
            0usize..3,
            any::<bool>(),
            log_uniform(1e-4, 1e3),
            prop::collection::vec(-5.0f32..5.0, 3),
            prop::collection::vec(-1.0f32..1.0, 3),
            prop_oneof![Just(0.0f32), 0.0f32..1.0],
            0.0f32..=1.0,
        )
            .prop_map(|(axis, positive, gap, o, d, away, time)| {
                let sign = if positive { 1.0 } else { -1.0 };
                let mut origin = Vec3::new(o[0], o[1], o[2]);
                origin[axis] = sign * (HALF + gap);
                let mut dir = Vec3::new(d[0], d[1], d[2]);
                dir[axis] = sign * away;
                let dir = dir.try_normalize().unwrap_or(Vec3::new(0.0, 0.0, 0.0));
                let dir = if dir == Vec3::ZERO {
                    let mut v = Vec3::ZERO;
                    v[axis] = sign;
                    v
                } else {
                    dir
                };
                TimedRay { origin, dir, time }
            })
    }

    /// A ray on a face, an edge or a corner of the box, parallel to the face or tilted by a hair.
    fn grazing_ray() -> impl Strategy<Value = TimedRay> {
        (
            prop::collection::vec(prop_oneof![Just(-HALF), Just(HALF), -HALF..HALF], 3),
            prop::collection::vec(
                prop_oneof![Just(0.0f32), Just(1e-7f32), Just(-1e-7f32), -1.0f32..1.0],
                3,
            ),
            0.0f32..=1.0,
        )
            .prop_map(|(o, d, time)| {
                let on_face = Vec3::new(o[0], o[1], o[2]);
                let dir = Vec3::new(d[0], d[1], d[2])
                    .try_normalize()
                    .unwrap_or(Vec3::X);
                // Start outside, 4 units back along the ray, so that it passes through the face
                // point (or starts on the surface when the step lands there).
                TimedRay {
                    origin: on_face - dir * 4.0,
                    dir,
                    time,
                }
            })
    }

    /// A ray through the box (towards a point inside it).
    fn hitting_ray() -> impl Strategy<Value = TimedRay> {
        (
            prop::collection::vec(-1.0f32..1.0, 3),
            prop::collection::vec(-1.0f32..1.0, 3),
            0.0f32..=1.0,
        )
            .prop_filter_map("degenerate", |(a, b, time)| {
                let target = Vec3::new(a[0], a[1], a[2]);
                let dir = Vec3::new(b[0], b[1], b[2]).try_normalize()?;
                Some(TimedRay {
                    origin: target - dir * 5.0,
                    dir,
                    time,
                })
            })
    }

    fn assert_render_sane(o: &RenderOutput, bg: [f32; 3]) {
        for i in 0..o.rgb.len() {
            assert!(o.rgb[i].iter().all(|v| v.is_finite()));
            for ch in 0..3 {
                let v = o.rgb[i][ch];
                assert!((-1e-5..=1.0 + 1e-5).contains(&v), "rgb {v} (bg {bg:?})");
            }
            assert!(o.opacity[i].is_finite() && (-1e-6..=1.0 + 1e-6).contains(&o.opacity[i]));
            assert!(o.depth[i].is_finite() && o.depth[i] >= 0.0);
            assert!(o.mask[i].is_finite() && o.min_mask[i].is_finite());
        }
    }

    proptest! {
        #![proptest_config(proptest_config(64))]

        /// Rays that miss the box render the background exactly, with zero opacity and depth, and
        /// a chunk of them contributes exactly zero gradient (only the background's error).
        #[test]
        fn rays_missing_the_box_give_background_and_zero_gradient(
            rays in prop::collection::vec(missing_ray(), 1..6),
            log_sigma in -20.0f32..100.0,
        ) {
            let bg = [0.2, 0.5, 0.9];
            let cfg = tiny_cfg(bg, 10);
            let layout = ModelLayout::new(&cfg);
            let p = constant_density(&layout, log_sigma, 1);
            let o = render(&cfg, &layout, &p, &rays);
            for i in 0..rays.len() {
                prop_assert_eq!(o.rgb[i], bg);
                prop_assert_eq!(o.opacity[i], 0.0);
                prop_assert_eq!(o.depth[i], 0.0);
            }
            let targets = vec![[1.0, 0.0, 0.5]; rays.len()];
            let (sq, grad) = train(&cfg, &layout, &p, &rays, &targets);
            let expect: f64 =
                (0..3).map(|c| ((bg[c] - targets[0][c]) as f64).powi(2)).sum::<f64>() / 3.0;
            prop_assert!((sq - expect * rays.len() as f64).abs() < 1e-5);
            prop_assert!(grad.iter().all(|&g| g == 0.0));
        }

        /// Rays along faces, edges and corners (exactly parallel or tilted by 1e-7): finite
        /// colours in range, opacity in [0, 1], finite losses and gradients.
        #[test]
        fn grazing_rays_stay_finite(
            rays in prop::collection::vec(grazing_ray(), 1..6),
            log_sigma in prop_oneof![Just(-100.0f32), Just(18.42f32), Just(100.0f32), -5.0f32..5.0],
        ) {
            let bg = [1.0, 1.0, 1.0];
            let cfg = tiny_cfg(bg, 10);
            let layout = ModelLayout::new(&cfg);
            let p = constant_density(&layout, log_sigma, 2);
            let o = render(&cfg, &layout, &p, &rays);
            assert_render_sane(&o, bg);
            let targets = vec![[0.3, 0.6, 0.1]; rays.len()];
            let (_, grad) = train(&cfg, &layout, &p, &rays, &targets);
            prop_assert!(grad.iter().all(|g| g.is_finite()));
        }

        /// A constant density from 0 to 1e8 (and the activation's ceiling) over the whole box:
        /// the rendered opacity is the analytic `1 - exp(-sigma L)` for the chord length `L`,
        /// the colour stays in range, and training gradients are finite.
        #[test]
        fn constant_density_gives_the_analytic_opacity(
            rays in prop::collection::vec(hitting_ray(), 1..6),
            sigma in density(),
        ) {
            let bg = [1.0, 1.0, 1.0];
            let cfg = tiny_cfg(bg, 10);
            let layout = ModelLayout::new(&cfg);
            let log_sigma = if sigma > 0.0 { sigma.ln() } else { -200.0 };
            let p = constant_density(&layout, log_sigma, 3);
            let o = render(&cfg, &layout, &p, &rays);
            assert_render_sane(&o, bg);
            for (i, r) in rays.iter().enumerate() {
                let ray = Ray { origin: r.origin, dir: r.dir };
                let iv = cfg.bounds.ray_interval(&ray, cfg.sampler.near, cfg.sampler.far);
                let chord = iv.map(|v| (v.far - v.near) as f64).unwrap_or(0.0);
                let s = trunc_exp(log_sigma) as f64;
                let expected = -(-(s * chord)).exp_m1();
                prop_assert!(
                    (o.opacity[i] as f64 - expected).abs() < 1e-4 + 1e-4 * expected,
                    "sigma {s} chord {chord}: opacity {} vs {expected}", o.opacity[i]
                );
            }
            let targets = vec![[0.0, 0.0, 0.0]; rays.len()];
            let (_, grad) = train(&cfg, &layout, &p, &rays, &targets);
            prop_assert!(grad.iter().all(|g| g.is_finite()));
        }
    }

    proptest! {
        #![proptest_config(proptest_config(64))]

        /// The same with an unbounded (contracted) scene, rays from anywhere up to 1e4 units away:
        /// the disparity spacing's steps grow to hundreds of units near the far plane (1000
        /// radii), and the opacity is still `1 - exp(-sigma (far - near))`.
        #[test]
        fn contracted_scene_constant_density_gives_the_analytic_opacity(
            origins in prop::collection::vec(
                (prop::collection::vec(-1.0f32..1.0, 3), log_uniform(1e-3, 1e4)),
                1..5,
            ),
            dirs in prop::collection::vec(prop::collection::vec(-1.0f32..1.0, 3), 5),
            sigma in density(),
        ) {
            let bounds = SceneBounds::Contracted { center: Vec3::new(0.2, -0.1, 0.0), radius: 1.5 };
            let bg = [0.0, 0.0, 0.0];
            let cfg = tiny_cfg_in(bounds, bg, 10);
            let layout = ModelLayout::new(&cfg);
            let log_sigma = if sigma > 0.0 { sigma.ln() } else { -200.0 };
            let p = constant_density(&layout, log_sigma, 7);
            let rays: Vec<TimedRay> = origins
                .iter()
                .zip(&dirs)
                .map(|((o, r), d)| TimedRay {
                    origin: Vec3::new(o[0], o[1], o[2]) * *r,
                    dir: Vec3::new(d[0], d[1], d[2]).try_normalize().unwrap_or(Vec3::Y),
                    time: 0.5,
                })
                .collect();
            let o = render(&cfg, &layout, &p, &rays);
            assert_render_sane(&o, bg);
            let chord = (cfg.sampler.far - cfg.sampler.near) as f64;
            let s = trunc_exp(log_sigma) as f64;
            let expected = -(-(s * chord)).exp_m1();
            for i in 0..rays.len() {
                prop_assert!(
                    (o.opacity[i] as f64 - expected).abs() < 1e-4 + 1e-3 * expected,
                    "sigma {s}: opacity {} vs {expected}", o.opacity[i]
                );
            }
            let (_, grad) = train(&cfg, &layout, &p, &rays, &vec![[0.5; 3]; rays.len()]);
            prop_assert!(grad.iter().all(|g| g.is_finite()));
        }
    }

    /// Finite differences of the training loss through the whole pipeline at near-saturated
    /// alpha: a constant main-field density whose optical depth over the box is 13 to 100 (the
    /// first samples take almost all the weight), differentiated with respect to the density
    /// MLP's output weight (`log sigma`) and a colour MLP weight. Sample positions come from the
    /// proposal field, which is left alone, so they are the same for every evaluation.
    #[test]
    fn pipeline_gradient_matches_fd_near_saturated_alpha() {
        let cfg = tiny_cfg([1.0, 1.0, 1.0], 10);
        let layout = ModelLayout::new(&cfg);
        let rays: Vec<TimedRay> = (0..6)
            .map(|i| TimedRay {
                origin: Vec3::new(0.1 * i as f32 - 0.3, 0.05 * i as f32, 4.0),
                dir: Vec3::new(0.02 * i as f32, -0.03, -1.0).normalize(),
                time: i as f32 / 5.0,
            })
            .collect();
        let targets: Vec<[f32; 3]> = (0..6).map(|i| [0.1 * i as f32, 0.7, 0.2]).collect();
        let step = StepSettings {
            anneal: 1.0,
            interlevel_weight: 1.0,
            distortion_weight: 0.01,
            loss_scale: 1.0 / rays.len() as f32,
            sample_mask_weight: 0.0,
            free_space_weight: 0.0,
            active_levels: None,
            proposal_levels: None,
        };
        let run = |p: &[f32], grad: &mut [f32]| {
            let l = train_chunk(
                &cfg,
                &layout,
                p,
                grad,
                &rays,
                &targets,
                None,
                &step,
                &mut Rng::new(11),
                &mut Workspace::default(),
            );
            (l.sq_err + step.distortion_weight as f64 * l.distortion) / rays.len() as f64
        };
        let (dm, dr) = &layout.field.density;
        let cr = &layout.field.color.1;
        for log_sigma in [1.5f32, 2.5, 3.5] {
            let mut p = constant_density(&layout, log_sigma, 8);
            // A colour that depends on the direction encoding, so the colour gradient is not 0.
            let mut rng = Rng::new(9);
            for v in &mut p[cr.clone()] {
                *v = rng.range_f32(-0.5, 0.5);
            }
            let mut grad = vec![0f32; p.len()];
            run(&p, &mut grad);
            assert!(grad.iter().all(|g| g.is_finite()));
            // The colour MLP weight with the largest gradient.
            let colour = cr
                .clone()
                .max_by(|&a, &b| grad[a].abs().total_cmp(&grad[b].abs()))
                .unwrap();
            assert!(grad[colour] != 0.0);
            for i in [dr.start + dm.offsets[1], colour] {
                let h = 1e-3f32;
                let mut q = p.clone();
                let mut scratch = vec![0f32; p.len()];
                q[i] = p[i] + h;
                let lp = run(&q, &mut scratch);
                q[i] = p[i] - h;
                let lm = run(&q, &mut scratch);
                let fd = (lp - lm) / (2.0 * h as f64);
                assert!(
                    (fd - grad[i] as f64).abs() <= 1e-6 + 2e-2 * fd.abs(),
                    "log sigma {log_sigma}, parameter {i}: backward {} vs fd {fd}",
                    grad[i]
                );
            }
        }
    }

    /// `t` exactly 0 and 1 render without trouble for 1 and 10,000 frames, and times outside
    /// `[0, 1]` (or NaN) render as the nearest end.
    #[test]
    fn times_at_and_beyond_the_ends_render_as_the_ends() {
        for frames in [1usize, 10_000] {
            let bg = [1.0, 1.0, 1.0];
            let cfg = tiny_cfg(bg, frames);
            let layout = ModelLayout::new(&cfg);
            let mut p = layout.init_params(4);
            let mut rng = Rng::new(5);
            for v in p.iter_mut() {
                *v += rng.range_f32(-0.5, 0.5);
            }
            let at = |time: f32| {
                let r = TimedRay {
                    origin: Vec3::new(0.1, 0.2, 4.0),
                    dir: Vec3::new(0.0, 0.05, -1.0).normalize(),
                    time,
                };
                let o = render(&cfg, &layout, &p, &[r]);
                assert_render_sane(&o, bg);
                let (_, g) = train(&cfg, &layout, &p, &[r], &[[0.5; 3]]);
                assert!(g.iter().all(|v| v.is_finite()));
                o.rgb[0]
            };
            assert_eq!(at(-1.0), at(0.0), "frames {frames}");
            assert_eq!(at(f32::NAN), at(0.0), "frames {frames}");
            assert_eq!(at(2.0), at(1.0), "frames {frames}");
            assert_eq!(at(f32::INFINITY), at(1.0), "frames {frames}");
        }
    }

    /// Rays with NaN or infinite origins or directions, or a zero direction, render the
    /// background and produce no gradient.
    #[test]
    fn broken_rays_render_background() {
        let bg = [0.1, 0.2, 0.3];
        let cfg = tiny_cfg(bg, 4);
        let layout = ModelLayout::new(&cfg);
        let p = constant_density(&layout, 3.0, 6);
        let rays: Vec<TimedRay> = [
            (Vec3::splat(f32::NAN), Vec3::Z),
            (Vec3::new(0.0, 0.0, 4.0), Vec3::new(f32::NAN, 0.0, -1.0)),
            (Vec3::new(f32::INFINITY, 0.0, 0.0), -Vec3::X),
            (Vec3::new(0.0, 0.0, 4.0), Vec3::ZERO),
            (
                Vec3::new(0.0, 0.0, 4.0),
                Vec3::new(0.0, 0.0, f32::NEG_INFINITY),
            ),
        ]
        .iter()
        .map(|&(origin, dir)| TimedRay {
            origin,
            dir,
            time: 0.5,
        })
        .collect();
        let o = render(&cfg, &layout, &p, &rays);
        for i in 0..rays.len() {
            assert_eq!(o.rgb[i], bg, "ray {i}");
            assert_eq!(o.opacity[i], 0.0);
        }
        let (_, grad) = train(&cfg, &layout, &p, &rays, &vec![[0.0; 3]; rays.len()]);
        assert!(grad.iter().all(|&g| g == 0.0));
    }
}
