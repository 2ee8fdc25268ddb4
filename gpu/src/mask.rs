//! The dense mask grid on the device, forward and backward, one invocation per sample: exactly
//! `msth_core::grid::DenseGrid3` (trilinear over `res^3` vertices) followed by the sigmoid of
//! `msth_core::field`'s mask, checked against the CPU in `tests/mask.rs`.

use bytemuck::{Pod, Zeroable};
use msth_core::grid::DenseGrid3;

use crate::device::{ComputeDevice, KernelPair, PairSource};
use crate::hashgrid::AtomicMode;
use crate::GpuError;

/// The common part of both kernels (bindings 0-1, the cell rule, the sigmoid).
pub const MASK_WGSL: &str = include_str!("../shaders/mask.wgsl");
/// The forward entry point `mask_forward` (after [`MASK_WGSL`]).
pub const MASK_FORWARD_WGSL: &str = include_str!("../shaders/mask_forward.wgsl");
/// The backward entry point `mask_backward` (after [`MASK_WGSL`] and an atomic variant).
pub const MASK_BACKWARD_WGSL: &str = include_str!("../shaders/mask_backward.wgsl");

/// The kernels' `Mask` uniform: `(samples, res, offset of the logits in floats, 0)`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct MaskU {
    run: [u32; 4],
}

/// One mask grid on the device: its resolution and its logits' offset (in floats) inside the
/// table buffer (e.g. the flat parameter buffer); the gradient buffer has the same layout.
#[derive(Clone, Copy, Debug)]
pub struct GpuMask {
    grid: DenseGrid3,
    offset: usize,
}

impl GpuMask {
    pub fn new(grid: DenseGrid3, offset_floats: usize) -> Result<Self, GpuError> {
        if grid.res < 2 || grid.res > 1024 {
            return Err(GpuError::Input(format!(
                "a mask of resolution {} (2 to 1024)",
                grid.res
            )));
        }
        if offset_floats + grid.num_params() > u32::MAX as usize {
            return Err(GpuError::Input(format!(
                "a mask at offset {offset_floats}: beyond 2^32 floats"
            )));
        }
        Ok(GpuMask {
            grid,
            offset: offset_floats,
        })
    }

    fn uniform(
        &self,
        n: usize,
        table: &wgpu::Buffer,
        points: &wgpu::Buffer,
        per_sample: (&wgpu::Buffer, u64),
    ) -> Result<MaskU, GpuError> {
        if n > u32::MAX as usize {
            return Err(GpuError::Input(format!("{n} samples exceed 2^32")));
        }
        let need = |what: &str, buf: &wgpu::Buffer, floats: u64| {
            if buf.size() < floats * 4 {
                Err(GpuError::Input(format!(
                    "the {what} buffer holds {} bytes; {n} samples need {}",
                    buf.size(),
                    floats * 4
                )))
            } else {
                Ok(())
            }
        };
        need(
            "mask logits",
            table,
            (self.offset + self.grid.num_params()) as u64,
        )?;
        need("points", points, n as u64 * 4)?;
        need("per-sample", per_sample.0, n as u64 * per_sample.1)?;
        Ok(MaskU {
            run: [n as u32, self.grid.res as u32, self.offset as u32, 0],
        })
    }
}

/// The compiled mask kernels of one device.
pub struct MaskKernels {
    kernels: KernelPair,
}

impl MaskKernels {
    /// Compiles forward and backward, the backward with `mode` (see
    /// [`crate::hashgrid::HashGridKernels::new`]).
    pub fn new(dev: &ComputeDevice, mode: AtomicMode) -> Result<Self, GpuError> {
        // Binding 1 points, 2 logits (forward) or (m, d m) pairs (backward), 3 m or grad.
        let kernels = KernelPair::new(
            dev,
            mode,
            PairSource {
                label: "mask",
                common: MASK_WGSL,
                forward: (MASK_FORWARD_WGSL, "mask_forward"),
                backward: (MASK_BACKWARD_WGSL, "mask_backward"),
            },
        )?;
        Ok(MaskKernels { kernels })
    }

    pub fn mode(&self) -> AtomicMode {
        self.kernels.mode
    }

    /// `m = sigmoid(trilinear logit)` of `n` samples (`points`: `(x, y, z, t)`, `t` unused) into
    /// `m_out` (one f32 per sample).
    pub fn forward(
        &self,
        dev: &ComputeDevice,
        mask: &GpuMask,
        logits: &wgpu::Buffer,
        points: &wgpu::Buffer,
        n: usize,
        m_out: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let u = mask.uniform(n, logits, points, (m_out, 1))?;
        self.kernels.run(
            dev,
            false,
            bytemuck::bytes_of(&u),
            &[points, logits, m_out],
            n as u64,
        )
    }

    /// Adds `d loss / d logits` of `n` samples into `grad` (the logits' layout, at the mask's
    /// offset), given `(m, d loss / d m)` per sample in `m_dm` (two f32 each). Entries
    /// accumulate: clear `grad` first for a fresh gradient.
    pub fn backward(
        &self,
        dev: &ComputeDevice,
        mask: &GpuMask,
        points: &wgpu::Buffer,
        m_dm: &wgpu::Buffer,
        n: usize,
        grad: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let u = mask.uniform(n, grad, points, (m_dm, 2))?;
        self.kernels.run(
            dev,
            true,
            bytemuck::bytes_of(&u),
            &[points, m_dm, grad],
            n as u64,
        )
    }

    /// [`MaskKernels::forward`] from and to host memory (`logits`: the mask's own values).
    pub fn forward_host(
        &self,
        dev: &ComputeDevice,
        grid: DenseGrid3,
        logits: &[f32],
        points: &[[f32; 4]],
    ) -> Result<Vec<f32>, GpuError> {
        let mask = GpuMask::new(grid, 0)?;
        if logits.len() != grid.num_params() {
            return Err(GpuError::Input(format!(
                "the mask holds {} logits; {} expected",
                logits.len(),
                grid.num_params()
            )));
        }
        let l = dev.buffer_f32("mask logits", logits)?;
        let p = dev.buffer_f32("points", bytemuck::cast_slice(points))?;
        let out = dev.zeros_f32("mask values", points.len())?;
        self.forward(dev, &mask, &l, &p, points.len(), &out)?;
        dev.read_f32(&out, points.len())
    }

    /// [`MaskKernels::backward`] from and to host memory: the gradient of the mask's logits.
    pub fn backward_host(
        &self,
        dev: &ComputeDevice,
        grid: DenseGrid3,
        points: &[[f32; 4]],
        m: &[f32],
        d_m: &[f32],
    ) -> Result<Vec<f32>, GpuError> {
        let mask = GpuMask::new(grid, 0)?;
        if m.len() != points.len() || d_m.len() != points.len() {
            return Err(GpuError::Input(format!(
                "{} points, {} mask values and {} gradients: one of each per sample expected",
                points.len(),
                m.len(),
                d_m.len()
            )));
        }
        let pairs: Vec<f32> = m.iter().zip(d_m).flat_map(|(a, b)| [*a, *b]).collect();
        let p = dev.buffer_f32("points", bytemuck::cast_slice(points))?;
        let md = dev.buffer_f32("mask values and gradients", &pairs)?;
        let g = dev.zeros_f32("mask gradient", grid.num_params())?;
        self.backward(dev, &mask, &p, &md, points.len(), &g)?;
        dev.read_f32(&g, grid.num_params())
    }
}
