//! COLMAP: the structure-from-motion program that `msth import` runs, and a reader for the
//! sparse models it writes.
//!
//! [`Colmap`] drives the `colmap` command line (feature extraction, matching, mapping), on the
//! CPU, one log file per step. [`read_binary_model`] reads the binary model the mapper writes
//! (`cameras.bin`, `images.bin`, `points3D.bin`; in [`binary`]), [`read_text_model`] the text one
//! (`cameras.txt`, `images.txt`, `points3D.txt`, as written by `colmap model_converter
//! --output_type TXT`), [`read_model`] whichever a folder holds; both check every entry and give
//! the same [`Model`], whose image poses [`Model::world_from_camera`] turns into the OpenGL
//! camera-to-world matrices the rest of `msth` uses.
//!
//! COLMAP conventions: an image's `QW QX QY QZ TX TY TZ` is the world-to-camera rotation and
//! translation of an OpenCV camera (+X right, +Y down, looking down +Z); pixel `(0, 0)`'s centre
//! is at `(0.5, 0.5)`, as in the nerfstudio files this crate reads.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use glam::{DMat3, DMat4, DQuat, DVec3, DVec4};

use crate::DatasetError;

mod binary;
pub use binary::{read_binary_model, BinaryModelError};

/// Largest accepted line count per model file (a reconstruction of a long video has a few
/// hundred thousand points; anything beyond is certainly not a COLMAP model).
const MAX_ENTRIES: usize = 20_000_000;

/// A COLMAP camera model with the parameter layout of `cameras.txt`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraModel {
    /// `f, cx, cy`.
    SimplePinhole,
    /// `fx, fy, cx, cy`.
    Pinhole,
    /// `f, cx, cy, k1`.
    SimpleRadial,
    /// `f, cx, cy, k1, k2`.
    Radial,
    /// `fx, fy, cx, cy, k1, k2, p1, p2` (nerfstudio's default for phone videos).
    Opencv,
}

impl CameraModel {
    /// The name COLMAP uses.
    pub fn name(self) -> &'static str {
        match self {
            CameraModel::SimplePinhole => "SIMPLE_PINHOLE",
            CameraModel::Pinhole => "PINHOLE",
            CameraModel::SimpleRadial => "SIMPLE_RADIAL",
            CameraModel::Radial => "RADIAL",
            CameraModel::Opencv => "OPENCV",
        }
    }

    fn num_params(self) -> usize {
        match self {
            CameraModel::SimplePinhole => 3,
            CameraModel::Pinhole => 4,
            CameraModel::SimpleRadial => 4,
            CameraModel::Radial => 5,
            CameraModel::Opencv => 8,
        }
    }
}

/// A camera model name that [`CameraModel`]'s `FromStr` does not know.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown camera model `{0}` (expected opencv, radial, simple_radial, pinhole or simple_pinhole)")]
pub struct UnknownCameraModel(pub String);

impl std::str::FromStr for CameraModel {
    type Err = UnknownCameraModel;
    fn from_str(s: &str) -> Result<Self, UnknownCameraModel> {
        match s.to_ascii_uppercase().replace('-', "_").as_str() {
            "SIMPLE_PINHOLE" => Ok(CameraModel::SimplePinhole),
            "PINHOLE" => Ok(CameraModel::Pinhole),
            "SIMPLE_RADIAL" => Ok(CameraModel::SimpleRadial),
            "RADIAL" => Ok(CameraModel::Radial),
            "OPENCV" => Ok(CameraModel::Opencv),
            _ => Err(UnknownCameraModel(s.to_string())),
        }
    }
}

/// Pinhole intrinsics in pixels plus the OpenCV distortion `k1, k2, p1, p2`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
}

/// One line of `cameras.txt`.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    pub model: CameraModel,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// The intrinsics in the OpenCV model (every supported model is a special case of it).
    pub fn intrinsics(&self) -> Intrinsics {
        let p = &self.params;
        let (fx, fy, cx, cy, rest) = match self.model {
            CameraModel::SimplePinhole | CameraModel::SimpleRadial | CameraModel::Radial => {
                (p[0], p[0], p[1], p[2], &p[3..])
            }
            CameraModel::Pinhole | CameraModel::Opencv => (p[0], p[1], p[2], p[3], &p[4..]),
        };
        let at = |i: usize| rest.get(i).copied().unwrap_or(0.0);
        Intrinsics {
            fx,
            fy,
            cx,
            cy,
            k1: at(0),
            k2: at(1),
            p1: at(2),
            p2: at(3),
        }
    }
}

/// One registered image of `images.txt` / `images.bin`.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    /// COLMAP's image id (a model's images are kept in id order).
    pub image_id: u32,
    /// World-to-camera rotation `(w, x, y, z)` and translation (OpenCV camera axes).
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: u32,
    /// The file name relative to the image folder COLMAP read (with `/` separators).
    pub name: String,
    /// Ids of the 3D points this image observes (each once).
    pub point_ids: Vec<u64>,
}

