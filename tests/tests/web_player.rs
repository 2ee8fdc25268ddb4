//! The web player (`web/`) end to end: built-in scene -> train (short) -> `msth export` -> the
//! server `msth serve --web web` runs, on a random loopback port -> headless Chromium (driven by
//! `web/tests/browser.mjs` through playwright-core) loads the page, which streams the file with
//! Range requests, decodes it in JavaScript and renders it with WebGPU (SwiftShader) using the
//! native renderer's WGSL. The page's frames must match `msth play` of the same camera and time
//! (PSNR >= 35 dB), for a `balanced`-preset model as well, also with the samples menu at
//! `faster` against `msth play --samples faster`, and with its kernels compiled for the model as
//! with the generic ones (`?mlp=generic`); dragging must orbit; scrubbing must
//! change the dynamic pixels and not the static ones, re-rendering only the dynamic pixels once
//! the static cache is built; without WebGPU the page must say so. The JavaScript decoder is also checked
//! bit-exactly against msth-codec's flat parameter buffers (`web/tests/decode.mjs`).
//!
//! Needs `node`, Chromium (`MSTH_CHROMIUM`, else `/usr/bin/chromium` or `chromium` on `PATH`)
//! and `npm ci --prefix web`; without them the test is reported as ignored with the reason,
//! unless `MSTH_REQUIRE_BROWSER=1` (CI), where it fails. This binary runs on `msth-testkit`'s
//! harness (`harness = false`), and [`main`] lists its tests.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use msth_core::config::Preset;
use msth_core::field::ModelLayout;
use msth_player::path::Rig;
use msth_server::{BackgroundServer, ServerConfig};
use msth_testkit::{Need, Tests};
use msth_tests::{export_cmd, fixture_run, msth, read_json, tiny_scene};
use msth_trainer::checkpoint::Checkpoint;
use msth_trainer::train::{train, TrainSettings};

fn main() -> std::process::ExitCode {
    let browser = Need::new("browser", || prerequisites().map(drop));
    Tests::new(file!())
        .needs(
            &[&browser],
            "web_player_streams_renders_and_matches_native",
            web_player_streams_renders_and_matches_native,
        )
        .run()
}

/// Image size of the compared frames (SwiftShader renders a few thousand rays per second).
const SIZE: (u32, u32) = (32, 24);
/// Longest a browser script may run before it is killed.
const BROWSER_TIMEOUT: Duration = Duration::from_secs(25 * 60);

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn find_chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("MSTH_CHROMIUM") {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    let fixed = Path::new("/usr/bin/chromium");
    if fixed.is_file() {
        return Some(fixed.to_path_buf());
    }
    std::env::split_paths(&std::env::var_os("PATH")?)
        .flat_map(|d| ["chromium", "chromium-browser"].map(|n| d.join(n)))
        .find(|p| p.is_file())
}

/// What the test needs, or why it cannot run.
fn prerequisites() -> Result<PathBuf, String> {
    let node = Command::new("node").arg("--version").output();
    if !node.map(|o| o.status.success()).unwrap_or(false) {
        return Err("`node` is not installed".into());
    }
    let chromium = find_chromium()
        .ok_or("Chromium is not installed (or MSTH_CHROMIUM names no file): install the `chromium` package")?;
    let web = repo_root().join("web");
    for dep in ["fzstd", "playwright-core"] {
        if !web
            .join("node_modules")
            .join(dep)
            .join("package.json")
            .is_file()
        {
            return Err(format!(
                "web/node_modules/{dep} is missing (run `npm ci --prefix web`)"
            ));
        }
    }
    if !web.join("shaders/render.wgsl").is_file() {
        return Err("web/shaders/render.wgsl is missing".into());
    }
    Ok(chromium)
}

