//! Camera paths for playback: where the camera is at each output frame.
//!
//! Specs (`msth play --path SPEC`):
//! - `N`: the file's playback camera `N`, fixed (incremental rendering applies);
//! - `view:AZ,EL,DIST`: a fixed free viewpoint, azimuth and elevation in degrees and a distance,
//!   around the scene centre in the frame of the file's cameras (see [`Rig`]);
//! - `orbit`: one turn around the scene at the cameras' mean elevation and distance (for a
//!   forward-facing, contracted scene: back and forth across the cameras' azimuth span, since
//!   nothing behind them was ever seen);
//! - `spiral`: the orbit with the elevation and distance swinging around their means;
//! - `cameras`: the file's cameras in turn, one per frame;
//! - a JSON file: `{"frames": [{"transform_matrix": 4x4 rows, "time": t, "fl_x" | "camera_angle_x",
//!   "fl_y", "cx", "cy", "w", "h"}, ...]}` (a bare list works too); each entry is one frame, `time`
//!   optional (the time range is used where it is missing), intrinsics optional (the first file
//!   camera's are used).

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3};
use msth_core::{Camera, SceneBounds};
use serde::Deserialize;

/// The frame the orbit-like paths turn in: centre, up and the horizontal axes, with the mean
/// distance and elevation of the file's cameras.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rig {
    pub center: Vec3,
    pub up: Vec3,
    /// Horizontal unit axes: `e1` points towards the first camera.
    pub e1: Vec3,
    pub e2: Vec3,
    pub radius: f32,
    /// Radians above the horizontal plane.
    pub elevation: f32,
    /// Azimuth span of the cameras (radians, around `e1`), for forward-facing scenes.
    pub azimuth_span: (f32, f32),
    pub forward_facing: bool,
    /// Intrinsics of the path's cameras.
    pub template: Camera,
}

impl Rig {
    /// The rig of a file: its bounds and playback cameras (any may be missing).
    pub fn new(bounds: &SceneBounds, cameras: &[Camera], template: Camera) -> Self {
        let (lo, hi) = bounds.extent();
        let (center, forward_facing) = match *bounds {
            SceneBounds::Box { .. } => (0.5 * (lo + hi), false),
            SceneBounds::Contracted { center, .. } => (center, true),
        };
        let up = snap_to_axis(
            cameras
                .iter()
                .map(|c| c.world_from_camera.y_axis.truncate())
                .sum::<Vec3>()
                .try_normalize()
                .unwrap_or(Vec3::Z),
        );
        let offsets: Vec<Vec3> = cameras
            .iter()
            .map(|c| c.center() - center)
            .filter(|v| v.length() > 1e-6)
            .collect();
        let radius = if offsets.is_empty() {
            2.0 * (hi - lo).length().clamp(1e-3, 1e3)
        } else {
            offsets.iter().map(|v| v.length()).sum::<f32>() / offsets.len() as f32
        };
        let elevation = if offsets.is_empty() {
            0.5
        } else {
            offsets
                .iter()
                .map(|v| (v.normalize().dot(up)).clamp(-1.0, 1.0).asin())
                .sum::<f32>()
                / offsets.len() as f32
        };
        let horizontal = |v: Vec3| (v - up * v.dot(up)).try_normalize();
        let e1 = offsets
            .first()
            .and_then(|&v| horizontal(v))
            .or_else(|| horizontal(Vec3::X))
            .or_else(|| horizontal(Vec3::Y))
            .unwrap_or(Vec3::X);
        let e2 = up.cross(e1);
        let az = |v: Vec3| v.dot(e2).atan2(v.dot(e1));
        let span = offsets.iter().fold((0f32, 0f32), |(a, b), &v| {
            let x = az(v);
            (a.min(x), b.max(x))
        });
        Rig {
            center,
            up,
            e1,
            e2,
            radius,
            elevation,
            azimuth_span: span,
            forward_facing,
            template,
        }
    }

    /// The camera at azimuth and elevation (radians) and distance, looking at the centre.
    pub fn view(&self, azimuth: f32, elevation: f32, distance: f32) -> Camera {
        let dir = elevation.cos() * (azimuth.cos() * self.e1 + azimuth.sin() * self.e2)
            + elevation.sin() * self.up;
        let eye = self.center + distance * dir;
        let mut cam = Camera::look_at(
            self.template.width,
            self.template.height,
            1.0,
            eye,
            self.center,
            self.up,
        );
        cam.fx = self.template.fx;
        cam.fy = self.template.fy;
        cam.cx = self.template.cx;
        cam.cy = self.template.cy;
        cam
    }
}

