//! The volume's bake and march against the exact field.

use glam::Vec3;

use super::bake::{
    bake, bake_slice, plan, plan_with, BakeError, BakeProgress, Occupancy, PlanOptions,
};
use super::march::{
    inner_segment, march_chunk, unit_velocity, ColourMode, MarchOutput, MarchSettings,
};
use super::*;
use crate::config::{Background, BlendMode, ModelConfig};
use crate::field::{FieldScratch, ModelLayout};
use crate::pipeline::TimedRay;
use crate::scene::SceneBounds;
use crate::Camera;

/// A small `mt` model over the D-NeRF box with its mask logit set to `mask_logit` everywhere.
fn model(mask_logit: f32, seed: u64) -> (ModelConfig, ModelLayout, Vec<f32>) {
    let mut cfg = ModelConfig::fast_on_white(8);
    cfg.field.encoding.resize(4, 10, 32.0, 8);
    cfg.proposal.encoding.resize(3, 10, 16.0, 8);
    let layout = ModelLayout::new(&cfg);
    let mut params = layout.init_params(seed);
    let mut rng = crate::rng::Rng::new(seed + 1);
    for e in &layout.params.entries {
        if e.name.ends_with("h3") || e.name.ends_with("h4") {
            for v in &mut params[e.range()] {
                *v = rng.range_f32(-0.5, 0.5);
            }
        }
    }
    let (_, r) = layout.field.encoding.mask.clone().expect("mask");
    params[r].fill(mask_logit);
    (cfg, layout, params)
}

fn camera(w: u32, h: u32) -> Camera {
    Camera::look_at(w, h, 0.8, Vec3::new(0.3, -4.0, 1.2), Vec3::ZERO, Vec3::Z)
}

fn rays(cam: &Camera, time: f32) -> Vec<TimedRay> {
    let mut v = Vec::new();
    for y in 0..cam.height {
        for x in 0..cam.width {
            v.push(TimedRay::through_pixel(cam, x, y, time));
        }
    }
    v
}

fn march(
    vol: &Volume,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    s: &MarchSettings,
) -> MarchOutput {
    let mut ws = Default::default();
    let mut out = MarchOutput::default();
    march_chunk(vol, cfg, layout, params, rays, s, &mut ws, &mut out);
    out
}

#[test]
fn geometry_keeps_the_index_within_its_bound() {
    let g = VolumeGeometry::new(512);
    assert_eq!((g.resolution, g.brick, g.bricks_per_side()), (512, 4, 128));
    let g = VolumeGeometry::new(1024);
    assert_eq!((g.resolution, g.brick, g.bricks_per_side()), (1024, 8, 128));
    let g = VolumeGeometry::new(2048);
    assert_eq!(
        (g.resolution, g.brick, g.bricks_per_side()),
        (2048, 16, 128)
    );
    assert_eq!(g.flag_words(), 16 * 16 * 16 / 32);
    let g = VolumeGeometry::new(100);
    assert_eq!((g.resolution, g.brick), (128, 4));
    let g = VolumeGeometry::new(1);
    assert_eq!(g.resolution, MIN_VOLUME_RESOLUTION);
    assert_eq!(
        VolumeGeometry::new(u32::MAX).resolution,
        MAX_VOLUME_RESOLUTION
    );
    assert_eq!(channels_for(ColourMode::PerSample, 15), 16);
    assert_eq!(channels_for(ColourMode::Baked, 15), 4);
    assert_eq!(channels_for(ColourMode::Deferred, 16), 24);
}

fn options(colour: ColourMode) -> PlanOptions {
    PlanOptions {
        budget: 64 << 20,
        max_resolution: Some(32),
        colour,
        eyes: vec![Vec3::new(0.3, -4.0, 1.2), Vec3::new(-2.0, -3.0, 1.0)],
        ..Default::default()
    }
}

/// Each stored vertex is the density MLP's output for the static encoding at that vertex (features), or its density and the colour MLP's output for the reference
/// direction (baked colour); a dynamic brick's slice holds the field at the slice's time.
#[test]
fn baked_vertices_hold_the_field() {
    for colour in [ColourMode::PerSample, ColourMode::Baked] {
        for logit in [6.0, -3.0] {
            baked_vertices_hold_the_field_in(colour, logit);
        }
    }
}

