//! The transforms JSON shared by the D-NeRF ([`crate::dnerf`]) and nerfstudio
//! ([`crate::nerfstudio`]) readers: parsing and checking a transforms file ([`parse_transforms`]),
//! the camera of each frame, camera ids, and assembling the dataset from the frames' images
//! (through the frame cache when one is asked for, [`assemble_with_storage`]).

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3, Vec4};
use msth_core::{Camera, SceneBounds};
use rayon::prelude::*;
use serde_json::{Map, Value};

use crate::bounds::{contracted_bounds_from_cameras, near_from_llff_rows};
use crate::cache::{store_frames, CacheKey, Fingerprint, FrameStorage, ProgressFn};
use crate::dnerf::LoadOptions;
use crate::imageio::{load_image_undistorted, LoadedImage, MAX_SIDE};
use crate::undistort::{Distortion, Intrinsics};
use crate::{Dataset, DatasetError, Image8, View};

/// Two poses closer than this (max abs difference of the matrix entries) are the same camera.
pub const SAME_POSE_TOLERANCE: f32 = 1e-4;

/// Largest accepted `camera_id` (anything beyond is certainly a broken file).
const MAX_CAMERA_ID: u64 = 1 << 20;

/// Intrinsics fields as written in a file (top level or one frame).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct IntrinsicFields {
    camera_angle_x: Option<f64>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    w: Option<u32>,
    h: Option<u32>,
    /// OpenCV distortion `k1, k2, k3, p1, p2` (nerfstudio).
    distortion: [Option<f64>; 5],
}

/// Names of the distortion fields, in the order of [`IntrinsicFields::distortion`].
const DISTORTION_FIELDS: [&str; 5] = ["k1", "k2", "k3", "p1", "p2"];

impl IntrinsicFields {
    /// The distortion model (absent coefficients are 0); `None` when there is none.
    pub(crate) fn distortion(&self) -> Option<Distortion> {
        let [k1, k2, k3, p1, p2] = self.distortion.map(|v| v.unwrap_or(0.0));
        let d = Distortion { k1, k2, k3, p1, p2 };
        (!d.is_identity()).then_some(d)
    }

    /// `self` with every field present in `over` replaced.
    fn overridden_by(self, over: IntrinsicFields) -> IntrinsicFields {
        IntrinsicFields {
            camera_angle_x: over.camera_angle_x.or(self.camera_angle_x),
            fl_x: over.fl_x.or(self.fl_x),
            fl_y: over.fl_y.or(self.fl_y),
            cx: over.cx.or(self.cx),
            cy: over.cy.or(self.cy),
            w: over.w.or(self.w),
            h: over.h.or(self.h),
            distortion: std::array::from_fn(|i| over.distortion[i].or(self.distortion[i])),
        }
    }
}

/// One frame of a transforms file, parsed and checked, image not yet read.
#[derive(Clone, Debug)]
pub(crate) struct FrameSpec {
    /// The transforms file it came from.
    json: PathBuf,
    /// `frames[index]` (for messages).
    index: usize,
    pub(crate) image: PathBuf,
    /// `None` when the frame has no `time` (allowed in nerfstudio files only).
    pub(crate) time: Option<f32>,
    pub(crate) pose: Mat4,
    pub(crate) intrinsics: IntrinsicFields,
    pub(crate) camera_id: Option<usize>,
}

impl FrameSpec {
    pub(crate) fn field(&self, name: &str) -> String {
        format!("frames[{}].{name}", self.index)
    }
}

/// A parsed transforms file.
pub(crate) struct TransformsFile {
    pub(crate) frames: Vec<FrameSpec>,
    pub(crate) scene_box: Option<SceneBounds>,
    /// The top-level object (for format-specific fields).
    pub(crate) root: Map<String, Value>,
}

pub(crate) fn field_error(path: &Path, field: &str, message: impl Into<String>) -> DatasetError {
    DatasetError::Field {
        path: path.to_path_buf(),
        field: field.to_string(),
        message: message.into(),
    }
}

