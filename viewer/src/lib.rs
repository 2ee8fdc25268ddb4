//! `msth view`: a window to fly through a `.msth` scene while it plays.
//!
//! - A winit window drawn with wgpu, the controls in egui ([`app`]); the picture comes from the
//!   player's [`msth_player::FrameRenderer`] (GPU, or the CPU renderer where no hardware GPU is
//!   there), on a thread of its own ([`worker`]), uploaded to a texture of the window.
//! - The viewer policy of the web page, from [`msth_player::policy`]: reduced resolution while
//!   the camera moves, refinement when it stops, the timeline at the model's frame rate.
//! - The exact / volume switch where the renderer has a play-time volume (CPU): the volume is
//!   baked in the background while exact frames go on ([`worker`]).
//! - Orbit and fly cameras, the file's cameras as viewpoints ([`camera`]).
//! - Screenshots, camera paths recorded for `msth play --path`, a JSON report, and scripted input
//!   for tests and demonstrations ([`script`]).
//!
//! Streaming from a URL works as in `msth play`: the window opens once the file's prefix is read,
//! and frames show as soon as the sections they need have arrived.

pub mod app;
pub mod camera;
pub mod script;
pub mod worker;

use std::path::PathBuf;
use std::time::Duration;

use msth_codec::Limits;
use msth_core::config::PlaySamples;
use msth_core::volume::MarchSettings;
use msth_player::volume::VolumeOptions;
use msth_player::{BackendChoice, HttpOptions, TableFormat};

pub use script::Script;

/// Everything `msth view` can be told.
#[derive(Clone, Debug)]
pub struct ViewOptions {
    /// An `http(s)://` URL or a local path.
    pub source: String,
    /// Full render size (default: the file's first camera's).
    pub size: Option<(u32, u32)>,
    /// Samples per ray at the start (the samples menu changes them).
    pub samples: PlaySamples,
    /// Start with the exact / volume switch on: bake the play-time volume once
    /// the static part has arrived, and draw from it when it is ready.
    pub volume: bool,
    /// How the volume is baked (`msth play --volume-budget`, `--volume-resolution`, ...).
    pub volume_options: VolumeOptions,
    /// How rays walk the volume (`--volume-step`).
    pub march: MarchSettings,
    pub backend: BackendChoice,
    /// The file camera shown first.
    pub camera: usize,
    /// Start paused at this normalised time (default: play from 0).
    pub time: Option<f32>,
    /// Keep the static cache under a still camera (incremental rendering).
    pub incremental: bool,
    pub skip_empty: bool,
    pub gpu_tables: Option<TableFormat>,
    pub http: HttpOptions,
    pub limits: Limits,
    pub section_timeout: Duration,
    /// Folder for screenshots and recorded camera paths.
    pub out: PathBuf,
    pub script: Option<Script>,
    /// Write a JSON report of the session here at the end.
    pub report: Option<PathBuf>,
    /// Inner size of the window in logical pixels (default: fits the picture and the controls).
    pub window_size: Option<(u32, u32)>,
}

impl ViewOptions {
    pub fn new(source: impl Into<String>) -> Self {
        ViewOptions {
            source: source.into(),
            size: None,
            samples: PlaySamples::default(),
            volume: false,
            volume_options: VolumeOptions::default(),
            march: MarchSettings::default(),
            backend: BackendChoice::Auto,
            camera: 0,
            time: None,
            incremental: true,
            skip_empty: true,
            gpu_tables: None,
            http: HttpOptions::default(),
            limits: Limits::default(),
            section_timeout: Duration::from_secs(120),
            out: PathBuf::from("."),
            script: None,
            report: None,
            window_size: None,
        }
    }
}

/// Why the viewer could not run, or stopped.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error(transparent)]
    Stream(#[from] msth_player::StreamError),
    #[error("{0}")]
    Options(String),
    /// No window system to open a window on.
    #[error(
        "cannot open a window: {0}. `msth view` needs a display (X11, or XWayland on a Wayland \
         desktop); `msth play` renders frames and videos without one"
    )]
    NoDisplay(String),
    /// A window, but nothing that draws into it.
    #[error(
        "cannot draw into the window: {0}. The window needs a Vulkan, Metal or DX12 driver, a \
         software one will do (Mesa's lavapipe: the mesa-vulkan-drivers package); `msth play` \
         renders without one"
    )]
    NoPresenter(String),
    #[error("rendering: {0}")]
    Render(String),
    #[error("{}: {message}", path.display())]
    Script { path: PathBuf, message: String },
    #[error("script step {step}: {message}")]
    ScriptStep { step: usize, message: String },
    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

pub use app::{run, ViewReport};
