//! The view-direction encoding on the device: `msth_core::sh::sh4` (16 real spherical
//! harmonics) of each direction, one invocation per direction, written into rows of a wider
//! buffer if asked (the colour MLP's input rows: SH first, then the geometry features). Forward
//! only: the encoding has no parameters and core computes no direction gradient. Checked
//! against the CPU in `tests/mlp.rs`.

use bytemuck::{Pod, Zeroable};
use msth_core::sh::SH_COEFFS;

use crate::device::ComputeDevice;
use crate::mlp::need_floats;
use crate::GpuError;

/// The kernel `sh_encode` (after [`sh4_wgsl`]).
pub const SH_WGSL: &str = include_str!("../shaders/sh.wgsl");

/// The render kernels' `sh` module ([`crate::shaders`], the one WGSL copy of the SH constants):
/// `fn sh4` and the private array it writes.
pub fn sh4_wgsl() -> Result<String, GpuError> {
    crate::shaders::compose_render(&["sh"]).map_err(|e| GpuError::Shader(e.to_string()))
}

/// The kernel's `Sh` uniform: `(directions, row stride, first column, 0)`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct ShU {
    run: [u32; 4],
}

/// The compiled SH kernel of one device.
pub struct ShKernel {
    layout: wgpu::BindGroupLayout,
    pipeline: wgpu::ComputePipeline,
}

impl ShKernel {
    pub fn new(dev: &ComputeDevice) -> Result<Self, GpuError> {
        // Binding 1 directions (3 floats each), 2 output rows.
        let layout = dev.bind_layout("sh", &[true, false]);
        let source = format!("{}\n{SH_WGSL}", sh4_wgsl()?);
        let pipeline = dev.pipeline("sh", &source, "sh_encode", &layout)?;
        Ok(ShKernel { layout, pipeline })
    }

    /// Encodes `n` directions (`dirs`: 3 floats each, unit length) into `out`: the 16 values of
    /// direction `i` at `i * stride + column`. Other entries of `out` are left as they are.
    pub fn encode(
        &self,
        dev: &ComputeDevice,
        dirs: &wgpu::Buffer,
        n: usize,
        out: &wgpu::Buffer,
        stride: usize,
        column: usize,
    ) -> Result<(), GpuError> {
        if column + SH_COEFFS > stride {
            return Err(GpuError::Input(format!(
                "{SH_COEFFS} values from column {column} do not fit rows of {stride}"
            )));
        }
        if (n as u64).saturating_mul(stride as u64) > u32::MAX as u64 {
            return Err(GpuError::Input(format!(
                "{n} rows of {stride} floats exceed 2^32"
            )));
        }
        need_floats("directions", dirs, n as u64 * 3, n)?;
        need_floats("output", out, (n * stride) as u64, n)?;
        let u = ShU {
            run: [n as u32, stride as u32, column as u32, 0],
        };
        dev.run(
            &self.pipeline,
            &self.layout,
            bytemuck::bytes_of(&u),
            &[dirs, out],
            n as u64,
        )
    }

    /// [`ShKernel::encode`] from and to host memory: `[n, 16]`.
    pub fn encode_host(
        &self,
        dev: &ComputeDevice,
        dirs: &[[f32; 3]],
    ) -> Result<Vec<f32>, GpuError> {
        let d = dev.buffer_f32("directions", bytemuck::cast_slice(dirs))?;
        let out = dev.zeros_f32("sh", dirs.len() * SH_COEFFS)?;
        self.encode(dev, &d, dirs.len(), &out, SH_COEFFS, 0)?;
        dev.read_f32(&out, dirs.len() * SH_COEFFS)
    }
}
