//! GPU playback: the kernels and their host code live in `msth-gpu` (re-exported here, so that
//! users of the player need no second dependency); this module adds [`GpuRenderer`], the GPU
//! counterpart of [`crate::render::Renderer`] with the same static-ray cache.

mod renderer;

pub use msth_gpu::specialise;
pub use msth_gpu::{
    layout, AdapterPolicy, FrameScratch, GpuContext, GpuError, GpuModel, GpuSampleCache, GpuScene,
    Kernel, Pixels, ViewU, ALLOW_SOFTWARE_ENV, FLAG_COMPACT, FLAG_LIST, RENDER_WGSL,
};
pub use renderer::{GpuMlps, GpuRenderer, MlpStatus};
