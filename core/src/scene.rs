//! Scene bounds: how world points map into the unit cube the grids live in, and where rays
//! start and stop.
//!
//! - [`SceneBounds::Box`]: object and stage scenes inside an axis-aligned box; points are
//!   mapped affinely to `[0, 1]^3`, rays are clipped to the box.
//! - [`SceneBounds::Contracted`]: unbounded or forward-facing scenes; `y = (x - center) / radius`
//!   then the L-inf contraction of method.md §2 (`y` if `|y|_inf < 1`, else
//!   `(2 - 1/|y|_inf) y/|y|_inf`), then `[-2, 2]^3 -> [0, 1]^3`.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::camera::Ray;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SceneBounds {
    Box { min: Vec3, max: Vec3 },
    Contracted { center: Vec3, radius: f32 },
}

/// Ray interval `[near, far]` in world distance along a unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayInterval {
    pub near: f32,
    pub far: f32,
}

/// Why scene bounds were rejected by [`SceneBounds::validate`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidBounds(pub String);

impl SceneBounds {
    /// The D-NeRF convention: a cube of half-size 1.5 around the origin.
    pub fn dnerf_default() -> Self {
        SceneBounds::Box {
            min: Vec3::splat(-1.5),
            max: Vec3::splat(1.5),
        }
    }

    pub fn validate(&self) -> Result<(), InvalidBounds> {
        match *self {
            SceneBounds::Box { min, max } => {
                if !(min.is_finite() && max.is_finite()) {
                    return Err(InvalidBounds("scene box has non-finite corners".into()));
                }
                if !(max.cmpgt(min).all()) {
                    return Err(InvalidBounds(format!(
                        "scene box max {max} must exceed min {min} on every axis"
                    )));
                }
            }
            SceneBounds::Contracted { center, radius } => {
                if !(center.is_finite() && radius.is_finite() && radius > 0.0) {
                    return Err(InvalidBounds(format!(
                        "contraction needs a finite centre and a positive radius (got {center}, {radius})"
                    )));
                }
            }
        }
        Ok(())
    }

    /// The same bounds in a world scaled by `s` about the origin.
    pub fn scaled(&self, s: f32) -> Self {
        match *self {
            SceneBounds::Box { min, max } => SceneBounds::Box {
                min: min * s,
                max: max * s,
            },
            SceneBounds::Contracted { center, radius } => SceneBounds::Contracted {
                center: center * s,
                radius: radius * s,
            },
        }
    }

    /// Maps a world point to the grids' unit cube (clamped to `[0, 1]^3`).
    #[inline]
    pub fn to_unit(&self, p: Vec3) -> Vec3 {
        match *self {
            SceneBounds::Box { min, max } => ((p - min) / (max - min)).clamp(Vec3::ZERO, Vec3::ONE),
            SceneBounds::Contracted { center, radius } => {
                let y = (p - center) / radius;
                let n = y.abs().max_element();
                let c = if n < 1.0 || !n.is_finite() {
                    if n.is_finite() {
                        y
                    } else {
                        y.signum() * 2.0
                    }
                } else {
                    (2.0 - 1.0 / n) * (y / n)
                };
                ((c + 2.0) * 0.25).clamp(Vec3::ZERO, Vec3::ONE)
            }
        }
    }

    /// The world point of a unit-cube point: the inverse of [`SceneBounds::to_unit`] inside the
    /// cube (`u` is clamped to it). A contracted scene's outer faces lie at infinity; points
    /// within 1e-4 of them map to 10,000 radii from the centre.
    pub fn from_unit(&self, u: Vec3) -> Vec3 {
        let u = u.clamp(Vec3::ZERO, Vec3::ONE);
        match *self {
            SceneBounds::Box { min, max } => min + u * (max - min),
            SceneBounds::Contracted { center, radius } => {
                let c = u * 4.0 - 2.0;
                let n = c.abs().max_element();
                let y = if n <= 1.0 {
                    c
                } else {
                    // |c| = 2 - 1/m for |y| = m >= 1, and c = (2 - 1/m) y / m.
                    let n = n.min(2.0 - 1e-4);
                    let m = 1.0 / (2.0 - n);
                    c / n * m
                };
                center + y * radius
            }
        }
    }

    /// The part of the ray the scene occupies, or `None` when the ray misses a box.
    pub fn ray_interval(&self, ray: &Ray, near_min: f32, far_max: f32) -> Option<RayInterval> {
        match *self {
            SceneBounds::Box { min, max } => {
                let inv = ray.dir.recip();
                let t0 = (min - ray.origin) * inv;
                let t1 = (max - ray.origin) * inv;
                let tmin = t0.min(t1);
                let tmax = t0.max(t1);
                // NaN-safe max/min: a direction component of 0 gives +-inf, which is fine, and
                // 0 * inf = NaN only when the origin is on a slab plane; treat NaN as unbounded.
                let mut near = near_min;
                let mut far = far_max;
                for a in 0..3 {
                    if tmin[a] > near {
                        near = tmin[a];
                    }
                    if tmax[a] < far {
                        far = tmax[a];
                    }
                }
                if far > near {
                    Some(RayInterval { near, far })
                } else {
                    None
                }
            }
            SceneBounds::Contracted { .. } => Some(RayInterval {
                near: near_min,
                far: far_max,
            }),
        }
    }

