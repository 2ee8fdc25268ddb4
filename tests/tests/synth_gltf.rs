//! `msth synth --gltf`: both layouts from the shared BoxAnimated model through the command,
//! read back by the trainer's loader, a short training run on the stage, and bad arguments.
//!
//! This binary runs on `msth-testkit`'s harness (`harness = false`): [`main`] lists its tests,
//! and a test whose need is missing is reported as ignored with the reason (the shared data:
//! `MSTH_REQUIRE_DATA=1` makes that a failure).

use std::path::Path;

use msth_dataset::dnerf::{load, LoadOptions};
use msth_testkit::{Need, Tests};
use msth_tests::{msth, read_json, shared_dataset, synth_cmd, train_cmd};

fn main() -> std::process::ExitCode {
    let gltf = Need::shared_data("gltf/BoxAnimated/BoxAnimated.gltf");
    Tests::new(file!())
        .needs(
            &[&gltf],
            "box_animated_both_layouts_load_and_the_stage_trains",
            box_animated_both_layouts_load_and_the_stage_trains,
        )
        .test(
            "bad_gltf_arguments_give_one_clear_error",
            bad_gltf_arguments_give_one_clear_error,
        )
        .run()
}

fn box_animated_both_layouts_load_and_the_stage_trains() {
    let gltf_dir = shared_dataset("gltf");
    let model = gltf_dir.join("BoxAnimated/BoxAnimated.gltf");
    let model = model.to_str().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let object = tmp.path().join("object");
    let stage = tmp.path().join("stage");
    let synth = |out: &Path, layout: &str, size: &str, frames: &str, cameras: &str| {
        let args = [
            "--layout",
            layout,
            "--size",
            size,
            "--frames",
            frames,
            "--cameras",
            cameras,
        ];
        synth_cmd(out, &[&["--gltf", model][..], &args].concat()).unwrap();
    };
    synth(&object, "object", "40x40", "6", "2");
    synth(&stage, "stage", "40x30", "5", "4");
    let o = load(&object, &LoadOptions::default()).unwrap();
    assert_eq!((o.train.len(), o.test.len()), (6, 2));
    assert!(o.train.iter().all(|v| v.alpha.is_some()));
    let s = load(&stage, &LoadOptions::default()).unwrap();
    assert_eq!((s.train.len(), s.test.len(), s.num_frames), (20, 5, 5));
    for c in 0..5 {
        assert!(stage.join(format!("cam{c:02}/0004.png")).is_file());
    }
    assert!(stage.join("poses_bounds.npy").is_file());
    // A few training steps on the generated stage, then evaluation.
    let run = tmp.path().join("run");
    train_cmd(&stage, &run, &["--preset", "fast", "--iters", "10"]).unwrap();
    let metrics = read_json(&run.join("metrics.json"));
    assert!(metrics["psnr"].as_f64().unwrap() > 5.0, "{metrics}");
}

fn bad_gltf_arguments_give_one_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let out = out.to_str().unwrap();
    let missing = tmp.path().join("missing.glb");
    let e = msth(&["synth", "--gltf", missing.to_str().unwrap(), "--out", out]).unwrap_err();
    assert!(
        e.contains("missing.glb") && e.contains("No such file"),
        "{e}"
    );
    let e = msth(&[
        "synth", "--gltf", "x.gltf", "--layout", "ring", "--out", out,
    ])
    .unwrap_err();
    assert!(e.contains("--layout `ring`"), "{e}");
    let e = msth(&["synth", "--gltf", "x.gltf", "--size", "200", "--out", out]).unwrap_err();
    assert!(e.contains("expected WxH"), "{e}");
    let e = msth(&["synth", "--gltf", "x.gltf", "--frames", "0", "--out", out]).unwrap_err();
    assert!(e.contains("frames"), "{e}");
    let e = msth(&["synth", "--layout", "stage", "--out", out]).unwrap_err();
    assert!(e.contains("--gltf only"), "{e}");
    assert!(!tmp.path().join("out").exists());
}