/// One line of `points3D.txt`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColmapPoint {
    pub position: DVec3,
    /// Mean reprojection error of the point's observations, pixels.
    pub error_px: f64,
    pub track_len: usize,
}

/// A sparse reconstruction.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Model {
    pub cameras: BTreeMap<u32, ColmapCamera>,
    pub images: Vec<ColmapImage>,
    pub points: BTreeMap<u64, ColmapPoint>,
}

impl Model {
    /// The mean over points of their reprojection error, pixels (COLMAP's "mean reprojection
    /// error"); 0 without points.
    pub fn mean_reprojection_error_px(&self) -> f64 {
        if self.points.is_empty() {
            return 0.0;
        }
        self.points.values().map(|p| p.error_px).sum::<f64>() / self.points.len() as f64
    }

    /// The mean of `fx` and `fy` over the cameras, pixels (0 without cameras).
    pub fn mean_focal_px(&self) -> f64 {
        let n = self.cameras.len().max(1) as f64;
        self.cameras
            .values()
            .map(|c| {
                let k = c.intrinsics();
                0.5 * (k.fx + k.fy)
            })
            .sum::<f64>()
            / n
    }

    /// The OpenGL camera-to-world matrix (+X right, +Y up, looking down -Z) of `image`.
    pub fn world_from_camera(image: &ColmapImage) -> DMat4 {
        let [w, x, y, z] = image.qvec;
        let camera_from_world = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        let r = camera_from_world.transpose();
        let center = -(r * DVec3::from_array(image.tvec));
        DMat4::from_cols(
            r.x_axis.extend(0.0),
            (-r.y_axis).extend(0.0),
            (-r.z_axis).extend(0.0),
            DVec4::new(center.x, center.y, center.z, 1.0),
        )
    }
}

fn bad(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Invalid {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// The non-comment, non-empty lines of a model file with their 1-based line numbers.
fn data_lines(path: &Path) -> Result<Vec<(usize, String)>, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let lines: Vec<(usize, String)> = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim().to_string()))
        .filter(|(_, l)| !l.starts_with('#'))
        .collect();
    if lines.len() > MAX_ENTRIES {
        return Err(bad(path, format!("more than {MAX_ENTRIES} lines")));
    }
    Ok(lines)
}

fn parse<T: std::str::FromStr>(
    path: &Path,
    line: usize,
    what: &str,
    s: &str,
) -> Result<T, DatasetError> {
    s.parse::<T>()
        .map_err(|_| bad(path, format!("line {line}: {what} `{s}` is not valid")))
}

fn finite(path: &Path, line: usize, what: &str, s: &str) -> Result<f64, DatasetError> {
    let v: f64 = parse(path, line, what, s)?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(bad(
            path,
            format!("line {line}: {what} `{s}` is not finite"),
        ))
    }
}

/// Why an entry of a COLMAP model (text or binary) was refused after it parsed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ModelEntryError {
    #[error("{model} takes {expected} parameters, found {found}")]
    ParameterCount {
        model: &'static str,
        expected: usize,
        found: usize,
    },
    #[error("parameter `{0}` is not finite")]
    NonFiniteParameter(f64),
    #[error("image size {width}x{height} is too large")]
    ImageTooLarge { width: u64, height: u64 },
    #[error("empty image or non-positive focal length")]
    EmptyImageOrFocal,
    #[error("pose value `{0}` is not finite")]
    NonFinitePose(f64),
    #[error("the quaternion is not a rotation (norm {0})")]
    NotARotation(f64),
    #[error("camera {0} appears twice")]
    DuplicateCamera(u32),
    #[error("camera {0} is not in the camera list")]
    UnknownCamera(u32),
    #[error("point {0} is not finite")]
    NonFinitePoint(u64),
    #[error("point {0} appears twice")]
    DuplicatePoint(u64),
    #[error("image {0} appears twice")]
    DuplicateImage(u32),
}

/// Checks one camera (both readers): a non-empty image that fits `u32`, the model's parameter
/// count, finite parameters and a positive focal length.
fn camera_entry(
    model: CameraModel,
    width: u64,
    height: u64,
    params: Vec<f64>,
) -> Result<ColmapCamera, ModelEntryError> {
    if params.len() != model.num_params() {
        return Err(ModelEntryError::ParameterCount {
            model: model.name(),
            expected: model.num_params(),
            found: params.len(),
        });
    }
    if let Some(&v) = params.iter().find(|v| !v.is_finite()) {
        return Err(ModelEntryError::NonFiniteParameter(v));
    }
    let (Ok(w), Ok(h)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(ModelEntryError::ImageTooLarge { width, height });
    };
    if w == 0 || h == 0 || params[0] <= 0.0 {
        return Err(ModelEntryError::EmptyImageOrFocal);
    }
    Ok(ColmapCamera {
        model,
        width: w,
        height: h,
        params,
    })
}

