//! The per-chunk pipeline shared by training and rendering: place proposal samples, evaluate the
//! proposal field, resample from its weights, evaluate the main field, composite; and for
//! training, the losses and the backward pass through both fields.
//!
//! A chunk is a few hundred rays processed by one thread with its own [`Workspace`]; the caller
//! splits batches into chunks and sums gradients in a fixed order, so results are repeatable for
//! a seed and a thread count.

use glam::Vec3;

use crate::config::{Background, ModelConfig};
use crate::field::{FieldScratch, ModelLayout};
use crate::losses;
use crate::render;
use crate::rng::Rng;
use crate::sampling::{sample_pdf, uniform_edges};
use crate::scene::SceneBounds;
use crate::sh::{sh4, SH_COEFFS};
use crate::Ray;

/// One ray at one time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedRay {
    pub origin: Vec3,
    pub dir: Vec3,
    pub time: f32,
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
}

/// Loss sums of one chunk (divide by the batch's ray count for means).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ChunkLosses {
    /// Sum over rays of the mean over channels of the squared error.
    pub sq_err: f64,
    pub interlevel: f64,
    pub distortion: f64,
    pub rays: usize,
    pub field_samples: usize,
    pub proposal_samples: usize,
}

impl std::ops::AddAssign for ChunkLosses {
    fn add_assign(&mut self, o: Self) {
        self.sq_err += o.sq_err;
        self.interlevel += o.interlevel;
        self.distortion += o.distortion;
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
/// ([`crate::field::EncodingScratch::static_cutoff`]).
pub const RENDER_STATIC_CUTOFF: f32 = 1e-3;

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
}

/// Samples whose transmittance has fallen below this get no colour evaluation: their weight,
/// and every gradient through them, is below it.
pub const HIDDEN_TRANSMITTANCE: f32 = 1e-4;

/// Distance unit of the spacing function (the contraction radius for unbounded scenes).
pub fn spacing_unit(bounds: &SceneBounds) -> f32 {
    match *bounds {
        SceneBounds::Contracted { radius, .. } => radius,
        SceneBounds::Box { .. } => 1.0,
    }
}

/// Per-ray `[near, far]` the samplers use; rays that miss the box, or are not finite, get an
/// empty interval (`near == far`).
pub fn ray_limits(cfg: &ModelConfig, r: &TimedRay) -> (f32, f32) {
    let ray = Ray {
        origin: r.origin,
        dir: r.dir,
    };
    let finite = r.origin.is_finite() && r.dir.is_finite() && r.dir.length_squared() > 0.0;
    if !finite {
        return (0.0, 0.0);
    }
    match cfg
        .bounds
        .ray_interval(&ray, cfg.sampler.near, cfg.sampler.far)
    {
        Some(i) => (i.near, i.far),
        None => (0.0, 0.0),
    }
}

/// Places samples at the midpoints (in distance) of the intervals given by normalised `edges`.
#[allow(clippy::too_many_arguments)]
fn place_samples(
    cfg: &ModelConfig,
    r: &TimedRay,
    (near, far): (f32, f32),
    edges: &[f32],
    t_out: &mut [f32],
    pts: &mut [f32],
    deltas: &mut [f32],
) {
    let unit = spacing_unit(&cfg.bounds);
    let spacing = cfg.sampler.spacing;
    for (k, &s) in edges.iter().enumerate() {
        t_out[k] = if far > near {
            spacing.t_of_s(s, near, far, unit)
        } else {
            near
        };
    }
    let time = if r.time >= 0.0 { r.time.min(1.0) } else { 0.0 };
    for k in 0..edges.len() - 1 {
        let (t0, t1) = (t_out[k], t_out[k + 1]);
        deltas[k] = (t1 - t0).max(0.0);
        let p = r.origin + r.dir * (0.5 * (t0 + t1));
        let u = cfg.bounds.to_unit(p);
        pts[k * 4..k * 4 + 4].copy_from_slice(&[u.x, u.y, u.z, time]);
    }
}

/// Forward of proposal and main fields for a chunk; leaves everything in `ws`.
fn forward_chunk(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    anneal: f32,
    mut rng: Option<&mut Rng>,
    ws: &mut Workspace,
) {
    let n = rays.len();
    let np = cfg.sampler.num_proposal_samples;
    let nf = cfg.sampler.num_samples;
    ws.near_far.clear();
    ws.near_far.extend(rays.iter().map(|r| ray_limits(cfg, r)));
    ws.sh.resize(n * SH_COEFFS, 0.0);
    for (i, r) in rays.iter().enumerate() {
        let d = if r.dir.is_finite() {
            r.dir.normalize_or_zero()
        } else {
            Vec3::ZERO
        };
        sh4(
            [d.x, d.y, d.z],
            &mut ws.sh[i * SH_COEFFS..(i + 1) * SH_COEFFS],
        );
    }
    // Proposal samples.
    ws.s_prop.resize(n * (np + 1), 0.0);
    ws.t_prop.resize(n * (np + 1), 0.0);
    ws.pts_prop.resize(n * np * 4, 0.0);
    ws.delta_prop.resize(n * np, 0.0);
    for i in 0..n {
        let e = &mut ws.s_prop[i * (np + 1)..(i + 1) * (np + 1)];
        uniform_edges(np, rng.as_deref_mut(), e);
        place_samples(
            cfg,
            &rays[i],
            ws.near_far[i],
            &ws.s_prop[i * (np + 1)..(i + 1) * (np + 1)],
            &mut ws.t_prop[i * (np + 1)..(i + 1) * (np + 1)],
            &mut ws.pts_prop[i * np * 4..(i + 1) * np * 4],
            &mut ws.delta_prop[i * np..(i + 1) * np],
        );
    }
    layout
        .proposal
        .field
        .forward_density(params, &ws.pts_prop, n * np, &mut ws.prop);
    ws.w_prop.resize(n * np, 0.0);
    ws.tfinal_prop.resize(n, 0.0);
    for i in 0..n {
        ws.tfinal_prop[i] = render::weights(
            &ws.prop.sigma[i * np..(i + 1) * np],
            &ws.delta_prop[i * np..(i + 1) * np],
            &mut ws.w_prop[i * np..(i + 1) * np],
        );
    }
    // Resample.
    ws.s_main.resize(n * (nf + 1), 0.0);
    ws.t_main.resize(n * (nf + 1), 0.0);
    ws.pts_main.resize(n * nf * 4, 0.0);
    ws.delta_main.resize(n * nf, 0.0);
    ws.annealed.resize(np, 0.0);
    for i in 0..n {
        for k in 0..np {
            let w = ws.w_prop[i * np + k];
            ws.annealed[k] = if anneal == 1.0 {
                w
            } else {
                w.max(0.0).powf(anneal)
            };
        }
        sample_pdf(
            &ws.s_prop[i * (np + 1)..(i + 1) * (np + 1)],
            &ws.annealed,
            cfg.sampler.histogram_padding,
            rng.as_deref_mut(),
            &mut ws.s_main[i * (nf + 1)..(i + 1) * (nf + 1)],
        );
        place_samples(
            cfg,
            &rays[i],
            ws.near_far[i],
            &ws.s_main[i * (nf + 1)..(i + 1) * (nf + 1)],
            &mut ws.t_main[i * (nf + 1)..(i + 1) * (nf + 1)],
            &mut ws.pts_main[i * nf * 4..(i + 1) * nf * 4],
            &mut ws.delta_main[i * nf..(i + 1) * nf],
        );
    }
    layout
        .field
        .forward_density(params, &ws.pts_main, n * nf, &mut ws.main);
    // Colour only where light can still arrive: a sample behind optical depth
    // `ln(1 / HIDDEN_TRANSMITTANCE)` has weight and gradient below that transmittance.
    let tau_hidden = (1.0 / HIDDEN_TRANSMITTANCE).ln();
    ws.active.clear();
    for i in 0..n {
        let mut tau = 0f32;
        for k in 0..nf {
            let idx = i * nf + k;
            if tau > tau_hidden {
                break;
            }
            ws.active.push(idx as u32);
            tau += render::tau_of(ws.main.sigma[idx], ws.delta_main[idx]);
        }
    }
    layout.field.forward_color(
        params,
        &ws.sh,
        &|j| j / nf,
        Some(&ws.active),
        n * nf,
        &mut ws.main,
    );
    ws.w_main.resize(n * nf, 0.0);
}

fn composite_ray(bg: Background, w: &[f32], rgb: &[f32], t_final: f32) -> [f32; 3] {
    let n = w.len();
    let bg_rgb = match bg {
        Background::Color { rgb } => rgb,
        Background::LastSample => {
            if n > 0 {
                [rgb[(n - 1) * 3], rgb[(n - 1) * 3 + 1], rgb[(n - 1) * 3 + 2]]
            } else {
                [0.0; 3]
            }
        }
    };
    render::composite(w, rgb, t_final, bg_rgb)
}

/// One training chunk: forward, losses and backward; gradients are added into `grad`.
/// `backgrounds`, when given, replaces the configured background per ray (training on random
/// backgrounds for images with transparency).
#[allow(clippy::too_many_arguments)]
pub fn train_chunk(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    grad: &mut [f32],
    rays: &[TimedRay],
    targets: &[[f32; 3]],
    backgrounds: Option<&[[f32; 3]]>,
    step: &StepSettings,
    rng: &mut Rng,
    ws: &mut Workspace,
) -> ChunkLosses {
    let n = rays.len();
    let np = cfg.sampler.num_proposal_samples;
    let nf = cfg.sampler.num_samples;
    // Training evaluates every point exactly (the gradients need every h4).
    ws.prop.enc.static_cutoff = 0.0;
    ws.main.enc.static_cutoff = 0.0;
    forward_chunk(cfg, layout, params, rays, step.anneal, Some(rng), ws);
    let mut out = ChunkLosses {
        rays: n,
        field_samples: n * nf,
        proposal_samples: n * np,
        ..Default::default()
    };
    ws.d_sigma_main.resize(n * nf, 0.0);
    ws.d_rgb_main.resize(n * nf * 3, 0.0);
    ws.d_sigma_prop.resize(n * np, 0.0);
    ws.d_w_prop.resize(n * np, 0.0);
    ws.d_w.resize(nf, 0.0);
    let scale = step.loss_scale;
    for i in 0..n {
        let fs = i * nf..(i + 1) * nf;
        let sigma = &ws.main.sigma[fs.clone()];
        let delta = &ws.delta_main[fs.clone()];
        let rgb = &ws.main.rgb[i * nf * 3..(i + 1) * nf * 3];
        let w = &mut ws.w_main[fs.clone()];
        let t_final = render::weights(sigma, delta, w);
        let background = match backgrounds {
            Some(b) => Background::Color { rgb: b[i] },
            None => cfg.background,
        };
        let c = composite_ray(background, w, rgb, t_final);
        // d(mean sq err)/dC
        let mut dc = [0f32; 3];
        let mut se = 0f32;
        for ch in 0..3 {
            let diff = c[ch] - targets[i][ch];
            se += diff * diff;
            dc[ch] = 2.0 * diff / 3.0 * scale;
        }
        out.sq_err += (se / 3.0) as f64;
        // dL/dw from the colour, and the background's dependence on T_N.
        for k in 0..nf {
            ws.d_w[k] = dc[0] * rgb[k * 3] + dc[1] * rgb[k * 3 + 1] + dc[2] * rgb[k * 3 + 2];
        }
        let d_rgb = &mut ws.d_rgb_main[i * nf * 3..(i + 1) * nf * 3];
        for k in 0..nf {
            for ch in 0..3 {
                d_rgb[k * 3 + ch] = dc[ch] * w[k];
            }
        }
        let d_t = match background {
            Background::Color { rgb: b } => dc[0] * b[0] + dc[1] * b[1] + dc[2] * b[2],
            Background::LastSample => {
                if nf > 0 {
                    for ch in 0..3 {
                        d_rgb[(nf - 1) * 3 + ch] += dc[ch] * t_final;
                    }
                    dc[0] * rgb[(nf - 1) * 3]
                        + dc[1] * rgb[(nf - 1) * 3 + 1]
                        + dc[2] * rgb[(nf - 1) * 3 + 2]
                } else {
                    0.0
                }
            }
        };
        let s_main = &ws.s_main[i * (nf + 1)..(i + 1) * (nf + 1)];
        if step.distortion_weight > 0.0 {
            out.distortion +=
                losses::distortion(s_main, w, step.distortion_weight * scale, &mut ws.d_w) as f64;
        }
        render::weights_backward(
            sigma,
            delta,
            w,
            t_final,
            &ws.d_w,
            d_t,
            &mut ws.d_sigma_main[fs],
        );
        // Interlevel: main weights held constant, gradient to the proposal weights.
        let ps = i * np..(i + 1) * np;
        let d_wp = &mut ws.d_w_prop[ps.clone()];
        d_wp.fill(0.0);
        out.interlevel += losses::interlevel(
            s_main,
            w,
            &ws.s_prop[i * (np + 1)..(i + 1) * (np + 1)],
            &ws.w_prop[ps.clone()],
            step.interlevel_weight * scale,
            d_wp,
        ) as f64;
        render::weights_backward(
            &ws.prop.sigma[ps.clone()],
            &ws.delta_prop[ps.clone()],
            &ws.w_prop[ps.clone()],
            ws.tfinal_prop[i],
            d_wp,
            0.0,
            &mut ws.d_sigma_prop[ps],
        );
    }
    layout.field.backward(
        params,
        &ws.pts_main,
        n * nf,
        &mut ws.main,
        &ws.d_sigma_main,
        &ws.d_rgb_main,
        grad,
    );
    layout.proposal.field.backward_density(
        params,
        &ws.pts_prop,
        n * np,
        &mut ws.prop,
        &ws.d_sigma_prop,
        grad,
    );
    out
}

/// Renders a chunk of rays for inference (deterministic sampling, no annealing).
pub fn render_chunk(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    ws: &mut Workspace,
    out: &mut RenderOutput,
) {
    let n = rays.len();
    let nf = cfg.sampler.num_samples;
    ws.prop.enc.static_cutoff = RENDER_STATIC_CUTOFF;
    ws.main.enc.static_cutoff = RENDER_STATIC_CUTOFF;
    forward_chunk(cfg, layout, params, rays, 1.0, None, ws);
    let enc = &layout.field.encoding;
    for i in 0..n {
        let fs = i * nf..(i + 1) * nf;
        let w = &mut ws.w_main[fs.clone()];
        let rgb = &ws.main.rgb[i * nf * 3..(i + 1) * nf * 3];
        let t_final = render::weights(&ws.main.sigma[fs.clone()], &ws.delta_main[fs.clone()], w);
        out.rgb.push(composite_ray(cfg.background, w, rgb, t_final));
        let mut depth = 0f32;
        let mut mask = 0f32;
        let mut min_mask = 1f32;
        let edges = &ws.t_main[i * (nf + 1)..(i + 1) * (nf + 1)];
        let mut visible = None;
        let mut acc = 0f32;
        for k in 0..nf {
            let t_mid = 0.5 * (edges[k] + edges[k + 1]);
            acc += w[k];
            if visible.is_none() && 1.0 - acc < VISIBLE_TRANSMITTANCE {
                visible = Some(edges[k + 1]);
            }
            depth += w[k] * t_mid;
            let m = if enc.mask.is_some() {
                ws.main.enc.m[i * nf + k]
            } else {
                enc.mask_at(params, &[0.0; 3])
            };
            mask += w[k] * m;
            if w[k] > 1e-4 {
                min_mask = min_mask.min(m);
            }
        }
        out.depth.push(depth);
        out.opacity.push(1.0 - t_final);
        out.mask.push(mask);
        out.min_mask.push(min_mask);
        out.visible_depth.push(visible.unwrap_or(edges[nf]));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{BlendMode, Preset};

    fn tiny_cfg() -> ModelConfig {
        let mut c = ModelConfig::preset(
            Preset::Fast,
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
            5,
        );
        for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
            enc.blend = BlendMode::Mst;
            enc.resize(2, 6, 8.0, 4);
            enc.grid4.finest_resolution[3] = 4.0;
            enc.grid3.base_resolution = vec![4.0; 3];
            enc.grid4.base_resolution = vec![4.0, 4.0, 4.0, 2.0];
        }
        c.field.density_hidden = 8;
        c.field.color_hidden = 8;
        c.field.geo_features = 3;
        c.proposal.hidden = 4;
        c.sampler.num_proposal_samples = 12;
        c.sampler.num_samples = 6;
        c
    }

    fn rays() -> (Vec<TimedRay>, Vec<[f32; 3]>) {
        let mut rng = Rng::new(8);
        let mut rays = Vec::new();
        let mut tg = Vec::new();
        for _ in 0..4 {
            let o = Vec3::new(rng.range_f32(-0.5, 0.5), rng.range_f32(-0.5, 0.5), 3.0);
            let d = Vec3::new(rng.range_f32(-0.2, 0.2), rng.range_f32(-0.2, 0.2), -1.0).normalize();
            rays.push(TimedRay {
                origin: o,
                dir: d,
                time: rng.f32(),
            });
            tg.push([rng.f32(), rng.f32(), rng.f32()]);
        }
        (rays, tg)
    }

    /// The full training loss (colour + distortion + interlevel with weights) differentiated by
    /// finite differences, with fixed sample positions (same rng stream for every evaluation).
    /// Only parameters whose gradient does not move sample positions are exact: the main field's
    /// parameters (the proposal's gradient comes from the interlevel loss alone, checked in
    /// `losses`, and the resampling itself is not differentiated, as in mip-NeRF 360).
    #[test]
    fn train_chunk_gradient_matches_finite_differences_for_main_field() {
        let cfg = tiny_cfg();
        cfg.validate().unwrap();
        let layout = ModelLayout::new(&cfg);
        let mut p = layout.init_params(1);
        let mut r = Rng::new(2);
        for v in p.iter_mut() {
            *v += r.range_f32(-0.3, 0.3);
        }
        let (rays, tg) = rays();
        let step = StepSettings {
            anneal: 1.0,
            interlevel_weight: 1.0,
            distortion_weight: 0.01,
            loss_scale: 1.0 / rays.len() as f32,
        };
        let total = |p: &[f32]| -> f64 {
            let mut ws = Workspace::default();
            let mut g = vec![0f32; p.len()];
            let l = train_chunk(
                &cfg,
                &layout,
                p,
                &mut g,
                &rays,
                &tg,
                None,
                &step,
                &mut Rng::new(5),
                &mut ws,
            );
            // only the terms that depend on the main field
            (l.sq_err + step.distortion_weight as f64 * l.distortion) / rays.len() as f64
        };
        let mut ws = Workspace::default();
        let mut grad = vec![0f32; p.len()];
        train_chunk(
            &cfg,
            &layout,
            &p,
            &mut grad,
            &rays,
            &tg,
            None,
            &step,
            &mut Rng::new(5),
            &mut ws,
        );
        let mut checked = 0;
        for e in layout
            .params
            .entries
            .iter()
            .filter(|e| e.name.starts_with("field"))
        {
            let mut idx: Vec<usize> = e.range().collect();
            idx.sort_by(|&a, &b| grad[b].abs().partial_cmp(&grad[a].abs()).unwrap());
            for &i in idx.iter().take(6) {
                let h = 2e-3;
                let mut q = p.clone();
                q[i] += h;
                let lp = total(&q);
                q[i] -= 2.0 * h;
                let lm = total(&q);
                let fd = (lp - lm) / (2.0 * h as f64);
                let tol = 1e-4 + 5e-2 * fd.abs();
                assert!(
                    (fd - grad[i] as f64).abs() < tol,
                    "{} [{}]: fd {fd} vs {}",
                    e.name,
                    i - e.offset,
                    grad[i]
                );
                checked += 1;
            }
        }
        assert!(checked >= 20);
    }

    #[test]
    fn render_is_deterministic_and_finite() {
        let cfg = tiny_cfg();
        let layout = ModelLayout::new(&cfg);
        let p = layout.init_params(3);
        let (rays, _) = rays();
        let mut a = RenderOutput::default();
        let mut b = RenderOutput::default();
        render_chunk(&cfg, &layout, &p, &rays, &mut Workspace::default(), &mut a);
        render_chunk(&cfg, &layout, &p, &rays, &mut Workspace::default(), &mut b);
        assert_eq!(a.rgb, b.rgb);
        assert!(a.rgb.iter().flatten().all(|v| v.is_finite()));
        // A ray that misses the box renders the background.
        let miss = [TimedRay {
            origin: Vec3::new(5.0, 5.0, 5.0),
            dir: Vec3::Z,
            time: 0.5,
        }];
        let mut m = RenderOutput::default();
        render_chunk(&cfg, &layout, &p, &miss, &mut Workspace::default(), &mut m);
        assert_eq!(m.rgb[0], [1.0, 1.0, 1.0]);
    }
}
