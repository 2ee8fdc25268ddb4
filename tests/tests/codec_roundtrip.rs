//! The codec end to end on a (briefly) trained model: the lossless mode is bit-exact and renders
//! the same pixels as the checkpoint with the same unstored 4D rows zeroed; lossy modes stay close;
//! `msth export` writes a file that decodes.

use msth_codec::{decode_all, encode, EncodeOptions, QuantMode};
use msth_core::field::ModelLayout;
use msth_dataset::Dataset;
use msth_tests::{export_cmd, short_run, tiny_scene};
use msth_trainer::checkpoint::Checkpoint;
use msth_trainer::eval::render_image;
use msth_trainer::metrics::psnr;
use msth_trainer::train::train;

/// A tiny scene trained for a few steps, saved as `model.ckpt` in a new temporary folder: the
/// folder, the checkpoint and the scene.
fn trained() -> (tempfile::TempDir, Checkpoint, Dataset) {
    let dir = tempfile::tempdir().unwrap();
    let (_, data) = tiny_scene();
    let s = short_run(&data, 30);
    train(&data, s, dir.path(), None, &mut |_| true).unwrap();
    let ckpt = Checkpoint::load(&dir.path().join("model.ckpt")).unwrap();
    (dir, ckpt, data)
}

#[test]
fn lossless_round_trip_renders_the_checkpoint_pixels() {
    let (_dir, ckpt, data) = trained();
    let model = &ckpt.header.model;
    let layout = ModelLayout::new(model);
    let camera = data.test[0].camera;
    for threshold in [0.5, 0.0] {
        let opts = EncodeOptions {
            quant: QuantMode::F32,
            chunk_frames: 2,
            dynamic_threshold: threshold,
            ..Default::default()
        };
        let (bytes, report) = encode(model, &ckpt.params, &ckpt.header.cameras, &opts).unwrap();
        let decoded = decode_all(&bytes).unwrap();
        assert_eq!(&decoded.config, model);
        assert_eq!(decoded.cameras, ckpt.header.cameras);
        let h4 = layout.field.encoding.h4.as_ref().unwrap().1.clone();
        for (i, (&a, &b)) in decoded.params.iter().zip(&ckpt.params).enumerate() {
            if !(h4.contains(&i) && a == 0.0) {
                assert_eq!(a.to_bits(), b.to_bits(), "parameter {i}");
            }
        }
        println!(
            "threshold {threshold}: {} bytes, {} chunks, kept {} of {} 4D values",
            bytes.len(),
            report.chunks.len(),
            report.h4_kept_union,
            report.h4_values
        );
        for (c, chunk) in decoded.chunks().iter().enumerate() {
            let span = &decoded.metadata.chunks[c];
            let t = 0.5 * (span.t_start + span.t_end);
            assert_eq!(decoded.chunk_for_time(t), Some(c));
            // The checkpoint with every 4D row this chunk does not store set to 0.
            let mut zeroed = ckpt.params.clone();
            zeroed[h4.clone()].fill(0.0);
            let (g, _) = layout.field.encoding.h4.as_ref().unwrap();
            for part in decoded.shared().into_iter().chain([chunk]) {
                for ((rows, _), level) in part.levels.iter().zip(&g.levels) {
                    for &r in rows {
                        let at = h4.start + level.offset + r as usize * g.features;
                        zeroed[at..at + g.features]
                            .copy_from_slice(&ckpt.params[at..at + g.features]);
                    }
                }
            }
            let from_file = render_image(model, &layout, &decoded.params_for_time(t), &camera, t);
            let expected = render_image(model, &layout, &zeroed, &camera, t);
            assert_eq!(from_file.rgb, expected.rgb, "chunk {c}: renders differ");
            let full = render_image(model, &layout, &ckpt.params, &camera, t);
            println!(
                "  chunk {c}: PSNR of the streamed render against the full checkpoint {:.1} dB",
                psnr(&from_file.rgb, &full.rgb)
            );
        }
    }
}

#[test]
fn lossy_modes_render_close_to_the_checkpoint() {
    let (_dir, ckpt, data) = trained();
    let model = &ckpt.header.model;
    let layout = ModelLayout::new(model);
    let view = &data.test[1];
    let full = render_image(model, &layout, &ckpt.params, &view.camera, view.time);
    let mut last_size = usize::MAX;
    // (mode, PSNR floor of the decoded render against the checkpoint's render, dB)
    for (mode, floor) in [
        (QuantMode::F16, 50.0),
        (QuantMode::Q8, 40.0),
        (QuantMode::Q6, 32.0),
        (QuantMode::K4, 28.0),
        (QuantMode::Q4, 25.0),
    ] {
        let opts = EncodeOptions {
            quant: mode,
            dynamic_threshold: 0.0,
            ..Default::default()
        };
        let (bytes, _) = encode(model, &ckpt.params, &[], &opts).unwrap();
        let d = decode_all(&bytes).unwrap();
        let r = render_image(
            model,
            &layout,
            &d.params_for_time(view.time),
            &view.camera,
            view.time,
        );
        let p = psnr(&r.rgb, &full.rgb);
        println!(
            "{mode}: {} bytes, {p:.1} dB against the checkpoint",
            bytes.len()
        );
        assert!(p >= floor, "{mode}: {p:.1} dB < {floor}");
        if mode != QuantMode::Q4 {
            assert!(
                bytes.len() < last_size,
                "{mode} is not smaller than the previous mode"
            );
            last_size = bytes.len();
        }
    }
}

