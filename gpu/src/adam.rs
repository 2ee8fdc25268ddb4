//! Adam over the flat parameter buffer on the device, one invocation per parameter: the
//! trainer's `msth_trainer::adam::Adam::update` step for step (bias correction, eps, the
//! gradient clamp, the mask loss fused into the mask slices' update with their learning-rate
//! scale), with its moments in two device buffers of the parameter buffer's layout (the same
//! `m` and `v` a checkpoint stores). Checked against the trainer's in `tests/adam.rs`.

use std::ops::Range;

use bytemuck::{Pod, Zeroable};

use crate::device::ComputeDevice;
use crate::layout::dispatch_size;
use crate::mlp::need_floats;
use crate::GpuError;

/// The kernel `adam_step`.
pub const ADAM_WGSL: &str = include_str!("../shaders/adam.wgsl");

/// The most mask slices one update takes (the trainer has one per field).
pub const MAX_MASK_SLICES: usize = 8;

/// Gradients are clamped to this magnitude before the moments (the trainer's
/// `msth_trainer::adam::MAX_GRADIENT`; `tests/adam.rs` checks they agree).
pub const MAX_GRADIENT: f32 = 1e18;

/// Adam's constants (the trainer's `AdamConfig` less its schedule: the caller passes the
/// step's learning rate).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamHyper {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

/// A slice of the parameter buffer with the mask loss `weight * mean(1 - sigmoid(x))` fused into
/// its update, its step scaled by `lr_scale` and `decay * x` added to its gradient (the trainer's
/// `ScaledSlice`).
#[derive(Clone, Debug, PartialEq)]
pub struct MaskSlice {
    pub range: Range<usize>,
    pub weight: f32,
    pub lr_scale: f32,
    pub decay: f32,
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct MaskSliceU {
    range: [u32; 4],
    vals: [f32; 4],
}

/// The kernel's `Adam` uniform (see `shaders/adam.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct AdamU {
    run: [u32; 4],
    coef: [f32; 4],
    more: [f32; 4],
    slices: [MaskSliceU; MAX_MASK_SLICES],
}

/// The compiled Adam kernel of one device.
pub struct AdamKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
}

impl AdamKernel {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // Binding 1 grad, 2 params, 3 m, 4 v, 5 per-workgroup mask-loss sums.
        let layout = dev.bind_layout("adam", &[true, false, false, false, false]);
        let pipeline = dev.pipeline("adam", ADAM_WGSL, "adam_step", &layout)?;
        Ok(AdamKernel { layout, pipeline })
    }
}

/// Adam's state on the device: both moments (`[n]` each) and the step count.
pub struct GpuAdam {
    m: wgpu::Buffer,
    v: wgpu::Buffer,
    partials: wgpu::Buffer,
    groups: usize,
    n: usize,
    step: u64,
    masked: bool,
}

impl GpuAdam {
    /// A fresh state for `n` parameters (moments zero, step 0).
    pub fn new(dev: &ComputeDevice, n: usize) -> Result<Self, GpuError> {
        Self::with_state(dev, &vec![0.0; n], &vec![0.0; n], 0)
    }

    /// A state resumed from `m`, `v` and `step` (a checkpoint's, whichever device wrote it).
    pub fn with_state(
        dev: &ComputeDevice,
        m: &[f32],
        v: &[f32],
        step: u64,
    ) -> Result<Self, GpuError> {
        let n = m.len();
        if v.len() != n || n == 0 || n > u32::MAX as usize {
            return Err(GpuError::Input(format!(
                "Adam moments of {} and {} values (equal, 1 to 2^32)",
                m.len(),
                v.len()
            )));
        }
        let max = dev.device.limits().max_compute_workgroups_per_dimension;
        let (gx, gy) = dispatch_size(n as u32, max).ok_or_else(|| GpuError::Limit {
            what: format!("Adam over {n} parameters"),
            amount: n as u64,
            unit: "invocations",
            limit: "max_compute_workgroups_per_dimension (squared, times 64)",
            max: max as u64 * max as u64 * 64,
        })?;
        let groups = gx as usize * gy as usize;
        Ok(GpuAdam {
            m: dev.buffer_f32("adam m", m)?,
            v: dev.buffer_f32("adam v", v)?,
            partials: dev.zeros_f32("adam mask-loss partials", groups)?,
            groups,
            n,
            step,
            masked: false,
        })
    }

    pub fn step(&self) -> u64 {
        self.step
    }

    /// One update of `params` (`[n]`) from `grad` with learning rate `lr`, as the trainer's
    /// `Adam::update` (its mask-loss value: [`GpuAdam::mask_loss`]).
    #[allow(clippy::too_many_arguments)]
    pub fn update(
        &mut self,
        dev: &ComputeDevice,
        kernel: &AdamKernel,
        hyper: &AdamHyper,
        lr: f32,
        params: &wgpu::Buffer,
        grad: &wgpu::Buffer,
        masks: &[MaskSlice],
    ) -> Result<(), GpuError> {
        let n = self.n;
        need_floats("parameter", params, n as u64, n)?;
        need_floats("gradient", grad, n as u64, n)?;
        if masks.len() > MAX_MASK_SLICES {
            return Err(GpuError::Input(format!(
                "{} mask slices (at most {MAX_MASK_SLICES})",
                masks.len()
            )));
        }
        let mut u = AdamU::zeroed();
        for (slot, s) in u.slices.iter_mut().zip(masks) {
            if s.range.start >= s.range.end || s.range.end > n {
                return Err(GpuError::Input(format!(
                    "a mask slice {:?} of {n} parameters",
                    s.range
                )));
            }
            *slot = MaskSliceU {
                range: [s.range.start as u32, s.range.end as u32, 0, 0],
                vals: [s.weight, s.lr_scale, s.range.len() as f32, s.decay],
            };
        }
        // The trainer's bias correction, in the same f32 operations.
        let t = (self.step + 1) as i32;
        let bc1 = 1.0 - hyper.beta1.powi(t);
        let bc2 = 1.0 - hyper.beta2.powi(t);
        u.run = [n as u32, masks.len() as u32, 0, 0];
        u.coef = [lr / bc1, 1.0 / bc2.sqrt(), hyper.beta1, hyper.beta2];
        u.more = [hyper.eps, MAX_GRADIENT, 0.0, 0.0];
        dev.run(
            &kernel.pipeline,
            &kernel.layout,
            bytemuck::bytes_of(&u),
            &[grad, params, &self.m, &self.v, &self.partials],
            n as u64,
        )?;
        self.step += 1;
        self.masked = !masks.is_empty();
        Ok(())
    }

    /// The mask loss of the last update (weighted sum over its slices, before the update, as
    /// the trainer's `Adam::update` returns it): the workgroups' sums, added in f64.
    pub fn mask_loss(&self, dev: &ComputeDevice) -> Result<f32, GpuError> {
        if !self.masked {
            return Ok(0.0);
        }
        let p = dev.read_f32(&self.partials, self.groups)?;
        Ok(p.iter().map(|&x| x as f64).sum::<f64>() as f32)
    }

    /// Both moments back on the host, for a checkpoint: `(m, v, step)`.
    pub fn state(&self, dev: &ComputeDevice) -> Result<(Vec<f32>, Vec<f32>, u64), GpuError> {
        Ok((
            dev.read_f32(&self.m, self.n)?,
            dev.read_f32(&self.v, self.n)?,
            self.step,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_size_matches_the_wgsl_struct() {
        assert_eq!(std::mem::size_of::<AdamU>(), 48 + 32 * MAX_MASK_SLICES);
    }
}
