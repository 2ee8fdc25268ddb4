//! The play-time volume on the device: a baked [`Volume`] (msth-core) uploaded once, its time
//! slices bound as frames need them, and frames drawn by the `volume_march` kernel
//! ([`crate::VOLUME_WGSL`], one invocation per pixel; the page runs the same text).
//!
//! The kernel is msth-core's march (`volume::march`) for a volume whose colour is baked
//! ([`ColourMode::Baked`]) and whose dynamic bricks have their slices: it never evaluates the
//! field. A frame whose slices are not baked yet is the caller's to bake first (the players do,
//! as the CPU renderer does) or to draw from the exact field.
//!
//! # Buffers
//! - `words` (`u32`): the brick index, the static slots' cell bits, the dynamic bricks'
//!   dynamic-cell bits, then two regions of slice cell bits (A and B);
//! - `values` (`vec2<u32>` per vertex: density pre-activation, red, green, blue as binary16,
//!   the volume's own [`msth_core::volume::Value`]s): the static slots, then two regions of
//!   slice values.
//!
//! A frame at time `t` reads the two slices around `t` ([`Volume::slices_for`]): each is kept in
//! a region until another slice needs it, so a playback moving forward uploads one slice per
//! slice interval.

use half::slice::HalfFloatSliceExt;
use msth_core::volume::march::TimeSlices;
use msth_core::volume::{ColourMode, MarchSettings, Volume};
use wgpu::util::DeviceExt;

use crate::layout::{dispatch_size, WORKGROUP};
use crate::render::{GpuContext, GpuError, GpuScene};
use crate::{ViewU, VOLUME_WGSL};

/// The `VolumeU` uniform of `volume.wgsl`, byte for byte.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct VolumeU {
    pub geom: [u32; 4],
    pub words: [u32; 4],
    pub values: [u32; 4],
    pub march: [f32; 4],
}

/// The compiled `volume_march` kernel and its bindings (model, view, pixel list, frame, the
/// volume).
pub struct VolumeKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    /// The pixel list's placeholder: the native player draws every pixel (no list flag).
    no_list: wgpu::Buffer,
}

impl VolumeKernel {
    /// Compiles the kernel on `ctx`'s device.
    pub fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        let device = &ctx.device;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("volume.wgsl"),
            source: wgpu::ShaderSource::Wgsl(VOLUME_WGSL.into()),
        });
        let entry = |binding: u32, ty: wgpu::BufferBindingType| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let read = wgpu::BufferBindingType::Storage { read_only: true };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("msth volume bindings"),
            entries: &[
                entry(0, wgpu::BufferBindingType::Uniform),
                entry(1, wgpu::BufferBindingType::Uniform),
                entry(5, read),
                entry(6, wgpu::BufferBindingType::Storage { read_only: false }),
                entry(7, wgpu::BufferBindingType::Uniform),
                entry(8, read),
                entry(9, read),
            ],
        });
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("msth volume"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("volume_march"),
            layout: Some(&pl),
            module: &module,
            entry_point: Some("volume_march"),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader(e.to_string()));
        }
        let no_list = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("no pixel list"),
            contents: &[0; 4],
            usage: wgpu::BufferUsages::STORAGE,
        });
        Ok(VolumeKernel {
            layout,
            pipeline,
            no_list,
        })
    }
}

/// Bytes [`GpuVolume::new`] allocates for `vol` on the device: both buffers, with two slice
/// regions when it has dynamic bricks.
pub fn device_bytes(vol: &Volume) -> u64 {
    let (w, v) = buffer_lengths(vol);
    w as u64 * 4 + v as u64 * 8
}

/// Lengths of the `words` (u32) and `values` (vertices of four binary16 values) buffers for
/// `vol`.
fn buffer_lengths(vol: &Volume) -> (usize, usize) {
    let g = vol.geometry;
    let fw = g.flag_words();
    let nv = g.vertices_per_brick();
    let nd = vol.dynamic.bricks.len();
    let words = vol.index.len() + vol.slots() * fw + 3 * nd * fw;
    let values = vol.slots() * nv + 2 * nd * nv;
    (words, values)
}

/// Invocations `volume_march` needs for a whole `w x h` frame: one workgroup per 8x8 tile (the
/// shader's `TILE`), the tiles on the right and bottom edges padded.
pub fn tile_invocations(w: u32, h: u32) -> u32 {
    const TILE: u32 = 8;
    w.div_ceil(TILE)
        .saturating_mul(h.div_ceil(TILE))
        .saturating_mul(TILE * TILE)
}

/// Points one dispatch of [`eval_points`] evaluates at most.
const EVAL_BATCH: usize = 1 << 20;

