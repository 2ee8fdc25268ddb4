//! SIMD kernels for the small MLPs of `mlp.rs` (inputs and widths of a few to a few dozen units,
//! batches of thousands of rows), used in place of `matrixmultiply`'s SGEMM, whose packing of
//! whole batches and fixed tiles cost more than the arithmetic at these shapes.
//!
//! - `gemm`: `C = epilogue(A B)` with `B` small and stored with its rows padded to whole vectors
//!   (a layer's weights, or their transpose for the backward pass), in register tiles of up to
//!   `ROWS` rows by two vectors: per step of the inner dimension, two vector loads of `B`, one
//!   broadcast per row of `A`, `2 ROWS` FMAs. The epilogue is the forward ReLU or the backward
//!   ReLU mask (keep where the activation is positive), applied before the tile is stored.
//!   Narrow column tails use masked stores.
//! - `at_b_accumulate`: `O += A^T B` summed over the batch (the weight gradient `X^T dY`), in the
//!   same register tiles, the batch walked in chunks that stay in L1 while every tile of the
//!   output passes over them.
//!
//! The same code is compiled twice (`kernels!`): [`avx2`] (AVX2 + FMA, 8 lanes, 6-row tiles, 16
//! registers) and [`avx512`] (AVX-512F, 16 lanes, 8-row tiles, 32 registers), the one
//! `matrixmultiply` itself takes where the CPU has it. FMAs round once where a multiply and an
//! add round twice, so the results differ from the `matrixmultiply` path by float rounding
//! (`core/tests/mlp_simd.rs` bounds it); the order of each output's sum is the plain one (inner
//! dimension, or batch rows, in order). Used only where the CPU has the features (checked at run
//! time).

/// Every padded row length is a multiple of this (whole vectors for both instruction sets).
pub(super) const PAD: usize = 16;

/// `n` rounded up to whole vectors of either instruction set.
pub(super) fn padded(n: usize) -> usize {
    n.div_ceil(PAD) * PAD
}

/// Batch rows per pass of the weight-gradient tiles: the chunk of both operands (up to 64 + 64
/// floats a row, 32 KB) stays in L1 while the tiles of the output pass over it.
const CHUNK_ROWS: usize = 64;

/// What `gemm` does to a tile before storing it.
#[derive(Clone, Copy)]
pub(super) enum Epilogue<'a> {
    /// Nothing (the output layer).
    Identity,
    /// `max(x, 0)` (a hidden layer's forward; NaN becomes 0 as with `f32::max`).
    Relu,
    /// `if gate > 0 { x } else { 0 }` with `gate` laid out as the output (the ReLU backward,
    /// gated by the layer's forward output).
    Gate(&'a [f32]),
}

