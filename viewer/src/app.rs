//! The window: winit's event loop, egui's controls painted with egui-wgpu, the picture as a
//! texture of the window, and the viewer's state (camera, timeline, policy, overlay, recording,
//! screenshots, the script).
//!
//! The render thread ([`crate::worker`]) renders one job at a time; the window sends the next
//! job when the last one is back, chosen by [`ResolutionPolicy`], so that the window never waits
//! for the renderer and the renderer never renders a view that is already stale.

use std::collections::VecDeque;
use std::num::NonZeroU32;
use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::Instant;

use egui::{Key, PointerButton};
use msth_core::Camera;
use msth_player::path::{keyframes_json, Rig};
use msth_player::policy::{reduced_camera, Activity, ResolutionPolicy, Step, Timeline};
use msth_player::{source, BackendInfo, Frame, ModelStream, StreamError};
use serde::Serialize;
use winit::application::ApplicationHandler;
use winit::event::{StartCause, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop, EventLoopProxy};
use winit::window::{Window, WindowId};

use crate::camera::{Mode, ViewCamera};
use crate::script::{self, Script};
use crate::worker::{self, Job, RenderControls, Reply, VolumeInfo, VolumeStatus, WorkerSetup};
use crate::{ViewError, ViewOptions};

/// One frame shown in the window.
#[derive(Clone, Debug, Serialize)]
pub struct FrameLog {
    /// Seconds since the viewer started.
    pub shown_at: f64,
    pub time: f32,
    pub width: u32,
    pub height: u32,
    pub divisor: u32,
    pub activity: Activity,
    /// Rendered in full (not from the static cache).
    pub full: bool,
    pub rays_rendered: usize,
    pub rays_total: usize,
    /// The renderer's time for the frame.
    pub render_seconds: f64,
    /// The file camera shown, if the view is one.
    pub file_camera: Option<usize>,
    /// Drawn from the play-time volume (else from the exact field).
    pub volume: bool,
}

/// A `bench` step's result: the timeline's model frames drawn one after the other.
#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// From sending the first frame's job to painting the last frame.
    pub seconds: f64,
    /// Frames shown per second.
    pub fps: f64,
    /// The renderer's own time, summed over the frames.
    pub render_seconds: f64,
    /// Frames per second of the renderer's time alone (what `msth play` reports).
    pub render_fps: f64,
    /// The window's time for the frames: uploading them and painting the window.
    pub window_seconds: f64,
}

/// A screenshot: the picture as rendered and the whole window.
#[derive(Clone, Debug, Serialize)]
pub struct ShotReport {
    pub frame: Option<PathBuf>,
    pub window: Option<PathBuf>,
    /// The picture's place in the window screenshot: `[x, y, width, height]` in pixels.
    pub picture_rect: [u32; 4],
    /// The overlay's place (drawn over the picture's top left corner), the same way.
    pub overlay_rect: [u32; 4],
    pub time: f32,
    /// The camera of the picture (full size).
    pub camera: [[f32; 4]; 4],
    pub file_camera: Option<usize>,
}

/// What a viewing session did (`msth view --report FILE.json`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct ViewReport {
    /// The adapter the window is drawn with.
    pub window_adapter: String,
    /// The renderer (CPU or GPU) of the last frame.
    pub backend: Option<BackendInfo>,
    /// Proposal and main samples per ray of the last frame, and the model's own.
    pub samples: Option<(usize, usize)>,
    pub model_samples: (usize, usize),
    pub frames: Vec<FrameLog>,
    pub screenshots: Vec<ShotReport>,
    /// Camera paths recorded (`msth play --path FILE.json`).
    pub paths: Vec<PathBuf>,
    pub bench: Vec<BenchReport>,
    /// The play-time volume, when one was baked (the exact / volume switch).
    pub volume: Option<VolumeInfo>,
    /// Why the volume switch went back to the exact field, the last time it did.
    pub volume_error: Option<String>,
    pub seconds: f64,
    pub bytes_fetched: u64,
    pub file_len: u64,
}

/// Wakes the event loop (a reply from the render thread, a screenshot read back).
#[derive(Debug)]
struct Wake;

