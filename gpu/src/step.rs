//! The whole training step on the device: `msth_core::pipeline::train_chunk` over a batch of
//! rays, chained from this crate's per-sample kernels, and Adam over the one flat parameter
//! buffer. `tests/step.rs` checks the step's losses and every gradient slice against the CPU
//! trainer's chunks on the same rays and random numbers.
//!
//! What the host does each step: it draws the rays and their colours (the dynamics-aware
//! sampler and the frame cache stay on the CPU, so data larger than GPU memory works as it
//! does on the CPU), computes each ray's limits and draws its two jitters (the CPU trainer's
//! per-chunk random streams, [`HostBatch::jitters`]), and uploads about 64 bytes per ray. Then,
//! on the device:
//!
//! 1. proposal samples: stratified edges, points, deltas ([`crate::sampling`]);
//! 2. the proposal field's density ([`GpuField::density_only`]) and its weights
//!    ([`crate::composite`]);
//! 3. resampling: the annealed proposal weights' CDF, inverted by bisection;
//! 4. the main field (grids, mask, blend, MLPs, SH: [`GpuField`]) at the new samples;
//! 5. compositing over the background (one colour, one per ray, or the last sample's), colours
//!    behind the CPU's `HIDDEN_TRANSMITTANCE` hidden as the CPU hides them;
//! 6. the losses: colour, distortion, per-sample mask, the interlevel loss into the proposal's
//!    weights, and the free-space loss (the main field's density at the host's random points,
//!    [`HostBatch::free_points`]) when its weight is not 0;
//! 7. both compositing backwards, then both fields' backwards, every gradient added into one
//!    flat buffer in the parameter layout;
//! 8. Adam ([`crate::adam`]) with the trainer's scaled slices (mask loss fused).
//!
//! A step ([`GpuStep::train_step`]) is recorded into one command encoder and submitted once
//! (`ComputeDevice::begin_batch`): no waits between its ~50 dispatches. Reading the losses back
//! ([`GpuStep::losses`]: four small per-ray buffers and one per-sample buffer) is the only
//! transfer to the host; a step that does not need them reads nothing.

use msth_core::config::{Background, ModelConfig};
use msth_core::field::ModelLayout;
use msth_core::pipeline::{
    free_space_delta, ChunkLosses, StepSettings, TimedRay, HIDDEN_TRANSMITTANCE,
};

use crate::adam::{AdamHyper, AdamKernel, GpuAdam, MaskSlice};
use crate::composite::{CompositeBuffers, CompositeKernels, CompositeMode, GpuRays};
use crate::device::ComputeDevice;
use crate::elementwise::Columns;
use crate::field::{FieldBuffers, FieldKernels, GpuField};
use crate::hashgrid::AtomicMode;
use crate::losses::{
    ColorLossKernel, DistortionKernel, FreeSpaceKernel, InterlevelKernel, LevelSamples,
    SampleMaskKernel,
};
use crate::sampling::{LevelBuffers, SampleRay, SamplingKernels};
use crate::GpuError;

/// Every kernel a training step runs, compiled for one device.
pub struct StepKernels {
    pub field: FieldKernels,
    pub sampling: SamplingKernels,
    pub composite: CompositeKernels,
    pub color: ColorLossKernel,
    pub distortion: DistortionKernel,
    pub interlevel: InterlevelKernel,
    pub sample_mask: SampleMaskKernel,
    pub free_space: FreeSpaceKernel,
    pub adam: AdamKernel,
}

impl StepKernels {
    pub fn new(dev: &ComputeDevice, mode: AtomicMode) -> Result<Self, GpuError> {
        Ok(StepKernels {
            field: FieldKernels::new(dev, mode)?,
            sampling: SamplingKernels::new(dev)?,
            composite: CompositeKernels::new(dev)?,
            color: ColorLossKernel::new(dev)?,
            distortion: DistortionKernel::new(dev)?,
            interlevel: InterlevelKernel::new(dev)?,
            sample_mask: SampleMaskKernel::new(dev)?,
            free_space: FreeSpaceKernel::new(dev)?,
            adam: AdamKernel::new(dev)?,
        })
    }
}

