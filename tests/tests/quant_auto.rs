//! `msth export --quant auto` and the play-time samples (issue #61, docs/format.md §3.4, §5.4):
//! the chosen file's loss, measured again from its bytes, stays within the budget on the test
//! models; the samples a file stores are what the player renders with; files without them (the
//! committed version-1 and version-2 fixtures) play at the model's own counts.

use std::path::{Path, PathBuf};

use msth_codec::{decode_all, encode, EncodeOptions, PlaySampleCounts, QuantMode, SectionQuant};
use msth_core::config::{PlaySamples, SampleLevel};
use msth_core::field::ModelLayout;
use msth_player::quant_auto::{choose_quant, choose_samples, mse, AutoOptions, Probe};
use msth_player::{play, BackendChoice, PlayOptions};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures")
}

/// A test model: the configuration, parameters and cameras of a committed fixture (a short
/// training run of the built-in scene), with a 4D table, a mask and dynamic chunks.
fn fixture_model(name: &str) -> msth_codec::DecodedModel {
    decode_all(&std::fs::read(fixtures().join(name)).unwrap()).unwrap()
}

/// The second test model: the fixture's model with its 4D features and MLP weights scaled, so
/// that the parts' errors weigh differently than in the first.
fn scaled_model() -> msth_codec::DecodedModel {
    let mut d = fixture_model("v2.msth");
    let layout = ModelLayout::new(&d.config);
    if let Some((_, r)) = &layout.field.encoding.h4 {
        for v in &mut d.params[r.clone()] {
            *v *= 3.0;
        }
    }
    d
}

/// The loss of `file` against the lossless encoding of the same model, rendered again here from
/// the decoded bytes.
fn measured_loss(
    d: &msth_codec::DecodedModel,
    base: &EncodeOptions,
    file: &[u8],
    probe: &Probe,
    auto: &AutoOptions,
) -> f64 {
    let lossless = EncodeOptions {
        quant: QuantMode::F32,
        ..base.clone()
    };
    let (f32_bytes, _) = encode(&d.config, &d.params, &d.cameras, &lossless).unwrap();
    let reference = decode_all(&f32_bytes).unwrap();
    let chosen = decode_all(file).unwrap();
    let a = probe.render(&d.config, &d.layout, &|t| reference.params_for_time(t));
    let b = probe.render(&d.config, &d.layout, &|t| chosen.params_for_time(t));
    auto.loss_db(mse(&a, &b))
}

#[test]
fn auto_never_exceeds_its_loss_budget_on_the_test_models() {
    for (name, d) in [
        ("fixture", fixture_model("v2.msth")),
        ("fixture with 3x 4D features", scaled_model()),
    ] {
        let base = EncodeOptions {
            chunk_frames: d.metadata.chunk_frames as usize,
            dynamic_threshold: d.metadata.dynamic_threshold,
            occupancy_resolution: 32,
            ..Default::default()
        };
        let mut sizes = Vec::new();
        for budget in [0.02, 0.1, 0.5] {
            let auto = AutoOptions {
                max_loss_db: budget,
                reference_psnr: 30.0,
                views: 3,
                side: 40,
            };
            let probe = Probe::new(&d.config, &d.cameras, &auto);
            let c = choose_quant(&d.config, &d.params, &d.cameras, &base, &probe, &auto).unwrap();
            assert!(
                c.loss_db <= budget,
                "{name}: reported {} dB > {budget}",
                c.loss_db
            );
            let opts = EncodeOptions {
                sections: Some(c.modes),
                ..base.clone()
            };
            let (bytes, report) = encode(&d.config, &d.params, &d.cameras, &opts).unwrap();
            assert_eq!(report.section_quant, c.modes);
            let meta = decode_all(&bytes).unwrap().metadata;
            assert_eq!(meta.section_quant, Some(c.modes));
            assert_eq!(meta.quant, c.modes.finest());
            let loss = measured_loss(&d, &base, &bytes, &probe, &auto);
            println!(
                "{name}, budget {budget} dB: {} -> {} bytes, loss {loss:.4} dB ({} measurements)",
                c.modes,
                bytes.len(),
                c.steps.len()
            );
            assert!(
                loss <= budget + 1e-9,
                "{name}: {} measured {loss} dB from the file, over the budget {budget}",
                c.modes
            );
            sizes.push(bytes.len());
        }
        // A budget large enough lets some part go below f32, and the lossless file is larger
        // than the chosen one.
        let (f32_bytes, _) = encode(
            &d.config,
            &d.params,
            &d.cameras,
            &EncodeOptions {
                quant: QuantMode::F32,
                ..base.clone()
            },
        )
        .unwrap();
        assert!(
            *sizes.last().unwrap() < f32_bytes.len(),
            "{name}: {sizes:?} against f32 {}",
            f32_bytes.len()
        );
    }
}