    /// Axis-aligned world-space extent (for a contracted scene, the inner, uncontracted cube).
    pub fn extent(&self) -> (Vec3, Vec3) {
        match *self {
            SceneBounds::Box { min, max } => (min, max),
            SceneBounds::Contracted { center, radius } => {
                (center - Vec3::splat(radius), center + Vec3::splat(radius))
            }
        }
    }
}

/// World length of one cell of an `resolution` grid in the scene's uncontracted part: the box's
/// smallest side over `resolution`, or for a contracted scene the inner cube (side `2 radius`,
/// half of the unit cube) over `resolution / 2`.
pub fn cell_world_size(bounds: &SceneBounds, resolution: u32) -> f32 {
    match *bounds {
        SceneBounds::Box { min, max } => (max - min).min_element() / resolution as f32,
        SceneBounds::Contracted { radius, .. } => 4.0 * radius / resolution as f32,
    }
}

/// The density threshold the export's occupancy grid uses (and the play-time volume, for files without one) for an opacity budget `alpha`: the density at which a
/// path along the grid's diagonal (`sqrt(3) R` cells) reaches opacity `alpha`.
pub fn density_threshold(bounds: &SceneBounds, resolution: u32, alpha: f32) -> f32 {
    let diagonal = 3f32.sqrt() * resolution as f32 * cell_world_size(bounds, resolution);
    -(1.0 - alpha.clamp(0.0, 0.999_999)).ln() / diagonal
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_maps_corners() {
        let b = SceneBounds::Box {
            min: Vec3::new(-1.0, -2.0, 0.0),
            max: Vec3::new(1.0, 2.0, 4.0),
        };
        assert_eq!(b.to_unit(Vec3::new(-1.0, -2.0, 0.0)), Vec3::ZERO);
        assert_eq!(b.to_unit(Vec3::new(1.0, 2.0, 4.0)), Vec3::ONE);
        assert_eq!(b.to_unit(Vec3::new(0.0, 0.0, 2.0)), Vec3::splat(0.5));
    }

    #[test]
    fn from_unit_inverts_to_unit() {
        let bounds = [
            SceneBounds::Box {
                min: Vec3::new(-1.0, -2.0, 0.0),
                max: Vec3::new(1.0, 2.0, 4.0),
            },
            SceneBounds::Contracted {
                center: Vec3::new(0.5, -1.0, 2.0),
                radius: 2.0,
            },
        ];
        let mut rng = crate::rng::Rng::new(3);
        for b in bounds {
            for _ in 0..1000 {
                let u = Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 0.998 + 0.001;
                let w = b.from_unit(u);
                let back = b.to_unit(w);
                assert!(
                    (back - u).abs().max_element() < 1e-4,
                    "{b:?}: {u} -> {w} -> {back}"
                );
            }
            // The cube's faces stay finite.
            for u in [Vec3::ZERO, Vec3::ONE, Vec3::new(0.0, 0.5, 1.0)] {
                assert!(b.from_unit(u).is_finite());
            }
        }
    }

    #[test]
    fn contraction_is_continuous_and_bounded() {
        let b = SceneBounds::Contracted {
            center: Vec3::ZERO,
            radius: 2.0,
        };
        let inside = b.to_unit(Vec3::new(1.999, 0.0, 0.0));
        let outside = b.to_unit(Vec3::new(2.001, 0.0, 0.0));
        assert!((inside - outside).length() < 1e-3);
        let far = b.to_unit(Vec3::new(1e30, -1e30, 0.0));
        assert!(far.is_finite() && far.cmple(Vec3::ONE).all() && far.cmpge(Vec3::ZERO).all());
        let inf = b.to_unit(Vec3::new(f32::INFINITY, 0.0, 0.0));
        assert!(inf.is_finite());
    }

    #[test]
    fn ray_box_clip() {
        let b = SceneBounds::dnerf_default();
        let r = Ray {
            origin: Vec3::new(0.0, 0.0, 5.0),
            dir: Vec3::new(0.0, 0.0, -1.0),
        };
        let i = b.ray_interval(&r, 0.0, 100.0).unwrap();
        assert!((i.near - 3.5).abs() < 1e-5 && (i.far - 6.5).abs() < 1e-5);
        let miss = Ray {
            origin: Vec3::new(5.0, 5.0, 5.0),
            dir: Vec3::new(0.0, 0.0, -1.0),
        };
        assert!(b.ray_interval(&miss, 0.0, 100.0).is_none());
    }
}