/// One step's batch as the host drew it.
#[derive(Clone, Copy, Debug)]
pub struct HostBatch<'a> {
    pub rays: &'a [TimedRay],
    pub targets: &'a [[f32; 3]],
    /// A background colour per ray (training on random backgrounds), else the model's.
    pub backgrounds: Option<&'a [[f32; 3]]>,
    /// Per ray, the proposal edges' jitter and the resampling jitter, each in `[0, 1)` (the CPU
    /// trainer draws them as `Rng::f32`); `None`: no jitter (the deterministic placement of
    /// rendering).
    pub jitters: Option<&'a [(f32, f32)]>,
    /// The free-space loss's points `(x, y, z, t)` in the unit cube and clip, one per ray (the
    /// CPU trainer draws them after the jitters, chunk by chunk); needed when
    /// `StepSettings::free_space_weight` is not 0.
    pub free_points: Option<&'a [[f32; 4]]>,
    /// Per ray, the factor of its per-sample mask loss terms (the CPU trainer's `mask_weights`
    /// of `train_chunk_with`); `None`: 1 for every ray.
    pub mask_weights: Option<&'a [f32]>,
}

/// One level's per-sample buffers.
struct Level {
    edges: wgpu::Buffer,
    points: wgpu::Buffer,
    sigma_delta: wgpu::Buffer,
    intervals: wgpu::Buffer,
    weights: wgpu::Buffer,
    /// `(d sigma, d rgb)` per sample from the compositing backward.
    d_sample: wgpu::Buffer,
    d_sigma: wgpu::Buffer,
    ray_out: wgpu::Buffer,
}

impl Level {
    fn new(dev: &ComputeDevice, rays: usize, ns: usize) -> Result<Self, GpuError> {
        let n = rays * ns;
        Ok(Level {
            edges: dev.zeros_f32("edges", rays * (ns + 1))?,
            points: dev.zeros_f32("points", 4 * n)?,
            sigma_delta: dev.zeros_f32("(sigma, delta)", 2 * n)?,
            intervals: dev.zeros_f32("intervals", 2 * n)?,
            weights: dev.zeros_f32("weights", n)?,
            d_sample: dev.zeros_f32("d sample", 4 * n)?,
            d_sigma: dev.zeros_f32("d sigma", n)?,
            ray_out: dev.zeros_f32("ray out", 4 * rays)?,
        })
    }

    fn buffers<'a>(&'a self, dirs: Option<&'a wgpu::Buffer>) -> LevelBuffers<'a> {
        LevelBuffers {
            edges: &self.edges,
            points: &self.points,
            sigma_delta: &self.sigma_delta,
            intervals: &self.intervals,
            dirs,
        }
    }
}

/// The ray ranges of one batch size at both levels.
struct Ranges {
    rays: usize,
    prop: GpuRays,
    main: GpuRays,
}

/// A model in training on the device: parameters, gradient, Adam's moments, and every buffer
/// of a batch of up to `capacity` rays.
pub struct GpuStep {
    cfg: ModelConfig,
    k: StepKernels,
    main: GpuField,
    prop: GpuField,
    /// The main field evaluated for its density alone, at the free-space loss's points.
    free: GpuField,
    n_params: usize,
    params: wgpu::Buffer,
    grad: wgpu::Buffer,
    adam: GpuAdam,
    capacity: usize,
    main_bufs: FieldBuffers,
    prop_bufs: FieldBuffers,
    lp: Level,
    lm: Level,
    rays: wgpu::Buffer,
    targets: wgpu::Buffer,
    backgrounds: wgpu::Buffer,
    dirs: wgpu::Buffer,
    cdf: wgpu::Buffer,
    /// Zeros: the proposal level's colours and its dC.
    zeros: wgpu::Buffer,
    d_color: wgpu::Buffer,
    d_w_main: wgpu::Buffer,
    d_w_prop: wgpu::Buffer,
    d_m: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
    sq_err: wgpu::Buffer,
    distortion: wgpu::Buffer,
    interlevel: wgpu::Buffer,
    sample_mask: wgpu::Buffer,
    /// Per ray, the factor of its per-sample mask loss ([`HostBatch::mask_weights`]).
    mask_weights: wgpu::Buffer,
    free_bufs: FieldBuffers,
    free_points: wgpu::Buffer,
    free_d_sigma: wgpu::Buffer,
    free_loss: wgpu::Buffer,
    ranges: Option<Ranges>,
    /// What the last [`GpuStep::gradients`] computed, for [`GpuStep::losses`].
    last: Option<Computed>,
}

/// Which terms the last [`GpuStep::gradients`] computed, over how many rays.
#[derive(Clone, Copy, Debug)]
struct Computed {
    rays: usize,
    distortion: bool,
    sample_mask: bool,
    free_space: bool,
}

