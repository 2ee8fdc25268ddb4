//! The keys: what each one does (the panel's help), the fly keys, the speed and sample steps,
//! and how key presses change the view, the timeline and the controls.

use egui::Key;

use super::ui::UiAction;
use super::App;
use crate::camera::Mode;

/// Fly keys: right, up, forward.
pub(super) const FLY_KEYS: [(Key, [f32; 3]); 6] = [
    (Key::W, [0.0, 0.0, 1.0]),
    (Key::S, [0.0, 0.0, -1.0]),
    (Key::A, [-1.0, 0.0, 0.0]),
    (Key::D, [1.0, 0.0, 0.0]),
    (Key::E, [0.0, 1.0, 0.0]),
    (Key::Q, [0.0, -1.0, 0.0]),
];

/// The keys and what they do (also the panel's help).
pub const KEYS: &[(&str, &str)] = &[
    ("drag", "orbit (fly mode: look around)"),
    ("right-drag, shift-drag", "pan"),
    ("wheel", "zoom (fly mode: forward and back)"),
    (
        "W A S D, Q E",
        "fly forward, left, back, right, down, up (shift: faster)",
    ),
    ("F", "orbit or fly mode"),
    ("0-9, C", "jump to file camera N, to the next one"),
    ("space", "play or pause"),
    ("left, right", "one model frame back or forward"),
    ("home", "to the start"),
    ("L", "loop on or off"),
    ("-, +", "half or twice the speed"),
    ("M", "samples per ray: file, full, fast, faster"),
    ("V", "exact field or play-time volume"),
    ("P, F12", "screenshot (the picture and the window)"),
    ("R", "record the camera path, again to stop and save it"),
    ("H", "hide or show the controls"),
    ("esc", "quit"),
];

pub(super) const SPEEDS: [f32; 7] = [0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0];
/// The samples menu and the M key: the file's play-time counts, then the levels.
pub(super) const SAMPLE_CHOICES: [msth_core::config::PlaySamples; 4] = {
    use msth_core::config::{PlaySamples, SampleLevel};
    [
        PlaySamples::File,
        PlaySamples::Level(SampleLevel::Full),
        PlaySamples::Level(SampleLevel::Fast),
        PlaySamples::Level(SampleLevel::Faster),
    ]
};

impl App {
    pub(super) fn keys(&mut self, ctx: &egui::Context, dt: f64, actions: &mut Vec<UiAction>) {
        if ctx.egui_wants_keyboard_input() {
            return;
        }
        let pressed = |k: Key| ctx.input(|i| i.key_pressed(k));
        if pressed(Key::Space) {
            self.timeline.playing = !self.timeline.playing;
            if self.timeline.playing && self.timeline.t >= 1.0 && !self.timeline.looping {
                self.timeline.t = 0.0;
            }
        }
        if pressed(Key::ArrowLeft) {
            self.timeline.step_to(self.timeline.frame() as isize - 1);
        }
        if pressed(Key::ArrowRight) {
            self.timeline.step_to(self.timeline.frame() as isize + 1);
        }
        if pressed(Key::Home) {
            self.timeline.seek(0.0);
        }
        if pressed(Key::L) {
            self.timeline.looping = !self.timeline.looping;
        }
        if pressed(Key::Minus) {
            self.timeline.speed = (self.timeline.speed / 2.0).max(SPEEDS[0]);
        }
        if pressed(Key::Plus) || pressed(Key::Equals) {
            self.timeline.speed = (self.timeline.speed * 2.0).min(SPEEDS[SPEEDS.len() - 1]);
        }
        const DIGITS: [Key; 10] = [
            Key::Num0,
            Key::Num1,
            Key::Num2,
            Key::Num3,
            Key::Num4,
            Key::Num5,
            Key::Num6,
            Key::Num7,
            Key::Num8,
            Key::Num9,
        ];
        for (i, k) in DIGITS.iter().enumerate() {
            if pressed(*k) {
                self.jump(i);
            }
        }
        if pressed(Key::C) && !self.cameras.is_empty() {
            let next = self
                .view
                .file_camera()
                .map_or(0, |i| (i + 1) % self.cameras.len());
            self.jump(next);
        }
        if pressed(Key::F) {
            self.view.mode = match self.view.mode {
                Mode::Orbit => Mode::Fly,
                Mode::Fly => Mode::Orbit,
            };
        }
        if pressed(Key::M) {
            let i = SAMPLE_CHOICES
                .iter()
                .position(|s| *s == self.controls.samples)
                .map_or(0, |i| (i + 1) % SAMPLE_CHOICES.len());
            self.controls.samples = SAMPLE_CHOICES[i];
        }
        if pressed(Key::V) && self.volumes {
            self.set_volume(!self.controls.volume);
        }
        if pressed(Key::P) || pressed(Key::F12) {
            actions.push(UiAction::Shot);
        }
        if pressed(Key::R) {
            actions.push(UiAction::Record);
        }
        if pressed(Key::H) {
            self.show_panel = !self.show_panel;
        }
        if pressed(Key::Escape) {
            actions.push(UiAction::Quit);
        }
        // Fly keys, held.
        let (shift, held): (bool, Vec<[f32; 3]>) = ctx.input(|i| {
            (
                i.modifiers.shift,
                FLY_KEYS
                    .iter()
                    .filter(|(k, _)| i.key_down(*k))
                    .map(|(_, v)| *v)
                    .collect(),
            )
        });
        if !held.is_empty() {
            let speed = self.view.fly_speed() * if shift { 4.0 } else { 1.0 } * dt as f32;
            let mut by = glam::Vec3::ZERO;
            for v in held {
                by += glam::Vec3::from(v);
            }
            self.view.fly(by * speed);
        }
    }

    pub(super) fn jump(&mut self, i: usize) {
        if let Some(c) = self.cameras.get(i) {
            let c = *c;
            self.view.jump(i, &c);
        }
    }
}