/// Checks one image pose (both readers): finite values and a quaternion that is a rotation.
fn pose_entry(q: &[f64; 4], t: &[f64; 3]) -> Result<(), ModelEntryError> {
    if let Some(&v) = q.iter().chain(t).find(|v| !v.is_finite()) {
        return Err(ModelEntryError::NonFinitePose(v));
    }
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !(0.5..=2.0).contains(&norm) {
        return Err(ModelEntryError::NotARotation(norm));
    }
    Ok(())
}

impl Model {
    fn add_camera(&mut self, id: u32, camera: ColmapCamera) -> Result<(), ModelEntryError> {
        match self.cameras.insert(id, camera) {
            Some(_) => Err(ModelEntryError::DuplicateCamera(id)),
            None => Ok(()),
        }
    }

    /// Adds an image whose observed point ids (`None`: no 3D point) are deduplicated here.
    fn add_image(
        &mut self,
        mut image: ColmapImage,
        observed: impl Iterator<Item = Option<u64>>,
    ) -> Result<(), ModelEntryError> {
        if !self.cameras.contains_key(&image.camera_id) {
            return Err(ModelEntryError::UnknownCamera(image.camera_id));
        }
        image.point_ids = observed.flatten().collect();
        image.point_ids.sort_unstable();
        image.point_ids.dedup();
        self.images.push(image);
        Ok(())
    }

    fn add_point(&mut self, id: u64, point: ColmapPoint) -> Result<(), ModelEntryError> {
        if !(point.position.is_finite() && point.error_px.is_finite()) {
            return Err(ModelEntryError::NonFinitePoint(id));
        }
        match self.points.insert(id, point) {
            Some(_) => Err(ModelEntryError::DuplicatePoint(id)),
            None => Ok(()),
        }
    }

    /// Images in id order; an id given twice is an error.
    fn sort_images(&mut self) -> Result<(), ModelEntryError> {
        self.images.sort_by_key(|i| i.image_id);
        match self
            .images
            .windows(2)
            .find(|w| w[0].image_id == w[1].image_id)
        {
            Some(w) => Err(ModelEntryError::DuplicateImage(w[0].image_id)),
            None => Ok(()),
        }
    }
}

/// Reads the model in `dir`: the binary one (`cameras.bin`, `images.bin`, `points3D.bin`) when
/// `cameras.bin` is there, else the text one.
pub fn read_model(dir: &Path) -> Result<Model, DatasetError> {
    if dir.join("cameras.bin").is_file() {
        binary::read_binary_model(dir)
    } else {
        read_text_model(dir)
    }
}

/// Reads `cameras.txt`, `images.txt` and `points3D.txt` from `dir`; images in id order.
pub fn read_text_model(dir: &Path) -> Result<Model, DatasetError> {
    let mut model = Model::default();
    let path = dir.join("cameras.txt");
    for (n, line) in data_lines(&path)? {
        if line.is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 4 {
            return Err(bad(
                &path,
                format!("line {n}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..."),
            ));
        }
        let id: u32 = parse(&path, n, "camera id", f[0])?;
        let model_kind: CameraModel = f[1].parse().map_err(|m: UnknownCameraModel| {
            bad(
                &path,
                format!("line {n}: {m}; import with --camera-model opencv"),
            )
        })?;
        let width: u64 = parse(&path, n, "width", f[2])?;
        let height: u64 = parse(&path, n, "height", f[3])?;
        let params = f[4..]
            .iter()
            .map(|s| finite(&path, n, "parameter", s))
            .collect::<Result<Vec<_>, _>>()?;
        camera_entry(model_kind, width, height, params)
            .and_then(|camera| model.add_camera(id, camera))
            .map_err(|m| bad(&path, format!("line {n}: {m}")))?;
    }
    let path = dir.join("images.txt");
    let lines = data_lines(&path)?;
    let mut i = 0;
    while i < lines.len() {
        let (n, ref line) = lines[i];
        if line.is_empty() {
            i += 1;
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 10 {
            return Err(bad(
                &path,
                format!("line {n}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
            ));
        }
        let image_id: u32 = parse(&path, n, "image id", f[0])?;
        let mut q = [0.0; 4];
        for (k, s) in f[1..5].iter().enumerate() {
            q[k] = finite(&path, n, "quaternion", s)?;
        }
        let mut t = [0.0; 3];
        for (k, s) in f[5..8].iter().enumerate() {
            t[k] = finite(&path, n, "translation", s)?;
        }
        pose_entry(&q, &t).map_err(|m| bad(&path, format!("line {n}: {m}")))?;
        let camera_id: u32 = parse(&path, n, "camera id", f[8])?;
        let image = ColmapImage {
            image_id,
            qvec: q,
            tvec: t,
            camera_id,
            name: f[9..].join(" "),
            point_ids: Vec::new(),
        };
        // The observations line (may be empty, or missing at the very end of the file).
        let mut observed = Vec::new();
        if let Some((m, obs)) = lines.get(i + 1) {
            let o: Vec<&str> = obs.split_whitespace().collect();
            if !o.len().is_multiple_of(3) {
                return Err(bad(
                    &path,
                    format!("line {m}: observations come in X Y POINT3D_ID triples"),
                ));
            }
            for tri in o.chunks_exact(3) {
                let id: i64 = parse(&path, *m, "point id", tri[2])?;
                observed.push(u64::try_from(id).ok());
            }
        }
        model
            .add_image(image, observed.into_iter())
            .map_err(|m| bad(&path, format!("line {n}: {m}")))?;
        i += 2;
    }
    model.sort_images().map_err(|m| bad(&path, m.to_string()))?;
    let path = dir.join("points3D.txt");
    for (n, line) in data_lines(&path)? {
        if line.is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        if f.len() < 8 || !(f.len() - 8).is_multiple_of(2) {
            return Err(bad(
                &path,
                format!("line {n}: expected POINT3D_ID X Y Z R G B ERROR TRACK[] (pairs)"),
            ));
        }
        let id: u64 = parse(&path, n, "point id", f[0])?;
        let p = DVec3::new(
            finite(&path, n, "x", f[1])?,
            finite(&path, n, "y", f[2])?,
            finite(&path, n, "z", f[3])?,
        );
        let error_px = finite(&path, n, "error", f[7])?;
        let point = ColmapPoint {
            position: p,
            error_px,
            track_len: (f.len() - 8) / 2,
        };
        model
            .add_point(id, point)
            .map_err(|m| bad(&path, format!("line {n}: {m}")))?;
    }
    Ok(model)
}

/// How images share intrinsics (`colmap feature_extractor`'s image reader options).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sharing {
    /// One camera for all images (videos from one device type at one size).
    All,
    /// One camera per sub-folder of the image folder (one folder per video).
    PerFolder,
}

/// How to match features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Matching {
    /// Every pair of images (small sets: rig time steps, short videos).
    Exhaustive,
    /// Each image with its neighbours in name order (long monocular videos).
    Sequential { overlap: usize },
}

