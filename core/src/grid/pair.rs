//! The 3D and 4D grids encoded (and their gradients scattered) in one pass over shared spatial
//! corners ([`pairable`] layouts): the walk is the single-grid kernels' (`walk_blocks`), with a
//! [`PairPass`] that does the 3D and the 4D halves of each level.

use super::*;

/// Whether [`encode_pair`] / [`backward_pair`] can share the spatial corners of `g3` (3D) and
/// `g4` (4D): same levels, features and table size, and the same `x, y, z` scales per level.
/// Levels where both are hashed then share the `x, y, z` part of the hash and of the weights;
/// the 4D corners are the 3D ones times the two `t` corners.
pub fn pairable(g3: &GridLayout, g4: &GridLayout) -> bool {
    g3.dims == 3
        && g4.dims == 4
        && g3.features == g4.features
        && g3.table_size == g4.table_size
        && g3.levels.len() == g4.levels.len()
        && g3
            .levels
            .iter()
            .zip(&g4.levels)
            .all(|(a, b)| a.scale[..3] == b.scale[..3])
}

/// [`GridLayout::encode`] of `g3` into `out3` and of `g4` into `out4` in one pass (same points,
/// output strides and offsets), with the same results. Needs [`pairable`].
#[allow(clippy::too_many_arguments)]
pub fn encode_pair(
    g3: &GridLayout,
    table3: &[f32],
    g4: &GridLayout,
    table4: &[f32],
    points: &[f32],
    point_stride: usize,
    out3: &mut [f32],
    out4: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) {
    let simd = simd_available();
    encode_pair_with(
        simd,
        g3,
        table3,
        g4,
        table4,
        points,
        point_stride,
        out3,
        out4,
        out_stride,
        out_offset,
    )
}

/// [`encode_pair`] with the AVX2 kernels on (`simd`, where [`simd_available`]) or off: the
/// same bits either way (`core/tests/grid_simd.rs`).
#[allow(clippy::too_many_arguments)]
pub fn encode_pair_with(
    simd: bool,
    g3: &GridLayout,
    table3: &[f32],
    g4: &GridLayout,
    table4: &[f32],
    points: &[f32],
    point_stride: usize,
    out3: &mut [f32],
    out4: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) {
    assert!(pairable(g3, g4) && point_stride >= 4);
    let n = points.len() / point_stride;
    assert!(out3.len() >= n * out_stride && out4.len() >= n * out_stride);
    assert!(out_offset + g3.output_dim() <= out_stride);
    assert!(table3.len() >= g3.num_params && table4.len() >= g4.num_params);
    let mut pass = EncodePair {
        simd,
        g3,
        table3,
        g4,
        table4,
        points,
        point_stride,
        out3,
        out4,
        out_stride,
    };
    pair_levels(g3, g4, out_offset, &mut pass);
}

/// [`GridLayout::backward`] of `g3` (from `d3`) and `g4` (from `d4`) in one pass, with the same
/// sums. Needs [`pairable`].
#[allow(clippy::too_many_arguments)]
pub fn backward_pair(
    g3: &GridLayout,
    g4: &GridLayout,
    points: &[f32],
    point_stride: usize,
    d3: &[f32],
    d4: &[f32],
    d_stride: usize,
    d_offset: usize,
    grad3: &mut [f32],
    grad4: &mut [f32],
) {
    let simd = simd_available();
    backward_pair_with(
        simd,
        g3,
        g4,
        points,
        point_stride,
        d3,
        d4,
        d_stride,
        d_offset,
        grad3,
        grad4,
    )
}

/// [`backward_pair`] with the AVX2 kernels on (`simd`, where [`simd_available`]) or off: the
/// same sums either way.
#[allow(clippy::too_many_arguments)]
pub fn backward_pair_with(
    simd: bool,
    g3: &GridLayout,
    g4: &GridLayout,
    points: &[f32],
    point_stride: usize,
    d3: &[f32],
    d4: &[f32],
    d_stride: usize,
    d_offset: usize,
    grad3: &mut [f32],
    grad4: &mut [f32],
) {
    assert!(pairable(g3, g4) && point_stride >= 4);
    assert!(grad3.len() >= g3.num_params && grad4.len() >= g4.num_params);
    let mut pass = BackwardPair {
        simd,
        g3,
        g4,
        points,
        point_stride,
        d3,
        d4,
        d_stride,
        grad3,
        grad4,
    };
    pair_levels(g3, g4, d_offset, &mut pass);
}

/// One paired pass over the levels of two [`pairable`] grids, the forward ([`EncodePair`]) or
/// the backward ([`BackwardPair`]), as [`pair_levels`] walks it. `offset` is where the level's
/// `F` features lie in each point's output (or gradient) row.
trait PairPass {
    /// Both levels hashed: the AVX2 kernel's full blocks, then the paired scalar kernel on the
    /// points it left.
    fn hashed<const F: usize>(&mut self, l3: &LevelLayout, l4: &LevelLayout, offset: usize);
    /// A dense level on either side: each grid's own level pass.
    fn separate<const F: usize>(&mut self, l3: &LevelLayout, l4: &LevelLayout, offset: usize);
}

