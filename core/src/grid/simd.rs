//! AVX2 kernels for hashed levels with two features per row (every preset's grids), eight points
//! at a time: one lane per point for the corner hashes and weights, one gather per four points
//! and corner for the rows.
//!
//! They compute what the scalar kernels of `grid.rs` compute, to the bit: the same IEEE
//! operations in the same order per point (multiplies and adds stay separate, as Rust never
//! contracts them into FMAs), corners and points visited in the same order on the backward
//! scatter. `core/tests/grid_simd.rs` checks it with `assert_eq!`. Used only
//! where the CPU has AVX2 (checked at run time) and every masked row lies inside the table.

use std::arch::x86_64::*;

use super::{clamp_unit, LevelLayout, PRIMES};

/// Points per kernel block: one AVX2 lane each.
const LANES: usize = 8;

/// Whether this CPU runs these kernels (cached by the standard library).
pub(super) fn available() -> bool {
    is_x86_feature_detected!("avx2")
}

/// Eight values, aligned for one AVX2 load.
#[repr(C, align(32))]
#[derive(Clone, Copy)]
struct Lanes<T>([T; LANES]);

/// Corner rows and weights of one block of eight points, corner-major (`rows[c].0[j]`: corner `c`
/// of point `j`): the first 8 corners are the 3D level's, all 16 the 4D level's.
#[derive(Clone, Copy)]
struct Block {
    r3: [Lanes<u32>; 8],
    w3: [Lanes<f32>; 8],
    r4: [Lanes<u32>; 16],
    w4: [Lanes<f32>; 16],
}

impl Block {
    fn new() -> Self {
        Block {
            r3: [Lanes([0; LANES]); 8],
            w3: [Lanes([0.0; LANES]); 8],
            r4: [Lanes([0; LANES]); 16],
            w4: [Lanes([0.0; LANES]); 16],
        }
    }
}

/// Axis `a` of points `start..start + 8` (stride `point_stride`), clamped like
/// [`clamp_unit`] (NaN to 0).
#[inline(always)]
fn axis(points: &[f32], point_stride: usize, start: usize, a: usize) -> Lanes<f32> {
    let p = &points[start * point_stride..(start + LANES) * point_stride];
    let mut x = Lanes([0f32; LANES]);
    for (j, v) in x.0.iter_mut().enumerate() {
        *v = clamp_unit(p[j * point_stride + a]);
    }
    x
}

