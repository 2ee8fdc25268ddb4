//! The play-time volume (`msth_core::volume`, `msth_player::volume`) against the exact renderer,
//! on the fixture `tests/fixtures/v2.msth`: frames from file cameras and a free camera at static
//! and dynamic times, incremental frames against full ones, a budget that only a coarser volume
//! fits, and files whose bake must end in an error.
//!
//! The thresholds are PSNRs of the volume's displayed (8-bit) frames against the exact
//! renderer's. They sit below what the fixture measures (printed by each test with
//! `--nocapture`) by a margin for other CPUs' float rounding, and far above what a wrong
//! volume draws (a shifted lookup, a missing slice or a wrong colour lands below 20 dB).

use std::sync::Arc;

use glam::Vec3;
use msth_codec::{decode_all, DecodedModel};
use msth_core::camera::Camera;
use msth_core::field::ModelLayout;
use msth_core::volume::{BakeError, BakePlan, BakeProgress, OutsideViews};
use msth_player::volume::{bake, plan_bake, BakedVolume, VolumeOptions};
use msth_player::{Frame, RenderSettings, Renderer, SlicePolicy};

/// The fixture with a mask that splits the scene ([`msth_tests::split_mask_fixture`]).
fn fixture() -> DecodedModel {
    decode_all(&msth_tests::split_mask_fixture()).unwrap()
}

fn baked(d: &DecodedModel, options: &VolumeOptions) -> BakedVolume {
    let plan = plan_bake(
        &d.config,
        &d.params,
        d.occupancy.as_ref(),
        &d.cameras,
        options,
    )
    .unwrap();
    bake_planned(d, plan)
}

fn bake_planned(d: &DecodedModel, plan: BakePlan) -> BakedVolume {
    let layout = ModelLayout::new(&d.config);
    let volume = bake(
        &plan,
        &d.config,
        &layout,
        &d.params,
        &BakeProgress::default(),
    )
    .unwrap();
    BakedVolume {
        volume,
        plan: Arc::new(plan),
    }
}

/// A renderer that bakes the volume's slices before the first frame that needs them.
fn renderer(d: &DecodedModel, volume: Option<BakedVolume>, incremental: bool) -> Renderer {
    renderer_with(d, volume, incremental, SlicePolicy::Always)
}

fn renderer_with(
    d: &DecodedModel,
    volume: Option<BakedVolume>,
    incremental: bool,
    slices: SlicePolicy,
) -> Renderer {
    let mut r = Renderer::new(
        &d.config,
        RenderSettings {
            incremental,
            exact: volume.is_none(),
            slices,
            // These tests draw the volume's own incremental frames.
            volume_when_still: true,
            ..Default::default()
        },
    );
    r.set_occupancy(d.occupancy.clone().map(Arc::new));
    r.set_volume(volume);
    r
}

fn draw(r: &mut Renderer, d: &DecodedModel, camera: &Camera, time: f32) -> Frame {
    r.render_probing(camera, time, &d.params_for_time(time), &mut |t| {
        Some(d.params_for_time(t))
    })
}

/// The file's first camera and a free one beside it, looking at the same point.
fn cameras(d: &DecodedModel) -> Vec<Camera> {
    let c = d.cameras[0];
    let forward = -c.world_from_camera.z_axis.truncate();
    let up = c.world_from_camera.y_axis.truncate();
    let fov_x = 2.0 * (0.5 * c.width as f32 / c.fx).atan();
    let target = c.center() + forward * 2.0;
    let eye = c.center() + Vec3::new(0.3, 0.15, -0.2);
    let free = Camera::look_at(c.width, c.height, fov_x, eye, target, up);
    vec![c, free]
}

#[test]
fn volume_frames_match_exact_frames() {
    let d = fixture();
    let mut exact = renderer(&d, None, false);
    let mut volume = renderer(&d, Some(baked(&d, &VolumeOptions::default())), false);
    // The file's camera sees the colours the volume baked for it (37.1-37.8 dB measured); the
    // free camera looks from about 11 degrees away, where the baked colours miss the field's view
    // dependence (30.4-30.5 dB).
    for (camera, least) in cameras(&d).into_iter().zip([35.0, 28.0]) {
        for time in [0.0, 0.37, 0.7, 1.0] {
            let e = draw(&mut exact, &d, &camera, time);
            let v = draw(&mut volume, &d, &camera, time);
            assert!(!e.stats.volume && v.stats.volume);
            let p = v.psnr_displayed(&e);
            println!("t={time}: volume against exact {p:.2} dB");
            assert!(p >= least, "t={time}: {p:.2} dB against the exact frame");
        }
    }
}

