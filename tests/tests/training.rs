//! Training behaviour end to end: it learns, it is repeatable for a seed, `--resume` continues
//! exactly, and the demo leaves the files later stages start from.
//!
//! This binary runs on `msth-testkit`'s harness (`harness = false`): [`main`] lists its tests,
//! and a test whose need is missing is reported as ignored with the reason (the shared data:
//! `MSTH_REQUIRE_DATA=1` makes that a failure).

use msth_core::config::Preset;
use msth_core::field::ModelLayout;
use msth_testkit::{Need, Tests};
use msth_tests::{msth, read_json, render_cmd, shared_dataset, tiny_scene, train_cmd};
use msth_trainer::checkpoint::Checkpoint;
use msth_trainer::eval::evaluate;
use msth_trainer::train::{train, TrainSettings};

fn main() -> std::process::ExitCode {
    let object = Need::shared_data("box_animated_object/transforms_train.json");
    Tests::new(file!())
        .test(
            "training_improves_held_out_psnr",
            training_improves_held_out_psnr,
        )
        .test(
            "same_seed_same_model_and_resume_is_exact",
            same_seed_same_model_and_resume_is_exact,
        )
        .test(
            "demo_leaves_checkpoint_and_metrics",
            demo_leaves_checkpoint_and_metrics,
        )
        .needs(
            &[&object],
            "shared_object_dataset_trains",
            shared_object_dataset_trains,
        )
        .test(
            "mask_learning_trains_repeatably_and_stays_out_of_the_checkpoint",
            mask_learning_trains_repeatably_and_stays_out_of_the_checkpoint,
        )
        .test(
            "divergence_stops_and_keeps_the_last_good_checkpoint",
            divergence_stops_and_keeps_the_last_good_checkpoint,
        )
        .test(
            "mask_learning_resume_is_exact",
            mask_learning_resume_is_exact,
        )
        .test(
            "training_until_converged_stops_when_the_held_out_psnr_stalls",
            training_until_converged_stops_when_the_held_out_psnr_stalls,
        )
        .run()
}

fn quick_settings(data: &msth_dataset::Dataset, iters: usize) -> TrainSettings {
    let mut s = TrainSettings::for_preset(Preset::Fast, data);
    s.iters = iters;
    s.batch_rays = 1024;
    s.anneal_steps = (iters / 4).max(1);
    s.checkpoint_every = 0;
    s
}

