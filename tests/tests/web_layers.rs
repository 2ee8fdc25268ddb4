//! The page reads progressive layers (format.md §6.6) as msth-codec does: `web/js/format.js`
//! (run under node by `web/tests/decode.mjs`) decodes a layered file to msth-codec's flat
//! buffers bit for bit, with every layer and with each prefix of them, both from the whole file
//! and from a decoder fed only the prefix's sections; `web/tests/decode_bad.mjs` rejects damaged
//! copies of it.
//!
//! The page and the native player choose the same layers on the same link: `web/js/abr.js`'s
//! `simulate` (run by `web/tests/abr_sim.mjs`) gives msth-player's `abr::simulate` trace, request
//! for request and frame for frame, on a steady link, on one that falls to a tenth and recovers,
//! and on one that starts slow.
//!
//! Needs `node` and the page's npm packages (`npm ci --prefix web`); without them the test is
//! reported as ignored with the reason.

use std::path::Path;
use std::process::Command;

use msth_codec::{encode, Decoder, EncodeOptions, QuantMode};
use msth_core::config::{BlendMode, ModelConfig};
use msth_core::field::ModelLayout;
use msth_testkit::Tests;

fn main() -> std::process::ExitCode {
    let node = msth_tests::web_decoder_need();
    Tests::new(file!())
        .needs(
            &[&node],
            "javascript_decodes_layers_as_msth_codec",
            javascript_decodes_layers_as_msth_codec,
        )
        .needs(
            &[&node],
            "page_and_native_choose_the_same_layers",
            page_and_native_choose_the_same_layers,
        )
        .run()
}

/// A small model with a dynamic region in its mask, four levels per table.
fn model() -> (ModelConfig, Vec<f32>) {
    let mut c = ModelConfig::fast_on_white(9);
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        enc.blend = BlendMode::Mst;
        enc.resize(4, 12, 48.0, 8);
    }
    c.resize_mlps(8, 8);
    let layout = ModelLayout::new(&c);
    let mut p = layout.init_params(5);
    for (i, v) in p.iter_mut().enumerate() {
        *v += ((i as f32) * 0.37).sin() * 0.05;
    }
    if let Some((g, r)) = &layout.field.encoding.mask {
        let res = g.res;
        for (i, v) in p[r.clone()].iter_mut().enumerate() {
            let (x, y, z) = (i % res, (i / res) % res, i / (res * res));
            let centre = [x, y, z].iter().all(|&a| (2..=5).contains(&a));
            *v = if centre { -3.0 } else { 3.0 };
        }
    }
    (c, p)
}

fn run_node(args: &[&str]) -> (bool, String) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let out = Command::new("node")
        .current_dir(&root)
        .args(args)
        .output()
        .expect("node runs");
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    println!("$ node {}\n{text}", args.join(" "));
    (out.status.success(), text)
}

fn javascript_decodes_layers_as_msth_codec() {
    let dir = tempfile::tempdir().unwrap();
    let (c, p) = model();
    let opts = EncodeOptions {
        quant: QuantMode::Q6,
        chunk_frames: 3,
        layers: 3,
        occupancy_resolution: 32,
        ..Default::default()
    };
    let (bytes, report) = encode(&c, &p, &[], &opts).unwrap();
    assert_eq!(report.layers.len(), 3);
    assert!(report.chunks.len() >= 2, "{}", report.chunks.len());
    let file = dir.path().join("layered.msth");
    std::fs::write(&file, &bytes).unwrap();
    let mut d = Decoder::new(&bytes).unwrap();
    d.feed(&bytes).unwrap();
    let mut refs = Vec::new();
    for t in [0.0f32, 0.6] {
        for k in [None, Some(1), Some(2), Some(3)] {
            let mut out = Vec::new();
            d.params_for_layers_into(t, k.unwrap_or(usize::MAX), &mut out)
                .unwrap();
            let key = match k {
                Some(k) => format!("{t}@{k}"),
                None => format!("{t}"),
            };
            let path = dir.path().join(format!("params_{key}.f32"));
            let raw: Vec<u8> = out.iter().flat_map(|v| v.to_le_bytes()).collect();
            std::fs::write(&path, raw).unwrap();
            refs.push(format!("{key}={}", path.display()));
        }
    }
    let mut args = vec!["web/tests/decode.mjs", file.to_str().unwrap()];
    args.extend(refs.iter().map(String::as_str));
    let (ok, out) = run_node(&args);
    assert!(
        ok,
        "the JavaScript decoder disagrees with msth-codec:\n{out}"
    );
    assert_eq!(out.matches("(bit-exact)").count(), refs.len(), "{out}");
    let (ok, out) = run_node(&["web/tests/decode_bad.mjs", file.to_str().unwrap()]);
    assert!(
        ok,
        "the JavaScript decoder mishandles a damaged layered file:\n{out}"
    );
}

