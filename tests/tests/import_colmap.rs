//! `msth import` with the real COLMAP on generated captures whose true cameras are known:
//! `msth synth --gltf BoxAnimated --layout stage` renders a textured stage filmed by fixed
//! cameras; only its videos go to `msth import`. The recovered cameras are aligned to the true
//! ones with a similarity transform fitted to the camera centres, then the rotation and position
//! errors are checked:
//! - the rig: every `camNN.mp4` as one fixed camera;
//! - a moving camera: one video whose frame `i` is camera `i`'s view at a time step that
//!   advances along the video (the monocular layout, every frame registered on its own).
//!
//! Needs `colmap`, `ffmpeg` and `../shared/data/gltf`; without them the tests are reported as
//! ignored with the reason (msth-testkit's harness, `harness = false`: [`main`] lists the
//! tests), unless `MSTH_REQUIRE_COLMAP=1` (or `_ALL`), where they fail. `import_then_train_*`
//! (run on request:
//! minutes of training) compares held-out PSNR after the same run on imported and true poses.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DMat4, DVec3};
use msth_dataset::video::{self, Tools};
use msth_dataset::{colmap, npy};
use msth_testkit::{Need, Tests};
use msth_tests::{msth, shared_dataset};
use msth_trainer::import::{average_pose, fit_similarity, rotation_angle_deg};
use serde_json::Value;

/// Time steps of the generated stage.
const STEPS: usize = 4;

/// The BoxAnimated model (the tests that call this run only where their needs are present:
/// see [`main`]).
fn box_animated() -> PathBuf {
    shared_dataset("gltf").join("BoxAnimated/BoxAnimated.gltf")
}

fn main() -> std::process::ExitCode {
    let needs = [Need::colmap(), Need::ffmpeg(), Need::shared_data("gltf")];
    let needs: Vec<&Need> = needs.iter().collect();
    Tests::new(file!())
        // On request, not in every run: it takes 4 to 7 minutes on the shared 2-core host
        // (two imports, each matching 78 image pairs and mapping three times). COLMAP's
        // matching is not repeatable; one import in seven used to come out wrong (focal 921 px
        // against 389, 15 degrees), which `msth import` now guards against by comparing three mapper
        // runs (docs/import.md, "Repeatability"); this test checks the accuracy of the result.
        .on_request(
            &needs,
            "stage_imports_as_a_rig_and_as_a_moving_camera",
            stage_imports_as_a_rig_and_as_a_moving_camera,
        )
        .needs(
            &[&Need::colmap()],
            "colmaps_binary_model_reads_like_its_text_model",
            colmaps_binary_model_reads_like_its_text_model,
        )
        .needs(
            &needs,
            "too_little_texture_fails_naming_the_count",
            too_little_texture_fails_naming_the_count,
        )
        .on_request(
            &needs,
            "import_then_train_matches_true_poses",
            import_then_train_matches_true_poses,
        )
        .run()
}

/// Renders the stage layout: `cameras` + the held-out cam00, `frames` time steps, 400x300
/// (at 200x150 COLMAP finds too few matches on this scene's repetitive textures to start).
fn stage(model: &Path, out: &Path, frames: usize, cameras: usize) {
    msth(&[
        "synth",
        "--gltf",
        model.to_str().unwrap(),
        "--layout",
        "stage",
        "--size",
        "400x300",
        "--frames",
        &frames.to_string(),
        "--cameras",
        &cameras.to_string(),
        "--supersample",
        "2",
        "--out",
        out.to_str().unwrap(),
    ])
    .unwrap();
}

/// True OpenGL camera-to-world rotation and centre of each row of `poses_bounds.npy`, and the
/// focal length.
fn true_cameras(stage: &Path) -> Vec<(DMat3, DVec3, f64)> {
    let a = npy::read(&stage.join("poses_bounds.npy")).unwrap();
    a.data
        .chunks_exact(17)
        .map(|r| {
            let col = |c: usize| DVec3::new(r[c], r[5 + c], r[10 + c]);
            // LLFF columns: [-Y, X, Z, centre, hwf].
            (DMat3::from_cols(col(1), -col(0), col(2)), col(3), r[14])
        })
        .collect()
}

/// `(rotation, centre)` of a `transform_matrix`.
fn pose_of(frame: &Value) -> (DMat3, DVec3) {
    let m = &frame["transform_matrix"];
    let at = |i: usize, j: usize| m[i][j].as_f64().unwrap();
    let r = DMat3::from_cols(
        DVec3::new(at(0, 0), at(1, 0), at(2, 0)),
        DVec3::new(at(0, 1), at(1, 1), at(2, 1)),
        DVec3::new(at(0, 2), at(1, 2), at(2, 2)),
    );
    (r, DVec3::new(at(0, 3), at(1, 3), at(2, 3)))
}

