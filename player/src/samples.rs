//! Sample-level reuse for incremental playback: the paper's "only render the dynamic parts"
//! taken down to the samples of a ray (method.md §5).
//!
//! The ray-level cache ([`crate::render`]) re-renders a dynamic ray in full every frame: the
//! proposal field, resampling, and both grids and both MLPs at every sample. Most of that work
//! does not depend on time. For each dynamic ray, [`SampleCache::build`] fixes one set of sample
//! positions that serves the whole clip ([`msth_core::pipeline::playback_partition`]: the proposal
//! weights of several times, combined per bin by their maximum) and sorts the samples:
//!
//! - **static samples** (`1 - m < cutoff`, the 4D lookup skipped as the full renderer skips it):
//!   density and colour are computed once and kept;
//! - **dynamic samples**: the 3D features (with the blend's coefficient) and the 4D weight
//!   `1 - m` are kept ([`msth_core::field::EncodingLayout::static_term`]); a frame evaluates
//!   only the field's dynamic part at the new time
//!   ([`msth_core::field::FieldLayout::forward_density_prescaled`]: the 4D grid and the density
//!   MLP) and the colour MLP, the latter only where the new transmittance can still reach the
//!   sample.
//!
//! A frame then costs, per dynamic ray, the dynamic samples' 4D lookups and MLPs, and no
//! proposal pass. The price is that sample positions no longer follow the proposal field frame
//! by frame: a frame is the same field integrated over a different (time-independent)
//! partition, which `msth bench play` measures against full renders (PSNR).
//!
//! [`reference_render`] is the plain version of a frame (per-point reference field, no cache),
//! which the fast path is tested against.

use msth_core::config::ModelConfig;
use msth_core::field::{FieldScratch, ModelLayout};
use msth_core::pipeline::{
    composite_ray, direction_encodings, playback_partition, Partition, TimedRay, Workspace,
    HIDDEN_TRANSMITTANCE,
};
use msth_core::render;
use msth_core::sh::SH_COEFFS;
use rayon::prelude::*;

/// Rays per work item when building and rendering.
const CHUNK: usize = 128;

/// Fixed samples of a set of rays, with everything about them that does not depend on time.
#[derive(Clone, Debug, Default)]
pub struct SampleCache {
    /// Samples per ray.
    samples: usize,
    rays: usize,
    /// `[rays * SH_COEFFS]`: direction encodings.
    sh: Vec<f32>,
    /// `[rays * samples]`: interval lengths.
    deltas: Vec<f32>,
    /// `[rays * samples]`: density of static samples (dynamic ones are filled per frame).
    sigma: Vec<f32>,
    /// `[rays * samples * 3]`: colour of static samples.
    rgb: Vec<f32>,
    /// `[rays + 1]`: each ray's range in the dynamic-sample arrays.
    dyn_start: Vec<u32>,
    /// Per dynamic sample: its index within its ray.
    dyn_slot: Vec<u16>,
    /// `[dynamic * 3]`: unit-cube points.
    dyn_pts: Vec<f32>,
    /// `[dynamic * h3_dim]`: static terms, the 3D features times the blend's 3D coefficient
    /// ([`msth_core::field::EncodingLayout::static_term`]; empty without h3).
    dyn_h3: Vec<f32>,
    /// Per dynamic sample: the blend's 4D coefficient.
    dyn_b: Vec<f32>,
}

/// Per-thread buffers of [`SampleCache::render`].
#[derive(Default)]
struct Scratch {
    /// `[dynamic * 4]`: the chunk's dynamic samples at the frame's time.
    pts: Vec<f32>,
    field: FieldScratch,
    /// Per dynamic sample of the chunk: its ray.
    dyn_ray: Vec<u32>,
    /// Visible dynamic samples (index from the chunk's first).
    active: Vec<u32>,
    sigma: Vec<f32>,
    w: Vec<f32>,
    rgb: Vec<f32>,
}

/// Upper bound of the bytes a [`SampleCache`] of `rays` rays with `samples` samples each takes.
pub fn cache_bytes_bound(layout: &ModelLayout, rays: usize, samples: usize) -> u64 {
    let e = layout.field.encoding.out_dim as u64;
    let per_sample = 4 * (1 + 1 + 3) + (2 + 4 * (3 + e + 1));
    rays as u64 * (samples as u64 * per_sample + 4 * (SH_COEFFS as u64 + 1))
}