#[test]
fn incremental_volume_frames_equal_full_frames() {
    let d = fixture();
    let vol = baked(&d, &VolumeOptions::default());
    let mut incremental = renderer(&d, Some(vol.clone()), true);
    let mut full = renderer(&d, Some(vol), false);
    let camera = d.cameras[0];
    let mut partial = 0;
    for k in 0..8 {
        let time = k as f32 / 7.0;
        let a = draw(&mut incremental, &d, &camera, time);
        let b = draw(&mut full, &d, &camera, time);
        if !a.stats.full {
            partial += 1;
            assert!(a.stats.rays_rendered < a.stats.rays_total);
        }
        assert_eq!(a.rgb, b.rgb, "t={time}: incremental frame differs");
    }
    assert_eq!(
        partial, 7,
        "every frame after the first re-renders only dynamic rays"
    );
}

#[test]
fn a_budget_too_small_for_the_fine_volume_gets_a_coarser_one() {
    let d = fixture();
    let fine = plan_bake(
        &d.config,
        &d.params,
        d.occupancy.as_ref(),
        &d.cameras,
        &VolumeOptions::default(),
    )
    .unwrap();
    // Bricks outside the cameras' views kept: the resolution is what gives.
    let options = VolumeOptions {
        budget: Some(fine.bytes_bound / 3),
        outside: OutsideViews::Bake,
        ..Default::default()
    };
    let coarse = baked(&d, &options);
    let (r0, r1) = (fine.geometry.resolution, coarse.plan.geometry.resolution);
    assert!(r1 < r0, "{r1}^3 under a third of the budget of {r0}^3");
    assert!(coarse.volume.bytes() <= options.budget.unwrap());
    let note = coarse.plan.note().expect("a coarser volume says so");
    assert!(note.contains("--volume-budget"), "{note}");
    let mut exact = renderer(&d, None, false);
    let mut volume = renderer(&d, Some(coarse), false);
    let camera = d.cameras[0];
    let p = draw(&mut volume, &d, &camera, 0.7).psnr_displayed(&draw(&mut exact, &d, &camera, 0.7));
    println!(
        "{r1}^3 (budget {} KiB): {p:.2} dB against exact",
        options.budget.unwrap() >> 10
    );
    // 34.3 dB measured at 64^3.
    assert!(p >= 30.0, "{p:.2} dB");

    // By default the bricks no camera looks into go first: a volume at least as fine, within
    // the same budget, that draws the file's own views as well.
    let seen = baked(
        &d,
        &VolumeOptions {
            outside: OutsideViews::Auto,
            ..options
        },
    );
    let r2 = seen.plan.geometry.resolution;
    assert!(r2 >= r1 && seen.volume.bytes() <= options.budget.unwrap());
    if seen.plan.outside_views > 0 {
        let note = seen.plan.note().unwrap();
        assert!(
            note.contains("none of the file's cameras looks into"),
            "{note}"
        );
    }
    let mut volume = renderer(&d, Some(seen), false);
    let q = draw(&mut volume, &d, &camera, 0.7).psnr_displayed(&draw(&mut exact, &d, &camera, 0.7));
    println!("{r2}^3 without the bricks outside the views: {q:.2} dB against exact");
    assert!(q >= p - 0.5, "{q:.2} dB against {p:.2} dB at {r1}^3");

    // Below the coarsest volume: an error naming the budget, never an allocation.
    let tiny = VolumeOptions {
        budget: Some(1024),
        ..Default::default()
    };
    match plan_bake(
        &d.config,
        &d.params,
        d.occupancy.as_ref(),
        &d.cameras,
        &tiny,
    ) {
        Err(e @ BakeError::OverBudget { .. }) => assert!(e.to_string().contains("--volume-budget")),
        other => panic!("expected OverBudget, got {other:?}"),
    }
}