#[test]
fn export_command_writes_a_decodable_file() {
    let (dir, _, _) = trained();
    let ckpt = dir.path().join("model.ckpt");
    let out = dir.path().join("scene.msth");
    let q8 = [
        "--quant",
        "q8",
        "--chunk-frames",
        "3",
        "--dynamic-threshold",
        "0.2",
    ];
    export_cmd(&ckpt, &out, &q8).unwrap();
    let d = decode_all(&std::fs::read(&out).unwrap()).unwrap();
    assert_eq!(d.metadata.quant, QuantMode::Q8);
    assert_eq!(d.metadata.chunk_frames, 3);
    assert!(export_cmd(&ckpt, &out, &["--quant", "q9"]).is_err());
}

/// `msth export` chooses each part's mode and the play-time samples by default (`--quant auto`,
/// `--play-samples auto`), within the budget it prints; `--quant MODE`, `--play-samples model`
/// and `P,M` set them; bad values are errors.
#[test]
fn export_command_chooses_sections_and_samples_by_default() {
    let (dir, ckpt, _) = trained();
    let path = dir.path().join("model.ckpt");
    let out = dir.path().join("auto.msth");
    export_cmd(&path, &out, &["--reference-psnr", "25"]).unwrap();
    let m = decode_all(&std::fs::read(&out).unwrap()).unwrap().metadata;
    let parts = m.section_quant.expect("each part's mode");
    assert_eq!(m.quant, parts.finest());
    let s = m.play_samples.expect("play-time samples");
    let own = &ckpt.header.model.sampler;
    assert!(s.proposal as usize <= own.num_proposal_samples);
    assert!(s.main as usize <= own.num_samples);
    export_cmd(&path, &out, &["--quant", "q5", "--play-samples", "7,5"]).unwrap();
    let m = decode_all(&std::fs::read(&out).unwrap()).unwrap().metadata;
    assert_eq!(
        m.section_quant,
        Some(msth_codec::SectionQuant::uniform(QuantMode::Q5))
    );
    assert_eq!(
        m.play_samples,
        Some(msth_codec::PlaySampleCounts {
            proposal: 7,
            main: 5
        })
    );
    export_cmd(&path, &out, &["--quant", "f32", "--play-samples", "model"]).unwrap();
    let m = decode_all(&std::fs::read(&out).unwrap()).unwrap().metadata;
    assert_eq!(m.quant, QuantMode::F32);
    assert_eq!(m.play_samples, None);
    for (bad, names) in [
        (&["--max-loss", "0"][..], "--max-loss"),
        (&["--max-loss", "NaN"][..], "--max-loss"),
        (&["--reference-psnr=-3"][..], "--reference-psnr"),
        (&["--play-samples", "0,4"][..], "auto, model or P,M"),
        (&["--quant", "q7"][..], "q7"),
    ] {
        let e = export_cmd(&path, &dir.path().join("bad.msth"), bad).unwrap_err();
        assert!(e.to_string().contains(names), "{bad:?}: {e}");
    }
}

/// The checkpoint says which of its cameras trained, and `msth export` keeps only the occupancy
/// cells those cameras see by default: a subset of what `--occupancy-from density` keeps.
#[test]
fn export_keeps_the_occupancy_cells_the_training_cameras_see() {
    let (dir, ckpt, data) = trained();
    let n_train = ckpt.header.train_cameras.expect("a new checkpoint says");
    assert!(n_train >= 1 && n_train < ckpt.header.cameras.len());
    assert_eq!(
        ckpt.header.training_cameras().unwrap()[0],
        data.train[0].camera
    );
    let path = dir.path().join("model.ckpt");
    let grid = |extra: &[&str]| {
        let out = dir.path().join("g.msth");
        export_cmd(&path, &out, extra).unwrap();
        decode_all(&std::fs::read(&out).unwrap())
            .unwrap()
            .occupancy
            .expect("a grid")
    };
    let seen = grid(&[]);
    let density = grid(&["--occupancy-from", "density"]);
    assert!(seen.occupied_cells() > 0);
    for (a, b) in seen.words.iter().zip(&density.words) {
        assert_eq!(a & !b, 0, "a seen cell the density grid calls empty");
    }
    println!(
        "occupied: {} seen, {} by density, of {}",
        seen.occupied_cells(),
        density.occupied_cells(),
        seen.cells()
    );
    // Every cell a sample of weight 0 or more lies in: at least the seen cells of 1e-3.
    let all = grid(&["--seen-weight", "0"]);
    for (a, b) in seen.words.iter().zip(&all.words) {
        assert_eq!(a & !b, 0);
    }
    // A checkpoint that does not list its training cameras (an older one) keeps the density
    // grid.
    let mut old = Checkpoint::load(&path).unwrap();
    old.header.train_cameras = None;
    let old_path = dir.path().join("old.ckpt");
    old.save(&old_path).unwrap();
    let out = dir.path().join("old.msth");
    export_cmd(&old_path, &out, &[]).unwrap();
    let from_old = decode_all(&std::fs::read(&out).unwrap())
        .unwrap()
        .occupancy
        .unwrap();
    assert_eq!(from_old, density);
    let out = dir.path().join("bad.msth");
    for bad in ["1", "-0.5", "NaN"] {
        let arg = format!("--seen-weight={bad}");
        let e = export_cmd(&path, &out, &[&arg]).unwrap_err();
        assert!(e.to_string().contains("--seen-weight"), "{e}");
    }
    assert!(!out.exists());
}
