//! What a viewing session did: the JSON report of `msth view --report`, its frames, screenshots
//! and bench results.

use std::path::PathBuf;

use msth_player::policy::Activity;
use msth_player::BackendInfo;
use serde::Serialize;

use crate::worker::VolumeInfo;

/// One frame shown in the window.
#[derive(Clone, Debug, Serialize)]
pub struct FrameLog {
    /// Seconds since the viewer started.
    pub shown_at: f64,
    pub time: f32,
    pub width: u32,
    pub height: u32,
    pub divisor: u32,
    pub activity: Activity,
    /// Rendered in full (not from the static cache).
    pub full: bool,
    pub rays_rendered: usize,
    pub rays_total: usize,
    /// The renderer's time for the frame.
    pub render_seconds: f64,
    /// The file camera shown, if the view is one.
    pub file_camera: Option<usize>,
    /// Drawn from the play-time volume (else from the exact field).
    pub volume: bool,
}

/// A `bench` step's result: the timeline's model frames drawn one after the other.
#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// From sending the first frame's job to painting the last frame.
    pub seconds: f64,
    /// Frames shown per second.
    pub fps: f64,
    /// The renderer's own time, summed over the frames.
    pub render_seconds: f64,
    /// Frames per second of the renderer's time alone (what `msth play` reports).
    pub render_fps: f64,
    /// The window's time for the frames: uploading them and painting the window.
    pub window_seconds: f64,
}

/// A screenshot: the picture as rendered and the whole window.
#[derive(Clone, Debug, Serialize)]
pub struct ShotReport {
    pub frame: Option<PathBuf>,
    pub window: Option<PathBuf>,
    /// The picture's place in the window screenshot: `[x, y, width, height]` in pixels.
    pub picture_rect: [u32; 4],
    /// The overlay's place (drawn over the picture's top left corner), the same way.
    pub overlay_rect: [u32; 4],
    pub time: f32,
    /// The camera of the picture (full size).
    pub camera: [[f32; 4]; 4],
    pub file_camera: Option<usize>,
}

/// What a viewing session did (`msth view --report FILE.json`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct ViewReport {
    /// The adapter the window is drawn with.
    pub window_adapter: String,
    /// The renderer (CPU or GPU) of the last frame.
    pub backend: Option<BackendInfo>,
    /// Proposal and main samples per ray of the last frame, and the model's own.
    pub samples: Option<(usize, usize)>,
    pub model_samples: (usize, usize),
    pub frames: Vec<FrameLog>,
    pub screenshots: Vec<ShotReport>,
    /// Camera paths recorded (`msth play --path FILE.json`).
    pub paths: Vec<PathBuf>,
    pub bench: Vec<BenchReport>,
    /// The play-time volume, when one was baked (the exact / volume switch).
    pub volume: Option<VolumeInfo>,
    /// Why the volume switch went back to the exact field, the last time it did.
    pub volume_error: Option<String>,
    pub seconds: f64,
    pub bytes_fetched: u64,
    pub file_len: u64,
}
