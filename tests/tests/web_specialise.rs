//! The page and the native player compile the same specialised kernels (encodings and MLPs
//! written for one model): `web/js/specialise.js`
//! (run under node by `web/tests/specialise.mjs`, on the page's own decoder and `gpuModel`)
//! writes byte for byte the text of msth-gpu's `specialise::specialised_region` for the same
//! `.msth` file, and refuses the same models with the same message. Models: the `fast` and
//! `balanced` presets, three colour layers, one feature per level, the static, 4D-only and
//! additive blends, and two that are not specialised (a 128-wide colour layer; more weights than
//! the cap).
//!
//! The page's binary16 hash tables (`toBinary16` and `tablesSource` of `web/js/renderer.js`, run
//! by `web/tests/binary16.mjs`) are msth-gpu's `TableFormat::F16` bit for bit: the packed words
//! of values at every rounding boundary, and the kernels' source.
//!
//! The page plans the play-time volume as the native players do: `web/js/volume.js` (run by
//! `web/tests/volume_plan.mjs` on the page's decoder) chooses the same resolution, the same
//! static, dynamic and left-out bricks, the same dynamic cells, slices and thresholds as
//! msth-player's `plan_bake` for the same file and budget.
//!
//! Needs `node`; without it the test is reported as ignored with the reason, unless
//! `MSTH_REQUIRE_NODE=1` (CI sets `MSTH_REQUIRE_ALL=1`).

use std::path::Path;
use std::process::Command;

use msth_core::config::{Background, ModelConfig, Preset};
use msth_core::field::ModelLayout;
use msth_core::rng::Rng;
use msth_core::SceneBounds;
use msth_gpu::specialise::{specialised_region, MAX_SPECIALISED_WEIGHTS};
use msth_gpu::{GpuModel, TableFormat};
use msth_testkit::{Need, Tests};

fn main() -> std::process::ExitCode {
    let node = Need::program("node", Some("MSTH_NODE"), "node", &["--version"]);
    Tests::new(file!())
        .needs(
            &[&node],
            "javascript_and_rust_specialise_the_same_text",
            javascript_and_rust_specialise_the_same_text,
        )
        .needs(
            &[&node],
            "javascript_and_rust_plan_the_same_volume",
            javascript_and_rust_plan_the_same_volume,
        )
        .needs(
            &[&node],
            "javascript_and_rust_hold_binary16_tables_alike",
            javascript_and_rust_hold_binary16_tables_alike,
        )
        .run()
}

fn config(name: &str) -> ModelConfig {
    let preset = if name == "balanced" {
        Preset::Balanced
    } else {
        Preset::Fast
    };
    let mut c = ModelConfig::preset(
        preset,
        SceneBounds::dnerf_default(),
        Background::Color { rgb: [1.0; 3] },
        4,
    );
    // Small tables: the file's size does not matter here, only its MLPs.
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        let levels = enc.grid3.levels;
        enc.resize(levels, 8, 16.0, 8);
    }
    match name {
        "three_layers" => c.field.color_layers = 3,
        "one_feature" => {
            c.field.encoding.grid3.features_per_level = 1;
            c.field.encoding.grid4.features_per_level = 1;
        }
        "static" => c.field.encoding.blend = msth_core::config::BlendMode::Static,
        "four_d" => c.field.encoding.blend = msth_core::config::BlendMode::FourD,
        "add" => c.field.encoding.blend = msth_core::config::BlendMode::Add,
        "wide" => {
            c.field.color_hidden = 128;
            c.field.color_layers = 1;
        }
        "many_weights" => {
            c.field.color_hidden = 64;
            c.field.color_layers = 4;
        }
        _ => {}
    }
    c
}

