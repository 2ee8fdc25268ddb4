//! Sizing the model from the data, end to end through `msth`: a static video (the built-in scene
//! with motion off) trains into a model with no 4D table and no mask, exports to a file without
//! dynamic sections or 4D rows, and plays; the dynamic scene keeps its 4D table; a user setting
//! wins over the sizing's choice; `--no-autosize` trains the preset.

use std::path::Path;

use msth_codec::{Decoder, SectionKind};
use msth_core::config::BlendMode;
use msth_tests::{export_cmd, msth, play_report, read_json, synth_cmd, train_cmd};
use msth_trainer::autosize::SizingReport;
use msth_trainer::checkpoint::Checkpoint;

/// Writes a small built-in scene (static or moving) into `dir`.
fn synth(dir: &Path, static_scene: bool) {
    let mut args = vec![
        "--width",
        "32",
        "--height",
        "24",
        "--frames",
        "4",
        "--cameras",
        "4",
    ];
    if static_scene {
        args.push("--static");
    }
    synth_cmd(dir, &args).unwrap();
}

/// A few steps of the fast preset with a small sampler.
const SHORT_TRAIN: &[&str] = &[
    "--preset",
    "fast",
    "--iters",
    "12",
    "--batch-rays",
    "256",
    "--set",
    "model.sampler.num_proposal_samples=16",
    "--set",
    "model.sampler.num_samples=8",
];

/// Trains [`SHORT_TRAIN`] without evaluation, with extra arguments.
fn train(data: &Path, out: &Path, extra: &[&str]) {
    train_cmd(data, out, &[SHORT_TRAIN, &["--no-eval"], extra].concat()).unwrap();
}

fn sizing(out: &Path) -> SizingReport {
    serde_json::from_slice(&std::fs::read(out.join("sizing.json")).unwrap()).unwrap()
}

fn export(out: &Path) -> (std::path::PathBuf, Decoder) {
    let file = out.join("model.msth");
    export_cmd(&out.join("model.ckpt"), &file, &["--chunk-frames", "2"]).unwrap();
    let bytes = std::fs::read(&file).unwrap();
    (file, Decoder::new(&bytes).unwrap())
}

#[test]
fn static_video_trains_exports_and_plays_without_a_4d_table() {
    let dir = tempfile::tempdir().unwrap();
    let (sdata, ddata) = (dir.path().join("static"), dir.path().join("moving"));
    synth(&sdata, true);
    synth(&ddata, false);
    let (sout, dout) = (dir.path().join("s"), dir.path().join("d"));
    train(&sdata, &sout, &[]);
    train(&ddata, &dout, &[]);

    // The sizing saw no motion in the static video and motion in the moving one.
    let s = sizing(&sout);
    let four_d = s.choices.iter().find(|c| c.name == "4D table").unwrap();
    assert!(
        four_d.applied && four_d.chosen.starts_with("none"),
        "{s:#?}"
    );
    let d = sizing(&dout);
    assert!(
        d.choices.iter().any(|c| c.name == "4D table rows"),
        "{d:#?}"
    );

    // The trained model has neither a 4D table nor a mask.
    let ckpt = Checkpoint::load(&sout.join("model.ckpt")).unwrap();
    let m = &ckpt.header.model;
    assert_eq!(m.field.encoding.blend, BlendMode::Static);
    assert_eq!(m.proposal.encoding.blend, BlendMode::Static);
    let layout = msth_core::field::ModelLayout::new(m);
    for e in &layout.params.entries {
        assert!(
            !e.name.ends_with(".h4") && !e.name.ends_with(".mask"),
            "{}",
            e.name
        );
    }
    let dyn_ckpt = Checkpoint::load(&dout.join("model.ckpt")).unwrap();
    assert!(dyn_ckpt.header.model.field.encoding.blend.uses_h4());

    // Nor has the file: no dynamic or shared section, a model without 4D rows.
    let (sfile, sdec) = export(&sout);
    let (dfile, ddec) = export(&dout);
    let kinds: Vec<SectionKind> = sdec.index().sections.iter().map(|s| s.kind).collect();
    assert!(
        !kinds.contains(&SectionKind::Dynamic) && !kinds.contains(&SectionKind::Shared),
        "{kinds:?}"
    );
    assert!(sdec.layout().field.encoding.h4.is_none());
    assert!(sdec.layout().proposal.field.encoding.h4.is_none());
    assert!(ddec
        .index()
        .sections
        .iter()
        .any(|s| s.kind == SectionKind::Dynamic));
    let (ss, ds) = (
        std::fs::metadata(&sfile).unwrap().len(),
        std::fs::metadata(&dfile).unwrap().len(),
    );
    println!("static file {ss} bytes, dynamic file {ds} bytes");
    assert!(ss < ds, "static {ss} vs dynamic {ds}");

    // It plays: every frame rendered.
    let frames = dir.path().join("frames");
    let r = play_report(sfile.to_str().unwrap(), &frames, &[]);
    assert_eq!(r["frames"].as_array().unwrap().len(), 4);
    for i in 0..4 {
        assert!(frames.join(format!("frame_{i:05}.png")).is_file());
    }
}

