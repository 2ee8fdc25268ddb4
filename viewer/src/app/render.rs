//! The render thread seen from the window: starting and stopping it, its replies (frames to the
//! picture's texture, the renderer, the volume's progress), and the next job to send.

use std::sync::mpsc;
use std::sync::Arc;
use std::time::Instant;

use msth_player::policy::{reduced_camera, Activity, Step};

use super::gfx::{upload, Gfx};
use super::{App, FrameLog, Shown, Wake};
use crate::worker::{self, Job, Reply, VolumeStatus, WorkerSetup};
use crate::ViewError;

impl App {
    pub(super) fn start_worker(&mut self) -> Result<(), ViewError> {
        let meta = &self.stream.index().metadata;
        let base = worker::base_settings(
            meta.parts_quant().finest_table(),
            self.opts.gpu_tables,
            self.opts.incremental,
        );
        let setup = WorkerSetup {
            stream: Arc::clone(&self.stream),
            base: msth_player::RenderSettings {
                march: self.opts.march,
                ..base
            },
            backend: self.opts.backend,
            skip_empty: self.opts.skip_empty,
            section_timeout: self.opts.section_timeout,
            limits: self.opts.limits,
            volume: self.opts.volume_options,
        };
        let (job_tx, job_rx) = mpsc::channel();
        let (reply_tx, reply_rx) = mpsc::channel();
        let proxy = self.proxy.clone();
        let handle = std::thread::Builder::new()
            .name("msth-view-render".into())
            .spawn(move || {
                worker::run(setup, job_rx, reply_tx, move || {
                    let _ = proxy.send_event(Wake);
                })
            })
            .map_err(|e| ViewError::Render(format!("cannot start the render thread: {e}")))?;
        self.jobs = Some(job_tx);
        self.replies = Some(reply_rx);
        self.worker = Some(handle);
        Ok(())
    }

    pub(super) fn stop_worker(&mut self) {
        self.jobs = None;
        if let Some(h) = self.worker.take() {
            let _ = h.join();
        }
    }

    /// Takes the render thread's replies; a frame goes to the window's texture.
    pub(super) fn take_replies(&mut self, gfx: &mut Gfx, now: f64) -> Result<(), ViewError> {
        let Some(rx) = &self.replies else {
            return Ok(());
        };
        let replies: Vec<Reply> = rx.try_iter().collect();
        for r in replies {
            match r {
                Reply::Renderer { info, samples } => {
                    self.report.backend = Some(info);
                    self.report.samples = Some(samples);
                    self.volumes = true;
                }
                Reply::Volume(status) => {
                    match &status {
                        VolumeStatus::Ready(info) => self.report.volume = Some(info.clone()),
                        VolumeStatus::Failed(e) => {
                            // Back to the exact field; the switch tries again when turned on.
                            self.controls.volume = false;
                            self.report.volume_error = Some(e.clone());
                        }
                        VolumeStatus::Baking { .. } => {}
                    }
                    self.volume = Some(status);
                }
                Reply::Buffering => self.buffering = true,
                Reply::Failed(e) => return Err(ViewError::Render(e)),
                Reply::Frame { job, frame, .. } => {
                    self.buffering = false;
                    self.in_flight = None;
                    let t = Instant::now();
                    upload(gfx, &frame);
                    let upload_s = t.elapsed().as_secs_f64();
                    let s = &frame.stats;
                    let pixels = frame.width as u64 * frame.height as u64;
                    self.policy.done(job.step, s.seconds, pixels, s.full);
                    self.report.frames.push(FrameLog {
                        shown_at: now,
                        time: job.time,
                        width: frame.width,
                        height: frame.height,
                        divisor: job.step.divisor,
                        activity: job.step.activity,
                        full: s.full,
                        rays_rendered: s.rays_rendered,
                        rays_total: s.rays_total,
                        render_seconds: s.seconds,
                        file_camera: job.file_camera,
                        volume: s.volume,
                    });
                    self.recent.push_back(now);
                    if let Some(b) = &mut self.bench {
                        if b.started.is_some() {
                            b.done += 1;
                            b.render_seconds += s.seconds;
                            b.window_seconds += upload_s;
                            b.size = (frame.width, frame.height);
                        }
                    }
                    self.shown = Some(Shown { job: *job, frame });
                }
            }
        }
        while self.recent.front().is_some_and(|&t| t < now - 1.0) {
            self.recent.pop_front();
        }
        Ok(())
    }

