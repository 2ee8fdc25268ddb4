//! Which rays, at which times, a training batch draws (paper §3.4, method.md §4).
//!
//! Three samplers, chosen by [`SamplingConfig::mode`]:
//! - `uniform`: a random training view, then a random pixel (the plain NeRF sampler).
//! - `dynamics`: the paper's dynamics-aware sampler. A pixel `r` of a physical camera is drawn
//!   with `P(r) ∝ exp(std_t C(r, t) / tau1)`, then a frame with
//!   `P(t | r) ∝ exp(|C(r, t) - median_t C(r)| / tau2)`.
//! - `static_dynamic`: the reference code's sampler. Pixels whose temporal variance exceeds
//!   `dynamic_variance` are dynamic; a batch draws static and dynamic pixels in a ratio decaying
//!   linearly from `ratio_start : 1` to `ratio_end : 1`, each dynamic pixel repeated at
//!   `1..=max_repeats` random frames.
//!
//! Statistics ([`PixelStats`]) are computed once per dataset. Colour distances are the RMS over
//! the three channels of values in `[0, 1]`: `std_t` is `sqrt(mean_ch var_t)` and the deviation
//! `sqrt(mean_ch (C - median)^2)`, both in `[0, 1]`, so the temperatures are in colour units.
//! `P(r)` is an alias table (`O(1)` per draw); `P(t | r)` keeps each pixel's deviations quantised
//! to 1/255 (one byte per pixel and frame, pixel-major) and draws by inverse CDF through a
//! 256-entry table of `exp(-d / tau2)`, `O(frames)` per draw, without a table per pixel.
//!
//! What a "pixel over time" is: views sharing [`View::camera_id`] (and image size) are one
//! physical camera filming every frame (multi-view video: Plenoptic Video, the built-in scene,
//! the glTF stage). A view without a camera id (monocular, D-NeRF style: a new pose per frame)
//! is a camera with a single frame: its temporal deviation is 0, so both dynamics-aware
//! samplers reduce to uniform sampling there, and on a purely monocular dataset the sampler
//! falls back to `uniform` with a note ([`RaySampler::note`]).
//!
//! Temperature extremes stay finite: weights are `exp((x - max) / tau)` (at most 1, the largest
//! exactly 1), `tau = 0` is the limit (only the largest values), `tau = inf` is uniform.

use std::collections::HashMap;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use msth_core::pipeline::TimedRay;
use msth_core::rng::Rng;

use msth_dataset::{Dataset, View};

/// The samplers of a training batch.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplingMode {
    /// A random view, then a random pixel (the default of settings written before the
    /// samplers existed; `msth train`'s presets use it on forward-facing captures and
    /// [`SamplingMode::Dynamics`] on object-centred scenes: `crate::train::default_sampling_mode`).
    #[default]
    Uniform,
    /// The paper: `P(r) ∝ exp(std_t / tau1)`, `P(t | r) ∝ exp(|C - median| / tau2)`.
    Dynamics,
    /// The reference code: static and dynamic pixels in a decaying ratio.
    StaticDynamic,
}

/// Settings of the batch sampler (`--set sampling.mode=dynamics`, ...).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SamplingConfig {
    pub mode: SamplingMode,
    /// `tau1` of `P(r)`, colour units. 0: only the most dynamic pixels; large: uniform.
    pub tau1: f32,
    /// `tau2` of `P(t | r)`, colour units. 0: only the frames farthest from the median.
    pub tau2: f32,
    /// `static_dynamic`: a pixel is dynamic when its temporal variance (mean over channels)
    /// exceeds this (reference code: 0.03).
    pub dynamic_variance: f32,
    /// `static_dynamic`: static pixels per dynamic pixel at the start (reference: 50).
    pub ratio_start: f32,
    /// `static_dynamic`: the same at the end of the run (reference: 10).
    pub ratio_end: f32,
    /// `static_dynamic`: a dynamic pixel is drawn at `1..=max_repeats` random frames (reference: 5).
    pub max_repeats: usize,
}

/// The chosen temperatures (docs/mask-learning.md, "Ray sampling"): soft, as the paper asks,
/// and chosen by the ablation. `P(r)`: with `tau1 = 0.2` a pixel whose colour varies with a
/// temporal std of 0.1 (a moving shadow or edge) is drawn 1.6 times as often as a static one, one
/// at 0.3 (an object passing over a contrasting background) 4.5 times; on the built-in scene this
/// raises the share of rays drawn in dynamic pixels from 22% to 38% (glTF stage: 10% to 17%).
/// `P(t | r)`: `tau2 = 1` only mildly favours the frames where a pixel is far from its median
/// (1.35 times at 0.3 away): the sharper `tau2 = 0.1` cost 2.2 dB on the built-in scene (the
/// frames where a moving object covers a pixel crowd out its background frames), uniform frames
/// and `tau2 = 1` did equally well.
pub const DEFAULT_TAU1: f32 = 0.2;
/// See [`DEFAULT_TAU1`].
pub const DEFAULT_TAU2: f32 = 1.0;

impl Default for SamplingConfig {
    fn default() -> Self {
        SamplingConfig {
            mode: SamplingMode::Uniform,
            tau1: DEFAULT_TAU1,
            tau2: DEFAULT_TAU2,
            dynamic_variance: 0.03,
            ratio_start: 50.0,
            ratio_end: 10.0,
            max_repeats: 5,
        }
    }
}

/// Why [`SamplingConfig::validate`] rejected a configuration; the message names the field.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidSamplingConfig(pub String);

/// Why an [`AliasTable`] could not be built from its weights.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AliasTableError {
    #[error("alias table: need 1..={} weights (got {got})", u32::MAX)]
    Count { got: usize },
    #[error("alias table: weight {index} is {weight} (must be finite and >= 0)")]
    Weight { index: usize, weight: f64 },
    #[error("alias table: the weights sum to {sum} (must be positive and finite)")]
    Sum { sum: f64 },
}

