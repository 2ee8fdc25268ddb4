//! Tests of the GPU renderer against the CPU: the WGSL field evaluation (`eval_points`: hash
//! lookups 3D/4D with dense and hashed levels, mask, blend, decoders, SH) against the plain CPU
//! references (`FieldLayout::eval_point_reference`) for every blend mode; whole frames, full and
//! incremental, of [`GpuRenderer`] against [`Renderer`] for box and contracted scenes, constant
//! and last-sample backgrounds; limits and bad input.
//!
//! They run on whatever adapter exists (Mesa's lavapipe in CI). Without one they are reported
//! as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1` (then they fail): this binary runs
//! on `msth-testkit`'s harness (`harness = false`), and [`main`] lists every test.

use msth_core::config::{Background, BlendMode, ModelConfig, PlaySamples, Preset, SampleLevel};
use msth_core::field::ModelLayout;
use msth_core::rng::Rng;
use msth_core::sh::{sh4, SH_COEFFS};
use msth_core::{Camera, SceneBounds};
use msth_player::gpu::{
    AdapterPolicy, GpuContext, GpuError, GpuMlps, GpuModel, GpuRenderer, GpuScene, Kernel,
    MlpStatus, ViewU, FLAG_COMPACT,
};
use msth_player::TableFormat;
use msth_player::{Frame, RenderSettings, Renderer, Reuse};
use msth_testkit::{Need, Skip, Tests};

fn main() -> std::process::ExitCode {
    // "No adapter" is a missing need; any other error opening one fails the test.
    let gpu = Need::new("gpu", || match GpuContext::open(AdapterPolicy::any()) {
        Ok(_) => Ok(()),
        Err(e @ GpuError::NoAdapter(_)) => Err(e.to_string()),
        Err(e) => panic!("{e}"),
    });
    Tests::new(file!())
        .needs(
            &[&gpu],
            "eval_points_matches_the_cpu_reference_for_every_blend",
            eval_points_matches_the_cpu_reference_for_every_blend,
        )
        .needs(
            &[&gpu],
            "eval_points_match_the_cpu_reference_for_every_feature_count",
            eval_points_match_the_cpu_reference_for_every_feature_count,
        )
        .needs(
            &[&gpu],
            "buffers_beyond_the_adapter_limits_are_clear_errors",
            buffers_beyond_the_adapter_limits_are_clear_errors,
        )
        .needs(
            &[&gpu],
            "models_beyond_lavapipes_loop_budget_are_clear_errors_there",
            models_beyond_lavapipes_loop_budget_are_clear_errors_there,
        )
        .test(
            "models_beyond_the_kernel_limits_are_clear_errors",
            models_beyond_the_kernel_limits_are_clear_errors,
        )
        .needs(
            &[&gpu],
            "gpu_frames_match_cpu_frames_full_and_incremental",
            gpu_frames_match_cpu_frames_full_and_incremental,
        )
        .needs(
            &[&gpu],
            "specialised_and_generic_kernels_render_the_same_frames",
            specialised_and_generic_kernels_render_the_same_frames,
        )
        .needs(
            &[&gpu],
            "gpu_frames_with_an_occupancy_grid_match_the_cpu_renderer",
            gpu_frames_with_an_occupancy_grid_match_the_cpu_renderer,
        )
        .needs(
            &[&gpu],
            "gpu_sample_reuse_matches_cpu_sample_reuse",
            gpu_sample_reuse_matches_cpu_sample_reuse,
        )
        .needs(
            &[&gpu],
            "balanced_preset_frames_match_the_cpu_full_and_incremental",
            balanced_preset_frames_match_the_cpu_full_and_incremental,
        )
        .needs(
            &[&gpu],
            "probes_render_with_the_parameters_of_their_time_on_the_gpu",
            probes_render_with_the_parameters_of_their_time_on_the_gpu,
        )
        .needs(
            &[&gpu],
            "new_parameters_upload_what_changed_and_versions_skip_the_comparison",
            new_parameters_upload_what_changed_and_versions_skip_the_comparison,
        )
        .needs(
            &[&gpu],
            "binary16_tables_render_the_frames_of_rounded_tables",
            binary16_tables_render_the_frames_of_rounded_tables,
        )
        .needs(
            &[&gpu],
            "playback_reports_table_values_binary16_clamps",
            playback_reports_table_values_binary16_clamps,
        )
        .needs(
            &[&gpu],
            "every_lane_count_renders_the_same_frames",
            every_lane_count_renders_the_same_frames,
        )
        .needs(
            &[&gpu],
            "volume_frames_on_the_gpu_match_the_cpu_march",
            volume_frames_on_the_gpu_match_the_cpu_march,
        )
        .needs(
            &[&gpu],
            "the_finest_volume_draws_on_the_gpu_as_on_the_cpu",
            the_finest_volume_draws_on_the_gpu_as_on_the_cpu,
        )
        .needs(
            &[&gpu],
            "rays_reaching_bricks_left_out_of_the_volume_draw_exactly_on_the_gpu",
            rays_reaching_bricks_left_out_of_the_volume_draw_exactly_on_the_gpu,
        )
        .needs(
            &[&gpu],
            "volumes_the_gpu_cannot_draw_are_clear_errors",
            volumes_the_gpu_cannot_draw_are_clear_errors,
        )
        .run()
}

/// The device (the tests that call this run only where one exists).
fn context() -> GpuContext {
    GpuContext::open(AdapterPolicy::any()).unwrap()
}

fn config(blend: BlendMode) -> ModelConfig {
    let mut c = ModelConfig::preset(
        Preset::Fast,
        SceneBounds::dnerf_default(),
        Background::Color { rgb: [1.0; 3] },
        10,
    );
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        enc.blend = blend;
        // Coarse levels dense, fine levels hashed (2^10 rows).
        enc.resize(4, 10, 64.0, 8);
        enc.grid4.finest_resolution[3] = 10.0;
        enc.grid3.base_resolution = vec![4.0; 3];
        enc.grid4.base_resolution = vec![4.0, 4.0, 4.0, 2.0];
    }
    c.field.density_hidden = 16;
    c.field.color_hidden = 16;
    c.field.geo_features = 7;
    c.proposal.hidden = 8;
    c
}

/// Shrinks `cfg` to a model that renders quickly on a software adapter.
fn small(cfg: &mut ModelConfig) {
    cfg.field.encoding.resize(3, 10, 64.0, 8);
    cfg.proposal.encoding.resize(2, 10, 32.0, 8);
    for enc in [&mut cfg.field.encoding, &mut cfg.proposal.encoding] {
        enc.grid3.base_resolution = vec![4.0; 3];
        enc.grid4.base_resolution = vec![4.0, 4.0, 4.0, 2.0];
    }
    cfg.field.density_hidden = 8;
    cfg.field.color_hidden = 8;
    cfg.field.geo_features = 3;
    cfg.proposal.hidden = 4;
    cfg.sampler.num_proposal_samples = 16;
    cfg.sampler.num_samples = 8;
}

fn random_params(layout: &ModelLayout, seed: u64) -> Vec<f32> {
    let mut p = layout.init_params(seed);
    let mut rng = Rng::new(seed + 1);
    for e in &layout.params.entries {
        let amp = if e.name.ends_with("mask") {
            3.0
        } else if e.name.ends_with("h3") || e.name.ends_with("h4") {
            1.0
        } else {
            0.0
        };
        if amp > 0.0 {
            for v in &mut p[e.range()] {
                *v = rng.range_f32(-amp, amp);
            }
        }
    }
    p
}

fn eval_points_matches_the_cpu_reference_for_every_blend() {
    let ctx = context();
    for blend in [
        BlendMode::Mst,
        BlendMode::Mt,
        BlendMode::Add,
        BlendMode::FourD,
        BlendMode::Static,
    ] {
        eval_points_match(&ctx, config(blend), &format!("{blend:?}"));
    }
}

/// The kernels accumulate features 0 and 1 of a level apart from features 2..: every allowed
/// number of features per level against the CPU reference.
fn eval_points_match_the_cpu_reference_for_every_feature_count() {
    let ctx = context();
    // One feature: the tables read value by value; more: in pairs.
    for features in [1, 4, 8] {
        let mut cfg = config(BlendMode::Mst);
        for enc in [&mut cfg.field.encoding, &mut cfg.proposal.encoding] {
            enc.grid3.features_per_level = features;
            enc.grid4.features_per_level = features;
        }
        eval_points_match(&ctx, cfg, &format!("{features} features per level"));
    }
}