fn javascript_and_rust_specialise_the_same_text() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let dir = tempfile::tempdir().unwrap();
    let mut specialised = 0;
    for name in [
        "fast",
        "balanced",
        "three_layers",
        "one_feature",
        "static",
        "four_d",
        "add",
        "wide",
        "many_weights",
    ] {
        let cfg = config(name);
        let layout = ModelLayout::new(&cfg);
        let mut params = layout.init_params(7);
        // Weights of every sign and magnitude, zeros and subnormals among them.
        let mut rng = Rng::new(3);
        for (i, v) in params.iter_mut().enumerate() {
            *v = match i % 97 {
                0 => 0.0,
                1 => -0.0,
                2 => 1e-41,
                _ => rng.range_f32(-2.0, 2.0),
            };
        }
        let cam = msth_core::Camera::look_at(
            8,
            8,
            0.8,
            glam::Vec3::new(0.0, -4.0, 1.0),
            glam::Vec3::ZERO,
            glam::Vec3::Z,
        );
        let opts = msth_codec::EncodeOptions {
            quant: msth_codec::QuantMode::F32,
            ..Default::default()
        };
        let (bytes, _) = msth_codec::encode(&cfg, &params, &[cam], &opts).unwrap();
        let file = dir.path().join(format!("{name}.msth"));
        std::fs::write(&file, &bytes).unwrap();

        let decoded = msth_codec::decode_all(&bytes).unwrap();
        let p = decoded.params_for_time(0.0);
        let gm = GpuModel::new(&cfg).unwrap();
        let rust = match specialised_region(&gm, &p[gm.split.rest.clone()]) {
            Ok(text) => {
                specialised += 1;
                text
            }
            Err(e) => format!("error: {e}\n"),
        };
        let out = Command::new("node")
            .current_dir(&root)
            .arg("web/tests/specialise.mjs")
            .arg(&file)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{name}: node failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let js = String::from_utf8(out.stdout).unwrap();
        if js != rust {
            let line = js
                .lines()
                .zip(rust.lines())
                .position(|(a, b)| a != b)
                .unwrap_or(js.lines().count().min(rust.lines().count()));
            panic!(
                "{name}: specialise.js and specialise.rs differ from line {} on:\njs:   {}\nrust: {}",
                line + 1,
                js.lines().nth(line).unwrap_or("(end)"),
                rust.lines().nth(line).unwrap_or("(end)")
            );
        }
        let what = if rust.starts_with("error: ") {
            rust.trim_end().to_string()
        } else {
            format!("{} bytes of WGSL", rust.len())
        };
        println!("{name}: the same in both languages ({what})");
        match name {
            "wide" => assert!(rust.contains("at most 64 are specialised"), "{rust}"),
            "many_weights" => assert!(
                rust.contains(&format!(
                    "at most {MAX_SPECIALISED_WEIGHTS} are specialised"
                )),
                "{rust}"
            ),
            _ => assert!(!rust.starts_with("error: "), "{name}: {rust}"),
        }
    }
    assert_eq!(specialised, 7);
}

fn javascript_and_rust_hold_binary16_tables_alike() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let dir = tempfile::tempdir().unwrap();
    // Every rounding case: exact values, ties either way, the ends of the normal range (the
    // least normal, just below it, the flush to zero), the clamp at 65504, signed zeros; then
    // random values over many magnitudes. An odd count (the last word padded).
    let mut values = vec![
        0.0,
        -0.0,
        1.0,
        -2.5,
        1.0 + 2f32.powi(-11),
        1.0 + 3.0 * 2f32.powi(-11),
        -(1.0 + 2f32.powi(-11) + 2f32.powi(-20)),
        2f32.powi(-14),
        2f32.powi(-14) - 2f32.powi(-25),
        2f32.powi(-14) - 2f32.powi(-24),
        -(2f32.powi(-14) - 2f32.powi(-26)),
        1e-6,
        -1e-30,
        1e-41,
        65504.0,
        65519.0,
        65520.0,
        1e6,
        -3e38,
        f32::MAX,
        2047.5,
        2048.5,
    ];
    let mut rng = Rng::new(9);
    for _ in 0..20_001 {
        let mag = 2f32.powf(rng.range_f32(-30.0, 20.0));
        values.push(if rng.range_f32(0.0, 1.0) < 0.5 {
            -mag
        } else {
            mag
        });
    }
    let input = dir.path().join("values.f32");
    let (bin, wgsl) = (dir.path().join("out.bin"), dir.path().join("out.wgsl"));
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&input, bytes).unwrap();
    let out = Command::new("node")
        .current_dir(&root)
        .arg("web/tests/binary16.mjs")
        .args([&input, &bin, &wgsl])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "node failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let js = std::fs::read(&bin).unwrap();
    let rust = TableFormat::F16.encode(&values);
    assert_eq!(js.len(), rust.len());
    if let Some(i) = (0..js.len() / 2).find(|&i| js[2 * i..2 * i + 2] != rust[2 * i..2 * i + 2]) {
        panic!(
            "value {i} ({:e}): js {:02x?}, rust {:02x?}",
            values.get(i).copied().unwrap_or(0.0),
            &js[2 * i..2 * i + 2],
            &rust[2 * i..2 * i + 2]
        );
    }
    // Both count the values the clamp changes alike.
    let stdout = String::from_utf8_lossy(&out.stdout);
    let clamped = TableFormat::F16.clamped(&values);
    assert!(
        clamped >= 5,
        "the values above hold 5 beyond ±65504: {clamped}"
    );
    assert_eq!(
        stdout.trim(),
        format!("{{\"clamped\":{clamped}}}"),
        "the page's count of clamped values"
    );
    let source = std::fs::read_to_string(&wgsl).unwrap();
    assert!(
        Some(source) == TableFormat::F16.source(msth_gpu::RENDER_WGSL),
        "the page's binary16 kernels differ from TableFormat::F16.source"
    );
    println!(
        "{} values packed alike in both languages, {clamped} of them clamped",
        values.len()
    );
}

