//! `msth-gpu`: every WGSL kernel of msth and its wgpu host code (Vulkan, Metal, DX12 natively;
//! the browser runs the same render kernels through WebGPU).
//!
//! - [`render`]: the renderer's kernels ([`RENDER_WGSL`]: the per-sample passes and
//!   `eval_points`), the device context that compiles them
//!   and one model's buffers on the device;
//! - [`shaders`]: the render kernels' WGSL modules (`shaders/render/`: camera and rays, hash
//!   grids, mask, MLPs, SH, the per-point field, the per-point entry point, the passes) and the
//!   preprocessor that composes them (`// #import NAME` lines);
//! - [`passes`]: rendering through per-sample passes over compacted work lists (frames, probes,
//!   and the sample cache of incremental playback);
//! - [`specialise`]: the passes' encodings and MLPs rewritten for one model, its level values
//!   and weights as constants (the page writes the same text in `web/js/specialise.js`);
//! - [`layout`]: the render kernels' uniforms and parameter-buffer split, byte for byte;
//! - [`device`]: a compute device for the training kernels (f32 atomics when the adapter has
//!   them), buffers, dispatches, read-back;
//! - [`hashgrid`]: the multi-resolution hash-grid encoding (3D and 4D), forward and backward;
//! - [`mask`]: the dense mask grid (trilinear + sigmoid), forward and backward;
//! - [`mlp`]: the density and colour MLPs (and their output activations), forward and backward,
//!   tiled through workgroup memory;
//! - [`sh`]: the view-direction encoding (spherical harmonics, forward);
//! - [`adam`]: Adam over the flat parameter buffer (the trainer's update, mask loss fused);
//! - [`composite`]: volume rendering of ray batches, forward and backward (scans per ray);
//! - [`elementwise`]: the encoding blend and column copies that chain a field's kernels;
//! - [`losses`]: per-ray losses (colour MSE and its dC; distortion and interlevel losses, values
//!   and gradients) and the per-sample mask loss;
//! - [`sampling`]: where a step's samples go (stratified proposal samples, inverse-CDF
//!   resampling, placement through the spacing and the contraction);
//! - [`step`]: the whole training step on the device, and Adam;
//! - [`volume`]: the play-time volume on the device and the march through it
//!   ([`VOLUME_WGSL`]).
//!
//! # The render shader: modules, and the web page's copy
//! The modules of `shaders/render/` are the one source. The build composes them into
//! [`RENDER_WGSL`] ([`shaders`]), which native code compiles. The browser page fetches
//! `web/shaders/render.wgsl` over HTTP, so `web/` holds a generated copy of that composed text,
//! and the test `tests/web_copy.rs` fails when the two differ by a byte
//! (`MSTH_UPDATE_WEB_WGSL=1` rewrites the copy).
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
//! (at most `2^D * F <= 128` loop iterations each), the mask one per sample (8 corners), the
//! MLPs one per sample (a layer's width of multiply-adds per output block), compositing one per
//! sample with the ray's sums as workgroup scans, Adam one per parameter, so the work spreads
//! over many invocations and lavapipe's per-invocation loop budget never binds. Kernels read
//! and write device buffers and return; the host chains passes.
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
//!
//! # MLPs: tiling, layout, and why
//! - **Weights: core's layout unchanged.** Each MLP is its named slice of the flat buffer
//!   (`field.density_mlp`, `field.color_mlp`, `proposal.density_mlp`), layer `k` row-major
//!   `[dims[k], dims[k + 1]]` at `MlpLayout::offsets[k]`, bias-free; the kernels take the flat
//!   buffer and the slice's offset, and the gradient buffer has the same layout (as the grids).
//! - **One workgroup = 256 samples, one invocation per sample.** Per layer, the workgroup
//!   stages the whole weight matrix in workgroup memory (rows padded to whole `vec4`s: at most
//!   64 x 64 floats = 16 KiB, WebGPU's guaranteed `max_compute_workgroup_storage_size`, hence
//!   [`mlp::MAX_WIDTH`] = 64, which every preset meets), then each invocation multiplies its
//!   own activation row (in registers, `vec4` blocks) by it; every invocation reads the same
//!   weight at the same time (a broadcast, no bank conflicts), one `vec4` load per 4 FMAs.
//! - **Activations sample-major**: input `[n, dims[0]]` (the encoding's `[n, levels, F]` as it
//!   is), outputs `[n, dims[L]]` after the output activation (`trunc_exp` on the density,
//!   `sigmoid` on rgb, as `msth_core::field`), and for training `acts` `[n, sum dims[1..]]`:
//!   the hidden outputs after the ReLU and the raw last layer, which the backward reads instead
//!   of recomputing the forward.
//! - **Backward, per layer from the last**: (B) the weight gradient of the workgroup's 256
//!   samples, staged 32 samples at a time (inputs and output gradients, 16 KiB); invocation
//!   `t` owns one 4x4 block of the layer's weights (a 64 x 64 layer has exactly 256 blocks)
//!   and sums it in registers over all 256 samples, then adds each entry once with
//!   `add_grad` (native f32 `atomicAdd` or the compare-exchange loop, [`hashgrid::AtomicMode`]):
//!   **one atomic per weight per 256 samples**, zero sums skipped. (A) the input gradient
//!   `dx = W dy` from the staged weights, masked by the ReLU; for the first layer it is
//!   written out (`d_input`, the columns asked for: all for the density MLPs, which feed the
//!   hash-grid backward; the geometry features only for the colour MLP).
//! - Why not per-sample atomics, or a partial-sum buffer reduced in a second pass: the first
//!   would issue 6,272 atomics per sample into the same 6,272 addresses (the colour MLP), the
//!   second moves `weights x 4` bytes per workgroup through memory twice; a 256-sample tile
//!   brings the atomics to 24.5 per sample, below the hash grid's hundreds.
//!
//! Per sample ([`mlp::mlp_counts`], pinned by a unit test; weights are read once per workgroup):
//!
//! | config | MLP | weights | fwd flops | bwd flops | fwd bytes | bwd bytes | bwd atomics |
//! |---|---|---|---|---|---|---|---|
//! | demo | density `[24, 64, 16]` | 2560 | 5120 | 10240 | 520 | 872 | 10 |
//! | demo, paper | colour `[31, 64, 64, 3]` | 6272 | 12544 | 25088 | 758 | 1394 | 24.5 |
//! | paper | density `[32, 64, 16]` | 3072 | 6144 | 12288 | 560 | 944 | 12 |
//! | demo, paper | proposal `[10, 16, 1]` | 176 | 352 | 704 | 115 | 219 | 0.7 |
//!
//! A main-field sample (density + colour) at the paper config: 18.7 kflop forward, 37.4 kflop
//! backward, about 3.7 KB of activation traffic and 36.5 atomics. At the aim of 1e8
//! samples/s that is 5.6e12 flop/s (a tenth of an H100's f32 peak: the MLPs are compute-bound
//! only at about 10x the aim), 3.7e11 bytes/s, and 3.7e9 atomics/s into 9,344 addresses, a
//! twentieth of the hash grid's 7.7e10. The SH encoding ([`sh`]): 12 bytes read, 64 written,
//! about 40 flops per direction. Adam ([`adam`]): 16 bytes read and 12 written per parameter
//! (gradient, parameter, both moments), one invocation each, no atomics. Compositing
//! ([`composite`]): one workgroup of 64 per ray, one invocation per sample, the sums along the
//! ray (optical depth front to back, the backward's `sum_{i>k} d_w_i w_i` back to front) as
//! 6-step scans in workgroup memory per chunk of 64 samples with a carry; per sample 20 bytes
//! read and 4 written forward (sigma, delta, rgb; w), about 40 read and 20 written backward, no
//! atomics; 48-sample rays keep 48 of 64 invocations busy. The distortion loss ([`losses`]):
//! the same per-ray scans (sums of `w` and `w m` before, after and in total), 24 bytes read per
//! sample twice and `d_w` updated in place (8 bytes), no atomics. The interlevel loss: per
//! main interval a bisection into the ray's proposal intervals (log2 128 = 7 steps) and a walk
//! over the few it overlaps; per proposal interval a bisection into the main intervals and a
//! gather of their gradients (each recomputing its bound): a few hundred bytes of cached reads
//! per ray sample, no atomics.
//!
//! Measured on lavapipe (`examples/bench_mlp.rs`; 2 shared CPU cores): the MLP kernels run at
//! about 1% of core's one-thread SGEMM MLP; lavapipe is a correctness target, not a speed one.
//!
//! # Measured on an NVIDIA H200 (2026-11-27, Vulkan, driver 580.159.04)
//! Every kernel test above passes there (`MSTH_REQUIRE_GPU=1`; three tolerances had to be
//! widened for what a GPU that fuses multiply-adds does, each argued in its test's header).
//! The whole main field ([`field::GpuField`], `examples/bench_field.rs`, 1,048,576 samples in
//! ray order, all buffers resident, each kernel its own submission):
//!
//! | config | forward | backward | forward + backward | CPU, one thread | ratio |
//! |---|---|---|---|---|---|
//! | demo | 98 M samples/s | 47 M | **32 M** | 0.44 M | 73x |
//! | paper | 55 M | 33 M | **21 M** | 0.24 M | 86x |
//!
//! The aim is 100 M/s on an H100: a third of the way at the demo configuration, a fifth
//! at the paper's. Per kernel (`bench_encode`, `bench_mlp`, 262,144 samples, after 0.3 s of
//! warm-up; single figures vary up to 2x between runs): hash grids, forward / backward, demo 3D
//! 700 / 370 M samples/s, demo 4D 420 / 220 M, paper 3D 235 / 200 M, paper 4D 99 / 90 M; MLPs,
//! forward / backward, density 300-370 / 250 M, colour 100-240 / 90 M. At the demo
//! configuration the colour MLP's backward is a third of the field's time; it runs at about
//! 2 TFLOP/s, a few percent of the card's f32 rate, so the MLP kernels (register pressure of a
//! 64-wide row per invocation, a weight read from workgroup memory per four multiply-adds) are
//! where the next factor is; the paper's 4D table (58 MiB, beyond L2) is the other.
//! Compiling the kernels per shape (constant loop bounds) changed nothing there.
//!
//! # The training step
//! [`step::GpuStep`] chains the kernels into the CPU trainer's step (proposal samples,
//! proposal density and weights, resampling, main field, compositing, every loss, both
//! backwards, Adam), recorded into one command encoder per step
//! ([`device::ComputeDevice::begin_batch`]: one submission, no waits between its ~50
//! dispatches; before, each kernel call submitted and waited, the per-operation
//! synchronisation trap of `../shared/docs/gpu-notes.md`). The host draws the rays and their
//! jitters ([`sampling::SampleRay`]: origin and time, direction, limits and two jitters, 48
//! bytes a ray) so the device step uses the CPU trainer's random numbers; `tests/step.rs`
//! checks its losses and every gradient slice against `msth_core::pipeline::train_chunk`.
//! Sampling keeps the per-sample rule: placing samples is one invocation per sample, the
//! resampling CDF a scan per ray (one workgroup, chunks of 64 bins), each new edge one
//! invocation (a bisection over the CDF).

pub mod adam;
pub mod composite;
pub mod device;
pub mod elementwise;
pub mod field;
pub mod hashgrid;
pub mod layout;
pub mod losses;
pub mod mask;
pub mod mlp;
pub mod passes;
pub mod presets;
pub mod render;
pub mod sampling;
pub mod sh;
pub mod shaders;
pub mod specialise;
pub mod step;
pub mod volume;

pub use device::{ComputeDevice, GpuDevice};
pub use layout::{GpuLayoutError, GpuModel, TableFormat, ViewU, FLAG_COMPACT, FLAG_LIST};
pub use passes::{FrameScratch, GpuSampleCache, PassCounts, Pixels, FRAME_WORK_BYTES};
pub use render::{
    with_lanes, AdapterPolicy, GpuContext, GpuError, GpuScene, Kernel, ReadBack,
    ALLOW_SOFTWARE_ENV, DEFAULT_LANES, DISCRETE_FRAME_WORK_BYTES, RENDER_WGSL,
};
pub use shaders::VOLUME_WGSL;
pub use volume::{GpuVolume, VolumeKernel};
