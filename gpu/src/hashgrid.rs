//! The multi-resolution hash-grid encoding (3D and 4D) on the device, forward and backward, one
//! invocation per (sample, level) pair: exactly `msth_core::grid::GridLayout`'s geometry (index
//! rules, dense and hashed levels, per-axis resolutions, multilinear weights), checked against
//! its CPU reference in `tests/hashgrid.rs`.
//!
//! - [`GpuGrid`]: one grid's level descriptors and where its table lies in a table buffer;
//! - [`HashGridKernels`]: the compiled forward and backward, the backward with native f32 atomics
//!   or a compare-exchange loop ([`AtomicMode`]);
//! - [`encoding_counts`]: bytes and atomics per sample, the figures GPU time follows.

use std::sync::{Arc, Mutex};

use bytemuck::{Pod, Zeroable};
use msth_core::grid::{GridLayout, MAX_LEVELS};

use crate::device::{ComputeDevice, KernelPair, PairSource};
use crate::layout::LevelU;
use crate::GpuError;

/// The common part of both kernels (bindings 0-1, cell and corner rules).
pub const HASHGRID_WGSL: &str = include_str!("../shaders/hashgrid.wgsl");
/// The forward entry point `encode_forward` (after [`HASHGRID_WGSL`]).
pub const HASHGRID_FORWARD_WGSL: &str = include_str!("../shaders/hashgrid_forward.wgsl");
/// The backward entry point `encode_backward` (after [`HASHGRID_WGSL`] and an atomic variant).
pub const HASHGRID_BACKWARD_WGSL: &str = include_str!("../shaders/hashgrid_backward.wgsl");
/// `add_grad` with native f32 atomics.
pub const ATOMIC_NATIVE_WGSL: &str = include_str!("../shaders/atomic_native.wgsl");
/// `add_grad` with a compare-exchange loop on the u32 bit pattern.
pub const ATOMIC_CAS_WGSL: &str = include_str!("../shaders/atomic_cas.wgsl");

/// Largest features per level the kernels hold (core allows 1, 2, 4, 8).
pub const MAX_FEATURES: usize = 8;

/// How a backward pass adds into shared gradient entries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AtomicMode {
    /// `atomicAdd` on `atomic<f32>` (needs `wgpu::Features::SHADER_FLOAT32_ATOMIC`).
    NativeF32,
    /// `atomicCompareExchangeWeak` on the u32 bit pattern, retried until no other invocation
    /// wrote in between (WebGPU core: works on every adapter).
    CompareExchange,
}

impl AtomicMode {
    /// Native f32 atomics where the device has them, the compare-exchange loop elsewhere.
    pub fn best(dev: &ComputeDevice) -> Self {
        if dev.has_float_atomics() {
            AtomicMode::NativeF32
        } else {
            AtomicMode::CompareExchange
        }
    }

    /// The WGSL of `add_grad` and the `grad` binding for this mode.
    pub fn wgsl(self) -> &'static str {
        match self {
            AtomicMode::NativeF32 => ATOMIC_NATIVE_WGSL,
            AtomicMode::CompareExchange => ATOMIC_CAS_WGSL,
        }
    }
}

/// The kernels' `Grid` uniform (16 + 16 + 48 * 32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GridParamsU {
    /// `(dims, features, levels, hash mask)`.
    shape: [u32; 4],
    /// `(samples, offset of the grid in the table buffer in floats, 0, 0)`.
    run: [u32; 4],
    levels: [LevelU; MAX_LEVELS],
}

/// One grid on the device: its level descriptors and its table's offset (in floats) inside the
/// table buffer, e.g. the grid's slice of the flat parameter buffer; the gradient buffer has the
/// same layout.
#[derive(Clone, Debug)]
pub struct GpuGrid {
    layout: GridLayout,
    offset: usize,
    params: GridParamsU,
}