/// By default ([`RenderSettings::volume_when_still`] off) the volume draws a moving camera, and a
/// camera that holds goes to the exact path's incremental cache: those frames are the exact
/// incremental renderer's, and the volume takes over again when the camera moves.
#[test]
fn a_still_camera_goes_to_the_exact_incremental_cache() {
    let d = fixture();
    let mut r = Renderer::new(
        &d.config,
        RenderSettings {
            incremental: true,
            slices: SlicePolicy::Always,
            ..Default::default()
        },
    );
    r.set_occupancy(d.occupancy.clone().map(Arc::new));
    r.set_volume(Some(baked(&d, &VolumeOptions::default())));
    let cams = cameras(&d);
    for camera in [cams[1], cams[0]] {
        assert!(
            draw(&mut r, &d, &camera, 0.2).stats.volume,
            "a moving camera"
        );
    }
    // Held from here: the exact renderer's incremental frames, from its first (full) one.
    let mut exact = renderer(&d, None, true);
    let mut partial = 0;
    for k in 0..4 {
        let time = 0.3 + 0.2 * k as f32;
        let a = draw(&mut r, &d, &cams[0], time);
        let b = draw(&mut exact, &d, &cams[0], time);
        assert!(
            !a.stats.volume,
            "t={time}: a still camera drew from the volume"
        );
        assert_eq!(a.rgb, b.rgb, "t={time}");
        partial += usize::from(!a.stats.full);
    }
    assert!(
        partial >= 2,
        "the exact cache re-rendered only dynamic rays"
    );
    assert!(draw(&mut r, &d, &cams[1], 0.5).stats.volume, "moving again");
}

/// A view a third as wide as camera `c`, from the same place.
fn narrow_view(c: &Camera) -> Camera {
    let forward = -c.world_from_camera.z_axis.truncate();
    let up = c.world_from_camera.y_axis.truncate();
    let fov_x = 2.0 * (0.5 * c.width as f32 / c.fx).atan();
    Camera::look_at(
        c.width,
        c.height,
        fov_x / 3.0,
        c.center(),
        c.center() + forward * 2.0,
        up,
    )
}

#[test]
fn rays_that_reach_bricks_left_out_are_drawn_exactly() {
    let d = fixture();
    let c = d.cameras[0];
    // The volume planned for a view a third as wide as the file's first camera, from the same
    // place: the budget holds the bricks that view sees, not every occupied brick.
    let narrow = narrow_view(&c);
    let full = plan_bake(
        &d.config,
        &d.params,
        d.occupancy.as_ref(),
        &[narrow],
        &VolumeOptions::default(),
    )
    .unwrap();
    let options = VolumeOptions {
        budget: Some(full.bytes_bound / 2),
        ..Default::default()
    };
    let plan = plan_bake(
        &d.config,
        &d.params,
        d.occupancy.as_ref(),
        &[narrow],
        &options,
    )
    .unwrap();
    assert!(plan.outside_views > 0, "the narrow view leaves bricks out");
    assert_eq!(plan.geometry.resolution, full.geometry.resolution);
    let note = plan.note().unwrap();
    assert!(note.contains("rendered exactly"), "{note}");
    let vol = bake_planned(&d, plan);
    let mut exact = renderer(&d, None, false);
    let mut volume = renderer(&d, Some(vol.clone()), false);
    let mut incremental = renderer(&d, Some(vol), true);
    // The wide camera's border rays reach the bricks left out and go to the exact path; the
    // frame matches the exact one as the full volume's does (35 dB and more).
    for time in [0.0, 0.7, 1.0] {
        let e = draw(&mut exact, &d, &c, time);
        let v = draw(&mut volume, &d, &c, time);
        let i = draw(&mut incremental, &d, &c, time);
        assert!(v.stats.volume);
        assert!(
            v.stats.rays_exact > 0 && v.stats.rays_exact < v.stats.rays_total,
            "{} of {} rays exact",
            v.stats.rays_exact,
            v.stats.rays_total
        );
        let p = v.psnr_displayed(&e);
        println!(
            "t={time}: {} of {} rays exact, {p:.2} dB against the exact frame",
            v.stats.rays_exact, v.stats.rays_total
        );
        assert!(p >= 35.0, "t={time}: {p:.2} dB");
        assert_eq!(i.rgb, v.rgb, "t={time}: incremental frame differs");
    }
}

