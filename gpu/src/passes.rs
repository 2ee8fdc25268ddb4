//! Rendering through per-sample passes: the host side of the `pass_*` entry points
//! of the render shader (modules `passes*` of `shaders/render/`, [`crate::shaders`]). A frame is rendered in batches of pixels; each batch is one
//! submission of nine dispatches over compacted work lists (rays that hit the scene, then
//! (ray, sample) pairs, then the samples light still reaches), sized on the device by
//! `pass_args` and dispatched indirectly, so that no invocation loops over a whole ray's field
//! evaluations and the host never waits between passes.
//!
//! - [`FrameScratch`]: the `work`, `ctrl` and `args` buffers of one batch size;
//! - [`GpuContext::render_passes`]: every pixel of a camera, or a listed subset (the dynamic
//!   pixels of an incremental frame, the probes of the static test);
//! - [`GpuSampleCache`]: sample-level reuse for incremental playback, the device version of
//!   msth-player's `samples.rs`: fixed samples over the clip, static samples evaluated once,
//!   the dynamic ones evaluated per frame.
//!
//! # The `work` buffer, and why one
//! Every pass binds the same group (`web/shaders/README.md`): the seven bindings of
//! `eval_points` (uniforms, tables, pixel list, output) plus `work` (one read-write f32 buffer holding every intermediate array at word
//! offsets given in the `Pass` uniform), `ctrl` (the atomic counters), the `Pass` uniform and
//! the file's occupancy grid (`pass_density` and `pass_visible` skip samples in its empty
//! cells, as msth-player's `empty_space.rs`). One buffer for the intermediates rather than one binding
//! each keeps every pass within WebGPU's default of 8 storage buffers per stage (8 used) and
//! lets one bind group serve all
//! nine dispatches. Per sample the passes keep `(r, g, b, sigma)` and the geometry features,
//! ray-major (`ray * S + k`), so that neighbouring invocations evaluate neighbouring points of
//! one ray (shared hash rows). The indirect dispatch sizes live in their own buffer (`args`),
//! bound in the `work` slot only for `pass_args`: a buffer may not be a storage binding and an
//! indirect argument of the same dispatch.

use wgpu::util::DeviceExt;

use crate::layout::{GpuModel, ViewU, FLAG_COMPACT, FLAG_LIST};
use crate::render::{GpuContext, GpuError, GpuScene};

/// `Pass.tile.z` bit: the output index is the batch-global list position (probes).
const P_LIST: u32 = FLAG_LIST;
const P_COMPACT: u32 = FLAG_COMPACT;
/// `Pass.tile.z` bit: only samples flagged dynamic get colours (the sample cache).
pub const PASS_FLAG_CACHE: u32 = 4;
/// `Pass.tile.z` bit: `pass_resample` reads the `wmax` histogram.
pub const PASS_FLAG_WMAX: u32 = 8;
/// `Pass.tile.z` bit: the live lists put the samples whose mask skips the 4D lookup apart, for
/// `pass_proposal3` and `pass_density3` (set when those are dispatched).
pub const PASS_FLAG_SPLIT: u32 = 16;
const P_CACHE: u32 = PASS_FLAG_CACHE;
const P_WMAX: u32 = PASS_FLAG_WMAX;

/// Scratch memory a frame's batch may take on the device; batches hold as many rays as fit.
pub const FRAME_WORK_BYTES: u64 = 128 << 20;

/// Byte offsets of the indirect dispatch sizes `pass_args` writes (3 u32 each): the proposal
/// samples / LANES (every pair, or with an occupancy grid the live samples with a 4D lookup),
/// rays, the main samples / LANES (likewise), the colour list / LANES, the dynamic samples /
/// LANES, every (ray, proposal sample) and (ray, main sample) pair, one per invocation
/// (`pass_live_*`), and the live proposal and main samples whose mask skips the 4D lookup /
/// LANES (`pass_proposal3`, `pass_density3`; none without a grid).
pub const ARGS_PROPOSAL: u64 = 0;
pub const ARGS_RAYS: u64 = 12;
pub const ARGS_SAMPLES: u64 = 24;
pub const ARGS_COLOR: u64 = 36;
pub const ARGS_DYNAMIC: u64 = 48;
pub const ARGS_PROPOSAL_PAIRS: u64 = 60;
pub const ARGS_SAMPLE_PAIRS: u64 = 72;
pub const ARGS_PROPOSAL3: u64 = 84;
pub const ARGS_SAMPLES3: u64 = 96;
/// Bytes of the indirect sizes buffer (and of the counters, `ctrl`).
pub const ARGS_BYTES: u64 = 112;
// `pass_args` writes nine sizes of 3 words, the last at ARGS_SAMPLES3.
const _: () = assert!(ARGS_PROPOSAL3 + 12 <= ARGS_SAMPLES3 && ARGS_SAMPLES3 + 12 <= ARGS_BYTES);

