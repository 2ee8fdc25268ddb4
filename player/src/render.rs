//! Incremental rendering on the CPU, the paper's playback trick (method.md §5).
//!
//! For a fixed camera the first frame is rendered in full. A ray is then *static* when the
//! learned mask says "static" (`m >= threshold`) everywhere along the part of the ray that can be
//! seen: from where it enters the scene to where the first frame's transmittance falls below
//! [`msth_core::pipeline::VISIBLE_TRANSMITTANCE`] (the surface it hits). Static rays keep their first-frame colour;
//! later frames re-render only the other rays. Checking the whole visible segment, not only the
//! samples that carried weight in frame 0, matters: empty space that a moving object enters later
//! is still marked dynamic by the mask, so the ray is re-rendered when the object arrives. A new
//! camera (or [`Renderer::invalidate`]) renders everything again.
//!
//! Empty space is skipped: rays that miss the scene box are never evaluated (they show the
//! background), the proposal field concentrates the samples of the others on surfaces, samples
//! in cells the file's occupancy grid marks empty skip the main field ([`crate::empty_space`],
//! [`Renderer::set_occupancy`]), and samples hidden behind surfaces skip the colour decoder
//! ([`msth_core::pipeline`]).
//!
//! Everything renders the parameters given, i.e. the decoded (quantised) model as shipped.

use std::sync::Arc;
use std::time::Instant;

use msth_codec::OccupancyGrid;

use msth_core::config::{Background, ModelConfig};
use msth_core::field::ModelLayout;
use msth_core::pipeline::{ray_limits, render_chunk, spacing_unit, RenderOutput, TimedRay};
use msth_core::Camera;
use rayon::prelude::*;

use msth_core::volume::{MarchOutput, MarchSettings, Volume};

use crate::volume::BakedVolume;

use crate::empty_space::{render_chunk_skipping, SkipWorkspace};
use crate::samples::{cache_bytes_bound, SampleCache};

/// How frames are rendered.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderSettings {
    /// Re-render only dynamic rays while the camera stays still.
    pub incremental: bool,
    /// A ray is static when the mask is at least this along its visible part (1 = static).
    pub static_threshold: f32,
    /// A static ray whose mask is at least this along its visible part is cached on the mask's
    /// word alone; static rays below it (the mask is uncertain there) go through the probes.
    /// Above 1: every static ray is probed; at or below `static_threshold`: none is.
    pub trust_threshold: f32,
    /// Probe the rays the mask alone caches too, only to count how often the probes disagree
    /// with the mask ([`ClassifyStats::trusted_disagree`]); the rays stay cached either way.
    pub audit_mask: bool,
    /// Mask lookups per ray for the static test, per mask-grid cell along the scene.
    pub mask_steps_per_cell: f32,
    /// Times (evenly over `time_range`, ends included) at which the rays the mask calls static are
    /// rendered once more when the cache is built; a ray whose colour changes by more than
    /// `probe_tolerance` at any of them is re-rendered every frame after all. 0 trusts the mask.
    pub probes: usize,
    /// Largest colour change (per channel, `[0, 1]` scale) a probe may show for a static ray.
    pub probe_tolerance: f32,
    /// What a frame re-evaluates on the dynamic rays (CPU renderer; the GPU re-renders rays).
    pub reuse: Reuse,
    /// [`Reuse::Samples`]: times at which the proposal field places the fixed samples, evenly
    /// over `time_range` (0: the model's frame count, at most [`DEFAULT_PARTITION_TIMES`]).
    pub partition_times: usize,
    /// [`Reuse::Samples`]: fixed samples per dynamic ray (0: the model's main samples).
    pub partition_samples: usize,
    /// [`Reuse::Samples`]: samples whose dynamic weight `1 - m` is below this are evaluated once.
    pub sample_cutoff: f32,
    /// [`Reuse::Samples`]: the most memory the sample cache may take; a larger one falls back
    /// to [`Reuse::Rays`] for that camera.
    pub max_sample_cache_bytes: u64,
    /// The times the playback will show (`[a, b]`, normalised): probes and the fixed samples
    /// cover this range.
    pub time_range: (f32, f32),
    /// GPU renderer: how the device holds the hash tables (binary16 halves their memory and
    /// reads, at a relative error of 2^-11 per value). The CPU renderer reads the parameters as
    /// given.
    pub gpu_tables: msth_gpu::TableFormat,
    /// GPU renderer: samples per invocation of the per-sample passes (1, 2 or 4; `None`:
    /// [`msth_gpu::DEFAULT_LANES`]). Frames are the same whatever the lanes.
    pub gpu_lanes: Option<u32>,
    /// Render with the exact field per sample even when a baked volume is set
    /// ([`Renderer::set_volume`]): the reference path (`msth play` without `--volume`).
    pub exact: bool,
    /// How rays walk the volume.
    pub march: MarchSettings,
    /// When the CPU renderer bakes the volume's time slices (the GPU renderer always does).
    pub slices: SlicePolicy,
    /// With a volume and `incremental`: keep drawing from the volume while the camera holds
    /// still. By default a camera that holds (the same camera as the previous frame) goes to
    /// the exact path's incremental cache, which re-evaluates only the dynamic samples of its
    /// dynamic rays (on the stage model at 256x256, 0.05 s a frame against 0.9 s re-marching
    /// the volume's dynamic rays with the time moving), and the volume draws the moving camera.
    pub volume_when_still: bool,
}

/// When the CPU renderer bakes a volume's time slices for a frame that lacks them; until then
/// the frame evaluates its dynamic bricks' samples from the exact field.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SlicePolicy {
    /// Once the exact evaluations spent on frames that needed the same missing slices reach
    /// what baking them costs (a slice's vertices): a playback that holds its time bakes after
    /// a few frames, one whose time moves to new slices every frame never pays for a slice it
    /// uses once. At most twice the cheaper of the two.
    #[default]
    Auto,
    /// Before the first frame that needs them.
    Always,
}

impl RenderSettings {
    /// The `j`-th of `k` times spread evenly over [`RenderSettings::time_range`], ends
    /// included (its middle when `k` is 1); a range that is not within `[0, 1]` counts as
    /// `[0, 1]`.
    pub fn clip_time(&self, j: usize, k: usize) -> f32 {
        let (a, b) = self.time_range;
        let ok = |v: f32| (0.0..=1.0).contains(&v);
        let (a, b) = if ok(a) && ok(b) {
            (a.min(b), a.max(b))
        } else {
            (0.0, 1.0)
        };
        if k > 1 {
            a + (b - a) * j as f32 / (k - 1) as f32
        } else {
            0.5 * (a + b)
        }
    }
}

/// What incremental frames re-evaluate on the rays that are not cached whole.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Reuse {
    /// The whole ray, as a full frame does (proposal, resampling, every sample): frames equal
    /// full renders.
    Rays,
    /// Fixed samples per ray ([`crate::samples`]); only the samples the mask leaves dynamic are
    /// evaluated, without a proposal pass.
    #[default]
    Samples,
}

/// Default of [`RenderSettings::probe_tolerance`], about 8/255. Chosen with sample-level reuse
/// on the built-in scene and the stage: against 1/255 it caches more rays and gives *higher*
/// PSNR against full renders (40.7 against 40.2 dB on the built-in scene), because a ray left
/// dynamic goes through the fixed samples, which differ from full renders by more than this.
/// Three probes (0, 0.5, 1) gave the same PSNR as five, with a third less cache-build time.
pub const DEFAULT_PROBE_TOLERANCE: f32 = 0.03;

