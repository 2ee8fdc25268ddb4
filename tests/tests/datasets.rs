//! The dataset layouts end to end: the shared stage scene read as Blender JSON and as DyNeRF
//! (same cameras, same times; mp4 frames close to the PNGs), layout detection and the dataset
//! options of `msth train`; the shared object and stage scenes read by the D-NeRF loader.
//!
//! Tests that read `../shared/data` or run `ffmpeg` are reported as ignored (with the reason)
//! where those are missing, unless `MSTH_REQUIRE_DATA=1` / `MSTH_REQUIRE_FFMPEG=1`: this binary
//! runs on `msth-testkit`'s harness (`harness = false`), and [`main`] lists its tests.

use std::path::Path;

use glam::Vec3;
use msth_core::config::Preset;
use msth_core::{Camera, SceneBounds};
use msth_dataset::dynerf::{self, DynerfOptions, FrameSource, Normalization};
use msth_dataset::{dnerf, Dataset, View};
use msth_testkit::{Need, Tests};
use msth_tests::{msth, shared_dataset};
use msth_trainer::train::TrainSettings;

fn main() -> std::process::ExitCode {
    // The stage scene in both layouts (the JSON files and poses_bounds.npy).
    let stage_both = Need::shared_data("box_animated_stage/poses_bounds.npy");
    let stage_json = Need::shared_data("box_animated_stage/transforms_train.json");
    let object_json = Need::shared_data("box_animated_object/transforms_train.json");
    let ffmpeg = Need::ffmpeg();
    Tests::new(file!())
        .needs(
            &[&stage_both, &stage_json],
            "stage_dynerf_cameras_equal_the_json_cameras",
            stage_dynerf_cameras_equal_the_json_cameras,
        )
        .needs(
            &[&stage_both, &ffmpeg],
            "stage_mp4_frames_are_close_to_the_pngs",
            stage_mp4_frames_are_close_to_the_pngs,
        )
        .test(
            "layout_detection_and_dataset_options",
            layout_detection_and_dataset_options,
        )
        .needs(
            &[&object_json],
            "shared_object_dataset_loads",
            shared_object_dataset_loads,
        )
        .needs(
            &[&stage_json],
            "shared_stage_dataset_loads",
            shared_stage_dataset_loads,
        )
        .on_request(
            &[&stage_both],
            "sampler_speed_memory_vs_cache",
            sampler_speed_memory_vs_cache,
        )
        .run()
}

/// The shared stage scene (the tests that call this declare the need).
fn stage() -> std::path::PathBuf {
    shared_dataset("box_animated_stage")
}

fn same_camera(a: &Camera, b: &Camera, tol: f32) -> bool {
    (a.width, a.height) == (b.width, b.height)
        && (a.fx - b.fx).abs() < tol * a.fx
        && (a.fy - b.fy).abs() < tol * a.fy
        && (a.cx - b.cx).abs() < 1e-3
        && (a.cy - b.cy).abs() < 1e-3
        && a.world_from_camera.abs_diff_eq(b.world_from_camera, tol)
}

/// Every view of `a` has a view in `b` with the same time and camera (`map` applied to `b`'s).
fn assert_same_views(a: &[View], b: &[View], map: impl Fn(&Camera) -> Camera) {
    assert_eq!(a.len(), b.len());
    for v in a {
        let found = b.iter().any(|w| {
            (w.time - v.time).abs() < 1e-6 && same_camera(&v.camera, &map(&w.camera), 1e-4)
        });
        assert!(found, "no view matches {:?} at t = {}", v.camera, v.time);
    }
}

fn load_dynerf(dir: &Path, normalization: Normalization, frames: FrameSource) -> Dataset {
    dynerf::load(
        dir,
        &DynerfOptions {
            normalization,
            frames,
            ..Default::default()
        },
    )
    .unwrap()
}

