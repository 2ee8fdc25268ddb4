//! Scene bounds from camera rigs: the contraction around the point closest to all optical axes
//! ([`contracted_bounds_from_cameras`], JSON datasets without a `scene_box`, `msth import`) and
//! its forward-facing variant with LLFF near/far bounds ([`forward_facing_bounds`], DyNeRF).

use glam::{DMat3, DVec3, Vec3};
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
