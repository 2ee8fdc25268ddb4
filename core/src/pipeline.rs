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
}

/// Loss sums of one chunk (divide by the batch's ray count for means).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ChunkLosses {
    /// Sum over rays of the mean over channels of the squared error.
    pub sq_err: f64,
    pub interlevel: f64,
    pub distortion: f64,
    /// Sum over rays of the per-sample mask loss, its weight included.
    pub sample_mask: f64,
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

/// Direction encodings (`SH_COEFFS` per ray) of `rays` into `out`; a direction that is not
/// finite encodes as zero.
pub fn direction_encodings(rays: &[TimedRay], out: &mut Vec<f32>) {
    out.resize(rays.len() * SH_COEFFS, 0.0);
    for (r, sh) in rays.iter().zip(out.chunks_exact_mut(SH_COEFFS)) {
        let d = if r.dir.is_finite() {
            r.dir.normalize_or_zero()
        } else {
            Vec3::ZERO
        };
        sh4([d.x, d.y, d.z], sh);
    }
}

/// Ray limits and the proposal samples of `rays` (uniform edges, jittered with `rng`) into `ws`.
fn place_proposal_samples(
    cfg: &ModelConfig,
    rays: &[TimedRay],
    mut rng: Option<&mut Rng>,
    ws: &mut Workspace,
) {
    let n = rays.len();
    let np = cfg.sampler.num_proposal_samples;
    ws.near_far.clear();
    ws.near_far.extend(rays.iter().map(|r| ray_limits(cfg, r)));
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
    direction_encodings(rays, &mut ws.sh);
    place_proposal_samples(cfg, rays, rng.as_deref_mut(), ws);
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

/// Composites one ray: `C = sum w_i c_i + T_N * bg`, the background being the configured colour
/// or the last sample's colour.
pub fn composite_ray(bg: Background, w: &[f32], rgb: &[f32], t_final: f32) -> [f32; 3] {
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
    train_chunk_with(
        cfg,
        layout,
        params,
        grad,
        rays,
        targets,
        backgrounds,
        step,
        rng,
        ws,
        None,
    )
}

/// The training-only parameters of uncertainty-guided mask learning for one chunk
/// ([`crate::uncertainty`]): settings, layout, values and the gradient buffer they add into.
pub struct AuxStep<'a> {
    pub cfg: &'a MaskLearningConfig,
    pub layout: &'a AuxLayout,
    pub params: &'a [f32],
    pub grad: &'a mut [f32],
}

/// The uncertainty-guided terms of one chunk, computed before the per-ray loop.
struct AuxForward {
    lambda: f32,
    mine: bool,
}

/// Adds the background's share of `dL/dC` into `d_rgb` (last-sample background) and returns
/// `dL/dT_N`.
fn background_backward(
    background: Background,
    dc: [f32; 3],
    rgb: &[f32],
    t_final: f32,
    d_rgb: &mut [f32],
) -> f32 {
    let nf = rgb.len() / 3;
    match background {
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
    }
}

