//! `msth-dataset`: datasets on disk, read and written. A dataset is views (a camera, a time, an
//! 8-bit RGB image) split into train and test.
//!
//! One module per on-disk format: [`dnerf`] (Blender / D-NeRF JSON), [`nerfstudio`] (a single
//! `transforms.json`), [`dynerf`] (Plenoptic Video / DyNeRF: `poses_bounds.npy` + videos or frame
//! folders); [`detect`] picks one from a folder's contents. Every loader validates what it reads
//! and reports the file and the field at fault ([`DatasetError`]). [`colmap`] runs COLMAP and
//! reads its sparse models (for `msth import` in the trainer).
//!
//! Images are stored as 8-bit RGB already composited on the dataset's background colour. Their
//! pixels ([`Pixels`]) live either in memory or in a memory-mapped frame cache on disk
//! ([`cache`]), so that a dataset larger than RAM is bounded by disk instead.

pub mod bounds;
pub mod cache;
pub mod colmap;
pub mod dnerf;
pub mod dynerf;
pub mod imageio;
pub mod nerfstudio;
pub mod npy;
pub mod staging;
pub(crate) mod transforms;
pub mod undistort;
pub mod video;

use std::ops::{Deref, DerefMut};
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub use imageio::downscale_rgb;

use msth_core::{Camera, SceneBounds};

/// The bytes of an image: owned in memory, or a range of a read-only frame cache file
/// ([`cache::FrameCache`]). Both dereference to `[u8]` (a cached frame through the file's memory
/// mapping); writing to a cached image first copies it into memory (copy on write), so the cache
/// file is never modified.
///
/// Hot paths read cached pixels with positional reads instead of the mapping
/// ([`Pixels::rgb_at`], [`Image8::loaded`]): pages touched through a mapping count in the
/// process's resident set until the kernel reclaims them, and random pixels of a dataset larger
/// than RAM would touch all of it.
#[derive(Clone)]
pub enum Pixels {
    Owned(Vec<u8>),
    Mapped {
        file: Arc<cache::CacheFile>,
        offset: usize,
        len: usize,
    },
}

impl Pixels {
    /// Whether the bytes live in a cache file.
    pub fn is_mapped(&self) -> bool {
        matches!(self, Pixels::Mapped { .. })
    }

    /// The three bytes at `i..i + 3`.
    #[inline]
    pub fn rgb_at(&self, i: usize) -> [u8; 3] {
        match self {
            Pixels::Owned(v) => [v[i], v[i + 1], v[i + 2]],
            Pixels::Mapped { file, offset, len } => {
                assert!(i + 3 <= *len, "pixel {i} outside a frame of {len} bytes");
                let mut b = [0u8; 3];
                file.read_at(offset + i, &mut b);
                b
            }
        }
    }

    /// The bytes in memory (a positional read of a cached frame; no copy when owned).
    pub fn loaded(&self) -> std::borrow::Cow<'_, [u8]> {
        match self {
            Pixels::Owned(v) => std::borrow::Cow::Borrowed(v),
            Pixels::Mapped { file, offset, len } => {
                let mut v = vec![0u8; *len];
                file.read_at(*offset, &mut v);
                std::borrow::Cow::Owned(v)
            }
        }
    }
}

impl Deref for Pixels {
    type Target = [u8];
    #[inline]
    fn deref(&self) -> &[u8] {
        match self {
            Pixels::Owned(v) => v,
            Pixels::Mapped { file, offset, len } => &file.bytes()[*offset..*offset + *len],
        }
    }
}

impl DerefMut for Pixels {
    fn deref_mut(&mut self) -> &mut [u8] {
        if let Pixels::Mapped { .. } = self {
            *self = Pixels::Owned(self.to_vec());
        }
        match self {
            Pixels::Owned(v) => v,
            Pixels::Mapped { .. } => unreachable!("converted to owned above"),
        }
    }
}

impl AsRef<[u8]> for Pixels {
    fn as_ref(&self) -> &[u8] {
        self
    }
}

impl From<Vec<u8>> for Pixels {
    fn from(v: Vec<u8>) -> Self {
        Pixels::Owned(v)
    }
}

impl PartialEq for Pixels {
    fn eq(&self, other: &Self) -> bool {
        **self == **other
    }
}

impl PartialEq<Vec<u8>> for Pixels {
    fn eq(&self, other: &Vec<u8>) -> bool {
        **self == other[..]
    }
}

impl PartialEq<Pixels> for Vec<u8> {
    fn eq(&self, other: &Pixels) -> bool {
        self[..] == **other
    }
}

impl<const N: usize> PartialEq<[u8; N]> for Pixels {
    fn eq(&self, other: &[u8; N]) -> bool {
        **self == other[..]
    }
}

impl std::fmt::Debug for Pixels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Pixels::Owned(v) => write!(f, "Pixels::Owned({} bytes)", v.len()),
            Pixels::Mapped { offset, len, .. } => {
                write!(f, "Pixels::Mapped({len} bytes at {offset})")
            }
        }
    }
}