fn stage_dynerf_cameras_equal_the_json_cameras() {
    let dir = stage();
    let json = dnerf::load(&dir, &dnerf::LoadOptions::default()).unwrap();
    // The frame folders need no ffmpeg.
    let raw = load_dynerf(&dir, Normalization::None, FrameSource::Images);
    assert_eq!(raw.num_frames, json.num_frames);
    assert_same_views(&raw.train, &json.train, |c| *c);
    assert_same_views(&raw.test, &json.test, |c| *c);
    // Same pixels too (the same PNGs), and cam00 is the test camera.
    for v in &raw.test {
        assert_eq!(v.camera_id, Some(0));
        let w = json.test.iter().find(|w| w.time == v.time).unwrap();
        assert_eq!(v.image, w.image);
    }
    // The default (LLFF) normalisation is a similarity of the JSON world.
    let (norm, rig, _) = dynerf::load_with_rig(
        &dir,
        &DynerfOptions {
            frames: FrameSource::Images,
            ..Default::default()
        },
    )
    .unwrap();
    let s = rig.normalization;
    assert_same_views(&norm.train, &json.train, |c| Camera {
        world_from_camera: s.apply_pose(&c.world_from_camera),
        ..*c
    });
    // The contraction centres agree (the same construction, in both worlds).
    match (norm.bounds, json.bounds) {
        (
            SceneBounds::Contracted {
                center: a,
                radius: ra,
            },
            SceneBounds::Contracted {
                center: b,
                radius: rb,
            },
        ) => {
            assert!(
                (a - s.apply_point(b)).length() < 1e-3 * s.scale,
                "{a} vs {b}"
            );
            assert!((ra - rb * s.scale).abs() < 1e-3 * ra);
        }
        other => panic!("{other:?}"),
    }
    // The near bound: the JSON reading takes it from the poses_bounds.npy beside it (the same
    // cameras), the DyNeRF reading from its own rows, scaled with the normalisation; the stage's
    // nearest content is its floor and props, between 1 and 4.6 units (the rig's distance).
    let near = json
        .near
        .expect("the JSON reading finds the near bound beside it");
    assert!(near > 1.0 && near < 4.6, "near {near}");
    assert_eq!(raw.near, Some(near));
    let normalised = norm.near.unwrap();
    assert!((normalised - near * s.scale).abs() < 1e-4 * normalised);
    // Training starts rays there, not at 5% of the contraction radius (unless told otherwise).
    let settings = TrainSettings::for_preset(Preset::Balanced, &json);
    assert_eq!(settings.model.sampler.near, near);
    // A rig in other units does not match the rows: no near bound, the preset's default.
    let mut scaled = json.clone();
    scaled.rescale(2.0);
    assert_eq!(scaled.near, Some(2.0 * near));
    let moved = tempfile::tempdir().unwrap();
    copy_json_layout(&dir, moved.path(), 2.0);
    let other = dnerf::load(moved.path(), &dnerf::LoadOptions::default()).unwrap();
    assert_eq!(other.near, None);
    let settings = TrainSettings::for_preset(Preset::Balanced, &other);
    match other.bounds {
        SceneBounds::Contracted { radius, .. } => {
            assert_eq!(settings.model.sampler.near, 0.05 * radius)
        }
        b => panic!("{b:?}"),
    }

    // Both layouts in one folder: detection reads the JSON, which has no held-out camera to
    // choose, so `--test-camera` is refused (it was silently ignored) and points to the DyNeRF
    // reading, which takes it.
    let out = tempfile::tempdir().unwrap();
    let (d, o) = (dir.to_str().unwrap(), out.path().to_str().unwrap());
    let e = msth(&[
        "train",
        d,
        "--out",
        o,
        "--print-settings",
        "--test-camera",
        "1",
    ])
    .unwrap_err();
    assert!(
        e.contains("D-NeRF JSON") && e.contains("--format dynerf"),
        "{e}"
    );
    let args = [
        "--print-settings",
        "--test-camera",
        "1",
        "--format",
        "dynerf",
    ];
    msth(&[&["train", d, "--out", o][..], &args[..]].concat()).unwrap();
}

