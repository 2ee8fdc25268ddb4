//! Animation sampling (glTF 2.0 section 3.11: STEP, LINEAR with quaternion slerp, CUBICSPLINE
//! Hermite), node hierarchy evaluation and linear blend skinning.
//!
//! Times here are glTF seconds (`time_secs`); the dataset layouts map their normalised time
//! `t in [0, 1]` onto [`Animation::start`]..[`Animation::end`].

use glam::{Mat3, Mat4, Quat, Vec3, Vec4};

use crate::model::{LocalTransform, Model, Skin};

/// How a sampler interpolates between keyframes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    Step,
    Linear,
    CubicSpline,
}

/// The node property a channel drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Property {
    Translation,
    Rotation,
    Scale,
}

impl Property {
    /// Components per value (3, or 4 for a quaternion).
    pub fn components(self) -> usize {
        match self {
            Property::Rotation => 4,
            _ => 3,
        }
    }
}

/// Keyframes: `input` times (seconds, non-decreasing) and `output` values, `k` components each;
/// CUBICSPLINE stores `(in-tangent, value, out-tangent)` per keyframe.
#[derive(Clone, Debug, PartialEq)]
pub struct Sampler {
    input: Vec<f32>,
    output: Vec<f32>,
    k: usize,
    interpolation: Interpolation,
}

/// Why a glTF animation sampler's keyframes were refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum KeyframeError {
    #[error("sampler has no keyframes")]
    NoKeyframes,
    #[error("keyframe times decrease at keyframe {index} ({time} after {previous})")]
    TimesDecrease {
        index: usize,
        time: f32,
        previous: f32,
    },
    #[error(
        "{times} keyframe times need {needed} output elements ({interpolation:?}), found {found}"
    )]
    OutputCount {
        times: usize,
        needed: usize,
        interpolation: Interpolation,
        found: usize,
    },
}

impl Sampler {
    /// Checks the keyframes: at least one, finite, non-decreasing times, and the number of
    /// output values matching the number of times.
    pub fn new(
        input: Vec<f32>,
        output: Vec<f32>,
        k: usize,
        interpolation: Interpolation,
    ) -> Result<Self, KeyframeError> {
        if input.is_empty() {
            return Err(KeyframeError::NoKeyframes);
        }
        if let Some(i) = input.windows(2).position(|w| w[1] < w[0]) {
            return Err(KeyframeError::TimesDecrease {
                index: i + 1,
                time: input[i + 1],
                previous: input[i],
            });
        }
        let per_key = if interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        let expected = input.len() * per_key * k;
        if output.len() != expected {
            return Err(KeyframeError::OutputCount {
                times: input.len(),
                needed: input.len() * per_key,
                interpolation,
                found: output.len() / k.max(1),
            });
        }
        Ok(Sampler {
            input,
            output,
            k,
            interpolation,
        })
    }

    pub fn start(&self) -> f32 {
        self.input[0]
    }

    pub fn end(&self) -> f32 {
        self.input[self.input.len() - 1]
    }

    /// Element `e` of keyframe `key` (for cubic splines: 0 in-tangent, 1 value, 2 out-tangent).
    fn element(&self, key: usize, e: usize) -> Vec4 {
        let per_key = if self.interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        let at = (key * per_key + e) * self.k;
        let mut v = [0.0; 4];
        v[..self.k].copy_from_slice(&self.output[at..at + self.k]);
        Vec4::from(v)
    }

    fn value(&self, key: usize) -> Vec4 {
        if self.interpolation == Interpolation::CubicSpline {
            self.element(key, 1)
        } else {
            self.element(key, 0)
        }
    }