impl SampleCache {
    /// Fixes `samples` samples on each of `rays` from the proposal weights at `times` and
    /// evaluates what does not change with time; samples with `1 - m >= cutoff` stay dynamic.
    pub fn build(
        cfg: &ModelConfig,
        layout: &ModelLayout,
        params: &[f32],
        rays: &[TimedRay],
        times: &[f32],
        samples: usize,
        cutoff: f32,
    ) -> SampleCache {
        let samples = samples.clamp(1, u16::MAX as usize);
        let parts: Vec<SampleCache> = rays
            .par_chunks(crate::render::rays_per_batch(cfg, CHUNK))
            .map_init(
                || (Workspace::default(), FieldScratch::default()),
                |(ws, fs), c| {
                    let part = playback_partition(cfg, layout, params, c, times, samples, None, ws);
                    Self::build_chunk(layout, params, c, &part, cutoff, fs)
                },
            )
            .collect();
        let mut out = SampleCache {
            samples,
            dyn_start: vec![0],
            ..Default::default()
        };
        for p in parts {
            let base = *out.dyn_start.last().expect("starts with 0");
            out.rays += p.rays;
            out.sh.extend(p.sh);
            out.deltas.extend(p.deltas);
            out.sigma.extend(p.sigma);
            out.rgb.extend(p.rgb);
            out.dyn_start
                .extend(p.dyn_start[1..].iter().map(|&s| s + base));
            out.dyn_slot.extend(p.dyn_slot);
            out.dyn_pts.extend(p.dyn_pts);
            out.dyn_h3.extend(p.dyn_h3);
            out.dyn_b.extend(p.dyn_b);
        }
        out
    }

    fn build_chunk(
        layout: &ModelLayout,
        params: &[f32],
        rays: &[TimedRay],
        part: &Partition,
        cutoff: f32,
        fs: &mut FieldScratch,
    ) -> SampleCache {
        let n = rays.len();
        let s = part.samples;
        let enc = &layout.field.encoding;
        let mut sh = Vec::new();
        direction_encodings(rays, &mut sh);
        // Static samples as the full renderer evaluates them: the 4D lookup skipped below the
        // cutoff (a cutoff of 0 skips nothing, and then no sample is static).
        fs.enc.static_cutoff = cutoff;
        layout
            .field
            .forward_density(params, &part.points, n * s, fs);
        layout
            .field
            .forward_color(params, &sh, &|j| j / s, None, n * s, fs);
        let mut out = SampleCache {
            samples: s,
            rays: n,
            sh,
            deltas: part.deltas.clone(),
            sigma: fs.sigma[..n * s].to_vec(),
            rgb: fs.rgb[..n * s * 3].to_vec(),
            dyn_start: Vec::with_capacity(n + 1),
            ..Default::default()
        };
        out.dyn_start.push(0);
        for i in 0..n {
            for k in 0..s {
                let j = i * s + k;
                if enc.is_dynamic(&fs.enc, j) {
                    out.dyn_slot.push(k as u16);
                    out.dyn_pts
                        .extend_from_slice(&part.points[j * 4..j * 4 + 3]);
                    let b = enc.static_term(&fs.enc, j, &mut out.dyn_h3);
                    out.dyn_b.push(b);
                    out.sigma[j] = 0.0;
                    out.rgb[j * 3..j * 3 + 3].fill(0.0);
                }
            }
            out.dyn_start.push(out.dyn_slot.len() as u32);
        }
        out
    }

    /// Rays in the cache.
    pub fn rays(&self) -> usize {
        self.rays
    }

    /// Samples per ray.
    pub fn samples_per_ray(&self) -> usize {
        self.samples
    }

    /// Samples evaluated at every frame.
    pub fn dynamic_samples(&self) -> usize {
        self.dyn_slot.len()
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        4 * (self.sh.len()
            + self.deltas.len()
            + self.sigma.len()
            + self.rgb.len()
            + self.dyn_start.len()
            + self.dyn_pts.len()
            + self.dyn_h3.len()
            + self.dyn_b.len()) as u64
            + 2 * self.dyn_slot.len() as u64
    }

