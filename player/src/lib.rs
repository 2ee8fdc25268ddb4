//! `msth-player`: plays `.msth` files, local or streamed over HTTP, as free-viewpoint video.
//!
//! - [`source`]: bytes from a file or an `http://` URL (Range requests, timeouts, retries);
//! - [`stream`]: the prefix first, then the static sections, then dynamic chunks from the
//!   playhead on, on a background thread; seek by asking for another time;
//! - [`render`]: CPU rendering of the decoded model, incremental for a fixed camera (static rays
//!   cached, dynamic rays re-rendered);
//! - [`samples`]: sample-level reuse on the dynamic rays (fixed samples, only dynamic ones
//!   evaluated per frame);
//! - [`empty_space`]: empty-space skipping with the file's occupancy grid;
//! - [`seen`]: the cells the training cameras see, which `msth export` keeps in that grid;
//! - [`gpu`]: the same on a GPU through wgpu, with the WGSL kernels of `msth-gpu`;
//! - [`backend`]: the choice between the two (automatic, `--cpu`, `--gpu`);
//! - [`path`]: camera paths (fixed, orbit, spiral, the file's cameras, JSON);
//! - [`policy`]: the interactive viewer policy (reduced resolution while moving, refinement when
//!   still, the timeline at the model's frame rate), shared by the native viewers;
//! - [`play`]: all of it together, writing PNG frames and an MP4;
//! - [`quant_auto`]: `msth export --quant auto`'s searches, measured on renders of the file's
//!   own cameras.
//!
//! The player links the codec and the field math, never the trainer.

pub mod abr;
pub mod backend;
pub mod empty_space;
pub mod gpu;
pub mod path;
pub mod play;
pub mod policy;
pub mod quant_auto;
pub mod render;
pub mod samples;
pub mod seen;
pub mod source;
pub mod stream;
pub mod volume;

pub use backend::{BackendChoice, BackendInfo, FrameRenderer};
pub use gpu::{GpuError, GpuRenderer};
pub use msth_gpu::TableFormat;
pub use path::CameraPath;
pub use play::{play, FrameRecord, PlayError, PlayOptions, PlayReport};
pub use render::{Frame, FrameStats, RenderSettings, Renderer, Reuse, SlicePolicy};
pub use source::{ByteSource, FileSource, HttpOptions, HttpSource, SourceError};
pub use stream::{ModelStream, StreamError, StreamProgress};
