//! One training chunk: forward, losses (colour, distortion, interlevel, per-sample mask) and the
//! backward pass through both fields, with the uncertainty branch of mask learning (static
//! branch, uncertainty grid, MINE) when it is on.

use super::*;

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
        None,
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
///
/// `mask_weights`, when given, holds one factor per ray for the per-sample mask loss (ray `i`'s
/// terms are scaled by `mask_weights[i]`): the trainer gives 0 to rays through pixels that
/// change over time, so the loss pulls toward static only what the data shows still. `None` is
/// a factor of 1 for every ray.
#[allow(clippy::too_many_arguments)]
pub fn train_chunk_with(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    grad: &mut [f32],
    rays: &[TimedRay],
    targets: &[[f32; 3]],
    backgrounds: Option<&[[f32; 3]]>,
    mask_weights: Option<&[f32]>,
    step: &StepSettings,
    rng: &mut Rng,
    ws: &mut Workspace,
    mut aux: Option<AuxStep<'_>>,
) -> ChunkLosses {
    let n = rays.len();
    assert!(
        mask_weights.is_none_or(|mw| mw.len() == n),
        "train_chunk_with: {n} rays need {n} mask weights"
    );
    let np = cfg.sampler.num_proposal_samples;
    let nf = cfg.sampler.num_samples;
    // Training evaluates every point exactly (the gradients need every h4).
    ws.prop.enc.static_cutoff = 0.0;
    ws.main.enc.static_cutoff = 0.0;
    ws.main.enc.d_m_extra.clear();
    // The coarse-to-fine schedule acts on every evaluation of the main field's encoding.
    for f in [&mut ws.main, &mut ws.stat, &mut ws.free] {
        f.enc.active_levels = step.active_levels;
    }
    ws.prop.enc.active_levels = step.proposal_levels;
    let padding = cfg.sampler.histogram_padding;
    forward_chunk(
        cfg,
        layout,
        params,
        rays,
        step.anneal,
        padding,
        Some(rng),
        ws,
    );
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
        let ray_mask_weight = mask_weights.map_or(1.0, |mw| mw[i]);
        if sample_mask && ray_mask_weight != 0.0 {
            let weight = step.sample_mask_weight * ray_mask_weight;
            let lam = weight * scale;
            for k in 0..nf {
                let m = ws.main.enc.m[i * nf + k];
                out.sample_mask += (w[k] * (1.0 - m)) as f64 * weight as f64;
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
    if step.free_space_weight > 0.0 && n > 0 {
        out.free_space = free_space(cfg, layout, params, grad, n, step, rng, ws);
    }
    out
}

/// One point of the free-space loss: `(x, y, z, t)` uniform over the grids' unit cube and the
/// clip (a GPU step draws its points with this from the chunk's stream, after the jitters).
pub fn free_space_point(rng: &mut Rng) -> [f32; 4] {
    [rng.f32(), rng.f32(), rng.f32(), sample_time(rng.f32())]
}

/// The free-space loss's step `delta` in world units: [`FREE_SPACE_STEP`] of the diagonal of
/// the scene's extent (the uncontracted cube of a contracted scene).
pub fn free_space_delta(bounds: &SceneBounds) -> f32 {
    let (lo, hi) = bounds.extent();
    (hi - lo).length() * FREE_SPACE_STEP
}

/// The free-space loss of one chunk ([`StepSettings::free_space_weight`]): `n` points drawn
/// uniformly over the grids' unit cube and the clip, the main field's density there, and its
/// gradient into `grad`. Returns the chunk's loss sum, its weight included.
#[allow(clippy::too_many_arguments)]
fn free_space(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    grad: &mut [f32],
    n: usize,
    step: &StepSettings,
    rng: &mut Rng,
    ws: &mut Workspace,
) -> f64 {
    let delta = free_space_delta(&cfg.bounds);
    ws.pts_free.clear();
    for _ in 0..n {
        ws.pts_free.extend_from_slice(&free_space_point(rng));
    }
    ws.free.enc.static_cutoff = 0.0;
    ws.free.enc.d_m_extra.clear();
    layout
        .field
        .forward_density(params, &ws.pts_free, n, &mut ws.free);
    let lam = step.free_space_weight;
    let g = lam * step.loss_scale * delta;
    ws.d_sigma_free.clear();
    let mut sum = 0f64;
    for &sigma in &ws.free.sigma[..n] {
        let e = (-sigma * delta).exp();
        sum += (1.0 - e) as f64;
        ws.d_sigma_free.push(g * e);
    }
    layout.field.backward_density(
        params,
        &ws.pts_free,
        n,
        &mut ws.free,
        &ws.d_sigma_free,
        grad,
    );
    sum * lam as f64
}