impl GpuGrid {
    /// Descriptors of `layout` with its table starting `offset_floats` into the table buffer.
    pub fn new(layout: &GridLayout, offset_floats: usize) -> Result<Self, GpuError> {
        let bad = |m: String| Err(GpuError::Input(m));
        if !(layout.dims == 3 || layout.dims == 4) {
            return bad(format!("a grid of {} dimensions (3 or 4)", layout.dims));
        }
        if layout.features == 0 || layout.features > MAX_FEATURES {
            return bad(format!(
                "{} features per level (1 to {MAX_FEATURES})",
                layout.features
            ));
        }
        if layout.levels.is_empty() || layout.levels.len() > MAX_LEVELS {
            return bad(format!(
                "{} levels (1 to {MAX_LEVELS})",
                layout.levels.len()
            ));
        }
        if !layout.table_size.is_power_of_two() || layout.table_size > u32::MAX as usize {
            return bad(format!("a table of {} rows", layout.table_size));
        }
        let end = offset_floats.checked_add(layout.num_params);
        if end.is_none_or(|e| e > u32::MAX as usize) {
            return bad(format!(
                "a grid of {} values at offset {offset_floats}: beyond 2^32 floats",
                layout.num_params
            ));
        }
        let mut levels = [LevelU::default(); MAX_LEVELS];
        for (slot, lv) in levels.iter_mut().zip(&layout.levels) {
            *slot = LevelU {
                scale: lv.scale,
                stride: lv.stride,
                info: [lv.offset as u32, lv.dense as u32, lv.rows as u32, 0],
            };
        }
        let params = GridParamsU {
            shape: [
                layout.dims as u32,
                layout.features as u32,
                layout.levels.len() as u32,
                (layout.table_size - 1) as u32,
            ],
            run: [0, offset_floats as u32, 0, 0],
            levels,
        };
        Ok(GpuGrid {
            layout: layout.clone(),
            offset: offset_floats,
            params,
        })
    }

    pub fn layout(&self) -> &GridLayout {
        &self.layout
    }

    /// Features per sample (`levels * F`).
    pub fn output_dim(&self) -> usize {
        self.layout.output_dim()
    }

    /// The uniform for a pass over `n` samples, after checking the buffers' sizes.
    fn uniform(
        &self,
        n: usize,
        table: &wgpu::Buffer,
        points: &wgpu::Buffer,
        per_sample: &wgpu::Buffer,
    ) -> Result<(GridParamsU, u64), GpuError> {
        let invocations = (n as u64).saturating_mul(self.layout.levels.len() as u64);
        if invocations > u32::MAX as u64 {
            return Err(GpuError::Input(format!(
                "{n} samples x {} levels exceed 2^32 invocations",
                self.layout.levels.len()
            )));
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
            "table",
            table,
            (self.offset + self.layout.num_params) as u64,
        )?;
        need("points", points, n as u64 * 4)?;
        need("features", per_sample, n as u64 * self.output_dim() as u64)?;
        let mut p = self.params;
        p.run[0] = n as u32;
        Ok((p, invocations))
    }
}

/// `(dimensions, features per level)`: what a compiled kernel pair is specialised to.
type GridShape = (usize, usize);

/// The compiled hash-grid kernels of one device: one forward and backward per grid shape
/// (dimensions, features per level), compiled on first use. Why per shape: with `DIMS` and `NF`
/// constants, the corner and feature loops have constant trip counts, which compilers unroll.
/// Measured in one run each against the kernels that read the counts from the uniform
/// (`examples/bench_encode.rs`): on lavapipe the forward runs 1.7-3.1x and the backward
/// 1.2-2.0x faster; on an NVIDIA H200 nothing changes (its compiler already did this; there
/// the figures of a kernel vary up to 2x between runs of 262,144 samples, more than any
/// difference between the two).
pub struct HashGridKernels {
    mode: AtomicMode,
    shapes: Mutex<Vec<(GridShape, Arc<KernelPair>)>>,
}