/// Evaluates `scene`'s fields at `points` (8 values each, the `eval_points` kernel's layout:
/// unit point and time, direction, kind; `points.wgsl`) in batches; returns one `vec4` per
/// point. The play-time volume's bake asks for kinds 2 and 3 (the density pre-activation and the
/// colour, under the renderer's static cutoff or with no 4D lookup).
pub fn eval_points(
    ctx: &GpuContext,
    scene: &GpuScene,
    points: &[f32],
) -> Result<Vec<[f32; 4]>, GpuError> {
    if !points.len().is_multiple_of(8) {
        return Err(GpuError::Input(format!(
            "{} values are not whole points of 8",
            points.len()
        )));
    }
    let n = points.len() / 8;
    let mut out = Vec::with_capacity(n);
    let batch = EVAL_BATCH.min(n.max(1));
    let buf = ctx.output_buffer("evaluated points", batch)?;
    let mut staging = crate::ReadBack::default();
    for chunk in points.chunks(batch * 8) {
        let m = chunk.len() / 8;
        let list = ctx.storage_buffer("points", bytemuck::cast_slice(chunk), false)?;
        let view = ViewU {
            c2w: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
            intr: [1.0; 4],
            size: [1, 1, m as u32, 0],
            time: [0.0; 4],
        };
        ctx.dispatch(crate::Kernel::EvalPoints, scene, &view, &list, &buf)?;
        ctx.read_vec4_with(&buf, m, &mut staging, |v| out.extend_from_slice(v))?;
    }
    Ok(out)
}

/// A baked volume on the device.
pub struct GpuVolume {
    words: wgpu::Buffer,
    values: wgpu::Buffer,
    uniform: VolumeU,
    /// Word and vertex offsets of the two slice regions.
    region_words: [u32; 2],
    region_values: [u32; 2],
    /// The slice each region holds.
    held: [Option<usize>; 2],
    /// Bytes on the device.
    bytes: u64,
}

/// `n` as a 32-bit offset, or the limit it exceeds.
fn offset(n: usize, what: &str) -> Result<u32, GpuError> {
    u32::try_from(n).map_err(|_| GpuError::Limit {
        what: what.to_string(),
        amount: n as u64,
        unit: "entries",
        limit: "32-bit offsets of volume.wgsl",
        max: u32::MAX as u64,
    })
}

impl GpuVolume {
    /// Uploads `vol`'s index, static slots and dynamic-cell bits; the slices follow with
    /// [`GpuVolume::bind_slices`]. Fails for a volume without baked colours (the kernel reads
    /// four values per vertex) or beyond the device's buffer limits.
    pub fn new(ctx: &GpuContext, vol: &Volume) -> Result<Self, GpuError> {
        if vol.colour != ColourMode::Baked || vol.channels != 4 {
            return Err(GpuError::Input(format!(
                "the device draws volumes with baked colours (4 values per vertex), not {:?} with {} values",
                vol.colour, vol.channels
            )));
        }
        let g = vol.geometry;
        let fw = g.flag_words();
        let nv = g.vertices_per_brick();
        let nd = vol.dynamic.bricks.len();
        let slots = vol.slots();
        let (nw, nval) = buffer_lengths(vol);
        let words_bytes = nw as u64 * 4;
        let values_bytes = nval.max(1) as u64 * 8;
        ctx.check_storage("the volume's index and cell bits", words_bytes)?;
        ctx.check_storage("the volume's vertex values", values_bytes)?;
        let at_occupied = vol.index.len();
        let at_cells = at_occupied + slots * fw;
        let at_a = at_cells + nd * fw;
        let at_b = at_a + nd * fw;
        let words = ctx.storage_buffer_sized("volume words", words_bytes)?;
        let values = ctx.storage_buffer_sized("volume values", values_bytes)?;
        let w = |at: usize, data: &[u32]| {
            if !data.is_empty() {
                ctx.queue
                    .write_buffer(&words, at as u64 * 4, bytemuck::cast_slice(data));
            }
        };
        w(0, &vol.index);
        w(at_occupied, &vol.occupied);
        w(at_cells, &vol.dynamic.cells);
        if !vol.values.is_empty() {
            ctx.queue.write_buffer(
                &values,
                0,
                bytemuck::cast_slice(vol.values.reinterpret_cast()),
            );
        }
        let uniform = VolumeU {
            geom: [g.resolution, g.brick, g.bricks_per_side(), fw as u32],
            words: [
                offset(at_occupied, "volume words")?,
                offset(at_cells, "volume words")?,
                offset(at_a, "volume words")?,
                offset(at_a, "volume words")?,
            ],
            values: [
                offset(slots * nv, "volume values")?,
                offset(slots * nv, "volume values")?,
                u32::from(nd > 0),
                0,
            ],
            march: [1.0, 0.0, 0.0, 0.0],
        };
        ctx.check_state()?;
        Ok(GpuVolume {
            words,
            values,
            uniform,
            region_words: [offset(at_a, "volume words")?, offset(at_b, "volume words")?],
            region_values: [
                offset(slots * nv, "volume values")?,
                offset((slots + nd) * nv, "volume values")?,
            ],
            held: [None, None],
            bytes: words_bytes + values_bytes,
        })
    }