/// The kernels over one instruction set's vector type `V` and mask type `M`, given, in the
/// invoking module, `LANES`, `ROWS`, `FEATURES` and the `#[target_feature]` helpers `zero`,
/// `load`, `store`, `first_lanes`, `maskload`, `maskstore`, `broadcast`, `fmadd`, `relu`,
/// `gate`; `$rows` lists `ROWS..=1` (the row counts a tile dispatches on).
macro_rules! kernels {
    ($features:literal, [$($rows:literal),*]) => {
        /// One register tile of `gemm`: rows `0..R` of `a` times the `C` column vectors of `b`,
        /// then the epilogue, stored to the first `cols` columns of `c` (and read from `gate`,
        /// laid out as `c`).
        ///
        /// # Safety
        /// The CPU has the features. `a` reads `R` rows of `k` floats (row stride `lda`); `b`
        /// reads `k` rows of `LANES C` floats (row stride `ldb`); `c` (and `gate` when not null)
        /// hold `R` rows of `cols` floats (row stride `ldc`), `cols` in
        /// `LANES (C - 1) + 1..=LANES C`.
        #[inline]
        #[target_feature(enable = $features)]
        #[allow(clippy::too_many_arguments)]
        unsafe fn gemm_tile<const R: usize, const C: usize>(
            k: usize,
            a: *const f32,
            lda: usize,
            b: *const f32,
            ldb: usize,
            c: *mut f32,
            ldc: usize,
            cols: usize,
            relu_out: bool,
            gate_in: *const f32,
        ) {
            let mut acc = [[zero(); C]; R];
            for p in 0..k {
                // SAFETY (this block and the stores below): in bounds by the caller's contract.
                unsafe {
                    let bp = b.add(p * ldb);
                    let mut bv = [zero(); C];
                    for (v, x) in bv.iter_mut().enumerate() {
                        *x = load(bp.add(v * LANES));
                    }
                    for (r, row) in acc.iter_mut().enumerate() {
                        let av = broadcast(a.add(r * lda + p));
                        for (x, &bx) in row.iter_mut().zip(&bv) {
                            *x = fmadd(av, bx, *x);
                        }
                    }
                }
            }
            let tail = first_lanes(cols - (C - 1) * LANES);
            for (r, row) in acc.iter().enumerate() {
                for (v, &x) in row.iter().enumerate() {
                    let at = r * ldc + v * LANES;
                    let full = v + 1 < C || cols == C * LANES;
                    let mut x = x;
                    if relu_out {
                        x = relu(x);
                    }
                    // SAFETY: as above; the last vector of a narrow tile is masked.
                    unsafe {
                        if !gate_in.is_null() {
                            let g = if full {
                                load(gate_in.add(at))
                            } else {
                                maskload(gate_in.add(at), tail)
                            };
                            x = gate(x, g);
                        }
                        if full {
                            store(c.add(at), x);
                        } else {
                            maskstore(c.add(at), tail, x);
                        }
                    }
                }
            }
        }

        /// The column tiles of one block of `R` rows of `gemm`.
        ///
        /// # Safety
        /// As `gemm_tile` for each tile: `c` and `gate` hold `R` rows of `n` columns, `b` rows of
        /// `padded(n)`.
        #[inline]
        #[target_feature(enable = $features)]
        #[allow(clippy::too_many_arguments)]
        unsafe fn gemm_rows<const R: usize>(
            k: usize,
            n: usize,
            a: *const f32,
            lda: usize,
            b: *const f32,
            ldb: usize,
            c: *mut f32,
            ldc: usize,
            relu_out: bool,
            gate_in: *const f32,
        ) {
            let width = 2 * LANES;
            let mut j = 0;
            while j < n {
                let cols = (n - j).min(width);
                let g = if gate_in.is_null() {
                    gate_in
                } else {
                    // SAFETY: column `j < n` of a row of `gate`.
                    unsafe { gate_in.add(j) }
                };
                // SAFETY: columns `j..j + cols <= n` of `c` and `gate`, columns
                // `j..j + LANES ceil(cols / LANES) <= padded(n)` of `b`.
                unsafe {
                    if cols > LANES {
                        gemm_tile::<R, 2>(k, a, lda, b.add(j), ldb, c.add(j), ldc, cols, relu_out, g)
                    } else {
                        gemm_tile::<R, 1>(k, a, lda, b.add(j), ldb, c.add(j), ldc, cols, relu_out, g)
                    }
                }
                j += width;
            }
        }

        /// `c[r][j] = epilogue(sum_p a[r][p] b[p][j])` for `r < m`, `j < n` (`a`: row stride
        /// `lda`, `k` columns; `b`: `k` rows of stride `ldb`, at least [`padded`]`(n)`, its
        /// columns `n..ldb` read but not used; `c`: row stride `ldc`). The sum runs over `p` in
        /// order, one FMA per step.
        ///
        /// # Safety
        /// The CPU has the features (`available`).
        #[allow(clippy::too_many_arguments)]
        #[target_feature(enable = $features)]
        pub(in crate::mlp) unsafe fn gemm(
            m: usize,
            k: usize,
            n: usize,
            a: &[f32],
            lda: usize,
            b: &[f32],
            ldb: usize,
            c: &mut [f32],
            ldc: usize,
            epilogue: Epilogue,
        ) {
            if m == 0 || n == 0 {
                return;
            }
            assert!(k <= lda && n <= ldc && padded(n) <= ldb);
            assert!(a.len() >= (m - 1) * lda + k, "mlp gemm: a out of bounds");
            assert!(b.len() >= k * ldb, "mlp gemm: b out of bounds");
            assert!(c.len() >= (m - 1) * ldc + n, "mlp gemm: c out of bounds");
            let (relu_out, gate_in) = match epilogue {
                Epilogue::Identity => (false, std::ptr::null()),
                Epilogue::Relu => (true, std::ptr::null()),
                Epilogue::Gate(g) => {
                    assert!(g.len() >= (m - 1) * ldc + n, "mlp gemm: gate out of bounds");
                    (false, g.as_ptr())
                }
            };
            let (a, b, c) = (a.as_ptr(), b.as_ptr(), c.as_mut_ptr());
            let mut r0 = 0;
            while r0 < m {
                let rows = (m - r0).min(ROWS);
                // SAFETY: the asserts above bound every row and column a tile touches: rows
                // `r0..r0 + rows <= m` of `a`, `c` and `gate`, `k` rows of `b`.
                unsafe {
                    let (ap, cp) = (a.add(r0 * lda), c.add(r0 * ldc));
                    let gp = if gate_in.is_null() {
                        gate_in
                    } else {
                        gate_in.add(r0 * ldc)
                    };
                    match rows {
                        $($rows => gemm_rows::<$rows>(k, n, ap, lda, b, ldb, cp, ldc, relu_out, gp),)*
                        _ => unreachable!(),
                    }
                }
                r0 += rows;
            }
        }

        /// One register tile of `at_b_accumulate`: `o[i][j] += sum_s a[s][i] b[s][j]` for
        /// `i < R` and the `C` column vectors of `b`, over `rows` batch rows (`a`: row stride
        /// `lda`; `b`: row stride `ldb`, its first `cols` columns read; `o`: `R` rows of
        /// `LANES C` floats, row stride `ldo`).
        ///
        /// # Safety
        /// The CPU has the features; the pointers hold what is described above, `cols` in
        /// `LANES (C - 1) + 1..=LANES C`.
        #[inline]
        #[target_feature(enable = $features)]
        #[allow(clippy::too_many_arguments)]
        unsafe fn at_b_tile<const R: usize, const C: usize>(
            rows: usize,
            a: *const f32,
            lda: usize,
            b: *const f32,
            ldb: usize,
            cols: usize,
            o: *mut f32,
            ldo: usize,
        ) {
            let mut acc = [[zero(); C]; R];
            // SAFETY (every block of this function): in bounds by the caller's contract.
            for (i, row) in acc.iter_mut().enumerate() {
                for (v, x) in row.iter_mut().enumerate() {
                    *x = unsafe { load(o.add(i * ldo + v * LANES)) };
                }
            }
            let tail = first_lanes(cols - (C - 1) * LANES);
            let full = cols == C * LANES;
            for s in 0..rows {
                unsafe {
                    let bp = b.add(s * ldb);
                    let mut bv = [zero(); C];
                    for (v, x) in bv.iter_mut().enumerate() {
                        *x = if v + 1 < C || full {
                            load(bp.add(v * LANES))
                        } else {
                            maskload(bp.add(v * LANES), tail)
                        };
                    }
                    let ap = a.add(s * lda);
                    for (i, row) in acc.iter_mut().enumerate() {
                        let av = broadcast(ap.add(i));
                        for (x, &bx) in row.iter_mut().zip(&bv) {
                            *x = fmadd(av, bx, *x);
                        }
                    }
                }
            }
            for (i, row) in acc.iter().enumerate() {
                for (v, &x) in row.iter().enumerate() {
                    unsafe { store(o.add(i * ldo + v * LANES), x) };
                }
            }
        }

        /// The column tiles of one block of `R` output rows of `at_b_accumulate`.
        ///
        /// # Safety
        /// As `at_b_tile` for each tile: `b` rows of `nb` columns, `o` rows of `padded(nb)`.
        #[inline]
        #[target_feature(enable = $features)]
        #[allow(clippy::too_many_arguments)]
        unsafe fn at_b_rows<const R: usize>(
            rows: usize,
            a: *const f32,
            lda: usize,
            b: *const f32,
            ldb: usize,
            nb: usize,
            o: *mut f32,
            ldo: usize,
        ) {
            let width = 2 * LANES;
            let mut j = 0;
            while j < nb {
                let cols = (nb - j).min(width);
                // SAFETY: columns `j..j + cols <= nb` of `b` (the tail vector masked), columns
                // `j..j + LANES ceil(cols / LANES) <= padded(nb)` of `o`.
                unsafe {
                    if cols > LANES {
                        at_b_tile::<R, 2>(rows, a, lda, b.add(j), ldb, cols, o.add(j), ldo)
                    } else {
                        at_b_tile::<R, 1>(rows, a, lda, b.add(j), ldb, cols, o.add(j), ldo)
                    }
                }
                j += width;
            }
        }

        /// `o[i][j] += sum_s a[s][i] b[s][j]` for `i < ma`, `j < nb`, over the `rows` batch
        /// rows (`a`: row stride `lda`, columns `0..ma` read; `b`: row stride `ldb`, columns
        /// `0..nb` read; `o`: `ma` rows of stride `ldo >= padded(nb)`, its columns `nb..` left
        /// with unspecified values). Each output's sum runs over the batch rows in order, one
        /// FMA per row, starting from what `o` holds.
        ///
        /// # Safety
        /// The CPU has the features (`available`).
        #[allow(clippy::too_many_arguments)]
        #[target_feature(enable = $features)]
        pub(in crate::mlp) unsafe fn at_b_accumulate(
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
            if rows == 0 || ma == 0 || nb == 0 {
                return;
            }
            assert!(ma <= lda && nb <= ldb && padded(nb) <= ldo);
            assert!(a.len() >= (rows - 1) * lda + ma, "mlp at_b: a out of bounds");
            assert!(b.len() >= (rows - 1) * ldb + nb, "mlp at_b: b out of bounds");
            assert!(o.len() >= ma * ldo, "mlp at_b: o out of bounds");
            let (a, b, o) = (a.as_ptr(), b.as_ptr(), o.as_mut_ptr());
            let mut s0 = 0;
            while s0 < rows {
                let chunk = (rows - s0).min(CHUNK_ROWS);
                let mut i = 0;
                while i < ma {
                    let tr = (ma - i).min(ROWS);
                    // SAFETY: the asserts above bound what a tile touches: batch rows
                    // `s0..s0 + chunk <= rows`, columns `i..i + tr <= ma` of `a`, rows
                    // `i..i + tr` of `o`.
                    unsafe {
                        let (ap, bp) = (a.add(s0 * lda + i), b.add(s0 * ldb));
                        let op = o.add(i * ldo);
                        match tr {
                            $($rows => at_b_rows::<$rows>(chunk, ap, lda, bp, ldb, nb, op, ldo),)*
                            _ => unreachable!(),
                        }
                    }
                    i += tr;
                }
                s0 += chunk;
            }
        }
    };
}