/// Fly keys: right, up, forward.
const FLY_KEYS: [(Key, [f32; 3]); 6] = [
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

const SPEEDS: [f32; 7] = [0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0];
/// The samples menu and the M key: the file's play-time counts, then the levels.
const SAMPLE_CHOICES: [msth_core::config::PlaySamples; 4] = {
    use msth_core::config::{PlaySamples, SampleLevel};
    [
        PlaySamples::File,
        PlaySamples::Level(SampleLevel::Full),
        PlaySamples::Level(SampleLevel::Fast),
        PlaySamples::Level(SampleLevel::Faster),
    ]
};

/// The window and what draws into it.
struct Gfx {
    window: Arc<Window>,
    painter: egui_wgpu::winit::Painter,
    egui: egui_winit::State,
    picture: Option<Picture>,
    adapter: String,
}

/// The picture's texture, shown through two egui ids: nearest (a full-size frame at an integer
/// zoom: each rendered pixel a block of window pixels) and linear (reduced frames, scaled).
struct Picture {
    texture: wgpu::Texture,
    size: (u32, u32),
    nearest: egui::TextureId,
    linear: egui::TextureId,
}

/// The frame on screen.
struct Shown {
    job: Job,
    frame: Frame,
}

struct Recording {
    frames: Vec<(Camera, Option<f32>)>,
    next_tick: f64,
}

struct BenchRun {
    frames: usize,
    sent: usize,
    done: usize,
    started: Option<f64>,
    render_seconds: f64,
    window_seconds: f64,
    size: (u32, u32),
}

#[derive(Default)]
enum Running {
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

struct ScriptRun {
    script: Script,
    index: usize,
    running: Running,
}

struct App {
    opts: ViewOptions,
    stream: Arc<ModelStream>,
    name: String,
    cameras: Vec<Camera>,
    view: ViewCamera,
    timeline: Timeline,
    policy: ResolutionPolicy,
    controls: RenderControls,
    /// Whether a renderer is ready: the volume switch is shown from then on.
    volumes: bool,
    /// Where the play-time volume stands, once the switch has been on.
    volume: Option<VolumeStatus>,
    model_samples: (usize, usize),
    probes: usize,
    proxy: EventLoopProxy<Wake>,
    gfx: Option<Gfx>,
    jobs: Option<mpsc::Sender<Job>>,
    replies: Option<mpsc::Receiver<Reply>>,
    worker: Option<JoinHandle<()>>,
    in_flight: Option<Job>,
    next_id: u64,
    shown: Option<Shown>,
    /// The full-size camera and the time of the last frame sent: the static cache is used when
    /// the time moves under a camera that stays.
    last_sent: Option<(Camera, f32)>,
    buffering: bool,
    start: Instant,
    last_tick: f64,
    recent: VecDeque<f64>,
    recording: Option<Recording>,
    shots_taken: usize,
    paths_saved: usize,
    script: Option<ScriptRun>,
    events: Vec<egui::Event>,
    /// A screenshot to take at the next paint: paths, and where the window's arrives.
    shot: Option<(script::Shot, mpsc::Receiver<Arc<egui::ColorImage>>)>,
    /// The window capture asked for at the next paint.
    pending_capture: Option<egui::ScreenshotCallback>,
    bench: Option<BenchRun>,
    picture_rect: Option<egui::Rect>,
    overlay_rect: Option<egui::Rect>,
    pixels_per_point: f32,
    show_panel: bool,
    status: String,
    wake_at: Option<f64>,
    quit: bool,
    error: Option<ViewError>,
    report: ViewReport,
}

/// Opens the viewer on `opts.source` and runs it until the window closes (or the script quits).
pub fn run(opts: &ViewOptions) -> Result<ViewReport, ViewError> {
    if let Some((w, h)) = opts.size {
        if w == 0 || h == 0 {
            return Err(ViewError::Options(format!(
                "--size {w}x{h}: sides must be at least 1"
            )));
        }
        opts.limits
            .check_image("--size", w, h)
            .map_err(|e| ViewError::Options(e.to_string()))?;
    }
    if let Some(t) = opts.time {
        if !(t.is_finite() && (0.0..=1.0).contains(&t)) {
            return Err(ViewError::Options(format!(
                "--time {t}: must lie in [0, 1]"
            )));
        }
    }
    let src = source::open(&opts.source, &opts.http).map_err(StreamError::from)?;
    let stream = Arc::new(ModelStream::open(src, &opts.limits)?);
    let meta = stream.index().metadata.clone();
    if !meta.cameras.is_empty() && opts.camera >= meta.cameras.len() {
        return Err(ViewError::Options(format!(
            "--camera {}: the file has {} cameras (0..{})",
            opts.camera,
            meta.cameras.len(),
            meta.cameras.len() - 1
        )));
    }
    std::fs::create_dir_all(&opts.out).map_err(|error| ViewError::Io {
        path: opts.out.clone(),
        error,
    })?;
    let event_loop = build_event_loop()?;
    let mut app = App::new(opts, stream, event_loop.create_proxy());
    let ran = event_loop.run_app(&mut app);
    app.stop_worker();
    if let Some(e) = app.error.take() {
        return Err(e);
    }
    ran.map_err(|e| ViewError::NoDisplay(e.to_string()))?;
    app.finish()
}

/// winit's event loop; on X11 it may run on any thread (the tests run it off the main thread).
fn build_event_loop() -> Result<EventLoop<Wake>, ViewError> {
    let mut builder = EventLoop::<Wake>::with_user_event();
    #[cfg(all(
        unix,
        not(any(target_os = "macos", target_os = "ios", target_os = "android"))
    ))]
    {
        use winit::platform::x11::EventLoopBuilderExtX11;
        builder.with_any_thread(true);
    }
    // A missing display is reported by some winit versions with a panic rather than an error.
    let built = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| builder.build()));
    match built {
        Ok(Ok(l)) => Ok(l),
        Ok(Err(e)) => Err(ViewError::NoDisplay(e.to_string())),
        Err(_) => Err(ViewError::NoDisplay(
            "the window system could not be reached (is DISPLAY set?)".into(),
        )),
    }
}