/// The stage's JSON layout (transforms files and the images they name) copied to `to` with
/// every camera centre scaled by `scale`, beside the original, unscaled `poses_bounds.npy`.
fn copy_json_layout(from: &Path, to: &Path, scale: f32) {
    for name in ["transforms_train.json", "transforms_test.json"] {
        let text = std::fs::read_to_string(from.join(name)).unwrap();
        let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
        for frame in json["frames"].as_array_mut().unwrap() {
            let path = frame["file_path"].as_str().unwrap();
            // Absolute image paths: the copy keeps its images where they are.
            let image = from.join(path.trim_start_matches("./"));
            frame["file_path"] = image.to_str().unwrap().into();
            for row in frame["transform_matrix"]
                .as_array_mut()
                .unwrap()
                .iter_mut()
                .take(3)
            {
                let t = row[3].as_f64().unwrap();
                row[3] = (t * scale as f64).into();
            }
        }
        std::fs::write(to.join(name), serde_json::to_vec(&json).unwrap()).unwrap();
    }
    std::fs::copy(from.join("poses_bounds.npy"), to.join("poses_bounds.npy")).unwrap();
}

/// PSNR in dB between two 8-bit images.
fn psnr8(a: &[u8], b: &[u8]) -> f64 {
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum();
    10.0 * (255.0f64.powi(2) / (se / a.len() as f64).max(1e-12)).log10()
}

fn stage_mp4_frames_are_close_to_the_pngs() {
    let dir = stage();
    let videos = load_dynerf(&dir, Normalization::None, FrameSource::Videos);
    let images = load_dynerf(&dir, Normalization::None, FrameSource::Images);
    assert!(videos.test[0]
        .source
        .to_string_lossy()
        .ends_with("cam00.mp4"));
    let mut all = Vec::new();
    for (a, b) in videos
        .train
        .iter()
        .chain(&videos.test)
        .zip(images.train.iter().chain(&images.test))
    {
        assert_eq!((a.camera_id, a.time), (b.camera_id, b.time));
        assert!(same_camera(&a.camera, &b.camera, 1e-6));
        all.push(psnr8(&a.image.data, &b.image.data));
    }
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    let min = all.iter().copied().fold(f64::INFINITY, f64::min);
    let max = all.iter().copied().fold(0.0, f64::max);
    println!(
        "decoded mp4 frames vs PNGs over {} frames: mean {mean:.2} dB, min {min:.2} dB, max {max:.2} dB",
        all.len()
    );
    // yuv420p (half-resolution chroma, limited range) alone costs about 34 dB on these
    // textured 200x150 frames; CRF 12 adds little.
    assert!(min > 30.0, "an mp4 frame is far from its PNG: {min} dB");
}

fn layout_detection_and_dataset_options() {
    let root = tempfile::tempdir().unwrap();
    // A tiny DyNeRF folder with frame folders (no ffmpeg needed).
    let data = root.path().join("rig");
    let (w, h) = (8u32, 6u32);
    let mut rows = Vec::new();
    for c in 0..3 {
        let eye = Vec3::new(c as f32 - 1.0, -4.0, 1.0);
        let cam = Camera::look_at(w, h, 0.9, eye, Vec3::ZERO, Vec3::Z);
        rows.push((cam, 1.0, 8.0));
        let d = data.join(format!("cam{c:02}"));
        std::fs::create_dir_all(&d).unwrap();
        for j in 0..3 {
            image::RgbImage::from_pixel(w, h, image::Rgb([c as u8 * 80, j as u8 * 60, 9]))
                .save(d.join(format!("{j:04}.png")))
                .unwrap();
        }
    }
    dynerf::write_poses_bounds(&data.join("poses_bounds.npy"), &rows).unwrap();
    let out = root.path().join("out");
    let (d, o) = (data.to_str().unwrap(), out.to_str().unwrap());
    msth(&["train", d, "--out", o, "--print-settings"]).unwrap();
    msth(&[
        "train",
        d,
        "--out",
        o,
        "--print-settings",
        "--test-camera",
        "2",
    ])
    .unwrap();
    let e = msth(&[
        "train",
        d,
        "--out",
        o,
        "--print-settings",
        "--test-camera",
        "5",
    ])
    .unwrap_err();
    assert!(e.contains("cam05") && e.contains("DyNerf"), "{e}");
    let e = msth(&[
        "train",
        d,
        "--out",
        o,
        "--format",
        "nerfstudio",
        "--print-settings",
    ])
    .unwrap_err();
    assert!(
        e.contains("transforms.json") && e.contains("cannot read"),
        "{e}"
    );
    let e = msth(&["train", d, "--out", o, "--format", "colmap"]).unwrap_err();
    assert!(e.contains("unknown dataset format `colmap`"), "{e}");
    // Train and evaluate a few steps through an explicit frame cache.
    let cache = root.path().join("cache");
    msth(&[
        "train",
        d,
        "--out",
        o,
        "--preset",
        "fast",
        "--iters",
        "3",
        "--batch-rays",
        "64",
        "--cache",
        cache.to_str().unwrap(),
        "--downscale",
        "2",
    ])
    .unwrap();
    let names: Vec<String> = std::fs::read_dir(&cache)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["rig-ds2.frames"]);
    assert!(out.join("metrics.json").exists());
    // Not a dataset.
    let empty = root.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let e = msth(&["train", empty.to_str().unwrap(), "--out", o]).unwrap_err();
    assert!(
        e.contains("poses_bounds.npy") && e.contains("transforms.json"),
        "{e}"
    );
}

