//! Bias-free fully connected networks (as tiny-cuda-nn's fully fused MLP): ReLU on hidden layers,
//! identity on the output (the caller applies `trunc_exp` / sigmoid).
//!
//! Weights of layer `k` are stored row-major `[dims[k], dims[k + 1]]` so that a batch
//! `X: [n, dims[k]]` maps to `X W: [n, dims[k + 1]]` with one GEMM. [`MlpLayout::forward_reference`]
//! is the plain per-row reference; [`MlpLayout::forward`] / [`MlpLayout::backward`] run whole
//! batches, on the SIMD kernels of `mlp/simd.rs` where the CPU has them (AVX-512F, else AVX2 +
//! FMA, checked at run time: [`MlpKernels::best`]), else on `matrixmultiply`'s SGEMM ([`gemm`]).
//! [`MlpLayout::forward_with`] / [`MlpLayout::backward_partial_with`] choose the kernels
//! explicitly (tests and benches compare them).

use crate::rng::Rng;

#[cfg(target_arch = "x86_64")]
mod simd;

/// Which kernels an MLP pass runs on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MlpKernels {
    /// `matrixmultiply`'s SGEMM ([`gemm`], which picks its own instruction set) and plain
    /// loops for the ReLU: every CPU.
    Gemm,
    /// The AVX2 + FMA kernels of `mlp/simd.rs`.
    Avx2,
    /// The AVX-512F kernels of `mlp/simd.rs`.
    Avx512,
}

impl MlpKernels {
    /// Whether this CPU runs these kernels (x86_64 with the features, checked at run time and
    /// cached by the standard library).
    pub fn available(self) -> bool {
        match self {
            MlpKernels::Gemm => true,
            #[cfg(target_arch = "x86_64")]
            MlpKernels::Avx2 => simd::avx2::available(),
            #[cfg(target_arch = "x86_64")]
            MlpKernels::Avx512 => simd::avx512::available(),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The fastest kernels this CPU runs: AVX-512F, else AVX2 + FMA, else [`MlpKernels::Gemm`].
    pub fn best() -> MlpKernels {
        [MlpKernels::Avx512, MlpKernels::Avx2]
            .into_iter()
            .find(|k| k.available())
            .unwrap_or(MlpKernels::Gemm)
    }

    /// `self` where this CPU runs it, else [`MlpKernels::Gemm`].
    fn or_gemm(self) -> MlpKernels {
        if self.available() {
            self
        } else {
            MlpKernels::Gemm
        }
    }
}

/// `C = alpha * A B + beta * C` for row-major slices with explicit leading dimensions.
/// `A: [m, k]` (row stride `lda`), `B: [k, n]` (row stride `ldb`), `C: [m, n]` (row stride `ldc`);
/// `transpose_a` / `transpose_b` read `A` / `B` as transposed views of row-major storage.
#[allow(clippy::too_many_arguments)]
pub fn gemm(
    m: usize,
    k: usize,
    n: usize,
    alpha: f32,
    a: &[f32],
    lda: usize,
    transpose_a: bool,
    b: &[f32],
    ldb: usize,
    transpose_b: bool,
    beta: f32,
    c: &mut [f32],
    ldc: usize,
) {
    if m == 0 || n == 0 {
        return;
    }
    // Bounds: the last element each operand touches must be inside its slice.
    let a_last = if transpose_a {
        (k.max(1) - 1) * lda + m - 1
    } else {
        (m - 1) * lda + k.max(1) - 1
    };
    let b_last = if transpose_b {
        (n - 1) * ldb + k.max(1) - 1
    } else {
        (k.max(1) - 1) * ldb + n - 1
    };
    assert!(
        k == 0 || (a_last < a.len() && b_last < b.len()),
        "gemm operand out of bounds"
    );
    assert!((m - 1) * ldc + n - 1 < c.len(), "gemm output out of bounds");
    let (rsa, csa) = if transpose_a {
        (1, lda as isize)
    } else {
        (lda as isize, 1)
    };
    let (rsb, csb) = if transpose_b {
        (1, ldb as isize)
    } else {
        (ldb as isize, 1)
    };
    // SAFETY: the asserts above guarantee every index the kernel touches is in bounds, and `c`
    // is a unique borrow that does not alias `a` or `b`.
    unsafe {
        matrixmultiply::sgemm(
            m,
            k,
            n,
            alpha,
            a.as_ptr(),
            rsa,
            csa,
            b.as_ptr(),
            rsb,
            csb,
            beta,
            c.as_mut_ptr(),
            ldc as isize,
            1,
        );
    }
}

/// Shape of an MLP and where its weights sit inside its parameter slice.
#[derive(Clone, Debug, PartialEq)]
pub struct MlpLayout {
    /// `[input, hidden..., output]`.
    pub dims: Vec<usize>,
    /// Offset of each layer's weight matrix inside the slice.
    pub offsets: Vec<usize>,
    pub num_params: usize,
}

/// Activations of one batch kept for the backward pass.
#[derive(Clone, Debug, Default)]
pub struct MlpActivations {
    /// `acts[k]`: output of layer `k` (post-ReLU for hidden layers, raw for the last), `[n, dims[k+1]]`.
    pub acts: Vec<Vec<f32>>,
    /// Scratch gradients, one per layer output.
    grads: Vec<Vec<f32>>,
    /// Scratch of the SIMD kernels: a layer's weights padded to whole vectors, or transposed.
    packed: Vec<f32>,
    /// Scratch of the SIMD kernels: one layer's weight gradient, summed over the batch before
    /// it is added to the caller's.
    dw: Vec<f32>,
}

impl MlpLayout {
    pub fn new(dims: &[usize]) -> Self {
        assert!(dims.len() >= 2);
        let mut offsets = Vec::new();
        let mut off = 0;
        for k in 0..dims.len() - 1 {
            offsets.push(off);
            off += dims[k] * dims[k + 1];
        }
        MlpLayout {
            dims: dims.to_vec(),
            offsets,
            num_params: off,
        }
    }

    pub fn input_dim(&self) -> usize {
        self.dims[0]
    }

    pub fn output_dim(&self) -> usize {
        *self.dims.last().unwrap_or(&0)
    }

    pub fn num_layers(&self) -> usize {
        self.dims.len() - 1
    }

    fn weights<'a>(&self, params: &'a [f32], k: usize) -> &'a [f32] {
        &params[self.offsets[k]..self.offsets[k] + self.dims[k] * self.dims[k + 1]]
    }

