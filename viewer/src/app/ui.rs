//! The egui panel and the picture: the timeline bar, the controls, the picture with its overlay,
//! and the pointer's camera moves.

use egui::PointerButton;

use super::input::{KEYS, SAMPLE_CHOICES, SPEEDS};
use super::App;
use crate::camera::Mode;
use crate::worker::{VolumeInfo, VolumeStatus};

impl App {
    /// The controls and the picture; keys and pointer input on the picture move the camera.
    pub(super) fn ui(
        &mut self,
        ui: &mut egui::Ui,
        now: f64,
        dt: f64,
        picture: Option<(egui::TextureId, egui::TextureId, (u32, u32))>,
        adapter: &str,
        actions: &mut Vec<UiAction>,
    ) {
        let ctx = ui.ctx().clone();
        self.keys(&ctx, dt, actions);
        if self.show_panel {
            egui::Panel::top("timeline").show(ui, |ui| self.timeline_bar(ui));
            egui::Panel::right("controls")
                .default_size(280.0)
                .show(ui, |ui| self.controls_panel(ui, adapter, actions));
        }
        egui::CentralPanel::default()
            .frame(egui::Frame::NONE.fill(egui::Color32::from_gray(24)))
            .show(ui, |ui| self.picture(ui, now, picture));
    }

