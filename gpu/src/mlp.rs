//! The bias-free MLPs on the device, forward and backward, batched over samples and tiled through
//! workgroup memory: exactly `msth_core::mlp::MlpLayout` (ReLU on hidden layers, a raw last
//! layer, weights of layer `k` row-major `[dims[k], dims[k + 1]]` at the layout's offsets inside
//! the MLP's named slice of the flat parameter buffer), followed by the output activation of
//! `msth_core::field` ([`OutputActivation`]); checked against the CPU in `tests/mlp.rs`.
//!
//! - [`GpuMlp`]: one MLP's shape, its slice's offset and its output activation;
//! - [`MlpKernels`]: the compiled forward and backward (weight gradients added once per
//!   workgroup with native f32 atomics or a compare-exchange loop, [`AtomicMode`]);
//! - [`mlp_counts`]: flops, bytes and atomics per sample.
//!
//! One workgroup of [`TILE`] invocations takes [`TILE`] samples, one invocation per sample, and
//! stages each layer's whole weight matrix in 16 KiB of workgroup memory (every width at most
//! [`MAX_WIDTH`]); the backward reduces the weight gradient of its tile in registers (each
//! invocation owns one 4x4 block of the layer's weights) and then issues one atomic add per
//! weight: [`TILE`] samples share each atomic.

use bytemuck::{Pod, Zeroable};
use msth_core::mlp::MlpLayout;

use crate::device::ComputeDevice;
use crate::hashgrid::AtomicMode;
use crate::GpuError;

/// The common part of both kernels (uniform, bindings 1-2, weight staging).
pub const MLP_WGSL: &str = include_str!("../shaders/mlp.wgsl");
/// The forward entry point `mlp_forward` (after [`MLP_WGSL`]).
pub const MLP_FORWARD_WGSL: &str = include_str!("../shaders/mlp_forward.wgsl");
/// The backward entry point `mlp_backward` (after [`MLP_WGSL`] and an atomic variant).
pub const MLP_BACKWARD_WGSL: &str = include_str!("../shaders/mlp_backward.wgsl");

/// Samples per workgroup (one invocation each): the tile whose weight gradients are reduced in
/// registers before one atomic add per weight.
pub const TILE: usize = 256;
/// The widest layer the kernels hold (a 64 x 64 layer is the 16 KiB of workgroup memory that
/// WebGPU guarantees, `max_compute_workgroup_storage_size`).
pub const MAX_WIDTH: usize = 64;
/// The most layers the kernels' uniform describes (its 12 slots of `dims`).
pub const MAX_LAYERS: usize = 11;
const _: () = assert!(MAX_LAYERS < 12);

const FLAG_ACTS: u32 = 1;
const FLAG_D_INPUT: u32 = 2;

/// What follows the raw last layer (as `msth_core::field` applies it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputActivation {
    /// The raw outputs (the proposal's and the field's MLPs before their activation).
    Identity,
    /// `sigmoid` on every output (the colour MLP: rgb).
    Sigmoid,
    /// `trunc_exp` on output 0 (the density), the others raw (the geometry features): the
    /// density MLPs. The backward uses `trunc_exp_grad` (the clamped exp) as the CPU does.
    Density,
}

impl OutputActivation {
    fn code(self) -> u32 {
        match self {
            OutputActivation::Identity => 0,
            OutputActivation::Sigmoid => 1,
            OutputActivation::Density => 2,
        }
    }
}

/// The kernels' `Mlp` uniform (see `shaders/mlp.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct MlpU {
    run: [u32; 4],
    info: [u32; 4],
    dims: [u32; 12],
    woff: [u32; 12],
    aoff: [u32; 12],
}

/// One MLP on the device: its shape, its weights' offset (in floats) inside the parameter buffer
/// (its named slice of the flat buffer; the gradient buffer has the same layout) and its output
/// activation.
#[derive(Clone, Debug)]
pub struct GpuMlp {
    layout: MlpLayout,
    offset: usize,
    activation: OutputActivation,
    acts_stride: usize,
}

