//! The object and stage layouts end to end on a small animated model built by the test:
//! files on disk, read back through the trainer's D-NeRF loader, LLFF rows, videos, and the
//! model's projection found in the images.
//!
//! This binary runs on `msth-testkit`'s harness (`harness = false`): [`main`] lists its tests.
//! The video test needs `ffmpeg`/`ffprobe`; without them it is reported as ignored with the
//! reason, unless `MSTH_REQUIRE_FFMPEG=1` (then it fails).

mod common;

use std::path::Path;

use common::{quad_mesh, Builder};
use glam::Vec3;
use msth_dataset::dnerf::{load as load_dnerf, LoadOptions};
use msth_scenegen::dynerf::{c2w_from_llff_row, read_npy};
use msth_scenegen::layout::{frame_time, OBJECT_MODEL_RADIUS, STAGE_MODEL_RADIUS};
use msth_scenegen::scene::{posed_triangles, Normalisation, Placement};
use msth_scenegen::{generate, load, Layout, Model, SynthSettings};
use msth_testkit::{Need, Tests};
use serde_json::{json, Value};

fn main() -> std::process::ExitCode {
    let ffmpeg = Need::ffmpeg();
    Tests::new(file!())
        .test(
            "object_layout_is_rgba_dnerf_and_alpha_covers_the_model",
            object_layout_is_rgba_dnerf_and_alpha_covers_the_model,
        )
        .test(
            "stage_layout_follows_the_dynerf_conventions",
            stage_layout_follows_the_dynerf_conventions,
        )
        .needs(
            &[&ffmpeg],
            "stage_videos_are_h264_with_one_frame_per_time",
            stage_videos_are_h264_with_one_frame_per_time,
        )
        .test(
            "missing_ffmpeg_is_a_note_not_a_failure",
            missing_ffmpeg_is_a_note_not_a_failure,
        )
        .test(
            "refuses_a_non_empty_folder_and_bad_settings_and_leaves_nothing",
            refuses_a_non_empty_folder_and_bad_settings_and_leaves_nothing,
        )
        .run()
}

/// A quad sliding along glTF +X over 1 s while spinning about +Z (LINEAR).
fn moving_quad(dir: &Path) -> Model {
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, false);
    let times = b.f32s(&[0.0, 1.0], 1);
    let tr = b.f32s(&[0., 0., 0., 1.5, 0., 0.], 3);
    let s = std::f32::consts::FRAC_1_SQRT_2;
    let rot = b.f32s(&[0., 0., 0., 1., 0., 0., s, s], 4);
    let rest = json!({
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [mesh],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.9, 0.3, 0.2, 1.0]}, "doubleSided": true}],
        "animations": [{
            "channels": [
                {"sampler": 0, "target": {"node": 0, "path": "translation"}},
                {"sampler": 1, "target": {"node": 0, "path": "rotation"}}
            ],
            "samplers": [
                {"input": times, "output": tr},
                {"input": times, "output": rot}
            ]
        }]
    });
    load(&b.write_gltf(dir, "moving.gltf", rest)).unwrap()
}

