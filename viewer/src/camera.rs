//! The viewer's camera: one of the file's cameras exactly, or a free camera that orbits a target
//! point or flies, in the frame of the file's cameras ([`msth_player::path::Rig`]: centre, up and
//! horizontal axes, the cameras' intrinsics). The first orbit, pan, zoom or fly step after a file
//! camera continues from that camera's position and viewing direction (the page's `camera.js`
//! does the same).

use glam::Vec3;
use msth_core::Camera;
use msth_player::path::Rig;

/// Orbit (drag turns the view about a target point) or fly (drag turns the view in place,
/// keys move the eye).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    Orbit,
    Fly,
}

/// Radians of turn per pixel dragged.
const TURN_PER_PIXEL: f32 = 0.005;
/// Elevation limit (radians), short of straight up or down.
const MAX_PITCH: f32 = 1.5;

#[derive(Clone, Debug)]
pub struct ViewCamera {
    rig: Rig,
    /// The file camera shown as it is until the first move.
    fixed: Option<(usize, Camera)>,
    eye: Vec3,
    /// Viewing direction: azimuth about `up` from `e1`, elevation above the horizontal.
    yaw: f32,
    pitch: f32,
    /// Distance from the eye to the orbit target along the view.
    dist: f32,
    pub mode: Mode,
    /// Full-size intrinsics of the free camera.
    template: Camera,
}

impl ViewCamera {
    /// A free camera at the rig's default view (the cameras' mean elevation and distance).
    pub fn new(rig: Rig) -> Self {
        let template = rig.template;
        let mut c = ViewCamera {
            rig,
            fixed: None,
            eye: Vec3::ZERO,
            yaw: 0.0,
            pitch: 0.0,
            dist: 1.0,
            mode: Mode::Orbit,
            template,
        };
        let start = rig.view(0.0, rig.elevation, rig.radius);
        c.follow(&start);
        c
    }

    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// The file camera shown, if the view is one.
    pub fn file_camera(&self) -> Option<usize> {
        self.fixed.map(|(i, _)| i)
    }

    /// Shows file camera `index` exactly (resized to the view's size), continuing from it on
    /// the next move.
    pub fn jump(&mut self, index: usize, camera: &Camera) {
        let t = &self.template;
        let cam = if (camera.width, camera.height) == (t.width, t.height) {
            *camera
        } else {
            camera.resized(t.width, t.height)
        };
        self.follow(&cam);
        self.fixed = Some((index, cam));
    }

    /// Sets the free camera's pose from `cam`: its eye and viewing direction, the orbit target
    /// at the point of its view axis nearest the scene centre.
    fn follow(&mut self, cam: &Camera) {
        let eye = cam.center();
        let forward = (-cam.world_from_camera.z_axis.truncate())
            .try_normalize()
            .unwrap_or(-self.rig.e1);
        let along = (self.rig.center - eye)
            .dot(forward)
            .max(0.05 * self.rig.radius.max(1e-3));
        let r = &self.rig;
        self.eye = eye;
        self.dist = along;
        self.pitch = forward.dot(r.up).clamp(-1.0, 1.0).asin();
        self.yaw = forward.dot(r.e2).atan2(forward.dot(r.e1));
    }

    fn forward(&self) -> Vec3 {
        let r = &self.rig;
        self.pitch.cos() * (self.yaw.cos() * r.e1 + self.yaw.sin() * r.e2) + self.pitch.sin() * r.up
    }

    fn right(&self) -> Vec3 {
        self.forward()
            .cross(self.rig.up)
            .try_normalize()
            .unwrap_or(self.rig.e2)
    }

    fn target(&self) -> Vec3 {
        self.eye + self.dist * self.forward()
    }

    /// Drag by `(dx, dy)` pixels: orbit about the target, or turn in place when flying.
    pub fn turn(&mut self, dx: f32, dy: f32) {
        let target = self.target();
        self.fixed = None;
        self.yaw += dx * TURN_PER_PIXEL;
        self.pitch = (self.pitch + dy * TURN_PER_PIXEL).clamp(-MAX_PITCH, MAX_PITCH);
        if self.mode == Mode::Orbit {
            self.eye = target - self.dist * self.forward();
        }
    }

