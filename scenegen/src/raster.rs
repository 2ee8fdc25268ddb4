//! Triangle rasterisation into a visibility buffer: which triangle is nearest at each sample,
//! with its perspective-correct barycentric coordinates and depth.
//!
//! Pipeline per triangle ([`setup`]): world -> camera space (OpenGL axes, the camera looks down
//! -Z, `msth_core::Camera`), clipping against the near plane and a guard band around the image
//! (Sutherland-Hodgman in camera space, each intersection computed from the inside vertex to
//! the outside one so that triangles sharing an edge get bitwise identical points), projection
//! to pixels, snapping to [`SUBPIXEL`] fixed point, back-face culling (glTF: counter-clockwise
//! = front), then coverage by exact integer edge functions with the top-left fill rule, so
//! that a closed mesh covers every sample exactly once.
//!
//! Two implementations produce the same buffer bit for bit: [`rasterize_reference`] (every
//! sample against every triangle, the plain definition) and [`rasterize`] (bounding boxes and
//! incremental edge functions, the one used for datasets). Samples lie at `(i + 0.5, j + 0.5)`
//! of the camera's pixel grid; supersampling is done by the caller, one
//! rasterisation per sub-pixel offset with the principal point shifted (`scene::render`).

use glam::{Mat4, Vec3};
use msth_core::Camera;

/// Fixed-point resolution of snapped screen coordinates (sub-pixel steps per pixel).
pub const SUBPIXEL: i64 = 256;
/// Guard band around the image, in pixels, that geometry is clipped to.
pub const GUARD_BAND: f32 = 64.0;
/// Sentinel triangle index of an empty sample.
pub const EMPTY: u32 = u32::MAX;

/// A triangle to rasterise: world positions and whether back faces are culled.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterTriangle {
    pub positions: [Vec3; 3],
    pub cull_back: bool,
}

/// The nearest surface at one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fragment {
    /// Index into the triangle list, or [`EMPTY`].
    pub tri: u32,
    /// Distance along the viewing axis (`-z` in camera space); `f32::INFINITY` when empty.
    pub depth: f32,
    /// Perspective-correct barycentric coordinates with respect to the triangle's vertices.
    pub bary: Vec3,
    /// The triangle is seen from its back side.
    pub back_facing: bool,
}

impl Fragment {
    pub const NONE: Fragment = Fragment {
        tri: EMPTY,
        depth: f32::INFINITY,
        bary: Vec3::ZERO,
        back_facing: false,
    };
}

/// A clipped vertex: camera-space position and barycentric coordinates in the source triangle.
#[derive(Clone, Copy, Debug)]
struct ClipVertex {
    p: Vec3,
    bary: Vec3,
}

/// A screen-space triangle ready for coverage tests, oriented so that its area is positive.
#[derive(Clone, Copy, Debug)]
struct ScreenTriangle {
    tri: u32,
    /// Snapped positions (fixed point, [`SUBPIXEL`] per pixel).
    x: [i64; 3],
    y: [i64; 3],
    /// `1 / depth` per vertex.
    inv_w: [f32; 3],
    /// Source-triangle barycentrics per vertex, pre-divided by depth.
    bary_over_w: [Vec3; 3],
    area: i64,
    /// Per edge (opposite vertex 0, 1, 2): 0 for top-left edges, -1 otherwise.
    bias: [i64; 3],
    back_facing: bool,
}

/// Plane `n . p + d >= 0` in camera space.
#[derive(Clone, Copy, Debug)]
struct Plane {
    n: Vec3,
    d: f32,
}

impl Plane {
    fn dist(&self, p: Vec3) -> f32 {
        self.n.dot(p) + self.d
    }
}

/// The clipping planes of `camera`: near plane and the guard band.
fn clip_planes(camera: &Camera, near: f32) -> [Plane; 5] {
    let (w, h) = (camera.width as f32, camera.height as f32);
    let g = GUARD_BAND;
    let (fx, fy, cx, cy) = (camera.fx, camera.fy, camera.cx, camera.cy);
    // depth = -z; u = cx + fx x / depth, v = cy - fy y / depth.
    [
        Plane {
            n: Vec3::new(0.0, 0.0, -1.0),
            d: -near,
        },
        // u >= -g
        Plane {
            n: Vec3::new(fx, 0.0, -(cx + g)),
            d: 0.0,
        },
        // u <= w + g
        Plane {
            n: Vec3::new(-fx, 0.0, -(w + g - cx)),
            d: 0.0,
        },
        // v >= -g
        Plane {
            n: Vec3::new(0.0, -fy, -(cy + g)),
            d: 0.0,
        },
        // v <= h + g
        Plane {
            n: Vec3::new(0.0, fy, -(h + g - cy)),
            d: 0.0,
        },
    ]
}

