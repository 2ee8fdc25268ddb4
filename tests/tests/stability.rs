//! Stability at the extremes, training level (issue #8, part 2): all-black, all-white and
//! constant-colour videos, one frame and 10,000 frames. Each dataset is written to disk in the
//! D-NeRF format (real PNGs and JSON), loaded by the real loader and trained for a bounded number
//! of steps on a small model. Every run must keep its loss, parameters and gradients finite, and
//! the render of a held-out view must move towards the video's constant colour.

use std::path::Path;

use glam::Vec3;
use msth_core::pipeline::{train_chunk, StepSettings, Workspace};
use msth_core::rng::Rng;
use msth_core::{Camera, SceneBounds};
use msth_dataset::dnerf::{load, LoadOptions};
use msth_dataset::imageio::encode_png;
use msth_dataset::{Dataset, Image8};
use msth_trainer::eval::{evaluate, render_image};
use msth_trainer::ray_sampling::sample_uniform;
use msth_trainer::train::{train, TrainSettings};

const SIDE: u32 = 8;
const FOV_X: f32 = 0.35;

/// Camera `k` of `n` on a ring of radius `4 scale` around the origin, looking at it (all its rays
/// cross the scene box of half-size `1.5 scale`).
fn ring_camera(k: usize, n: usize, scale: f32) -> Camera {
    let a = k as f32 / n as f32 * std::f32::consts::TAU;
    let eye = Vec3::new(4.0 * a.cos(), 0.8, 4.0 * a.sin()) * scale;
    Camera::look_at(SIDE, SIDE, FOV_X, eye, Vec3::ZERO, Vec3::Y)
}

/// Writes a D-NeRF dataset of `frames` time steps whose every pixel has colour `rgb`: one training
/// view per frame (cameras cycling over 8 poses; at least 8 views), 2 test views; the scene box
/// and the cameras are scaled by `scale`.
fn write_constant_video(dir: &Path, frames: usize, rgb: [u8; 3], scale: f32) {
    let image = Image8 {
        width: SIDE,
        height: SIDE,
        data: rgb.repeat((SIDE * SIDE) as usize).into(),
    };
    let mut png = Vec::new();
    encode_png(&mut png, &image).unwrap();
    let time = |f: usize| {
        if frames > 1 {
            f as f64 / (frames - 1) as f64
        } else {
            0.0
        }
    };
    let split = |name: &str, views: Vec<(usize, f64)>| {
        std::fs::create_dir_all(dir.join(name)).unwrap();
        let mut list = Vec::new();
        for (i, (cam, t)) in views.into_iter().enumerate() {
            let file = format!("{name}/r_{i:05}");
            std::fs::write(dir.join(format!("{file}.png")), &png).unwrap();
            let m = ring_camera(cam, 8, scale).world_from_camera.transpose();
            list.push(serde_json::json!({
                "file_path": file,
                "time": t,
                "transform_matrix": m.to_cols_array_2d(),
            }));
        }
        let (lo, hi) = ([-1.5 * scale; 3], [1.5 * scale; 3]);
        let json = serde_json::json!({
            "camera_angle_x": FOV_X,
            "scene_box": {"min": lo, "max": hi},
            "frames": list,
        });
        std::fs::write(
            dir.join(format!("transforms_{name}.json")),
            serde_json::to_vec(&json).unwrap(),
        )
        .unwrap();
    };
    let n_train = frames.max(8);
    split(
        "train",
        (0..n_train).map(|i| (i % 8, time(i % frames))).collect(),
    );
    split("test", vec![(1, time(0)), (5, time(frames - 1))]);
}

/// Fast-preset settings shrunk to a model that trains in seconds.
fn small_settings(data: &Dataset, iters: usize) -> TrainSettings {
    let mut s = TrainSettings::for_preset(msth_core::config::Preset::Fast, data);
    s.iters = iters;
    s.batch_rays = 512;
    s.anneal_steps = (iters / 4).max(1);
    s.checkpoint_every = 0;
    let m = &mut s.model;
    for enc in [&mut m.field.encoding, &mut m.proposal.encoding] {
        enc.resize(4, 12, 64.0, 16);
    }
    m.resize_mlps(16, 8);
    m.field.geo_features = 7;
    m.sampler.set_samples(32, 16);
    s.validate().unwrap();
    s
}

