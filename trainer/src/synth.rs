//! The built-in procedural dynamic scene ("builtin"): a small ray-traced room with static props
//! and moving objects, filmed by a forward-facing multi-camera rig, with analytic ground truth
//! for any camera and time ([`render_gt`]).
//!
//! World frame +Z up; everything lies inside [`SCENE_MIN`]..[`SCENE_MAX`]. Contents:
//! - room: a floor (soft checker of 0.35 units modulated by value noise), a brick back wall, a
//!   left wall of smooth coloured noise and a right wall of soft horizontal stripes (walls are
//!   one-sided, seen from inside; the open front faces the cameras);
//! - static props: a lat-long checkered sphere, a 3D-checker crate, a ringed cylinder;
//! - moving (over `t` in `[0, 1]`): a beach ball bouncing three times while rolling to the right,
//!   a two-faced sign slab spinning about a vertical axis, a sphere cycling through all hues,
//!   a small "moon" orbiting it twice;
//! - shading: Lambert from one directional light with hard shadows (cast by props and moving
//!   objects, so moving shadows are dynamic content too) plus a hemispheric ambient term.
//!
//! Cameras: `num_train_cams` fixed cameras on a forward-facing arc (50 degrees of azimuth, two
//! staggered elevations, 3.5 from the look-at point, `fov_x` 0.9) all filming every frame, and one
//! held-out test camera in the middle of the arc at an intermediate elevation. The arc is
//! narrower than Plenoptic Video's ~70 degrees on purpose: with the scene box fixed to
//! 3 x 3 x 3 units, wider cameras would see past the side walls out of the box.
//!
//! Pixels average `supersample^2` stratified, jittered sub-pixel samples (deterministic hashes),
//! so the output depends only on the configuration, never on thread scheduling.

use std::path::PathBuf;

use glam::Vec3;
use msth_core::{Camera, Ray, SceneBounds};
use rayon::prelude::*;

use msth_dataset::{Dataset, Image8, View};

/// Scene box corners (also `Dataset::bounds`).
pub const SCENE_MIN: Vec3 = Vec3::new(-1.5, -1.5, -1.0);
pub const SCENE_MAX: Vec3 = Vec3::new(1.5, 1.5, 2.0);

/// Point the rig looks at.
pub const LOOK_AT: Vec3 = Vec3::new(0.0, 0.6, -0.4);
/// Distance of every camera from [`LOOK_AT`].
pub const CAMERA_DISTANCE: f32 = 3.5;
/// Horizontal field of view of every camera (radians).
pub const FOV_X: f32 = 0.9;
/// Half of the azimuth span of the training arc (degrees).
const HALF_ARC_DEG: f32 = 25.0;
/// Elevations (degrees) of the lower and upper training cameras and of the test camera.
const ELEVATION_LO_DEG: f32 = 22.0;
const ELEVATION_HI_DEG: f32 = 30.0;
const ELEVATION_TEST_DEG: f32 = 26.0;

const FLOOR_Z: f32 = -0.95;
const WALL: f32 = 1.45;
const FRONT_Y: f32 = -1.49;
const TOP_Z: f32 = 1.95;
const T_MIN: f32 = 1e-4;

/// Settings of the built-in scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SynthConfig {
    pub width: u32,
    pub height: u32,
    pub num_frames: usize,
    pub num_train_cams: usize,
    /// Sub-pixel samples per axis (`supersample^2` per pixel); 0 counts as 1.
    pub supersample: u32,
    /// `false` freezes every moving object in its `t = 0` state (a static video).
    pub motion: bool,
    /// Seeds the texture noise and the sub-pixel jitter.
    pub seed: u64,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            width: 96,
            height: 72,
            num_frames: 20,
            num_train_cams: 12,
            supersample: 3,
            motion: true,
            seed: 0,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Hashing and noise

fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn hash(seed: u64, a: i64, b: i64, c: i64) -> u64 {
    let mut h = mix64(seed ^ 0x9E37_79B9_7F4A_7C15);
    for v in [a, b, c] {
        h = mix64(h ^ (v as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    }
    h
}

/// Uniform in `[0, 1)`.
fn hash01(seed: u64, a: i64, b: i64, c: i64) -> f32 {
    (hash(seed, a, b, c) >> 40) as f32 / (1u64 << 24) as f32
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// 2D value noise in `[0, 1]` with unit lattice spacing.
fn value_noise(seed: u64, x: f32, y: f32) -> f32 {
    let (fx, fy) = (x.floor(), y.floor());
    let (ix, iy) = (fx as i64, fy as i64);
    let (tx, ty) = (smoothstep(0.0, 1.0, x - fx), smoothstep(0.0, 1.0, y - fy));
    let v00 = hash01(seed, ix, iy, 0);
    let v10 = hash01(seed, ix + 1, iy, 0);
    let v01 = hash01(seed, ix, iy + 1, 0);
    let v11 = hash01(seed, ix + 1, iy + 1, 0);
    let a = v00 + (v10 - v00) * tx;
    let b = v01 + (v11 - v01) * tx;
    a + (b - a) * ty
}

/// Two octaves of value noise with the coarse cell size `cell` (world units), in `[0, 1]`.
fn fbm(seed: u64, x: f32, y: f32, cell: f32) -> f32 {
    let n1 = value_noise(seed, x / cell, y / cell);
    let n2 = value_noise(seed ^ 0x51, 2.0 * x / cell + 17.3, 2.0 * y / cell - 5.1);
    (n1 * 2.0 + n2) / 3.0
}

/// A checker in `[0, 1]` with cells of `cell` units and edges softened over `soft` units.
fn soft_checker(x: f32, y: f32, cell: f32, soft: f32) -> f32 {
    let tri = |v: f32| {
        // distance to the nearest cell edge, signed by cell parity
        let s = v / cell;
        let f = s - s.floor();
        let parity = if (s.floor() as i64).rem_euclid(2) == 0 {
            1.0
        } else {
            -1.0
        };
        let d = f.min(1.0 - f) * cell;
        (parity, d)
    };
    let (px, dx) = tri(x);
    let (py, dy) = tri(y);
    let edge = smoothstep(0.0, soft, dx.min(dy));
    let v = if px * py > 0.0 { 1.0 } else { 0.0 };
    0.5 + (v - 0.5) * edge
}

fn mix(a: Vec3, b: Vec3, t: f32) -> Vec3 {
    a + (b - a) * t
}

fn hsv(h: f32, s: f32, v: f32) -> Vec3 {
    let h6 = (h - h.floor()) * 6.0;
    let f = |n: f32| {
        let k = (n + h6) % 6.0;
        v - v * s * k.min(4.0 - k).clamp(0.0, 1.0)
    };
    Vec3::new(f(5.0), f(3.0), f(1.0))
}

// ---------------------------------------------------------------------------------------------
// Scene state at one time

/// What a ray hit.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Surface {
    Floor,
    BackWall,
    LeftWall,
    RightWall,
    PropSphere,
    PropCrate,
    PropCylinder,
    Ball,
    Slab,
    HueSphere,
    Moon,
}

#[derive(Clone, Copy, Debug)]
struct Hit {
    t: f32,
    surface: Surface,
    normal: Vec3,
}

const PROP_SPHERE: (Vec3, f32) = (Vec3::new(-0.95, 0.85, FLOOR_Z + 0.4), 0.4);
const CRATE_CENTER: Vec3 = Vec3::new(0.8, 0.85, FLOOR_Z + 0.3);
const CRATE_HALF: Vec3 = Vec3::new(0.28, 0.22, 0.3);
const CYL_CENTER: (f32, f32) = (0.1, 1.05);
const CYL_RADIUS: f32 = 0.16;
const CYL_TOP: f32 = 0.25;
const BALL_RADIUS: f32 = 0.2;
const SLAB_CENTER: Vec3 = Vec3::new(0.6, -0.1, FLOOR_Z + 0.32);
const SLAB_HALF: Vec3 = Vec3::new(0.26, 0.04, 0.24);
const HUE_SPHERE: (Vec3, f32) = (Vec3::new(-0.15, 0.35, FLOOR_Z + 0.25), 0.25);
const MOON_RADIUS: f32 = 0.08;
const MOON_ORBIT: f32 = 0.33;

/// Direction towards the light.
fn light_dir() -> Vec3 {
    Vec3::new(0.45, -0.55, 1.4).normalize()
}

/// The moving objects at one time.
#[derive(Clone, Copy, Debug)]
struct State {
    ball_center: Vec3,
    /// Rolling angle of the ball about the world Y axis.
    ball_spin: f32,
    slab_cos: f32,
    slab_sin: f32,
    hue_color: Vec3,
    moon_center: Vec3,
}

impl State {
    fn at(t: f32) -> State {
        let tau = std::f32::consts::TAU;
        let x = -0.75 + 0.55 * t;
        let z = FLOOR_Z + BALL_RADIUS + 0.32 * (std::f32::consts::PI * 3.0 * t).sin().abs();
        let angle = 0.4 + 0.75 * tau * t;
        let moon = 2.0 * tau * t + 1.0;
        State {
            ball_center: Vec3::new(x, -0.35, z),
            ball_spin: -(x + 0.75) / BALL_RADIUS,
            slab_cos: angle.cos(),
            slab_sin: angle.sin(),
            hue_color: hsv(t + 0.05, 0.8, 0.92),
            moon_center: HUE_SPHERE.0
                + Vec3::new(
                    MOON_ORBIT * moon.cos(),
                    MOON_ORBIT * moon.sin(),
                    HUE_SPHERE.1 + 0.1 * (moon * 0.5).sin() + 0.05,
                ),
        }
    }

    /// Slab-local coordinates of a world vector (rotation about +Z by minus the slab angle).
    fn slab_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(
            self.slab_cos * v.x + self.slab_sin * v.y,
            -self.slab_sin * v.x + self.slab_cos * v.y,
            v.z,
        )
    }

    fn slab_world(&self, v: Vec3) -> Vec3 {
        Vec3::new(
            self.slab_cos * v.x - self.slab_sin * v.y,
            self.slab_sin * v.x + self.slab_cos * v.y,
            v.z,
        )
    }
}

fn sphere_hit(ray: &Ray, center: Vec3, radius: f32) -> Option<(f32, Vec3)> {
    let oc = ray.origin - center;
    let b = oc.dot(ray.dir);
    let c = oc.length_squared() - radius * radius;
    let disc = b * b - c;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    let t = if -b - s > T_MIN { -b - s } else { -b + s };
    if t <= T_MIN {
        return None;
    }
    Some((t, (ray.origin + ray.dir * t - center) / radius))
}

/// Ray against an axis-aligned box centred at the origin (ray in box coordinates).
fn box_hit(origin: Vec3, dir: Vec3, half: Vec3) -> Option<(f32, Vec3)> {
    let inv = dir.recip();
    let t0 = (-half - origin) * inv;
    let t1 = (half - origin) * inv;
    let tmin = t0.min(t1);
    let tmax = t0.max(t1);
    let near = tmin.max_element();
    let far = tmax.min_element();
    if near.is_nan() || far.is_nan() || far < near || far <= T_MIN {
        return None;
    }
    if near > T_MIN {
        let axis = if tmin.x >= tmin.y && tmin.x >= tmin.z {
            0
        } else if tmin.y >= tmin.z {
            1
        } else {
            2
        };
        let mut n = Vec3::ZERO;
        n[axis] = -dir[axis].signum();
        Some((near, n))
    } else {
        None
    }
}

/// Vertical capped cylinder from the floor to `CYL_TOP`.
fn cylinder_hit(ray: &Ray) -> Option<(f32, Vec3)> {
    let (cx, cy) = CYL_CENTER;
    let mut best: Option<(f32, Vec3)> = None;
    let (ox, oy) = (ray.origin.x - cx, ray.origin.y - cy);
    let (dx, dy) = (ray.dir.x, ray.dir.y);
    let a = dx * dx + dy * dy;
    if a > 1e-12 {
        let b = ox * dx + oy * dy;
        let c = ox * ox + oy * oy - CYL_RADIUS * CYL_RADIUS;
        let disc = b * b - a * c;
        if disc >= 0.0 {
            let t = (-b - disc.sqrt()) / a;
            let z = ray.origin.z + ray.dir.z * t;
            if t > T_MIN && (FLOOR_Z..=CYL_TOP).contains(&z) {
                let p = ray.origin + ray.dir * t;
                best = Some((t, Vec3::new(p.x - cx, p.y - cy, 0.0) / CYL_RADIUS));
            }
        }
    }
    if ray.dir.z < 0.0 {
        let t = (CYL_TOP - ray.origin.z) / ray.dir.z;
        let p = ray.origin + ray.dir * t;
        let r2 = (p.x - cx).powi(2) + (p.y - cy).powi(2);
        if t > T_MIN && r2 <= CYL_RADIUS * CYL_RADIUS && best.is_none_or(|(bt, _)| t < bt) {
            best = Some((t, Vec3::Z));
        }
    }
    best
}

/// One-sided axis plane `p[axis] = value`, seen by rays with `dir[axis]` of sign `-facing`,
/// bounded by `lo`/`hi` on the two other axes.
fn wall_hit(ray: &Ray, axis: usize, value: f32, facing: f32, lo: Vec3, hi: Vec3) -> Option<f32> {
    let d = ray.dir[axis];
    if d * facing >= 0.0 {
        return None;
    }
    let t = (value - ray.origin[axis]) / d;
    if t <= T_MIN {
        return None;
    }
    let p = ray.origin + ray.dir * t;
    for a in 0..3 {
        if a != axis && !(p[a] >= lo[a] && p[a] <= hi[a]) {
            return None;
        }
    }
    Some(t)
}

struct Scene {
    state: State,
    seed: u64,
}

impl Scene {
    /// Nearest hit among the objects that cast shadows (props and moving objects).
    fn hit_objects(&self, ray: &Ray, mut best: Option<Hit>) -> Option<Hit> {
        let s = &self.state;
        let mut consider = |surface: Surface, r: Option<(f32, Vec3)>| {
            if let Some((t, normal)) = r {
                if best.is_none_or(|b| t < b.t) {
                    best = Some(Hit { t, surface, normal });
                }
            }
        };
        consider(
            Surface::PropSphere,
            sphere_hit(ray, PROP_SPHERE.0, PROP_SPHERE.1),
        );
        consider(
            Surface::PropCrate,
            box_hit(ray.origin - CRATE_CENTER, ray.dir, CRATE_HALF),
        );
        consider(Surface::PropCylinder, cylinder_hit(ray));
        consider(Surface::Ball, sphere_hit(ray, s.ball_center, BALL_RADIUS));
        let slab = box_hit(
            s.slab_local(ray.origin - SLAB_CENTER),
            s.slab_local(ray.dir),
            SLAB_HALF,
        )
        .map(|(t, n)| (t, s.slab_world(n)));
        consider(Surface::Slab, slab);
        consider(
            Surface::HueSphere,
            sphere_hit(ray, HUE_SPHERE.0, HUE_SPHERE.1),
        );
        consider(Surface::Moon, sphere_hit(ray, s.moon_center, MOON_RADIUS));
        best
    }

    fn trace(&self, ray: &Ray) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let lo = Vec3::new(-WALL, FRONT_Y, FLOOR_Z);
        let hi = Vec3::new(WALL, WALL, TOP_Z);
        let walls = [
            (Surface::Floor, 2, FLOOR_Z, 1.0, Vec3::Z),
            (Surface::BackWall, 1, WALL, -1.0, Vec3::NEG_Y),
            (Surface::LeftWall, 0, -WALL, 1.0, Vec3::X),
            (Surface::RightWall, 0, WALL, -1.0, Vec3::NEG_X),
        ];
        for (surface, axis, value, facing, normal) in walls {
            if let Some(t) = wall_hit(ray, axis, value, facing, lo, hi) {
                if best.is_none_or(|b| t < b.t) {
                    best = Some(Hit { t, surface, normal });
                }
            }
        }
        self.hit_objects(ray, best)
    }

    fn in_shadow(&self, p: Vec3) -> bool {
        let ray = Ray {
            origin: p,
            dir: light_dir(),
        };
        self.hit_objects(&ray, None).is_some()
    }

    fn albedo(&self, hit: &Hit, p: Vec3) -> Vec3 {
        let seed = self.seed;
        let s = &self.state;
        match hit.surface {
            Surface::Floor => {
                let c = soft_checker(p.x, p.y, 0.35, 0.06);
                let n = fbm(seed ^ 1, p.x, p.y, 0.4);
                let base = mix(Vec3::new(0.36, 0.25, 0.16), Vec3::new(0.86, 0.78, 0.62), c);
                base * (0.7 + 0.6 * n)
            }
            Surface::BackWall => {
                let (bw, bh, mortar) = (0.5, 0.25, 0.07);
                let row = (p.z / bh).floor();
                let shift = if (row as i64).rem_euclid(2) == 0 {
                    0.0
                } else {
                    0.5 * bw
                };
                let col = ((p.x + shift) / bw).floor();
                let fx = (p.x + shift) - col * bw;
                let fz = p.z - row * bh;
                let d = fx.min(bw - fx).min(fz.min(bh - fz));
                let m = smoothstep(0.5 * mortar - 0.03, 0.5 * mortar + 0.03, d);
                let v = hash01(seed ^ 2, col as i64, row as i64, 0);
                let brick = mix(Vec3::new(0.55, 0.2, 0.12), Vec3::new(0.78, 0.42, 0.25), v)
                    * (0.85 + 0.3 * fbm(seed ^ 3, p.x, p.z, 0.3));
                mix(Vec3::new(0.82, 0.8, 0.74), brick, m)
            }
            Surface::LeftWall => {
                let a = fbm(seed ^ 4, p.y, p.z, 0.45);
                let b = fbm(seed ^ 5, p.y + 3.1, p.z - 7.7, 0.3);
                mix(Vec3::new(0.1, 0.35, 0.45), Vec3::new(0.55, 0.8, 0.6), a)
                    + Vec3::new(0.25, -0.05, -0.1) * (b - 0.5)
            }
            Surface::RightWall => {
                let phase = p.z / 0.3 + 0.15 * (p.y * 2.0).sin();
                let stripe =
                    smoothstep(0.3, 0.7, 0.5 + 0.5 * (std::f32::consts::TAU * phase).sin());
                let tint = 0.5 + 0.5 * (p.y * 1.7).sin();
                mix(
                    mix(Vec3::new(0.1, 0.12, 0.4), Vec3::new(0.3, 0.1, 0.35), tint),
                    Vec3::new(0.95, 0.82, 0.3),
                    stripe,
                )
            }
            Surface::PropSphere => {
                let q = (p - PROP_SPHERE.0) / PROP_SPHERE.1;
                let lon = q.y.atan2(q.x) / std::f32::consts::TAU * 10.0;
                let lat = q.z.clamp(-1.0, 1.0).asin() / std::f32::consts::PI * 6.0;
                let c = soft_checker(lon, lat, 1.0, 0.12);
                mix(Vec3::new(0.12, 0.45, 0.18), Vec3::new(0.9, 0.93, 0.85), c)
            }
            Surface::PropCrate => {
                let q = p - CRATE_CENTER;
                let cell = 0.3;
                // A 3D checker with soft edges (a product of sines through a smoothstep).
                let pi = std::f32::consts::PI;
                let wave =
                    (pi * q.x / cell).sin() * (pi * q.y / cell).sin() * (pi * q.z / cell).sin();
                let v = smoothstep(-0.25, 0.25, wave);
                mix(Vec3::new(0.5, 0.3, 0.1), Vec3::new(0.85, 0.65, 0.35), v)
            }
            Surface::PropCylinder => {
                let rings = 0.5 + 0.5 * (std::f32::consts::TAU * p.z / 0.3).sin();
                let ang = (p.y - CYL_CENTER.1).atan2(p.x - CYL_CENTER.0);
                let stripes = smoothstep(-0.3, 0.3, (ang * 4.0).sin());
                if hit.surface == Surface::PropCylinder && hit.normal.z > 0.5 {
                    Vec3::new(0.9, 0.9, 0.88)
                } else {
                    mix(
                        Vec3::new(0.45, 0.15, 0.55),
                        Vec3::new(0.95, 0.55, 0.2),
                        0.65 * rings + 0.35 * stripes,
                    )
                }
            }
            Surface::Ball => {
                let q = p - s.ball_center;
                // Undo the rolling rotation about +Y.
                let (sn, cs) = (-s.ball_spin).sin_cos();
                let local = Vec3::new(cs * q.x + sn * q.z, q.y, -sn * q.x + cs * q.z);
                if local.z.abs() > 0.85 * BALL_RADIUS {
                    return Vec3::new(0.95, 0.95, 0.95);
                }
                let seg =
                    ((local.y.atan2(local.x) / std::f32::consts::TAU + 0.5) * 6.0).floor() as i64;
                match seg.rem_euclid(3) {
                    0 => Vec3::new(0.9, 0.12, 0.1),
                    1 => Vec3::new(0.95, 0.95, 0.92),
                    _ => Vec3::new(0.1, 0.3, 0.85),
                }
            }
            Surface::Slab => {
                let q = s.slab_local(p - SLAB_CENTER);
                let n = s.slab_local(hit.normal);
                if n.y < -0.5 {
                    let c = soft_checker(q.x, q.z, 0.2, 0.025);
                    mix(Vec3::new(0.95, 0.45, 0.05), Vec3::new(0.98, 0.93, 0.8), c)
                } else if n.y > 0.5 {
                    let st = smoothstep(0.35, 0.65, 0.5 + 0.5 * (q.x * 20.0).sin());
                    mix(Vec3::new(0.05, 0.2, 0.7), Vec3::new(0.85, 0.9, 0.98), st)
                } else {
                    Vec3::splat(0.3)
                }
            }
            Surface::HueSphere => {
                let q = (p - HUE_SPHERE.0) / HUE_SPHERE.1;
                s.hue_color * (0.8 + 0.2 * (q.z * 9.0).cos())
            }
            Surface::Moon => Vec3::new(1.0, 0.9, 0.55),
        }
    }

    /// Colour seen along `ray`, `None` when it leaves the scene.
    fn radiance(&self, ray: &Ray) -> Option<Vec3> {
        let hit = self.trace(ray)?;
        let p = ray.origin + ray.dir * hit.t;
        let n = hit.normal;
        let albedo = self.albedo(&hit, p).clamp(Vec3::ZERO, Vec3::ONE);
        let l = light_dir();
        let ndl = n.dot(l);
        let direct = if ndl > 0.0 && !self.in_shadow(p + n * 1e-3) {
            0.58 * ndl
        } else {
            0.0
        };
        let ambient = 0.36 + 0.08 * n.z;
        Some((albedo * (ambient + direct)).clamp(Vec3::ZERO, Vec3::ONE))
    }
}