/// `--volume-outside exact` leaves the bricks no camera looks into to the exact path even where
/// the budget holds them all, and `bake` bakes them: a view wider than the cameras' draws its
/// border from the exact renderer in the one, from colours baked for the cameras' direction in
/// the other.
#[test]
fn outside_exact_draws_beyond_the_views_as_the_exact_renderer() {
    let d = fixture();
    let c = d.cameras[0];
    let views = [narrow_view(&c)];
    let plan = |outside| {
        let options = VolumeOptions {
            outside,
            ..Default::default()
        };
        plan_bake(&d.config, &d.params, d.occupancy.as_ref(), &views, &options).unwrap()
    };
    let (auto, exact_plan, bake_plan) = (
        plan(OutsideViews::Auto),
        plan(OutsideViews::Exact),
        plan(OutsideViews::Bake),
    );
    // The default budget holds every brick: `auto` bakes them.
    assert_eq!(auto.outside_views, 0);
    assert_eq!(bake_plan.outside_views, 0);
    assert!(exact_plan.outside_views > 0);
    assert_eq!(
        exact_plan.geometry.resolution,
        bake_plan.geometry.resolution
    );
    let note = exact_plan.note().unwrap();
    assert!(note.contains("--volume-outside exact"), "{note}");
    let mut exact = renderer(&d, None, false);
    let mut left_out = renderer(&d, Some(bake_planned(&d, exact_plan)), false);
    let mut baked_all = renderer(&d, Some(bake_planned(&d, bake_plan)), false);
    for time in [0.0, 0.7] {
        let e = draw(&mut exact, &d, &c, time);
        let l = draw(&mut left_out, &d, &c, time);
        let b = draw(&mut baked_all, &d, &c, time);
        assert!(l.stats.rays_exact > 0 && l.stats.rays_exact < l.stats.rays_total);
        assert_eq!(b.stats.rays_exact, 0);
        let (pl, pb) = (l.psnr_displayed(&e), b.psnr_displayed(&e));
        println!(
            "t={time}: outside exact {pl:.2} dB ({} rays exact), outside baked {pb:.2} dB against the exact frame",
            l.stats.rays_exact
        );
        assert!(
            pl >= 35.0 && pl >= pb - 0.1,
            "t={time}: {pl:.2} against {pb:.2} dB"
        );
    }
}

#[test]
fn hostile_files_end_the_bake_with_an_error() {
    // Parameters the decoder cannot bound (its checks are structural): a NaN in the static
    // network.
    let mut d = fixture();
    let layout = ModelLayout::new(&d.config);
    // (the density network's weights: every sample is NaN).
    for x in &mut d.params[layout.field.density.1.clone()] {
        *x = f32::NAN;
    }
    let plan = plan_bake(
        &d.config,
        &d.params,
        d.occupancy.as_ref(),
        &d.cameras,
        &VolumeOptions::default(),
    )
    .unwrap();
    let r = bake(
        &plan,
        &d.config,
        &layout,
        &d.params,
        &BakeProgress::default(),
    );
    assert!(matches!(r, Err(BakeError::NotFinite(_))), "{r:?}");

    // A resolution far beyond any budget is planned down to what fits, not allocated.
    let d = fixture();
    let huge = VolumeOptions {
        max_resolution: Some(1 << 16),
        budget: Some(8 << 20),
        ..Default::default()
    };
    let plan = plan_bake(
        &d.config,
        &d.params,
        d.occupancy.as_ref(),
        &d.cameras,
        &huge,
    )
    .unwrap();
    assert!(plan.bytes_bound <= huge.budget.unwrap());
}

/// Cells where the proposal network's density stays low are left empty, more of them the higher
/// the threshold, and none without it.
#[test]
fn the_proposal_threshold_empties_cells() {
    let d = fixture();
    let occupied = |a: f32| {
        baked(
            &d,
            &VolumeOptions {
                min_proposal_alpha: a,
                ..Default::default()
            },
        )
        .volume
        .stats
        .occupied_cells
    };
    let (none, some, most) = (occupied(0.0), occupied(0.05), occupied(0.5));
    println!("occupied cells: {none} without the test, {some} at 0.05, {most} at 0.5");
    assert!(none > some && some > most, "{none} {some} {most}");
}