/// The level loop of the paired passes: per level of `g3` and `g4`, with the features as a
/// constant, [`PairPass::hashed`] where both are hashed, else [`PairPass::separate`].
fn pair_levels(g3: &GridLayout, g4: &GridLayout, offset: usize, pass: &mut impl PairPass) {
    macro_rules! go {
        ($f:literal) => {
            for (l, (l3, l4)) in g3.levels.iter().zip(&g4.levels).enumerate() {
                let off = offset + l * $f;
                if !l3.dense && !l4.dense {
                    pass.hashed::<$f>(l3, l4, off);
                } else {
                    pass.separate::<$f>(l3, l4, off);
                }
            }
        };
    }
    match g3.features {
        1 => go!(1),
        2 => go!(2),
        4 => go!(4),
        8 => go!(8),
        _ => unreachable!("validated grid config"),
    }
}

/// The [`PairPass`] of [`encode_pair_with`].
struct EncodePair<'a> {
    simd: bool,
    g3: &'a GridLayout,
    table3: &'a [f32],
    g4: &'a GridLayout,
    table4: &'a [f32],
    points: &'a [f32],
    point_stride: usize,
    out3: &'a mut [f32],
    out4: &'a mut [f32],
    out_stride: usize,
}

impl PairPass for EncodePair<'_> {
    fn hashed<const F: usize>(&mut self, l3: &LevelLayout, l4: &LevelLayout, offset: usize) {
        let t3 = &self.table3[l3.offset..l3.offset + l3.rows * F];
        let t4 = &self.table4[l4.offset..l4.offset + l4.rows * F];
        let (points, ps, stride) = (self.points, self.point_stride, self.out_stride);
        let pass = Pass::Pair(l3, l4);
        let (o3, o4) = (&mut *self.out3, &mut *self.out4);
        let done = simd_encode(
            self.simd, self.g3, pass, t3, t4, points, ps, o3, o4, stride, offset,
        );
        let o = done * stride;
        encode_pair_level::<F>(
            self.g3,
            l3,
            t3,
            l4,
            t4,
            &points[done * ps..],
            ps,
            &mut o3[o..],
            &mut o4[o..],
            stride,
            offset,
        );
    }

    fn separate<const F: usize>(&mut self, l3: &LevelLayout, l4: &LevelLayout, offset: usize) {
        let t3 = &self.table3[l3.offset..l3.offset + l3.rows * F];
        let t4 = &self.table4[l4.offset..l4.offset + l4.rows * F];
        let (p, ps, stride) = (self.points, self.point_stride, self.out_stride);
        encode_level::<3, F>(self.simd, self.g3, l3, t3, p, ps, self.out3, stride, offset);
        encode_level::<4, F>(self.simd, self.g4, l4, t4, p, ps, self.out4, stride, offset);
    }
}

/// The [`PairPass`] of [`backward_pair_with`].
struct BackwardPair<'a> {
    simd: bool,
    g3: &'a GridLayout,
    g4: &'a GridLayout,
    points: &'a [f32],
    point_stride: usize,
    d3: &'a [f32],
    d4: &'a [f32],
    d_stride: usize,
    grad3: &'a mut [f32],
    grad4: &'a mut [f32],
}

impl PairPass for BackwardPair<'_> {
    fn hashed<const F: usize>(&mut self, l3: &LevelLayout, l4: &LevelLayout, offset: usize) {
        let r3 = &mut self.grad3[l3.offset..l3.offset + l3.rows * F];
        let r4 = &mut self.grad4[l4.offset..l4.offset + l4.rows * F];
        let (points, ps) = (self.points, self.point_stride);
        let (d3, d4, ds) = (self.d3, self.d4, self.d_stride);
        let pass = Pass::Pair(l3, l4);
        let done = simd_backward(
            self.simd, self.g3, pass, r3, r4, points, ps, d3, d4, ds, offset,
        );
        let o = (done * ds).min(d3.len().min(d4.len()));
        backward_pair_level::<F>(
            self.g3,
            l3,
            r3,
            l4,
            r4,
            &points[done * ps..],
            ps,
            &d3[o..],
            &d4[o..],
            ds,
            offset,
        );
    }

    fn separate<const F: usize>(&mut self, l3: &LevelLayout, l4: &LevelLayout, offset: usize) {
        let r3 = &mut self.grad3[l3.offset..l3.offset + l3.rows * F];
        let r4 = &mut self.grad4[l4.offset..l4.offset + l4.rows * F];
        let (p, ps, ds) = (self.points, self.point_stride, self.d_stride);
        backward_level::<3, F>(self.simd, self.g3, l3, r3, p, ps, self.d3, ds, offset);
        backward_level::<4, F>(self.simd, self.g4, l4, r4, p, ps, self.d4, ds, offset);
    }
}

