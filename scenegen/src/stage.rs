//! The stage set around the model: a textured floor, a back wall and two side walls, and a
//! few static props, all with procedural solid textures. Everything is in the +Z-up world,
//! with the model standing at the origin on the floor (z = 0) and the cameras at -Y.

use glam::{Vec2, Vec3, Vec4};

use crate::scene::{SurfaceMaterial, Triangle};
use crate::texture::{srgb, Procedural};

/// Half width of the floor (x) and the side walls' position.
pub const ROOM_HALF_WIDTH: f32 = 4.0;
/// The back wall's y.
pub const BACK_WALL_Y: f32 = 3.2;
/// The front edge of the floor (behind the cameras).
pub const FRONT_Y: f32 = -7.0;
/// Height of the walls.
pub const WALL_HEIGHT: f32 = 3.6;

/// Geometry and materials of the set; material indices start at `material_offset`.
pub struct StageSet {
    pub triangles: Vec<Triangle>,
    pub materials: Vec<SurfaceMaterial>,
}

fn tri(p: [Vec3; 3], material: u32) -> Triangle {
    let n = (p[1] - p[0]).cross(p[2] - p[0]).normalize_or_zero();
    Triangle {
        positions: p,
        normals: [n; 3],
        uvs: [Vec2::ZERO; 3],
        colors: [Vec4::ONE; 3],
        material,
    }
}

/// A quad `a b c d` (counter-clockwise seen from the front), split in two triangles.
fn quad(out: &mut Vec<Triangle>, a: Vec3, b: Vec3, c: Vec3, d: Vec3, material: u32) {
    out.push(tri([a, b, c], material));
    out.push(tri([a, c, d], material));
}

/// The faces of a box: the corners of each, counter-clockwise seen from outside, as corner
/// numbers whose bits 0, 1, 2 pick the high end in x, y, z.
const CUBOID_FACES: [[usize; 4]; 6] = [
    [0, 1, 5, 4], // -Y
    [3, 2, 6, 7], // +Y
    [2, 0, 4, 6], // -X
    [1, 3, 7, 5], // +X
    [4, 5, 7, 6], // +Z
    [2, 3, 1, 0], // -Z
];

/// An axis-aligned box with outward faces.
fn cuboid(out: &mut Vec<Triangle>, lo: Vec3, hi: Vec3, material: u32) {
    let corner = |bits: usize| {
        Vec3::new(
            if bits & 1 != 0 { hi.x } else { lo.x },
            if bits & 2 != 0 { hi.y } else { lo.y },
            if bits & 4 != 0 { hi.z } else { lo.z },
        )
    };
    for [a, b, c, d] in CUBOID_FACES {
        quad(out, corner(a), corner(b), corner(c), corner(d), material);
    }
}

/// A UV sphere with smooth normals.
fn sphere(out: &mut Vec<Triangle>, centre: Vec3, r: f32, material: u32) {
    let (n_lat, n_lon) = (16, 32);
    let point = |i: usize, j: usize| {
        let th = std::f32::consts::PI * i as f32 / n_lat as f32;
        let ph = std::f32::consts::TAU * j as f32 / n_lon as f32;
        Vec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos())
    };
    for i in 0..n_lat {
        for j in 0..n_lon {
            let (a, b, c, d) = (
                point(i, j),
                point(i + 1, j),
                point(i + 1, j + 1),
                point(i, j + 1),
            );
            for (x, y, z) in [(a, b, c), (a, c, d)] {
                if (y - x).cross(z - x).length() < 1e-9 {
                    continue;
                }
                out.push(Triangle {
                    positions: [centre + x * r, centre + y * r, centre + z * r],
                    normals: [x, y, z],
                    uvs: [Vec2::ZERO; 3],
                    colors: [Vec4::ONE; 3],
                    material,
                });
            }
        }
    }
}

/// A vertical cylinder (`apex_radius = 0` makes a cone) standing on z = `base.z`.
fn cylinder(
    out: &mut Vec<Triangle>,
    base: Vec3,
    r: f32,
    apex_radius: f32,
    height: f32,
    material: u32,
) {
    let n = 32;
    let ring = |j: usize, rr: f32, z: f32| {
        let ph = std::f32::consts::TAU * j as f32 / n as f32;
        base + Vec3::new(rr * ph.cos(), rr * ph.sin(), z)
    };
    let slope = (r - apex_radius) / height;
    for j in 0..n {
        let (a, b) = (ring(j, r, 0.0), ring(j + 1, r, 0.0));
        let (c, d) = (
            ring(j + 1, apex_radius, height),
            ring(j, apex_radius, height),
        );
        let nrm = |j: usize| {
            let ph = std::f32::consts::TAU * j as f32 / n as f32;
            Vec3::new(ph.cos(), ph.sin(), slope).normalize()
        };
        let (na, nb) = (nrm(j), nrm(j + 1));
        let mk = |p: [Vec3; 3], ns: [Vec3; 3]| Triangle {
            positions: p,
            normals: ns,
            uvs: [Vec2::ZERO; 3],
            colors: [Vec4::ONE; 3],
            material,
        };
        out.push(mk([a, b, c], [na, nb, nb]));
        if apex_radius > 0.0 {
            out.push(mk([a, c, d], [na, nb, na]));
            out.push(tri([base + Vec3::Z * height, d, c], material));
        }
    }
}