/// Errors of `found` against `truth` (same order) after alignment:
/// - `rot_*`: rotation errors in degrees after the best global rotation of the orientations
///   (the chordal mean of `R_true R_found^T`): how well the cameras' relative orientations agree;
/// - `rot_centres_*`: rotation errors after the similarity fitted to the camera centres alone
///   (Umeyama): this adds the error of that fit's rotation, which the centres of a shallow arc of
///   cameras determine poorly (a few hundredths of the scene size of position noise tilt it by a
///   degree);
/// - `pos_*`: camera centre errors after the Umeyama fit, relative to the scene size (the
///   spread of the true centres: twice their RMS distance to their mean).
struct Errors {
    rot_mean_deg: f64,
    rot_max_deg: f64,
    rot_centres_mean_deg: f64,
    pos_mean_rel: f64,
    pos_max_rel: f64,
    sim: msth_trainer::import::Similarity3,
}

fn align_errors(found: &[(DMat3, DVec3)], truth: &[(DMat3, DVec3)]) -> Errors {
    let from: Vec<DVec3> = found.iter().map(|p| p.1).collect();
    let to: Vec<DVec3> = truth.iter().map(|p| p.1).collect();
    let sim = fit_similarity(&from, &to).expect("non-degenerate camera centres");
    let mean = to.iter().sum::<DVec3>() / to.len() as f64;
    let size = 2.0
        * (to.iter().map(|c| (*c - mean).length_squared()).sum::<f64>() / to.len() as f64).sqrt();
    let deltas: Vec<DMat4> = found
        .iter()
        .zip(truth)
        .map(|(f, t)| DMat4::from_mat3(t.0 * f.0.transpose()))
        .collect();
    let global = DMat3::from_mat4(average_pose(&deltas));
    let rot: Vec<f64> = found
        .iter()
        .zip(truth)
        .map(|(f, t)| rotation_angle_deg(global * f.0, t.0))
        .collect();
    let rot_centres: Vec<f64> = found
        .iter()
        .zip(truth)
        .map(|(f, t)| rotation_angle_deg(sim.rotation * f.0, t.0))
        .collect();
    let pos: Vec<f64> = found
        .iter()
        .zip(truth)
        .map(|(f, t)| (sim.apply(f.1) - t.1).length() / size)
        .collect();
    let mean_of = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let max_of = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    Errors {
        rot_mean_deg: mean_of(&rot),
        rot_max_deg: max_of(&rot),
        rot_centres_mean_deg: mean_of(&rot_centres),
        pos_mean_rel: mean_of(&pos),
        pos_max_rel: max_of(&pos),
        sim,
    }
}

/// Accepted errors: mean and max orientation error (degrees), mean rotation error after the
/// centre fit (degrees), mean position error (fraction of the scene size).
struct Bounds(f64, f64, f64, f64);

/// The rig. COLMAP's multi-threaded matching and bundle adjustment are not repeatable run to
/// run: on this small capture four runs measured a mean orientation error of 0.24-0.68 degree
/// (max 0.72-1.29), 0.61-2.41 degrees after the centre-only fit (camera centres on a shallow
/// arc pin that fit's rotation poorly) and 0.8-1.1% position error (docs/import.md). The issue
/// aims at 0.5 degree; these bounds are regression checks at about twice the spread seen (a
/// wrong reconstruction is off by tens of degrees), not the aim.
const RIG: Bounds = Bounds(1.5, 3.0, 5.0, 0.03);
/// The moving camera: every frame registered on its own, from 13 frames (measured: 0.79-1.01
/// degree mean, 1.44-1.72 max, 2.2-4.1 after the centre fit, 1.0-1.3% position), bounds likewise.
const MOVING: Bounds = Bounds(2.0, 4.0, 8.0, 0.04);

fn check(e: &Errors, b: &Bounds) {
    assert!(
        e.rot_mean_deg < b.0,
        "mean rotation error {} deg",
        e.rot_mean_deg
    );
    assert!(
        e.rot_max_deg < b.1,
        "max rotation error {} deg",
        e.rot_max_deg
    );
    assert!(
        e.rot_centres_mean_deg < b.2,
        "mean rotation error after the centre fit {} deg",
        e.rot_centres_mean_deg
    );
    assert!(
        e.pos_mean_rel < b.3,
        "mean position error {}",
        e.pos_mean_rel
    );
}

