//! The version-1 fixture `tests/fixtures/v1.msth` still decodes and renders the same pixels.
//! Any format change must keep it loading or bump the version with a migration (docs/format.md).
//!
//! The expected render (`v1_render.rgb`: raw 8-bit RGB, row-major; `v1_render.png` to look at) is
//! compared with a tolerance of 2/255 per channel and a mean of 0.25/255: the renderer is
//! deterministic on one machine, but another CPU or compiler may fuse or reorder float operations
//! (FMA), which moves a few pixels by one level. Regenerate both (after an intended change only):
//! `cargo test --release -p msth-tests --test codec_fixture -- --ignored regenerate_fixture`.

use std::path::{Path, PathBuf};

use msth_codec::{decode_all, encode, EncodeOptions, QuantMode};
use msth_core::field::ModelLayout;
use msth_tests::{fixture_run, tiny_scene};
use msth_trainer::dataset::Image8;
use msth_trainer::eval::render_image;
use msth_trainer::imageio::save_png_atomic;
use msth_trainer::train::train;

const TIME: f32 = 0.7;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures")
}

/// Renders the fixture's first playback camera at [`TIME`] the way a player does.
fn render(bytes: &[u8]) -> Image8 {
    let d = decode_all(bytes).unwrap();
    let camera = d.cameras[0];
    let r = render_image(
        &d.config,
        &d.layout,
        &d.params_for_time(TIME),
        &camera,
        TIME,
    );
    Image8::from_f32(r.width, r.height, &r.rgb)
}

#[test]
#[ignore = "rewrites tests/fixtures/v1.*; run only after an intended change"]
fn regenerate_fixture() {
    let (_, data) = tiny_scene();
    let s = fixture_run(&data);
    let dir = tempfile::tempdir().unwrap();
    let (trainer, _) = train(&data, s, dir.path(), None, &mut |_| true).unwrap();
    let cameras = vec![data.test[0].camera];
    let opts = EncodeOptions {
        quant: QuantMode::Q8,
        chunk_frames: 3,
        dynamic_threshold: 0.3,
        frame_rate: Some(24.0),
        ..Default::default()
    };
    let (bytes, report) =
        encode(&trainer.settings.model, &trainer.params, &cameras, &opts).unwrap();
    assert!(
        !report.chunks.is_empty(),
        "the fixture should have dynamic chunks"
    );
    assert!(bytes.len() < 200_000, "fixture is {} bytes", bytes.len());
    std::fs::create_dir_all(fixtures()).unwrap();
    std::fs::write(fixtures().join("v1.msth"), &bytes).unwrap();
    let img = render(&bytes);
    std::fs::write(fixtures().join("v1_render.rgb"), &img.data).unwrap();
    save_png_atomic(&fixtures().join("v1_render.png"), &img).unwrap();
    println!("{} bytes, {} chunks", bytes.len(), report.chunks.len());
}

#[test]
fn v1_fixture_decodes_and_renders_the_same_pixels() {
    let bytes = std::fs::read(fixtures().join("v1.msth")).unwrap();
    let d = decode_all(&bytes).unwrap();
    assert_eq!(d.params.len(), ModelLayout::new(&d.config).params.total);
    assert_eq!(d.metadata.quant, QuantMode::Q8);
    assert!(!d.chunks().is_empty());
    let expected = std::fs::read(fixtures().join("v1_render.rgb")).unwrap();
    let got = render(&bytes);
    assert_eq!(got.data.len(), expected.len());
    let diffs: Vec<u8> = got
        .data
        .iter()
        .zip(&expected)
        .map(|(a, b)| a.abs_diff(*b))
        .collect();
    let max = diffs.iter().copied().max().unwrap_or(0);
    let mean = diffs.iter().map(|&d| d as f64).sum::<f64>() / diffs.len() as f64;
    assert!(
        max <= 2 && mean <= 0.25,
        "max {max}, mean {mean:.3} (levels of 255)"
    );
}