/// The world axis (+-X, +-Y, +-Z) within 30 degrees of `v`, else `v`: cameras that look down at
/// a scene have tilted up vectors, while captures are almost always levelled on a world axis.
fn snap_to_axis(v: Vec3) -> Vec3 {
    let axes = [Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X, -Vec3::Y, -Vec3::Z];
    let best = axes
        .into_iter()
        .max_by(|a, b| a.dot(v).total_cmp(&b.dot(v)))
        .unwrap_or(Vec3::Z);
    if best.dot(v) >= 30f32.to_radians().cos() {
        best
    } else {
        v
    }
}

/// Where the camera is at each frame.
#[derive(Clone, Debug, PartialEq)]
pub enum CameraPath {
    Fixed(Camera),
    Orbit(Rig),
    Spiral(Rig),
    Cameras(Vec<Camera>),
    /// One entry per frame, with an optional time.
    Keyframes(Vec<(Camera, Option<f32>)>),
}

#[derive(Deserialize)]
#[serde(untagged)]
enum PathFile {
    Object { frames: Vec<KeyframeJson> },
    List(Vec<KeyframeJson>),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyframeJson {
    transform_matrix: [[f32; 4]; 4],
    time: Option<f32>,
    fl_x: Option<f32>,
    fl_y: Option<f32>,
    camera_angle_x: Option<f32>,
    cx: Option<f32>,
    cy: Option<f32>,
    w: Option<u32>,
    h: Option<u32>,
}

/// Why a `--path` spec is not a camera path. Each message names the spec or the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum PathError {
    #[error("--path {index}: the file has {count} cameras (0..{})", count.saturating_sub(1))]
    NoSuchCamera { index: usize, count: usize },
    #[error("--path cameras: the file has no cameras")]
    NoCameras,
    #[error("--path {spec}: expected view:AZ,EL,DIST (numbers)")]
    ViewNotNumbers { spec: String },
    #[error("--path {spec}: expected view:AZ,EL,DIST with finite numbers and DIST > 0")]
    BadView { spec: String },
    #[error(
        "--path {}: not a camera index, view:, orbit, spiral, cameras or a readable JSON file ({source})",
        path.display()
    )]
    Unreadable {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: malformed path JSON: {message}", path.display())]
    Json { path: PathBuf, message: String },
    #[error("{}: a path needs 1 to {MAX_KEYFRAMES} frames, found {found}", path.display())]
    FrameCount { path: PathBuf, found: usize },
    #[error("{}: frames[{index}]: {message}", path.display())]
    Frame {
        path: PathBuf,
        index: usize,
        message: String,
    },
}

/// Most frames a JSON path may hold.
const MAX_KEYFRAMES: usize = 1 << 20;

impl CameraPath {
    /// Parses a `--path` spec (see the module docs). `cameras` are the file's playback cameras,
    /// `size` overrides every camera's image size.
    pub fn parse(
        spec: &str,
        bounds: &SceneBounds,
        cameras: &[Camera],
        size: Option<(u32, u32)>,
    ) -> Result<Self, PathError> {
        let sized = |c: &Camera| match size {
            Some((w, h)) => c.resized(w, h),
            None => *c,
        };
        let template = sized(
            &cameras
                .first()
                .copied()
                .unwrap_or_else(|| Camera::from_fov_x(256, 256, 0.8, Mat4::IDENTITY)),
        );
        let rig = || Rig::new(bounds, cameras, template);
        if let Ok(i) = spec.parse::<usize>() {
            let c = cameras.get(i).ok_or(PathError::NoSuchCamera {
                index: i,
                count: cameras.len(),
            })?;
            return Ok(CameraPath::Fixed(sized(c)));
        }
        match spec {
            "orbit" => return Ok(CameraPath::Orbit(rig())),
            "spiral" => return Ok(CameraPath::Spiral(rig())),
            "cameras" if cameras.is_empty() => return Err(PathError::NoCameras),
            "cameras" => return Ok(CameraPath::Cameras(cameras.iter().map(sized).collect())),
            _ => {}
        }
        if let Some(rest) = spec.strip_prefix("view:") {
            let v: Vec<f32> = rest
                .split(',')
                .map(|s| s.trim().parse::<f32>())
                .collect::<Result<_, _>>()
                .map_err(|_| PathError::ViewNotNumbers {
                    spec: spec.to_string(),
                })?;
            if v.len() != 3 || !v.iter().all(|x| x.is_finite()) || v[2] <= 0.0 {
                return Err(PathError::BadView {
                    spec: spec.to_string(),
                });
            }
            let cam = rig().view(v[0].to_radians(), v[1].to_radians(), v[2]);
            return Ok(CameraPath::Fixed(cam));
        }
        Self::from_json(Path::new(spec), &template, size)
    }

