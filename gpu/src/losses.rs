//! Per-ray losses on the device, checked against the CPU in `tests/composite.rs`:
//! - the colour loss (the trainer's mean squared error over rgb): squared error per ray and
//!   `dC` where the compositing backward reads it, one invocation per ray;
//! - the distortion loss of mip-NeRF 360 (`msth_core::losses::distortion`): its value per ray
//!   and its gradient with respect to the weights added into a per-sample buffer (which the
//!   compositing backward takes as its extra `d_w`); one workgroup per ray, one invocation per
//!   sample, the sums along the ray as scans (`shaders/ray_scan.wgsl`);
//! - the interlevel loss of mip-NeRF 360 (`msth_core::losses::interlevel`): its value per ray
//!   and its gradient with respect to the proposal weights, one workgroup per ray, one
//!   invocation per main interval (bisection into the proposal intervals) and then per proposal
//!   interval (gathering the main intervals over it: no scatter, no atomics).

use bytemuck::{Pod, Zeroable};

use crate::composite::{GpuRays, RAY_SCAN_WGSL};
use crate::device::ComputeDevice;
use crate::mlp::need_floats;
use crate::GpuError;

/// The kernel `color_loss`.
pub const COLOR_LOSS_WGSL: &str = include_str!("../shaders/color_loss.wgsl");
/// The kernel `interlevel` (after [`RAY_SCAN_WGSL`]).
pub const INTERLEVEL_WGSL: &str = include_str!("../shaders/interlevel.wgsl");
/// The kernel `sample_mask`.
pub const SAMPLE_MASK_WGSL: &str = include_str!("../shaders/sample_mask.wgsl");
/// The kernel `free_space`.
pub const FREE_SPACE_WGSL: &str = include_str!("../shaders/free_space.wgsl");
/// The kernel `distortion` (after [`RAY_SCAN_WGSL`]).
pub const DISTORTION_WGSL: &str = include_str!("../shaders/distortion.wgsl");

/// The uniform of both loss kernels: `(rays, 0, 0, 0)` and `(scale, 0, 0, 0)`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct LossU {
    run: [u32; 4],
    scale: [f32; 4],
}

impl LossU {
    fn new(rays: &GpuRays, scale: f32) -> Self {
        LossU {
            run: [rays.rays() as u32, 0, 0, 0],
            scale: [scale, 0.0, 0.0, 0.0],
        }
    }
}

/// The compiled colour-loss kernel of one device.
pub struct ColorLossKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
    unused: wgpu::Buffer,
}

impl ColorLossKernel {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // 1 (C, T_N) per ray, 2 targets (rgb per ray), 3 (dC, d_T) per ray, 4 squared error,
        // 5 background per ray.
        let layout = dev.bind_layout("colour loss", &[true, true, false, false, true]);
        let pipeline = dev.pipeline("colour loss", COLOR_LOSS_WGSL, "color_loss", &layout)?;
        Ok(ColorLossKernel {
            layout,
            pipeline,
            unused: dev.zeros_f32("unused", 4)?,
        })
    }

    /// Per ray: the mean squared error of `ray_out`'s colour against `targets` (3 floats per
    /// ray) into `sq_err`, and `dC = scale * d(mse)/dC` into `d_color` (4 floats per ray: dC,
    /// and `d_T = dC . bg` over a black background).
    pub fn run(
        &self,
        dev: &ComputeDevice,
        rays: &GpuRays,
        ray_out: &wgpu::Buffer,
        targets: &wgpu::Buffer,
        scale: f32,
        out: (&wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), GpuError> {
        self.run_with(dev, rays, ray_out, targets, scale, ([0.0; 3], None), out)
    }

    /// [`ColorLossKernel::run`] with `d_T = dC . bg` for background `bg`, or with a background
    /// per ray (4 floats each) when one is given.
    #[allow(clippy::too_many_arguments)]
    pub fn run_with(
        &self,
        dev: &ComputeDevice,
        rays: &GpuRays,
        ray_out: &wgpu::Buffer,
        targets: &wgpu::Buffer,
        scale: f32,
        (bg, ray_bg): ([f32; 3], Option<&wgpu::Buffer>),
        (d_color, sq_err): (&wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), GpuError> {
        let n = rays.rays();
        need_floats("per-ray output", ray_out, 4 * n as u64, n)?;
        need_floats("targets", targets, 3 * n as u64, n)?;
        need_floats("d_color", d_color, 4 * n as u64, n)?;
        need_floats("squared error", sq_err, n as u64, n)?;
        if let Some(b) = ray_bg {
            need_floats("backgrounds", b, 4 * n as u64, n)?;
        }
        let mut u = LossU::new(rays, scale);
        u.run[1] = ray_bg.is_some() as u32;
        u.scale = [scale, bg[0], bg[1], bg[2]];
        dev.run(
            &self.pipeline,
            &self.layout,
            bytemuck::bytes_of(&u),
            &[
                ray_out,
                targets,
                d_color,
                sq_err,
                ray_bg.unwrap_or(&self.unused),
            ],
            n as u64,
        )
    }
}

/// The compiled per-sample mask-loss kernel of one device.
pub struct SampleMaskKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
}

