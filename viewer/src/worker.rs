//! The render thread: owns the [`FrameRenderer`] (GPU or CPU) and renders the newest job the
//! window sends, with the parameters the stream has for the job's time; the window thread stays
//! free for input and drawing. A job that is overtaken while it waits for its chunk is dropped.
//!
//! The CPU renderer can draw from a play-time volume baked from the file
//! ([`RenderControls::volume`]): the first job that asks for it starts a bake on a thread of its
//! own ([`BakeJob`]) once the static part has arrived; frames come from the exact field until the
//! bake is done, and the thread reports its progress ([`VolumeStatus`]) meanwhile. The volume is
//! kept when the switch goes off, so that it comes back at once.

use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, TryRecvError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use msth_core::config::{ModelConfig, PlaySamples};
use msth_core::Camera;
use msth_player::play::gpu_tables_for;
use msth_player::policy::Step;
use msth_player::volume::{plan_bake, BakeJob, BakedVolume, VolumeOptions};
use msth_player::{BackendChoice, BackendInfo, Frame, FrameRenderer, ModelStream, RenderSettings};
use serde::Serialize;

/// The render settings the window's controls set. A new value of a field that
/// [`RenderControls::rebuilds`] names rebuilds the renderer; the others are switched on the
/// renderer there is.
///
/// A control bound to another render setting is one more field here, one line in
/// [`RenderControls::apply`] (and in [`RenderControls::rebuilds`] or the render loop) and one
/// widget in the panel (`app/ui.rs`, `controls_panel`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderControls {
    /// Samples per ray (the samples menu).
    pub samples: PlaySamples,
    /// Draw from the play-time volume (the exact / volume switch): the first job
    /// that asks for it starts the bake, and frames come from the exact field until it is done.
    /// Off: the exact field, the reference.
    pub volume: bool,
}

impl RenderControls {
    /// `base` with these controls applied.
    fn apply(&self, base: RenderSettings) -> RenderSettings {
        RenderSettings {
            exact: !self.volume,
            ..base
        }
    }

    /// Whether going from `self` to `next` needs a new renderer (the volume switch does not: the
    /// renderer keeps its volume and switches).
    fn rebuilds(&self, next: &RenderControls) -> bool {
        self.samples != next.samples
    }
}

/// The play-time volume, once baked.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VolumeInfo {
    /// Cells per side.
    pub resolution: u32,
    /// Bricks kept, and of those the dynamic ones (baked per time slice as frames need them).
    pub bricks: usize,
    pub dynamic_bricks: usize,
    /// Bytes it holds without its time slices.
    pub bytes: u64,
    /// Wall time of the bake.
    pub seconds: f64,
    /// Why it is coarser than the model asked for, if it is.
    pub note: Option<String>,
}

/// Where the play-time volume stands.
#[derive(Clone, Debug, PartialEq)]
pub enum VolumeStatus {
    /// Baking: the fraction of the static bricks done.
    Baking { fraction: f64 },
    /// Baked: frames come from it while [`RenderControls::volume`] is on.
    Ready(VolumeInfo),
    /// No volume (the bake failed, or could not be planned): frames come from the exact field.
    /// A job with the switch off clears it; the next one with the switch on tries again.
    Failed(String),
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
    /// The play-time volume's bake started, moved on (at most once per percent), finished or
    /// failed.
    Volume(VolumeStatus),
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
    /// How the play-time volume is baked when [`RenderControls::volume`] asks for it.
    pub volume: VolumeOptions,
}

/// How often a running bake is looked at while no job comes.
const BAKE_POLL: Duration = Duration::from_millis(200);

/// The render thread's play-time volume.
enum Bake {
    /// None asked for yet (or the last one failed and the switch went off since).
    Idle,
    Running {
        job: BakeJob,
        note: Option<String>,
        /// The last percentage said.
        said: u32,
    },
    /// Baked: the renderer holds it (and hands it on when it is rebuilt).
    Done,
    /// Failed: frames come from the exact field until a job with the switch off (a job with it
    /// on hears why again).
    Failed(String),
}

impl Bake {
    /// Starts baking for `cfg` with `params` (the static part at least).
    fn start(
        setup: &WorkerSetup,
        cfg: &ModelConfig,
        params: &[f32],
        renderer: &FrameRenderer,
        say: &dyn Fn(Reply) -> bool,
    ) -> (Bake, bool) {
        let meta = &setup.stream.index().metadata;
        let grid = setup.stream.occupancy();
        let mut options = setup.volume;
        options.budget.get_or_insert(renderer.volume_budget());
        match plan_bake(cfg, params, grid.as_deref(), &meta.cameras, &options) {
            Ok(plan) => {
                let note = plan.note();
                let job = BakeJob::start(plan, cfg, params.to_vec());
                let ok = say(Reply::Volume(VolumeStatus::Baking { fraction: 0.0 }));
                (Bake::Running { job, note, said: 0 }, ok)
            }
            Err(e) => {
                let e = format!("cannot plan the volume: {e}");
                let ok = say(Reply::Volume(VolumeStatus::Failed(e.clone())));
                (Bake::Failed(e), ok)
            }
        }
    }