fn javascript_and_rust_plan_the_same_volume() {
    use msth_core::volume::OutsideViews;
    use msth_player::volume::{plan_bake, VolumeOptions};
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let dir = tempfile::tempdir().unwrap();
    // The fixture with a mask that splits the scene (static and dynamic bricks), as it is and
    // with one narrow camera (so that a budget leaves bricks out of the views).
    let split = msth_tests::split_mask_fixture();
    let d = msth_codec::decode_all(&split).unwrap();
    let narrow = {
        let mut cam = d.cameras[0];
        cam.fx *= 3.0;
        cam.fy *= 3.0;
        msth_tests::reencode(&d, &d.params, &[cam])
    };
    let mut kinds = std::collections::BTreeSet::new();
    for (name, bytes) in [("split", &split), ("narrow", &narrow)] {
        let file = dir.path().join(format!("{name}.msth"));
        std::fs::write(&file, bytes).unwrap();
        let d = msth_codec::decode_all(bytes).unwrap();
        let policies = [OutsideViews::Auto, OutsideViews::Exact, OutsideViews::Bake];
        for (outside, budget) in policies
            .into_iter()
            .flat_map(|o| [512u64 << 20, 1 << 20, 300 << 10, 100 << 10, 4 << 10].map(|b| (o, b)))
        {
            let rust = plan_bake(
                &d.config,
                &d.params,
                d.occupancy.as_ref(),
                &d.cameras,
                &VolumeOptions {
                    budget: Some(budget),
                    outside,
                    ..Default::default()
                },
            );
            let out = Command::new("node")
                .current_dir(&root)
                .arg("web/tests/volume_plan.mjs")
                .arg(&file)
                .arg(budget.to_string())
                .arg(outside.name())
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{name}: node failed:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
            let js: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
            let what = format!("{name} at {budget} bytes, outside {}", outside.name());
            let plan = match rust {
                Ok(plan) => plan,
                Err(e) => {
                    let err = js["error"]
                        .as_str()
                        .unwrap_or_else(|| panic!("{what}: rust refuses ({e}), js plans {js}"));
                    assert!(err.starts_with("even a 32^3 volume needs"), "{what}: {err}");
                    kinds.insert("over budget");
                    println!("{what}: both refuse: {err}");
                    continue;
                }
            };
            let ints = |k: &str| -> Vec<u64> {
                js[k]
                    .as_array()
                    .unwrap_or_else(|| panic!("{what}: {k} missing in {js}"))
                    .iter()
                    .map(|v| v.as_u64().unwrap())
                    .collect()
            };
            let widen = |v: &[u32]| v.iter().map(|&x| x as u64).collect::<Vec<_>>();
            assert_eq!(
                js["resolution"].as_u64(),
                Some(plan.geometry.resolution as u64),
                "{what}"
            );
            assert_eq!(
                js["brick"].as_u64(),
                Some(plan.geometry.brick as u64),
                "{what}"
            );
            for (k, rust) in [
                ("static_bricks", &plan.static_bricks),
                ("dynamic_bricks", &plan.dynamic_bricks),
                ("dynamic_cells", &plan.dynamic_cells),
                ("outside_bricks", &plan.outside_bricks),
            ] {
                assert_eq!(ints(k), widen(rust), "{what}: {k}");
            }
            assert_eq!(
                js["resident_slices"].as_u64(),
                Some(plan.resident_slices as u64),
                "{what}"
            );
            let times: Vec<f64> = js["slice_times"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            assert_eq!(
                times,
                plan.slice_times
                    .iter()
                    .map(|&t| t as f64)
                    .collect::<Vec<_>>(),
                "{what}"
            );
            for (k, want) in [
                ("density_threshold", plan.density_threshold),
                ("proposal_threshold", plan.proposal_threshold),
            ] {
                let got = js[k].as_f64().unwrap();
                assert!(
                    (got - want as f64).abs() <= 1e-6 * want.abs() as f64,
                    "{what}: {k} {got} against {want}"
                );
            }
            if !plan.outside_bricks.is_empty() {
                kinds.insert("bricks left out");
                if budget == 512 << 20 {
                    kinds.insert("left out within the budget");
                }
            }
            if plan.geometry.resolution < plan.requested_resolution {
                kinds.insert("coarser");
            }
            if !plan.dynamic_bricks.is_empty() && !plan.static_bricks.is_empty() {
                kinds.insert("static and dynamic");
            }
            println!(
                "{what}: the same plan: {}^3, {} static, {} dynamic, {} left out, {} of {} slices resident",
                plan.geometry.resolution,
                plan.static_bricks.len(),
                plan.dynamic_bricks.len(),
                plan.outside_bricks.len(),
                plan.resident_slices,
                plan.slice_times.len()
            );
        }
    }
    // The budgets reach every branch of the plan.
    assert_eq!(
        kinds.into_iter().collect::<Vec<_>>(),
        [
            "bricks left out",
            "coarser",
            "left out within the budget",
            "over budget",
            "static and dynamic"
        ]
    );
}