    /// The value at `time_secs`: clamped to the first / last keyframe outside the keyed range.
    /// `rotation` selects quaternion interpolation (slerp for LINEAR, normalised results).
    pub fn sample(&self, time_secs: f32, rotation: bool) -> Vec4 {
        let n = self.input.len();
        if n == 1 || time_secs <= self.input[0] {
            return self.value(0);
        }
        if time_secs >= self.input[n - 1] {
            return self.value(n - 1);
        }
        // The last keyframe at or before time_secs.
        let k = self.input.partition_point(|&t| t <= time_secs) - 1;
        let (t0, t1) = (self.input[k], self.input[k + 1]);
        let dt = t1 - t0;
        if dt <= 0.0 {
            return self.value(k + 1);
        }
        let u = (time_secs - t0) / dt;
        match self.interpolation {
            Interpolation::Step => self.value(k),
            Interpolation::Linear => {
                let (a, b) = (self.value(k), self.value(k + 1));
                if rotation {
                    slerp(a, b, u)
                } else {
                    a + (b - a) * u
                }
            }
            Interpolation::CubicSpline => {
                let v0 = self.element(k, 1);
                let b0 = self.element(k, 2);
                let a1 = self.element(k + 1, 0);
                let v1 = self.element(k + 1, 1);
                let (u2, u3) = (u * u, u * u * u);
                let p = v0 * (2.0 * u3 - 3.0 * u2 + 1.0)
                    + b0 * (dt * (u3 - 2.0 * u2 + u))
                    + v1 * (-2.0 * u3 + 3.0 * u2)
                    + a1 * (dt * (u3 - u2));
                if rotation {
                    let l = p.length();
                    if l > 0.0 {
                        p / l
                    } else {
                        v1
                    }
                } else {
                    p
                }
            }
        }
    }
}

/// Spherical linear interpolation of unit quaternions `(x, y, z, w)` along the shorter arc.
pub fn slerp(a: Vec4, b: Vec4, u: f32) -> Vec4 {
    let mut b = b;
    let mut d = a.dot(b);
    if d < 0.0 {
        b = -b;
        d = -d;
    }
    if d > 0.9995 {
        // Nearly parallel: lerp and normalise (the angle is too small for sin() to be exact).
        return (a + (b - a) * u).normalize();
    }
    let theta = d.clamp(-1.0, 1.0).acos();
    let s = theta.sin();
    (a * ((1.0 - u) * theta).sin() + b * (u * theta).sin()) / s
}

/// One animation channel: which node property the sampler drives.
#[derive(Clone, Debug, PartialEq)]
pub struct Channel {
    pub node: usize,
    pub property: Property,
    pub sampler: Sampler,
}

/// The channels of one glTF animation and its time range (seconds).
#[derive(Clone, Debug, PartialEq)]
pub struct Animation {
    pub channels: Vec<Channel>,
    /// Earliest keyframe of any channel (0 when there are none).
    pub start: f32,
    /// Latest keyframe of any channel (0 when there are none).
    pub end: f32,
}

impl Animation {
    pub fn new(channels: Vec<Channel>) -> Self {
        let start = channels
            .iter()
            .map(|c| c.sampler.start())
            .fold(f32::INFINITY, f32::min);
        let end = channels
            .iter()
            .map(|c| c.sampler.end())
            .fold(f32::NEG_INFINITY, f32::max);
        let (start, end) = if channels.is_empty() {
            (0.0, 0.0)
        } else {
            (start, end)
        };
        Animation {
            channels,
            start,
            end,
        }
    }

    /// Seconds for normalised time `t in [0, 1]` over the full animation.
    pub fn time_secs(&self, t: f32) -> f32 {
        self.start + t.clamp(0.0, 1.0) * (self.end - self.start)
    }

    /// Overwrites the animated properties of `locals` with their values at `time_secs`.
    pub fn apply(&self, time_secs: f32, locals: &mut [LocalTransform]) {
        for ch in &self.channels {
            let rotation = ch.property == Property::Rotation;
            let v = ch.sampler.sample(time_secs, rotation);
            if let LocalTransform::Trs {
                translation,
                rotation: r,
                scale,
            } = &mut locals[ch.node]
            {
                match ch.property {
                    Property::Translation => *translation = v.truncate(),
                    Property::Scale => *scale = v.truncate(),
                    Property::Rotation => *r = Quat::from_vec4(v).normalize(),
                }
            }
        }
    }
}