/// A field of the wrong JSON type: "expected {expected}, got {what v is}".
pub(crate) fn wrong_type(path: &Path, field: &str, expected: &str, v: &Value) -> DatasetError {
    field_error(
        path,
        field,
        format!("expected {expected}, got {}", type_name(v)),
    )
}

pub(crate) fn type_name(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// A finite number, or an error naming `field`.
fn number(v: &Value, path: &Path, field: &str) -> Result<f64, DatasetError> {
    match v.as_f64() {
        Some(x) if x.is_finite() => Ok(x),
        Some(x) => Err(field_error(path, field, format!("{x} is not finite"))),
        None => Err(wrong_type(path, field, "a number", v)),
    }
}

/// An optional number field (absent or `null` = `None`).
fn opt_number(
    obj: &Map<String, Value>,
    key: &str,
    path: &Path,
    prefix: &str,
) -> Result<Option<f64>, DatasetError> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => number(v, path, &format!("{prefix}{key}")).map(Some),
    }
}

/// An optional positive float that must stay finite as `f32`.
fn opt_positive(
    obj: &Map<String, Value>,
    key: &str,
    path: &Path,
    prefix: &str,
) -> Result<Option<f64>, DatasetError> {
    let v = opt_number(obj, key, path, prefix)?;
    if let Some(x) = v {
        if !(x > 0.0 && (x as f32).is_finite()) {
            return Err(field_error(
                path,
                &format!("{prefix}{key}"),
                format!("{x} must be positive and representable as f32"),
            ));
        }
    }
    Ok(v)
}

/// An optional integer image side in `1..=MAX_SIDE`.
fn opt_side(
    obj: &Map<String, Value>,
    key: &str,
    path: &Path,
    prefix: &str,
) -> Result<Option<u32>, DatasetError> {
    let Some(x) = opt_number(obj, key, path, prefix)? else {
        return Ok(None);
    };
    if x.fract() != 0.0 || x < 1.0 || x > MAX_SIDE as f64 {
        return Err(field_error(
            path,
            &format!("{prefix}{key}"),
            format!("{x} is not an image size (an integer in 1..={MAX_SIDE})"),
        ));
    }
    Ok(Some(x as u32))
}

fn intrinsic_fields(
    obj: &Map<String, Value>,
    path: &Path,
    prefix: &str,
) -> Result<IntrinsicFields, DatasetError> {
    let camera_angle_x = opt_positive(obj, "camera_angle_x", path, prefix)?;
    if let Some(a) = camera_angle_x {
        if a >= std::f64::consts::PI {
            return Err(field_error(
                path,
                &format!("{prefix}camera_angle_x"),
                format!("{a} rad is not a field of view in (0, pi)"),
            ));
        }
    }
    let cx = opt_number(obj, "cx", path, prefix)?;
    let cy = opt_number(obj, "cy", path, prefix)?;
    for (k, v) in [("cx", cx), ("cy", cy)] {
        if v.is_some_and(|x| !(x as f32).is_finite()) {
            return Err(field_error(path, &format!("{prefix}{k}"), "overflows f32"));
        }
    }
    let mut distortion = [None; 5];
    for (slot, k) in distortion.iter_mut().zip(DISTORTION_FIELDS) {
        *slot = opt_number(obj, k, path, prefix)?;
        if slot.is_some_and(|x| x.abs() > 1e3) {
            return Err(field_error(
                path,
                &format!("{prefix}{k}"),
                "is not a plausible distortion coefficient (|value| > 1000)",
            ));
        }
    }
    Ok(IntrinsicFields {
        distortion,
        camera_angle_x,
        fl_x: opt_positive(obj, "fl_x", path, prefix)?,
        fl_y: opt_positive(obj, "fl_y", path, prefix)?,
        cx,
        cy,
        w: opt_side(obj, "w", path, prefix)?,
        h: opt_side(obj, "h", path, prefix)?,
    })
}