    /// Glorot-uniform initialisation.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        for k in 0..self.num_layers() {
            let (fi, fo) = (self.dims[k], self.dims[k + 1]);
            let bound = (6.0 / (fi + fo) as f32).sqrt();
            for w in &mut params[self.offsets[k]..self.offsets[k] + fi * fo] {
                *w = rng.range_f32(-bound, bound);
            }
        }
    }

    /// Plain reference forward of one input row.
    pub fn forward_reference(&self, params: &[f32], input: &[f32]) -> Vec<f32> {
        let mut x = input.to_vec();
        for k in 0..self.num_layers() {
            let w = self.weights(params, k);
            let (fi, fo) = (self.dims[k], self.dims[k + 1]);
            let mut y = vec![0f32; fo];
            for o in 0..fo {
                let mut s = 0f32;
                for i in 0..fi {
                    s += x[i] * w[i * fo + o];
                }
                y[o] = if k + 1 < self.num_layers() {
                    s.max(0.0)
                } else {
                    s
                };
            }
            x = y;
        }
        x
    }

    /// Batched forward of `n` rows of `input` (row stride `dims[0]`); the output is
    /// `acts.acts.last()`. Runs on [`MlpKernels::best`].
    pub fn forward(&self, params: &[f32], input: &[f32], n: usize, acts: &mut MlpActivations) {
        self.forward_with(MlpKernels::best(), params, input, n, acts);
    }

    /// [`MlpLayout::forward`] on `kernels` ([`MlpKernels::Gemm`] where this CPU does not run
    /// them): the same sums whichever, up to float rounding (`core/tests/mlp_simd.rs`).
    pub fn forward_with(
        &self,
        kernels: MlpKernels,
        params: &[f32],
        input: &[f32],
        n: usize,
        acts: &mut MlpActivations,
    ) {
        let kernels = kernels.or_gemm();
        let layers = self.num_layers();
        acts.acts.resize_with(layers, Vec::new);
        let MlpActivations {
            acts: outs, packed, ..
        } = acts;
        for k in 0..layers {
            let (fi, fo) = (self.dims[k], self.dims[k + 1]);
            let (prev, rest) = outs.split_at_mut(k);
            let x: &[f32] = if k == 0 { input } else { &prev[k - 1] };
            let y = &mut rest[0];
            y.resize(n * fo, 0.0);
            let relu = k + 1 < layers;
            let w = self.weights(params, k);
            if simd_forward_layer(kernels, w, fi, fo, x, n, y, relu, packed) {
                continue;
            }
            gemm(n, fi, fo, 1.0, x, fi, false, w, fo, false, 0.0, y, fo);
            if relu {
                for v in y.iter_mut() {
                    *v = v.max(0.0);
                }
            }
        }
    }

    /// Output of the last [`MlpLayout::forward`].
    pub fn output<'a>(&self, acts: &'a MlpActivations) -> &'a [f32] {
        &acts.acts[self.num_layers() - 1]
    }

    /// Backward of the last forward: accumulates weight gradients into `grad` (this MLP's slice)
    /// and, when `d_input` is given, writes `dL/d input` (`[n, dims[0]]`) into it.
    pub fn backward(
        &self,
        params: &[f32],
        input: &[f32],
        n: usize,
        acts: &mut MlpActivations,
        d_output: &[f32],
        grad: &mut [f32],
        d_input: Option<&mut [f32]>,
    ) {
        self.backward_partial(
            params,
            input,
            n,
            acts,
            d_output,
            grad,
            d_input.map(|d| (0, d)),
        );
    }

    /// [`MlpLayout::backward`] where only the input columns `from..dims[0]` need a gradient:
    /// `d_input = Some((from, d))` writes them into `d` (`[n, dims[0] - from]`), skipping the
    /// work for the others (the colour MLP needs none for its direction encoding). Runs on
    /// [`MlpKernels::best`].
    #[allow(clippy::too_many_arguments)]
    pub fn backward_partial(
        &self,
        params: &[f32],
        input: &[f32],
        n: usize,
        acts: &mut MlpActivations,
        d_output: &[f32],
        grad: &mut [f32],
        d_input: Option<(usize, &mut [f32])>,
    ) {
        self.backward_partial_with(
            MlpKernels::best(),
            params,
            input,
            n,
            acts,
            d_output,
            grad,
            d_input,
        );
    }

    /// [`MlpLayout::backward_partial`] on `kernels` ([`MlpKernels::Gemm`] where this CPU does not
    /// run them).
    #[allow(clippy::too_many_arguments)]
    pub fn backward_partial_with(
        &self,
        kernels: MlpKernels,
        params: &[f32],
        input: &[f32],
        n: usize,
        acts: &mut MlpActivations,
        d_output: &[f32],
        grad: &mut [f32],
        d_input: Option<(usize, &mut [f32])>,
    ) {
        let kernels = kernels.or_gemm();
        let layers = self.num_layers();
        acts.grads.resize_with(layers, Vec::new);
        let MlpActivations {
            acts: a,
            grads,
            packed,
            dw,
        } = acts;
        grads[layers - 1].clear();
        grads[layers - 1].extend_from_slice(&d_output[..n * self.output_dim()]);
        let mut d_input = d_input;
        for k in (0..layers).rev() {
            let (fi, fo) = (self.dims[k], self.dims[k + 1]);
            let x: &[f32] = if k == 0 { input } else { &a[k - 1] };
            let (lower, upper) = grads.split_at_mut(k);
            let dy = &upper[0];
            // dW += x^T dy
            let off = self.offsets[k];
            let g = &mut grad[off..off + fi * fo];
            if !simd_weight_grad(kernels, x, fi, dy, fo, n, g, dw) {
                gemm(fi, n, fo, 1.0, x, fi, true, dy, fo, false, 1.0, g, fo);
            }
            let w = self.weights(params, k);
            if k > 0 {
                let dx = &mut lower[k - 1];
                dx.resize(n * fi, 0.0);
                let act = &a[k - 1];
                if simd_input_grad(kernels, w, fi, fo, 0, dy, n, dx, Some(act), packed) {
                    continue;
                }
                gemm(n, fo, fi, 1.0, dy, fo, false, w, fo, true, 0.0, dx, fi);
                // A select rather than a branch: about half the units are off, at random, so
                // a branch mispredicts often; the select also vectorises.
                for (d, &act) in dx.iter_mut().zip(act) {
                    *d = if act > 0.0 { *d } else { 0.0 };
                }
            } else if let Some((from, dx)) = d_input.as_mut() {
                let (from, cols) = (*from, fi - (*from).min(fi));
                if simd_input_grad(kernels, w, fi, fo, from, dy, n, dx, None, packed) {
                    continue;
                }
                // Rows `from..` of W (`[fi, fo]`, row-major) are the ones those columns read.
                gemm(
                    n,
                    fo,
                    cols,
                    1.0,
                    dy,
                    fo,
                    false,
                    &w[from * fo..],
                    fo,
                    true,
                    0.0,
                    dx,
                    cols,
                );
            }
        }
    }
}