/// Default of [`RenderSettings::trust_threshold`]: a ray whose mask stays at or above this along
/// its visible part is cached without probes (docs/mask-learning.md, "The mask decides": on the
/// built-in scene the probes disagree with about 1% of such rays).
pub const DEFAULT_TRUST_THRESHOLD: f32 = 0.9;

/// Default of [`RenderSettings::static_threshold`]: rays whose mask stays between this and
/// [`DEFAULT_TRUST_THRESHOLD`] are probed; below it they are re-rendered every frame.
pub const DEFAULT_STATIC_THRESHOLD: f32 = 0.5;

/// Default of [`RenderSettings::sample_cutoff`]: a sample whose dynamic weight `1 - m` is below
/// 5% is evaluated once (chosen on the built-in scene; `msth bench play` measures the effect).
pub const DEFAULT_SAMPLE_CUTOFF: f32 = 0.05;

/// Default of [`RenderSettings::partition_times`] (fewer for models with fewer frames): on the
/// built-in scene and the stage, 8 times give the same PSNR against full renders as one per
/// frame (20 and 30), at a third of the cost.
pub const DEFAULT_PARTITION_TIMES: usize = 8;

/// Upper bound of [`RenderSettings::partition_times`].
pub const MAX_PARTITION_TIMES: usize = 32;

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            incremental: true,
            static_threshold: DEFAULT_STATIC_THRESHOLD,
            trust_threshold: DEFAULT_TRUST_THRESHOLD,
            audit_mask: false,
            mask_steps_per_cell: 4.0,
            probes: 3,
            probe_tolerance: DEFAULT_PROBE_TOLERANCE,
            reuse: Reuse::default(),
            partition_times: 0,
            partition_samples: 0,
            sample_cutoff: DEFAULT_SAMPLE_CUTOFF,
            max_sample_cache_bytes: 2 << 30,
            time_range: (0.0, 1.0),
            gpu_tables: msth_gpu::TableFormat::F32,
            gpu_lanes: None,
            exact: false,
            march: MarchSettings::default(),
            slices: SlicePolicy::default(),
            volume_when_still: false,
        }
    }
}

/// Whether `camera` is the previous frame's (`last`, which becomes `camera`) for a playback
/// that sends a still camera to the exact incremental cache
/// ([`RenderSettings::volume_when_still`] off, `incremental` on).
pub(crate) fn holds_still(
    settings: &RenderSettings,
    last: &mut Option<Camera>,
    camera: &Camera,
) -> bool {
    let held = last.replace(*camera) == Some(*camera);
    held && settings.incremental && !settings.volume_when_still
}

/// What one frame cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct FrameStats {
    /// Rays evaluated for this frame.
    pub rays_rendered: usize,
    /// Pixels in the frame.
    pub rays_total: usize,
    /// Pixels served from the static cache.
    pub rays_cached: usize,
    /// Pixels that miss the scene (background, never evaluated).
    pub rays_empty: usize,
    /// Whether the frame was rendered in full (first frame or a new camera).
    pub full: bool,
    /// Wall time of the frame, `cache_seconds` included.
    pub seconds: f64,
    /// Time spent sorting the first frame's rays into static and dynamic (the second frame of a
    /// fixed camera pays it, so that the first frame is not delayed), and building the sample
    /// cache.
    pub cache_seconds: f64,
    /// Samples evaluated at this frame on rays with sample-level reuse (0 otherwise).
    pub samples_evaluated: usize,
    /// GPU frames: host time after the device finished the frame's passes (reading the output
    /// back, converting it to the frame's colours); 0 on the CPU.
    pub host_seconds: f64,
    /// How the static cache was sorted, on the frame that sorted it (the second of a camera).
    pub classify: Option<ClassifyStats>,
    /// Whether the frame was drawn from the baked volume (else from the exact field).
    pub volume: bool,
    /// Volume frames: samples composited (static and dynamic).
    pub volume_samples: usize,
    /// Volume frames: steps of the march, samples and skips of empty cells and bricks alike
    /// (counted on the CPU): the walk's cost beside the samples'.
    pub volume_steps: usize,
    /// Volume frames: time spent baking the dynamic bricks' time slices this frame needed.
    pub slice_seconds: f64,
    /// Volume frames: rays drawn by the exact path because they reach bricks the volume left
    /// out (none of the file's cameras looks into them).
    pub rays_exact: usize,
    /// Volume frames: the time those rays took.
    pub exact_seconds: f64,
}

/// How one camera's rays were sorted into cached and re-rendered ([`classify_static_with_stats`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct ClassifyStats {
    /// Rays sorted (the camera's rays that hit the scene).
    pub rays: usize,
    /// Rays the mask alone caches (mask at least `trust_threshold` along the visible part).
    pub trusted: usize,
    /// Rays the mask calls static but not surely (between `static_threshold` and
    /// `trust_threshold`): probed.
    pub probed: usize,
    /// Of those, the rays the probes kept static (cached).
    pub probed_static: usize,
    /// With [`RenderSettings::audit_mask`]: trusted rays whose colour moved by more than the
    /// probe tolerance at a probe time (the mask and the probes disagree); `None` without audit
    /// or without probes.
    pub trusted_disagree: Option<usize>,
}

impl ClassifyStats {
    /// Rays cached: trusted plus probed-and-static.
    pub fn cached(&self) -> usize {
        self.trusted + self.probed_static
    }
}

/// A rendered frame: linear RGB in `[0, 1]`, row-major, 3 floats per pixel.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
    pub stats: FrameStats,
}

impl Frame {
    /// PSNR (dB) against `other` of the same size, of the colours as displayed (clamped to
    /// `[0, 1]`); 200 dB for identical frames.
    pub fn psnr_displayed(&self, other: &Frame) -> f64 {
        let mse = self
            .rgb
            .iter()
            .zip(&other.rgb)
            .map(|(x, y)| ((x.clamp(0.0, 1.0) - y.clamp(0.0, 1.0)) as f64).powi(2))
            .sum::<f64>()
            / self.rgb.len().max(1) as f64;
        -10.0 * mse.max(1e-20).log10()
    }

    /// 8-bit RGB, rounded.
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.rgb
            .iter()
            .map(|&v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
            .collect()
    }
}

/// The static cache of one camera.
struct Cache {
    camera: Camera,
    rgb: Vec<f32>,
    /// Pixels re-rendered every frame, and their rays.
    dynamic: Vec<u32>,
    rays: Vec<TimedRay>,
    /// Sample-level reuse of `rays` ([`Reuse::Samples`]).
    samples: Option<SampleCache>,
    empty: usize,
    /// The first frame's evaluated rays, until the second frame classifies them (so that the
    /// first frame is shown without waiting for the static test and the probes).
    pending: Option<Pending>,
    /// How the rays were sorted, once they are.
    classified: Option<ClassifyStats>,
}

struct Pending {
    pixels: Vec<u32>,
    rays: Vec<TimedRay>,
    rgb: Vec<[f32; 3]>,
    visible_depth: Vec<f32>,
}