fn baked_vertices_hold_the_field_in(colour: ColourMode, logit: f32) {
    let (cfg, layout, params) = model(logit, 1);
    let opts = options(colour);
    let p = plan_with(&cfg, &layout, &params, None, &opts).unwrap();
    assert_eq!(p.geometry.resolution, 32);
    let mut vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    let dynamic = logit < 0.0;
    assert_eq!(
        p.dynamic_bricks.is_empty(),
        !dynamic,
        "m = sigmoid({logit})"
    );
    let k = 3;
    let time = p.slice_times.get(k).copied().unwrap_or(0.0);
    if dynamic {
        assert_eq!(p.slice_times.len(), cfg.num_frames);
        bake_slice(&mut vol, &p, k, &cfg, &layout, &params).unwrap();
    }
    let g = vol.geometry;
    let mut s = FieldScratch::default();
    s.enc.static_cutoff = VOLUME_STATIC_CUTOFF;
    let (dm, _) = &layout.field.density;
    let mut checked = 0;
    for (brick, &entry) in vol.index.iter().enumerate() {
        if entry == EMPTY_BRICK || brick % 7 != 0 {
            continue;
        }
        let (values, slot) = if entry & DYNAMIC_BRICK != 0 {
            let slice = vol.dynamic.slices[k].as_ref().unwrap();
            (&slice.values, (entry & !DYNAMIC_BRICK) as usize)
        } else {
            (&vol.values, entry as usize)
        };
        let i = g.bricks_per_side() as usize;
        let (bx, by, bz) = (brick % i, (brick / i) % i, brick / (i * i));
        let v1 = g.brick as usize + 1;
        // Owned vertices and border vertices (copied from their owners or evaluated).
        for v in [0, 1, v1 + 2, v1 * v1 - 1, g.vertices_per_brick() - 1] {
            let (x, y, z) = (v % v1, (v / v1) % v1, v / (v1 * v1));
            let b = g.brick as usize;
            let u = [
                (bx * b + x) as f32 / g.resolution as f32,
                (by * b + y) as f32 / g.resolution as f32,
                (bz * b + z) as f32 / g.resolution as f32,
            ];
            layout
                .field
                .forward_density(&params, &[u[0], u[1], u[2], time], 1, &mut s);
            let mut exact = dm.output(&s.density_acts).to_vec();
            if colour == ColourMode::Baked {
                let x = cfg.bounds.from_unit(Vec3::from(u));
                let d = reference_direction(&opts.eyes, x);
                let mut input = vec![0f32; crate::sh::SH_COEFFS];
                crate::sh::sh4([d.x, d.y, d.z], &mut input);
                input.extend_from_slice(&exact[1..]);
                let (cm, cr) = &layout.field.color;
                let c = cm.forward_reference(&params[cr.clone()], &input);
                exact = vec![exact[0]];
                exact.extend(c.iter().map(|&v| crate::activation::sigmoid(v)));
            }
            let base = (slot * g.vertices_per_brick() + v) * vol.channels;
            for c in 0..=vol.payload() {
                let stored = values[base + c].to_f32();
                // The field's value rounded to binary16 (half a unit in the last place, 2^-11
                // relative), after a computation that agrees to 1e-5.
                let tol = 1e-5 * exact[c].abs().max(1.0) + exact[c].abs() * 2f32.powi(-11);
                assert!(
                    (stored - exact[c]).abs() <= tol,
                    "{colour:?} vertex {u:?} channel {c}: stored {stored} exact {}",
                    exact[c]
                );
            }
            checked += 1;
        }
    }
    assert!(checked > 10);
}