impl HashGridKernels {
    /// Prepares the kernels, the backward with `mode`; [`AtomicMode::NativeF32`] on a device
    /// without f32 atomics is a [`GpuError::MissingFeature`]. Compiles the shape of the demo's
    /// grids (3D, 2 features) now, so that a compile error shows here; other shapes compile
    /// when first run.
    pub fn new(dev: &ComputeDevice, mode: AtomicMode) -> Result<Self, GpuError> {
        let k = HashGridKernels {
            mode,
            shapes: Mutex::new(Vec::new()),
        };
        k.kernels(dev, 3, 2)?;
        Ok(k)
    }

    /// The kernels of grids with `dims` dimensions and `features` per level.
    fn kernels(
        &self,
        dev: &ComputeDevice,
        dims: usize,
        features: usize,
    ) -> Result<Arc<KernelPair>, GpuError> {
        let mut shapes = self.shapes.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, k)) = shapes.iter().find(|(s, _)| *s == (dims, features)) {
            return Ok(k.clone());
        }
        let common =
            format!("const DIMS: u32 = {dims}u;\nconst NF: u32 = {features}u;\n{HASHGRID_WGSL}");
        // Binding 1 points, 2 table (forward) or d_features (backward), 3 features or grad.
        let k = Arc::new(KernelPair::new(
            dev,
            self.mode,
            PairSource {
                label: &format!("hashgrid {dims}D F{features}"),
                common: &common,
                forward: (HASHGRID_FORWARD_WGSL, "encode_forward"),
                backward: (HASHGRID_BACKWARD_WGSL, "encode_backward"),
            },
        )?);
        shapes.push(((dims, features), k.clone()));
        Ok(k)
    }

    pub fn mode(&self) -> AtomicMode {
        self.mode
    }

    /// Features of `n` samples: `points` holds `(x, y, z, t)` per sample (3D grids ignore `t`),
    /// `table` the grid's values at its offset; writes `n * levels * F` floats to `features`,
    /// sample-major (`[n, levels, F]`).
    pub fn forward(
        &self,
        dev: &ComputeDevice,
        grid: &GpuGrid,
        table: &wgpu::Buffer,
        points: &wgpu::Buffer,
        n: usize,
        features: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (u, inv) = grid.uniform(n, table, points, features)?;
        let l = grid.layout();
        self.kernels(dev, l.dims, l.features)?.run(
            dev,
            false,
            bytemuck::bytes_of(&u),
            &[points, table, features],
            inv,
        )
    }

    /// Adds `d loss / d table` of `n` samples into `grad` (the table's layout, at the grid's
    /// offset), given `d_features` laid out as [`HashGridKernels::forward`]'s output. Entries
    /// accumulate: clear `grad` first for a fresh gradient.
    pub fn backward(
        &self,
        dev: &ComputeDevice,
        grid: &GpuGrid,
        points: &wgpu::Buffer,
        d_features: &wgpu::Buffer,
        n: usize,
        grad: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let (u, inv) = grid.uniform(n, grad, points, d_features)?;
        let l = grid.layout();
        self.kernels(dev, l.dims, l.features)?.run(
            dev,
            true,
            bytemuck::bytes_of(&u),
            &[points, d_features, grad],
            inv,
        )
    }

    /// [`HashGridKernels::forward`] from and to host memory: `table` is the grid's own slice.
    pub fn forward_host(
        &self,
        dev: &ComputeDevice,
        layout: &GridLayout,
        table: &[f32],
        points: &[[f32; 4]],
    ) -> Result<Vec<f32>, GpuError> {
        let grid = GpuGrid::new(layout, 0)?;
        check_len("table", table.len(), layout.num_params)?;
        let t = dev.buffer_f32("hash table", table)?;
        let p = dev.buffer_f32("points", bytemuck::cast_slice(points))?;
        let n_out = points.len() * grid.output_dim();
        let out = dev.zeros_f32("features", n_out)?;
        self.forward(dev, &grid, &t, &p, points.len(), &out)?;
        dev.read_f32(&out, n_out)
    }

    /// [`HashGridKernels::backward`] from and to host memory: the gradient of the grid's own
    /// slice (zero where no sample reached).
    pub fn backward_host(
        &self,
        dev: &ComputeDevice,
        layout: &GridLayout,
        points: &[[f32; 4]],
        d_features: &[f32],
    ) -> Result<Vec<f32>, GpuError> {
        let grid = GpuGrid::new(layout, 0)?;
        check_len(
            "d_features",
            d_features.len(),
            points.len() * grid.output_dim(),
        )?;
        let p = dev.buffer_f32("points", bytemuck::cast_slice(points))?;
        let d = dev.buffer_f32("d features", d_features)?;
        let g = dev.zeros_f32("hash gradient", layout.num_params)?;
        self.backward(dev, &grid, &p, &d, points.len(), &g)?;
        dev.read_f32(&g, layout.num_params)
    }
}