    /// Bytes the volume takes on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Binds the slices `s` of `vol` (uploading those the regions do not hold); fails when one
    /// is not baked. A volume without dynamic bricks needs none.
    pub fn bind_slices(
        &mut self,
        ctx: &GpuContext,
        vol: &Volume,
        s: Option<TimeSlices>,
    ) -> Result<(), GpuError> {
        if vol.dynamic.bricks.is_empty() {
            self.uniform.march[2] = 0.0;
            return Ok(());
        }
        let Some(TimeSlices { k0, k1, f }) = s else {
            return Err(GpuError::Input(
                "the volume's time slices for this frame are not baked".into(),
            ));
        };
        let k1 = if f > 0.0 { k1 } else { k0 };
        let ra = self.region_for(ctx, vol, k0, None)?;
        let rb = if k1 == k0 {
            ra
        } else {
            self.region_for(ctx, vol, k1, Some(ra))?
        };
        self.uniform.words[2] = self.region_words[ra];
        self.uniform.words[3] = self.region_words[rb];
        self.uniform.values[0] = self.region_values[ra];
        self.uniform.values[1] = self.region_values[rb];
        self.uniform.march[2] = if k1 == k0 { 0.0 } else { f };
        Ok(())
    }

    /// The region holding slice `k`, uploaded into one (not `keep`) if none does.
    fn region_for(
        &mut self,
        ctx: &GpuContext,
        vol: &Volume,
        k: usize,
        keep: Option<usize>,
    ) -> Result<usize, GpuError> {
        if let Some(r) = self.held.iter().position(|&h| h == Some(k)) {
            return Ok(r);
        }
        let slice = vol
            .dynamic
            .slices
            .get(k)
            .and_then(|s| s.as_ref())
            .ok_or_else(|| GpuError::Input(format!("time slice {k} of the volume is not baked")))?;
        let r = match keep {
            Some(0) => 1,
            Some(_) => 0,
            None => self.held.iter().position(|h| h.is_none()).unwrap_or(0),
        };
        let g = vol.geometry;
        let nd = vol.dynamic.bricks.len();
        if slice.occupied.len() != nd * g.flag_words()
            || slice.values.len() != nd * g.vertices_per_brick() * 4
        {
            return Err(GpuError::Input(format!(
                "time slice {k} of the volume has the wrong size"
            )));
        }
        ctx.queue.write_buffer(
            &self.words,
            self.region_words[r] as u64 * 4,
            bytemuck::cast_slice(&slice.occupied),
        );
        if !slice.values.is_empty() {
            ctx.queue.write_buffer(
                &self.values,
                self.region_values[r] as u64 * 8,
                bytemuck::cast_slice(slice.values.reinterpret_cast()),
            );
        }
        self.held[r] = Some(k);
        Ok(r)
    }

    /// Draws every pixel of `view` (`size.x` by `size.y`, in 8x8 tiles) through the volume into
    /// `out` (`(r, g, b, visible depth)` per pixel) with `scene`'s model uniform, the slices last
    /// bound and `settings`; waits for it.
    pub fn render(
        &mut self,
        ctx: &GpuContext,
        kernel: &VolumeKernel,
        scene: &GpuScene,
        view: &ViewU,
        settings: &MarchSettings,
        out: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        if view.size[2] == 0 {
            return Ok(());
        }
        let count = tile_invocations(view.size[0], view.size[1]);
        let max = ctx.limits.max_compute_workgroups_per_dimension;
        let (gx, gy) = dispatch_size(count, max).ok_or_else(|| GpuError::Limit {
            what: format!("a dispatch of {count} invocations"),
            amount: count as u64,
            unit: "invocations",
            limit: "max_compute_workgroups_per_dimension (squared, times 64)",
            max: max as u64 * max as u64 * WORKGROUP as u64,
        })?;
        self.uniform.march[0] = settings.step;
        self.uniform.march[1] = settings.stop_transmittance;
        let device = &ctx.device;
        let view_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("view"),
            contents: bytemuck::bytes_of(view),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let vol_buf = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("volume uniform"),
            contents: bytemuck::bytes_of(&self.uniform),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("msth volume"),
            layout: &kernel.layout,
            entries: &[
                bind(0, &scene.model),
                bind(1, &view_buf),
                bind(5, &kernel.no_list),
                bind(6, out),
                bind(7, &vol_buf),
                bind(8, &self.words),
                bind(9, &self.values),
            ],
        });
        let mut enc =
            device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
            pass.set_pipeline(&kernel.pipeline);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        ctx.queue.submit([enc.finish()]);
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Backend(e.to_string()));
        }
        ctx.wait()?;
        ctx.check_state()
    }
}

fn bind(binding: u32, buf: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buf.as_entire_binding(),
    }
}
