//! `msth view` in a real window: an X server of its own (Xvfb), the window drawn through wgpu
//! (Mesa's lavapipe where there is no GPU), the viewer's event loop driven by a script of input
//! events (key presses, drags, the wheel) that take the same path as a person's.
//!
//! A small model of the built-in scene is trained and exported losslessly (or
//! `MSTH_VIEW_MODEL=FILE.msth` with `MSTH_VIEW_CKPT=model.ckpt` names another, such as the demo's),
//! then the viewer opens it paused at t = 0.5 and
//! 1. shows file camera 0 and, after the key `2`, file camera 2: the pictures it rendered and the
//!    window's screenshots (the picture's pixels, the overlay left out) must match `msth play` of
//!    that camera and time and `msth render` of the checkpoint at >= 35 dB;
//! 2. records a camera path (the key `R`) over a drag, a wheel step and a pan; `msth play --path`
//!    of the recorded file must render as many frames as were recorded, its last one the view
//!    shown when the recording stopped (>= 35 dB against the viewer's picture);
//! 3. plays for a second (space): the timeline must advance through several times;
//! 4. where the renderer draws volumes (the CPU renderer), turns the play-time volume on (the key
//!    `V`): once baked, the view is drawn from it, close to the exact picture; `V` again draws the
//!    exact picture again.
//!
//! Without Xvfb or without a wgpu adapter the test is reported as ignored, unless
//! `MSTH_REQUIRE_DISPLAY=1` / `MSTH_REQUIRE_GPU=1` (or `MSTH_REQUIRE_ALL=1`).
//! `MSTH_VIEW_SCREENSHOTS=DIR` copies the window screenshots there (the README's pictures).

use std::path::{Path, PathBuf};

use msth_testkit::Tests;
use msth_tests::{display_need, export_cmd, gpu_need, render_cmd, short_run, tiny_scene, Xvfb};
use msth_trainer::train::train;
use msth_viewer::{Script, ViewOptions, ViewReport};

fn main() -> std::process::ExitCode {
    let display = display_need();
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&display, &gpu],
            "the_window_flies_plays_and_matches_msth_play_and_render",
            the_window_flies_plays_and_matches_msth_play_and_render,
        )
        .run()
}

fn read_rgb(p: &Path) -> (u32, u32, Vec<u8>) {
    let img = image::open(p)
        .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
        .to_rgb8();
    let (w, h) = img.dimensions();
    (w, h, img.into_raw())
}

/// PSNR (dB) of two 8-bit pictures over the pixels `keep` accepts.
fn psnr8(a: &[u8], b: &[u8], w: u32, keep: impl Fn(u32, u32) -> bool) -> f64 {
    assert_eq!(a.len(), b.len());
    let (mut se, mut n) = (0f64, 0usize);
    for (i, (pa, pb)) in a.chunks(3).zip(b.chunks(3)).enumerate() {
        let (x, y) = (i as u32 % w, i as u32 / w);
        if !keep(x, y) {
            continue;
        }
        for c in 0..3 {
            se += ((pa[c] as f64 - pb[c] as f64) / 255.0).powi(2);
            n += 1;
        }
    }
    assert!(n > 0, "no pixels compared");
    -10.0 * (se / n as f64).max(1e-20).log10()
}

/// The picture's pixels in a window screenshot: the centre of each rendered pixel's block (the
/// viewer shows a full-size frame at an integer zoom, nearest filtered), and which of them the
/// overlay covers.
fn picture_in_window(
    window: &Path,
    rect: [u32; 4],
    overlay: [u32; 4],
    (w, h): (u32, u32),
) -> (Vec<u8>, Vec<bool>) {
    let (ww, _, px) = read_rgb(window);
    let zoom = rect[2] / w;
    assert!(
        zoom >= 1 && rect[2] == w * zoom && rect[3] == h * zoom,
        "{rect:?} for {w}x{h}"
    );
    let mut out = Vec::with_capacity((w * h * 3) as usize);
    let mut covered = Vec::with_capacity((w * h) as usize);
    for y in 0..h {
        for x in 0..w {
            let (wx, wy) = (rect[0] + x * zoom + zoom / 2, rect[1] + y * zoom + zoom / 2);
            let i = ((wy * ww + wx) * 3) as usize;
            out.extend_from_slice(&px[i..i + 3]);
            // The block touches the overlay's rectangle (plus a pixel of its rounded corners).
            let (x0, y0, x1, y1) = (
                rect[0] + x * zoom,
                rect[1] + y * zoom,
                rect[0] + (x + 1) * zoom,
                rect[1] + (y + 1) * zoom,
            );
            covered.push(
                x1 + 1 >= overlay[0]
                    && x0 <= overlay[0] + overlay[2] + 1
                    && y1 + 1 >= overlay[1]
                    && y0 <= overlay[1] + overlay[3] + 1,
            );
        }
    }
    (out, covered)
}