#[test]
fn a_dynamic_mask_makes_every_brick_dynamic() {
    let (cfg, layout, params) = model(-2.0, 2);
    let p = plan(&cfg, &layout, &params, None, 64 << 20, Some(32)).unwrap();
    assert!(p.static_bricks.is_empty());
    assert_eq!(p.dynamic_bricks.len(), 8 * 8 * 8);
    let vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    assert_eq!(vol.stats.dynamic_cells, 32 * 32 * 32);
    assert_eq!(vol.dynamic.times.len(), cfg.num_frames);
    assert!(!vol.dynamic.ready_for(0.5));
    assert_eq!(
        vol.dynamic.missing_for(0.5).len(),
        2,
        "0.5 lies between frames"
    );
    assert_eq!(
        vol.dynamic.missing_for(3.0 / 7.0),
        vec![3],
        "a frame's own time"
    );
}

#[test]
fn slices_around_a_time() {
    let d = DynamicPart {
        times: (0..5).map(|k| k as f32 / 4.0).collect(),
        ..Default::default()
    };
    assert_eq!(d.around(0.0), Some((0, 0, 0.0)));
    assert_eq!(d.around(1.0), Some((4, 4, 0.0)));
    assert_eq!(d.around(0.5), Some((2, 2, 0.0)));
    let (a, b, f) = d.around(0.3).unwrap();
    assert_eq!((a, b), (1, 2));
    assert!((f - 0.2).abs() < 1e-5);
    assert_eq!(
        d.around(f32::NAN),
        Some((0, 0, 0.0)),
        "NaN times count as 0"
    );
    assert_eq!(DynamicPart::default().around(0.5), None);
}

#[test]
fn the_budget_picks_a_coarser_volume_and_refuses_below_the_coarsest() {
    let (cfg, layout, params) = model(6.0, 3);
    let full = plan(&cfg, &layout, &params, None, 1 << 40, Some(128)).unwrap();
    assert_eq!(full.geometry.resolution, 128);
    assert!(full.note().is_none());
    let small = plan(
        &cfg,
        &layout,
        &params,
        None,
        full.bytes_bound / 4,
        Some(128),
    )
    .unwrap();
    assert!(small.geometry.resolution < 128);
    assert!(small.bytes_bound <= full.bytes_bound / 4);
    assert!(small
        .note()
        .unwrap()
        .contains("instead of 128^3, which would not fit"));
    match plan(&cfg, &layout, &params, None, 1000, Some(128)) {
        Err(BakeError::OverBudget { resolution, .. }) => {
            assert_eq!(resolution, MIN_VOLUME_RESOLUTION)
        }
        other => panic!("{other:?}"),
    }
}

/// Where the model's resolution does not fit over every brick, the bricks no camera looks into
/// are left out first, and only then (or when told to keep them) is the volume coarser.
#[test]
fn bricks_outside_the_views_go_before_the_resolution() {
    let (cfg, layout, params) = model(6.0, 3);
    // A narrow view (0.3 rad) into the box.
    let cam = Camera::look_at(64, 48, 0.3, Vec3::new(0.3, -4.0, 1.2), Vec3::ZERO, Vec3::Z);
    let with_views = |budget: u64, outside: OutsideViews| {
        plan_with(
            &cfg,
            &layout,
            &params,
            None,
            &PlanOptions {
                budget,
                max_resolution: Some(128),
                views: vec![cam],
                outside,
                ..Default::default()
            },
        )
        .unwrap()
    };
    let full = with_views(1 << 40, OutsideViews::Auto);
    assert_eq!((full.geometry.resolution, full.outside_views), (128, 0));
    let bake = with_views(1 << 40, OutsideViews::Bake);
    assert_eq!(
        (&full.static_bricks, &full.dynamic_bricks, full.geometry),
        (&bake.static_bricks, &bake.dynamic_bricks, bake.geometry)
    );
    let all = full.static_bricks.len() + full.dynamic_bricks.len();
    // Half of the full volume's bytes: the view of one camera holds less than that.
    let half = full.bytes_bound / 2;
    let seen = with_views(half, OutsideViews::Auto);
    assert_eq!(seen.geometry.resolution, 128);
    let kept = seen.static_bricks.len() + seen.dynamic_bricks.len();
    assert!(kept + seen.outside_views == all && seen.outside_views > 0);
    assert!(seen.bytes_bound <= half);
    assert!(seen
        .note()
        .unwrap()
        .contains("none of the file's cameras looks into"));
    let in_view = views::bricks_in_view(&seen.geometry, &cfg.bounds, &[cam]);
    for b in seen.static_bricks.iter().chain(&seen.dynamic_bricks) {
        assert!(in_view[*b as usize]);
    }
    let coarser = with_views(half, OutsideViews::Bake);
    assert!(coarser.geometry.resolution < 128 && coarser.outside_views == 0);
    // `Exact` leaves them out whatever the budget: the bricks of the budget-bound plan.
    let exact = with_views(1 << 40, OutsideViews::Exact);
    assert_eq!(exact.geometry.resolution, 128);
    assert_eq!(
        (
            &exact.static_bricks,
            &exact.dynamic_bricks,
            &exact.outside_bricks
        ),
        (
            &seen.static_bricks,
            &seen.dynamic_bricks,
            &seen.outside_bricks
        )
    );
    assert!(exact.note().unwrap().contains("--volume-outside exact"));
}

