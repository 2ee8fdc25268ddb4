//! The occupancy grid (format.md §6.5, version 2): one bit per cell of a regular grid over the
//! model's unit cube (the grids' coordinates, after the scene bounds' affine map or contraction),
//! set where the field has density at any of the model's frames. A renderer skips samples in
//! empty cells without consulting the proposal network.
//!
//! - [`OccupancyGrid`]: the decoded bits with their layout (cell `(x, y, z)` is bit
//!   `i = x + R (y + R z)`, bit `i % 32` of little-endian word `i / 32`), the lookup a renderer
//!   uses ([`OccupancyGrid::occupied_unit`]) and the section payload's writer and strict reader;
//! - [`compute`]: what `msth export` stores: the main field's density evaluated at the grid's
//!   vertices at every frame, a cell occupied when one of its 8 corners is at or above the
//!   threshold at any frame, then dilated by one cell.
//!
//! The export then keeps only the cells the training cameras see, which takes casting rays:
//! that lives with the renderers (`msth_player::seen`).

use msth_core::config::ModelConfig;
use msth_core::field::{FieldScratch, ModelLayout};
use msth_core::pipeline::RENDER_STATIC_CUTOFF;
use rayon::prelude::*;

use crate::error::DecodeError;

/// Bytes before the bits: `resolution: u32`, `density_threshold: f32`, `frames: u32`,
/// reserved `u32`.
pub const OCCUPANCY_HEADER: usize = 16;
/// The largest resolution a decoder accepts by default (512^3 bits = 16 MiB).
pub const MAX_OCCUPANCY_RESOLUTION: u64 = 512;
/// The writer's default resolution (cells per axis). 128 since 2026-11-30 (64 before): on a
/// forward-facing stage the finer grid leaves a third fewer live proposal samples in a training
/// camera's view at the same held-out PSNR (docs/playback.md, "The occupancy grid").
pub const DEFAULT_OCCUPANCY_RESOLUTION: u32 = 128;
/// The writer's default opacity budget: the density threshold is the one at which a ray crossing
/// the whole grid along its diagonal (world units of the scene's uncontracted part) would reach
/// this opacity. Skipped samples are below the threshold, so a ray loses less than this opacity
/// to skipping (inside the uncontracted part), i.e. a pixel moves by less than 0.01: PSNR of at
/// least 40 dB against the unskipped frame wherever the vertices sample the density well enough
/// (the one-cell dilation is the margin for that).
pub const DEFAULT_OCCUPANCY_ALPHA: f32 = 1e-2;

/// One bit per cell over the unit cube, the union over the model's frames.
#[derive(Clone, Debug, PartialEq)]
pub struct OccupancyGrid {
    /// Cells per axis (`R`); the grid covers `[0, 1]^3` of the unit cube.
    pub resolution: u32,
    /// The density (world units^-1) at or above which a vertex counted as occupied.
    pub density_threshold: f32,
    /// Times at which the density was evaluated (the model's frames, at most
    /// [`MAX_OCCUPANCY_TIMES`]).
    pub frames: u32,
    /// `ceil(R^3 / 32)` words; bit `i % 32` of word `i / 32` is cell `i = x + R (y + R z)`;
    /// bits past `R^3` are 0.
    pub words: Vec<u32>,
}

impl OccupancyGrid {
    /// A grid with every cell occupied (nothing is skipped).
    pub fn full(resolution: u32) -> Self {
        let cells = (resolution as usize).pow(3);
        let mut words = vec![u32::MAX; cells.div_ceil(32)];
        if !cells.is_multiple_of(32) {
            *words.last_mut().unwrap() = (1u32 << (cells % 32)) - 1;
        }
        OccupancyGrid {
            resolution,
            density_threshold: 0.0,
            frames: 0,
            words,
        }
    }

    /// A grid with no cell occupied (everything may be skipped).
    pub fn empty(resolution: u32) -> Self {
        OccupancyGrid {
            resolution,
            density_threshold: 0.0,
            frames: 0,
            words: vec![0; (resolution as usize).pow(3).div_ceil(32)],
        }
    }

    pub fn cells(&self) -> u64 {
        (self.resolution as u64).pow(3)
    }

    pub fn occupied_cells(&self) -> u64 {
        self.words.iter().map(|w| w.count_ones() as u64).sum()
    }

    /// Fraction of occupied cells.
    pub fn occupied_fraction(&self) -> f64 {
        self.occupied_cells() as f64 / self.cells().max(1) as f64
    }

    #[inline]
    pub fn cell(&self, x: u32, y: u32, z: u32) -> bool {
        let r = self.resolution as usize;
        let i = x as usize + r * (y as usize + r * z as usize);
        (self.words[i >> 5] >> (i & 31)) & 1 == 1
    }