    fn from_json(
        path: &Path,
        template: &Camera,
        size: Option<(u32, u32)>,
    ) -> Result<Self, PathError> {
        let owned = || path.to_path_buf();
        let text = match std::fs::read_to_string(path) {
            Ok(text) => text,
            Err(source) => {
                return Err(PathError::Unreadable {
                    path: owned(),
                    source,
                })
            }
        };
        let file: PathFile = serde_json::from_str(&text).map_err(|e| PathError::Json {
            path: owned(),
            message: e.to_string(),
        })?;
        let frames = match file {
            PathFile::Object { frames } | PathFile::List(frames) => frames,
        };
        if frames.is_empty() || frames.len() > MAX_KEYFRAMES {
            return Err(PathError::FrameCount {
                path: path.to_path_buf(),
                found: frames.len(),
            });
        }
        let mut out = Vec::with_capacity(frames.len());
        for (i, f) in frames.iter().enumerate() {
            let at = |message: String| PathError::Frame {
                path: path.to_path_buf(),
                index: i,
                message,
            };
            let pose = Mat4::from_cols_array_2d(&f.transform_matrix).transpose();
            let (w, h) = (
                f.w.unwrap_or(template.width),
                f.h.unwrap_or(template.height),
            );
            if w == 0 || h == 0 || w > 1 << 14 || h > 1 << 14 {
                return Err(at(format!("image size {w}x{h} outside 1..16384")));
            }
            let mut cam = match (f.fl_x, f.camera_angle_x) {
                (Some(fx), _) => Camera {
                    width: w,
                    height: h,
                    fx,
                    fy: f.fl_y.unwrap_or(fx),
                    cx: f.cx.unwrap_or(w as f32 / 2.0),
                    cy: f.cy.unwrap_or(h as f32 / 2.0),
                    world_from_camera: pose,
                },
                (None, Some(a)) => Camera::from_fov_x(w, h, a, pose),
                (None, None) => Camera {
                    world_from_camera: pose,
                    ..*template
                },
            };
            if let Some((w, h)) = size {
                cam = cam.resized(w, h);
            }
            cam.validate().map_err(|e| at(e.to_string()))?;
            if let Some(t) = f.time {
                if !(0.0..=1.0).contains(&t) {
                    return Err(at(format!("time {t} outside [0, 1]")));
                }
            }
            out.push((cam, f.time));
        }
        Ok(CameraPath::Keyframes(out))
    }

    /// Whether every frame uses the same camera (incremental rendering then applies).
    pub fn is_fixed(&self) -> bool {
        matches!(self, CameraPath::Fixed(_))
    }

    /// Frames the path itself defines (JSON paths), if any.
    pub fn frame_count(&self) -> Option<usize> {
        match self {
            CameraPath::Keyframes(k) => Some(k.len()),
            _ => None,
        }
    }