/// Renders frames of one model, keeping the static cache between frames.
pub struct Renderer {
    cfg: ModelConfig,
    layout: ModelLayout,
    settings: RenderSettings,
    cache: Option<Cache>,
    /// The file's occupancy grid: samples in empty cells are skipped ([`crate::empty_space`]).
    occupancy: Option<Arc<OccupancyGrid>>,
    /// The baked volume frames are drawn from ([`Renderer::set_volume`]).
    volume: Option<BakedVolume>,
    /// Why the volume's time slices could not be baked, if they could not (its dynamic bricks
    /// are then evaluated exactly).
    slice_error: Option<String>,
    /// The volume path's cache of one camera.
    volume_cache: Option<VolumeCache>,
    /// [`SlicePolicy::Auto`]: the slices the last frames lacked, and the dynamic samples they
    /// evaluated exactly instead.
    slice_debt: (Vec<usize>, usize),
    /// The previous frame's camera ([`RenderSettings::volume_when_still`]).
    last_camera: Option<Camera>,
    /// Field evaluations one time slice of the volume costs ([`msth_core::volume::BakePlan::slice_evaluations`],
    /// counted once per volume).
    slice_cost: usize,
}

/// The volume path's cache of one camera: the last frame, and the pixels whose rays met a
/// dynamic sample (re-rendered at every frame; the others do not depend on time).
struct VolumeCache {
    camera: Camera,
    /// Whether its frame read the time slices (else its dynamic bricks were exact): a frame of
    /// the other kind renders every pixel.
    sliced: bool,
    rgb: Vec<f32>,
    dynamic: Vec<u32>,
    rays: Vec<TimedRay>,
    empty: usize,
}

/// Most rays per work item of the parallel loop.
const CHUNK: usize = 256;

/// Side of the square tiles in which the volume's rays are marched: neighbouring rays cross the
/// same bricks, so a tile's rays find them in the cache where a row's would not.
const MARCH_TILE: u32 = 8;

/// The pixels of a `w x h` frame, `tile x tile` squares at a time (row by row within a square,
/// squares row by row); a tile of 1 is plain row order.
fn tile_order(w: u32, h: u32, tile: u32) -> impl Iterator<Item = (u32, u32)> {
    let tile = tile.max(1);
    (0..h.div_ceil(tile)).flat_map(move |ty| {
        (0..w.div_ceil(tile)).flat_map(move |tx| {
            let (y0, x0) = (ty * tile, tx * tile);
            (y0..(y0 + tile).min(h))
                .flat_map(move |y| (x0..(x0 + tile).min(w)).map(move |x| (x, y)))
        })
    })
}

/// Scratch memory one rendering thread may use for one batch of rays, bytes. The scratch grows
/// with rays x samples x the floats kept per sample; batches are sized to stay near this, so
/// that a file asking for many samples per ray gets smaller batches, not more memory (the
/// paper's 128 + 48 samples give whole batches of 256 rays at about 30 MiB).
pub const BATCH_SCRATCH_BYTES: u64 = 64 << 20;

/// Bytes of rendering scratch one ray of `cfg` takes (an upper estimate of what
/// `msth_core::pipeline`'s `Workspace` keeps per sample: points, intervals, weights, both
/// encodings' 3D/4D/blended features and mask, every MLP activation, colours; doubled for the
/// buffers packed and copied along the way).
pub fn scratch_bytes_per_ray(cfg: &ModelConfig) -> u64 {
    let enc_dim = |e: &msth_core::config::EncodingConfig| {
        let g3 = e.grid3.levels as u64 * e.grid3.features_per_level as u64;
        let g4 = e.grid4.levels as u64 * e.grid4.features_per_level as u64;
        3 * g3.max(g4) + 2
    };
    let f = &cfg.field;
    let per_proposal = 12 + enc_dim(&cfg.proposal.encoding) + cfg.proposal.hidden as u64 + 2;
    let color_in = msth_core::sh::SH_COEFFS as u64 + f.geo_features as u64;
    let per_main = 16
        + enc_dim(&f.encoding)
        + f.density_hidden as u64
        + 1
        + f.geo_features as u64
        + color_in
        + f.color_hidden as u64 * f.color_layers as u64
        + 8;
    let s = &cfg.sampler;
    2 * 4 * (s.num_proposal_samples as u64 * per_proposal + s.num_samples as u64 * per_main)
}

/// Rays per batch for `cfg`: as many as fit [`BATCH_SCRATCH_BYTES`], between 1 and `most`.
pub fn rays_per_batch(cfg: &ModelConfig, most: usize) -> usize {
    let per_ray = scratch_bytes_per_ray(cfg).max(1);
    ((BATCH_SCRATCH_BYTES / per_ray) as usize).clamp(1, most.max(1))
}

/// Renders `rays` in parallel, in order, in batches of [`rays_per_batch`] rays.
pub fn render_rays(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
) -> RenderOutput {
    render_rays_skipping(cfg, layout, params, rays, None)
}

/// [`render_rays`], skipping the main field's samples in the cells `occupancy` marks empty
/// ([`crate::empty_space`]; `None` evaluates every sample).
pub fn render_rays_skipping(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    occupancy: Option<&OccupancyGrid>,
) -> RenderOutput {
    let parts: Vec<RenderOutput> = rays
        .par_chunks(rays_per_batch(cfg, CHUNK))
        .map_init(SkipWorkspace::default, |ws, c| {
            let mut out = RenderOutput::default();
            match occupancy {
                Some(g) => render_chunk_skipping(cfg, layout, params, c, g, ws, &mut out),
                None => render_chunk(cfg, layout, params, c, ws.core(), &mut out),
            }
            out
        })
        .collect();
    let mut out = RenderOutput::default();
    for p in parts {
        out.rgb.extend(p.rgb);
        out.depth.extend(p.depth);
        out.opacity.extend(p.opacity);
        out.mask.extend(p.mask);
        out.min_mask.extend(p.min_mask);
        out.visible_depth.extend(p.visible_depth);
    }
    out
}

/// The smallest mask value along `ray` from its entry into the scene to `visible_end` (1 for a ray
/// that misses the scene). Lookups are uniform in the sampler's spacing coordinate, `steps` of
/// them over the ray's whole interval; the walk stops early once the minimum is below `floor`
/// (the caller's lowest threshold: the exact value below it does not matter). Without a mask
/// the value is the encoding's constant mask (1 for a model with no 4D part, 0 otherwise).
pub fn ray_min_mask(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    ray: &TimedRay,
    visible_end: f32,
    steps: usize,
    floor: f32,
) -> f32 {
    let enc = &layout.field.encoding;
    if enc.mask.is_none() {
        return enc.mask_at(params, &[0.0; 3]);
    }
    let (near, far) = ray_limits(cfg, ray);
    if far <= near {
        return 1.0;
    }
    let unit = spacing_unit(&cfg.bounds);
    let steps = steps.max(1);
    let mut min = 1.0f32;
    for k in 0..=steps {
        let s = k as f32 / steps as f32;
        let t = cfg.sampler.spacing.t_of_s(s, near, far, unit);
        if t > visible_end {
            break;
        }
        let u = cfg.bounds.to_unit(ray.origin + ray.dir * t);
        min = min.min(enc.mask_at(params, &[u.x, u.y, u.z]));
        if min < floor {
            break;
        }
    }
    min
}

impl Renderer {
    pub fn new(cfg: &ModelConfig, settings: RenderSettings) -> Self {
        Renderer {
            cfg: cfg.clone(),
            layout: ModelLayout::new(cfg),
            settings,
            cache: None,
            occupancy: None,
            volume: None,
            slice_error: None,
            volume_cache: None,
            slice_debt: (Vec::new(), 0),
            last_camera: None,
            slice_cost: 0,
        }
    }

    /// Draws frames from `volume` (unless [`RenderSettings::exact`]); `None` returns to the
    /// exact field. Forgets the caches.
    pub fn set_volume(&mut self, volume: Option<BakedVolume>) {
        self.volume = volume;
        self.slice_error = None;
        self.cache = None;
        self.volume_cache = None;
        self.slice_debt = (Vec::new(), 0);
        self.slice_cost = self
            .volume
            .as_ref()
            .map_or(0, |v| v.plan.slice_evaluations());
    }

