//! The render thread: owns the [`FrameRenderer`] (GPU or CPU) and renders the newest job the
//! window sends, with the parameters the stream has for the job's time; the window thread stays
//! free for input and drawing. A job that is overtaken while it waits for its chunk is dropped.

use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use msth_core::config::PlaySamples;
use msth_core::Camera;
use msth_player::play::gpu_tables_for;
use msth_player::policy::Step;
use msth_player::{BackendChoice, BackendInfo, Frame, FrameRenderer, ModelStream, RenderSettings};

/// The render settings the window's controls set. A new value rebuilds the renderer.
///
/// A control bound to another render setting (such as the volume renderer's exact / volume
/// switch) is one more field here, one line in [`RenderControls::apply`] and one widget in the
/// panel (`app.rs`, `controls_panel`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderControls {
    /// Samples per ray (the samples menu).
    pub samples: PlaySamples,
}

impl RenderControls {
    /// `base` with these controls applied.
    fn apply(&self, base: RenderSettings) -> RenderSettings {
        base
    }
}

/// One frame to draw.
#[derive(Clone, Debug)]
pub struct Job {
    pub id: u64,
    /// The camera at the size to render (reduced or full).
    pub camera: Camera,
    /// The same view at full size.
    pub full_camera: Camera,
    pub time: f32,
    pub controls: RenderControls,
    /// The size to render at and why; `step.incremental`: keep the static cache (a still camera
    /// at full size), else render every pixel.
    pub step: Step,
    /// The file camera shown, if the view is one.
    pub file_camera: Option<usize>,
}

/// What the render thread says.
pub enum Reply {
    /// A renderer is ready for these controls: which backend, and the samples per ray (rendered
    /// and the model's own).
    Renderer {
        info: BackendInfo,
        samples: (usize, usize),
    },
    Frame {
        job: Box<Job>,
        frame: Frame,
        chunk: Option<usize>,
    },
    /// The job's chunk is still streaming.
    Buffering,
    /// The renderer or the stream failed; the thread stops.
    Failed(String),
}

/// Fixed settings of every renderer the thread builds.
pub struct WorkerSetup {
    pub stream: Arc<ModelStream>,
    pub base: RenderSettings,
    pub backend: BackendChoice,
    pub skip_empty: bool,
    /// Longest wait for a probe time's chunk while the static cache is built.
    pub section_timeout: Duration,
    pub limits: msth_codec::Limits,
}

/// Runs the render loop until the job channel closes; `wake` is called after each reply.
pub fn run(setup: WorkerSetup, jobs: Receiver<Job>, replies: Sender<Reply>, wake: impl Fn()) {
    let say = |r: Reply| {
        let ok = replies.send(r).is_ok();
        wake();
        ok
    };
    if let Err(e) = render_loop(&setup, &jobs, &say) {
        say(Reply::Failed(e));
    }
}

fn render_loop(
    setup: &WorkerSetup,
    jobs: &Receiver<Job>,
    say: &dyn Fn(Reply) -> bool,
) -> Result<(), String> {
    let stream = &setup.stream;
    let meta = stream.index().metadata.clone();
    let mut renderer: Option<(RenderControls, FrameRenderer)> = None;
    let mut params = Vec::new();
    let mut loaded: Option<Option<usize>> = None;
    let mut version = 0u64;
    let mut pending: Option<Job> = None;
    loop {
        // The newest job: wait for one, then skip those already overtaken.
        let mut job = match pending.take() {
            Some(j) => j,
            None => match jobs.recv() {
                Ok(j) => j,
                Err(_) => return Ok(()),
            },
        };
        loop {
            match jobs.try_recv() {
                Ok(j) => job = j,
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => return Ok(()),
            }
        }
        if renderer.as_ref().is_none_or(|(c, _)| *c != job.controls) {
            let model = job
                .controls
                .samples
                .apply(
                    &meta.model,
                    setup.limits.max_proposal_samples as usize,
                    setup.limits.max_samples as usize,
                )
                .map_err(|e| format!("--{e}"))?;
            let settings = job.controls.apply(setup.base);
            let (r, info) = FrameRenderer::new(&model, settings, setup.backend)
                .map_err(|e| format!("cannot start the renderer: {e}"))?;
            renderer = Some((job.controls, r));
            loaded = None;
            let samples = (
                model.sampler.num_proposal_samples,
                model.sampler.num_samples,
            );
            if !say(Reply::Renderer { info, samples }) {
                return Ok(());
            }
        }
        let Some((_, r)) = renderer.as_mut() else {
            continue;
        };
        // The parameters of the job's time: wait for its chunk, giving way to a newer job.
        let chunk = stream.index().chunk_for_time(job.time);
        if loaded != Some(chunk) {
            stream.seek(job.time);
            let mut said = false;
            loop {
                match stream.params_for_time(job.time, &mut params, Duration::from_millis(50)) {
                    Ok(_) => break,
                    Err(msth_player::StreamError::Timeout { .. }) => {
                        if !said {
                            said = true;
                            if !say(Reply::Buffering) {
                                return Ok(());
                            }
                        }
                        match jobs.recv_timeout(Duration::from_millis(1)) {
                            Ok(j) => {
                                pending = Some(j);
                                break;
                            }
                            Err(RecvTimeoutError::Timeout) => {}
                            Err(RecvTimeoutError::Disconnected) => return Ok(()),
                        }
                    }
                    Err(e) => return Err(e.to_string()),
                }
            }
            if pending.is_some() {
                continue;
            }
            version += 1;
            r.set_params_version(version);
            if loaded.is_none() && setup.skip_empty {
                r.set_occupancy(stream.occupancy())
                    .map_err(|e| e.to_string())?;
            }
            loaded = Some(chunk);
        }
        if !job.step.incremental {
            r.invalidate();
        }
        let timeout = setup.section_timeout;
        let mut params_at = |t: f32| {
            if stream.index().chunk_for_time(t) == chunk {
                return None;
            }
            let mut v = Vec::new();
            stream.params_at(t, &mut v, timeout).ok().map(|_| v)
        };
        let start = Instant::now();
        let mut frame = r
            .render_probing(&job.camera, job.time, &params, &mut params_at)
            .map_err(|e| format!("rendering failed: {e}"))?;
        frame.stats.seconds = frame.stats.seconds.max(start.elapsed().as_secs_f64());
        if !say(Reply::Frame {
            job: Box::new(job),
            frame,
            chunk,
        }) {
            return Ok(());
        }
    }
}

/// The render settings of a viewer: the player's defaults over the whole clip, the hash tables
/// as the file's quantisation suggests unless told.
pub fn base_settings(
    quant: msth_codec::QuantMode,
    tables: Option<msth_player::TableFormat>,
    incremental: bool,
) -> RenderSettings {
    RenderSettings {
        incremental,
        time_range: (0.0, 1.0),
        gpu_tables: tables.unwrap_or(gpu_tables_for(quant)),
        ..RenderSettings::default()
    }
}