impl App {
    fn new(opts: &ViewOptions, stream: Arc<ModelStream>, proxy: EventLoopProxy<Wake>) -> Self {
        let meta = stream.index().metadata.clone();
        let sized = |c: &Camera| match opts.size {
            Some((w, h)) => c.resized(w, h),
            None => *c,
        };
        let cameras: Vec<Camera> = meta.cameras.iter().map(sized).collect();
        let template = cameras.first().copied().unwrap_or_else(|| {
            let (w, h) = opts.size.unwrap_or((256, 256));
            Camera::from_fov_x(w, h, 0.8, glam::Mat4::IDENTITY)
        });
        let rig = Rig::new(&meta.model.bounds, &cameras, template);
        let mut view = ViewCamera::new(rig);
        if let Some(c) = cameras.get(opts.camera) {
            view.jump(opts.camera, c);
        }
        let mut timeline = Timeline::new(meta.model.num_frames, meta.frame_rate);
        if let Some(t) = opts.time {
            timeline.seek(t);
            timeline.playing = false;
        }
        let name = Path::new(&opts.source)
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| opts.source.clone());
        let model_samples = (
            meta.model.sampler.num_proposal_samples,
            meta.model.sampler.num_samples,
        );
        let base = worker::base_settings(
            meta.parts_quant().finest_table(),
            opts.gpu_tables,
            opts.incremental,
        );
        App {
            opts: opts.clone(),
            name,
            cameras,
            view,
            timeline,
            policy: ResolutionPolicy::new(meta.frame_rate),
            controls: RenderControls {
                samples: opts.samples,
                volume: opts.volume,
            },
            volumes: false,
            volume: None,
            model_samples,
            probes: if opts.incremental { base.probes } else { 0 },
            proxy,
            gfx: None,
            jobs: None,
            replies: None,
            worker: None,
            in_flight: None,
            next_id: 0,
            shown: None,
            last_sent: None,
            buffering: false,
            start: Instant::now(),
            last_tick: 0.0,
            recent: VecDeque::new(),
            recording: None,
            shots_taken: 0,
            paths_saved: 0,
            script: opts.script.clone().map(|script| ScriptRun {
                script,
                index: 0,
                running: Running::Next,
            }),
            events: Vec::new(),
            shot: None,
            pending_capture: None,
            bench: None,
            picture_rect: None,
            overlay_rect: None,
            pixels_per_point: 1.0,
            show_panel: true,
            status: String::new(),
            wake_at: None,
            quit: false,
            error: None,
            report: ViewReport {
                model_samples,
                file_len: stream.index().file_len(),
                ..ViewReport::default()
            },
            stream,
        }
    }

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn fail(&mut self, event_loop: &ActiveEventLoop, e: ViewError) {
        if self.error.is_none() {
            self.error = Some(e);
        }
        event_loop.exit();
    }

    /// Opens the window, its painter and the render thread.
    fn open(&mut self, event_loop: &ActiveEventLoop) -> Result<(), ViewError> {
        let t = self.view.rig().template;
        let (w, h) = self.opts.window_size.unwrap_or_else(|| {
            // The picture at most about 640x480 at a whole zoom: the window is painted once per
            // frame, and on a software adapter its size is what that costs.
            let zoom = (640 / t.width.max(1)).min(480 / t.height.max(1)).max(1);
            (t.width * zoom + 300, t.height * zoom + 90)
        });
        let attrs = Window::default_attributes()
            .with_title(format!("msth view: {}", self.name))
            .with_inner_size(winit::dpi::LogicalSize::new(w, h));
        let window = Arc::new(
            event_loop
                .create_window(attrs)
                .map_err(|e| ViewError::NoDisplay(e.to_string()))?,
        );
        let ctx = egui::Context::default();
        let config = egui_wgpu::WgpuConfiguration {
            wgpu_setup: egui_wgpu::WgpuSetup::CreateNew(egui_wgpu::WgpuSetupCreateNew {
                native_adapter_selector: Some(Arc::new(pick_window_adapter)),
                ..egui_wgpu::WgpuSetupCreateNew::without_display_handle()
            }),
            // Frames come when the renderer has them: presenting should not wait for a vblank.
            surface: egui_wgpu::SurfaceConfig {
                present_mode: wgpu::PresentMode::AutoNoVsync,
                desired_maximum_frame_latency: Some(1),
            },
            ..egui_wgpu::WgpuConfiguration::default()
        };
        let options = egui_wgpu::RendererOptions {
            dithering: false,
            ..egui_wgpu::RendererOptions::default()
        };
        let mut painter = pollster::block_on(egui_wgpu::winit::Painter::new(
            ctx.clone(),
            config,
            false,
            options,
        ));
        pollster::block_on(painter.set_window(egui::ViewportId::ROOT, Some(window.clone())))
            .map_err(|e| ViewError::NoPresenter(e.to_string()))?;
        let rs = painter
            .render_state()
            .ok_or_else(|| ViewError::NoPresenter("no device".into()))?;
        let info = rs.adapter.get_info();
        let adapter = format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type);
        self.report.window_adapter = adapter.clone();
        let egui = egui_winit::State::new(
            ctx,
            egui::ViewportId::ROOT,
            window.as_ref(),
            Some(window.scale_factor() as f32),
            None,
            painter.max_texture_side(),
        );
        self.gfx = Some(Gfx {
            window,
            painter,
            egui,
            picture: None,
            adapter,
        });
        self.start_worker()
    }

    fn start_worker(&mut self) -> Result<(), ViewError> {
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

    fn stop_worker(&mut self) {
        self.jobs = None;
        if let Some(h) = self.worker.take() {
            let _ = h.join();
        }
    }

    /// Takes the render thread's replies; a frame goes to the window's texture.
    fn take_replies(&mut self, gfx: &mut Gfx, now: f64) -> Result<(), ViewError> {
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
    fn set_volume(&mut self, on: bool) {
        self.controls.volume = on;
        if on && matches!(self.volume, Some(VolumeStatus::Failed(_))) {
            self.volume = None;
        }
    }

    /// Whether the picture shows the current view at full size, drawn as the controls ask (from
    /// the volume: once it is baked), and nothing is pending.
    fn settled(&self, now: f64) -> bool {
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
    fn submit(&mut self, now: f64) {
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

    /// Advances the script by what can be done in this frame.
    fn run_script(&mut self, now: f64) -> Result<(), ViewError> {
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

    /// Ends a bench once its last frame is painted.
    fn finish_bench(&mut self, now: f64, paint_seconds: f64) {
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
    fn toggle_recording(&mut self, now: f64) -> Result<(), ViewError> {
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

    fn record_tick(&mut self, now: f64) {
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
    fn save_shot(&mut self, gfx: &Gfx) -> Result<(), ViewError> {
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
    fn request_shot(&mut self) {
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

    fn finish(mut self) -> Result<ViewReport, ViewError> {
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

/// The adapter the window is drawn with: a hardware one that can draw into the window, else a
/// software one (Mesa's lavapipe draws a window without a GPU).
fn pick_window_adapter(
    adapters: &[wgpu::Adapter],
    surface: Option<&wgpu::Surface<'_>>,
) -> Result<wgpu::Adapter, String> {
    let rank = |t: wgpu::DeviceType| match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    };
    let usable: Vec<&wgpu::Adapter> = adapters
        .iter()
        .filter(|a| surface.is_none_or(|s| a.is_surface_supported(s)))
        .collect();
    usable
        .into_iter()
        .min_by_key(|a| rank(a.get_info().device_type))
        .cloned()
        .ok_or_else(|| {
            if adapters.is_empty() {
                "no Vulkan, Metal or DX12 adapter at all".to_string()
            } else {
                format!(
                    "none of the adapters can draw into the window: {}",
                    adapters
                        .iter()
                        .map(|a| a.get_info().name)
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            }
        })
}

/// Uploads `frame` to the picture's texture (made anew when the size changes).
fn upload(gfx: &mut Gfx, frame: &Frame) {
    let Some(rs) = gfx.painter.render_state() else {
        return;
    };
    let size = (frame.width, frame.height);
    if gfx.picture.as_ref().is_none_or(|p| p.size != size) {
        let texture = rs.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("msth view picture"),
            size: wgpu::Extent3d {
                width: size.0,
                height: size.1,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let mut renderer = rs.renderer.write();
        let sampler = |filter| wgpu::SamplerDescriptor {
            label: Some("msth view picture"),
            mag_filter: filter,
            min_filter: filter,
            ..Default::default()
        };
        let (nearest, linear) = match gfx.picture.take() {
            Some(p) => {
                renderer.update_egui_texture_from_wgpu_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Nearest),
                    p.nearest,
                );
                renderer.update_egui_texture_from_wgpu_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Linear),
                    p.linear,
                );
                (p.nearest, p.linear)
            }
            None => (
                renderer.register_native_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Nearest),
                ),
                renderer.register_native_texture_with_sampler_options(
                    &rs.device,
                    &view,
                    sampler(wgpu::FilterMode::Linear),
                ),
            ),
        };
        gfx.picture = Some(Picture {
            texture,
            size,
            nearest,
            linear,
        });
    }
    let Some(p) = &gfx.picture else {
        return;
    };
    let rgb = frame.to_rgb8();
    let mut rgba = Vec::with_capacity(rgb.len() / 3 * 4);
    for c in rgb.chunks_exact(3) {
        rgba.extend_from_slice(&[c[0], c[1], c[2], 255]);
    }
    rs.queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture: &p.texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        &rgba,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(4 * size.0),
            rows_per_image: Some(size.1),
        },
        wgpu::Extent3d {
            width: size.0,
            height: size.1,
            depth_or_array_layers: 1,
        },
    );
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

impl ApplicationHandler<Wake> for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_some() {
            return;
        }
        if let Err(e) = self.open(event_loop) {
            self.fail(event_loop, e);
            return;
        }
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
    }

    fn new_events(&mut self, _: &ActiveEventLoop, cause: StartCause) {
        if let (StartCause::ResumeTimeReached { .. }, Some(g)) = (cause, &self.gfx) {
            g.window.request_redraw();
        }
    }

    fn user_event(&mut self, _: &ActiveEventLoop, _: Wake) {
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        let Some(mut gfx) = self.gfx.take() else {
            return;
        };
        let response = gfx.egui.on_window_event(&gfx.window, &event);
        match &event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let (Some(w), Some(h)) =
                    (NonZeroU32::new(size.width), NonZeroU32::new(size.height))
                {
                    gfx.painter.on_window_resized(egui::ViewportId::ROOT, w, h);
                }
                gfx.window.request_redraw();
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw(&mut gfx) {
                    self.gfx = Some(gfx);
                    self.fail(event_loop, e);
                    return;
                }
                if self.quit {
                    event_loop.exit();
                }
            }
            _ => {}
        }
        if response.repaint {
            gfx.window.request_redraw();
        }
        self.gfx = Some(gfx);
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let now = self.now();
        match (self.wake_at, &self.gfx) {
            (Some(t), Some(g)) if t <= now => {
                g.window.request_redraw();
                event_loop.set_control_flow(ControlFlow::Wait);
            }
            (Some(t), Some(_)) => match std::time::Duration::try_from_secs_f64(t) {
                Ok(d) => event_loop.set_control_flow(ControlFlow::WaitUntil(self.start + d)),
                Err(_) => event_loop.set_control_flow(ControlFlow::Wait),
            },
            _ => event_loop.set_control_flow(ControlFlow::Wait),
        }
    }
}

impl App {
    /// One pass: replies, the clock, the script, the controls, the next job, the paint.
    fn redraw(&mut self, gfx: &mut Gfx) -> Result<(), ViewError> {
        let now = self.now();
        let dt = (now - self.last_tick).clamp(0.0, 0.25);
        self.last_tick = now;
        self.take_replies(gfx, now)?;
        self.finish_bench(now, 0.0);
        if self.bench.is_none() {
            let ready = self.stream.ready_for(self.timeline.t);
            self.timeline.advance(dt, ready);
        }
        self.run_script(now)?;
        let before = self.view.camera();
        let mut raw = gfx.egui.take_egui_input(&gfx.window);
        raw.events.append(&mut self.events);
        let ctx = gfx.egui.egui_ctx().clone();
        let picture = gfx.picture.as_ref().map(|p| (p.nearest, p.linear, p.size));
        let adapter = gfx.adapter.clone();
        let mut actions = Vec::new();
        let mut output = ctx.run_ui(raw, |ui| {
            self.ui(ui, now, dt, picture, &adapter, &mut actions);
        });
        if self.view.camera() != before {
            self.policy.input(now);
        }
        for a in actions {
            match a {
                UiAction::Shot => self.request_shot(),
                UiAction::Record => self.toggle_recording(now)?,
                UiAction::Quit => self.quit = true,
            }
        }
        self.record_tick(now);
        gfx.egui
            .handle_platform_output(&gfx.window, std::mem::take(&mut output.platform_output));
        self.pixels_per_point = output.pixels_per_point;
        self.submit(now);
        // Paint.
        let paint_start = Instant::now();
        let primitives =
            ctx.tessellate(std::mem::take(&mut output.shapes), output.pixels_per_point);
        let captures: Vec<egui::ScreenshotCallback> =
            self.pending_capture.take().into_iter().collect();
        let capture = !captures.is_empty();
        gfx.painter.paint_and_update_textures(
            egui::ViewportId::ROOT,
            output.pixels_per_point,
            [0.1, 0.1, 0.1, 1.0],
            &primitives,
            &mut output.textures_delta,
            captures,
            &gfx.window,
        );
        if capture {
            if let Some(rs) = gfx.painter.render_state() {
                let _ = rs.device.poll(wgpu::PollType::wait_indefinitely());
            }
        }
        let paint_seconds = paint_start.elapsed().as_secs_f64();
        self.save_shot(gfx)?;
        self.finish_bench(self.now(), paint_seconds);
        // When to come back: egui's wish, the script, playback, refinement, held keys.
        let repaint = output
            .viewport_output
            .get(&egui::ViewportId::ROOT)
            .map(|v| v.repaint_delay.as_secs_f64())
            .unwrap_or(f64::INFINITY);
        let mut wake = now + repaint;
        let soon = now + 1.0 / 60.0;
        let keys_held = ctx.input(|i| FLY_KEYS.iter().any(|(k, _)| i.key_down(*k)));
        if self.script.is_some() || keys_held || self.shot.is_some() {
            wake = wake.min(soon);
        }
        if self.in_flight.is_none() && (self.timeline.playing || self.bench.is_some()) {
            wake = wake.min(if self.buffering { now + 0.05 } else { now });
        }
        if self.policy.moving(now) || self.policy.wants_refine(now + 1.0, false) {
            wake = wake.min(now + msth_player::policy::STILL / 4.0);
        }
        if let Some(r) = &self.recording {
            wake = wake.min(r.next_tick);
        }
        // egui's "no repaint needed" is a delay of years.
        self.wake_at = (wake < now + 3600.0).then_some(wake);
        Ok(())
    }

    /// The controls and the picture; keys and pointer input on the picture move the camera.
    fn ui(
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

    fn keys(&mut self, ctx: &egui::Context, dt: f64, actions: &mut Vec<UiAction>) {
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

    fn jump(&mut self, i: usize) {
        if let Some(c) = self.cameras.get(i) {
            let c = *c;
            self.view.jump(i, &c);
        }
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

enum UiAction {
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