/// Builds the set. `seed` varies the textures' noise.
pub fn build(material_offset: u32, seed: u64) -> StageSet {
    let m = |k: u32| material_offset + k;
    let materials = vec![
        // 0 floor: soft checker with noise
        SurfaceMaterial::procedural(Procedural::Checker {
            scale: 0.5,
            a: srgb(0.78, 0.76, 0.70),
            b: srgb(0.42, 0.40, 0.38),
            noise: 0.18,
            seed,
        }),
        // 1 back wall: bricks
        SurfaceMaterial::procedural(Procedural::Brick {
            u_axis: 0,
            v_axis: 2,
            width: 0.5,
            height: 0.22,
            brick: srgb(0.62, 0.28, 0.20),
            mortar: srgb(0.80, 0.78, 0.74),
            seed: seed ^ 11,
        }),
        // 2 left wall: marble
        SurfaceMaterial::procedural(Procedural::Marble {
            scale: 0.9,
            a: srgb(0.30, 0.55, 0.45),
            b: srgb(0.85, 0.80, 0.55),
            c: srgb(0.20, 0.20, 0.35),
            seed: seed ^ 22,
        }),
        // 3 right wall: large checker
        SurfaceMaterial::procedural(Procedural::Checker {
            scale: 0.6,
            a: srgb(0.55, 0.62, 0.80),
            b: srgb(0.88, 0.88, 0.90),
            noise: 0.05,
            seed: seed ^ 33,
        }),
        // 4 cube prop: small 3D checker
        SurfaceMaterial::procedural(Procedural::Checker {
            scale: 0.2,
            a: srgb(0.90, 0.75, 0.20),
            b: srgb(0.25, 0.22, 0.20),
            noise: 0.0,
            seed: seed ^ 44,
        }),
        // 5 sphere prop: cells
        SurfaceMaterial::procedural(Procedural::Cells {
            scale: 0.18,
            base: srgb(0.75, 0.55, 0.70),
            seed: seed ^ 55,
        }),
        // 6 column: bricks around (x, z)
        SurfaceMaterial::procedural(Procedural::Brick {
            u_axis: 0,
            v_axis: 2,
            width: 0.25,
            height: 0.15,
            brick: srgb(0.70, 0.66, 0.58),
            mortar: srgb(0.35, 0.33, 0.30),
            seed: seed ^ 66,
        }),
        // 7 cone: checker
        SurfaceMaterial::procedural(Procedural::Checker {
            scale: 0.15,
            a: srgb(0.20, 0.55, 0.85),
            b: srgb(0.95, 0.95, 0.95),
            noise: 0.0,
            seed: seed ^ 77,
        }),
    ];
    let (w, b, f, h) = (ROOM_HALF_WIDTH, BACK_WALL_Y, FRONT_Y, WALL_HEIGHT);
    let mut t = Vec::new();
    // Floor (z = 0, facing +Z).
    quad(
        &mut t,
        Vec3::new(-w, f, 0.0),
        Vec3::new(w, f, 0.0),
        Vec3::new(w, b, 0.0),
        Vec3::new(-w, b, 0.0),
        m(0),
    );
    // Back wall (y = b, facing -Y).
    quad(
        &mut t,
        Vec3::new(-w, b, 0.0),
        Vec3::new(w, b, 0.0),
        Vec3::new(w, b, h),
        Vec3::new(-w, b, h),
        m(1),
    );
    // Left wall (x = -w, facing +X).
    quad(
        &mut t,
        Vec3::new(-w, f, 0.0),
        Vec3::new(-w, b, 0.0),
        Vec3::new(-w, b, h),
        Vec3::new(-w, f, h),
        m(2),
    );
    // Right wall (x = w, facing -X).
    quad(
        &mut t,
        Vec3::new(w, b, 0.0),
        Vec3::new(w, f, 0.0),
        Vec3::new(w, f, h),
        Vec3::new(w, b, h),
        m(3),
    );
    // Props, clear of the model (radius 1.25 around the z axis).
    cuboid(
        &mut t,
        Vec3::new(-2.6, 0.6, 0.0),
        Vec3::new(-1.8, 1.4, 0.8),
        m(4),
    );
    sphere(&mut t, Vec3::new(2.2, 1.2, 0.55), 0.55, m(5));
    cylinder(&mut t, Vec3::new(-2.9, 2.4, 0.0), 0.3, 0.3, 2.6, m(6));
    cylinder(&mut t, Vec3::new(2.5, -0.6, 0.0), 0.4, 0.0, 0.9, m(7));
    StageSet {
        triangles: t,
        materials,
    }
}