#[test]
fn mixed_sections_store_each_part_in_its_mode() {
    let d = fixture_model("v2.msth");
    let modes = SectionQuant {
        mlp: QuantMode::F32,
        proposal: QuantMode::Q8,
        static_table: QuantMode::K3,
        mask: QuantMode::F16,
        dynamic: QuantMode::Q4,
    };
    let opts = EncodeOptions {
        sections: Some(modes),
        occupancy_resolution: 16,
        ..Default::default()
    };
    let (bytes, _) = encode(&d.config, &d.params, &d.cameras, &opts).unwrap();
    let out = decode_all(&bytes).unwrap();
    assert_eq!(out.metadata.quant, QuantMode::F32);
    let l = &out.layout;
    // The MLPs are lossless, the mask is binary16, the 3D table has at most 8 values per level.
    for r in [&l.field.density.1, &l.field.color.1] {
        assert_eq!(out.params[r.clone()], d.params[r.clone()]);
    }
    let (_, mask) = l.field.encoding.mask.as_ref().unwrap();
    for (a, b) in out.params[mask.clone()].iter().zip(&d.params[mask.clone()]) {
        assert_eq!(*a, half::f16::from_f32(*b).to_f32());
    }
    let (g3, r3) = l.field.encoding.h3.as_ref().unwrap();
    for level in g3.levels.iter().filter(|lv| !lv.dense) {
        let start = r3.start + level.offset;
        let mut values: Vec<u32> = out.params[start..start + level.rows * g3.features]
            .iter()
            .map(|v| v.to_bits())
            .collect();
        values.sort_unstable();
        values.dedup();
        assert!(values.len() <= 8, "{} distinct values", values.len());
    }
}

fn play_samples(file: &Path, samples: PlaySamples) -> ((usize, usize), (usize, usize)) {
    let mut o = PlayOptions::new(file.to_str().unwrap());
    o.backend = BackendChoice::Cpu;
    o.frames = Some(2);
    o.size = Some((24, 18));
    o.video = false;
    o.samples = samples;
    let r = play(&o, &mut |_, _| {}).unwrap();
    (r.samples, r.model_samples)
}

#[test]
fn players_use_the_stored_samples_and_old_files_the_models_own() {
    let dir = tempfile::tempdir().unwrap();
    let d = fixture_model("v2.msth");
    let own = (
        d.config.sampler.num_proposal_samples,
        d.config.sampler.num_samples,
    );
    // What the export's search chooses is stored, and the player renders with it.
    let auto = AutoOptions {
        views: 2,
        side: 32,
        ..Default::default()
    };
    let probe = Probe::new(&d.config, &d.cameras, &auto);
    let chosen = choose_samples(&d, &probe, &auto).unwrap();
    assert!(chosen.loss_db <= auto.max_loss_db, "{chosen:?}");
    for stored in [
        chosen.samples,
        PlaySampleCounts {
            proposal: 7,
            main: 5,
        },
    ] {
        let opts = EncodeOptions {
            quant: QuantMode::Q8,
            play_samples: Some(stored),
            occupancy_resolution: 16,
            ..Default::default()
        };
        let (bytes, _) = encode(&d.config, &d.params, &d.cameras, &opts).unwrap();
        let path = dir.path().join("stored.msth");
        std::fs::write(&path, &bytes).unwrap();
        assert_eq!(
            decode_all(&bytes).unwrap().metadata.play_samples,
            Some(stored)
        );
        let want = (stored.proposal as usize, stored.main as usize);
        assert_eq!(play_samples(&path, PlaySamples::default()), (want, own));
        // The user overrides them: the model's own, a level of the model's, exact counts.
        assert_eq!(
            play_samples(&path, PlaySamples::Level(SampleLevel::Full)),
            (own, own)
        );
        assert_eq!(
            play_samples(&path, PlaySamples::Level(SampleLevel::Faster)).0,
            (own.0.div_ceil(2), own.1.div_ceil(2))
        );
        assert_eq!(play_samples(&path, PlaySamples::Counts(3, 2)).0, (3, 2));
    }
    // Version-1 and version-2 files store none: the model's own counts.
    for old in ["v1.msth", "v2.msth"] {
        assert_eq!(
            play_samples(&fixtures().join(old), PlaySamples::default()),
            (own, own),
            "{old}"
        );
    }
}