/// Evaluates 300 points (field and proposal, faces and corners of the cube among them) with
/// `Kernel::EvalPoints` and compares them with the CPU reference; `what` names the case.
fn eval_points_match(ctx: &GpuContext, cfg: ModelConfig, what: &str) {
    let layout = ModelLayout::new(&cfg);
    let (g3, _) = layout
        .field
        .encoding
        .h3
        .clone()
        .or(layout.field.encoding.h4.clone())
        .unwrap();
    assert!(g3.levels.iter().any(|l| l.dense) && g3.levels.iter().any(|l| !l.dense));
    let params = random_params(&layout, 3);
    let gm = GpuModel::new(&cfg).unwrap();
    let scene = GpuScene::new(ctx, gm, &params).unwrap();
    let mut rng = Rng::new(11);
    let n = 300;
    let mut words = Vec::with_capacity(n * 8);
    let mut pts = Vec::new();
    for j in 0..n {
        let p = [rng.f32(), rng.f32(), rng.f32(), rng.f32()];
        // A few points on the cube's faces and corners.
        let p = if j < 8 {
            [
                (j & 1) as f32,
                ((j >> 1) & 1) as f32,
                ((j >> 2) & 1) as f32,
                (j & 1) as f32,
            ]
        } else {
            p
        };
        let d = glam::Vec3::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5)
            .normalize_or(glam::Vec3::Z);
        let which = (j % 3 == 2) as u32 as f32;
        for v in [p[0], p[1], p[2], p[3], d.x, d.y, d.z, which] {
            words.push(v.to_bits());
        }
        pts.push((p, d, which));
    }
    let list = ctx
        .storage_buffer("points", bytemuck::cast_slice(&words), false)
        .unwrap();
    let out = ctx.output_buffer("values", n).unwrap();
    let cam = Camera::look_at(
        1,
        1,
        1.0,
        glam::Vec3::Z * 3.0,
        glam::Vec3::ZERO,
        glam::Vec3::Y,
    );
    let view = ViewU::new(&cam, 0.0, n as u32, FLAG_COMPACT);
    ctx.dispatch(Kernel::EvalPoints, &scene, &view, &list, &out)
        .unwrap();
    let got = ctx.read_vec4(&out, n).unwrap();
    for (j, (p, d, which)) in pts.iter().enumerate() {
        let g = got[j];
        if *which == 1.0 {
            let f = &layout.proposal.field;
            let (enc, m) = f.encoding.encode_point_reference(&params, p);
            let o = f
                .density
                .0
                .forward_reference(&params[f.density.1.clone()], &enc);
            let sigma = msth_core::activation::trunc_exp(o[0]);
            assert!(
                (g[3] - sigma).abs() <= 1e-4 * sigma.max(1.0),
                "{what} proposal point {j}: sigma {} vs {sigma}",
                g[3]
            );
            assert!((g[0] - m).abs() < 1e-5, "{what} proposal mask");
        } else {
            let mut sh = vec![0f32; SH_COEFFS];
            sh4([d.x, d.y, d.z], &mut sh);
            let (sigma, rgb, _) = layout.field.eval_point_reference(&params, p, &sh);
            assert!(
                (g[3] - sigma).abs() <= 1e-4 * sigma.max(1.0),
                "{what} point {j} {p:?}: sigma {} vs {sigma}",
                g[3]
            );
            for c in 0..3 {
                assert!(
                    (g[c] - rgb[c]).abs() < 1e-5,
                    "{what} point {j}: rgb {g:?} vs {rgb:?}"
                );
            }
        }
    }
}

fn buffers_beyond_the_adapter_limits_are_clear_errors() {
    let ctx = context();
    let e = ctx
        .check_storage("a test buffer", u64::MAX / 2)
        .unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("max_storage_buffer_binding_size"), "{msg}");
    assert!(msg.contains("a test buffer"), "{msg}");
    // A frame too large for one output buffer.
    let e = ctx.output_buffer("frame", usize::MAX / 64).unwrap_err();
    assert!(matches!(e, GpuError::Limit { .. }), "{e}");
}

fn models_beyond_lavapipes_loop_budget_are_clear_errors_there() -> Result<(), Skip> {
    let ctx = context();
    if !ctx.is_lavapipe() {
        return Err(Skip::new("the adapter is not lavapipe"));
    }
    let cfg = ModelConfig::preset(
        Preset::Fast,
        SceneBounds::dnerf_default(),
        Background::Color { rgb: [1.0; 3] },
        10,
    );
    // Five hidden colour layers of 128: one sample's colour loops over more weights than
    // lavapipe runs loop iterations per invocation.
    let mut deep = cfg.clone();
    deep.field.color_hidden = 128;
    deep.field.color_layers = 5;
    let e = GpuRenderer::new(ctx, &deep, RenderSettings::default())
        .err()
        .expect("a very deep colour MLP exceeds lavapipe's loop budget");
    assert!(
        e.to_string().contains("loop iterations") && e.to_string().contains("per-sample"),
        "{e}"
    );
    // A preset model fits it.
    GpuRenderer::new(context(), &cfg, RenderSettings::default()).unwrap();
    Ok(())
}

fn models_beyond_the_kernel_limits_are_clear_errors() {
    let mut cfg = config(BlendMode::Mt);
    cfg.field.density_hidden = 512;
    let e = GpuModel::new(&cfg).unwrap_err().to_string();
    assert!(
        e.contains("field.density_hidden") && e.contains("128"),
        "{e}"
    );
    let mut cfg = config(BlendMode::Mt);
    cfg.sampler.num_samples = 1000;
    let e = GpuModel::new(&cfg).unwrap_err().to_string();
    assert!(e.contains("num_samples"), "{e}");
}

fn max_diff(a: &Frame, b: &Frame) -> f32 {
    a.rgb
        .iter()
        .zip(&b.rgb)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max)
}

/// Full and incremental frames of the GPU renderer equal the CPU renderer's to float rounding,
/// with the same rays cached and re-rendered.
fn gpu_frames_match_cpu_frames_full_and_incremental() {
    let scenes = [
        (
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
        ),
        (
            SceneBounds::Contracted {
                center: glam::Vec3::ZERO,
                radius: 1.0,
            },
            Background::LastSample,
        ),
    ];
    for (bounds, background) in scenes {
        let mut cfg = config(BlendMode::Mt);
        cfg.bounds = bounds;
        cfg.background = background;
        let defaults = ModelConfig::preset(Preset::Fast, bounds, background, 10);
        cfg.sampler = defaults.sampler;
        // Small, for a software adapter's speed.
        small(&mut cfg);
        let layout = ModelLayout::new(&cfg);
        let mut params = random_params(&layout, 5);
        // Static everywhere but around the centre of the scene.
        let (grid, r) = layout.field.encoding.mask.clone().unwrap();
        let res = grid.res;
        for (k, v) in params[r].iter_mut().enumerate() {
            let (x, y, z) = (k % res, (k / res) % res, k / (res * res));
            let centre = |c: usize| (res / 2 - 1..=res / 2).contains(&c);
            *v = if centre(x) && centre(y) && centre(z) {
                -3.0
            } else {
                9.0
            };
        }
        // The mask alone decides (the random 4D table moves every colour a probe would see).
        // Whole dynamic rays on both (sample-level reuse has its own test,
        // `gpu_sample_reuse_matches_cpu_sample_reuse`).
        let settings = RenderSettings {
            probes: 0,
            reuse: Reuse::Rays,
            ..Default::default()
        };
        let mut cpu = Renderer::new(&cfg, settings);
        let mut gpu = GpuRenderer::new(context(), &cfg, settings).unwrap();
        // Far enough for the box to leave pixels around it.
        let cam = Camera::look_at(
            40,
            30,
            0.9,
            glam::Vec3::new(0.6, -7.0, 2.4),
            glam::Vec3::ZERO,
            glam::Vec3::Z,
        );
        for (i, t) in [0.0f32, 0.4, 0.9].into_iter().enumerate() {
            let a = cpu.render(&cam, t, &params);
            let b = gpu.render(&cam, t, &params).unwrap();
            assert_eq!(a.stats.full, b.stats.full);
            assert_eq!(a.stats.full, i == 0);
            let d = max_diff(&a, &b);
            assert!(d < 2e-3, "{bounds:?} frame {i}: max difference {d}");
            // The classification is the CPU renderer's: the same counts (rays near the static
            // threshold could flip on rounding; none do here).
            assert_eq!(a.stats.rays_empty, b.stats.rays_empty, "frame {i}");
            assert_eq!(a.stats.rays_rendered, b.stats.rays_rendered, "frame {i}");
            // The box is seen against its background: the GPU marks the rays that miss it in its
            // output, and the host counts those marks.
            if matches!(background, Background::Color { .. }) {
                assert!(b.stats.rays_empty > 0, "frame {i}: no ray misses the box");
            }
            // Classified from the second frame on, as the CPU renderer.
            assert_eq!(gpu.dynamic_fraction().is_some(), i > 0, "frame {i}");
            assert_eq!(cpu.dynamic_fraction().is_some(), i > 0, "frame {i}");
        }
        let (fc, fg) = (
            cpu.dynamic_fraction().unwrap(),
            gpu.dynamic_fraction().unwrap(),
        );
        assert_eq!(fc, fg);
        assert!(fc > 0.0 && fc < 1.0, "dynamic fraction {fc}");
        // A new parameter buffer (a new chunk) is uploaded: frames follow it.
        let mut p2 = params.clone();
        let (_, h4) = layout.field.encoding.h4.clone().unwrap();
        for v in &mut p2[h4] {
            *v = -*v;
        }
        cpu.invalidate();
        gpu.invalidate();
        let a = cpu.render(&cam, 0.5, &p2);
        let b = gpu.render(&cam, 0.5, &p2).unwrap();
        assert!(max_diff(&a, &b) < 2e-3);
        // The wrong parameter count is an error, not a panic.
        let e = gpu.render(&cam, 0.5, &p2[1..]).err().unwrap();
        assert!(e.to_string().contains("parameter buffer"), "{e}");
    }
}