/// Clips a convex polygon against one plane (Sutherland-Hodgman).
fn clip_polygon(poly: &[ClipVertex], plane: Plane, out: &mut Vec<ClipVertex>) {
    out.clear();
    for i in 0..poly.len() {
        let a = poly[i];
        let b = poly[(i + 1) % poly.len()];
        let (da, db) = (plane.dist(a.p), plane.dist(b.p));
        let (ina, inb) = (da >= 0.0, db >= 0.0);
        if ina {
            out.push(a);
        }
        if ina != inb {
            // From the inside vertex to the outside one, for bitwise-identical shared points.
            let (inside, outside, di, dout) = if ina { (a, b, da, db) } else { (b, a, db, da) };
            let t = di / (di - dout);
            out.push(ClipVertex {
                p: inside.p + (outside.p - inside.p) * t,
                bary: inside.bary + (outside.bary - inside.bary) * t,
            });
        }
    }
}

fn edge(ax: i64, ay: i64, bx: i64, by: i64, px: i64, py: i64) -> i64 {
    (bx - ax) * (py - ay) - (by - ay) * (px - ax)
}

/// Top-left rule for an edge `a -> b` of a positive-area triangle (y grows downwards): a top
/// edge is horizontal going right, a left edge goes up.
fn is_top_left(ax: i64, ay: i64, bx: i64, by: i64) -> bool {
    let (dx, dy) = (bx - ax, by - ay);
    (dy == 0 && dx > 0) || dy < 0
}

/// Clips, projects, snaps and orients one triangle; appends 0..=5 screen triangles to `out`
/// (0 when culled, degenerate or outside the view).
fn setup(
    camera: &Camera,
    camera_from_world: &Mat4,
    planes: &[Plane; 5],
    index: u32,
    tri: &RasterTriangle,
    out: &mut Vec<ScreenTriangle>,
) {
    let mut poly: Vec<ClipVertex> = (0..3)
        .map(|k| ClipVertex {
            p: camera_from_world.transform_point3(tri.positions[k]),
            bary: Vec3::AXES[k],
        })
        .collect();
    if !poly.iter().all(|v| v.p.is_finite()) {
        return;
    }
    let mut scratch = Vec::with_capacity(8);
    for plane in planes {
        if poly.iter().all(|v| plane.dist(v.p) >= 0.0) {
            continue;
        }
        clip_polygon(&poly, *plane, &mut scratch);
        std::mem::swap(&mut poly, &mut scratch);
        if poly.len() < 3 {
            return;
        }
    }
    let screen: Vec<(i64, i64, f32, Vec3)> = poly
        .iter()
        .map(|v| {
            let depth = -v.p.z;
            let u = camera.cx + camera.fx * v.p.x / depth;
            let w = camera.cy - camera.fy * v.p.y / depth;
            (
                (u * SUBPIXEL as f32).round() as i64,
                (w * SUBPIXEL as f32).round() as i64,
                1.0 / depth,
                v.bary / depth,
            )
        })
        .collect();
    for k in 1..screen.len() - 1 {
        let mut v = [screen[0], screen[k], screen[k + 1]];
        let area = edge(v[0].0, v[0].1, v[1].0, v[1].1, v[2].0, v[2].1);
        if area == 0 {
            continue;
        }
        // Counter-clockwise as seen by the camera (front) has negative area with y down.
        let back_facing = area > 0;
        if back_facing && tri.cull_back {
            continue;
        }
        if area < 0 {
            v.swap(1, 2);
        }
        let x = [v[0].0, v[1].0, v[2].0];
        let y = [v[0].1, v[1].1, v[2].1];
        let bias = [
            if is_top_left(x[1], y[1], x[2], y[2]) {
                0
            } else {
                -1
            },
            if is_top_left(x[2], y[2], x[0], y[0]) {
                0
            } else {
                -1
            },
            if is_top_left(x[0], y[0], x[1], y[1]) {
                0
            } else {
                -1
            },
        ];
        out.push(ScreenTriangle {
            tri: index,
            x,
            y,
            inv_w: [v[0].2, v[1].2, v[2].2],
            bary_over_w: [v[0].3, v[1].3, v[2].3],
            area: area.abs(),
            bias,
            back_facing,
        });
    }
}