    /// Whether frames should come from the volume now: the switch is on and the volume baked.
    fn volume_frames(&self) -> bool {
        self.controls.volume && matches!(self.volume, Some(VolumeStatus::Ready(_)))
    }

    /// Whether `s` was drawn with the current controls (from the volume once it is ready).
    fn drawn_as_asked(&self, s: &Shown) -> bool {
        s.job.controls == self.controls && s.frame.stats.volume == self.volume_frames()
    }

    /// Turns the exact / volume switch on or off.
    pub(super) fn set_volume(&mut self, on: bool) {
        self.controls.volume = on;
        if on && matches!(self.volume, Some(VolumeStatus::Failed(_))) {
            self.volume = None;
        }
    }

    /// Whether the picture shows the current view at full size, drawn as the controls ask (from
    /// the volume: once it is baked), and nothing is pending.
    pub(super) fn settled(&self, now: f64) -> bool {
        let Some(s) = &self.shown else {
            return false;
        };
        let baking =
            self.controls.volume && matches!(self.volume, Some(VolumeStatus::Baking { .. }));
        !baking
            && self.in_flight.is_none()
            && s.job.full_camera == self.view.camera()
            && s.job.time == self.timeline.t
            && self.drawn_as_asked(s)
            && s.job.step.divisor == 1
            && !self.policy.moving(now)
            && !self.timeline.playing
    }

    /// Sends the next job when none is in flight and the view needs one.
    pub(super) fn submit(&mut self, now: f64) {
        if self.in_flight.is_some() || self.jobs.is_none() {
            return;
        }
        let full = self.view.camera();
        let (step, time) = if let Some(b) = &mut self.bench {
            if b.sent >= b.frames {
                return;
            }
            let n = b.frames;
            let t = if n > 1 {
                b.sent as f32 / (n - 1) as f32
            } else {
                self.timeline.t
            };
            b.sent += 1;
            b.started.get_or_insert(now);
            self.timeline.t = t;
            let step = Step {
                divisor: 1,
                activity: Activity::Playing,
                incremental: self.opts.incremental,
            };
            (step, t)
        } else {
            let t = self.timeline.t;
            let playing = self.timeline.playing;
            // The static cache serves a still camera whose time moved, once the probe times'
            // chunks are in.
            let time_moved = self.last_sent.is_some_and(|(c, lt)| c == full && lt != t);
            let probes_ready = (0..self.probes).all(|j| {
                let pt = worker::base_settings(msth_codec::QuantMode::F32, None, true)
                    .clip_time(j, self.probes);
                self.stream.ready_for(pt)
            });
            let probes = if time_moved && probes_ready {
                self.probes
            } else {
                0
            };
            let pixels = full.width as u64 * full.height as u64;
            let step = self.policy.next(now, playing, pixels, probes);
            let same = self.shown.as_ref().is_some_and(|s| {
                s.job.full_camera == full && s.job.time == t && self.drawn_as_asked(s)
            });
            let refine = self.policy.wants_refine(now, playing);
            if same && !refine {
                return;
            }
            // The renderer's cache of a still camera survives only frames at full size.
            let step = if step.divisor != 1 {
                Step {
                    incremental: false,
                    ..step
                }
            } else {
                step
            };
            (step, t)
        };
        let job = Job {
            id: self.next_id,
            camera: reduced_camera(&full, step.divisor),
            full_camera: full,
            time,
            controls: self.controls,
            step,
            file_camera: self.view.file_camera(),
        };
        self.next_id += 1;
        self.last_sent = Some((full, time));
        if let Some(tx) = &self.jobs {
            if tx.send(job.clone()).is_ok() {
                self.in_flight = Some(job);
            }
        }
    }
}