/// Adam's state as checkpoints hold it: `(m, v, step)`.
pub type AdamState = (Vec<f32>, Vec<f32>, u64);

impl GpuStep {
    /// A model of `cfg` with parameters `params` (and Adam's state, when resuming) on `dev`,
    /// with buffers for batches of up to `capacity` rays. Clear errors: a model the kernels
    /// cannot run (no mask, a layer wider than [`crate::mlp::MAX_WIDTH`]), or buffers beyond
    /// the adapter's limits (named).
    pub fn new(
        dev: &ComputeDevice,
        cfg: &ModelConfig,
        params: &[f32],
        adam: Option<AdamState>,
        capacity: usize,
    ) -> Result<Self, GpuError> {
        let layout = ModelLayout::new(cfg);
        if params.len() != layout.params.total {
            return Err(GpuError::Input(format!(
                "{} parameters for a model of {}",
                params.len(),
                layout.params.total
            )));
        }
        let np = cfg.sampler.num_proposal_samples;
        let nf = cfg.sampler.num_samples;
        let per_ray = 4 * (np.max(nf) + 1);
        if capacity == 0 || np == 0 || nf == 0 || capacity > u32::MAX as usize / per_ray {
            return Err(GpuError::Input(format!(
                "a batch of {capacity} rays with {np} proposal and {nf} field samples (each at least 1, at most 2^32 values per buffer)"
            )));
        }
        let main = GpuField::new(&layout.field)?;
        let prop = GpuField::density_only(&layout.proposal.field)?;
        let free = GpuField::density_only(&layout.field)?;
        let k = StepKernels::new(dev, AtomicMode::best(dev))?;
        let adam = match adam {
            Some((m, v, step)) => GpuAdam::with_state(dev, &m, &v, step)?,
            None => GpuAdam::new(dev, params.len())?,
        };
        let (c, cm, cp) = (capacity, capacity * nf, capacity * np);
        Ok(GpuStep {
            main_bufs: main.buffers(dev, cm)?,
            prop_bufs: prop.buffers(dev, cp)?,
            lp: Level::new(dev, c, np)?,
            lm: Level::new(dev, c, nf)?,
            rays: dev.zeros_f32("rays", 12 * c)?,
            targets: dev.zeros_f32("targets", 3 * c)?,
            backgrounds: dev.zeros_f32("backgrounds", 4 * c)?,
            dirs: dev.zeros_f32("directions", 3 * cm)?,
            cdf: dev.zeros_f32("cdf", cp)?,
            zeros: dev.zeros_f32("zeros", (3 * cp).max(4 * c))?,
            d_color: dev.zeros_f32("d colour", 4 * c)?,
            d_w_main: dev.zeros_f32("d w", cm)?,
            d_w_prop: dev.zeros_f32("d w proposal", cp)?,
            d_m: dev.zeros_f32("d m", cm)?,
            d_rgb: dev.zeros_f32("d rgb", 3 * cm)?,
            sq_err: dev.zeros_f32("squared error", c)?,
            distortion: dev.zeros_f32("distortion", c)?,
            interlevel: dev.zeros_f32("interlevel", c)?,
            sample_mask: dev.zeros_f32("sample mask loss", cm)?,
            mask_weights: dev.zeros_f32("mask loss factors", c)?,
            free_bufs: free.buffers(dev, c)?,
            free_points: dev.zeros_f32("free-space points", 4 * c)?,
            free_d_sigma: dev.zeros_f32("free-space d sigma", c)?,
            free_loss: dev.zeros_f32("free-space loss", c)?,
            n_params: params.len(),
            params: dev.buffer_f32("parameters", params)?,
            grad: dev.zeros_f32("gradient", params.len())?,
            adam,
            capacity,
            main,
            prop,
            free,
            k,
            cfg: cfg.clone(),
            ranges: None,
            last: None,
        })
    }

    fn ranges(&mut self, dev: &ComputeDevice, n: usize) -> Result<(), GpuError> {
        if self.ranges.as_ref().is_some_and(|r| r.rays == n) {
            return Ok(());
        }
        let np = self.cfg.sampler.num_proposal_samples as u32;
        let nf = self.cfg.sampler.num_samples as u32;
        let offsets = |ns: u32| (0..=n as u32).map(|r| r * ns).collect::<Vec<u32>>();
        self.ranges = Some(Ranges {
            rays: n,
            prop: GpuRays::new(dev, &offsets(np))?,
            main: GpuRays::new(dev, &offsets(nf))?,
        });
        Ok(())
    }

