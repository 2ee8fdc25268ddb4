//! nerfstudio datasets: one `transforms.json` for all frames.
//!
//! The file has the fields of [`super::dnerf`] (intrinsics `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`
//! or `camera_angle_x`, at the top level or per frame; per-frame `file_path`,
//! `transform_matrix`, optional `camera_id`), plus:
//! - optional distortion `k1`, `k2`, `k3`, `p1`, `p2` (OpenCV model; top level or per frame).
//!   Images are undistorted at load time to the pinhole camera with the same `fl_x, fl_y, cx,
//!   cy`, by bilinear resampling ([`super::undistort`]); `camera_model` must then be `OPENCV`
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

use super::dnerf::{
    self, assemble, camera_ids, field_error, image_path, parse_transforms, FrameSpec,
};
use super::{Dataset, DatasetError};

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
        Some(v) => Err(field_error(
            path,
            key,
            format!("expected a list of file names, got {}", dnerf::type_name(v)),
        )),
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
    let listed_train = name_list(&file.root, "train_filenames", &path)?
        .map(|n| select(dir, &file.frames, &n, "train_filenames", &path))
        .transpose()?;
    let mut train = Vec::new();
    let mut test = Vec::new();
    for (i, f) in file.frames.iter().enumerate() {
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
    assemble(dir, &train, &test, file.scene_box, &opts.json)
}