    /// Takes the volume back (frames come from the exact field from now on); forgets the
    /// caches.
    pub fn take_volume(&mut self) -> Option<BakedVolume> {
        let v = self.volume.take();
        if v.is_some() {
            self.set_volume(None);
        }
        v
    }

    /// The volume frames are drawn from, if any.
    pub fn volume(&self) -> Option<&Volume> {
        self.volume.as_ref().map(|v| &v.volume)
    }

    /// Why the volume's time slices could not be baked, if they could not.
    pub fn slice_error(&self) -> Option<&str> {
        self.slice_error.as_deref()
    }

    /// Whether the next frame comes from the volume.
    pub fn uses_volume(&self) -> bool {
        self.volume.is_some() && !self.settings.exact
    }

    /// Switches between the exact field and the volume ([`RenderSettings::exact`]).
    pub fn set_exact(&mut self, exact: bool) {
        if self.settings.exact != exact {
            self.settings.exact = exact;
            self.cache = None;
            self.volume_cache = None;
        }
    }

    /// Uses the file's occupancy grid to skip empty space (`None`: a version-1 file, or
    /// skipping off); forgets the cache, whose frame was rendered with the previous setting.
    pub fn set_occupancy(&mut self, grid: Option<Arc<OccupancyGrid>>) {
        self.occupancy = grid;
        self.cache = None;
    }

