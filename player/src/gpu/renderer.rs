//! The GPU counterpart of [`crate::render::Renderer`]: the same frames, the same static-ray cache,
//! the same sample-level reuse.
//!
//! A full frame renders every pixel on the device into a frame buffer that stays there
//! (`(r, g, b, visible depth)` per pixel, a negative depth for a ray that missed the scene),
//! through the per-sample passes of `msth-gpu` ([`msth_gpu::passes`]), in batches of rays sized
//! to the scratch budget ([`GpuRenderer::set_scratch_budget`]). The second frame of a fixed
//! camera classifies the first frame's rays with [`classify_static_with_stats`] (the CPU
//! renderer's mask test, then probes rendered on the device, each with the parameters of its own
//! time), uploads the compacted list of dynamic pixels, and, with [`Reuse::Samples`], builds the
//! device's sample cache of those rays ([`GpuSampleCache`]: fixed samples over the clip, static
//! samples evaluated once). From then on each frame evaluates only the dynamic samples (or, with
//! [`Reuse::Rays`], the dynamic pixels' whole rays) into a compact output of the dynamic pixels,
//! which alone is read back and written into the host's copy of the frame.

use std::sync::Arc;
use std::time::Instant;

use msth_codec::OccupancyGrid;
use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::pipeline::TimedRay;
use msth_core::Camera;
use msth_gpu::passes::FrameScratch;
use msth_gpu::{GpuSampleCache, GpuVolume, Pixels, ReadBack, VolumeKernel};

use super::{GpuContext, GpuError, GpuModel, GpuScene, ViewU, FLAG_COMPACT, FLAG_LIST};
use crate::render::{
    classify_static_with_stats, partition_samples, partition_times, ClassifyStats, Frame,
    FrameStats, RenderSettings, Reuse,
};
use crate::volume::{bake_set_on_device, BakedVolume};
use msth_core::volume::bake::bake_slice_with;
use msth_core::volume::BakeError;

/// How the per-sample passes evaluate the model's fields (encodings and MLPs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum GpuMlps {
    /// Compiled for the model, its level values and MLP weights as constants
    /// (`msth_gpu::specialise`), when its first parameters are uploaded; the generic passes
    /// where its MLPs are too large.
    #[default]
    Specialised,
    /// The generic passes: level values and weights read from buffers (for comparisons).
    Generic,
}

/// What became of [`GpuMlps::Specialised`].
#[derive(Clone, Debug, PartialEq)]
pub enum MlpStatus {
    /// Not asked for ([`GpuMlps::Generic`]) or no parameters uploaded yet.
    Generic,
    /// Specialised; compiling took this many seconds.
    Specialised(f64),
    /// The generic passes, because of this.
    Refused(msth_gpu::specialise::SpecialiseError),
}

impl std::fmt::Display for MlpStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MlpStatus::Generic => write!(f, "generic kernels"),
            MlpStatus::Specialised(s) => {
                write!(f, "kernels compiled for this model ({s:.2} s)")
            }
            MlpStatus::Refused(e) => write!(f, "generic kernels ({e})"),
        }
    }
}

#[derive(Default)]
struct Pending {
    pixels: Vec<u32>,
    rays: Vec<TimedRay>,
    rgb: Vec<[f32; 3]>,
    visible_depth: Vec<f32>,
}

/// The static cache of one camera; the cached frame itself is the device's frame buffer.
struct Cache {
    camera: Camera,
    total: usize,
    empty: usize,
    /// Pixels re-rendered every frame, on the host and on the device.
    dynamic: Vec<u32>,
    dynamic_buf: Option<wgpu::Buffer>,
    /// The dynamic pixels' output on the device, compact (entry `i` for `dynamic[i]`): an
    /// incremental frame reads back only these.
    dynamic_out: Option<wgpu::Buffer>,
    /// Sample-level reuse of the dynamic pixels ([`Reuse::Samples`]).
    samples: Option<GpuSampleCache>,
    /// The full frame's time, until the same camera comes again: its output (still in the
    /// device's frame buffer) is then read back, and its rays listed and classified. A moving
    /// camera pays for neither.
    deferred: Option<f32>,
    /// The last frame's RGB (row-major, every pixel), held on the host from the full frame's
    /// output on: an incremental frame writes its dynamic pixels into it.
    shown: Vec<f32>,
}