/// An 8-bit RGB image, row-major, `data.len() == width * height * 3`, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image8 {
    pub width: u32,
    pub height: u32,
    pub data: Pixels,
}

impl Image8 {
    pub fn new(width: u32, height: u32) -> Self {
        Image8 {
            width,
            height,
            data: vec![0; width as usize * height as usize * 3].into(),
        }
    }

    /// Pixel `(x, y)` as linear-in-file floats in `[0, 1]` (a positional read for a cached
    /// frame, see [`Pixels`]).
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> [f32; 3] {
        let i = (y as usize * self.width as usize + x as usize) * 3;
        let p = self.data.rgb_at(i);
        [
            p[0] as f32 / 255.0,
            p[1] as f32 / 255.0,
            p[2] as f32 / 255.0,
        ]
    }

    /// The image with its pixels in memory: itself when they are, else a copy read from the
    /// frame cache (without mapping it, see [`Pixels`]).
    pub fn loaded(&self) -> std::borrow::Cow<'_, Image8> {
        if self.data.is_mapped() {
            std::borrow::Cow::Owned(Image8 {
                width: self.width,
                height: self.height,
                data: Pixels::Owned(self.data.loaded().into_owned()),
            })
        } else {
            std::borrow::Cow::Borrowed(self)
        }
    }

    /// From floats in `[0, 1]` (clamped; NaN becomes 0).
    pub fn from_f32(width: u32, height: u32, rgb: &[f32]) -> Self {
        let data = rgb
            .iter()
            .map(|&v| {
                let v = if v.is_nan() { 0.0 } else { v };
                (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
            })
            .collect::<Vec<u8>>();
        Image8 {
            width,
            height,
            data: data.into(),
        }
    }

    pub fn to_f32(&self) -> Vec<f32> {
        self.data.iter().map(|&v| v as f32 / 255.0).collect()
    }
}

/// One training or test image: where it was taken from and when.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    /// Normalised time in `[0, 1]`.
    pub time: f32,
    pub image: Image8,
    /// Where the image came from (for messages).
    pub source: PathBuf,
    /// Index of the physical camera for multi-view video datasets (views sharing a pose), or
    /// `None` for monocular data where every view has its own pose.
    pub camera_id: Option<usize>,
    /// Straight alpha per pixel (`width * height`) for images that had transparency; `image` is
    /// then the composite on white. Lets training composite on random backgrounds instead.
    pub alpha: Option<Vec<u8>>,
}

/// A loaded dataset: training and held-out views with the scene's bounds.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub name: String,
    pub train: Vec<View>,
    pub test: Vec<View>,
    pub bounds: SceneBounds,
    /// Background colour that transparent pixels were composited on and that the renderer uses
    /// for the transmittance left at the end of a ray.
    pub background: [f32; 3],
    /// Number of distinct time steps in the training set.
    pub num_frames: usize,
    /// The nearest any content is to a training camera, in world units, where the capture
    /// states it (LLFF near bounds: DyNeRF's `poses_bounds.npy`, or one beside a JSON layout
    /// with the same cameras, [`bounds::near_from_llff_rows`]). Rays start there.
    pub near: Option<f32>,
}

impl Dataset {
    /// Multiplies every world length by `s` (camera positions, scene bounds): the same images of
    /// a scene `s` times larger. Camera orientations and intrinsics are unchanged.
    pub fn rescale(&mut self, s: f32) {
        for v in self.train.iter_mut().chain(self.test.iter_mut()) {
            v.camera = scale_camera(v.camera, s);
        }
        self.bounds = self.bounds.scaled(s);
        self.near = self.near.map(|n| n * s);
    }
}

/// `camera` in a world scaled by `s` about the origin.
pub fn scale_camera(mut camera: Camera, s: f32) -> Camera {
    let w = &mut camera.world_from_camera.w_axis;
    w.x *= s;
    w.y *= s;
    w.z *= s;
    camera
}

/// Everything that can be wrong with a dataset on disk. Each variant names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: malformed JSON: {message}")]
    Json { path: PathBuf, message: String },
    #[error("{path}: field `{field}`: {message}")]
    Field {
        path: PathBuf,
        field: String,
        message: String,
    },
    #[error("{path}: cannot decode image: {message}")]
    Image { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("{path}: not a valid .npy array: {source}")]
    Npy {
        path: PathBuf,
        #[source]
        source: npy::NpyError,
    },
    #[error("{path}: not a valid COLMAP binary model file: {source}")]
    ColmapBinary {
        path: PathBuf,
        #[source]
        source: colmap::BinaryModelError,
    },
}

