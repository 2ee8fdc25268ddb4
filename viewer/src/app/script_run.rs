//! Scripted input (`msth view --script`): the step running now, and how each step is played
//! into the window (keys, drags, waits, screenshots, benches).

use std::sync::{mpsc, Arc};

use egui::Key;

use super::output::BenchRun;
use super::{App, Wake};
use crate::script::{self, Script};
use crate::ViewError;

#[derive(Default)]
pub(super) enum Running {
    #[default]
    Next,
    Until(f64),
    Frames(usize),
    Still(f64),
    Hold {
        key: Key,
        until: f64,
    },
    Drag {
        drag: script::Drag,
        k: usize,
    },
    Shot,
    Bench,
}

pub(super) struct ScriptRun {
    pub(super) script: Script,
    pub(super) index: usize,
    pub(super) running: Running,
}

impl App {
    /// Advances the script by what can be done in this frame.
    pub(super) fn run_script(&mut self, now: f64) -> Result<(), ViewError> {
        let Some(mut run) = self.script.take() else {
            return Ok(());
        };
        let result = self.script_steps(&mut run, now);
        if run.index < run.script.steps.len() {
            self.script = Some(run);
        }
        result
    }

    fn script_steps(&mut self, run: &mut ScriptRun, now: f64) -> Result<(), ViewError> {
        loop {
            let step_no = run.index;
            let Some(step) = run.script.steps.get(step_no).cloned() else {
                return Ok(());
            };
            let fail = |message: String| ViewError::ScriptStep {
                step: step_no,
                message,
            };
            match std::mem::take(&mut run.running) {
                Running::Next => {
                    run.running = match step {
                        script::Step::Wait(s) => Running::Until(now + s),
                        script::Step::WaitFrames(n) => {
                            Running::Frames(self.report.frames.len() + n)
                        }
                        script::Step::WaitStill(s) => Running::Still(now + s),
                        script::Step::Key(k) => {
                            let key = Key::from_name(&k).ok_or_else(|| fail(format!("key {k}")))?;
                            self.events.push(script::key_events(key, true));
                            self.events.push(script::key_events(key, false));
                            run.index += 1;
                            // One key per frame: its effect shows before the next step.
                            return Ok(());
                        }
                        script::Step::Hold(h) => {
                            let key = Key::from_name(&h.key)
                                .ok_or_else(|| fail(format!("key {}", h.key)))?;
                            self.events.push(script::key_events(key, true));
                            Running::Hold {
                                key,
                                until: now + h.seconds,
                            }
                        }
                        script::Step::Drag(d) => Running::Drag { drag: d, k: 0 },
                        script::Step::Scroll(lines) => {
                            let rect = self
                                .picture_rect
                                .ok_or_else(|| fail("no picture to scroll over yet".into()))?;
                            self.events.push(egui::Event::PointerMoved(rect.center()));
                            self.events.push(egui::Event::MouseWheel {
                                unit: egui::MouseWheelUnit::Line,
                                delta: egui::vec2(0.0, lines),
                                phase: egui::TouchPhase::Move,
                                source: egui::MouseWheelSource::Unknown,
                                modifiers: egui::Modifiers::NONE,
                            });
                            run.index += 1;
                            return Ok(());
                        }
                        script::Step::Seek(t) => {
                            self.timeline.seek(t);
                            run.index += 1;
                            continue;
                        }
                        script::Step::Screenshot(shot) => {
                            let (tx, rx) = mpsc::channel();
                            let proxy = self.proxy.clone();
                            self.shot = Some((shot, rx));
                            self.pending_capture = Some(egui::ScreenshotCallback::new(
                                move |img: Arc<egui::ColorImage>| {
                                    let _ = tx.send(img);
                                    let _ = proxy.send_event(Wake);
                                },
                            ));
                            Running::Shot
                        }
                        script::Step::Bench(b) => {
                            self.timeline.playing = false;
                            self.bench = Some(BenchRun {
                                frames: b.frames,
                                sent: 0,
                                done: 0,
                                started: None,
                                render_seconds: 0.0,
                                window_seconds: 0.0,
                                size: (0, 0),
                            });
                            Running::Bench
                        }
                        script::Step::Quit(q) => {
                            self.quit |= q;
                            run.index += 1;
                            return Ok(());
                        }
                    };
                    // The step has started: see at once whether it is already over.
                    continue;
                }
                Running::Until(t) if now >= t => {}
                Running::Frames(n) if self.report.frames.len() >= n => {}
                Running::Still(deadline) => {
                    if !self.settled(now) {
                        if now > deadline {
                            return Err(fail(format!(
                                "the view was not drawn at full size within {:.1} s",
                                match step {
                                    script::Step::WaitStill(s) => s,
                                    _ => 0.0,
                                }
                            )));
                        }
                        run.running = Running::Still(deadline);
                        return Ok(());
                    }
                }
                Running::Hold { key, until } => {
                    if now < until {
                        run.running = Running::Hold { key, until };
                        return Ok(());
                    }
                    self.events.push(script::key_events(key, false));
                }
                Running::Drag { drag, k } => {
                    let rect = self
                        .picture_rect
                        .ok_or_else(|| fail("no picture to drag on yet".into()))?;
                    if let Some(ev) = script::drag_events(&drag, k, rect) {
                        self.events.extend(ev);
                        run.running = Running::Drag { drag, k: k + 1 };
                        return Ok(());
                    }
                }
                Running::Shot if self.shot.is_some() => {
                    run.running = Running::Shot;
                    return Ok(());
                }
                Running::Bench if self.bench.is_some() => {
                    run.running = Running::Bench;
                    return Ok(());
                }
                Running::Shot | Running::Bench => {}
                other => {
                    run.running = other;
                    return Ok(());
                }
            }
            run.index += 1;
        }
    }
}