/// With the file's occupancy grid (here: every cell with `x < R / 2` empty) the GPU renderer
/// skips what the CPU renderer skips (`empty_space.rs`): full and incremental frames (whole dynamic
/// rays) equal the CPU renderer's with the same grid, the grid changes the frame, and without a
/// grid (a version-1 file) frames are the unskipped ones again.
fn gpu_frames_with_an_occupancy_grid_match_the_cpu_renderer() {
    let mut cfg = config(BlendMode::Mt);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let mut params = random_params(&layout, 7);
    centre_dynamic(&cfg, &mut params);
    let r = 16u32;
    let mut grid = msth_codec::OccupancyGrid::full(r);
    for z in 0..r {
        for y in 0..r {
            for x in 0..r / 2 {
                let i = (x + r * (y + r * z)) as usize;
                grid.words[i / 32] &= !(1u32 << (i % 32));
            }
        }
    }
    let grid = std::sync::Arc::new(grid);
    let settings = RenderSettings {
        probes: 0,
        reuse: Reuse::Rays,
        ..Default::default()
    };
    let mut cpu = Renderer::new(&cfg, settings);
    cpu.set_occupancy(Some(grid.clone()));
    let mut gpu = GpuRenderer::new(context(), &cfg, settings).unwrap();
    gpu.set_occupancy(Some(grid.clone())).unwrap();
    let cam = test_camera(40, 30);
    for (i, t) in [0.0f32, 0.4, 0.9].into_iter().enumerate() {
        let a = cpu.render(&cam, t, &params);
        let b = gpu.render(&cam, t, &params).unwrap();
        assert_eq!(b.stats.full, i == 0);
        let d = max_diff(&a, &b);
        assert!(d < 2e-3, "frame {i}: max difference {d}");
        if i == 0 {
            // The full frame (one batch) split the live samples by the mask: the static ones
            // went to the passes without a 4D lookup, the centre's to those with one.
            let c = gpu.last_pass_counts().unwrap().unwrap();
            eprintln!("occupancy grid, frame 0: {c:?}");
            assert!(c.samples3 > 0 && c.samples4 > 0, "{c:?}");
            assert!(c.proposal3 + c.proposal4 > 0, "{c:?}");
        }
    }
    // The grid matters: without it the frame differs.
    let full = RenderSettings {
        incremental: false,
        ..settings
    };
    // The generic passes split the samples alike.
    let mut cpu_full = Renderer::new(&cfg, full);
    cpu_full.set_occupancy(Some(grid.clone()));
    let mut generic = GpuRenderer::new(context(), &cfg, full).unwrap();
    generic.set_mlps(GpuMlps::Generic);
    generic.set_occupancy(Some(grid.clone())).unwrap();
    let a = cpu_full.render(&cam, 0.4, &params);
    let b = generic.render(&cam, 0.4, &params).unwrap();
    let d = max_diff(&a, &b);
    assert!(d < 2e-3, "generic passes: max difference {d}");
    let c = generic.last_pass_counts().unwrap().unwrap();
    assert!(c.samples3 > 0 && c.samples4 > 0, "generic passes: {c:?}");
    // Batches: the frame in one batch (the default scratch) and in batches of a few dozen rays,
    // the last one short, are the same to the bit.
    let mut one = GpuRenderer::new(context(), &cfg, full).unwrap();
    one.set_occupancy(Some(grid.clone())).unwrap();
    let whole = one.render(&cam, 0.4, &params).unwrap();
    assert_eq!(one.batch_rays(), Some(cam.width * cam.height));
    for kib in [24u64, 56] {
        one.set_scratch_budget(kib << 10);
        let f = one.render(&cam, 0.4, &params).unwrap();
        let batch = one.batch_rays().unwrap();
        eprintln!("{kib} KiB of scratch: batches of {batch} rays");
        assert!(batch > 0 && batch * 3 < cam.width * cam.height, "{batch}");
        assert_eq!(
            max_diff(&whole, &f),
            0.0,
            "{kib} KiB batches ({batch} rays)"
        );
    }
    // A budget below one ray's scratch is a clear error.
    one.set_scratch_budget(16);
    let e = one.render(&cam, 0.4, &params).err().unwrap();
    assert!(e.to_string().contains("scratch budget"), "{e}");
    eprintln!("{e}");
    let mut plain = Renderer::new(&cfg, full);
    let mut skipping = GpuRenderer::new(context(), &cfg, full).unwrap();
    skipping.set_occupancy(Some(grid)).unwrap();
    let a = plain.render(&cam, 0.4, &params);
    let b = skipping.render(&cam, 0.4, &params).unwrap();
    assert!(max_diff(&a, &b) > 0.05, "the grid changed nothing");
    // No grid: every sample again.
    skipping.set_occupancy(None).unwrap();
    let b = skipping.render(&cam, 0.4, &params).unwrap();
    let d = max_diff(&a, &b);
    assert!(d < 2e-3, "without a grid: max difference {d}");
    // A grid of the wrong size is an error, not a panic.
    let bad = msth_codec::OccupancyGrid {
        words: vec![0; 3],
        ..msth_codec::OccupancyGrid::full(8)
    };
    let e = skipping
        .set_occupancy(Some(std::sync::Arc::new(bad)))
        .err()
        .unwrap();
    assert!(e.to_string().contains("occupancy grid"), "{e}");
}

/// PSNR (dB) of two frames.
fn psnr(a: &Frame, b: &Frame) -> f64 {
    let mse = a
        .rgb
        .iter()
        .zip(&b.rgb)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.rgb.len().max(1) as f64;
    -10.0 * mse.max(1e-20).log10()
}

/// A model whose mask is dynamic around the centre of the scene and static elsewhere.
fn centre_dynamic(cfg: &ModelConfig, params: &mut [f32]) {
    let layout = ModelLayout::new(cfg);
    let (grid, r) = layout.field.encoding.mask.clone().unwrap();
    let res = grid.res;
    for (k, v) in params[r].iter_mut().enumerate() {
        let (x, y, z) = (k % res, (k / res) % res, k / (res * res));
        let centre = |c: usize| (res / 3..=2 * res / 3).contains(&c);
        *v = if centre(x) && centre(y) && centre(z) {
            -3.0
        } else {
            9.0
        };
    }
}

fn test_camera(w: u32, h: u32) -> Camera {
    Camera::look_at(
        w,
        h,
        0.9,
        glam::Vec3::new(0.3, -3.5, 1.2),
        glam::Vec3::ZERO,
        glam::Vec3::Z,
    )
}

