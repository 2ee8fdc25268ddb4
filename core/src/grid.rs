//! Multi-resolution hash grids over 3D `(x, y, z)` and 4D `(x, y, z, t)` with per-axis
//! ("rectangular") resolutions, and the dense 3D voxel grid used for the mask.
//!
//! Geometry (method.md §1), per level `l` and axis `a`:
//! - growth `s_a = exp((ln finest_a - ln base_a) / (L - 1))`,
//! - `scale_a = base_a * s_a^l - 1`, `res_a = ceil(scale_a) + 1`,
//! - `pos_a = x_a * scale_a + 0.5`, `i_a = floor(pos_a)`, weight `pos_a - i_a`; the `2^D` corners
//!   `i_a` / `i_a + 1` are interpolated multilinearly, so corner coordinates lie in `0..=res_a`;
//! - a level whose dense grid `prod(res_a + 1)` fits in `T = 2^log2_table_size` rows is indexed
//!   densely (`sum c_a * stride_a`) with `prod(res_a + 1)` rows rounded up to 8; otherwise it has
//!   `T` rows indexed by `XOR_a(c_a * prime_a) mod T` (u32 wrapping), primes
//!   `(1, 2654435761, 805459861, 3674653429)`.
//!
//! Tables are stored level after level, row-major `[rows, F]`, inside one parameter slice.
//! Inputs are expected in `[0, 1]`; anything else (NaN included) is clamped into it.
//!
//! [`GridLayout::encode_point_reference`] / [`GridLayout::backward_point_reference`] are the plain
//! references; [`GridLayout::encode`] / [`GridLayout::backward`] are the batched, level-major fast
//! paths (const-generic over dimension and features) that the trainer and player use. On x86_64
//! with AVX2, hashed levels with two features run eight points at a time (`grid/simd.rs`), with
//! the scalar kernels' bits.

use serde::{Deserialize, Serialize};

#[cfg(target_arch = "x86_64")]
mod pair;
mod simd;

pub use pair::{backward_pair, backward_pair_with, encode_pair, encode_pair_with, pairable};

/// Calls the local macro `$go!(D, F)` with the grid's dimension and features as constants.
macro_rules! dispatch_shape {
    ($dims:expr, $features:expr, $go:ident) => {
        match ($dims, $features) {
            (3, 1) => $go!(3, 1),
            (3, 2) => $go!(3, 2),
            (3, 4) => $go!(3, 4),
            (3, 8) => $go!(3, 8),
            (4, 1) => $go!(4, 1),
            (4, 2) => $go!(4, 2),
            (4, 4) => $go!(4, 4),
            (4, 8) => $go!(4, 8),
            _ => unreachable!("validated grid config"),
        }
    };
}

/// Hash primes for (x, y, z, t).
pub const PRIMES: [u32; 4] = [1, 2_654_435_761, 805_459_861, 3_674_653_429];

/// Largest supported table: 2^24 rows per level.
pub const MAX_LOG2_TABLE_SIZE: u32 = 24;
/// Largest supported number of levels.
pub const MAX_LEVELS: usize = 32;
/// Largest supported resolution along one axis.
pub const MAX_RESOLUTION: f32 = 1_048_576.0;

/// What a user configures for one hash grid.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GridConfig {
    pub levels: usize,
    pub features_per_level: usize,
    pub log2_table_size: u32,
    /// Coarsest resolution per axis (length = dimension: 3 or 4).
    pub base_resolution: Vec<f32>,
    /// Finest resolution per axis.
    pub finest_resolution: Vec<f32>,
}

/// Why a grid configuration was rejected by [`GridConfig::validate`]: which grid, and what is wrong.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{what}: {reason}")]
pub struct InvalidGrid {
    /// The grid's name in the configuration, e.g. `field.encoding.grid3`.
    pub what: String,
    pub reason: String,
}

impl InvalidGrid {
    fn new(what: &str, reason: String) -> Self {
        InvalidGrid {
            what: what.to_string(),
            reason,
        }
    }
}

impl GridConfig {
    pub fn dims(&self) -> usize {
        self.base_resolution.len()
    }