fn vec3_field(v: &Value, path: &Path, field: &str) -> Result<Vec3, DatasetError> {
    let arr = v
        .as_array()
        .filter(|a| a.len() == 3)
        .ok_or_else(|| wrong_type(path, field, "3 numbers", v))?;
    let mut out = [0.0f32; 3];
    for (i, x) in arr.iter().enumerate() {
        out[i] = number(x, path, &format!("{field}[{i}]"))? as f32;
    }
    Ok(Vec3::from(out))
}

fn scene_box(v: &Value, path: &Path) -> Result<SceneBounds, DatasetError> {
    let obj = v
        .as_object()
        .ok_or_else(|| wrong_type(path, "scene_box", "an object {min, max}", v))?;
    let get = |k: &str| {
        obj.get(k)
            .ok_or_else(|| field_error(path, &format!("scene_box.{k}"), "missing"))
    };
    let min = vec3_field(get("min")?, path, "scene_box.min")?;
    let max = vec3_field(get("max")?, path, "scene_box.max")?;
    let b = SceneBounds::Box { min, max };
    b.validate()
        .map_err(|m| field_error(path, "scene_box", m.to_string()))?;
    Ok(b)
}

fn transform_matrix(v: &Value, path: &Path, field: &str) -> Result<Mat4, DatasetError> {
    let rows = v
        .as_array()
        .filter(|r| r.len() == 3 || r.len() == 4)
        .ok_or_else(|| wrong_type(path, field, "a 4x4 (or 3x4) matrix", v))?;
    let mut m = [[0.0f32; 4]; 4];
    m[3] = [0.0, 0.0, 0.0, 1.0];
    for (i, row) in rows.iter().enumerate() {
        let r = row
            .as_array()
            .filter(|r| r.len() == 4)
            .ok_or_else(|| wrong_type(path, &format!("{field}[{i}]"), "a row of 4 numbers", row))?;
        for (j, x) in r.iter().enumerate() {
            m[i][j] = number(x, path, &format!("{field}[{i}][{j}]"))? as f32;
        }
    }
    let bottom = Vec4::from(m[3]);
    if (bottom - Vec4::W).abs().max_element() > 1e-4 {
        return Err(field_error(
            path,
            field,
            format!("bottom row must be [0, 0, 0, 1], got {bottom} (transposed matrix?)"),
        ));
    }
    // Rows in the file, columns in glam.
    let pose = Mat4::from_cols_array_2d(&m).transpose();
    // Check the pose alone (intrinsics are checked once the image size is known).
    let probe = Camera {
        width: 1,
        height: 1,
        fx: 1.0,
        fy: 1.0,
        cx: 0.5,
        cy: 0.5,
        world_from_camera: pose,
    };
    probe
        .validate()
        .map_err(|msg| field_error(path, field, msg.to_string()))?;
    Ok(pose)
}

/// The image path of `file_path`: relative to `dir`, `.png` appended when there is no extension
/// (or when only the `.png` variant exists, for names like `r_0.5`).
pub(crate) fn image_path(dir: &Path, file_path: &str) -> PathBuf {
    let p = dir.join(file_path);
    if p.extension().is_none() {
        return PathBuf::from(format!("{}.png", p.display()));
    }
    if !p.exists() {
        let with_png = PathBuf::from(format!("{}.png", p.display()));
        if with_png.exists() {
            return with_png;
        }
    }
    p
}

