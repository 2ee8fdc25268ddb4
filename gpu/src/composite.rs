//! Volume rendering (compositing) for training on the device, forward and backward:
//! `msth_core::render`'s `weights`, `composite` and `weights_backward` over a batch of rays,
//! one workgroup per ray and one invocation per sample, the sums along a ray as scans in
//! workgroup memory (chunks of 64 samples with a carry); checked against the CPU in
//! `tests/composite.rs`.
//!
//! Samples are ray-major: ray `r` owns samples `offsets[r] .. offsets[r + 1]` of every
//! per-sample buffer (`(sigma, delta)` pairs, `rgb` triples, weights), so rays of any length
//! (the proposal's 128 samples, the field's 48, fewer after culling) share one dispatch.

use bytemuck::{Pod, Zeroable};

use crate::device::ComputeDevice;
use crate::mlp::need_floats;
use crate::GpuError;

/// Per-ray scans (binding 1: the rays' offsets), before every per-ray kernel.
pub const RAY_SCAN_WGSL: &str = include_str!("../shaders/ray_scan.wgsl");
/// The common part of both compositing kernels (uniform, bindings 2-3, `tau_of`).
pub const COMPOSITE_WGSL: &str = include_str!("../shaders/composite.wgsl");
/// The forward entry point `composite_forward` (after [`COMPOSITE_WGSL`]).
pub const COMPOSITE_FORWARD_WGSL: &str = include_str!("../shaders/composite_forward.wgsl");
/// The backward entry point `composite_backward` (after [`COMPOSITE_WGSL`]).
pub const COMPOSITE_BACKWARD_WGSL: &str = include_str!("../shaders/composite_backward.wgsl");

/// Invocations per workgroup (= per ray).
const RAY_GROUP: u64 = 64;

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct CompositeU {
    run: [u32; 4],
    bg: [f32; 4],
}

/// A batch of rays on the device: their sample ranges and count.
pub struct GpuRays {
    offsets: wgpu::Buffer,
    rays: usize,
    samples: usize,
}

impl GpuRays {
    /// `offsets`: `rays + 1` non-decreasing sample indices starting at 0 (ray `r` owns samples
    /// `offsets[r] .. offsets[r + 1]`).
    pub fn new(dev: &ComputeDevice, offsets: &[u32]) -> Result<Self, GpuError> {
        let ok = offsets.first() == Some(&0) && offsets.windows(2).all(|p| p[0] <= p[1]);
        if !ok {
            return Err(GpuError::Input(
                "ray offsets must start at 0 and never decrease".into(),
            ));
        }
        Ok(GpuRays {
            offsets: dev.buffer_f32("ray offsets", bytemuck::cast_slice(offsets))?,
            rays: offsets.len() - 1,
            samples: *offsets.last().unwrap_or(&0) as usize,
        })
    }

    pub fn rays(&self) -> usize {
        self.rays
    }

    pub fn samples(&self) -> usize {
        self.samples
    }

    /// The offsets buffer (binding 1 of every per-ray kernel).
    pub fn offsets(&self) -> &wgpu::Buffer {
        &self.offsets
    }
}

const FLAG_EXTRA_DW: u32 = 1;
const FLAG_RAY_BG: u32 = 2;
const FLAG_LAST_SAMPLE: u32 = 4;
const FLAG_HIDE: u32 = 8;

/// How a batch's rays meet their background, and which colours count (the training step's
/// choices; [`CompositeMode::color`] is plain compositing over one colour).
#[derive(Clone, Copy, Debug)]
pub struct CompositeMode<'a> {
    pub bg: [f32; 3],
    /// A background per ray (4 floats each, rgb used) instead of `bg`. The forward reads it;
    /// the backward reads `d_T = dC . bg` from each ray's 4th `d_color` float instead (the
    /// colour loss writes it there: [`crate::losses::ColorLossKernel::run`]).
    pub ray_bg: Option<&'a wgpu::Buffer>,
    /// The last sample's colour as the background (`Background::LastSample`).
    pub last_sample: bool,
    /// Samples behind this optical depth get colour 0 and no colour gradient, as the CPU
    /// trainer, which evaluates no colour behind `HIDDEN_TRANSMITTANCE`.
    pub hide_beyond: Option<f32>,
}

impl CompositeMode<'_> {
    /// Over one background colour, every colour counted.
    pub fn color(bg: [f32; 3]) -> Self {
        CompositeMode {
            bg,
            ray_bg: None,
            last_sample: false,
            hide_beyond: None,
        }
    }

    fn uniform(&self, rays: &GpuRays, extra_dw: bool) -> CompositeU {
        let flag = |on: bool, f: u32| if on { f } else { 0 };
        let flags = flag(extra_dw, FLAG_EXTRA_DW)
            | flag(self.ray_bg.is_some(), FLAG_RAY_BG)
            | flag(self.last_sample, FLAG_LAST_SAMPLE)
            | flag(self.hide_beyond.is_some(), FLAG_HIDE);
        CompositeU {
            run: [rays.rays as u32, flags, 0, 0],
            bg: [
                self.bg[0],
                self.bg[1],
                self.bg[2],
                self.hide_beyond.unwrap_or(0.0),
            ],
        }
    }
}

/// The compiled compositing kernels of one device.
pub struct CompositeKernels {
    forward_layout: wgpu::BindGroupLayout,
    backward_layout: wgpu::BindGroupLayout,
    forward: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
    unused: wgpu::Buffer,
}

