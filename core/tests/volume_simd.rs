//! The volume's march compiled for AVX2, FMA and F16C (`march_chunk` where the CPU has them)
//! gives the portable march's bits: colours, depths, flags and counts, for static and dynamic
//! bricks, with their slices baked and without, on a box and a contracted scene.
//!
//! On a CPU without those features there is nothing to compare, and the test is reported as
//! ignored with the reason (unless `MSTH_REQUIRE_AVX2=1`): this binary runs on `msth-testkit`'s
//! harness.

use glam::Vec3;
use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::pipeline::TimedRay;
use msth_core::scene::SceneBounds;
use msth_core::volume::bake::{bake, bake_slice, plan, BakeProgress};
use msth_core::volume::march::{march_chunk, march_chunk_portable, simd_available};
use msth_core::volume::{MarchOutput, MarchSettings, MarchWorkspace};
use msth_core::Camera;
use msth_testkit::{Need, Tests};

fn main() -> std::process::ExitCode {
    let avx2 = Need::new("avx2", || {
        if simd_available() {
            Ok(())
        } else {
            Err("this CPU has no AVX2, FMA and F16C (or is not x86_64)".into())
        }
    });
    Tests::new(file!())
        .needs(
            &[&avx2],
            "the_simd_march_equals_the_portable_march",
            the_simd_march_equals_the_portable_march,
        )
        .run()
}

/// A small model over the D-NeRF box whose mask leaves the half `x > 0.5` of the cube to the
/// 4D grid, with random hash tables.
fn model(contracted: bool, seed: u64) -> (ModelConfig, ModelLayout, Vec<f32>) {
    let mut cfg = ModelConfig::fast_on_white(8);
    cfg.field.encoding.resize(4, 10, 32.0, 8);
    cfg.proposal.encoding.resize(3, 10, 16.0, 8);
    if contracted {
        cfg.bounds = SceneBounds::Contracted {
            center: Vec3::ZERO,
            radius: 1.0,
        };
    }
    let layout = ModelLayout::new(&cfg);
    let mut params = layout.init_params(seed);
    let mut rng = msth_core::rng::Rng::new(seed + 1);
    for e in &layout.params.entries {
        if e.name.ends_with("h3") || e.name.ends_with("h4") {
            for v in &mut params[e.range()] {
                *v = rng.range_f32(-0.5, 0.5);
            }
        }
    }
    let (d, r) = layout.field.encoding.mask.clone().expect("mask");
    let res = d.res;
    for (i, v) in params[r].iter_mut().enumerate() {
        *v = if (i % res) * 2 >= res { -3.0 } else { 6.0 };
    }
    (cfg, layout, params)
}

fn march(
    simd: bool,
    vol: &msth_core::volume::Volume,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
) -> MarchOutput {
    let mut ws = MarchWorkspace::default();
    let mut out = MarchOutput::default();
    let s = MarchSettings::default();
    if simd {
        march_chunk(vol, cfg, layout, params, rays, &s, &mut ws, &mut out);
    } else {
        march_chunk_portable(vol, cfg, layout, params, rays, &s, &mut ws, &mut out);
    }
    out
}

fn the_simd_march_equals_the_portable_march() {
    for contracted in [false, true] {
        let (cfg, layout, params) = model(contracted, 5);
        let p = plan(&cfg, &layout, &params, None, 64 << 20, Some(32)).unwrap();
        let mut vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
        assert!(
            !p.dynamic_bricks.is_empty(),
            "the test needs dynamic bricks"
        );
        let cam = Camera::look_at(24, 18, 0.8, Vec3::new(0.3, -4.0, 1.2), Vec3::ZERO, Vec3::Z);
        for sliced in [false, true] {
            if sliced {
                for k in 0..p.slice_times.len() {
                    bake_slice(&mut vol, &p, k, &cfg, &layout, &params).unwrap();
                }
            }
            // On a slice's time and between two.
            for time in [
                p.slice_times[2],
                0.5 * (p.slice_times[2] + p.slice_times[3]),
            ] {
                let mut rays = Vec::new();
                for y in 0..cam.height {
                    for x in 0..cam.width {
                        rays.push(TimedRay::through_pixel(&cam, x, y, time));
                    }
                }
                let a = march(true, &vol, &cfg, &layout, &params, &rays);
                let b = march(false, &vol, &cfg, &layout, &params, &rays);
                let what = format!("contracted {contracted}, sliced {sliced}, time {time}");
                assert!(a.samples > 0, "{what}: the rays meet the field");
                let bits = |o: &MarchOutput| {
                    o.rgb
                        .iter()
                        .flatten()
                        .chain(&o.visible_depth)
                        .map(|x| x.to_bits())
                        .collect::<Vec<_>>()
                };
                let (ba, bb) = (bits(&a), bits(&b));
                let first = ba.iter().zip(&bb).position(|(x, y)| x != y);
                assert_eq!(first, None, "{what}: the first value that differs");
                assert_eq!(a.dynamic, b.dynamic, "{what}");
                assert_eq!(a.outside, b.outside, "{what}");
                assert_eq!(
                    (a.samples, a.dynamic_samples, a.steps),
                    (b.samples, b.dynamic_samples, b.steps),
                    "{what}"
                );
            }
        }
    }
}