/// `c = epilogue(a b)` on the SIMD `kernels` (see `simd::avx2::gemm`).
///
/// # Safety
/// This CPU runs `kernels`, which are not [`MlpKernels::Gemm`].
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
unsafe fn simd_gemm(
    kernels: MlpKernels,
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    lda: usize,
    b: &[f32],
    ldb: usize,
    c: &mut [f32],
    ldc: usize,
    epilogue: simd::Epilogue,
) {
    // SAFETY: the caller's contract.
    unsafe {
        match kernels {
            MlpKernels::Avx2 => simd::avx2::gemm(m, k, n, a, lda, b, ldb, c, ldc, epilogue),
            MlpKernels::Avx512 => simd::avx512::gemm(m, k, n, a, lda, b, ldb, c, ldc, epilogue),
            MlpKernels::Gemm => unreachable!(),
        }
    }
}

/// `o += a^T b` over `rows` batch rows on the SIMD `kernels` (see `simd::avx2::at_b_accumulate`).
///
/// # Safety
/// This CPU runs `kernels`, which are not [`MlpKernels::Gemm`].
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
unsafe fn simd_at_b(
    kernels: MlpKernels,
    rows: usize,
    a: &[f32],
    lda: usize,
    ma: usize,
    b: &[f32],
    ldb: usize,
    nb: usize,
    o: &mut [f32],
    ldo: usize,
) {
    // SAFETY: the caller's contract.
    unsafe {
        match kernels {
            MlpKernels::Avx2 => simd::avx2::at_b_accumulate(rows, a, lda, ma, b, ldb, nb, o, ldo),
            MlpKernels::Avx512 => {
                simd::avx512::at_b_accumulate(rows, a, lda, ma, b, ldb, nb, o, ldo)
            }
            MlpKernels::Gemm => unreachable!(),
        }
    }
}

