//! The per-chunk pipeline shared by training and rendering: place proposal samples, evaluate the
//! proposal field, resample from its weights, evaluate the main field, composite; and for
//! training, the losses and the backward pass through both fields.
//!
//! A chunk is a few hundred rays processed by one thread with its own [`Workspace`]; the caller
//! splits batches into chunks and sums gradients in a fixed order, so results are repeatable for
//! a seed and a thread count.
//!
//! This module holds the types a chunk shares (rays, settings, losses, outputs, the per-thread
//! [`Workspace`]); the work is split by concern:
//! - `sampling`: ray limits, sample placement, direction encodings;
//! - `forward`: the forward pass of both fields over a chunk, compositing, inference rendering;
//! - `train`: the training step of a chunk (losses and backward), with the uncertainty branch of
//!   mask learning;
//! - `playback`: the time-independent sample partition of the player's sample reuse.

use glam::Vec3;

use crate::config::{Background, ModelConfig, SamplerConfig};
use crate::field::{FieldScratch, ModelLayout};
use crate::losses;
use crate::render;
use crate::rng::Rng;
use crate::sampling::{sample_pdf, uniform_edges};
use crate::scene::SceneBounds;
use crate::sh::{sh4, SH_COEFFS};
use crate::uncertainty::{
    mine_estimate, ray_uncertainty, ray_uncertainty_backward, shuffle, uncertainty_loss, AuxLayout,
    MaskLearningConfig, MineScratch,
};
use crate::Ray;

/// One ray at one time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedRay {
    pub origin: Vec3,
    pub dir: Vec3,
    pub time: f32,
}

impl TimedRay {
    /// The ray through the centre of pixel (`x`, `y`) of `camera`, at `time`.
    pub fn through_pixel(camera: &crate::Camera, x: u32, y: u32, time: f32) -> Self {
        let r = camera.pixel_ray(x, y);
        TimedRay {
            origin: r.origin,
            dir: r.dir,
            time,
        }
    }
}

/// Per-step training settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepSettings {
    /// Proposal weight annealing exponent `a` (`w^a`), 1 at the end of the schedule.
    pub anneal: f32,
    pub interlevel_weight: f32,
    pub distortion_weight: f32,
    /// `1 / rays in the whole batch`: losses are means over the batch.
    pub loss_scale: f32,
    /// Weight of the per-sample mask loss `mean_r sum_i w_i (1 - m_i)` (the rendering weights
    /// `w_i` held constant): pushes the mask toward static where rays see matter, scaled like
    /// the image loss, so a voxel stays dynamic only where the 4D grid pays for itself. 0: off.
    pub sample_mask_weight: f32,
    /// Weight of the free-space loss: at one random point of the unit cube and clip per ray,
    /// the main field's opacity over a step of [`FREE_SPACE_STEP`] of the scene's diagonal,
    /// `mean_j (1 - exp(-sigma_j delta))`, scaled like the image loss. Space no training ray
    /// constrains (behind walls, inside objects, floaters only a held-out view would see) is
    /// pulled empty; where rays see matter the image loss outweighs it. 0: off.
    pub free_space_weight: f32,
    /// Coarse-to-fine over the main field's levels: with `Some(a)`, level `l`'s features (and
    /// their gradients) are scaled by [`crate::field::level_factor`]`(a, l) = clamp(a - l, 0, 1)`,
    /// so the first `a` levels are on, the next one partly, the finer ones off. `None` (and any
    /// `a` at or above the level count) leaves the encoding as it is.
    pub active_levels: Option<f32>,
    /// The same for the proposal field's levels (nested dropout over progressive layers, whose
    /// later layers hold the proposal's finer levels too). `None`: every level.
    pub proposal_levels: Option<f32>,
}

/// The free-space loss's step `delta` as a share of the diagonal of the scene's extent (the
/// uncontracted cube of a contracted scene): 1/128, about half a cell of the export's 64^3
/// occupancy grid, so the loss acts on the opacities the occupancy test reads.
pub const FREE_SPACE_STEP: f32 = 1.0 / 128.0;

/// Loss sums of one chunk (divide by the batch's ray count for means).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ChunkLosses {
    /// Sum over rays of the mean over channels of the squared error.
    pub sq_err: f64,
    pub interlevel: f64,
    pub distortion: f64,
    /// Sum over rays of the per-sample mask loss, its weight included.
    pub sample_mask: f64,
    /// Sum over the chunk's free-space points (one per ray) of their opacity, its weight
    /// included (0 when off).
    pub free_space: f64,
    /// Sum over rays of the uncertainty loss `L_u` (mask learning; 0 when off).
    pub uncertainty: f64,
    /// Sum over chunks of the MINE estimate `I(m, u)` times the chunk's ray count (0 when off).
    pub mine: f64,
    pub rays: usize,
    pub field_samples: usize,
    pub proposal_samples: usize,
}

impl std::ops::AddAssign for ChunkLosses {
    fn add_assign(&mut self, o: Self) {
        self.sq_err += o.sq_err;
        self.interlevel += o.interlevel;
        self.distortion += o.distortion;
        self.sample_mask += o.sample_mask;
        self.free_space += o.free_space;
        self.uncertainty += o.uncertainty;
        self.mine += o.mine;
        self.rays += o.rays;
        self.field_samples += o.field_samples;
        self.proposal_samples += o.proposal_samples;
    }
}

