//! What the viewer writes: recorded camera paths, screenshots, bench results and the session's
//! report, and the files they go to.

use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc};

use msth_core::Camera;
use msth_player::path::keyframes_json;

use super::gfx::Gfx;
use super::{App, BenchReport, ShotReport, ViewReport, Wake};
use crate::script;
use crate::ViewError;

pub(super) struct Recording {
    pub(super) frames: Vec<(Camera, Option<f32>)>,
    pub(super) next_tick: f64,
}

pub(super) struct BenchRun {
    pub(super) frames: usize,
    pub(super) sent: usize,
    pub(super) done: usize,
    pub(super) started: Option<f64>,
    pub(super) render_seconds: f64,
    pub(super) window_seconds: f64,
    pub(super) size: (u32, u32),
}

impl App {
    /// Ends a bench once its last frame is painted.
    pub(super) fn finish_bench(&mut self, now: f64, paint_seconds: f64) {
        let Some(b) = &mut self.bench else {
            return;
        };
        if b.started.is_some() && b.done > 0 {
            b.window_seconds += paint_seconds;
        }
        if b.done < b.frames {
            return;
        }
        let seconds = now - b.started.unwrap_or(now);
        let r = BenchReport {
            frames: b.frames,
            width: b.size.0,
            height: b.size.1,
            seconds,
            fps: b.frames as f64 / seconds.max(1e-9),
            render_seconds: b.render_seconds,
            render_fps: b.frames as f64 / b.render_seconds.max(1e-9),
            window_seconds: b.window_seconds,
        };
        println!(
            "bench: {} frames of {}x{} in {:.3} s: {:.2} FPS shown, {:.2} FPS of render time ({:.3} s), the window's upload and paint {:.3} s",
            r.frames, r.width, r.height, r.seconds, r.fps, r.render_fps, r.render_seconds, r.window_seconds
        );
        self.report.bench.push(r);
        self.bench = None;
    }

    /// Starts or stops recording the camera path; stopping writes it.
    pub(super) fn toggle_recording(&mut self, now: f64) -> Result<(), ViewError> {
        match self.recording.take() {
            None => {
                self.recording = Some(Recording {
                    frames: Vec::new(),
                    next_tick: now,
                });
                self.status = "recording the camera path (R stops)".into();
            }
            Some(mut rec) => {
                // The path ends at the view shown when recording stops.
                rec.frames.push((self.view.camera(), Some(self.timeline.t)));
                let path = self
                    .opts
                    .out
                    .join(format!("path-{:03}.json", self.paths_saved));
                self.paths_saved += 1;
                let json = keyframes_json(&rec.frames);
                write_atomic(&path, json.to_string().as_bytes())?;
                self.status = format!(
                    "recorded {} frames: msth play {} --path {}",
                    rec.frames.len(),
                    self.opts.source,
                    path.display()
                );
                println!("{}", self.status);
                self.report.paths.push(path);
            }
        }
        Ok(())
    }

    pub(super) fn record_tick(&mut self, now: f64) {
        let cam = self.view.camera();
        let t = self.timeline.t;
        let step = 1.0 / self.timeline.frame_rate as f64;
        if let Some(rec) = &mut self.recording {
            while rec.next_tick <= now {
                rec.frames.push((cam, Some(t)));
                rec.next_tick += step;
            }
        }
    }

    /// Saves the screenshot once the window's image is back.
    pub(super) fn save_shot(&mut self, gfx: &Gfx) -> Result<(), ViewError> {
        let Some((shot, rx)) = &self.shot else {
            return Ok(());
        };
        let Ok(img) = rx.try_recv() else {
            return Ok(());
        };
        let shot = shot.clone();
        self.shot = None;
        let Some(shown) = &self.shown else {
            return Ok(());
        };
        if let Some(p) = &shot.frame {
            msth_player::play::write_png(p, &shown.frame).map_err(|e| ViewError::Io {
                path: p.clone(),
                error: std::io::Error::other(e.to_string()),
            })?;
        }
        if let Some(p) = &shot.window {
            let [w, h] = img.size;
            let rgb: Vec<u8> = img
                .pixels
                .iter()
                .flat_map(|c| [c.r(), c.g(), c.b()])
                .collect();
            save_rgb(p, w as u32, h as u32, &rgb)?;
        }
        let ppp = self.pixels_per_point;
        let px = |v: f32| (v * ppp).round().max(0.0) as u32;
        let rect = |r: Option<egui::Rect>| {
            let r = r.unwrap_or(egui::Rect::ZERO);
            [px(r.min.x), px(r.min.y), px(r.width()), px(r.height())]
        };
        let cam = shown.job.full_camera;
        self.report.screenshots.push(ShotReport {
            frame: shot.frame.clone(),
            window: shot.window.clone(),
            picture_rect: rect(self.picture_rect),
            overlay_rect: rect(self.overlay_rect),
            time: shown.job.time,
            camera: cam.world_from_camera.transpose().to_cols_array_2d(),
            file_camera: shown.job.file_camera,
        });
        self.status = format!(
            "screenshot: {}",
            [&shot.frame, &shot.window]
                .iter()
                .filter_map(|p| p.as_ref().map(|p| p.display().to_string()))
                .collect::<Vec<_>>()
                .join(", ")
        );
        println!("{}", self.status);
        let _ = gfx;
        Ok(())
    }

    /// A screenshot by key or button: `shot-NNN.png` and `shot-NNN-window.png` in the output
    /// folder.
    pub(super) fn request_shot(&mut self) {
        if self.shot.is_some() || self.shown.is_none() {
            return;
        }
        let base = self.opts.out.join(format!("shot-{:03}", self.shots_taken));
        self.shots_taken += 1;
        let (tx, rx) = mpsc::channel();
        let proxy = self.proxy.clone();
        self.shot = Some((
            script::Shot {
                frame: Some(base.with_extension("png")),
                window: Some(PathBuf::from(format!("{}-window.png", base.display()))),
            },
            rx,
        ));
        self.pending_capture = Some(egui::ScreenshotCallback::new(
            move |img: Arc<egui::ColorImage>| {
                let _ = tx.send(img);
                let _ = proxy.send_event(Wake);
            },
        ));
    }

    pub(super) fn finish(mut self) -> Result<ViewReport, ViewError> {
        self.report.seconds = self.now();
        let p = self.stream.progress();
        self.report.bytes_fetched = p.transfer.bytes;
        if let Some(path) = &self.opts.report {
            let json = serde_json::to_vec_pretty(&self.report)
                .map_err(|e| ViewError::Render(e.to_string()))?;
            write_atomic(path, &json)?;
        }
        Ok(self.report)
    }
}

fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ViewError> {
    let io = |error| ViewError::Io {
        path: path.to_path_buf(),
        error,
    };
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

fn save_rgb(path: &Path, w: u32, h: u32, rgb: &[u8]) -> Result<(), ViewError> {
    let tmp = path.with_extension("png.tmp");
    image::save_buffer_with_format(
        &tmp,
        rgb,
        w,
        h,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(|e| ViewError::Io {
        path: path.to_path_buf(),
        error: std::io::Error::other(e.to_string()),
    })?;
    std::fs::rename(&tmp, path).map_err(|error| ViewError::Io {
        path: path.to_path_buf(),
        error,
    })
}