/// The hashed 3D corners of eight points, as `grid::corners::<3, false>` makes them, and (with
/// `l4`) the 4D corners as `grid::pair_corners_block` makes them (the same rows and weights as
/// `grid::corners::<4, false>`, since masking commutes with XOR). No prefetches: eight points'
/// independent gathers keep enough loads in flight (prefetching the rows of the next block made
/// the forward pass 1.25x slower on L2-sized tables and did not help on 4 MB ones).
#[target_feature(enable = "avx2")]
fn corners8(
    mask: u32,
    l3: &LevelLayout,
    l4: Option<&LevelLayout>,
    points: &[f32],
    point_stride: usize,
    start: usize,
    out: &mut Block,
) {
    let one = _mm256_set1_ps(1.0);
    let half = _mm256_set1_ps(0.5);
    let one_i = _mm256_set1_epi32(1);
    let mut rows = [_mm256_setzero_si256(); 8];
    let mut w = [one; 8];
    let mut n = 1;
    for a in 0..3 {
        let x = axis(points, point_stride, start, a);
        // SAFETY: `Lanes` is 32-byte aligned and holds eight f32.
        let x = unsafe { _mm256_load_ps(x.0.as_ptr()) };
        let p = _mm256_add_ps(_mm256_mul_ps(x, _mm256_set1_ps(l3.scale[a])), half);
        let i = _mm256_cvttps_epi32(p); // p >= 0.5 and below 2^31: truncation is floor
        let fr = _mm256_sub_ps(p, _mm256_cvtepi32_ps(i));
        let prime = _mm256_set1_epi32(PRIMES[a] as i32);
        let lo = _mm256_mullo_epi32(i, prime);
        let hi = _mm256_mullo_epi32(_mm256_add_epi32(i, one_i), prime);
        let not_fr = _mm256_sub_ps(one, fr);
        for c in 0..n {
            let (r, wc) = (rows[c], w[c]);
            rows[c] = _mm256_xor_si256(r, lo);
            rows[c + n] = _mm256_xor_si256(r, hi);
            w[c] = _mm256_mul_ps(wc, not_fr);
            w[c + n] = _mm256_mul_ps(wc, fr);
        }
        n *= 2;
    }
    let m = _mm256_set1_epi32(mask as i32);
    for c in 0..8 {
        rows[c] = _mm256_and_si256(rows[c], m);
        // SAFETY: `Lanes` is 32-byte aligned and holds eight u32 / f32.
        unsafe {
            _mm256_store_si256(out.r3[c].0.as_mut_ptr() as *mut __m256i, rows[c]);
            _mm256_store_ps(out.w3[c].0.as_mut_ptr(), w[c]);
        }
    }
    let Some(l4) = l4 else { return };
    let x = axis(points, point_stride, start, 3);
    // SAFETY: as above.
    let x = unsafe { _mm256_load_ps(x.0.as_ptr()) };
    let p = _mm256_add_ps(_mm256_mul_ps(x, _mm256_set1_ps(l4.scale[3])), half);
    let i = _mm256_cvttps_epi32(p);
    let fr = _mm256_sub_ps(p, _mm256_cvtepi32_ps(i));
    let prime = _mm256_set1_epi32(PRIMES[3] as i32);
    let lo = _mm256_and_si256(_mm256_mullo_epi32(i, prime), m);
    let hi = _mm256_and_si256(_mm256_mullo_epi32(_mm256_add_epi32(i, one_i), prime), m);
    let not_fr = _mm256_sub_ps(one, fr);
    for c in 0..8 {
        // SAFETY: as above.
        unsafe {
            let p = out.r4.as_mut_ptr();
            _mm256_store_si256(
                (*p.add(c)).0.as_mut_ptr() as *mut __m256i,
                _mm256_xor_si256(rows[c], lo),
            );
            _mm256_store_si256(
                (*p.add(c + 8)).0.as_mut_ptr() as *mut __m256i,
                _mm256_xor_si256(rows[c], hi),
            );
            let q = out.w4.as_mut_ptr();
            _mm256_store_ps((*q.add(c)).0.as_mut_ptr(), _mm256_mul_ps(w[c], not_fr));
            _mm256_store_ps((*q.add(c + 8)).0.as_mut_ptr(), _mm256_mul_ps(w[c], fr));
        }
    }
}

/// `sum_c w_c table[row_c]` for the eight points of a block over `rows.len()` corners, in corner
/// order, written to `out[j * out_stride + out_offset..][..2]`.
///
/// # Safety
/// Every row must be below `table.len() / 2`.
#[target_feature(enable = "avx2")]
unsafe fn gather8(
    table: &[f32],
    rows: &[Lanes<u32>],
    weights: &[Lanes<f32>],
    out: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) {
    let base = table.as_ptr() as *const f64;
    let dup_lo = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3);
    let dup_hi = _mm256_setr_epi32(4, 4, 5, 5, 6, 6, 7, 7);
    let (mut acc_lo, mut acc_hi) = (_mm256_setzero_ps(), _mm256_setzero_ps());
    for (r, w) in rows.iter().zip(weights) {
        // SAFETY: aligned loads of `Lanes`; the rows are in the table (the caller's contract),
        // and a row of two f32 is eight bytes, read as one f64 lane (no alignment needed).
        let (idx, wv) = unsafe {
            (
                _mm256_load_si256(r.0.as_ptr() as *const __m256i),
                _mm256_load_ps(w.0.as_ptr()),
            )
        };
        let (f_lo, f_hi) = unsafe {
            (
                _mm256_castpd_ps(_mm256_i32gather_pd::<8>(base, _mm256_castsi256_si128(idx))),
                _mm256_castpd_ps(_mm256_i32gather_pd::<8>(
                    base,
                    _mm256_extracti128_si256::<1>(idx),
                )),
            )
        };
        let w_lo = _mm256_permutevar8x32_ps(wv, dup_lo);
        let w_hi = _mm256_permutevar8x32_ps(wv, dup_hi);
        acc_lo = _mm256_add_ps(acc_lo, _mm256_mul_ps(w_lo, f_lo));
        acc_hi = _mm256_add_ps(acc_hi, _mm256_mul_ps(w_hi, f_hi));
    }
    let mut v = Lanes([0f32; 8]);
    let mut u = Lanes([0f32; 8]);
    // SAFETY: aligned stores into `Lanes`.
    unsafe {
        _mm256_store_ps(v.0.as_mut_ptr(), acc_lo);
        _mm256_store_ps(u.0.as_mut_ptr(), acc_hi);
    }
    for j in 0..LANES {
        let src = if j < 4 {
            &v.0[2 * j..2 * j + 2]
        } else {
            &u.0[2 * (j - 4)..2 * (j - 4) + 2]
        };
        let o = j * out_stride + out_offset;
        out[o..o + 2].copy_from_slice(src);
    }
}