fn scene_at(cfg: &SynthConfig, time: f32) -> Scene {
    let t = if cfg.motion {
        time.clamp(0.0, 1.0)
    } else {
        0.0
    };
    Scene {
        state: State::at(t),
        seed: cfg.seed,
    }
}

/// Analytic ground truth: the scene at `time` seen by `camera` (any camera, any time in `[0, 1]`,
/// clamped), with the configuration's supersampling and seed. Rays that leave the scene (only
/// possible for cameras outside the rig) are white, the dataset background.
pub fn render_gt(cfg: &SynthConfig, camera: &Camera, time: f32) -> Image8 {
    let scene = scene_at(cfg, time);
    let s = cfg.supersample.max(1);
    let inv = 1.0 / s as f32;
    let width = camera.width;
    let rows: Vec<Vec<f32>> = (0..camera.height)
        .into_par_iter()
        .map(|y| {
            let mut row = Vec::with_capacity(width as usize * 3);
            for x in 0..width {
                let mut acc = Vec3::ZERO;
                for k in 0..s * s {
                    let (a, b) = (k % s, k / s);
                    let (ja, jb) = if s == 1 {
                        (0.5, 0.5)
                    } else {
                        let h = hash(cfg.seed ^ 0xA5A5, x as i64, y as i64, k as i64);
                        (
                            (h >> 40) as f32 / (1u64 << 24) as f32,
                            ((h >> 16) & 0xFF_FFFF) as f32 / (1u64 << 24) as f32,
                        )
                    };
                    let u = x as f32 + (a as f32 + ja) * inv;
                    let v = y as f32 + (b as f32 + jb) * inv;
                    let ray = camera.ray_at(u, v);
                    acc += scene.radiance(&ray).unwrap_or(Vec3::ONE);
                }
                let c = acc * (inv * inv);
                row.extend_from_slice(&c.to_array());
            }
            row
        })
        .collect();
    let rgb: Vec<f32> = rows.concat();
    Image8::from_f32(width, camera.height, &rgb)
}