    fn timeline_bar(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            let label = if self.timeline.playing {
                "pause"
            } else {
                "play"
            };
            let b = ui.button(label);
            if b.clicked() {
                self.timeline.playing = !self.timeline.playing;
                // Space plays and pauses by itself: a focused button would take it too.
                b.surrender_focus();
            }
            let mut t = self.timeline.t;
            let slider = ui.add(
                egui::Slider::new(&mut t, 0.0..=1.0)
                    .text("time")
                    .fixed_decimals(3),
            );
            if slider.changed() {
                self.timeline.seek(t);
            }
            ui.label(format!(
                "frame {} / {}",
                self.timeline.frame(),
                self.timeline.frames.saturating_sub(1)
            ));
            ui.checkbox(&mut self.timeline.looping, "loop");
            egui::ComboBox::from_label("speed")
                .selected_text(format!("{}x", self.timeline.speed))
                .show_ui(ui, |ui| {
                    for s in SPEEDS {
                        ui.selectable_value(&mut self.timeline.speed, s, format!("{s}x"));
                    }
                });
        });
    }

    fn controls_panel(&mut self, ui: &mut egui::Ui, adapter: &str, actions: &mut Vec<UiAction>) {
        ui.heading(&self.name);
        ui.separator();
        ui.label("view");
        let selected = match self.view.file_camera() {
            Some(i) => format!("camera {i}"),
            None => "free".to_string(),
        };
        let mut jump = None;
        egui::ComboBox::from_id_salt("camera")
            .selected_text(selected)
            .show_ui(ui, |ui| {
                for i in 0..self.cameras.len() {
                    if ui
                        .selectable_label(self.view.file_camera() == Some(i), format!("camera {i}"))
                        .clicked()
                    {
                        jump = Some(i);
                    }
                }
            });
        if let Some(i) = jump {
            self.jump(i);
        }
        ui.horizontal(|ui| {
            ui.radio_value(&mut self.view.mode, Mode::Orbit, "orbit");
            ui.radio_value(&mut self.view.mode, Mode::Fly, "fly");
        });
        ui.separator();
        // Render settings: each control writes a field of `RenderControls` (worker.rs).
        ui.label("samples per ray");
        let meta = &self.stream.index().metadata;
        let model = meta.model.sampler.clone();
        let stored = meta
            .play_samples
            .map(|s| (s.proposal as usize, s.main as usize));
        let name = |s: msth_core::config::PlaySamples| {
            let (p, m) = s.counts(&model, stored);
            match s {
                msth_core::config::PlaySamples::Level(l) => format!("{} ({p} + {m})", l.name()),
                msth_core::config::PlaySamples::File => format!("file ({p} + {m})"),
                _ => format!("{p} + {m}"),
            }
        };
        egui::ComboBox::from_id_salt("samples")
            .selected_text(name(self.controls.samples))
            .show_ui(ui, |ui| {
                for s in SAMPLE_CHOICES {
                    ui.selectable_value(&mut self.controls.samples, s, name(s));
                }
            });
        if self.volumes {
            let mut on = self.controls.volume;
            let b = ui.checkbox(&mut on, "play-time volume (V)").on_hover_text(
                "Draw from a volume baked from the file (off: the exact field, the \
                     reference). The bake runs in the background; its quality depends on the \
                     scene (docs/viewer.md).",
            );
            if b.changed() {
                self.set_volume(on);
                // Space plays and pauses: a focused checkbox would take it too.
                b.surrender_focus();
            }
            if let Some(line) = self.volume_line() {
                ui.label(line);
            }
            match &self.volume {
                Some(VolumeStatus::Ready(VolumeInfo { note: Some(n), .. })) => {
                    ui.label(format!("note: {n}"));
                }
                Some(VolumeStatus::Failed(e)) => {
                    ui.colored_label(ui.visuals().warn_fg_color, format!("no volume: {e}"));
                }
                _ => {}
            }
        }
        ui.separator();
        if let Some(b) = &self.report.backend {
            ui.label(format!("renderer: {} ({})", b.kind, b.device));
            if let Some(n) = &b.note {
                ui.label(n);
            }
        } else {
            ui.label("renderer: starting…");
        }
        ui.label(format!("window: {adapter}"));
        ui.separator();
        ui.horizontal(|ui| {
            if ui.button("screenshot (P)").clicked() {
                actions.push(UiAction::Shot);
            }
            let rec = if self.recording.is_some() {
                "stop recording (R)"
            } else {
                "record path (R)"
            };
            if ui.button(rec).clicked() {
                actions.push(UiAction::Record);
            }
        });
        if !self.status.is_empty() {
            ui.label(&self.status);
        }
        ui.separator();
        egui::CollapsingHeader::new("keys")
            .default_open(false)
            .show(ui, |ui| {
                egui::Grid::new("keys").striped(true).show(ui, |ui| {
                    for (k, what) in KEYS {
                        ui.label(*k);
                        ui.label(*what);
                        ui.end_row();
                    }
                });
            });
    }

    /// The picture, the overlay, and the pointer's camera moves.
    fn picture(
        &mut self,
        ui: &mut egui::Ui,
        now: f64,
        picture: Option<(egui::TextureId, egui::TextureId, (u32, u32))>,
    ) {
        let t = self.view.rig().template;
        let avail = ui.available_rect_before_wrap();
        let ppp = ui.ctx().pixels_per_point();
        // Whole window pixels per rendered pixel where it fits, else scaled down.
        let fit =
            (avail.width() * ppp / t.width as f32).min(avail.height() * ppp / t.height as f32);
        let zoom = if fit >= 1.0 {
            fit.floor()
        } else {
            fit.max(0.01)
        };
        let size = egui::vec2(t.width as f32 * zoom, t.height as f32 * zoom) / ppp;
        let min = (avail.center() - 0.5 * size) * ppp;
        let min = egui::pos2(min.x.round(), min.y.round()) / ppp;
        let rect = egui::Rect::from_min_size(min, size);
        self.picture_rect = Some(rect);
        let response = ui.allocate_rect(rect, egui::Sense::click_and_drag());
        if let (Some((nearest, linear, _)), Some(s)) = (picture, &self.shown) {
            let crisp = s.job.step.divisor == 1 && zoom.fract() == 0.0;
            let id = if crisp { nearest } else { linear };
            ui.painter().image(
                id,
                rect,
                egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0)),
                egui::Color32::WHITE,
            );
        } else {
            ui.painter().text(
                rect.center(),
                egui::Align2::CENTER_CENTER,
                if self.buffering {
                    "loading…"
                } else {
                    "starting…"
                },
                egui::FontId::proportional(18.0),
                egui::Color32::LIGHT_GRAY,
            );
        }
        // Camera moves.
        let shift = ui.input(|i| i.modifiers.shift);
        let d = response.drag_delta() * ppp;
        if response.dragged_by(PointerButton::Primary) && !shift {
            self.view.turn(-d.x, -d.y);
        } else if response.dragged_by(PointerButton::Secondary)
            || (response.dragged_by(PointerButton::Primary) && shift)
        {
            self.view.pan(d.x, d.y);
        }
        if response.hovered() {
            // Wheel steps, from the events (egui's own scroll delta is smoothed over frames).
            let steps: f32 = ui.input(|i| {
                i.events
                    .iter()
                    .map(|e| match e {
                        egui::Event::MouseWheel { unit, delta, .. } => match unit {
                            egui::MouseWheelUnit::Line => delta.y,
                            egui::MouseWheelUnit::Page => 10.0 * delta.y,
                            egui::MouseWheelUnit::Point => delta.y / 50.0,
                        },
                        _ => 0.0,
                    })
                    .sum()
            });
            if steps != 0.0 {
                self.view.zoom(steps);
            }
        }
        self.overlay_rect = Some(self.overlay(ui, rect, now));
    }

    /// What the picture is drawn from and where the volume stands, once the switch has been
    /// used: `exact field · baking the volume 42%`, `volume 128³ (45.2 MB, baked in 3.1 s)`.
    fn volume_line(&self) -> Option<String> {
        if !self.volumes || (self.volume.is_none() && !self.controls.volume) {
            return None;
        }
        let from_volume = self.shown.as_ref().is_some_and(|s| s.frame.stats.volume);
        Some(match (&self.volume, from_volume) {
            (Some(VolumeStatus::Ready(v)), true) => format!(
                "volume {}³ ({}, baked in {:.1} s)",
                v.resolution,
                bytes(v.bytes),
                v.seconds
            ),
            (Some(VolumeStatus::Baking { fraction }), _) if *fraction >= 1.0 => {
                "exact field · baking the volume 100%, finishing".into()
            }
            (Some(VolumeStatus::Baking { fraction }), _) => format!(
                "exact field · baking the volume {:.0}%",
                (100.0 * fraction).floor()
            ),
            (Some(VolumeStatus::Ready(_)), false) if self.controls.volume => {
                "exact field · volume ready".into()
            }
            (Some(VolumeStatus::Ready(_)), false) => "exact field (V: the volume)".into(),
            _ => "exact field".into(),
        })
    }

    /// Draws the overlay over the picture's top left corner; returns where.
    fn overlay(&self, ui: &egui::Ui, rect: egui::Rect, now: f64) -> egui::Rect {
        let mut lines = Vec::new();
        let fps = self.recent.len();
        let last = self.shown.as_ref();
        lines.push(match last {
            Some(s) => format!("{fps} fps · {:.1} ms/frame", 1e3 * s.frame.stats.seconds),
            None => "– fps".into(),
        });
        if let Some(s) = last {
            let st = &s.frame.stats;
            let why = if s.job.step.divisor == 1 {
                if st.full {
                    "full".to_string()
                } else {
                    "full, incremental".to_string()
                }
            } else {
                format!("1/{}, {}", s.job.step.divisor, s.job.step.activity.name())
            };
            lines.push(format!("{}x{} ({why})", s.frame.width, s.frame.height));
            lines.push(format!(
                "re-rendered {:.1}% of the pixels",
                100.0 * st.rays_rendered as f64 / st.rays_total.max(1) as f64
            ));
        }
        let p = self.stream.progress();
        lines.push(format!(
            "fetched {} of {} ({} of {} sections)",
            bytes(p.transfer.bytes.max(p.bytes_ready.min(p.file_len))),
            bytes(p.file_len),
            p.sections_ready,
            p.sections
        ));
        if let Some(s) = self.report.samples {
            if s != self.model_samples {
                lines.push(format!("{} + {} samples per ray", s.0, s.1));
            }
        }
        if let Some(l) = self.volume_line() {
            lines.push(l);
        }
        if let Some(VolumeStatus::Failed(e)) = &self.volume {
            lines.push(format!("no volume: {e}"));
        }
        lines.push(format!(
            "t = {:.3} · frame {}{}",
            self.timeline.t,
            self.timeline.frame(),
            if self.buffering {
                " · buffering…"
            } else {
                ""
            }
        ));
        if self.recording.is_some() {
            lines.push("● recording the camera path".into());
        }
        let _ = now;
        let text = lines.join("\n");
        let font = egui::FontId::monospace(12.0);
        // Long lines (a bake's error) wrap at the picture's width.
        let wrap = (rect.width() - 12.0).max(120.0);
        let galley = ui.painter().layout(text, font, egui::Color32::WHITE, wrap);
        let at = rect.min + egui::vec2(6.0, 6.0);
        let bg = egui::Rect::from_min_size(at, galley.size()).expand(4.0);
        ui.painter()
            .rect_filled(bg, 3.0, egui::Color32::from_black_alpha(150));
        ui.painter().galley(at, galley, egui::Color32::WHITE);
        bg
    }
}

pub(super) enum UiAction {
    Shot,
    Record,
    Quit,
}

/// `n` bytes, readable.
fn bytes(n: u64) -> String {
    match n {
        n if n >= 1 << 20 => format!("{:.1} MB", n as f64 / 1e6),
        n if n >= 1 << 10 => format!("{:.1} kB", n as f64 / 1e3),
        n => format!("{n} B"),
    }
}
