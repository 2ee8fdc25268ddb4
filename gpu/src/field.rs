//! The main field on the device, chained from the per-sample kernels: hash grids (3D and 4D),
//! the mask, the blend, the density MLP (`trunc_exp`), the direction encoding (SH), the
//! geometry-feature copy and the colour MLP (sigmoid); the backward in reverse through the same
//! buffers, every gradient added into one flat buffer in the parameter layout.
//!
//! `msth_core::field::FieldLayout` is the reference (`tests/field.rs` checks values and the
//! gradient of every slice against it); `examples/bench_field.rs` times the chain.
//!
//! What a training step would add around it: proposal sampling, compositing and the losses
//! ([`crate::composite`], [`crate::losses`]), Adam ([`crate::adam`]), and recording every pass
//! into one command encoder (each call here still submits and waits, `ComputeDevice::run`).

use msth_core::field::FieldLayout;
use msth_core::sh::SH_COEFFS;

use crate::device::ComputeDevice;
use crate::elementwise::{Blend, Columns, ElementwiseKernels};
use crate::hashgrid::{AtomicMode, GpuGrid, HashGridKernels};
use crate::mask::{GpuMask, MaskKernels};
use crate::mlp::{GpuMlp, MlpKernels, OutputActivation};
use crate::sh::ShKernel;
use crate::GpuError;

/// Every kernel the field chains, compiled for one device.
pub struct FieldKernels {
    pub grid: HashGridKernels,
    pub mask: MaskKernels,
    pub mlp: MlpKernels,
    pub elementwise: ElementwiseKernels,
    pub sh: ShKernel,
}

impl FieldKernels {
    pub fn new(dev: &ComputeDevice, mode: AtomicMode) -> Result<Self, GpuError> {
        Ok(FieldKernels {
            grid: HashGridKernels::new(dev, mode)?,
            mask: MaskKernels::new(dev, mode)?,
            mlp: MlpKernels::new(dev, mode)?,
            elementwise: ElementwiseKernels::new(dev)?,
            sh: ShKernel::new(dev)?,
        })
    }
}

/// One main field's slices of the flat parameter buffer, as the kernels take them.
pub struct GpuField {
    layout: FieldLayout,
    grid3: GpuGrid,
    grid4: GpuGrid,
    mask: GpuMask,
    density: GpuMlp,
    /// None for a density-only field (the proposal's).
    colour: Option<GpuMlp>,
    /// The coarse-to-fine factor of the next passes (`StepSettings::active_levels`); `None`
    /// leaves every level on.
    pub active_levels: Option<f32>,
}

/// Per-sample buffers of one batch of at most `capacity` samples: the forward's intermediates
/// (kept for the backward) and the backward's.
pub struct FieldBuffers {
    capacity: usize,
    h3: wgpu::Buffer,
    h4: wgpu::Buffer,
    /// `m` per sample (the mask's values), for the per-sample mask loss.
    pub m: wgpu::Buffer,
    enc: wgpu::Buffer,
    /// `[n, 1 + geo]`: sigma (after `trunc_exp`) and the geometry features.
    pub density: wgpu::Buffer,
    density_acts: wgpu::Buffer,
    colour_in: wgpu::Buffer,
    /// `[n, 3]` after the sigmoid.
    pub rgb: wgpu::Buffer,
    colour_acts: wgpu::Buffer,
    d_geo: wgpu::Buffer,
    d_density: wgpu::Buffer,
    d_enc: wgpu::Buffer,
    d_h3: wgpu::Buffer,
    d_h4: wgpu::Buffer,
    m_dm: wgpu::Buffer,
}

impl GpuField {
    /// The field of `layout`; a field without a 3D grid, a 4D grid or a mask (the MSTH blends
    /// need all three) is a [`GpuError::Input`].
    pub fn new(layout: &FieldLayout) -> Result<Self, GpuError> {
        Self::build(layout, true)
    }