/// `grad[row_c] += w_c g` over the corners of point `j`, in corner order (no-op for `g == 0`).
#[inline(always)]
fn scatter(grad: &mut [f32], rows: &[Lanes<u32>], weights: &[Lanes<f32>], j: usize, g: &[f32]) {
    if g[0] == 0.0 && g[1] == 0.0 {
        return;
    }
    let (g0, g1) = (g[0], g[1]);
    for (r, w) in rows.iter().zip(weights) {
        let (r, w) = (r.0[j] as usize * 2, w.0[j]);
        let dst = &mut grad[r..r + 2];
        dst[0] += w * g0;
        dst[1] += w * g1;
    }
}

/// Whether a hashed level's table of `len` floats holds every masked row of two features.
pub(super) fn rows_fit(mask: u32, len: usize) -> bool {
    len / 2 > mask as usize
}

/// The full blocks of one hashed level pass with two features per row, eight points at a time:
/// a 3D level (`table3`), a 4D level (`table4`, its `x, y, z` scales those of `spatial` and its
/// `t` scale that of `t_level`), or a pair of both, as `grid::encode_level_impl::<3 | 4, 2, false>`
/// and `grid::encode_pair_level::<2>` compute them. Returns how many leading points it encoded (a
/// multiple of eight).
///
/// # Safety
/// The CPU has AVX2 ([`available`]), [`rows_fit`] holds for the tables given, and `t_level` is
/// given with `table4`.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn encode_level(
    mask: u32,
    spatial: &LevelLayout,
    t_level: Option<&LevelLayout>,
    table3: Option<&[f32]>,
    table4: Option<&[f32]>,
    points: &[f32],
    point_stride: usize,
    out3: &mut [f32],
    out4: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) -> usize {
    let blocks = points.len() / point_stride / LANES;
    let mut blk = Block::new();
    for b in 0..blocks {
        corners8(
            mask,
            spatial,
            t_level,
            points,
            point_stride,
            b * LANES,
            &mut blk,
        );
        let o = b * LANES * out_stride;
        // SAFETY: rows are masked and fit the tables (the caller's contract).
        unsafe {
            if let Some(table3) = table3 {
                gather8(
                    table3,
                    &blk.r3,
                    &blk.w3,
                    &mut out3[o..],
                    out_stride,
                    out_offset,
                );
            }
            if let Some(table4) = table4 {
                gather8(
                    table4,
                    &blk.r4,
                    &blk.w4,
                    &mut out4[o..],
                    out_stride,
                    out_offset,
                );
            }
        }
    }
    blocks * LANES
}

/// The backward counterpart of [`encode_level`] (`grid::backward_level_impl::<3 | 4, 2, false>`
/// and `grid::backward_pair_level::<2>`): the same sums, points and corners in the same order.
/// Returns how many leading points it visited. `t_level` must be given with `grad4`.
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
pub(super) fn backward_level(
    mask: u32,
    spatial: &LevelLayout,
    t_level: Option<&LevelLayout>,
    mut grad3: Option<&mut [f32]>,
    mut grad4: Option<&mut [f32]>,
    points: &[f32],
    point_stride: usize,
    d3: &[f32],
    d4: &[f32],
    d_stride: usize,
    d_offset: usize,
) -> usize {
    let blocks = points.len() / point_stride / LANES;
    let mut blk = Block::new();
    for b in 0..blocks {
        corners8(
            mask,
            spatial,
            t_level,
            points,
            point_stride,
            b * LANES,
            &mut blk,
        );
        for j in 0..LANES {
            let o = (b * LANES + j) * d_stride + d_offset;
            if let Some(g3) = grad3.as_deref_mut() {
                scatter(g3, &blk.r3, &blk.w3, j, &d3[o..o + 2]);
            }
            if let Some(g4) = grad4.as_deref_mut() {
                scatter(g4, &blk.r4, &blk.w4, j, &d4[o..o + 2]);
            }
        }
    }
    blocks * LANES
}