/// `SlicePolicy::Auto`: frames whose time moves to new slices evaluate the dynamic bricks
/// exactly and bake nothing; a held time bakes its slices once the exact evaluations spent
/// waiting for them reach a slice's cost, and from then on evaluates nothing. Incremental frames
/// still equal full ones across the switch.
#[test]
fn auto_slices_are_baked_once_a_held_time_has_paid_for_them() {
    let d = fixture();
    let vol = baked(&d, &VolumeOptions::default());
    assert!(vol.volume.has_dynamic(), "the fixture has dynamic bricks");
    let cost = vol.plan.slice_evaluations();
    let auto = |incremental| renderer_with(&d, Some(vol.clone()), incremental, SlicePolicy::Auto);
    let (mut full, mut incremental) = (auto(false), auto(true));
    let mut always = renderer(&d, Some(vol.clone()), false);
    let camera = d.cameras[0];
    // A new slice interval every frame: nothing baked, dynamic samples exact.
    let n = vol.volume.dynamic.times.len();
    for k in 0..4.min(n - 1) {
        let time = (k as f32 + 0.5) / (n - 1) as f32;
        let a = draw(&mut full, &d, &camera, time);
        let b = draw(&mut incremental, &d, &camera, time);
        assert_eq!(a.rgb, b.rgb, "t={time}: incremental frame differs");
        assert!(a.stats.slice_seconds == 0.0 && a.stats.samples_evaluated > 0);
        let p = a.psnr_displayed(&draw(&mut always, &d, &camera, time));
        println!("t={time}: exact dynamic samples against slices {p:.2} dB");
        assert!(p >= 30.0, "t={time}: {p:.2} dB");
    }
    // The time held: exact frames until they have paid for the slices, then none.
    let time = 0.5 / (n - 1) as f32;
    let (mut paid, mut frames) = (0, 0);
    loop {
        let a = draw(&mut full, &d, &camera, time);
        let b = draw(&mut incremental, &d, &camera, time);
        assert_eq!(
            a.rgb, b.rgb,
            "held frame {frames}: incremental frame differs"
        );
        frames += 1;
        if a.stats.samples_evaluated == 0 {
            break;
        }
        paid += a.stats.samples_evaluated;
        assert!(frames < 1000, "the slices were never baked");
    }
    println!("baked after {frames} frames, {paid} exact evaluations for slices of {cost}");
    assert!(
        paid >= cost,
        "baked after {paid} exact evaluations, before paying {cost}"
    );
    let last = draw(&mut full, &d, &camera, time);
    assert_eq!(last.stats.samples_evaluated, 0);
    assert_eq!(last.rgb, draw(&mut always, &d, &camera, time).rgb);
}

/// `msth eval FILE.msth --path`: a camera path's frames drawn by both renderers, the volume's
/// against the exact ones, the worst frame as a picture and every frame in the report; bad
/// paths, frame counts, sizes and times are errors that name the flag.
#[test]
fn eval_compares_the_renderers_along_a_path() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("split.msth");
    std::fs::write(&file, msth_tests::split_mask_fixture()).unwrap();
    let file = file.to_str().unwrap();
    let out = dir.path().join("eval");
    let out_s = out.to_str().unwrap();
    let args = [
        "eval", file, "--path", "0", "--frames", "3", "--size", "40x30", "--time", "0.2:0.8",
        "--out", out_s,
    ];
    msth_tests::msth(&args).unwrap();
    let report = msth_tests::read_json(&out.join("eval-path.json"));
    let frames = report["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 3);
    let times: Vec<f64> = frames.iter().map(|f| f["time"].as_f64().unwrap()).collect();
    assert!(
        (times[0] - 0.2).abs() < 1e-6 && (times[2] - 0.8).abs() < 1e-6,
        "{times:?}"
    );
    let worst = report["volume_vs_exact"][0].as_f64().unwrap();
    println!("volume against exact at the file's camera: {worst:.1} dB worst");
    // What `volume_frames_match_exact_frames` holds for the file's camera.
    assert!(worst >= 35.0, "{worst} dB");
    let pictures: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.starts_with("worst_frame_"))
        .collect();
    assert_eq!(pictures.len(), 1, "{pictures:?}");
    let png = image::open(out.join(&pictures[0])).unwrap();
    assert_eq!(
        (png.width(), png.height()),
        (3 * 40 + 2 * 2, 30),
        "exact | volume | difference, 2 pixels apart"
    );

    for (extra, flag) in [
        (&["--path", "nowhere.json"][..], "--path"),
        (&["--path", "orbit", "--frames", "0"][..], "--frames"),
        (&["--path", "orbit", "--size", "0x10"][..], "--size"),
        (&["--path", "orbit", "--time", "0:2"][..], "--time"),
    ] {
        let mut a = vec!["eval", file, "--out", out_s];
        a.extend_from_slice(extra);
        let e = msth_tests::msth(&a).unwrap_err();
        assert!(e.contains(flag), "{a:?}: {e}");
    }
    let e = msth_tests::msth(&["eval", file, "--path", "orbit", "--data", "builtin"]).unwrap_err();
    assert!(e.contains("--data") || e.contains("--path"), "{e}");
}