/// Sample-level reuse on the device follows the CPU renderer's: the same classification, the
/// same fixed samples, the same static/dynamic split; frames within float rounding of the CPU's
/// incremental frames and close to full renders.
fn gpu_sample_reuse_matches_cpu_sample_reuse() {
    let mut cfg = config(BlendMode::Mt);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let mut params = random_params(&layout, 5);
    centre_dynamic(&cfg, &mut params);
    let settings = RenderSettings {
        probes: 0,
        ..Default::default()
    };
    assert_eq!(settings.reuse, Reuse::Samples);
    let mut cpu = Renderer::new(&cfg, settings);
    let mut gpu = GpuRenderer::new(context(), &cfg, settings).unwrap();
    let mut full = Renderer::new(
        &cfg,
        RenderSettings {
            incremental: false,
            ..settings
        },
    );
    let cam = test_camera(40, 30);
    let first = full.render(&cam, 0.0, &params);
    for (i, t) in [0.0f32, 0.3, 0.9].into_iter().enumerate() {
        let a = cpu.render(&cam, t, &params);
        let b = gpu.render(&cam, t, &params).unwrap();
        assert_eq!(a.stats.full, i == 0);
        assert_eq!(b.stats.full, i == 0);
        assert_eq!(a.stats.rays_rendered, b.stats.rays_rendered, "frame {i}");
        let d = max_diff(&a, &b);
        let g = full.render(&cam, t, &params);
        println!(
            "frame {i}: GPU vs CPU incremental max {d:.2e}, {:.1} dB; vs CPU full {:.1} dB; {} samples evaluated (CPU {})",
            psnr(&a, &b),
            psnr(&b, &g),
            b.stats.samples_evaluated,
            a.stats.samples_evaluated
        );
        assert!(d < 2e-3, "frame {i}: max difference {d}");
        assert!(psnr(&b, &g) >= 40.0, "frame {i}: {:.1} dB", psnr(&b, &g));
        if i > 0 {
            assert_eq!(a.stats.samples_evaluated, b.stats.samples_evaluated);
            assert!(b.stats.samples_evaluated > 0);
            // The frame does move with time, and the incremental frame follows it.
            assert!(max_diff(&first, &g) > 5e-3);
        }
    }
    let f = gpu.dynamic_fraction().unwrap();
    assert!(f > 0.0 && f < 1.0, "dynamic fraction {f}");
}

/// A `balanced`-preset model with random tables (the MLPs as initialised) whose mask is dynamic
/// around the centre.
fn balanced_model(seed: u64) -> (ModelConfig, Vec<f32>) {
    let cfg = ModelConfig::preset(
        Preset::Balanced,
        SceneBounds::dnerf_default(),
        Background::Color { rgb: [1.0; 3] },
        30,
    );
    let layout = ModelLayout::new(&cfg);
    let mut params = random_params(&layout, seed);
    centre_dynamic(&cfg, &mut params);
    (cfg, params)
}

/// A `balanced`-preset model: full and incremental GPU frames against the CPU renderer's.
fn balanced_preset_frames_match_the_cpu_full_and_incremental() {
    let (cfg, params) = balanced_model(3);
    let cam = test_camera(32, 24);
    for reuse in [Reuse::Rays, Reuse::Samples] {
        let settings = RenderSettings {
            probes: 0,
            reuse,
            ..Default::default()
        };
        let mut cpu = Renderer::new(&cfg, settings);
        let mut gpu = GpuRenderer::new(context(), &cfg, settings).unwrap();
        for (i, t) in [0.0f32, 0.5, 1.0].into_iter().enumerate() {
            let a = cpu.render(&cam, t, &params);
            let b = gpu.render(&cam, t, &params).unwrap();
            assert_eq!(b.stats.full, i == 0);
            let p = psnr(&a, &b);
            println!(
                "balanced {reuse:?} frame {i}: {p:.1} dB, max {:.2e}, {} rays rendered, {} samples",
                max_diff(&a, &b),
                b.stats.rays_rendered,
                b.stats.samples_evaluated
            );
            assert!(p >= 40.0, "{reuse:?} frame {i}: {p:.1} dB");
            assert_eq!(a.stats.rays_rendered, b.stats.rays_rendered);
        }
    }
    // Fewer samples per ray (`msth play --samples faster`, the page's samples menu): the GPU
    // renders the model with the CPU's counts, and the frame is not the full-samples one.
    // Counts that are no multiple of the passes' 4 samples per invocation as well.
    let settings = RenderSettings {
        incremental: false,
        ..Default::default()
    };
    let full = Renderer::new(&cfg, settings).render(&cam, 0.5, &params);
    for (samples, counts) in [
        (PlaySamples::Level(SampleLevel::Faster), (48, 16)),
        (PlaySamples::Level(SampleLevel::Fast), (64, 24)),
        (PlaySamples::Counts(33, 18), (33, 18)),
        (PlaySamples::Counts(7, 5), (7, 5)),
        // The extreme: one sample of each (no NaN, the same frame on both).
        (PlaySamples::Counts(1, 1), (1, 1)),
    ] {
        let fewer = samples.apply(&cfg, None, 1024, 512).unwrap();
        let s = &fewer.sampler;
        assert_eq!((s.num_proposal_samples, s.num_samples), counts);
        let a = Renderer::new(&fewer, settings).render(&cam, 0.5, &params);
        let b = GpuRenderer::new(context(), &fewer, settings)
            .unwrap()
            .render(&cam, 0.5, &params)
            .unwrap();
        let (p, p_full) = (psnr(&a, &b), psnr(&a, &full));
        println!(
            "balanced, samples {counts:?}: {p:.1} dB against the CPU (max {:.2e}), {p_full:.1} dB against full samples",
            max_diff(&a, &b)
        );
        assert!(p >= 40.0, "samples {counts:?}: {p:.1} dB");
        assert!(max_diff(&a, &full) > 1e-3 && p_full < p, "{p_full:.1} dB");
    }
}