/// One layer's forward on the SIMD `kernels`, `y = x w` (`[n, fi] [fi, fo]`), ReLU when `relu`;
/// the weights are padded to whole vectors in `packed` unless `fo` is a multiple of 16. Returns
/// whether it ran (not for [`MlpKernels::Gemm`]; `kernels` come from [`MlpKernels::or_gemm`]).
#[allow(clippy::too_many_arguments)]
fn simd_forward_layer(
    kernels: MlpKernels,
    w: &[f32],
    fi: usize,
    fo: usize,
    x: &[f32],
    n: usize,
    y: &mut [f32],
    relu: bool,
    packed: &mut Vec<f32>,
) -> bool {
    #[cfg(target_arch = "x86_64")]
    if kernels != MlpKernels::Gemm {
        let ld = simd::padded(fo);
        let b: &[f32] = if ld == fo {
            w
        } else {
            packed.clear();
            packed.resize(fi * ld, 0.0);
            for (dst, src) in packed.chunks_exact_mut(ld).zip(w.chunks_exact(fo)) {
                dst[..fo].copy_from_slice(src);
            }
            packed
        };
        let epilogue = if relu {
            simd::Epilogue::Relu
        } else {
            simd::Epilogue::Identity
        };
        // SAFETY: `kernels` come from `or_gemm`, so this CPU runs them.
        unsafe { simd_gemm(kernels, n, fi, fo, x, fi, b, ld, y, fo, epilogue) };
        return true;
    }
    let _ = (kernels, w, fi, fo, x, n, y, relu, packed);
    false
}