/// Renders frames of one model on the GPU, keeping the static cache between frames.
pub struct GpuRenderer {
    ctx: GpuContext,
    cfg: ModelConfig,
    layout: ModelLayout,
    settings: RenderSettings,
    gpu_model: GpuModel,
    scene: Option<GpuScene>,
    /// Per-pixel output, and how many pixels it holds.
    frame: Option<(wgpu::Buffer, usize)>,
    /// The staging buffer frames are read back through (full frames and the dynamic pixels of
    /// incremental ones), kept between frames.
    readback: ReadBack,
    /// The passes' scratch, and the pixel count it was made for (made by each frame whose pixel
    /// count differs; `None` before the first exact frame).
    scratch: Option<(FrameScratch, usize)>,
    /// Bytes of scratch one batch of rays may take ([`GpuContext::default_scratch_budget`]
    /// unless set).
    scratch_budget: u64,
    /// The caller's version of the parameters it passes ([`GpuRenderer::set_params_version`]),
    /// and the version the device holds (`None`: compare the values).
    params_version: Option<u64>,
    uploaded_version: Option<u64>,
    cache: Option<Cache>,
    /// The file's occupancy grid: the per-sample passes skip samples in its empty cells.
    occupancy: Option<Arc<OccupancyGrid>>,
    mlps: GpuMlps,
    mlp_status: MlpStatus,
    /// The baked volume frames are drawn from ([`GpuRenderer::set_volume`]), on the host (its
    /// slices are baked there) and on the device.
    volume: Option<(BakedVolume, GpuVolume)>,
    /// The march kernel, compiled with the first volume.
    volume_kernel: Option<VolumeKernel>,
    /// The previous frame's camera ([`RenderSettings::volume_when_still`]).
    last_camera: Option<Camera>,
    /// Why the volume's time slices could not be baked, if they could not (frames then come
    /// from the exact field).
    slice_error: Option<String>,
    /// Whether time slices are baked on the device ([`GpuRenderer::set_device_bake`]).
    device_bake: bool,
}

impl GpuRenderer {
    /// A renderer of `cfg` on `ctx` with the per-sample passes; fails when the kernels cannot
    /// render the model (beyond the kernels' or the adapter's limits, or lavapipe's loop budget).
    pub fn new(
        ctx: GpuContext,
        cfg: &ModelConfig,
        settings: RenderSettings,
    ) -> Result<Self, GpuError> {
        let gpu_model = GpuModel::new(cfg).map_err(|e| GpuError::Model(e.to_string()))?;
        if ctx.is_lavapipe() {
            let n = super::layout::loop_iterations_per_invocation(cfg);
            if n > super::layout::LAVAPIPE_LOOP_ITERATIONS {
                return Err(GpuError::Limit {
                    what: "one per-sample invocation of this model".to_string(),
                    amount: n,
                    unit: "loop iterations",
                    limit: "lavapipe loop iterations per invocation (LP_MAX_TGSI_LOOP_ITERATIONS)",
                    max: super::layout::LAVAPIPE_LOOP_ITERATIONS,
                });
            }
        }
        for (what, bytes) in gpu_model.buffer_sizes(ctx.tables()) {
            ctx.check_storage(what, bytes)?;
        }
        let ctx_software = ctx.is_software();
        let scratch_budget = ctx.default_scratch_budget();
        Ok(GpuRenderer {
            ctx,
            cfg: cfg.clone(),
            layout: ModelLayout::new(cfg),
            settings,
            gpu_model,
            scene: None,
            frame: None,
            readback: ReadBack::default(),
            scratch: None,
            scratch_budget,
            params_version: None,
            uploaded_version: None,
            cache: None,
            occupancy: None,
            mlps: GpuMlps::default(),
            mlp_status: MlpStatus::Generic,
            volume: None,
            volume_kernel: None,
            last_camera: None,
            slice_error: None,
            device_bake: !ctx_software,
        })
    }

    /// Bakes the volume's time slices on the device (`true`; the default on hardware adapters)
    /// or on the host's threads (the default on software adapters such as lavapipe, where the
    /// per-point kernel is two orders of magnitude slower than the host's bake). The slices are
    /// the same to float rounding either way.
    pub fn set_device_bake(&mut self, on: bool) {
        self.device_bake = on;
    }

    /// Draws frames from `volume` (unless [`RenderSettings::exact`]), uploaded to the device
    /// here; `None` returns to the exact field. Fails, keeping the exact field, for a volume
    /// beyond the device's limits or without baked colours ([`GpuVolume::new`]).
    pub fn set_volume(&mut self, volume: Option<BakedVolume>) -> Result<(), GpuError> {
        self.volume = None;
        self.slice_error = None;
        self.cache = None;
        let Some(v) = volume else {
            return Ok(());
        };
        if self.volume_kernel.is_none() {
            self.volume_kernel = Some(VolumeKernel::new(&self.ctx)?);
        }
        let g = GpuVolume::new(&self.ctx, &v.volume)?;
        self.volume = Some((v, g));
        Ok(())
    }

