//! Scene bounds from camera rigs: the contraction around the point closest to all optical axes
//! ([`contracted_bounds_from_cameras`], JSON datasets without a `scene_box`, `msth import`) and
//! its forward-facing variant with LLFF near/far bounds ([`forward_facing_bounds`], DyNeRF), and
//! the near bound of a JSON layout's cameras from LLFF rows beside it ([`near_from_llff_rows`]).

use glam::{DMat3, DVec3, Mat4, Vec3};
use msth_core::{Camera, SceneBounds};

/// The point closest (least squares) to all cameras' optical axes, and the median camera distance
/// to it; the mean of the camera centres when the axes are (nearly) parallel.
pub fn contracted_bounds_from_cameras(cameras: &[Camera]) -> SceneBounds {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    let mut mean = DVec3::ZERO;
    for c in cameras {
        let o = c.center().as_dvec3();
        let d = (-c.world_from_camera.z_axis.truncate())
            .as_dvec3()
            .normalize_or_zero();
        let p = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * o;
        mean += o;
    }
    let n = cameras.len().max(1) as f64;
    mean /= n;
    let det = a.determinant();
    let center = if det.is_finite() && det.abs() > 1e-6 * n * n * n {
        a.inverse() * b
    } else {
        mean
    };
    let center = if center.is_finite() { center } else { mean };
    let mut dists: Vec<f64> = cameras
        .iter()
        .map(|c| (c.center().as_dvec3() - center).length())
        .filter(|d| d.is_finite())
        .collect();
    dists.sort_by(f64::total_cmp);
    let radius = dists.get(dists.len() / 2).copied().unwrap_or(1.0) as f32;
    let radius = if radius.is_finite() && radius > 1e-6 {
        radius
    } else {
        1.0
    };
    SceneBounds::Contracted {
        center: center.as_vec3(),
        radius,
    }
}

/// Scene bounds for a forward-facing rig (see the module docs).
pub fn forward_facing_bounds(cameras: &[Camera], nears: &[f32], fars: &[f32]) -> SceneBounds {
    let n = cameras.len().max(1) as f32;
    let mean_center = cameras.iter().map(|c| c.center()).sum::<Vec3>() / n;
    let forward = (-cameras
        .iter()
        .map(|c| c.world_from_camera.z_axis.truncate())
        .sum::<Vec3>())
    .normalize_or_zero();
    let min_near = nears.iter().copied().fold(f32::INFINITY, f32::min);
    let max_far = fars.iter().copied().fold(0.0f32, f32::max);
    if let SceneBounds::Contracted { center, radius } = contracted_bounds_from_cameras(cameras) {
        let depth = (center - mean_center).dot(forward);
        if depth.is_finite() && depth >= min_near && depth <= max_far {
            return SceneBounds::Contracted { center, radius };
        }
    }
    let mut mids: Vec<f32> = nears.iter().zip(fars).map(|(a, b)| 0.5 * (a + b)).collect();
    mids.sort_by(f32::total_cmp);
    let mid = mids.get(mids.len() / 2).copied().unwrap_or(1.0);
    let mid = if mid.is_finite() && mid > 0.0 {
        mid
    } else {
        1.0
    };
    SceneBounds::Contracted {
        center: mean_center + forward * mid,
        radius: mid,
    }
}

/// The smallest near bound of the LLFF `rows` (camera-to-world pose, near, far) that describe
/// `cameras`: `None` unless every camera has a row with the same centre (to 1e-4 of the rig's
/// size) and the same viewing direction (to about 1 degree), so rows of another rig, or of the
/// same rig in other units, are never used.
pub fn near_from_llff_rows(cameras: &[Camera], rows: &[(Mat4, f32, f32)]) -> Option<f32> {
    if cameras.is_empty() || rows.is_empty() {
        return None;
    }
    let size = cameras
        .iter()
        .map(|c| c.center().abs().max_element())
        .fold(1.0f32, f32::max);
    let tolerance = 1e-4 * size;
    let mut near = f32::INFINITY;
    for c in cameras {
        let forward = -c.world_from_camera.z_axis.truncate().normalize_or_zero();
        let matched = rows.iter().find(|(pose, n, _)| {
            let row_forward = -pose.z_axis.truncate().normalize_or_zero();
            (pose.w_axis.truncate() - c.center()).length() <= tolerance
                && forward.dot(row_forward) > 0.9998
                && n.is_finite()
                && *n > 0.0
        })?;
        near = near.min(matched.1);
    }
    near.is_finite().then_some(near)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera_at(center: Vec3) -> Camera {
        Camera::look_at(64, 48, 0.8, center, Vec3::ZERO, Vec3::Y)
    }

    #[test]
    fn near_comes_only_from_rows_of_the_same_cameras() {
        let cams = [
            camera_at(Vec3::new(0.0, 0.0, 4.0)),
            camera_at(Vec3::new(1.0, 0.0, 4.0)),
        ];
        let rows: Vec<(Mat4, f32, f32)> = cams
            .iter()
            .zip([2.5, 2.0])
            .map(|(c, n)| (c.world_from_camera, n, 9.0))
            .collect();
        assert_eq!(near_from_llff_rows(&cams, &rows), Some(2.0));
        // A row more than the rig allows: still found, extra rows are ignored.
        let mut more = rows.clone();
        more.push((Mat4::IDENTITY, 0.1, 1.0));
        assert_eq!(near_from_llff_rows(&cams, &more), Some(2.0));
        // The same rig in other units (twice as large): no match, no near.
        let scaled: Vec<(Mat4, f32, f32)> = rows
            .iter()
            .map(|(p, n, f)| {
                let mut p = *p;
                p.w_axis = (p.w_axis.truncate() * 2.0).extend(1.0);
                (p, n * 2.0, f * 2.0)
            })
            .collect();
        assert_eq!(near_from_llff_rows(&cams, &scaled), None);
        // One camera without a row: no near.
        assert_eq!(near_from_llff_rows(&cams, &rows[..1]), None);
        // Same centre, another direction: no match.
        let turned: Vec<(Mat4, f32, f32)> = rows
            .iter()
            .map(|(p, n, f)| (*p * Mat4::from_rotation_y(0.5), *n, *f))
            .collect();
        assert_eq!(near_from_llff_rows(&cams, &turned), None);
    }
}
