//! Plenoptic Video / DyNeRF datasets: `poses_bounds.npy` with one video (or frame folder) per
//! camera.
//!
//! ```text
//! poses_bounds.npy        N x 17 (LLFF), row i = the i-th camera in name order
//! cam00.mp4 ... camNN.mp4 one video per camera (.mp4, .mov or .mkv), decoded with ffmpeg
//!   or cam00/ ... camNN/  one folder of images per camera (.png / .jpg), frames in name order
//! ```
//!
//! - Row `i` of `poses_bounds.npy` is a row-major 3x5 matrix `[R | t | hwf]` followed by `near`,
//!   `far`. `R`'s columns are LLFF's (down, right, backwards) axes, i.e. `[-Y, X, Z]` of the
//!   OpenGL camera-to-world matrix; `t` is the camera centre; `hwf` = (height, width, focal in
//!   pixels) of the images the poses were made for (frames of another size with the same aspect
//!   ratio get the focal length scaled). The principal point is the image centre.
//! - Cameras are matched to rows in name order (`cam00` < `cam01` < ..., gaps allowed as in the
//!   Plenoptic release). Every camera must have the same frame size and number of frames `T`;
//!   frame `j` has time `j / (T - 1)`.
//! - The held-out (test) camera is `cam00` unless [`DynerfOptions::test_camera`] names another;
//!   it is left out of training and of the scene bounds.
//! - When a camera has both a video and a folder, videos are used (see [`FrameSource`]).
//!
//! Pose normalisation for forward-facing captures ([`Normalization::Llff`], the default), the
//! steps of the LLFF loader, a similarity transform of the world ([`Similarity`]):
//! 1. scale: the world is scaled by `s = 1 / (0.75 * min near)`, so the nearest content is at
//!    depth 4/3 (and `near`, `far` with it);
//! 2. recentre: the average camera (mean centre; forward = mean viewing axis; up = mean up,
//!    made orthogonal) becomes the identity, so the rig sits at the origin looking down -Z.
//!
//! Scene bounds ([`forward_facing_bounds`]): the contraction of method.md around the point
//! closest to all training cameras' optical axes with radius the median camera distance to it
//! (as for JSON stage captures); when the axes do not converge in front of the rig (parallel
//! cameras), the centre is put on the mean optical axis at the median mid-depth
//! `(near + far) / 2` and the radius is that depth, so the content from the cameras up to twice
//! that depth is in the uncontracted region and everything beyond is contracted.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::{Mat3, Mat4, Vec3};
use msth_core::{Camera, SceneBounds};
use rayon::prelude::*;

pub use crate::bounds::forward_facing_bounds;
use crate::cache::{store_frames, CacheKey, FrameSink, FrameStorage, ProgressFn, Stored};
use crate::imageio::load_image;
use crate::video::{self, Tools, VideoInfo};
use crate::{downscale_rgb, Dataset, DatasetError, Image8, View};

/// Largest accepted number of cameras (rows).
const MAX_CAMERAS: usize = 4096;
/// Largest accepted frames x cameras.
const MAX_VIEWS: u64 = 1 << 24;

/// How the world is normalised (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Normalization {
    /// LLFF-style: scale by the near bound, recentre on the average camera.
    #[default]
    Llff,
    /// Keep the file's world coordinates.
    None,
}

/// Where frames come from when a camera has both a video and a folder of images.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FrameSource {
    /// Videos when every camera has one, else image folders when every camera has one.
    #[default]
    Auto,
    Videos,
    Images,
}

/// How to load a DyNeRF dataset.
#[derive(Clone)]
pub struct DynerfOptions {
    /// Integer area-filter downscale factor.
    pub downscale: u32,
    /// Scene bounds instead of [`forward_facing_bounds`].
    pub bounds: Option<SceneBounds>,
    /// The number `NN` of the held-out camera `camNN` (default 0).
    pub test_camera: Option<usize>,
    pub normalization: Normalization,
    pub frames: FrameSource,
    /// In memory or in a frame cache on disk.
    pub storage: FrameStorage,
    pub tools: Tools,
    /// Called as frames are decoded: `(done, total)`.
    pub progress: Option<Arc<ProgressFn>>,
}

impl Default for DynerfOptions {
    fn default() -> Self {
        DynerfOptions {
            downscale: 1,
            bounds: None,
            test_camera: None,
            normalization: Normalization::default(),
            frames: FrameSource::default(),
            storage: FrameStorage::Memory,
            tools: Tools::default(),
            progress: None,
        }
    }
}

/// A similarity transform `p -> scale * rotation * p + translation` of world points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    pub scale: f32,
    pub rotation: Mat3,
    pub translation: Vec3,
}

impl Similarity {
    /// The transform that changes nothing.
    pub const IDENTITY: Similarity = Similarity {
        scale: 1.0,
        rotation: Mat3::IDENTITY,
        translation: Vec3::ZERO,
    };

