//! The renderer's kernels ([`RENDER_WGSL`], composed from `shaders/render/`: the same text the
//! browser player runs)
//! and their host code: they render exactly what the CPU renderer of `msth-player` renders from
//! the same parameters, camera and time.
//!
//! - [`GpuContext`]: adapter, device, the compiled kernels; [`GpuContext::open`] picks the
//!   adapter ([`AdapterPolicy`]);
//! - [`GpuScene`]: one model's uniforms and parameter buffers on the device, re-uploaded when the
//!   parameters change (a new dynamic chunk);
//! - [`GpuContext::render_passes`] ([`crate::passes`]): a frame, or listed pixels of it, through
//!   the per-sample passes; [`GpuContext::dispatch`]: one `eval_points` pass. The frame-level
//!   policy (full frames, then incremental frames for a fixed camera with the CPU renderer's
//!   classification) is `msth_player::gpu::GpuRenderer`, built on these.
//!
//! Errors (no adapter, a model or frame beyond the adapter's limits, a lost device, a failed
//! dispatch) are [`GpuError`]s, never panics.

use std::sync::{Arc, Mutex};

use wgpu::util::DeviceExt;

use crate::layout::{self, GpuModel, ParamSplit, TableFormat, ViewU};

/// The kernels' source, shared with the browser player ([`crate::shaders`]).
pub use crate::shaders::RENDER_WGSL;

/// Environment variable that lets the automatic choice use a software adapter (Mesa lavapipe,
/// WARP, SwiftShader); `--gpu` always may.
pub const ALLOW_SOFTWARE_ENV: &str = "MSTH_GPU_SOFTWARE";

/// Why the GPU path is unavailable or failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GpuError {
    #[error("no GPU adapter found ({0}); install a Vulkan driver (e.g. Mesa's lavapipe: mesa-vulkan-drivers) or use --cpu")]
    NoAdapter(String),
    #[error("GPU adapter {adapter}: could not open a device: {error}")]
    Device { adapter: String, error: String },
    #[error("{what} needs {amount} {unit}, more than the adapter's {limit} ({max} {unit}); use --cpu or a smaller size")]
    Limit {
        what: String,
        amount: u64,
        unit: &'static str,
        limit: &'static str,
        max: u64,
    },
    #[error("the model cannot be rendered on the GPU: {0}")]
    Model(String),
    #[error("GPU kernels failed to compile: {0}")]
    Shader(String),
    #[error("GPU device lost: {0}")]
    Lost(String),
    #[error("GPU error: {0}")]
    Backend(String),
    #[error("the GPU adapter cannot run this kernel: {0}")]
    MissingFeature(String),
    #[error("bad input to a GPU kernel: {0}")]
    Input(String),
}

/// Which adapters [`GpuContext::open`] may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AdapterPolicy {
    /// Software adapters (device type CPU: lavapipe, WARP) count too.
    pub allow_software: bool,
}

impl AdapterPolicy {
    /// The automatic choice: hardware adapters only, unless [`ALLOW_SOFTWARE_ENV`] is `1`.
    pub fn automatic() -> Self {
        AdapterPolicy {
            allow_software: std::env::var(ALLOW_SOFTWARE_ENV).is_ok_and(|v| v == "1"),
        }
    }

    /// `--gpu`: any adapter, hardware preferred.
    pub fn any() -> Self {
        AdapterPolicy {
            allow_software: true,
        }
    }
}

/// Rank of an adapter type, best first; `None` for types the policy excludes.
fn rank(t: wgpu::DeviceType, policy: AdapterPolicy) -> Option<u8> {
    match t {
        wgpu::DeviceType::DiscreteGpu => Some(0),
        wgpu::DeviceType::IntegratedGpu => Some(1),
        wgpu::DeviceType::VirtualGpu => Some(2),
        wgpu::DeviceType::Other => Some(3),
        wgpu::DeviceType::Cpu => policy.allow_software.then_some(4),
    }
}

/// Errors the device reported outside a dispatch's own checks.
#[derive(Default)]
pub(crate) struct DeviceState {
    lost: Option<String>,
    errors: Vec<String>,
}