    /// Forward and backward of one batch: the gradient buffer is cleared, then holds the
    /// batch's gradient (losses as means over `step.loss_scale`'s batch, as the CPU trainer's
    /// chunks add them). One submission for the whole pass.
    pub fn gradients(
        &mut self,
        dev: &ComputeDevice,
        batch: &HostBatch,
        step: &StepSettings,
    ) -> Result<(), GpuError> {
        self.upload(dev, batch, step)?;
        dev.begin_batch()?;
        let r = self.record_gradients(dev, batch, step);
        let end = dev.end_batch();
        r.and(end)
    }

    /// A whole training step: [`GpuStep::gradients`] and [`GpuStep::update`] recorded into one
    /// submission (the losses stay on the device until [`GpuStep::losses`] reads them).
    #[allow(clippy::too_many_arguments)]
    pub fn train_step(
        &mut self,
        dev: &ComputeDevice,
        batch: &HostBatch,
        step: &StepSettings,
        hyper: &AdamHyper,
        lr: f32,
        slices: &[MaskSlice],
    ) -> Result<(), GpuError> {
        self.upload(dev, batch, step)?;
        dev.begin_batch()?;
        let r = self
            .record_gradients(dev, batch, step)
            .and_then(|_| self.update(dev, hyper, lr, slices));
        let end = dev.end_batch();
        r.and(end)
    }

    /// Checks the batch and writes its rays, targets, backgrounds and free-space points to the
    /// device.
    fn upload(
        &mut self,
        dev: &ComputeDevice,
        batch: &HostBatch,
        step: &StepSettings,
    ) -> Result<(), GpuError> {
        let n = batch.rays.len();
        if n == 0 || n > self.capacity {
            return Err(GpuError::Input(format!(
                "a batch of {n} rays (1 to {})",
                self.capacity
            )));
        }
        if batch.targets.len() != n
            || batch.backgrounds.is_some_and(|b| b.len() != n)
            || batch.jitters.is_some_and(|j| j.len() != n)
            || batch.mask_weights.is_some_and(|m| m.len() != n)
        {
            return Err(GpuError::Input(format!(
                "{n} rays need {n} targets, backgrounds, jitters and mask weights"
            )));
        }
        if step.sample_mask_weight > 0.0 {
            match batch.mask_weights {
                Some(m) => dev.write_f32(&self.mask_weights, m)?,
                None => dev.write_f32(&self.mask_weights, &vec![1.0; n])?,
            }
        }
        if step.free_space_weight != 0.0 {
            match batch.free_points {
                Some(p) if p.len() == n => {
                    dev.write_f32(&self.free_points, bytemuck::cast_slice(p))?
                }
                _ => {
                    return Err(GpuError::Input(format!(
                        "the free-space loss needs {n} points for {n} rays"
                    )))
                }
            }
        }
        self.ranges(dev, n)?;
        let cfg = &self.cfg;
        let rays: Vec<SampleRay> = batch
            .rays
            .iter()
            .enumerate()
            .map(|(i, r)| SampleRay::new(cfg, r, batch.jitters.map_or((0.0, 0.0), |j| j[i])))
            .collect();
        dev.write_f32(&self.rays, bytemuck::cast_slice(&rays))?;
        dev.write_f32(&self.targets, bytemuck::cast_slice(batch.targets))?;
        if let Some(b) = batch.backgrounds {
            let bg: Vec<[f32; 4]> = b.iter().map(|c| [c[0], c[1], c[2], 0.0]).collect();
            dev.write_f32(&self.backgrounds, bytemuck::cast_slice(&bg))?;
        }
        Ok(())
    }