impl LocalTransform {
    /// The local matrix (`T * R * S` or the fixed matrix).
    pub fn matrix(&self) -> Mat4 {
        match *self {
            LocalTransform::Trs {
                translation,
                rotation,
                scale,
            } => Mat4::from_scale_rotation_translation(scale, rotation, translation),
            LocalTransform::Matrix(m) => m,
        }
    }
}

/// Node-to-world matrices for the model at `time_secs` (rest pose when the model has no
/// animation), with `root_transform` applied above the scene roots. Nodes outside the displayed
/// scene get `None`.
pub fn world_matrices(model: &Model, time_secs: f32, root_transform: Mat4) -> Vec<Option<Mat4>> {
    let mut locals: Vec<LocalTransform> = model.nodes.iter().map(|n| n.local).collect();
    if let Some(a) = &model.animation {
        a.apply(time_secs, &mut locals);
    }
    let mut world = vec![None; model.nodes.len()];
    // The hierarchy is a forest (checked on load), so a plain stack visits each node once.
    let mut stack: Vec<(usize, Mat4)> = model.roots.iter().map(|&r| (r, root_transform)).collect();
    while let Some((i, parent)) = stack.pop() {
        if world[i].is_some() {
            continue;
        }
        let m = parent * locals[i].matrix();
        world[i] = Some(m);
        for &c in &model.nodes[i].children {
            stack.push((c, m));
        }
    }
    world
}

/// Joint matrices of `skin`: `world(joint) * inverse_bind(joint)` (identity for a joint outside
/// the displayed scene).
pub fn joint_matrices(skin: &Skin, world: &[Option<Mat4>]) -> Vec<Mat4> {
    skin.joints
        .iter()
        .zip(&skin.inverse_bind)
        .map(|(&j, ib)| world[j].unwrap_or(Mat4::IDENTITY) * *ib)
        .collect()
}

/// The linear-blend-skinned matrix of one vertex: `sum_i w_i * joint[j_i]`, weights
/// normalised; `None` when all weights are zero.
pub fn blend_matrix(joints: [u16; 4], weights: Vec4, joint_mats: &[Mat4]) -> Option<Mat4> {
    let w = weights.to_array();
    let sum: f32 = w.iter().sum();
    if sum.is_nan() || sum <= 1e-8 {
        return None;
    }
    let mut acc = [0.0f32; 16];
    for i in 0..4 {
        if w[i] == 0.0 {
            continue;
        }
        let m = joint_mats[joints[i] as usize].to_cols_array();
        for (a, v) in acc.iter_mut().zip(m) {
            *a += v * w[i] / sum;
        }
    }
    Some(Mat4::from_cols_array(&acc))
}

/// The matrix for normals under `m`: inverse transpose of the upper 3x3 (the 3x3 itself when
/// it is singular).
pub fn normal_matrix(m: &Mat4) -> Mat3 {
    let a = Mat3::from_mat4(*m);
    let det = a.determinant();
    if det.abs() > 1e-12 {
        a.inverse().transpose()
    } else {
        a
    }
}

