//! `msth-gpu`: every WGSL kernel of msth and its wgpu host code (Vulkan, Metal, DX12 natively;
//! the browser runs the same render kernels through WebGPU).
//!
//! - [`render`]: the renderer's kernels (`shaders/render.wgsl`: one invocation per ray, and
//!   `eval_points`), the device context that compiles them and one model's buffers on the device;
//! - [`layout`]: the render kernels' uniforms and parameter-buffer split, byte for byte.
//!
//! # The web page's copy of `render.wgsl`
//! `shaders/render.wgsl` here is the one source. The browser page fetches
//! `web/shaders/render.wgsl` over HTTP, so `web/` holds a generated copy, and the test
//! `tests/web_copy.rs` fails when the two differ (`MSTH_UPDATE_WEB_WGSL=1` rewrites the copy).
//! A copy rather than the server handing out [`RENDER_WGSL`]: `web/` stays a self-contained
//! static site (any static file server, or `file://` tooling, serves the page the same way as
//! `msth serve --web web`), and the server need not link the GPU stack nor special-case one URL.

pub mod layout;
pub mod render;

pub use layout::{GpuModel, ViewU, FLAG_COMPACT, FLAG_LIST};
pub use render::{
    AdapterPolicy, GpuContext, GpuError, GpuScene, Kernel, ALLOW_SOFTWARE_ENV, RENDER_WGSL,
};