fn rig_camera(cfg: &SynthConfig, azimuth_deg: f32, elevation_deg: f32) -> Camera {
    let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
    let offset = Vec3::new(el.cos() * az.sin(), -el.cos() * az.cos(), el.sin()) * CAMERA_DISTANCE;
    Camera::look_at(
        cfg.width,
        cfg.height,
        FOV_X,
        LOOK_AT + offset,
        LOOK_AT,
        Vec3::Z,
    )
}

/// The training cameras: an arc of [`HALF_ARC_DEG`]`* 2` degrees, alternating elevations.
pub fn train_cameras(cfg: &SynthConfig) -> Vec<Camera> {
    let n = cfg.num_train_cams;
    (0..n)
        .map(|i| {
            let az = -HALF_ARC_DEG + 2.0 * HALF_ARC_DEG * (i as f32 + 0.5) / n as f32;
            let el = if i % 2 == 0 {
                ELEVATION_LO_DEG
            } else {
                ELEVATION_HI_DEG
            };
            rig_camera(cfg, az, el)
        })
        .collect()
}

/// The held-out test camera: middle of the arc, between the two training elevations.
pub fn test_camera(cfg: &SynthConfig) -> Camera {
    rig_camera(cfg, 0.0, ELEVATION_TEST_DEG)
}