/// What to run.
#[derive(Clone, Debug, PartialEq)]
pub struct RunOptions {
    pub camera_model: CameraModel,
    pub sharing: Sharing,
    pub matching: Matching,
    /// CPU threads for every step.
    pub threads: usize,
    /// Mapper runs on the same matches, with random seeds `0..mapper_runs` (at least one): the
    /// one agreeing best with the others is kept ([`choose_trial`]).
    pub mapper_runs: usize,
}

/// The `colmap` program: `colmap` from `PATH`, or the path in `MSTH_COLMAP`. Runs headless
/// (`QT_QPA_PLATFORM=offscreen`, CPU SIFT).
#[derive(Clone, Debug, PartialEq)]
pub struct Colmap {
    pub program: PathBuf,
}

impl Default for Colmap {
    fn default() -> Self {
        Colmap {
            program: std::env::var_os("MSTH_COLMAP")
                .map(PathBuf::from)
                .unwrap_or_else(|| PathBuf::from("colmap")),
        }
    }
}

/// What a COLMAP run produced.
#[derive(Clone, Debug, Default)]
pub struct Reconstruction {
    /// The largest model (most registered images).
    pub model: Model,
    /// Where it is (`sparse/seedS/N`).
    pub model_dir: PathBuf,
    /// Number of models COLMAP made (more than one: the images fell apart into groups).
    pub num_models: usize,
    /// Wall time of all steps.
    pub wall: Duration,
    /// Every mapper run that made a model, in seed order, and which of them is [`Self::model`].
    pub trials: Vec<TrialSummary>,
    pub chosen: usize,
}

/// One mapper run of [`Colmap::reconstruct`].
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TrialSummary {
    pub seed: u32,
    pub images_registered: usize,
    pub points: usize,
    pub mean_reprojection_error_px: f64,
    /// Mean of `fx` and `fy` over the cameras, pixels.
    pub focal_px: f64,
    /// Mean [`rotation_disagreement_deg`] with the other runs (`None` for a single run).
    pub disagreement_deg: Option<f64>,
}

/// Why running COLMAP failed.
#[derive(Debug, thiserror::Error)]
pub enum ColmapError {
    #[error("`{program}` was not found: install COLMAP (Debian/Ubuntu: `apt-get install colmap`, or see https://colmap.github.io/install.html) or set MSTH_COLMAP to its path")]
    Missing { program: String },
    #[error("COLMAP's {step} failed ({message}); its output is in {log}")]
    Failed {
        step: &'static str,
        message: String,
        log: PathBuf,
    },
    #[error("COLMAP registered no images: {why}; its output is in {log}")]
    NoModel { why: String, log: PathBuf },
    #[error(transparent)]
    Dataset(#[from] DatasetError),
}

impl Colmap {
    fn command(&self) -> Command {
        let mut c = Command::new(&self.program);
        c.env("QT_QPA_PLATFORM", "offscreen").stdin(Stdio::null());
        c
    }

    /// Whether the program starts (`colmap help`).
    pub fn check(&self) -> Result<(), ColmapError> {
        let missing = || ColmapError::Missing {
            program: self.program.display().to_string(),
        };
        let status = self
            .command()
            .arg("help")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .map_err(|_| missing())?;
        if status.success() {
            Ok(())
        } else {
            Err(missing())
        }
    }

