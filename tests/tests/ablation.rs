//! Issue #6 items 2-3 end to end: `msth bench ablation` writes its table, JSON and mask pictures
//! and reuses finished runs; a long run with every training term on stays finite.

use std::path::Path;

use msth_core::config::{BlendMode, Preset};
use msth_tests::{msth, tiny_scene};
use msth_trainer::checkpoint::Checkpoint;
use msth_trainer::ray_sampling::SamplingMode;
use msth_trainer::train::{train, TrainSettings};

#[test]
fn ablation_bench_writes_table_json_and_mask_pictures() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("abl");
    let o = out.to_str().unwrap();
    let args = [
        "--threads",
        "2",
        "bench",
        "ablation",
        "builtin",
        "--downscale",
        "4",
        "--out",
        o,
        "--iters",
        "3",
        "--batch-rays",
        "64",
        "--eval-stride",
        "10",
        "--set",
        "mask_learning.uncertainty_resolution=8",
    ];
    msth(&args).unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("ablation.json")).unwrap()).unwrap();
    let runs = json["runs"].as_array().unwrap();
    let names: Vec<&str> = runs.iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "4d-uniform",
            "4d-dynamics",
            "add-uniform",
            "add-dynamics",
            "mt-uniform",
            "mt-dynamics",
            "mst-uniform",
            "mst-dynamics",
            "full-uniform",
            "full-dynamics"
        ]
    );
    let md = std::fs::read_to_string(out.join("ablation.md")).unwrap();
    for r in runs {
        assert_eq!(r["steps"], 3);
        let psnr = r["psnr"].as_f64().unwrap();
        assert!(psnr.is_finite() && psnr > 5.0, "{r}");
        assert!(r["dynamic_psnr"].as_f64().unwrap().is_finite(), "{r}");
        let has_mask = !matches!(r["variant"].as_str().unwrap(), "4d" | "add");
        assert_eq!(r["mask_above_0_9"].is_number(), has_mask, "{r}");
        assert_eq!(r["skippable_static_rays"].is_number(), has_mask, "{r}");
        // The dynamics-aware sampler draws more rays in dynamic pixels than the uniform one.
        let share = r["train_dynamic_ray_share"].as_f64().unwrap();
        assert!(share > 0.0 && share < 1.0);
        let pic = Path::new(r["picture"].as_str().unwrap());
        let img = image::open(pic).unwrap();
        // ground truth | render | mask | skippable rays: four 24-pixel images and three gaps
        assert!(img.width() > 4 * 24, "{}", img.width());
        assert!(md.contains(r["label"].as_str().unwrap()));
    }
    let share = |n: &str| {
        runs.iter().find(|r| r["name"] == n).unwrap()["train_dynamic_ray_share"]
            .as_f64()
            .unwrap()
    };
    assert!(share("mt-dynamics") > share("mt-uniform"));
    assert_eq!(md.lines().filter(|l| l.starts_with("| ")).count(), 11);

    // A second call reuses every finished run (same settings): nothing is retrained.
    let before = std::fs::metadata(out.join("mt-uniform/model.ckpt"))
        .unwrap()
        .modified()
        .unwrap();
    msth(&args).unwrap();
    let after = std::fs::metadata(out.join("mt-uniform/model.ckpt"))
        .unwrap()
        .modified()
        .unwrap();
    assert_eq!(before, after, "a finished run was trained again");
    // Other settings: that run is trained again.
    let mut changed = args.to_vec();
    changed.extend(["--variants", "mt", "--samplers", "uniform", "--seed", "1"]);
    msth(&changed).unwrap();
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("ablation.json")).unwrap()).unwrap();
    assert_eq!(json["runs"].as_array().unwrap().len(), 1);
    assert_eq!(json["seed"], 1);

    let e = msth(&[
        "bench",
        "ablation",
        "builtin",
        "--out",
        o,
        "--variants",
        "5d",
    ])
    .unwrap_err();
    assert!(e.contains("5d"), "{e}");
}

/// Issue #6: 10,000 training steps with every term on (MSTH "mst", uncertainty, MINE, the
/// dynamics-aware sampler, the mask loss, a raised mask learning rate) stay finite: the run
/// ends without the divergence guard firing, and every parameter of the final checkpoint and of
/// the auxiliary state is finite. A tiny model and batch keep it short.
#[test]
fn ten_thousand_steps_with_every_term_on_stay_finite() {
    let (_, data) = tiny_scene();
    let mut s = TrainSettings::for_preset(Preset::Fast, &data);
    s.iters = 10_000;
    s.batch_rays = 16;
    s.chunk_rays = 16;
    s.anneal_steps = 2500;
    s.checkpoint_every = 2500;
    s.mask_loss_weight = 1.0;
    s.mask_lr_scale = 10.0;
    s.sampling.mode = SamplingMode::Dynamics;
    s.mask_learning.uncertainty = true;
    s.mask_learning.mine = true;
    s.mask_learning.uncertainty_resolution = 8;
    s.mask_learning.mine_hidden = 8;
    for enc in [&mut s.model.field.encoding, &mut s.model.proposal.encoding] {
        enc.blend = BlendMode::Mst;
        enc.resize(3, 10, 48.0, 12);
    }
    s.model.resize_mlps(16, 8);
    s.model.sampler.set_samples(12, 8);
    let dir = tempfile::tempdir().unwrap();
    let mut max_loss = 0f32;
    let (t, outcome) = train(&data, s, dir.path(), None, &mut |p| {
        assert!(p.loss.is_finite(), "step {}: loss {}", p.step, p.loss);
        max_loss = max_loss.max(p.loss);
        true
    })
    .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(outcome.steps, 10_000);
    assert!(outcome.last_loss.is_finite());
    let c = Checkpoint::load(&dir.path().join("model.ckpt")).unwrap();
    assert_eq!(c.header.step, 10_000);
    assert!(c.params.iter().all(|v| v.is_finite()));
    let aux = t.aux.as_ref().unwrap();
    assert!(aux.params.iter().all(|v| v.is_finite()));
    assert!(aux.adam.m.iter().chain(&aux.adam.v).all(|v| v.is_finite()));
    assert!(t.adam.m.iter().chain(&t.adam.v).all(|v| v.is_finite()));
    eprintln!(
        "10,000 steps: largest step loss {max_loss}, last {}",
        outcome.last_loss
    );
}