/// AVX2 + FMA: 8 lanes, tiles of 6 rows by 16 columns (12 accumulators of 16 registers).
pub(super) mod avx2 {
    use super::{padded, Epilogue, CHUNK_ROWS};
    use std::arch::x86_64::*;

    const LANES: usize = 8;
    const ROWS: usize = 6;

    /// Whether this CPU runs these kernels (cached by the standard library).
    pub(in crate::mlp) fn available() -> bool {
        is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn zero() -> __m256 {
        _mm256_setzero_ps()
    }

    /// # Safety
    /// `p` holds 8 floats.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn load(p: *const f32) -> __m256 {
        unsafe { _mm256_loadu_ps(p) }
    }

    /// # Safety
    /// `p` holds 8 floats.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn store(p: *mut f32, x: __m256) {
        unsafe { _mm256_storeu_ps(p, x) }
    }

    /// The first `k` lanes (`k` in `1..=8`).
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn first_lanes(k: usize) -> __m256i {
        _mm256_cmpgt_epi32(
            _mm256_set1_epi32(k as i32),
            _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
        )
    }

    /// # Safety
    /// `p` holds the lanes of `m`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn maskload(p: *const f32, m: __m256i) -> __m256 {
        unsafe { _mm256_maskload_ps(p, m) }
    }

    /// # Safety
    /// `p` holds the lanes of `m`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn maskstore(p: *mut f32, m: __m256i, x: __m256) {
        unsafe { _mm256_maskstore_ps(p, m, x) }
    }

    /// # Safety
    /// `p` holds a float.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn broadcast(p: *const f32) -> __m256 {
        unsafe { _mm256_broadcast_ss(&*p) }
    }

    /// `a b + c`, rounded once.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn fmadd(a: __m256, b: __m256, c: __m256) -> __m256 {
        _mm256_fmadd_ps(a, b, c)
    }

    /// `max(x, 0)`, NaN to 0.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn relu(x: __m256) -> __m256 {
        _mm256_max_ps(x, _mm256_setzero_ps())
    }

    /// `x` where `g > 0`, else 0 (NaN `g` gives 0).
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn gate(x: __m256, g: __m256) -> __m256 {
        _mm256_and_ps(x, _mm256_cmp_ps::<_CMP_GT_OQ>(g, _mm256_setzero_ps()))
    }

    kernels!("avx2,fma", [6, 5, 4, 3, 2, 1]);
}