/// Why a [`RaySampler`] (or its [`PixelStats`]) could not be built.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SamplingError {
    #[error(transparent)]
    Config(#[from] InvalidSamplingConfig),
    #[error(transparent)]
    AliasTable(#[from] AliasTableError),
    #[error("dynamics-aware sampling: {pixels} training pixels are more than it indexes (4e9); use --downscale or sampling.mode=uniform")]
    TooManyPixels { pixels: usize },
}

impl SamplingConfig {
    pub fn validate(&self) -> Result<(), InvalidSamplingConfig> {
        for (n, v) in [("tau1", self.tau1), ("tau2", self.tau2)] {
            if v.is_nan() || v < 0.0 {
                return Err(InvalidSamplingConfig(format!(
                    "sampling.{n} must be >= 0 (got {v})"
                )));
            }
        }
        if !(self.dynamic_variance.is_finite() && self.dynamic_variance >= 0.0) {
            return Err(InvalidSamplingConfig(
                "sampling.dynamic_variance must be finite and >= 0".into(),
            ));
        }
        for (n, v) in [
            ("ratio_start", self.ratio_start),
            ("ratio_end", self.ratio_end),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(InvalidSamplingConfig(format!(
                    "sampling.{n} must be finite and >= 0"
                )));
            }
        }
        if !(1..=1000).contains(&self.max_repeats) {
            return Err(InvalidSamplingConfig(
                "sampling.max_repeats must be in 1..=1000".into(),
            ));
        }
        Ok(())
    }
}

/// `exp((x - max) / tau)` for `x <= max`: 1 at the maximum, in `[0, 1]` elsewhere; `tau = 0` is
/// the limit (1 at the maximum, 0 elsewhere) and `tau = inf` gives 1 everywhere.
pub fn tempered_weight(x: f64, max: f64, tau: f64) -> f64 {
    if x >= max {
        1.0
    } else if tau <= 0.0 {
        0.0
    } else {
        ((x - max) / tau).exp()
    }
}

/// Walker / Vose alias table: draws index `i` with probability `w_i / sum w` in `O(1)`.
#[derive(Clone, Debug)]
pub struct AliasTable {
    prob: Vec<f32>,
    alias: Vec<u32>,
}

impl AliasTable {
    /// From non-negative finite weights with a positive sum (at most `u32::MAX` of them).
    pub fn new(weights: &[f64]) -> Result<Self, AliasTableError> {
        let n = weights.len();
        if n == 0 || n > u32::MAX as usize {
            return Err(AliasTableError::Count { got: n });
        }
        if let Some(i) = weights.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(AliasTableError::Weight {
                index: i,
                weight: weights[i],
            });
        }
        let sum: f64 = weights.iter().sum();
        if !(sum > 0.0 && sum.is_finite()) {
            return Err(AliasTableError::Sum { sum });
        }
        let mut scaled: Vec<f64> = weights.iter().map(|w| w * n as f64 / sum).collect();
        let mut prob = vec![1f32; n];
        let mut alias: Vec<u32> = (0..n as u32).collect();
        let mut small: Vec<u32> = Vec::new();
        let mut large: Vec<u32> = Vec::new();
        for (i, &p) in scaled.iter().enumerate() {
            if p < 1.0 {
                small.push(i as u32);
            } else {
                large.push(i as u32);
            }
        }
        while let (Some(&s), Some(&l)) = (small.last(), large.last()) {
            small.pop();
            prob[s as usize] = scaled[s as usize] as f32;
            alias[s as usize] = l;
            scaled[l as usize] -= 1.0 - scaled[s as usize];
            if scaled[l as usize] < 1.0 {
                large.pop();
                small.push(l);
            }
        }
        // What is left has probability 1 up to rounding.
        for i in small.into_iter().chain(large) {
            prob[i as usize] = 1.0;
            alias[i as usize] = i;
        }
        Ok(AliasTable { prob, alias })
    }

    pub fn len(&self) -> usize {
        self.prob.len()
    }

    pub fn is_empty(&self) -> bool {
        self.prob.is_empty()
    }

    /// One draw.
    #[inline]
    pub fn sample(&self, rng: &mut Rng) -> usize {
        let i = rng.below(self.prob.len() as u64) as usize;
        if rng.f32() < self.prob[i] {
            i
        } else {
            self.alias[i] as usize
        }
    }

    /// The distribution the table encodes (what [`AliasTable::sample`] draws from).
    pub fn probabilities(&self) -> Vec<f64> {
        let n = self.prob.len() as f64;
        let mut p = vec![0f64; self.prob.len()];
        for (i, (&q, &a)) in self.prob.iter().zip(&self.alias).enumerate() {
            p[i] += q as f64 / n;
            p[a as usize] += (1.0 - q as f64) / n;
        }
        p
    }
}

/// One physical camera: its views sorted by time, all of the same size.
#[derive(Clone, Debug)]
pub struct CameraGroup {
    /// Indices into the view list the statistics were built from, in time order.
    pub views: Vec<usize>,
    pub width: u32,
    pub height: u32,
    /// Index of this camera's first pixel in [`PixelStats::std`].
    pub pixel_offset: usize,
    /// Start of this camera's deviations in the byte buffer (`pixels * frames` bytes).
    dev_offset: usize,
}

impl CameraGroup {
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
    pub fn frames(&self) -> usize {
        self.views.len()
    }
}

/// Per-pixel temporal statistics of a list of views, grouped by physical camera.
#[derive(Clone, Debug)]
pub struct PixelStats {
    pub groups: Vec<CameraGroup>,
    /// Temporal standard deviation per pixel (`sqrt(mean_ch var_t)`), cameras concatenated.
    pub std: Vec<f32>,
    /// `sqrt(mean_ch (C(r, t) - median_t C(r))^2)` in units of 1/255, `[pixel][frame]` per
    /// camera (single-frame cameras hold none; empty when not kept, see [`PixelStats::new`]).
    dev: Vec<u8>,
    kept_deviations: bool,
}

/// The most bytes of per-pixel deviations [`PixelStats`] keeps (pixels x frames); beyond it
/// frames are drawn uniformly (with a note).
pub const MAX_DEVIATION_BYTES: usize = 1 << 32;