/// Records `device`'s loss and uncaptured errors into a [`DeviceState`].
pub(crate) fn watch(device: &wgpu::Device) -> Arc<Mutex<DeviceState>> {
    let state = Arc::new(Mutex::new(DeviceState::default()));
    let s = state.clone();
    device.set_device_lost_callback(move |reason, msg| {
        if let Ok(mut s) = s.lock() {
            s.lost = Some(format!("{reason:?}: {msg}"));
        }
    });
    let s = state.clone();
    device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
        if let Ok(mut s) = s.lock() {
            s.errors.push(e.to_string());
        }
    }));
    state
}

/// Fails with what the device reported since the last check (lost device, validation).
pub(crate) fn check_state(state: &Mutex<DeviceState>) -> Result<(), GpuError> {
    let mut s = state
        .lock()
        .map_err(|_| GpuError::Backend("device state poisoned".into()))?;
    if let Some(l) = &s.lost {
        return Err(GpuError::Lost(l.clone()));
    }
    if !s.errors.is_empty() {
        let e = s.errors.join("; ");
        s.errors.clear();
        return Err(GpuError::Backend(e));
    }
    Ok(())
}

/// The best adapter `policy` allows (discrete, integrated, virtual, other, then software), or
/// why there is none.
pub(crate) fn pick_adapter(policy: AdapterPolicy) -> Result<wgpu::Adapter, GpuError> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
    let mut seen = Vec::new();
    let mut best: Option<(u8, wgpu::Adapter)> = None;
    for a in adapters {
        let info = a.get_info();
        seen.push(format!(
            "{} ({:?}, {:?})",
            info.name, info.device_type, info.backend
        ));
        if let Some(r) = rank(info.device_type, policy) {
            if best.as_ref().is_none_or(|(b, _)| r < *b) {
                best = Some((r, a));
            }
        }
    }
    match best {
        Some((_, adapter)) => Ok(adapter),
        None => {
            let why = if seen.is_empty() {
                "no adapters at all".to_string()
            } else {
                format!(
                    "only software adapters, which the automatic choice skips unless {ALLOW_SOFTWARE_ENV}=1 or --gpu: {}",
                    seen.join(", ")
                )
            };
            Err(GpuError::NoAdapter(why))
        }
    }
}

/// Scratch per batch of a frame's rays on a discrete GPU (the adapter's binding limit still
/// applies): fewer, fuller batches. On an NVIDIA H200 a 1352x1014 frame of a balanced stage model
/// took 5 batches instead of 38, at 9.9 instead of 8.3 FPS (docs/playback.md, "Measured on an
/// NVIDIA H200").
pub const DISCRETE_FRAME_WORK_BYTES: u64 = 1 << 30;

/// The line of `render.wgsl` that sets how many samples one invocation of the per-sample passes
/// evaluates.
const LANES_LINE: &str = "const LANES: u32 = 4u;\n";

/// Samples per invocation of the per-sample passes that [`GpuContext::open_with_kernels`]
/// compiles when not told: the kernels' own. Four samples share each MLP weight read, which
/// software adapters (lavapipe, SwiftShader) gather lane by lane: on lavapipe, fewer lanes are
/// slower; no hardware GPU has measured the others yet (docs/playback.md, "Batches and
/// lanes").
pub const DEFAULT_LANES: u32 = 4;

/// `wgsl` (a `render.wgsl`) with the per-sample passes evaluating `lanes` samples per
/// invocation (1, 2 or 4): the source itself for 4.
pub fn with_lanes(wgsl: &str, lanes: u32) -> Result<String, GpuError> {
    if !matches!(lanes, 1 | 2 | 4) {
        return Err(GpuError::Input(format!(
            "{lanes} samples per invocation: the kernels take 1, 2 or 4"
        )));
    }
    if !wgsl.contains(LANES_LINE) {
        return Err(GpuError::Shader(
            "the shader does not set LANES to 4 on a line of its own".into(),
        ));
    }
    Ok(wgsl.replacen(LANES_LINE, &format!("const LANES: u32 = {lanes}u;\n"), 1))
}

