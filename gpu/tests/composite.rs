//! The compositing kernels against `msth_core::render` (`weights`, `composite`,
//! `weights_backward`) on whatever adapter exists: rays of 0, 1, 5, 48, 64, 65, 128 and 300
//! samples (chunk boundaries of the scans), ordinary densities, and a ray of extremes (zero,
//! tiny, 1e8, infinite, NaN and negative densities: the CPU's `tau_of` rules), with and without
//! an extra per-sample weight gradient.
//!
//! Tolerances (the GPU sums optical depth, colours and the backward's suffix in a tree order,
//! the CPU front to back; the tests' optical depths stay below ~20):
//! - weights and T_N: |gpu - cpu| <= 1e-5 value + 1e-7; colour: 1e-5 absolute;
//! - d sigma: |gpu - cpu| <= 2e-5 delta (1 + sum_i |d_w_i| w_i + |d_T| T_N) + 1e-7;
//! - d rgb: |gpu - cpu| <= 1e-5 |dC| w + 1e-8;
//! - the colour loss (mean squared error over rgb, dC = 2 diff / 3 x scale): equal to the
//!   trainer's arithmetic on the GPU's colours within 4 ulp (bit-equal on lavapipe);
//! - the distortion loss (`msth_core::losses::distortion`, same rays): per ray
//!   |gpu - cpu| <= 1e-5 (sum w)^2 + 1e-8, its gradient (added into a buffer already holding
//!   values) |gpu - cpu| <= 2e-5 scale (1 + sum w) + 1e-8;
//! - the interlevel loss (`msth_core::losses::interlevel`, main and proposal levels of 0 to 130
//!   samples): per ray |gpu - cpu| <= 1e-4 loss + 1e-6 (the GPU sums each bound directly, the
//!   CPU as a difference of prefix sums), its gradient |gpu - cpu| <= 1e-4 (scale + |cpu|).
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`), and
//! [`main`] lists every test.

mod common;

use msth_core::losses::{distortion, interlevel};
use msth_core::render::{composite, weights, weights_backward};
use msth_core::rng::Rng;
use msth_gpu::composite::{CompositeBuffers, CompositeKernels, GpuRays};
use msth_gpu::losses::{ColorLossKernel, DistortionKernel, InterlevelKernel, LevelSamples};
use msth_gpu::GpuError;
use msth_testkit::Tests;

use common::{device, gpu_need};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "composite_forward_and_backward_match_the_cpu",
            composite_forward_and_backward_match_the_cpu,
        )
        .needs(
            &[&gpu],
            "distortion_loss_matches_the_cpu",
            distortion_loss_matches_the_cpu,
        )
        .needs(
            &[&gpu],
            "interlevel_loss_matches_the_cpu",
            interlevel_loss_matches_the_cpu,
        )
        .needs(
            &[&gpu],
            "composite_bad_input_is_an_error",
            composite_bad_input_is_an_error,
        )
        .run()
}

const BG: [f32; 3] = [1.0, 0.5, 0.25];

fn composite_forward_and_backward_match_the_cpu() {
    let dev = device();
    let k = CompositeKernels::new(&dev).unwrap();
    let mut rng = Rng::new(31);
    let counts = [0usize, 1, 5, 48, 64, 65, 128, 300, 12];
    let mut offsets = vec![0u32];
    let (mut sig, mut del) = (Vec::new(), Vec::new());
    for (r, &c) in counts.iter().enumerate() {
        for j in 0..c {
            if r == counts.len() - 1 {
                // The ray of extremes.
                let s = [0.0, 1e-8, 2.0, 1e8, f32::INFINITY, f32::NAN, -5.0, 1.0];
                sig.push(s[j % s.len()]);
                del.push([1e-3, 0.05, 1.0][j % 3]);
            } else {
                sig.push(rng.range_f32(0.0, 4.0));
                del.push(rng.range_f32(0.002, 0.04));
            }
        }
        offsets.push(sig.len() as u32);
    }
    let n = sig.len();
    let rgb: Vec<f32> = (0..3 * n).map(|_| rng.f32()).collect();
    let extra: Vec<f32> = (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect();
    let d_col: Vec<f32> = (0..4 * (counts.len()))
        .map(|_| rng.range_f32(-1.0, 1.0))
        .collect();
    let rays = GpuRays::new(&dev, &offsets).unwrap();
    let sd: Vec<f32> = sig.iter().zip(&del).flat_map(|(s, d)| [*s, *d]).collect();
    let sd_b = dev.buffer_f32("sd", &sd).unwrap();
    let rgb_b = dev.buffer_f32("rgb", &rgb).unwrap();
    let w_b = dev.zeros_f32("w", n).unwrap();
    let ray_b = dev.zeros_f32("rays", 4 * counts.len()).unwrap();
    let bufs = CompositeBuffers {
        sigma_delta: &sd_b,
        rgb: &rgb_b,
        weights: &w_b,
        ray_out: &ray_b,
    };
    k.forward(&dev, &rays, &bufs, BG).unwrap();
    let w_gpu = dev.read_f32(&w_b, n).unwrap();
    let ray_gpu = dev.read_f32(&ray_b, 4 * counts.len()).unwrap();
    // The colour loss from the GPU's colours: the trainer's arithmetic, exactly.
    let targets: Vec<f32> = (0..3 * counts.len()).map(|_| rng.f32()).collect();
    let loss_k = ColorLossKernel::new(&dev).unwrap();
    let (t_b, dcl_b, se_b) = (
        dev.buffer_f32("targets", &targets).unwrap(),
        dev.zeros_f32("dC from the loss", 4 * counts.len()).unwrap(),
        dev.zeros_f32("squared error", counts.len()).unwrap(),
    );
    loss_k
        .run(&dev, &rays, &ray_b, &t_b, 0.5, (&dcl_b, &se_b))
        .unwrap();
    let (dcl, se) = (
        dev.read_f32(&dcl_b, 4 * counts.len()).unwrap(),
        dev.read_f32(&se_b, counts.len()).unwrap(),
    );
    // Within 4 ulp (Vulkan allows the division 2.5).
    let close = |g: f32, c: f32| (g - c).abs() <= 4.0 * f32::EPSILON * c.abs();
    for r in 0..counts.len() {
        let mut sum = 0f32;
        for ch in 0..3 {
            let diff = ray_gpu[4 * r + ch] - targets[3 * r + ch];
            sum += diff * diff;
            let want = 2.0 * diff / 3.0 * 0.5;
            assert!(
                close(dcl[4 * r + ch], want),
                "ray {r}: dC {} vs {want}",
                dcl[4 * r + ch]
            );
        }
        assert!(
            close(se[r], sum / 3.0),
            "ray {r}: squared error {} vs {}",
            se[r],
            sum / 3.0
        );
    }
    let dc_b = dev.buffer_f32("dC", &d_col).unwrap();
    let ex_b = dev.buffer_f32("extra", &extra).unwrap();
    let ds_b = dev.zeros_f32("d sample", 4 * n).unwrap();
    let (mut worst_f, mut worst_b) = (0f32, 0f32);
    for with_extra in [false, true] {
        k.backward(
            &dev,
            &rays,
            &bufs,
            BG,
            &dc_b,
            with_extra.then_some(&ex_b),
            &ds_b,
        )
        .unwrap();
        let ds_gpu = dev.read_f32(&ds_b, 4 * n).unwrap();
        for r in 0..counts.len() {
            let (a, b) = (offsets[r] as usize, offsets[r + 1] as usize);
            let m = b - a;
            let mut w = vec![0f32; m];
            let t = weights(&sig[a..b], &del[a..b], &mut w);
            let c = composite(&w, &rgb[3 * a..3 * b], t, BG);
            let check = |what: &str, g: f32, cpu: f32, tol: f32, worst: &mut f32| {
                let err = (g - cpu).abs();
                assert!(
                    err <= tol,
                    "ray {r} ({m} samples): {what}: gpu {g} cpu {cpu}"
                );
                *worst = worst.max(err / tol);
            };
            for i in 0..m {
                check(
                    &format!("w[{i}]"),
                    w_gpu[a + i],
                    w[i],
                    1e-5 * w[i] + 1e-7,
                    &mut worst_f,
                );
            }
            check("T_N", ray_gpu[4 * r + 3], t, 1e-5 * t + 1e-7, &mut worst_f);
            for ch in 0..3 {
                check("C", ray_gpu[4 * r + ch], c[ch], 1e-5, &mut worst_f);
            }
            // Backward: d_w = extra + dC . rgb, d_T = dC . bg.
            let dc = &d_col[4 * r..4 * r + 3];
            let d_w: Vec<f32> = (0..m)
                .map(|i| {
                    let e = if with_extra { extra[a + i] } else { 0.0 };
                    e + (0..3).map(|ch| dc[ch] * rgb[3 * (a + i) + ch]).sum::<f32>()
                })
                .collect();
            let d_t: f32 = (0..3).map(|ch| dc[ch] * BG[ch]).sum();
            let mut d_sigma = vec![0f32; m];
            weights_backward(&sig[a..b], &del[a..b], &w, t, &d_w, d_t, &mut d_sigma);
            let scale: f32 =
                1.0 + d_w.iter().zip(&w).map(|(x, y)| (x * y).abs()).sum::<f32>() + (d_t * t).abs();
            for i in 0..m {
                let d = &ds_gpu[4 * (a + i)..4 * (a + i + 1)];
                let delta = del[a + i];
                check(
                    &format!("d sigma[{i}] (extra {with_extra})"),
                    d[0],
                    d_sigma[i],
                    2e-5 * delta * scale + 1e-7,
                    &mut worst_b,
                );
                for ch in 0..3 {
                    check(
                        &format!("d rgb[{i}]"),
                        d[1 + ch],
                        dc[ch] * w[i],
                        1e-5 * dc[ch].abs() * w[i] + 1e-8,
                        &mut worst_b,
                    );
                }
            }
        }
    }
    println!(
        "composite: {} rays, {n} samples: forward worst error / tolerance {worst_f:.3}, backward {worst_b:.3}",
        counts.len()
    );
}

fn composite_bad_input_is_an_error() {
    let dev = device();
    let k = CompositeKernels::new(&dev).unwrap();
    for offsets in [&[][..], &[1, 2][..], &[0, 5, 3][..]] {
        let e = GpuRays::new(&dev, offsets).err().unwrap();
        assert!(matches!(e, GpuError::Input(_)), "{e}");
    }
    let rays = GpuRays::new(&dev, &[0, 10]).unwrap();
    let small = dev.zeros_f32("small", 4).unwrap();
    let bufs = CompositeBuffers {
        sigma_delta: &small,
        rgb: &small,
        weights: &small,
        ray_out: &small,
    };
    let e = k.forward(&dev, &rays, &bufs, BG).unwrap_err();
    assert!(matches!(e, GpuError::Input(_)), "{e}");
}

fn distortion_loss_matches_the_cpu() {
    let dev = device();
    let k = DistortionKernel::new(&dev).unwrap();
    let mut rng = Rng::new(32);
    let counts = [0usize, 1, 5, 48, 64, 65, 128, 300];
    let mut offsets = vec![0u32];
    let (mut edges, mut intervals, mut w) = (Vec::new(), Vec::new(), Vec::new());
    for &c in &counts {
        // Sorted edges over [0, 1] (the normalised ray coordinate), weights summing below 1.
        let (e, pairs) = sorted_intervals(c, &mut rng);
        intervals.extend(pairs);
        w.extend((0..c).map(|_| rng.f32() * 2.0 / c as f32));
        edges.push(e);
        offsets.push(w.len() as u32);
    }
    let n = w.len();
    let scale = 0.7;
    let d_w0: Vec<f32> = (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect();
    let rays = GpuRays::new(&dev, &offsets).unwrap();
    let iv_b = dev.buffer_f32("intervals", &intervals).unwrap();
    let w_b = dev.buffer_f32("w", &w).unwrap();
    let dw_b = dev.buffer_f32("d_w", &d_w0).unwrap();
    let loss_b = dev.zeros_f32("loss", counts.len()).unwrap();
    k.run(&dev, &rays, &iv_b, &w_b, scale, &dw_b, &loss_b)
        .unwrap();
    let loss = dev.read_f32(&loss_b, counts.len()).unwrap();
    let d_w = dev.read_f32(&dw_b, n).unwrap();
    let mut worst = 0f32;
    for r in 0..counts.len() {
        let (a, b) = (offsets[r] as usize, offsets[r + 1] as usize);
        let mut d_cpu = d_w0[a..b].to_vec();
        let l = distortion(&edges[r], &w[a..b], scale, &mut d_cpu);
        let total: f32 = w[a..b].iter().sum();
        let tol = 1e-5 * total * total + 1e-8;
        assert!(
            (loss[r] - l).abs() <= tol,
            "ray {r}: loss gpu {} cpu {l}",
            loss[r]
        );
        worst = worst.max((loss[r] - l).abs() / tol);
        for i in 0..b - a {
            let tol = 2e-5 * scale * (1.0 + total) + 1e-8;
            let err = (d_w[a + i] - d_cpu[i]).abs();
            assert!(
                err <= tol,
                "ray {r} sample {i}: d_w gpu {} cpu {}",
                d_w[a + i],
                d_cpu[i]
            );
            worst = worst.max(err / tol);
        }
    }
    println!("distortion: worst error / tolerance {worst:.3}");
}

/// Sorted edges over [0, 1] as `(s_i, s_{i+1})` pairs, and the edges themselves.
fn sorted_intervals(count: usize, rng: &mut Rng) -> (Vec<f32>, Vec<f32>) {
    let mut e: Vec<f32> = (0..=count).map(|_| rng.f32()).collect();
    e.sort_by(f32::total_cmp);
    let pairs = (0..count).flat_map(|i| [e[i], e[i + 1]]).collect();
    (e, pairs)
}

fn interlevel_loss_matches_the_cpu() {
    let dev = device();
    let k = InterlevelKernel::new(&dev).unwrap();
    let mut rng = Rng::new(33);
    let shapes = [
        (0usize, 0usize),
        (1, 3),
        (5, 16),
        (48, 128),
        (64, 64),
        (65, 130),
        (20, 0),
    ];
    let (mut off_m, mut off_p) = (vec![0u32], vec![0u32]);
    let (mut iv_m, mut iv_p, mut w_m, mut w_p) = (vec![], vec![], vec![], vec![]);
    let mut edges = Vec::new();
    for &(nf, np) in &shapes {
        let (em, pm) = sorted_intervals(nf, &mut rng);
        let (ep, pp) = sorted_intervals(np, &mut rng);
        iv_m.extend(pm);
        iv_p.extend(pp);
        w_m.extend((0..nf).map(|_| rng.f32() * 2.0 / nf as f32));
        w_p.extend((0..np).map(|_| rng.f32() * 1.5 / np as f32));
        edges.push((em, ep));
        off_m.push(w_m.len() as u32);
        off_p.push(w_p.len() as u32);
    }
    let scale = 0.3;
    let d0: Vec<f32> = (0..w_p.len()).map(|_| rng.range_f32(-1.0, 1.0)).collect();
    let (rays_m, rays_p) = (
        GpuRays::new(&dev, &off_m).unwrap(),
        GpuRays::new(&dev, &off_p).unwrap(),
    );
    let b = |what: &str, v: &[f32]| dev.buffer_f32(what, v).unwrap();
    let (ivm_b, wm_b, ivp_b, wp_b) = (
        b("iv m", &iv_m),
        b("w m", &w_m),
        b("iv p", &iv_p),
        b("w p", &w_p),
    );
    let (d_b, loss_b) = (
        b("d w_prop", &d0),
        dev.zeros_f32("loss", shapes.len()).unwrap(),
    );
    let main = LevelSamples {
        rays: &rays_m,
        intervals: &ivm_b,
        weights: &wm_b,
    };
    let prop = LevelSamples {
        rays: &rays_p,
        intervals: &ivp_b,
        weights: &wp_b,
    };
    k.run(&dev, &main, &prop, scale, (&d_b, &loss_b)).unwrap();
    let loss = dev.read_f32(&loss_b, shapes.len()).unwrap();
    let d = dev.read_f32(&d_b, w_p.len()).unwrap();
    let (mut worst, mut active) = (0f32, 0);
    for (r, (em, ep)) in edges.iter().enumerate() {
        let (a, b) = (off_m[r] as usize, off_m[r + 1] as usize);
        let (pa, pb) = (off_p[r] as usize, off_p[r + 1] as usize);
        let mut d_cpu = d0[pa..pb].to_vec();
        let l = interlevel(em, &w_m[a..b], ep, &w_p[pa..pb], scale, &mut d_cpu);
        let tol = 1e-4 * l + 1e-6;
        assert!(
            (loss[r] - l).abs() <= tol,
            "ray {r}: loss gpu {} cpu {l}",
            loss[r]
        );
        worst = worst.max((loss[r] - l).abs() / tol);
        for j in 0..pb - pa {
            let tol = 1e-4 * (scale + d_cpu[j].abs());
            let err = (d[pa + j] - d_cpu[j]).abs();
            assert!(
                err <= tol,
                "ray {r} proposal {j}: gpu {} cpu {}",
                d[pa + j],
                d_cpu[j]
            );
            worst = worst.max(err / tol);
            active += (d_cpu[j] != d0[pa + j]) as usize;
        }
    }
    assert!(active > 50, "only {active} proposal weights got a gradient");
    println!(
        "interlevel: {active} proposal weights with a gradient, worst error / tolerance {worst:.3}"
    );
}
