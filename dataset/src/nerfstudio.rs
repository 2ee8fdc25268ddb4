//! nerfstudio datasets: one `transforms.json` for all frames.
//!
//! The file has the fields of [`crate::dnerf`] (intrinsics `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`
//! or `camera_angle_x`, at the top level or per frame; per-frame `file_path`,
//! `transform_matrix`, optional `camera_id`), plus:
//! - optional distortion `k1`, `k2`, `k3`, `p1`, `p2` (OpenCV model; top level or per frame).
//!   Images are undistorted at load time to the pinhole camera with the same `fl_x, fl_y, cx,
//!   cy`, by bilinear resampling ([`crate::undistort`]); `camera_model` must then be `OPENCV`
//!   (or absent); fisheye and other models are refused;
//! - optional per-frame `time` in `[0, 1]`: all frames have one or none does (a static scene,
//!   time 0).
//!
//! Train / test split, first rule that applies:
//! 1. the file lists `test_filenames` (else `val_filenames`) and optionally `train_filenames`,
//!    as nerfstudio does: those frames are the test set, the listed (or all other) frames train;
//! 2. the frames come from several physical cameras that each saw several frames (multi-view
//!    video: frames grouped by `camera_id`, else by identical poses): the camera numbered
//!    [`NerfstudioOptions::test_camera`] (default 0: `camera_id` 0, or the camera of the first
//!    frame) is held out;
//! 3. otherwise every 8th frame in file order (0, 8, 16, ...) is a test frame (the LLFF
//!    `llffhold = 8` rule).

use std::path::Path;

use serde_json::Value;

use crate::cache::{FrameStorage, ProgressFn};
use crate::dnerf;
use crate::transforms::{
    assemble_with_storage, camera_ids, field_error, image_path, parse_transforms, wrong_type,
    FrameSpec,
};
use crate::{Dataset, DatasetError};

/// How to load a nerfstudio dataset.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NerfstudioOptions {
    /// Downscale factor and bounds override, as for D-NeRF.
    pub json: dnerf::LoadOptions,
    /// The held-out camera for multi-camera captures (split rule 2).
    pub test_camera: Option<usize>,
}

/// Every `HOLD`-th frame is a test frame under split rule 3.
pub const HOLD: usize = 8;

fn name_list(
    root: &serde_json::Map<String, Value>,
    key: &str,
    path: &Path,
) -> Result<Option<Vec<String>>, DatasetError> {
    match root.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::Array(a)) => a
            .iter()
            .enumerate()
            .map(|(i, v)| {
                v.as_str().map(str::to_string).ok_or_else(|| {
                    field_error(path, &format!("{key}[{i}]"), "expected a file name")
                })
            })
            .collect::<Result<Vec<_>, _>>()
            .map(Some),
        Some(v) => Err(wrong_type(path, key, "a list of file names", v)),
    }
}

/// Indices of the frames named by `names` (each must name a frame).
fn select(
    dir: &Path,
    frames: &[FrameSpec],
    names: &[String],
    key: &str,
    path: &Path,
) -> Result<Vec<bool>, DatasetError> {
    let mut chosen = vec![false; frames.len()];
    for (i, n) in names.iter().enumerate() {
        let p = image_path(dir, n);
        let Some(k) = frames.iter().position(|f| f.image == p) else {
            return Err(field_error(
                path,
                &format!("{key}[{i}]"),
                format!("`{n}` is not the file_path of any frame"),
            ));
        };
        chosen[k] = true;
    }
    Ok(chosen)
}

