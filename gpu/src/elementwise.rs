//! The elementwise passes between one field's kernels: the encoding blend of `msth_core::field`
//! (`enc = a(m) h3 + b(m) h4`, forward and backward, the backward handing the mask backward its
//! `(m, d m)` pairs) and column copies between row layouts (the density MLP's geometry features
//! into the colour MLP's input rows and the gradients back). One invocation per sample (blend)
//! or per value (copies). `tests/field.rs` chains them with the grid, mask, MLP and SH kernels
//! into the main field and checks it against `msth_core::field::FieldLayout`.

use bytemuck::{Pod, Zeroable};
use msth_core::config::BlendMode;

use crate::device::ComputeDevice;
use crate::mlp::need_floats;
use crate::GpuError;

/// The common part of the blend kernels (uniform, bindings 1-3, the coefficients).
pub const BLEND_WGSL: &str = include_str!("../shaders/blend.wgsl");
/// The forward entry point `blend_forward` (after [`BLEND_WGSL`]).
pub const BLEND_FORWARD_WGSL: &str = include_str!("../shaders/blend_forward.wgsl");
/// The backward entry point `blend_backward` (after [`BLEND_WGSL`]).
pub const BLEND_BACKWARD_WGSL: &str = include_str!("../shaders/blend_backward.wgsl");
/// The kernel `copy_columns`.
pub const COLUMNS_WGSL: &str = include_str!("../shaders/columns.wgsl");

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct BlendU {
    run: [u32; 4],
    coef: [f32; 4],
    ramp: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct ColumnsU {
    a: [u32; 4],
    b: [u32; 4],
}

/// `(a0, a1, b0, b1)` with `a(m) = a0 + a1 m`, `b(m) = b0 + b1 m` ([`BlendMode::coefficients`]).
fn blend_coefficients(mode: BlendMode) -> [f32; 4] {
    match mode {
        BlendMode::Mt => [1.0, 0.0, 1.0, -1.0],
        BlendMode::Mst => [0.0, 1.0, 1.0, -1.0],
        BlendMode::Add => [1.0, 0.0, 1.0, 0.0],
        BlendMode::FourD => [0.0, 0.0, 1.0, 0.0],
        BlendMode::Static => [1.0, 0.0, 0.0, 0.0],
    }
}

/// Where `cols` columns of each row sit: `(row stride, first column)` in floats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Columns {
    pub stride: usize,
    pub first: usize,
}

/// One blend pass: the mode, `samples` rows of `features` values, and the per-sample buffers
/// (`h3`/`h4` unread where the mode does not use the grid).
pub struct Blend<'a> {
    pub mode: BlendMode,
    /// Coarse-to-fine: `(active levels, features per level)`, level `l`'s features scaled by
    /// `msth_core::field::level_factor` forward and backward; `None`: every level on.
    pub ramp: Option<(f32, usize)>,
    pub samples: usize,
    pub features: usize,
    pub h3: &'a wgpu::Buffer,
    pub h4: &'a wgpu::Buffer,
    /// `m` per sample (the mask's values; any filler where the mode has no mask).
    pub m: &'a wgpu::Buffer,
}

/// The compiled elementwise kernels of one device.
pub struct ElementwiseKernels {
    blend_fwd_layout: wgpu::BindGroupLayout,
    blend_bwd_layout: wgpu::BindGroupLayout,
    columns_layout: wgpu::BindGroupLayout,
    blend_fwd: wgpu::ComputePipeline,
    blend_bwd: wgpu::ComputePipeline,
    columns: wgpu::ComputePipeline,
    unused: wgpu::Buffer,
}

