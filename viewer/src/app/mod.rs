//! The window: winit's event loop, egui's controls painted with egui-wgpu, the picture as a
//! texture of the window, and the viewer's state (camera, timeline, policy, overlay, recording,
//! screenshots, the script).
//!
//! The render thread ([`crate::worker`]) renders one job at a time; the window sends the next
//! job when the last one is back, chosen by [`ResolutionPolicy`], so that the window never waits
//! for the renderer and the renderer never renders a view that is already stale.
//!
//! This module holds [`run`] and the viewer's state; its parts are in submodules: the report
//! types (`report`), the window's drawing (`gfx`), the event loop and the redraw pass
//! (`event_loop`), the render thread's jobs and replies (`render`), the script (`script_run`),
//! the keys (`input`), the controls panel and the overlay (`ui`), and the files written
//! (`output`).

mod event_loop;
mod gfx;
mod input;
mod output;
mod render;
mod report;
mod script_run;
mod ui;

use std::collections::VecDeque;
use std::path::Path;
use std::sync::{mpsc, Arc};
use std::thread::JoinHandle;
use std::time::Instant;

use msth_core::Camera;
use msth_player::path::Rig;
use msth_player::policy::{ResolutionPolicy, Timeline};
use msth_player::{source, Frame, ModelStream, StreamError};
use winit::event_loop::{ActiveEventLoop, EventLoopProxy};

use crate::camera::ViewCamera;
use crate::script;
use crate::worker::{self, Job, RenderControls, Reply, VolumeStatus};
use crate::{ViewError, ViewOptions};

use event_loop::build_event_loop;
use gfx::Gfx;
use output::{BenchRun, Recording};
use script_run::{Running, ScriptRun};

pub use input::KEYS;
pub use report::{BenchReport, FrameLog, ShotReport, ViewReport};

/// Wakes the event loop (a reply from the render thread, a screenshot read back).
#[derive(Debug)]
struct Wake;

/// The frame on screen.
struct Shown {
    job: Job,
    frame: Frame,
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
}