/// AVX-512F: 16 lanes, tiles of 8 rows by 32 columns (16 accumulators of 32 registers).
pub(super) mod avx512 {
    use super::{padded, Epilogue, CHUNK_ROWS};
    use std::arch::x86_64::*;

    const LANES: usize = 16;
    const ROWS: usize = 8;

    /// Whether this CPU runs these kernels (cached by the standard library).
    pub(in crate::mlp) fn available() -> bool {
        is_x86_feature_detected!("avx512f")
    }

    #[inline]
    #[target_feature(enable = "avx512f")]
    fn zero() -> __m512 {
        _mm512_setzero_ps()
    }

    /// # Safety
    /// `p` holds 16 floats.
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn load(p: *const f32) -> __m512 {
        unsafe { _mm512_loadu_ps(p) }
    }

    /// # Safety
    /// `p` holds 16 floats.
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn store(p: *mut f32, x: __m512) {
        unsafe { _mm512_storeu_ps(p, x) }
    }

    /// The first `k` lanes (`k` in `1..=16`).
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn first_lanes(k: usize) -> __mmask16 {
        ((1u32 << k) - 1) as __mmask16
    }

    /// # Safety
    /// `p` holds the lanes of `m`.
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn maskload(p: *const f32, m: __mmask16) -> __m512 {
        unsafe { _mm512_maskz_loadu_ps(m, p) }
    }

    /// # Safety
    /// `p` holds the lanes of `m`.
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn maskstore(p: *mut f32, m: __mmask16, x: __m512) {
        unsafe { _mm512_mask_storeu_ps(p, m, x) }
    }

    /// # Safety
    /// `p` holds a float.
    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn broadcast(p: *const f32) -> __m512 {
        unsafe { _mm512_set1_ps(*p) }
    }

    /// `a b + c`, rounded once.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn fmadd(a: __m512, b: __m512, c: __m512) -> __m512 {
        _mm512_fmadd_ps(a, b, c)
    }

    /// `max(x, 0)`, NaN to 0.
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn relu(x: __m512) -> __m512 {
        _mm512_max_ps(x, _mm512_setzero_ps())
    }

    /// `x` where `g > 0`, else 0 (NaN `g` gives 0).
    #[inline]
    #[target_feature(enable = "avx512f")]
    fn gate(x: __m512, g: __m512) -> __m512 {
        _mm512_maskz_mov_ps(_mm512_cmp_ps_mask::<_CMP_GT_OQ>(g, _mm512_setzero_ps()), x)
    }

    kernels!("avx512f", [8, 7, 6, 5, 4, 3, 2, 1]);
}
