//! Which bricks of a volume the file's cameras can see any part of.
//!
//! A volume serves views near the file's cameras. Where the budget cannot hold the model's
//! resolution over every occupied brick, the plan leaves the bricks no camera looks into out of
//! the volume and keeps the resolution ([`super::bake::OutsideViews`]): on a forward-facing
//! capture most of the contracted cube lies behind, beside or above the cameras.
//! A ray of another view that reaches such a brick ([`super::OUTSIDE_BRICK`]) is drawn by the
//! exact path.

use glam::{Mat4, Vec3};

use super::VolumeGeometry;
use crate::scene::SceneBounds;
use crate::Camera;

/// The distance in front of a camera (world units) where a brick that straddles the camera's
/// plane is clipped before it is projected.
const NEAR_CLIP: f32 = 1e-4;

/// Per brick of `g` (index order), whether some part of it projects into the image of one of
/// `cameras`, in front of it. A brick's world shape is taken as the convex hull of its 8
/// corners ([`SceneBounds::from_unit`]), clipped to the half space in front of the camera; the
/// test is conservative for that hull (its projected bounding rectangle overlaps the image).
pub fn bricks_in_view(g: &VolumeGeometry, bounds: &SceneBounds, cameras: &[Camera]) -> Vec<bool> {
    let i = g.bricks_per_side() as usize;
    let v = i + 1;
    let world: Vec<Vec3> = (0..v * v * v)
        .map(|k| {
            let u = Vec3::new(
                (k % v) as f32 / i as f32,
                ((k / v) % v) as f32 / i as f32,
                (k / (v * v)) as f32 / i as f32,
            );
            bounds.from_unit(u)
        })
        .collect();
    let mut seen = vec![false; i * i * i];
    let mut local = vec![Vec3::ZERO; world.len()];
    for cam in cameras {
        let camera_from_world: Mat4 = cam.world_from_camera.inverse();
        if !camera_from_world.is_finite() {
            continue;
        }
        local
            .iter_mut()
            .zip(&world)
            .for_each(|(l, &w)| *l = camera_from_world.transform_point3(w));
        seen.iter_mut().enumerate().for_each(|(b, s)| {
            if *s {
                return;
            }
            let (x, y, z) = (b % i, (b / i) % i, b / (i * i));
            let mut corners = [Vec3::ZERO; 8];
            for (c, corner) in corners.iter_mut().enumerate() {
                let (dx, dy, dz) = (c & 1, (c >> 1) & 1, c >> 2);
                *corner = local[(x + dx) + v * ((y + dy) + v * (z + dz))];
            }
            *s = hull_in_view(cam, &corners);
        });
    }
    seen
}

/// Whether the convex hull of `corners` (camera space, the camera looking down -z; corner `c`
/// at offsets `c & 1`, `c >> 1 & 1`, `c >> 2` of a box) reaches into `cam`'s image in front of
/// it.
fn hull_in_view(cam: &Camera, corners: &[Vec3; 8]) -> bool {
    let front = |p: Vec3| p.z <= -NEAR_CLIP;
    let (mut lo, mut hi) = (
        glam::Vec2::splat(f32::INFINITY),
        glam::Vec2::splat(f32::NEG_INFINITY),
    );
    let mut add = |p: Vec3| {
        let q = glam::Vec2::new(cam.cx + cam.fx * p.x / -p.z, cam.cy - cam.fy * p.y / -p.z);
        lo = lo.min(q);
        hi = hi.max(q);
    };
    let mut any = false;
    for &p in corners {
        if front(p) {
            add(p);
            any = true;
        }
    }
    if !any {
        return false;
    }
    // The box's 12 edges: where one crosses the clipping plane, the crossing is a vertex of
    // the clipped hull.
    for a in 0..8usize {
        for bit in [1usize, 2, 4] {
            if a & bit != 0 {
                continue;
            }
            let (p, q) = (corners[a], corners[a | bit]);
            if front(p) != front(q) {
                let f = (-NEAR_CLIP - p.z) / (q.z - p.z);
                add(p + (q - p) * f);
            }
        }
    }
    !(hi.x < 0.0 || hi.y < 0.0 || lo.x > cam.width as f32 || lo.y > cam.height as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Camera {
        Camera::look_at(64, 48, 0.4, Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, Vec3::Z)
    }

    /// The reference: a brick is in view when one of many points inside it projects into the
    /// image in front of the camera.
    fn sampled(g: &VolumeGeometry, bounds: &SceneBounds, cam: &Camera, b: usize) -> bool {
        let i = g.bricks_per_side() as usize;
        let o = Vec3::new((b % i) as f32, ((b / i) % i) as f32, (b / (i * i)) as f32);
        let n = 6;
        for z in 0..=n {
            for y in 0..=n {
                for x in 0..=n {
                    let u = (o + Vec3::new(x as f32, y as f32, z as f32) / n as f32) / i as f32;
                    if let Some((px, py)) = cam.project(bounds.from_unit(u)) {
                        if (0.0..=cam.width as f32).contains(&px)
                            && (0.0..=cam.height as f32).contains(&py)
                        {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }

    #[test]
    fn every_brick_a_camera_sees_is_kept_and_most_others_are_not() {
        let g = VolumeGeometry::new(64);
        for bounds in [
            SceneBounds::dnerf_default(),
            SceneBounds::Contracted {
                center: Vec3::ZERO,
                radius: 1.0,
            },
        ] {
            let cam = camera();
            let kept = bricks_in_view(&g, &bounds, std::slice::from_ref(&cam));
            let mut seen = 0;
            for (b, &k) in kept.iter().enumerate() {
                let s = sampled(&g, &bounds, &cam, b);
                assert!(k || !s, "brick {b} is seen but dropped ({bounds:?})");
                seen += s as usize;
            }
            let kept_count = kept.iter().filter(|&&k| k).count();
            // A 0.4 rad view into the bounds leaves most of the cube out.
            assert!(
                kept_count < kept.len() / 2,
                "{kept_count} of {}",
                kept.len()
            );
            assert!(
                seen > 0 && kept_count <= seen * 2,
                "{kept_count} kept, {seen} seen"
            );
        }
    }

    #[test]
    fn a_brick_around_the_camera_is_in_view_and_one_behind_it_is_not() {
        let g = VolumeGeometry::new(32);
        let bounds = SceneBounds::dnerf_default();
        let (lo, hi) = bounds.extent();
        let eye = lo + (hi - lo) * Vec3::new(0.51, 0.2, 0.52);
        let cam = Camera::look_at(64, 48, 0.8, eye, eye + Vec3::Y, Vec3::Z);
        let kept = bricks_in_view(&g, &bounds, std::slice::from_ref(&cam));
        let i = g.bricks_per_side() as usize;
        let at = |u: Vec3| {
            let c = (u * i as f32).floor();
            c.x as usize + i * (c.y as usize + i * c.z as usize)
        };
        assert!(kept[at(Vec3::new(0.51, 0.2, 0.52))]);
        assert!(kept[at(Vec3::new(0.51, 0.6, 0.52))]);
        assert!(!kept[at(Vec3::new(0.51, 0.02, 0.52))]);
        // No camera: nothing is in view.
        assert!(!bricks_in_view(&g, &bounds, &[]).contains(&true));
    }
}