/// Parses and checks a transforms file; `time_required` is false for nerfstudio files, where
/// frames may leave out `time`.
pub(crate) fn parse_transforms(
    dir: &Path,
    path: &Path,
    time_required: bool,
) -> Result<TransformsFile, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let root: Value = serde_json::from_slice(&bytes).map_err(|e| DatasetError::Json {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let obj = root.as_object().ok_or_else(|| DatasetError::Json {
        path: path.to_path_buf(),
        message: format!(
            "expected an object at the top level, got {}",
            type_name(&root)
        ),
    })?;
    let top = intrinsic_fields(obj, path, "")?;
    let scene_box = match obj.get("scene_box") {
        None | Some(Value::Null) => None,
        Some(v) => Some(scene_box(v, path)?),
    };
    let frames_v = obj
        .get("frames")
        .ok_or_else(|| field_error(path, "frames", "missing"))?;
    let frames_a = frames_v
        .as_array()
        .ok_or_else(|| wrong_type(path, "frames", "an array", frames_v))?;
    if frames_a.is_empty() {
        return Err(field_error(path, "frames", "the list is empty"));
    }
    let mut frames = Vec::with_capacity(frames_a.len());
    for (index, fv) in frames_a.iter().enumerate() {
        let prefix = format!("frames[{index}].");
        let f = |k: &str| format!("{prefix}{k}");
        let fo = fv
            .as_object()
            .ok_or_else(|| wrong_type(path, &format!("frames[{index}]"), "an object", fv))?;
        let file_path = match fo.get("file_path") {
            Some(Value::String(s)) if !s.is_empty() => s.as_str(),
            Some(v) => return Err(wrong_type(path, &f("file_path"), "a non-empty string", v)),
            None => return Err(field_error(path, &f("file_path"), "missing")),
        };
        let time = match fo.get("time") {
            None if time_required => return Err(field_error(path, &f("time"), "missing")),
            None => None,
            Some(v) => Some(number(v, path, &f("time"))?),
        };
        if let Some(time) = time.filter(|t| !(0.0..=1.0).contains(t)) {
            return Err(field_error(
                path,
                &f("time"),
                format!("{time} is outside [0, 1]"),
            ));
        }
        let pose = match fo.get("transform_matrix") {
            None => return Err(field_error(path, &f("transform_matrix"), "missing")),
            Some(v) => transform_matrix(v, path, &f("transform_matrix"))?,
        };
        let camera_id = match fo.get("camera_id") {
            None | Some(Value::Null) => None,
            Some(v) => match v.as_u64() {
                Some(id) if id <= MAX_CAMERA_ID => Some(id as usize),
                _ => {
                    return Err(field_error(
                        path,
                        &f("camera_id"),
                        format!("expected an integer in 0..={MAX_CAMERA_ID}, got {v}"),
                    ))
                }
            },
        };
        let intrinsics = top.overridden_by(intrinsic_fields(fo, path, &prefix)?);
        if intrinsics.camera_angle_x.is_none()
            && intrinsics.fl_x.is_none()
            && intrinsics.fl_y.is_none()
        {
            return Err(field_error(
                path,
                "camera_angle_x",
                format!("missing (needed by frames[{index}]; or give fl_x/fl_y)"),
            ));
        }
        frames.push(FrameSpec {
            json: path.to_path_buf(),
            index,
            image: image_path(dir, file_path),
            time: time.map(|t| t as f32),
            pose,
            intrinsics,
            camera_id,
        });
    }
    Ok(TransformsFile {
        frames,
        scene_box,
        root: obj.clone(),
    })
}

/// Pinhole intrinsics of `k` for an image of `width x height` (`None` without a focal length).
fn pinhole(k: &IntrinsicFields, width: u32, height: u32) -> Option<Intrinsics> {
    let (fx, fy) = match (k.fl_x, k.fl_y, k.camera_angle_x) {
        (Some(fx), fy, _) => (fx, fy.unwrap_or(fx)),
        (None, Some(fy), _) => (fy, fy),
        (None, None, Some(a)) => {
            let f = 0.5 * width as f64 / (0.5 * a).tan();
            (f, f)
        }
        (None, None, None) => return None,
    };
    Some(Intrinsics {
        fx,
        fy,
        cx: k.cx.unwrap_or(0.5 * width as f64),
        cy: k.cy.unwrap_or(0.5 * height as f64),
    })
}

/// The full-resolution camera of a frame whose image is `width x height`.
fn frame_camera(spec: &FrameSpec, width: u32, height: u32) -> Result<Camera, DatasetError> {
    let k = spec.intrinsics;
    let json = &spec.json;
    for (name, given, actual) in [("w", k.w, width), ("h", k.h, height)] {
        if let Some(g) = given {
            if g != actual {
                return Err(field_error(
                    json,
                    name,
                    format!(
                        "says {g} but image {} is {width}x{height}",
                        spec.image.display()
                    ),
                ));
            }
        }
    }
    let (fx, fy, field) = match (k.fl_x, k.fl_y) {
        (Some(fx), fy) => (fx, fy.unwrap_or(fx), "fl_x"),
        (None, Some(fy)) => (fy, fy, "fl_y"),
        (None, None) => {
            let Some(angle) = k.camera_angle_x else {
                return Err(field_error(json, "camera_angle_x", "missing"));
            };
            let f = 0.5 * width as f64 / (0.5 * angle).tan();
            (f, f, "camera_angle_x")
        }
    };
    let camera = Camera {
        width,
        height,
        fx: fx as f32,
        fy: fy as f32,
        cx: k.cx.unwrap_or(0.5 * width as f64) as f32,
        cy: k.cy.unwrap_or(0.5 * height as f64) as f32,
        world_from_camera: spec.pose,
    };
    camera
        .validate()
        .map_err(|m| field_error(json, &spec.field(field), m.to_string()))?;
    Ok(camera)
}

fn same_pose(a: &Mat4, b: &Mat4) -> bool {
    a.to_cols_array()
        .iter()
        .zip(b.to_cols_array().iter())
        .all(|(x, y)| (x - y).abs() < SAME_POSE_TOLERANCE)
}

/// The frames of `specs` through a frame cache (built or reused), as [`LoadedImage`]s without
/// alpha; fails with the [`TRANSPARENT`] message at the first image with transparency.
fn cached_images(
    specs: &[&FrameSpec],
    downscale: u32,
    (ref_w, ref_h): (u32, u32),
    storage: &FrameStorage,
    progress: Option<&ProgressFn>,
) -> Result<Vec<LoadedImage>, DatasetError> {
    let mut fp = Fingerprint::default();
    fp.str("json-v1");
    fp.bytes(&downscale.to_le_bytes());
    let mut jsons: Vec<&Path> = specs.iter().map(|s| s.json.as_path()).collect();
    jsons.dedup();
    for p in jsons {
        fp.file(p)?;
    }
    for s in specs {
        fp.file(&s.image)?;
    }
    let (w, h) = (ref_w / downscale, ref_h / downscale);
    let key = CacheKey {
        width: w,
        height: h,
        count: specs.len() as u64,
        fingerprint: fp.finish(),
    };
    let stored = store_frames(storage, key, progress, &mut |sink| {
        for batch in specs.chunks(64) {
            let imgs: Vec<Result<LoadedImage, DatasetError>> = batch
                .par_iter()
                .map(|s| load_frame_image(s, downscale))
                .collect();
            for (spec, img) in batch.iter().zip(imgs) {
                let img = img?;
                check_size(spec, &img, specs[0], (ref_w, ref_h))?;
                if img.transparent {
                    return Err(DatasetError::Invalid {
                        path: spec.image.clone(),
                        message: TRANSPARENT.into(),
                    });
                }
                sink.push(&img.image.data)?;
            }
        }
        Ok(())
    })?;
    Ok(stored
        .frames()
        .into_iter()
        .map(|data| LoadedImage {
            width: ref_w,
            height: ref_h,
            image: Image8 {
                width: w,
                height: h,
                data,
            },
            transparent: false,
            alpha: None,
        })
        .collect())
}

/// Camera ids of the train and test views.
type CameraIds = (Vec<Option<usize>>, Vec<Option<usize>>);

/// Camera ids from the files, or from grouping identical poses (`None` for monocular data).
pub(crate) fn camera_ids(
    train: &[FrameSpec],
    test: &[FrameSpec],
) -> Result<CameraIds, DatasetError> {
    let all = || train.iter().chain(test);
    if let Some(with) = all().find(|f| f.camera_id.is_some()) {
        if let Some(without) = all().find(|f| f.camera_id.is_none()) {
            return Err(field_error(
                &without.json,
                &without.field("camera_id"),
                format!(
                    "missing, but {} {} has one (give it for every frame or none)",
                    with.json.display(),
                    with.field("camera_id")
                ),
            ));
        }
        return Ok((
            train.iter().map(|f| f.camera_id).collect(),
            test.iter().map(|f| f.camera_id).collect(),
        ));
    }
    let mut groups: Vec<Mat4> = Vec::new();
    let mut group_of = |pose: &Mat4| -> usize {
        if let Some(i) = groups.iter().position(|g| same_pose(g, pose)) {
            i
        } else {
            groups.push(*pose);
            groups.len() - 1
        }
    };
    let train_ids: Vec<usize> = train.iter().map(|f| group_of(&f.pose)).collect();
    let monocular = train_ids.iter().enumerate().all(|(i, &g)| g == i);
    if monocular {
        return Ok((vec![None; train.len()], vec![None; test.len()]));
    }
    let test_ids = test.iter().map(|f| Some(group_of(&f.pose))).collect();
    Ok((train_ids.into_iter().map(Some).collect(), test_ids))
}

/// The error message that stops a frame cache build at the first transparent image.
const TRANSPARENT: &str = "transparent image: the frames stay in memory with their alpha";

/// Reads the images of parsed frames and builds the dataset (shared with nerfstudio), with the
/// frames in `storage`: camera ids, bounds, frame count. Frames without a time get time 0.
///
/// A frame cache holds 8-bit RGB only, so it serves opaque datasets: a build that meets an
/// image with transparency stops, and the dataset is loaded into memory with its alpha (object
/// captures are small). Its fingerprint covers the transforms files, every image file and the
/// downscale factor.
pub(crate) fn assemble_with_storage(
    dir: &Path,
    train_specs: &[FrameSpec],
    test_specs: &[FrameSpec],
    scene_box: Option<SceneBounds>,
    opts: &LoadOptions,
    storage: &FrameStorage,
    progress: Option<&ProgressFn>,
) -> Result<Dataset, DatasetError> {
    let specs: Vec<&FrameSpec> = train_specs.iter().chain(test_specs).collect();
    let f = opts.downscale;
    let images = if *storage == FrameStorage::Memory {
        None
    } else {
        let first = &specs[0].image;
        let (ref_w, ref_h) = image::image_dimensions(first).map_err(|e| match e {
            image::ImageError::IoError(source) => DatasetError::Io {
                path: first.clone(),
                source,
            },
            e => DatasetError::Image {
                path: first.clone(),
                message: e.to_string(),
            },
        })?;
        let bytes = specs.len() as u64 * (ref_w / f) as u64 * (ref_h / f) as u64 * 3;
        match storage.cache_file(bytes) {
            Some(_) if ref_w >= f && ref_h >= f => {
                match cached_images(&specs, f, (ref_w, ref_h), storage, progress) {
                    Err(DatasetError::Invalid { message, .. }) if message == TRANSPARENT => None,
                    r => Some(r?),
                }
            }
            _ => None,
        }
    };
    let images = match images {
        Some(i) => i,
        None => {
            let loaded: Vec<Result<LoadedImage, DatasetError>> =
                specs.par_iter().map(|s| load_frame_image(s, f)).collect();
            let mut images = Vec::with_capacity(loaded.len());
            for r in loaded {
                images.push(r?);
            }
            images
        }
    };

    let (ref_w, ref_h) = (images[0].width, images[0].height);
    let mut transparent = false;
    let mut views = Vec::with_capacity(specs.len());
    for (spec, img) in specs.iter().zip(images) {
        check_size(spec, &img, specs[0], (ref_w, ref_h))?;
        transparent |= img.transparent;
        let mut camera = frame_camera(spec, img.width, img.height)?;
        if opts.downscale > 1 {
            camera = camera.scaled(1.0 / opts.downscale as f32);
            camera.width = img.image.width;
            camera.height = img.image.height;
        }
        views.push(View {
            camera,
            time: spec.time.unwrap_or(0.0),
            image: img.image,
            source: spec.image.clone(),
            camera_id: None,
            alpha: img.alpha,
        });
    }
    let mut test = views.split_off(train_specs.len());
    let mut train = views;

    let (train_ids, test_ids) = camera_ids(train_specs, test_specs)?;
    for (v, id) in train.iter_mut().zip(train_ids) {
        v.camera_id = id;
    }
    for (v, id) in test.iter_mut().zip(test_ids) {
        v.camera_id = id;
    }

    let bounds = if let Some(b) = opts.bounds {
        b
    } else if let Some(b) = scene_box {
        b
    } else if transparent {
        SceneBounds::dnerf_default()
    } else {
        let cams: Vec<Camera> = train.iter().map(|v| v.camera).collect();
        contracted_bounds_from_cameras(&cams)
    };

    let mut times: Vec<f32> = train.iter().map(|v| v.time).collect();
    times.sort_by(f32::total_cmp);
    times.dedup();

    let name = dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .or_else(|| {
            let full = dir.canonicalize().ok()?;
            Some(full.file_name()?.to_string_lossy().into_owned())
        })
        .unwrap_or_else(|| "dataset".to_string());

    // The held-out cameras' too: they render from the same sampler.
    let cams: Vec<Camera> = train.iter().chain(&test).map(|v| v.camera).collect();
    let near = near_from_sibling_llff(dir, &cams);
    Ok(Dataset {
        name,
        train,
        test,
        bounds,
        background: [1.0; 3],
        num_frames: times.len(),
        near,
    })
}

/// The near bound of `cameras` from a `poses_bounds.npy` beside the JSON, when it describes the
/// same cameras in the same units ([`near_from_llff_rows`]). A missing, unreadable or unrelated
/// file gives `None`: it is not part of the JSON layout, so it never fails the load.
fn near_from_sibling_llff(dir: &Path, cameras: &[Camera]) -> Option<f32> {
    let path = dir.join("poses_bounds.npy");
    if !path.is_file() {
        return None;
    }
    let rows = crate::dynerf::read_pose_bounds(&path).ok()?;
    near_from_llff_rows(cameras, &rows)
}

/// The image of one frame, undistorted when its intrinsics carry a distortion model.
fn load_frame_image(spec: &FrameSpec, downscale: u32) -> Result<LoadedImage, DatasetError> {
    let k = spec.intrinsics;
    let undistort =
        move |width: u32, height: u32| Some((pinhole(&k, width, height)?, k.distortion()?));
    load_image_undistorted(&spec.image, downscale, Some(&undistort))
}

/// Every image of a dataset has the size of the first one (`first`, `ref_w x ref_h` before
/// downscaling).
fn check_size(
    spec: &FrameSpec,
    img: &LoadedImage,
    first: &FrameSpec,
    (ref_w, ref_h): (u32, u32),
) -> Result<(), DatasetError> {
    if (img.width, img.height) == (ref_w, ref_h) {
        return Ok(());
    }
    Err(DatasetError::Invalid {
        path: spec.image.clone(),
        message: format!(
            "image is {}x{} but {} is {ref_w}x{ref_h} (all images must have one size)",
            img.width,
            img.height,
            first.image.display()
        ),
    })
}