fn training_improves_held_out_psnr() {
    let (_, data) = tiny_scene();
    let s = quick_settings(&data, 150);
    let layout = ModelLayout::new(&s.model);
    let init = layout.init_params(s.seed);
    let before = evaluate(&data, &s.model, &layout, &init, 2, None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (trainer, outcome) = train(&data, s, dir.path(), None, &mut |_| true).unwrap();
    let after = evaluate(
        &data,
        &trainer.settings.model,
        &trainer.layout,
        &trainer.params,
        2,
        None,
    )
    .unwrap();
    println!(
        "held-out PSNR {:.2} -> {:.2} dB in {} steps",
        before.psnr, after.psnr, outcome.steps
    );
    assert!(
        after.psnr > before.psnr + 6.0,
        "{:.2} -> {:.2}",
        before.psnr,
        after.psnr
    );
    assert!(after.psnr > 18.0, "{:.2}", after.psnr);
    assert!(after.ssim > before.ssim);
}

/// `converge_every`: the held-out PSNR measured every N steps, the run stopped (and its
/// checkpoint written) at the first measurement that gains less than the threshold; the
/// measurements equal an evaluation of the parameters at that step.
fn training_until_converged_stops_when_the_held_out_psnr_stalls() {
    let (_, data) = tiny_scene();
    let mut s = quick_settings(&data, 400);
    s.batch_rays = 256;
    s.eval_stride = 2;
    s.converge_every = 20;
    // No run gains 1000 dB in 20 steps: the second measurement stops it.
    s.converge_min_gain_db = 1000.0;
    let dir = tempfile::tempdir().unwrap();
    let mut reported = Vec::new();
    let (trainer, outcome) = train(&data, s, dir.path(), None, &mut |p| {
        if let Some(psnr) = p.held_out_psnr {
            reported.push((p.step, psnr));
        }
        true
    })
    .unwrap();
    assert!(outcome.converged);
    assert_eq!(outcome.steps, 40, "stopped at the second measurement");
    assert_eq!(
        outcome.held_out.iter().map(|m| m.0).collect::<Vec<_>>(),
        vec![20, 40]
    );
    assert_eq!(reported, outcome.held_out, "each measurement is reported");
    let last = evaluate(
        &data,
        &trainer.settings.model,
        &trainer.layout,
        &trainer.params,
        2,
        None,
    )
    .unwrap();
    assert_eq!(last.psnr, outcome.held_out[1].1);
    let ckpt = Checkpoint::load(&dir.path().join("model.ckpt")).unwrap();
    assert_eq!(ckpt.header.step, 40);

    // A dataset without held-out views cannot measure convergence: a clear error.
    let mut none = data.clone();
    none.test.clear();
    let mut s = quick_settings(&none, 40);
    s.converge_every = 20;
    let dir = tempfile::tempdir().unwrap();
    let e = train(&none, s, dir.path(), None, &mut |_| true)
        .err()
        .unwrap();
    assert!(e.to_string().contains("held-out views"), "{e}");
}

fn same_seed_same_model_and_resume_is_exact() {
    let (_, data) = tiny_scene();
    // Runs a 12-step schedule, stopping after `stop_at` steps (the callback's `false`).
    let run = |stop_at: usize, seed: u64, dir: &std::path::Path, resume: bool| {
        let mut s = quick_settings(&data, 12);
        s.seed = seed;
        s.batch_rays = 256;
        s.anneal_steps = 8;
        let r = resume.then(|| Checkpoint::load(&dir.join("model.ckpt")).unwrap());
        train(&data, s, dir, r, &mut |p| p.step < stop_at)
            .unwrap()
            .0
            .params
    };
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    let c = tempfile::tempdir().unwrap();
    let straight = run(12, 7, a.path(), false);
    assert_eq!(
        straight,
        run(12, 7, b.path(), false),
        "same seed must give the same model"
    );
    assert_ne!(
        straight,
        run(12, 8, c.path(), false),
        "another seed gives another model"
    );
    // 6 steps, then resume to 12: identical to 12 straight.
    let d = tempfile::tempdir().unwrap();
    run(6, 7, d.path(), false);
    let resumed = run(12, 7, d.path(), true);
    assert_eq!(straight, resumed, "resume must continue exactly");
    // Only the checkpoint is left in the folder: no temporary files.
    let names: Vec<String> = std::fs::read_dir(d.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, vec!["model.ckpt".to_string()]);
}

fn demo_leaves_checkpoint_and_metrics() {
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("demo");
    msth(&[
        "demo",
        "--out",
        out.to_str().unwrap(),
        "--iters",
        "20",
        "--play-size",
        "48x36",
        "--play-frames",
        "7",
    ])
    .unwrap();
    let m = read_json(&out.join("metrics.json"));
    for k in [
        "psnr",
        "ssim",
        "dssim",
        "train_seconds",
        "field_samples_per_sec",
        "frames",
    ] {
        assert!(!m[k].is_null(), "metrics.json lacks {k}");
    }
    assert!(m["frames"].as_array().unwrap().len() >= 10);
    let ckpt = Checkpoint::load(&out.join("model.ckpt")).unwrap();
    assert_eq!(ckpt.header.step, 20);
    assert!(!ckpt.header.cameras.is_empty());
    // Pictures exist and render works from the checkpoint for any camera and time.
    let pic = m["pictures"][0].as_str().unwrap();
    assert!(std::path::Path::new(pic).is_file());
    let png = t.path().join("r.png");
    let ck = out.join("model.ckpt");
    let orbit = [
        "--camera",
        "orbit:30,20,3",
        "--time",
        "0.5",
        "--width",
        "40",
    ];
    render_cmd(&ck, &png, &orbit).unwrap();
    assert!(png.is_file());
    let err = render_cmd(&ck, &png, &["--time", "1.5"]).unwrap_err();
    assert!(err.contains("--time"), "{err}");
    let err = render_cmd(&ck, &png, &["--camera", "99"]).unwrap_err();
    assert!(err.contains("cameras"), "{err}");
}

/// The shared D-NeRF-style object scene trains on random backgrounds and gets the object right.
fn shared_object_dataset_trains() {
    let dir = shared_dataset("box_animated_object");
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("obj");
    let settings = ["--preset", "fast", "--iters", "150", "--downscale", "2"];
    train_cmd(
        &dir,
        &out,
        &[&settings[..], &["--set", "eval_stride=5"]].concat(),
    )
    .unwrap();
    let m = read_json(&out.join("metrics.json"));
    let psnr = m["psnr"].as_f64().unwrap();
    // An all-white prediction scores about 22.5 dB here; learning the object must beat it.
    assert!(psnr > 25.0, "held-out PSNR {psnr:.2}");
}

/// Uncertainty-guided mask learning with every term on (paper weights): the run is finite and
/// repeatable, its auxiliary parameters learn, and none of them reach the checkpoint (whose
/// parameter buffer is exactly the model's, which is all the codec reads).
fn mask_learning_trains_repeatably_and_stays_out_of_the_checkpoint() {
    let (_, data) = tiny_scene();
    let run = |dir: &std::path::Path| {
        let mut s = quick_settings(&data, 8);
        s.batch_rays = 256;
        s.apply_overrides(
            None,
            &[
                "mask_learning.uncertainty=true".into(),
                "mask_learning.mine=true".into(),
                "mask_learning.uncertainty_resolution=16".into(),
            ],
        )
        .unwrap();
        train(&data, s, dir, None, &mut |p| {
            assert!(p.loss.is_finite());
            true
        })
        .unwrap()
    };
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    let (ta, oa) = run(a.path());
    let (tb, _) = run(b.path());
    assert!(oa.last_loss.is_finite());
    assert_eq!(ta.params, tb.params, "same seed must give the same model");
    let aux = ta.aux.as_ref().expect("mask learning is on");
    assert_eq!(aux.params, tb.aux.as_ref().unwrap().params);
    assert!(aux.params.iter().all(|v| v.is_finite()));
    let init = aux.layout.init_params(ta.settings.seed);
    for e in &aux.layout.params.entries {
        assert!(
            aux.params[e.range()] != init[e.range()],
            "{} did not learn",
            e.name
        );
    }
    let ckpt = Checkpoint::load(&a.path().join("model.ckpt")).unwrap();
    let layout = ModelLayout::new(&ckpt.header.model);
    assert_eq!(ckpt.params.len(), layout.params.total);
    assert!(layout
        .params
        .entries
        .iter()
        .all(|e| !e.name.starts_with("aux")));
    // The mask learned something different from a run without the new terms.
    let c = tempfile::tempdir().unwrap();
    let mut s = quick_settings(&data, 8);
    s.batch_rays = 256;
    let (plain, _) = train(&data, s, c.path(), None, &mut |_| true).unwrap();
    assert!(plain.aux.is_none());
    let mask = layout.params.get("field.mask").unwrap().range();
    assert_ne!(plain.params[mask.clone()], ta.params[mask]);
}

/// The divergence guard: a run driven to non-finite values stops with a message naming the step
/// and the last good checkpoint, which is left as it was.
fn divergence_stops_and_keeps_the_last_good_checkpoint() {
    let (_, data) = tiny_scene();
    let dir = tempfile::tempdir().unwrap();
    let mut s = quick_settings(&data, 3);
    s.batch_rays = 128;
    train(&data, s.clone(), dir.path(), None, &mut |_| true).unwrap();
    let ckpt_path = dir.path().join("model.ckpt");
    let good = std::fs::read(&ckpt_path).unwrap();
    // Resume with an absurd learning rate: the parameters blow up within a few steps.
    s.iters = 40;
    s.adam.lr = 1e30;
    s.adam.lr_final = 1e30;
    s.mask_learning.uncertainty = true;
    s.mask_learning.mine = true;
    s.mask_learning.uncertainty_resolution = 8;
    let resume = Checkpoint::load(&ckpt_path).unwrap();
    let err = match train(&data, s, dir.path(), Some(resume), &mut |_| true) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a learning rate of 1e30 must diverge"),
    };
    assert!(err.contains("diverged at step"), "{err}");
    assert!(err.contains("model.ckpt"), "{err}");
    assert_eq!(std::fs::read(&ckpt_path).unwrap(), good);
}

/// With mask learning on, the auxiliary state is kept in `model.aux` next to the checkpoint and
/// a resumed run continues exactly (model and auxiliary parameters).
fn mask_learning_resume_is_exact() {
    let (_, data) = tiny_scene();
    let run = |stop_at: usize, dir: &std::path::Path, resume: bool| {
        let mut s = quick_settings(&data, 8);
        s.batch_rays = 256;
        s.mask_learning.uncertainty = true;
        s.mask_learning.mine = true;
        s.mask_learning.uncertainty_resolution = 16;
        let r = resume.then(|| Checkpoint::load(&dir.join("model.ckpt")).unwrap());
        let (t, _) = train(&data, s, dir, r, &mut |p| p.step < stop_at).unwrap();
        (t.params, t.aux.unwrap().params)
    };
    let a = tempfile::tempdir().unwrap();
    let straight = run(8, a.path(), false);
    let d = tempfile::tempdir().unwrap();
    run(4, d.path(), false);
    assert!(d.path().join("model.aux").exists());
    let resumed = run(8, d.path(), true);
    assert_eq!(straight, resumed, "resume must continue exactly");
}