    fn render_rays(&self, params: &[f32], rays: &[TimedRay]) -> RenderOutput {
        render_rays_skipping(
            &self.cfg,
            &self.layout,
            params,
            rays,
            self.occupancy.as_deref(),
        )
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// Forgets the static cache: the next frame is rendered in full.
    pub fn invalidate(&mut self) {
        self.cache = None;
        self.volume_cache = None;
    }

    /// Fraction of the cached camera's pixels that are re-rendered every frame (`None` before
    /// the first frame).
    pub fn dynamic_fraction(&self) -> Option<f32> {
        if self.uses_volume() {
            return self
                .volume_cache
                .as_ref()
                .map(|c| c.dynamic.len() as f32 / (c.rgb.len() / 3).max(1) as f32);
        }
        self.cache
            .as_ref()
            .filter(|c| c.pending.is_none())
            .map(|c| c.dynamic.len() as f32 / (c.rgb.len() / 3).max(1) as f32)
    }

    /// Renders `camera` at normalised time `time` with `params` (the flat buffer for that time).
    /// The probes of the static test render other times with `params` too: right for a model
    /// decoded whole, not for one streamed in time chunks ([`Renderer::render_probing`]).
    pub fn render(&mut self, camera: &Camera, time: f32, params: &[f32]) -> Frame {
        self.render_probing(camera, time, params, &mut |_| None)
    }

    /// [`Renderer::render`], with `params_at(t)` giving the flat buffer for a probe time `t`
    /// when it differs from `params` (a file streamed in time chunks holds only the current
    /// chunk's 4D rows); `None` means `params` serves.
    pub fn render_probing(
        &mut self,
        camera: &Camera,
        time: f32,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
    ) -> Frame {
        let still = holds_still(&self.settings, &mut self.last_camera, camera);
        if self.uses_volume() && !still {
            return self.render_volume(camera, time, params, params_at);
        }
        let start = Instant::now();
        let (w, h) = (camera.width, camera.height);
        let total = w as usize * h as usize;
        let reuse = self.settings.incremental
            && self
                .cache
                .as_ref()
                .is_some_and(|c| c.camera == *camera && c.rgb.len() == total * 3);
        let mut stats = FrameStats {
            rays_total: total,
            ..Default::default()
        };
        let rgb = if reuse {
            let mut cache = self.cache.take().expect("checked above");
            if let Some(p) = cache.pending.take() {
                let t = Instant::now();
                self.classify(params, params_at, p, &mut cache);
                stats.cache_seconds = t.elapsed().as_secs_f64();
                stats.classify = cache.classified;
            }
            let colours = match &cache.samples {
                Some(sc) => {
                    stats.samples_evaluated = sc.dynamic_samples();
                    sc.render(&self.cfg, &self.layout, params, time)
                }
                None => {
                    for r in &mut cache.rays {
                        r.time = time;
                    }
                    self.render_rays(params, &cache.rays).rgb
                }
            };
            let mut rgb = cache.rgb.clone();
            for (&p, c) in cache.dynamic.iter().zip(&colours) {
                rgb[p as usize * 3..p as usize * 3 + 3].copy_from_slice(c);
            }
            stats.rays_rendered = cache.rays.len();
            stats.rays_empty = cache.empty;
            stats.rays_cached = total - cache.rays.len() - cache.empty;
            self.cache = Some(cache);
            rgb
        } else {
            let (rgb, cache) = self.render_full(camera, time, params);
            stats.full = true;
            stats.rays_rendered = total - cache.empty;
            stats.rays_empty = cache.empty;
            self.cache = self.settings.incremental.then_some(cache);
            rgb
        };
        stats.seconds = start.elapsed().as_secs_f64();
        Frame {
            width: w,
            height: h,
            rgb,
            stats,
        }
    }

    /// A frame through the volume: every pixel for a new camera, else only the pixels whose rays
    /// met a dynamic sample (the others do not depend on time, so the frame equals a full one).
    fn render_volume(
        &mut self,
        camera: &Camera,
        time: f32,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
    ) -> Frame {
        let start = Instant::now();
        let slice_seconds = self.bake_slices(time, params, params_at);
        let vol = &self.volume.as_ref().expect("uses_volume checked it").volume;
        let sliced = vol.dynamic.ready_for(time);
        let (w, h) = (camera.width, camera.height);
        let total = w as usize * h as usize;
        let mut stats = FrameStats {
            rays_total: total,
            volume: true,
            slice_seconds,
            ..Default::default()
        };
        let reuse = self.settings.incremental
            && self.volume_cache.as_ref().is_some_and(|c| {
                c.camera == *camera && c.sliced == sliced && c.rgb.len() == total * 3
            });
        let rgb = if reuse {
            let mut cache = self.volume_cache.take().expect("checked above");
            for r in &mut cache.rays {
                r.time = time;
            }
            let mut out = crate::volume::render_rays(
                vol,
                &self.cfg,
                &self.layout,
                params,
                &cache.rays,
                &self.settings.march,
            );
            self.render_outside(params, &cache.rays, &mut out, &mut stats);
            for (&p, c) in cache.dynamic.iter().zip(&out.rgb) {
                cache.rgb[p as usize * 3..p as usize * 3 + 3].copy_from_slice(c);
            }
            stats.rays_rendered = cache.rays.len();
            stats.rays_empty = cache.empty;
            stats.rays_cached = total - cache.rays.len() - cache.empty;
            stats.samples_evaluated = out.dynamic_samples;
            stats.volume_samples = out.samples;
            stats.volume_steps = out.steps;
            let rgb = cache.rgb.clone();
            self.volume_cache = Some(cache);
            rgb
        } else {
            let (mut rgb, pixels, rays, empty) = self.pixel_rays(camera, time, MARCH_TILE);
            let mut out = crate::volume::render_rays(
                vol,
                &self.cfg,
                &self.layout,
                params,
                &rays,
                &self.settings.march,
            );
            self.render_outside(params, &rays, &mut out, &mut stats);
            let mut dynamic = Vec::new();
            let mut dyn_rays = Vec::new();
            for (k, (&p, c)) in pixels.iter().zip(&out.rgb).enumerate() {
                rgb[p as usize * 3..p as usize * 3 + 3].copy_from_slice(c);
                // A ray drawn by the exact path may depend on the time: it is drawn again.
                if out.dynamic[k] || out.outside[k] {
                    dynamic.push(p);
                    dyn_rays.push(rays[k]);
                }
            }
            stats.full = true;
            stats.rays_rendered = rays.len();
            stats.rays_empty = empty;
            stats.samples_evaluated = out.dynamic_samples;
            stats.volume_samples = out.samples;
            stats.volume_steps = out.steps;
            self.volume_cache = self.settings.incremental.then(|| VolumeCache {
                camera: *camera,
                sliced,
                rgb: rgb.clone(),
                dynamic,
                rays: dyn_rays,
                empty,
            });
            rgb
        };
        if !sliced {
            self.slice_debt.1 += stats.samples_evaluated;
        }
        stats.seconds = start.elapsed().as_secs_f64();
        Frame {
            width: w,
            height: h,
            rgb,
            stats,
        }
    }

    /// Draws the rays of `out` that reached a brick the volume left out with the exact path,
    /// into `out.rgb`; counts and times them in `stats` (`rays_exact`, `exact_seconds`).
    fn render_outside(
        &self,
        params: &[f32],
        rays: &[TimedRay],
        out: &mut MarchOutput,
        stats: &mut FrameStats,
    ) {
        let start = Instant::now();
        let at: Vec<usize> = (0..rays.len()).filter(|&k| out.outside[k]).collect();
        if !at.is_empty() {
            let subset: Vec<TimedRay> = at.iter().map(|&k| rays[k]).collect();
            let exact = self.render_rays(params, &subset);
            for (&k, c) in at.iter().zip(&exact.rgb) {
                out.rgb[k] = *c;
            }
        }
        stats.rays_exact = at.len();
        stats.exact_seconds = start.elapsed().as_secs_f64();
    }

    /// Bakes the time slices the volume needs at `time` that it does not hold, when
    /// [`RenderSettings::slices`] says so (each with the flat buffer at its own time:
    /// `params_at`, else `params`); returns the seconds spent. A slice that cannot be baked
    /// leaves the dynamic bricks to the exact field.
    fn bake_slices(
        &mut self,
        time: f32,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
    ) -> f64 {
        let start = Instant::now();
        let Some(bv) = self.volume.as_mut() else {
            return 0.0;
        };
        if self.slice_error.is_some() {
            return 0.0;
        }
        if self.settings.slices == SlicePolicy::Auto {
            let missing = bv.volume.dynamic.missing_for(time);
            if missing.is_empty() {
                return 0.0;
            }
            if missing != self.slice_debt.0 {
                self.slice_debt = (missing, 0);
                return 0.0;
            }
            let cost = self.slice_cost * missing.len();
            if self.slice_debt.1 < cost {
                return 0.0;
            }
            self.slice_debt = (Vec::new(), 0);
        }
        let (cfg, layout) = (&self.cfg, &self.layout);
        if let Err(e) = bv.bake_missing_slices(time, params, params_at, &mut |v, plan, k, p| {
            crate::volume::bake_slice(v, plan, k, cfg, layout, p)
        }) {
            self.slice_error = Some(e.to_string());
        }
        start.elapsed().as_secs_f64()
    }

    /// The frame with the background where rays miss the scene, and the other pixels with their
    /// rays.
    fn pixel_rays(
        &self,
        camera: &Camera,
        time: f32,
        tile: u32,
    ) -> (Vec<f32>, Vec<u32>, Vec<TimedRay>, usize) {
        let (w, h) = (camera.width, camera.height);
        let total = w as usize * h as usize;
        let bg = match self.cfg.background {
            Background::Color { rgb } => Some(rgb),
            Background::LastSample => None,
        };
        let mut rgb = vec![0f32; total * 3];
        let mut pixels = Vec::with_capacity(total);
        let mut rays = Vec::with_capacity(total);
        let mut empty = 0;
        for (x, y) in tile_order(w, h, tile) {
            let ray = TimedRay::through_pixel(camera, x, y, time);
            let (near, far) = ray_limits(&self.cfg, &ray);
            let p = (y * w + x) as usize;
            match bg {
                // Misses the scene: the background, with nothing to evaluate.
                Some(c) if far <= near => {
                    rgb[p * 3..p * 3 + 3].copy_from_slice(&c);
                    empty += 1;
                }
                _ => {
                    pixels.push(p as u32);
                    rays.push(ray);
                }
            }
        }
        (rgb, pixels, rays, empty)
    }

    /// Renders every pixel and builds the static cache.
    fn render_full(&self, camera: &Camera, time: f32, params: &[f32]) -> (Vec<f32>, Cache) {
        let (mut rgb, pixels, rays, empty) = self.pixel_rays(camera, time, 1);
        let out = self.render_rays(params, &rays);
        for (&p, c) in pixels.iter().zip(&out.rgb) {
            rgb[p as usize * 3..p as usize * 3 + 3].copy_from_slice(c);
        }
        let cache = Cache {
            camera: *camera,
            rgb: rgb.clone(),
            dynamic: Vec::new(),
            rays: Vec::new(),
            samples: None,
            empty,
            classified: None,
            pending: Some(Pending {
                pixels,
                rays,
                rgb: out.rgb,
                visible_depth: out.visible_depth,
            }),
        };
        (rgb, cache)
    }

    /// Sorts the first frame's rays into static (cached) and dynamic (re-rendered): the mask
    /// test, then the probes.
    fn classify(
        &self,
        params: &[f32],
        params_at: &mut dyn FnMut(f32) -> Option<Vec<f32>>,
        p: Pending,
        cache: &mut Cache,
    ) {
        let flags = classify_static_with_stats(
            &self.cfg,
            &self.layout,
            params,
            &self.settings,
            &p.rays,
            &p.rgb,
            &p.visible_depth,
            |idx, t| {
                let probe: Vec<TimedRay> = idx
                    .iter()
                    .map(|&i| TimedRay {
                        time: t,
                        ..p.rays[i]
                    })
                    .collect();
                let owned = params_at(t);
                let at_t = owned.as_deref().unwrap_or(params);
                Ok::<_, std::convert::Infallible>(self.render_rays(at_t, &probe).rgb)
            },
        );
        let (flags, counts) = match flags {
            Ok(f) => f,
            Err(never) => match never {},
        };
        cache.classified = Some(counts);
        for ((&px, r), is_static) in p.pixels.iter().zip(&p.rays).zip(flags) {
            if !is_static {
                cache.dynamic.push(px);
                cache.rays.push(*r);
            }
        }
        if self.settings.reuse == Reuse::Samples && !cache.rays.is_empty() {
            let samples = partition_samples(&self.cfg, &self.settings);
            let bound = cache_bytes_bound(&self.layout, cache.rays.len(), samples);
            if bound <= self.settings.max_sample_cache_bytes {
                let times = partition_times(&self.cfg, &self.settings);
                cache.samples = Some(SampleCache::build(
                    &self.cfg,
                    &self.layout,
                    params,
                    &cache.rays,
                    &times,
                    samples,
                    self.settings.sample_cutoff,
                ));
            }
        }
    }
}

/// Fixed samples per dynamic ray under `settings` ([`Reuse::Samples`]).
pub fn partition_samples(cfg: &ModelConfig, settings: &RenderSettings) -> usize {
    match settings.partition_samples {
        0 => cfg.sampler.num_samples,
        n => n,
    }
    .clamp(1, u16::MAX as usize)
}

/// Times at which the proposal field places the fixed samples ([`Reuse::Samples`]): evenly over
/// the settings' time range, ends included.
pub fn partition_times(cfg: &ModelConfig, settings: &RenderSettings) -> Vec<f32> {
    let k = match settings.partition_times {
        0 => cfg.num_frames.min(DEFAULT_PARTITION_TIMES),
        k => k,
    }
    .clamp(1, MAX_PARTITION_TIMES);
    (0..k).map(|j| settings.clip_time(j, k)).collect()
}

/// Mask lookups per ray for the static test ([`ray_min_mask`]) under `settings`.
pub fn mask_steps(cfg: &ModelConfig, settings: &RenderSettings) -> usize {
    let cells = cfg.field.encoding.mask_resolution.max(1) as f32;
    // The longest straight path through the unit cube is sqrt(3) long.
    (cells * 3f32.sqrt() * settings.mask_steps_per_cell).ceil() as usize
}

/// Sorts a first frame's rays into static (`true`: cached) and dynamic, as every renderer of the
/// player does, by the mask along each
/// ray's visible segment (up to `visible_depth`, [`ray_min_mask`]):
/// - at least `trust_threshold`: static on the mask's word alone;
/// - at least `static_threshold` (the mask is not sure): static only if the probes agree: the
///   ray is rendered at each probe time, and one whose colour moves by more than the tolerance
///   from `rgb0` becomes dynamic;
/// - below: dynamic.
///
/// `render(indices, time)` renders the rays `rays[i]` for the given indices at `time` and returns
/// their colours in order (the backend's own renderer).
#[allow(clippy::too_many_arguments)]
pub fn classify_static_with_stats<E>(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    settings: &RenderSettings,
    rays: &[TimedRay],
    rgb0: &[[f32; 3]],
    visible_depth: &[f32],
    mut render: impl FnMut(&[usize], f32) -> Result<Vec<[f32; 3]>, E>,
) -> Result<(Vec<bool>, ClassifyStats), E> {
    let steps = mask_steps(cfg, settings);
    let threshold = settings.static_threshold;
    // A trust threshold below the static one trusts exactly the static rays.
    let trust = settings.trust_threshold.max(threshold);
    let min_mask: Vec<f32> = rays
        .par_iter()
        .zip(visible_depth)
        .map(|(r, &end)| ray_min_mask(cfg, layout, params, r, end, steps, threshold))
        .collect();
    let mut flags: Vec<bool> = min_mask.iter().map(|&m| m >= threshold).collect();
    let trusted: Vec<bool> = min_mask.iter().map(|&m| m >= trust).collect();
    let mut stats = ClassifyStats {
        rays: rays.len(),
        trusted: trusted.iter().filter(|&&t| t).count(),
        probed: flags
            .iter()
            .zip(&trusted)
            .filter(|(&f, &t)| f && !t)
            .count(),
        probed_static: 0,
        trusted_disagree: (settings.audit_mask && settings.probes > 0).then_some(0),
    };
    // Rays the probes still test: the uncertain static ones, plus (auditing) the trusted ones.
    let mut testing: Vec<bool> = flags
        .iter()
        .zip(&trusted)
        .map(|(&f, &t)| f && (!t || settings.audit_mask))
        .collect();
    let mut disagree = vec![false; rays.len()];
    let k = settings.probes;
    for j in 0..k {
        let t = settings.clip_time(j, k);
        // The first frame itself is a probe at its own time: rendering it again changes nothing.
        if rays.iter().all(|r| r.time == t) {
            continue;
        }
        let idx: Vec<usize> = (0..rays.len()).filter(|&i| testing[i]).collect();
        if idx.is_empty() {
            break;
        }
        let out = render(&idx, t)?;
        for (&i, c) in idx.iter().zip(&out) {
            let moved = (0..3).any(|ch| (c[ch] - rgb0[i][ch]).abs() > settings.probe_tolerance);
            if moved {
                testing[i] = false;
                if trusted[i] {
                    disagree[i] = true;
                } else {
                    flags[i] = false;
                }
            }
        }
    }
    stats.probed_static = flags
        .iter()
        .zip(&trusted)
        .filter(|(&f, &t)| f && !t)
        .count();
    if let Some(d) = stats.trusted_disagree.as_mut() {
        *d = disagree.iter().filter(|&&x| x).count();
    }
    Ok((flags, stats))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::config::Preset;
    use msth_core::SceneBounds;

    fn model(blend: msth_core::config::BlendMode) -> (ModelConfig, Vec<f32>) {
        let mut cfg = ModelConfig::fast_on_white(10);
        cfg.field.encoding.resize(4, 10, 64.0, 8);
        cfg.proposal.encoding.resize(3, 10, 32.0, 8);
        cfg.field.encoding.blend = blend;
        let layout = ModelLayout::new(&cfg);
        let params = layout.init_params(7);
        (cfg, params)
    }

    fn camera() -> Camera {
        Camera::look_at(24, 16, 0.9, Vec3::new(0.0, -4.0, 1.0), Vec3::ZERO, Vec3::Z)
    }

    /// Sets every mask logit of the main field to `logit`.
    fn set_mask(cfg: &ModelConfig, params: &mut [f32], logit: f32) {
        let layout = ModelLayout::new(cfg);
        let (_, r) = layout.field.encoding.mask.clone().expect("mask");
        params[r].fill(logit);
    }

    /// An `mt` model whose mask logit is `logit` everywhere over a 4D table of uniform values in
    /// `[-amplitude, amplitude]`: frames move wherever the mask lets the table through.
    fn mask_over_a_moving_table(logit: f32, amplitude: f32) -> (ModelConfig, Vec<f32>) {
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        let layout = ModelLayout::new(&cfg);
        set_mask(&cfg, &mut params, logit);
        let mut rng = msth_core::rng::Rng::new(9);
        let (_, h4) = layout.field.encoding.h4.clone().unwrap();
        for v in &mut params[h4] {
            *v = rng.range_f32(-amplitude, amplitude);
        }
        (cfg, params)
    }

    #[test]
    fn all_static_mask_renders_once_and_matches_full_renders() {
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        set_mask(&cfg, &mut params, 8.0); // m = 0.9997
        let mut inc = Renderer::new(
            &cfg,
            RenderSettings {
                probes: 0,
                ..Default::default()
            },
        );
        let mut full = full_renderer(&cfg);
        let cam = camera();
        let f0 = inc.render(&cam, 0.0, &params);
        assert!(f0.stats.full);
        assert_eq!(
            inc.dynamic_fraction(),
            None,
            "classified on the second frame"
        );
        let f1 = inc.render(&cam, 0.7, &params);
        assert_eq!(inc.dynamic_fraction(), Some(0.0));
        assert!(!f1.stats.full);
        assert_eq!(f1.stats.rays_rendered, 0);
        assert_eq!(f1.rgb, f0.rgb);
        // The full render at 0.7 differs from frame 0 only by the (1 - m) h4 term.
        let g1 = full.render(&cam, 0.7, &params);
        assert!(g1.stats.full);
        let (max_diff, _) = compare(&f1, &g1);
        assert!(max_diff < 2e-2, "{max_diff}");
    }

    #[test]
    fn dynamic_mask_rerenders_and_equals_full_render() {
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        set_mask(&cfg, &mut params, -3.0);
        let mut inc = Renderer::new(
            &cfg,
            RenderSettings {
                reuse: Reuse::Rays,
                ..Default::default()
            },
        );
        let mut full = full_renderer(&cfg);
        let cam = camera();
        inc.render(&cam, 0.0, &params);
        let f1 = inc.render(&cam, 0.5, &params);
        let g1 = full.render(&cam, 0.5, &params);
        assert_eq!(
            f1.stats.rays_rendered + f1.stats.rays_empty,
            f1.stats.rays_total
        );
        assert_eq!(f1.rgb, g1.rgb);
        // A camera move renders everything again.
        let mut cam2 = cam;
        cam2.world_from_camera.w_axis.x += 0.1;
        assert!(inc.render(&cam2, 0.5, &params).stats.full);
    }

    #[test]
    fn probes_catch_rays_a_lenient_mask_calls_static() {
        // m = 0.73: "static" at threshold 0.5, unsure (below the trust threshold).
        let (cfg, params) = mask_over_a_moving_table(1.0, 2.0);
        let lenient = RenderSettings {
            static_threshold: 0.5,
            probe_tolerance: 1.0 / 255.0,
            reuse: Reuse::Rays,
            ..Default::default()
        };
        let cam = camera();
        let mut full = Renderer::new(
            &cfg,
            RenderSettings {
                incremental: false,
                ..lenient
            },
        );
        for (probes, must_match) in [(0, false), (5, true)] {
            let mut inc = Renderer::new(&cfg, RenderSettings { probes, ..lenient });
            inc.render(&cam, 0.0, &params);
            let f = inc.render(&cam, 0.5, &params);
            let g = full.render(&cam, 0.5, &params);
            let (max_diff, _) = compare(&f, &g);
            if must_match {
                // 0.5 is a probe time: every cached ray is within the tolerance there.
                assert!(max_diff <= lenient.probe_tolerance + 1e-6, "{max_diff}");
                assert!(f.stats.rays_rendered > 0);
            } else {
                assert!(
                    max_diff > 0.005,
                    "the mask alone misses the motion: {max_diff}"
                );
            }
        }
    }

    #[test]
    fn a_sure_mask_is_trusted_without_probes_and_the_audit_counts_its_errors() {
        // The mask says "surely static" (m = 0.968, above the trust threshold) while a 4D table
        // of huge values makes everything move through the 3.2% left to it (above the static
        // cutoff, so rendering reads it): trusted rays are cached on the mask's word (the
        // probes do not see them), the audit counts them as disagreements, and a trust
        // threshold above 1 probes them again.
        let (cfg, params) = mask_over_a_moving_table(3.4, 100.0);
        let base = RenderSettings {
            probes: 5,
            probe_tolerance: 1.0 / 255.0,
            reuse: Reuse::Rays,
            ..Default::default()
        };
        let cam = camera();
        let classify = |settings: RenderSettings| {
            let mut r = Renderer::new(&cfg, settings);
            r.render(&cam, 0.0, &params);
            let f = r.render(&cam, 0.5, &params);
            f.stats.classify.expect("the second frame sorts the rays")
        };
        let trusted = classify(RenderSettings {
            audit_mask: true,
            ..base
        });
        assert!(trusted.rays > 0);
        assert_eq!(trusted.trusted, trusted.rays, "{trusted:?}");
        assert_eq!(trusted.probed, 0);
        let wrong = trusted.trusted_disagree.expect("audited");
        assert!(
            wrong > trusted.rays / 2,
            "the audit sees the motion: {trusted:?}"
        );
        let quiet = classify(base);
        assert_eq!(quiet.trusted_disagree, None);
        assert_eq!(quiet.cached(), quiet.rays);
        let probed = classify(RenderSettings {
            trust_threshold: 1.5,
            ..base
        });
        assert_eq!(probed.trusted, 0);
        assert_eq!(probed.probed, probed.rays);
        assert_eq!(probed.probed_static, probed.rays - wrong, "{probed:?}");
    }

    #[test]
    fn static_test_sees_dynamic_empty_space_in_front_of_a_surface() {
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        set_mask(&cfg, &mut params, 8.0);
        let layout = ModelLayout::new(&cfg);
        let (grid, r) = layout.field.encoding.mask.clone().unwrap();
        // One dynamic vertex near the box centre, on the ray's path.
        let res = grid.res;
        let c = res / 2;
        params[r.start + (c * res + c) * res + c] = -8.0;
        let v = -1.5 + 3.0 * c as f32 / (res - 1) as f32;
        let ray = TimedRay {
            origin: Vec3::new(v, -4.0, v),
            dir: Vec3::Y,
            time: 0.0,
        };
        let steps = 64;
        // Visible to the far side: the dynamic vertex is crossed.
        let min_mask =
            |ray: &TimedRay, end: f32| ray_min_mask(&cfg, &layout, &params, ray, end, steps, 0.95);
        assert!(min_mask(&ray, 10.0) < 0.95);
        // A surface before it hides it.
        assert!(min_mask(&ray, 3.5) >= 0.95);
        // A ray that misses the box is static.
        let miss = TimedRay {
            origin: Vec3::new(0.0, -4.0, 5.0),
            dir: Vec3::Y,
            time: 0.0,
        };
        assert!(min_mask(&miss, 10.0) >= 0.95);
    }

    #[test]
    fn models_without_a_mask_are_static_only_without_4d() {
        use msth_core::config::BlendMode;
        let cam = camera();
        for (blend, is_static) in [(BlendMode::Static, true), (BlendMode::FourD, false)] {
            let (cfg, params) = model(blend);
            let mut r = Renderer::new(&cfg, RenderSettings::default());
            r.render(&cam, 0.0, &params);
            let f = r.render(&cam, 1.0, &params);
            assert_eq!(f.stats.rays_rendered == 0, is_static, "{blend:?}");
        }
    }

    /// A renderer that renders every frame in full (the reference of incremental playback).
    fn full_renderer(cfg: &ModelConfig) -> Renderer {
        Renderer::new(
            cfg,
            RenderSettings {
                incremental: false,
                ..Default::default()
            },
        )
    }

    /// Largest per-channel difference and PSNR of two frames.
    fn compare(a: &Frame, b: &Frame) -> (f32, f64) {
        let max = a
            .rgb
            .iter()
            .zip(&b.rgb)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        let mse = a
            .rgb
            .iter()
            .zip(&b.rgb)
            .map(|(x, y)| ((x - y) as f64).powi(2))
            .sum::<f64>()
            / a.rgb.len() as f64;
        (max, -10.0 * mse.max(1e-20).log10())
    }

    #[test]
    fn sample_reuse_evaluates_only_dynamic_samples_and_follows_full_renders() {
        // Dynamic in a slab through the middle of the scene, static elsewhere.
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        let layout = ModelLayout::new(&cfg);
        // Grid values of order 1, so that densities and colours vary and change with time.
        let mut rng = msth_core::rng::Rng::new(5);
        for name in ["field.h3", "field.h4", "proposal.h3", "proposal.h4"] {
            let e = layout.params.get(name).expect(name).range();
            for v in &mut params[e] {
                *v = rng.range_f32(-1.0, 1.0);
            }
        }
        let (d, r) = layout.field.encoding.mask.clone().expect("mask");
        for (k, v) in params[r].iter_mut().enumerate() {
            let x = k % d.res;
            *v = if (d.res / 3..2 * d.res / 3).contains(&x) {
                -3.0
            } else {
                12.0
            };
        }
        let settings = RenderSettings {
            probes: 0,
            static_threshold: 0.99,
            ..Default::default()
        };
        assert_eq!(settings.reuse, Reuse::Samples);
        let mut inc = Renderer::new(&cfg, settings);
        let mut full = full_renderer(&cfg);
        let cam = camera();
        inc.render(&cam, 0.0, &params);
        let first = full.render(&cam, 0.0, &params);
        for t in [0.3, 0.9] {
            let f = inc.render(&cam, t, &params);
            let g = full.render(&cam, t, &params);
            // The frames do change with time (else any cache would pass).
            let (moved, _) = compare(&first, &g);
            assert!(
                moved > 5e-3,
                "t = {t}: the full render moved by {moved} only"
            );
            assert!(!f.stats.full && f.stats.rays_rendered > 0);
            let fixed = f.stats.rays_rendered * partition_samples(&cfg, &settings);
            assert!(
                f.stats.samples_evaluated > 0 && f.stats.samples_evaluated < fixed,
                "{} of {fixed} samples evaluated",
                f.stats.samples_evaluated
            );
            // The same field over other sample positions: close, not equal.
            let (max, psnr) = compare(&f, &g);
            println!(
                "t = {t}: {} of {fixed} samples evaluated, {psnr:.1} dB against the full render",
                f.stats.samples_evaluated
            );
            assert!(
                psnr > 45.0 && max < moved,
                "t = {t}: {psnr:.1} dB, largest difference {max} (the frame moved by {moved})"
            );
        }
    }

    #[test]
    fn sample_cache_over_budget_falls_back_to_whole_rays() {
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        set_mask(&cfg, &mut params, -3.0);
        let mut inc = Renderer::new(
            &cfg,
            RenderSettings {
                max_sample_cache_bytes: 0,
                ..Default::default()
            },
        );
        let mut full = full_renderer(&cfg);
        let cam = camera();
        inc.render(&cam, 0.0, &params);
        let f = inc.render(&cam, 0.5, &params);
        assert!(f.stats.rays_rendered > 0);
        assert_eq!(f.stats.samples_evaluated, 0);
        assert_eq!(f.rgb, full.render(&cam, 0.5, &params).rgb);
    }

    #[test]
    fn probes_render_with_the_parameters_of_their_time() {
        // m = 0.95 everywhere: every ray passes the mask test at 0.9, and the 4D table still
        // counts (weight 0.05). With a zero 4D table nothing moves; the table "of another chunk"
        // is random, so probes made with it must see change.
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        let layout = ModelLayout::new(&cfg);
        set_mask(&cfg, &mut params, 3.0);
        let (_, h4) = layout.field.encoding.h4.clone().unwrap();
        params[h4.clone()].fill(0.0);
        let mut other = params.clone();
        let mut rng = msth_core::rng::Rng::new(4);
        for v in &mut other[h4] {
            *v = rng.range_f32(-3.0, 3.0);
        }
        let settings = RenderSettings {
            reuse: Reuse::Rays,
            probe_tolerance: 1.0 / 255.0,
            // Probe every static ray (this test is about the probes' parameters).
            trust_threshold: 2.0,
            ..Default::default()
        };
        let cam = camera();
        let second = |provider: &mut dyn FnMut(f32) -> Option<Vec<f32>>| {
            let mut r = Renderer::new(&cfg, settings);
            r.render(&cam, 0.0, &params);
            r.render_probing(&cam, 0.0, &params, provider).stats
        };
        let same = second(&mut |_| None);
        assert_eq!(same.rays_rendered, 0, "a still model caches every ray");
        let mut asked = Vec::new();
        let chunked = second(&mut |t| {
            asked.push(t);
            (t > 0.0).then(|| other.clone())
        });
        assert!(
            chunked.rays_rendered > 0,
            "probes ignored the other chunk's rows"
        );
        assert!(asked.iter().all(|&t| t > 0.0), "{asked:?}");
        assert!(!asked.is_empty());
    }

    #[test]
    fn tile_order_visits_every_pixel_once_tile_by_tile() {
        for (w, h, tile) in [(17, 9, 8), (8, 8, 8), (5, 3, 1), (1, 20, 4), (3, 2, 8)] {
            let order: Vec<(u32, u32)> = tile_order(w, h, tile).collect();
            let mut seen = vec![false; (w * h) as usize];
            for &(x, y) in &order {
                assert!(x < w && y < h, "{w}x{h}/{tile}: ({x}, {y}) outside");
                let p = (y * w + x) as usize;
                assert!(!seen[p], "{w}x{h}/{tile}: ({x}, {y}) twice");
                seen[p] = true;
            }
            assert_eq!(order.len(), (w * h) as usize, "{w}x{h}/{tile}");
            // Each tile's pixels come together: the tile number never goes back.
            let tiles: Vec<u32> = order
                .iter()
                .map(|&(x, y)| (y / tile) * w.div_ceil(tile) + x / tile)
                .collect();
            assert!(tiles.windows(2).all(|t| t[0] <= t[1]), "{w}x{h}/{tile}");
        }
        let rows: Vec<(u32, u32)> = tile_order(4, 3, 1).collect();
        let plain: Vec<(u32, u32)> = (0..3).flat_map(|y| (0..4).map(move |x| (x, y))).collect();
        assert_eq!(rows, plain, "a tile of 1 is row order");
    }

    #[test]
    fn batches_keep_scratch_memory_bounded_whatever_the_sampler() {
        let paper = ModelConfig::preset(
            Preset::Paper,
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
            300,
        );
        // The paper's 128 + 48 samples: whole batches.
        assert_eq!(rays_per_batch(&paper, CHUNK), CHUNK);
        assert!(CHUNK as u64 * scratch_bytes_per_ray(&paper) <= BATCH_SCRATCH_BYTES);
        // The decoder's largest sampler and far beyond it: smaller batches, never over budget
        // (unless a single ray is), never empty.
        for (np, nf) in [(1024, 512), (4096, 4096)] {
            let mut cfg = paper.clone();
            cfg.sampler.set_samples(np, nf);
            let n = rays_per_batch(&cfg, CHUNK);
            assert!((1..CHUNK).contains(&n), "{np} + {nf}: {n} rays");
            assert!(n as u64 * scratch_bytes_per_ray(&cfg) <= BATCH_SCRATCH_BYTES);
        }
    }

    #[test]
    fn probes_and_fixed_samples_cover_the_time_range_played() {
        let s = RenderSettings {
            time_range: (0.4, 0.2),
            trust_threshold: 2.0,
            ..Default::default()
        };
        let times: Vec<f32> = (0..3).map(|j| s.clip_time(j, 3)).collect();
        assert_eq!(times, [0.2, 0.3, 0.4]);
        assert_eq!(s.clip_time(0, 1), 0.3);
        let bad = RenderSettings {
            time_range: (f32::NAN, 2.0),
            ..Default::default()
        };
        assert_eq!(bad.clip_time(2, 3), 1.0);
        // The probes ask for the parameters of times within the range only (and never of the
        // first frame's own time).
        let (cfg, mut params) = model(msth_core::config::BlendMode::Mt);
        set_mask(&cfg, &mut params, 3.0);
        let mut r = Renderer::new(&cfg, s);
        let cam = camera();
        r.render(&cam, 0.2, &params);
        let mut asked = Vec::new();
        r.render_probing(&cam, 0.2, &params, &mut |t| {
            asked.push(t);
            None
        });
        assert_eq!(asked, [0.3, 0.4]);
        let cfg10 = ModelConfig {
            num_frames: 10,
            ..cfg.clone()
        };
        let p = partition_times(&cfg10, &s);
        assert_eq!(p.len(), DEFAULT_PARTITION_TIMES);
        assert!(p.iter().all(|t| (0.2..=0.4).contains(t)), "{p:?}");
    }
}