/// Which frames are test frames (see the module docs for the rules).
fn split(
    dir: &Path,
    path: &Path,
    frames: &[FrameSpec],
    root: &serde_json::Map<String, Value>,
    test_camera: Option<usize>,
) -> Result<Vec<bool>, DatasetError> {
    let test_list = match name_list(root, "test_filenames", path)? {
        Some(l) => Some((l, "test_filenames")),
        None => name_list(root, "val_filenames", path)?.map(|l| (l, "val_filenames")),
    };
    if let Some((names, key)) = test_list {
        let test = select(dir, frames, &names, key, path)?;
        if let Some(train_names) = name_list(root, "train_filenames", path)? {
            let train = select(dir, frames, &train_names, "train_filenames", path)?;
            if let Some(i) = (0..frames.len()).find(|&i| train[i] && test[i]) {
                return Err(field_error(
                    path,
                    "train_filenames",
                    format!(
                        "{} is listed for training and for testing",
                        frames[i].image.display()
                    ),
                ));
            }
            // Frames in neither list are left out by `load`.
        }
        return Ok(test);
    }
    let (ids, _) = camera_ids(frames, &[])?;
    let mut cams: Vec<usize> = ids.iter().flatten().copied().collect();
    cams.sort();
    let counts = {
        let mut c = cams.clone();
        c.dedup();
        c.len()
    };
    let multi_view = counts >= 2 && cams.len() > counts;
    if multi_view {
        let explicit = frames.iter().any(|f| f.camera_id.is_some());
        let want = test_camera.unwrap_or(if explicit { 0 } else { ids[0].unwrap_or(0) });
        if !ids.contains(&Some(want)) {
            return Err(DatasetError::Invalid {
                path: path.to_path_buf(),
                message: format!("there is no camera {want} to hold out ({counts} cameras)"),
            });
        }
        return Ok(ids.iter().map(|&id| id == Some(want)).collect());
    }
    Ok((0..frames.len()).map(|i| i % HOLD == 0).collect())
}

/// Loads `dir/transforms.json` (see the module docs).
pub fn load(dir: &Path, opts: &NerfstudioOptions) -> Result<Dataset, DatasetError> {
    load_with_storage(dir, opts, &FrameStorage::Memory, None)
}

