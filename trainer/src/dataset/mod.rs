//! Datasets in memory: views (a camera, a time, an 8-bit RGB image) split into train and test.
//!
//! One module per on-disk format ([`dnerf`] for Blender/D-NeRF JSON). Every loader validates what
//! it reads and reports the file and the field at fault ([`DatasetError`]).
//! Images are stored as 8-bit RGB already composited on the dataset's background colour.

pub mod dnerf;

use std::path::PathBuf;

use msth_core::{Camera, SceneBounds};

/// An 8-bit RGB image, row-major, `data.len() == width * height * 3`, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image8 {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl Image8 {
    pub fn new(width: u32, height: u32) -> Self {
        Image8 {
            width,
            height,
            data: vec![0; width as usize * height as usize * 3],
        }
    }

    /// Pixel `(x, y)` as linear-in-file floats in `[0, 1]`.
    #[inline]
    pub fn get(&self, x: u32, y: u32) -> [f32; 3] {
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [
            self.data[i] as f32 / 255.0,
            self.data[i + 1] as f32 / 255.0,
            self.data[i + 2] as f32 / 255.0,
        ]
    }

    /// From floats in `[0, 1]` (clamped; NaN becomes 0).
    pub fn from_f32(width: u32, height: u32, rgb: &[f32]) -> Self {
        let data = rgb
            .iter()
            .map(|&v| {
                let v = if v.is_nan() { 0.0 } else { v };
                (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
            })
            .collect();
        Image8 {
            width,
            height,
            data,
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
}