impl PixelStats {
    /// Statistics of `views` (one pass over every image; cameras in parallel). The per-frame
    /// deviations are kept when `deviations` is set and they fit in [`MAX_DEVIATION_BYTES`]
    /// ([`PixelStats::has_deviations`]).
    pub fn new(views: &[View], deviations: bool) -> Result<Self, SamplingError> {
        let mut groups: Vec<CameraGroup> = Vec::new();
        let mut by_key: HashMap<(usize, u32, u32), usize> = HashMap::new();
        for (i, v) in views.iter().enumerate() {
            let (w, h) = (v.image.width, v.image.height);
            // Views of one camera id and size share a group; a view without an id is alone.
            let key = v.camera_id.map(|id| (id, w, h));
            let g = match key.and_then(|k| by_key.get(&k)) {
                Some(&g) => g,
                None => {
                    groups.push(CameraGroup {
                        views: Vec::new(),
                        width: w,
                        height: h,
                        pixel_offset: 0,
                        dev_offset: 0,
                    });
                    if let Some(k) = key {
                        by_key.insert(k, groups.len() - 1);
                    }
                    groups.len() - 1
                }
            };
            groups[g].views.push(i);
        }
        let (mut pix, mut dev) = (0usize, 0usize);
        for g in groups.iter_mut() {
            g.views
                .sort_by(|&a, &b| views[a].time.total_cmp(&views[b].time).then(a.cmp(&b)));
            g.pixel_offset = pix;
            g.dev_offset = dev;
            pix += g.pixels();
            if g.frames() > 1 {
                dev = dev.saturating_add(g.pixels().saturating_mul(g.frames()));
            }
        }
        if pix >= u32::MAX as usize {
            return Err(SamplingError::TooManyPixels { pixels: pix });
        }
        let keep = deviations && dev <= MAX_DEVIATION_BYTES;
        let per_group: Vec<(Vec<f32>, Vec<u8>)> = groups
            .par_iter()
            .map(|g| group_stats(views, g, keep))
            .collect();
        let mut std = Vec::with_capacity(pix);
        let mut devs = Vec::with_capacity(if keep { dev } else { 0 });
        for (s, d) in per_group {
            std.extend(s);
            devs.extend(d);
        }
        Ok(PixelStats {
            groups,
            std,
            dev: devs,
            kept_deviations: keep,
        })
    }

    /// Whether the per-frame deviations were kept.
    pub fn has_deviations(&self) -> bool {
        self.kept_deviations
    }

    /// Bytes the per-frame deviations take (or would take).
    pub fn deviation_bytes(&self) -> usize {
        self.groups
            .iter()
            .filter(|g| g.frames() > 1)
            .map(|g| g.pixels() * g.frames())
            .sum()
    }

    /// Whether some camera films more than one frame (else nothing is known about motion).
    pub fn has_video(&self) -> bool {
        self.groups.iter().any(|g| g.frames() > 1)
    }

    /// The camera of global pixel `p` and the pixel's index inside it.
    pub fn locate(&self, p: usize) -> (usize, usize) {
        let g = self.groups.partition_point(|g| g.pixel_offset <= p) - 1;
        (g, p - self.groups[g].pixel_offset)
    }

    /// The quantised deviations of pixel `k` of camera `g`, one per frame (empty for a
    /// single-frame camera).
    pub fn deviations(&self, g: usize, k: usize) -> &[u8] {
        let grp = &self.groups[g];
        if grp.frames() < 2 || !self.kept_deviations {
            return &[];
        }
        let t = grp.frames();
        &self.dev[grp.dev_offset + k * t..grp.dev_offset + (k + 1) * t]
    }
}

/// Temporal std per pixel and quantised deviations from the median of one camera.
fn group_stats(views: &[View], g: &CameraGroup, keep: bool) -> (Vec<f32>, Vec<u8>) {
    let n = g.pixels();
    let t = g.frames();
    if t < 2 {
        return (vec![0.0; n], Vec::new());
    }
    let frames: Vec<std::borrow::Cow<'_, [u8]>> = g
        .views
        .iter()
        .map(|&i| views[i].image.data.loaded())
        .collect();
    let mut std = vec![0f32; n];
    let mut dev = vec![0u8; if keep { n * t } else { 0 }];
    let mut vals = vec![0u8; t];
    for (k, s) in std.iter_mut().enumerate() {
        let mut var = 0f64;
        let mut sq = vec![0f64; t];
        for ch in 0..3 {
            let mut sum = 0f64;
            let mut sum2 = 0f64;
            for (j, f) in frames.iter().enumerate() {
                let v = f[k * 3 + ch];
                vals[j] = v;
                let x = v as f64 / 255.0;
                sum += x;
                sum2 += x * x;
            }
            let mean = sum / t as f64;
            var += (sum2 / t as f64 - mean * mean).max(0.0);
            // The lower median (as torch.median), a value of the data.
            let mut sorted = vals.clone();
            sorted.sort_unstable();
            let med = sorted[(t - 1) / 2] as f64 / 255.0;
            for (j, q) in sq.iter_mut().enumerate() {
                let d = vals[j] as f64 / 255.0 - med;
                *q += d * d;
            }
        }
        *s = (var / 3.0).sqrt() as f32;
        if !keep {
            continue;
        }
        for (j, q) in sq.iter().enumerate() {
            dev[k * t + j] = ((q / 3.0).sqrt() * 255.0).round().clamp(0.0, 255.0) as u8;
        }
    }
    (std, dev)
}

enum Kind {
    Uniform,
    Dynamics {
        stats: PixelStats,
        pixels: AliasTable,
        /// `exp(-d / 255 / tau2)` for a deviation `d` below the pixel's largest.
        time_lut: Box<[f64; 256]>,
    },
    StaticDynamic {
        stats: PixelStats,
        static_px: Vec<u32>,
        dynamic_px: Vec<u32>,
        cfg: SamplingConfig,
    },
}

/// A batch sampler built once per dataset.
pub struct RaySampler {
    kind: Kind,
    /// Why the sampler is not the one asked for (monocular data), for the user.
    pub note: Option<String>,
}