/// The passes compiled for the model (`msth_gpu::specialise`: encodings and MLPs, the default)
/// and the generic ones render the same frames as the CPU, full and incremental (the sample
/// cache's dynamic samples go through them too), for every blend; a model outside the
/// specialiser's limits, or a shader the device refuses, keeps the generic passes and says why;
/// new MLP weights are compiled anew, not rendered with the old.
fn specialised_and_generic_kernels_render_the_same_frames() {
    let (cfg, params) = balanced_model(5);
    let layout = ModelLayout::new(&cfg);
    let cam = test_camera(32, 24);
    let settings = RenderSettings {
        probes: 0,
        reuse: Reuse::Samples,
        ..Default::default()
    };
    let mut cpu = Renderer::new(&cfg, settings);
    let mut spec = GpuRenderer::new(context(), &cfg, settings).unwrap();
    let mut generic = GpuRenderer::new(context(), &cfg, settings).unwrap();
    generic.set_mlps(GpuMlps::Generic);
    for (i, t) in [0.0f32, 0.5, 1.0].into_iter().enumerate() {
        let a = cpu.render(&cam, t, &params);
        let b = spec.render(&cam, t, &params).unwrap();
        let c = generic.render(&cam, t, &params).unwrap();
        let (pb, pc, pbc) = (psnr(&a, &b), psnr(&a, &c), psnr(&b, &c));
        println!(
            "balanced frame {i} ({}): specialised {pb:.1} dB, generic {pc:.1} dB against the CPU; {pbc:.1} dB between them (max {:.2e}); {} samples evaluated",
            if i == 0 { "full" } else { "incremental" },
            max_diff(&b, &c),
            b.stats.samples_evaluated
        );
        assert!(pb >= 40.0 && pc >= 40.0 && pbc >= 40.0);
        assert_eq!(b.stats.samples_evaluated, c.stats.samples_evaluated);
    }
    assert!(
        matches!(spec.mlp_status(), MlpStatus::Specialised(_)),
        "{}",
        spec.mlp_status()
    );
    assert_eq!(generic.mlp_status(), &MlpStatus::Generic);
    assert!(spec
        .mlp_status()
        .to_string()
        .starts_with("kernels compiled for this model"));

    // Another model's MLP weights on the same renderer (the same layout): compiled anew.
    let mut other = params.clone();
    let (_, r) = layout.field.color.clone();
    let mut rng = Rng::new(11);
    for v in &mut other[r] {
        *v = rng.range_f32(-0.3, 0.3);
    }
    let full = RenderSettings {
        incremental: false,
        ..Default::default()
    };
    let mut cpu = Renderer::new(&cfg, full);
    let mut spec = GpuRenderer::new(context(), &cfg, full).unwrap();
    let first = spec.render(&cam, 0.5, &params).unwrap();
    let a = cpu.render(&cam, 0.5, &other);
    let b = spec.render(&cam, 0.5, &other).unwrap();
    println!(
        "new colour weights: {:.1} dB against the CPU, {:.1} dB against the old weights' frame",
        psnr(&a, &b),
        psnr(&first, &b)
    );
    assert!(psnr(&a, &b) >= 40.0);
    assert!(psnr(&first, &b) < 40.0);
    assert!(matches!(spec.mlp_status(), MlpStatus::Specialised(_)));

    // Every blend (the specialised encodings drop the lookups a blend does not make), and one
    // feature per level.
    for blend in BlendMode::ALL {
        let counts: &[usize] = if blend == BlendMode::Mst {
            &[2, 1]
        } else {
            &[2]
        };
        for &features in counts {
            let mut c = config(blend);
            small(&mut c);
            for g in [&mut c.field.encoding.grid3, &mut c.field.encoding.grid4] {
                g.features_per_level = features;
            }
            let layout = ModelLayout::new(&c);
            let mut params = random_params(&layout, 9);
            if layout.field.encoding.mask.is_some() {
                centre_dynamic(&c, &mut params);
            }
            let mut gpu = GpuRenderer::new(context(), &c, full).unwrap();
            let b = gpu.render(&cam, 0.5, &params).unwrap();
            let a = Renderer::new(&c, full).render(&cam, 0.5, &params);
            println!(
                "{blend:?}, {features} feature(s) per level: {:.1} dB against the CPU; {}",
                psnr(&a, &b),
                gpu.mlp_status()
            );
            assert!(psnr(&a, &b) >= 40.0, "{blend:?}");
            assert!(matches!(gpu.mlp_status(), MlpStatus::Specialised(_)));
        }
    }

    // A colour layer of 128 inputs: the generic passes, and the reason.
    let mut wide = config(BlendMode::Mst);
    small(&mut wide);
    wide.field.color_hidden = 128;
    wide.field.color_layers = 1;
    let layout = ModelLayout::new(&wide);
    let params = random_params(&layout, 6);
    let mut gpu = GpuRenderer::new(context(), &wide, full).unwrap();
    let b = gpu.render(&cam, 0.5, &params).unwrap();
    let a = Renderer::new(&wide, full).render(&cam, 0.5, &params);
    let status = gpu.mlp_status().to_string();
    println!(
        "128-wide colour layer: {status}; {:.1} dB against the CPU",
        psnr(&a, &b)
    );
    assert_eq!(
        status,
        "generic kernels (an MLP layer has 128 inputs; at most 64 are specialised)"
    );
    assert!(psnr(&a, &b) >= 40.0);

    // A device that refuses the specialised shader (here: a source whose generic kernels call a
    // renamed `blend_of`, which the generated encodings still call): the generic kernels render,
    // and the status says why.
    let mut c = config(BlendMode::Mst);
    small(&mut c);
    let layout = ModelLayout::new(&c);
    let params = random_params(&layout, 10);
    let source = msth_player::gpu::RENDER_WGSL.replace("blend_of", "blend_of_generic");
    let ctx = GpuContext::open_with_source(AdapterPolicy::any(), &source).unwrap();
    let mut gpu = GpuRenderer::new(ctx, &c, full).unwrap();
    let b = gpu.render(&cam, 0.5, &params).unwrap();
    let a = Renderer::new(&c, full).render(&cam, 0.5, &params);
    let status = gpu.mlp_status().to_string();
    println!(
        "a refused shader: {status}; {:.1} dB against the CPU",
        psnr(&a, &b)
    );
    assert!(
        status.starts_with("generic kernels (compiling them for the model failed: ")
            && status.contains("blend_of"),
        "{status}"
    );
    assert!(psnr(&a, &b) >= 40.0);
}

/// Probes render with the parameters of their own time (a file streamed in chunks): a still
/// first chunk caches every ray; another chunk's table at the probe times makes rays dynamic.
fn probes_render_with_the_parameters_of_their_time_on_the_gpu() {
    let mut cfg = config(BlendMode::Mt);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let mut params = random_params(&layout, 8);
    let (_, r) = layout.field.encoding.mask.clone().unwrap();
    params[r].fill(3.0);
    // Nothing depends on time in this chunk: no 4D features in the field or the proposal.
    let p4 = layout.params.get("proposal.h4").unwrap().range();
    params[p4].fill(0.0);
    let (_, h4) = layout.field.encoding.h4.clone().unwrap();
    params[h4.clone()].fill(0.0);
    let mut other = params.clone();
    let mut rng = Rng::new(4);
    for v in &mut other[h4] {
        *v = rng.range_f32(-3.0, 3.0);
    }
    let settings = RenderSettings {
        reuse: Reuse::Rays,
        probe_tolerance: 1.0 / 255.0,
        // Probe every static ray (this test is about the probes' parameters).
        trust_threshold: 2.0,
        ..Default::default()
    };
    let cam = test_camera(24, 16);
    let second = |provider: &mut dyn FnMut(f32) -> Option<Vec<f32>>| {
        let mut g = GpuRenderer::new(context(), &cfg, settings).unwrap();
        g.render(&cam, 0.0, &params).unwrap();
        g.render_probing(&cam, 0.0, &params, provider)
            .unwrap()
            .stats
    };
    assert_eq!(second(&mut |_| None).rays_rendered, 0);
    let chunked = second(&mut |t| (t > 0.0).then(|| other.clone()));
    assert!(chunked.rays_rendered > 0, "probes ignored the other chunk");
}

/// A renderer that gets one parameter buffer after another renders each as a fresh renderer
/// does, whichever part changed (the 4D table of a new time chunk, the 3D table, an MLP weight:
/// `GpuScene::update` uploads the parts that differ); with versions
/// (`GpuRenderer::set_params_version`) a new version uploads, and the same version trusts the
/// device's copy without comparing.
fn new_parameters_upload_what_changed_and_versions_skip_the_comparison() {
    let mut cfg = config(BlendMode::Mt);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let a = random_params(&layout, 11);
    let (_, h4) = layout.field.encoding.h4.clone().unwrap();
    let (_, h3) = layout.field.encoding.h3.clone().unwrap();
    let mut rng = Rng::new(12);
    let mut b = a.clone(); // a new chunk: the field's 4D table alone
    for v in &mut b[h4] {
        *v = rng.range_f32(-1.0, 1.0);
    }
    let mut c = b.clone(); // the 3D table
    for v in &mut c[h3] {
        *v = rng.range_f32(-1.0, 1.0);
    }
    let mut d = c.clone(); // a colour MLP weight: the specialised kernels are compiled again
    let colour = layout.params.get("field.color_mlp").unwrap().range();
    d[colour.start] += 0.5;
    let mut e = d.clone(); // the proposal field's 4D table (read from the table buffers)
    let p4 = layout.params.get("proposal.h4").unwrap().range();
    for v in &mut e[p4] {
        *v = rng.range_f32(-1.0, 1.0);
    }
    let full = RenderSettings {
        incremental: false,
        ..Default::default()
    };
    let cam = test_camera(24, 16);
    let fresh = |p: &[f32]| {
        GpuRenderer::new(context(), &cfg, full)
            .unwrap()
            .render(&cam, 0.3, p)
            .unwrap()
    };
    let expected: Vec<Frame> = [&a, &b, &c, &d, &e].map(|p| fresh(p)).into();
    for w in expected.windows(2) {
        assert!(
            max_diff(&w[0], &w[1]) > 0.0,
            "a change rendered nothing new"
        );
    }
    let mut r = GpuRenderer::new(context(), &cfg, full).unwrap();
    for (i, p) in [&a, &b, &c, &d, &e, &a].into_iter().enumerate() {
        let f = r.render(&cam, 0.3, p).unwrap();
        assert_eq!(max_diff(&f, &expected[i % 5]), 0.0, "buffer {i}");
    }
    // Versions: a new one uploads; the same one renders the device's copy, whatever is passed.
    let mut r = GpuRenderer::new(context(), &cfg, full).unwrap();
    r.set_params_version(1);
    assert_eq!(
        max_diff(&r.render(&cam, 0.3, &a).unwrap(), &expected[0]),
        0.0
    );
    r.set_params_version(2);
    assert_eq!(
        max_diff(&r.render(&cam, 0.3, &b).unwrap(), &expected[1]),
        0.0
    );
    let trusted = r.render(&cam, 0.3, &e).unwrap();
    assert_eq!(
        max_diff(&trusted, &expected[1]),
        0.0,
        "the same version compared anyway"
    );
    r.set_params_version(3);
    assert_eq!(
        max_diff(&r.render(&cam, 0.3, &e).unwrap(), &expected[4]),
        0.0
    );
    // Incremental playback across a chunk change, its probes uploading another time's
    // parameters and then the frame's again: with versions as without.
    let settings = RenderSettings {
        reuse: Reuse::Rays,
        trust_threshold: 2.0,
        ..Default::default()
    };
    let mut plain = GpuRenderer::new(context(), &cfg, settings).unwrap();
    let mut versioned = GpuRenderer::new(context(), &cfg, settings).unwrap();
    let frames = [
        (0.0f32, &a, 1u64),
        (0.2, &a, 1),
        (0.5, &b, 2),
        (0.7, &b, 2),
        (0.9, &a, 3),
    ];
    let mut rendered = 0;
    for (i, &(t, p, v)) in frames.iter().enumerate() {
        let mut probe = |pt: f32| (pt > 0.45).then(|| b.clone());
        let x = plain.render_probing(&cam, t, p, &mut probe).unwrap();
        versioned.set_params_version(v);
        let y = versioned.render_probing(&cam, t, p, &mut probe).unwrap();
        assert_eq!(x.stats.full, y.stats.full, "frame {i}");
        assert_eq!(x.stats.rays_rendered, y.stats.rays_rendered, "frame {i}");
        assert_eq!(max_diff(&x, &y), 0.0, "incremental frame {i}");
        rendered += usize::from(!x.stats.full);
    }
    assert!(rendered > 0, "no incremental frame");
}

