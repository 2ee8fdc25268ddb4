//! The sampling kernels against their plain references in `msth_core`: the proposal level's
//! stratified edges (`sampling::uniform_edges`), the samples placed on them (the spacing's
//! `t_of_s`, the bounds' `to_unit`, deltas, intervals, unit directions), and inverse-CDF
//! resampling (`sampling::sample_pdf`, annealed weights), for a box with linear spacing and a
//! contracted scene with spacing linear in disparity; rays with an empty interval, zero,
//! negative, NaN and infinite weights among them.
//!
//! Tolerances: edges and intervals within 2 ulp of 1 (the same arithmetic, in another order only
//! where FMA contracts it); resampled edges within 2e-5 (the device sums the CDF in a tree, the
//! CPU front to back: a few ulp of the CDF, divided by a bin's mass); points within 1e-5 of the
//! unit cube, deltas 1e-5 relative (distances go through `t_of_s`'s division); directions 1e-6.
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`).

mod common;

use glam::Vec3;
use msth_core::config::ModelConfig;
use msth_core::pipeline::{spacing_unit, TimedRay};
use msth_core::rng::Rng;
use msth_core::sampling::{sample_pdf, uniform_edges};
use msth_gpu::composite::GpuRays;
use msth_gpu::device::ComputeDevice;
use msth_gpu::sampling::{LevelBuffers, SampleRay, SamplingKernels};
use msth_testkit::Tests;

use common::{device, gpu_need};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "placement_and_resampling_match_core_in_a_box",
            || check(box_model()),
        )
        .needs(
            &[&gpu],
            "placement_and_resampling_match_core_when_contracted",
            || check(contracted_model()),
        )
        .run()
}

fn box_model() -> ModelConfig {
    common::box_model(70, 33)
}

fn contracted_model() -> ModelConfig {
    common::stage_model(70, 33, (0.2, 500.0))
}

fn buf(dev: &ComputeDevice, what: &str, v: &[f32]) -> wgpu::Buffer {
    dev.buffer_f32(what, v).unwrap()
}

fn check(cfg: ModelConfig) {
    let dev = device();
    let k = SamplingKernels::new(&dev).unwrap();
    let (np, nf) = (cfg.sampler.num_proposal_samples, cfg.sampler.num_samples);
    let mut rng = Rng::new(17);
    let mut rays: Vec<TimedRay> = (0..40)
        .map(|i| {
            let a = rng.range_f32(0.0, std::f32::consts::TAU);
            let origin = Vec3::new(4.0 * a.cos(), 4.0 * a.sin(), rng.range_f32(0.0, 2.0));
            let aim = Vec3::new(rng.range_f32(-1.0, 1.0), rng.range_f32(-1.0, 1.0), 0.5);
            TimedRay {
                origin,
                // Some unnormalised directions: the samples take the unit one.
                dir: (aim - origin) * if i % 3 == 0 { 2.5 } else { 1.0 } / (aim - origin).length(),
                time: rng.range_f32(-0.2, 1.2),
            }
        })
        .collect();
    // A ray that misses the box (an empty interval) or points nowhere.
    rays[5].dir = Vec3::new(0.0, 0.0, 1.0);
    rays[5].origin = Vec3::new(10.0, 10.0, 0.0);
    rays[6].dir = Vec3::ZERO;
    let n = rays.len();
    // Each ray's jitters: the first draws of two streams, which the core functions draw again.
    let stream = |i: usize, which: u64| Rng::stream(1, 2 * i as u64 + which);
    let jit: Vec<(f32, f32)> = (0..n)
        .map(|i| (stream(i, 0).f32(), stream(i, 1).f32()))
        .collect();
    let sr: Vec<SampleRay> = rays
        .iter()
        .zip(&jit)
        .map(|(r, j)| SampleRay::new(&cfg, r, *j))
        .collect();
    let ray_buf = buf(&dev, "rays", bytemuck::cast_slice(&sr));
    let z = |what: &str, len: usize| dev.zeros_f32(what, len).unwrap();

    // The proposal level: edges made on the device.
    let (e_p, pts_p, sd_p, iv_p) = (
        z("edges", n * (np + 1)),
        z("points", 4 * n * np),
        z("sd", 2 * n * np),
        z("intervals", 2 * n * np),
    );
    let dirs = z("dirs", 3 * n * np);
    let level = LevelBuffers {
        edges: &e_p,
        points: &pts_p,
        sigma_delta: &sd_p,
        intervals: &iv_p,
        dirs: Some(&dirs),
    };
    k.place(&dev, &cfg, (&ray_buf, n), np, true, true, &level)
        .unwrap();
    let edges = dev.read_f32(&e_p, n * (np + 1)).unwrap();
    let mut want = vec![0f32; np + 1];
    for i in 0..n {
        uniform_edges(np, Some(&mut stream(i, 0)), &mut want);
        for (k2, w) in want.iter().enumerate() {
            let g = edges[i * (np + 1) + k2];
            assert!(
                (g - w).abs() <= 2.0 * f32::EPSILON,
                "ray {i} edge {k2}: {g} vs {w}"
            );
        }
    }
    compare_samples(
        &dev,
        &cfg,
        &rays,
        &sr,
        np,
        &edges,
        (&pts_p, &sd_p, &iv_p),
        Some(&dirs),
    );

    // Resampling from weights with every kind of value, annealed.
    let mut w: Vec<f32> = (0..n * np).map(|_| rng.f32().powi(3)).collect();
    w[3] = -1.0;
    w[4] = f32::NAN;
    w[np + 7] = f32::INFINITY;
    for v in &mut w[2 * np..3 * np] {
        *v = 0.0;
    }
    let offsets: Vec<u32> = (0..=n as u32).map(|r| r * np as u32).collect();
    let prop = GpuRays::new(&dev, &offsets).unwrap();
    let w_b = buf(&dev, "w", &w);
    let (cdf, e_m) = (z("cdf", n * np), z("new edges", n * (nf + 1)));
    for anneal in [1.0f32, 0.37] {
        k.resample(
            &dev,
            &cfg,
            (&ray_buf, &prop),
            (&w_b, &e_p),
            anneal,
            true,
            nf,
            (&cdf, &e_m),
        )
        .unwrap();
        let got = dev.read_f32(&e_m, n * (nf + 1)).unwrap();
        let mut want = vec![0f32; nf + 1];
        let mut annealed = vec![0f32; np];
        let mut worst = 0f32;
        for i in 0..n {
            for b in 0..np {
                let x = w[i * np + b];
                annealed[b] = if anneal == 1.0 {
                    x
                } else {
                    x.max(0.0).powf(anneal)
                };
            }
            sample_pdf(
                &edges[i * (np + 1)..(i + 1) * (np + 1)],
                &annealed,
                cfg.sampler.histogram_padding,
                Some(&mut stream(i, 1)),
                &mut want,
            );
            for k2 in 0..=nf {
                let (g, c) = (got[i * (nf + 1) + k2], want[k2]);
                worst = worst.max((g - c).abs());
                assert!(
                    (g - c).abs() <= 2e-5,
                    "anneal {anneal} ray {i} edge {k2}: {g} vs {c}"
                );
            }
        }
        println!("resampled edges, anneal {anneal}: worst |gpu - cpu| {worst:.1e}");
    }

    // The main level on the resampled edges, read from the buffer.
    let new_edges = dev.read_f32(&e_m, n * (nf + 1)).unwrap();
    let (pts_m, sd_m, iv_m) = (
        z("points", 4 * n * nf),
        z("sd", 2 * n * nf),
        z("iv", 2 * n * nf),
    );
    let level = LevelBuffers {
        edges: &e_m,
        points: &pts_m,
        sigma_delta: &sd_m,
        intervals: &iv_m,
        dirs: None,
    };
    k.place(&dev, &cfg, (&ray_buf, n), nf, false, true, &level)
        .unwrap();
    compare_samples(
        &dev,
        &cfg,
        &rays,
        &sr,
        nf,
        &new_edges,
        (&pts_m, &sd_m, &iv_m),
        None,
    );
}

#[allow(clippy::too_many_arguments)]
fn compare_samples(
    dev: &ComputeDevice,
    cfg: &ModelConfig,
    rays: &[TimedRay],
    sr: &[SampleRay],
    ns: usize,
    edges: &[f32],
    (pts, sd, iv): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
    dirs: Option<&wgpu::Buffer>,
) {
    let n = rays.len();
    let pts = dev.read_f32(pts, 4 * n * ns).unwrap();
    let sd = dev.read_f32(sd, 2 * n * ns).unwrap();
    let iv = dev.read_f32(iv, 2 * n * ns).unwrap();
    let dirs = dirs.map(|d| dev.read_f32(d, 3 * n * ns).unwrap());
    let unit = spacing_unit(&cfg.bounds);
    for (i, (r, s)) in rays.iter().zip(sr).enumerate() {
        let (near, far) = (s.limits[0], s.limits[1]);
        let t_of = |e: f32| {
            if far > near {
                cfg.sampler.spacing.t_of_s(e, near, far, unit)
            } else {
                near
            }
        };
        let d_unit = r.dir.normalize_or_zero();
        for k in 0..ns {
            let j = i * ns + k;
            let (s0, s1) = (edges[i * (ns + 1) + k], edges[i * (ns + 1) + k + 1]);
            assert_eq!((iv[2 * j], iv[2 * j + 1]), (s0, s1), "ray {i} interval {k}");
            let (t0, t1) = (t_of(s0), t_of(s1));
            let delta = (t1 - t0).max(0.0);
            let g = sd[2 * j + 1];
            assert!(
                (g - delta).abs() <= 1e-5 * delta.max(1.0),
                "ray {i} delta {k}: {g} vs {delta}"
            );
            let u = cfg.bounds.to_unit(r.origin + r.dir * (0.5 * (t0 + t1)));
            let time = s.origin_time[3];
            for (a, c) in [u.x, u.y, u.z, time].into_iter().enumerate() {
                let g = pts[4 * j + a];
                assert!(
                    (g - c).abs() <= 1e-5,
                    "ray {i} sample {k} axis {a}: {g} vs {c}"
                );
            }
            if let Some(d) = &dirs {
                for (a, c) in [d_unit.x, d_unit.y, d_unit.z].into_iter().enumerate() {
                    assert!((d[3 * j + a] - c).abs() <= 1e-6, "ray {i} direction");
                }
            }
        }
    }
}
