//! Playback: stream a file, walk a camera path over a time range, render each frame (incrementally
//! while the camera stands still), write PNG frames and an MP4 when `ffmpeg` is installed.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use msth_codec::Limits;
use msth_core::config::PlaySamples;
use msth_dataset::video::{self, EncodeError};

use crate::backend::{BackendChoice, BackendInfo, FrameRenderer};
use crate::gpu::GpuError;
use crate::path::{CameraPath, PathError};
use crate::render::{Frame, FrameStats, RenderSettings};
use crate::source::{self, HttpOptions, TransferStats};
use crate::stream::{ModelStream, StreamError};
use crate::volume::{plan_bake, BakeJob, VolumeOptions};

/// Everything `msth play` can be told.
#[derive(Clone, Debug)]
pub struct PlayOptions {
    /// An `http://` URL or a local path.
    pub source: String,
    /// Camera path spec ([`CameraPath::parse`]).
    pub path: String,
    /// Output image size (default: the cameras' own).
    pub size: Option<(u32, u32)>,
    /// Frames to render (default: the model's frame count, or the JSON path's).
    pub frames: Option<usize>,
    /// Normalised time range, played from the first to the second value.
    pub time_range: (f32, f32),
    /// Frame rate of the video (default: the file's, else 30).
    pub fps: Option<f32>,
    /// Folder for `frame_00000.png ...` and `video.mp4` (none: render only).
    pub out: Option<PathBuf>,
    /// Make an MP4 when `ffmpeg` is installed.
    pub video: bool,
    pub render: RenderSettings,
    /// CPU or GPU renderer ([`BackendChoice::Auto`]: the GPU when a hardware adapter exists).
    pub backend: BackendChoice,
    pub http: HttpOptions,
    pub limits: Limits,
    /// Longest wait for any one section to arrive.
    pub section_timeout: Duration,
    /// Skip samples in the cells the file's occupancy grid marks empty (CPU renderer, and the
    /// GPU renderer's per-sample passes; files of format version 1 have no grid and skip
    /// nothing).
    pub skip_empty: bool,
    /// Samples per ray: the file's play-time counts (the default; the model's own when it
    /// stores none), the model's own, or fewer, for speed.
    pub samples: PlaySamples,
    /// GPU renderer: how the device holds the hash tables. `None`: f32 when a hash-table part of
    /// the file is lossless (mode `f32`), else binary16, whose rounding lies below every
    /// quantised mode's step ([`msth_gpu::TableFormat::F16`]).
    pub gpu_tables: Option<msth_gpu::TableFormat>,
    /// The play-time volume, baked once the static part has arrived (unless
    /// [`RenderSettings::exact`]).
    pub volume: VolumeOptions,
    /// Wait for the bake before the first frame; otherwise frames are drawn from the exact field
    /// until the volume is ready.
    pub bake_first: bool,
}