impl ScreenTriangle {
    /// Edge values at fixed-point point `(px, py)`: the weights of vertices 0, 1, 2.
    #[inline]
    fn weights(&self, px: i64, py: i64) -> [i64; 3] {
        let (x, y) = (&self.x, &self.y);
        [
            edge(x[1], y[1], x[2], y[2], px, py),
            edge(x[2], y[2], x[0], y[0], px, py),
            edge(x[0], y[0], x[1], y[1], px, py),
        ]
    }

    #[inline]
    fn covers(&self, w: [i64; 3]) -> bool {
        w[0] + self.bias[0] >= 0 && w[1] + self.bias[1] >= 0 && w[2] + self.bias[2] >= 0
    }

    /// The fragment for edge weights `w` (perspective-correct).
    #[inline]
    fn fragment(&self, w: [i64; 3]) -> Fragment {
        let inv_area = 1.0 / self.area as f32;
        let l = [
            w[0] as f32 * inv_area,
            w[1] as f32 * inv_area,
            w[2] as f32 * inv_area,
        ];
        let inv_depth = l[0] * self.inv_w[0] + l[1] * self.inv_w[1] + l[2] * self.inv_w[2];
        let depth = 1.0 / inv_depth;
        let bary =
            (self.bary_over_w[0] * l[0] + self.bary_over_w[1] * l[1] + self.bary_over_w[2] * l[2])
                * depth;
        Fragment {
            tri: self.tri,
            depth,
            bary,
            back_facing: self.back_facing,
        }
    }
}

/// Clip-space setup for every triangle, in order.
fn setup_all(camera: &Camera, triangles: &[RasterTriangle], near: f32) -> Vec<ScreenTriangle> {
    let camera_from_world = camera.world_from_camera.inverse();
    let planes = clip_planes(camera, near);
    let mut out = Vec::with_capacity(triangles.len());
    for (i, t) in triangles.iter().enumerate() {
        setup(camera, &camera_from_world, &planes, i as u32, t, &mut out);
    }
    out
}

/// The fixed-point centre of sample `i` along one axis.
#[inline]
fn sample_centre(i: u32) -> i64 {
    i as i64 * SUBPIXEL + SUBPIXEL / 2
}

/// Plain reference: every sample tested against every screen triangle in order; the nearest
/// wins, ties go to the earlier triangle.
pub fn rasterize_reference(
    camera: &Camera,
    triangles: &[RasterTriangle],
    near: f32,
) -> Vec<Fragment> {
    let screen = setup_all(camera, triangles, near);
    let (w, h) = (camera.width, camera.height);
    let mut buf = vec![Fragment::NONE; w as usize * h as usize];
    for j in 0..h {
        for i in 0..w {
            let (px, py) = (sample_centre(i), sample_centre(j));
            let best = &mut buf[(j * w + i) as usize];
            for t in &screen {
                let wts = t.weights(px, py);
                if t.covers(wts) {
                    let f = t.fragment(wts);
                    if f.depth < best.depth {
                        *best = f;
                    }
                }
            }
        }
    }
    buf
}