impl GpuMlp {
    /// Checks the shape against the kernels' limits ([`MAX_WIDTH`], [`MAX_LAYERS`]).
    pub fn new(
        layout: &MlpLayout,
        offset_floats: usize,
        activation: OutputActivation,
    ) -> Result<Self, GpuError> {
        let layers = layout.num_layers();
        if layers == 0 || layers > MAX_LAYERS {
            return Err(GpuError::Input(format!(
                "an MLP of {layers} layers (1 to {MAX_LAYERS})"
            )));
        }
        if layout.dims.contains(&0) {
            return Err(GpuError::Input(format!(
                "an MLP with a layer of width 0 (dims {:?})",
                layout.dims
            )));
        }
        if let Some(&w) = layout.dims.iter().find(|&&w| w > MAX_WIDTH) {
            return Err(GpuError::Limit {
                what: format!("an MLP layer of width {w} (dims {:?})", layout.dims),
                amount: w as u64,
                unit: "units",
                limit: "msth-gpu's MLP width (a 64 x 64 layer fills WebGPU's 16 KiB of workgroup memory)",
                max: MAX_WIDTH as u64,
            });
        }
        let end = offset_floats.checked_add(layout.num_params);
        if end.is_none_or(|e| e > u32::MAX as usize) {
            return Err(GpuError::Input(format!(
                "an MLP of {} weights at offset {offset_floats}: beyond 2^32 floats",
                layout.num_params
            )));
        }
        Ok(GpuMlp {
            layout: layout.clone(),
            offset: offset_floats,
            activation,
            acts_stride: layout.dims[1..].iter().sum(),
        })
    }

    pub fn layout(&self) -> &MlpLayout {
        &self.layout
    }

    /// Floats per sample of the activations the forward keeps for the backward: every hidden
    /// layer's output (after the ReLU), then the raw last layer.
    pub fn acts_stride(&self) -> usize {
        self.acts_stride
    }

    fn uniform(&self, n: usize, flags: u32, d_input_from: usize) -> MlpU {
        let l = &self.layout;
        let mut u = MlpU::zeroed();
        u.run = [n as u32, l.num_layers() as u32, self.offset as u32, flags];
        u.info = [
            self.activation.code(),
            self.acts_stride as u32,
            d_input_from as u32,
            0,
        ];
        let mut a = 0;
        for k in 0..l.num_layers() {
            u.woff[k] = l.offsets[k] as u32;
            u.aoff[k] = a as u32;
            a += l.dims[k + 1];
        }
        for (slot, &d) in u.dims.iter_mut().zip(&l.dims) {
            *slot = d as u32;
        }
        u
    }
}

/// An error unless `buf` holds `floats` f32 for a pass over `n` samples.
pub(crate) fn need_floats(
    what: &str,
    buf: &wgpu::Buffer,
    floats: u64,
    n: usize,
) -> Result<(), GpuError> {
    if buf.size() < floats.saturating_mul(4) {
        Err(GpuError::Input(format!(
            "the {what} buffer holds {} bytes; {n} samples need {}",
            buf.size(),
            floats.saturating_mul(4)
        )))
    } else {
        Ok(())
    }
}

/// The compiled MLP kernels of one device.
pub struct MlpKernels {
    forward_layout: wgpu::BindGroupLayout,
    backward_layout: wgpu::BindGroupLayout,
    forward: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
    mode: AtomicMode,
    /// A one-word buffer bound where an optional output is not asked for.
    unused: wgpu::Buffer,
}