/// `params` with every hash-table value the kernels read (both fields' 3D and 4D tables) as
/// `format` holds it.
fn tables_rounded(cfg: &ModelConfig, params: &[f32], format: TableFormat) -> Vec<f32> {
    let split = GpuModel::new(cfg).unwrap().split;
    let mut p = params.to_vec();
    for (_, _, r) in split.tables().into_iter().flatten() {
        for v in &mut p[r] {
            *v = format.round(*v);
        }
    }
    p
}

/// Hash tables held as binary16 (`TableFormat::F16`, what `msth play` uses for quantised files)
/// render the frames the f32 kernels render from tables rounded to binary16 on the host (bit for
/// bit on lavapipe):
/// the packing (pairs in one word, one-feature rows half a word, the proposal
/// field's tables after the field's, values beyond binary16's range clamped) and the kernels'
/// unpacking agree, full and incremental, specialised and generic. Against the CPU renderer
/// with the unrounded tables they stay within 40 dB, for the `balanced` preset too.
fn binary16_tables_render_the_frames_of_rounded_tables() {
    let half = || GpuContext::open_with_tables(AdapterPolicy::any(), TableFormat::F16).unwrap();
    assert_eq!(half().tables(), TableFormat::F16);
    assert_eq!(context().tables(), TableFormat::F32);
    let exact = context().is_lavapipe();
    let cam = test_camera(33, 21);
    for features in [2, 1, 4] {
        let mut cfg = config(BlendMode::Mst);
        small(&mut cfg);
        for enc in [&mut cfg.field.encoding, &mut cfg.proposal.encoding] {
            enc.grid3.features_per_level = features;
            enc.grid4.features_per_level = features;
        }
        let layout = ModelLayout::new(&cfg);
        let mut params = random_params(&layout, 21);
        centre_dynamic(&cfg, &mut params);
        // Values beyond binary16's range (largest finite 65504) and below its normal range.
        let split = GpuModel::new(&cfg).unwrap().split;
        for (i, v) in [(3, 1e6), (8, -3e38), (13, 1e-6), (20, -7e-8)] {
            params[split.tab3.start + i] = v;
            params[split.tab4.start + i] = v;
        }
        let rounded = tables_rounded(&cfg, &params, TableFormat::F16);
        assert_eq!(rounded[split.tab3.start + 3], 65504.0);
        assert_eq!(rounded[split.tab4.start + 8], -65504.0);
        for (incremental, mlps) in [
            (false, GpuMlps::Specialised),
            (false, GpuMlps::Generic),
            (true, GpuMlps::Specialised),
        ] {
            let settings = RenderSettings {
                incremental,
                probes: 0,
                ..Default::default()
            };
            let mut a = GpuRenderer::new(half(), &cfg, settings).unwrap();
            let mut b = GpuRenderer::new(context(), &cfg, settings).unwrap();
            a.set_mlps(mlps);
            b.set_mlps(mlps);
            for t in [0.0, 0.4, 0.9] {
                let fa = a.render(&cam, t, &params).unwrap();
                let fb = b.render(&cam, t, &rounded).unwrap();
                let what =
                    format!("{features} features, incremental {incremental}, {mlps:?}, t = {t}");
                assert_eq!(fa.stats.rays_rendered, fb.stats.rays_rendered, "{what}");
                // Bit for bit where the two kernel texts compile alike (lavapipe: no fused
                // multiply-adds); another driver may schedule the two texts' arithmetic apart.
                let d = max_diff(&fa, &fb);
                assert!(if exact { d == 0.0 } else { d < 1e-4 }, "{what}: {d}");
                // And the rounding shows: the f32 kernels with the unrounded tables differ.
                if t == 0.0 && !incremental {
                    let mut c = GpuRenderer::new(context(), &cfg, settings).unwrap();
                    c.set_mlps(mlps);
                    let fc = c.render(&cam, t, &params).unwrap();
                    assert!(max_diff(&fa, &fc) > 0.0, "{what}");
                }
            }
            // The device holds 1e6 and -3e38 clamped in each field table, and says so; the f32
            // renderer (given the rounded tables) holds nothing clamped.
            assert_eq!(a.clamped_table_values(), 4, "{features} features");
            assert_eq!(b.clamped_table_values(), 0, "{features} features");
        }
    }
    let (cfg, params) = balanced_model(5);
    let cam = test_camera(32, 24);
    for incremental in [false, true] {
        let settings = RenderSettings {
            incremental,
            probes: 0,
            ..Default::default()
        };
        let mut cpu = Renderer::new(&cfg, settings);
        let mut gpu = GpuRenderer::new(half(), &cfg, settings).unwrap();
        for t in [0.0f32, 0.5, 1.0] {
            let a = cpu.render(&cam, t, &params);
            let b = gpu.render(&cam, t, &params).unwrap();
            let p = psnr(&a, &b);
            println!(
                "balanced, binary16 tables, incremental {incremental}, t = {t}: {p:.1} dB against the CPU (max {:.2e})",
                max_diff(&a, &b)
            );
            assert!(p >= 40.0, "incremental {incremental}, t = {t}: {p:.1} dB");
        }
        assert_eq!(gpu.clamped_table_values(), 0);
    }
}

/// `play` of a quantised file whose field tables hold values beyond binary16's range: the GPU
/// renderer holds the tables as f16 by default and reports how many values it clamped; with
/// `gpu_tables` f32 it clamps none.
fn playback_reports_table_values_binary16_clamps() {
    let mut cfg = config(BlendMode::Mst);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let mut params = random_params(&layout, 4);
    let split = GpuModel::new(&cfg).unwrap().split;
    // Beyond ±65504 in the 3D table and in the 4D table.
    for (at, v) in [
        (split.tab3.start + 5, 2e5),
        (split.tab3.start + 40, -1e6),
        (split.tab4.start + 9, 3e5),
    ] {
        params[at] = v;
    }
    let cam = test_camera(12, 8);
    let opts = msth_codec::EncodeOptions {
        quant: msth_codec::QuantMode::Q8,
        ..Default::default()
    };
    let (bytes, _) = msth_codec::encode(&cfg, &params, &[cam], &opts).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("wide.msth");
    std::fs::write(&file, &bytes).unwrap();
    // What the decoded file holds beyond the range (q8 keeps each block's extremes).
    let decoded = msth_codec::decode_all(&bytes).unwrap().params_for_time(0.0);
    let wide = TableFormat::F16.clamped(&decoded[split.tab3.clone()])
        + TableFormat::F16.clamped(&decoded[split.tab4.clone()]);
    assert!(wide >= 3, "{wide}");
    for (tables, want) in [(None, wide), (Some(TableFormat::F32), 0)] {
        let mut o = msth_player::PlayOptions::new(file.to_str().unwrap());
        o.backend = msth_player::BackendChoice::Gpu;
        o.frames = Some(2);
        o.size = Some((12, 8));
        o.video = false;
        o.gpu_tables = tables;
        let report = msth_player::play(&o, &mut |_, _| {}).unwrap();
        let expected = if tables.is_none() { "f16" } else { "f32" };
        assert_eq!(report.backend.tables, Some(expected));
        assert_eq!(report.backend.tables_clamped, want, "{tables:?}");
    }
}