/// The on-disk layouts `msth` reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// Blender / D-NeRF: `transforms_train.json` + `transforms_test.json` ([`dnerf`]).
    DNerf,
    /// nerfstudio: one `transforms.json` ([`nerfstudio`]).
    Nerfstudio,
    /// Plenoptic Video / DyNeRF: `poses_bounds.npy` + `camNN.mp4` or `camNN/` ([`dynerf`]).
    DyNerf,
}

/// A dataset format name that [`Format`]'s `FromStr` does not know.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown dataset format `{0}` (expected dnerf, nerfstudio or dynerf)")]
pub struct UnknownFormat(pub String);

impl std::str::FromStr for Format {
    type Err = UnknownFormat;
    fn from_str(s: &str) -> Result<Self, UnknownFormat> {
        match s.to_ascii_lowercase().as_str() {
            "dnerf" | "d-nerf" | "blender" => Ok(Format::DNerf),
            "nerfstudio" => Ok(Format::Nerfstudio),
            "dynerf" | "plenoptic" | "llff" => Ok(Format::DyNerf),
            _ => Err(UnknownFormat(s.to_string())),
        }
    }
}

impl Format {
    /// The file whose presence identifies the layout.
    pub fn marker(self) -> &'static str {
        match self {
            Format::DNerf => "transforms_train.json",
            Format::Nerfstudio => "transforms.json",
            Format::DyNerf => "poses_bounds.npy",
        }
    }
}

/// The layout of the dataset folder `dir`, by the first marker file found in this order:
/// `transforms_train.json` (D-NeRF), `transforms.json` (nerfstudio), `poses_bounds.npy` (DyNeRF).
pub fn detect(dir: &Path) -> Option<Format> {
    [Format::DNerf, Format::Nerfstudio, Format::DyNerf]
        .into_iter()
        .find(|f| dir.join(f.marker()).is_file())
}

/// Options shared by every loader (each ignores what does not apply to it).
#[derive(Clone)]
pub struct LoadOptions {
    /// The layout; detected with [`detect`] when `None`.
    pub format: Option<Format>,
    /// Integer area-filter downscale factor (1 = full resolution).
    pub downscale: u32,
    /// Scene bounds instead of the loader's choice.
    pub bounds: Option<SceneBounds>,
    /// The held-out camera: `camNN` for DyNeRF, the camera index for multi-camera nerfstudio.
    pub test_camera: Option<usize>,
    /// Where frames live. A frame cache holds opaque RGB: JSON datasets with transparency
    /// always load into memory (with their alpha).
    pub storage: cache::FrameStorage,
    /// DyNeRF: pose normalisation and video vs image frames.
    pub normalization: dynerf::Normalization,
    pub frames: dynerf::FrameSource,
    pub tools: video::Tools,
    /// Frame decoding progress `(done, total)`.
    pub progress: Option<Arc<cache::ProgressFn>>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            format: None,
            downscale: 1,
            bounds: None,
            test_camera: None,
            storage: cache::FrameStorage::Memory,
            normalization: Default::default(),
            frames: Default::default(),
            tools: Default::default(),
            progress: None,
        }
    }
}

/// Loads the dataset in `dir` in the given or detected layout.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset, DatasetError> {
    let format = match opts.format.or_else(|| detect(dir)) {
        Some(f) => f,
        None => {
            return Err(DatasetError::Invalid {
                path: dir.to_path_buf(),
                message: "not a dataset folder: expected transforms_train.json (D-NeRF), transforms.json (nerfstudio) or poses_bounds.npy (DyNeRF)".into(),
            })
        }
    };
    if let (Format::DNerf, Some(n)) = (format, opts.test_camera) {
        let also = if dir.join("poses_bounds.npy").is_file() {
            "; this folder also has poses_bounds.npy: add --format dynerf to read it as DyNeRF"
        } else {
            ""
        };
        return Err(DatasetError::Invalid {
            path: dir.to_path_buf(),
            message: format!(
                "a held-out camera ({n}) was asked for, but this folder is read as D-NeRF JSON, \
                 whose held-out views are transforms_test.json (--test-camera applies to DyNeRF \
                 and multi-camera nerfstudio layouts){also}"
            ),
        });
    }
    let json_opts = dnerf::LoadOptions {
        downscale: opts.downscale,
        bounds: opts.bounds,
    };
    let progress = opts.progress.as_deref();
    match format {
        Format::DNerf => dnerf::load_with_storage(dir, &json_opts, &opts.storage, progress),
        Format::Nerfstudio => nerfstudio::load_with_storage(
            dir,
            &nerfstudio::NerfstudioOptions {
                json: json_opts,
                test_camera: opts.test_camera,
            },
            &opts.storage,
            progress,
        ),
        Format::DyNerf => dynerf::load(
            dir,
            &dynerf::DynerfOptions {
                downscale: opts.downscale,
                bounds: opts.bounds,
                test_camera: opts.test_camera,
                normalization: opts.normalization,
                frames: opts.frames,
                storage: opts.storage.clone(),
                tools: opts.tools.clone(),
                progress: opts.progress.clone(),
            },
        ),
    }
}