    /// A world point in the new world.
    pub fn apply_point(&self, p: Vec3) -> Vec3 {
        self.scale * (self.rotation * p) + self.translation
    }

    /// A camera-to-world pose in the new world (rotation kept orthonormal, centre mapped).
    pub fn apply_pose(&self, pose: &Mat4) -> Mat4 {
        let r = self.rotation * Mat3::from_mat4(*pose);
        let c = self.apply_point(pose.w_axis.truncate());
        Mat4::from_cols(
            r.x_axis.extend(0.0),
            r.y_axis.extend(0.0),
            r.z_axis.extend(0.0),
            c.extend(1.0),
        )
    }
}

/// Where one camera's frames are.
#[derive(Clone, Debug, PartialEq)]
pub enum Frames {
    Video(PathBuf),
    /// A folder and its image files in name order.
    Images(PathBuf, Vec<PathBuf>),
}

/// One camera of the rig, as read from the folder and its row of `poses_bounds.npy`.
#[derive(Clone, Debug)]
pub struct RigCamera {
    /// `NN` of `camNN`.
    pub number: usize,
    pub frames: Frames,
    /// Full-resolution camera in the normalised world.
    pub camera: Camera,
    /// Depth bounds in the normalised world.
    pub near: f32,
    pub far: f32,
}

/// A DyNeRF rig: cameras, their frame count and the normalisation that was applied.
#[derive(Clone, Debug)]
pub struct Rig {
    pub cameras: Vec<RigCamera>,
    /// Frames per camera.
    pub frames: usize,
    /// Maps the file's world to the dataset's world.
    pub normalization: Similarity,
    /// Index into `cameras` of the held-out camera.
    pub test: usize,
}