    /// Bakes `plan`'s static bricks with `params` on the device, waiting for it, when the
    /// device bakes ([`GpuRenderer::set_device_bake`]); `None` when the host should (a software
    /// adapter: the players' bake thread, [`crate::volume::BakeJob`]).
    pub fn bake_on_device(
        &mut self,
        plan: std::sync::Arc<msth_core::volume::BakePlan>,
        params: &[f32],
    ) -> Option<Result<BakedVolume, BakeError>> {
        if !self.device_bake {
            return None;
        }
        if let Err(e) = self.upload(params) {
            return Some(Err(BakeError::Device(e.to_string())));
        }
        let scene = self.scene.as_ref().expect("uploaded above");
        let (ctx, cfg, layout) = (&self.ctx, &self.cfg, &self.layout);
        let volume = msth_core::volume::bake::bake_with(&plan, &mut |set| {
            bake_set_on_device(ctx, scene, &plan, cfg, layout, params, set)
        });
        Some(volume.map(|volume| BakedVolume { volume, plan }))
    }

    /// Takes the volume back (frames come from the exact field from now on).
    pub fn take_volume(&mut self) -> Option<BakedVolume> {
        self.cache = None;
        self.slice_error = None;
        self.volume.take().map(|(v, _)| v)
    }

    /// The volume frames are drawn from, if any.
    pub fn volume(&self) -> Option<&msth_core::volume::Volume> {
        self.volume.as_ref().map(|(v, _)| &v.volume)
    }

    /// Why the volume's time slices could not be baked, if they could not.
    pub fn slice_error(&self) -> Option<&str> {
        self.slice_error.as_deref()
    }

    /// Whether the next frame comes from the volume.
    pub fn uses_volume(&self) -> bool {
        self.volume.is_some() && !self.settings.exact && self.slice_error.is_none()
    }

    /// Switches between the exact field and the volume ([`RenderSettings::exact`]).
    pub fn set_exact(&mut self, exact: bool) {
        if self.settings.exact != exact {
            self.settings.exact = exact;
            self.cache = None;
        }
    }

    /// The most bytes a volume may take on this device by default
    /// ([`GpuContext::volume_budget`]).
    pub fn volume_budget(&self) -> u64 {
        self.ctx.volume_budget()
    }

    /// Lets one batch of rays of the per-sample passes take up to `bytes` of scratch memory
    /// (default: [`GpuContext::default_scratch_budget`], 1 GiB on a discrete GPU, else
    /// [`msth_gpu::FRAME_WORK_BYTES`], 128 MiB; the adapter's binding limit still applies): a
    /// frame of more rays than a batch holds renders in several batches, each a round of every
    /// pass. Larger batches mean fewer, fuller dispatches; the frame is the same.
    pub fn set_scratch_budget(&mut self, bytes: u64) {
        if bytes != self.scratch_budget {
            self.scratch_budget = bytes;
            self.scratch = None;
        }
    }

    /// Bytes of scratch one batch of rays may take ([`GpuRenderer::set_scratch_budget`]).
    pub fn scratch_budget(&self) -> u64 {
        self.scratch_budget
    }

    /// Promises that the parameters passed with the frames from now on hold the same values for
    /// as long as `version` stays the same (a player sets a new version each time it writes a
    /// new time chunk's parameters into its buffer). Frames then skip comparing the parameters
    /// with the device's copy, a pass over the whole buffer (tens of MB for a large model) per
    /// frame; a new version compares them and uploads what changed. Without a version (the
    /// default) every frame compares.
    pub fn set_params_version(&mut self, version: u64) {
        self.params_version = Some(version);
    }

    /// Rays per batch of the per-sample passes at the last frame's size (None before the
    /// first exact frame).
    pub fn batch_rays(&self) -> Option<u32> {
        self.scratch.as_ref().map(|(s, _)| s.capacity())
    }

    /// How the passes run the MLPs from the next parameter upload on (the default:
    /// [`GpuMlps::Specialised`]).
    pub fn set_mlps(&mut self, mlps: GpuMlps) {
        self.mlps = mlps;
        if mlps == GpuMlps::Generic {
            if let Some(s) = &mut self.scene {
                s.mlps_generic();
            }
            self.mlp_status = MlpStatus::Generic;
        }
    }

