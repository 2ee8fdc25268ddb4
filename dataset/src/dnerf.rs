//! D-NeRF / Blender-NeRF JSON datasets: [`load`] (validating every field) and [`write`].
//!
//! Layout of a dataset folder:
//!
//! ```text
//! transforms_train.json            required
//! transforms_test.json             else transforms_val.json
//! train/r_000.png ... (any paths)  named by each frame's `file_path`
//! ```
//!
//! Each transforms file is an object with intrinsics at the top level and a `frames` list:
//! - intrinsics: `camera_angle_x` (horizontal field of view, square pixels, centred principal
//!   point), or the nerfstudio fields `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` (each optional except
//!   `fl_x`/`fl_y`: `fl_y` defaults to `fl_x`, the principal point to the image centre). Any of
//!   them may also appear per frame, where they override the top-level value; nerfstudio fields win
//!   over `camera_angle_x`;
//! - `frames[i].file_path`: image path relative to the folder (`.png` is appended when the path has
//!   no extension, as in D-NeRF);
//! - `frames[i].time`: normalised time, finite, in `[0, 1]` (required);
//! - `frames[i].transform_matrix`: 4x4 (or 3x4) camera-to-world matrix, row-major, OpenGL camera
//!   axes (see `msth_core::camera`); the bottom row must be `[0, 0, 0, 1]`;
//! - extensions: `frames[i].camera_id` (non-negative integer, physical camera of multi-view video)
//!   and top-level `scene_box: {"min": [x, y, z], "max": [x, y, z]}`.
//!
//! Images: RGBA is composited on white (`rgb * a + (1 - a)`, straight alpha, D-NeRF convention),
//! grey is expanded to RGB, 16-bit is reduced to 8-bit. The dataset background is white.
//! The transforms file itself is read by [`crate::transforms`] (shared with nerfstudio); this
//! module is the D-NeRF layout around it, read and written.
//!
//! Scene bounds when not given: [`SceneBounds::dnerf_default`] if any image has transparency
//! (object captures), otherwise a contraction around the point closest to all training cameras'
//! optical axes (forward-facing / stage captures).

use std::collections::BTreeMap;
use std::path::Path;

use msth_core::{Camera, SceneBounds};
use rayon::prelude::*;
use serde::Serialize;

pub use crate::bounds::contracted_bounds_from_cameras;
use crate::cache::{FrameStorage, ProgressFn};
use crate::imageio;
use crate::staging::{StagingDir, StagingError};
pub use crate::transforms::SAME_POSE_TOLERANCE;
use crate::transforms::{assemble_with_storage, parse_transforms};
use crate::{Dataset, DatasetError, View};

/// How to load a dataset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoadOptions {
    /// Integer downscale factor (1 = full resolution). Images are reduced with an area (box)
    /// filter; a remainder of `size % downscale` pixels at the right and bottom is cropped.
    pub downscale: u32,
    /// Scene bounds to use instead of the file's `scene_box` or the automatic choice.
    pub bounds: Option<SceneBounds>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            downscale: 1,
            bounds: None,
        }
    }
}

/// Loads a D-NeRF / Blender JSON dataset from `dir` (see the module header for the format).
///
/// Every problem is reported as a [`DatasetError`] naming the file and, where relevant, the JSON
/// field; this function does not panic on any input.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset, DatasetError> {
    load_with_storage(dir, opts, &FrameStorage::Memory, None)
}

/// [`load`] with the frames in `storage` (see [`assemble_with_storage`] for what goes to a
/// frame cache) and decoding progress reported to `progress`.
pub fn load_with_storage(
    dir: &Path,
    opts: &LoadOptions,
    storage: &FrameStorage,
    progress: Option<&ProgressFn>,
) -> Result<Dataset, DatasetError> {
    if opts.downscale == 0 {
        return Err(DatasetError::Invalid {
            path: dir.to_path_buf(),
            message: "downscale factor must be at least 1".into(),
        });
    }
    if let Some(b) = &opts.bounds {
        b.validate().map_err(|message| DatasetError::Invalid {
            path: dir.to_path_buf(),
            message: format!("bounds override: {message}"),
        })?;
    }
    let train_path = dir.join("transforms_train.json");
    let train_file = parse_transforms(dir, &train_path, true)?;
    let test_path = ["transforms_test.json", "transforms_val.json"]
        .iter()
        .map(|n| dir.join(n))
        .find(|p| p.exists())
        .ok_or_else(|| DatasetError::Invalid {
            path: dir.join("transforms_test.json"),
            message: "missing (and there is no transforms_val.json either)".into(),
        })?;
    let test_file = parse_transforms(dir, &test_path, true)?;
    let scene_box = train_file.scene_box.or(test_file.scene_box);
    assemble_with_storage(
        dir,
        &train_file.frames,
        &test_file.frames,
        scene_box,
        opts,
        storage,
        progress,
    )
}