/// The `LANES` a source sets (4 when it sets none: an older `render.wgsl`).
fn lanes_of(wgsl: &str) -> u32 {
    wgsl.lines()
        .find_map(|l| {
            l.strip_prefix("const LANES: u32 = ")?
                .strip_suffix("u;")?
                .parse()
                .ok()
        })
        .unwrap_or(4)
}

/// An open device with the compiled kernels.
pub struct GpuContext {
    gpu: crate::device::GpuDevice,
    pub(crate) layout: wgpu::BindGroupLayout,
    eval: wgpu::ComputePipeline,
    /// The per-sample passes' pipelines ([`crate::passes`]).
    pub(crate) passes: crate::passes::Pipelines,
    /// The layout every kernel uses, and the WGSL the kernels were compiled from (for the
    /// pipelines of the kernels specialised to a model, [`GpuScene::specialise`]).
    pipeline_layout: wgpu::PipelineLayout,
    source: String,
    /// How the scenes' hash tables are held ([`TableFormat`]); the pipelines are compiled for it.
    tables: TableFormat,
    /// Samples per invocation of the per-sample passes ([`with_lanes`]).
    lanes: u32,
    /// Whether the device writes timestamps at pass boundaries (the pass-by-pass profile).
    pub(crate) timestamps: bool,
    /// Bound at bindings 7-10 by `eval_points`, which uses none of them.
    pub(crate) placeholders: crate::passes::Placeholders,
}

impl std::ops::Deref for GpuContext {
    type Target = crate::device::GpuDevice;

    fn deref(&self) -> &crate::device::GpuDevice {
        &self.gpu
    }
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuContext({})", self.adapter_name())
    }
}

/// Which kernel a dispatch runs (the per-sample passes run through
/// [`GpuContext::render_passes`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// `eval_points`: one field evaluation per invocation.
    EvalPoints,
}

impl GpuContext {
    /// Opens the best adapter `policy` allows (discrete, integrated, virtual, other, then
    /// software), or says why none can be used.
    pub fn open(policy: AdapterPolicy) -> Result<Self, GpuError> {
        Self::open_with_tables(policy, TableFormat::F32)
    }

    /// [`GpuContext::open`] with the hash tables of its scenes held in `tables`' format.
    pub fn open_with_tables(policy: AdapterPolicy, tables: TableFormat) -> Result<Self, GpuError> {
        Self::open_with_kernels(policy, tables, None)
    }

    /// [`GpuContext::open_with_tables`] with the per-sample passes evaluating `lanes` samples
    /// per invocation (1, 2 or 4; `None`: [`DEFAULT_LANES`]). The frames are the same whatever
    /// the lanes; the speed is not (see [`DEFAULT_LANES`]).
    pub fn open_with_kernels(
        policy: AdapterPolicy,
        tables: TableFormat,
        lanes: Option<u32>,
    ) -> Result<Self, GpuError> {
        let source = with_lanes(RENDER_WGSL, lanes.unwrap_or(DEFAULT_LANES))?;
        Self::with_adapter(pick_adapter(policy)?, &source, tables)
    }

    /// [`GpuContext::open`] with another WGSL source of the same entry points and bindings (a
    /// benchmark's older version of `render.wgsl`, to time old kernels against new ones), its
    /// tables f32 (an older source has no "Hash tables" region to replace).
    pub fn open_with_source(policy: AdapterPolicy, wgsl: &str) -> Result<Self, GpuError> {
        Self::with_adapter(pick_adapter(policy)?, wgsl, TableFormat::F32)
    }