/// The `Pass` uniform (80 bytes; `render.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct PassU {
    /// `(first, count, flags, samples per ray)`.
    pub tile: [u32; 4],
    /// Word offsets `(rays, hist, edges, samp)`.
    pub reg0: [u32; 4],
    /// Word offsets `(geo, clist, wmax, pts)`.
    pub reg1: [u32; 4],
    /// `(dlist, occupancy resolution (0: none), plist, slist)`: with a grid, the live proposal
    /// and main samples' lists.
    pub reg2: [u32; 4],
    /// `(build cutoff, first time of pass_wmax, 0, 0)`.
    pub misc: [f32; 4],
}

/// Where the regions of `work` lie for `rays` rays of `samples` samples, and how many words
/// they take; `cache` adds the sample cache's regions (`wmax`, `pts`, `dlist`).
pub fn regions(model: &GpuModel, rays: u64, samples: u64, cache: bool) -> (PassU, u64) {
    let np = model.model.sampler[0] as u64;
    let geo = model.model.color[3] as u64;
    let mut at = 0u64;
    let mut take = |words: u64| {
        let o = at;
        // 16-byte aligned regions (vec4 loads stay aligned).
        at += words.div_ceil(4) * 4;
        o as u32
    };
    let rays_o = take(4 * rays);
    let hist = take(np * rays);
    let edges = take((samples + 1) * rays);
    let samp = take(4 * samples * rays);
    let geo_o = take(geo * samples * rays);
    let clist = take(samples * rays);
    let (plist, slist) = if cache {
        (0, 0)
    } else {
        (take(np * rays), take(samples * rays))
    };
    let (wmax, pts, dlist) = if cache {
        (
            take(np * rays),
            take(4 * samples * rays),
            take(samples * rays),
        )
    } else {
        (0, 0, 0)
    };
    let pass = PassU {
        tile: [0, 0, 0, samples as u32],
        reg0: [rays_o, hist, edges, samp],
        reg1: [geo_o, clist, wmax, pts],
        reg2: [dlist, 0, plist, slist],
        misc: [0.0; 4],
    };
    (pass, at.max(4))
}

/// Words of `work` per ray (frame batches, or the sample cache).
pub fn words_per_ray(model: &GpuModel, samples: u64, cache: bool) -> u64 {
    let np = model.model.sampler[0] as u64;
    let geo = model.model.color[3] as u64;
    let frame = 4 + np + (samples + 1) + samples * (4 + geo + 1) + 16;
    frame
        + if cache {
            np + 5 * samples
        } else {
            np + samples
        }
}

/// The pass pipelines, compiled with `eval_points` over one layout.
pub(crate) struct Pipelines {
    setup: wgpu::ComputePipeline,
    args: wgpu::ComputePipeline,
    proposal: wgpu::ComputePipeline,
    wmax: wgpu::ComputePipeline,
    resample: wgpu::ComputePipeline,
    density: wgpu::ComputePipeline,
    build: wgpu::ComputePipeline,
    dynamic: wgpu::ComputePipeline,
    visible: wgpu::ComputePipeline,
    color: wgpu::ComputePipeline,
    composite: wgpu::ComputePipeline,
    /// `pass_live_proposal` and `pass_live_samples`; `None` for a shader without them.
    live: Option<LivePipelines>,
    static3: Option<Static3>,
}

pub(crate) struct LivePipelines {
    proposal: wgpu::ComputePipeline,
    samples: wgpu::ComputePipeline,
}

/// The passes that evaluate fields, compiled from a `render.wgsl` whose `specialise` region was
/// written for one model (`crate::specialise`); a [`GpuScene`] that has them uses them instead
/// of the context's generic ones.
pub(crate) struct MlpPipelines {
    proposal: wgpu::ComputePipeline,
    density: wgpu::ComputePipeline,
    color: wgpu::ComputePipeline,
    dynamic: wgpu::ComputePipeline,
    /// `pass_proposal3` and `pass_density3`; `None` for a shader without them.
    static3: Option<Static3>,
}

/// The field passes over the live samples whose mask skips the 4D lookup.
pub(crate) struct Static3 {
    proposal: wgpu::ComputePipeline,
    density: wgpu::ComputePipeline,
}

impl Static3 {
    fn new(wgsl: &str, pipeline: &impl Fn(&str) -> wgpu::ComputePipeline) -> Option<Self> {
        wgsl.contains("fn pass_density3(").then(|| Static3 {
            proposal: pipeline("pass_proposal3"),
            density: pipeline("pass_density3"),
        })
    }
}

