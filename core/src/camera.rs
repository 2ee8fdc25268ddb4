//! Pinhole cameras and ray generation.
//!
//! Conventions (stated once, also in the README):
//! - World frame: right-handed; datasets decide which axis is up (Blender data is +Z up).
//! - Camera frame: OpenGL/Blender, +X right, +Y up, the camera looks down **-Z**.
//! - `world_from_camera` is the 4x4 camera-to-world matrix of NeRF `transform_matrix`.
//! - Pixels: `(u, v)` with `u` to the right and `v` downwards, pixel `(i, j)` covers
//!   `[i, i+1) x [j, j+1)`; rays go through pixel centres `(i + 0.5, j + 0.5)`.
//!   Camera-space direction of image point `(u, v)`: `((u - cx) / fx, -(v - cy) / fy, -1)`.

use glam::{Mat4, Vec3};
use serde::{Deserialize, Serialize};

/// A pinhole camera: intrinsics in pixels and a camera-to-world pose.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Camera-to-world, OpenGL camera axes (looks down -Z).
    pub world_from_camera: Mat4,
}

/// One ray: origin and unit direction in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

/// Why a camera was rejected by [`Camera::validate`] (pose or intrinsics).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidCamera(pub String);

impl Camera {
    /// A camera from the horizontal field of view (NeRF `camera_angle_x`), principal point centred.
    pub fn from_fov_x(width: u32, height: u32, fov_x: f32, world_from_camera: Mat4) -> Self {
        let f = 0.5 * width as f32 / (0.5 * fov_x).tan();
        Camera {
            width,
            height,
            fx: f,
            fy: f,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            world_from_camera,
        }
    }

    /// A camera at `eye` looking at `target` with `up` as the approximate up vector.
    pub fn look_at(width: u32, height: u32, fov_x: f32, eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let back = (eye - target).normalize();
        let right = up.cross(back).normalize();
        let cam_up = back.cross(right);
        let m = Mat4::from_cols(
            right.extend(0.0),
            cam_up.extend(0.0),
            back.extend(0.0),
            eye.extend(1.0),
        );
        Self::from_fov_x(width, height, fov_x, m)
    }

    /// Camera centre in world space.
    pub fn center(&self) -> Vec3 {
        self.world_from_camera.w_axis.truncate()
    }

    /// The ray through image point `(u, v)` (pixel units, see the module conventions).
    pub fn ray_at(&self, u: f32, v: f32) -> Ray {
        let d_cam = Vec3::new((u - self.cx) / self.fx, -(v - self.cy) / self.fy, -1.0);
        let dir = self.world_from_camera.transform_vector3(d_cam).normalize();
        Ray {
            origin: self.center(),
            dir,
        }
    }

    /// The ray through the centre of pixel `(px, py)`.
    pub fn pixel_ray(&self, px: u32, py: u32) -> Ray {
        self.ray_at(px as f32 + 0.5, py as f32 + 0.5)
    }

    /// Projects a world point to image coordinates `(u, v)`; `None` behind the camera.
    pub fn project(&self, point_in_world: Vec3) -> Option<(f32, f32)> {
        self.project_camera_point(
            self.world_from_camera
                .inverse()
                .transform_point3(point_in_world),
        )
    }

    /// [`Camera::project`] of a point already in camera space (`world_from_camera` inverted
    /// once by the caller, for many points).
    pub fn project_camera_point(&self, p: Vec3) -> Option<(f32, f32)> {
        if p.z >= 0.0 {
            return None;
        }
        Some((
            self.cx + self.fx * p.x / -p.z,
            self.cy - self.fy * p.y / -p.z,
        ))
    }

    /// The same pose with the image resized to `width x height`, keeping the horizontal field
    /// of view and square pixels (both focal lengths scale with the width); the principal
    /// point scales with each axis. Another aspect ratio shows more or less of the scene
    /// vertically, never a stretched view.
    pub fn resized(&self, width: u32, height: u32) -> Camera {
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Camera {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sx,
            cx: self.cx * sx,
            cy: self.cy * sy,
            world_from_camera: self.world_from_camera,
        }
    }

    /// The same camera with the image scaled by `factor` (e.g. 0.5 halves the resolution).
    pub fn scaled(&self, factor: f32) -> Camera {
        Camera {
            width: ((self.width as f32 * factor).round() as u32).max(1),
            height: ((self.height as f32 * factor).round() as u32).max(1),
            fx: self.fx * factor,
            fy: self.fy * factor,
            cx: self.cx * factor,
            cy: self.cy * factor,
            world_from_camera: self.world_from_camera,
        }
    }

    /// Checks that the pose is finite and invertible and the intrinsics positive.
    pub fn validate(&self) -> Result<(), InvalidCamera> {
        let m = self.world_from_camera;
        if !m.to_cols_array().iter().all(|v| v.is_finite()) {
            return Err(InvalidCamera("pose has non-finite entries".into()));
        }
        let det = glam::Mat3::from_mat4(m).determinant();
        if !det.is_finite() || det.abs() < 1e-6 {
            return Err(InvalidCamera(format!(
                "pose rotation is not invertible (determinant {det})"
            )));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(InvalidCamera(format!(
                    "focal length {name} = {v} must be finite and positive"
                )));
            }
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(InvalidCamera("principal point is not finite".into()));
        }
        if self.width == 0 || self.height == 0 {
            return Err(InvalidCamera("image size is zero".into()));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_projects_target_to_centre() {
        let cam = Camera::look_at(64, 48, 0.8, Vec3::new(3.0, 1.0, 2.0), Vec3::ZERO, Vec3::Z);
        let (u, v) = cam.project(Vec3::ZERO).unwrap();
        assert!(
            (u - 32.0).abs() < 1e-3 && (v - 24.0).abs() < 1e-3,
            "{u} {v}"
        );
        let r = cam.ray_at(32.0, 24.0);
        assert!((r.dir - (-cam.center()).normalize()).length() < 1e-5);
    }

    #[test]
    fn project_inverts_ray() {
        let cam = Camera::look_at(80, 60, 0.9, Vec3::new(0.0, -4.0, 1.0), Vec3::ZERO, Vec3::Z);
        let r = cam.ray_at(10.0, 50.0);
        let p = r.origin + r.dir * 3.0;
        let (u, v) = cam.project(p).unwrap();
        assert!((u - 10.0).abs() < 1e-3 && (v - 50.0).abs() < 1e-3);
        // v grows downwards: a point above the target projects above the centre.
        let (_, v_up) = cam.project(Vec3::new(0.0, 0.0, 0.5)).unwrap();
        assert!(v_up < 30.0);
    }
}