    fn with_adapter(
        adapter: wgpu::Adapter,
        wgsl: &str,
        tables: TableFormat,
    ) -> Result<Self, GpuError> {
        let source = tables.source(wgsl).ok_or_else(|| {
            GpuError::Shader(format!(
                "the shader has no \"Hash tables\" region to hold {} tables",
                tables.name()
            ))
        })?;
        let wgsl = source.as_str();
        // Timestamp queries where the adapter has them: only the pass-by-pass profile
        // (`MSTH_GPU_PASS_PROFILE`) writes any.
        let gpu = crate::device::GpuDevice::open(adapter, "msth", wgpu::Features::TIMESTAMP_QUERY)?;
        let device = &gpu.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("render.wgsl"),
            source: wgpu::ShaderSource::Wgsl(wgsl.into()),
        });
        let storage = |binding: u32, read_only: bool| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let uniform = |binding: u32| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("msth render bindings"),
            entries: &[
                uniform(0),
                uniform(1),
                storage(2, true),
                storage(3, true),
                storage(4, true),
                storage(5, true),
                storage(6, false),
                storage(7, false),
                storage(8, false),
                uniform(9),
                storage(10, true),
            ],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("msth render"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = |entry: &str| {
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: Some(&pl),
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
        };
        let eval = pipeline("eval_points");
        let passes = crate::passes::Pipelines::new(wgsl, pipeline);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader(e.to_string()));
        }
        let placeholders = crate::passes::Placeholders::new(device);
        let timestamps = gpu.features.contains(wgpu::Features::TIMESTAMP_QUERY);
        Ok(GpuContext {
            gpu,
            layout,
            eval,
            passes,
            pipeline_layout: pl,
            lanes: lanes_of(&source),
            timestamps,
            source,
            tables,
            placeholders,
        })
    }

    /// How this context's scenes hold their hash tables.
    pub fn tables(&self) -> TableFormat {
        self.tables
    }

    /// Samples one invocation of the per-sample passes evaluates ([`with_lanes`]).
    pub fn lanes(&self) -> u32 {
        self.lanes
    }

    /// Bytes of scratch a batch of a frame's rays takes by default on this adapter
    /// ([`GpuContext::frame_scratch_within`]): [`DISCRETE_FRAME_WORK_BYTES`] on a discrete GPU,
    /// [`crate::FRAME_WORK_BYTES`] elsewhere (integrated GPUs share the host's memory; software
    /// adapters gain nothing from larger batches).
    pub fn default_scratch_budget(&self) -> u64 {
        if self.info.device_type == wgpu::DeviceType::DiscreteGpu {
            DISCRETE_FRAME_WORK_BYTES
        } else {
            crate::FRAME_WORK_BYTES
        }
    }

    /// The most bytes a play-time volume may take on this device by default: a quarter of the
    /// smaller of its buffer limits (one buffer and one binding hold the volume's values).
    pub fn volume_budget(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
            / 4
    }

    /// Whether the adapter is a software rasteriser (lavapipe, WARP).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Whether the adapter is Mesa's llvmpipe-based Vulkan driver (lavapipe), which ends every loop
    /// of an invocation after [`layout::LAVAPIPE_LOOP_ITERATIONS`] iterations in total.
    pub fn is_lavapipe(&self) -> bool {
        self.is_software() && self.info.name.contains("llvmpipe")
    }

    /// A storage buffer with `data` (at least 4 bytes: empty data gets a placeholder word).
    pub fn storage_buffer(
        &self,
        what: &str,
        data: &[u8],
        writable: bool,
    ) -> Result<wgpu::Buffer, GpuError> {
        let bytes = data.len().max(4) as u64;
        self.check_storage(what, bytes)?;
        let mut usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        if writable {
            usage |= wgpu::BufferUsages::COPY_SRC;
        }
        let contents: &[u8] = if data.is_empty() { &[0; 4] } else { data };
        Ok(self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(what),
                contents,
                usage,
            }))
    }

    /// A zeroed read-only storage buffer of `bytes` bytes, filled later with `GpuContext::write`
    /// or the queue.
    pub fn storage_buffer_sized(&self, what: &str, bytes: u64) -> Result<wgpu::Buffer, GpuError> {
        self.check_storage(what, bytes)?;
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }))
    }

    /// An output buffer of `n` `vec4<f32>`.
    pub fn output_buffer(&self, what: &str, n: usize) -> Result<wgpu::Buffer, GpuError> {
        let bytes = (n.max(1) * 16) as u64;
        self.check_storage(what, bytes)?;
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        }))
    }

    /// Runs `kernel` for `view.size[2]` invocations over `scene`, reading `list` and writing
    /// `out`; waits for it to finish.
    pub fn dispatch(
        &self,
        kernel: Kernel,
        scene: &GpuScene,
        view: &ViewU,
        list: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let count = view.size[2];
        if count == 0 {
            return Ok(());
        }
        let max = self.limits.max_compute_workgroups_per_dimension;
        let (gx, gy) = layout::dispatch_size(count, max).ok_or_else(|| GpuError::Limit {
            what: format!("a dispatch of {count} invocations"),
            amount: count as u64,
            unit: "invocations",
            limit: "max_compute_workgroups_per_dimension (squared, times 64)",
            max: max as u64 * max as u64 * layout::WORKGROUP as u64,
        })?;
        let view_buf = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("view"),
                contents: bytemuck::bytes_of(view),
                usage: wgpu::BufferUsages::UNIFORM,
            });
        let entries = [
            scene.model.as_entire_binding(),
            view_buf.as_entire_binding(),
            scene.tab3.as_entire_binding(),
            scene.tab4.as_entire_binding(),
            scene.rest.as_entire_binding(),
            list.as_entire_binding(),
            out.as_entire_binding(),
            self.placeholders.work.as_entire_binding(),
            self.placeholders.ctrl.as_entire_binding(),
            self.placeholders.pass.as_entire_binding(),
            self.placeholders.occupancy.as_entire_binding(),
        ];
        let entries: Vec<wgpu::BindGroupEntry> = entries
            .into_iter()
            .enumerate()
            .map(|(i, resource)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource,
            })
            .collect();
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let bg = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("msth render"),
            layout: &self.layout,
            entries: &entries,
        });
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(match kernel {
                Kernel::EvalPoints => &self.eval,
            });
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        self.queue.submit([enc.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(e.to_string()));
        }
        self.wait()?;
        self.check_state()
    }

    pub(crate) fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| GpuError::Backend(format!("waiting for the device: {e}")))
    }

    /// Reads the first `n` `vec4<f32>` of `buf` back.
    pub fn read_vec4(&self, buf: &wgpu::Buffer, n: usize) -> Result<Vec<[f32; 4]>, GpuError> {
        self.read_vec4_with(buf, n, &mut ReadBack::default(), |v| v.to_vec())
    }

    /// Reads the first `n` `vec4<f32>` of `buf` back through `staging` (made or grown here,
    /// kept for the next read) and hands them to `f` where they lie, without a copy: a player
    /// reading a 1352x1014 frame every frame neither allocates 22 MB of mapped memory each
    /// time nor copies it before converting it.
    pub fn read_vec4_with<R>(
        &self,
        buf: &wgpu::Buffer,
        n: usize,
        staging: &mut ReadBack,
        f: impl FnOnce(&[[f32; 4]]) -> R,
    ) -> Result<R, GpuError> {
        if n == 0 {
            return Ok(f(&[]));
        }
        let bytes = (n * 16) as u64;
        if staging.buffer.as_ref().is_none_or(|b| b.size() < bytes) {
            staging.buffer = None;
            staging.buffer = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        let staging = staging.buffer.as_ref().expect("made above");
        let mut enc = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        enc.copy_buffer_to_buffer(buf, 0, staging, 0, bytes);
        self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, ..bytes, move |r| {
            let _ = tx.send(r);
        });
        self.wait()?;
        match rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(GpuError::Backend(format!("reading results back: {e}"))),
            Err(_) => return Err(GpuError::Backend("reading results back: no answer".into())),
        }
        // Unmapped whatever happens, so that the next read can map it again.
        let out = self.check_state().and_then(|()| {
            let view = staging
                .get_mapped_range(..bytes)
                .map_err(|e| GpuError::Backend(format!("reading results back: {e}")))?;
            Ok(f(bytemuck::cast_slice::<u8, [f32; 4]>(&view)))
        });
        staging.unmap();
        out
    }

    /// Writes `data` at the start of `buf`.
    pub fn write(&self, buf: &wgpu::Buffer, data: &[u8]) {
        if !data.is_empty() {
            self.queue.write_buffer(buf, 0, data);
        }
    }
}