/// Frame times: `j / (num_frames - 1)`, or 0 for a single frame.
pub fn frame_times(cfg: &SynthConfig) -> Vec<f32> {
    let n = cfg.num_frames;
    (0..n)
        .map(|j| {
            if n > 1 {
                j as f32 / (n - 1) as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// Renders the whole built-in dataset: every training camera and the test camera at every frame.
pub fn generate(cfg: &SynthConfig) -> Dataset {
    let times = frame_times(cfg);
    let mut jobs: Vec<(Camera, usize, usize, bool)> = Vec::new();
    for (c, cam) in train_cameras(cfg).into_iter().enumerate() {
        for j in 0..times.len() {
            jobs.push((cam, c, j, false));
        }
    }
    let test_id = cfg.num_train_cams;
    let test_cam = test_camera(cfg);
    for j in 0..times.len() {
        jobs.push((test_cam, test_id, j, true));
    }
    let views: Vec<(bool, View)> = jobs
        .par_iter()
        .map(|&(camera, id, j, is_test)| {
            let split = if is_test { "test" } else { "train" };
            (
                is_test,
                View {
                    camera,
                    time: times[j],
                    image: render_gt(cfg, &camera, times[j]),
                    source: PathBuf::from(format!("builtin/{split}/cam{id:02}_{j:04}")),
                    camera_id: Some(id),
                    alpha: None,
                },
            )
        })
        .collect();
    let (test, train): (Vec<_>, Vec<_>) = views.into_iter().partition(|(t, _)| *t);
    Dataset {
        name: "builtin".to_string(),
        train: train.into_iter().map(|(_, v)| v).collect(),
        test: test.into_iter().map(|(_, v)| v).collect(),
        bounds: SceneBounds::Box {
            min: SCENE_MIN,
            max: SCENE_MAX,
        },
        background: [1.0; 3],
        num_frames: times.len(),
        near: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use msth_dataset::dnerf;

    fn small() -> SynthConfig {
        SynthConfig {
            width: 48,
            height: 36,
            num_frames: 6,
            num_train_cams: 8,
            supersample: 2,
            ..Default::default()
        }
    }

    /// Fraction of pixels of training camera `cam` that differ between some frame and frame 0.
    fn dynamic_fraction(d: &Dataset, cam: usize) -> f64 {
        let views: Vec<&View> = d
            .train
            .iter()
            .filter(|v| v.camera_id == Some(cam))
            .collect();
        let first = &views[0].image;
        let n = (first.width * first.height) as usize;
        let changed = (0..n)
            .filter(|&i| {
                views
                    .iter()
                    .any(|v| v.image.data[i * 3..i * 3 + 3] != first.data[i * 3..i * 3 + 3])
            })
            .count();
        changed as f64 / n as f64
    }

    #[test]
    fn layout_and_cameras() {
        let cfg = small();
        let d = generate(&cfg);
        assert_eq!(d.name, "builtin");
        assert_eq!(d.train.len(), 8 * 6);
        assert_eq!(d.test.len(), 6);
        assert_eq!(d.num_frames, 6);
        assert_eq!(d.background, [1.0; 3]);
        assert_eq!(d.test[5].time, 1.0);
        assert_eq!(d.train[7].camera_id, Some(1));
        assert!(d.test.iter().all(|v| v.camera_id == Some(8)));
        let test = test_camera(&cfg);
        for c in train_cameras(&cfg) {
            assert!(c.validate().is_ok());
            assert!((c.center() - test.center()).length() > 0.1);
            // Cameras sit outside the scene box (and so outside every object).
            let p = c.center();
            assert!(p.cmplt(SCENE_MIN).any() || p.cmpgt(SCENE_MAX).any(), "{p}");
        }
        assert_eq!(
            frame_times(&SynthConfig {
                num_frames: 1,
                ..cfg.clone()
            }),
            [0.0]
        );
        // Rendering at any camera matches the dataset.
        assert_eq!(
            render_gt(&cfg, &d.test[2].camera, d.test[2].time),
            d.test[2].image
        );
    }

    #[test]
    fn deterministic() {
        let cfg = SynthConfig {
            num_train_cams: 2,
            ..small()
        };
        let a = generate(&cfg);
        let b = generate(&cfg);
        for (x, y) in a
            .train
            .iter()
            .chain(&a.test)
            .zip(b.train.iter().chain(&b.test))
        {
            assert_eq!(x.image, y.image);
        }
        let other = generate(&SynthConfig { seed: 9, ..cfg });
        assert_ne!(a.train[0].image, other.train[0].image);
    }

    #[test]
    fn every_ray_hits_a_surface() {
        let cfg = SynthConfig {
            num_train_cams: 8,
            ..Default::default()
        };
        let mut cams = train_cameras(&cfg);
        cams.push(test_camera(&cfg));
        for t in [0.0, 0.37, 1.0] {
            let scene = scene_at(&cfg, t);
            for cam in &cams {
                // Pixel corners as well as centres.
                for y in 0..=cam.height {
                    for x in 0..=cam.width {
                        let ray = cam.ray_at(x as f32, y as f32);
                        let hit = scene.trace(&ray);
                        let Some(hit) = hit else {
                            panic!("ray {x},{y} of camera at {} misses", cam.center());
                        };
                        let p = ray.origin + ray.dir * hit.t;
                        assert!(
                            p.cmpge(SCENE_MIN).all() && p.cmple(SCENE_MAX).all(),
                            "hit {p} outside the box"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn dynamic_fraction_with_and_without_motion() {
        let cfg = SynthConfig {
            supersample: 1,
            ..Default::default()
        };
        let d = generate(&cfg);
        for cam in 0..cfg.num_train_cams {
            let f = dynamic_fraction(&d, cam);
            println!("camera {cam}: dynamic fraction {f:.3}");
            assert!(
                (0.03..=0.30).contains(&f),
                "camera {cam}: dynamic fraction {f}"
            );
        }
        let frozen = generate(&SynthConfig {
            motion: false,
            ..cfg.clone()
        });
        for cam in 0..cfg.num_train_cams {
            assert_eq!(dynamic_fraction(&frozen, cam), 0.0);
        }
        // Frozen = the t = 0 state of the moving scene.
        assert_eq!(frozen.train[3].image, d.train[0].image);
    }

    /// Renders a few frames to /tmp for a human look (`cargo test ... -- --ignored`).
    #[test]
    #[ignore]
    fn write_preview_pngs() {
        let cfg = SynthConfig::default();
        let start = std::time::Instant::now();
        let d = generate(&cfg);
        println!("generate(default): {:.3} s", start.elapsed().as_secs_f64());
        for cam in [0usize, 3, 7] {
            let frames: Vec<&Image8> = d
                .train
                .iter()
                .filter(|v| v.camera_id == Some(cam))
                .step_by(6)
                .map(|v| &v.image)
                .collect();
            // Where the video changes at all (white), for judging the dynamic content.
            let first = frames[0];
            let all: Vec<&View> = d
                .train
                .iter()
                .filter(|v| v.camera_id == Some(cam))
                .collect();
            let mut mask = first.clone();
            for (i, px) in mask.data.chunks_mut(3).enumerate() {
                let moving = all
                    .iter()
                    .any(|v| v.image.data[i * 3..i * 3 + 3] != first.data[i * 3..i * 3 + 3]);
                if moving {
                    px.copy_from_slice(&[255, 255, 255]);
                } else {
                    px.iter_mut().for_each(|c| *c /= 3);
                }
            }
            let mut frames = frames;
            frames.push(&mask);
            let p = msth_dataset::imageio::panel(&frames);
            let path = format!("/tmp/msth_builtin_cam{cam:02}.png");
            msth_dataset::imageio::save_png_atomic(std::path::Path::new(&path), &p).unwrap();
            println!("wrote {path}");
        }
        let big = SynthConfig {
            width: 384,
            height: 288,
            ..cfg.clone()
        };
        let img = render_gt(&big, &test_camera(&big), 0.4);
        msth_dataset::imageio::save_png_atomic(
            std::path::Path::new("/tmp/msth_builtin_test_big.png"),
            &img,
        )
        .unwrap();
    }

    /// The D-NeRF writer and reader on the built-in scene (moved here from the dataset crate,
    /// which does not know the built-in scene).
    #[test]
    fn dnerf_write_then_load_round_trip() {
        let mut cfg = small();
        (cfg.width, cfg.height, cfg.num_frames) = (20, 14, 4);
        (cfg.num_train_cams, cfg.supersample) = (3, 1);
        let d = generate(&cfg);
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("scene");
        dnerf::write(&d, &out).unwrap();
        // Nothing but the dataset is left next to it.
        assert_eq!(std::fs::read_dir(root.path()).unwrap().count(), 1);
        let back = dnerf::load(&out, &dnerf::LoadOptions::default()).unwrap();
        assert_eq!(back.name, "scene");
        assert_eq!(back.bounds, d.bounds);
        assert_eq!(back.num_frames, d.num_frames);
        assert_eq!(
            (back.train.len(), back.test.len()),
            (d.train.len(), d.test.len())
        );
        let originals = d.train.iter().chain(&d.test);
        let read_back = back.train.iter().chain(&back.test);
        for (a, b) in originals.zip(read_back) {
            assert_eq!(a.image, b.image);
            assert_eq!(a.time, b.time);
            assert_eq!(a.camera_id, b.camera_id);
            let (ca, cb) = (a.camera, b.camera);
            assert_eq!((ca.width, ca.height), (cb.width, cb.height));
            for (x, y) in [
                (ca.fx, cb.fx),
                (ca.fy, cb.fy),
                (ca.cx, cb.cx),
                (ca.cy, cb.cy),
            ] {
                assert!((x - y).abs() < 1e-5);
            }
            assert!(ca.world_from_camera.abs_diff_eq(cb.world_from_camera, 1e-5));
        }
        let val: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("transforms_val.json")).unwrap())
                .unwrap();
        assert_eq!(
            val["frames"].as_array().unwrap().len(),
            d.test.len().div_ceil(3)
        );
        assert!(val["frames"][0]["file_path"]
            .as_str()
            .unwrap()
            .starts_with("./test/cam03_"));
        // Refuses to overwrite a dataset.
        let err = dnerf::write(&d, &out).unwrap_err();
        assert!(err.to_string().contains("not an empty folder"), "{err}");
        // An empty target folder is fine.
        let empty = root.path().join("empty");
        std::fs::create_dir(&empty).unwrap();
        dnerf::write(&d, &empty).unwrap();
        assert!(empty.join("transforms_train.json").exists());
    }
}