    pub fn validate(&self, what: &str) -> Result<(), InvalidGrid> {
        let d = self.base_resolution.len();
        if !(d == 3 || d == 4) || self.finest_resolution.len() != d {
            return Err(InvalidGrid::new(
                what,
                format!(
                    "base and finest resolutions need 3 or 4 axes each (got {} and {})",
                    d,
                    self.finest_resolution.len()
                ),
            ));
        }
        if self.levels == 0 || self.levels > MAX_LEVELS {
            return Err(InvalidGrid::new(
                what,
                format!("levels must be in 1..={MAX_LEVELS} (got {})", self.levels),
            ));
        }
        if ![1, 2, 4, 8].contains(&self.features_per_level) {
            return Err(InvalidGrid::new(
                what,
                format!(
                    "features_per_level must be 1, 2, 4 or 8 (got {})",
                    self.features_per_level
                ),
            ));
        }
        if !(3..=MAX_LOG2_TABLE_SIZE).contains(&self.log2_table_size) {
            return Err(InvalidGrid::new(
                what,
                format!(
                    "log2_table_size must be in 3..={MAX_LOG2_TABLE_SIZE} (got {})",
                    self.log2_table_size
                ),
            ));
        }
        for a in 0..d {
            let (b, f) = (self.base_resolution[a], self.finest_resolution[a]);
            if !(b.is_finite() && (1.0..=MAX_RESOLUTION).contains(&b)) {
                return Err(InvalidGrid::new(
                    what,
                    format!("base resolution {b} on axis {a} is out of range"),
                ));
            }
            if !(f.is_finite() && (b..=MAX_RESOLUTION).contains(&f)) {
                return Err(InvalidGrid::new(
                    what,
                    format!(
                        "finest resolution {f} on axis {a} must be in [base {b}, {MAX_RESOLUTION}]"
                    ),
                ));
            }
        }
        Ok(())
    }

    pub fn output_dim(&self) -> usize {
        self.levels * self.features_per_level
    }
}

/// Derived geometry of one level.
#[derive(Clone, Debug, PartialEq)]
pub struct LevelLayout {
    /// `scale_a` per axis (unused axes: 0).
    pub scale: [f32; 4],
    /// `res_a = ceil(scale_a) + 1`; corner coordinates lie in `0..=res_a`.
    pub res: [u32; 4],
    /// Dense strides (only meaningful when `dense`).
    pub stride: [u32; 4],
    pub rows: usize,
    /// Offset of this level's table, in floats, from the start of the grid's slice.
    pub offset: usize,
    pub dense: bool,
}

/// Derived geometry of a whole grid: levels, row counts, parameter count.
#[derive(Clone, Debug, PartialEq)]
pub struct GridLayout {
    pub dims: usize,
    pub features: usize,
    pub levels: Vec<LevelLayout>,
    pub num_params: usize,
    pub table_size: usize,
}

impl GridLayout {
    /// Builds the layout; call [`GridConfig::validate`] first for a friendly error.
    pub fn new(cfg: &GridConfig) -> Self {
        let d = cfg.dims();
        let n_levels = cfg.levels;
        let table_size = 1usize << cfg.log2_table_size;
        let mut levels = Vec::with_capacity(n_levels);
        let mut offset = 0usize;
        for l in 0..n_levels {
            let mut scale = [0f32; 4];
            let mut res = [0u32; 4];
            let mut dense_size: u128 = 1;
            for a in 0..d {
                let (b, f) = (
                    cfg.base_resolution[a] as f64,
                    cfg.finest_resolution[a] as f64,
                );
                let growth = if n_levels > 1 {
                    ((f.ln() - b.ln()) / (n_levels as f64 - 1.0)).exp()
                } else {
                    1.0
                };
                let s = (b * growth.powi(l as i32) - 1.0).max(0.0);
                scale[a] = s as f32;
                res[a] = (scale[a] as f64).ceil() as u32 + 1;
                dense_size = dense_size.saturating_mul(res[a] as u128 + 1);
            }
            let dense = dense_size <= table_size as u128;
            let rows = if dense {
                (dense_size as usize).div_ceil(8) * 8
            } else {
                table_size
            };
            let mut stride = [0u32; 4];
            if dense {
                let mut s = 1u32;
                for a in 0..d {
                    stride[a] = s;
                    s = s.saturating_mul(res[a] + 1);
                }
            }
            levels.push(LevelLayout {
                scale,
                res,
                stride,
                rows,
                offset,
                dense,
            });
            offset += rows * cfg.features_per_level;
        }
        GridLayout {
            dims: d,
            features: cfg.features_per_level,
            levels,
            num_params: offset,
            table_size,
        }
    }