fn page_and_native_choose_the_same_layers() {
    let dir = tempfile::tempdir().unwrap();
    let (c, p) = model();
    let opts = EncodeOptions {
        quant: QuantMode::Q8,
        chunk_frames: 2,
        layers: 4,
        occupancy_resolution: 32,
        ..Default::default()
    };
    let (bytes, _) = encode(&c, &p, &[], &opts).unwrap();
    let file = dir.path().join("layered.msth");
    std::fs::write(&file, &bytes).unwrap();
    let ix = msth_codec::FileIndex::parse(&bytes, &msth_codec::Limits::default()).unwrap();
    let total = ix.file_len() as f64;
    let (latency, frames, fps) = (0.02, 150, 30.0);
    let mut layered_frames = 0;
    for schedule in [
        vec![(0.0, total / 3.0)],
        vec![(0.0, total / 3.0), (0.8, total / 30.0), (2.5, total / 3.0)],
        vec![(0.0, total / 40.0), (3.0, total)],
    ] {
        let rate_at = |t: f64| {
            schedule
                .iter()
                .rev()
                .find(|&&(at, _)| t >= at)
                .map_or(schedule[0].1, |&(_, r)| r)
        };
        let native = msth_player::abr::simulate(&ix, &rate_at, latency, frames, fps);
        let text: Vec<String> = schedule
            .iter()
            .enumerate()
            .map(|(i, (at, r))| {
                if i == 0 {
                    format!("{r:?}")
                } else {
                    format!("{r:?}@{at:?}")
                }
            })
            .collect();
        let (ok, out) = run_node(&[
            "web/tests/abr_sim.mjs",
            file.to_str().unwrap(),
            &latency.to_string(),
            &frames.to_string(),
            &fps.to_string(),
            &text.join(","),
        ]);
        assert!(ok, "{out}");
        let page: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
        let requests = page["requests"].as_array().unwrap();
        assert_eq!(requests.len(), native.requests.len(), "{schedule:?}");
        for (a, b) in native.requests.iter().zip(requests) {
            assert_eq!(
                (a.sections.start, a.sections.end),
                (
                    b["sections"][0].as_u64().unwrap() as usize,
                    b["sections"][1].as_u64().unwrap() as usize
                ),
                "{schedule:?}"
            );
            assert_eq!(a.at, b["at"].as_f64().unwrap(), "{schedule:?}");
        }
        let shown = page["frames"].as_array().unwrap();
        assert_eq!(shown.len(), native.frames.len());
        for (a, b) in native.frames.iter().zip(shown) {
            assert_eq!(a.layers as u64, b["layers"].as_u64().unwrap());
            assert_eq!(a.at, b["at"].as_f64().unwrap());
        }
        assert_eq!(
            native.stalls.len(),
            page["stalls"].as_array().unwrap().len()
        );
        layered_frames += native.frames.iter().filter(|f| f.layers > 1).count();
        // The first frame needs layer 0 alone; no frame is drawn without a layer.
        assert_eq!(native.frames[0].layers, 1, "{schedule:?}");
    }
    assert!(layered_frames > 0);
}
