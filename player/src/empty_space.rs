//! Empty-space skipping with the file's occupancy grid (format.md §6.5, `msth_codec::occupancy`).
//!
//! [`render_chunk_skipping`] renders a batch of rays as `msth_core::pipeline::render_chunk` does
//! (samples resampled from the proposal's weights, through `playback_partition` at the
//! batch's one time) but evaluates both fields only at samples whose occupancy cell is set: the
//! others get density 0 and no colour. The grid is the union over the model's frames of where
//! the density reaches a threshold, dilated by one cell, so the skipped samples are those the
//! export found empty at every frame; with a grid of every cell set the result equals
//! `render_chunk` (tested below).
//!
//! A proposal sample in an empty cell gets density 0 without evaluation, so it carries no
//! proposal weight and the resampled samples land in occupied cells: that moves samples only
//! where the proposal network put density in space the main field leaves empty, and frames stay
//! within a fraction of a grey level of the unskipped render (64 dB on the object scene,
//! docs/playback.md) while the empty space around an object costs nothing.

use msth_codec::OccupancyGrid;
use msth_core::config::ModelConfig;
use msth_core::field::{FieldScratch, ModelLayout};
use msth_core::pipeline::{
    composite_ray, direction_encodings, playback_partition, ray_limits, render_chunk, RenderOutput,
    TimedRay, Workspace, HIDDEN_TRANSMITTANCE, RENDER_STATIC_CUTOFF, VISIBLE_TRANSMITTANCE,
};
use msth_core::render;

/// Per-thread buffers of [`render_chunk_skipping`].
#[derive(Default)]
pub struct SkipWorkspace {
    core: Workspace,
    field: FieldScratch,
    pts: Vec<f32>,
    /// Per occupied sample: its index in the batch (`ray * samples + k`).
    owner: Vec<u32>,
    /// Per batch sample: its index among the occupied ones, or `u32::MAX`.
    slot: Vec<u32>,
    active: Vec<u32>,
    sh: Vec<f32>,
    sigma: Vec<f32>,
    w: Vec<f32>,
    rgb: Vec<f32>,
    /// Samples evaluated and samples skipped, summed over calls.
    pub evaluated: u64,
    pub skipped: u64,
}

impl SkipWorkspace {
    /// The core workspace, for batches rendered by `render_chunk`.
    pub fn core(&mut self) -> &mut Workspace {
        &mut self.core
    }
}