impl RaySampler {
    /// Builds the sampler `cfg` asks for over `data.train`.
    pub fn new(data: &Dataset, cfg: &SamplingConfig) -> Result<Self, SamplingError> {
        cfg.validate()?;
        if cfg.mode == SamplingMode::Uniform {
            return Ok(RaySampler {
                kind: Kind::Uniform,
                note: None,
            });
        }
        let tau2 = cfg.tau2 as f64;
        let mut lut = Box::new([0f64; 256]);
        for (d, v) in lut.iter_mut().enumerate() {
            *v = tempered_weight(-(d as f64) / 255.0, 0.0, tau2);
        }
        // Deviations are only needed when P(t | r) is not uniform.
        let time_uniform = lut.iter().all(|&v| v == 1.0);
        let want_dev = cfg.mode == SamplingMode::Dynamics && !time_uniform;
        let stats = PixelStats::new(&data.train, want_dev)?;
        let mut note = None;
        if want_dev && !stats.has_deviations() {
            note = Some(format!(
                "sampling: P(t | r) would keep {:.1} GiB of per-frame deviations (limit {} GiB); drawing frames uniformly (use --downscale for P(t | r))",
                stats.deviation_bytes() as f64 / (1u64 << 30) as f64,
                MAX_DEVIATION_BYTES >> 30
            ));
        }
        if !stats.has_video() {
            return Ok(RaySampler {
                kind: Kind::Uniform,
                note: Some(format!(
                    "sampling.mode={:?}: every training camera of {} sees a single frame (monocular data), so no pixel has a temporal history; sampling uniformly",
                    cfg.mode, data.name
                )),
            });
        }
        let kind = match cfg.mode {
            SamplingMode::Uniform => Kind::Uniform,
            SamplingMode::Dynamics => {
                let max = stats.std.iter().fold(0f32, |a, &b| a.max(b)) as f64;
                let tau1 = cfg.tau1 as f64;
                let w: Vec<f64> = stats
                    .std
                    .iter()
                    .map(|&s| tempered_weight(s as f64, max, tau1))
                    .collect();
                let pixels = AliasTable::new(&w)?;
                Kind::Dynamics {
                    stats,
                    pixels,
                    time_lut: lut,
                }
            }
            SamplingMode::StaticDynamic => {
                let (mut st, mut dy) = (Vec::new(), Vec::new());
                for (p, &s) in stats.std.iter().enumerate() {
                    if (s as f64) * (s as f64) > cfg.dynamic_variance as f64 {
                        dy.push(p as u32);
                    } else {
                        st.push(p as u32);
                    }
                }
                Kind::StaticDynamic {
                    stats,
                    static_px: st,
                    dynamic_px: dy,
                    cfg: cfg.clone(),
                }
            }
        };
        Ok(RaySampler { kind, note })
    }

    /// One line about the sampler (for logs).
    pub fn describe(&self) -> String {
        match &self.kind {
            Kind::Uniform => "uniform".into(),
            Kind::Dynamics { stats, .. } => format!(
                "dynamics-aware over {} pixels of {} cameras",
                stats.std.len(),
                stats.groups.len()
            ),
            Kind::StaticDynamic {
                static_px,
                dynamic_px,
                ..
            } => format!(
                "static/dynamic: {} static and {} dynamic pixels",
                static_px.len(),
                dynamic_px.len()
            ),
        }
    }

    /// Draws `(view index, x, y)` for `n` rays; `fraction` is how far the run is (0..1).
    pub fn draw(&self, data: &Dataset, n: usize, fraction: f32, rng: &mut Rng) -> Vec<[u32; 3]> {
        let mut out = Vec::with_capacity(n);
        match &self.kind {
            Kind::Uniform => {
                for _ in 0..n {
                    let i = rng.below(data.train.len() as u64) as usize;
                    let img = &data.train[i].image;
                    let x = rng.below(img.width as u64) as u32;
                    let y = rng.below(img.height as u64) as u32;
                    out.push([i as u32, x, y]);
                }
            }
            Kind::Dynamics {
                stats,
                pixels,
                time_lut,
            } => {
                for _ in 0..n {
                    let p = pixels.sample(rng);
                    let (g, k) = stats.locate(p);
                    let frames = stats.groups[g].frames();
                    let t = draw_time(stats.deviations(g, k), frames, time_lut, rng);
                    out.push(pixel_of(stats, g, k, t));
                }
            }
            Kind::StaticDynamic {
                stats,
                static_px,
                dynamic_px,
                cfg,
            } => {
                let f = fraction.clamp(0.0, 1.0);
                let ratio = cfg.ratio_start + (cfg.ratio_end - cfg.ratio_start) * f;
                let n_dyn = if dynamic_px.is_empty() {
                    0
                } else if static_px.is_empty() {
                    n
                } else {
                    ((n as f32 / (ratio + 1.0)).round() as usize).min(n)
                };
                while out.len() < n_dyn {
                    let p = dynamic_px[rng.below(dynamic_px.len() as u64) as usize] as usize;
                    let (g, k) = stats.locate(p);
                    let reps = 1 + rng.below(cfg.max_repeats as u64) as usize;
                    for _ in 0..reps.min(n_dyn - out.len()) {
                        let t = rng.below(stats.groups[g].frames() as u64) as usize;
                        out.push(pixel_of(stats, g, k, t));
                    }
                }
                while out.len() < n {
                    let p = static_px[rng.below(static_px.len() as u64) as usize] as usize;
                    let (g, k) = stats.locate(p);
                    let t = rng.below(stats.groups[g].frames() as u64) as usize;
                    out.push(pixel_of(stats, g, k, t));
                }
            }
        }
        out
    }