    /// Moves the eye and the target sideways by `(dx, dy)` pixels of the view.
    pub fn pan(&mut self, dx: f32, dy: f32) {
        self.fixed = None;
        // One pixel at the target's distance.
        let px = self.dist / self.template.fx.max(1e-3);
        let up = self.right().cross(self.forward());
        self.eye += px * (-dx * self.right() + dy * up);
    }

    /// Zooms by `steps` wheel steps: towards the target when orbiting, forward when flying.
    pub fn zoom(&mut self, steps: f32) {
        self.fixed = None;
        let factor = 0.9f32.powf(steps);
        match self.mode {
            Mode::Orbit => {
                let target = self.target();
                self.dist =
                    (self.dist * factor).clamp(1e-3 * self.rig.radius, 1e3 * self.rig.radius);
                self.eye = target - self.dist * self.forward();
            }
            Mode::Fly => self.fly(Vec3::new(0.0, 0.0, steps * 0.1 * self.rig.radius)),
        }
    }

    /// Moves the eye by `(right, up, forward)` world units (the target moves along).
    pub fn fly(&mut self, by: Vec3) {
        self.fixed = None;
        self.eye += by.x * self.right() + by.y * self.rig.up + by.z * self.forward();
    }

    /// World units per second of a fly key at normal speed.
    pub fn fly_speed(&self) -> f32 {
        0.5 * self.rig.radius
    }

    /// The full-size camera of the view.
    pub fn camera(&self) -> Camera {
        if let Some((_, c)) = self.fixed {
            return c;
        }
        let t = &self.template;
        let mut cam = Camera::look_at(t.width, t.height, 1.0, self.eye, self.target(), self.rig.up);
        cam.fx = t.fx;
        cam.fy = t.fy;
        cam.cx = t.cx;
        cam.cy = t.cy;
        cam
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use msth_core::SceneBounds;

    fn rig() -> (Rig, Vec<Camera>) {
        let cams: Vec<Camera> = (0..3)
            .map(|k| {
                let a = k as f32 * 0.7;
                Camera::look_at(
                    40,
                    30,
                    0.8,
                    Vec3::new(4.0 * a.cos(), 4.0 * a.sin(), 1.5),
                    Vec3::new(0.1, 0.0, 0.0),
                    Vec3::Z,
                )
            })
            .collect();
        (
            Rig::new(&SceneBounds::dnerf_default(), &cams, cams[0]),
            cams,
        )
    }

    #[test]
    fn a_file_camera_is_shown_exactly_and_moves_continue_from_it() {
        let (rig, cams) = rig();
        let mut v = ViewCamera::new(rig);
        v.jump(1, &cams[1]);
        assert_eq!(v.camera(), cams[1]);
        assert_eq!(v.file_camera(), Some(1));
        // A zero turn leaves the eye and the viewing direction where they were.
        v.turn(0.0, 0.0);
        assert_eq!(v.file_camera(), None);
        let c = v.camera();
        assert!((c.center() - cams[1].center()).length() < 1e-4);
        let fwd = |c: &Camera| -c.world_from_camera.z_axis.truncate();
        assert!((fwd(&c) - fwd(&cams[1])).length() < 1e-4);
    }

    #[test]
    fn orbit_keeps_the_distance_to_the_target_and_fly_keeps_the_eye() {
        let (rig, _) = rig();
        let mut v = ViewCamera::new(rig);
        let target = v.target();
        let d = (v.camera().center() - target).length();
        v.turn(120.0, -40.0);
        assert!(((v.camera().center() - target).length() - d).abs() < 1e-3);
        assert!((v.target() - target).length() < 1e-3);
        v.mode = Mode::Fly;
        let eye = v.camera().center();
        v.turn(50.0, 10.0);
        assert!((v.camera().center() - eye).length() < 1e-5);
        v.fly(Vec3::new(0.0, 0.0, 1.0));
        assert!(((v.camera().center() - eye).length() - 1.0).abs() < 1e-4);
        let before = v.camera().center();
        v.mode = Mode::Orbit;
        v.zoom(2.0);
        assert!((v.camera().center() - before).length() > 1e-3);
    }
}
