//! `msth-gpu`: every WGSL kernel of msth and its wgpu host code (Vulkan, Metal, DX12 natively;
//! the browser runs the same render kernels through WebGPU).
//!
//! - [`render`]: the renderer's kernels (`shaders/render.wgsl`: the per-sample passes, the older
//!   one-invocation-per-ray `render`, and `eval_points`), the device context that compiles them
//!   and one model's buffers on the device;
//! - [`passes`]: rendering through per-sample passes over compacted work lists (frames, probes,
//!   and the sample cache of incremental playback);
//! - [`layout`]: the render kernels' uniforms and parameter-buffer split, byte for byte;
//! - [`device`]: a compute device for the training kernels (f32 atomics when the adapter has
//!   them), buffers, dispatches, read-back;
//! - [`hashgrid`]: the multi-resolution hash-grid encoding (3D and 4D), forward and backward;
//! - [`mask`]: the dense mask grid (trilinear + sigmoid), forward and backward;
//! - [`mlp`]: the density and colour MLPs (and their output activations), forward and backward,
//!   tiled through workgroup memory;
//! - [`sh`]: the view-direction encoding (spherical harmonics, forward);
//! - [`adam`]: Adam over the flat parameter buffer (the trainer's update, mask loss fused).
//!
//! # The web page's copy of `render.wgsl`
//! `shaders/render.wgsl` here is the one source. The browser page fetches
//! `web/shaders/render.wgsl` over HTTP, so `web/` holds a generated copy, and the test
//! `tests/web_copy.rs` fails when the two differ (`MSTH_UPDATE_WEB_WGSL=1` rewrites the copy).
//! A copy rather than the server handing out [`RENDER_WGSL`]: `web/` stays a self-contained
//! static site (any static file server serves the page the same way as
//! `msth serve --web web`), and the server need not link the GPU stack nor special-case one URL.
//!
//! # Render passes: buffer layout, and why
//! A frame is rendered in batches; each batch is nine dispatches (ray setup, proposal per
//! sample, resampling per ray, density per sample, visibility per ray, colour per visible
//! sample, compositing per ray, and two that size the next dispatches from atomic counters:
//! indirect dispatch, no host round trip). Every intermediate lives in one `work` buffer at
//! word offsets given in a uniform ([`passes::regions`]): ray records, proposal densities,
//! edges, per-sample `(r, g, b, sigma)` and geometry features, the colour list; samples
//! ray-major. Why one buffer: every pass then binds the same 10 bindings (7 storage buffers,
//! within WebGPU's default of 8 per stage, so the page runs the same WGSL), one bind group
//! serves a whole batch, and neighbouring invocations read neighbouring samples of one ray
//! (shared hash rows). Only the indirect sizes have their own buffer: one buffer may not be a
//! storage binding and the indirect argument of the same dispatch.
//!
//! # Training kernels: per-sample passes
//! No invocation loops over a ray. The encoding runs one invocation per (sample, level) pair
//! (at most `2^D * F <= 128` loop iterations each), the mask one per sample (8 corners), so the
//! work spreads over `samples * levels` invocations and lavapipe's per-invocation loop budget
//! never binds. Kernels read and write device buffers and return; the host chains passes.
//!
//! # Buffer layout, and why
//! - **Tables: core's layout unchanged.** A grid's table is its slice of the one flat
//!   parameter buffer: levels one after the other (per-level offsets from
//!   `msth_core::grid::GridLayout`, dense levels with `prod(res + 1)` rows rounded up to 8,
//!   hashed levels with `T` rows), each level row-major `[rows, F]`, i.e. **a row's F features
//!   interleaved**. The kernels take the flat buffer plus the grid's offset in floats, and the
//!   gradient buffer has the same layout. Why: parameters, gradients and Adam state stay one
//!   flat buffer with the same named slices as on the CPU and in checkpoints (no repacking on
//!   upload, download or resume), the render kernels already read that layout, and one corner
//!   read fetches its F features together (8 contiguous bytes at F = 2: one memory transaction
//!   per corner, where a feature-major `[F, rows]` layout would issue F).
//! - **Level descriptors** (`scale`, dense `stride`, `(offset, dense, rows)`) travel in a
//!   uniform of 32 level slots (the render kernels' `Level` struct), the grid shape and
//!   `(samples, offset)` with them.
//! - **Samples** are `vec4<f32>` `(x, y, z, t)` in the unit cube / unit time (3D grids ignore
//!   `t`); **features** are sample-major `[n, levels, F]`, the CPU batch layout, so the MLP pass
//!   that follows reads one sample's input contiguously; `d_features` has the same layout.
//! - **Gradient scatter** uses atomics: native `atomicAdd` on `atomic<f32>` where the adapter has
//!   `wgpu::Features::SHADER_FLOAT32_ATOMIC`, else a compare-exchange loop on the u32 bit pattern
//!   ([`hashgrid::AtomicMode`], chosen at run time, both tested). Contributions of zero issue
//!   no atomic.
//!
//! # What one sample costs (the figures GPU time will follow)
//! Per sample and grid ([`hashgrid::encoding_counts`], pinned by a unit test), for the main
//! field's grids of a 300-frame scene:
//!
//! | config | grid | rows read | table bytes read (fwd) | feature bytes | atomics (bwd) | of which dense levels | table |
//! |---|---|---|---|---|---|---|---|
//! | demo: 12 levels x 2 features, 2^15 rows | 3D | 96 | 768 | 96 | 192 | 48 (3 levels) | 2.6 MiB |
//! | demo | 4D | 192 | 1536 | 96 | 384 | 0 | 3.0 MiB |
//! | paper: 16 levels x 2 features, 2^19 rows | 3D | 128 | 1024 | 128 | 256 | 80 (5 levels) | 46.7 MiB |
//! | paper | 4D | 256 | 2048 | 128 | 512 | 64 (2 levels) | 58.7 MiB |
//!
//! A main-field sample encodes both grids: 288 scattered rows, 2304 bytes of table reads and
//! 576 atomic adds at the demo config; 384 rows, 3072 bytes and 768 atomics at the paper config
//! (plus the mask: 8 reads of 4 bytes forward, at most 8 atomics backward). Each row is a
//! separate 8-byte access, so the memory system moves a full sector (32 bytes) per row: about
//! 4x the bytes above. At the demo config both tables (5.6 MiB) fit an H100's 50 MiB L2; at the
//! paper config (105 MiB) they do not, and the hashed levels' reads go to HBM. At the issue's
//! aim of 1e8 field samples/s the paper config's forward moves about 1.2e12 bytes/s in 32-byte
//! sectors if every row missed L2 (a third of an H100's 3.35e12 bytes/s), and its backward
//! issues 7.7e10 atomic adds/s; the atomics, not the bytes, are the risk. Hence, next: keep
//! samples in ray order (neighbouring samples share rows, so most reads hit L2), and for the
//! dense coarse levels, where every sample of a batch adds into the same few rows, reduce in
//! workgroup memory before issuing atomics (`../shared/docs/gpu-notes.md`: the Metal port
//! of tiny-cuda-nn spent 30 of 33 ms in this scatter).

pub mod adam;
pub mod device;
pub mod hashgrid;
pub mod layout;
pub mod mask;
pub mod mlp;
pub mod passes;
pub mod render;
pub mod sh;

pub use layout::{GpuLayoutError, GpuModel, ViewU, FLAG_COMPACT, FLAG_LIST};
pub use passes::{FrameScratch, GpuSampleCache, Pixels};
pub use render::{
    AdapterPolicy, GpuContext, GpuError, GpuScene, Kernel, ALLOW_SOFTWARE_ENV, RENDER_WGSL,
};