/// What rendering returns per ray.
#[derive(Clone, Debug, Default)]
pub struct RenderOutput {
    pub rgb: Vec<[f32; 3]>,
    /// Expected termination distance (world units).
    pub depth: Vec<f32>,
    /// Accumulated opacity `1 - T_N`.
    pub opacity: Vec<f32>,
    /// Weight-averaged mask value `sum w_i m_i` (1 = static), for mask pictures.
    pub mask: Vec<f32>,
    /// Smallest mask value among samples that carry weight (`w > 1e-4`); 1 for empty rays.
    /// A ray is static for incremental rendering when this is above `1 - eps`.
    pub min_mask: Vec<f32>,
    /// Distance at which the transmittance falls below [`VISIBLE_TRANSMITTANCE`] (the far end of
    /// the samples when it never does): nothing behind it can change the pixel visibly.
    pub visible_depth: Vec<f32>,
}

/// Rendering (not training) skips the 4D lookup of points whose dynamic weight `1 - m` is below
/// this: their encoding changes by less than this fraction of `|h4|`
/// ([`crate::field::EncodingScratch::static_cutoff`]), in the proposal field and the main field.
///
/// 0.02 since 2026-11-30 (1e-3 before): on the held-out views of the balanced stage model and
/// of `msth demo`'s model (`msth eval`) it moves PSNR by -0.0007 and +0.003 dB and skips 80% and
/// 21% of the main field's 4D lookups and 48% of the proposal field's (docs/playback.md, "The
/// static cutoff"). The GPU passes evaluate a sample with a 4D lookup at several times
/// the cost of one without.
pub const RENDER_STATIC_CUTOFF: f32 = 0.02;

/// Rendering (not training) resamples the proposal's weights with at most this padding per
/// histogram bin (`sampler.histogram_padding`, 0.01 in every preset): see
/// [`render_histogram_padding`].
///
/// Training pads every bin so that the main samples keep exploring the whole ray while the
/// proposal network is still wrong; with 96 bins, 0.01 a bin is about half the mass of an opaque
/// ray's histogram, so about half the main samples are spread evenly along the ray whatever the
/// proposal says. A trained model needs no exploration: at 0.001 (since 2026-12-01) the held-out
/// PSNR of three trained models (`msth eval`: the balanced stage model, `msth demo`'s model, a
/// fast object model) is 0.02-0.11 dB higher at their own samples per ray, 0.01-0.12 dB at
/// `fast` and 0.03-0.54 dB at `faster`, in every one of the nine cases (docs/tradeoff.md,
/// "Histogram padding at play time").
pub const RENDER_HISTOGRAM_PADDING: f32 = 1e-3;

/// The padding per proposal bin with which rendering resamples (the CPU renderers, the GPU
/// passes and the page alike): the model's own `histogram_padding`, or
/// [`RENDER_HISTOGRAM_PADDING`] where that is smaller. Training keeps the model's own, and so
/// does the export's [`weighted_samples`] (its doc says why).
pub fn render_histogram_padding(sampler: &SamplerConfig) -> f32 {
    sampler.histogram_padding.min(RENDER_HISTOGRAM_PADDING)
}

/// Transmittance below which what lies further along a ray is treated as invisible by
/// [`RenderOutput::visible_depth`] (it contributes at most this fraction of the pixel).
pub const VISIBLE_TRANSMITTANCE: f32 = 1e-3;

/// Reusable buffers of one thread.
#[derive(Clone, Debug, Default)]
pub struct Workspace {
    near_far: Vec<(f32, f32)>,
    sh: Vec<f32>,
    s_prop: Vec<f32>,
    t_prop: Vec<f32>,
    pts_prop: Vec<f32>,
    delta_prop: Vec<f32>,
    w_prop: Vec<f32>,
    tfinal_prop: Vec<f32>,
    s_main: Vec<f32>,
    t_main: Vec<f32>,
    pts_main: Vec<f32>,
    delta_main: Vec<f32>,
    w_main: Vec<f32>,
    annealed: Vec<f32>,
    d_w: Vec<f32>,
    d_sigma_main: Vec<f32>,
    d_rgb_main: Vec<f32>,
    d_sigma_prop: Vec<f32>,
    d_w_prop: Vec<f32>,
    active: Vec<u32>,
    prop: FieldScratch,
    main: FieldScratch,
    // Mask learning (training only, empty otherwise).
    stat: FieldScratch,
    w_stat: Vec<f32>,
    tfinal_stat: Vec<f32>,
    d_sigma_stat: Vec<f32>,
    d_rgb_stat: Vec<f32>,
    u_main: Vec<f32>,
    d_u_main: Vec<f32>,
    m_ray: Vec<f32>,
    u_ray: Vec<f32>,
    d_m_ray: Vec<f32>,
    d_u_ray: Vec<f32>,
    perm: Vec<usize>,
    mine: MineScratch,
    // The free-space loss (training only, empty otherwise).
    free: FieldScratch,
    pts_free: Vec<f32>,
    d_sigma_free: Vec<f32>,
}

/// Samples whose transmittance has fallen below this get no colour evaluation: their weight,
/// and every gradient through them, is below it.
pub const HIDDEN_TRANSMITTANCE: f32 = 1e-4;

mod forward;
mod playback;
mod sampling;
#[cfg(test)]
mod tests;
mod train;

use forward::forward_chunk;
pub use forward::{composite_ray, render_chunk, weighted_samples, WeightedSample};
pub use playback::{playback_partition, KeepPoint, Partition};
pub use sampling::{direction_encodings, ray_limits, sample_time, spacing_unit};
use sampling::{place_proposal_samples, place_samples};
pub use train::{free_space_delta, free_space_point, train_chunk, train_chunk_with, AuxStep};