    /// Marks cell `i = x + R (y + R z)` occupied.
    #[inline]
    pub fn set(&mut self, i: usize) {
        self.words[i >> 5] |= 1 << (i & 31);
    }

    /// The index `x + R (y + R z)` of the cell holding unit-cube point `p` (clamped to the
    /// cube; a coordinate of exactly 1 belongs to the last cell).
    #[inline]
    pub fn cell_index_unit(&self, p: [f32; 3]) -> usize {
        let c = |v: f32| self.cell_along(v) as usize;
        let r = self.resolution as usize;
        c(p[0]) + r * (c(p[1]) + r * c(p[2]))
    }

    /// The cell along one axis that holds unit coordinate `v` (clamped to `[0, 1]`).
    #[inline]
    pub fn cell_along(&self, v: f32) -> u32 {
        let r = self.resolution;
        ((v.clamp(0.0, 1.0) * r as f32) as u32).min(r - 1)
    }

    /// This grid with every cell next to an occupied one (26 neighbours) occupied too.
    pub fn dilated(&self) -> OccupancyGrid {
        let r = self.resolution as usize;
        let mut out = OccupancyGrid {
            density_threshold: self.density_threshold,
            frames: self.frames,
            ..OccupancyGrid::empty(self.resolution)
        };
        let range = |c: usize| c.saturating_sub(1)..=(c + 1).min(r - 1);
        for z in 0..r {
            for y in 0..r {
                for x in 0..r {
                    if self.cell(x as u32, y as u32, z as u32) {
                        for nz in range(z) {
                            for ny in range(y) {
                                for nx in range(x) {
                                    out.set(nx + r * (ny + r * nz));
                                }
                            }
                        }
                    }
                }
            }
        }
        out
    }

    /// Keeps only the cells also occupied in `other` (of the same resolution).
    pub fn intersect(&mut self, other: &OccupancyGrid) {
        assert_eq!(
            self.resolution, other.resolution,
            "grids of different sizes"
        );
        for (a, b) in self.words.iter_mut().zip(&other.words) {
            *a &= b;
        }
    }

    /// Whether the cell holding unit-cube point `p` is occupied (`p` is clamped to the cube; a
    /// coordinate of exactly 1 belongs to the last cell).
    #[inline]
    pub fn occupied_unit(&self, p: [f32; 3]) -> bool {
        let i = self.cell_index_unit(p);
        (self.words[i >> 5] >> (i & 31)) & 1 == 1
    }

    /// The section payload (format.md §6.5).
    pub fn to_payload(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(OCCUPANCY_HEADER + 4 * self.words.len());
        out.extend_from_slice(&self.resolution.to_le_bytes());
        out.extend_from_slice(&self.density_threshold.to_le_bytes());
        out.extend_from_slice(&self.frames.to_le_bytes());
        out.extend_from_slice(&0u32.to_le_bytes());
        for w in &self.words {
            out.extend_from_slice(&w.to_le_bytes());
        }
        out
    }

    /// Payload bytes for a resolution.
    pub fn payload_len(resolution: u64) -> u64 {
        OCCUPANCY_HEADER as u64 + 4 * resolution.pow(3).div_ceil(32)
    }

    /// Reads a payload strictly: resolution in `1..=max_resolution`, threshold finite and
    /// `>= 0`, reserved 0, exactly the bytes the resolution needs, padding bits 0.
    pub fn from_payload(raw: &[u8], max_resolution: u64, what: &str) -> Result<Self, DecodeError> {
        if raw.len() < OCCUPANCY_HEADER {
            return Err(DecodeError::malformed(
                what,
                format!(
                    "{} bytes, the occupancy header needs {OCCUPANCY_HEADER}",
                    raw.len()
                ),
            ));
        }
        let u32_at = |o: usize| u32::from_le_bytes([raw[o], raw[o + 1], raw[o + 2], raw[o + 3]]);
        let resolution = u32_at(0);
        let density_threshold = f32::from_bits(u32_at(4));
        let frames = u32_at(8);
        if resolution == 0 {
            return Err(DecodeError::malformed(what, "occupancy resolution 0"));
        }
        if resolution as u64 > max_resolution {
            return Err(DecodeError::limit(
                format!("{what} resolution"),
                resolution as u64,
                max_resolution,
            ));
        }
        if !(density_threshold.is_finite() && density_threshold >= 0.0) {
            return Err(DecodeError::malformed(
                what,
                format!("density threshold {density_threshold} is not finite and >= 0"),
            ));
        }
        if u32_at(12) != 0 {
            return Err(DecodeError::malformed(what, "reserved field must be zero"));
        }
        let need = Self::payload_len(resolution as u64);
        if raw.len() as u64 != need {
            return Err(DecodeError::malformed(
                what,
                format!("{} bytes, resolution {resolution} needs {need}", raw.len()),
            ));
        }
        let words: Vec<u32> = raw[OCCUPANCY_HEADER..]
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let cells = (resolution as u64).pow(3);
        let tail = (cells % 32) as u32;
        if tail != 0 && words.last().is_some_and(|&w| w >> tail != 0) {
            return Err(DecodeError::malformed(
                what,
                "bits past the last cell must be zero",
            ));
        }
        Ok(OccupancyGrid {
            resolution,
            density_threshold,
            frames,
            words,
        })
    }
}