/// One layer's weight gradient on the SIMD `kernels`: `g += x^T dy` (`x: [n, fi]`,
/// `dy: [n, fo]`, `g: [fi, fo]`), summed over the batch in `dw` and then added to `g`. Where
/// the layer narrows (`fo < fi`) it sums `dy^T x` instead, whose rows are the wider ones.
/// Returns whether it ran (not for [`MlpKernels::Gemm`]; `kernels` come from
/// [`MlpKernels::or_gemm`]).
#[allow(clippy::too_many_arguments)]
fn simd_weight_grad(
    kernels: MlpKernels,
    x: &[f32],
    fi: usize,
    dy: &[f32],
    fo: usize,
    n: usize,
    g: &mut [f32],
    dw: &mut Vec<f32>,
) -> bool {
    #[cfg(target_arch = "x86_64")]
    if kernels != MlpKernels::Gemm {
        if fo >= fi {
            let ld = simd::padded(fo);
            dw.clear();
            dw.resize(fi * ld, 0.0);
            // SAFETY: `kernels` come from `or_gemm`, so this CPU runs them.
            unsafe { simd_at_b(kernels, n, x, fi, fi, dy, fo, fo, dw, ld) };
            for (gr, dr) in g.chunks_exact_mut(fo).zip(dw.chunks_exact(ld)) {
                for (gv, &dv) in gr.iter_mut().zip(dr) {
                    *gv += dv;
                }
            }
        } else {
            let ld = simd::padded(fi);
            dw.clear();
            dw.resize(fo * ld, 0.0);
            // SAFETY: as above.
            unsafe { simd_at_b(kernels, n, dy, fo, fo, x, fi, fi, dw, ld) };
            for (i, gr) in g.chunks_exact_mut(fo).enumerate() {
                for (o, gv) in gr.iter_mut().enumerate() {
                    *gv += dw[o * ld + i];
                }
            }
        }
        return true;
    }
    let _ = (kernels, x, fi, dy, fo, n, g, dw);
    false
}