    /// Runs `colmap ARGS`, output into `log`.
    fn step(&self, step: &'static str, args: &[String], log: &Path) -> Result<(), ColmapError> {
        let file = File::create(log).map_err(|source| DatasetError::Io {
            path: log.to_path_buf(),
            source,
        })?;
        let err_file = file.try_clone().map_err(|source| DatasetError::Io {
            path: log.to_path_buf(),
            source,
        })?;
        let status = self
            .command()
            .args(args)
            .stdout(file)
            .stderr(err_file)
            .status();
        let status = match status {
            Ok(s) => s,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(ColmapError::Missing {
                    program: self.program.display().to_string(),
                })
            }
            Err(e) => {
                return Err(ColmapError::Failed {
                    step,
                    message: format!("cannot start it: {e}"),
                    log: log.to_path_buf(),
                })
            }
        };
        if !status.success() {
            return Err(ColmapError::Failed {
                step,
                message: format!("{status}: {}", last_line(log)),
                log: log.to_path_buf(),
            });
        }
        Ok(())
    }

    /// Reconstructs the images under `images` (sub-folders allowed) in `work` (which must exist):
    /// `database.db`, `sparse/N/` (COLMAP's binary models) and one log per step.
    /// `progress` receives a line before each step.
    pub fn reconstruct(
        &self,
        images: &Path,
        work: &Path,
        opts: &RunOptions,
        progress: &mut dyn FnMut(&str),
    ) -> Result<Reconstruction, ColmapError> {
        self.check()?;
        let start = Instant::now();
        let s = |p: &Path| p.display().to_string();
        let db = work.join("database.db");
        let sparse = work.join("sparse");
        std::fs::create_dir_all(&sparse).map_err(|source| DatasetError::Io {
            path: sparse.clone(),
            source,
        })?;
        let threads = opts.threads.max(1).to_string();
        let mut args: Vec<String> = vec![
            "feature_extractor".into(),
            "--database_path".into(),
            s(&db),
            "--image_path".into(),
            s(images),
            "--ImageReader.camera_model".into(),
            opts.camera_model.name().into(),
            "--SiftExtraction.use_gpu".into(),
            "0".into(),
            "--SiftExtraction.num_threads".into(),
            threads.clone(),
        ];
        match opts.sharing {
            Sharing::All => args.extend(["--ImageReader.single_camera".into(), "1".into()]),
            Sharing::PerFolder => {
                args.extend(["--ImageReader.single_camera_per_folder".into(), "1".into()])
            }
        }
        progress("COLMAP: extracting SIFT features (CPU)");
        self.step("feature extraction", &args, &work.join("features.log"))?;
        let mut args: Vec<String> = match opts.matching {
            Matching::Exhaustive => vec!["exhaustive_matcher".into()],
            Matching::Sequential { overlap } => vec![
                "sequential_matcher".into(),
                "--SequentialMatching.overlap".into(),
                overlap.max(1).to_string(),
            ],
        };
        // Guided matching (re-matching under the estimated two-view geometry) finds the
        // matches that the ratio test drops on repetitive texture (bricks, checkers); without it
        // small frames of such scenes often give no initial pair.
        args.extend([
            "--database_path".into(),
            s(&db),
            "--SiftMatching.guided_matching".into(),
            "1".into(),
            "--SiftMatching.use_gpu".into(),
            "0".into(),
            "--SiftMatching.num_threads".into(),
            threads.clone(),
        ]);
        progress("COLMAP: matching features");
        self.step("matching", &args, &work.join("matching.log"))?;
        let runs = opts.mapper_runs.max(1);
        let mut trials: Vec<(u32, Model, PathBuf, usize)> = Vec::new();
        let mut first_log = None;
        for seed in 0..runs as u32 {
            progress(&format!(
                "COLMAP: mapping (incremental structure from motion), run {} of {runs}",
                seed + 1
            ));
            let out = sparse.join(format!("seed{seed}"));
            std::fs::create_dir_all(&out).map_err(|source| DatasetError::Io {
                path: out.clone(),
                source,
            })?;
            let log = work.join(format!("mapper-seed{seed}.log"));
            first_log.get_or_insert_with(|| log.clone());
            let mapped = self.step(
                "mapping",
                &[
                    "mapper".into(),
                    "--database_path".into(),
                    s(&db),
                    "--image_path".into(),
                    s(images),
                    "--output_path".into(),
                    s(&out),
                    "--Mapper.num_threads".into(),
                    threads.clone(),
                    // The mapper is deterministic for a given database and seed; other seeds
                    // give other RANSAC samples, hence independent reconstructions to compare.
                    "--random_seed".into(),
                    seed.to_string(),
                    // Run the global bundle adjustments to convergence (as nerfstudio does):
                    // the default stops early, which costs accuracy on small captures.
                    "--Mapper.ba_global_function_tolerance".into(),
                    "1e-6".into(),
                ],
                &log,
            );
            match mapped {
                Err(ColmapError::Failed { message, .. })
                    if message.contains("failed to create sparse model") =>
                {
                    continue
                }
                Err(e) => return Err(e),
                Ok(()) => {}
            }
            if let Some((model, dir, n)) = largest_model(&out)? {
                trials.push((seed, model, dir, n));
            }
        }
        if trials.is_empty() {
            return Err(ColmapError::NoModel {
                why: "the mapper found no pair of images with enough matches to start from (too little texture or overlap?)".into(),
                log: first_log.unwrap_or_else(|| work.join("mapper-seed0.log")),
            });
        }
        let models: Vec<&Model> = trials.iter().map(|t| &t.1).collect();
        let (chosen, disagreement) = choose_trial(&models);
        let summaries = trials
            .iter()
            .zip(disagreement)
            .map(|((seed, model, _, _), d)| TrialSummary {
                seed: *seed,
                images_registered: model.images.len(),
                points: model.points.len(),
                mean_reprojection_error_px: model.mean_reprojection_error_px(),
                focal_px: model.mean_focal_px(),
                disagreement_deg: d,
            })
            .collect();
        let (_, model, model_dir, num_models) = trials.swap_remove(chosen);
        Ok(Reconstruction {
            model,
            model_dir,
            num_models,
            wall: start.elapsed(),
            trials: summaries,
            chosen,
        })
    }
}