    /// Draws a batch of `n` rays with their colours (see [`push_ray`] for backgrounds and
    /// jitter); `fraction` is how far the run is (0..1). With `pixels`, the `(view, x, y)` of
    /// each ray is recorded there (for [`PixelMotion::mask_weights`]).
    #[allow(clippy::too_many_arguments)]
    pub fn sample_batch(
        &self,
        data: &Dataset,
        n: usize,
        fraction: f32,
        rng: &mut Rng,
        rays: &mut Vec<TimedRay>,
        targets: &mut Vec<[f32; 3]>,
        mut backgrounds: Option<&mut Vec<[f32; 3]>>,
        jitter: bool,
        pixels: Option<&mut Vec<[u32; 3]>>,
    ) {
        if let Kind::Uniform = self.kind {
            // The original sampler, draw for draw.
            return sample_uniform(data, n, rng, rays, targets, backgrounds, jitter, pixels);
        }
        rays.clear();
        targets.clear();
        if let Some(b) = backgrounds.as_deref_mut() {
            b.clear();
        }
        let drawn = self.draw(data, n, fraction, rng);
        for &[v, x, y] in &drawn {
            push_ray(
                data,
                &data.train[v as usize],
                x,
                y,
                rng,
                jitter,
                rays,
                targets,
                backgrounds.as_deref_mut(),
            );
        }
        if let Some(p) = pixels {
            p.clear();
            p.extend(drawn);
        }
    }
}

/// The plain NeRF sampler: a random training view, then a random pixel, for each of `n` rays
/// (with its colour and, with `backgrounds`, its background: [`push_ray`]); with `pixels`, each
/// ray's `(view, x, y)` is recorded there.
#[allow(clippy::too_many_arguments)]
pub fn sample_uniform(
    data: &Dataset,
    n: usize,
    rng: &mut Rng,
    rays: &mut Vec<TimedRay>,
    targets: &mut Vec<[f32; 3]>,
    mut backgrounds: Option<&mut Vec<[f32; 3]>>,
    jitter: bool,
    mut pixels: Option<&mut Vec<[u32; 3]>>,
) {
    rays.clear();
    targets.clear();
    if let Some(b) = backgrounds.as_deref_mut() {
        b.clear();
    }
    if let Some(p) = pixels.as_deref_mut() {
        p.clear();
    }
    let views = &data.train;
    for _ in 0..n {
        let vi = rng.below(views.len() as u64) as usize;
        let v = &views[vi];
        let px = rng.below(v.image.width as u64) as u32;
        let py = rng.below(v.image.height as u64) as u32;
        push_ray(
            data,
            v,
            px,
            py,
            rng,
            jitter,
            rays,
            targets,
            backgrounds.as_deref_mut(),
        );
        if let Some(p) = pixels.as_deref_mut() {
            p.push([vi as u32, px, py]);
        }
    }
}

/// The temporal standard deviation of every training pixel, looked up by `(view, x, y)`: which
/// rays the per-sample mask loss spares (`TrainSettings::sample_mask_moving_std`).
pub struct PixelMotion<'a> {
    /// The sampler's statistics when it keeps them, else computed here.
    stats: std::borrow::Cow<'a, PixelStats>,
    /// The camera group of each training view.
    group_of_view: Vec<u32>,
}

impl<'a> PixelMotion<'a> {
    /// The statistics of `data.train`: borrowed from `sampler` when it keeps them (the
    /// dynamics-aware samplers), else one pass over the images. `None` when no training camera
    /// films more than one frame (monocular data: nothing is known about motion per pixel).
    pub fn new(data: &Dataset, sampler: &'a RaySampler) -> Result<Option<Self>, SamplingError> {
        let stats = match &sampler.kind {
            Kind::Dynamics { stats, .. } | Kind::StaticDynamic { stats, .. } => {
                std::borrow::Cow::Borrowed(stats)
            }
            Kind::Uniform => std::borrow::Cow::Owned(PixelStats::new(&data.train, false)?),
        };
        if !stats.has_video() {
            return Ok(None);
        }
        let mut group_of_view = vec![0u32; data.train.len()];
        for (g, grp) in stats.groups.iter().enumerate() {
            for &v in &grp.views {
                group_of_view[v] = g as u32;
            }
        }
        Ok(Some(PixelMotion {
            stats,
            group_of_view,
        }))
    }

    /// The temporal std of pixel `(x, y)` of training view `v` (0 for a single-frame camera).
    pub fn std_at(&self, [v, x, y]: [u32; 3]) -> f32 {
        let g = &self.stats.groups[self.group_of_view[v as usize] as usize];
        self.stats.std[g.pixel_offset + y as usize * g.width as usize + x as usize]
    }

    /// The share of training pixels (over cameras, not frames) whose std exceeds `moving_std`.
    pub fn moving_share(&self, moving_std: f32) -> f64 {
        let n = self.stats.std.len().max(1);
        self.stats.std.iter().filter(|&&s| s > moving_std).count() as f64 / n as f64
    }

    /// One factor per ray for the per-sample mask loss: 0 for a pixel whose std exceeds
    /// `moving_std`, else 1.
    pub fn mask_weights(&self, pixels: &[[u32; 3]], moving_std: f32, out: &mut Vec<f32>) {
        out.clear();
        out.extend(pixels.iter().map(|&p| {
            if self.std_at(p) > moving_std {
                0.0
            } else {
                1.0
            }
        }));
    }
}

fn pixel_of(stats: &PixelStats, g: usize, k: usize, t: usize) -> [u32; 3] {
    let grp = &stats.groups[g];
    let w = grp.width as usize;
    [grp.views[t] as u32, (k % w) as u32, (k / w) as u32]
}

/// A frame index with `P(t) ∝ lut[max_dev - dev_t]` (frame 0 for a single-frame camera, a
/// uniform frame without deviations).
fn draw_time(devs: &[u8], frames: usize, lut: &[f64; 256], rng: &mut Rng) -> usize {
    if frames < 2 {
        return 0;
    }
    if devs.len() != frames {
        return rng.below(frames as u64) as usize;
    }
    let top = *devs.iter().max().unwrap_or(&0);
    let total: f64 = devs.iter().map(|&d| lut[(top - d) as usize]).sum();
    let mut u = rng.f32() as f64 * total;
    let mut last_max = 0;
    for (t, &d) in devs.iter().enumerate() {
        let w = lut[(top - d) as usize];
        if u < w {
            return t;
        }
        u -= w;
        if d == top {
            last_max = t;
        }
    }
    // Rounding left `u` just above the sum: the last frame with weight 1.
    last_max
}