/// The per-sample passes compiled for 1, 2 and 4 samples per invocation render the same frames,
/// full (the live lists split by the mask, with an occupancy grid) and incremental (the sample
/// cache's `pass_build` and `pass_dynamic`), specialised and generic; other counts are clear
/// errors.
fn every_lane_count_renders_the_same_frames() {
    let (cfg, params) = balanced_model(5);
    let r = 16u32;
    let mut grid = msth_codec::OccupancyGrid::full(r);
    for i in 0..(r * r * r) as usize {
        // Clear every cell with x < r / 4.
        if (i as u32 % r) < r / 4 {
            grid.words[i / 32] &= !(1u32 << (i % 32));
        }
    }
    let grid = std::sync::Arc::new(grid);
    // 37 x 23 pixels: lists whose lengths are rarely a multiple of 4.
    let cam = test_camera(37, 23);
    let settings = RenderSettings {
        probes: 0,
        reuse: Reuse::Samples,
        ..Default::default()
    };
    let mut cpu = Renderer::new(&cfg, settings);
    cpu.set_occupancy(Some(grid.clone()));
    let times = [0.0f32, 0.5, 1.0];
    let cpu_frames: Vec<Frame> = times
        .iter()
        .map(|&t| cpu.render(&cam, t, &params))
        .collect();
    let render = |lanes: u32, mlps: GpuMlps| -> Vec<Frame> {
        let ctx =
            GpuContext::open_with_kernels(AdapterPolicy::any(), TableFormat::F32, Some(lanes))
                .unwrap();
        assert_eq!(ctx.lanes(), lanes);
        let mut gpu = GpuRenderer::new(ctx, &cfg, settings).unwrap();
        gpu.set_mlps(mlps);
        gpu.set_occupancy(Some(grid.clone())).unwrap();
        let frames: Vec<Frame> = times
            .iter()
            .map(|&t| gpu.render(&cam, t, &params).unwrap())
            .collect();
        assert_eq!(
            matches!(gpu.mlp_status(), MlpStatus::Specialised(_)),
            mlps == GpuMlps::Specialised
        );
        frames
    };
    for mlps in [GpuMlps::Specialised, GpuMlps::Generic] {
        let four = render(4, mlps);
        for lanes in [1u32, 2] {
            let other = render(lanes, mlps);
            for (i, ((a, b), c)) in four.iter().zip(&other).zip(&cpu_frames).enumerate() {
                let d = max_diff(a, b);
                println!(
                    "{mlps:?}, {lanes} lane(s), frame {i} ({}): max difference {d:.2e} from 4 lanes; {:.1} dB against the CPU",
                    if b.stats.full { "full" } else { "incremental" },
                    psnr(c, b)
                );
                assert!(d <= 1e-5, "{lanes} lanes, frame {i}: {d}");
                assert_eq!(a.stats.samples_evaluated, b.stats.samples_evaluated);
                assert!(psnr(c, b) >= 40.0);
            }
        }
    }
    for bad in [0u32, 3, 8] {
        let e = GpuContext::open_with_kernels(AdapterPolicy::any(), TableFormat::F32, Some(bad))
            .err()
            .unwrap();
        assert!(e.to_string().contains("1, 2 or 4"), "{e}");
    }
}

/// A volume of `cfg` baked on the host (the players' bake), its colours facing `cam`.
fn baked_volume(
    cfg: &ModelConfig,
    params: &[f32],
    cam: &Camera,
    colour: msth_core::volume::ColourMode,
) -> msth_player::volume::BakedVolume {
    use msth_player::volume::{plan_bake, VolumeOptions};
    let options = VolumeOptions {
        max_resolution: Some(64),
        colour,
        ..Default::default()
    };
    let plan = plan_bake(cfg, params, None, &[*cam], &options).unwrap();
    bake_planned(cfg, params, plan)
}

/// The volume `plan` baked on the host.
fn bake_planned(
    cfg: &ModelConfig,
    params: &[f32],
    plan: msth_core::volume::BakePlan,
) -> msth_player::volume::BakedVolume {
    use msth_player::volume::{bake, BakedVolume};
    let layout = ModelLayout::new(cfg);
    let volume = bake(
        &plan,
        cfg,
        &layout,
        params,
        &msth_core::volume::BakeProgress::default(),
    )
    .unwrap();
    BakedVolume {
        volume,
        plan: std::sync::Arc::new(plan),
    }
}

/// The device's bake (`eval_points` kinds 2 and 3) holds the host's values and cell bits, and the
/// GPU's march (`volume.wgsl`) draws the CPU's march frames (msth-core `volume::march`)
/// from the same static bake, each renderer baking its own time slices (the GPU on the device):
/// box and contracted scenes, constant and last-sample
/// backgrounds, static and dynamic bricks, at slice times and between them, from the camera the
/// colours were baked for and from another. Both march the same steps; a step whose midpoint
/// lies within rounding of a cell's face could skip on one and not the other on some device, so
/// the frames are compared by PSNR and a bound on the largest difference (lavapipe draws the
/// CPU's frames to 1e-5: over 125 dB), while the frames move with time by more than 4e-3 (0.006-0.07 measured).
fn volume_frames_on_the_gpu_match_the_cpu_march() {
    let scenes = [
        (
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
        ),
        (
            SceneBounds::Contracted {
                center: glam::Vec3::ZERO,
                radius: 1.0,
            },
            Background::LastSample,
        ),
    ];
    for (bounds, background) in scenes {
        let mut cfg = config(BlendMode::Mst);
        cfg.bounds = bounds;
        cfg.background = background;
        let defaults = ModelConfig::preset(Preset::Fast, bounds, background, 10);
        cfg.sampler = defaults.sampler;
        small(&mut cfg);
        let layout = ModelLayout::new(&cfg);
        let mut params = random_params(&layout, 11);
        centre_dynamic(&cfg, &mut params);
        // A 4D grid that moves the dynamic bricks' colours and densities visibly with time.
        let (_, h4) = layout.field.encoding.h4.clone().unwrap();
        for v in &mut params[h4] {
            *v *= 6.0;
        }
        let cam = test_camera(48, 36);
        let vol = baked_volume(&cfg, &params, &cam, msth_core::volume::ColourMode::Baked);
        assert!(vol.volume.has_dynamic(), "{bounds:?}: no dynamic brick");
        // The GPU renderer reads baked slices for every frame: so must the CPU's frames it is
        // compared with.
        let settings = RenderSettings {
            exact: false,
            incremental: false,
            slices: msth_player::SlicePolicy::Always,
            ..Default::default()
        };
        let mut cpu = Renderer::new(&cfg, settings);
        cpu.set_volume(Some(vol.clone()));
        let mut gpu = GpuRenderer::new(context(), &cfg, settings).unwrap();
        // Baked on the device, as on a hardware adapter: the static bricks' values and cell
        // bits are the host's.
        gpu.set_device_bake(true);
        let on_device = gpu
            .bake_on_device(vol.plan.clone(), &params)
            .expect("the device bakes")
            .unwrap();
        let host = &vol.volume;
        assert_eq!(on_device.volume.index, host.index);
        assert_eq!(
            on_device.volume.occupied, host.occupied,
            "{bounds:?}: cell bits"
        );
        let d = on_device
            .volume
            .values
            .iter()
            .zip(&host.values)
            .map(|(a, b)| (a.to_f32() - b.to_f32()).abs() / b.to_f32().abs().max(1.0))
            .fold(0f32, f32::max);
        // Equal to 1e-4 before the rounding to binary16, so at most one binary16 step (2^-10
        // relative) apart after it.
        assert!(
            d <= 1e-4 + 2f32.powi(-10),
            "{bounds:?}: baked values differ by {d}"
        );
        // The host's static bake from here on; the slices baked on the device.
        gpu.set_volume(Some(vol)).unwrap();
        assert!(gpu.uses_volume());
        let other = Camera::look_at(
            40,
            30,
            0.8,
            glam::Vec3::new(-2.5, -2.0, 1.5),
            glam::Vec3::new(0.1, 0.0, 0.0),
            glam::Vec3::Z,
        );
        for camera in [cam, other] {
            let mut first: Option<Frame> = None;
            for t in [0.0f32, 0.37, 0.5, 1.0] {
                let a = cpu.render(&camera, t, &params);
                let b = gpu.render(&camera, t, &params).unwrap();
                assert!(
                    a.stats.volume && b.stats.volume,
                    "t={t}: not from the volume"
                );
                assert!(a.stats.volume_samples > 0, "t={t}: nothing drawn");
                match &first {
                    None => first = Some(a.clone()),
                    // The dynamic bricks show: the frame moves with time.
                    Some(f) => {
                        let moved = max_diff(f, &a);
                        println!("t={t}: max change since t=0 {moved:.4}");
                        assert!(moved > 4e-3, "t={t}: the frame moved by {moved} only");
                    }
                }
                let p = psnr(&a, &b);
                let d = max_diff(&a, &b);
                println!("{bounds:?} t={t}: GPU against CPU march {p:.1} dB, max {d:.4}");
                assert!(p >= 70.0, "{bounds:?} t={t}: {p:.1} dB");
                assert!(d < 0.01, "{bounds:?} t={t}: max difference {d}");
            }
        }
        // The exact switch draws from the field again, on both.
        gpu.set_exact(true);
        cpu.set_exact(true);
        let a = cpu.render(&cam, 0.5, &params);
        let b = gpu.render(&cam, 0.5, &params).unwrap();
        assert!(!a.stats.volume && !b.stats.volume);
        assert!(max_diff(&a, &b) < 2e-3);
    }
}