    pub fn output_dim(&self) -> usize {
        self.levels.len() * self.features
    }

    /// Row index of an integer corner (plain reference).
    pub fn corner_row(&self, level: &LevelLayout, corner: &[u32]) -> usize {
        if level.dense {
            let mut idx = 0u64;
            for a in 0..self.dims {
                idx += corner[a] as u64 * level.stride[a] as u64;
            }
            idx as usize
        } else {
            let mut h = 0u32;
            for a in 0..self.dims {
                h ^= corner[a].wrapping_mul(PRIMES[a]);
            }
            (h as usize) & (self.table_size - 1)
        }
    }

    /// Plain reference encoding of one point: `levels * F` features.
    pub fn encode_point_reference(&self, table: &[f32], x: &[f32]) -> Vec<f32> {
        let mut out = vec![0f32; self.output_dim()];
        for (l, level) in self.levels.iter().enumerate() {
            self.for_each_corner_reference(level, x, |row, w| {
                for f in 0..self.features {
                    out[l * self.features + f] += w * table[level.offset + row * self.features + f];
                }
            });
        }
        out
    }

    /// Plain reference backward of one point: `grad_table += d(out)/d(table)^T d_out`.
    pub fn backward_point_reference(&self, x: &[f32], d_out: &[f32], grad_table: &mut [f32]) {
        for (l, level) in self.levels.iter().enumerate() {
            self.for_each_corner_reference(level, x, |row, w| {
                for f in 0..self.features {
                    grad_table[level.offset + row * self.features + f] +=
                        w * d_out[l * self.features + f];
                }
            });
        }
    }

    fn for_each_corner_reference(
        &self,
        level: &LevelLayout,
        x: &[f32],
        mut f: impl FnMut(usize, f32),
    ) {
        let d = self.dims;
        let mut base = [0u32; 4];
        let mut frac = [0f32; 4];
        for a in 0..d {
            let p = clamp_unit(x[a]) * level.scale[a] + 0.5;
            let i = p.floor();
            base[a] = i as u32;
            frac[a] = p - i;
        }
        for corner in 0..(1usize << d) {
            let mut c = [0u32; 4];
            let mut w = 1f32;
            for a in 0..d {
                if corner >> a & 1 == 1 {
                    c[a] = base[a] + 1;
                    w *= frac[a];
                } else {
                    c[a] = base[a];
                    w *= 1.0 - frac[a];
                }
            }
            f(self.corner_row(level, &c[..d]), w);
        }
    }

    /// Batched fast encoding. `points` holds `n` points with `point_stride` floats each (the
    /// first `dims` are used); features of point `i` go to
    /// `out[i * out_stride + out_offset ..][..levels * F]`.
    pub fn encode(
        &self,
        table: &[f32],
        points: &[f32],
        point_stride: usize,
        out: &mut [f32],
        out_stride: usize,
        out_offset: usize,
    ) {
        let n = points.len() / point_stride;
        assert!(out.len() >= n * out_stride && out_offset + self.output_dim() <= out_stride);
        assert!(table.len() >= self.num_params);
        let simd = simd_available();
        macro_rules! go {
            ($d:literal, $f:literal) => {
                for (l, level) in self.levels.iter().enumerate() {
                    encode_level::<$d, $f>(
                        simd,
                        self,
                        level,
                        &table[level.offset..level.offset + level.rows * $f],
                        points,
                        point_stride,
                        out,
                        out_stride,
                        out_offset + l * $f,
                    );
                }
            };
        }
        dispatch_shape!(self.dims, self.features, go)
    }