/// Renders `rays` (one time for all; other batches go to `render_chunk`) skipping the main
/// field in cells `grid` marks empty. Fills `out` as `render_chunk` does.
pub fn render_chunk_skipping(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    grid: &OccupancyGrid,
    ws: &mut SkipWorkspace,
    out: &mut RenderOutput,
) {
    let n = rays.len();
    if n == 0 {
        return;
    }
    let time = rays[0].time;
    if rays.iter().any(|r| r.time.to_bits() != time.to_bits()) {
        render_chunk(cfg, layout, params, rays, &mut ws.core, out);
        return;
    }
    let nf = cfg.sampler.num_samples;
    // The samples render_chunk places: the proposal's weights at `time` resampled, the
    // proposal evaluated in occupied cells only (its density is 0 in the others, so the
    // samples go to occupied cells).
    let keep = |p: [f32; 3]| grid.occupied_unit(p);
    let part = playback_partition(
        cfg,
        layout,
        params,
        rays,
        &[time],
        nf,
        Some(&keep),
        &mut ws.core,
    );
    let t_point = if time >= 0.0 { time.min(1.0) } else { 0.0 };
    ws.pts.clear();
    ws.owner.clear();
    ws.slot.clear();
    ws.slot.resize(n * nf, u32::MAX);
    for k in 0..n * nf {
        let p = &part.points[k * 4..k * 4 + 3];
        if grid.occupied_unit([p[0], p[1], p[2]]) {
            ws.slot[k] = ws.owner.len() as u32;
            ws.owner.push(k as u32);
            ws.pts.extend_from_slice(&[p[0], p[1], p[2], t_point]);
        }
    }
    let m = ws.owner.len();
    ws.evaluated += m as u64;
    ws.skipped += (n * nf - m) as u64;
    ws.sigma.clear();
    ws.sigma.resize(n * nf, 0.0);
    ws.field.enc.static_cutoff = RENDER_STATIC_CUTOFF;
    if m > 0 {
        layout
            .field
            .forward_density(params, &ws.pts, m, &mut ws.field);
        for (j, &k) in ws.owner.iter().enumerate() {
            ws.sigma[k as usize] = ws.field.sigma[j];
        }
        // Colour only where light can still arrive (as render_chunk does).
        let tau_hidden = (1.0 / HIDDEN_TRANSMITTANCE).ln();
        ws.active.clear();
        for i in 0..n {
            let mut tau = 0f32;
            for k in i * nf..(i + 1) * nf {
                if tau > tau_hidden {
                    break;
                }
                if ws.slot[k] != u32::MAX {
                    ws.active.push(ws.slot[k]);
                }
                tau += render::tau_of(ws.sigma[k], part.deltas[k]);
            }
        }
        direction_encodings(rays, &mut ws.sh);
        let owner = &ws.owner;
        layout.field.forward_color(
            params,
            &ws.sh,
            &|j| owner[j] as usize / nf,
            Some(&ws.active),
            m,
            &mut ws.field,
        );
    }
    let has_mask = layout.field.encoding.mask.is_some();
    let m_const = layout.field.encoding.mask_at(params, &[0.0; 3]);
    ws.w.resize(nf, 0.0);
    ws.rgb.resize(nf * 3, 0.0);
    for (i, ray) in rays.iter().enumerate() {
        let fs = i * nf..(i + 1) * nf;
        let t_final = render::weights(&ws.sigma[fs.clone()], &part.deltas[fs.clone()], &mut ws.w);
        for k in 0..nf {
            let c = match ws.slot[i * nf + k] {
                u32::MAX => [0.0; 3],
                j => {
                    let j = j as usize;
                    [
                        ws.field.rgb[j * 3],
                        ws.field.rgb[j * 3 + 1],
                        ws.field.rgb[j * 3 + 2],
                    ]
                }
            };
            ws.rgb[k * 3..k * 3 + 3].copy_from_slice(&c);
        }
        out.rgb
            .push(composite_ray(cfg.background, &ws.w, &ws.rgb, t_final));
        // Depth, mask and visible depth as render_chunk computes them; the sample edges are
        // `near` plus the running sum of the intervals (sample_pdf's first edge is 0, its last 1).
        let (near, _) = ray_limits(cfg, ray);
        let mut edge = near;
        let (mut depth, mut mask, mut min_mask) = (0f32, 0f32, 1f32);
        let mut visible = None;
        let mut acc = 0f32;
        for k in 0..nf {
            let d = part.deltas[i * nf + k];
            let t_mid = edge + 0.5 * d;
            edge += d;
            let w = ws.w[k];
            acc += w;
            if visible.is_none() && 1.0 - acc < VISIBLE_TRANSMITTANCE {
                visible = Some(edge);
            }
            depth += w * t_mid;
            let mv = match ws.slot[i * nf + k] {
                j if j != u32::MAX && has_mask => ws.field.enc.m[j as usize],
                _ => m_const,
            };
            mask += w * mv;
            if w > 1e-4 {
                min_mask = min_mask.min(mv);
            }
        }
        out.depth.push(depth);
        out.opacity.push(1.0 - t_final);
        out.mask.push(mask);
        out.min_mask.push(min_mask);
        out.visible_depth.push(visible.unwrap_or(edge));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::config::BlendMode;

    fn model() -> (ModelConfig, ModelLayout, Vec<f32>) {
        let mut cfg = ModelConfig::fast_on_white(4);
        for enc in [&mut cfg.field.encoding, &mut cfg.proposal.encoding] {
            enc.blend = BlendMode::Mst;
            enc.resize(3, 12, 32.0, 10);
        }
        cfg.sampler.set_samples(24, 12);
        let layout = ModelLayout::new(&cfg);
        let params = layout.init_params(5);
        (cfg, layout, params)
    }

    fn rays(time: f32) -> Vec<TimedRay> {
        (0..40)
            .map(|i| {
                let a = i as f32 * 0.05 - 1.0;
                TimedRay {
                    origin: Vec3::new(a, 0.3 * a, 4.0),
                    dir: Vec3::new(-0.1 * a, 0.05, -1.0).normalize(),
                    time,
                }
            })
            .collect()
    }

    #[test]
    fn a_full_grid_renders_exactly_what_render_chunk_does() {
        let (cfg, layout, params) = model();
        let rays = rays(0.4);
        let mut a = RenderOutput::default();
        render_chunk(
            &cfg,
            &layout,
            &params,
            &rays,
            &mut Workspace::default(),
            &mut a,
        );
        let mut b = RenderOutput::default();
        let mut ws = SkipWorkspace::default();
        let grid = OccupancyGrid::full(8);
        render_chunk_skipping(&cfg, &layout, &params, &rays, &grid, &mut ws, &mut b);
        assert_eq!(ws.skipped, 0);
        for (x, y) in a.rgb.iter().zip(&b.rgb) {
            for c in 0..3 {
                assert!((x[c] - y[c]).abs() < 1e-5, "{x:?} {y:?}");
            }
        }
        for (x, y) in [
            (&a.depth, &b.depth),
            (&a.visible_depth, &b.visible_depth),
            (&a.mask, &b.mask),
            (&a.min_mask, &b.min_mask),
            (&a.opacity, &b.opacity),
        ] {
            for (p, q) in x.iter().zip(y) {
                assert!((p - q).abs() <= 1e-4 * (1.0 + p.abs()), "{p} {q}");
            }
        }
    }

    #[test]
    fn an_empty_grid_shows_the_background_and_evaluates_nothing() {
        let (cfg, layout, params) = model();
        let rays = rays(0.0);
        let mut grid = OccupancyGrid::full(4);
        grid.words.iter_mut().for_each(|w| *w = 0);
        let mut out = RenderOutput::default();
        let mut ws = SkipWorkspace::default();
        render_chunk_skipping(&cfg, &layout, &params, &rays, &grid, &mut ws, &mut out);
        assert_eq!(ws.evaluated, 0);
        assert!(ws.skipped > 0);
        assert!(out.rgb.iter().all(|c| *c == [1.0; 3]));
        assert!(out.opacity.iter().all(|&o| o == 0.0));
    }
}