fn play_one(file: &Path, out: &Path, path: &str, extra: &[&str]) -> PathBuf {
    let mut args = vec![
        "play",
        file.to_str().unwrap(),
        "--path",
        path,
        "--out",
        out.to_str().unwrap(),
        "--no-video",
        "--quiet",
    ];
    args.extend_from_slice(extra);
    msth_tests::msth(&args).unwrap_or_else(|e| panic!("msth play: {e}"));
    out.to_path_buf()
}

fn the_window_flies_plays_and_matches_msth_play_and_render() {
    let dir = tempfile::tempdir().unwrap();
    let (file, ckpt) = match (
        std::env::var_os("MSTH_VIEW_MODEL"),
        std::env::var_os("MSTH_VIEW_CKPT"),
    ) {
        (Some(f), Some(c)) => (PathBuf::from(f), PathBuf::from(c)),
        _ => {
            let (_, data) = tiny_scene();
            let s = short_run(&data, 60);
            let train_dir = dir.path().join("train");
            train(&data, s, &train_dir, None, &mut |_| true).unwrap();
            let file = dir.path().join("tiny.msth");
            let ckpt = train_dir.join("model.ckpt");
            export_cmd(&ckpt, &file, &["--quant", "f32", "--chunk-frames", "2"]).unwrap();
            (file, ckpt)
        }
    };
    let shots = dir.path().join("shots");
    std::fs::create_dir_all(&shots).unwrap();
    let shot = |name: &str| {
        serde_json::json!({"screenshot": {
            "frame": shots.join(format!("{name}.png")),
            "window": shots.join(format!("{name}-window.png")),
        }})
    };
    let script = serde_json::json!({"steps": [
        {"wait_still": 300},
        shot("camera0"),
        {"key": "2"},
        {"wait_still": 300},
        shot("camera2"),
        {"key": "R"},
        {"drag": {"from": [0.5, 0.5], "to": [0.68, 0.42], "steps": 6}},
        {"scroll": 1},
        {"drag": {"from": [0.5, 0.5], "to": [0.47, 0.52], "steps": 3, "button": "right"}},
        {"wait_still": 300},
        {"key": "R"},
        shot("free"),
        {"key": "Space"},
        {"wait": 1.5},
        {"key": "Space"},
        {"wait_still": 300},
        shot("played"),
        {"key": "V"},
        {"wait_still": 600},
        shot("volume"),
        {"key": "V"},
        {"wait_still": 300},
        shot("exact"),
        {"quit": true},
    ]});
    let script_path = dir.path().join("script.json");
    std::fs::write(&script_path, script.to_string()).unwrap();
    let mut opts = ViewOptions::new(file.to_str().unwrap());
    opts.time = Some(0.5);
    opts.out = dir.path().join("out");
    opts.script = Some(Script::load(&script_path).unwrap());
    opts.window_size = Some((900, 560));

    let x = Xvfb::start(1280, 1024).expect("the display need was met a moment ago");
    std::env::set_var("DISPLAY", &x.display);
    std::env::remove_var("WAYLAND_DISPLAY");
    let report: ViewReport = msth_viewer::run(&opts).unwrap_or_else(|e| panic!("msth view: {e}"));
    drop(x);
    println!(
        "window: {}; renderer: {:?}; {} frames shown in {:.1} s",
        report.window_adapter,
        report.backend.as_ref().map(|b| (b.kind, b.device.clone())),
        report.frames.len(),
        report.seconds
    );
    assert_eq!(report.screenshots.len(), 6, "{:?}", report.screenshots);

    // 1. File cameras 0 and 2 at t = 0.5 against msth play and msth render.
    for (i, (name, camera)) in [("camera0", 0usize), ("camera2", 2)].iter().enumerate() {
        let s = &report.screenshots[i];
        assert_eq!(s.file_camera, Some(*camera), "{name}");
        assert_eq!(s.time, 0.5, "{name}");
        let played = play_one(
            &file,
            &dir.path().join(format!("play-{name}")),
            &camera.to_string(),
            &["--frames", "1", "--time", "0.5:0.5"],
        )
        .join("frame_00000.png");
        let (w, h, reference) = read_rgb(&played);
        let (fw, fh, frame) = read_rgb(s.frame.as_ref().unwrap());
        assert_eq!((fw, fh), (w, h), "{name}: size");
        let p_frame = psnr8(&frame, &reference, w, |_, _| true);
        let (win, covered) = picture_in_window(
            s.window.as_ref().unwrap(),
            s.picture_rect,
            s.overlay_rect,
            (w, h),
        );
        let p_window = psnr8(&win, &reference, w, |x, y| !covered[(y * w + x) as usize]);
        let rendered = dir.path().join(format!("render-{name}.png"));
        render_cmd(
            &ckpt,
            &rendered,
            &["--camera", &camera.to_string(), "--time", "0.5"],
        )
        .unwrap();
        let (_, _, direct) = read_rgb(&rendered);
        let p_render = psnr8(&frame, &direct, w, |_, _| true);
        println!(
            "{name}: the viewer's picture against msth play {p_frame:.2} dB, against msth render {p_render:.2} dB; the window's pixels against msth play {p_window:.2} dB ({} of {} pixels under the overlay left out)",
            covered.iter().filter(|&&c| c).count(),
            covered.len()
        );
        assert!(p_frame >= 35.0, "{name}: {p_frame:.2} dB");
        assert!(p_window >= 35.0, "{name}: window {p_window:.2} dB");
        assert!(
            p_render >= 35.0,
            "{name}: against msth render {p_render:.2} dB"
        );
        assert!(
            covered.iter().filter(|&&c| !c).count() * 2 > covered.len(),
            "{name}: most of the picture is compared"
        );
    }
    // The jump showed camera 2, not camera 0 again.
    let (_, _, a) = read_rgb(report.screenshots[0].frame.as_ref().unwrap());
    let (_, _, b) = read_rgb(report.screenshots[1].frame.as_ref().unwrap());
    assert!(a != b, "cameras 0 and 2 show the same picture");

    // 2. The recorded path plays back through msth play; its last frame is the view shown.
    assert_eq!(report.paths.len(), 1, "{:?}", report.paths);
    let recorded = &report.paths[0];
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(recorded).unwrap()).unwrap();
    let entries = json["frames"].as_array().unwrap().len();
    assert!(entries >= 2, "{entries} frames recorded");
    let free = &report.screenshots[2];
    assert_eq!(free.file_camera, None, "the drag left the file camera");
    let last = &json["frames"][entries - 1];
    let m: [[f32; 4]; 4] = serde_json::from_value(last["transform_matrix"].clone()).unwrap();
    assert_eq!(m, free.camera, "the path ends at the view shown");
    let out = play_one(
        &file,
        &dir.path().join("play-path"),
        recorded.to_str().unwrap(),
        &[],
    );
    let pngs = msth_testkit::files_with_extension(&out, "png");
    assert_eq!(
        pngs.len(),
        entries,
        "msth play renders every recorded frame"
    );
    let (w, _, reference) = read_rgb(pngs.last().unwrap());
    let (_, _, frame) = read_rgb(free.frame.as_ref().unwrap());
    let p = psnr8(&frame, &reference, w, |_, _| true);
    let first = read_rgb(&pngs[0]).2;
    println!(
        "recorded path: {entries} frames; its last frame against the viewer's picture {p:.2} dB; the first and last frames differ: {}",
        first != reference
    );
    assert!(p >= 35.0, "recorded path: {p:.2} dB");
    assert!(first != reference, "the recorded path moves");

    // 3. The timeline advanced while playing.
    let played: Vec<f32> = report
        .frames
        .iter()
        .filter(|f| f.activity == msth_player::policy::Activity::Playing)
        .map(|f| f.time)
        .collect();
    let mut distinct = played.clone();
    distinct.sort_by(f32::total_cmp);
    distinct.dedup();
    println!(
        "playing: {} frames shown at {} times ({:?})",
        played.len(),
        distinct.len(),
        &played[..played.len().min(12)]
    );
    assert!(distinct.len() >= 3, "{played:?}");
    assert_ne!(report.screenshots[3].time, 0.5, "the timeline moved");

    // 4. The volume switch (the CPU renderer; the GPU renderer has no volume and ignores V).
    let cpu = report.backend.as_ref().is_some_and(|b| b.kind == "cpu");
    let shot_frame = |i: usize| read_rgb(report.screenshots[i].frame.as_ref().unwrap());
    let (w, _, played) = shot_frame(3);
    let (_, _, volume) = shot_frame(4);
    let (_, _, exact) = shot_frame(5);
    if cpu {
        assert!(report.volume_error.is_none(), "{:?}", report.volume_error);
        let v = report.volume.as_ref().expect("a volume was baked");
        let from_volume = report.frames.iter().filter(|f| f.volume).count();
        let p_volume = psnr8(&volume, &played, w, |_, _| true);
        let p_exact = psnr8(&exact, &played, w, |_, _| true);
        println!(
            "volume: {}^3 cells, {} bricks, baked in {:.2} s; {from_volume} frames drawn from it; against the exact picture {p_volume:.2} dB; V again: {p_exact:.2} dB",
            v.resolution, v.bricks, v.seconds
        );
        assert!(from_volume > 0, "no frame came from the volume");
        assert!(
            !report.frames.last().unwrap().volume,
            "V again: the exact field"
        );
        // A wrong volume (a shifted lookup, a missing slice, wrong colours) lands below 20 dB.
        assert!(p_volume >= 20.0, "volume: {p_volume:.2} dB");
        assert!(p_exact >= 35.0, "exact again: {p_exact:.2} dB");
    } else {
        assert!(report.volume.is_none() && report.frames.iter().all(|f| !f.volume));
        assert_eq!(exact, played, "V does nothing on the GPU renderer");
    }

    if let Some(to) = std::env::var_os("MSTH_VIEW_SCREENSHOTS") {
        let to = PathBuf::from(to);
        std::fs::create_dir_all(&to).unwrap();
        for s in &report.screenshots {
            let w = s.window.as_ref().unwrap();
            std::fs::copy(w, to.join(w.file_name().unwrap())).unwrap();
        }
        println!("window screenshots copied to {}", to.display());
    }
}