/// The CPU and GPU renderers drawing full frames from `vol`, its slices baked before the
/// first frame that needs them.
fn volume_renderers(
    cfg: &ModelConfig,
    vol: msth_player::volume::BakedVolume,
) -> (Renderer, GpuRenderer) {
    let settings = RenderSettings {
        exact: false,
        incremental: false,
        slices: msth_player::SlicePolicy::Always,
        ..Default::default()
    };
    let mut cpu = Renderer::new(cfg, settings);
    cpu.set_volume(Some(vol.clone()));
    let mut gpu = GpuRenderer::new(context(), cfg, settings).unwrap();
    gpu.set_volume(Some(vol)).unwrap();
    (cpu, gpu)
}

/// The finest volume, `2048^3` in bricks of `16^3` cells (`--volume-resolution 2048`), over one
/// occupied cell of a `64^3` occupancy grid: `volume.wgsl` draws what the CPU's march draws.
fn the_finest_volume_draws_on_the_gpu_as_on_the_cpu() {
    use msth_core::volume::bake::{plan_with, PlanOptions};
    use msth_core::volume::Occupancy;
    let mut cfg = config(BlendMode::Mst);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let params = random_params(&layout, 7);
    let mut words = vec![0u32; 64 * 64 * 64 / 32];
    let cell = 32 + 64 * (32 + 64 * 32);
    words[cell / 32] |= 1 << (cell % 32);
    let options = PlanOptions {
        budget: 64 << 20,
        max_resolution: Some(2048),
        min_proposal_alpha: 0.0,
        ..Default::default()
    };
    let occupancy = Occupancy {
        resolution: 64,
        words: &words,
        density_threshold: 1e-3,
    };
    let plan = plan_with(&cfg, &layout, &params, Some(occupancy), &options).unwrap();
    assert_eq!((plan.geometry.resolution, plan.geometry.brick), (2048, 16));
    let vol = bake_planned(&cfg, &params, plan);
    assert!(vol.volume.stats.bricks > 0, "nothing baked");
    let (mut cpu, mut gpu) = volume_renderers(&cfg, vol);
    // A narrow camera whose rays all cross the occupied cell.
    let target = cfg.bounds.from_unit(glam::Vec3::splat(32.5 / 64.0));
    let cam = Camera::look_at(
        16,
        12,
        0.01,
        glam::Vec3::new(0.3, -3.5, 1.2),
        target,
        glam::Vec3::Z,
    );
    let a = cpu.render(&cam, 0.0, &params);
    let b = gpu.render(&cam, 0.0, &params).unwrap();
    assert!(a.stats.volume && b.stats.volume);
    assert!(a.stats.volume_samples > 0, "no sample in the cell");
    let (p, d) = (psnr(&a, &b), max_diff(&a, &b));
    println!("2048^3: GPU against CPU march {p:.1} dB, max {d:.5}");
    assert!(p >= 70.0 && d < 0.01, "{p:.1} dB, max difference {d}");
}

/// A volume planned for a narrow view within a budget that holds only the bricks that view sees
/// leaves the others out ([`msth_core::volume::OUTSIDE_BRICK`]); a wider camera's rays that reach
/// them are drawn by the exact passes on the GPU, as by the exact renderer on the CPU.
fn rays_reaching_bricks_left_out_of_the_volume_draw_exactly_on_the_gpu() {
    use msth_player::volume::{plan_bake, VolumeOptions};
    let mut cfg = config(BlendMode::Mst);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let mut params = random_params(&layout, 5);
    centre_dynamic(&cfg, &mut params);
    let cam = test_camera(48, 36);
    let forward = -cam.world_from_camera.z_axis.truncate();
    let fov_x = 2.0 * (0.5 * cam.width as f32 / cam.fx).atan();
    let narrow = Camera::look_at(
        cam.width,
        cam.height,
        fov_x / 3.0,
        cam.center(),
        cam.center() + forward,
        cam.world_from_camera.y_axis.truncate(),
    );
    let options = |budget| VolumeOptions {
        max_resolution: Some(64),
        budget,
        ..Default::default()
    };
    let full = plan_bake(&cfg, &params, None, &[narrow], &options(None)).unwrap();
    let plan = plan_bake(
        &cfg,
        &params,
        None,
        &[narrow],
        // Fewer resident time slices fit the full volume in half its bound: a fifth does not.
        &options(Some(full.bytes_bound / 5)),
    )
    .unwrap();
    assert!(plan.outside_views > 0, "no brick left out");
    assert_eq!(plan.geometry.resolution, full.geometry.resolution);
    let vol = bake_planned(&cfg, &params, plan);
    let (mut cpu, mut gpu) = volume_renderers(&cfg, vol);
    for t in [0.0f32, 0.5] {
        let a = cpu.render(&cam, t, &params);
        let b = gpu.render(&cam, t, &params).unwrap();
        assert!(a.stats.volume && b.stats.volume);
        let (ea, eb) = (a.stats.rays_exact, b.stats.rays_exact);
        println!(
            "t={t}: {ea} (CPU) and {eb} (GPU) of {} rays exact",
            a.stats.rays_total
        );
        assert!(ea > 0 && ea < a.stats.rays_total, "{ea} rays exact");
        // The same rays, but for a step within rounding of a brick's face.
        assert!(
            ea.abs_diff(eb) <= a.stats.rays_total / 100,
            "{ea} against {eb}"
        );
        let p = psnr(&a, &b);
        let d = max_diff(&a, &b);
        println!("t={t}: GPU against CPU {p:.1} dB, max {d:.4}");
        assert!(p >= 60.0 && d < 0.01, "t={t}: {p:.1} dB, max {d}");
    }
}

/// A volume without baked colours is refused with a message (the device's march reads four
/// values per vertex), and the renderer keeps drawing from the exact field.
fn volumes_the_gpu_cannot_draw_are_clear_errors() {
    let mut cfg = config(BlendMode::Mst);
    small(&mut cfg);
    let layout = ModelLayout::new(&cfg);
    let mut params = random_params(&layout, 3);
    centre_dynamic(&cfg, &mut params);
    let cam = test_camera(16, 12);
    let vol = baked_volume(&cfg, &params, &cam, msth_core::volume::ColourMode::Deferred);
    let settings = RenderSettings {
        exact: false,
        ..Default::default()
    };
    let mut gpu = GpuRenderer::new(context(), &cfg, settings).unwrap();
    let e = gpu.set_volume(Some(vol)).unwrap_err();
    assert!(e.to_string().contains("baked colours"), "{e}");
    assert!(!gpu.uses_volume());
    let f = gpu.render(&cam, 0.2, &params).unwrap();
    assert!(!f.stats.volume);
}