    /// Colours of the cached rays at normalised time `time`, in order.
    pub fn render(
        &self,
        cfg: &ModelConfig,
        layout: &ModelLayout,
        params: &[f32],
        time: f32,
    ) -> Vec<[f32; 3]> {
        let time = if time >= 0.0 { time.min(1.0) } else { 0.0 };
        let batch = crate::render::rays_per_batch(cfg, CHUNK);
        let chunks = self.rays.div_ceil(batch);
        let parts: Vec<Vec<[f32; 3]>> = (0..chunks)
            .into_par_iter()
            .map_init(Scratch::default, |sc, c| {
                let r0 = c * batch;
                let r1 = (r0 + batch).min(self.rays);
                self.render_chunk(cfg, layout, params, time, r0..r1, sc)
            })
            .collect();
        parts.into_iter().flatten().collect()
    }

    fn render_chunk(
        &self,
        cfg: &ModelConfig,
        layout: &ModelLayout,
        params: &[f32],
        time: f32,
        rays: std::ops::Range<usize>,
        sc: &mut Scratch,
    ) -> Vec<[f32; 3]> {
        let field = &layout.field;
        let enc = &field.encoding;
        let h3_dim = if enc.h3.is_some() { enc.out_dim } else { 0 };
        let s = self.samples;
        let d0 = self.dyn_start[rays.start] as usize;
        let d1 = self.dyn_start[rays.end] as usize;
        let nd = d1 - d0;
        // Density of the dynamic samples: the field's dynamic part at `time` from their kept
        // static terms.
        if nd > 0 {
            sc.pts.clear();
            for j in d0..d1 {
                sc.pts.extend_from_slice(&self.dyn_pts[j * 3..j * 3 + 3]);
                sc.pts.push(time);
            }
            field.forward_density_prescaled(
                params,
                &sc.pts,
                nd,
                &self.dyn_h3[d0 * h3_dim..d1 * h3_dim],
                &self.dyn_b[d0..d1],
                &mut sc.field,
            );
        }
        // Per ray: densities, weights, and which dynamic samples light can still reach.
        let tau_hidden = (1.0 / HIDDEN_TRANSMITTANCE).ln();
        let nr = rays.len();
        sc.sigma.clear();
        sc.sigma
            .extend_from_slice(&self.sigma[rays.start * s..rays.end * s]);
        sc.dyn_ray.clear();
        sc.active.clear();
        for (li, ri) in rays.clone().enumerate() {
            let (a, b) = (self.dyn_start[ri] as usize, self.dyn_start[ri + 1] as usize);
            for j in a..b {
                let slot = self.dyn_slot[j] as usize;
                sc.sigma[li * s + slot] = sc.field.sigma[j - d0];
                sc.dyn_ray.push(ri as u32);
            }
            // Walk the ray; a dynamic sample gets a colour when the optical depth before it is
            // below the hidden threshold.
            let mut tau = 0f32;
            let mut next = a;
            for k in 0..s {
                if tau > tau_hidden {
                    break;
                }
                if next < b && self.dyn_slot[next] as usize == k {
                    sc.active.push((next - d0) as u32);
                    next += 1;
                }
                tau += render::tau_of(sc.sigma[li * s + k], self.deltas[ri * s + k]);
            }
        }
        // Colour of the visible dynamic samples.
        if !sc.active.is_empty() {
            let dyn_ray = &sc.dyn_ray;
            field.forward_color(
                params,
                &self.sh,
                &|j| dyn_ray[j] as usize,
                Some(&sc.active),
                nd,
                &mut sc.field,
            );
        }
        sc.rgb.clear();
        sc.rgb
            .extend_from_slice(&self.rgb[rays.start * s * 3..rays.end * s * 3]);
        for &j in &sc.active {
            let j = j as usize;
            let li = sc.dyn_ray[j] as usize - rays.start;
            let slot = self.dyn_slot[d0 + j] as usize;
            sc.rgb[(li * s + slot) * 3..(li * s + slot) * 3 + 3]
                .copy_from_slice(&sc.field.rgb[j * 3..j * 3 + 3]);
        }
        sc.w.resize(s, 0.0);
        let mut out = Vec::with_capacity(nr);
        for li in 0..nr {
            let ri = rays.start + li;
            let t_final = render::weights(
                &sc.sigma[li * s..(li + 1) * s],
                &self.deltas[ri * s..(ri + 1) * s],
                &mut sc.w,
            );
            out.push(composite_ray(
                cfg.background,
                &sc.w,
                &sc.rgb[li * s * 3..(li + 1) * s * 3],
                t_final,
            ));
        }
        out
    }
}