#[test]
fn the_budget_holds_fewer_slices_before_a_coarser_volume() {
    let (cfg, layout, params) = model(-2.0, 3);
    let all = plan(&cfg, &layout, &params, None, 1 << 40, Some(32)).unwrap();
    assert_eq!(all.resident_slices, cfg.num_frames);
    let per_slice = all.dynamic_bricks.len() as u64 * all.geometry.slot_bytes(all.channels);
    let fixed = all.bytes_bound - cfg.num_frames as u64 * per_slice;
    let three = plan(
        &cfg,
        &layout,
        &params,
        None,
        fixed + 3 * per_slice,
        Some(32),
    )
    .unwrap();
    assert_eq!(three.geometry.resolution, 32);
    assert_eq!(three.resident_slices, 3);
    assert!(three
        .note()
        .unwrap()
        .contains("3 of the dynamic part's 8 time slices"));
    let (mut vol, p) = (
        bake(&three, &cfg, &layout, &params, &BakeProgress::default()).unwrap(),
        three,
    );
    for k in 0..cfg.num_frames {
        bake_slice(&mut vol, &p, k, &cfg, &layout, &params).unwrap();
        assert!(vol.dynamic.baked() <= 3);
        assert!(vol.dynamic.slices[k].is_some());
    }
    assert!(vol.bytes() <= p.bytes_bound);
}

#[test]
fn the_occupancy_grid_limits_the_bricks() {
    let (cfg, layout, params) = model(6.0, 4);
    // One occupied cell of an 8^3 grid: the bricks of a 32^3 volume inside it.
    let mut words = vec![0u32; 512 / 32];
    let cell = 3 + 8 * (4 + 8 * 5);
    words[cell / 32] |= 1 << (cell % 32);
    let occ = Occupancy {
        resolution: 8,
        words: &words,
        density_threshold: 1e-3,
    };
    let p = plan(&cfg, &layout, &params, Some(occ), 64 << 20, Some(32)).unwrap();
    assert_eq!(
        p.static_bricks.len(),
        1,
        "a 4-cell brick of 32^3 is one cell of 8^3"
    );
    let vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    assert!(vol.stats.bricks <= 1);
    // No grid cell occupied: nothing to bake, every ray shows the background.
    let none = vec![0u32; 512 / 32];
    let occ = Occupancy {
        resolution: 8,
        words: &none,
        density_threshold: 1e-3,
    };
    let p = plan(&cfg, &layout, &params, Some(occ), 64 << 20, Some(32)).unwrap();
    let vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    assert_eq!(vol.stats.bricks, 0);
    let cam = camera(8, 6);
    let out = march(
        &vol,
        &cfg,
        &layout,
        &params,
        &rays(&cam, 0.0),
        &MarchSettings::default(),
    );
    let Background::Color { rgb } = cfg.background else {
        panic!("white background")
    };
    for c in &out.rgb {
        assert_eq!(*c, rgb);
    }
    assert_eq!(out.samples, 0);
}