/// Checks that `words` are the bit words of an occupancy grid of resolution `r` (format.md §6.5).
pub fn check_occupancy(r: u32, words: &[u32]) -> Result<(), GpuError> {
    let cells = (r as u64).pow(3);
    if r == 0 || words.len() as u64 != cells.div_ceil(32) {
        return Err(GpuError::Input(format!(
            "an occupancy grid of resolution {r} needs {} words, not {}",
            cells.div_ceil(32),
            words.len()
        )));
    }
    Ok(())
}

/// Whether two runs of values hold the same bits (a memory comparison; unlike `==` on floats, a
/// NaN equals itself and -0 differs from 0, as for an upload).
fn same_bits(a: &[f32], b: &[f32]) -> bool {
    bytemuck::cast_slice::<f32, u32>(a) == bytemuck::cast_slice::<f32, u32>(b)
}

/// Writes both fields' hash tables from `params` into the `tab3` and `tab4` buffers
/// ([`crate::layout::ParamSplit::tables`]), those for which `which(buffer, part)` holds (buffer
/// 0 `tab3`, 1 `tab4`; part 0 the field's table, 1 the proposal field's).
fn write_tables(
    ctx: &GpuContext,
    split: &ParamSplit,
    bufs: [&wgpu::Buffer; 2],
    params: &[f32],
    which: impl Fn(usize, usize) -> bool,
    clamped: &mut [[usize; 2]; 2],
) {
    let format = ctx.tables;
    for (b, (buf, parts)) in bufs.into_iter().zip(split.tables()).enumerate() {
        for (p, (_, at, r)) in parts.into_iter().enumerate() {
            if !r.is_empty() && which(b, p) {
                let values = &params[r];
                clamped[b][p] = format.clamped(values);
                let data = format.encode(values);
                ctx.queue.write_buffer(buf, format.byte_offset(at), &data);
            }
        }
    }
}