/// Fast path: each screen triangle visits the samples of its bounding box, stepping its edge
/// functions incrementally. Produces exactly the buffer of [`rasterize_reference`].
pub fn rasterize(camera: &Camera, triangles: &[RasterTriangle], near: f32) -> Vec<Fragment> {
    let screen = setup_all(camera, triangles, near);
    let (w, h) = (camera.width as i64, camera.height as i64);
    let mut buf = vec![Fragment::NONE; (w * h) as usize];
    for t in &screen {
        let min_x = t.x.iter().copied().min().unwrap_or(0);
        let max_x = t.x.iter().copied().max().unwrap_or(0);
        let min_y = t.y.iter().copied().min().unwrap_or(0);
        let max_y = t.y.iter().copied().max().unwrap_or(0);
        // Samples whose centre can lie inside the box.
        let i0 = (min_x - SUBPIXEL / 2).div_euclid(SUBPIXEL).max(0);
        let i1 = (max_x - SUBPIXEL / 2).div_euclid(SUBPIXEL).min(w - 1);
        let j0 = (min_y - SUBPIXEL / 2).div_euclid(SUBPIXEL).max(0);
        let j1 = (max_y - SUBPIXEL / 2).div_euclid(SUBPIXEL).min(h - 1);
        if i0 > i1 || j0 > j1 {
            continue;
        }
        // d(weight)/d(sample step) per edge.
        let (x, y) = (&t.x, &t.y);
        let step_x = [
            -(y[2] - y[1]) * SUBPIXEL,
            -(y[0] - y[2]) * SUBPIXEL,
            -(y[1] - y[0]) * SUBPIXEL,
        ];
        let step_y = [
            (x[2] - x[1]) * SUBPIXEL,
            (x[0] - x[2]) * SUBPIXEL,
            (x[1] - x[0]) * SUBPIXEL,
        ];
        let mut row = t.weights(sample_centre(i0 as u32), sample_centre(j0 as u32));
        for j in j0..=j1 {
            let mut wts = row;
            let base = (j * w) as usize;
            for i in i0..=i1 {
                if t.covers(wts) {
                    let f = t.fragment(wts);
                    let best = &mut buf[base + i as usize];
                    if f.depth < best.depth {
                        *best = f;
                    }
                }
                for k in 0..3 {
                    wts[k] += step_x[k];
                }
            }
            for k in 0..3 {
                row[k] += step_y[k];
            }
        }
    }
    buf
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(w: u32, h: u32) -> Camera {
        Camera::look_at(w, h, 0.9, Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, Vec3::Z)
    }

    /// Deterministic pseudo-random floats in [0, 1).
    fn rng(seed: &mut u64) -> f32 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*seed >> 40) as f32 / (1u64 << 24) as f32
    }

    fn random_soup(n: usize, seed: u64) -> Vec<RasterTriangle> {
        let mut s = seed;
        (0..n)
            .map(|k| {
                let c = Vec3::new(
                    rng(&mut s) * 4.0 - 2.0,
                    rng(&mut s) * 8.0 - 4.5,
                    rng(&mut s) * 3.0 - 1.5,
                );
                let mut p = [c; 3];
                for v in &mut p {
                    *v += Vec3::new(rng(&mut s) - 0.5, rng(&mut s) - 0.5, rng(&mut s) - 0.5) * 2.0;
                }
                RasterTriangle {
                    positions: p,
                    cull_back: k % 3 == 0,
                }
            })
            .collect()
    }

    #[test]
    fn fast_path_matches_reference_bit_for_bit() {
        // Random triangles, some crossing the near plane and the image border.
        for seed in 0..4 {
            let tris = random_soup(60, seed);
            let c = cam(47, 33);
            let a = rasterize_reference(&c, &tris, 0.05);
            let b = rasterize(&c, &tris, 0.05);
            assert_eq!(a, b, "seed {seed}");
            assert!(a.iter().filter(|f| f.tri != EMPTY).count() > 100);
        }
    }

    /// A grid of `n x n` quads (two triangles each) in the plane y = 0, filling [-s, s]^2 in x, z.
    fn grid(n: usize, s: f32, jitter: u64) -> Vec<RasterTriangle> {
        let mut seed = jitter;
        let mut pts = vec![vec![Vec3::ZERO; n + 1]; n + 1];
        for (a, row) in pts.iter_mut().enumerate() {
            for (b, p) in row.iter_mut().enumerate() {
                let mut x = -s + 2.0 * s * a as f32 / n as f32;
                let mut z = -s + 2.0 * s * b as f32 / n as f32;
                if a > 0 && a < n && b > 0 && b < n {
                    x += (rng(&mut seed) - 0.5) * s / n as f32;
                    z += (rng(&mut seed) - 0.5) * s / n as f32;
                }
                *p = Vec3::new(x, 0.0, z);
            }
        }
        let mut tris = Vec::new();
        for a in 0..n {
            for b in 0..n {
                let (p00, p10, p01, p11) =
                    (pts[a][b], pts[a + 1][b], pts[a][b + 1], pts[a + 1][b + 1]);
                tris.push(RasterTriangle {
                    positions: [p00, p10, p11],
                    cull_back: false,
                });
                tris.push(RasterTriangle {
                    positions: [p00, p11, p01],
                    cull_back: false,
                });
            }
        }
        tris
    }

    #[test]
    fn shared_edges_cover_each_sample_exactly_once() {
        // Count coverage per sample over all screen triangles (no depth test): inside the
        // projected grid every sample must be covered once, never twice, never missed.
        let c = cam(64, 48);
        for jitter in 0..3 {
            let tris = grid(7, 1.0, jitter);
            let screen = setup_all(&c, &tris, 0.05);
            let mut count = vec![0u32; 64 * 48];
            for j in 0..48 {
                for i in 0..64 {
                    for t in &screen {
                        if t.covers(t.weights(sample_centre(i), sample_centre(j))) {
                            count[(j * 64 + i) as usize] += 1;
                        }
                    }
                }
            }
            // Samples well inside the square's projection.
            let (u0, v0) = c.project(Vec3::new(-0.9, 0.0, 0.9)).unwrap();
            let (u1, v1) = c.project(Vec3::new(0.9, 0.0, -0.9)).unwrap();
            let mut inside = 0;
            for j in 0..48u32 {
                for i in 0..64u32 {
                    let (u, v) = (i as f32 + 0.5, j as f32 + 0.5);
                    let n = count[(j * 64 + i) as usize];
                    assert!(n <= 1, "sample ({i}, {j}) covered {n} times");
                    if u > u0 && u < u1 && v > v0 && v < v1 {
                        assert_eq!(n, 1, "sample ({i}, {j}) missed");
                        inside += 1;
                    }
                }
            }
            assert!(inside > 500);
        }
    }

    #[test]
    fn back_faces_are_culled_and_flagged() {
        let c = cam(32, 32);
        // Counter-clockwise seen from the camera at -Y: x right, z up.
        let front = RasterTriangle {
            positions: [
                Vec3::new(-1.0, 0.0, -1.0),
                Vec3::new(1.0, 0.0, -1.0),
                Vec3::new(0.0, 0.0, 1.0),
            ],
            cull_back: true,
        };
        let mut back = front;
        back.positions.swap(1, 2);
        let f = rasterize(&c, &[front], 0.05);
        assert!(f.iter().any(|f| f.tri == 0 && !f.back_facing));
        assert!(rasterize(&c, &[back], 0.05).iter().all(|f| f.tri == EMPTY));
        back.cull_back = false;
        let b = rasterize(&c, &[back], 0.05);
        assert!(b.iter().any(|f| f.tri == 0 && f.back_facing));
    }

    #[test]
    fn barycentrics_and_depth_are_perspective_correct() {
        // A triangle slanted in depth; at each covered sample the interpolated point must lie
        // on the camera ray through the sample, at the reported depth.
        let c = cam(40, 30);
        let tri = RasterTriangle {
            positions: [
                Vec3::new(-1.5, -1.0, -1.0),
                Vec3::new(1.5, 2.0, -0.8),
                Vec3::new(0.0, 0.5, 1.2),
            ],
            cull_back: false,
        };
        let buf = rasterize(&c, &[tri], 0.05);
        let inv = c.world_from_camera.inverse();
        let mut n = 0;
        for j in 0..30u32 {
            for i in 0..40u32 {
                let f = buf[(j * 40 + i) as usize];
                if f.tri == EMPTY {
                    continue;
                }
                n += 1;
                assert!((f.bary.x + f.bary.y + f.bary.z - 1.0).abs() < 1e-4);
                let p = tri.positions[0] * f.bary.x
                    + tri.positions[1] * f.bary.y
                    + tri.positions[2] * f.bary.z;
                let pc = inv.transform_point3(p);
                assert!((-pc.z - f.depth).abs() < 1e-3 * f.depth);
                let (u, v) = c.project(p).unwrap();
                // Within the snapping error of the sample centre.
                assert!(
                    (u - (i as f32 + 0.5)).abs() < 0.02 && (v - (j as f32 + 0.5)).abs() < 0.02,
                    "{u} {v} vs {i} {j}"
                );
            }
        }
        assert!(n > 100);
    }

    #[test]
    fn nearer_triangle_wins() {
        let c = cam(16, 16);
        let quad = |y: f32| RasterTriangle {
            positions: [
                Vec3::new(-3.0, y, -3.0),
                Vec3::new(3.0, y, -3.0),
                Vec3::new(0.0, y, 3.0),
            ],
            cull_back: false,
        };
        let buf = rasterize(&c, &[quad(1.0), quad(-1.0), quad(0.5)], 0.05);
        let centre = buf[8 * 16 + 8];
        assert_eq!(centre.tri, 1);
        assert!((centre.depth - 3.0).abs() < 1e-4);
    }
}
