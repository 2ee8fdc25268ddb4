//! Scripted input (`msth view --script FILE.json`): a list of steps that the viewer plays into its
//! own event loop as if a person used it. Input steps become egui input events (pointer moves and
//! buttons, keys, the wheel) added to the window's own events of the frame, so that they take
//! the same path as real input; the other steps wait for the viewer or act on it. For tests,
//! demonstrations and benchmarks.
//!
//! ```json
//! {"steps": [
//!   {"wait_still": 60},
//!   {"key": "3"},
//!   {"drag": {"from": [0.5, 0.5], "to": [0.7, 0.45], "steps": 10}},
//!   {"drag": {"from": [0.5, 0.5], "to": [0.5, 0.6], "button": "right"}},
//!   {"scroll": 2},
//!   {"hold": {"key": "W", "seconds": 0.2}},
//!   {"seek": 0.5},
//!   {"wait": 0.5},
//!   {"wait_frames": 3},
//!   {"screenshot": {"frame": "a.png", "window": "a-window.png"}},
//!   {"bench": {"frames": 20}},
//!   {"quit": true}
//! ]}
//! ```
//!
//! Positions are fractions of the picture's rectangle in the window (`[0, 0]` top left); key
//! names are egui's (`"Space"`, `"ArrowLeft"`, `"A"`, `"3"`, `"F12"`); `wait_still` waits (at most
//! the given seconds) until the view is drawn at full size for the current camera, time and
//! settings; `bench` draws the timeline's model frames one after the other as fast as they come,
//! from the current camera at full size, and reports the frame rate.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::ViewError;

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Script {
    pub steps: Vec<Step>,
}

#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum Button {
    #[default]
    Left,
    Right,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Drag {
    pub from: [f32; 2],
    pub to: [f32; 2],
    /// Pointer moves between the press and the release, one per frame.
    #[serde(default = "default_drag_steps")]
    pub steps: usize,
    #[serde(default)]
    pub button: Button,
}

fn default_drag_steps() -> usize {
    8
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Hold {
    pub key: String,
    pub seconds: f64,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Shot {
    /// The picture as rendered, at its own size.
    pub frame: Option<PathBuf>,
    /// The whole window, controls included.
    pub window: Option<PathBuf>,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bench {
    pub frames: usize,
}

#[derive(Clone, Debug, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Step {
    Wait(f64),
    WaitFrames(usize),
    WaitStill(f64),
    Key(String),
    Hold(Hold),
    Drag(Drag),
    Scroll(f32),
    Seek(f32),
    Screenshot(Shot),
    Bench(Bench),
    Quit(bool),
}

impl Script {
    pub fn load(path: &Path) -> Result<Script, ViewError> {
        let bad = |message: String| ViewError::Script {
            path: path.to_path_buf(),
            message,
        };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let script: Script = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        for (i, s) in script.steps.iter().enumerate() {
            let key = match s {
                Step::Key(k) => Some(k),
                Step::Hold(h) => Some(&h.key),
                _ => None,
            };
            if let Some(k) = key {
                if egui::Key::from_name(k).is_none() {
                    return Err(bad(format!("steps[{i}]: no key named {k:?}")));
                }
            }
            match s {
                Step::Drag(d) if d.steps == 0 => {
                    return Err(bad(format!("steps[{i}]: a drag needs at least one step")))
                }
                Step::Bench(b) if b.frames == 0 => {
                    return Err(bad(format!("steps[{i}]: bench needs at least one frame")))
                }
                Step::Wait(s) | Step::WaitStill(s) if !(s.is_finite() && *s >= 0.0) => {
                    return Err(bad(format!(
                        "steps[{i}]: seconds must be a finite number >= 0"
                    )))
                }
                _ => {}
            }
        }
        Ok(script)
    }
}

/// egui's events for pressing (and releasing) `key`.
pub fn key_events(key: egui::Key, pressed: bool) -> egui::Event {
    egui::Event::Key {
        key,
        physical_key: Some(key),
        pressed,
        repeat: false,
        modifiers: egui::Modifiers::NONE,
    }
}

/// The events of frame `k` (0-based) of a drag over `rect`: press at the start, one move per
/// frame, release after the last move. `None` once the drag is over.
pub fn drag_events(d: &Drag, k: usize, rect: egui::Rect) -> Option<Vec<egui::Event>> {
    let at = |f: [f32; 2]| rect.min + egui::vec2(f[0] * rect.width(), f[1] * rect.height());
    let button = match d.button {
        Button::Left => egui::PointerButton::Primary,
        Button::Right => egui::PointerButton::Secondary,
    };
    let press = |pos, pressed| egui::Event::PointerButton {
        pos,
        button,
        pressed,
        modifiers: egui::Modifiers::NONE,
    };
    let (a, b) = (at(d.from), at(d.to));
    let n = d.steps;
    Some(match k {
        0 => vec![egui::Event::PointerMoved(a), press(a, true)],
        k if k <= n => {
            let f = k as f32 / n as f32;
            vec![egui::Event::PointerMoved(a + f * (b - a))]
        }
        k if k == n + 1 => vec![press(b, false)],
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scripts_parse_and_bad_ones_say_where() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.json");
        std::fs::write(
            &p,
            r#"{"steps": [{"wait_still": 5}, {"key": "Space"}, {"drag": {"from": [0.1, 0.2], "to": [0.3, 0.4]}},
                {"hold": {"key": "W", "seconds": 0.1}}, {"screenshot": {"frame": "a.png"}}, {"quit": true}]}"#,
        )
        .unwrap();
        let s = Script::load(&p).unwrap();
        assert_eq!(s.steps.len(), 6);
        for bad in [
            r#"{"steps": [{"key": "NoSuchKey"}]}"#,
            r#"{"steps": [{"fly": 1}]}"#,
            r#"{"steps": [{"drag": {"from": [0, 0], "to": [1, 1], "steps": 0}}]}"#,
        ] {
            std::fs::write(&p, bad).unwrap();
            let e = Script::load(&p).unwrap_err().to_string();
            assert!(e.contains("s.json"), "{e}");
        }
    }

    #[test]
    fn a_drag_presses_moves_and_releases() {
        let d = Drag {
            from: [0.0, 0.5],
            to: [1.0, 0.5],
            steps: 2,
            button: Button::Left,
        };
        let rect = egui::Rect::from_min_size(egui::pos2(10.0, 10.0), egui::vec2(100.0, 50.0));
        let frames: Vec<_> = (0..).map_while(|k| drag_events(&d, k, rect)).collect();
        assert_eq!(frames.len(), 4);
        assert!(matches!(
            frames[0][1],
            egui::Event::PointerButton { pressed: true, .. }
        ));
        assert!(
            matches!(frames[2][0], egui::Event::PointerMoved(p) if p == egui::pos2(110.0, 35.0))
        );
        assert!(matches!(
            frames[3][0],
            egui::Event::PointerButton { pressed: false, .. }
        ));
    }
}