fn read_json(p: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

/// Copies only the videos of a stage into a new folder.
fn videos_only(stage: &Path, dir: &Path) -> usize {
    std::fs::create_dir_all(dir).unwrap();
    let mut n = 0;
    for e in std::fs::read_dir(stage).unwrap().flatten() {
        let p = e.path();
        if p.extension().is_some_and(|x| x == "mp4") {
            std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
            n += 1;
        }
    }
    n
}

/// The stage's 13 videos imported as a rig, then a sweep along its cameras as a moving camera
/// (one rendering for both).
fn stage_imports_as_a_rig_and_as_a_moving_camera() {
    let model = box_animated();
    let tmp = tempfile::tempdir().unwrap();
    let st = tmp.path().join("stage");
    stage(&model, &st, STEPS, 12);
    let videos = tmp.path().join("videos");
    let n = videos_only(&st, &videos);
    assert_eq!(n, 13);
    let out = tmp.path().join("imported");
    let t = Instant::now();
    msth(&[
        "import",
        videos.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
    .unwrap();
    let secs = t.elapsed().as_secs_f64();
    let report = read_json(&out.join("import.json"));
    let tf = read_json(&out.join("transforms.json"));
    let frames = tf["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 13 * STEPS, "every frame of every camera");
    // One pose per camera_id (camNN.mp4 in name order = camera NN).
    let truth = true_cameras(&st);
    let mut found = vec![None; 13];
    for f in frames {
        let id = f["camera_id"].as_u64().unwrap() as usize;
        let p = pose_of(f);
        if let Some(q) = found[id] {
            assert_eq!(q, p, "camera {id} has one pose for all its frames");
        }
        found[id] = Some(p);
    }
    let found: Vec<(DMat3, DVec3)> = found.into_iter().map(Option::unwrap).collect();
    let truth_poses: Vec<(DMat3, DVec3)> = truth.iter().map(|t| (t.0, t.1)).collect();
    let e = align_errors(&found, &truth_poses);
    let focal = tf["fl_x"].as_f64().unwrap();
    println!(
        "rig: {}/{} cameras, {} points, reprojection {:.3} px, COLMAP {:.1} s (import {:.1} s); \
         rotation error mean {:.3} max {:.3} deg (after the centre fit: mean {:.3}); \
         position error mean {:.4} max {:.4} of the scene size; focal {:.1} (true {:.1}), k1 {:.4}",
        report["cameras_registered"],
        report["cameras_total"],
        report["points"],
        report["mean_reprojection_error_px"].as_f64().unwrap(),
        report["colmap_seconds"].as_f64().unwrap(),
        secs,
        e.rot_mean_deg,
        e.rot_max_deg,
        e.rot_centres_mean_deg,
        e.pos_mean_rel,
        e.pos_max_rel,
        focal,
        truth[0].2,
        tf["k1"].as_f64().unwrap(),
    );
    println!("rig: mapper runs {}", report["colmap_runs"]);
    assert_eq!(report["colmap_runs"].as_array().map(Vec::len), Some(3));
    assert_eq!(report["cameras_registered"], 13);
    check(&e, &RIG);
    assert!(
        // Four runs measured -6.2% to +3.9% (COLMAP trades focal length against distortion on
        // this shallow rig); 12% is a regression check at twice that spread.
        (focal / truth[0].2 - 1.0).abs() < 0.12,
        "focal {focal} vs {}",
        truth[0].2
    );
    // Up is up: the true world's +Z (up) seen in the imported world is close to its +Z (the
    // imported world puts the mean camera up vector there; the stage cameras look down a little).
    let up = (e.sim.rotation.transpose() * DVec3::Z).normalize();
    let tilt = up.dot(DVec3::Z).clamp(-1.0, 1.0).acos().to_degrees();
    println!("rig: true up is {tilt:.2} deg from the imported +Z");
    assert!(tilt < 15.0, "up is {tilt} deg off");
    // The dataset loads for training: cam00 held out, all time steps.
    let d = msth_dataset::load(&out, &Default::default()).unwrap();
    assert_eq!(
        (d.train.len(), d.test.len(), d.num_frames),
        (12 * STEPS, STEPS, STEPS)
    );
    moving_camera(&st, tmp.path(), STEPS);
}

/// The moving-camera part of [`stage_imports_as_a_rig_and_as_a_moving_camera`]: one video whose
/// frame `i` is the `i`-th camera along the arc at a time step advancing with `i`.
fn moving_camera(st: &Path, tmp: &Path, steps: usize) {
    let truth = true_cameras(st);
    // Along the arc: sort the cameras by azimuth so that the video sweeps smoothly.
    let mut order: Vec<usize> = (0..truth.len()).collect();
    order.sort_by(|&a, &b| {
        let az = |i: usize| truth[i].1.y.atan2(truth[i].1.x);
        az(a).total_cmp(&az(b))
    });
    let mut rgb = Vec::new();
    let n = order.len();
    for (i, &cam) in order.iter().enumerate() {
        let t = i * (steps - 1) / (n - 1);
        let img = image::open(st.join(format!("cam{cam:02}/{t:04}.png")))
            .unwrap()
            .to_rgb8();
        rgb.push(img.into_raw());
    }
    let clip = tmp.join("walk.mp4");
    video::encode(&Tools::default(), &clip, 400, 300, &rgb, 12).unwrap();
    let out = tmp.join("imported-walk");
    msth(&[
        "import",
        clip.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
    .unwrap();
    let report = read_json(&out.join("import.json"));
    let tf = read_json(&out.join("transforms.json"));
    let frames = tf["frames"].as_array().unwrap();
    let mut found = Vec::new();
    let mut want = Vec::new();
    for f in frames {
        let name = f["file_path"].as_str().unwrap();
        let i: usize = name["frames/".len()..name.len() - 4].parse().unwrap();
        found.push(pose_of(f));
        want.push((truth[order[i]].0, truth[order[i]].1));
    }
    let e = align_errors(&found, &want);
    println!(
        "moving camera: {}/{} frames, {} points, reprojection {:.3} px, COLMAP {:.1} s; \
         rotation error mean {:.3} max {:.3} deg (after the centre fit: mean {:.3}); \
         position error mean {:.4} max {:.4} of the scene size",
        report["cameras_registered"],
        report["cameras_total"],
        report["points"],
        report["mean_reprojection_error_px"].as_f64().unwrap(),
        report["colmap_seconds"].as_f64().unwrap(),
        e.rot_mean_deg,
        e.rot_max_deg,
        e.rot_centres_mean_deg,
        e.pos_mean_rel,
        e.pos_max_rel,
    );
    println!("moving camera: mapper runs {}", report["colmap_runs"]);
    assert_eq!(report["cameras_registered"], 13);
    check(&e, &MOVING);
    let d = msth_dataset::load(&out, &Default::default()).unwrap();
    assert_eq!(d.train.len() + d.test.len(), 13);
}

/// A small text model converted to binary by the real `colmap model_converter` reads equal to
/// the text model (cameras, images in id order with their observed points, points).
fn colmaps_binary_model_reads_like_its_text_model() {
    let tmp = tempfile::tempdir().unwrap();
    let text = tmp.path().join("text");
    let bin = tmp.path().join("bin");
    std::fs::create_dir_all(&text).unwrap();
    std::fs::create_dir_all(&bin).unwrap();
    std::fs::write(
        text.join("cameras.txt"),
        "1 OPENCV 400 300 383.6567297 389.1892 200.5 149.25 0.0213 -0.004 0.0007 -0.0002\n\
         2 SIMPLE_RADIAL 64 48 50.125 32 24 0.05\n\
         3 PINHOLE 640 480 500 510 320 240\n",
    )
    .unwrap();
    // Images given out of id order; image 5 observes point 7 twice and one 2D point without a
    // 3D point; image 2 (camera 2) sees both points.
    std::fs::write(
        text.join("images.txt"),
        "5 0.9238795325112867 0 0.3826834323650898 0 0.1 -2.5 3.25 1 cam01/t0000.png\n\
         10 20 7 30 40 -1 50 60 7 70 80 30\n\
         2 1 0 0 0 0 0 0 2 cam00/t0000.png\n\
         11 21 7 31 41 30\n",
    )
    .unwrap();
    std::fs::write(
        text.join("points3D.txt"),
        "7 0.5 -1.25 4 255 0 0 0.5 5 0 5 2 2 0\n30 1 1 3 0 255 0 0.25 5 3 2 1\n",
    )
    .unwrap();
    let out = std::process::Command::new(
        std::env::var_os("MSTH_COLMAP").unwrap_or_else(|| "colmap".into()),
    )
    .env("QT_QPA_PLATFORM", "offscreen")
    .args(["model_converter", "--input_path"])
    .arg(&text)
    .arg("--output_path")
    .arg(&bin)
    .args(["--output_type", "BIN"])
    .output()
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let from_text = colmap::read_text_model(&text).unwrap();
    let from_bin = colmap::read_binary_model(&bin).unwrap();
    assert_eq!(from_bin, from_text);
    assert_eq!(colmap::read_model(&bin).unwrap(), from_text);
    assert_eq!(from_text.cameras.len(), 3);
    assert_eq!(from_text.images[0].name, "cam00/t0000.png");
    assert_eq!(from_text.images[1].point_ids, [7, 30]);
    assert_eq!(from_text.points[&7].track_len, 3);
}

fn too_little_texture_fails_naming_the_count() {
    // Three flat grey videos: nothing for SIFT to find.
    let tmp = tempfile::tempdir().unwrap();
    let mut videos = Vec::new();
    for i in 0..3 {
        let p = tmp.path().join(format!("cam{i:02}.mp4"));
        let frames = vec![vec![128u8 + i as u8 * 10; 64 * 48 * 3]; 3];
        video::encode(&Tools::default(), &p, 64, 48, &frames, 12).unwrap();
        videos.push(p.to_str().unwrap().to_string());
    }
    let out = tmp.path().join("imported");
    let mut args = vec!["import"];
    args.extend(videos.iter().map(String::as_str));
    args.extend(["--out", out.to_str().unwrap()]);
    let e = msth(&args).unwrap_err();
    assert!(
        e.contains("COLMAP registered 0 of 3 cameras") || e.contains("registered no images"),
        "{e}"
    );
    assert!(!out.exists(), "nothing is left behind");
    let left: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp-"))
        .collect();
    assert!(left.is_empty(), "no staging folder is left behind");
}

/// Held-out PSNR after the same training run on the imported dataset and on a copy of it with
/// the true cameras (same frames, same split: cam00 held out). Minutes of CPU: run with
/// `cargo test --release -p msth-tests --test import_colmap -- --ignored --nocapture`
/// (`MSTH_IMPORT_TRAIN_ITERS`, default 400 steps of the balanced preset).
fn import_then_train_matches_true_poses() {
    let model = box_animated();
    let iters = std::env::var("MSTH_IMPORT_TRAIN_ITERS").unwrap_or_else(|_| "400".into());
    let tmp = tempfile::tempdir().unwrap();
    let st = tmp.path().join("stage");
    stage(&model, &st, STEPS, 12);
    let videos = tmp.path().join("videos");
    videos_only(&st, &videos);
    let imported = tmp.path().join("imported");
    msth(&[
        "import",
        videos.to_str().unwrap(),
        "--out",
        imported.to_str().unwrap(),
    ])
    .unwrap();
    // The same frames with the true cameras: pinhole, no distortion.
    let truth = true_cameras(&st);
    let true_dir = tmp.path().join("true");
    let mut tf = read_json(&imported.join("transforms.json"));
    for f in tf["frames"].as_array_mut().unwrap() {
        let id = f["camera_id"].as_u64().unwrap() as usize;
        let (r, c, _) = truth[id];
        let m = [
            [r.x_axis.x, r.y_axis.x, r.z_axis.x, c.x],
            [r.x_axis.y, r.y_axis.y, r.z_axis.y, c.y],
            [r.x_axis.z, r.y_axis.z, r.z_axis.z, c.z],
            [0.0, 0.0, 0.0, 1.0],
        ];
        f["transform_matrix"] = serde_json::json!(m);
        let src = imported.join(f["file_path"].as_str().unwrap());
        let dst = true_dir.join(f["file_path"].as_str().unwrap());
        std::fs::create_dir_all(dst.parent().unwrap()).unwrap();
        std::fs::copy(src, dst).unwrap();
    }
    let focal = truth[0].2;
    for (k, v) in [
        ("fl_x", focal),
        ("fl_y", focal),
        ("cx", 200.0),
        ("cy", 150.0),
        ("k1", 0.0),
        ("k2", 0.0),
        ("p1", 0.0),
        ("p2", 0.0),
    ] {
        tf[k] = serde_json::json!(v);
    }
    std::fs::write(true_dir.join("transforms.json"), tf.to_string()).unwrap();
    let mut psnr = Vec::new();
    for (name, data) in [("imported", &imported), ("true", &true_dir)] {
        let run = tmp.path().join(format!("run-{name}"));
        let t = Instant::now();
        msth(&[
            "train",
            data.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
            "--preset",
            "balanced",
            "--iters",
            &iters,
        ])
        .unwrap();
        let m = read_json(&run.join("metrics.json"));
        let p = m["psnr"].as_f64().unwrap();
        println!(
            "{name} poses: held-out PSNR {p:.2} dB after {iters} steps ({:.0} s)",
            t.elapsed().as_secs_f64()
        );
        psnr.push(p);
    }
    assert!(
        psnr[0] > psnr[1] - 1.0,
        "imported {:.2} dB vs true {:.2} dB",
        psnr[0],
        psnr[1]
    );
}