/// [`train_chunk`] with, when `aux` is given, the uncertainty loss `lambda * L_u` (static branch,
/// uncertainty grid) and the mutual-information term `-gamma * I(m, u)` (per-ray pairs of the
/// weight-averaged mask `sum w_i m_i` and the ray uncertainty `U`, marginals by shuffling `U`
/// within the chunk). Without `aux`, or with every term off, it is exactly [`train_chunk`].
#[allow(clippy::too_many_arguments)]
pub fn train_chunk_with(
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
    mut aux: Option<AuxStep<'_>>,
) -> ChunkLosses {
    let n = rays.len();
    let np = cfg.sampler.num_proposal_samples;
    let nf = cfg.sampler.num_samples;
    // Training evaluates every point exactly (the gradients need every h4).
    ws.prop.enc.static_cutoff = 0.0;
    ws.main.enc.static_cutoff = 0.0;
    ws.main.enc.d_m_extra.clear();
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
    let static_field = match &aux {
        Some(a) if a.cfg.uncertainty => layout.field.static_branch(),
        _ => None,
    };
    let ray_background = |i: usize| match backgrounds {
        Some(b) => Background::Color { rgb: b[i] },
        None => cfg.background,
    };
    let aux_fw = match (&mut aux, &static_field) {
        (Some(a), Some(sf)) => {
            // Static branch, per-sample uncertainty, and the per-ray (m, U) pairs.
            sf.forward_density(params, &ws.pts_main, n * nf, &mut ws.stat);
            sf.forward_color(params, &ws.sh, &|j| j / nf, None, n * nf, &mut ws.stat);
            ws.u_main.clear();
            for k in 0..n * nf {
                ws.u_main.push(
                    a.layout
                        .uncertainty_at(a.params, &ws.pts_main[k * 4..k * 4 + 3]),
                );
            }
            ws.w_stat.resize(n * nf, 0.0);
            ws.tfinal_stat.resize(n, 0.0);
            ws.d_sigma_stat.resize(n * nf, 0.0);
            ws.d_rgb_stat.clear();
            ws.d_rgb_stat.resize(n * nf * 3, 0.0);
            ws.d_u_main.clear();
            ws.d_u_main.resize(n * nf, 0.0);
            ws.d_u_ray.clear();
            ws.d_u_ray.resize(n, 0.0);
            ws.d_m_ray.clear();
            ws.d_m_ray.resize(n, 0.0);
            for i in 0..n {
                let fs = i * nf..(i + 1) * nf;
                ws.tfinal_stat[i] = render::weights(
                    &ws.stat.sigma[fs.clone()],
                    &ws.delta_main[fs.clone()],
                    &mut ws.w_stat[fs],
                );
            }
            let mine = a.cfg.mine && a.cfg.mine_weight > 0.0 && n > 1;
            if mine {
                ws.m_ray.clear();
                ws.u_ray.clear();
                for i in 0..n {
                    let fs = i * nf..(i + 1) * nf;
                    let w = &mut ws.w_main[fs.clone()];
                    render::weights(&ws.main.sigma[fs.clone()], &ws.delta_main[fs.clone()], w);
                    let m: f32 = (0..nf).map(|k| w[k] * ws.main.enc.m[i * nf + k]).sum();
                    ws.m_ray.push(m);
                    ws.u_ray.push(ray_uncertainty(w, &ws.u_main[fs]));
                }
                shuffle(n, rng, &mut ws.perm);
                let (mlp, r) = &a.layout.mine;
                let i_est = mine_estimate(
                    mlp,
                    &a.params[r.clone()],
                    &ws.m_ray,
                    &ws.u_ray,
                    &ws.perm,
                    -a.cfg.mine_weight * n as f32 * scale,
                    &mut a.grad[r.clone()],
                    &mut ws.d_m_ray,
                    &mut ws.d_u_ray,
                    &mut ws.mine,
                );
                out.mine += i_est as f64 * n as f64;
            }
            Some(AuxForward {
                lambda: a.cfg.uncertainty_weight,
                mine,
            })
        }
        _ => None,
    };
    let sample_mask = step.sample_mask_weight > 0.0 && layout.field.encoding.mask.is_some();
    if aux_fw.as_ref().is_some_and(|a| a.mine) || sample_mask {
        ws.main.enc.d_m_extra.resize(n * nf, 0.0);
    }
    for i in 0..n {
        let fs = i * nf..(i + 1) * nf;
        let sigma = &ws.main.sigma[fs.clone()];
        let delta = &ws.delta_main[fs.clone()];
        let rgb = &ws.main.rgb[i * nf * 3..(i + 1) * nf * 3];
        let w = &mut ws.w_main[fs.clone()];
        let t_final = render::weights(sigma, delta, w);
        let background = ray_background(i);
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
        // The uncertainty loss: its gradients into C, C_s and U.
        let mut d_u_ray = 0f32;
        if let Some(af) = &aux_fw {
            let stat_rgb = &ws.stat.rgb[i * nf * 3..(i + 1) * nf * 3];
            let w_s = &ws.w_stat[fs.clone()];
            let cs = composite_ray(background, w_s, stat_rgb, ws.tfinal_stat[i]);
            let u_ray = ray_uncertainty(w, &ws.u_main[fs.clone()]);
            let (lu, g) = uncertainty_loss(c, cs, u_ray, af.lambda * scale);
            out.uncertainty += lu as f64;
            for ch in 0..3 {
                dc[ch] += g.d_c[ch];
            }
            d_u_ray = g.d_u + ws.d_u_ray[i];
            // Static branch backward to its densities and colours.
            let d_rgb_s = &mut ws.d_rgb_stat[i * nf * 3..(i + 1) * nf * 3];
            for k in 0..nf {
                ws.d_w[k] = g.d_cs[0] * stat_rgb[k * 3]
                    + g.d_cs[1] * stat_rgb[k * 3 + 1]
                    + g.d_cs[2] * stat_rgb[k * 3 + 2];
                for ch in 0..3 {
                    d_rgb_s[k * 3 + ch] = g.d_cs[ch] * w_s[k];
                }
            }
            let d_t_s =
                background_backward(background, g.d_cs, stat_rgb, ws.tfinal_stat[i], d_rgb_s);
            render::weights_backward(
                &ws.stat.sigma[fs.clone()],
                delta,
                w_s,
                ws.tfinal_stat[i],
                &ws.d_w,
                d_t_s,
                &mut ws.d_sigma_stat[fs.clone()],
            );
        }
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
        let d_t = background_backward(background, dc, rgb, t_final, d_rgb);
        if let Some(af) = &aux_fw {
            // U = sum w u: into the weights and the per-sample uncertainties.
            ray_uncertainty_backward(
                w,
                &ws.u_main[fs.clone()],
                d_u_ray,
                &mut ws.d_w,
                &mut ws.d_u_main[fs.clone()],
            );
            if af.mine {
                // m(r) = sum w m: into the weights and the per-sample mask values.
                let d_m = ws.d_m_ray[i];
                for k in 0..nf {
                    ws.d_w[k] += d_m * ws.main.enc.m[i * nf + k];
                    ws.main.enc.d_m_extra[i * nf + k] = d_m * w[k];
                }
            }
        }
        if sample_mask {
            let lam = step.sample_mask_weight * scale;
            for k in 0..nf {
                let m = ws.main.enc.m[i * nf + k];
                out.sample_mask += (w[k] * (1.0 - m)) as f64 * step.sample_mask_weight as f64;
                ws.main.enc.d_m_extra[i * nf + k] -= lam * w[k];
            }
        }
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
    if let (Some(a), Some(sf)) = (aux.as_mut(), &static_field) {
        sf.backward(
            params,
            &ws.pts_main,
            n * nf,
            &mut ws.stat,
            &ws.d_sigma_stat,
            &ws.d_rgb_stat,
            grad,
        );
        for k in 0..n * nf {
            let d = ws.d_u_main[k];
            if d != 0.0 {
                a.layout
                    .uncertainty_backward(a.params, &ws.pts_main[k * 4..k * 4 + 3], d, a.grad);
            }
        }
    }
    out
}

/// Fixed sample positions for playback with sample-level reuse (see the player's
/// `samples` module): `samples` per ray, the same at every time.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Partition {
    /// Samples per ray.
    pub samples: usize,
    /// `[rays * samples * 4]`: each sample's unit-cube point, and time 0.
    pub points: Vec<f32>,
    /// `[rays * samples]`: interval lengths (world units).
    pub deltas: Vec<f32>,
}

