//! Where a training step's samples go, on the device: the proposal level's stratified edges and
//! samples, inverse-CDF resampling from the proposal weights, and the main level's samples, as
//! `msth_core::pipeline`'s `forward_chunk` places them (checked against it in
//! `tests/step.rs`, through the whole step).
//!
//! The host hands over each ray with its limits (`msth_core::pipeline::ray_limits`: a box
//! scene's slab test, or the sampler's near/far) and its two jitters already drawn
//! ([`SampleRay`]): the CPU trainer draws them from its per-chunk random streams, so the device
//! step can use the very same numbers, and the device needs no random-number generator.

use bytemuck::{Pod, Zeroable};
use msth_core::config::ModelConfig;
use msth_core::pipeline::{ray_limits, sample_time, spacing_unit, TimedRay};
use msth_core::sampling::Spacing;
use msth_core::scene::SceneBounds;

use crate::composite::{GpuRays, RAY_SCAN_WGSL};
use crate::device::ComputeDevice;
use crate::mlp::need_floats;
use crate::GpuError;

/// The common part of the sampling kernels (uniform, spacing, contraction).
pub const SAMPLING_WGSL: &str = include_str!("../shaders/sampling.wgsl");
/// The entry point `place_samples` (after [`SAMPLING_WGSL`]).
pub const SAMPLE_PLACE_WGSL: &str = include_str!("../shaders/sample_place.wgsl");
/// The entry points `pdf_cdf` and `pdf_sample` (after [`RAY_SCAN_WGSL`] and [`SAMPLING_WGSL`]).
pub const SAMPLE_PDF_WGSL: &str = include_str!("../shaders/sample_pdf.wgsl");

const FLAG_LINDISP: u32 = 1;
const FLAG_CONTRACTED: u32 = 2;
const FLAG_JITTER: u32 = 4;
const FLAG_UNIFORM_EDGES: u32 = 8;
const FLAG_DIRS: u32 = 16;

/// One ray as the sampling kernels read it: origin and time, direction, and
/// `(near, far, proposal jitter, resampling jitter)` (jitters in `[0, 1)`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct SampleRay {
    pub origin_time: [f32; 4],
    pub dir: [f32; 4],
    pub limits: [f32; 4],
}

impl SampleRay {
    /// `ray` under `cfg` (its limits, and its time clamped to `[0, 1]` as the CPU places
    /// samples), with the two jitters the CPU trainer would draw for it.
    pub fn new(cfg: &ModelConfig, ray: &TimedRay, jitters: (f32, f32)) -> Self {
        let (near, far) = ray_limits(cfg, ray);
        let time = sample_time(ray.time);
        SampleRay {
            origin_time: [ray.origin.x, ray.origin.y, ray.origin.z, time],
            dir: [ray.dir.x, ray.dir.y, ray.dir.z, 0.0],
            limits: [near, far, jitters.0, jitters.1],
        }
    }
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct SamplingU {
    run: [u32; 4],
    f: [f32; 4],
    b0: [f32; 4],
    b1: [f32; 4],
}

/// The per-level buffers [`SamplingKernels::place`] fills: edges (`ns + 1` per ray), points
/// `(x, y, z, t)`, `(sigma, delta)` (delta written) and `(s_i, s_i+1)` per sample, and where
/// given, each sample's unit view direction (3 floats).
pub struct LevelBuffers<'a> {
    pub edges: &'a wgpu::Buffer,
    pub points: &'a wgpu::Buffer,
    pub sigma_delta: &'a wgpu::Buffer,
    pub intervals: &'a wgpu::Buffer,
    pub dirs: Option<&'a wgpu::Buffer>,
}

/// The compiled sampling kernels of one device.
pub struct SamplingKernels {
    place_layout: wgpu::BindGroupLayout,
    pdf_layout: wgpu::BindGroupLayout,
    place: wgpu::ComputePipeline,
    cdf: wgpu::ComputePipeline,
    sample: wgpu::ComputePipeline,
    unused: wgpu::Buffer,
}