/// Mean absolute difference between the renders of the test views and the constant colour.
fn render_error(
    data: &Dataset,
    s: &TrainSettings,
    layout: &msth_core::field::ModelLayout,
    params: &[f32],
    rgb: [f32; 3],
) -> f32 {
    let mut err = 0f32;
    let mut n = 0usize;
    for v in &data.test {
        let r = render_image(&s.model, layout, params, &v.camera, v.time);
        assert!(r.rgb.iter().all(|c| c.is_finite()), "render not finite");
        for px in r.rgb.chunks(3) {
            for ch in 0..3 {
                err += (px[ch] - rgb[ch]).abs();
            }
            n += 3;
        }
    }
    err / n as f32
}

/// The whole-model gradient of one batch on `params`: must be finite.
fn assert_gradient_finite(data: &Dataset, s: &TrainSettings, params: &[f32]) {
    let layout = msth_core::field::ModelLayout::new(&s.model);
    let mut rays = Vec::new();
    let mut targets = Vec::new();
    let mut rng = Rng::new(17);
    sample_uniform(
        data,
        256,
        &mut rng,
        &mut rays,
        &mut targets,
        None,
        true,
        None,
    );
    let mut grad = vec![0f32; params.len()];
    let step = StepSettings {
        anneal: 1.0,
        interlevel_weight: s.interlevel_weight,
        distortion_weight: s.distortion_weight,
        loss_scale: 1.0 / rays.len() as f32,
        sample_mask_weight: 0.0,
        free_space_weight: 0.0,
        active_levels: None,
        proposal_levels: None,
    };
    let l = train_chunk(
        &s.model,
        &layout,
        params,
        &mut grad,
        &rays,
        &targets,
        None,
        &step,
        &mut rng,
        &mut Workspace::default(),
    );
    assert!(l.sq_err.is_finite() && l.interlevel.is_finite() && l.distortion.is_finite());
    if let Some(i) = grad.iter().position(|g| !g.is_finite()) {
        panic!("gradient {i} is {}", grad[i]);
    }
    assert!(grad.iter().any(|&g| g != 0.0), "no gradient at all");
}

/// What a run on a constant video reached.
struct Run {
    /// Mean absolute error of the held-out renders to the colour, before and after training.
    before: f32,
    after: f32,
    /// Held-out PSNR after training (dB).
    psnr: f64,
}

impl Run {
    /// Converged towards the colour: small final error, at most half the initial one, and a
    /// held-out PSNR above 20 dB.
    fn assert_converged(&self, what: &str) {
        let Run {
            before,
            after,
            psnr,
        } = *self;
        assert!(
            after < 0.1 && after < 0.5 * before && psnr > 20.0,
            "{what}: render error {before} -> {after}, PSNR {psnr}"
        );
    }
}

/// Writes, loads and trains a constant video.
fn train_constant_video(frames: usize, rgb: [u8; 3], iters: usize) -> Run {
    train_scaled_constant_video(frames, rgb, iters, 1.0)
}

/// [`train_constant_video`] in a scene scaled by `scale` (box half-size `1.5 scale`).
fn train_scaled_constant_video(frames: usize, rgb: [u8; 3], iters: usize, scale: f32) -> Run {
    let dir = tempfile::tempdir().unwrap();
    write_constant_video(dir.path(), frames, rgb, scale);
    let data = load(dir.path(), &LoadOptions::default()).unwrap();
    assert_eq!(data.num_frames, frames);
    assert_eq!(
        data.bounds,
        SceneBounds::Box {
            min: Vec3::splat(-1.5 * scale),
            max: Vec3::splat(1.5 * scale)
        }
    );
    let s = small_settings(&data, iters);
    let colour = rgb.map(|c| c as f32 / 255.0);
    let layout = msth_core::field::ModelLayout::new(&s.model);
    let init = layout.init_params(s.seed);
    let before = render_error(&data, &s, &layout, &init, colour);
    assert_gradient_finite(&data, &s, &init);
    let out = dir.path().join("run");
    let mut losses = Vec::new();
    let (trainer, outcome) = train(&data, s.clone(), &out, None, &mut |p| {
        losses.push(p.loss);
        true
    })
    .unwrap_or_else(|e| panic!("{frames} frames of {rgb:?}: {e}"));
    assert_eq!(outcome.steps, iters);
    assert!(losses.iter().all(|l| l.is_finite()), "{losses:?}");
    if let Some(i) = trainer.params.iter().position(|v| !v.is_finite()) {
        panic!("parameter {i} is {}", trainer.params[i]);
    }
    assert_gradient_finite(&data, &s, &trainer.params);
    let after = render_error(&data, &s, &trainer.layout, &trainer.params, colour);
    // The evaluation of a constant image (zero variance, possibly zero error) is finite too.
    let m = evaluate(&data, &s.model, &trainer.layout, &trainer.params, 1, None).unwrap();
    assert!(
        m.psnr.is_finite() && m.ssim.is_finite() && m.dssim.is_finite(),
        "{m:?}"
    );
    serde_json::to_string(&m).unwrap();
    println!(
        "{frames} frames of {rgb:?} at scale {scale}: render error {before:.4} -> {after:.4}, \
         loss {:.5} -> {:.5}, PSNR {:.1} dB",
        losses[0],
        losses[losses.len() - 1],
        m.psnr
    );
    Run {
        before,
        after,
        psnr: m.psnr,
    }
}