    /// Checks a path's `--time START:END` (both in `[0, 1]`) and `--size WxH` (sides at least 1,
    /// within `limits`: the bound of the file's own cameras, format.md §8), as `msth play` and
    /// `msth eval --path` take them.
    pub fn check_options(
        time: (f32, f32),
        size: Option<(u32, u32)>,
        limits: &msth_codec::Limits,
    ) -> Result<(), String> {
        let (t0, t1) = time;
        if !(t0.is_finite()
            && t1.is_finite()
            && (0.0..=1.0).contains(&t0)
            && (0.0..=1.0).contains(&t1))
        {
            return Err(format!("--time {t0}:{t1}: both ends must lie in [0, 1]"));
        }
        if let Some((w, h)) = size {
            if w == 0 || h == 0 {
                return Err(format!("--size {w}x{h}: sides must be at least 1"));
            }
            // The frame, the static cache and the rays all grow with the pixel count.
            limits
                .check_image("--size", w, h)
                .map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    /// How many frames to draw: the path file's own count, else `asked` (`--frames`), else
    /// `default`. An error naming `--frames` when `asked` disagrees with the file or the count is
    /// 0 or above `max`.
    pub fn frames(
        &self,
        asked: Option<usize>,
        default: usize,
        max: usize,
    ) -> Result<usize, String> {
        let n = match (self.frame_count(), asked) {
            (Some(k), Some(f)) if k != f => {
                return Err(format!("--frames {f}: the path file defines {k} frames"))
            }
            (Some(k), _) => k,
            (None, Some(f)) => f,
            (None, None) => default,
        };
        if n == 0 || n > max {
            return Err(format!("--frames {n}: between 1 and {max}"));
        }
        Ok(n)
    }

    /// The time of frame `i` of `n`: the path's own when it fixes one, else evenly over
    /// `(t0, t1)`, both ends included.
    pub fn frame_time(&self, i: usize, n: usize, (t0, t1): (f32, f32)) -> f32 {
        self.camera(i, n).1.unwrap_or(if n > 1 {
            t0 + (t1 - t0) * i as f32 / (n - 1) as f32
        } else {
            t0
        })
    }

    /// The camera of frame `i` of `n`, and the frame's time when the path fixes it.
    ///
    /// `orbit` and `spiral` are closed: frame `i` is at `i / n` of the way round, so a video of
    /// `n` frames loops without showing a pose twice (frame `n` would be frame 0). Around a
    /// forward-facing rig they sweep the cameras' arc there and back, which meets every pose
    /// twice; frame `i` is at `(i + 1/4) / n`, which never lands on a turning point or on
    /// another frame's pose. Two consecutive frames with the same pose would play as a camera
    /// that holds still for a frame: the player would hand that frame to the exact renderer's
    /// incremental cache at the cost of a full exact frame.
    pub fn camera(&self, i: usize, n: usize) -> (Camera, Option<f32>) {
        let closed_phase = |rig: &Rig| {
            let offset = if rig.forward_facing && n > 1 {
                0.25
            } else {
                0.0
            };
            (i as f32 + offset) / n.max(1) as f32
        };
        let turn = std::f32::consts::TAU;
        let sweep = |rig: &Rig, f: f32| {
            if rig.forward_facing {
                let (a, b) = rig.azimuth_span;
                // Back and forth across the span.
                a + (b - a) * (0.5 - 0.5 * (f * turn).cos())
            } else {
                f * turn
            }
        };
        match self {
            CameraPath::Fixed(c) => (*c, None),
            CameraPath::Orbit(rig) => {
                let f = closed_phase(rig);
                (rig.view(sweep(rig, f), rig.elevation, rig.radius), None)
            }
            CameraPath::Spiral(rig) => {
                let f = closed_phase(rig);
                let swing = (2.0 * f * turn).sin();
                let el = rig.elevation + 0.25 * swing;
                let dist = rig.radius * (1.0 + 0.1 * (f * turn).sin());
                (rig.view(sweep(rig, f), el, dist), None)
            }
            CameraPath::Cameras(cams) => (cams[i % cams.len()], None),
            CameraPath::Keyframes(k) => k[i.min(k.len() - 1)],
        }
    }
}

/// The JSON of a keyframe path that [`CameraPath::parse`] reads back as the same cameras and
/// times (`{"frames": [{"transform_matrix", "time", "fl_x", "fl_y", "cx", "cy", "w", "h"}]}`):
/// what `msth view` records for `msth play --path FILE.json`.
pub fn keyframes_json(frames: &[(Camera, Option<f32>)]) -> serde_json::Value {
    let frames: Vec<serde_json::Value> = frames
        .iter()
        .map(|(c, t)| {
            let mut f = serde_json::json!({
                "transform_matrix": c.world_from_camera.transpose().to_cols_array_2d(),
                "fl_x": c.fx,
                "fl_y": c.fy,
                "cx": c.cx,
                "cy": c.cy,
                "w": c.width,
                "h": c.height,
            });
            if let Some(t) = t {
                f["time"] = serde_json::json!(t);
            }
            f
        })
        .collect();
    serde_json::json!({ "frames": frames })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cams() -> Vec<Camera> {
        (0..4)
            .map(|k| {
                let a = k as f32 * 0.5;
                Camera::look_at(
                    40,
                    30,
                    0.8,
                    Vec3::new(4.0 * a.cos(), 4.0 * a.sin(), 1.0),
                    Vec3::ZERO,
                    Vec3::Z,
                )
            })
            .collect()
    }

    #[test]
    fn rig_recovers_centre_up_radius() {
        let c = cams();
        let rig = Rig::new(&SceneBounds::dnerf_default(), &c, c[0]);
        assert_eq!(rig.up, Vec3::Z);
        assert!((rig.radius - 17f32.sqrt()).abs() < 1e-4);
        // The view at azimuth 0 and the cameras' elevation is the first camera.
        let v = rig.view(0.0, rig.elevation, rig.radius);
        assert!((v.center() - c[0].center()).length() < 0.05);
    }

    #[test]
    fn specs_parse_and_fail_clearly() {
        let c = cams();
        let b = SceneBounds::dnerf_default();
        let p = CameraPath::parse("2", &b, &c, Some((64, 48))).unwrap();
        let (cam, t) = p.camera(5, 10);
        assert_eq!((cam.width, cam.height, t), (64, 48, None));
        assert!(p.is_fixed());
        assert!(CameraPath::parse("9", &b, &c, None)
            .unwrap_err()
            .to_string()
            .contains("4 cameras"));
        assert!(CameraPath::parse("view:1,2", &b, &c, None).is_err());
        assert!(CameraPath::parse("view:10,20,0", &b, &c, None).is_err());
        assert!(CameraPath::parse("view:10,20,3", &b, &c, None)
            .unwrap()
            .is_fixed());
        let orbit = CameraPath::parse("orbit", &b, &c, None).unwrap();
        let (a, _) = orbit.camera(0, 9);
        let (z, _) = orbit.camera(9, 9);
        assert!((a.center() - z.center()).length() < 1e-3, "a full turn");
        assert!(CameraPath::parse("no-such-file.json", &b, &c, None)
            .unwrap_err()
            .to_string()
            .contains("not a camera index"));
    }

    #[test]
    fn closed_paths_never_show_a_pose_twice() {
        let c = cams();
        let boxed = SceneBounds::dnerf_default();
        let facing = SceneBounds::Contracted {
            center: Vec3::ZERO,
            radius: 1.0,
        };
        for bounds in [boxed, facing] {
            for name in ["orbit", "spiral"] {
                let path = CameraPath::parse(name, &bounds, &c, None).unwrap();
                for n in 2..=48 {
                    let poses: Vec<Camera> = (0..n).map(|i| path.camera(i, n).0).collect();
                    for i in 0..n {
                        for j in i + 1..n {
                            let d = (poses[i].world_from_camera - poses[j].world_from_camera)
                                .abs()
                                .to_cols_array()
                                .into_iter()
                                .fold(0f32, f32::max);
                            assert!(d > 1e-4, "{name} over {bounds:?}, {n} frames: {i} and {j}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn json_paths_parse_and_validate() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("path.json");
        let id = "[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]";
        std::fs::write(
            &p,
            format!(
                r#"{{"frames":[{{"transform_matrix":{id},"time":0.25,"camera_angle_x":0.7,"w":32,"h":16}},
                   {{"transform_matrix":{id}}}]}}"#
            ),
        )
        .unwrap();
        let c = cams();
        let b = SceneBounds::dnerf_default();
        let path = CameraPath::parse(p.to_str().unwrap(), &b, &c, None).unwrap();
        assert_eq!(path.frame_count(), Some(2));
        let (cam, t) = path.camera(0, 2);
        assert_eq!((cam.width, cam.height, t), (32, 16, Some(0.25)));
        assert_eq!(path.camera(1, 2).0.width, 40);
        // What keyframes_json writes reads back as the same cameras and times.
        let frames = vec![(c[1], Some(0.5)), (c[2], None)];
        std::fs::write(&p, keyframes_json(&frames).to_string()).unwrap();
        let back = CameraPath::parse(p.to_str().unwrap(), &b, &c, None).unwrap();
        assert_eq!(back, CameraPath::Keyframes(frames));
        for bad in [
            r#"{"frames":[]}"#,
            r#"{"frames":[{"transform_matrix":[[1,0,0,0]]}]}"#,
            r#"[{"transform_matrix":[[0,0,0,0],[0,0,0,0],[0,0,0,0],[0,0,0,1]]}]"#,
            r#"[{"transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],"time":2}]"#,
            r#"[{"transform_matrix":[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]],"speed":2}]"#,
        ] {
            std::fs::write(&p, bad).unwrap();
            let e = CameraPath::parse(p.to_str().unwrap(), &b, &c, None)
                .unwrap_err()
                .to_string();
            assert!(e.contains("path.json"), "{e}");
        }
    }
}