impl MlpKernels {
    /// Compiles forward and backward, the backward's weight-gradient adds with `mode`;
    /// [`AtomicMode::NativeF32`] on a device without f32 atomics is a
    /// [`GpuError::MissingFeature`].
    pub fn new(dev: &ComputeDevice, mode: AtomicMode) -> Result<Self, GpuError> {
        if mode == AtomicMode::NativeF32 && !dev.has_float_atomics() {
            return Err(GpuError::MissingFeature(format!(
                "{} has no f32 atomics (wgpu::Features::SHADER_FLOAT32_ATOMIC)",
                dev.adapter_name()
            )));
        }
        // Forward: 1 params, 2 input, 3 output, 4 acts.
        let forward_layout = dev.bind_layout("mlp forward", &[true, true, false, false]);
        // Backward: 1 params, 2 input, 3 grad (the atomic variant's binding), 4 acts,
        // 5 d_output, 6 d_input.
        let backward_layout =
            dev.bind_layout("mlp backward", &[true, true, false, true, true, false]);
        let forward = dev.pipeline(
            "mlp forward",
            &format!("{MLP_WGSL}\n{MLP_FORWARD_WGSL}"),
            "mlp_forward",
            &forward_layout,
        )?;
        let backward = dev.pipeline(
            "mlp backward",
            &format!("{MLP_WGSL}\n{}\n{MLP_BACKWARD_WGSL}", mode.wgsl()),
            "mlp_backward",
            &backward_layout,
        )?;
        let unused = dev.zeros_f32("unused", 1)?;
        Ok(MlpKernels {
            forward_layout,
            backward_layout,
            forward,
            backward,
            mode,
            unused,
        })
    }

    pub fn mode(&self) -> AtomicMode {
        self.mode
    }

    /// What to ask [`ComputeDevice::run`] for `n` samples: it dispatches one workgroup per 64
    /// "invocations", and each of these kernels' workgroups ([`TILE`] invocations) takes a tile
    /// of [`TILE`] samples, so 64 per tile.
    fn invocations(n: usize) -> Result<u64, GpuError> {
        if n > u32::MAX as usize - TILE {
            return Err(GpuError::Input(format!("{n} samples exceed 2^32")));
        }
        Ok(n.div_ceil(TILE) as u64 * 64)
    }

