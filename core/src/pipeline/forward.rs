//! The forward pass of a chunk (proposal field, resampling, main field with colour only where
//! light still arrives), compositing, and inference rendering.

use super::*;

/// Forward of proposal and main fields for a chunk, the main samples resampled with `padding`
/// per proposal bin; leaves everything in `ws`.
#[allow(clippy::too_many_arguments)]
pub(super) fn forward_chunk(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    anneal: f32,
    padding: f32,
    rng: Option<&mut Rng>,
    ws: &mut Workspace,
) {
    forward_geometry(cfg, layout, params, rays, anneal, padding, rng, ws);
    let n = rays.len();
    let nf = cfg.sampler.num_samples;
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
}

/// The proposal field, the resampling (with `padding` per proposal bin) and the main field's
/// density of a chunk (no colour).
#[allow(clippy::too_many_arguments)]
fn forward_geometry(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    anneal: f32,
    padding: f32,
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
            padding,
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
    ws.w_main.resize(n * nf, 0.0);
}

/// A main sample that [`weighted_samples`] reports.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WeightedSample {
    /// The ray's index in the chunk.
    pub ray: usize,
    /// The sample's point in the grids' coordinates `(x, y, z)`.
    pub unit: [f32; 3],
    /// Its interval along the ray, in world units from the ray's origin (the ray's direction
    /// is a unit vector): the sample stands for the ray between these two distances.
    pub t: [f32; 2],
    /// Its rendering weight (NaN where the density was NaN).
    pub weight: f32,
}

/// Where a chunk's light comes from: calls `seen` with every main sample whose rendering weight
/// is at least `min_weight` (or NaN), sampling as [`render_chunk`] does but with the model's own
/// histogram padding (the main field's colour is not evaluated). `msth export` marks the
/// occupancy grid's cells that its training cameras see this way.
///
/// Why the model's padding and not [`render_histogram_padding`]: each reported sample stands for
/// its whole interval along the ray. The training padding spreads some samples evenly along the
/// ray and so cuts empty stretches into short intervals of small weight. With the render
/// padding those stretches become a few long intervals, each heavy enough to count as seen. On
/// the balanced stage model that doubled the cells seen (54,593 to 116,552). The grid grew from
/// 82.3% to 85.7% of its cells, and a frame had 39% more live proposal samples, with no frame
/// kept better (docs/tradeoff.md, "Histogram padding at play time"). The render samples lie where the weight is, so
/// they fall in the cells this finer sampling marks.
pub fn weighted_samples(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    min_weight: f32,
    ws: &mut Workspace,
    mut seen: impl FnMut(WeightedSample),
) {
    let nf = cfg.sampler.num_samples;
    ws.prop.enc.static_cutoff = RENDER_STATIC_CUTOFF;
    ws.main.enc.static_cutoff = RENDER_STATIC_CUTOFF;
    let padding = cfg.sampler.histogram_padding;
    forward_geometry(cfg, layout, params, rays, 1.0, padding, None, ws);
    for i in 0..rays.len() {
        let fs = i * nf..(i + 1) * nf;
        let w = &mut ws.w_main[fs.clone()];
        render::weights(&ws.main.sigma[fs.clone()], &ws.delta_main[fs.clone()], w);
        let edges = &ws.t_main[i * (nf + 1)..(i + 1) * (nf + 1)];
        for (k, &wk) in w.iter().enumerate() {
            // NaN weights count as seen: nothing is skipped on their account.
            if wk >= min_weight || wk.is_nan() {
                let p = &ws.pts_main[(i * nf + k) * 4..];
                seen(WeightedSample {
                    ray: i,
                    unit: [p[0], p[1], p[2]],
                    t: [edges[k], edges[k + 1]],
                    weight: wk,
                });
            }
        }
    }
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
    let padding = render_histogram_padding(&cfg.sampler);
    forward_chunk(cfg, layout, params, rays, 1.0, padding, None, ws);
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
