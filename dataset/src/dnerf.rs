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
//! Scene bounds when not given: [`SceneBounds::dnerf_default`] if any image has transparency
//! (object captures), otherwise a contraction around the point closest to all training cameras'
//! optical axes (forward-facing / stage captures).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3, Mat4, Vec3, Vec4};
use msth_core::{Camera, SceneBounds};
use rayon::prelude::*;
use serde::Serialize;
use serde_json::{Map, Value};

use crate::cache::{store_frames, CacheKey, Fingerprint, FrameStorage, ProgressFn};
use crate::imageio;
use crate::undistort::{undistort_image, Distortion, Intrinsics};
use crate::{downscale_rgb, Dataset, DatasetError, Image8, View};

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

/// Two poses closer than this (max abs difference of the matrix entries) are the same camera.
pub const SAME_POSE_TOLERANCE: f32 = 1e-4;

/// Largest accepted image side and `camera_id` (anything beyond is certainly a broken file).
const MAX_SIDE: u32 = 1 << 16;
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

/// An image read and prepared for the dataset.
pub(crate) struct LoadedImage {
    /// Size before downscaling.
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) image: Image8,
    /// Some pixel had alpha < 255.
    pub(crate) transparent: bool,
    /// Alpha after downscaling, when the image had transparency.
    pub(crate) alpha: Option<Vec<u8>>,
}

pub(crate) fn field_error(path: &Path, field: &str, message: impl Into<String>) -> DatasetError {
    DatasetError::Field {
        path: path.to_path_buf(),
        field: field.to_string(),
        message: message.into(),
    }
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
        None => Err(field_error(
            path,
            field,
            format!("expected a number, got {}", type_name(v)),
        )),
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
    let arr = v.as_array().filter(|a| a.len() == 3).ok_or_else(|| {
        field_error(
            path,
            field,
            format!("expected 3 numbers, got {}", type_name(v)),
        )
    })?;
    let mut out = [0.0f32; 3];
    for (i, x) in arr.iter().enumerate() {
        out[i] = number(x, path, &format!("{field}[{i}]"))? as f32;
    }
    Ok(Vec3::from(out))
}

fn scene_box(v: &Value, path: &Path) -> Result<SceneBounds, DatasetError> {
    let obj = v.as_object().ok_or_else(|| {
        field_error(
            path,
            "scene_box",
            format!("expected an object {{min, max}}, got {}", type_name(v)),
        )
    })?;
    let get = |k: &str| {
        obj.get(k)
            .ok_or_else(|| field_error(path, &format!("scene_box.{k}"), "missing"))
    };
    let min = vec3_field(get("min")?, path, "scene_box.min")?;
    let max = vec3_field(get("max")?, path, "scene_box.max")?;
    let b = SceneBounds::Box { min, max };
    b.validate()
        .map_err(|m| field_error(path, "scene_box", m))?;
    Ok(b)
}