    /// Batched fast backward: scatters `d_out` (same layout as [`GridLayout::encode`]'s `out`)
    /// into `grad_table`.
    pub fn backward(
        &self,
        points: &[f32],
        point_stride: usize,
        d_out: &[f32],
        d_stride: usize,
        d_offset: usize,
        grad_table: &mut [f32],
    ) {
        assert!(grad_table.len() >= self.num_params);
        let simd = simd_available();
        macro_rules! go {
            ($d:literal, $f:literal) => {
                for (l, level) in self.levels.iter().enumerate() {
                    backward_level::<$d, $f>(
                        simd,
                        self,
                        level,
                        &mut grad_table[level.offset..level.offset + level.rows * $f],
                        points,
                        point_stride,
                        d_out,
                        d_stride,
                        d_offset + l * $f,
                    );
                }
            };
        }
        dispatch_shape!(self.dims, self.features, go)
    }

    /// Calls `f(level, row)` for every table row that point `x` reads (used by the codec to find
    /// the entries a region reaches).
    pub fn visit_rows(&self, x: &[f32], mut f: impl FnMut(usize, usize)) {
        for (l, level) in self.levels.iter().enumerate() {
            self.for_each_corner_reference(level, x, |row, _| f(l, row));
        }
    }
}

/// Clamps into `[0, 1]`, mapping NaN to 0.
#[inline(always)]
pub fn clamp_unit(x: f32) -> f32 {
    if x >= 0.0 {
        x.min(1.0)
    } else {
        0.0
    }
}

/// Corner rows and weights of one point on one level (fast path). `DENSE` selects the indexing
/// once per level instead of once per corner; weights are built by doubling, one axis at a time.
#[inline(always)]
fn corners<const D: usize, const DENSE: bool>(
    mask: u32,
    level: &LevelLayout,
    x: &[f32],
    rows: &mut [u32; 16],
    weights: &mut [f32; 16],
) {
    rows[0] = 0;
    weights[0] = 1.0;
    let mut n = 1usize;
    for a in 0..D {
        let p = clamp_unit(x[a]) * level.scale[a] + 0.5;
        let i = p as u32; // p >= 0.5, so truncation is floor
        let fr = p - i as f32;
        let (lo, hi) = if DENSE {
            let lo = i * level.stride[a];
            (lo, lo + level.stride[a])
        } else {
            (i.wrapping_mul(PRIMES[a]), (i + 1).wrapping_mul(PRIMES[a]))
        };
        for c in 0..n {
            let (r, w) = (rows[c], weights[c]);
            if DENSE {
                rows[c] = r + lo;
                rows[c + n] = r + hi;
            } else {
                rows[c] = r ^ lo;
                rows[c + n] = r ^ hi;
            }
            weights[c] = w * (1.0 - fr);
            weights[c + n] = w * fr;
        }
        n *= 2;
    }
    if !DENSE {
        for r in rows.iter_mut().take(n) {
            *r &= mask;
        }
    }
}

