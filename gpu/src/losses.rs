//! Per-ray losses on the device: the distortion loss of mip-NeRF 360
//! (`msth_core::losses::distortion`), its value per ray and its gradient with respect to the
//! weights added into a per-sample buffer (which the compositing backward takes as its extra
//! `d_w`); one workgroup per ray, one invocation per sample, the sums along the ray as scans
//! (`shaders/ray_scan.wgsl`). Checked against the CPU in `tests/composite.rs`.

use bytemuck::{Pod, Zeroable};

use crate::composite::{GpuRays, RAY_SCAN_WGSL};
use crate::device::ComputeDevice;
use crate::mlp::need_floats;
use crate::GpuError;

/// The kernel `distortion` (after [`RAY_SCAN_WGSL`]).
pub const DISTORTION_WGSL: &str = include_str!("../shaders/distortion.wgsl");

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct DistortionU {
    run: [u32; 4],
    scale: [f32; 4],
}

/// The compiled distortion-loss kernel of one device.
pub struct DistortionKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
}

impl DistortionKernel {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // 1 offsets, 2 (s_i, s_i+1) per sample, 3 w, 4 d_w (added into), 5 loss per ray.
        let layout = dev.bind_layout("distortion", &[true, true, true, false, false]);
        let pipeline = dev.pipeline(
            "distortion",
            &format!("{RAY_SCAN_WGSL}\n{DISTORTION_WGSL}"),
            "distortion",
            &layout,
        )?;
        Ok(DistortionKernel { layout, pipeline })
    }

    /// The loss of every ray (`loss`: one f32 per ray) over `intervals` (`(s_i, s_{i+1})` per
    /// sample, 2 floats) with weights `w`; adds `scale * dL/dw` into `d_w` (one per sample).
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        dev: &ComputeDevice,
        rays: &GpuRays,
        intervals: &wgpu::Buffer,
        w: &wgpu::Buffer,
        scale: f32,
        d_w: &wgpu::Buffer,
        loss: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let n = rays.samples();
        need_floats("intervals", intervals, 2 * n as u64, n)?;
        need_floats("weights", w, n as u64, n)?;
        need_floats("d_w", d_w, n as u64, n)?;
        need_floats("loss", loss, rays.rays() as u64, n)?;
        let u = DistortionU {
            run: [rays.rays() as u32, 0, 0, 0],
            scale: [scale, 0.0, 0.0, 0.0],
        };
        dev.run(
            &self.pipeline,
            &self.layout,
            bytemuck::bytes_of(&u),
            &[rays.offsets(), intervals, w, d_w, loss],
            rays.rays() as u64 * 64,
        )
    }
}
