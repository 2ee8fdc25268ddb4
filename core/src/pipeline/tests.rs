//! Tests of the chunk pipeline: finite differences of the training step, determinism of
//! rendering, the playback partition.

use super::*;
use crate::config::BlendMode;
use crate::test_support::{central_difference, largest_first};

fn tiny_cfg() -> ModelConfig {
    let mut c = ModelConfig::fast_on_white(5);
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        enc.blend = BlendMode::Mst;
        enc.resize(2, 6, 8.0, 4);
        enc.grid4.finest_resolution[3] = 4.0;
        enc.grid3.base_resolution = vec![4.0; 3];
        enc.grid4.base_resolution = vec![4.0, 4.0, 4.0, 2.0];
    }
    c.resize_mlps(8, 4);
    c.field.geo_features = 3;
    c.sampler.set_samples(12, 6);
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

/// One chunk of the training step over `rays` with the random stream every test here uses:
/// its losses and its gradient.
fn chunk(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    p: &[f32],
    (rays, tg): (&[TimedRay], &[[f32; 3]]),
    step: &StepSettings,
) -> (ChunkLosses, Vec<f32>) {
    let mut g = vec![0f32; p.len()];
    let l = train_chunk(
        cfg,
        layout,
        p,
        &mut g,
        rays,
        tg,
        None,
        step,
        &mut Rng::new(5),
        &mut Workspace::default(),
    );
    (l, g)
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
    let p = perturbed_params(&layout);
    let (rays, tg) = rays();
    let step = full_step(rays.len(), 0.0);
    let total = |p: &[f32]| -> f64 {
        let (l, _) = chunk(&cfg, &layout, p, (&rays, &tg), &step);
        // only the terms that depend on the main field
        (l.sq_err + step.distortion_weight as f64 * l.distortion) / rays.len() as f64
    };
    let (_, grad) = chunk(&cfg, &layout, &p, (&rays, &tg), &step);
    let mut checked = 0;
    for e in layout
        .params
        .entries
        .iter()
        .filter(|e| e.name.starts_with("field"))
    {
        for &i in largest_first(e.range(), |i| grad[i] as f64).iter().take(6) {
            let fd = central_difference(total, &p, i, 2e-3);
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
    let step = full_step(rays.len(), 0.0);
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
        let idx = largest_first(range, &grad);
        assert!(
            grad(idx[0]).abs() > self.min_grad,
            "no gradient reaches these parameters"
        );
        for &i in idx.iter().take(self.count) {
            let fd = central_difference(&loss, p, i, self.h);
            assert!(
                (fd - grad(i)).abs() < self.tol_abs + self.tol_rel * fd.abs(),
                "[{i}]: fd {fd} vs {}",
                grad(i)
            );
        }
    }
}

/// The settings of a full training step (annealing done, interlevel and distortion on) over
/// `rays` rays, with per-sample mask loss weight `sample_mask_weight`.
fn full_step(rays: usize, sample_mask_weight: f32) -> StepSettings {
    StepSettings {
        anneal: 1.0,
        interlevel_weight: 1.0,
        distortion_weight: 0.01,
        loss_scale: 1.0 / rays as f32,
        sample_mask_weight,
        free_space_weight: 0.0,
        active_levels: None,
        proposal_levels: None,
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
        let loss = |q: &[f32]| aux_chunk(&cfg, &layout, q, &mc, &al, &ap).0;
        for &i in largest_first(e.range(), |i| grad[i] as f64).iter().take(6) {
            check(&e.name, central_difference(loss, &p, i, 2e-3), grad[i]);
            checked += 1;
        }
    }
    for e in &al.params.entries {
        let idx = largest_first(e.range(), |i| agrad[i] as f64);
        assert!(agrad[idx[0]] != 0.0, "{} gets no gradient", e.name);
        let loss = |q: &[f32]| aux_chunk(&cfg, &layout, &p, &mc, &al, q).0;
        for &i in idx.iter().take(6) {
            check(&e.name, central_difference(loss, &ap, i, 2e-3), agrad[i]);
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
/// with the rendering weights held constant (finite differences over the mask logits), also with
/// per-ray factors (each ray's terms scaled by its factor; factors of 1 are no factors), it
/// reaches nothing but the mask, and weight 0 is the plain step.
#[test]
fn sample_mask_loss_matches_finite_differences() {
    let cfg = tiny_cfg();
    let layout = ModelLayout::new(&cfg);
    let p = perturbed_params(&layout);
    let (rays, tg) = rays();
    let lam = 0.5f32;
    let run = |lam: f32, mask_weights: Option<&[f32]>, ws: &mut Workspace| {
        let step = full_step(rays.len(), lam);
        let mut g = vec![0f32; p.len()];
        let l = train_chunk_with(
            &cfg,
            &layout,
            &p,
            &mut g,
            &rays,
            &tg,
            None,
            mask_weights,
            &step,
            &mut Rng::new(5),
            ws,
            None,
        );
        (l, g)
    };
    let (l_off, g_off) = run(0.0, None, &mut Workspace::default());
    assert_eq!(l_off.sample_mask, 0.0);
    // Per-ray factors of 1 are the unweighted loss, to the bit.
    let ones = vec![1f32; rays.len()];
    let (l_ones, g_ones) = run(lam, Some(&ones), &mut Workspace::default());
    // One ray spared, one at half weight (the trainer gives 0 or 1; the loss is linear in them).
    let spared: Vec<f32> = (0..rays.len())
        .map(|i| [1.0, 0.0, 0.5, 1.0][i % 4])
        .collect();
    for mask_weights in [None, Some(&spared[..])] {
        let mut ws = Workspace::default();
        let (l_on, g_on) = run(lam, mask_weights, &mut ws);
        if mask_weights.is_none() {
            assert_eq!(l_on, l_ones);
            assert_eq!(g_on, g_ones);
        }
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
        let nf = w.len() / rays.len();
        let enc = &layout.field.encoding;
        let scale = 1.0 / rays.len() as f64;
        let ray_factor = |j: usize| mask_weights.map_or(1.0, |mw| mw[j / nf] as f64);
        let term = |q: &[f32]| -> f64 {
            (0..w.len())
                .map(|j| {
                    let m = enc.mask_at(q, &pts[j * stride..j * stride + 3]) as f64;
                    ray_factor(j) * w[j] as f64 * (1.0 - m)
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
        fd.largest(&p, mask.clone(), |i| (g_on[i] - g_off[i]) as f64, term);
    }
}

/// The free-space loss: its value is the opacity over `FREE_SPACE_STEP` of the diagonal at
/// points drawn after the forward pass (so the image terms are unchanged), its gradient matches
/// finite differences, it reaches only the main field, and weight 0 is the plain step.
#[test]
fn free_space_loss_matches_finite_differences() {
    let cfg = tiny_cfg();
    let layout = ModelLayout::new(&cfg);
    let mut p = perturbed_params(&layout);
    // Density well inside the loss's range: raise the density MLP's output so that
    // sigma * delta is of order one at the random points.
    for v in &mut p[layout.field.density.1.clone()] {
        *v *= 3.0;
    }
    let (rays, tg) = rays();
    let lam = 0.7f32;
    let run = |q: &[f32], lam: f32| {
        let mut step = full_step(rays.len(), 0.0);
        step.free_space_weight = lam;
        chunk(&cfg, &layout, q, (&rays, &tg), &step)
    };
    let (l_on, g_on) = run(&p, lam);
    let (l_off, g_off) = run(&p, 0.0);
    assert_eq!(l_off.free_space, 0.0);
    assert_eq!(l_on.sq_err, l_off.sq_err);
    assert_eq!(l_on.interlevel, l_off.interlevel);
    assert!(
        l_on.free_space > 1e-3 * lam as f64 * rays.len() as f64,
        "the points must see density: {}",
        l_on.free_space
    );
    for e in &layout.params.entries {
        if !e.name.starts_with("field") {
            for i in e.range() {
                assert_eq!(g_on[i], g_off[i], "{} moved", e.name);
            }
        }
    }
    let scale = 1.0 / rays.len() as f64;
    let term = |q: &[f32]| run(q, lam).0.free_space * scale;
    let fd = FdCheck {
        count: 6,
        h: 1e-2,
        tol_abs: 1e-6,
        tol_rel: 2e-2,
        min_grad: 1e-5,
    };
    for name in ["field.h3", "field.h4", "field.density_mlp", "field.mask"] {
        let e = layout.params.get(name).unwrap();
        fd.largest(&p, e.range(), |i| (g_on[i] - g_off[i]) as f64, term);
    }
}

/// Coarse-to-fine (`StepSettings::active_levels`): at 1.5 of the tiny model's 2 levels the
/// gradient matches finite differences; at 1.0 the finer level's table rows get no gradient;
/// at the level count the step is the plain one, bit for bit.
#[test]
fn level_ramp_matches_finite_differences() {
    let cfg = tiny_cfg();
    let layout = ModelLayout::new(&cfg);
    let p = perturbed_params(&layout);
    let (rays, tg) = rays();
    let run = |q: &[f32], active: Option<f32>| {
        let mut step = full_step(rays.len(), 0.0);
        step.active_levels = active;
        chunk(&cfg, &layout, q, (&rays, &tg), &step)
    };
    let levels = cfg.field.encoding.grid3.levels;
    assert_eq!(levels, 2);
    let (l_plain, g_plain) = run(&p, None);
    let (l_all, g_all) = run(&p, Some(levels as f32));
    assert_eq!(l_plain, l_all);
    assert_eq!(g_plain, g_all);
    // The finer level's rows of both grids: no gradient with one level on.
    let (_, g_one) = run(&p, Some(1.0));
    for (name, grid) in [
        ("field.h3", &layout.field.encoding.h3),
        ("field.h4", &layout.field.encoding.h4),
    ] {
        let (g, _) = grid.as_ref().unwrap();
        let e = layout.params.get(name).unwrap();
        let fine = &g.levels[1];
        let rows = e.offset + fine.offset..e.offset + fine.offset + fine.rows * g.features;
        assert!(
            g_one[rows.clone()].iter().all(|&v| v == 0.0),
            "{name}: level 1 moved"
        );
        assert!(
            g_plain[rows].iter().any(|&v| v != 0.0),
            "{name}: level 1 unused"
        );
    }
    let (l_half, g_half) = run(&p, Some(1.5));
    assert_ne!(l_half.sq_err, l_plain.sq_err);
    let scale = 1.0 / rays.len() as f64;
    let dw = full_step(rays.len(), 0.0).distortion_weight as f64;
    let loss = |q: &[f32]| {
        let l = run(q, Some(1.5)).0;
        (l.sq_err + dw * l.distortion) * scale
    };
    let fd = FdCheck {
        count: 5,
        h: 2e-3,
        tol_abs: 1e-4,
        tol_rel: 5e-2,
        min_grad: 1e-6,
    };
    for name in ["field.h3", "field.h4", "field.density_mlp", "field.mask"] {
        let e = layout.params.get(name).unwrap();
        fd.largest(&p, e.range(), |i| g_half[i] as f64, loss);
    }
}

/// The proposal's levels under nested dropout (`StepSettings::proposal_levels`): with one level
/// on, its finer level's rows get no gradient and the proposal's samples move (the loss
/// changes); at the level count the step is the plain one, bit for bit. (The proposal's gradient
/// cannot be checked against finite differences through the whole step, which resamples from
/// it; the ramp's forward and backward are the encoding's, checked on the main field above.)
#[test]
fn proposal_level_ramp_turns_the_finer_proposal_levels_off() {
    let cfg = tiny_cfg();
    let layout = ModelLayout::new(&cfg);
    let p = perturbed_params(&layout);
    let (rays, tg) = rays();
    let run = |q: &[f32], active: Option<f32>| {
        let mut step = full_step(rays.len(), 0.0);
        step.proposal_levels = active;
        chunk(&cfg, &layout, q, (&rays, &tg), &step)
    };
    let levels = cfg.proposal.encoding.grid3.levels;
    assert!(levels >= 2);
    let (l_plain, g_plain) = run(&p, None);
    let (l_all, g_all) = run(&p, Some(levels as f32));
    assert_eq!(l_plain, l_all);
    assert_eq!(g_plain, g_all);
    let (l_one, g_one) = run(&p, Some(1.0));
    assert_ne!(l_one.interlevel, l_plain.interlevel);
    for name in ["proposal.h3", "proposal.h4"] {
        let grid = if name.ends_with("h3") {
            &layout.proposal.field.encoding.h3
        } else {
            &layout.proposal.field.encoding.h4
        };
        let (g, _) = grid.as_ref().unwrap();
        let e = layout.params.get(name).unwrap();
        let fine = &g.levels[1];
        let rows = e.offset + fine.offset..e.offset + fine.offset + fine.rows * g.features;
        assert!(g_one[rows.clone()].iter().all(|&v| v == 0.0), "{name}");
        assert!(g_plain[rows].iter().any(|&v| v != 0.0), "{name}");
    }
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
        free_space_weight: 0.0,
        active_levels: None,
        proposal_levels: None,
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
        let part = playback_partition(&cfg, &layout, &p, &[*r], &[r.time], nf, None, &mut ws);
        assert_eq!(part.samples, nf);
        assert_eq!(part.deltas, deltas[..nf]);
        for k in 0..nf {
            assert_eq!(part.points[k * 4..k * 4 + 3], rendered[k * 4..k * 4 + 3]);
            assert_eq!(part.points[k * 4 + 3], 0.0);
        }
        // Weights combine by their maximum: a repeated time changes nothing.
        let twice = playback_partition(&cfg, &layout, &p, &[*r], &[r.time; 2], nf, None, &mut ws);
        assert_eq!(twice, part);
        let other = (r.time + 0.5) % 1.0;
        let both = playback_partition(
            &cfg,
            &layout,
            &p,
            &[*r],
            &[r.time, other],
            nf,
            None,
            &mut ws,
        );
        assert!(both.points.iter().all(|v| v.is_finite()));
        assert!(both.deltas.iter().all(|&d| d >= 0.0));
    }
}

#[test]
fn a_partition_skipping_proposal_samples_moves_the_samples_to_kept_space() {
    let cfg = tiny_cfg();
    let layout = ModelLayout::new(&cfg);
    let p = perturbed_params(&layout);
    let (rays, _) = rays();
    let nf = cfg.sampler.num_samples;
    let mut ws = Workspace::default();
    let t = [0.3];
    let all = playback_partition(&cfg, &layout, &p, &rays, &t, nf, None, &mut ws);
    // Keeping every point is the plain partition, exactly.
    let keep_all = |_: [f32; 3]| true;
    let same = playback_partition(&cfg, &layout, &p, &rays, &t, nf, Some(&keep_all), &mut ws);
    assert_eq!(same, all);
    // Keeping the far half of the box (unit z < 0.5; the rays travel along -z): the proposal
    // sees density only there, so the samples move there (up to the histogram's padding).
    let far_half = |q: [f32; 3]| q[2] < 0.5;
    let moved = playback_partition(&cfg, &layout, &p, &rays, &t, nf, Some(&far_half), &mut ws);
    let in_far = |part: &Partition| {
        (0..rays.len() * nf)
            .filter(|k| part.points[k * 4 + 2] < 0.5)
            .count()
    };
    let (before, after) = (in_far(&all), in_far(&moved));
    assert!(
        after > before && after >= rays.len() * nf * 3 / 4,
        "{before} -> {after} of {} samples in the kept half",
        rays.len() * nf
    );
    assert!(moved.deltas.iter().all(|&d| d.is_finite() && d >= 0.0));
}

/// Rendering resamples with [`render_histogram_padding`] whatever the model was trained with,
/// and a training step with the model's own padding: a model with 0.01 renders the samples and
/// colours of the same model with [`RENDER_HISTOGRAM_PADDING`], while its training step (and a
/// resampling at 0.01) places them elsewhere.
#[test]
fn rendering_resamples_with_the_render_padding_and_training_with_its_own() {
    let mut cfg = tiny_cfg();
    cfg.sampler.histogram_padding = 0.01;
    let mut low = cfg.clone();
    low.sampler.histogram_padding = RENDER_HISTOGRAM_PADDING;
    assert_eq!(
        render_histogram_padding(&cfg.sampler),
        RENDER_HISTOGRAM_PADDING
    );
    let mut none = cfg.clone();
    none.sampler.histogram_padding = 0.0;
    assert_eq!(render_histogram_padding(&none.sampler), 0.0);
    let layout = ModelLayout::new(&cfg);
    let p = perturbed_params(&layout);
    let (rays, tg) = rays();
    let render = |c: &ModelConfig| {
        let mut ws = Workspace::default();
        let mut out = RenderOutput::default();
        render_chunk(c, &layout, &p, &rays, &mut ws, &mut out);
        (ws.pts_main.clone(), out.rgb)
    };
    assert_eq!(render(&cfg), render(&low));
    // The padding moves the samples of these rays: at the model's own 0.01 they lie elsewhere.
    let mut ws = Workspace::default();
    forward_chunk(&cfg, &layout, &p, &rays, 1.0, 0.01, None, &mut ws);
    assert_ne!(ws.pts_main, render(&cfg).0);
    // Training keeps the model's own padding.
    let step = full_step(rays.len(), 0.0);
    let (_, g_own) = chunk(&cfg, &layout, &p, (&rays, &tg), &step);
    let (_, g_low) = chunk(&low, &layout, &p, (&rays, &tg), &step);
    assert_ne!(g_own, g_low);
}

/// The export's pass over what the cameras see ([`weighted_samples`]) samples with the model's
/// own padding, not the render padding (its doc says why): its intervals are those of a
/// resampling at the model's 0.01.
#[test]
fn weighted_samples_sample_with_the_models_own_padding() {
    let mut cfg = tiny_cfg();
    cfg.sampler.histogram_padding = 0.01;
    let layout = ModelLayout::new(&cfg);
    let p = perturbed_params(&layout);
    let (rays, _) = rays();
    let nf = cfg.sampler.num_samples;
    let mut got = Vec::new();
    weighted_samples(
        &cfg,
        &layout,
        &p,
        &rays,
        0.0,
        &mut Workspace::default(),
        |s| got.push((s.ray, s.t)),
    );
    let interval = |padding: f32| {
        let mut ws = Workspace::default();
        forward_chunk(&cfg, &layout, &p, &rays, 1.0, padding, None, &mut ws);
        (0..rays.len())
            .flat_map(|i| (0..nf).map(move |k| (i, k)))
            .map(|(i, k)| {
                let e = &ws.t_main[i * (nf + 1)..(i + 1) * (nf + 1)];
                (i, [e[k], e[k + 1]])
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(got, interval(0.01));
    assert_ne!(got, interval(RENDER_HISTOGRAM_PADDING));
}