pub use msth_core::scene::{cell_world_size, density_threshold};

/// Vertices per work item.
const BATCH: usize = 4096;

/// The resolution from which [`compute`] first computes the grid at half the resolution and
/// evaluates only the vertices in its occupied cells.
pub const COARSE_TO_FINE_FROM: u32 = 128;

/// The most times [`compute`] evaluates: every frame of a model with at most this many, else this
/// many times evenly over `[0, 1]` (ends included). Bounds the export's cost for long videos
/// (10,000 frames would otherwise mean 10,000 passes over the grid).
pub const MAX_OCCUPANCY_TIMES: usize = 256;

/// The normalised times [`compute`] evaluates for a model of `frames` frames.
pub fn evaluation_times(frames: usize) -> Vec<f32> {
    let n = frames.clamp(1, MAX_OCCUPANCY_TIMES);
    (0..n).map(|k| crate::encode::frame_time(k, n)).collect()
}

/// The occupancy grid of a model: the main field's density at the `(R + 1)^3` grid vertices at
/// every frame time `f / (num_frames - 1)` (at most [`MAX_OCCUPANCY_TIMES`] times, evenly spread,
/// for longer models); a cell is occupied when one of its 8 corners reaches
/// `density_threshold(bounds, R, alpha)` at some frame; the occupied set is then dilated by one
/// cell (26 neighbours) so that density peaking between vertices, and the quantisation of the
/// shipped tables, lose nothing visible. A vertex found occupied is not evaluated again.
///
/// From [`COARSE_TO_FINE_FROM`] cells per side on (an even `R`), the grid at half the
/// resolution is computed first, and only the vertices in its occupied cells are evaluated: the
/// others count as empty. Its one-cell dilation, two cells of this grid, is the margin for
/// density between its vertices, as it is for a grid of that resolution on its own. A scene that
/// leaves most of space empty then costs about what the coarser grid costs (an object scene's
/// export at 128^3 took 4.2-4.6 s, against 21.6 s evaluating every vertex, on 2 cores).
pub fn compute(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    resolution: u32,
    alpha: f32,
) -> OccupancyGrid {
    let r = resolution.max(1) as usize;
    let threshold = density_threshold(&cfg.bounds, resolution.max(1), alpha);
    let v = r + 1;
    let nv = v * v * v;
    // Per vertex: EVALUATE until found at or above the threshold (HIT); SKIPPED where the
    // coarser grid leaves it empty. One byte per vertex, written in place batch by batch.
    const EVALUATE: u8 = 0;
    const HIT: u8 = 1;
    const SKIPPED: u8 = 2;
    let mut state = vec![EVALUATE; nv];
    if resolution >= COARSE_TO_FINE_FROM && r.is_multiple_of(2) {
        let coarse = compute(cfg, layout, params, resolution / 2, alpha);
        let rc = r / 2;
        let c = |a: usize| (a / 2).min(rc - 1) as u32;
        state.par_iter_mut().enumerate().for_each(|(i, s)| {
            if !coarse.cell(c(i % v), c((i / v) % v), c(i / (v * v))) {
                *s = SKIPPED;
            }
        });
    }
    let frames = cfg.num_frames.max(1);
    let times = evaluation_times(frames);
    for &t in &times {
        if !state.par_iter().any(|&s| s == EVALUATE) {
            break;
        }
        state.par_chunks_mut(BATCH).enumerate().for_each_init(
            || (FieldScratch::default(), Vec::new(), Vec::new()),
            |(scratch, pts, ids), (b, chunk)| {
                scratch.enc.static_cutoff = RENDER_STATIC_CUTOFF;
                pts.clear();
                ids.clear();
                for (k, s) in chunk.iter().enumerate() {
                    if *s != EVALUATE {
                        continue;
                    }
                    let i = b * BATCH + k;
                    let (x, y, z) = (i % v, (i / v) % v, i / (v * v));
                    ids.push(k);
                    pts.extend_from_slice(&[
                        x as f32 / r as f32,
                        y as f32 / r as f32,
                        z as f32 / r as f32,
                        t,
                    ]);
                }
                if ids.is_empty() {
                    return;
                }
                layout
                    .field
                    .forward_density(params, pts, ids.len(), scratch);
                for (&k, &sigma) in ids.iter().zip(&scratch.sigma) {
                    if sigma >= threshold || !sigma.is_finite() {
                        chunk[k] = HIT;
                    }
                }
            },
        );
    }
    let vertex_hit = |i: usize| state[i] == HIT;
    // A cell is occupied when any of its corners is; dilate by one cell: a cell is kept when a
    // vertex of it or of a neighbour is hit, i.e. when any vertex within one cell of its box is.
    let mut grid = OccupancyGrid {
        resolution: r as u32,
        density_threshold: threshold,
        frames: times.len() as u32,
        words: vec![0; (r * r * r).div_ceil(32)],
    };
    // Cell c spans vertices c..=c+1 per axis; dilated: c-1..=c+2.
    for z in 0..r {
        for y in 0..r {
            for x in 0..r {
                let range = |c: usize| c.saturating_sub(1)..=(c + 2).min(r);
                let hit = range(z).any(|vz| {
                    range(y).any(|vy| range(x).any(|vx| vertex_hit(vx + v * (vy + v * vz))))
                });
                if hit {
                    grid.set(x + r * (y + r * z));
                }
            }
        }
    }
    grid
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dilation_intersection_and_cell_of_a_point() {
        let r = 5u32;
        let mut g = OccupancyGrid::empty(r);
        // A corner cell and an inner one.
        g.set(g.cell_index_unit([0.0, 0.0, 0.0]));
        g.set(g.cell_index_unit([0.5, 0.5, 0.5]));
        assert!(g.cell(0, 0, 0) && g.cell(2, 2, 2));
        assert_eq!(g.cell_index_unit([1.0, 1.0, 1.0]), 124);
        assert_eq!(g.cell_index_unit([-1.0, 0.99, 0.0]), 4 * 5);
        let d = g.dilated();
        // 2^3 around the corner, 3^3 around (2, 2, 2), sharing (1, 1, 1).
        assert_eq!(d.occupied_cells(), 8 + 27 - 1);
        for (x, y, z) in [(0, 0, 0), (1, 1, 1), (3, 3, 3), (3, 1, 2)] {
            assert!(d.cell(x, y, z), "({x}, {y}, {z})");
        }
        for (x, y, z) in [(4, 4, 4), (2, 0, 0), (0, 0, 2)] {
            assert!(!d.cell(x, y, z), "({x}, {y}, {z})");
        }
        let mut full = OccupancyGrid::full(r);
        full.intersect(&d);
        assert_eq!(full, d);
        let mut empty = d.clone();
        empty.intersect(&OccupancyGrid::empty(r));
        assert_eq!(empty.occupied_cells(), 0);
    }

    #[test]
    fn payload_round_trips_and_rejects_bad_bits() {
        let mut g = OccupancyGrid::full(3);
        g.words[0] &= !(1 << 5);
        let p = g.to_payload();
        assert_eq!(p.len() as u64, OccupancyGrid::payload_len(3));
        let back = OccupancyGrid::from_payload(&p, 512, "occupancy").unwrap();
        assert_eq!(back, g);
        assert!(!back.cell(2, 1, 0));
        assert!(back.cell(1, 1, 0));
        assert_eq!(back.occupied_cells(), 26);
        // A padding bit past cell 27.
        let mut bad = p.clone();
        let last = bad.len() - 1;
        bad[last] |= 0x80;
        assert!(OccupancyGrid::from_payload(&bad, 512, "occupancy").is_err());
        // Over the limit, zero, short, long, reserved, threshold.
        assert!(OccupancyGrid::from_payload(&p, 2, "occupancy").is_err());
        let mut zero = p.clone();
        zero[0..4].copy_from_slice(&0u32.to_le_bytes());
        assert!(OccupancyGrid::from_payload(&zero, 512, "occupancy").is_err());
        assert!(OccupancyGrid::from_payload(&p[..p.len() - 4], 512, "o").is_err());
        let mut long = p.clone();
        long.extend_from_slice(&[0; 4]);
        assert!(OccupancyGrid::from_payload(&long, 512, "o").is_err());
        let mut res = p.clone();
        res[12] = 1;
        assert!(OccupancyGrid::from_payload(&res, 512, "o").is_err());
        let mut nan = p;
        nan[4..8].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(OccupancyGrid::from_payload(&nan, 512, "o").is_err());
    }

    #[test]
    fn unit_points_map_to_their_cells() {
        let mut g = OccupancyGrid::full(4);
        g.words.iter_mut().for_each(|w| *w = 0);
        g.set(3 + 4 * 4 * 2);
        assert!(g.occupied_unit([0.99, 0.1, 0.6]));
        assert!(g.occupied_unit([1.0, 0.0, 0.5]));
        assert!(!g.occupied_unit([0.74, 0.1, 0.6]));
        assert!(!g.occupied_unit([0.99, 0.26, 0.6]));
    }
}