/// The model in `sparse` (one sub-folder per model, binary as the mapper writes it, or text)
/// with the most registered images, its folder and how many models there are; `None` without
/// any.
fn largest_model(sparse: &Path) -> Result<Option<(Model, PathBuf, usize)>, DatasetError> {
    let entries = std::fs::read_dir(sparse).map_err(|source| DatasetError::Io {
        path: sparse.to_path_buf(),
        source,
    })?;
    let mut dirs: Vec<PathBuf> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("cameras.bin").is_file() || p.join("cameras.txt").is_file())
        .collect();
    dirs.sort();
    let num_models = dirs.len();
    let mut best: Option<(Model, PathBuf)> = None;
    for dir in dirs {
        let model = read_model(&dir)?;
        if best
            .as_ref()
            .is_none_or(|(b, _)| model.images.len() > b.images.len())
        {
            best = Some((model, dir));
        }
    }
    Ok(best.map(|(m, d)| (m, d, num_models)))
}

/// The chordal mean of rotations: the quaternions, sign-aligned with the first, summed and
/// normalised (identity for none).
pub fn mean_rotation(rotations: &[DQuat]) -> DQuat {
    let Some(&q0) = rotations.first() else {
        return DQuat::IDENTITY;
    };
    let sum: DVec4 = rotations
        .iter()
        .map(|&q| {
            let v = DVec4::from(q);
            if q.dot(q0) < 0.0 {
                -v
            } else {
                v
            }
        })
        .sum();
    DQuat::from_vec4(sum).normalize()
}

/// The angle of a rotation, degrees.
fn angle_deg(q: DQuat) -> f64 {
    (2.0 * q.w.abs().clamp(0.0, 1.0).acos()).to_degrees()
}

/// How much two reconstructions of the same images disagree on the cameras' relative
/// orientations: over the images both registered (by name, at least two), the mean angle
/// between each image's `world_a <- world_b` rotation and their mean, degrees. Independent of
/// each reconstruction's own world frame; `None` with fewer than two common images.
pub fn rotation_disagreement_deg(a: &Model, b: &Model) -> Option<f64> {
    let quat = |im: &ColmapImage| {
        let [w, x, y, z] = im.qvec;
        DQuat::from_xyzw(x, y, z, w).normalize()
    };
    let in_b: BTreeMap<&str, DQuat> = b
        .images
        .iter()
        .map(|i| (i.name.as_str(), quat(i)))
        .collect();
    let deltas: Vec<DQuat> = a
        .images
        .iter()
        .filter_map(|i| in_b.get(i.name.as_str()).map(|qb| quat(i).inverse() * *qb))
        .collect();
    if deltas.len() < 2 {
        return None;
    }
    let mean = mean_rotation(&deltas);
    Some(
        deltas
            .iter()
            .map(|d| angle_deg(mean.inverse() * *d))
            .sum::<f64>()
            / deltas.len() as f64,
    )
}

/// Reconstructions whose [`rotation_disagreement_deg`] with the consensus one is below this
/// agree with it (runs of one capture differ by a few tenths of a degree; the wrong
/// reconstruction seen on the generated stage was 15 degrees off).
pub const AGREEMENT_DEG: f64 = 2.0;