/// [`load`] with the frames in `storage` (as for [`dnerf::load_with_storage`]).
pub fn load_with_storage(
    dir: &Path,
    opts: &NerfstudioOptions,
    storage: &FrameStorage,
    progress: Option<&ProgressFn>,
) -> Result<Dataset, DatasetError> {
    if opts.json.downscale == 0 {
        return Err(DatasetError::Invalid {
            path: dir.to_path_buf(),
            message: "downscale factor must be at least 1".into(),
        });
    }
    let path = dir.join("transforms.json");
    let file = parse_transforms(dir, &path, false)?;
    if let Some(m) = file.root.get("camera_model") {
        let model = m.as_str().unwrap_or("");
        if !matches!(model, "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE") {
            return Err(field_error(
                &path,
                "camera_model",
                format!("{m} is not supported (OPENCV or PINHOLE; fisheye models are not)"),
            ));
        }
    }
    let with_time = file.frames.iter().filter(|f| f.time.is_some()).count();
    if with_time != 0 && with_time != file.frames.len() {
        let f = file
            .frames
            .iter()
            .find(|f| f.time.is_none())
            .map(|f| f.field("time"))
            .unwrap_or_default();
        return Err(field_error(
            &path,
            &f,
            "missing, but other frames have a time (give it for every frame or none)",
        ));
    }
    let is_test = split(dir, &path, &file.frames, &file.root, opts.test_camera)?;
    // Camera numbers in file order (explicit `camera_id`s, else pose groups in order of first
    // appearance), fixed before the split so that train and test agree on them.
    let (ids, _) = camera_ids(&file.frames, &[])?;
    let mut frames = file.frames.clone();
    for (f, id) in frames.iter_mut().zip(ids) {
        f.camera_id = id;
    }
    let listed_train = name_list(&file.root, "train_filenames", &path)?
        .map(|n| select(dir, &file.frames, &n, "train_filenames", &path))
        .transpose()?;
    let mut train = Vec::new();
    let mut test = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        if is_test[i] {
            test.push(f.clone());
        } else if listed_train.as_ref().is_none_or(|t| t[i]) {
            train.push(f.clone());
        }
    }
    if train.is_empty() || test.is_empty() {
        return Err(DatasetError::Invalid {
            path,
            message: format!(
                "the split leaves {} training and {} test frames; need at least one of each",
                train.len(),
                test.len()
            ),
        });
    }
    assemble_with_storage(
        dir,
        &train,
        &test,
        file.scene_box,
        &opts.json,
        storage,
        progress,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::Camera;
    use serde_json::json;

    fn pose(eye: Vec3) -> Value {
        let c = Camera::look_at(8, 6, 0.9, eye, Vec3::ZERO, Vec3::Z);
        json!(c.world_from_camera.transpose().to_cols_array_2d())
    }

    fn png(path: &Path, w: u32, h: u32, v: u8) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        image::RgbImage::from_pixel(w, h, image::Rgb([v, v / 2, 255 - v]))
            .save(path)
            .unwrap();
    }

    /// `n` frames `images/f_XX.png`, with `eye(i)` and `time(i)` per frame.
    fn fixture(
        n: usize,
        eye: impl Fn(usize) -> Vec3,
        time: impl Fn(usize) -> Option<f64>,
    ) -> (tempfile::TempDir, Value) {
        let dir = tempfile::tempdir().unwrap();
        let mut frames = Vec::new();
        for i in 0..n {
            let name = format!("images/f_{i:02}.png");
            png(&dir.path().join(&name), 8, 6, (i * 20) as u8);
            let mut f = json!({"file_path": name, "transform_matrix": pose(eye(i))});
            if let Some(t) = time(i) {
                f["time"] = json!(t);
            }
            frames.push(f);
        }
        let root = json!({"fl_x": 7.0, "fl_y": 7.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6,
                          "frames": frames});
        (dir, root)
    }

    fn load_json(
        dir: &Path,
        root: &Value,
        opts: &NerfstudioOptions,
    ) -> Result<Dataset, DatasetError> {
        std::fs::write(
            dir.join("transforms.json"),
            serde_json::to_vec(root).unwrap(),
        )
        .unwrap();
        load(dir, opts)
    }

    fn orbit(i: usize) -> Vec3 {
        let a = i as f32 * 0.3;
        Vec3::new(4.0 * a.cos(), 4.0 * a.sin(), 1.0)
    }

    fn names(views: &[crate::View]) -> Vec<String> {
        views
            .iter()
            .map(|v| v.source.file_name().unwrap().to_string_lossy().into_owned())
            .collect()
    }

    #[test]
    fn monocular_split_every_eighth_frame_and_optional_time() {
        let (dir, root) = fixture(10, orbit, |_| None);
        let d = load_json(dir.path(), &root, &Default::default()).unwrap();
        assert_eq!(names(&d.test), ["f_00.png", "f_08.png"]);
        assert_eq!(d.train.len(), 8);
        assert!(d
            .train
            .iter()
            .all(|v| v.time == 0.0 && v.camera_id.is_none()));
        assert_eq!(d.num_frames, 1);
        let c = d.train[0].camera;
        assert_eq!((c.fx, c.cx, c.width), (7.0, 4.0, 8));
        // With times.
        let (dir, root) = fixture(10, orbit, |i| Some(i as f64 / 9.0));
        let d = load_json(dir.path(), &root, &Default::default()).unwrap();
        assert_eq!(d.test[1].time, 8.0 / 9.0);
        assert_eq!(d.num_frames, 8);
        // Downscale 2.
        let opts = NerfstudioOptions {
            json: dnerf::LoadOptions {
                downscale: 2,
                bounds: None,
            },
            test_camera: None,
        };
        let h = load_json(dir.path(), &root, &opts).unwrap();
        assert_eq!((h.train[0].image.width, h.train[0].camera.fx), (4, 3.5));
    }

    #[test]
    fn jpeg_frames_load() {
        let (dir, mut root) = fixture(3, orbit, |_| None);
        let img = image::RgbImage::from_pixel(8, 6, image::Rgb([200, 100, 50]));
        img.save(dir.path().join("images/photo.jpg")).unwrap();
        root["frames"][1]["file_path"] = json!("images/photo.jpg");
        let d = load_json(dir.path(), &root, &Default::default()).unwrap();
        let p = d.train[0].image.get(3, 3);
        assert!((p[0] - 200.0 / 255.0).abs() < 0.05 && (p[2] - 50.0 / 255.0).abs() < 0.05);
    }

    #[test]
    fn listed_filenames_decide_the_split() {
        let (dir, mut root) = fixture(6, orbit, |_| None);
        root["test_filenames"] = json!(["images/f_02.png", "./images/f_05.png"]);
        let d = load_json(dir.path(), &root, &Default::default()).unwrap();
        assert_eq!(names(&d.test), ["f_02.png", "f_05.png"]);
        assert_eq!(d.train.len(), 4);
        // train_filenames leaves the others out.
        root["train_filenames"] = json!(["images/f_00.png", "images/f_01.png"]);
        let d = load_json(dir.path(), &root, &Default::default()).unwrap();
        assert_eq!(names(&d.train), ["f_00.png", "f_01.png"]);
        root["train_filenames"] = json!(["images/f_02.png"]);
        let e = load_json(dir.path(), &root, &Default::default()).unwrap_err();
        assert!(e.to_string().contains("training and for testing"), "{e}");
        root["test_filenames"] = json!(["images/nope.png"]);
        let e = load_json(dir.path(), &root, &Default::default()).unwrap_err();
        assert!(e.to_string().contains("test_filenames[0]"), "{e}");
    }

    #[test]
    fn multi_camera_video_holds_out_a_camera() {
        // 3 cameras x 3 times, frames camera-major.
        let (dir, root) = fixture(9, |i| orbit(i / 3), |i| Some((i % 3) as f64 / 2.0));
        let d = load_json(dir.path(), &root, &Default::default()).unwrap();
        assert_eq!(names(&d.test), ["f_00.png", "f_01.png", "f_02.png"]);
        assert!(d.test.iter().all(|v| v.camera_id == Some(0)));
        assert_eq!(d.num_frames, 3);
        let opts = NerfstudioOptions {
            test_camera: Some(2),
            ..Default::default()
        };
        let d = load_json(dir.path(), &root, &opts).unwrap();
        assert_eq!(names(&d.test), ["f_06.png", "f_07.png", "f_08.png"]);
        let opts = NerfstudioOptions {
            test_camera: Some(5),
            ..Default::default()
        };
        let e = load_json(dir.path(), &root, &opts).unwrap_err();
        assert!(e.to_string().contains("no camera 5"), "{e}");
    }

    #[test]
    fn broken_files_are_named() {
        let (dir, root) = fixture(4, orbit, |i| Some(i as f64 / 3.0));
        let check = |root: &Value, needles: &[&str]| {
            let e = load_json(dir.path(), root, &Default::default())
                .unwrap_err()
                .to_string();
            for n in needles {
                assert!(e.contains(n), "`{e}` should mention `{n}`");
            }
        };
        // Missing intrinsics.
        let mut r = root.clone();
        for k in ["fl_x", "fl_y"] {
            r.as_object_mut().unwrap().remove(k);
        }
        check(
            &r,
            &["transforms.json", "camera_angle_x", "missing", "fl_x"],
        );
        // `w` disagreeing with the image.
        let mut r = root.clone();
        r["w"] = json!(10);
        check(&r, &["transforms.json", "`w`", "says 10"]);
        // Time on some frames only.
        let mut r = root.clone();
        r["frames"][2].as_object_mut().unwrap().remove("time");
        check(&r, &["frames[2].time", "every frame or none"]);
        // Unsupported camera model; non-numeric distortion.
        let mut r = root.clone();
        r["camera_model"] = json!("OPENCV_FISHEYE");
        check(&r, &["camera_model", "OPENCV_FISHEYE"]);
        let mut r = root.clone();
        r["k1"] = json!("barrel");
        check(&r, &["k1", "expected a number"]);
        let mut r = root.clone();
        r["frames"][1]["p2"] = json!(1e9);
        check(&r, &["frames[1].p2"]);
        // Missing image; missing file.
        let mut r = root.clone();
        r["frames"][3]["file_path"] = json!("images/none.png");
        check(&r, &["none.png", "cannot read"]);
        std::fs::remove_file(dir.path().join("transforms.json")).unwrap();
        let e = load(dir.path(), &Default::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("transforms.json") && e.contains("cannot read"),
            "{e}"
        );
    }

    fn pattern(x: f64, y: f64) -> [u8; 3] {
        [
            (127.5 + 100.0 * (12.0 * x).sin() * (9.0 * y).cos()).round() as u8,
            (127.5 + 100.0 * (10.0 * (x + y)).cos()).round() as u8,
            (127.5 + 80.0 * (14.0 * y - 4.0 * x).sin()).round() as u8,
        ]
    }

    /// A distorted photo made analytically loads as the pinhole image (within resampling error).
    #[test]
    fn distortion_is_undistorted_on_load() {
        use crate::undistort::Distortion;
        let (w, h) = (96u32, 72u32);
        let (fx, fy, cx, cy) = (80.0, 82.0, 48.5, 35.0);
        let d = Distortion {
            k1: -0.3,
            k2: 0.08,
            k3: 0.0,
            p1: 0.001,
            p2: -0.002,
        };
        let render = |distorted: bool| {
            image::RgbImage::from_fn(w, h, |u, v| {
                let (x, y) = ((u as f64 + 0.5 - cx) / fx, (v as f64 + 0.5 - cy) / fy);
                let (x, y) = if distorted {
                    d.undistort_point(x, y).unwrap()
                } else {
                    (x, y)
                };
                image::Rgb(pattern(x, y))
            })
        };
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("images")).unwrap();
        render(true).save(dir.path().join("images/a.png")).unwrap();
        render(true).save(dir.path().join("images/b.png")).unwrap();
        let frame = |n: &str, e: Vec3| json!({"file_path": n, "transform_matrix": pose(e)});
        let mut root = json!({"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": w, "h": h,
            "k1": d.k1, "k2": d.k2, "p1": d.p1, "p2": d.p2, "camera_model": "OPENCV",
            "frames": [frame("images/a.png", orbit(0)), frame("images/b.png", orbit(1))]});
        let loaded = load_json(dir.path(), &root, &Default::default()).unwrap();
        let got = &loaded.test[0].image;
        let want = render(false);
        let (mut se, mut n) = (0.0, 0.0);
        for y in 8..h - 8 {
            for x in 8..w - 8 {
                let i = ((y * w + x) * 3) as usize;
                for c in 0..3 {
                    se += (got.data[i + c] as f64 - want.get_pixel(x, y).0[c] as f64).powi(2);
                    n += 1.0;
                }
            }
        }
        let psnr = 10.0 * (255.0f64 * 255.0 / (se / n)).log10();
        println!("undistorted on load vs analytic pinhole: {psnr:.1} dB");
        assert!(psnr > 38.0, "{psnr}");
        // Without distortion fields, the pixels are the file's.
        for k in ["k1", "k2", "p1", "p2"] {
            root.as_object_mut().unwrap().remove(k);
        }
        let raw = load_json(dir.path(), &root, &Default::default()).unwrap();
        assert_eq!(raw.test[0].image.data, render(true).into_raw());
    }
}