    /// The dispatches of [`GpuStep::gradients`] (after [`GpuStep::upload`]).
    fn record_gradients(
        &mut self,
        dev: &ComputeDevice,
        batch: &HostBatch,
        step: &StepSettings,
    ) -> Result<(), GpuError> {
        // The coarse-to-fine schedule acts on every evaluation of the main field's encoding.
        self.main.active_levels = step.active_levels;
        self.free.active_levels = step.active_levels;
        self.prop.active_levels = step.proposal_levels;
        let n = batch.rays.len();
        let cfg = &self.cfg;
        let np = cfg.sampler.num_proposal_samples;
        let nf = cfg.sampler.num_samples;
        let jitter = batch.jitters.is_some();
        dev.clear(&self.grad)?;
        let Some(ranges) = &self.ranges else {
            return Err(GpuError::Input("no ray ranges".into()));
        };
        let k = &self.k;
        let (lp, lm) = (&self.lp, &self.lm);
        let (n_p, n_m) = (n * np, n * nf);
        let at = |stride, first| Columns { stride, first };

        // 1-2: proposal samples, density, weights.
        k.sampling.place(
            dev,
            cfg,
            (&self.rays, n),
            np,
            true,
            jitter,
            &lp.buffers(None),
        )?;
        self.prop.forward(
            dev,
            &k.field,
            &self.params,
            &lp.points,
            &self.dirs,
            n_p,
            &self.prop_bufs,
        )?;
        k.field.elementwise.copy_columns(
            dev,
            n_p,
            1,
            &self.prop_bufs.density,
            at(1, 0),
            &lp.sigma_delta,
            at(2, 0),
        )?;
        let plain = CompositeMode::color([0.0; 3]);
        let prop_composite = CompositeBuffers {
            sigma_delta: &lp.sigma_delta,
            rgb: &self.zeros,
            weights: &lp.weights,
            ray_out: &lp.ray_out,
        };
        k.composite
            .forward_with(dev, &ranges.prop, &prop_composite, &plain)?;

        // 3-4: resampling and the main field.
        k.sampling.resample(
            dev,
            cfg,
            (&self.rays, &ranges.prop),
            (&lp.weights, &lp.edges),
            step.anneal,
            jitter,
            nf,
            (&self.cdf, &lm.edges),
        )?;
        k.sampling.place(
            dev,
            cfg,
            (&self.rays, n),
            nf,
            false,
            jitter,
            &lm.buffers(Some(&self.dirs)),
        )?;
        self.main.forward(
            dev,
            &k.field,
            &self.params,
            &lm.points,
            &self.dirs,
            n_m,
            &self.main_bufs,
        )?;
        let dw = self.main.layout().density.0.output_dim();
        k.field.elementwise.copy_columns(
            dev,
            n_m,
            1,
            &self.main_bufs.density,
            at(dw, 0),
            &lm.sigma_delta,
            at(2, 0),
        )?;

        // 5: compositing.
        let (bg, last_sample) = match cfg.background {
            Background::Color { rgb } => (rgb, false),
            Background::LastSample => ([0.0; 3], true),
        };
        let ray_bg = batch.backgrounds.map(|_| &self.backgrounds);
        let mode = CompositeMode {
            bg,
            ray_bg,
            last_sample: last_sample && ray_bg.is_none(),
            hide_beyond: Some((1.0 / HIDDEN_TRANSMITTANCE).ln()),
        };
        let main_composite = CompositeBuffers {
            sigma_delta: &lm.sigma_delta,
            rgb: &self.main_bufs.rgb,
            weights: &lm.weights,
            ray_out: &lm.ray_out,
        };
        k.composite
            .forward_with(dev, &ranges.main, &main_composite, &mode)?;

        // 6: losses.
        let scale = step.loss_scale;
        k.color.run_with(
            dev,
            &ranges.main,
            &lm.ray_out,
            &self.targets,
            scale,
            (bg, ray_bg),
            (&self.d_color, &self.sq_err),
        )?;
        dev.clear(&self.d_w_main)?;
        let distortion = step.distortion_weight > 0.0;
        if distortion {
            k.distortion.run(
                dev,
                &ranges.main,
                &lm.intervals,
                &lm.weights,
                step.distortion_weight * scale,
                &self.d_w_main,
                &self.distortion,
            )?;
        }
        let sample_mask = step.sample_mask_weight > 0.0;
        if sample_mask {
            k.sample_mask.run(
                dev,
                n_m,
                (&lm.weights, &self.main_bufs.m, &self.mask_weights),
                nf,
                step.sample_mask_weight,
                scale,
                (&self.d_m, &self.sample_mask),
            )?;
        }
        dev.clear(&self.d_w_prop)?;
        k.interlevel.run(
            dev,
            &LevelSamples {
                rays: &ranges.main,
                intervals: &lm.intervals,
                weights: &lm.weights,
            },
            &LevelSamples {
                rays: &ranges.prop,
                intervals: &lp.intervals,
                weights: &lp.weights,
            },
            step.interlevel_weight * scale,
            (&self.d_w_prop, &self.interlevel),
        )?;

        // 7: backwards.
        k.composite.backward_with(
            dev,
            &ranges.main,
            &main_composite,
            &mode,
            &self.d_color,
            Some(&self.d_w_main),
            &lm.d_sample,
        )?;
        let elementwise = &k.field.elementwise;
        elementwise.copy_columns(dev, n_m, 1, &lm.d_sample, at(4, 0), &lm.d_sigma, at(1, 0))?;
        elementwise.copy_columns(dev, n_m, 3, &lm.d_sample, at(4, 1), &self.d_rgb, at(3, 0))?;
        k.composite.backward_with(
            dev,
            &ranges.prop,
            &prop_composite,
            &plain,
            &self.zeros,
            Some(&self.d_w_prop),
            &lp.d_sample,
        )?;
        elementwise.copy_columns(dev, n_p, 1, &lp.d_sample, at(4, 0), &lp.d_sigma, at(1, 0))?;
        self.main.backward(
            dev,
            &k.field,
            &self.params,
            &lm.points,
            n_m,
            &self.main_bufs,
            &lm.d_sigma,
            &self.d_rgb,
            sample_mask.then_some(&self.d_m),
            &self.grad,
        )?;
        self.prop.backward(
            dev,
            &k.field,
            &self.params,
            &lp.points,
            n_p,
            &self.prop_bufs,
            &lp.d_sigma,
            &self.d_rgb,
            None,
            &self.grad,
        )?;
        // The free-space loss: the main field's density at the batch's random points.
        let free_space = step.free_space_weight != 0.0;
        if free_space {
            self.free.forward(
                dev,
                &k.field,
                &self.params,
                &self.free_points,
                &self.dirs,
                n,
                &self.free_bufs,
            )?;
            let delta = free_space_delta(&cfg.bounds);
            let stride = self.free.layout().density.0.output_dim();
            k.free_space.run(
                dev,
                n,
                (&self.free_bufs.density, stride),
                (step.free_space_weight, scale, delta),
                (&self.free_d_sigma, &self.free_loss),
            )?;
            self.free.backward(
                dev,
                &k.field,
                &self.params,
                &self.free_points,
                n,
                &self.free_bufs,
                &self.free_d_sigma,
                &self.d_rgb,
                None,
                &self.grad,
            )?;
        }
        self.last = Some(Computed {
            rays: n,
            distortion,
            sample_mask,
            free_space,
        });
        Ok(())
    }

