//! Progressive layers end to end, through the command line: a model trained with nested
//! dropout (`--set nested_dropout=...`), exported in layers (`msth export --layers`), measured
//! prefix by prefix (`msth bench layers`) and streamed over a throttled loopback server (`msth
//! bench stream`). What is checked is that each step does what it says and writes its reports;
//! the figures themselves are docs/streaming.md's.

use msth_testkit::Tests;
use msth_tests::{export_cmd, msth, read_json, synth_cmd, train_cmd};

fn main() -> std::process::ExitCode {
    Tests::new(file!())
        .test(
            "layers_train_export_measure_and_stream",
            layers_train_export_measure_and_stream,
        )
        .run()
}

fn layers_train_export_measure_and_stream() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    synth_cmd(
        &data,
        &["--size", "32x24", "--frames", "6", "--cameras", "3"],
    )
    .unwrap();
    let run = tmp.path().join("run");
    train_cmd(
        &data,
        &run,
        &[
            "--preset",
            "fast",
            "--iters",
            "20",
            "--batch-rays",
            "256",
            "--threads",
            "2",
            "--set",
            "nested_dropout=0.5",
            "--set",
            "nested_dropout_layers=3",
        ],
    )
    .unwrap();
    let ckpt = run.join("model.ckpt");

    // Prefix by prefix: bytes grow with the layers, every PSNR is a number.
    let bench = tmp.path().join("bench");
    msth(&[
        "bench",
        "layers",
        ckpt.to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--layers",
        "3",
        "--out",
        bench.to_str().unwrap(),
    ])
    .unwrap();
    let rows = read_json(&bench.join("layers.json"))["rows"]
        .as_array()
        .unwrap()
        .clone();
    assert_eq!(rows.len(), 3);
    for w in rows.windows(2) {
        assert!(w[0]["bytes"].as_u64() < w[1]["bytes"].as_u64(), "{rows:?}");
        assert!(w[0]["first_frame_bytes"].as_u64() < w[1]["first_frame_bytes"].as_u64());
        assert!(w[0]["h3_levels"].as_u64() < w[1]["h3_levels"].as_u64());
    }
    assert!(rows
        .iter()
        .all(|r| r["psnr"].as_f64().is_some_and(f64::is_finite)));
    assert!(bench.join("layers.md").is_file());
    let layered = bench.join("run.msth");
    let head = std::fs::read(&layered).unwrap();
    assert_eq!(&head[4..6], &4u16.to_le_bytes());

    // The same model in one layer, and both streamed over a throttled link.
    let flat = tmp.path().join("flat").join("flat.msth");
    std::fs::create_dir_all(flat.parent().unwrap()).unwrap();
    export_cmd(&ckpt, &flat, &["--layers", "1"]).unwrap();
    let out = tmp.path().join("stream");
    msth(&[
        "bench",
        "stream",
        layered.to_str().unwrap(),
        flat.to_str().unwrap(),
        "--rate",
        "20mbit",
        "--schedule",
        "20mbit,2mbit@0.5",
        "--seconds",
        "1.5",
        "--size",
        "16x12",
        "--out",
        out.to_str().unwrap(),
    ])
    .unwrap();
    let r = read_json(&out.join("stream.json"));
    let firsts = r["first_picture"].as_array().unwrap();
    assert_eq!(firsts.len(), 2);
    assert_eq!(firsts[0]["layer_count"], 3);
    assert_eq!(firsts[1]["layer_count"], 1);
    for f in firsts {
        let layers = f["layers"].as_u64().unwrap();
        assert!(layers >= 1 && layers <= f["layer_count"].as_u64().unwrap());
        assert!(f["first_frame_data_s"].as_f64().unwrap() <= f["every_layer_s"].as_f64().unwrap());
    }
    let frames = r["playback"]["frames"].as_array().unwrap();
    assert!(!frames.is_empty());
    assert!(frames
        .iter()
        .all(|f| (1..=3).contains(&f["layers"].as_u64().unwrap())));
}