impl SampleMaskKernel {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // 1 w, 2 m, 3 d m, 4 loss per sample, 5 factor per ray.
        let layout = dev.bind_layout("sample mask loss", &[true, true, false, false, true]);
        let pipeline =
            dev.pipeline("sample mask loss", SAMPLE_MASK_WGSL, "sample_mask", &layout)?;
        Ok(SampleMaskKernel { layout, pipeline })
    }

    /// For `n` samples (`per_ray` per ray, rays in order) with weights `w`, mask values `m` and
    /// one factor `f` per ray: `d_m = -weight * f * scale * w` (the blend backward's extra mask
    /// gradient) and each sample's `weight * f * w (1 - m)` in `loss`.
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        dev: &ComputeDevice,
        n: usize,
        (w, m, f): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
        per_ray: usize,
        weight: f32,
        scale: f32,
        (d_m, loss): (&wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), GpuError> {
        if per_ray == 0 || !n.is_multiple_of(per_ray) {
            return Err(GpuError::Input(format!(
                "sample mask loss: {n} samples are not whole rays of {per_ray}"
            )));
        }
        for (what, b) in [("weights", w), ("m", m), ("d m", d_m), ("loss", loss)] {
            need_floats(what, b, n as u64, n)?;
        }
        need_floats("ray factors", f, (n / per_ray) as u64, n / per_ray)?;
        let u = LossU {
            run: [n as u32, per_ray as u32, 0, 0],
            scale: [weight, weight * scale, 0.0, 0.0],
        };
        dev.run(
            &self.pipeline,
            &self.layout,
            bytemuck::bytes_of(&u),
            &[w, m, d_m, loss, f],
            n as u64,
        )
    }
}

/// The compiled free-space-loss kernel of one device.
pub struct FreeSpaceKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
}

impl FreeSpaceKernel {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // 1 density rows, 2 d sigma, 3 loss per point.
        let layout = dev.bind_layout("free-space loss", &[true, false, false]);
        let pipeline = dev.pipeline("free-space loss", FREE_SPACE_WGSL, "free_space", &layout)?;
        Ok(FreeSpaceKernel { layout, pipeline })
    }

    /// For `n` points whose density MLP output rows (`stride` floats, sigma first) are in
    /// `density`: `d_sigma = weight * scale * delta * exp(-sigma delta)` and each point's
    /// `weight * (1 - exp(-sigma delta))` in `loss` (`msth_core::pipeline`'s free-space loss).
    pub fn run(
        &self,
        dev: &ComputeDevice,
        n: usize,
        (density, stride): (&wgpu::Buffer, usize),
        (weight, scale, delta): (f32, f32, f32),
        (d_sigma, loss): (&wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), GpuError> {
        need_floats("density rows", density, (n * stride) as u64, n)?;
        for (what, b) in [("d sigma", d_sigma), ("loss", loss)] {
            need_floats(what, b, n as u64, n)?;
        }
        let u = LossU {
            run: [n as u32, stride as u32, 0, 0],
            scale: [weight, weight * scale * delta, delta, 0.0],
        };
        dev.run(
            &self.pipeline,
            &self.layout,
            bytemuck::bytes_of(&u),
            &[density, d_sigma, loss],
            n as u64,
        )
    }
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
        let u = LossU::new(rays, scale);
        dev.run(
            &self.pipeline,
            &self.layout,
            bytemuck::bytes_of(&u),
            &[rays.offsets(), intervals, w, d_w, loss],
            rays.rays() as u64 * 64,
        )
    }
}

/// One ray batch's samples at one level: ray ranges, `(s_i, s_{i+1})` per sample (2 floats) and
/// weights.
pub struct LevelSamples<'a> {
    pub rays: &'a GpuRays,
    pub intervals: &'a wgpu::Buffer,
    pub weights: &'a wgpu::Buffer,
}

impl LevelSamples<'_> {
    fn check(&self, level: &str) -> Result<(), GpuError> {
        let n = self.rays.samples();
        need_floats(
            &format!("{level} intervals"),
            self.intervals,
            2 * n as u64,
            n,
        )?;
        need_floats(&format!("{level} weights"), self.weights, n as u64, n)
    }
}

/// The compiled interlevel-loss kernel of one device.
pub struct InterlevelKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
}

impl InterlevelKernel {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // 1 main offsets, 2 main intervals, 3 main w, 4 proposal offsets, 5 proposal
        // intervals, 6 proposal w, 7 d w_prop (added into), 8 loss per ray.
        let layout = dev.bind_layout(
            "interlevel",
            &[true, true, true, true, true, true, false, false],
        );
        let pipeline = dev.pipeline(
            "interlevel",
            &format!("{RAY_SCAN_WGSL}\n{INTERLEVEL_WGSL}"),
            "interlevel",
            &layout,
        )?;
        Ok(InterlevelKernel { layout, pipeline })
    }

    /// The loss of every ray (`loss`: one f32 per ray) of the main weights (held constant)
    /// against the proposal's; adds `scale * dL/dw_prop` into `d_w_prop` (one per proposal
    /// sample). Both levels hold the same rays, each ray's intervals in increasing order.
    pub fn run(
        &self,
        dev: &ComputeDevice,
        main: &LevelSamples,
        prop: &LevelSamples,
        scale: f32,
        (d_w_prop, loss): (&wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), GpuError> {
        let rays = main.rays.rays();
        if prop.rays.rays() != rays {
            return Err(GpuError::Input(format!(
                "{rays} main rays and {} proposal rays",
                prop.rays.rays()
            )));
        }
        main.check("main")?;
        prop.check("proposal")?;
        let np = prop.rays.samples();
        need_floats("d w_prop", d_w_prop, np as u64, np)?;
        need_floats("loss", loss, rays as u64, np)?;
        let u = LossU::new(main.rays, scale);
        dev.run(
            &self.pipeline,
            &self.layout,
            bytemuck::bytes_of(&u),
            &[
                main.rays.offsets(),
                main.intervals,
                main.weights,
                prop.rays.offsets(),
                prop.intervals,
                prop.weights,
                d_w_prop,
                loss,
            ],
            rays as u64 * 64,
        )
    }
}