/// The finest volume, `2048^3` in bricks of `16^3` cells: its vertices hold the field, and rays
/// through it draw what they draw through a `1024^3` volume (bricks of `8^3`) of the same region.
#[test]
fn the_finest_volume_has_bricks_of_16_cells() {
    let (cfg, layout, params) = model(6.0, 5);
    // One occupied cell of a 64^3 grid: 32 cells of 2048^3 a side, 2^3 bricks.
    let mut words = vec![0u32; 64 * 64 * 64 / 32];
    let cell = 32 + 64 * (32 + 64 * 32);
    words[cell / 32] |= 1 << (cell % 32);
    let occupancy = || Occupancy {
        resolution: 64,
        words: &words,
        density_threshold: 1e-3,
    };
    // Every cell the grid keeps is baked (no proposal test: this model's proposal is untrained).
    let at = |max_resolution| {
        let o = PlanOptions {
            budget: 64 << 20,
            max_resolution: Some(max_resolution),
            min_proposal_alpha: 0.0,
            ..Default::default()
        };
        plan_with(&cfg, &layout, &params, Some(occupancy()), &o).unwrap()
    };
    let fine = at(4096);
    assert_eq!((fine.geometry.resolution, fine.geometry.brick), (2048, 16));
    assert_eq!(fine.static_bricks.len(), 8);
    let coarse = at(1024);
    assert_eq!(
        (coarse.geometry.resolution, coarse.geometry.brick),
        (1024, 8)
    );
    let fine = bake(&fine, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    let coarse = bake(&coarse, &cfg, &layout, &params, &BakeProgress::default()).unwrap();

    // Vertex (16, 16, 16) of the first brick is the far corner of a 17^3 slot.
    let g = fine.geometry;
    let first = fine.index.iter().position(|&e| e != EMPTY_BRICK).unwrap();
    let i = g.bricks_per_side() as usize;
    let corner = [first % i, (first / i) % i, first / (i * i)].map(|b| (b + 1) * 16);
    let u = corner.map(|c| c as f32 / 2048.0);
    let mut s = FieldScratch::default();
    s.enc.static_cutoff = VOLUME_STATIC_CUTOFF;
    layout
        .field
        .forward_density(&params, &[u[0], u[1], u[2], 0.0], 1, &mut s);
    let exact = layout.field.density.0.output(&s.density_acts)[0];
    let slot = fine.index[first] as usize;
    let stored = fine.values[(slot * g.vertices_per_brick() + 17 * 17 * 17 - 1) * fine.channels];
    let tol = 1e-5 * exact.abs().max(1.0) + exact.abs() * 2f32.powi(-11);
    assert!(
        (stored.to_f32() - exact).abs() <= tol,
        "{stored} against {exact}"
    );

    // A narrow camera whose rays all cross the occupied cell.
    let target = cfg.bounds.from_unit(Vec3::splat(32.5 / 64.0));
    let cam = Camera::look_at(8, 8, 0.004, Vec3::new(0.3, -4.0, 1.2), target, Vec3::Z);
    let rs = rays(&cam, 0.0);
    let a = march(
        &fine,
        &cfg,
        &layout,
        &params,
        &rs,
        &MarchSettings::default(),
    );
    let b = march(
        &coarse,
        &cfg,
        &layout,
        &params,
        &rs,
        &MarchSettings::default(),
    );
    assert!(a.samples > 0 && b.samples > 0);
    // What the cell adds to the white background, and how far the two volumes differ.
    let (mut signal, mut worst) = (0f32, 0f32);
    for (p, q) in a.rgb.iter().zip(&b.rgb) {
        for k in 0..3 {
            signal = signal.max(1.0 - p[k]);
            worst = worst.max((p[k] - q[k]).abs());
        }
    }
    assert!(signal > 0.01, "the rays cross the cell: {signal}");
    assert!(
        worst < 0.1 * signal,
        "2048^3 and 1024^3 differ by {worst}, the cell draws {signal}"
    );
}

#[test]
fn a_malformed_occupancy_grid_is_refused() {
    let (cfg, layout, params) = model(6.0, 5);
    let words = vec![0u32; 3];
    let occ = Occupancy {
        resolution: 8,
        words: &words,
        density_threshold: 1e-3,
    };
    assert!(matches!(
        plan(&cfg, &layout, &params, Some(occ), 64 << 20, Some(32)),
        Err(BakeError::BadOccupancy(_))
    ));
}

#[test]
fn non_finite_parameters_end_the_bake_with_an_error() {
    for logit in [6.0, -3.0] {
        let (cfg, layout, mut params) = model(logit, 6);
        let p = plan(&cfg, &layout, &params, None, 64 << 20, Some(32)).unwrap();
        let (_, r) = layout.field.density.clone();
        params[r].fill(f32::NAN);
        let mut vol = Volume::allocate(&p);
        let baked = bake(&p, &cfg, &layout, &params, &BakeProgress::default());
        if p.static_bricks.is_empty() {
            assert!(baked.is_ok());
            assert!(matches!(
                bake_slice(&mut vol, &p, 0, &cfg, &layout, &params),
                Err(BakeError::NotFinite(_))
            ));
        } else {
            assert!(matches!(baked, Err(BakeError::NotFinite(_))));
        }
    }
}

#[test]
fn a_model_without_a_static_part_has_no_volume() {
    for blend in [BlendMode::FourD, BlendMode::Add] {
        let (mut cfg, _, _) = model(6.0, 7);
        cfg.field.encoding.blend = blend;
        let layout = ModelLayout::new(&cfg);
        let params = layout.init_params(1);
        assert_eq!(
            plan(&cfg, &layout, &params, None, 64 << 20, None),
            Err(BakeError::NoStaticPart(blend))
        );
    }
}

#[test]
fn a_cancelled_bake_stops() {
    let (cfg, layout, params) = model(6.0, 8);
    let p = plan(&cfg, &layout, &params, None, 64 << 20, Some(32)).unwrap();
    let progress = BakeProgress::default();
    progress.cancel();
    assert_eq!(
        bake(&p, &cfg, &layout, &params, &progress),
        Err(BakeError::Cancelled)
    );
}

/// The unit-cube velocity is the derivative of `to_unit` along the ray, inside the contraction
/// and beyond it.
#[test]
fn unit_velocity_is_the_derivative_of_the_unit_map() {
    let bounds = [
        SceneBounds::Box {
            min: Vec3::new(-1.0, -2.0, 0.0),
            max: Vec3::new(2.0, 1.0, 1.5),
        },
        SceneBounds::Contracted {
            center: Vec3::new(0.1, 0.2, 0.3),
            radius: 2.0,
        },
    ];
    let dirs = [
        Vec3::new(0.3, -0.8, 0.2).normalize(),
        Vec3::new(-0.9, 0.1, 0.4).normalize(),
    ];
    let points = [
        Vec3::new(0.2, 0.1, 0.5),
        Vec3::new(3.0, -1.0, 0.5),
        Vec3::new(-0.5, 9.0, 4.0),
        Vec3::new(30.0, 2.0, -40.0),
    ];
    for b in bounds {
        for d in dirs {
            for x in points {
                if let SceneBounds::Box { min, max } = b {
                    if x.cmplt(min).any() || x.cmpgt(max).any() {
                        continue;
                    }
                }
                let v = unit_velocity(&b, x, d);
                let h = 1e-3 * (1.0 + x.length());
                let fd = (b.to_unit(x + d * h) - b.to_unit(x - d * h)) / (2.0 * h);
                assert!(
                    (v - fd).length() <= 2e-2 * fd.length().max(1e-4),
                    "{b:?} at {x}: {v} against {fd}"
                );
            }
        }
    }
}

/// Deferred and per-sample colour agree exactly where every sample carries the same features,
/// whatever the weights: deferring only moves where the colour MLP meets the average.
#[test]
fn deferred_colour_equals_per_sample_colour_for_uniform_features() {
    let (cfg, layout, mut params) = model(6.0, 9);
    // Geometry features that are 0 everywhere (the density MLP's last layer has no weight into
    // them; the MLPs are bias-free), the density unchanged.
    let (dm, r) = layout.field.density.clone();
    let last = dm.num_layers() - 1;
    let (off, nin, nout) = (dm.offsets[last], dm.dims[last], dm.dims[last + 1]);
    for i in 0..nin {
        for o in 1..nout {
            params[r.start + off + i * nout + o] = 0.0;
        }
    }
    let bake_in = |colour| {
        let p = plan_with(&cfg, &layout, &params, None, &options(colour)).unwrap();
        bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap()
    };
    let cam = camera(12, 9);
    let rs = rays(&cam, 0.2);
    let s = MarchSettings::default();
    let deferred = march(
        &bake_in(ColourMode::Deferred),
        &cfg,
        &layout,
        &params,
        &rs,
        &s,
    );
    let per_sample = march(
        &bake_in(ColourMode::PerSample),
        &cfg,
        &layout,
        &params,
        &rs,
        &s,
    );
    assert!(deferred.samples > 0);
    for (a, b) in deferred.rgb.iter().zip(&per_sample.rgb) {
        for c in 0..3 {
            assert!((a[c] - b[c]).abs() < 1e-4, "{a:?} against {b:?}");
        }
    }
}

/// A ray that meets no dynamic cell has the same colour at every time, bit for bit, whether the
/// dynamic bricks are read from their slices or evaluated exactly; rays that meet one follow the
/// time.
#[test]
fn rays_without_dynamic_samples_do_not_depend_on_time() {
    let (cfg, layout, mut params) = model(6.0, 10);
    // Dynamic in one half of the cube (x > 0.5 of the mask grid), static elsewhere.
    let (d, r) = layout.field.encoding.mask.clone().unwrap();
    let res = d.res;
    for z in 0..res {
        for y in 0..res {
            for x in 0..res {
                if x * 2 >= res {
                    params[r.start + x + res * (y + res * z)] = -3.0;
                }
            }
        }
    }
    let p = plan(&cfg, &layout, &params, None, 64 << 20, Some(32)).unwrap();
    let mut vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    assert!(vol.stats.dynamic_cells > 0 && vol.stats.dynamic_cells < 32 * 32 * 32);
    let cam = camera(16, 12);
    let s = MarchSettings::default();
    for sliced in [false, true] {
        if sliced {
            for k in 0..p.slice_times.len() {
                bake_slice(&mut vol, &p, k, &cfg, &layout, &params).unwrap();
            }
        }
        let (t0, t1) = (0.0, 0.6);
        assert_eq!(vol.slices_for(t1).is_some(), sliced);
        let a = march(&vol, &cfg, &layout, &params, &rays(&cam, t0), &s);
        let b = march(&vol, &cfg, &layout, &params, &rays(&cam, t1), &s);
        let (mut fixed, mut moving) = (0, 0);
        for i in 0..a.rgb.len() {
            if !a.dynamic[i] && !b.dynamic[i] {
                assert_eq!(a.rgb[i], b.rgb[i]);
                fixed += 1;
            } else if a.rgb[i] != b.rgb[i] {
                moving += 1;
            }
        }
        assert!(fixed > 0, "some rays stay in the static half");
        assert!(moving > 0, "rays through the dynamic half change with time");
        assert_eq!(
            a.dynamic_samples > 0,
            !sliced,
            "exact samples only without slices"
        );
    }
}

/// The slices are the field at their times: a frame drawn from them is close to one whose
/// dynamic samples are evaluated exactly (they differ between the volume's vertices only).
#[test]
fn slices_stand_for_the_exact_dynamic_samples() {
    let (cfg, layout, params) = model(-3.0, 12);
    let p = plan(&cfg, &layout, &params, None, 64 << 20, Some(32)).unwrap();
    let mut vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    let cam = camera(16, 12);
    let t = p.slice_times[2];
    let s = MarchSettings::default();
    let exact = march(&vol, &cfg, &layout, &params, &rays(&cam, t), &s);
    bake_slice(&mut vol, &p, 2, &cfg, &layout, &params).unwrap();
    let sliced = march(&vol, &cfg, &layout, &params, &rays(&cam, t), &s);
    assert_eq!(sliced.dynamic_samples, 0);
    let mse: f32 = exact
        .rgb
        .iter()
        .zip(&sliced.rgb)
        .map(|(a, b)| (0..3).map(|c| (a[c] - b[c]).powi(2)).sum::<f32>() / 3.0)
        .sum::<f32>()
        / exact.rgb.len() as f32;
    let psnr = -10.0 * mse.max(1e-12).log10();
    assert!(psnr > 25.0, "{psnr} dB");
}

/// Rays walk in steps of the settings' size: halving the step changes a smooth field's frame
/// little (the march converges), and the samples double.
#[test]
fn finer_steps_converge() {
    let (cfg, layout, params) = model(6.0, 11);
    let p = plan(&cfg, &layout, &params, None, 64 << 20, Some(32)).unwrap();
    let vol = bake(&p, &cfg, &layout, &params, &BakeProgress::default()).unwrap();
    let cam = camera(12, 9);
    let rs = rays(&cam, 0.5);
    let run = |step: f32| {
        march(
            &vol,
            &cfg,
            &layout,
            &params,
            &rs,
            &MarchSettings {
                step,
                ..Default::default()
            },
        )
    };
    let (a, b, c) = (run(0.5), run(0.25), run(0.125));
    let diff = |x: &MarchOutput, y: &MarchOutput| {
        x.rgb
            .iter()
            .zip(&y.rgb)
            .map(|(p, q)| (0..3).map(|k| (p[k] - q[k]).abs()).fold(0f32, f32::max))
            .fold(0f32, f32::max)
    };
    assert!(b.samples > a.samples * 3 / 2);
    assert!(
        diff(&b, &c) <= diff(&a, &b) + 1e-3,
        "{} then {}",
        diff(&a, &b),
        diff(&b, &c)
    );
}

/// Inside a contracted scene's inner cube the march steps along `u0 + v t`: that is the unit
/// point and velocity the general path computes, over exactly the part of the ray inside.
#[test]
fn the_inner_cube_of_a_contracted_scene_is_affine() {
    let bounds = SceneBounds::Contracted {
        center: Vec3::new(0.2, -0.1, 0.3),
        radius: 1.5,
    };
    let (center, radius) = (Vec3::new(0.2, -0.1, 0.3), 1.5);
    let mut rng = crate::rng::Rng::new(3);
    let mut crossed = 0;
    for _ in 0..500 {
        let o = Vec3::new(
            rng.range_f32(-4.0, 4.0),
            rng.range_f32(-4.0, 4.0),
            rng.range_f32(-4.0, 4.0),
        );
        let d = Vec3::new(
            rng.range_f32(-1.0, 1.0),
            rng.range_f32(-1.0, 1.0),
            rng.range_f32(-1.0, 1.0),
        )
        .normalize();
        let ray = TimedRay {
            origin: o,
            dir: d,
            time: 0.0,
        };
        let inside = |t: f32| {
            let y = (o + d * t - center) / radius;
            y.abs().max_element() < 1.0
        };
        let Some((t0, t1, u0, v, step)) = inner_segment(center, radius, &ray, 0.01) else {
            // A miss: no point of the ray is inside.
            assert!((0..=400).all(|i| !inside(-10.0 + 0.05 * i as f32)));
            continue;
        };
        crossed += 1;
        assert!(!inside(t0 - 1e-3) && inside(t0 + 1e-3) && inside(t1 - 1e-3) && !inside(t1 + 1e-3));
        assert!((step * v.length() - 0.01).abs() < 1e-6);
        for i in 0..=10 {
            let t = t0 + (t1 - t0) * i as f32 / 10.0;
            let x = o + d * t;
            assert!((u0 + v * t - bounds.to_unit(x)).abs().max_element() < 1e-5);
            assert!((v - unit_velocity(&bounds, x, d)).abs().max_element() < 1e-6);
        }
    }
    assert!(crossed > 100, "{crossed} rays crossed the inner cube");
}