/// Builds a [`Partition`] of `rays` that serves every time in `times`: the proposal field is
/// evaluated at its (deterministic, time-independent) samples at each of `times`, the weights of
/// each bin are combined by their maximum over the times, and `samples` intervals are drawn
/// from that histogram as rendering draws them from one time's. A surface that is anywhere
/// along the ray at one of `times` thus gets samples; a static one gets the same as in a frame.
pub fn playback_partition(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    times: &[f32],
    samples: usize,
    ws: &mut Workspace,
) -> Partition {
    let n = rays.len();
    let np = cfg.sampler.num_proposal_samples;
    let samples = samples.max(1);
    ws.prop.enc.static_cutoff = RENDER_STATIC_CUTOFF;
    place_proposal_samples(cfg, rays, None, ws);
    // Per-bin maximum of the proposal weights over the times.
    ws.annealed.clear();
    ws.annealed.resize(n * np, 0.0);
    ws.w_prop.resize(n * np, 0.0);
    for &t in times {
        let t = if t >= 0.0 { t.min(1.0) } else { 0.0 };
        for k in 0..n * np {
            ws.pts_prop[k * 4 + 3] = t;
        }
        layout
            .proposal
            .field
            .forward_density(params, &ws.pts_prop, n * np, &mut ws.prop);
        for i in 0..n {
            let r = i * np..(i + 1) * np;
            render::weights(
                &ws.prop.sigma[r.clone()],
                &ws.delta_prop[r.clone()],
                &mut ws.w_prop[r.clone()],
            );
            for k in r {
                ws.annealed[k] = ws.annealed[k].max(ws.w_prop[k]);
            }
        }
    }
    let mut out = Partition {
        samples,
        points: vec![0.0; n * samples * 4],
        deltas: vec![0.0; n * samples],
    };
    ws.s_main.resize(samples + 1, 0.0);
    ws.t_main.resize(samples + 1, 0.0);
    for i in 0..n {
        sample_pdf(
            &ws.s_prop[i * (np + 1)..(i + 1) * (np + 1)],
            &ws.annealed[i * np..(i + 1) * np],
            cfg.sampler.histogram_padding,
            None,
            &mut ws.s_main[..samples + 1],
        );
        let r0 = TimedRay {
            time: 0.0,
            ..rays[i]
        };
        place_samples(
            cfg,
            &r0,
            ws.near_far[i],
            &ws.s_main[..samples + 1],
            &mut ws.t_main[..samples + 1],
            &mut out.points[i * samples * 4..(i + 1) * samples * 4],
            &mut out.deltas[i * samples..(i + 1) * samples],
        );
    }
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
            sample_mask_weight: 0.0,
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

    /// Everything about mask learning the FD test needs: settings with visible weights, the
    /// auxiliary layout and perturbed auxiliary parameters.
    fn aux_setup(mine: bool) -> (MaskLearningConfig, AuxLayout, Vec<f32>) {
        let mc = MaskLearningConfig {
            uncertainty: true,
            uncertainty_weight: 0.5,
            uncertainty_resolution: 4,
            mine,
            mine_weight: 0.5,
            mine_hidden: 6,
            ..Default::default()
        };
        let al = AuxLayout::new(&mc);
        let mut ap = al.init_params(3);
        let mut r = Rng::new(9);
        for v in &mut ap[al.grid.1.clone()] {
            *v = r.range_f32(-1.0, 1.0);
        }
        (mc, al, ap)
    }

    /// Losses and gradients (model, auxiliary) of one chunk with mask learning.
    #[allow(clippy::type_complexity)]
    fn aux_chunk(
        cfg: &ModelConfig,
        layout: &ModelLayout,
        p: &[f32],
        mc: &MaskLearningConfig,
        al: &AuxLayout,
        ap: &[f32],
    ) -> (f64, Vec<f32>, Vec<f32>) {
        let (rays, tg) = rays();
        let step = StepSettings {
            anneal: 1.0,
            interlevel_weight: 1.0,
            distortion_weight: 0.01,
            loss_scale: 1.0 / rays.len() as f32,
            sample_mask_weight: 0.0,
        };
        let mut g = vec![0f32; p.len()];
        let mut ag = vec![0f32; ap.len()];
        let l = train_chunk_with(
            cfg,
            layout,
            p,
            &mut g,
            &rays,
            &tg,
            None,
            &step,
            &mut Rng::new(5),
            &mut Workspace::default(),
            Some(AuxStep {
                cfg: mc,
                layout: al,
                params: ap,
                grad: &mut ag,
            }),
        );
        let nr = rays.len() as f64;
        let total = (l.sq_err + step.distortion_weight as f64 * l.distortion) / nr
            + mc.uncertainty_weight as f64 * l.uncertainty / nr
            - if mc.mine {
                mc.mine_weight as f64 * l.mine / nr
            } else {
                0.0
            };
        (total, g, ag)
    }

    /// A central-difference check of the parameters with the largest analytic gradient.
    struct FdCheck {
        /// How many parameters to check.
        count: usize,
        h: f32,
        tol_abs: f64,
        tol_rel: f64,
        /// The largest gradient must exceed this (the term must reach the parameters at all).
        min_grad: f64,
    }

    impl FdCheck {
        /// Checks `grad(i)` against central differences of `loss` for the `count` parameters of
        /// `range` with the largest `|grad|`: `|fd - grad| < tol_abs + tol_rel * |fd|`.
        fn largest(
            &self,
            p: &[f32],
            range: std::ops::Range<usize>,
            grad: impl Fn(usize) -> f64,
            loss: impl Fn(&[f32]) -> f64,
        ) {
            let mut idx: Vec<usize> = range.collect();
            idx.sort_by(|&a, &b| grad(b).abs().partial_cmp(&grad(a).abs()).unwrap());
            assert!(
                grad(idx[0]).abs() > self.min_grad,
                "no gradient reaches these parameters"
            );
            for &i in idx.iter().take(self.count) {
                let mut q = p.to_vec();
                q[i] += self.h;
                let lp = loss(&q);
                q[i] -= 2.0 * self.h;
                let lm = loss(&q);
                let fd = (lp - lm) / (2.0 * self.h as f64);
                assert!(
                    (fd - grad(i)).abs() < self.tol_abs + self.tol_rel * fd.abs(),
                    "[{i}]: fd {fd} vs {}",
                    grad(i)
                );
            }
        }
    }

    fn perturbed_params(layout: &ModelLayout) -> Vec<f32> {
        let mut p = layout.init_params(1);
        let mut r = Rng::new(2);
        for v in p.iter_mut() {
            *v += r.range_f32(-0.3, 0.3);
        }
        p
    }

    /// The whole training step with every mask-learning term on, against finite differences:
    /// the main field (h3, h4, mask, both MLPs: the static branch shares them), the uncertainty
    /// grid and the MINE network.
    #[test]
    fn train_chunk_with_mask_learning_matches_finite_differences() {
        let cfg = tiny_cfg();
        let layout = ModelLayout::new(&cfg);
        let p = perturbed_params(&layout);
        let (mc, al, ap) = aux_setup(true);
        let (_, grad, agrad) = aux_chunk(&cfg, &layout, &p, &mc, &al, &ap);
        let check = |name: &str, fd: f64, g: f32| {
            let tol = 1e-4 + 5e-2 * fd.abs();
            assert!((fd - g as f64).abs() < tol, "{name}: fd {fd} vs {g}");
        };
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
                let lp = aux_chunk(&cfg, &layout, &q, &mc, &al, &ap).0;
                q[i] -= 2.0 * h;
                let lm = aux_chunk(&cfg, &layout, &q, &mc, &al, &ap).0;
                check(&e.name, (lp - lm) / (2.0 * h as f64), grad[i]);
                checked += 1;
            }
        }
        for e in &al.params.entries {
            let mut idx: Vec<usize> = e.range().collect();
            idx.sort_by(|&a, &b| agrad[b].abs().partial_cmp(&agrad[a].abs()).unwrap());
            assert!(agrad[idx[0]] != 0.0, "{} gets no gradient", e.name);
            for &i in idx.iter().take(6) {
                let h = 2e-3;
                let mut q = ap.clone();
                q[i] += h;
                let lp = aux_chunk(&cfg, &layout, &p, &mc, &al, &q).0;
                q[i] -= 2.0 * h;
                let lm = aux_chunk(&cfg, &layout, &p, &mc, &al, &q).0;
                check(&e.name, (lp - lm) / (2.0 * h as f64), agrad[i]);
                checked += 1;
            }
        }
        assert!(checked >= 30);
    }

    /// The `-gamma * I` term reaches the mask grid: the mask gradient with MINE on differs from
    /// the one without by the finite difference of the MINE term alone.
    #[test]
    fn mine_gradient_reaches_the_mask_grid() {
        let cfg = tiny_cfg();
        let layout = ModelLayout::new(&cfg);
        let p = perturbed_params(&layout);
        let (mut mc_on, al, ap) = aux_setup(true);
        // A large weight, so that the MINE term stands out of the rounding of the total.
        mc_on.mine_weight = 50.0;
        let (mc_off, _, _) = aux_setup(false);
        let (_, g_on, _) = aux_chunk(&cfg, &layout, &p, &mc_on, &al, &ap);
        let (_, g_off, _) = aux_chunk(&cfg, &layout, &p, &mc_off, &al, &ap);
        let mine_only = |q: &[f32]| {
            aux_chunk(&cfg, &layout, q, &mc_on, &al, &ap).0
                - aux_chunk(&cfg, &layout, q, &mc_off, &al, &ap).0
        };
        let mask = layout.params.get("field.mask").unwrap().range();
        // The MINE term is summed in f32: steps below 1e-2 drown in rounding.
        let fd = FdCheck {
            count: 6,
            h: 1e-2,
            tol_abs: 1e-4,
            tol_rel: 5e-2,
            min_grad: 1e-3,
        };
        fd.largest(&p, mask, |i| (g_on[i] - g_off[i]) as f64, mine_only);
    }

    /// The per-sample mask loss: its gradient is that of `lambda * mean_r sum_i w_i (1 - m_i)`
    /// with the rendering weights held constant (finite differences over the mask logits), it
    /// reaches nothing but the mask, and weight 0 is the plain step.
    #[test]
    fn sample_mask_loss_matches_finite_differences() {
        let cfg = tiny_cfg();
        let layout = ModelLayout::new(&cfg);
        let p = perturbed_params(&layout);
        let (rays, tg) = rays();
        let lam = 0.5f32;
        let run = |lam: f32, ws: &mut Workspace| {
            let step = StepSettings {
                anneal: 1.0,
                interlevel_weight: 1.0,
                distortion_weight: 0.01,
                loss_scale: 1.0 / rays.len() as f32,
                sample_mask_weight: lam,
            };
            let mut g = vec![0f32; p.len()];
            let l = train_chunk_with(
                &cfg,
                &layout,
                &p,
                &mut g,
                &rays,
                &tg,
                None,
                &step,
                &mut Rng::new(5),
                ws,
                None,
            );
            (l, g)
        };
        let mut ws = Workspace::default();
        let (l_on, g_on) = run(lam, &mut ws);
        let (l_off, g_off) = run(0.0, &mut Workspace::default());
        assert_eq!(l_off.sample_mask, 0.0);
        assert_eq!(l_on.sq_err, l_off.sq_err);
        let mask = layout.params.get("field.mask").unwrap().range();
        for i in 0..p.len() {
            if !mask.contains(&i) {
                assert_eq!(g_on[i], g_off[i], "parameter {i} outside the mask moved");
            }
        }
        // The run's weights and sample points, held fixed.
        let w = ws.w_main.clone();
        let pts = ws.pts_main.clone();
        let stride = pts.len() / w.len();
        let enc = &layout.field.encoding;
        let scale = 1.0 / rays.len() as f64;
        let term = |q: &[f32]| -> f64 {
            (0..w.len())
                .map(|j| {
                    let m = enc.mask_at(q, &pts[j * stride..j * stride + 3]) as f64;
                    w[j] as f64 * (1.0 - m)
                })
                .sum::<f64>()
                * lam as f64
                * scale
        };
        let t0 = term(&p);
        assert!(
            (t0 - l_on.sample_mask * scale).abs() < 1e-5 * t0.abs().max(1e-3),
            "loss {} vs {t0}",
            l_on.sample_mask * scale
        );
        let fd = FdCheck {
            count: 8,
            h: 1e-3,
            tol_abs: 1e-6,
            tol_rel: 1e-2,
            min_grad: 1e-4,
        };
        fd.largest(&p, mask, |i| (g_on[i] - g_off[i]) as f64, term);
    }

    /// The whole step with mask learning at its extremes (uncertainty logits at +-60, so `u` at
    /// its floor or huge; MINE weights scaled up until its statistics saturate; `u_min = 0`):
    /// finite losses and gradients.
    #[test]
    fn mask_learning_step_extremes_stay_finite() {
        let cfg = tiny_cfg();
        let layout = ModelLayout::new(&cfg);
        let p = perturbed_params(&layout);
        for (logit, mine_scale, u_min) in [
            (-60.0f32, 1.0f32, 0.0f32),
            (60.0, 50.0, 0.01),
            (-60.0, 200.0, 0.0),
        ] {
            let (mut mc, mut al, mut ap) = aux_setup(true);
            mc.uncertainty_min = u_min;
            al.u_min = u_min;
            ap[al.grid.1.clone()].fill(logit);
            for v in &mut ap[al.mine.1.clone()] {
                *v *= mine_scale;
            }
            let (total, g, ag) = aux_chunk(&cfg, &layout, &p, &mc, &al, &ap);
            assert!(total.is_finite(), "{logit} {mine_scale}: {total}");
            assert!(
                g.iter().chain(&ag).all(|v| v.is_finite()),
                "{logit} {mine_scale}"
            );
        }
    }

    /// With the mask-learning settings present but every term off, a chunk is bit-for-bit the
    /// plain [`train_chunk`].
    #[test]
    fn mask_learning_off_is_the_plain_step() {
        let cfg = tiny_cfg();
        let layout = ModelLayout::new(&cfg);
        let p = perturbed_params(&layout);
        let (rays, tg) = rays();
        let step = StepSettings {
            anneal: 0.7,
            interlevel_weight: 1.0,
            distortion_weight: 0.01,
            loss_scale: 0.25,
            sample_mask_weight: 0.0,
        };
        let mc = MaskLearningConfig::default();
        let al = AuxLayout::new(&mc);
        let ap = al.init_params(1);
        let mut ag = vec![0f32; ap.len()];
        let mut g1 = vec![0f32; p.len()];
        let mut g2 = vec![0f32; p.len()];
        let mut ws = Workspace::default();
        let l1 = train_chunk(
            &cfg,
            &layout,
            &p,
            &mut g1,
            &rays,
            &tg,
            None,
            &step,
            &mut Rng::new(5),
            &mut ws,
        );
        let l2 = train_chunk_with(
            &cfg,
            &layout,
            &p,
            &mut g2,
            &rays,
            &tg,
            None,
            &step,
            &mut Rng::new(5),
            &mut ws,
            Some(AuxStep {
                cfg: &mc,
                layout: &al,
                params: &ap,
                grad: &mut ag,
            }),
        );
        assert_eq!(l1, l2);
        assert_eq!(g1, g2);
        assert!(ag.iter().all(|&v| v == 0.0));
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

    #[test]
    fn playback_partition_at_one_time_is_the_render_samples() {
        let cfg = tiny_cfg();
        let layout = ModelLayout::new(&cfg);
        let p = perturbed_params(&layout);
        let (rays, _) = rays();
        let nf = cfg.sampler.num_samples;
        for r in &rays {
            let mut ws = Workspace::default();
            render_chunk(
                &cfg,
                &layout,
                &p,
                &[*r],
                &mut ws,
                &mut RenderOutput::default(),
            );
            let rendered = ws.pts_main.clone();
            let deltas = ws.delta_main.clone();
            let part = playback_partition(&cfg, &layout, &p, &[*r], &[r.time], nf, &mut ws);
            assert_eq!(part.samples, nf);
            assert_eq!(part.deltas, deltas[..nf]);
            for k in 0..nf {
                assert_eq!(part.points[k * 4..k * 4 + 3], rendered[k * 4..k * 4 + 3]);
                assert_eq!(part.points[k * 4 + 3], 0.0);
            }
            // Weights combine by their maximum: a repeated time changes nothing.
            let twice = playback_partition(&cfg, &layout, &p, &[*r], &[r.time; 2], nf, &mut ws);
            assert_eq!(twice, part);
            let other = (r.time + 0.5) % 1.0;
            let both = playback_partition(&cfg, &layout, &p, &[*r], &[r.time, other], nf, &mut ws);
            assert!(both.points.iter().all(|v| v.is_finite()));
            assert!(both.deltas.iter().all(|&d| d >= 0.0));
        }
    }
}