    /// The loss sums of the last [`GpuStep::gradients`], as the CPU trainer's chunks add them
    /// (read back from the device).
    pub fn losses(&self, dev: &ComputeDevice) -> Result<ChunkLosses, GpuError> {
        let Some(Computed {
            rays: n,
            distortion,
            sample_mask,
            free_space,
        }) = self.last
        else {
            return Ok(ChunkLosses::default());
        };
        let nf = self.cfg.sampler.num_samples;
        let sum = |b: &wgpu::Buffer, len: usize| -> Result<f64, GpuError> {
            Ok(dev.read_f32(b, len)?.iter().map(|&x| x as f64).sum())
        };
        Ok(ChunkLosses {
            sq_err: sum(&self.sq_err, n)?,
            interlevel: sum(&self.interlevel, n)?,
            distortion: if distortion {
                sum(&self.distortion, n)?
            } else {
                0.0
            },
            sample_mask: if sample_mask {
                sum(&self.sample_mask, n * nf)?
            } else {
                0.0
            },
            free_space: if free_space {
                sum(&self.free_loss, n)?
            } else {
                0.0
            },
            rays: n,
            field_samples: n * nf,
            proposal_samples: n * self.cfg.sampler.num_proposal_samples,
            ..Default::default()
        })
    }

    /// The gradient of the last [`GpuStep::gradients`], on the host.
    pub fn gradient(&self, dev: &ComputeDevice) -> Result<Vec<f32>, GpuError> {
        dev.read_f32(&self.grad, self.n_params)
    }

    /// One Adam update of the parameters from the gradient (the trainer's `Adam::update`, its
    /// slices with their step scales and fused mask losses).
    pub fn update(
        &mut self,
        dev: &ComputeDevice,
        hyper: &AdamHyper,
        lr: f32,
        slices: &[MaskSlice],
    ) -> Result<(), GpuError> {
        self.adam.update(
            dev,
            &self.k.adam,
            hyper,
            lr,
            &self.params,
            &self.grad,
            slices,
        )
    }

    /// The parameters, on the host.
    pub fn params(&self, dev: &ComputeDevice) -> Result<Vec<f32>, GpuError> {
        dev.read_f32(&self.params, self.n_params)
    }

    /// Adam's state, on the host (for a checkpoint).
    pub fn adam_state(&self, dev: &ComputeDevice) -> Result<AdamState, GpuError> {
        self.adam.state(dev)
    }
}