/// One layer's input gradient on the SIMD `kernels`: `dx = dy w^T` for the input columns
/// `from..fi` (`dy: [n, fo]`, `dx: [n, fi - from]`), zero where `gate` (laid out as `dx`) is
/// not positive (the ReLU backward). The transposed rows of `w` go to `packed`, padded to whole
/// vectors. Returns whether it ran (not for [`MlpKernels::Gemm`]; `kernels` come from
/// [`MlpKernels::or_gemm`]).
#[allow(clippy::too_many_arguments)]
fn simd_input_grad(
    kernels: MlpKernels,
    w: &[f32],
    fi: usize,
    fo: usize,
    from: usize,
    dy: &[f32],
    n: usize,
    dx: &mut [f32],
    gate: Option<&[f32]>,
    packed: &mut Vec<f32>,
) -> bool {
    #[cfg(target_arch = "x86_64")]
    if kernels != MlpKernels::Gemm {
        let cols = fi - from.min(fi);
        let ld = simd::padded(cols);
        packed.clear();
        packed.resize(fo * ld, 0.0);
        for (i, wr) in w.chunks_exact(fo).skip(from).enumerate() {
            for (o, &v) in wr.iter().enumerate() {
                packed[o * ld + i] = v;
            }
        }
        let epilogue = gate.map_or(simd::Epilogue::Identity, simd::Epilogue::Gate);
        // SAFETY: `kernels` come from `or_gemm`, so this CPU runs them.
        unsafe { simd_gemm(kernels, n, fo, cols, dy, fo, packed, ld, dx, cols, epilogue) };
        return true;
    }
    let _ = (kernels, w, fi, fo, from, dy, n, dx, gate, packed);
    false
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::central_difference;

    /// An MLP of `sizes` with initial weights from seed `seed` and `n` inputs uniform in
    /// `[-1, 1]`; the generator is returned for further draws.
    fn random_mlp(sizes: &[usize], seed: u64, n: usize) -> (MlpLayout, Vec<f32>, Vec<f32>, Rng) {
        let mlp = MlpLayout::new(sizes);
        let mut rng = Rng::new(seed);
        let mut p = vec![0f32; mlp.num_params];
        mlp.init(&mut p, &mut rng);
        let x: Vec<f32> = (0..n * sizes[0])
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        (mlp, p, x, rng)
    }

    #[test]
    fn gemm_matches_naive_with_transposes() {
        let mut rng = Rng::new(2);
        let (m, k, n) = (7, 5, 3);
        let a: Vec<f32> = (0..m * k).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let b: Vec<f32> = (0..k * n).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let mut c = vec![1f32; m * n];
        gemm(m, k, n, 1.0, &a, k, false, &b, n, false, 1.0, &mut c, n);
        for i in 0..m {
            for j in 0..n {
                let s: f32 = (0..k).map(|t| a[i * k + t] * b[t * n + j]).sum::<f32>() + 1.0;
                assert!((s - c[i * n + j]).abs() < 1e-5);
            }
        }
        // A^T stored as [k, m]
        let at: Vec<f32> = (0..k * m).map(|idx| a[(idx % m) * k + idx / m]).collect();
        let mut c2 = vec![0f32; m * n];
        gemm(m, k, n, 1.0, &at, m, true, &b, n, false, 0.0, &mut c2, n);
        for i in 0..m * n {
            assert!((c2[i] - c[i] + 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn batched_forward_matches_reference() {
        let n = 37;
        let (mlp, p, x, _) = random_mlp(&[31, 64, 64, 3], 3, n);
        let mut acts = MlpActivations::default();
        mlp.forward(&p, &x, n, &mut acts);
        let out = mlp.output(&acts);
        for i in 0..n {
            let r = mlp.forward_reference(&p, &x[i * 31..(i + 1) * 31]);
            for o in 0..3 {
                assert!((r[o] - out[i * 3 + o]).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let n = 5;
        let (mlp, p, x, mut rng) = random_mlp(&[6, 8, 8, 3], 4, n);
        let wts: Vec<f32> = (0..n * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let loss = |p: &[f32], x: &[f32]| -> f64 {
            let mut s = 0f64;
            for i in 0..n {
                let r = mlp.forward_reference(p, &x[i * 6..(i + 1) * 6]);
                for o in 0..3 {
                    s += r[o] as f64 * wts[i * 3 + o] as f64;
                }
            }
            s
        };
        let mut acts = MlpActivations::default();
        mlp.forward(&p, &x, n, &mut acts);
        let mut grad = vec![0f32; mlp.num_params];
        let mut dx = vec![0f32; n * 6];
        mlp.backward(&p, &x, n, &mut acts, &wts, &mut grad, Some(&mut dx));
        let h = 1e-3f32;
        for i in 0..mlp.num_params {
            let fd = central_difference(|pp| loss(pp, &x), &p, i, h);
            assert!(
                (fd - grad[i] as f64).abs() < 2e-3,
                "w{i}: {fd} vs {}",
                grad[i]
            );
        }
        for i in 0..n * 6 {
            let fd = central_difference(|xx| loss(&p, xx), &x, i, h);
            assert!((fd - dx[i] as f64).abs() < 2e-3, "x{i}: {fd} vs {}", dx[i]);
        }
    }
}
