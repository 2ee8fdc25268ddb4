//! Where a chunk's samples go: per-ray limits, samples at the midpoints of normalised edges,
//! the proposal samples of a chunk, and the direction encodings.

use super::*;

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

/// The time a ray's samples carry: its time clamped to `[0, 1]` (negative and NaN times: 0).
pub fn sample_time(time: f32) -> f32 {
    if time >= 0.0 {
        time.min(1.0)
    } else {
        0.0
    }
}

/// Places samples at the midpoints (in distance) of the intervals given by normalised `edges`.
#[allow(clippy::too_many_arguments)]
pub(super) fn place_samples(
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
    let time = sample_time(r.time);
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
pub(super) fn place_proposal_samples(
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