/// The per-sample and per-ray buffers of one batch: `(sigma, delta)` and `rgb` in, weights and
/// `(r, g, b, T_N)` per ray out of the forward.
pub struct CompositeBuffers<'a> {
    pub sigma_delta: &'a wgpu::Buffer,
    pub rgb: &'a wgpu::Buffer,
    pub weights: &'a wgpu::Buffer,
    pub ray_out: &'a wgpu::Buffer,
}

impl CompositeKernels {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // Forward: 1 offsets, 2 (sigma, delta), 3 rgb, 4 w, 5 (C, T_N) per ray, 6 bg per ray.
        let forward_layout =
            dev.bind_layout("composite forward", &[true, true, true, false, false, true]);
        // Backward: 1-3 as the forward, 4 w, 5 (C, T_N), 6 dC, 7 extra d_w, 8 d per sample.
        let backward_layout = dev.bind_layout(
            "composite backward",
            &[true, true, true, true, true, true, true, false],
        );
        let forward = dev.pipeline(
            "composite forward",
            &format!("{RAY_SCAN_WGSL}\n{COMPOSITE_WGSL}\n{COMPOSITE_FORWARD_WGSL}"),
            "composite_forward",
            &forward_layout,
        )?;
        let backward = dev.pipeline(
            "composite backward",
            &format!("{RAY_SCAN_WGSL}\n{COMPOSITE_WGSL}\n{COMPOSITE_BACKWARD_WGSL}"),
            "composite_backward",
            &backward_layout,
        )?;
        Ok(CompositeKernels {
            forward_layout,
            backward_layout,
            forward,
            backward,
            unused: dev.zeros_f32("unused", 4)?,
        })
    }

    fn check(rays: &GpuRays, b: &CompositeBuffers) -> Result<(), GpuError> {
        let n = rays.samples;
        need_floats("(sigma, delta)", b.sigma_delta, 2 * n as u64, n)?;
        need_floats("rgb", b.rgb, 3 * n as u64, n)?;
        need_floats("weights", b.weights, n as u64, n)?;
        need_floats("per-ray output", b.ray_out, 4 * rays.rays as u64, n)
    }

    /// Weights `w` per sample and `(C, T_N)` per ray, over background `bg`.
    pub fn forward(
        &self,
        dev: &ComputeDevice,
        rays: &GpuRays,
        b: &CompositeBuffers,
        bg: [f32; 3],
    ) -> Result<(), GpuError> {
        self.forward_with(dev, rays, b, &CompositeMode::color(bg))
    }

    /// [`CompositeKernels::forward`] with the background and hiding of `mode`.
    pub fn forward_with(
        &self,
        dev: &ComputeDevice,
        rays: &GpuRays,
        b: &CompositeBuffers,
        mode: &CompositeMode,
    ) -> Result<(), GpuError> {
        Self::check(rays, b)?;
        if let Some(bg) = mode.ray_bg {
            need_floats("backgrounds", bg, 4 * rays.rays as u64, rays.samples)?;
        }
        let u = mode.uniform(rays, false);
        dev.run(
            &self.forward,
            &self.forward_layout,
            bytemuck::bytes_of(&u),
            &[
                &rays.offsets,
                b.sigma_delta,
                b.rgb,
                b.weights,
                b.ray_out,
                mode.ray_bg.unwrap_or(&self.unused),
            ],
            rays.rays as u64 * RAY_GROUP,
        )
    }

    /// Backward of [`CompositeKernels::forward`] (whose outputs `b` holds): from `d_color`
    /// (`(dC, unused)` per ray) and optionally an extra d loss / d w per sample, writes
    /// `(d sigma, d rgb)` per sample into `d_sample` (4 floats each).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        dev: &ComputeDevice,
        rays: &GpuRays,
        b: &CompositeBuffers,
        bg: [f32; 3],
        d_color: &wgpu::Buffer,
        d_w_extra: Option<&wgpu::Buffer>,
        d_sample: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        self.backward_with(
            dev,
            rays,
            b,
            &CompositeMode::color(bg),
            d_color,
            d_w_extra,
            d_sample,
        )
    }

    /// [`CompositeKernels::backward`] with the background and hiding of `mode` (the forward's).
    #[allow(clippy::too_many_arguments)]
    pub fn backward_with(
        &self,
        dev: &ComputeDevice,
        rays: &GpuRays,
        b: &CompositeBuffers,
        mode: &CompositeMode,
        d_color: &wgpu::Buffer,
        d_w_extra: Option<&wgpu::Buffer>,
        d_sample: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        Self::check(rays, b)?;
        let n = rays.samples;
        need_floats("d_color", d_color, 4 * rays.rays as u64, n)?;
        need_floats("d_sample", d_sample, 4 * n as u64, n)?;
        if let Some(e) = d_w_extra {
            need_floats("extra d_w", e, n as u64, n)?;
        }
        let u = mode.uniform(rays, d_w_extra.is_some());
        dev.run(
            &self.backward,
            &self.backward_layout,
            bytemuck::bytes_of(&u),
            &[
                &rays.offsets,
                b.sigma_delta,
                b.rgb,
                b.weights,
                b.ray_out,
                d_color,
                d_w_extra.unwrap_or(&self.unused),
                d_sample,
            ],
            rays.rays as u64 * RAY_GROUP,
        )
    }
}