    /// Whether the frames use kernels compiled for the model, and how long that took.
    pub fn mlp_status(&self) -> &MlpStatus {
        &self.mlp_status
    }

    /// The most hash-table values the device held clamped at once (binary16 tables: values
    /// beyond ±65504; [`msth_gpu::GpuScene::clamped_table_values`]); 0 before the first frame.
    pub fn clamped_table_values(&self) -> usize {
        self.scene.as_ref().map_or(0, |s| s.clamped_table_values())
    }

    /// Uses the file's occupancy grid to skip empty space, as the CPU renderer's
    /// [`crate::render::Renderer::set_occupancy`] (`None`: a version-1 file, or skipping off):
    /// the per-sample passes evaluate the main field only at samples in occupied cells; the
    /// sample cache evaluates every sample. Forgets the static cache.
    pub fn set_occupancy(&mut self, grid: Option<Arc<OccupancyGrid>>) -> Result<(), GpuError> {
        if let Some(g) = &grid {
            msth_gpu::render::check_occupancy(g.resolution, &g.words)?;
        }
        self.occupancy = grid;
        self.cache = None;
        if let Some(scene) = &mut self.scene {
            apply_occupancy(&self.ctx, scene, self.occupancy.as_deref())?;
        }
        Ok(())
    }

    /// The device this renderer uses.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// Forgets the static cache: the next frame is rendered in full.
    pub fn invalidate(&mut self) {
        self.cache = None;
    }

    /// Fraction of the cached camera's pixels that are re-rendered every frame (`None` before
    /// the second frame of a fixed camera).
    pub fn dynamic_fraction(&self) -> Option<f32> {
        self.cache
            .as_ref()
            .filter(|c| c.deferred.is_none())
            .map(|c| c.dynamic.len() as f32 / c.total.max(1) as f32)
    }

    /// Samples the sample cache evaluates at every frame (`None` without one).
    pub fn dynamic_samples(&self) -> Option<u32> {
        self.cache
            .as_ref()
            .and_then(|c| c.samples.as_ref())
            .map(|s| s.dynamic_samples())
    }

    /// The list sizes of the last batch of per-sample passes that rendered pixels through the
    /// frame scratch (a full frame, or an incremental one without the sample cache; reads them
    /// back from the device); `None` before the first exact frame.
    pub fn last_pass_counts(&self) -> Option<Result<msth_gpu::PassCounts, GpuError>> {
        self.scratch.as_ref().map(|(s, _)| s.last_counts(&self.ctx))
    }

    fn upload(&mut self, params: &[f32]) -> Result<(), GpuError> {
        let promised =
            self.params_version.is_some() && self.params_version == self.uploaded_version;
        match &mut self.scene {
            Some(_) if promised => {}
            Some(s) => {
                // A failed upload leaves the device's copy unknown: no version until it succeeds.
                self.uploaded_version = None;
                s.update(&self.ctx, params)?;
            }
            None => {
                self.uploaded_version = None;
                let mut scene = GpuScene::new(&self.ctx, self.gpu_model.clone(), params)?;
                apply_occupancy(&self.ctx, &mut scene, self.occupancy.as_deref())?;
                self.scene = Some(scene);
            }
        }
        self.uploaded_version = self.params_version;
        Ok(())
    }

    /// Compiles the passes for the model ([`GpuMlps::Specialised`]) before its first exact frame
    /// (frames from a volume need none of them).
    fn specialise(&mut self) -> Result<(), GpuError> {
        let want = self.mlps == GpuMlps::Specialised;
        if let Some(scene) = &mut self.scene {
            if want && !scene.is_specialised() && !matches!(self.mlp_status, MlpStatus::Refused(_))
            {
                self.mlp_status = match scene.specialise(&self.ctx)? {
                    Ok(secs) => MlpStatus::Specialised(secs),
                    Err(why) => MlpStatus::Refused(why),
                };
            }
        }
        Ok(())
    }

    /// Renders `camera` at normalised time `time` with `params` (the flat buffer for that time).
    /// The probes of the static test render other times with `params` too (see
    /// [`GpuRenderer::render_probing`]).
    pub fn render(
        &mut self,
        camera: &Camera,
        time: f32,
        params: &[f32],
    ) -> Result<Frame, GpuError> {
        self.render_probing(camera, time, params, &mut |_| None)
    }