fn read_json(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// World-space triangle centroids of the normalised model at normalised time `t`.
fn centroids(model: &Model, norm: &Normalisation, t: f32) -> Vec<Vec3> {
    let secs = model.animation.as_ref().unwrap().time_secs(t);
    posed_triangles(model, secs, norm.root_transform, 0)
        .iter()
        .map(|t| (t.positions[0] + t.positions[1] + t.positions[2]) / 3.0)
        .collect()
}

fn object_layout_is_rgba_dnerf_and_alpha_covers_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let model = moving_quad(dir.path());
    let mut s = SynthSettings::new(Layout::Object);
    (s.width, s.height, s.frames, s.cameras, s.supersample) = (48, 40, 5, 3, 2);
    let out = dir.path().join("object");
    let calls = std::sync::atomic::AtomicUsize::new(0);
    let summary = generate(&model, &s, &out, &|| {
        calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    })
    .unwrap();
    assert_eq!(summary.images, 8);
    assert_eq!(calls.into_inner(), 8);
    for f in [
        "transforms_train.json",
        "transforms_test.json",
        "transforms_val.json",
        "render_meta.json",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    // The images on disk are RGBA.
    let first = image::open(out.join("train/r_000.png")).unwrap();
    assert_eq!(first.color(), image::ColorType::Rgba8);
    let data = load_dnerf(&out, &LoadOptions::default()).unwrap();
    assert_eq!(
        (data.train.len(), data.test.len(), data.num_frames),
        (5, 3, 5)
    );
    let norm = Normalisation::fit(&model, OBJECT_MODEL_RADIUS, Placement::Centred, 97);
    for (j, v) in data.train.iter().enumerate() {
        assert!((v.time - frame_time(j, 5)).abs() < 1e-6);
        let alpha = v.alpha.as_ref().expect("transparent background");
        let mut inside = 0;
        for c in centroids(&model, &norm, v.time) {
            let (u, w) = v.camera.project(c).unwrap();
            if u >= 0.0 && w >= 0.0 && u < 48.0 && w < 40.0 {
                inside += 1;
                assert!(
                    alpha[(w as u32 * 48 + u as u32) as usize] > 0,
                    "view {j}: model not in the mask"
                );
            }
        }
        assert!(inside > 0, "view {j}: the model is outside the image");
        // Corners are background: transparent, and white after compositing.
        assert_eq!(alpha[0], 0);
        assert_eq!(v.image.get(0, 0), [1.0, 1.0, 1.0]);
    }
}

fn stage_layout_follows_the_dynerf_conventions() {
    let dir = tempfile::tempdir().unwrap();
    let model = moving_quad(dir.path());
    let mut s = SynthSettings::new(Layout::Stage);
    (s.width, s.height, s.frames, s.cameras, s.supersample) = (40, 30, 4, 3, 1);
    s.ffmpeg = None;
    let out = dir.path().join("stage");
    let summary = generate(&model, &s, &out, &|| {}).unwrap();
    assert_eq!(summary.images, 16);
    // Frames.
    for c in 0..4 {
        for j in 0..4 {
            let p = out.join(format!("cam{c:02}/{j:04}.png"));
            let img = image::open(&p).unwrap();
            assert_eq!((img.width(), img.height()), (40, 30));
            assert_eq!(img.color(), image::ColorType::Rgb8, "{}", p.display());
        }
    }
    // poses_bounds.npy: N x 17, row i = camNN, row 0 = held-out cam00.
    let rows = read_npy(&out.join("poses_bounds.npy")).unwrap();
    let train_rows = read_npy(&out.join("poses_bounds_train.npy")).unwrap();
    assert_eq!(rows.len(), 4);
    assert_eq!(&rows[1..], &train_rows[..]);
    let cams = read_json(&out.join("cameras.json"));
    let test = read_json(&out.join("transforms_test.json"));
    let train = read_json(&out.join("transforms_train.json"));
    assert_eq!(cams["cameras"][0]["role"], "test");
    for (i, row) in rows.iter().enumerate() {
        let c = &cams["cameras"][i];
        assert_eq!(c["name"], format!("cam{i:02}"));
        let m: Vec<Vec<f64>> = serde_json::from_value(c["transform_matrix"].clone()).unwrap();
        let back = c2w_from_llff_row(row);
        for r in 0..3 {
            for k in 0..4 {
                assert!((back.col(k)[r] as f64 - m[r][k]).abs() < 1e-6);
            }
        }
        assert_eq!((row[4], row[9]), (30.0, 40.0));
        assert!((row[14] - c["fl_x"].as_f64().unwrap()).abs() < 1e-4);
        let (near, far) = (row[15], row[16]);
        assert!(near > 0.0 && far > near, "near {near} far {far}");
    }
    // The JSON twin: test = cam00 at every time, val = every third, train = cams 1.. x times.
    assert_eq!(test["frames"].as_array().unwrap().len(), 4);
    assert_eq!(test["frames"][1]["file_path"], "./cam00/0001");
    assert_eq!(
        read_json(&out.join("transforms_val.json"))["frames"]
            .as_array()
            .unwrap()
            .len(),
        2
    );
    assert_eq!(train["frames"].as_array().unwrap().len(), 12);
    assert_eq!(train["frames"][0]["file_path"], "./cam01/0000");
    let data = load_dnerf(&out, &LoadOptions::default()).unwrap();
    assert_eq!(
        (data.train.len(), data.test.len(), data.num_frames),
        (12, 4, 4)
    );
    // The model projects inside every camera's image at every time.
    let norm = Normalisation::fit(&model, STAGE_MODEL_RADIUS, Placement::OnFloor, 97);
    assert!(norm.bbox_min.z.abs() < 1e-4, "model stands on the floor");
    for v in data.train.iter().chain(&data.test) {
        for c in centroids(&model, &norm, v.time) {
            let (u, w) = v.camera.project(c).unwrap();
            assert!(u > 0.0 && u < 40.0 && w > 0.0 && w < 30.0, "{u} {w}");
        }
    }
    // No videos were asked for: a note says so, and no camNN.mp4 exists (the videos are
    // `stage_videos_are_h264_with_one_frame_per_time`, which needs ffmpeg).
    assert_eq!(
        summary.videos_skipped.as_deref(),
        Some("videos not requested")
    );
    assert!(!out.join("cam00.mp4").exists());
}

/// The stage layout's `camNN.mp4`: H.264, yuv420p, one frame per time, checked by `ffprobe`.
fn stage_videos_are_h264_with_one_frame_per_time() {
    let dir = tempfile::tempdir().unwrap();
    let model = moving_quad(dir.path());
    let mut s = SynthSettings::new(Layout::Stage);
    (s.width, s.height, s.frames, s.cameras, s.supersample) = (40, 30, 4, 3, 1);
    s.ffmpeg = Some(std::env::var_os("MSTH_FFMPEG").map_or("ffmpeg".into(), Into::into));
    let out = dir.path().join("stage");
    let summary = generate(&model, &s, &out, &|| {}).unwrap();
    assert_eq!(summary.videos_skipped, None);
    let ffprobe = std::env::var_os("MSTH_FFPROBE").unwrap_or("ffprobe".into());
    for c in 0..4 {
        let mp4 = out.join(format!("cam{c:02}.mp4"));
        assert!(std::fs::metadata(&mp4).unwrap().len() > 0);
        let o = std::process::Command::new(&ffprobe)
            .args([
                "-v",
                "error",
                "-select_streams",
                "v:0",
                "-count_frames",
                "-show_entries",
                "stream=codec_name,pix_fmt,nb_read_frames",
                "-of",
                "csv=p=0",
            ])
            .arg(&mp4)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&o.stdout);
        assert_eq!(text.trim(), "h264,yuv420p,4", "{}", mp4.display());
    }
}

