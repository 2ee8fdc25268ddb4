//! The time-independent sample partition of playback with sample-level reuse (the player's
//! `samples` module): one set of sample positions per ray that serves every time of a clip.

use super::*;

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

/// Which proposal samples [`playback_partition`] evaluates: `keep(unit point)`; the others get
/// density 0 (an empty-space structure's test, such as the player's occupancy grid).
pub type KeepPoint<'a> = &'a (dyn Fn([f32; 3]) -> bool + Sync);

/// Builds a [`Partition`] of `rays` that serves every time in `times`: the proposal field is
/// evaluated at its (deterministic, time-independent) samples at each of `times`, the weights of
/// each bin are combined by their maximum over the times, and `samples` intervals are drawn
/// from that histogram as rendering draws them from one time's. A surface that is anywhere
/// along the ray at one of `times` thus gets samples; a static one gets the same as in a frame.
/// With `keep`, the proposal field is evaluated only at samples whose unit-cube point it
/// accepts; a rejected sample has density 0, so it carries no proposal weight and the resampled
/// samples move to the accepted ones.
#[allow(clippy::too_many_arguments)]
pub fn playback_partition(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    times: &[f32],
    samples: usize,
    keep: Option<KeepPoint<'_>>,
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
        match keep {
            None => {
                layout
                    .proposal
                    .field
                    .forward_density(params, &ws.pts_prop, n * np, &mut ws.prop)
            }
            Some(keep) => {
                // Evaluate the kept samples only, packed (into `pts_main`, unused by playback),
                // then spread their densities over all samples in `w_stat` (a training-only
                // buffer, free here) and swap it in as the proposal's densities.
                ws.active.clear();
                ws.pts_main.clear();
                for k in 0..n * np {
                    let p = &ws.pts_prop[k * 4..k * 4 + 4];
                    if keep([p[0], p[1], p[2]]) {
                        ws.active.push(k as u32);
                        ws.pts_main.extend_from_slice(p);
                    }
                }
                let m = ws.active.len();
                if m > 0 {
                    layout
                        .proposal
                        .field
                        .forward_density(params, &ws.pts_main, m, &mut ws.prop);
                }
                ws.w_stat.clear();
                ws.w_stat.resize(n * np, 0.0);
                for (j, &k) in ws.active.iter().enumerate() {
                    ws.w_stat[k as usize] = ws.prop.sigma[j];
                }
                std::mem::swap(&mut ws.w_stat, &mut ws.prop.sigma);
            }
        }
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
            render_histogram_padding(&cfg.sampler),
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