    /// [`GpuRenderer::render`], with `params_at(t)` giving the flat buffer for a probe time `t`
    /// when it differs from `params` (a file streamed in time chunks), as
    /// [`crate::render::Renderer::render_probing`].
    pub fn render_probing(
        &mut self,
        camera: &Camera,
        time: f32,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
    ) -> Result<Frame, GpuError> {
        let start = Instant::now();
        camera
            .validate()
            .map_err(|e| GpuError::Model(format!("camera: {e}")))?;
        self.upload(params)?;
        let still = crate::render::holds_still(&self.settings, &mut self.last_camera, camera);
        if self.uses_volume() && !still {
            let slice_seconds = self.bake_slices(time, params, params_at);
            if self.slice_error.is_none() {
                return self.render_volume(camera, time, start, slice_seconds);
            }
        }
        self.specialise()?;
        let (w, h) = (camera.width, camera.height);
        let total = w as usize * h as usize;
        let pixels32 = u32::try_from(total)
            .map_err(|_| GpuError::Model(format!("{w}x{h} pixels exceed 32-bit indices")))?;
        if self.scratch.as_ref().is_none_or(|(_, n)| *n != total) {
            self.scratch = None;
            let s =
                self.ctx
                    .frame_scratch_within(&self.gpu_model, pixels32, self.scratch_budget)?;
            self.scratch = Some((s, total));
        }
        let reuse = self.settings.incremental
            && self
                .cache
                .as_ref()
                .is_some_and(|c| c.camera == *camera && c.total == total);
        let mut stats = FrameStats {
            rays_total: total,
            ..Default::default()
        };
        let rgb = if reuse {
            let mut cache = self.cache.take().expect("checked above");
            let t = Instant::now();
            if let Some(t0) = cache.deferred.take() {
                let (frame, _) = self.frame.as_ref().expect("rendered by the full frame");
                let out = self.ctx.read_vec4(frame, total)?;
                (cache.shown, _) = frame_colours(&out);
                let p = frame_rays(camera, t0, &out);
                stats.classify = Some(self.classify(camera, params, params_at, p, &mut cache)?);
                stats.cache_seconds = t.elapsed().as_secs_f64();
            }
            let mut host = Instant::now();
            let scene = self.scene.as_ref().expect("uploaded above");
            if let (Some(list), Some(out)) = (&cache.dynamic_buf, &cache.dynamic_out) {
                // The dynamic pixels only, into their compact output; read back alone and
                // written into the host's copy of the frame.
                let n = cache.dynamic.len() as u32;
                let view = ViewU::new(camera, time, n, FLAG_LIST | FLAG_COMPACT);
                match &cache.samples {
                    Some(sc) => {
                        stats.samples_evaluated = sc.dynamic_samples() as usize;
                        self.ctx.render_sample_cache(scene, &view, sc, list, out)?;
                    }
                    None => {
                        let (scratch, _) = self.scratch.as_ref().expect("made above");
                        let px = Pixels::List {
                            list,
                            n,
                            compact: true,
                        };
                        self.ctx.render_passes(scene, &view, px, out, scratch)?;
                    }
                }
                host = Instant::now();
                // Written into the host's frame from the mapped staging buffer, kept between
                // frames (as the full frame's).
                let (dynamic, shown) = (&cache.dynamic, &mut cache.shown);
                self.ctx
                    .read_vec4_with(out, dynamic.len(), &mut self.readback, |v| {
                        for (&px, c) in dynamic.iter().zip(v) {
                            let at = 3 * px as usize;
                            shown[at..at + 3].copy_from_slice(&c[..3]);
                        }
                    })?;
            }
            stats.rays_rendered = cache.dynamic.len();
            stats.rays_empty = cache.empty;
            stats.rays_cached = total - cache.dynamic.len() - cache.empty;
            let rgb = cache.shown.clone();
            stats.host_seconds = host.elapsed().as_secs_f64();
            self.cache = Some(cache);
            rgb
        } else {
            // The frame buffer is about to change: a cache whose full frame waits there
            // (`Cache::deferred`) goes first, whether or not this frame succeeds.
            self.cache = None;
            if self.frame.as_ref().is_none_or(|(_, n)| *n < total) {
                self.frame = None;
                self.frame = Some((self.ctx.output_buffer("frame", total)?, total));
            }
            let scene = self.scene.as_ref().expect("uploaded above");
            let (frame, _) = self.frame.as_ref().expect("made above");
            let (scratch, _) = self.scratch.as_ref().expect("made above");
            let view = ViewU::new(camera, time, pixels32, 0);
            self.ctx
                .render_passes(scene, &view, Pixels::All(pixels32), frame, scratch)?;
            // The colours and the count of rays that missed the scene, straight from the
            // mapped staging buffer; the rays' list waits for the camera to stay.
            let host = Instant::now();
            let (rgb, empty) =
                self.ctx
                    .read_vec4_with(frame, total, &mut self.readback, frame_colours)?;
            stats.host_seconds = host.elapsed().as_secs_f64();
            stats.full = true;
            stats.rays_rendered = total - empty;
            stats.rays_empty = empty;
            self.cache = self.settings.incremental.then(|| Cache {
                camera: *camera,
                total,
                empty,
                dynamic: Vec::new(),
                dynamic_buf: None,
                dynamic_out: None,
                samples: None,
                deferred: Some(time),
                shown: Vec::new(),
            });
            rgb
        };
        stats.seconds = start.elapsed().as_secs_f64();
        Ok(Frame {
            width: w,
            height: h,
            rgb,
            stats,
        })
    }