    fn build(layout: &FieldLayout, with_colour: bool) -> Result<Self, GpuError> {
        let enc = &layout.encoding;
        let missing = |what: &str| {
            GpuError::Input(format!(
                "the GPU field needs a 3D grid, a 4D grid and a mask; this one has no {what}"
            ))
        };
        let (g3, r3) = enc.h3.clone().ok_or_else(|| missing("3D grid"))?;
        let (g4, r4) = enc.h4.clone().ok_or_else(|| missing("4D grid"))?;
        let (mg, rm) = enc.mask.clone().ok_or_else(|| missing("mask"))?;
        let (dm, dr) = layout.density.clone();
        let (cm, cr) = layout.color.clone();
        Ok(GpuField {
            grid3: GpuGrid::new(&g3, r3.start)?,
            grid4: GpuGrid::new(&g4, r4.start)?,
            mask: GpuMask::new(mg, rm.start)?,
            density: GpuMlp::new(&dm, dr.start, OutputActivation::Density)?,
            colour: if with_colour {
                Some(GpuMlp::new(&cm, cr.start, OutputActivation::Sigmoid)?)
            } else {
                None
            },
            layout: layout.clone(),
            active_levels: None,
        })
    }

    /// A field evaluated for its density alone: the proposal field (one output, sigma), or a
    /// main field at points where only sigma matters (the free-space loss's). The forward
    /// stops after the density MLP, and the backward takes `d_sigma` with no gradient into the
    /// geometry features; there is no colour.
    pub fn density_only(layout: &FieldLayout) -> Result<Self, GpuError> {
        if layout.density.0.output_dim() != 1 + layout.geo_features {
            return Err(GpuError::Input(format!(
                "a density MLP of {} outputs for sigma and {} geometry features",
                layout.density.0.output_dim(),
                layout.geo_features
            )));
        }
        Self::build(layout, false)
    }

    pub fn layout(&self) -> &FieldLayout {
        &self.layout
    }

    fn widths(&self) -> (usize, usize, usize, usize) {
        let e = self.layout.encoding.out_dim;
        let geo = self.layout.geo_features;
        let dw = self.layout.density.0.output_dim();
        (e, geo, dw, SH_COEFFS + geo)
    }

    /// Buffers for batches of at most `capacity` samples.
    pub fn buffers(&self, dev: &ComputeDevice, capacity: usize) -> Result<FieldBuffers, GpuError> {
        let (e, geo, dw, cw) = self.widths();
        let n = capacity;
        let z = |what: &str, len: usize| dev.zeros_f32(what, len.max(1));
        // A density-only field needs no colour buffers.
        let nc = if self.colour.is_some() { n } else { 0 };
        Ok(FieldBuffers {
            capacity,
            h3: z("h3", n * e)?,
            h4: z("h4", n * e)?,
            m: z("m", n)?,
            enc: z("enc", n * e)?,
            density: z("density out", n * dw)?,
            density_acts: z("density acts", n * self.density.acts_stride())?,
            colour_in: z("colour in", nc * cw)?,
            rgb: z("rgb", 3 * nc)?,
            colour_acts: z(
                "colour acts",
                nc * self.colour.as_ref().map_or(0, |c| c.acts_stride()),
            )?,
            d_geo: z("d geo", n * geo)?,
            d_density: z("d density out", n * dw)?,
            d_enc: z("d enc", n * e)?,
            d_h3: z("d h3", n * e)?,
            d_h4: z("d h4", n * e)?,
            m_dm: z("m dm", 2 * n)?,
        })
    }

    fn check(&self, b: &FieldBuffers, n: usize) -> Result<(), GpuError> {
        if n > b.capacity {
            return Err(GpuError::Input(format!(
                "{n} samples in buffers made for {}",
                b.capacity
            )));
        }
        Ok(())
    }