/// Appends the ray through pixel `(px, py)` of `v` (jittered inside the pixel when asked) and its
/// colour. With `backgrounds`, a view with alpha is composited on a random colour (recorded);
/// views without alpha record the dataset background.
#[allow(clippy::too_many_arguments)]
pub fn push_ray(
    data: &Dataset,
    v: &View,
    px: u32,
    py: u32,
    rng: &mut Rng,
    jitter: bool,
    rays: &mut Vec<TimedRay>,
    targets: &mut Vec<[f32; 3]>,
    backgrounds: Option<&mut Vec<[f32; 3]>>,
) {
    let w = v.image.width;
    // jitter inside the pixel so that the field sees the whole footprint
    let (ju, jv) = if jitter {
        (rng.f32(), rng.f32())
    } else {
        (0.5, 0.5)
    };
    let ray = v.camera.ray_at(px as f32 + ju, py as f32 + jv);
    rays.push(TimedRay {
        origin: ray.origin,
        dir: ray.dir,
        time: v.time,
    });
    let mut target = v.image.get(px, py);
    if let Some(b) = backgrounds {
        match &v.alpha {
            Some(alpha) => {
                let bg = [rng.f32(), rng.f32(), rng.f32()];
                let a = alpha[(py * w + px) as usize] as f32 / 255.0;
                // the image is composited on white: c*a + (1 - a)
                for ch in 0..3 {
                    target[ch] += (bg[ch] - 1.0) * (1.0 - a);
                }
                b.push(bg);
            }
            None => b.push(data.background),
        }
    }
    targets.push(target);
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::{Camera, SceneBounds};
    use msth_dataset::Image8;
    use std::path::PathBuf;

    /// Pearson's chi-square of `counts` against `probs` (bins with expected count < 5 merged
    /// into one), and its degrees of freedom.
    fn chi_square(counts: &[u64], probs: &[f64]) -> (f64, usize) {
        let n: u64 = counts.iter().sum();
        let (mut chi, mut bins) = (0.0, 0usize);
        let (mut rest_obs, mut rest_exp) = (0.0, 0.0);
        for (&c, &p) in counts.iter().zip(probs) {
            let e = p * n as f64;
            if e < 5.0 {
                rest_obs += c as f64;
                rest_exp += e;
                if e == 0.0 {
                    assert_eq!(c, 0, "drew an outcome of probability 0");
                }
                continue;
            }
            chi += (c as f64 - e).powi(2) / e;
            bins += 1;
        }
        if rest_exp >= 5.0 {
            chi += (rest_obs - rest_exp).powi(2) / rest_exp;
            bins += 1;
        }
        (chi, bins.saturating_sub(1))
    }

    /// The 99.9% quantile of chi-square with `k` degrees of freedom (Wilson-Hilferty).
    fn chi_square_999(k: usize) -> f64 {
        let k = k as f64;
        let z = 3.09;
        k * (1.0 - 2.0 / (9.0 * k) + z * (2.0 / (9.0 * k)).sqrt()).powi(3)
    }

    #[test]
    fn alias_table_matches_its_weights() {
        let w: Vec<f64> = (0..37)
            .map(|i| match i % 5 {
                0 => 0.0,
                1 => 1.0,
                2 => 7.5,
                3 => 0.01,
                _ => (i as f64).sqrt(),
            })
            .collect();
        let t = AliasTable::new(&w).unwrap();
        let sum: f64 = w.iter().sum();
        for (p, wi) in t.probabilities().iter().zip(&w) {
            assert!((p - wi / sum).abs() < 1e-6, "{p} vs {}", wi / sum);
        }
        let mut rng = Rng::new(7);
        let mut counts = vec![0u64; w.len()];
        for _ in 0..400_000 {
            counts[t.sample(&mut rng)] += 1;
        }
        let probs: Vec<f64> = w.iter().map(|x| x / sum).collect();
        let (chi, dof) = chi_square(&counts, &probs);
        assert!(chi < chi_square_999(dof), "chi2 {chi} with {dof} dof");
        // A deliberately wrong target is rejected by the same test (the test can fail).
        let mut wrong = probs.clone();
        wrong.swap(1, 2);
        let (chi_w, _) = chi_square(&counts, &wrong);
        assert!(chi_w > chi_square_999(dof), "wrong target passed: {chi_w}");
    }

    #[test]
    fn alias_table_rejects_bad_weights() {
        assert!(AliasTable::new(&[]).is_err());
        assert!(AliasTable::new(&[0.0, 0.0]).is_err());
        assert!(AliasTable::new(&[1.0, f64::NAN]).is_err());
        assert!(AliasTable::new(&[1.0, -1.0]).is_err());
        assert!(AliasTable::new(&[f64::MAX, f64::MAX]).is_err());
        // One weight: always that index.
        let t = AliasTable::new(&[3.0]).unwrap();
        let mut rng = Rng::new(1);
        assert!((0..100).all(|_| t.sample(&mut rng) == 0));
    }

    /// `cams` fixed cameras filming `frames` frames of `w x h`, pixel colours from `colour`.
    fn video(
        cams: usize,
        frames: usize,
        w: u32,
        h: u32,
        colour: impl Fn(usize, usize, u32, u32) -> [u8; 3],
    ) -> Dataset {
        let mut train = Vec::new();
        for c in 0..cams {
            let cam = Camera::look_at(
                w,
                h,
                0.9,
                Vec3::new(c as f32, -4.0, 0.0),
                Vec3::ZERO,
                Vec3::Z,
            );
            for f in 0..frames {
                let mut data = Vec::new();
                for y in 0..h {
                    for x in 0..w {
                        data.extend_from_slice(&colour(c, f, x, y));
                    }
                }
                train.push(View {
                    camera: cam,
                    time: if frames > 1 {
                        f as f32 / (frames - 1) as f32
                    } else {
                        0.0
                    },
                    image: Image8 {
                        width: w,
                        height: h,
                        data: data.into(),
                    },
                    source: PathBuf::from(format!("cam{c}/{f}")),
                    camera_id: Some(c),
                    alpha: None,
                });
            }
        }
        // Shuffle the order of the views: grouping must not depend on it.
        train.reverse();
        Dataset {
            name: "test-video".into(),
            train,
            test: Vec::new(),
            bounds: SceneBounds::dnerf_default(),
            background: [1.0; 3],
            num_frames: frames,
            near: None,
        }
    }

    /// Pixel x of camera c blinks between 0 and a level that grows with x, on frames where
    /// `f % (x + 1) == 0`: different temporal std per pixel and non-uniform times.
    fn blinking(c: usize, f: usize, x: u32, _y: u32) -> [u8; 3] {
        let level = (40 * x as usize + 20 * c).min(255) as u8;
        let on = f.is_multiple_of(x as usize + 1);
        if on {
            [level, level / 2, 0]
        } else {
            [0, 0, 0]
        }
    }

    fn dynamics(tau1: f32, tau2: f32) -> SamplingConfig {
        SamplingConfig {
            mode: SamplingMode::Dynamics,
            tau1,
            tau2,
            ..Default::default()
        }
    }

    /// The exact target of the dynamics-aware sampler over `(view, x, y)`, from the images.
    fn expected(data: &Dataset, tau1: f64, tau2: f64) -> HashMap<[u32; 3], f64> {
        let stats = PixelStats::new(&data.train, false).unwrap();
        let max = stats.std.iter().fold(0f32, |a, &b| a.max(b)) as f64;
        let pw: Vec<f64> = stats
            .std
            .iter()
            .map(|&s| tempered_weight(s as f64, max, tau1))
            .collect();
        let psum: f64 = pw.iter().sum();
        let mut out = HashMap::new();
        for (p, &w) in pw.iter().enumerate() {
            let (g, k) = stats.locate(p);
            let grp = &stats.groups[g];
            let (x, y) = (k as u32 % grp.width, k as u32 / grp.width);
            // deviations straight from the pixels, RMS over channels
            let mut devs = Vec::new();
            let vals: Vec<[f64; 3]> = grp
                .views
                .iter()
                .map(|&v| {
                    let c = data.train[v].image.get(x, y);
                    [c[0] as f64, c[1] as f64, c[2] as f64]
                })
                .collect();
            let mut med = [0f64; 3];
            for ch in 0..3 {
                let mut s: Vec<f64> = vals.iter().map(|v| v[ch]).collect();
                s.sort_by(f64::total_cmp);
                med[ch] = s[(s.len() - 1) / 2];
            }
            for v in &vals {
                let d2: f64 = (0..3).map(|ch| (v[ch] - med[ch]).powi(2)).sum::<f64>() / 3.0;
                devs.push((d2.sqrt() * 255.0).round() / 255.0);
            }
            let top = devs.iter().cloned().fold(0.0, f64::max);
            let tw: Vec<f64> = devs
                .iter()
                .map(|&d| tempered_weight(d, top, tau2))
                .collect();
            let tsum: f64 = tw.iter().sum();
            for (t, wt) in tw.iter().enumerate() {
                *out.entry([grp.views[t] as u32, x, y]).or_insert(0.0) += w / psum * wt / tsum;
            }
        }
        out
    }

    fn draw_counts(data: &Dataset, cfg: &SamplingConfig, n: usize) -> HashMap<[u32; 3], u64> {
        let s = RaySampler::new(data, cfg).unwrap();
        assert!(s.note.is_none());
        let mut rng = Rng::new(11);
        let mut c = HashMap::new();
        for px in s.draw(data, n, 0.5, &mut rng) {
            *c.entry(px).or_insert(0u64) += 1;
        }
        c
    }

    /// `PixelMotion` spares exactly the pixels whose temporal std exceeds the threshold, each
    /// sampler records the pixel each ray went through (its target is that pixel's colour), and
    /// a monocular dataset has no motion to spare.
    #[test]
    fn mask_loss_spares_the_pixels_that_change() {
        // Camera 0: column 0 still (grey), column 1 blinking; camera 1: still everywhere.
        let data = video(2, 6, 2, 3, |c, f, x, _| {
            if c == 0 && x == 1 && f % 2 == 0 {
                [250, 250, 250]
            } else {
                [90, 90, 90]
            }
        });
        for mode in [SamplingMode::Uniform, SamplingMode::Dynamics] {
            let cfg = SamplingConfig {
                mode,
                ..SamplingConfig::default()
            };
            let sampler = RaySampler::new(&data, &cfg).unwrap();
            // Computed for the uniform sampler, borrowed from the dynamics-aware one.
            let motion = PixelMotion::new(&data, &sampler).unwrap().expect("a video");
            assert!((motion.moving_share(0.02) - 3.0 / 12.0).abs() < 1e-12);
            let (mut rays, mut targets, mut pixels, mut w) =
                (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            sampler.sample_batch(
                &data,
                500,
                0.5,
                &mut Rng::new(3),
                &mut rays,
                &mut targets,
                None,
                false,
                Some(&mut pixels),
            );
            assert_eq!(pixels.len(), 500);
            motion.mask_weights(&pixels, 0.02, &mut w);
            let (mut spared, mut kept) = (0, 0);
            for ((&[v, x, y], t), &wi) in pixels.iter().zip(&targets).zip(&w) {
                let view = &data.train[v as usize];
                assert_eq!(
                    *t,
                    view.image.get(x, y),
                    "{mode:?}: the target is the pixel's"
                );
                let moving = view.camera_id == Some(0) && x == 1;
                assert_eq!(
                    wi,
                    if moving { 0.0 } else { 1.0 },
                    "{mode:?} view {v} x {x}"
                );
                if moving {
                    spared += 1;
                } else {
                    kept += 1;
                }
            }
            assert!(
                spared > 0 && kept > 0,
                "{mode:?}: {spared} spared, {kept} kept"
            );
            // Without the record the same draws give the same rays.
            let (mut rays2, mut targets2) = (Vec::new(), Vec::new());
            sampler.sample_batch(
                &data,
                500,
                0.5,
                &mut Rng::new(3),
                &mut rays2,
                &mut targets2,
                None,
                false,
                None,
            );
            assert_eq!(targets2, targets);
        }
        // One frame per camera: nothing is known about motion.
        let still = video(3, 1, 2, 2, |_, _, _, _| [10, 20, 30]);
        let uniform = RaySampler::new(&still, &SamplingConfig::default()).unwrap();
        assert!(PixelMotion::new(&still, &uniform).unwrap().is_none());
    }

    #[test]
    fn dynamics_sampler_matches_the_paper_distribution() {
        let data = video(2, 6, 5, 2, blinking);
        for (tau1, tau2) in [(0.1, 0.1), (0.05, 0.3), (1.0, 0.02), (0.2, f32::INFINITY)] {
            let exp = expected(&data, tau1 as f64, tau2 as f64);
            let counts = draw_counts(&data, &dynamics(tau1, tau2), 300_000);
            let keys: Vec<[u32; 3]> = exp.keys().cloned().collect();
            let obs: Vec<u64> = keys
                .iter()
                .map(|k| counts.get(k).copied().unwrap_or(0))
                .collect();
            let probs: Vec<f64> = keys.iter().map(|k| exp[k]).collect();
            assert_eq!(obs.iter().sum::<u64>(), 300_000, "drew outside the targets");
            let (chi, dof) = chi_square(&obs, &probs);
            assert!(
                chi < chi_square_999(dof),
                "tau {tau1}/{tau2}: chi2 {chi}, {dof} dof"
            );
        }
    }

    #[test]
    fn temperature_extremes_and_constant_video_stay_finite() {
        let data = video(2, 4, 4, 3, blinking);
        let stats = PixelStats::new(&data.train, false).unwrap();
        let max = stats.std.iter().fold(0f32, |a, &b| a.max(b));
        for tau in [0.0f32, 1e-30, 1e-6, 1.0, 1e30, f32::MAX, f32::INFINITY] {
            let cfg = dynamics(tau, tau);
            let s = RaySampler::new(&data, &cfg).unwrap();
            let mut rng = Rng::new(3);
            let d = s.draw(&data, 2000, 0.0, &mut rng);
            assert_eq!(d.len(), 2000);
            for &[v, x, y] in &d {
                let img = &data.train[v as usize].image;
                assert!(x < img.width && y < img.height);
            }
            if tau <= 1e-6 {
                // Only the most dynamic pixels (of the largest std) are drawn.
                let ok = d.iter().all(|&[v, x, y]| {
                    let cam = data.train[v as usize].camera_id.unwrap();
                    let g = stats
                        .groups
                        .iter()
                        .position(|g| data.train[g.views[0]].camera_id == Some(cam))
                        .unwrap();
                    let k = (y * stats.groups[g].width + x) as usize;
                    stats.std[stats.groups[g].pixel_offset + k] == max
                });
                assert!(ok, "tau {tau}: drew a pixel below the largest std");
            }
        }
        // At tau = inf both draws are uniform: the target is the uniform sampler's.
        let exp = expected(&data, f64::INFINITY, f64::INFINITY);
        let u = 1.0 / (data.train.len() * 12) as f64;
        assert!(exp.values().all(|p| (p - u).abs() < 1e-12));
        // A constant video: every std and deviation is 0; any temperature is uniform.
        let flat = video(3, 5, 4, 2, |_, _, _, _| [90, 90, 90]);
        for tau in [0.0f32, 1e-30, 0.1, f32::INFINITY] {
            let exp = expected(&flat, tau as f64, tau as f64);
            let u = 1.0 / (flat.train.len() * 8) as f64;
            assert!(exp.values().all(|p| (p - u).abs() < 1e-12), "tau {tau}");
            let counts = draw_counts(&flat, &dynamics(tau, tau), 60_000);
            let keys: Vec<[u32; 3]> = exp.keys().cloned().collect();
            let obs: Vec<u64> = keys
                .iter()
                .map(|k| counts.get(k).copied().unwrap_or(0))
                .collect();
            let (chi, dof) = chi_square(&obs, &vec![u; keys.len()]);
            assert!(
                chi < chi_square_999(dof),
                "constant video, tau {tau}: {chi}"
            );
        }
        // Invalid temperatures are refused by name.
        for bad in [-1.0, f32::NAN] {
            let e = SamplingConfig {
                tau1: bad,
                ..dynamics(0.1, 0.1)
            }
            .validate()
            .unwrap_err();
            assert!(e.to_string().contains("tau1"), "{e}");
        }
    }

    #[test]
    fn monocular_data_falls_back_to_uniform_with_a_note() {
        let mut data = video(1, 6, 4, 3, blinking);
        for v in data.train.iter_mut() {
            v.camera_id = None;
        }
        for mode in [SamplingMode::Dynamics, SamplingMode::StaticDynamic] {
            let cfg = SamplingConfig {
                mode,
                ..Default::default()
            };
            let s = RaySampler::new(&data, &cfg).unwrap();
            let note = s.note.clone().expect("a note");
            assert!(note.contains("monocular"), "{note}");
            assert_eq!(s.describe(), "uniform");
        }
    }

    #[test]
    fn static_dynamic_sampler_follows_the_ratio() {
        // Camera 0 pixel x = 4 blinks between 0 and 160 every other frame: variance 0.1 > 0.03;
        // everything else is far below.
        let data = video(2, 6, 5, 2, |c, f, x, _| {
            if c == 0 && x == 4 && f % 2 == 0 {
                [160, 160, 160]
            } else {
                [10, 20, 30]
            }
        });
        let cfg = SamplingConfig {
            mode: SamplingMode::StaticDynamic,
            ..Default::default()
        };
        let s = RaySampler::new(&data, &cfg).unwrap();
        assert!(s.describe().contains("2 dynamic"), "{}", s.describe());
        let mut rng = Rng::new(5);
        for (fraction, ratio) in [(0.0, 50.0), (1.0, 10.0)] {
            let d = s.draw(&data, 5100, fraction, &mut rng);
            let dynamic = d
                .iter()
                .filter(|&&[v, x, _]| data.train[v as usize].camera_id == Some(0) && x == 4)
                .count();
            let want = (5100.0f64 / (ratio + 1.0)).round() as usize;
            assert_eq!(dynamic, want, "fraction {fraction}");
        }
    }
}