/// Plain reference of a frame over the fixed partition: every sample through the per-point
/// reference field at `time` (no cutoff, no cache, colour everywhere), composited.
pub fn reference_render(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    part: &Partition,
    time: f32,
) -> Vec<[f32; 3]> {
    let time = if time >= 0.0 { time.min(1.0) } else { 0.0 };
    let s = part.samples;
    rays.iter()
        .enumerate()
        .map(|(i, r)| {
            let mut sh = Vec::new();
            direction_encodings(std::slice::from_ref(r), &mut sh);
            let mut sigma = vec![0f32; s];
            let mut rgb = vec![0f32; s * 3];
            for k in 0..s {
                let j = i * s + k;
                let p = [
                    part.points[j * 4],
                    part.points[j * 4 + 1],
                    part.points[j * 4 + 2],
                    time,
                ];
                let (sg, c, _) = layout.field.eval_point_reference(params, &p, &sh);
                sigma[k] = sg;
                rgb[k * 3..k * 3 + 3].copy_from_slice(&c);
            }
            let mut w = vec![0f32; s];
            let t_final = render::weights(&sigma, &part.deltas[i * s..(i + 1) * s], &mut w);
            composite_ray(cfg.background, &w, &rgb, t_final)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::config::{Background, BlendMode, Preset};
    use msth_core::rng::Rng;
    use msth_core::{Camera, SceneBounds};

    /// A small model whose grids hold values of order 1 (so that time and the mask matter) and
    /// whose mask is `logit(x)` at mask vertex `x` (unit coordinates).
    fn model(blend: BlendMode, logit: impl Fn([f32; 3]) -> f32) -> (ModelConfig, Vec<f32>) {
        let mut cfg = ModelConfig::preset(
            Preset::Fast,
            SceneBounds::dnerf_default(),
            Background::Color {
                rgb: [1.0, 0.5, 0.25],
            },
            10,
        );
        cfg.field.encoding.resize(4, 10, 64.0, 8);
        cfg.proposal.encoding.resize(3, 10, 32.0, 8);
        cfg.field.encoding.blend = blend;
        cfg.sampler.set_samples(16, 8);
        let layout = ModelLayout::new(&cfg);
        let mut params = layout.init_params(7);
        let mut rng = Rng::new(3);
        for name in ["field.h3", "field.h4", "proposal.h3", "proposal.h4"] {
            if let Some(e) = layout.params.get(name) {
                for v in &mut params[e.range()] {
                    *v = rng.range_f32(-1.0, 1.0);
                }
            }
        }
        if let Some((d, r)) = layout.field.encoding.mask.clone() {
            let res = d.res;
            for (k, v) in params[r].iter_mut().enumerate() {
                let (x, y, z) = (k % res, (k / res) % res, k / (res * res));
                let u = |c: usize| c as f32 / (res - 1) as f32;
                *v = logit([u(x), u(y), u(z)]);
            }
        }
        (cfg, params)
    }

    fn rays() -> Vec<TimedRay> {
        let cam = Camera::look_at(12, 10, 0.9, Vec3::new(0.3, -3.0, 1.0), Vec3::ZERO, Vec3::Z);
        (0..cam.height)
            .flat_map(|y| (0..cam.width).map(move |x| (x, y)))
            .map(|(x, y)| {
                let r = cam.pixel_ray(x, y);
                TimedRay {
                    origin: r.origin,
                    dir: r.dir,
                    time: 0.0,
                }
            })
            .collect()
    }

    fn max_diff(a: &[[f32; 3]], b: &[[f32; 3]]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .flat_map(|(x, y)| (0..3).map(move |c| (x[c] - y[c]).abs()))
            .fold(0.0, f32::max)
    }

    fn partition(
        cfg: &ModelConfig,
        layout: &ModelLayout,
        params: &[f32],
        r: &[TimedRay],
    ) -> Partition {
        let mut ws = Workspace::default();
        playback_partition(cfg, layout, params, r, &TIMES, SAMPLES, None, &mut ws)
    }

    const TIMES: [f32; 3] = [0.0, 0.5, 1.0];
    const SAMPLES: usize = 12;

    #[test]
    fn frames_match_the_plain_reference_for_every_blend() {
        for blend in [
            BlendMode::Mt,
            BlendMode::Mst,
            BlendMode::Add,
            BlendMode::FourD,
        ] {
            let (cfg, params) = model(blend, |x| 6.0 * (x[0] - 0.5));
            let layout = ModelLayout::new(&cfg);
            let r = rays();
            // Cutoff 0: every sample is evaluated at every frame, so the fast path must equal
            // the reference up to the colours of hidden samples (weight below 1e-4; in practice the two agree to 1e-7).
            let cache = SampleCache::build(&cfg, &layout, &params, &r, &TIMES, SAMPLES, 0.0);
            assert_eq!(cache.rays(), r.len());
            assert_eq!(cache.dynamic_samples(), r.len() * SAMPLES, "{blend:?}");
            let part = partition(&cfg, &layout, &params, &r);
            for t in [0.0, 0.37, 1.0] {
                let fast = cache.render(&cfg, &layout, &params, t);
                let reference = reference_render(&cfg, &layout, &params, &r, &part, t);
                let d = max_diff(&fast, &reference);
                assert!(d < 1e-4, "{blend:?} t = {t}: {d}");
            }
            // Time matters in this model: a wrong time would be caught.
            let a = cache.render(&cfg, &layout, &params, 0.0);
            let b = reference_render(&cfg, &layout, &params, &r, &part, 1.0);
            let dt = max_diff(&a, &b);
            assert!(dt > 2e-3, "{blend:?}: frames do not depend on time");
        }
    }

    #[test]
    fn static_samples_are_evaluated_once_and_exactly() {
        // Static (m = 1 to f32 precision) where x > 0.5, dynamic elsewhere.
        let (cfg, params) = model(BlendMode::Mt, |x| if x[0] > 0.5 { 40.0 } else { -40.0 });
        let layout = ModelLayout::new(&cfg);
        let r = rays();
        // A tiny cutoff: the samples left static skip a 4D term below 1e-6 of its size.
        let cutoff = 1e-6;
        let cache = SampleCache::build(&cfg, &layout, &params, &r, &TIMES, SAMPLES, cutoff);
        let total = r.len() * SAMPLES;
        let dynamic = cache.dynamic_samples();
        assert!(
            dynamic > total / 10 && dynamic < total * 9 / 10,
            "{dynamic} of {total}"
        );
        let part = partition(&cfg, &layout, &params, &r);
        for t in [0.0, 0.61, 1.0] {
            let fast = cache.render(&cfg, &layout, &params, t);
            let reference = reference_render(&cfg, &layout, &params, &r, &part, t);
            let d = max_diff(&fast, &reference);
            assert!(d < 1e-4, "t = {t}: {d}");
        }
    }

    #[test]
    fn an_all_static_mask_leaves_nothing_to_evaluate() {
        let (cfg, params) = model(BlendMode::Mt, |_| 40.0);
        let layout = ModelLayout::new(&cfg);
        let r = rays();
        let cache = SampleCache::build(&cfg, &layout, &params, &r, &TIMES, SAMPLES, 1e-3);
        assert_eq!(cache.dynamic_samples(), 0);
        let a = cache.render(&cfg, &layout, &params, 0.0);
        let b = cache.render(&cfg, &layout, &params, 1.0);
        assert_eq!(a, b);
        let part = partition(&cfg, &layout, &params, &r);
        let reference = reference_render(&cfg, &layout, &params, &r, &part, 0.3);
        assert!(max_diff(&a, &reference) < 1e-4);
        assert!(cache.bytes() <= cache_bytes_bound(&layout, r.len(), SAMPLES));
    }

    #[test]
    fn times_outside_the_clip_and_empty_caches_are_safe() {
        let (cfg, params) = model(BlendMode::Mt, |x| 6.0 * (x[2] - 0.5));
        let layout = ModelLayout::new(&cfg);
        let r = rays();
        let cache = SampleCache::build(&cfg, &layout, &params, &r, &TIMES, SAMPLES, 0.01);
        let at = |t: f32| cache.render(&cfg, &layout, &params, t);
        assert_eq!(at(-3.0), at(0.0));
        assert_eq!(at(7.0), at(1.0));
        assert!(at(f32::NAN).iter().flatten().all(|v| v.is_finite()));
        let empty = SampleCache::build(&cfg, &layout, &params, &[], &TIMES, SAMPLES, 0.01);
        assert!(empty.render(&cfg, &layout, &params, 0.5).is_empty());
    }
}