impl ElementwiseKernels {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // Blend forward: 1 h3, 2 h4, 3 m, 4 enc; backward: 4 d_enc, 5 extra d m, 6 d h3,
        // 7 d h4, 8 (m, d m).
        let blend_fwd_layout = dev.bind_layout("blend forward", &[true, true, true, false]);
        let blend_bwd_layout = dev.bind_layout(
            "blend backward",
            &[true, true, true, true, true, false, false, false],
        );
        let columns_layout = dev.bind_layout("columns", &[true, false]);
        Ok(ElementwiseKernels {
            blend_fwd: dev.pipeline(
                "blend forward",
                &format!("{BLEND_WGSL}\n{BLEND_FORWARD_WGSL}"),
                "blend_forward",
                &blend_fwd_layout,
            )?,
            blend_bwd: dev.pipeline(
                "blend backward",
                &format!("{BLEND_WGSL}\n{BLEND_BACKWARD_WGSL}"),
                "blend_backward",
                &blend_bwd_layout,
            )?,
            columns: dev.pipeline("columns", COLUMNS_WGSL, "copy_columns", &columns_layout)?,
            blend_fwd_layout,
            blend_bwd_layout,
            columns_layout,
            unused: dev.zeros_f32("unused", 1)?,
        })
    }

    fn blend_uniform(b: &Blend, extra: bool) -> Result<BlendU, GpuError> {
        let (mode, n, features) = (b.mode, b.samples, b.features);
        let nf = (n as u64).saturating_mul(features as u64);
        if nf > u32::MAX as u64 {
            return Err(GpuError::Input(format!(
                "{n} samples x {features} features exceed 2^32"
            )));
        }
        if mode.uses_h3() {
            need_floats("h3", b.h3, nf, n)?;
        }
        if mode.uses_h4() {
            need_floats("h4", b.h4, nf, n)?;
        }
        need_floats("m", b.m, n as u64, n)?;
        let flags = mode.uses_h3() as u32 | (mode.uses_h4() as u32) << 1 | (extra as u32) << 2;
        // (active levels, features per level, level count): the shader scales only while the
        // first is below the last, as the CPU does (`EncodingLayout::forward`).
        let ramp = match b.ramp {
            Some((active, per_level)) if per_level > 0 && active.is_finite() => {
                let levels = (features / per_level) as f32;
                [active.min(levels), per_level as f32, levels, 0.0]
            }
            _ => [1.0, 1.0, 0.0, 0.0],
        };
        Ok(BlendU {
            run: [n as u32, features as u32, flags, 0],
            coef: blend_coefficients(mode),
            ramp,
        })
    }

    /// `enc = a(m) h3 + b(m) h4` for `n` samples of `features` values (`[n, features]` each).
    pub fn blend_forward(
        &self,
        dev: &ComputeDevice,
        b: &Blend,
        enc: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let u = Self::blend_uniform(b, false)?;
        let n = b.samples;
        need_floats("enc", enc, (n * b.features) as u64, n)?;
        dev.run(
            &self.blend_fwd,
            &self.blend_fwd_layout,
            bytemuck::bytes_of(&u),
            &[b.h3, b.h4, b.m, enc],
            n as u64,
        )
    }

    /// Backward of [`ElementwiseKernels::blend_forward`]: `d_h3`, `d_h4` (`[n, features]`, written
    /// where the mode uses the grid) and `(m, d m)` pairs (`[n, 2]`; `d_m_extra`, e.g. the
    /// per-sample mask loss's gradient, added).
    pub fn blend_backward(
        &self,
        dev: &ComputeDevice,
        b: &Blend,
        d_enc: &wgpu::Buffer,
        d_m_extra: Option<&wgpu::Buffer>,
        (d_h3, d_h4, m_dm): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), GpuError> {
        let u = Self::blend_uniform(b, d_m_extra.is_some())?;
        let (mode, n) = (b.mode, b.samples);
        let nf = (n * b.features) as u64;
        need_floats("d_enc", d_enc, nf, n)?;
        if let Some(e) = d_m_extra {
            need_floats("extra d m", e, n as u64, n)?;
        }
        if mode.uses_h3() {
            need_floats("d h3", d_h3, nf, n)?;
        }
        if mode.uses_h4() {
            need_floats("d h4", d_h4, nf, n)?;
        }
        need_floats("(m, d m)", m_dm, 2 * n as u64, n)?;
        dev.run(
            &self.blend_bwd,
            &self.blend_bwd_layout,
            bytemuck::bytes_of(&u),
            &[
                b.h3,
                b.h4,
                b.m,
                d_enc,
                d_m_extra.unwrap_or(&self.unused),
                d_h3,
                d_h4,
                m_dm,
            ],
            n as u64,
        )
    }

    /// Copies `cols` columns of `rows` rows from `src` (at `from`) to `dst` (at `to`); the
    /// other entries of `dst` stay as they are.
    #[allow(clippy::too_many_arguments)]
    pub fn copy_columns(
        &self,
        dev: &ComputeDevice,
        rows: usize,
        cols: usize,
        src: &wgpu::Buffer,
        from: Columns,
        dst: &wgpu::Buffer,
        to: Columns,
    ) -> Result<(), GpuError> {
        for (what, buf, at) in [("source", src, from), ("destination", dst, to)] {
            if at.first + cols > at.stride {
                return Err(GpuError::Input(format!(
                    "{cols} {what} columns from column {} do not fit rows of {}",
                    at.first, at.stride
                )));
            }
            need_floats(
                what,
                buf,
                (rows as u64).saturating_mul(at.stride as u64),
                rows,
            )?;
        }
        let values = (rows as u64).saturating_mul(cols as u64);
        if values > u32::MAX as u64 || to.stride > u32::MAX as usize {
            return Err(GpuError::Input(format!(
                "{rows} rows x {cols} columns exceed 2^32"
            )));
        }
        let u = ColumnsU {
            a: [
                rows as u32,
                cols as u32,
                from.stride as u32,
                from.first as u32,
            ],
            b: [to.stride as u32, to.first as u32, 0, 0],
        };
        dev.run(
            &self.columns,
            &self.columns_layout,
            bytemuck::bytes_of(&u),
            &[src, dst],
            values,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The constants reproduce core's coefficients exactly.
    #[test]
    fn coefficients_match_core() {
        for mode in [
            BlendMode::Mt,
            BlendMode::Mst,
            BlendMode::Add,
            BlendMode::FourD,
            BlendMode::Static,
        ] {
            let [a0, a1, b0, b1] = blend_coefficients(mode);
            for m in [0.0f32, 0.3, 0.77, 1.0] {
                assert_eq!((a0 + a1 * m, b0 + b1 * m), mode.coefficients(m), "{mode:?}");
            }
        }
    }
}