/// Whether the AVX2 kernels of `grid/simd.rs` run on this CPU (x86_64 with AVX2, checked at run
/// time); where they do not, every pass takes the scalar kernels.
pub fn simd_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    return simd::available();
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// One hashed level pass for the AVX2 kernels of `grid/simd.rs`: a 3D level, a 4D level, or a
/// pair of both (same table size and spatial scales, see [`pairable`]).
#[derive(Clone, Copy)]
enum Pass<'a> {
    /// A 3D level.
    Three(&'a LevelLayout),
    /// A 4D level.
    Four(&'a LevelLayout),
    /// A 3D level and the 4D level with its spatial scales.
    Pair(&'a LevelLayout, &'a LevelLayout),
}

impl<'a> Pass<'a> {
    /// The level whose `x, y, z` scales make the corners, and the one whose `t` scale does.
    fn levels(self) -> (&'a LevelLayout, Option<&'a LevelLayout>) {
        match self {
            Pass::Three(l) => (l, None),
            Pass::Four(l) => (l, Some(l)),
            Pass::Pair(l3, l4) => (l3, Some(l4)),
        }
    }

    /// `three` and `four` where the pass reads or writes the 3D and the 4D level.
    fn sides<T>(self, three: T, four: T) -> (Option<T>, Option<T>) {
        match self {
            Pass::Three(_) => (Some(three), None),
            Pass::Four(_) => (None, Some(four)),
            Pass::Pair(..) => (Some(three), Some(four)),
        }
    }

    /// Whether the AVX2 kernels take this pass (`simd`: the CPU has them): two features per
    /// row, hashed levels, points with the pass's axes.
    fn simd_applies(self, simd: bool, layout: &GridLayout, point_stride: usize) -> bool {
        let (spatial, t_level) = self.levels();
        let dense = spatial.dense || t_level.is_some_and(|l| l.dense);
        let dims = if t_level.is_some() { 4 } else { 3 };
        simd && layout.features == 2 && !dense && point_stride >= dims
    }
}

/// The AVX2 forward of the full eight-point blocks of a hashed level pass with two features
/// (`table3` / `out3` for the 3D level, `table4` / `out4` for the 4D one; the other pair is
/// unused). Returns how many leading points it encoded, 0 where the kernels do not apply; the
/// caller's scalar kernel does the rest.
#[allow(clippy::too_many_arguments)]
fn simd_encode(
    simd: bool,
    layout: &GridLayout,
    pass: Pass,
    table3: &[f32],
    table4: &[f32],
    points: &[f32],
    point_stride: usize,
    out3: &mut [f32],
    out4: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        let mask = (layout.table_size - 1) as u32;
        let (spatial, t_level) = pass.levels();
        let (t3, t4) = pass.sides(table3, table4);
        let fits = t3.is_none_or(|t| simd::rows_fit(mask, t.len()))
            && t4.is_none_or(|t| simd::rows_fit(mask, t.len()));
        if fits && pass.simd_applies(simd, layout, point_stride) {
            // SAFETY: `simd` comes from `simd_available`, every masked row fits the tables, and
            // `t_level` comes with `t4`.
            return unsafe {
                simd::encode_level(
                    mask,
                    spatial,
                    t_level,
                    t3,
                    t4,
                    points,
                    point_stride,
                    out3,
                    out4,
                    out_stride,
                    out_offset,
                )
            };
        }
    }
    let _ = (simd, layout, pass, table3, table4, points, point_stride);
    let _ = (out3, out4, out_stride, out_offset);
    0
}

/// Largest table (rows per level) whose backward pass takes the AVX2 scatter. Beyond it the
/// levels outgrow the L2 cache, and the scalar scatter, which prefetches the next block's rows,
/// is faster (paper configuration, 2^19 rows: 7.8 s against 6.9 s per step on one thread).
const SIMD_SCATTER_MAX_ROWS: usize = 1 << 17;

/// The backward counterpart of [`simd_encode`]: scatters the full blocks, returns how many
/// leading points it visited (0 for tables over [`SIMD_SCATTER_MAX_ROWS`] rows).
#[allow(clippy::too_many_arguments)]
fn simd_backward(
    simd: bool,
    layout: &GridLayout,
    pass: Pass,
    grad3: &mut [f32],
    grad4: &mut [f32],
    points: &[f32],
    point_stride: usize,
    d3: &[f32],
    d4: &[f32],
    d_stride: usize,
    d_offset: usize,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        let mask = (layout.table_size - 1) as u32;
        let (spatial, t_level) = pass.levels();
        let (g3, g4) = pass.sides(grad3, grad4);
        let fits = layout.table_size <= SIMD_SCATTER_MAX_ROWS
            && g3.as_ref().is_none_or(|g| simd::rows_fit(mask, g.len()))
            && g4.as_ref().is_none_or(|g| simd::rows_fit(mask, g.len()));
        if fits && pass.simd_applies(simd, layout, point_stride) {
            // SAFETY: `simd` comes from `simd_available`, so the CPU has AVX2.
            return unsafe {
                simd::backward_level(
                    mask,
                    spatial,
                    t_level,
                    g3,
                    g4,
                    points,
                    point_stride,
                    d3,
                    d4,
                    d_stride,
                    d_offset,
                )
            };
        }
    }
    let _ = (simd, layout, pass, points, point_stride);
    let _ = (d3, d4, d_stride, d_offset);
    0
}