    /// The MLP over `n` samples: `input` `[n, dims[0]]` (sample-major), `params` the buffer
    /// holding the weights at the MLP's offset; writes the activated outputs to `output`
    /// `[n, dims[L]]` and, when `acts` is given (training), the activations the backward needs
    /// (`[n, acts_stride]`).
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &self,
        dev: &ComputeDevice,
        mlp: &GpuMlp,
        params: &wgpu::Buffer,
        input: &wgpu::Buffer,
        n: usize,
        output: &wgpu::Buffer,
        acts: Option<&wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        let l = &mlp.layout;
        let inv = Self::invocations(n)?;
        need_floats("parameter", params, (mlp.offset + l.num_params) as u64, n)?;
        need_floats("input", input, (n * l.input_dim()) as u64, n)?;
        need_floats("output", output, (n * l.output_dim()) as u64, n)?;
        let flags = if let Some(a) = acts {
            need_floats("activations", a, (n * mlp.acts_stride) as u64, n)?;
            FLAG_ACTS
        } else {
            0
        };
        let u = mlp.uniform(n, flags, 0);
        dev.run(
            &self.forward,
            &self.forward_layout,
            bytemuck::bytes_of(&u),
            &[params, input, output, acts.unwrap_or(&self.unused)],
            inv,
        )
    }

    /// Backward of a [`MlpKernels::forward`] that kept `acts`: given `d_output` (d loss / d
    /// activated outputs, `[n, dims[L]]`), adds d loss / d weights into `grad` (the parameter
    /// buffer's layout: entries accumulate, clear it first for a fresh gradient) and, with
    /// `d_input = Some((from, buf))`, writes d loss / d input columns `from..dims[0]` into `buf`
    /// (`[n, dims[0] - from]`; the colour MLP needs none for its direction encoding).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        dev: &ComputeDevice,
        mlp: &GpuMlp,
        params: &wgpu::Buffer,
        input: &wgpu::Buffer,
        acts: &wgpu::Buffer,
        d_output: &wgpu::Buffer,
        n: usize,
        grad: &wgpu::Buffer,
        d_input: Option<(usize, &wgpu::Buffer)>,
    ) -> Result<(), GpuError> {
        let l = &mlp.layout;
        let inv = Self::invocations(n)?;
        let end = (mlp.offset + l.num_params) as u64;
        need_floats("parameter", params, end, n)?;
        need_floats("gradient", grad, end, n)?;
        need_floats("input", input, (n * l.input_dim()) as u64, n)?;
        need_floats("activations", acts, (n * mlp.acts_stride) as u64, n)?;
        need_floats("d_output", d_output, (n * l.output_dim()) as u64, n)?;
        let (flags, from, d_in) = match d_input {
            Some((from, buf)) => {
                if from >= l.input_dim() {
                    return Err(GpuError::Input(format!(
                        "an input gradient from column {from} of {}",
                        l.input_dim()
                    )));
                }
                need_floats("d_input", buf, (n * (l.input_dim() - from)) as u64, n)?;
                (FLAG_D_INPUT, from, buf)
            }
            None => (0, 0, &self.unused),
        };
        let u = mlp.uniform(n, flags, from);
        dev.run(
            &self.backward,
            &self.backward_layout,
            bytemuck::bytes_of(&u),
            &[params, input, grad, acts, d_output, d_in],
            inv,
        )
    }

    /// [`MlpKernels::forward`] from and to host memory (`weights`: the MLP's own slice):
    /// `(outputs, acts)`.
    pub fn forward_host(
        &self,
        dev: &ComputeDevice,
        mlp: &GpuMlp,
        weights: &[f32],
        input: &[f32],
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let (mlp, n) = host_shape(mlp, weights, input)?;
        let w = dev.buffer_f32("mlp weights", weights)?;
        let x = dev.buffer_f32("mlp input", input)?;
        let out = dev.zeros_f32("mlp output", n * mlp.layout.output_dim())?;
        let acts = dev.zeros_f32("mlp activations", n * mlp.acts_stride)?;
        self.forward(dev, &mlp, &w, &x, n, &out, Some(&acts))?;
        Ok((
            dev.read_f32(&out, n * mlp.layout.output_dim())?,
            dev.read_f32(&acts, n * mlp.acts_stride)?,
        ))
    }

    /// Forward and backward from and to host memory: `(weight gradient, input gradient of
    /// columns d_input_from..)` for `d_output` per sample.
    pub fn backward_host(
        &self,
        dev: &ComputeDevice,
        mlp: &GpuMlp,
        weights: &[f32],
        input: &[f32],
        d_output: &[f32],
        d_input_from: usize,
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let (mlp, n) = host_shape(mlp, weights, input)?;
        let l = &mlp.layout;
        if d_output.len() != n * l.output_dim() {
            return Err(GpuError::Input(format!(
                "{} output gradients for {n} samples of {} outputs",
                d_output.len(),
                l.output_dim()
            )));
        }
        let w = dev.buffer_f32("mlp weights", weights)?;
        let x = dev.buffer_f32("mlp input", input)?;
        let out = dev.zeros_f32("mlp output", n * l.output_dim())?;
        let acts = dev.zeros_f32("mlp activations", n * mlp.acts_stride)?;
        self.forward(dev, &mlp, &w, &x, n, &out, Some(&acts))?;
        let dy = dev.buffer_f32("mlp d_output", d_output)?;
        let g = dev.zeros_f32("mlp gradient", l.num_params)?;
        let cols = l.input_dim().saturating_sub(d_input_from);
        let dx = dev.zeros_f32("mlp d_input", n * cols)?;
        self.backward(
            dev,
            &mlp,
            &w,
            &x,
            &acts,
            &dy,
            n,
            &g,
            Some((d_input_from, &dx)),
        )?;
        Ok((
            dev.read_f32(&g, l.num_params)?,
            dev.read_f32(&dx, n * cols)?,
        ))
    }
}

/// `mlp` at offset 0 (host calls pass its own slice) and the sample count of `input`.
fn host_shape(mlp: &GpuMlp, weights: &[f32], input: &[f32]) -> Result<(GpuMlp, usize), GpuError> {
    let l = &mlp.layout;
    if weights.len() != l.num_params || !input.len().is_multiple_of(l.input_dim()) {
        return Err(GpuError::Input(format!(
            "{} weights and {} inputs for an MLP of {} weights and {} inputs per sample",
            weights.len(),
            input.len(),
            l.num_params,
            l.input_dim()
        )));
    }
    Ok((
        GpuMlp::new(l, 0, mlp.activation)?,
        input.len() / l.input_dim(),
    ))
}