    /// Looks at a running bake: says its progress, hands a finished volume to `renderer`.
    /// Returns false when the window has gone.
    fn poll(&mut self, renderer: &mut FrameRenderer, say: &dyn Fn(Reply) -> bool) -> bool {
        let Bake::Running { job, note, said } = self else {
            return true;
        };
        match job.poll() {
            None => {
                let fraction = job.fraction();
                let pct = (100.0 * fraction).floor() as u32;
                if pct == *said {
                    return true;
                }
                *said = pct;
                say(Reply::Volume(VolumeStatus::Baking { fraction }))
            }
            Some(Ok(baked)) => {
                let info = volume_info(&baked, note.take());
                if let Err(e) = renderer.set_volume(Some(baked)) {
                    let e = format!("the volume does not fit the device: {e}");
                    *self = Bake::Failed(e.clone());
                    return say(Reply::Volume(VolumeStatus::Failed(e)));
                }
                *self = Bake::Done;
                say(Reply::Volume(VolumeStatus::Ready(info)))
            }
            Some(Err(e)) => {
                let e = format!("the bake failed: {e}");
                *self = Bake::Failed(e.clone());
                say(Reply::Volume(VolumeStatus::Failed(e)))
            }
        }
    }
}

fn volume_info(baked: &BakedVolume, note: Option<String>) -> VolumeInfo {
    let v = &baked.volume;
    VolumeInfo {
        resolution: v.geometry.resolution,
        bricks: v.stats.bricks,
        dynamic_bricks: v.stats.dynamic_bricks,
        bytes: v.bytes(),
        seconds: v.stats.seconds,
        note,
    }
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
    let mut renderer: Option<(RenderControls, ModelConfig, FrameRenderer)> = None;
    let mut bake = Bake::Idle;
    let mut params = Vec::new();
    // The chunk whose parameters are loaded, and with how many progressive layers.
    let mut loaded: Option<(Option<usize>, usize)> = None;
    let mut version = 0u64;
    let mut pending: Option<Job> = None;
    loop {
        if let Some((_, _, r)) = renderer.as_mut() {
            if !bake.poll(r, say) {
                return Ok(());
            }
        }
        // The newest job: wait for one (looking at the bake now and then), then skip those
        // already overtaken.
        let mut job = match pending.take() {
            Some(j) => j,
            None if matches!(bake, Bake::Running { .. }) => match jobs.recv_timeout(BAKE_POLL) {
                Ok(j) => j,
                Err(RecvTimeoutError::Timeout) => continue,
                Err(RecvTimeoutError::Disconnected) => return Ok(()),
            },
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
        if renderer
            .as_ref()
            .is_none_or(|(c, _, _)| c.rebuilds(&job.controls))
        {
            let model = job
                .controls
                .samples
                .apply(
                    &meta.model,
                    meta.play_samples
                        .map(|s| (s.proposal as usize, s.main as usize)),
                    setup.limits.max_proposal_samples as usize,
                    setup.limits.max_samples as usize,
                )
                .map_err(|e| format!("--{e}"))?;
            let settings = job.controls.apply(setup.base);
            // The volume does not depend on the samples per ray: the new renderer draws from it.
            let kept = renderer.as_mut().and_then(|(_, _, r)| r.take_volume());
            let (mut r, info) = FrameRenderer::new(&model, settings, setup.backend)
                .map_err(|e| format!("cannot start the renderer: {e}"))?;
            if kept.is_some() {
                // A volume that fit the last renderer's device fits this one's (the same).
                r.set_volume(kept).map_err(|e| e.to_string())?;
            }
            let samples = (
                model.sampler.num_proposal_samples,
                model.sampler.num_samples,
            );
            renderer = Some((job.controls, model, r));
            loaded = None;
            if !say(Reply::Renderer { info, samples }) {
                return Ok(());
            }
        }
        let Some((_, cfg, r)) = renderer.as_mut() else {
            continue;
        };
        // The parameters of the job's time: wait for its chunk, giving way to a newer job.
        // Of a layered file, the frame is drawn from the layers in and again as finer ones come.
        let chunk = stream.index().chunk_for_time(job.time);
        let have = loaded.filter(|&(c, _)| c == chunk).map(|(_, l)| l);
        if have.is_none_or(|l| stream.layers_for(job.time) > l) {
            stream.seek(job.time);
            let mut said = false;
            let mut layers = 0;
            loop {
                match stream.params_progressive(job.time, &mut params, Duration::from_millis(50)) {
                    Ok((_, l)) => {
                        layers = l;
                        break;
                    }
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
            if have.is_some() {
                // Finer layers of the same chunk: nothing cached from the coarser ones holds.
                r.invalidate();
            }
            loaded = Some((chunk, layers));
        }
        // The volume switch: the static part is here, so a bake can start.
        if job.controls.volume {
            let ok = match &bake {
                Bake::Idle => {
                    let (b, ok) = Bake::start(setup, cfg, &params, r, say);
                    bake = b;
                    ok
                }
                Bake::Failed(e) => say(Reply::Volume(VolumeStatus::Failed(e.clone()))),
                Bake::Running { .. } | Bake::Done => true,
            };
            if !ok || !bake.poll(r, say) {
                return Ok(());
            }
        } else if matches!(bake, Bake::Failed(_)) {
            bake = Bake::Idle;
        }
        r.set_exact(!job.controls.volume);
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
        // The volume switch (V) is the viewer's own choice: it holds for a still camera too.
        volume_when_still: true,
        ..RenderSettings::default()
    }
}