/// Corners of one block of points on a hashed 3D level and the hashed 4D level with the same
/// spatial scales: the 3D corners as [`corners`] makes them, then the 4D ones as the 3D ones
/// XOR the two `t` hashes (masking commutes with XOR) and times the two `t` weights (the last
/// doubling step of [`corners`], so the same bits). Prefetches both tables' rows.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn pair_corners_block<const F: usize>(
    mask: u32,
    l3: &LevelLayout,
    table3: &[f32],
    l4: &LevelLayout,
    table4: &[f32],
    points: &[f32],
    point_stride: usize,
    start: usize,
    m: usize,
    live: impl Fn(usize) -> bool,
    c3: &mut CornerBlock,
    c4: &mut CornerBlock,
) {
    for j in 0..m {
        let i = start + j;
        if !live(i) {
            c3.1[j] = [0.0; 16];
            c4.1[j] = [0.0; 16];
            continue;
        }
        let x = &points[i * point_stride..i * point_stride + 4];
        corners::<3, false>(mask, l3, x, &mut c3.0[j], &mut c3.1[j]);
        let p = clamp_unit(x[3]) * l4.scale[3] + 0.5;
        let it = p as u32;
        let fr = p - it as f32;
        let (lo, hi) = (
            it.wrapping_mul(PRIMES[3]) & mask,
            (it + 1).wrapping_mul(PRIMES[3]) & mask,
        );
        for c in 0..8 {
            let (r, w) = (c3.0[j][c], c3.1[j][c]);
            c4.0[j][c] = r ^ lo;
            c4.0[j][c + 8] = r ^ hi;
            c4.1[j][c] = w * (1.0 - fr);
            c4.1[j][c + 8] = w * fr;
        }
        for c in 0..8 {
            prefetch(table3, c3.0[j][c] as usize * F);
        }
        for c in 0..16 {
            prefetch(table4, c4.0[j][c] as usize * F);
        }
    }
}

/// The scalar forward of a paired level: [`encode_level_impl`] of both levels in one walk, over
/// the corners [`pair_corners_block`] makes.
#[allow(clippy::too_many_arguments)]
#[inline(never)]
fn encode_pair_level<const F: usize>(
    layout: &GridLayout,
    l3: &LevelLayout,
    table3: &[f32],
    l4: &LevelLayout,
    table4: &[f32],
    points: &[f32],
    point_stride: usize,
    out3: &mut [f32],
    out4: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) {
    let n = points.len() / point_stride;
    let mask = (layout.table_size - 1) as u32;
    let (rows3, rows4) = (table3.len() / F, table4.len() / F);
    walk_blocks(
        n,
        (EMPTY_BLOCK, EMPTY_BLOCK),
        &mut (out3, out4),
        |_, start, m, (c3, c4)| {
            let (ps, all) = (point_stride, |_| true);
            pair_corners_block::<F>(
                mask, l3, table3, l4, table4, points, ps, start, m, all, c3, c4,
            )
        },
        |(out3, out4), i, j, (c3, c4)| {
            let o = i * out_stride + out_offset;
            out3[o..o + F].copy_from_slice(&gather::<F>(table3, rows3, c3, j, 8));
            out4[o..o + F].copy_from_slice(&gather::<F>(table4, rows4, c4, j, 16));
        },
    );
}

/// The scalar backward of a paired level: [`backward_level_impl`] of both levels in one walk.
#[allow(clippy::too_many_arguments)]
#[inline(never)]
fn backward_pair_level<const F: usize>(
    layout: &GridLayout,
    l3: &LevelLayout,
    grad3: &mut [f32],
    l4: &LevelLayout,
    grad4: &mut [f32],
    points: &[f32],
    point_stride: usize,
    d3: &[f32],
    d4: &[f32],
    d_stride: usize,
    d_offset: usize,
) {
    let n = points.len() / point_stride;
    let mask = (layout.table_size - 1) as u32;
    let row = |i: usize| i * d_stride + d_offset..i * d_stride + d_offset + F;
    let live =
        |i: usize| d3[row(i)].iter().any(|&v| v != 0.0) || d4[row(i)].iter().any(|&v| v != 0.0);
    walk_blocks(
        n,
        (EMPTY_BLOCK, EMPTY_BLOCK),
        &mut (grad3, grad4),
        |(grad3, grad4), start, m, (c3, c4)| {
            let ps = point_stride;
            pair_corners_block::<F>(
                mask, l3, grad3, l4, grad4, points, ps, start, m, live, c3, c4,
            )
        },
        |(grad3, grad4), i, j, (c3, c4)| {
            scatter::<F>(grad3, c3, j, &d3[row(i)], 8);
            scatter::<F>(grad4, c4, j, &d4[row(i)], 16);
        },
    );
}