    /// Bakes the time slices the volume needs at `time` that it does not hold, their vertices
    /// evaluated on the device ([`crate::volume::bake_set_on_device`]) or on the host
    /// ([`GpuRenderer::set_device_bake`]), each with the flat buffer
    /// at its own time (`params_at`, else `params`); returns the seconds spent. A slice that
    /// cannot be baked sends frames to the exact field ([`GpuRenderer::slice_error`]).
    fn bake_slices(
        &mut self,
        time: f32,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
    ) -> f64 {
        let start = Instant::now();
        let (Some((bv, _)), Some(scene)) = (self.volume.as_mut(), self.scene.as_mut()) else {
            return 0.0;
        };
        let (ctx, cfg, layout) = (&self.ctx, &self.cfg, &self.layout);
        let on_device = self.device_bake;
        let uploaded_version = &mut self.uploaded_version;
        let result = bv.bake_missing_slices(time, params, params_at, &mut |v, plan, k, p| {
            if !on_device {
                return crate::volume::bake_slice(v, plan, k, cfg, layout, p);
            }
            let device = |e: GpuError| BakeError::Device(e.to_string());
            // Another chunk's parameters for this slice: on the device for it, then the frame's
            // back.
            let other = !std::ptr::eq(p, params);
            if other {
                *uploaded_version = None;
                scene.update(ctx, p).map_err(device)?;
            }
            let n = bake_slice_with(v, plan, k, &mut |set| {
                bake_set_on_device(ctx, scene, plan, cfg, layout, p, set)
            })?;
            if other {
                scene.update(ctx, params).map_err(device)?;
            }
            Ok(n)
        });
        if let Err(e) = result {
            self.slice_error = Some(e.to_string());
        }
        start.elapsed().as_secs_f64()
    }

    /// A frame through the volume on the device: every pixel marched by `volume_march`, read
    /// back whole (no cache: a frame costs what a moving camera's does).
    fn render_volume(
        &mut self,
        camera: &Camera,
        time: f32,
        start: Instant,
        slice_seconds: f64,
    ) -> Result<Frame, GpuError> {
        let (w, h) = (camera.width, camera.height);
        let total = w as usize * h as usize;
        let pixels32 = u32::try_from(total)
            .map_err(|_| GpuError::Model(format!("{w}x{h} pixels exceed 32-bit indices")))?;
        // The frame buffer is about to change: the exact path's cache goes.
        self.cache = None;
        if self.frame.as_ref().is_none_or(|(_, n)| *n < total) {
            self.frame = None;
            self.frame = Some((self.ctx.output_buffer("frame", total)?, total));
        }
        let (bv, gv) = self.volume.as_mut().expect("uses_volume checked it");
        let vol = &bv.volume;
        let slices = vol.slices_for(msth_core::pipeline::sample_time(time));
        gv.bind_slices(&self.ctx, vol, slices)?;
        let scene = self.scene.as_ref().expect("uploaded by the caller");
        let (frame, _) = self.frame.as_ref().expect("made above");
        let view = ViewU::new(camera, time, pixels32, 0);
        let kernel = self
            .volume_kernel
            .as_ref()
            .expect("compiled with the volume");
        gv.render(&self.ctx, kernel, scene, &view, &self.settings.march, frame)?;
        let host = Instant::now();
        let (mut rgb, empty, outside) =
            self.ctx
                .read_vec4_with(frame, total, &mut self.readback, volume_colours)?;
        let mut host_seconds = host.elapsed().as_secs_f64();
        let exact_start = Instant::now();
        if !outside.is_empty() {
            // The rays that reached bricks the volume left out: the exact passes draw them.
            self.specialise()?;
            if self.scratch.is_none() {
                let s = self.ctx.frame_scratch_within(
                    &self.gpu_model,
                    pixels32,
                    self.scratch_budget,
                )?;
                self.scratch = Some((s, total));
            }
            let scene = self.scene.as_ref().expect("uploaded by the caller");
            let (scratch, _) = self.scratch.as_ref().expect("made above");
            let colours = render_list(&self.ctx, scene, scratch, camera, time, &outside, None)?;
            let host = Instant::now();
            for (&p, c) in outside.iter().zip(&colours) {
                rgb[3 * p as usize..3 * p as usize + 3].copy_from_slice(c);
            }
            host_seconds += host.elapsed().as_secs_f64();
        }
        let exact_seconds = exact_start.elapsed().as_secs_f64();
        let stats = FrameStats {
            rays_total: total,
            rays_rendered: total - empty,
            rays_empty: empty,
            rays_exact: outside.len(),
            exact_seconds,
            full: true,
            volume: true,
            slice_seconds,
            host_seconds,
            seconds: start.elapsed().as_secs_f64(),
            ..Default::default()
        };
        Ok(Frame {
            width: w,
            height: h,
            rgb,
            stats,
        })
    }