fn bad(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Invalid {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// `camNN` (+ extension) -> NN.
fn camera_number(name: &str) -> Option<usize> {
    let digits = name.strip_prefix("cam")?;
    if digits.is_empty() || digits.len() > 6 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

const VIDEO_EXTENSIONS: [&str; 3] = ["mp4", "mov", "mkv"];
const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Paths by camera number.
type Numbered = Vec<(usize, PathBuf)>;

/// Videos and image folders by camera number.
fn discover(dir: &Path) -> Result<(Numbered, Numbered), DatasetError> {
    let entries = std::fs::read_dir(dir).map_err(|source| DatasetError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut videos = Vec::new();
    let mut folders = Vec::new();
    for e in entries.flatten() {
        let path = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if path.is_dir() {
            if let Some(n) = camera_number(&name) {
                folders.push((n, path));
            }
        } else if let Some((stem, ext)) = name.rsplit_once('.') {
            if VIDEO_EXTENSIONS.contains(&ext.to_ascii_lowercase().as_str()) {
                if let Some(n) = camera_number(stem) {
                    videos.push((n, path));
                }
            }
        }
    }
    videos.sort();
    folders.sort();
    for list in [&videos, &folders] {
        if let Some(w) = list.windows(2).find(|w| w[0].0 == w[1].0) {
            return Err(bad(
                &w[1].1,
                format!("camera {} also has {}", w[0].0, w[0].1.display()),
            ));
        }
    }
    Ok((videos, folders))
}

fn image_files(folder: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(folder)
        .map_err(|source| DatasetError::Io {
            path: folder.to_path_buf(),
            source,
        })?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension().is_some_and(|e| {
                    IMAGE_EXTENSIONS.contains(&e.to_string_lossy().to_ascii_lowercase().as_str())
                })
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(bad(folder, "holds no .png / .jpg frames"));
    }
    Ok(files)
}

/// One row of `poses_bounds.npy` as an OpenGL camera-to-world pose, `(h, w, f)` and near/far.
struct Row {
    pose: Mat4,
    hwf: [f64; 3],
    near: f64,
    far: f64,
}

fn parse_row(path: &Path, i: usize, r: &[f64]) -> Result<Row, DatasetError> {
    let at = |what: &str| format!("row {i} (camera {i} in name order): {what}");
    if let Some(k) = r.iter().position(|v| !v.is_finite()) {
        return Err(bad(
            path,
            at(&format!("value {k} is {} (not finite)", r[k])),
        ));
    }
    // Row-major 3x5: m[row][col] = r[row * 5 + col].
    let col = |c: usize| Vec3::new(r[c] as f32, r[5 + c] as f32, r[10 + c] as f32);
    let (down, right, back, t) = (col(0), col(1), col(2), col(3));
    let hwf = [r[4], r[9], r[14]];
    let (near, far) = (r[15], r[16]);
    let rot = Mat3::from_cols(right, -down, back);
    let ortho = (rot.transpose() * rot - Mat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f32, |m, v| m.max(v.abs()));
    if ortho > 1e-3 || rot.determinant() < 0.0 {
        return Err(bad(
            path,
            at(&format!(
                "the 3x3 rotation is not orthonormal and right-handed (|R^T R - I| = {ortho:.2e}, det {:.3})",
                rot.determinant()
            )),
        ));
    }
    let [h, w, f] = hwf;
    if !(h >= 1.0 && w >= 1.0 && h <= 65536.0 && w <= 65536.0 && f > 0.0) {
        return Err(bad(
            path,
            at(&format!(
                "hwf = ({h}, {w}, {f}): need a positive height, width and focal length"
            )),
        ));
    }
    if !(near > 0.0 && far > near) {
        return Err(bad(
            path,
            at(&format!("near/far = {near}, {far}: need 0 < near < far")),
        ));
    }
    let pose = Mat4::from_cols(
        rot.x_axis.extend(0.0),
        rot.y_axis.extend(0.0),
        rot.z_axis.extend(0.0),
        t.extend(1.0),
    );
    Ok(Row {
        pose,
        hwf,
        near,
        far,
    })
}

/// Every row of a `poses_bounds.npy`, checked: shape `(N, 17)` with `N` in `2..=MAX_CAMERAS`,
/// finite values, an orthonormal right-handed rotation, a positive size and focal length,
/// `0 < near < far`.
fn read_rows(path: &Path) -> Result<Vec<Row>, DatasetError> {
    let arr = crate::npy::read(path)?;
    if arr.shape.len() != 2 || arr.shape[1] != 17 {
        return Err(bad(
            path,
            format!(
                "shape {:?}: expected (N, 17), one row per camera of a 3x5 [R | t | hwf] matrix then near, far",
                arr.shape
            ),
        ));
    }
    let rows_n = arr.shape[0];
    if !(2..=MAX_CAMERAS).contains(&rows_n) {
        return Err(bad(
            path,
            format!("{rows_n} rows: need 2..={MAX_CAMERAS} cameras (one is held out)"),
        ));
    }
    arr.data
        .chunks_exact(17)
        .enumerate()
        .map(|(i, r)| parse_row(path, i, r))
        .collect()
}

/// The cameras of a `poses_bounds.npy` as OpenGL camera-to-world poses with their near and far
/// bounds, in the file's own units (no normalisation).
pub fn read_pose_bounds(path: &Path) -> Result<Vec<(Mat4, f32, f32)>, DatasetError> {
    Ok(read_rows(path)?
        .into_iter()
        .map(|row| (row.pose, row.near as f32, row.far as f32))
        .collect())
}

/// The LLFF normalisation of poses with the given near bounds (see the module docs).
pub fn llff_normalization(poses: &[Mat4], nears: &[f32]) -> Similarity {
    let min_near = nears.iter().copied().fold(f32::INFINITY, f32::min);
    let scale = if min_near.is_finite() && min_near > 0.0 {
        1.0 / (0.75 * min_near)
    } else {
        1.0
    };
    let n = poses.len().max(1) as f32;
    let center = poses.iter().map(|p| p.w_axis.truncate()).sum::<Vec3>() / n;
    let back = poses
        .iter()
        .map(|p| p.z_axis.truncate())
        .sum::<Vec3>()
        .normalize_or_zero();
    let up = poses.iter().map(|p| p.y_axis.truncate()).sum::<Vec3>();
    let x = up.cross(back).normalize_or_zero();
    let y = back.cross(x);
    let avg = Mat3::from_cols(x, y, back);
    if (avg.determinant() - 1.0).abs() > 1e-3 {
        // Degenerate rig (e.g. one camera looking along its mean up): only scale and centre.
        return Similarity {
            scale,
            rotation: Mat3::IDENTITY,
            translation: -scale * center,
        };
    }
    let rotation = avg.transpose();
    Similarity {
        scale,
        rotation,
        translation: -scale * (rotation * center),
    }
}

/// Reads `poses_bounds.npy` and finds every camera's frames; no frame is decoded except to learn
/// sizes and counts.
pub fn read_rig(dir: &Path, opts: &DynerfOptions) -> Result<Rig, DatasetError> {
    let npy_path = dir.join("poses_bounds.npy");
    let rows = read_rows(&npy_path)?;
    let rows_n = rows.len();

    let (videos, folders) = discover(dir)?;
    let use_videos = match opts.frames {
        FrameSource::Videos => true,
        FrameSource::Images => false,
        FrameSource::Auto => {
            videos.len() == rows_n || (folders.len() != rows_n && !videos.is_empty())
        }
    };
    let found: Vec<(usize, Frames)> = if use_videos {
        videos
            .into_iter()
            .map(|(n, p)| (n, Frames::Video(p)))
            .collect()
    } else {
        let mut v = Vec::new();
        for (n, p) in folders {
            let files = image_files(&p)?;
            v.push((n, Frames::Images(p, files)));
        }
        v
    };
    let kind = if use_videos {
        "camNN.mp4 videos"
    } else {
        "camNN/ frame folders"
    };
    if found.len() != rows_n {
        let names: Vec<String> = found.iter().map(|(n, _)| format!("cam{n:02}")).collect();
        return Err(bad(
            &npy_path,
            format!(
                "{rows_n} rows (one per camera) but {} {kind} were found{}{}",
                found.len(),
                if names.is_empty() { "" } else { ": " },
                names.join(", ")
            ),
        ));
    }
    let test_number = opts.test_camera.unwrap_or(0);
    let test = found
        .iter()
        .position(|(n, _)| *n == test_number)
        .ok_or_else(|| {
            bad(
                dir,
                format!(
                    "there is no camera cam{test_number:02} to hold out (cameras: {})",
                    found
                        .iter()
                        .map(|(n, _)| format!("cam{n:02}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )
        })?;

    // Sizes and frame counts.
    let infos: Vec<Result<VideoInfo, DatasetError>> = found
        .par_iter()
        .map(|(_, f)| match f {
            Frames::Video(p) => video::probe(&opts.tools, p),
            Frames::Images(_, files) => {
                let (w, h) =
                    image::image_dimensions(&files[0]).map_err(|e| DatasetError::Image {
                        path: files[0].clone(),
                        message: e.to_string(),
                    })?;
                Ok(VideoInfo {
                    width: w,
                    height: h,
                    frames: files.len() as u64,
                })
            }
        })
        .collect();
    let infos: Vec<VideoInfo> = infos.into_iter().collect::<Result<_, _>>()?;
    let source_of = |i: usize| match &found[i].1 {
        Frames::Video(p) | Frames::Images(p, _) => p.display().to_string(),
    };
    let first = infos[0];
    for (i, info) in infos.iter().enumerate().skip(1) {
        if (info.width, info.height) != (first.width, first.height) {
            return Err(bad(
                Path::new(&source_of(i)),
                format!(
                    "frames are {}x{} but {} has {}x{} (all cameras must have one size)",
                    info.width,
                    info.height,
                    source_of(0),
                    first.width,
                    first.height
                ),
            ));
        }
        if info.frames != first.frames {
            return Err(bad(
                Path::new(&source_of(i)),
                format!(
                    "has {} frames but {} has {} (every camera must have the same number of frames)",
                    info.frames,
                    source_of(0),
                    first.frames
                ),
            ));
        }
    }
    if first.frames * rows_n as u64 > MAX_VIEWS {
        return Err(bad(
            dir,
            format!("{} frames x {rows_n} cameras is too many", first.frames),
        ));
    }
    if first.width < opts.downscale || first.height < opts.downscale {
        return Err(bad(
            dir,
            format!(
                "frames of {}x{} are smaller than the downscale factor {}",
                first.width, first.height, opts.downscale
            ),
        ));
    }

    // Cameras in the file's world.
    let (w, h) = (first.width, first.height);
    let mut cameras = Vec::with_capacity(rows_n);
    for (i, row) in rows.iter().enumerate() {
        let [hh, ww, f] = row.hwf;
        let (sx, sy) = (w as f64 / ww, h as f64 / hh);
        if (sx - sy).abs() > 0.01 * sx.max(sy) {
            return Err(bad(
                &npy_path,
                format!(
                    "row {i}: hwf says {ww}x{hh} but {} has {w}x{h} frames (a different aspect ratio)",
                    source_of(i)
                ),
            ));
        }
        let focal = (f * 0.5 * (sx + sy)) as f32;
        let camera = Camera {
            width: w,
            height: h,
            fx: focal,
            fy: focal,
            cx: 0.5 * w as f32,
            cy: 0.5 * h as f32,
            world_from_camera: row.pose,
        };
        camera
            .validate()
            .map_err(|m| bad(&npy_path, format!("row {i}: {m}")))?;
        cameras.push(camera);
    }
    let normalization = match opts.normalization {
        Normalization::None => Similarity::IDENTITY,
        Normalization::Llff => {
            let poses: Vec<Mat4> = rows.iter().map(|r| r.pose).collect();
            let nears: Vec<f32> = rows.iter().map(|r| r.near as f32).collect();
            llff_normalization(&poses, &nears)
        }
    };
    let cams = found
        .into_iter()
        .zip(cameras)
        .zip(&rows)
        .map(|(((number, frames), mut camera), row)| {
            camera.world_from_camera = normalization.apply_pose(&camera.world_from_camera);
            RigCamera {
                number,
                frames,
                camera,
                near: row.near as f32 * normalization.scale,
                far: row.far as f32 * normalization.scale,
            }
        })
        .collect();
    Ok(Rig {
        cameras: cams,
        frames: first.frames as usize,
        normalization,
        test,
    })
}

/// Pushes every frame of `rig` (camera by camera, frame by frame) into `sink`, downscaled.
fn produce_frames(
    rig: &Rig,
    opts: &DynerfOptions,
    sink: &mut dyn FrameSink,
) -> Result<(), DatasetError> {
    let f = opts.downscale;
    let (w, h) = (rig.cameras[0].camera.width, rig.cameras[0].camera.height);
    for cam in &rig.cameras {
        match &cam.frames {
            Frames::Video(path) => {
                let info = VideoInfo {
                    width: w,
                    height: h,
                    frames: rig.frames as u64,
                };
                video::decode(&opts.tools, path, &info, &mut |_, rgb| {
                    if f > 1 {
                        sink.push(&downscale_rgb(rgb, w, h, f))
                    } else {
                        sink.push(rgb)
                    }
                })?;
            }
            Frames::Images(_, files) => {
                // Decode in parallel batches, push in order.
                for batch in files.chunks(32) {
                    let imgs: Vec<Result<Image8, DatasetError>> = batch
                        .par_iter()
                        .map(|p| {
                            let img = load_image(p, f)?;
                            if (img.width, img.height) != (w, h) {
                                return Err(bad(
                                    p,
                                    format!(
                                        "image is {}x{} but the first frame of the first camera is {w}x{h}",
                                        img.width, img.height
                                    ),
                                ));
                            }
                            Ok(img.image)
                        })
                        .collect();
                    for img in imgs {
                        sink.push(&img?.data)?;
                    }
                }
            }
        }
    }
    Ok(())
}

/// A fingerprint of the rig's sources and the options that change pixels.
fn fingerprint(rig: &Rig, opts: &DynerfOptions) -> Result<u64, DatasetError> {
    let mut fp = crate::cache::Fingerprint::default();
    fp.str("dynerf-v1");
    fp.bytes(&opts.downscale.to_le_bytes());
    for c in &rig.cameras {
        match &c.frames {
            Frames::Video(p) => fp.file(p)?,
            Frames::Images(_, files) => {
                for p in files {
                    fp.file(p)?;
                }
            }
        }
    }
    Ok(fp.finish())
}

/// The LLFF row (3x5 `[R | t | hwf]` row-major, then near, far) of an OpenGL camera.
pub fn llff_row(camera: &Camera, near: f64, far: f64) -> [f64; 17] {
    let m = camera.world_from_camera;
    let (x, y, z, t) = (
        m.x_axis.truncate(),
        m.y_axis.truncate(),
        m.z_axis.truncate(),
        m.w_axis.truncate(),
    );
    // Columns: down (-Y), right (X), backwards (Z), centre, hwf.
    let cols = [-y, x, z, t];
    let hwf = [camera.height as f64, camera.width as f64, camera.fx as f64];
    let mut r = [0.0; 17];
    for row in 0..3 {
        for (c, v) in cols.iter().enumerate() {
            r[row * 5 + c] = v[row] as f64;
        }
        r[row * 5 + 4] = hwf[row];
    }
    r[15] = near;
    r[16] = far;
    r
}

/// The OpenGL camera-to-world matrix of an LLFF row (the inverse of [`llff_row`]'s pose part).
pub fn c2w_from_llff_row(row: &[f64; 17]) -> Mat4 {
    let col = |c: usize| Vec3::new(row[c] as f32, row[5 + c] as f32, row[10 + c] as f32);
    let (down, right, back, t) = (col(0), col(1), col(2), col(3));
    Mat4::from_cols(
        right.extend(0.0),
        (-down).extend(0.0),
        back.extend(0.0),
        t.extend(1.0),
    )
}

/// Writes `poses_bounds.npy` for cameras with their near/far bounds (fixtures, tools).
pub fn write_poses_bounds(path: &Path, cameras: &[(Camera, f64, f64)]) -> std::io::Result<()> {
    let data: Vec<f64> = cameras
        .iter()
        .flat_map(|(c, n, f)| llff_row(c, *n, *f))
        .collect();
    crate::npy::write_f64(path, &[cameras.len(), 17], &data)
}

/// Loads a DyNeRF dataset from `dir` (see the module docs). Frames are decoded into memory or
/// into the frame cache that `opts.storage` names (reused without decoding when it is valid).
pub fn load(dir: &Path, opts: &DynerfOptions) -> Result<Dataset, DatasetError> {
    Ok(load_with_rig(dir, opts)?.0)
}

/// [`load`], also returning the rig (normalisation, cameras, sources) and where frames went.
pub fn load_with_rig(
    dir: &Path,
    opts: &DynerfOptions,
) -> Result<(Dataset, Rig, Stored), DatasetError> {
    if opts.downscale == 0 {
        return Err(bad(dir, "downscale factor must be at least 1"));
    }
    if let Some(b) = &opts.bounds {
        b.validate()
            .map_err(|m| bad(dir, format!("bounds override: {m}")))?;
    }
    let rig = read_rig(dir, opts)?;
    let f = opts.downscale;
    let (w0, h0) = (rig.cameras[0].camera.width, rig.cameras[0].camera.height);
    let (w, h) = (w0 / f, h0 / f);
    let key = CacheKey {
        width: w,
        height: h,
        count: (rig.cameras.len() * rig.frames) as u64,
        fingerprint: fingerprint(&rig, opts)?,
    };
    let stored = store_frames(&opts.storage, key, opts.progress.as_deref(), &mut |sink| {
        produce_frames(&rig, opts, sink)
    })?;
    let mut frames = stored.clone().frames().into_iter();
    let mut train = Vec::new();
    let mut test = Vec::new();
    for (ci, cam) in rig.cameras.iter().enumerate() {
        let mut camera = cam.camera;
        if f > 1 {
            camera = camera.scaled(1.0 / f as f32);
            camera.width = w;
            camera.height = h;
        }
        let source = match &cam.frames {
            Frames::Video(p) | Frames::Images(p, _) => p.clone(),
        };
        for j in 0..rig.frames {
            let data = frames
                .next()
                .ok_or_else(|| bad(dir, "internal: too few frames"))?;
            let view = View {
                camera,
                time: if rig.frames > 1 {
                    j as f32 / (rig.frames - 1) as f32
                } else {
                    0.0
                },
                image: Image8 {
                    width: w,
                    height: h,
                    data,
                },
                source: source.clone(),
                camera_id: Some(cam.number),
                alpha: None,
            };
            if ci == rig.test {
                test.push(view);
            } else {
                train.push(view);
            }
        }
    }
    let bounds = opts.bounds.unwrap_or_else(|| {
        let train_cams: Vec<&RigCamera> = rig
            .cameras
            .iter()
            .enumerate()
            .filter(|(i, _)| *i != rig.test)
            .map(|(_, c)| c)
            .collect();
        let cams: Vec<Camera> = train_cams.iter().map(|c| c.camera).collect();
        let nears: Vec<f32> = train_cams.iter().map(|c| c.near).collect();
        let fars: Vec<f32> = train_cams.iter().map(|c| c.far).collect();
        forward_facing_bounds(&cams, &nears, &fars)
    });
    let name = dir
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| "dataset".into());
    let dataset = Dataset {
        name,
        train,
        test,
        bounds,
        background: [1.0; 3],
        num_frames: rig.frames,
        // Every camera's, the held-out one's too: it renders from the same sampler.
        near: rig
            .cameras
            .iter()
            .map(|c| c.near)
            .reduce(f32::min)
            .filter(|n| n.is_finite() && *n > 0.0),
    };
    Ok((dataset, rig, stored))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A forward-facing arc of `n` cameras looking at `target`.
    fn rig(n: usize, w: u32, h: u32) -> Vec<Camera> {
        let target = Vec3::new(0.0, 0.3, 0.9);
        (0..n)
            .map(|i| {
                let a = (i as f32 / (n - 1).max(1) as f32 - 0.5) * 1.2;
                let eye = target + Vec3::new(4.0 * a.sin(), -4.0 * a.cos(), 0.5 + 0.1 * i as f32);
                Camera::look_at(w, h, 0.9, eye, target, Vec3::Z)
            })
            .collect()
    }

    /// Pixel value of camera `c`, frame `j`, pixel `i`, channel `ch`.
    fn value(c: usize, j: usize, i: usize, ch: usize) -> u8 {
        ((c * 60 + j * 17 + i * 5 + ch * 40) % 256) as u8
    }

    fn frame(c: usize, j: usize, w: u32, h: u32) -> Vec<u8> {
        (0..(w * h) as usize * 3)
            .map(|k| value(c, j, k / 3, k % 3))
            .collect()
    }

    /// `cams` cameras x `frames` frames of `w x h` as `camNN/` PNG folders (`skip` left out).
    fn write_folders(dir: &Path, cams: usize, frames: usize, w: u32, h: u32) {
        for c in 0..cams {
            let d = dir.join(format!("cam{c:02}"));
            std::fs::create_dir_all(&d).unwrap();
            for j in 0..frames {
                let img = image::RgbImage::from_raw(w, h, frame(c, j, w, h)).unwrap();
                img.save(d.join(format!("{j:04}.png"))).unwrap();
            }
        }
    }

    fn write_npy(dir: &Path, cams: &[Camera]) {
        let rows: Vec<(Camera, f64, f64)> = cams.iter().map(|c| (*c, 2.0, 9.0)).collect();
        write_poses_bounds(&dir.join("poses_bounds.npy"), &rows).unwrap();
    }

    fn raw_opts() -> DynerfOptions {
        DynerfOptions {
            normalization: Normalization::None,
            ..Default::default()
        }
    }

    fn expect_err(dir: &Path, opts: &DynerfOptions, needles: &[&str]) {
        let e = load(dir, opts).unwrap_err().to_string();
        for n in needles {
            assert!(e.contains(n), "error `{e}` should mention `{n}`");
        }
    }

    #[test]
    fn llff_rows_round_trip_to_opengl_cameras() {
        let cams = rig(3, 8, 6);
        for c in &cams {
            let r = llff_row(c, 1.0, 2.0);
            let row = parse_row(Path::new("x"), 0, &r).ok().unwrap();
            assert!(row.pose.abs_diff_eq(c.world_from_camera, 1e-6));
            assert_eq!(row.hwf, [6.0, 8.0, c.fx as f64]);
        }
    }

    #[test]
    fn folders_load_with_cameras_times_split_and_downscale() {
        let dir = tempfile::tempdir().unwrap();
        let cams = rig(3, 8, 6);
        write_folders(dir.path(), 3, 4, 8, 6);
        write_npy(dir.path(), &cams);
        let d = load(dir.path(), &raw_opts()).unwrap();
        assert_eq!((d.train.len(), d.test.len(), d.num_frames), (8, 4, 4));
        assert!(d.test.iter().all(|v| v.camera_id == Some(0)));
        let times: Vec<f32> = d.test.iter().map(|v| v.time).collect();
        assert_eq!(times, [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0]);
        for v in d.train.iter().chain(&d.test) {
            let c = v.camera_id.unwrap();
            assert!(v
                .camera
                .world_from_camera
                .abs_diff_eq(cams[c].world_from_camera, 1e-6));
            assert!((v.camera.fx - cams[c].fx).abs() < 1e-4);
            let j = (v.time * 3.0).round() as usize;
            assert_eq!(v.image.data, frame(c, j, 8, 6));
        }
        // Another held-out camera.
        let opts = DynerfOptions {
            test_camera: Some(2),
            ..raw_opts()
        };
        let d2 = load(dir.path(), &opts).unwrap();
        assert!(d2.test.iter().all(|v| v.camera_id == Some(2)));
        expect_err(
            dir.path(),
            &DynerfOptions {
                test_camera: Some(7),
                ..raw_opts()
            },
            &["cam07", "cam00, cam01, cam02"],
        );
        // Downscale 2: area filter, halved intrinsics.
        let half = load(
            dir.path(),
            &DynerfOptions {
                downscale: 2,
                ..raw_opts()
            },
        )
        .unwrap();
        let v = &half.train[0];
        assert_eq!((v.image.width, v.image.height), (4, 3));
        assert_eq!((v.camera.width, v.camera.height), (4, 3));
        assert!((v.camera.fx - cams[1].fx / 2.0).abs() < 1e-4);
        let full = frame(1, 0, 8, 6);
        assert_eq!(v.image.data, downscale_rgb(&full, 8, 6, 2));
    }

    #[test]
    fn llff_normalization_recentres_and_scales() {
        let dir = tempfile::tempdir().unwrap();
        let cams = rig(4, 8, 6);
        write_folders(dir.path(), 4, 2, 8, 6);
        write_npy(dir.path(), &cams);
        let (d, rig, _) = load_with_rig(dir.path(), &DynerfOptions::default()).unwrap();
        let s = rig.normalization;
        assert!((s.scale - 1.0 / (0.75 * 2.0)).abs() < 1e-6);
        // Mean centre at the origin, mean viewing axis -Z, cameras the similarity of the input.
        let n = rig.cameras.len() as f32;
        let mean = rig.cameras.iter().map(|c| c.camera.center()).sum::<Vec3>() / n;
        assert!(mean.length() < 1e-5, "{mean}");
        let back = rig
            .cameras
            .iter()
            .map(|c| c.camera.world_from_camera.z_axis.truncate())
            .sum::<Vec3>()
            .normalize();
        assert!((back - Vec3::Z).length() < 1e-5, "{back}");
        for (rc, c) in rig.cameras.iter().zip(&cams) {
            assert!(rc
                .camera
                .world_from_camera
                .abs_diff_eq(s.apply_pose(&c.world_from_camera), 1e-5));
            assert!((rc.near - 4.0 / 3.0).abs() < 1e-5);
            assert!((rc.far - 9.0 * s.scale).abs() < 1e-4);
        }
        // Distances scale uniformly.
        let a = (cams[0].center() - cams[3].center()).length();
        let b = (rig.cameras[0].camera.center() - rig.cameras[3].camera.center()).length();
        assert!((b - a * s.scale).abs() < 1e-4);
        // The contraction centre is the (normalised) look-at point, in front of the rig.
        match d.bounds {
            SceneBounds::Contracted { center, radius } => {
                let target = s.apply_point(Vec3::new(0.0, 0.3, 0.9));
                assert!((center - target).length() < 1e-3, "{center} vs {target}");
                assert!(center.z < 0.0);
                assert!(radius > 0.0);
            }
            b => panic!("{b:?}"),
        }
    }

    #[test]
    fn parallel_rig_contracts_around_the_mid_depth() {
        let cams: Vec<Camera> = (0..3)
            .map(|i| {
                let eye = Vec3::new(i as f32 - 1.0, 0.0, 0.0);
                Camera::look_at(8, 6, 0.9, eye, eye - Vec3::Z, Vec3::Y)
            })
            .collect();
        let b = forward_facing_bounds(&cams, &[1.0; 3], &[5.0; 3]);
        match b {
            SceneBounds::Contracted { center, radius } => {
                assert!(
                    (center - Vec3::new(0.0, 0.0, -3.0)).length() < 1e-5,
                    "{center}"
                );
                assert_eq!(radius, 3.0);
                // Content between near and 2x the mid depth is uncontracted; beyond, contracted.
                let inner = b.to_unit(Vec3::new(0.0, 0.0, -1.0));
                let far = b.to_unit(Vec3::new(0.0, 0.0, -100.0));
                assert!(inner.z > 0.25 && inner.z < 0.75, "{inner}");
                assert!(far.z < 0.25 && far.z > 0.0, "{far}");
            }
            b => panic!("{b:?}"),
        }
    }

    #[test]
    fn broken_pose_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let cams = rig(3, 8, 6);
        write_folders(dir.path(), 3, 2, 8, 6);
        let npy = dir.path().join("poses_bounds.npy");
        let rows: Vec<f64> = cams.iter().flat_map(|c| llff_row(c, 2.0, 9.0)).collect();
        let o = raw_opts();
        // Truncated.
        let bytes = crate::npy::encode_f64(&[3, 17], &rows);
        std::fs::write(&npy, &bytes[..bytes.len() - 8]).unwrap();
        expect_err(dir.path(), &o, &["poses_bounds.npy", "truncated"]);
        // Wrong column count.
        crate::npy::write_f64(&npy, &[3, 16], &rows[..48]).unwrap();
        expect_err(dir.path(), &o, &["poses_bounds.npy", "(N, 17)", "[3, 16]"]);
        // Non-finite pose.
        let mut r = rows.clone();
        r[17 + 3] = f64::NAN;
        crate::npy::write_f64(&npy, &[3, 17], &r).unwrap();
        expect_err(dir.path(), &o, &["poses_bounds.npy", "row 1", "not finite"]);
        // Not a rotation.
        let mut r = rows.clone();
        r[0] *= 3.0;
        crate::npy::write_f64(&npy, &[3, 17], &r).unwrap();
        expect_err(dir.path(), &o, &["row 0", "orthonormal"]);
        // near >= far.
        let mut r = rows.clone();
        r[2 * 17 + 16] = 1.0;
        crate::npy::write_f64(&npy, &[3, 17], &r).unwrap();
        expect_err(dir.path(), &o, &["row 2", "near/far"]);
        // More rows than cameras.
        let mut r = rows.clone();
        r.extend_from_slice(&rows[..17]);
        crate::npy::write_f64(&npy, &[4, 17], &r).unwrap();
        expect_err(dir.path(), &o, &["4 rows", "3 camNN/ frame folders"]);
        // hwf with another aspect ratio than the frames.
        let mut r = rows.clone();
        r[4] = 5.0;
        crate::npy::write_f64(&npy, &[3, 17], &r).unwrap();
        expect_err(dir.path(), &o, &["row 0", "aspect ratio"]);
        // Missing file.
        std::fs::remove_file(&npy).unwrap();
        expect_err(dir.path(), &o, &["poses_bounds.npy", "cannot read"]);
    }

    #[test]
    fn broken_frame_folders_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let cams = rig(3, 8, 6);
        write_folders(dir.path(), 3, 3, 8, 6);
        write_npy(dir.path(), &cams);
        let o = raw_opts();
        // One camera with fewer frames.
        std::fs::remove_file(dir.path().join("cam02/0002.png")).unwrap();
        expect_err(dir.path(), &o, &["cam02", "2 frames", "cam00", "3"]);
        // A frame that is not an image.
        std::fs::write(dir.path().join("cam02/0002.png"), b"garbage").unwrap();
        expect_err(dir.path(), &o, &["cam02/0002.png", "decode"]);
        // A frame of another size.
        image::RgbImage::new(6, 6)
            .save(dir.path().join("cam02/0002.png"))
            .unwrap();
        expect_err(dir.path(), &o, &["cam02/0002.png", "6x6"]);
    }
}