/// Which of several reconstructions of the same images to keep. The consensus one is, among
/// those registering the most images, the one disagreeing least with all the others (summed
/// [`rotation_disagreement_deg`], 180 degrees where two share too few images); of those that
/// register as many images and agree with it within [`AGREEMENT_DEG`], the one with the lowest
/// mean reprojection error is kept. Also each one's mean disagreement with the others (`None`
/// alone).
pub fn choose_trial(models: &[&Model]) -> (usize, Vec<Option<f64>>) {
    let n = models.len();
    let mut d = vec![vec![0.0; n]; n];
    for i in 0..n {
        for j in i + 1..n {
            let v = rotation_disagreement_deg(models[i], models[j]).unwrap_or(180.0);
            d[i][j] = v;
            d[j][i] = v;
        }
    }
    let most = models.iter().map(|m| m.images.len()).max().unwrap_or(0);
    let score = |i: usize| d[i].iter().sum::<f64>();
    let error = |i: usize| models[i].mean_reprojection_error_px();
    let complete = || (0..n).filter(|&i| models[i].images.len() == most);
    let consensus = complete()
        .min_by(|&i, &j| {
            score(i)
                .total_cmp(&score(j))
                .then(error(i).total_cmp(&error(j)))
        })
        .unwrap_or(0);
    let chosen = complete()
        .filter(|&i| d[consensus][i] < AGREEMENT_DEG)
        .min_by(|&i, &j| error(i).total_cmp(&error(j)))
        .unwrap_or(consensus);
    let mean = (0..n)
        .map(|i| (n > 1).then(|| score(i) / (n - 1) as f64))
        .collect();
    (chosen, mean)
}