#[allow(clippy::too_many_arguments)]
fn encode_level<const D: usize, const F: usize>(
    simd: bool,
    layout: &GridLayout,
    level: &LevelLayout,
    table: &[f32],
    points: &[f32],
    point_stride: usize,
    out: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) {
    let (o, ps) = (out_offset, point_stride);
    let done = if D == 3 {
        let pass = Pass::Three(level);
        simd_encode(
            simd,
            layout,
            pass,
            table,
            &[],
            points,
            ps,
            out,
            &mut [],
            out_stride,
            o,
        )
    } else {
        let pass = Pass::Four(level);
        simd_encode(
            simd,
            layout,
            pass,
            &[],
            table,
            points,
            ps,
            &mut [],
            out,
            out_stride,
            o,
        )
    };
    if done > 0 {
        return encode_level::<D, F>(
            false,
            layout,
            level,
            table,
            &points[done * point_stride..],
            point_stride,
            &mut out[done * out_stride..],
            out_stride,
            out_offset,
        );
    }
    if level.dense {
        encode_level_impl::<D, F, true>(
            layout,
            level,
            table,
            points,
            point_stride,
            out,
            out_stride,
            out_offset,
        )
    } else {
        encode_level_impl::<D, F, false>(
            layout,
            level,
            table,
            points,
            point_stride,
            out,
            out_stride,
            out_offset,
        )
    }
}

/// Points whose corner rows are computed (and prefetched) together. The kernels work one block
/// ahead: while block `b` is read (forward) or written (backward), the rows of block `b + 1` are
/// already on their way, so the cache misses of hashed rows overlap the arithmetic instead of
/// stalling it one point at a time.
const ENCODE_BLOCK: usize = 8;