impl MlpPipelines {
    pub(crate) fn new(wgsl: &str, pipeline: impl Fn(&str) -> wgpu::ComputePipeline) -> Self {
        MlpPipelines {
            static3: Static3::new(wgsl, &pipeline),
            proposal: pipeline("pass_proposal"),
            density: pipeline("pass_density"),
            color: pipeline("pass_color"),
            dynamic: pipeline("pass_dynamic"),
        }
    }
}

/// A scene's field passes: specialised or generic.
struct FieldPasses<'a> {
    proposal: &'a wgpu::ComputePipeline,
    density: &'a wgpu::ComputePipeline,
    color: &'a wgpu::ComputePipeline,
    dynamic: &'a wgpu::ComputePipeline,
    static3: Option<&'a Static3>,
}

impl Pipelines {
    /// `scene`'s specialised pipelines, or the generic ones.
    fn mlps<'a>(&'a self, scene: &'a GpuScene) -> FieldPasses<'a> {
        match &scene.mlps {
            Some(m) => FieldPasses {
                proposal: &m.proposal,
                density: &m.density,
                color: &m.color,
                dynamic: &m.dynamic,
                static3: m.static3.as_ref(),
            },
            None => FieldPasses {
                proposal: &self.proposal,
                density: &self.density,
                color: &self.color,
                dynamic: &self.dynamic,
                static3: self.static3.as_ref(),
            },
        }
    }
}

impl Pipelines {
    /// The pipelines of `wgsl`'s entry points (`pipeline` compiles one).
    pub(crate) fn new(wgsl: &str, pipeline: impl Fn(&str) -> wgpu::ComputePipeline) -> Self {
        let live = wgsl
            .contains("fn pass_live_proposal(")
            .then(|| LivePipelines {
                proposal: pipeline("pass_live_proposal"),
                samples: pipeline("pass_live_samples"),
            });
        Pipelines {
            live,
            static3: Static3::new(wgsl, &pipeline),
            setup: pipeline("pass_setup"),
            args: pipeline("pass_args"),
            proposal: pipeline("pass_proposal"),
            wmax: pipeline("pass_wmax"),
            resample: pipeline("pass_resample"),
            density: pipeline("pass_density"),
            build: pipeline("pass_build"),
            dynamic: pipeline("pass_dynamic"),
            visible: pipeline("pass_visible"),
            color: pipeline("pass_color"),
            composite: pipeline("pass_composite"),
        }
    }
}

/// Small buffers bound at bindings 7-10 by kernels that use none of them.
pub(crate) struct Placeholders {
    pub(crate) work: wgpu::Buffer,
    pub(crate) ctrl: wgpu::Buffer,
    pub(crate) pass: wgpu::Buffer,
    pub(crate) occupancy: wgpu::Buffer,
}

impl Placeholders {
    pub(crate) fn new(device: &wgpu::Device) -> Self {
        let storage = |label| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        };
        Placeholders {
            work: storage("work placeholder"),
            ctrl: storage("ctrl placeholder"),
            pass: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pass placeholder"),
                size: std::mem::size_of::<PassU>() as u64,
                usage: wgpu::BufferUsages::UNIFORM,
                mapped_at_creation: false,
            }),
            occupancy: storage("occupancy placeholder"),
        }
    }
}

/// The device buffers of the passes: `work`, the counters and the indirect sizes.
pub struct FrameScratch {
    work: wgpu::Buffer,
    ctrl: wgpu::Buffer,
    args: wgpu::Buffer,
    /// Rays one batch holds.
    capacity: u32,
    samples: u32,
    base: PassU,
}

impl FrameScratch {
    /// Rays one batch holds.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// What the lists of the last batch rendered with this scratch held (reads the counters
    /// back: a wait for the device).
    pub fn last_counts(&self, ctx: &GpuContext) -> Result<PassCounts, GpuError> {
        let c = ctx.read_u32(&self.ctrl, 7)?;
        Ok(PassCounts {
            rays: c[0],
            colour: c[1],
            proposal4: c[3],
            samples4: c[4],
            proposal3: c[5],
            samples3: c[6],
        })
    }
}

/// The sizes of a batch's lists (the `ctrl` counters of `render.wgsl`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PassCounts {
    /// Rays that hit the scene.
    pub rays: u32,
    /// Samples that got a colour.
    pub colour: u32,
    /// With an occupancy grid: live proposal samples whose mask leaves them a 4D lookup
    /// (`pass_proposal`), and those whose 4D lookup it skips (`pass_proposal3`); 0 without.
    pub proposal4: u32,
    pub proposal3: u32,
    /// The same for the main samples (`pass_density`, `pass_density3`).
    pub samples4: u32,
    pub samples3: u32,
}

/// Which pixels a call renders.
#[derive(Clone, Copy)]
pub enum Pixels<'a> {
    /// Pixels `0..n` (row-major), written to `frame[pixel]`.
    All(u32),
    /// Pixels `list[0..n]`, written to `frame[pixel]`, or to `frame[i]` when `compact`.
    List {
        list: &'a wgpu::Buffer,
        n: u32,
        compact: bool,
    },
}