// ---------------------------------------------------------------------------------------------
// Writing

#[derive(Serialize)]
struct BoxOut {
    min: [f32; 3],
    max: [f32; 3],
}

#[derive(Serialize)]
struct FrameOut {
    file_path: String,
    time: f32,
    transform_matrix: [[f32; 4]; 4],
    #[serde(skip_serializing_if = "Option::is_none")]
    camera_id: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    fl_x: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    fl_y: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    cx: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    cy: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    w: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    h: Option<u32>,
}

#[derive(Serialize)]
struct TransformsOut {
    camera_angle_x: f32,
    fl_x: f32,
    fl_y: f32,
    cx: f32,
    cy: f32,
    w: u32,
    h: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    scene_box: Option<BoxOut>,
    frames: Vec<FrameOut>,
}

fn intrinsics_equal(a: &Camera, b: &Camera) -> bool {
    (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (b.fx, b.fy, b.cx, b.cy, b.width, b.height)
}

/// File stems (`r_000` or `camNN_TTTT`, per-camera running index) for the views of one split.
fn image_stems(views: &[View]) -> Vec<String> {
    let mut per_camera: BTreeMap<usize, usize> = BTreeMap::new();
    views
        .iter()
        .enumerate()
        .map(|(i, v)| match v.camera_id {
            None => format!("r_{i:03}"),
            Some(c) => {
                let k = per_camera.entry(c).or_insert(0);
                *k += 1;
                format!("cam{c:02}_{:04}", *k - 1)
            }
        })
        .collect()
}

fn transforms_for(
    views: &[View],
    stems: &[String],
    subdir: &str,
    scene_box: Option<&SceneBounds>,
) -> Option<TransformsOut> {
    let first = views.first()?.camera;
    let frames = views
        .iter()
        .zip(stems)
        .map(|(v, stem)| {
            let c = &v.camera;
            let differs = !intrinsics_equal(c, &first);
            let m = c.world_from_camera.transpose().to_cols_array_2d();
            FrameOut {
                file_path: format!("./{subdir}/{stem}"),
                time: v.time,
                transform_matrix: m,
                camera_id: v.camera_id,
                fl_x: differs.then_some(c.fx),
                fl_y: differs.then_some(c.fy),
                cx: differs.then_some(c.cx),
                cy: differs.then_some(c.cy),
                w: differs.then_some(c.width),
                h: differs.then_some(c.height),
            }
        })
        .collect();
    let scene_box = match scene_box {
        Some(SceneBounds::Box { min, max }) => Some(BoxOut {
            min: min.to_array(),
            max: max.to_array(),
        }),
        _ => None,
    };
    Some(TransformsOut {
        camera_angle_x: 2.0 * (0.5 * first.width as f32 / first.fx).atan(),
        fl_x: first.fx,
        fl_y: first.fy,
        cx: first.cx,
        cy: first.cy,
        w: first.width,
        h: first.height,
        scene_box,
        frames,
    })
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn write_json(path: &Path, value: &TransformsOut) -> Result<(), DatasetError> {
    let mut bytes = serde_json::to_vec_pretty(value).map_err(|e| DatasetError::Json {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    bytes.push(b'\n');
    std::fs::write(path, bytes).map_err(io_error(path))
}

fn write_split(root: &Path, subdir: &str, views: &[View]) -> Result<Vec<String>, DatasetError> {
    let folder = root.join(subdir);
    std::fs::create_dir(&folder).map_err(io_error(&folder))?;
    let stems = image_stems(views);
    views
        .par_iter()
        .zip(stems.par_iter())
        .map(|(v, stem)| {
            let path = folder.join(format!("{stem}.png"));
            let file = std::fs::File::create(&path).map_err(io_error(&path))?;
            imageio::encode_png(std::io::BufWriter::new(file), &v.image).map_err(|e| {
                DatasetError::Image {
                    path: path.clone(),
                    message: e.to_string(),
                }
            })
        })
        .collect::<Result<Vec<()>, DatasetError>>()?;
    Ok(stems)
}

fn write_into(dataset: &Dataset, root: &Path) -> Result<(), DatasetError> {
    let box_bounds = match dataset.bounds {
        b @ SceneBounds::Box { .. } => Some(b),
        SceneBounds::Contracted { .. } => None,
    };
    let splits: [(&str, &str, &[View]); 2] = [
        ("train", "transforms_train.json", &dataset.train),
        ("test", "transforms_test.json", &dataset.test),
    ];
    for (subdir, json_name, views) in splits {
        let json = root.join(json_name);
        if views.is_empty() {
            return Err(DatasetError::Invalid {
                path: json,
                message: format!("the dataset has no {subdir} views to write"),
            });
        }
        let stems = write_split(root, subdir, views)?;
        if let Some(t) = transforms_for(views, &stems, subdir, box_bounds.as_ref()) {
            write_json(&json, &t)?;
        }
        if subdir == "test" {
            let val_views: Vec<View> = views.iter().step_by(3).cloned().collect();
            let val_stems: Vec<String> = stems.iter().step_by(3).cloned().collect();
            if let Some(t) = transforms_for(&val_views, &val_stems, subdir, box_bounds.as_ref()) {
                write_json(&root.join("transforms_val.json"), &t)?;
            }
        }
    }
    Ok(())
}

/// Writes `dataset` to `dir` in the layout [`load`] reads: `transforms_{train,test,val}.json`
/// (val = every third test view, sharing the test images), PNGs in `train/` and `test/` named
/// `r_000.png` (monocular) or `camNN_TTTT.png` (with camera ids, `TTTT` counting that camera's
/// views). Intrinsics go at the top level as both `camera_angle_x` and `fl_x, fl_y, cx, cy, w, h`
/// (taken from the first view of the split; frames with other intrinsics repeat them per frame),
/// `camera_id` per frame when present, `scene_box` when the bounds are a box.
///
/// The folder is built as a sibling staging folder ([`StagingDir`]) and renamed to `dir` at the
/// end, so a failure leaves no partial dataset. `dir` must not exist or be an empty folder.
pub fn write(dataset: &Dataset, dir: &Path) -> Result<(), DatasetError> {
    let staging = StagingDir::new(dir).map_err(|e| match e {
        StagingError::NotEmpty(path) => DatasetError::Invalid {
            path,
            message: "refusing to write a dataset here: exists and is not an empty folder".into(),
        },
        e => staging_error(e),
    })?;
    write_into(dataset, staging.path())?;
    staging.commit().map_err(staging_error)
}

fn staging_error(e: StagingError) -> DatasetError {
    match e {
        StagingError::Io { path, source } => DatasetError::Io { path, source },
        StagingError::NotAFolderName(path) => DatasetError::Invalid {
            path,
            message: "not a folder name".into(),
        },
        StagingError::NotEmpty(path) => DatasetError::Invalid {
            path,
            message: "exists and is not an empty folder".into(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use serde_json::json;
    use serde_json::Value;

    /// Writes a `width x height` PNG, RGBA when `alpha` is given.
    fn png(path: &Path, width: u32, height: u32, value: u8, alpha: Option<u8>) {
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).unwrap();
        }
        match alpha {
            Some(a) => {
                let mut px = Vec::new();
                for _ in 0..width * height {
                    px.extend_from_slice(&[value, value / 2, 0, a]);
                }
                image::RgbaImage::from_raw(width, height, px)
                    .unwrap()
                    .save(path)
                    .unwrap();
            }
            None => {
                image::RgbImage::from_raw(width, height, vec![value; (width * height * 3) as usize])
                    .unwrap()
                    .save(path)
                    .unwrap()
            }
        }
    }

    fn pose(x: f64) -> Value {
        json!([
            [1.0, 0.0, 0.0, x],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 4.0],
            [0.0, 0.0, 0.0, 1.0]
        ])
    }

    /// A valid two-split fixture: 2 train frames, 1 test frame, 4x4 RGBA images.
    fn fixture() -> (tempfile::TempDir, Value, Value) {
        let dir = tempfile::tempdir().unwrap();
        for name in ["train/r_000", "train/r_001", "test/r_000"] {
            png(
                &dir.path().join(format!("{name}.png")),
                4,
                4,
                200,
                Some(128),
            );
        }
        let train = json!({
            "camera_angle_x": 0.69,
            "frames": [
                {"file_path": "./train/r_000", "time": 0.0, "transform_matrix": pose(0.0)},
                {"file_path": "train/r_001.png", "time": 1.0, "transform_matrix": pose(1.0)},
            ]
        });
        let test = json!({
            "camera_angle_x": 0.69,
            "frames": [{"file_path": "./test/r_000", "time": 0.5, "transform_matrix": pose(2.0)}]
        });
        (dir, train, test)
    }

    fn put(dir: &Path, name: &str, v: &Value) {
        std::fs::write(dir.join(name), serde_json::to_vec(v).unwrap()).unwrap();
    }

    fn load_fixture(train: &Value, test: &Value, dir: &Path) -> Result<Dataset, DatasetError> {
        put(dir, "transforms_train.json", train);
        put(dir, "transforms_test.json", test);
        load(dir, &LoadOptions::default())
    }

    fn expect_error(dir: &Path, train: &Value, test: &Value, needles: &[&str]) -> String {
        let err = load_fixture(train, test, dir).expect_err("load should fail");
        let msg = err.to_string();
        for n in needles {
            assert!(msg.contains(n), "`{msg}` does not mention `{n}`");
        }
        msg
    }

    #[test]
    fn frame_cache_for_opaque_images_memory_for_transparent_ones() {
        let (dir, train, test) = fixture();
        let cache = tempfile::tempdir().unwrap();
        let file = cache.path().join("d.frames");
        let disk = FrameStorage::Disk(file.clone());
        // Transparent (alpha 128): no cache, alpha kept.
        put(dir.path(), "transforms_train.json", &train);
        put(dir.path(), "transforms_test.json", &test);
        let d = load_with_storage(dir.path(), &LoadOptions::default(), &disk, None).unwrap();
        assert!(d
            .train
            .iter()
            .all(|v| v.alpha.is_some() && !v.image.data.is_mapped()));
        assert_eq!(d.bounds, SceneBounds::dnerf_default());
        assert_eq!(std::fs::read_dir(cache.path()).unwrap().count(), 0);
        // Opaque: the same pixels from the cache, reused on the next load.
        for name in ["train/r_000", "train/r_001", "test/r_000"] {
            png(&dir.path().join(format!("{name}.png")), 4, 4, 90, None);
        }
        let mem = load(dir.path(), &LoadOptions::default()).unwrap();
        let opts = LoadOptions {
            downscale: 2,
            bounds: None,
        };
        let mem2 = load(dir.path(), &opts).unwrap();
        for (o, m) in [(LoadOptions::default(), &mem), (opts, &mem2)] {
            let c = load_with_storage(dir.path(), &o, &disk, None).unwrap();
            for (a, b) in m
                .train
                .iter()
                .chain(&m.test)
                .zip(c.train.iter().chain(&c.test))
            {
                assert!(b.image.data.is_mapped() && b.alpha.is_none());
                assert_eq!(a.image, b.image);
                assert_eq!(a.camera, b.camera);
            }
            assert_eq!(c.bounds, m.bounds);
        }
        let modified = std::fs::metadata(&file).unwrap().modified().unwrap();
        load_with_storage(dir.path(), &opts, &disk, None).unwrap();
        assert_eq!(
            std::fs::metadata(&file).unwrap().modified().unwrap(),
            modified
        );
        // A broken image is still named.
        std::fs::write(dir.path().join("train/r_001.png"), b"junk").unwrap();
        let e = load_with_storage(dir.path(), &opts, &disk, None).unwrap_err();
        assert!(e.to_string().contains("r_001.png"), "{e}");
    }

    #[test]
    fn valid_fixture_loads() {
        let (dir, train, test) = fixture();
        let d = load_fixture(&train, &test, dir.path()).unwrap();
        assert_eq!((d.train.len(), d.test.len(), d.num_frames), (2, 1, 2));
        assert_eq!(d.bounds, SceneBounds::dnerf_default());
        assert_eq!(d.background, [1.0; 3]);
        assert!(d.train.iter().all(|v| v.camera_id.is_none()));
        // 200 * 128/255 + 255 * 127/255 = 100.4 + 127 = 227.4
        assert_eq!(&d.train[0].image.data[0..3], &[227, 177, 127]);
        let c = d.train[1].camera;
        assert!((c.fx - 2.0 / (0.345f32).tan()).abs() < 1e-4);
        assert_eq!(c.center(), Vec3::new(1.0, 0.0, 4.0));
        assert_eq!(d.name, dir.path().file_name().unwrap().to_string_lossy());
    }

    #[test]
    fn missing_transforms_files() {
        let dir = tempfile::tempdir().unwrap();
        let err = load(dir.path(), &LoadOptions::default()).unwrap_err();
        assert!(err.to_string().contains("transforms_train.json"), "{err}");
        let (dir, train, _) = fixture();
        put(dir.path(), "transforms_train.json", &train);
        let err = load(dir.path(), &LoadOptions::default()).unwrap_err();
        assert!(err.to_string().contains("transforms_test.json"), "{err}");
        // transforms_val.json is the fallback.
        put(dir.path(), "transforms_val.json", &train);
        assert_eq!(
            load(dir.path(), &LoadOptions::default())
                .unwrap()
                .test
                .len(),
            2
        );
    }

    #[test]
    fn malformed_json() {
        let (dir, _, test) = fixture();
        put(dir.path(), "transforms_test.json", &test);
        std::fs::write(
            dir.path().join("transforms_train.json"),
            b"{\"frames\": [ {",
        )
        .unwrap();
        let err = load(dir.path(), &LoadOptions::default()).unwrap_err();
        assert!(matches!(err, DatasetError::Json { .. }));
        assert!(err.to_string().contains("transforms_train.json"), "{err}");
        // NaN is not JSON.
        std::fs::write(
            dir.path().join("transforms_train.json"),
            b"{\"camera_angle_x\": NaN}",
        )
        .unwrap();
        assert!(matches!(
            load(dir.path(), &LoadOptions::default()),
            Err(DatasetError::Json { .. })
        ));
        // Not an object at the top level.
        std::fs::write(dir.path().join("transforms_train.json"), b"[1, 2]").unwrap();
        let err = load(dir.path(), &LoadOptions::default()).unwrap_err();
        assert!(err.to_string().contains("transforms_train.json"), "{err}");
    }

    #[test]
    fn wrong_types_and_shapes() {
        let (dir, train, test) = fixture();
        let cases: Vec<(Value, &[&str])> = vec![
            (
                json!({"camera_angle_x": 0.69, "frames": []}),
                &["frames", "empty"],
            ),
            (
                json!({"camera_angle_x": 0.69, "frames": {}}),
                &["frames", "array"],
            ),
            (json!({"camera_angle_x": 0.69}), &["frames", "missing"]),
            (
                json!({"camera_angle_x": "wide", "frames": train["frames"]}),
                &["camera_angle_x"],
            ),
            (
                json!({"camera_angle_x": -1.0, "frames": train["frames"]}),
                &["camera_angle_x"],
            ),
            (
                json!({"camera_angle_x": 1e39, "frames": train["frames"]}),
                &["camera_angle_x"],
            ),
            (
                json!({"frames": train["frames"]}),
                &["camera_angle_x", "missing"],
            ),
            (
                json!({"camera_angle_x": 0.69, "frames": [3]}),
                &["frames[0]", "object"],
            ),
            (
                json!({"camera_angle_x": 0.69, "frames": [{"file_path": 7, "time": 0.0,
                       "transform_matrix": pose(0.0)}]}),
                &["frames[0].file_path"],
            ),
            (
                json!({"camera_angle_x": 0.69, "frames": [{"file_path": "train/r_000",
                       "time": "NaN", "transform_matrix": pose(0.0)}]}),
                &["frames[0].time", "string"],
            ),
            (
                json!({"camera_angle_x": 0.69, "frames": [{"file_path": "train/r_000",
                       "time": 0.0, "transform_matrix": [[1, 0, 0], [0, 1, 0]]}]}),
                &["frames[0].transform_matrix"],
            ),
            (
                json!({"camera_angle_x": 0.69, "frames": [{"file_path": "train/r_000",
                       "time": 0.0, "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0],
                       [0, 0, 1, 0], [1, 2, 3, 1]]}]}),
                &["frames[0].transform_matrix", "bottom row"],
            ),
            (
                json!({"camera_angle_x": 0.69, "frames": [{"file_path": "train/r_000",
                       "time": 0.0, "transform_matrix": pose(0.0), "camera_id": -2}]}),
                &["frames[0].camera_id"],
            ),
            (
                json!({"camera_angle_x": 0.69, "scene_box": {"min": [0, 0, 0], "max": [1, 0, 1]},
                       "frames": train["frames"]}),
                &["scene_box"],
            ),
            (
                json!({"fl_x": 10.0, "w": 8, "frames": train["frames"]}),
                &["`w`", "says 8"],
            ),
        ];
        for (bad_train, needles) in cases {
            let mut n = vec!["transforms_train.json"];
            n.extend_from_slice(needles);
            expect_error(dir.path(), &bad_train, &test, &n);
        }
    }

    #[test]
    fn missing_image() {
        let (dir, mut train, test) = fixture();
        train["frames"][1]["file_path"] = json!("./train/nope");
        expect_error(dir.path(), &train, &test, &["nope.png", "cannot read"]);
        std::fs::write(dir.path().join("train/garbage.png"), b"not a png").unwrap();
        train["frames"][1]["file_path"] = json!("./train/garbage");
        expect_error(dir.path(), &train, &test, &["garbage.png", "decode"]);
    }

    #[test]
    fn mixed_sizes() {
        let (dir, train, test) = fixture();
        png(&dir.path().join("test/r_000.png"), 5, 4, 10, Some(255));
        expect_error(
            dir.path(),
            &train,
            &test,
            &["test/r_000.png", "5x4", "4x4", "r_000.png"],
        );
    }

    #[test]
    fn bad_poses() {
        let (dir, mut train, test) = fixture();
        let singular = json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]);
        for (matrix, why) in [(singular, "invertible"), (pose(1e39), "non-finite")] {
            train["frames"][0]["transform_matrix"] = matrix;
            let needles = ["transforms_train.json", "frames[0].transform_matrix", why];
            expect_error(dir.path(), &train, &test, &needles);
        }
    }

    #[test]
    fn bad_times() {
        let (dir, mut train, test) = fixture();
        train["frames"][1]["time"] = json!(1.5);
        expect_error(
            dir.path(),
            &train,
            &test,
            &["transforms_train.json", "frames[1].time", "outside"],
        );
        train["frames"][1]["time"] = json!(-0.1);
        expect_error(dir.path(), &train, &test, &["frames[1].time"]);
        train["frames"][1].as_object_mut().unwrap().remove("time");
        expect_error(
            dir.path(),
            &train,
            &test,
            &["transforms_train.json", "frames[1].time", "missing"],
        );
        let mut test = test;
        test["frames"][0]["time"] = json!(null);
        train["frames"][1]["time"] = json!(1);
        expect_error(
            dir.path(),
            &train,
            &test,
            &["transforms_test.json", "frames[0].time"],
        );
    }

    #[test]
    fn nerfstudio_intrinsics_and_options() {
        let (dir, mut train, mut test) = fixture();
        for t in [&mut train, &mut test] {
            let o = t.as_object_mut().unwrap();
            o.remove("camera_angle_x");
            o.insert("fl_x".into(), json!(5.0));
            o.insert("cx".into(), json!(1.5));
            o.insert("w".into(), json!(4));
            o.insert("h".into(), json!(4));
        }
        train["frames"][1]["fl_y"] = json!(6.0);
        let d = load_fixture(&train, &test, dir.path()).unwrap();
        let c0 = d.train[0].camera;
        assert_eq!((c0.fx, c0.fy, c0.cx, c0.cy), (5.0, 5.0, 1.5, 2.0));
        assert_eq!(d.train[1].camera.fy, 6.0);
        // Downscale by 2: 2x2 images, halved intrinsics; factor 0 and 5 are errors.
        let half = load(
            dir.path(),
            &LoadOptions {
                downscale: 2,
                bounds: None,
            },
        )
        .unwrap();
        let c = half.train[0].camera;
        assert_eq!((c.width, c.height, c.fx, c.cx), (2, 2, 2.5, 0.75));
        assert_eq!(half.train[0].image.width, 2);
        for f in [0, 5] {
            let opts = LoadOptions {
                downscale: f,
                bounds: None,
            };
            assert!(load(dir.path(), &opts).is_err());
        }
        let b = SceneBounds::Box {
            min: Vec3::ZERO,
            max: Vec3::ONE,
        };
        let opts = LoadOptions {
            downscale: 1,
            bounds: Some(b),
        };
        assert_eq!(load(dir.path(), &opts).unwrap().bounds, b);
    }

    #[test]
    fn camera_grouping_and_contraction() {
        let dir = tempfile::tempdir().unwrap();
        let mut frames = Vec::new();
        // Three opaque cameras looking at the origin from x, y, z axes, two times each.
        let eyes = [
            Vec3::new(3.0, 0.0, 0.0),
            Vec3::new(0.0, -4.0, 0.0),
            Vec3::new(0.0, 0.0, 5.0),
        ];
        for (c, eye) in eyes.iter().enumerate() {
            let up = if c == 2 { Vec3::Y } else { Vec3::Z };
            let cam = Camera::look_at(4, 4, 0.7, *eye, Vec3::ZERO, up);
            let m = cam.world_from_camera.transpose().to_cols_array_2d();
            for t in 0..2 {
                let name = format!("cam{c}/{t}.png");
                png(&dir.path().join(&name), 4, 4, 50, None);
                frames.push(json!({"file_path": name, "time": t as f64, "transform_matrix": m}));
            }
        }
        let train = json!({"camera_angle_x": 0.7, "frames": frames});
        let test = json!({"camera_angle_x": 0.7, "frames": [frames[2].clone()]});
        let d = load_fixture(&train, &test, dir.path()).unwrap();
        let ids: Vec<_> = d.train.iter().map(|v| v.camera_id).collect();
        assert_eq!(ids, [Some(0), Some(0), Some(1), Some(1), Some(2), Some(2)]);
        assert_eq!(d.test[0].camera_id, Some(1));
        assert_eq!(d.num_frames, 2);
        match d.bounds {
            SceneBounds::Contracted { center, radius } => {
                assert!(center.length() < 1e-4, "{center}");
                assert!((radius - 4.0).abs() < 1e-4, "{radius}");
            }
            b => panic!("expected contraction, got {b:?}"),
        }
        // Explicit ids must be given for all frames or none.
        let mut train2 = train.clone();
        train2["frames"][0]["camera_id"] = json!(7);
        expect_error(dir.path(), &train2, &test, &["camera_id", "frames[1]"]);
    }

    #[test]
    fn parallel_axes_fall_back_to_mean() {
        let cams: Vec<Camera> = (0..3)
            .map(|i| {
                let eye = Vec3::new(i as f32, 0.0, 4.0);
                Camera::look_at(4, 4, 0.7, eye, eye - Vec3::Z, Vec3::Y)
            })
            .collect();
        match contracted_bounds_from_cameras(&cams) {
            SceneBounds::Contracted { center, radius } => {
                assert!((center - Vec3::new(1.0, 0.0, 4.0)).length() < 1e-5);
                assert!((radius - 1.0).abs() < 1e-5);
            }
            b => panic!("{b:?}"),
        }
    }

    #[test]
    fn write_load_monocular_with_downscale_and_grey() {
        // Monocular, grey image input, odd size with downscale 2 (crop of the remainder).
        let dir = tempfile::tempdir().unwrap();
        let grey = image::GrayImage::from_fn(5, 3, |x, _| image::Luma([x as u8 * 50]));
        std::fs::create_dir_all(dir.path().join("train")).unwrap();
        grey.save(dir.path().join("train/a.png")).unwrap();
        let train = json!({"camera_angle_x": 1.0, "frames": [
            {"file_path": "train/a", "time": 0.25, "transform_matrix": pose(0.0)}]});
        let d = load_fixture(&train, &train, dir.path()).unwrap();
        assert_eq!(d.train[0].image.data[3..6], [50, 50, 50]);
        assert_eq!(d.num_frames, 1);
        let opts = LoadOptions {
            downscale: 2,
            bounds: None,
        };
        let h = load(dir.path(), &opts).unwrap();
        let im = &h.train[0].image;
        assert_eq!((im.width, im.height), (2, 1));
        // mean of 0, 50, 0, 50 = 25; of 100, 150, 100, 150 = 125
        assert_eq!(im.data, [25, 25, 25, 125, 125, 125]);
        assert_eq!((h.train[0].camera.width, h.train[0].camera.height), (2, 1));
        assert!(matches!(h.bounds, SceneBounds::Contracted { .. }));
    }
}