/// Hints the CPU to start loading the cache line holding `table[i]` (no effect where there is no
/// such instruction; never faults, whatever the index).
#[inline(always)]
fn prefetch(table: &[f32], i: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: SSE is part of the x86_64 baseline, and a prefetch never faults, whatever the
        // address (`wrapping_add` keeps computing it free of undefined behaviour).
        unsafe { _mm_prefetch::<_MM_HINT_T0>(table.as_ptr().wrapping_add(i) as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (table, i);
}

/// Corner rows and weights of the points of one block on one level: `.0[j][c]` and `.1[j][c]`
/// for corner `c` of the block's `j`-th point.
type CornerBlock = ([[u32; 16]; ENCODE_BLOCK], [[f32; 16]; ENCODE_BLOCK]);

/// A [`CornerBlock`] before its first fill.
const EMPTY_BLOCK: CornerBlock = ([[0; 16]; ENCODE_BLOCK], [[0.0; 16]; ENCODE_BLOCK]);

/// The walk of every scalar level kernel over its `n` points, one block ahead
/// ([`ENCODE_BLOCK`]): `fill(state, start, m, block)` makes (and prefetches) the corners of the
/// `m` points from `start`, the next block's before `visit(state, i, j, block)` takes point `i`,
/// the `j`-th of the current one. Points are visited in order, so sums come out as one point at
/// a time. `state` is what the visits write (outputs, or the gradient table the fills prefetch
/// from), lent to each call in turn; `B` holds one block's corners (one grid's, or a pair's).
#[inline(always)]
fn walk_blocks<S: ?Sized, B: Copy>(
    n: usize,
    empty: B,
    state: &mut S,
    fill: impl Fn(&S, usize, usize, &mut B),
    mut visit: impl FnMut(&mut S, usize, usize, &B),
) {
    let mut blocks = [empty, empty];
    let count = n.div_ceil(ENCODE_BLOCK);
    let size = |b: usize| (n - b * ENCODE_BLOCK).min(ENCODE_BLOCK);
    if count > 0 {
        fill(state, 0, size(0), &mut blocks[0]);
    }
    for b in 0..count {
        let (cur, next) = (b & 1, (b + 1) & 1);
        if b + 1 < count {
            fill(
                state,
                (b + 1) * ENCODE_BLOCK,
                size(b + 1),
                &mut blocks[next],
            );
        }
        for j in 0..size(b) {
            visit(state, b * ENCODE_BLOCK + j, j, &blocks[cur]);
        }
    }
}

/// Corner rows and weights of one block of points on one level, and (hashed levels) prefetches of
/// their rows in `table`. `live(i)` false leaves point `i` out (its weights are zeroed).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn corners_block<const D: usize, const F: usize, const DENSE: bool>(
    mask: u32,
    level: &LevelLayout,
    table: &[f32],
    points: &[f32],
    point_stride: usize,
    start: usize,
    m: usize,
    live: impl Fn(usize) -> bool,
    block: &mut CornerBlock,
) {
    let (rows, weights) = block;
    for j in 0..m {
        let i = start + j;
        if !live(i) {
            weights[j] = [0.0; 16];
            continue;
        }
        let x = &points[i * point_stride..i * point_stride + D];
        corners::<D, DENSE>(mask, level, x, &mut rows[j], &mut weights[j]);
        if !DENSE {
            for c in 0..(1usize << D) {
                prefetch(table, rows[j][c] as usize * F);
            }
        }
    }
}

/// The scalar forward of one level: per point, the weighted sum of its corners' rows
/// ([`gather`]), pipelined by [`walk_blocks`].
#[allow(clippy::too_many_arguments)]
#[inline(never)]
fn encode_level_impl<const D: usize, const F: usize, const DENSE: bool>(
    layout: &GridLayout,
    level: &LevelLayout,
    table: &[f32],
    points: &[f32],
    point_stride: usize,
    out: &mut [f32],
    out_stride: usize,
    out_offset: usize,
) {
    let n = points.len() / point_stride;
    let mask = (layout.table_size - 1) as u32;
    let rows_in_table = table.len() / F;
    walk_blocks(
        n,
        EMPTY_BLOCK,
        out,
        |_, start, m, block| {
            let all = |_| true;
            corners_block::<D, F, DENSE>(
                mask,
                level,
                table,
                points,
                point_stride,
                start,
                m,
                all,
                block,
            )
        },
        |out, i, j, block| {
            let o = i * out_stride + out_offset;
            out[o..o + F].copy_from_slice(&gather::<F>(table, rows_in_table, block, j, 1 << D));
        },
    );
}

#[allow(clippy::too_many_arguments)]
fn backward_level<const D: usize, const F: usize>(
    simd: bool,
    layout: &GridLayout,
    level: &LevelLayout,
    grad: &mut [f32],
    points: &[f32],
    point_stride: usize,
    d_out: &[f32],
    d_stride: usize,
    d_offset: usize,
) {
    let (o, ps) = (d_offset, point_stride);
    let done = if D == 3 {
        let pass = Pass::Three(level);
        simd_backward(
            simd,
            layout,
            pass,
            grad,
            &mut [],
            points,
            ps,
            d_out,
            &[],
            d_stride,
            o,
        )
    } else {
        let pass = Pass::Four(level);
        simd_backward(
            simd,
            layout,
            pass,
            &mut [],
            grad,
            points,
            ps,
            &[],
            d_out,
            d_stride,
            o,
        )
    };
    if done > 0 {
        return backward_level::<D, F>(
            false,
            layout,
            level,
            grad,
            &points[done * point_stride..],
            point_stride,
            &d_out[(done * d_stride).min(d_out.len())..],
            d_stride,
            d_offset,
        );
    }
    if level.dense {
        backward_level_impl::<D, F, true>(
            layout,
            level,
            grad,
            points,
            point_stride,
            d_out,
            d_stride,
            d_offset,
        )
    } else {
        backward_level_impl::<D, F, false>(
            layout,
            level,
            grad,
            points,
            point_stride,
            d_out,
            d_stride,
            d_offset,
        )
    }
}

/// The scatter of [`GridLayout::backward`] on one level ([`scatter`]), pipelined like
/// [`encode_level_impl`]: points are visited in order and corners in order, so the sums are the
/// same as one point at a time. Points whose incoming gradient is zero are skipped.
#[allow(clippy::too_many_arguments)]
#[inline(never)]
fn backward_level_impl<const D: usize, const F: usize, const DENSE: bool>(
    layout: &GridLayout,
    level: &LevelLayout,
    grad: &mut [f32],
    points: &[f32],
    point_stride: usize,
    d_out: &[f32],
    d_stride: usize,
    d_offset: usize,
) {
    let n = points.len() / point_stride;
    let mask = (layout.table_size - 1) as u32;
    let d_row = |i: usize| &d_out[i * d_stride + d_offset..i * d_stride + d_offset + F];
    let live = |i: usize| d_row(i).iter().any(|&v| v != 0.0);
    walk_blocks(
        n,
        EMPTY_BLOCK,
        grad,
        |grad, start, m, block| {
            corners_block::<D, F, DENSE>(
                mask,
                level,
                grad,
                points,
                point_stride,
                start,
                m,
                live,
                block,
            )
        },
        |grad, i, j, block| scatter::<F>(grad, block, j, d_row(i), 1 << D),
    );
}

/// `sum_c w_c table[row_c]` over the first `corners` corners of point `j` of a block, in corner
/// order.
#[inline(always)]
fn gather<const F: usize>(
    table: &[f32],
    rows_in_table: usize,
    block: &CornerBlock,
    j: usize,
    corners: usize,
) -> [f32; F] {
    let mut acc = [0f32; F];
    for c in 0..corners {
        let r = block.0[j][c] as usize;
        // Rows are in range by construction (dense: corners <= res; hashed: masked); the check
        // keeps the access safe and lets the compiler drop per-feature checks.
        if r < rows_in_table {
            let feat = &table[r * F..r * F + F];
            for f in 0..F {
                acc[f] += block.1[j][c] * feat[f];
            }
        }
    }
    acc
}

/// `grad[row_c] += w_c g` over the first `corners` corners of point `j` of a block, in corner
/// order (nothing where `g` is zero).
#[inline(always)]
fn scatter<const F: usize>(
    grad: &mut [f32],
    block: &CornerBlock,
    j: usize,
    g: &[f32],
    corners: usize,
) {
    if g.iter().all(|&v| v == 0.0) {
        return;
    }
    let rows_in_table = grad.len() / F;
    let mut gv = [0f32; F];
    gv.copy_from_slice(g);
    for c in 0..corners {
        let r = block.0[j][c] as usize;
        if r < rows_in_table {
            let dst = &mut grad[r * F..r * F + F];
            for f in 0..F {
                dst[f] += block.1[j][c] * gv[f];
            }
        }
    }
}

/// A dense 3D grid of scalars at `res^3` vertices covering `[0, 1]^3`, read trilinearly
/// (`pos = x * (res - 1)`). Used for the mask (and later the uncertainty grid).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DenseGrid3 {
    pub res: usize,
}

