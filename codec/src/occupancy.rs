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

use msth_core::config::ModelConfig;
use msth_core::field::{FieldScratch, ModelLayout};
use msth_core::pipeline::{
    weighted_samples, TimedRay, WeightedSample, Workspace, RENDER_STATIC_CUTOFF,
};
use msth_core::scene::SceneBounds;
use msth_core::Camera;
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

    fn set(&mut self, i: usize) {
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
    fn cell_along(&self, v: f32) -> u32 {
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

/// The rendering weight a main sample must carry for [`seen_cells`] to count its cell as seen.
pub const DEFAULT_SEEN_WEIGHT: f32 = 1e-3;
/// The most rays [`seen_cells`] casts (pixels are strided evenly to stay below it).
pub const SEEN_RAY_BUDGET: u64 = 1 << 19;

/// What [`seen_cells`] cast.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SeenReport {
    pub cameras: usize,
    pub times: usize,
    /// Every `stride`-th pixel per side, at its centre.
    pub stride: u32,
    pub rays: u64,
    /// Cells seen before the dilation.
    pub seen_cells: u64,
    /// Cells wholly in view of one of the cameras; the others are kept whatever was seen.
    pub covered_cells: u64,
    /// Weighted samples one of whose footprint's cubes spanned more than
    /// [`MAX_FOOTPRINT_CELLS`] cells per side and was marked only that far around its middle
    /// (0 unless the grid is far finer than the cast rays).
    pub clipped_footprints: u64,
}

/// The most cells per side one cube of a weighted sample's footprint marks ([`seen_cells`]),
/// which bounds the work per cube.
pub const MAX_FOOTPRINT_CELLS: u32 = 9;

/// The most cubes a weighted sample's footprint is made of: an interval longer than this many
/// half cells is cut into this many pieces, each then longer than half a cell.
pub const MAX_FOOTPRINT_PIECES: u32 = 64;

/// Marks the cells of `grid` that the weighted sample `s` of `ray` stands for ([`seen_cells`]):
/// its own cell, and its interval along the ray, thickened by the distance `spread t` to the
/// neighbouring cast rays at distance `t` (world units). The interval is cut into pieces of
/// about half a cell or less (at most [`MAX_FOOTPRINT_PIECES`]), and each piece marks an
/// axis-aligned cube around its middle whose side is the larger of its length and `spread t`,
/// mapped to the grid's coordinates corner by corner and cut to [`MAX_FOOTPRINT_CELLS`] per
/// side around the cell of its middle. Returns whether a cube was cut.
fn mark_footprint(
    grid: &mut OccupancyGrid,
    bounds: &SceneBounds,
    ray: &TimedRay,
    s: WeightedSample,
    spread: f32,
) -> bool {
    let own = grid.cell_index_unit(s.unit);
    grid.set(own);
    let [t0, t1] = s.t;
    let at = |t: f32| ray.origin + ray.dir * t;
    if !(t0.is_finite() && t1.is_finite() && spread.is_finite() && at(t0).is_finite()) {
        return false;
    }
    let r = grid.resolution as f32;
    let len = (t1 - t0).max(0.0);
    let (u0, u1) = (bounds.to_unit(at(t0)), bounds.to_unit(at(t1)));
    let cells_along = (u1 - u0).abs().max_element() * r;
    let pieces = (2.0 * cells_along)
        .ceil()
        .clamp(1.0, MAX_FOOTPRINT_PIECES as f32) as u32;
    let mut cut = false;
    for j in 0..pieces {
        let a = t0 + len * j as f32 / pieces as f32;
        let b = t0 + len * (j + 1) as f32 / pieces as f32;
        let t = 0.5 * (a + b);
        cut |= mark_cube(grid, bounds, at(t), 0.5 * (b - a).max(spread * t));
    }
    cut
}

/// Marks the cells of `grid` that an axis-aligned cube of half side `half` around the world
/// point `centre` covers, mapped to the grid's coordinates corner by corner and cut to
/// [`MAX_FOOTPRINT_CELLS`] per side around the cell of `centre`. Returns whether it was cut.
fn mark_cube(
    grid: &mut OccupancyGrid,
    bounds: &SceneBounds,
    centre: glam::Vec3,
    half: f32,
) -> bool {
    let mid = bounds.to_unit(centre);
    let mut lo = mid;
    let mut hi = mid;
    for k in 0..8 {
        let sign = |bit: usize| if k & bit == 0 { -half } else { half };
        let u = bounds.to_unit(centre + glam::Vec3::new(sign(1), sign(2), sign(4)));
        lo = lo.min(u);
        hi = hi.max(u);
    }
    let reach = MAX_FOOTPRINT_CELLS / 2;
    let mut cut = false;
    let mut span = |lo: f32, hi: f32, mid: f32| {
        let (a, b, m) = (
            grid.cell_along(lo),
            grid.cell_along(hi),
            grid.cell_along(mid),
        );
        cut |= a + reach < m || b > m + reach;
        (a.max(m.saturating_sub(reach)), b.min(m + reach))
    };
    let (xa, xb) = span(lo.x, hi.x, mid.x);
    let (ya, yb) = span(lo.y, hi.y, mid.y);
    let (za, zb) = span(lo.z, hi.z, mid.z);
    let ru = grid.resolution as usize;
    for z in za..=zb {
        for y in ya..=yb {
            for x in xa..=xb {
                grid.set(x as usize + ru * (y as usize + ru * z as usize));
            }
        }
    }
    cut
}

/// What the cameras leave worth drawing: the cells of an `R^3` grid over the unit cube that a
/// main sample of weight `>= min_weight` stands for, on a ray of one of `cameras` at one of the
/// model's frame times ([`evaluation_times`]), sampled as the renderers sample (`pipeline::
/// weighted_samples`), through every `stride`-th pixel per side (the stride chosen so that at
/// most [`SEEN_RAY_BUDGET`] rays are cast), dilated by one cell (26 neighbours); and every cell
/// not wholly in view of one of the cameras (all 8 corners in front of it and inside its image),
/// about which they say nothing.
///
/// A sample stands for more than its own cell ([`mark_footprint`]): for its interval along the
/// ray (the renderer gives the whole interval the density of its midpoint) and for the space
/// between its ray and the neighbouring cast rays, `stride` pixels away. On a grid finer than
/// the cast rays, marking only the cells of the midpoints left holes that a view from elsewhere
/// saw as missing haze or surface (at 128^3: 29 dB against the unskipped frame on an orbit of
/// the demo model, against 41 dB with footprints; docs/playback.md, "The occupancy grid").
///
/// `msth export` keeps the cells of the density grid ([`compute`]) that are also in this grid:
/// density the training cameras look through or never reach past a surface, such as haze
/// between the cameras and the surfaces (weights too small to count) or what lies behind a
/// wall, is skipped; space outside their views keeps what the density test found, so a wider
/// view still shows the model's extrapolation there.
pub fn seen_cells(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    cameras: &[Camera],
    resolution: u32,
    min_weight: f32,
) -> (OccupancyGrid, SeenReport) {
    let r = resolution.max(1);
    let times = evaluation_times(cfg.num_frames.max(1));
    let pixels: u64 = cameras
        .iter()
        .map(|c| c.width as u64 * c.height as u64)
        .sum::<u64>()
        * times.len() as u64;
    let mut stride = 1u32;
    while pixels.div_ceil(stride as u64 * stride as u64) > SEEN_RAY_BUDGET {
        stride += 1;
    }
    let jobs: Vec<(usize, f32)> = (0..cameras.len())
        .flat_map(|c| times.iter().map(move |&t| (c, t)))
        .collect();
    let cells = (r as usize).pow(3);
    let blank = || OccupancyGrid {
        frames: times.len() as u32,
        ..OccupancyGrid::empty(r)
    };
    let (seen, rays, clipped) = jobs
        .par_iter()
        .fold(
            || (blank(), 0u64, 0u64, Workspace::default(), Vec::new()),
            |(mut grid, mut count, mut clipped, mut ws, mut rays), &(c, t)| {
                let cam = &cameras[c];
                let time = msth_core::pipeline::sample_time(t);
                let mut y = stride / 2;
                while y < cam.height {
                    rays.clear();
                    let mut x = stride / 2;
                    while x < cam.width {
                        let ray = cam.ray_at(x as f32 + 0.5, y as f32 + 0.5);
                        rays.push(TimedRay {
                            origin: ray.origin,
                            dir: ray.dir,
                            time,
                        });
                        x += stride;
                    }
                    count += rays.len() as u64;
                    // Neighbouring cast rays lie `stride` pixels apart: at distance `t` that
                    // is `stride t / f` world units, which a sample's footprint must span so
                    // that a surface between two cast rays is not left unseen.
                    let spread = stride as f32 / cam.fx.min(cam.fy).max(f32::MIN_POSITIVE);
                    weighted_samples(cfg, layout, params, &rays, min_weight, &mut ws, |s| {
                        clipped +=
                            mark_footprint(&mut grid, &cfg.bounds, &rays[s.ray], s, spread) as u64;
                    });
                    y += stride;
                }
                (grid, count, clipped, ws, rays)
            },
        )
        .map(|(g, n, k, _, _)| (g, n, k))
        .reduce(
            || (blank(), 0, 0),
            |(mut a, na, ka), (b, nb, kb)| {
                for (wa, wb) in a.words.iter_mut().zip(&b.words) {
                    *wa |= wb;
                }
                (a, na + nb, ka + kb)
            },
        );
    let mut keep = seen.dilated();
    let covered = covered_cells(&cfg.bounds, cameras, r);
    for (k, c) in keep.words.iter_mut().zip(&covered.words) {
        *k |= !c;
    }
    let tail = cells % 32;
    if tail != 0 {
        *keep.words.last_mut().unwrap() &= (1u32 << tail) - 1;
    }
    let report = SeenReport {
        cameras: cameras.len(),
        times: times.len(),
        stride,
        rays,
        seen_cells: seen.occupied_cells(),
        covered_cells: covered.occupied_cells(),
        clipped_footprints: clipped,
    };
    (keep, report)
}

/// The cells of an `R^3` grid that lie wholly in the view of one of `cameras`: all 8 corners
/// (in world space, [`SceneBounds::from_unit`]) in front of it and inside its image.
fn covered_cells(bounds: &SceneBounds, cameras: &[Camera], resolution: u32) -> OccupancyGrid {
    let r = resolution as usize;
    let v = r + 1;
    // Per vertex, one bit per camera: the first 64 (a cell only later ones see stays
    // uncovered, so it is kept: the safe side).
    let views: Vec<(glam::Mat4, &Camera)> = cameras
        .iter()
        .take(64)
        .map(|c| (c.world_from_camera.inverse(), c))
        .collect();
    let inside: Vec<u64> = (0..v * v * v)
        .into_par_iter()
        .map(|i| {
            let u = glam::Vec3::new(
                (i % v) as f32 / r as f32,
                ((i / v) % v) as f32 / r as f32,
                (i / (v * v)) as f32 / r as f32,
            );
            let w = bounds.from_unit(u);
            let mut bits = 0u64;
            for (k, (camera_from_world, c)) in views.iter().enumerate() {
                if let Some((x, y)) = c.project_camera_point(camera_from_world.transform_point3(w))
                {
                    if (0.0..=c.width as f32).contains(&x) && (0.0..=c.height as f32).contains(&y) {
                        bits |= 1 << k;
                    }
                }
            }
            bits
        })
        .collect();
    let mut grid = OccupancyGrid::empty(resolution);
    for z in 0..r {
        for y in 0..r {
            for x in 0..r {
                let mut all = u64::MAX;
                for (dx, dy, dz) in (0..8).map(|c| (c & 1, (c >> 1) & 1, c >> 2)) {
                    all &= inside[(x + dx) + v * ((y + dy) + v * (z + dz))];
                }
                if all != 0 {
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
    fn a_weighted_sample_marks_its_interval_and_the_gap_to_the_next_ray() {
        use glam::Vec3;
        // World = unit cube: a ray along +x at y = z = 0.53, a sample over x in [0.2, 0.6].
        let bounds = SceneBounds::Box {
            min: Vec3::ZERO,
            max: Vec3::ONE,
        };
        let ray = TimedRay {
            origin: Vec3::new(-1.0, 0.53, 0.53),
            dir: Vec3::X,
            time: 0.0,
        };
        let sample = |t0: f32, t1: f32| WeightedSample {
            ray: 0,
            unit: [(t0 + t1) / 2.0 - 1.0, 0.53, 0.53],
            t: [t0, t1],
            weight: 0.5,
        };
        let marked = |g: &OccupancyGrid| {
            let r = g.resolution;
            let mut box_ = [[r, 0]; 3];
            for z in 0..r {
                for y in 0..r {
                    for x in 0..r {
                        if g.cell(x, y, z) {
                            for (a, v) in [x, y, z].into_iter().enumerate() {
                                box_[a] = [box_[a][0].min(v), box_[a][1].max(v)];
                            }
                        }
                    }
                }
            }
            (g.occupied_cells(), box_)
        };
        // The interval, x from 0.2 to 0.6 at 16 cells per side: cells 3..=9 along the ray, in
        // 13 pieces of 0.03 (under half a cell), so only the ray's own row across.
        let mark = |g: &mut OccupancyGrid, t0, t1, spread| {
            mark_footprint(g, &bounds, &ray, sample(t0, t1), spread)
        };
        let mut g = OccupancyGrid::empty(16);
        assert!(!mark(&mut g, 1.2, 1.6, 0.0));
        assert_eq!(marked(&g), (7, [[3, 9], [8, 8], [8, 8]]));
        // A short interval: its own cell only; with the neighbouring ray 0.1 away at t = 1.4
        // (spread 0.1 / 1.4), 0.05 on either side: cells 5..=7 along x, 7..=9 across.
        let mut g = OccupancyGrid::empty(16);
        mark(&mut g, 1.39, 1.41, 0.0);
        assert_eq!(marked(&g), (1, [[6, 6], [8, 8], [8, 8]]));
        let mut g = OccupancyGrid::empty(16);
        mark(&mut g, 1.39, 1.41, 0.1 / 1.4);
        assert_eq!(marked(&g), (27, [[5, 7], [7, 9], [7, 9]]));
        // An interval across the whole grid of 128 cells: at most MAX_FOOTPRINT_PIECES pieces,
        // two cells long each, and still every cell along the ray (row 67 across).
        let mut g = OccupancyGrid::empty(128);
        assert!(!mark(&mut g, 1.0, 2.0, 0.0));
        assert!((0..128).all(|x| g.cell(x, 67, 67)));
        assert_eq!(marked(&g), (128 * 3 * 3, [[0, 127], [66, 68], [66, 68]]));
        // A gap wider than MAX_FOOTPRINT_CELLS (here the whole grid) is cut around each
        // piece's cell and reported: 9 cells across, about the ray's 2 cells along it.
        let mut g = OccupancyGrid::empty(64);
        assert!(mark(&mut g, 1.39, 1.41, 1.0));
        let n = MAX_FOOTPRINT_CELLS as u64;
        let (count, box_) = marked(&g);
        assert!((n * n * n..=3 * n * n * n).contains(&count), "{count}");
        assert_eq!(box_[1], [33 - 4, 33 + 4]);
        // Not finite: the sample's own cell only, nothing else.
        let mut g = OccupancyGrid::empty(16);
        mark(&mut g, f32::NAN, 1.4, 0.0);
        mark(&mut g, 1.3, f32::INFINITY, 0.0);
        assert_eq!(g.occupied_cells(), 2);
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