fn transform_matrix(v: &Value, path: &Path, field: &str) -> Result<Mat4, DatasetError> {
    let rows = v
        .as_array()
        .filter(|r| r.len() == 3 || r.len() == 4)
        .ok_or_else(|| {
            field_error(
                path,
                field,
                format!("expected a 4x4 (or 3x4) matrix, got {}", type_name(v)),
            )
        })?;
    let mut m = [[0.0f32; 4]; 4];
    m[3] = [0.0, 0.0, 0.0, 1.0];
    for (i, row) in rows.iter().enumerate() {
        let r = row.as_array().filter(|r| r.len() == 4).ok_or_else(|| {
            field_error(
                path,
                &format!("{field}[{i}]"),
                format!("expected a row of 4 numbers, got {}", type_name(row)),
            )
        })?;
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
        .map_err(|msg| field_error(path, field, msg))?;
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
    let frames_a = frames_v.as_array().ok_or_else(|| {
        field_error(
            path,
            "frames",
            format!("expected an array, got {}", type_name(frames_v)),
        )
    })?;
    if frames_a.is_empty() {
        return Err(field_error(path, "frames", "the list is empty"));
    }
    let mut frames = Vec::with_capacity(frames_a.len());
    for (index, fv) in frames_a.iter().enumerate() {
        let prefix = format!("frames[{index}].");
        let f = |k: &str| format!("{prefix}{k}");
        let fo = fv.as_object().ok_or_else(|| {
            field_error(
                path,
                &format!("frames[{index}]"),
                format!("expected an object, got {}", type_name(fv)),
            )
        })?;
        let file_path = match fo.get("file_path") {
            Some(Value::String(s)) if !s.is_empty() => s.as_str(),
            Some(v) => {
                return Err(field_error(
                    path,
                    &f("file_path"),
                    format!("expected a non-empty string, got {}", type_name(v)),
                ))
            }
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

/// Area-filter downscale by an integer factor; the remainder at the right/bottom is cropped.
fn downscale_box(img: &Image8, factor: u32) -> Image8 {
    if factor <= 1 {
        return img.clone();
    }
    Image8 {
        width: img.width / factor,
        height: img.height / factor,
        data: downscale_rgb(&img.data, img.width, img.height, factor).into(),
    }
}

/// Reads an image file, composites it on white and downscales it.
pub(crate) fn load_image(path: &Path, downscale: u32) -> Result<LoadedImage, DatasetError> {
    load_image_undistorted(path, downscale, None)
}

/// [`load_image`], undistorting the image to the pinhole camera first when `undistort` gives the
/// frame's intrinsics fields with a distortion model (nerfstudio).
pub(crate) fn load_image_undistorted(
    path: &Path,
    downscale: u32,
    undistort: Option<&IntrinsicFields>,
) -> Result<LoadedImage, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let decoded = image::load_from_memory(&bytes).map_err(|e| DatasetError::Image {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let (width, height) = (decoded.width(), decoded.height());
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(DatasetError::Image {
            path: path.to_path_buf(),
            message: format!("unsupported image size {width}x{height}"),
        });
    }
    if width < downscale || height < downscale {
        return Err(DatasetError::Invalid {
            path: path.to_path_buf(),
            message: format!(
                "image {width}x{height} is smaller than the downscale factor {downscale}"
            ),
        });
    }
    let has_alpha = decoded.color().has_alpha();
    let mut rgba = decoded.to_rgba8();
    if let Some(k) = undistort {
        if let (Some(d), Some(pin)) = (k.distortion(), pinhole(k, width, height)) {
            // Undistort RGBA as two RGB images (colour, and alpha replicated).
            let mut colour = Image8::new(width, height);
            let mut alpha = Image8::new(width, height);
            let (cd, ad): (&mut [u8], &mut [u8]) = (&mut colour.data, &mut alpha.data);
            for ((c, a), p) in cd
                .chunks_exact_mut(3)
                .zip(ad.chunks_exact_mut(3))
                .zip(rgba.pixels())
            {
                c.copy_from_slice(&p.0[..3]);
                a.fill(p.0[3]);
            }
            let colour = undistort_image(&colour, &pin, &d);
            let alpha = undistort_image(&alpha, &pin, &d);
            for ((p, c), a) in rgba
                .pixels_mut()
                .zip(colour.data.chunks_exact(3))
                .zip(alpha.data.chunks_exact(3))
            {
                p.0 = [c[0], c[1], c[2], a[0]];
            }
        }
    }
    let mut image = Image8::new(width, height);
    let mut transparent = false;
    for (dst, src) in image.data.chunks_exact_mut(3).zip(rgba.pixels()) {
        let a = src.0[3] as u32;
        if has_alpha && a < 255 {
            transparent = true;
        }
        for c in 0..3 {
            // rgb * a + (1 - a) on white, in 8-bit fixed point with rounding.
            dst[c] = ((src.0[c] as u32 * a + 255 * (255 - a) + 127) / 255) as u8;
        }
    }
    let alpha = transparent.then(|| {
        // Box-filter the alpha channel the same way as the colours (through a grey image).
        let mut a = Image8::new(width, height);
        for (dst, src) in a.data.chunks_exact_mut(3).zip(rgba.pixels()) {
            dst.fill(src.0[3]);
        }
        downscale_box(&a, downscale)
            .data
            .chunks_exact(3)
            .map(|p| p[0])
            .collect()
    });
    Ok(LoadedImage {
        width,
        height,
        image: downscale_box(&image, downscale),
        transparent,
        alpha,
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
        .map_err(|m| field_error(json, &spec.field(field), m))?;
    Ok(camera)
}

/// The point closest (least squares) to all cameras' optical axes, and the median camera distance
/// to it; the mean of the camera centres when the axes are (nearly) parallel.
pub fn contracted_bounds_from_cameras(cameras: &[Camera]) -> SceneBounds {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    let mut mean = DVec3::ZERO;
    for c in cameras {
        let o = c.center().as_dvec3();
        let d = (-c.world_from_camera.z_axis.truncate())
            .as_dvec3()
            .normalize_or_zero();
        let p = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * o;
        mean += o;
    }
    let n = cameras.len().max(1) as f64;
    mean /= n;
    let det = a.determinant();
    let center = if det.is_finite() && det.abs() > 1e-6 * n * n * n {
        a.inverse() * b
    } else {
        mean
    };
    let center = if center.is_finite() { center } else { mean };
    let mut dists: Vec<f64> = cameras
        .iter()
        .map(|c| (c.center().as_dvec3() - center).length())
        .filter(|d| d.is_finite())
        .collect();
    dists.sort_by(f64::total_cmp);
    let radius = dists.get(dists.len() / 2).copied().unwrap_or(1.0) as f32;
    let radius = if radius.is_finite() && radius > 1e-6 {
        radius
    } else {
        1.0
    };
    SceneBounds::Contracted {
        center: center.as_vec3(),
        radius,
    }
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
                .map(|s| load_image_undistorted(&s.image, downscale, Some(&s.intrinsics)))
                .collect();
            for (spec, img) in batch.iter().zip(imgs) {
                let img = img?;
                if (img.width, img.height) != (ref_w, ref_h) {
                    return Err(DatasetError::Invalid {
                        path: spec.image.clone(),
                        message: format!(
                            "image is {}x{} but {} is {ref_w}x{ref_h} (all images must have one size)",
                            img.width,
                            img.height,
                            specs[0].image.display()
                        ),
                    });
                }
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
            let loaded: Vec<Result<LoadedImage, DatasetError>> = specs
                .par_iter()
                .map(|s| load_image_undistorted(&s.image, f, Some(&s.intrinsics)))
                .collect();
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
        if (img.width, img.height) != (ref_w, ref_h) {
            return Err(DatasetError::Invalid {
                path: spec.image.clone(),
                message: format!(
                    "image is {}x{} but {} is {ref_w}x{ref_h} (all images must have one size)",
                    img.width,
                    img.height,
                    specs[0].image.display()
                ),
            });
        }
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

    Ok(Dataset {
        name,
        train,
        test,
        bounds,
        background: [1.0; 3],
        num_frames: times.len(),
    })
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
/// The folder is built as a sibling `dir.tmp-<pid>-<nanos>` and renamed to `dir` at the end, so a
/// failure leaves no partial dataset. `dir` must not exist or be an empty folder.
pub fn write(dataset: &Dataset, dir: &Path) -> Result<(), DatasetError> {
    if dir.exists() {
        let non_empty = match std::fs::read_dir(dir) {
            Ok(mut entries) => entries.next().is_some(),
            Err(_) => true,
        };
        if non_empty || !dir.is_dir() {
            return Err(DatasetError::Invalid {
                path: dir.to_path_buf(),
                message: "refusing to write a dataset here: exists and is not an empty folder"
                    .into(),
            });
        }
    }
    let name = dir
        .file_name()
        .ok_or_else(|| DatasetError::Invalid {
            path: dir.to_path_buf(),
            message: "not a folder name".into(),
        })?
        .to_string_lossy()
        .into_owned();
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let tmp = dir.with_file_name(format!("{name}.tmp-{}-{nanos}", std::process::id()));
    if let Some(parent) = tmp.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io_error(parent))?;
    }
    std::fs::create_dir(&tmp).map_err(io_error(&tmp))?;
    let result = write_into(dataset, &tmp).and_then(|()| {
        if dir.exists() {
            std::fs::remove_dir(dir).map_err(io_error(dir))?;
        }
        std::fs::rename(&tmp, dir).map_err(io_error(dir))
    });
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

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
        train["frames"][0]["transform_matrix"] =
            json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]);
        expect_error(
            dir.path(),
            &train,
            &test,
            &[
                "transforms_train.json",
                "frames[0].transform_matrix",
                "invertible",
            ],
        );
        train["frames"][0]["transform_matrix"] = pose(1e39);
        expect_error(
            dir.path(),
            &train,
            &test,
            &[
                "transforms_train.json",
                "frames[0].transform_matrix",
                "non-finite",
            ],
        );
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