/// A staging buffer kept between reads ([`GpuContext::read_vec4_with`]).
#[derive(Debug, Default)]
pub struct ReadBack {
    buffer: Option<wgpu::Buffer>,
}

/// One model on the device: its `Model` uniform, the three parameter buffers and the file's
/// occupancy grid.
pub struct GpuScene {
    pub gpu_model: GpuModel,
    pub(crate) model: wgpu::Buffer,
    pub(crate) tab3: wgpu::Buffer,
    pub(crate) tab4: wgpu::Buffer,
    pub(crate) rest: wgpu::Buffer,
    /// The occupancy grid's words (a placeholder word without one).
    pub(crate) occupancy: wgpu::Buffer,
    /// Its resolution `R`; 0: no grid, the passes evaluate every sample.
    pub(crate) occupancy_resolution: u32,
    /// The parameters last uploaded (to notice a new chunk).
    uploaded: Vec<f32>,
    /// The passes that evaluate fields, specialised to this scene ([`GpuScene::specialise`]);
    /// `None`: the context's generic ones.
    pub(crate) mlps: Option<crate::passes::MlpPipelines>,
    /// Per table buffer and part ([`ParamSplit::tables`]): the values of the last upload that
    /// the table format clamped ([`TableFormat::clamped`]).
    clamped: [[usize; 2]; 2],
    /// The most values clamped at once since the scene was created.
    most_clamped: usize,
}