#[test]
fn user_settings_and_no_autosize_win() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("static");
    synth(&data, true);
    // A user's blend on a static video: kept, and the report says the choice was not applied.
    let out = dir.path().join("mt");
    train(&data, &out, &["--set", "model.field.encoding.blend=mt"]);
    let ckpt = Checkpoint::load(&out.join("model.ckpt")).unwrap();
    assert_eq!(ckpt.header.model.field.encoding.blend, BlendMode::Mt);
    let s = sizing(&out);
    let c = s.choices.iter().find(|c| c.name == "4D table").unwrap();
    assert!(!c.applied);
    // The other choices still apply.
    assert!(s
        .choices
        .iter()
        .filter(|c| c.name != "4D table")
        .all(|c| c.applied));

    // --no-autosize: the preset's model exactly, no sizing.json.
    let out = dir.path().join("off");
    train(&data, &out, &["--no-autosize"]);
    let ckpt = Checkpoint::load(&out.join("model.ckpt")).unwrap();
    let mut preset = msth_core::config::ModelConfig::preset(
        msth_core::config::Preset::Fast,
        ckpt.header.model.bounds,
        ckpt.header.model.background,
        4,
    );
    preset.sampler.set_samples(16, 8);
    assert_eq!(ckpt.header.model, preset);
    assert!(!out.join("sizing.json").exists());
}

/// Multiplies the camera positions and the scene box of a D-NeRF folder's JSON files by `s`.
fn shrink_json(dir: &Path, s: f64) {
    for split in ["train", "test", "val"] {
        let p = dir.join(format!("transforms_{split}.json"));
        let Ok(text) = std::fs::read_to_string(&p) else {
            continue;
        };
        let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
        if let Some(b) = v.get_mut("scene_box") {
            for k in ["min", "max"] {
                for x in b[k].as_array_mut().unwrap() {
                    *x = (x.as_f64().unwrap() * s).into();
                }
            }
        }
        for f in v["frames"].as_array_mut().unwrap() {
            for r in 0..3 {
                let x = &mut f["transform_matrix"][r][3];
                *x = (x.as_f64().unwrap() * s).into();
            }
        }
        std::fs::write(&p, serde_json::to_vec(&v).unwrap()).unwrap();
    }
}

/// A scene 1000 times smaller is trained in a rescaled world; the checkpoint records the scale
/// and `msth eval` applies it to the dataset it loads, scoring exactly what training scored.
#[test]
fn scene_scale_is_recorded_and_applied_by_eval() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("tiny");
    synth(&data, false);
    shrink_json(&data, 1e-3);
    let out = dir.path().join("out");
    train_cmd(&data, &out, SHORT_TRAIN).unwrap();
    let s = sizing(&out);
    let c = s.choices.iter().find(|c| c.name == "scene scale").unwrap();
    assert!(c.applied && c.chosen != "1", "{c:?}");
    let ckpt = Checkpoint::load(&out.join("model.ckpt")).unwrap();
    let scale = ckpt.header.scene_scale();
    assert!((scale - 1000.0).abs() < 1.0, "{scale}");
    // The model lives in the scaled world: a box of about 3 units.
    let (lo, hi) = ckpt.header.model.bounds.extent();
    assert!(((hi - lo).max_element() - 3.0).abs() < 1e-2);
    let psnr = |p: &Path| -> f64 { read_json(p)["psnr"].as_f64().unwrap() };
    let trained = psnr(&out.join("metrics.json"));
    let again = dir.path().join("eval");
    msth(&[
        "eval",
        out.join("model.ckpt").to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--out",
        again.to_str().unwrap(),
    ])
    .unwrap();
    let evaluated = psnr(&again.join("metrics.json"));
    assert!(
        (trained - evaluated).abs() < 1e-6,
        "{trained} vs {evaluated}"
    );
    // `--samples faster` without `--out`: half the samples per ray, into a subfolder beside the
    // checkpoint; the training's own metrics stay.
    let own = &ckpt.header.model.sampler;
    let (p, m) = (
        own.num_proposal_samples.div_ceil(2),
        own.num_samples.div_ceil(2),
    );
    msth(&[
        "eval",
        out.join("model.ckpt").to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--samples",
        "faster",
    ])
    .unwrap();
    let fewer = read_json(&out.join(format!("eval-samples-{p}-{m}/metrics.json")));
    assert_eq!(fewer["samples_per_ray"], serde_json::json!([p, m]));
    assert!(fewer["psnr"].as_f64().unwrap().is_finite());
    assert_eq!(psnr(&out.join("metrics.json")), trained);
    // `--set scene_scale=1` keeps the dataset's units (the user's value wins).
    let out1 = dir.path().join("unscaled");
    let unscaled = ["--set", "scene_scale=1", "--no-eval"];
    train_cmd(&data, &out1, &[SHORT_TRAIN, &unscaled].concat()).unwrap();
    let ckpt = Checkpoint::load(&out1.join("model.ckpt")).unwrap();
    assert_eq!(ckpt.header.scene_scale(), 1.0);
    let (lo, hi) = ckpt.header.model.bounds.extent();
    assert!(((hi - lo).max_element() - 3e-3).abs() < 1e-5);
}