/// Runs a command with a time limit, echoing its output; returns (success, output).
fn run_node(args: &[&str], timeout: Duration) -> (bool, String) {
    let mut child = Command::new("node")
        .args(args)
        .current_dir(repo_root())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("node starts");
    let mut out = child.stdout.take().expect("stdout");
    let mut err = child.stderr.take().expect("stderr");
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        out.read_to_string(&mut s).ok();
        let mut e = String::new();
        err.read_to_string(&mut e).ok();
        s + &e
    });
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait") {
            break Some(s);
        }
        if start.elapsed() > timeout {
            child.kill().ok();
            child.wait().ok();
            break None;
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    let text = reader.join().unwrap_or_default();
    println!("$ node {}\n{text}", args.join(" "));
    match status {
        Some(s) => (s.success(), text),
        None => (false, format!("{text}\n(killed after {timeout:?})")),
    }
}

fn web_player_streams_renders_and_matches_native() {
    let chromium = prerequisites().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (_, data) = tiny_scene();
    let s = fixture_run(&data);
    let train_dir = dir.path().join("train");
    train(&data, s, &train_dir, None, &mut |_| true).unwrap();

    // A quantised file with several chunks: the page streams and decodes them all.
    let served = dir.path().join("models");
    std::fs::create_dir_all(&served).unwrap();
    let file = served.join("tiny.msth");
    let q8 = ["--quant", "q8", "--chunk-frames", "2"];
    export_cmd(&train_dir.join("model.ckpt"), &file, &q8).unwrap();
    // The same model in two progressive layers (format version 4).
    let layered = served.join("layered.msth");
    export_cmd(
        &train_dir.join("model.ckpt"),
        &layered,
        &["--quant", "q8", "--chunk-frames", "2", "--layers", "2"],
    )
    .unwrap();

    // A balanced-preset model (#17: the page renders its layout as the native renderers do:
    // 16 levels, 2^17-row tables, 96 proposal + 32 main samples per ray). A few steps: what is
    // checked is that the renderers agree, not what the model learnt.
    let mut sb = TrainSettings::for_preset(Preset::Balanced, &data);
    (
        sb.iters,
        sb.batch_rays,
        sb.anneal_steps,
        sb.checkpoint_every,
    ) = (8, 256, 2, 0);
    let train_balanced = dir.path().join("train_balanced");
    train(&data, sb, &train_balanced, None, &mut |_| true).unwrap();
    // Half the scene static (mask logit 9: `1 - m` below the renderers' static cutoff) in both
    // fields, so that the page's live lists hold samples with and without a 4D lookup, for
    // `pass_proposal3` and `pass_density3`.
    let ckpt_path = train_balanced.join("model.ckpt");
    let mut ckpt = Checkpoint::load(&ckpt_path).unwrap();
    let layout = ModelLayout::new(&ckpt.header.model);
    for mask in [
        &layout.field.encoding.mask,
        &layout.proposal.field.encoding.mask,
    ] {
        let (grid, range) = mask.clone().expect("the balanced preset has masks");
        for (k, v) in ckpt.params[range].iter_mut().enumerate() {
            if k % grid.res < grid.res / 2 {
                *v = 9.0;
            }
        }
    }
    ckpt.save(&ckpt_path).unwrap();
    let balanced = served.join("balanced.msth");
    export_cmd(
        &train_balanced.join("model.ckpt"),
        &balanced,
        &["--quant", "q8"],
    )
    .unwrap();

    // The tiny model with three hash-table values beyond binary16's range (±65504), quantised:
    // the page holds its tables as binary16 and must say how many values it clamped, as `msth
    // play` does (counted here as msth-gpu counts them, over the four tables the buffers hold).
    let mut wide_ckpt = Checkpoint::load(&train_dir.join("model.ckpt")).unwrap();
    let wide_layout = ModelLayout::new(&wide_ckpt.header.model);
    let h3 = wide_layout.field.encoding.h3.clone().unwrap().1;
    let h4 = wide_layout.field.encoding.h4.clone().unwrap().1;
    for (at, v) in [
        (h3.start + 5, 2e5),
        (h3.start + 40, -1e6),
        (h4.start + 9, 3e5),
    ] {
        wide_ckpt.params[at] = v;
    }
    let wide_dir = dir.path().join("train_wide");
    std::fs::create_dir_all(&wide_dir).unwrap();
    wide_ckpt.save(&wide_dir.join("model.ckpt")).unwrap();
    let wide = served.join("wide.msth");
    export_cmd(&wide_dir.join("model.ckpt"), &wide, &["--quant", "q8"]).unwrap();
    let wide_params = msth_codec::decode_all(&std::fs::read(&wide).unwrap())
        .unwrap()
        .params_for_time(0.0);
    let split = msth_gpu::GpuModel::new(&wide_ckpt.header.model)
        .unwrap()
        .split;
    let wide_clamped: usize = split
        .tables()
        .iter()
        .flatten()
        .map(|(_, _, r)| msth_gpu::TableFormat::F16.clamped(&wide_params[r.clone()]))
        .sum();
    // The two 3D values at least (the file keeps only the 4D rows the mask calls dynamic).
    assert!(wide_clamped >= 2, "{wide_clamped}");
    let wide_clamped = wide_clamped.to_string();

    // The JavaScript decoder reproduces msth-codec's flat parameter buffers bit for bit.
    let bytes = std::fs::read(&file).unwrap();
    let decoded = msth_codec::decode_all(&bytes).unwrap();
    let mut refs = Vec::new();
    for t in [0.0f32, 0.5, 1.0] {
        let p = dir.path().join(format!("params_{t}.f32"));
        let raw: Vec<u8> = decoded
            .params_for_time(t)
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        std::fs::write(&p, raw).unwrap();
        refs.push(format!("{t}={}", p.display()));
    }
    let mut args = vec!["web/tests/decode.mjs", file.to_str().unwrap()];
    args.extend(refs.iter().map(String::as_str));
    let (ok, out) = run_node(&args, Duration::from_secs(300));
    assert!(
        ok,
        "the JavaScript decoder disagrees with msth-codec:\n{out}"
    );
    // ... and rejects damaged copies of the file with a clear error.
    let (ok, out) = run_node(
        &["web/tests/decode_bad.mjs", file.to_str().unwrap()],
        Duration::from_secs(300),
    );
    assert!(ok, "the JavaScript decoder mishandles bad input:\n{out}");

    // Native references: `msth play` of the same free viewpoint at t = 0 and t = 1, on the CPU
    // renderer (the reference the GPU kernels are tested against).
    let meta = &decoded.metadata;
    let rig = Rig::new(&meta.model.bounds, &meta.cameras, meta.cameras[0]);
    let view = format!("30,25,{:.3}", 1.4 * rig.radius);
    let size = format!("{}x{}", SIZE.0, SIZE.1);
    let mut natives = Vec::new();
    for (name, src, t, samples) in [
        // The page starts at `fast` on a software adapter (SwiftShader here).
        ("0", &file, "0", "fast"),
        ("1", &file, "1", "fast"),
        ("balanced", &balanced, "0", "full"),
        ("balanced_faster", &balanced, "0", "faster"),
    ] {
        let out = dir.path().join(format!("native_{name}"));
        msth(&[
            "play",
            src.to_str().unwrap(),
            "--path",
            &format!("view:{view}"),
            "--size",
            &size,
            "--frames",
            "1",
            "--time",
            &format!("{t}:{t}"),
            "--out",
            out.to_str().unwrap(),
            "--no-video",
            "--quiet",
            "--cpu",
            "--samples",
            samples,
        ])
        .unwrap();
        natives.push(out.join("frame_00000.png"));
    }

    // The play-time volume: the fixture whose mask splits the scene (static and dynamic bricks),
    // drawn by the native CPU renderer's volume at its camera, between two time slices.
    let split = served.join("split.msth");
    std::fs::write(&split, msth_tests::split_mask_fixture()).unwrap();
    let native_volume = dir.path().join("native_volume");
    msth(&[
        "play",
        split.to_str().unwrap(),
        "--path",
        "0",
        "--frames",
        "1",
        "--time",
        "0.37:0.37",
        "--out",
        native_volume.to_str().unwrap(),
        "--no-video",
        "--quiet",
        "--cpu",
        "--volume",
        "--bake-first",
        "--volume-slices",
        "always",
        "--volume-still",
        "--volume-budget",
        "64",
    ])
    .unwrap();
    let native_volume = native_volume.join("frame_00000.png");

    // The server `msth serve --web web` runs, on a random loopback port.
    let server = BackgroundServer::start(ServerConfig {
        addr: "127.0.0.1:0".parse().unwrap(),
        web_dir: Some(repo_root().join("web")),
        ..ServerConfig::new(&served)
    })
    .unwrap();
    let base = format!("http://{}", server.addr());
    let results = dir.path().join("browser.json");
    // README screenshots (issue #17): `MSTH_UPDATE_SCREENSHOTS=1` writes the page, paused at
    // t = 0.5 at the file's camera 0 (its first training camera), to docs/images/web-player.png;
    // `MSTH_SCREENSHOT_MODEL=FILE.msth` (e.g. `msth demo`'s scene.msth) is served beside the
    // test's model and shown instead.
    let screenshot = repo_root().join("docs/images/web-player.png");
    let mut extra: Vec<String> = Vec::new();
    if std::env::var("MSTH_UPDATE_SCREENSHOTS").is_ok_and(|v| v == "1") {
        extra.extend(["--screenshot".into(), screenshot.display().to_string()]);
        if let Some(m) = std::env::var_os("MSTH_SCREENSHOT_MODEL") {
            std::fs::copy(&m, served.join("screenshot.msth")).unwrap();
            extra.extend(["--screenshot-model".into(), "screenshot.msth".into()]);
        }
        // Files exported before the trainer listed the training cameras first have the
        // held-out camera at 0: `MSTH_SCREENSHOT_CAMERA=1` shows a training camera of those.
        if let Ok(k) = std::env::var("MSTH_SCREENSHOT_CAMERA") {
            extra.extend(["--screenshot-camera".into(), k]);
        }
    }
    let (ok, out) = run_node(
        &[
            "web/tests/browser.mjs",
            "--base",
            &base,
            "--model",
            "tiny.msth",
            "--view",
            &view,
            "--size",
            &size,
            "--native0",
            natives[0].to_str().unwrap(),
            "--native1",
            natives[1].to_str().unwrap(),
            "--model2",
            "balanced.msth",
            "--native2",
            natives[2].to_str().unwrap(),
            "--native2-faster",
            natives[3].to_str().unwrap(),
            "--model-wide",
            "wide.msth",
            "--model-layered",
            "layered.msth",
            "--wide-clamped",
            &wide_clamped,
            "--model-volume",
            "split.msth",
            "--native-volume",
            native_volume.to_str().unwrap(),
            "--chromium",
            chromium.to_str().unwrap(),
            "--out",
            results.to_str().unwrap(),
        ]
        .into_iter()
        .chain(extra.iter().map(String::as_str))
        .collect::<Vec<_>>(),
        BROWSER_TIMEOUT,
    );
    assert!(ok, "the browser test failed:\n{out}");
    let r = read_json(&results);
    let checks = r["checks"].as_array().unwrap();
    assert!(
        checks.len() >= 15 && checks.iter().all(|c| c["ok"] == true),
        "{r:#}"
    );
    assert!(r["figures"]["psnr_vs_native_t0"].as_f64().unwrap() >= 35.0);
    assert!(r["figures"]["psnr_layered_vs_one_layer"].as_f64().unwrap() >= 40.0);
    assert!(
        r["figures"]["psnr_volume_vs_native_volume"]
            .as_f64()
            .unwrap()
            >= 35.0
    );
    assert!(r["figures"]["psnr_model2_vs_native"].as_f64().unwrap() >= 35.0);
    assert!(
        r["figures"]["psnr_model2_faster_vs_native"]
            .as_f64()
            .unwrap()
            >= 35.0
    );
    println!("figures: {:#}", r["figures"]);
}