/// An all-black video in front of the white background: the box must become opaque and black.
#[test]
fn all_black_video_trains_to_black() {
    train_constant_video(4, [0, 0, 0], 120).assert_converged("black");
}

/// A scene a thousand times larger than the default (sample steps of about 1e2 units, so the
/// density must fall to about 1e-2 where it is not opaque) converges like the default.
#[test]
fn huge_scene_trains() {
    train_scaled_constant_video(4, [64, 160, 220], 120, 1e3).assert_converged("scale 1e3");
}

/// A scene a thousand times smaller (steps of about 2e-4 units; the density must reach about 1e4
/// to be opaque) stays finite and improves, but converges much more slowly: densities are per
/// world unit, so the log-density must climb by about 9 first (see docs/stability.md, "noticed").
#[test]
fn tiny_scene_trains_finite_and_improves() {
    let r = train_scaled_constant_video(4, [64, 160, 220], 120, 1e-3);
    assert!(r.after < 0.75 * r.before, "{} -> {}", r.before, r.after);
}

/// An all-white video, the colour of the background: empty space or white matter both fit.
#[test]
fn all_white_video_trains_to_white() {
    let r = train_constant_video(4, [255, 255, 255], 60);
    assert!(
        r.after < 0.05 && r.psnr > 20.0,
        "{} -> {}, PSNR {}",
        r.before,
        r.after,
        r.psnr
    );
}

/// A constant colour unlike the background.
#[test]
fn constant_colour_video_trains_to_the_colour() {
    train_constant_video(4, [64, 160, 220], 120).assert_converged("constant colour");
}

/// One frame: a static scene (every time is 0; the 4D grid has the minimum time resolution).
#[test]
fn one_frame_trains() {
    train_constant_video(1, [200, 40, 40], 120).assert_converged("one frame");
}

/// 10,000 frames: 10,000 views, the 4D grid's finest time resolution 10,000.
#[test]
fn ten_thousand_frames_train() {
    train_constant_video(10_000, [30, 200, 90], 120).assert_converged("10,000 frames");
}

/// Adam is invariant to the scale of the gradient: for gradients from 1e-10 to `f32::MAX` a
/// step moves every parameter by about the learning rate against the gradient's sign, and the
/// parameters and moments stay finite. (Gradients beyond 1.8e19 used to overflow `g^2` to
/// infinity, which froze the parameter for good: `m / sqrt(inf) = 0` on every later step.)
#[test]
fn adam_steps_by_the_learning_rate_at_any_gradient_scale() {
    use msth_trainer::adam::{Adam, AdamConfig};
    let cfg = AdamConfig::default();
    let scales = [1e-10f32, 1.0, 1e10, 1e19, 1e30, f32::MAX];
    let n = 2 * scales.len();
    let mut p = vec![0f32; n];
    let mut adam = Adam::new(n);
    let g: Vec<f32> = (0..n)
        .map(|i| scales[i / 2] * if i % 2 == 0 { 1.0 } else { -1.0 })
        .collect();
    let lr = 1e-2;
    for step in 1..=10 {
        adam.update(&cfg, lr, &mut p, &g, &[]);
        for i in 0..n {
            assert!(
                p[i].is_finite() && adam.m[i].is_finite() && adam.v[i].is_finite(),
                "gradient {}: parameter {} m {} v {}",
                g[i],
                p[i],
                adam.m[i],
                adam.v[i]
            );
            // Constant gradient: each bias-corrected step is lr (to eps / sqrt(v) relative).
            let expected = -(step as f32) * lr * g[i].signum();
            assert!(
                (p[i] - expected).abs() <= 1e-3 * step as f32 * lr,
                "gradient {} after {step} steps: parameter {} (expected {expected})",
                g[i],
                p[i]
            );
        }
    }
}
