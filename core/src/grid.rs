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
mod simd;

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
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn cfg(dims: usize, levels: usize, log2: u32, f: usize) -> GridConfig {
        GridConfig {
            levels,
            features_per_level: f,
            log2_table_size: log2,
            base_resolution: vec![4.0; dims],
            finest_resolution: if dims == 3 {
                vec![64.0; 3]
            } else {
                vec![64.0, 64.0, 64.0, 20.0]
            },
        }
    }

    fn random(n: usize, rng: &mut Rng) -> Vec<f32> {
        (0..n).map(|_| rng.f32()).collect()
    }

    #[test]
    fn method_md_reference_geometry() {
        // method.md: 16 levels, base 16, finest 2048 -> per-level scale 1.38191.
        let c = GridConfig {
            levels: 16,
            features_per_level: 2,
            log2_table_size: 19,
            base_resolution: vec![16.0, 16.0, 16.0, 15.0],
            finest_resolution: vec![2048.0, 2048.0, 2048.0, 300.0],
        };
        let g = GridLayout::new(&c);
        assert_eq!(g.levels[0].scale[0], 15.0);
        assert_eq!(g.levels[0].res[0], 16);
        assert!((g.levels[1].scale[0] - (16.0 * 1.381_91 - 1.0)).abs() < 1e-3);
        assert!((g.levels[1].scale[3] - (15.0 * 1.221_06 - 1.0)).abs() < 1e-3);
        assert!((g.levels[15].scale[0] - 2047.0).abs() < 0.05);
        assert!((g.levels[15].scale[3] - 299.0).abs() < 0.05);
        // 17^3*16 = 78608 rows fit in 2^19, so level 0 of the 4D grid is dense.
        assert!(g.levels[0].dense);
        assert_eq!(g.levels[0].rows, 17 * 17 * 17 * 16);
        assert!(!g.levels[3].dense);
        assert_eq!(g.levels[3].rows, 1 << 19);
    }

    #[test]
    fn fast_matches_reference_all_shapes() {
        let mut rng = Rng::new(1);
        for dims in [3, 4] {
            for f in [1, 2, 4, 8] {
                for log2 in [6, 12] {
                    let c = cfg(dims, 5, log2, f);
                    c.validate("test").unwrap();
                    let g = GridLayout::new(&c);
                    let table: Vec<f32> = (0..g.num_params)
                        .map(|_| rng.range_f32(-1.0, 1.0))
                        .collect();
                    let n = 64;
                    let mut pts = random(n * 4, &mut rng);
                    pts[0] = 0.0;
                    pts[5] = 1.0;
                    pts[6] = f32::NAN;
                    pts[7] = -3.0;
                    let e = g.output_dim();
                    let mut out = vec![0f32; n * (e + 3)];
                    g.encode(&table, &pts, 4, &mut out, e + 3, 1);
                    let d_out: Vec<f32> =
                        (0..n * (e + 3)).map(|_| rng.range_f32(-1.0, 1.0)).collect();
                    let mut grad_fast = vec![0f32; g.num_params];
                    g.backward(&pts, 4, &d_out, e + 3, 1, &mut grad_fast);
                    let mut grad_ref = vec![0f32; g.num_params];
                    for i in 0..n {
                        let r = g.encode_point_reference(&table, &pts[i * 4..i * 4 + dims]);
                        for k in 0..e {
                            let v = out[i * (e + 3) + 1 + k];
                            assert!(
                                (v - r[k]).abs() < 1e-5,
                                "dims {dims} f {f}: {v} vs {}",
                                r[k]
                            );
                        }
                        g.backward_point_reference(
                            &pts[i * 4..i * 4 + dims],
                            &d_out[i * (e + 3) + 1..i * (e + 3) + 1 + e],
                            &mut grad_ref,
                        );
                    }
                    for (a, b) in grad_fast.iter().zip(&grad_ref) {
                        assert!((a - b).abs() < 1e-4);
                    }
                }
            }
        }
    }

    /// The paired 3D + 4D pass gives the same bits as the two grids' own passes, forward and
    /// backward, on dense, hashed and mixed levels (and zero gradients on some points).
    #[test]
    fn pair_matches_separate_passes_exactly() {
        let mut rng = Rng::new(11);
        for f in [1, 2, 4, 8] {
            for log2 in [6, 9, 12] {
                let (g3, g4) = (
                    GridLayout::new(&cfg(3, 6, log2, f)),
                    GridLayout::new(&cfg(4, 6, log2, f)),
                );
                assert!(pairable(&g3, &g4));
                let t3: Vec<f32> = (0..g3.num_params)
                    .map(|_| rng.range_f32(-1.0, 1.0))
                    .collect();
                let t4: Vec<f32> = (0..g4.num_params)
                    .map(|_| rng.range_f32(-1.0, 1.0))
                    .collect();
                let n = 77;
                let mut pts = random(n * 4, &mut rng);
                pts[2] = f32::NAN;
                pts[7] = 1.0;
                let e = g3.output_dim();
                let (mut a3, mut a4) = (vec![0f32; n * (e + 1)], vec![0f32; n * (e + 1)]);
                g3.encode(&t3, &pts, 4, &mut a3, e + 1, 1);
                g4.encode(&t4, &pts, 4, &mut a4, e + 1, 1);
                let (mut b3, mut b4) = (vec![0f32; n * (e + 1)], vec![0f32; n * (e + 1)]);
                encode_pair(&g3, &t3, &g4, &t4, &pts, 4, &mut b3, &mut b4, e + 1, 1);
                assert_eq!(a3, b3);
                assert_eq!(a4, b4);
                let mut d3: Vec<f32> = (0..n * (e + 1)).map(|_| rng.range_f32(-1.0, 1.0)).collect();
                let mut d4: Vec<f32> = (0..n * (e + 1)).map(|_| rng.range_f32(-1.0, 1.0)).collect();
                d3[..5 * (e + 1)].fill(0.0);
                d4[3 * (e + 1)..9 * (e + 1)].fill(0.0);
                let (mut s3, mut s4) = (vec![0f32; g3.num_params], vec![0f32; g4.num_params]);
                g3.backward(&pts, 4, &d3, e + 1, 1, &mut s3);
                g4.backward(&pts, 4, &d4, e + 1, 1, &mut s4);
                let (mut p3, mut p4) = (vec![0f32; g3.num_params], vec![0f32; g4.num_params]);
                backward_pair(&g3, &g4, &pts, 4, &d3, &d4, e + 1, 1, &mut p3, &mut p4);
                assert_eq!(s3, p3);
                assert_eq!(s4, p4);
            }
        }
        // Different spatial scales cannot share corners.
        let mut c4 = cfg(4, 6, 9, 2);
        c4.finest_resolution[0] = 32.0;
        assert!(!pairable(
            &GridLayout::new(&cfg(3, 6, 9, 2)),
            &GridLayout::new(&c4)
        ));
    }

    /// The encoding is linear in the table, so the finite-difference check of the table gradient
    /// is exact up to rounding; the check still runs through the public API end to end.
    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = Rng::new(3);
        for dims in [3, 4] {
            let c = cfg(dims, 4, 8, 2);
            let g = GridLayout::new(&c);
            let mut table: Vec<f64> = (0..g.num_params)
                .map(|_| rng.range_f32(-1.0, 1.0) as f64)
                .collect();
            let x: Vec<f32> = random(dims, &mut rng);
            let w: Vec<f32> = random(g.output_dim(), &mut rng);
            let loss = |t: &[f64]| -> f64 {
                let t32: Vec<f32> = t.iter().map(|&v| v as f32).collect();
                let o = g.encode_point_reference(&t32, &x);
                o.iter()
                    .zip(&w)
                    .map(|(a, b)| (*a as f64) * (*b as f64))
                    .sum()
            };
            let mut grad = vec![0f32; g.num_params];
            g.backward_point_reference(&x, &w, &mut grad);
            let touched: Vec<usize> = (0..g.num_params).filter(|&i| grad[i] != 0.0).collect();
            assert!(!touched.is_empty());
            for &i in touched.iter().take(40) {
                let h = 1e-2;
                let v = table[i];
                table[i] = v + h;
                let lp = loss(&table);
                table[i] = v - h;
                let lm = loss(&table);
                table[i] = v;
                let fd = (lp - lm) / (2.0 * h);
                assert!((fd - grad[i] as f64).abs() < 1e-4, "{fd} vs {}", grad[i]);
            }
        }
    }

    /// Gradient with respect to the input position (not used in training, but it validates the
    /// interpolation weights): the encoding must be continuous across cell borders.
    #[test]
    fn encoding_is_continuous() {
        let mut rng = Rng::new(9);
        let g = GridLayout::new(&cfg(4, 6, 10, 2));
        let table: Vec<f32> = (0..g.num_params)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        for _ in 0..200 {
            let x = random(4, &mut rng);
            let mut y = x.clone();
            y[rng.below(4) as usize] += 1e-5;
            let a = g.encode_point_reference(&table, &x);
            let b = g.encode_point_reference(&table, &y);
            for k in 0..a.len() {
                assert!((a[k] - b[k]).abs() < 1e-2);
            }
        }
    }

    #[test]
    fn extreme_configs_do_not_overflow() {
        for log2 in [3, 10, 24] {
            for levels in [1, 32] {
                let c = GridConfig {
                    levels,
                    features_per_level: 2,
                    log2_table_size: log2,
                    base_resolution: vec![1.0, 1.0, 1.0, 1.0],
                    finest_resolution: vec![65536.0, 65536.0, 65536.0, 65536.0],
                };
                c.validate("t").unwrap();
                let g = GridLayout::new(&c);
                for level in &g.levels {
                    assert!(level.rows <= 1 << log2);
                }
                let x = [1.0f32, 1.0, 1.0, 1.0];
                let mut rows_seen = 0;
                g.visit_rows(&x, |l, r| {
                    assert!(r < g.levels[l].rows);
                    rows_seen += 1;
                });
                assert_eq!(rows_seen, 16 * levels);
            }
        }
    }

    #[test]
    fn dense_rows_stay_in_table() {
        let g = GridLayout::new(&cfg(3, 8, 16, 2));
        let mut rng = Rng::new(4);
        for _ in 0..2000 {
            let mut x = random(3, &mut rng);
            if rng.f32() < 0.3 {
                x[0] = 1.0;
                x[1] = 1.0;
            }
            g.visit_rows(&x, |l, r| {
                assert!(r < g.levels[l].rows, "level {l} row {r}")
            });
        }
    }

    #[test]
    fn dense_grid_matches_fd() {
        let dg = DenseGrid3 { res: 5 };
        let mut rng = Rng::new(5);
        let vals: Vec<f32> = (0..dg.num_params())
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let x = [0.3f32, 0.77, 0.51];
        let mut grad = vec![0f32; vals.len()];
        dg.backward(&x, 1.0, &mut grad);
        for i in 0..vals.len() {
            let mut v = vals.clone();
            v[i] += 1e-2;
            let fd = (dg.sample(&v, &x) - dg.sample(&vals, &x)) / 1e-2;
            assert!((fd - grad[i]).abs() < 1e-3);
        }
        // corners are exact
        assert_eq!(dg.sample(&vals, &[0.0, 0.0, 0.0]), vals[0]);
        assert_eq!(dg.sample(&vals, &[1.0, 1.0, 1.0]), vals[124]);
    }
}