fn check_len(what: &str, got: usize, want: usize) -> Result<(), GpuError> {
    if got == want {
        Ok(())
    } else {
        Err(GpuError::Input(format!(
            "{what} holds {got} values; {want} expected"
        )))
    }
}

/// What one sample costs one grid's kernels, the figures GPU time follows (the encoding is
/// memory- and atomic-bound: a handful of flops per byte).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EncodingCounts {
    /// Corner reads of the forward: `levels * 2^D * F * 4` bytes of table, in `levels * 2^D`
    /// scattered rows of `F * 4` bytes.
    pub forward_table_bytes: u64,
    /// Features written by the forward (and `d_features` read by the backward):
    /// `levels * F * 4` bytes.
    pub feature_bytes: u64,
    /// Scattered rows per sample (`levels * 2^D`), each a separate memory transaction.
    pub rows: u64,
    /// Atomic adds issued by the backward (every non-zero contribution): `levels * 2^D * F`.
    pub atomics: u64,
    /// Of those, atomics into dense levels (coarse levels: few rows, shared by many samples,
    /// the contended ones).
    pub dense_atomics: u64,
    /// Size of the whole table in bytes.
    pub table_bytes: u64,
}

/// [`EncodingCounts`] of one sample of `layout` (at most: a zero contribution issues no atomic).
pub fn encoding_counts(layout: &GridLayout) -> EncodingCounts {
    let corners = 1u64 << layout.dims;
    let l = layout.levels.len() as u64;
    let f = layout.features as u64;
    let dense = layout.levels.iter().filter(|lv| lv.dense).count() as u64;
    EncodingCounts {
        forward_table_bytes: l * corners * f * 4,
        feature_bytes: l * f * 4,
        rows: l * corners,
        atomics: l * corners * f,
        dense_atomics: dense * corners * f,
        table_bytes: layout.num_params as u64 * 4,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::presets::{reference_model, REFERENCE_PRESETS};

    /// The table of the crate header: per-sample counts of the main field's grids of a
    /// 300-frame scene at the demo (fast preset) and paper configurations.
    #[test]
    fn counts_match_the_crate_header() {
        let mut rows = Vec::new();
        for (_, preset) in REFERENCE_PRESETS {
            let cfg = reference_model(preset);
            for g in [&cfg.field.encoding.grid3, &cfg.field.encoding.grid4] {
                let c = encoding_counts(&GridLayout::new(g));
                let dense = GridLayout::new(g).levels.iter().filter(|l| l.dense).count();
                println!("{preset:?} {}D: {c:?}, {dense} dense levels", g.dims());
                rows.push((
                    c.rows,
                    c.forward_table_bytes,
                    c.feature_bytes,
                    c.atomics,
                    c.dense_atomics,
                    dense,
                    (c.table_bytes as f64 / 1048576.0 * 10.0).round() / 10.0,
                ));
            }
        }
        assert_eq!(
            rows,
            vec![
                (96, 768, 96, 192, 48, 3, 2.6),
                (192, 1536, 96, 384, 0, 0, 3.0),
                (128, 1024, 128, 256, 80, 5, 46.7),
                (256, 2048, 128, 512, 64, 2, 58.7),
            ]
        );
    }
}