impl DenseGrid3 {
    pub fn num_params(&self) -> usize {
        self.res * self.res * self.res
    }

    #[inline(always)]
    fn corners(&self, x: &[f32]) -> ([usize; 8], [f32; 8]) {
        let r = self.res;
        let mut base = [0usize; 3];
        let mut fr = [0f32; 3];
        for a in 0..3 {
            let p = clamp_unit(x[a]) * (r - 1) as f32;
            let i = (p as usize).min(r - 2);
            base[a] = i;
            fr[a] = p - i as f32;
        }
        let mut idx = [0usize; 8];
        let mut w = [0f32; 8];
        for c in 0..8 {
            let (bx, by, bz) = (c & 1, (c >> 1) & 1, (c >> 2) & 1);
            idx[c] = (base[0] + bx) + r * ((base[1] + by) + r * (base[2] + bz));
            w[c] = (if bx == 1 { fr[0] } else { 1.0 - fr[0] })
                * (if by == 1 { fr[1] } else { 1.0 - fr[1] })
                * (if bz == 1 { fr[2] } else { 1.0 - fr[2] });
        }
        (idx, w)
    }

    /// Trilinear value at `x` (first three components used).
    #[inline]
    pub fn sample(&self, values: &[f32], x: &[f32]) -> f32 {
        let (idx, w) = self.corners(x);
        let mut v = 0.0;
        for c in 0..8 {
            v += w[c] * values[idx[c]];
        }
        v
    }

    /// Scatters `d` into the gradient of the values read at `x`.
    #[inline]
    pub fn backward(&self, x: &[f32], d: f32, grad: &mut [f32]) {
        if d == 0.0 {
            return;
        }
        let (idx, w) = self.corners(x);
        for c in 0..8 {
            grad[idx[c]] += w[c] * d;
        }
    }
}

#[cfg(test)]
mod tests;