    fn blend<'a>(&self, b: &'a FieldBuffers, n: usize) -> Blend<'a> {
        let enc = &self.layout.encoding;
        let per_level = enc
            .h3
            .as_ref()
            .or(enc.h4.as_ref())
            .map_or(1, |(g, _)| g.features);
        Blend {
            mode: self.layout.encoding.blend,
            ramp: self.active_levels.map(|a| (a, per_level)),
            samples: n,
            features: self.layout.encoding.out_dim,
            h3: &b.h3,
            h4: &b.h4,
            m: &b.m,
        }
    }

    /// `(sigma, geometry features)` into `b.density` and rgb into `b.rgb` for `n` samples:
    /// `points` `(x, y, z, t)` per sample in the unit cube / unit time, `dirs` unit view
    /// directions (`[n, 3]`), `params` the flat parameter buffer. A density-only field stops
    /// after sigma (`dirs` unread).
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &self,
        dev: &ComputeDevice,
        k: &FieldKernels,
        params: &wgpu::Buffer,
        points: &wgpu::Buffer,
        dirs: &wgpu::Buffer,
        n: usize,
        b: &FieldBuffers,
    ) -> Result<(), GpuError> {
        self.check(b, n)?;
        let (_, geo, dw, cw) = self.widths();
        k.grid.forward(dev, &self.grid3, params, points, n, &b.h3)?;
        k.grid.forward(dev, &self.grid4, params, points, n, &b.h4)?;
        k.mask.forward(dev, &self.mask, params, points, n, &b.m)?;
        k.elementwise
            .blend_forward(dev, &self.blend(b, n), &b.enc)?;
        k.mlp.forward(
            dev,
            &self.density,
            params,
            &b.enc,
            n,
            &b.density,
            Some(&b.density_acts),
        )?;
        let Some(colour) = &self.colour else {
            return Ok(());
        };
        k.sh.encode(dev, dirs, n, &b.colour_in, cw, 0)?;
        let at = |stride, first| Columns { stride, first };
        k.elementwise.copy_columns(
            dev,
            n,
            geo,
            &b.density,
            at(dw, 1),
            &b.colour_in,
            at(cw, SH_COEFFS),
        )?;
        k.mlp.forward(
            dev,
            colour,
            params,
            &b.colour_in,
            n,
            &b.rgb,
            Some(&b.colour_acts),
        )
    }

    /// Backward of the last [`GpuField::forward`] of these buffers: `d_sigma` `[n]` and `d_rgb`
    /// `[n, 3]` in (unread for a density-only field), and optionally an extra `dL/dm` per
    /// sample (the per-sample mask loss); every field slice's gradient added into `grad` (the
    /// flat parameter layout; clear it first for a fresh gradient).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        dev: &ComputeDevice,
        k: &FieldKernels,
        params: &wgpu::Buffer,
        points: &wgpu::Buffer,
        n: usize,
        b: &FieldBuffers,
        d_sigma: &wgpu::Buffer,
        d_rgb: &wgpu::Buffer,
        d_m_extra: Option<&wgpu::Buffer>,
        grad: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        self.check(b, n)?;
        let (_, geo, dw, _) = self.widths();
        let at = |stride, first| Columns { stride, first };
        if let Some(colour) = &self.colour {
            k.mlp.backward(
                dev,
                colour,
                params,
                &b.colour_in,
                &b.colour_acts,
                d_rgb,
                n,
                grad,
                Some((SH_COEFFS, &b.d_geo)),
            )?;
        }
        k.elementwise
            .copy_columns(dev, n, 1, d_sigma, at(1, 0), &b.d_density, at(dw, 0))?;
        if geo > 0 {
            k.elementwise.copy_columns(
                dev,
                n,
                geo,
                &b.d_geo,
                at(geo, 0),
                &b.d_density,
                at(dw, 1),
            )?;
        }
        k.mlp.backward(
            dev,
            &self.density,
            params,
            &b.enc,
            &b.density_acts,
            &b.d_density,
            n,
            grad,
            Some((0, &b.d_enc)),
        )?;
        k.elementwise.blend_backward(
            dev,
            &self.blend(b, n),
            &b.d_enc,
            d_m_extra,
            (&b.d_h3, &b.d_h4, &b.m_dm),
        )?;
        k.grid
            .backward(dev, &self.grid3, points, &b.d_h3, n, grad)?;
        k.grid
            .backward(dev, &self.grid4, points, &b.d_h4, n, grad)?;
        k.mask.backward(dev, &self.mask, points, &b.m_dm, n, grad)
    }
}