/// Fixed samples of a set of rays with what does not change with time (msth-player's
/// `SampleCache` on the device): per ray its limits and `S + 1` edges; per sample its point,
/// whether it is dynamic, its colour and density (static samples: once; dynamic ones: each
/// frame), and the list of dynamic samples.
pub struct GpuSampleCache {
    work: wgpu::Buffer,
    ctrl: wgpu::Buffer,
    args: wgpu::Buffer,
    base: PassU,
    rays: u32,
    dynamic: u32,
    bytes: u64,
}

impl GpuSampleCache {
    /// Rays in the cache.
    pub fn rays(&self) -> u32 {
        self.rays
    }

    /// Samples evaluated at every frame.
    pub fn dynamic_samples(&self) -> u32 {
        self.dynamic
    }

    /// Bytes held on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

impl GpuContext {
    fn storage_rw(&self, what: &str, bytes: u64, extra: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size: bytes.max(16),
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_DST
                | wgpu::BufferUsages::COPY_SRC
                | extra,
            mapped_at_creation: false,
        })
    }

    fn ctrl_and_args(&self) -> (wgpu::Buffer, wgpu::Buffer) {
        (
            self.storage_rw("pass counters", ARGS_BYTES, wgpu::BufferUsages::empty()),
            self.storage_rw(
                "pass dispatch sizes",
                ARGS_BYTES,
                wgpu::BufferUsages::INDIRECT,
            ),
        )
    }

    /// Scratch for batches of at most `pixels` rays of `model` (fewer when a batch would take
    /// more than [`FRAME_WORK_BYTES`] or the adapter's binding limit).
    pub fn frame_scratch(&self, model: &GpuModel, pixels: u32) -> Result<FrameScratch, GpuError> {
        self.frame_scratch_within(model, pixels, FRAME_WORK_BYTES)
    }

    /// [`GpuContext::frame_scratch`] with batches of at most `budget` bytes of scratch instead
    /// of [`FRAME_WORK_BYTES`] (still within the adapter's binding limit): fewer, larger batches
    /// per frame, or more, smaller ones. Frames are the same whatever the batches.
    pub fn frame_scratch_within(
        &self,
        model: &GpuModel,
        pixels: u32,
        budget: u64,
    ) -> Result<FrameScratch, GpuError> {
        let samples = model.model.sampler[1];
        let per_ray = 4 * words_per_ray(model, samples as u64, false);
        let binding = self.limits.max_storage_buffer_binding_size;
        let fit = (budget.min(binding) / per_ray).min(u32::MAX as u64) as u32;
        if fit == 0 && budget < binding {
            return Err(GpuError::Model(format!(
                "the per-sample scratch of one ray needs {per_ray} bytes, more than the scratch budget of a batch ({budget} bytes)"
            )));
        }
        if fit == 0 {
            return Err(GpuError::Limit {
                what: "the per-sample scratch of one ray".into(),
                amount: per_ray,
                unit: "bytes",
                limit: "max_storage_buffer_binding_size",
                max: binding,
            });
        }
        let capacity = pixels.max(1).min(fit);
        let (base, words) = regions(model, capacity as u64, samples as u64, false);
        self.check_storage("per-sample scratch", words * 4)?;
        let work = self.storage_rw("work", words * 4, wgpu::BufferUsages::empty());
        let (ctrl, args) = self.ctrl_and_args();
        Ok(FrameScratch {
            work,
            ctrl,
            args,
            capacity,
            samples,
            base,
        })
    }

    #[allow(clippy::too_many_arguments)]
    fn pass_groups(
        &self,
        scene: &GpuScene,
        view: &wgpu::Buffer,
        pass: &wgpu::Buffer,
        list: &wgpu::Buffer,
        out: &wgpu::Buffer,
        work: &wgpu::Buffer,
        ctrl: &wgpu::Buffer,
        args: &wgpu::Buffer,
    ) -> (wgpu::BindGroup, wgpu::BindGroup) {
        let group = |work: &wgpu::Buffer| {
            let entries: Vec<wgpu::BindGroupEntry> = [
                &scene.model,
                view,
                &scene.tab3,
                &scene.tab4,
                &scene.rest,
                list,
                out,
                work,
                ctrl,
                pass,
                &scene.occupancy,
            ]
            .into_iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
            self.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("msth passes"),
                layout: &self.layout,
                entries: &entries,
            })
        };
        (group(work), group(args))
    }

    fn uniform(&self, what: &str, bytes: &[u8]) -> wgpu::Buffer {
        self.device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(what),
                contents: bytes,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            })
    }

    fn direct_groups(&self, n: u32) -> Result<(u32, u32), GpuError> {
        let max = self.limits.max_compute_workgroups_per_dimension;
        crate::layout::dispatch_size(n, max).ok_or_else(|| GpuError::Limit {
            what: format!("a dispatch of {n} invocations"),
            amount: n as u64,
            unit: "invocations",
            limit: "max_compute_workgroups_per_dimension (squared, times 64)",
            max: max as u64 * max as u64 * crate::layout::WORKGROUP as u64,
        })
    }

    /// Renders `pixels` of `view`'s camera at its time with the per-sample passes into `out`
    /// (`(r, g, b, visible depth)` per pixel; a negative depth for a ray that missed), in
    /// batches of `scratch.capacity()` pixels; waits for the device.
    pub fn render_passes(
        &self,
        scene: &GpuScene,
        view: &ViewU,
        pixels: Pixels,
        out: &wgpu::Buffer,
        scratch: &FrameScratch,
    ) -> Result<(), GpuError> {
        let (n, list, flags) = match pixels {
            Pixels::All(n) => (n, &self.placeholders.work, 0),
            Pixels::List { list, n, compact } => {
                (n, list, P_LIST | if compact { P_COMPACT } else { 0 })
            }
        };
        if n == 0 {
            return Ok(());
        }
        if scratch.samples != scene.gpu_model.model.sampler[1] {
            return Err(GpuError::Input(
                "the scratch was made for another model".into(),
            ));
        }
        let view_buf = self.uniform("view", bytemuck::bytes_of(view));
        let pass_buf = self.uniform("pass", bytemuck::bytes_of(&scratch.base));
        let (main, args) = self.pass_groups(
            scene,
            &view_buf,
            &pass_buf,
            list,
            out,
            &scratch.work,
            &scratch.ctrl,
            &scratch.args,
        );
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let p = &self.passes;
        let fields = p.mlps(scene);
        // MSTH_GPU_PASS_PROFILE=1: every dispatch its own submission, timed, and the counters
        // (rays, colour list, live samples) summed over the batches (stderr).
        let profile = std::env::var("MSTH_GPU_PASS_PROFILE").as_deref() == Ok("1");
        // With an occupancy grid the two field passes run over the live samples, listed by
        // `pass_live_*` (a shader without them, such as an older `render.wgsl` a benchmark
        // compiles, evaluates every sample and skips none).
        let live = match &p.live {
            Some(l) if scene.occupancy_resolution != 0 => Some(l),
            _ => None,
        };
        // Live samples whose mask skips the 4D lookup go to passes compiled without it.
        let static3 = live.and(fields.static3);
        let mut steps: Vec<(&str, &wgpu::ComputePipeline, Option<u64>)> =
            vec![("setup", &p.setup, None), ("args", &p.args, None)];
        if let Some(l) = live {
            steps.push(("live proposal", &l.proposal, Some(ARGS_PROPOSAL_PAIRS)));
            steps.push(("args", &p.args, None));
        }
        steps.push(("proposal", fields.proposal, Some(ARGS_PROPOSAL)));
        if let Some(s) = static3 {
            steps.push(("proposal 3D", &s.proposal, Some(ARGS_PROPOSAL3)));
        }
        steps.push(("resample", &p.resample, Some(ARGS_RAYS)));
        if let Some(l) = live {
            steps.push(("live samples", &l.samples, Some(ARGS_SAMPLE_PAIRS)));
            steps.push(("args", &p.args, None));
        }
        steps.push(("density", fields.density, Some(ARGS_SAMPLES)));
        if let Some(s) = static3 {
            steps.push(("density 3D", &s.density, Some(ARGS_SAMPLES3)));
        }
        steps.extend([
            ("visible", &p.visible, Some(ARGS_RAYS)),
            ("args", &p.args, None),
            ("color", fields.color, Some(ARGS_COLOR)),
            ("composite", &p.composite, Some(ARGS_RAYS)),
        ]);
        let mut spent = vec![0f64; steps.len()];
        // With timestamp queries the profile times each pass on the device, the batch still one
        // submission; without, each pass is its own submission, timed on the host (which adds
        // a submission's and a wait's cost to every pass).
        let stamps = if profile && self.timestamps {
            let count = 2 * steps.len() as u32;
            let set = self.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("pass timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count,
            });
            let resolved = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pass timestamps"),
                size: 8 * count as u64,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            Some((set, resolved))
        } else {
            None
        };
        let mut counted = [0u64; 6];
        let mut first = 0u32;
        while first < n {
            let count = scratch.capacity.min(n - first);
            let mut pass = scratch.base;
            let split = if static3.is_some() {
                PASS_FLAG_SPLIT
            } else {
                0
            };
            pass.tile = [first, count, flags | split, scratch.samples];
            // The grid's resolution also for a shader without the listing passes: its
            // `pass_density` skips empty cells by itself.
            pass.reg2[1] = scene.occupancy_resolution;
            self.queue
                .write_buffer(&pass_buf, 0, bytemuck::bytes_of(&pass));
            let (gx, gy) = self.direct_groups(count)?;
            let mut enc = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
            enc.clear_buffer(&scratch.ctrl, 0, None);
            let record =
                |cp: &mut wgpu::ComputePass,
                 (name, pl, at): &(&str, &wgpu::ComputePipeline, Option<u64>)| {
                    let bg = if *name == "args" { &args } else { &main };
                    cp.set_bind_group(0, bg, &[]);
                    cp.set_pipeline(pl);
                    match (at, *name) {
                        (Some(at), _) => cp.dispatch_workgroups_indirect(&scratch.args, *at),
                        (None, "setup") => cp.dispatch_workgroups(gx, gy, 1),
                        (None, _) => cp.dispatch_workgroups(1, 1, 1),
                    }
                };
            if let Some((set, resolved)) = &stamps {
                for (i, step) in steps.iter().enumerate() {
                    let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some(step.0),
                        timestamp_writes: Some(wgpu::ComputePassTimestampWrites {
                            query_set: set,
                            beginning_of_pass_write_index: Some(2 * i as u32),
                            end_of_pass_write_index: Some(2 * i as u32 + 1),
                        }),
                    });
                    record(&mut cp, step);
                }
                enc.resolve_query_set(set, 0..2 * steps.len() as u32, resolved, 0);
                self.queue.submit([enc.finish()]);
                let words = self.read_u32(resolved, 4 * steps.len())?;
                let period = f64::from(self.queue.get_timestamp_period()) * 1e-9;
                for (i, t) in spent.iter_mut().enumerate() {
                    let at = |q: usize| u64::from(words[2 * q]) | u64::from(words[2 * q + 1]) << 32;
                    *t += at(2 * i + 1).saturating_sub(at(2 * i)) as f64 * period;
                }
            } else {
                let mut k = 0;
                while k < steps.len() {
                    let k_end = if profile { k + 1 } else { steps.len() };
                    {
                        let mut cp =
                            enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
                        for step in &steps[k..k_end] {
                            record(&mut cp, step);
                        }
                    }
                    let t = std::time::Instant::now();
                    self.queue.submit([enc.finish()]);
                    if profile {
                        self.wait()?;
                        spent[k] += t.elapsed().as_secs_f64();
                    }
                    enc = self
                        .device
                        .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
                    k = k_end;
                }
            }
            if profile {
                let c = scratch.last_counts(self)?;
                let now = [
                    c.rays,
                    c.colour,
                    c.proposal4,
                    c.samples4,
                    c.proposal3,
                    c.samples3,
                ];
                for (sum, c) in counted.iter_mut().zip(now) {
                    *sum += u64::from(c);
                }
            }
            first += count;
        }
        if profile {
            let line: Vec<String> = steps
                .iter()
                .zip(&spent)
                .map(|((name, _, _), s)| format!("{name} {s:.4} s"))
                .collect();
            let clock = if stamps.is_some() {
                "device timestamps"
            } else {
                "host clock, a submission per pass"
            };
            let total: f64 = spent.iter().sum();
            eprintln!(
                "per-sample passes ({n} pixels; {clock}; {total:.4} s in all): {}",
                line.join(", ")
            );
            let [rays, colour, proposal4, samples4, proposal3, samples3] = counted;
            let lists = if live.is_some() {
                format!(
                    ", live proposal samples {} ({proposal3} without a 4D lookup), live main samples {} ({samples3} without)",
                    proposal4 + proposal3,
                    samples4 + samples3
                )
            } else {
                String::new()
            };
            eprintln!("  counts: rays {rays}{lists}, colour list {colour}");
        }
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(e.to_string()));
        }
        self.wait()?;
        self.check_state()
    }

    /// Device bytes a sample cache of `rays` rays with `samples` samples each takes.
    pub fn sample_cache_bytes(model: &GpuModel, rays: u64, samples: u64) -> u64 {
        let (_, words) = regions(model, rays, samples, true);
        words * 4 + 16 + ARGS_BYTES
    }

    /// Builds the sample cache of the `n` pixels in `list` of `view`'s camera: the proposal
    /// field at each of `times` (per-bin maximum of the weights), `samples` fixed samples per
    /// ray from that histogram, static samples (`1 - m < cutoff`) evaluated once at time 0.
    /// The cache's frames are compact: `frame` (here, and in [`GpuContext::render_sample_cache`])
    /// holds entry `i` for the list's pixel `i` (a pixel that misses the scene gets the
    /// background here, once).
    #[allow(clippy::too_many_arguments)]
    pub fn build_sample_cache(
        &self,
        scene: &GpuScene,
        view: &ViewU,
        list: &wgpu::Buffer,
        n: u32,
        times: &[f32],
        samples: u32,
        cutoff: f32,
        frame: &wgpu::Buffer,
    ) -> Result<GpuSampleCache, GpuError> {
        if times.is_empty() || samples == 0 {
            return Err(GpuError::Input(
                "a sample cache needs at least one time and one sample".into(),
            ));
        }
        let model = &scene.gpu_model;
        let (mut base, words) = regions(model, n.max(1) as u64, samples as u64, true);
        let bytes = Self::sample_cache_bytes(model, n.max(1) as u64, samples as u64);
        self.check_storage("the sample cache", words * 4)?;
        let work = self.storage_rw("sample cache", words * 4, wgpu::BufferUsages::empty());
        let (ctrl, args) = self.ctrl_and_args();
        base.misc[0] = cutoff;
        let mut v = *view;
        v.time = [times[0], 0.0, 0.0, 0.0];
        let view_buf = self.uniform("view", bytemuck::bytes_of(&v));
        let pass_buf = self.uniform("pass", bytemuck::bytes_of(&base));
        let (main, args_g) = self.pass_groups(
            scene, &view_buf, &pass_buf, list, frame, &work, &ctrl, &args,
        );
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let p = &self.passes;
        let (gx, gy) = self.direct_groups(n.max(1))?;
        let sizes = |cp: &mut wgpu::ComputePass| {
            cp.set_bind_group(0, &args_g, &[]);
            cp.set_pipeline(&p.args);
            cp.dispatch_workgroups(1, 1, 1);
            cp.set_bind_group(0, &main, &[]);
        };
        let ind = |cp: &mut wgpu::ComputePass, pl: &wgpu::ComputePipeline, at: u64| {
            cp.set_pipeline(pl);
            cp.dispatch_workgroups_indirect(&args, at);
        };
        for (i, &t) in times.iter().enumerate() {
            let mut pass = base;
            pass.tile = [0, n, P_LIST | P_COMPACT, samples];
            pass.misc[1] = if i == 0 { 1.0 } else { 0.0 };
            v.time = [t, 0.0, 0.0, 0.0];
            self.queue
                .write_buffer(&pass_buf, 0, bytemuck::bytes_of(&pass));
            self.queue
                .write_buffer(&view_buf, 0, bytemuck::bytes_of(&v));
            let mut enc = self
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
            if i == 0 {
                enc.clear_buffer(&ctrl, 0, None);
            }
            {
                let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
                cp.set_bind_group(0, &main, &[]);
                if i == 0 {
                    cp.set_pipeline(&p.setup);
                    cp.dispatch_workgroups(gx, gy, 1);
                    sizes(&mut cp);
                }
                ind(&mut cp, p.mlps(scene).proposal, ARGS_PROPOSAL);
                ind(&mut cp, &p.wmax, ARGS_RAYS);
            }
            self.queue.submit([enc.finish()]);
        }
        let mut pass = base;
        pass.tile = [0, n, P_LIST | P_WMAX, samples];
        self.queue
            .write_buffer(&pass_buf, 0, bytemuck::bytes_of(&pass));
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            cp.set_bind_group(0, &main, &[]);
            ind(&mut cp, &p.resample, ARGS_RAYS);
            ind(&mut cp, &p.build, ARGS_SAMPLES);
        }
        self.queue.submit([enc.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(e.to_string()));
        }
        let counts = self.read_u32(&ctrl, 3)?;
        base.tile = [0, n, P_LIST | P_CACHE, samples];
        Ok(GpuSampleCache {
            work,
            ctrl,
            args,
            base,
            rays: counts[0],
            dynamic: counts[2],
            bytes,
        })
    }

    /// Renders the cached rays at `view`'s time into `frame[i]` for the list's pixel `i`
    /// (compact): the dynamic samples' density, which samples light reaches, their colours,
    /// compositing. `list` and `frame` must be those the cache was built with.
    pub fn render_sample_cache(
        &self,
        scene: &GpuScene,
        view: &ViewU,
        cache: &GpuSampleCache,
        list: &wgpu::Buffer,
        frame: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        if cache.rays == 0 {
            return Ok(());
        }
        let view_buf = self.uniform("view", bytemuck::bytes_of(view));
        let pass_buf = self.uniform("pass", bytemuck::bytes_of(&cache.base));
        let (main, args_g) = self.pass_groups(
            scene,
            &view_buf,
            &pass_buf,
            list,
            frame,
            &cache.work,
            &cache.ctrl,
            &cache.args,
        );
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let p = &self.passes;
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        // The colour list is rebuilt every frame; the ray and dynamic-sample counts stay.
        enc.clear_buffer(&cache.ctrl, 4, Some(4));
        {
            let mut cp = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            let sizes = |cp: &mut wgpu::ComputePass| {
                cp.set_bind_group(0, &args_g, &[]);
                cp.set_pipeline(&p.args);
                cp.dispatch_workgroups(1, 1, 1);
                cp.set_bind_group(0, &main, &[]);
            };
            let ind = |cp: &mut wgpu::ComputePass, pl: &wgpu::ComputePipeline, at: u64| {
                cp.set_pipeline(pl);
                cp.dispatch_workgroups_indirect(&cache.args, at);
            };
            sizes(&mut cp);
            ind(&mut cp, p.mlps(scene).dynamic, ARGS_DYNAMIC);
            ind(&mut cp, &p.visible, ARGS_RAYS);
            sizes(&mut cp);
            ind(&mut cp, p.mlps(scene).color, ARGS_COLOR);
            ind(&mut cp, &p.composite, ARGS_RAYS);
        }
        self.queue.submit([enc.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(e.to_string()));
        }
        self.wait()?;
        self.check_state()
    }

    /// Reads the first `n` u32 of `buf` back.
    pub fn read_u32(&self, buf: &wgpu::Buffer, n: usize) -> Result<Vec<u32>, GpuError> {
        let words = n.div_ceil(4);
        let v = self.read_vec4(buf, words)?;
        Ok(v.iter().flatten().map(|f| f.to_bits()).take(n).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hashgrid::MAX_FEATURES;
    use crate::layout::{MAX_GEO, MAX_HIDDEN, MAX_PROPOSAL_SAMPLES, MAX_SAMPLES, WORKGROUP};
    use msth_core::grid::MAX_LEVELS;
    use msth_core::pipeline::{HIDDEN_TRANSMITTANCE, VISIBLE_TRANSMITTANCE};

    /// The value of `const NAME: TY = V;` in `render.wgsl`, parsed (a `u` suffix dropped).
    fn wgsl_const<T: std::str::FromStr>(name: &str, ty: &str) -> T
    where
        T::Err: std::fmt::Debug,
    {
        let needle = format!("const {name}: {ty} = ");
        let line = crate::render::RENDER_WGSL
            .lines()
            .find_map(|l| l.strip_prefix(needle.as_str()))
            .unwrap_or_else(|| panic!("render.wgsl declares no `{needle}`"));
        let value = line.split_once(';').map(|(v, _)| v).unwrap_or(line);
        let value = value.strip_suffix('u').unwrap_or(value);
        value
            .parse()
            .unwrap_or_else(|e| panic!("{name}: {value:?}: {e:?}"))
    }

    fn wgsl_u32(name: &str) -> u64 {
        wgsl_const(name, "u32")
    }

    fn wgsl_f32(name: &str) -> f32 {
        wgsl_const(name, "f32")
    }

    /// The shader's copies of the host's constants (the `Pass` flags, the limits) agree.
    #[test]
    fn shader_constants_match_the_host() {
        for (name, host) in [
            ("FLAG_P_LIST", P_LIST as u64),
            ("FLAG_P_COMPACT", P_COMPACT as u64),
            ("FLAG_P_CACHE", PASS_FLAG_CACHE as u64),
            ("FLAG_P_WMAX", PASS_FLAG_WMAX as u64),
            ("FLAG_P_SPLIT", PASS_FLAG_SPLIT as u64),
            ("MAX_PROPOSAL_SAMPLES", MAX_PROPOSAL_SAMPLES as u64),
            ("MAX_SAMPLES", MAX_SAMPLES as u64),
            ("MAX_HIDDEN", MAX_HIDDEN as u64),
            ("MAX_LEVELS", MAX_LEVELS as u64),
            ("MAX_FEATURES", MAX_FEATURES as u64),
            ("MAX_GEO", MAX_GEO as u64),
            ("WORKGROUP", WORKGROUP as u64),
        ] {
            assert_eq!(wgsl_u32(name), host, "{name}");
        }
        // The rendering thresholds of msth-core (`pipeline`), which the shader writes out:
        // where a ray's visible depth ends, and the optical depth beyond which no colour is
        // evaluated (`ln(1 / HIDDEN_TRANSMITTANCE)`, to f32 rounding).
        assert_eq!(wgsl_f32("VISIBLE_TRANSMITTANCE"), VISIBLE_TRANSMITTANCE);
        let tau_hidden = (1.0 / HIDDEN_TRANSMITTANCE).ln();
        let wgsl = wgsl_f32("TAU_HIDDEN");
        assert!(
            (wgsl - tau_hidden).abs() <= 4.0 * f32::EPSILON * tau_hidden,
            "TAU_HIDDEN {wgsl} against ln(1 / {HIDDEN_TRANSMITTANCE}) = {tau_hidden}"
        );
    }
}
