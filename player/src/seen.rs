//! What the training cameras see, for the occupancy grid `msth export` writes: rays cast through
//! a stride of their pixels at the model's frame times, each weighted sample marking the cells it
//! stands for ([`seen_cells`]). The grid itself and the density test it refines are the codec's
//! ([`msth_codec::occupancy`]); casting rays is rendering, so it lives here with the renderers.

use msth_codec::occupancy::{evaluation_times, OccupancyGrid};
use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::pipeline::{weighted_samples, TimedRay, WeightedSample, Workspace};
use msth_core::scene::SceneBounds;
use msth_core::Camera;
use rayon::prelude::*;

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
/// `msth export` keeps the cells of the density grid ([`msth_codec::occupancy::compute`]) that are also in this grid:
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
}