/// The last non-empty line of a log file (for messages).
fn last_line(log: &Path) -> String {
    std::fs::read(log)
        .map(|b| {
            String::from_utf8_lossy(&b)
                .lines()
                .map(str::trim)
                .rfind(|l| !l.is_empty())
                .unwrap_or("(no output)")
                .chars()
                .take(300)
                .collect()
        })
        .unwrap_or_else(|_| "(no output)".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(super) fn write_model(dir: &Path, cameras: &str, images: &str, points: &str) {
        std::fs::write(dir.join("cameras.txt"), cameras).unwrap();
        std::fs::write(dir.join("images.txt"), images).unwrap();
        std::fs::write(dir.join("points3D.txt"), points).unwrap();
    }

    pub(super) const CAMERAS: &str = "# Camera list\n1 OPENCV 200 150 180 170 100 75 -0.1 0.02 0.001 -0.002\n2 SIMPLE_RADIAL 64 48 50 32 24 0.05\n";
    // Image 1: identity rotation, camera at the origin; image 2: rotated 90 degrees about Y.
    pub(super) const IMAGES: &str = "# Image list\n1 1 0 0 0 0 0 0 1 cam00/t0000.png\n10 20 7 30 40 -1 50 60 7\n2 0.7071067811865476 0 0.7071067811865476 0 0 0 2 2 cam01/t0000.png\n\n";
    pub(super) const POINTS: &str = "7 0 0 2 255 0 0 0.5 1 0 2 0\n30 1 1 3 0 255 0 0.25 1 1\n";

    #[test]
    fn reads_a_text_model_and_converts_poses() {
        let dir = tempfile::tempdir().unwrap();
        write_model(dir.path(), CAMERAS, IMAGES, POINTS);
        let m = read_text_model(dir.path()).unwrap();
        assert_eq!(m.cameras.len(), 2);
        let k = m.cameras[&1].intrinsics();
        assert_eq!(
            (k.fx, k.fy, k.cx, k.cy, k.k1, k.p2),
            (180.0, 170.0, 100.0, 75.0, -0.1, -0.002)
        );
        let k = m.cameras[&2].intrinsics();
        assert_eq!((k.fx, k.fy, k.k1, k.k2), (50.0, 50.0, 0.05, 0.0));
        assert_eq!(m.images.len(), 2);
        assert_eq!(m.images[0].name, "cam00/t0000.png");
        assert_eq!(m.images[0].point_ids, [7]);
        assert!(m.images[1].point_ids.is_empty());
        assert_eq!(m.points.len(), 2);
        assert_eq!(m.points[&7].track_len, 2);
        assert!((m.mean_reprojection_error_px() - 0.375).abs() < 1e-12);
        // Identity: OpenCV looks down +Z, so the OpenGL camera's -Z is world +Z and +Y is world -Y.
        let p = Model::world_from_camera(&m.images[0]);
        assert!((p.z_axis.truncate() - DVec3::new(0.0, 0.0, -1.0)).length() < 1e-12);
        assert!((p.y_axis.truncate() - DVec3::new(0.0, -1.0, 0.0)).length() < 1e-12);
        let c = Model::world_from_camera(&m.images[1]);
        // x_cam = R x_world + t must map the camera centre to 0.
        let center = c.w_axis.truncate();
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let r = DMat3::from_quat(DQuat::from_xyzw(0.0, h, 0.0, h));
        assert!((r * center + DVec3::new(0.0, 0.0, 2.0)).length() < 1e-9);
        // Looking direction: OpenCV +Z of the camera in the world = R^T e_z = -(OpenGL z axis).
        assert!((r.transpose() * DVec3::Z + c.z_axis.truncate()).length() < 1e-9);
    }

    #[test]
    fn broken_models_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let cases: Vec<(String, String, String, &str)> = vec![
            (
                CAMERAS.replace("OPENCV", "FISHEYE"),
                IMAGES.into(),
                POINTS.into(),
                "cameras.txt",
            ),
            (
                CAMERAS.replace(" 0.05", ""),
                IMAGES.into(),
                POINTS.into(),
                "takes 4 parameters",
            ),
            (
                CAMERAS.into(),
                IMAGES.replace("0.7071067811865476 0 0.7071", "9 0 0.7071"),
                POINTS.into(),
                "not a rotation",
            ),
            (
                CAMERAS.into(),
                IMAGES.replace(" 2 cam01", " 5 cam01"),
                POINTS.into(),
                "camera 5 is not",
            ),
            (
                CAMERAS.into(),
                IMAGES.replace("-1 50 60 7", "-1 50 60"),
                POINTS.into(),
                "triples",
            ),
            (
                CAMERAS.into(),
                IMAGES.into(),
                POINTS.replace("0.25", "nan"),
                "not finite",
            ),
            (
                CAMERAS.into(),
                IMAGES.into(),
                POINTS.replace("1 1\n", "1\n"),
                "points3D.txt",
            ),
        ];
        for (c, i, p, needle) in cases {
            write_model(dir.path(), &c, &i, &p);
            let e = read_text_model(dir.path()).unwrap_err().to_string();
            assert!(e.contains(needle), "`{e}` should mention `{needle}`");
        }
        std::fs::remove_file(dir.path().join("images.txt")).unwrap();
        let e = read_text_model(dir.path()).unwrap_err().to_string();
        assert!(e.contains("images.txt"), "{e}");
    }

    /// A model of `n` images whose camera-from-world rotations are `rotation(i)`, and one point
    /// with reprojection error `error_px`.
    fn posed(n: usize, rotation: impl Fn(usize) -> DQuat, error_px: f64) -> Model {
        let mut m = Model::default();
        m.cameras.insert(
            1,
            ColmapCamera {
                model: CameraModel::SimplePinhole,
                width: 4,
                height: 3,
                params: vec![5.0, 2.0, 1.5],
            },
        );
        for i in 0..n {
            let q = rotation(i);
            m.images.push(ColmapImage {
                image_id: i as u32 + 1,
                qvec: [q.w, q.x, q.y, q.z],
                tvec: [0.0, 0.0, i as f64],
                camera_id: 1,
                name: format!("{i:04}.png"),
                point_ids: vec![],
            });
        }
        let point = ColmapPoint {
            position: DVec3::ZERO,
            error_px,
            track_len: 2,
        };
        m.points.insert(1, point);
        m
    }

    #[test]
    fn the_reconstruction_agreeing_with_the_others_is_chosen() {
        let own = |i: usize| DQuat::from_euler(glam::EulerRot::YXZ, 0.3 * i as f64, 0.1, 0.0);
        let a = posed(6, own, 0.5);
        // The same cameras in another world frame: x_b = G x_a, so R_b = R_a G^-1.
        let g = DQuat::from_axis_angle(DVec3::new(1.0, 2.0, 3.0).normalize(), 1.0);
        let b = posed(6, |i| own(i) * g.inverse(), 0.4);
        // Wrong: every camera off by its own 10 degrees.
        let c = posed(
            6,
            |i| {
                own(i)
                    * DQuat::from_rotation_x((if i % 2 == 0 { 10f64 } else { -10.0 }).to_radians())
            },
            0.1,
        );
        assert!(rotation_disagreement_deg(&a, &b).unwrap() < 1e-9);
        let d = rotation_disagreement_deg(&a, &c).unwrap();
        assert!((d - 10.0).abs() < 1e-6, "{d}");
        assert_eq!(rotation_disagreement_deg(&a, &posed(1, own, 0.5)), None);
        // a and b agree (tie broken by the lower reprojection error), c disagrees.
        let (chosen, mean) = choose_trial(&[&c, &a, &b]);
        assert_eq!(chosen, 2);
        assert!((mean[0].unwrap() - 10.0).abs() < 1e-6 && mean[2].unwrap() < 5.1);
        // More registered images come first; one run has no disagreement.
        let (chosen, _) = choose_trial(&[&a, &b, &posed(7, own, 2.0)]);
        assert_eq!(chosen, 2);
        assert_eq!(choose_trial(&[&a]), (0, vec![None]));
        // All agree within AGREEMENT_DEG: the lowest reprojection error, even off the consensus.
        let e = posed(
            6,
            |i| own(i) * DQuat::from_rotation_y(if i % 2 == 0 { 0.01 } else { -0.01 }),
            0.3,
        );
        let (chosen, _) = choose_trial(&[&a, &b, &e]);
        assert_eq!(chosen, 2);
        let mean = mean_rotation(&[g, -g]);
        assert!(angle_deg(mean.inverse() * g) < 1e-9);
    }

    #[test]
    fn a_missing_program_is_named() {
        let c = Colmap {
            program: PathBuf::from("/nonexistent/colmap-for-msth-test"),
        };
        let e = c.check().unwrap_err().to_string();
        assert!(
            e.contains("apt-get install colmap") && e.contains("MSTH_COLMAP"),
            "{e}"
        );
    }
}