impl PlayOptions {
    pub fn new(source: impl Into<String>) -> Self {
        PlayOptions {
            source: source.into(),
            path: "0".into(),
            size: None,
            frames: None,
            time_range: (0.0, 1.0),
            fps: None,
            out: None,
            video: true,
            // The exact field unless the caller asks for the volume (`exact: false`).
            render: RenderSettings {
                exact: true,
                ..Default::default()
            },
            backend: BackendChoice::Auto,
            http: HttpOptions::default(),
            limits: Limits::default(),
            section_timeout: Duration::from_secs(120),
            skip_empty: true,
            samples: PlaySamples::default(),
            gpu_tables: None,
            volume: VolumeOptions::default(),
            bake_first: false,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PlayError {
    #[error(transparent)]
    Stream(#[from] StreamError),
    #[error("{0}")]
    Options(String),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("{path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    /// The `--path` spec (camera index, view, orbit, JSON file) is not a camera path.
    #[error(transparent)]
    Path(#[from] PathError),
}

/// How the GPU renderer holds the hash tables of a file whose finest hash-table part is quantised
/// with `quant` (`SectionQuant::finest_table`) unless told otherwise: f32 when it is lossless,
/// else binary16, whose rounding lies below every quantised
/// mode's step ([`msth_gpu::TableFormat::F16`]; the page's `main.js` chooses alike).
pub fn gpu_tables_for(quant: msth_codec::QuantMode) -> msth_gpu::TableFormat {
    match quant {
        msth_codec::QuantMode::F32 => msth_gpu::TableFormat::F32,
        _ => msth_gpu::TableFormat::F16,
    }
}

/// One rendered frame's record.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct FrameRecord {
    pub index: usize,
    pub time: f32,
    /// The dynamic chunk its parameters came from.
    pub chunk: Option<usize>,
    pub stats: FrameStats,
}

/// What a playback did and how fast.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PlayReport {
    pub frames: Vec<FrameRecord>,
    /// From the start of [`play`] to the first frame rendered (prefix, static sections, the first
    /// chunk, the full render).
    pub time_to_first_frame: f64,
    /// Wall time of the whole playback, writing included.
    pub seconds: f64,
    pub file_len: u64,
    pub transfer: TransferStats,
    /// Fraction of the first fixed camera's pixels re-rendered each frame.
    pub dynamic_fraction: Option<f32>,
    pub video: Option<PathBuf>,
    /// Why no video was made, when one was asked for.
    pub video_note: Option<String>,
    /// The renderer used (CPU or GPU, and which adapter).
    pub backend: BackendInfo,
    /// Proposal and main samples per ray rendered (`PlayOptions::samples` of the model's).
    pub samples: (usize, usize),
    /// The model's own proposal and main samples per ray.
    pub model_samples: (usize, usize),
    /// The play-time volume, when one was baked.
    pub bake: Option<BakeReport>,
    /// Why frames came from the exact field, when the volume was asked for and not used.
    pub volume_note: Option<String>,
}

/// What baking the play-time volume cost.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BakeReport {
    pub geometry: msth_core::volume::VolumeGeometry,
    pub stats: msth_core::volume::BakeStats,
    /// Bytes the volume holds without its time slices.
    pub bytes: u64,
    /// Bytes of one time slice of the dynamic bricks.
    pub slice_bytes: u64,
    /// Field evaluations one time slice costs.
    pub slice_evaluations: usize,
    /// The first frame drawn from it.
    pub first_frame: usize,
    /// Why the volume is coarser than the model asked for, if it is.
    pub note: Option<String>,
}

impl PlayReport {
    /// Frames per second over `frames`, each costing `seconds(frame)`.
    fn rate<'a>(
        frames: impl Iterator<Item = &'a FrameRecord>,
        seconds: impl Fn(&FrameStats) -> f64,
    ) -> Option<f64> {
        let (n, s) = frames.fold((0usize, 0f64), |(n, s), f| (n + 1, s + seconds(&f.stats)));
        (n > 0 && s > 0.0).then(|| n as f64 / s)
    }
    /// Frames per second over `frames` (render time only).
    fn fps_of<'a>(frames: impl Iterator<Item = &'a FrameRecord>) -> Option<f64> {
        Self::rate(frames, |s| s.seconds)
    }
    /// Rendering rate of the frames rendered in full.
    pub fn full_fps(&self) -> Option<f64> {
        Self::fps_of(self.frames.iter().filter(|f| f.stats.full))
    }
    /// Rendering rate of the incremental frames.
    pub fn incremental_fps(&self) -> Option<f64> {
        Self::fps_of(self.frames.iter().filter(|f| !f.stats.full))
    }
    /// Rendering rate of the incremental frames once the static cache exists: the one-off cost
    /// of building it ([`FrameStats::cache_seconds`], paid by the first frame after the camera
    /// stops) left out.
    pub fn steady_incremental_fps(&self) -> Option<f64> {
        Self::rate(self.frames.iter().filter(|f| !f.stats.full), |s| {
            (s.seconds - s.cache_seconds).max(0.0)
        })
    }
    /// Seconds spent building static caches (classification and probe renders).
    pub fn cache_seconds(&self) -> f64 {
        self.frames.iter().map(|f| f.stats.cache_seconds).sum()
    }
    /// Rendering rate over all frames.
    pub fn fps(&self) -> Option<f64> {
        Self::fps_of(self.frames.iter())
    }
}

/// Plays `opts`, calling `on_frame` after each frame.
pub fn play(
    opts: &PlayOptions,
    on_frame: &mut dyn FnMut(&FrameRecord, &Frame),
) -> Result<PlayReport, PlayError> {
    let start = Instant::now();
    let (t0, t1) = opts.time_range;
    CameraPath::check_options(opts.time_range, opts.size, &opts.limits)
        .map_err(PlayError::Options)?;
    let src = source::open(&opts.source, &opts.http).map_err(StreamError::from)?;
    let stream = ModelStream::open(src, &opts.limits)?;
    let meta = stream.index().metadata.clone();
    let path = CameraPath::parse(&opts.path, &meta.model.bounds, &meta.cameras, opts.size)?;
    let n = path
        .frames(opts.frames, meta.model.num_frames.max(1), 1 << 20)
        .map_err(PlayError::Options)?;
    if let Some(dir) = &opts.out {
        std::fs::create_dir_all(dir).map_err(|error| PlayError::Io {
            path: dir.clone(),
            error,
        })?;
    }
    stream.seek(t0);
    // The incremental renderer probes and places its fixed samples over the times shown.
    let frame_time = |i: usize| path.frame_time(i, n, (t0, t1));
    let mut render_settings = opts.render;
    render_settings.gpu_tables = opts
        .gpu_tables
        .unwrap_or(gpu_tables_for(meta.parts_quant().finest_table()));
    render_settings.time_range = (0..n).map(frame_time).fold((1f32, 0f32), |(lo, hi), t| {
        let t = t.clamp(0.0, 1.0);
        (lo.min(t), hi.max(t))
    });
    let model = opts
        .samples
        .apply(
            &meta.model,
            meta.play_samples
                .map(|s| (s.proposal as usize, s.main as usize)),
            opts.limits.max_proposal_samples as usize,
            opts.limits.max_samples as usize,
        )
        .map_err(|e| PlayError::Options(format!("--{e}")))?;
    let samples = (
        model.sampler.num_proposal_samples,
        model.sampler.num_samples,
    );
    let model_samples = (
        meta.model.sampler.num_proposal_samples,
        meta.model.sampler.num_samples,
    );
    let (mut renderer, backend) = FrameRenderer::new(&model, render_settings, opts.backend)?;
    // The bake under way, with the plan's note for its report.
    let mut bake_job: Option<(BakeJob, Option<String>)> = None;
    let mut bake: Option<BakeReport> = None;
    let mut volume_note = None;
    let mut params = Vec::new();
    let mut params_version = 0u64;
    let mut loaded: Option<Option<usize>> = None;
    let mut records = Vec::with_capacity(n);
    let mut first_frame = None;
    let mut dynamic_fraction = None;
    for i in 0..n {
        let (camera, _) = path.camera(i, n);
        let time = frame_time(i);
        // Ask for the next frame's chunk early so it streams while this one renders.
        let chunk = stream.index().chunk_for_time(time);
        if loaded != Some(chunk) {
            stream.params_for_time(time, &mut params, opts.section_timeout)?;
            // `params` holds the same values until the next chunk: the GPU renderer need not
            // compare them with its copy each frame.
            params_version += 1;
            renderer.set_params_version(params_version);
            if loaded.is_none() && opts.skip_empty {
                // The occupancy section is one of the static sections, decoded by now.
                renderer.set_occupancy(stream.occupancy())?;
            }
            if loaded.is_none() && !render_settings.exact {
                // The static part is here: bake the volume (it reads nothing else).
                {
                    let grid = stream.occupancy();
                    let mut vopts = opts.volume;
                    vopts.budget.get_or_insert(renderer.volume_budget());
                    match plan_bake(&model, &params, grid.as_deref(), &meta.cameras, &vopts) {
                        Ok(plan) => {
                            let note = plan.note();
                            let plan = std::sync::Arc::new(plan);
                            // Waited for anyway: on a hardware GPU the device bakes.
                            let on_device = if opts.bake_first {
                                renderer.bake_on_device(plan.clone(), &params)
                            } else {
                                None
                            };
                            match on_device {
                                Some(r) => finish_bake(
                                    r.map_err(|e| e.to_string()),
                                    note,
                                    i,
                                    &mut renderer,
                                    &mut bake,
                                    &mut volume_note,
                                ),
                                None => {
                                    let mut job = BakeJob::start(plan, &model, params.clone());
                                    if opts.bake_first {
                                        if let Some(r) = job.wait() {
                                            finish_bake(
                                                r,
                                                note,
                                                i,
                                                &mut renderer,
                                                &mut bake,
                                                &mut volume_note,
                                            );
                                        }
                                    } else {
                                        bake_job = Some((job, note));
                                    }
                                }
                            }
                        }
                        Err(e) => {
                            volume_note = Some(format!(
                                "no play-time volume ({e}): frames are drawn from the exact field"
                            ))
                        }
                    }
                }
            }
            loaded = Some(chunk);
        }
        if i + 1 < n {
            let next = frame_time(i + 1);
            if !stream.ready_for(next) {
                stream.seek(next);
            }
        }
        // Probes of the static test at other times need those times' 4D rows: a time in
        // another chunk waits for that chunk (fetched in playback order; the playhead stays).
        let timeout = opts.section_timeout;
        let mut params_at = |t: f32| {
            if stream.index().chunk_for_time(t) == chunk {
                return None;
            }
            let mut v = Vec::new();
            stream.params_at(t, &mut v, timeout).ok().map(|_| v)
        };
        if let Some((job, note)) = bake_job.as_mut() {
            if let Some(r) = job.poll() {
                finish_bake(
                    r,
                    note.take(),
                    i,
                    &mut renderer,
                    &mut bake,
                    &mut volume_note,
                );
                bake_job = None;
            }
        }
        let frame = renderer.render_probing(&camera, time, &params, &mut params_at)?;
        if first_frame.is_none() {
            first_frame = Some(start.elapsed().as_secs_f64());
        }
        if dynamic_fraction.is_none() && path.is_fixed() {
            dynamic_fraction = renderer.dynamic_fraction();
        }
        let record = FrameRecord {
            index: i,
            time,
            chunk,
            stats: frame.stats,
        };
        if let Some(dir) = &opts.out {
            write_png(&dir.join(format!("frame_{i:05}.png")), &frame)?;
        }
        on_frame(&record, &frame);
        records.push(record);
    }
    if let Some((job, _)) = &bake_job {
        volume_note = Some(format!(
            "the volume's bake was {:.0}% done when playback ended: every frame came from the exact field (--bake-first waits for it)",
            100.0 * job.fraction()
        ));
    }
    let (video, video_note) = match (&opts.out, opts.video) {
        (Some(dir), true) => {
            let fps = opts.fps.or(meta.frame_rate).unwrap_or(30.0);
            match make_video(dir, fps) {
                Ok(p) => (Some(p), None),
                Err(note) => (None, Some(note.to_string())),
            }
        }
        _ => (None, None),
    };
    let progress = stream.progress();
    let mut backend = backend;
    backend.mlps = renderer.mlp_note();
    backend.tables_clamped = renderer.clamped_table_values();
    Ok(PlayReport {
        frames: records,
        time_to_first_frame: first_frame.unwrap_or(0.0),
        seconds: start.elapsed().as_secs_f64(),
        file_len: progress.file_len,
        transfer: progress.transfer,
        dynamic_fraction,
        video,
        video_note,
        backend,
        samples,
        model_samples,
        bake,
        volume_note,
    })
}

/// Hands a finished bake to the renderer (from frame `frame` on), or notes why there is none.
fn finish_bake(
    result: Result<crate::volume::BakedVolume, String>,
    note: Option<String>,
    frame: usize,
    renderer: &mut FrameRenderer,
    bake: &mut Option<BakeReport>,
    volume_note: &mut Option<String>,
) {
    match result {
        Ok(baked) => {
            let vol = &baked.volume;
            *bake = Some(BakeReport {
                geometry: vol.geometry,
                stats: vol.stats,
                bytes: vol.bytes(),
                slice_bytes: vol.slice_bytes(),
                slice_evaluations: baked.plan.slice_evaluations(),
                first_frame: frame,
                note,
            });
            if let Err(e) = renderer.set_volume(Some(baked)) {
                *volume_note = Some(format!(
                    "the volume does not fit the device ({e}): frames are drawn from the exact field"
                ));
            }
        }
        Err(e) => *volume_note = Some(format!("no play-time volume: {e}")),
    }
}

/// Writes an 8-bit PNG through a temporary file and a rename.
pub fn write_png(path: &Path, frame: &Frame) -> Result<(), PlayError> {
    let io = |error| PlayError::Io {
        path: path.to_path_buf(),
        error,
    };
    let tmp = path.with_extension("png.tmp");
    image::save_buffer_with_format(
        &tmp,
        &frame.to_rgb8(),
        frame.width,
        frame.height,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(|e| io(std::io::Error::other(e.to_string())))?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// Why [`make_video`] made no MP4 (the PNG frames are there either way).
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("ffmpeg is not installed: PNG frames only")]
    NotInstalled,
    #[error("cannot run ffmpeg: {0}")]
    Spawn(std::io::Error),
    #[error("ffmpeg failed ({0}): PNG frames only")]
    Failed(std::process::ExitStatus),
    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

/// Encodes `dir/frame_*.png` into `dir/video.mp4` with ffmpeg (H.264, yuv420p); `Err` says why
/// not (`msth demo` calls it to time the video on its own).
pub fn make_video(dir: &Path, fps: f32) -> Result<PathBuf, VideoError> {
    let out = dir.join("video.mp4");
    let tmp = dir.join("video.tmp.mp4");
    let encoded = video::encode_png_sequence(
        Path::new("ffmpeg"),
        &dir.join("frame_%05d.png"),
        fps,
        18,
        &tmp,
    );
    match encoded {
        Err(EncodeError::NotInstalled { .. }) => Err(VideoError::NotInstalled),
        Err(EncodeError::Spawn { source, .. }) => Err(VideoError::Spawn(source)),
        Err(EncodeError::Failed { status, .. }) => {
            let _ = std::fs::remove_file(&tmp);
            Err(VideoError::Failed(status))
        }
        Ok(()) => std::fs::rename(&tmp, &out)
            .map(|_| out.clone())
            .map_err(|error| VideoError::Io { path: out, error }),
    }
}