    /// Sorts the first frame's rays into static and dynamic ([`classify_static_with_stats`], probes on the
    /// device with their own time's parameters), uploads the dynamic pixels and, with
    /// [`Reuse::Samples`], builds the sample cache (falling back to whole rays when it would
    /// take more than `max_sample_cache_bytes` or the adapter's limits).
    fn classify(
        &mut self,
        camera: &Camera,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
        p: Pending,
        cache: &mut Cache,
    ) -> Result<ClassifyStats, GpuError> {
        let ctx = &self.ctx;
        let scene = self.scene.as_mut().expect("uploaded before");
        let (scratch, _) = self.scratch.as_ref().expect("made by the frame");
        // The probes upload other times' parameters and then the frame's again; should one
        // fail, the device's copy is unknown.
        let version = self.uploaded_version.take();
        let (flags, counts) = classify_static_with_stats(
            &self.cfg,
            &self.layout,
            params,
            &self.settings,
            &p.rays,
            &p.rgb,
            &p.visible_depth,
            |idx, t| {
                let px: Vec<u32> = idx.iter().map(|&i| p.pixels[i]).collect();
                let other = params_at(t);
                if let Some(o) = &other {
                    scene.update(ctx, o)?;
                }
                let out = render_list(ctx, scene, scratch, camera, t, &px, None);
                if other.is_some() {
                    scene.update(ctx, params)?;
                }
                out
            },
        )?;
        self.uploaded_version = version;
        cache.dynamic = p
            .pixels
            .iter()
            .zip(flags)
            .filter(|(_, s)| !s)
            .map(|(&px, _)| px)
            .collect();
        cache.dynamic_buf = None;
        cache.dynamic_out = None;
        cache.samples = None;
        if cache.dynamic.is_empty() {
            return Ok(counts);
        }
        let list = ctx.storage_buffer(
            "dynamic pixels",
            bytemuck::cast_slice(&cache.dynamic),
            false,
        )?;
        let out = ctx.output_buffer("dynamic pixels' colours", cache.dynamic.len())?;
        if self.settings.reuse == Reuse::Samples {
            let n = cache.dynamic.len() as u32;
            let samples = partition_samples(&self.cfg, &self.settings) as u32;
            let bytes = GpuContext::sample_cache_bytes(&self.gpu_model, n as u64, samples as u64);
            if bytes <= self.settings.max_sample_cache_bytes {
                let times = partition_times(&self.cfg, &self.settings);
                let view = ViewU::new(camera, 0.0, n, FLAG_LIST | FLAG_COMPACT);
                match ctx.build_sample_cache(
                    scene,
                    &view,
                    &list,
                    n,
                    &times,
                    samples,
                    self.settings.sample_cutoff,
                    &out,
                ) {
                    Ok(c) => cache.samples = Some(c),
                    // Beyond the adapter's buffer limits: whole rays, as over the budget.
                    Err(GpuError::Limit { .. }) => {}
                    Err(e) => return Err(e),
                }
            }
        }
        cache.dynamic_buf = Some(list);
        cache.dynamic_out = Some(out);
        Ok(counts)
    }
}