/// Convenience: a point under a matrix.
pub fn transform_point(m: &Mat4, p: Vec3) -> Vec3 {
    m.transform_point3(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lin(input: &[f32], output: &[f32], k: usize, i: Interpolation) -> Sampler {
        Sampler::new(input.to_vec(), output.to_vec(), k, i).unwrap()
    }

    #[test]
    fn step_holds_the_previous_keyframe() {
        let s = lin(
            &[0.0, 1.0, 2.0],
            &[0., 0., 0., 10., 0., 0., 20., 0., 0.],
            3,
            Interpolation::Step,
        );
        assert_eq!(s.sample(0.99, false).x, 0.0);
        assert_eq!(s.sample(1.0, false).x, 10.0);
        assert_eq!(s.sample(1.5, false).x, 10.0);
        assert_eq!(s.sample(5.0, false).x, 20.0);
        assert_eq!(s.sample(-1.0, false).x, 0.0);
    }

    #[test]
    fn linear_translation_hand_values() {
        // From (1, 2, 3) at t=1 to (3, 6, -1) at t=3: at t=1.5, u=0.25 -> (1.5, 3, 2).
        let s = lin(
            &[1.0, 3.0],
            &[1., 2., 3., 3., 6., -1.],
            3,
            Interpolation::Linear,
        );
        let v = s.sample(1.5, false);
        assert!(
            (v.truncate() - Vec3::new(1.5, 3.0, 2.0)).length() < 1e-6,
            "{v}"
        );
        // Clamped outside the keyed range.
        assert_eq!(s.sample(0.0, false).truncate(), Vec3::new(1., 2., 3.));
        assert_eq!(s.sample(9.0, false).truncate(), Vec3::new(3., 6., -1.));
    }

    #[test]
    fn linear_rotation_is_slerp() {
        // Identity to 90 degrees about Z; at u = 1/3 the angle is 30 degrees:
        // q = (0, 0, sin 15deg, cos 15deg).
        let h = std::f32::consts::FRAC_1_SQRT_2;
        let s = lin(
            &[0.0, 3.0],
            &[0., 0., 0., 1., 0., 0., h, h],
            4,
            Interpolation::Linear,
        );
        let q = s.sample(1.0, true);
        let a = 15f32.to_radians();
        assert!(
            (q - Vec4::new(0.0, 0.0, a.sin(), a.cos())).length() < 1e-6,
            "{q}"
        );
        // The shorter arc: the same target written as -q gives the same result.
        let s2 = lin(
            &[0.0, 3.0],
            &[0., 0., 0., 1., 0., 0., -h, -h],
            4,
            Interpolation::Linear,
        );
        assert!((s2.sample(1.0, true) - q).length() < 1e-6);
    }

    #[test]
    fn cubic_spline_hand_values() {
        // Scalar-like first component: v0 = 0, b0 (out-tangent) = 2, v1 = 1, a1 (in-tangent) = 0,
        // keys at 0 and 2 (dt = 2). At u = 0.5:
        // h00 = 0.5, h10 = 0.125, h01 = 0.5, h11 = -0.125
        // p = 0*0.5 + 2*2*0.125 + 1*0.5 + 0*2*(-0.125) = 1.0.
        let out = [
            9., 0., 0., /* a0 */ 0., 0., 0., /* v0 */ 2., 0., 0., /* b0 */
            0., 0., 0., /* a1 */ 1., 0., 0., /* v1 */ 9., 0., 0., /* b1 */
        ];
        let s = lin(&[0.0, 2.0], &out, 3, Interpolation::CubicSpline);
        assert!((s.sample(1.0, false).x - 1.0).abs() < 1e-6);
        // u = 0.25: h00 = 0.84375, h10 = 0.140625, h01 = 0.15625, h11 = -0.046875
        // p = 2*2*0.140625 + 0.15625 = 0.71875.
        assert!((s.sample(0.5, false).x - 0.71875).abs() < 1e-6);
        // At the keys: the values, not the tangents.
        assert_eq!(s.sample(0.0, false).x, 0.0);
        assert_eq!(s.sample(2.0, false).x, 1.0);
    }

    #[test]
    fn bad_keyframes_are_rejected() {
        assert!(Sampler::new(vec![], vec![], 3, Interpolation::Linear).is_err());
        assert!(Sampler::new(vec![1.0, 0.0], vec![0.0; 6], 3, Interpolation::Linear).is_err());
        let e =
            Sampler::new(vec![0.0, 1.0], vec![0.0; 6], 3, Interpolation::CubicSpline).unwrap_err();
        assert!(e.to_string().contains("6 output elements"), "{e}");
    }

    #[test]
    fn blend_matrix_mixes_translations() {
        let mats = [
            Mat4::from_translation(Vec3::new(1.0, 0.0, 0.0)),
            Mat4::from_translation(Vec3::new(0.0, 2.0, 0.0)),
        ];
        let m = blend_matrix([0, 1, 0, 0], Vec4::new(0.25, 0.75, 0.0, 0.0), &mats).unwrap();
        assert!((m.transform_point3(Vec3::ZERO) - Vec3::new(0.25, 1.5, 0.0)).length() < 1e-6);
        assert!(blend_matrix([0; 4], Vec4::ZERO, &mats).is_none());
    }
}