impl GpuScene {
    /// Uploads `params` (the flat buffer of `gpu_model`'s config).
    pub fn new(ctx: &GpuContext, gpu_model: GpuModel, params: &[f32]) -> Result<Self, GpuError> {
        let split = gpu_model.split.clone();
        if params.len() != split.rest.end {
            return Err(GpuError::Model(format!(
                "the parameter buffer holds {} values; the model's layout needs {}",
                params.len(),
                split.rest.end
            )));
        }
        let bytes =
            |r: &std::ops::Range<usize>| bytemuck::cast_slice::<f32, u8>(&params[r.clone()]);
        let [(n3, s3), (n4, s4), (nr, _)] = gpu_model.buffer_sizes(ctx.tables);
        let tab3 = ctx.storage_buffer_sized(n3, s3)?;
        let tab4 = ctx.storage_buffer_sized(n4, s4)?;
        let mut clamped = [[0; 2]; 2];
        write_tables(
            ctx,
            &split,
            [&tab3, &tab4],
            params,
            |_, _| true,
            &mut clamped,
        );
        let rest = ctx.storage_buffer(nr, bytes(&split.rest), false)?;
        let model = ctx
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("model"),
                contents: bytemuck::bytes_of(&gpu_model.model),
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            });
        let occupancy = ctx.storage_buffer("no occupancy grid", &[], false)?;
        ctx.check_state()?;
        Ok(GpuScene {
            gpu_model,
            model,
            tab3,
            tab4,
            rest,
            occupancy,
            occupancy_resolution: 0,
            uploaded: params.to_vec(),
            mlps: None,
            clamped,
            most_clamped: clamped.iter().flatten().sum(),
        })
    }

    /// The most hash-table values the device held clamped at once since the scene was created:
    /// with [`TableFormat::F16`], values beyond ±65504, which the kernels read as ±65504 (the
    /// frames then differ from the CPU renderer's; f32 tables hold them as they are).
    pub fn clamped_table_values(&self) -> usize {
        self.most_clamped
    }

    /// Uses the file's occupancy grid (docs/format.md §6.5: `resolution` cells per axis, the bit
    /// words) to skip the main field in empty cells in the per-sample passes' frames, or none
    /// (every sample evaluated). The sample cache of incremental playback evaluates every
    /// sample, as the CPU renderer's sample cache does.
    pub fn set_occupancy(
        &mut self,
        ctx: &GpuContext,
        grid: Option<(u32, &[u32])>,
    ) -> Result<(), GpuError> {
        match grid {
            None => {
                self.occupancy = ctx.storage_buffer("no occupancy grid", &[], false)?;
                self.occupancy_resolution = 0;
            }
            Some((r, words)) => {
                check_occupancy(r, words)?;
                self.occupancy =
                    ctx.storage_buffer("occupancy grid", bytemuck::cast_slice(words), false)?;
                self.occupancy_resolution = r;
            }
        }
        Ok(())
    }

    /// Compiles the passes that evaluate fields (`pass_proposal`, `pass_density`, `pass_color`,
    /// and `pass_dynamic` of the sample cache) with this scene's level values and MLP weights as
    /// constants ([`crate::specialise`]), which the frames then use. `Ok(Err(why))`: the model
    /// is not specialised (MLPs too large, a weight not finite, or the device refused the
    /// shader) and the generic passes stay; `Ok(Ok(seconds))`: the time it took to create them (a driver may compile later, at
    /// the first dispatch: lavapipe does). New MLP weights ([`GpuScene::update`]) drop them again.
    pub fn specialise(
        &mut self,
        ctx: &GpuContext,
    ) -> Result<Result<f64, crate::specialise::SpecialiseError>, GpuError> {
        let t = std::time::Instant::now();
        let rest = &self.uploaded[self.gpu_model.split.rest.clone()];
        let source = match crate::specialise::specialise_wgsl(&ctx.source, &self.gpu_model, rest) {
            Ok(s) => s,
            Err(e) => return Ok(Err(e)),
        };
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = ctx
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("render.wgsl, specialised to the model"),
                source: wgpu::ShaderSource::Wgsl(source.as_str().into()),
            });
        let mlps = crate::passes::MlpPipelines::new(&source, |entry| {
            ctx.device
                .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(entry),
                    layout: Some(&ctx.pipeline_layout),
                    module: &module,
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    cache: None,
                })
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            // The generic kernels still work: say why they stay, as for a model too large.
            let first = e.to_string();
            let first = first
                .lines()
                .find(|l| l.contains("error"))
                .unwrap_or(&first);
            return Ok(Err(crate::specialise::SpecialiseError::Compile(
                first.trim().to_string(),
            )));
        }
        ctx.check_state()?;
        self.mlps = Some(mlps);
        Ok(Ok(t.elapsed().as_secs_f64()))
    }

    /// Drops the specialised pipelines: the frames use the generic passes again.
    pub fn mlps_generic(&mut self) {
        self.mlps = None;
    }

    /// Whether the frames use passes specialised to this scene ([`GpuScene::specialise`]).
    pub fn is_specialised(&self) -> bool {
        self.mlps.is_some()
    }

    /// The occupancy grid's resolution in use (0: none).
    pub fn occupancy_resolution(&self) -> u32 {
        self.occupancy_resolution
    }

    /// Uploads the parts of `params` that differ from the last upload, bit for bit: the field's
    /// 3D table, its 4D table and the rest (proposal tables, mask, MLPs) apart, so that a new
    /// time chunk, which changes the 4D table alone, sends that table and not the whole buffer.
    /// `true` when anything changed.
    pub fn update(&mut self, ctx: &GpuContext, params: &[f32]) -> Result<bool, GpuError> {
        if params.len() != self.uploaded.len() {
            return Err(GpuError::Model(format!(
                "the parameter buffer changed size from {} to {} values",
                self.uploaded.len(),
                params.len()
            )));
        }
        let split = self.gpu_model.split.clone();
        let [field3, field4] = split.tables().map(|parts| parts[0].2.clone());
        let differs =
            |r: &std::ops::Range<usize>| !same_bits(&params[r.clone()], &self.uploaded[r.clone()]);
        let (d3, d4, drest) = (differs(&field3), differs(&field4), differs(&split.rest));
        if !(d3 || d4 || drest) {
            return Ok(false);
        }
        if drest {
            // New MLP weights (a model's are the same at every time; this is another model's
            // buffer): the specialised pipelines no longer apply.
            let at = split.rest.start;
            if split
                .mlps
                .iter()
                .any(|r| differs(&(at + r.start..at + r.end)))
            {
                self.mlps = None;
            }
            ctx.write(
                &self.rest,
                bytemuck::cast_slice(&params[split.rest.clone()]),
            );
        }
        // The field's tables where they changed; the proposal field's (which lie in the rest
        // and are read from the table buffers) with the rest.
        let field = [d3, d4];
        write_tables(
            ctx,
            &split,
            [&self.tab3, &self.tab4],
            params,
            |b, p| if p == 0 { field[b] } else { drest },
            &mut self.clamped,
        );
        self.most_clamped = self.most_clamped.max(self.clamped.iter().flatten().sum());
        for (r, d) in [(field3, d3), (field4, d4), (split.rest, drest)] {
            if d {
                self.uploaded[r.clone()].copy_from_slice(&params[r]);
            }
        }
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `with_lanes` rewrites the one `LANES` line of the kernels, and refuses other counts.
    #[test]
    fn lanes_rewrite_the_kernels_constant() {
        assert_eq!(lanes_of(RENDER_WGSL), 4);
        for lanes in [1u32, 2, 4] {
            let s = with_lanes(RENDER_WGSL, lanes).unwrap();
            assert_eq!(lanes_of(&s), lanes);
            assert_eq!(s.matches("const LANES: u32 = ").count(), 1);
            assert_eq!(s.len(), RENDER_WGSL.len());
        }
        assert_eq!(with_lanes(RENDER_WGSL, 4).unwrap(), RENDER_WGSL);
        for bad in [0u32, 3, 8] {
            let e = with_lanes(RENDER_WGSL, bad).unwrap_err();
            assert!(e.to_string().contains("1, 2 or 4"), "{e}");
        }
        // A source that does not set LANES as the kernels do is refused, not compiled as is.
        let other = RENDER_WGSL.replace(LANES_LINE, "const LANES: u32 = 4u; // four\n");
        assert!(matches!(with_lanes(&other, 1), Err(GpuError::Shader(_))));
    }
}