/// Prints how long drawing a training batch takes with frames in memory and in a frame cache
/// (positional reads). Informational, never a pass/fail on time:
/// `cargo test --release -p msth-tests --test datasets -- --ignored`.
fn sampler_speed_memory_vs_cache() {
    use msth_core::rng::Rng;
    use msth_dataset::cache::FrameStorage;
    use msth_trainer::ray_sampling::sample_uniform;
    let dir = stage();
    let cache = tempfile::tempdir().unwrap();
    for storage in [
        FrameStorage::Memory,
        FrameStorage::Disk(cache.path().join("stage.frames")),
    ] {
        let d = dynerf::load(
            &dir,
            &DynerfOptions {
                frames: FrameSource::Images,
                storage: storage.clone(),
                ..Default::default()
            },
        )
        .unwrap();
        let (mut rays, mut targets) = (Vec::new(), Vec::new());
        let mut rng = Rng::stream(1, 2);
        let t = std::time::Instant::now();
        let n = 200;
        for _ in 0..n {
            sample_uniform(
                &d,
                2048,
                &mut rng,
                &mut rays,
                &mut targets,
                None,
                false,
                None,
            );
        }
        println!(
            "{storage:?}: {:.0} us per batch of 2048 rays",
            t.elapsed().as_secs_f64() * 1e6 / n as f64
        );
    }
}

/// The shared object scene (D-NeRF layout): 100 training and 20 test views of 200x200, one per
/// frame, in a box.
fn shared_object_dataset_loads() {
    let dir = shared_dataset("box_animated_object");
    let d = dnerf::load(&dir, &dnerf::LoadOptions::default()).unwrap();
    assert_eq!((d.train.len(), d.test.len()), (100, 20));
    assert_eq!(
        (d.train[0].image.width, d.train[0].image.height),
        (200, 200)
    );
    assert!(matches!(d.bounds, SceneBounds::Box { .. }));
    assert_eq!(d.num_frames, 100);
    assert!(d.train.iter().all(|v| v.camera_id.is_none()));
    assert_eq!(d.name, "box_animated_object");
}

/// The shared stage scene read as D-NeRF JSON: 8 training cameras and a test camera over 30
/// frames of 200x150, contracted around the look-at point.
fn shared_stage_dataset_loads() {
    let dir = stage();
    let d = dnerf::load(&dir, &dnerf::LoadOptions::default()).unwrap();
    assert_eq!((d.train.len(), d.test.len()), (240, 30));
    assert_eq!(
        (d.train[0].image.width, d.train[0].image.height),
        (200, 150)
    );
    assert_eq!(d.num_frames, 30);
    let mut ids: Vec<usize> = d.train.iter().filter_map(|v| v.camera_id).collect();
    ids.sort();
    ids.dedup();
    assert_eq!(ids, (0..8).collect::<Vec<_>>());
    assert!(d.test.iter().all(|v| v.camera_id == Some(8)));
    match d.bounds {
        SceneBounds::Contracted { center, radius } => {
            println!("stage bounds: centre {center}, radius {radius}");
            let look_at = Vec3::new(0.0, 0.3, 0.9);
            assert!((center - look_at).length() < 0.5, "centre {center}");
            assert!(radius > 3.0 && radius < 6.0, "radius {radius}");
        }
        b => panic!("expected contraction, got {b:?}"),
    }
}