/// The rays of a full frame that the kernels evaluated (`out`, its output; a negative visible
/// depth marks a ray that missed the scene under a constant background, never evaluated, as in
/// the CPU renderer): their pixels, rays, colours and visible depths.
fn frame_rays(camera: &Camera, time: f32, out: &[[f32; 4]]) -> Pending {
    use rayon::prelude::*;
    let w = camera.width as usize;
    // Row by row on every thread, in order: a 1352x1014 frame's rays took 130-270 ms on one
    // core, more than an H200 takes to render the frame.
    let rows: Vec<Pending> = out
        .par_chunks(w.max(1))
        .enumerate()
        .map(|(y, row)| {
            let mut p = Pending::default();
            for (x, v) in row.iter().enumerate() {
                if v[3] < 0.0 {
                    continue;
                }
                p.pixels.push((y * w + x) as u32);
                p.rays
                    .push(TimedRay::through_pixel(camera, x as u32, y as u32, time));
                p.rgb.push([v[0], v[1], v[2]]);
                p.visible_depth.push(v[3]);
            }
            p
        })
        .collect();
    let n = rows.iter().map(|p| p.pixels.len()).sum();
    let mut all = Pending {
        pixels: Vec::with_capacity(n),
        rays: Vec::with_capacity(n),
        rgb: Vec::with_capacity(n),
        visible_depth: Vec::with_capacity(n),
    };
    for p in rows {
        all.pixels.extend(p.pixels);
        all.rays.extend(p.rays);
        all.rgb.extend(p.rgb);
        all.visible_depth.extend(p.visible_depth);
    }
    all
}

/// A full frame's colours (row-major RGB) from its output, and how many of its rays missed the
/// scene (negative visible depth); on every thread, row blocks in order.
fn frame_colours(out: &[[f32; 4]]) -> (Vec<f32>, usize) {
    use rayon::prelude::*;
    const BLOCK: usize = 16 * 1024;
    let mut rgb = vec![0f32; 3 * out.len()];
    let empty = rgb
        .par_chunks_mut(3 * BLOCK)
        .zip(out.par_chunks(BLOCK))
        .map(|(to, from)| {
            let mut empty = 0;
            for (c, v) in to.chunks_exact_mut(3).zip(from) {
                c.copy_from_slice(&v[..3]);
                empty += usize::from(v[3] < 0.0);
            }
            empty
        })
        .sum();
    (rgb, empty)
}

/// The visible depth `volume.wgsl` writes for a ray that reached a brick the volume left out.
const OUTSIDE_DEPTH: f32 = -2.0;

/// A volume frame's colours, its count of rays that missed the scene, and its pixels whose rays
/// reached a brick the volume left out (their colours still to draw).
fn volume_colours(out: &[[f32; 4]]) -> (Vec<f32>, usize, Vec<u32>) {
    let (rgb, missed) = frame_colours(out);
    let outside: Vec<u32> = (0..out.len() as u32)
        .filter(|&p| out[p as usize][3] == OUTSIDE_DEPTH)
        .collect();
    (rgb, missed - outside.len(), outside)
}

fn apply_occupancy(
    ctx: &GpuContext,
    scene: &mut GpuScene,
    grid: Option<&OccupancyGrid>,
) -> Result<(), GpuError> {
    scene.set_occupancy(ctx, grid.map(|g| (g.resolution, g.words.as_slice())))
}

/// Renders the listed pixels of `camera` at `time` into a compact output and reads their colours
/// back (probes), with the per-sample passes through `scratch`; `visible`, when given, receives
/// the visible depths.
pub(crate) fn render_list(
    ctx: &GpuContext,
    scene: &GpuScene,
    scratch: &FrameScratch,
    camera: &Camera,
    time: f32,
    pixels: &[u32],
    visible: Option<&mut Vec<f32>>,
) -> Result<Vec<[f32; 3]>, GpuError> {
    if pixels.is_empty() {
        return Ok(Vec::new());
    }
    let list = ctx.storage_buffer("pixel list", bytemuck::cast_slice(pixels), false)?;
    let out = ctx.output_buffer("probe colours", pixels.len())?;
    let n = pixels.len() as u32;
    let view = ViewU::new(camera, time, n, FLAG_LIST | FLAG_COMPACT);
    let px = Pixels::List {
        list: &list,
        n,
        compact: true,
    };
    ctx.render_passes(scene, &view, px, &out, scratch)?;
    let v = ctx.read_vec4(&out, pixels.len())?;
    if let Some(vis) = visible {
        vis.clear();
        vis.extend(v.iter().map(|x| x[3]));
    }
    Ok(v.iter().map(|x| [x[0], x[1], x[2]]).collect())
}