impl SamplingKernels {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // Place: 1 rays, 2 edges, 3 points, 4 (sigma, delta), 5 intervals, 6 directions.
        let place_layout =
            dev.bind_layout("place samples", &[true, false, false, false, false, false]);
        // Pdf: 1 proposal offsets, 2 rays, 3 proposal w, 4 proposal edges, 5 cdf, 6 new edges.
        let pdf_layout = dev.bind_layout("resample", &[true, true, true, true, false, false]);
        let pdf_src = format!("{RAY_SCAN_WGSL}\n{SAMPLING_WGSL}\n{SAMPLE_PDF_WGSL}");
        Ok(SamplingKernels {
            place: dev.pipeline(
                "place samples",
                &format!("{SAMPLING_WGSL}\n{SAMPLE_PLACE_WGSL}"),
                "place_samples",
                &place_layout,
            )?,
            cdf: dev.pipeline("resample cdf", &pdf_src, "pdf_cdf", &pdf_layout)?,
            sample: dev.pipeline("resample", &pdf_src, "pdf_sample", &pdf_layout)?,
            place_layout,
            pdf_layout,
            unused: dev.zeros_f32("unused", 1)?,
        })
    }

    fn uniform(cfg: &ModelConfig, rays: usize, ns: usize, flags: u32) -> SamplingU {
        let mut flags = flags;
        if cfg.sampler.spacing == Spacing::LinDisp {
            flags |= FLAG_LINDISP;
        }
        let (b0, b1) = match cfg.bounds {
            SceneBounds::Box { min, max } => {
                ([min.x, min.y, min.z, 0.0], [max.x, max.y, max.z, 0.0])
            }
            SceneBounds::Contracted { center, radius } => {
                flags |= FLAG_CONTRACTED;
                ([center.x, center.y, center.z, radius], [0.0; 4])
            }
        };
        SamplingU {
            run: [rays as u32, ns as u32, flags, 0],
            f: [
                spacing_unit(&cfg.bounds),
                cfg.sampler.histogram_padding,
                1.0,
                0.0,
            ],
            b0,
            b1,
        }
    }

    /// Places `ns` samples on each of `rays.len()` rays (`rays`: [`SampleRay`]s): with
    /// `uniform_edges` the level's edges are made (stratified, jittered by each ray's proposal
    /// jitter when `jitter`) and written, else they are read from `level.edges`.
    #[allow(clippy::too_many_arguments)]
    pub fn place(
        &self,
        dev: &ComputeDevice,
        cfg: &ModelConfig,
        rays: (&wgpu::Buffer, usize),
        ns: usize,
        uniform_edges: bool,
        jitter: bool,
        level: &LevelBuffers,
    ) -> Result<(), GpuError> {
        let (ray_buf, n) = rays;
        let samples = (n as u64).saturating_mul(ns as u64);
        if samples > u32::MAX as u64 / 4 || ns == 0 {
            return Err(GpuError::Input(format!(
                "{n} rays x {ns} samples (1 to 2^30 samples)"
            )));
        }
        let ns_n = n * ns;
        need_floats("rays", ray_buf, 12 * n as u64, ns_n)?;
        need_floats("edges", level.edges, (ns as u64 + 1) * n as u64, ns_n)?;
        need_floats("points", level.points, 4 * samples, ns_n)?;
        need_floats("(sigma, delta)", level.sigma_delta, 2 * samples, ns_n)?;
        need_floats("intervals", level.intervals, 2 * samples, ns_n)?;
        if let Some(d) = level.dirs {
            need_floats("directions", d, 3 * samples, ns_n)?;
        }
        let flags = (uniform_edges as u32 * FLAG_UNIFORM_EDGES)
            | (jitter as u32 * FLAG_JITTER)
            | (level.dirs.is_some() as u32 * FLAG_DIRS);
        let u = Self::uniform(cfg, n, ns, flags);
        dev.run(
            &self.place,
            &self.place_layout,
            bytemuck::bytes_of(&u),
            &[
                ray_buf,
                level.edges,
                level.points,
                level.sigma_delta,
                level.intervals,
                level.dirs.unwrap_or(&self.unused),
            ],
            samples,
        )
    }

    /// Resamples `ns + 1` new edges per ray (into `edges_out`) from the proposal weights `w_prop`
    /// (annealed by `anneal`) over the proposal edges `edges_prop`; `cdf` is scratch of one
    /// float per proposal sample.
    #[allow(clippy::too_many_arguments)]
    pub fn resample(
        &self,
        dev: &ComputeDevice,
        cfg: &ModelConfig,
        rays: (&wgpu::Buffer, &GpuRays),
        (w_prop, edges_prop): (&wgpu::Buffer, &wgpu::Buffer),
        anneal: f32,
        jitter: bool,
        ns: usize,
        (cdf, edges_out): (&wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), GpuError> {
        let (ray_buf, prop) = rays;
        let n = prop.rays();
        let np = cfg.sampler.num_proposal_samples;
        if prop.samples() != n * np || np == 0 {
            return Err(GpuError::Input(format!(
                "{} proposal samples for {n} rays of {np}",
                prop.samples()
            )));
        }
        need_floats("rays", ray_buf, 12 * n as u64, n)?;
        need_floats("proposal weights", w_prop, (n * np) as u64, n)?;
        need_floats("proposal edges", edges_prop, (n * (np + 1)) as u64, n)?;
        need_floats("cdf", cdf, (n * np) as u64, n)?;
        need_floats("new edges", edges_out, (n * (ns + 1)) as u64, n)?;
        let mut u = Self::uniform(cfg, n, np, jitter as u32 * FLAG_JITTER);
        u.run[3] = np as u32;
        u.f[2] = anneal;
        let bufs = [prop.offsets(), ray_buf, w_prop, edges_prop, cdf, edges_out];
        dev.run(
            &self.cdf,
            &self.pdf_layout,
            bytemuck::bytes_of(&u),
            &bufs,
            n as u64 * 64,
        )?;
        u.run[1] = ns as u32;
        dev.run(
            &self.sample,
            &self.pdf_layout,
            bytemuck::bytes_of(&u),
            &bufs,
            (n * (ns + 1)) as u64,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_size_matches_the_wgsl_structs() {
        assert_eq!(std::mem::size_of::<SamplingU>(), 64);
        assert_eq!(std::mem::size_of::<SampleRay>(), 48);
    }
}