/// What one sample costs one MLP's kernels (the weights themselves are read once per workgroup
/// of [`TILE`] samples, from L2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MlpCounts {
    /// Weights (`sum dims[k] * dims[k + 1]`).
    pub weights: u64,
    /// Forward flops: one multiply-add (2 flops) per weight.
    pub forward_flops: u64,
    /// Backward flops: weight gradient and input gradient, 2 multiply-adds per weight (the first
    /// layer's input gradient counted: the density MLPs need it, the colour MLP half of it).
    pub backward_flops: u64,
    /// Global-memory bytes of the forward: input read, outputs and kept activations written,
    /// plus the sample's share of the weight reads.
    pub forward_bytes: u64,
    /// Global-memory bytes of the backward: input, raw outputs and d_output read, each hidden
    /// activation read twice (the weight gradient's tile and the ReLU mask), d_input written
    /// (all of it counted), plus the sample's share of the weight reads.
    pub backward_bytes: u64,
    /// Atomic adds of the backward per workgroup of [`TILE`] samples (one per non-zero weight
    /// gradient): `weights / TILE` per sample.
    pub atomics_per_tile: u64,
}

/// [`MlpCounts`] of one sample through `layout`.
pub fn mlp_counts(layout: &MlpLayout) -> MlpCounts {
    let weights = layout.num_params as u64;
    let d = |k: usize| layout.dims[k] as u64;
    let layers = layout.num_layers();
    let hidden: u64 = (1..layers).map(d).sum();
    let acts = hidden + d(layers);
    let share = (weights * 4).div_ceil(TILE as u64);
    MlpCounts {
        weights,
        forward_flops: 2 * weights,
        backward_flops: 4 * weights,
        forward_bytes: 4 * (d(0) + d(layers) + acts) + share,
        backward_bytes: 4 * (2 * d(0) + 2 * hidden + 2 * d(layers)) + share,
        atomics_per_tile: weights,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::presets::{reference_model, REFERENCE_PRESETS};
    use msth_core::field::ModelLayout;

    #[test]
    fn uniform_size_matches_the_wgsl_struct() {
        // run, info: 2 x 16 bytes; dims, woff, aoff: 3 x array<vec4<u32>, 3>.
        assert_eq!(std::mem::size_of::<MlpU>(), 32 + 3 * 48);
    }

    /// The MLP rows of the crate header: the demo (fast preset) and paper models' MLPs fit the
    /// kernels, and their per-sample counts.
    #[test]
    fn counts_match_the_crate_header() {
        let mut rows = Vec::new();
        for (_, preset) in REFERENCE_PRESETS {
            let cfg = reference_model(preset);
            let m = ModelLayout::new(&cfg);
            for l in [
                &m.field.density.0,
                &m.field.color.0,
                &m.proposal.field.density.0,
            ] {
                GpuMlp::new(l, 0, OutputActivation::Identity).unwrap();
                let c = mlp_counts(l);
                println!("{preset:?} {:?}: {c:?}", l.dims);
                rows.push((
                    l.dims.clone(),
                    c.weights,
                    c.forward_flops,
                    c.backward_flops,
                    c.forward_bytes,
                    c.backward_bytes,
                ));
            }
        }
        assert_eq!(
            rows,
            vec![
                (vec![24, 64, 16], 2560, 5120, 10240, 520, 872),
                (vec![31, 64, 64, 3], 6272, 12544, 25088, 758, 1394),
                (vec![10, 16, 1], 176, 352, 704, 115, 219),
                (vec![32, 64, 16], 3072, 6144, 12288, 560, 944),
                (vec![31, 64, 64, 3], 6272, 12544, 25088, 758, 1394),
                (vec![10, 16, 1], 176, 352, 704, 115, 219),
            ]
        );
    }

    #[test]
    fn too_wide_or_deep_mlps_are_errors() {
        let e =
            GpuMlp::new(&MlpLayout::new(&[8, 128, 3]), 0, OutputActivation::Sigmoid).unwrap_err();
        assert!(matches!(e, GpuError::Limit { max: 64, .. }), "{e}");
        let deep = MlpLayout::new(&[4; 13]);
        assert!(GpuMlp::new(&deep, 0, OutputActivation::Identity).is_err());
    }
}