fn missing_ffmpeg_is_a_note_not_a_failure() {
    let dir = tempfile::tempdir().unwrap();
    let model = moving_quad(dir.path());
    let mut s = SynthSettings::new(Layout::Stage);
    (s.width, s.height, s.frames, s.cameras, s.supersample) = (16, 12, 2, 1, 1);
    s.ffmpeg = Some(dir.path().join("no-such-ffmpeg"));
    let out = dir.path().join("stage");
    let summary = generate(&model, &s, &out, &|| {}).unwrap();
    let why = summary.videos_skipped.unwrap();
    assert!(
        why.contains("no-such-ffmpeg") && why.contains("not installed"),
        "{why}"
    );
    assert!(!out.join("cam00.mp4").exists());
    let meta = read_json(&out.join("render_meta.json"));
    assert!(meta["videos"].as_str().unwrap().starts_with("skipped"));
}

fn refuses_a_non_empty_folder_and_bad_settings_and_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let model = moving_quad(dir.path());
    let out = dir.path().join("busy");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("keep.txt"), b"x").unwrap();
    let mut s = SynthSettings::new(Layout::Stage);
    (s.width, s.height, s.frames, s.cameras) = (8, 6, 2, 1);
    let e = generate(&model, &s, &out, &|| {}).unwrap_err().to_string();
    assert!(e.contains("not an empty folder"), "{e}");
    for bad in [
        SynthSettings {
            frames: 0,
            ..s.clone()
        },
        SynthSettings {
            width: 0,
            ..s.clone()
        },
        SynthSettings {
            cameras: 100,
            ..s.clone()
        },
        SynthSettings {
            width: 16384,
            height: 16384,
            frames: 1000,
            ..s.clone()
        },
    ] {
        let e = generate(&model, &bad, &dir.path().join("new"), &|| {})
            .unwrap_err()
            .to_string();
        assert!(e.contains("invalid settings"), "{e}");
    }
    // A file whose scene shows no mesh (the mesh node is not under the scene's roots).
    let mut b = Builder::default();
    let mesh = quad_mesh(&mut b, false);
    let hidden = b.write_gltf(
        dir.path(),
        "hidden.gltf",
        json!({"scenes": [{"nodes": [1]}], "nodes": [{"mesh": 0}, {}], "meshes": [mesh], "materials": [{}]}),
    );
    let hidden = load(&hidden).unwrap();
    let e = generate(&hidden, &s, &dir.path().join("new"), &|| {})
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("hidden.gltf") && e.contains("no triangles"),
        "{e}"
    );
    std::fs::remove_file(dir.path().join("hidden.gltf")).unwrap();
    // Only the model file, the busy folder and its file remain: no staging folders.
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), 1);
}
