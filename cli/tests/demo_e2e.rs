//! `msth demo --serve` end to end, shortened (a small built-in scene, 30 steps, a 14-frame tour
//! of 48x36 frames), as a separate process run from the repository root: the stages leave the
//! checkpoint, `scene.msth`, the tour, the frames and the MP4 (or, without ffmpeg, the frames and
//! a line saying so) and the strip picture; the printed page URL answers while the server runs,
//! Ctrl-C stops it; and every frame the demo played through its server equals `msth render` of
//! the same checkpoint at the frame's camera and time within the codec's stated tolerance.
//!
//! The tolerance: the demo exports with `q5`. The codec states per-mode PSNR floors of a decoded
//! file's render against the checkpoint's render (`tests/tests/codec_roundtrip.rs`,
//! `lossy_modes_render_close_to_the_checkpoint`): q6 32 dB, q4 25 dB. `q5` stores every block
//! with at least as many bits as `q4` (docs/format.md §5.3), so its floor is q4's, 25 dB; the
//! player's incremental frames add their own error (40 dB and up against full renders,
//! `tests/tests/play_e2e.rs`), far below it.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

mod support;
use support::KillOnDrop;

/// PSNR floor of a played frame against `msth render` (q5; see the module docs).
const Q5_FLOOR_DB: f64 = 25.0;

fn read_rgb(p: &Path) -> (u32, u32, Vec<u8>) {
    let img = image::open(p)
        .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
        .to_rgb8();
    let (w, h) = img.dimensions();
    (w, h, img.into_raw())
}

fn psnr(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mse = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = (x as f64 - y as f64) / 255.0;
            d * d
        })
        .sum::<f64>()
        / a.len() as f64;
    if mse == 0.0 {
        100.0
    } else {
        -10.0 * mse.log10()
    }
}

/// `GET path` on `addr` (HTTP/1.1, connection closed after): status line and body.
fn http_get(addr: &str, path: &str) -> (String, String) {
    let mut s = TcpStream::connect(addr).unwrap_or_else(|e| panic!("connecting to {addr}: {e}"));
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    (head.lines().next().unwrap_or("").to_string(), body.into())
}

/// The lines of `msth demo` up to the first one containing `until` (or the end).
fn lines_until(rx: &mpsc::Receiver<String>, until: &str, deadline: Instant) -> Vec<String> {
    let mut out = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) => {
                println!("demo| {line}");
                let done = line.contains(until);
                out.push(line);
                if done {
                    return out;
                }
            }
            Err(e) => panic!("msth demo: no line containing `{until}` ({e:?}); got {out:#?}"),
        }
    }
}

#[test]
fn shortened_demo_serves_plays_and_matches_msth_render() {
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let mut child = Command::new(env!("CARGO_BIN_EXE_msth"))
        .args(["demo", "--out", out.to_str().unwrap(), "--serve", "--cpu"])
        .args(["--size", "48x36", "--frames", "6", "--cameras", "6"])
        .args([
            "--iters",
            "30",
            "--play-size",
            "48x36",
            "--play-frames",
            "14",
        ])
        .current_dir(&repo)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting msth demo");
    let stdout = child.stdout.take().unwrap();
    let mut demo = KillOnDrop(child); // killed when the test fails half-way
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });

    // Every stage, then the server's line; a loaded 2-core machine gets 15 minutes.
    let deadline = Instant::now() + Duration::from_secs(900);
    let lines = lines_until(&rx, "Ctrl-C stops", deadline);
    for name in [
        "scene", "train", "eval", "export", "serve", "play", "video", "strip",
    ] {
        let n = lines
            .iter()
            .filter(|l| l.trim_start().starts_with(&format!("{name} ")))
            .count();
        assert_eq!(n, 1, "one `{name}` stage line expected in {lines:#?}");
    }
    let find = |key: &str| {
        lines
            .iter()
            .find(|l| l.starts_with(key))
            .unwrap_or_else(|| panic!("no line starting `{key}` in {lines:#?}"))
            .clone()
    };
    let playback = find("playback:");
    for word in ["time to first frame", "FPS", "fetched", "HTTP requests"] {
        assert!(playback.contains(word), "{playback}");
    }

    // The files each stage leaves.
    let scene = out.join("scene.msth");
    let ckpt = out.join("model.ckpt");
    for f in [
        &ckpt,
        &scene,
        &out.join("metrics.json"),
        &out.join("strip.png"),
    ] {
        assert!(f.is_file(), "{} missing", f.display());
    }
    let decoded = msth_codec::decode_all(&std::fs::read(&scene).unwrap()).unwrap();
    // Exported as `msth export` does by default: each part's mode chosen (`--quant auto`) and
    // play-time samples stored, no more than the model's own; the demo prints both.
    let parts = decoded
        .metadata
        .section_quant
        .expect("a version-3 file lists each part's mode");
    assert_eq!(decoded.metadata.quant, parts.finest());
    let s = decoded
        .metadata
        .play_samples
        .expect("the export stores play-time samples");
    let own = &decoded.config.sampler;
    assert!(
        s.proposal as usize <= own.num_proposal_samples && s.main as usize <= own.num_samples,
        "{s:?}"
    );
    for word in ["quant auto:", "play-time samples per ray:"] {
        assert!(lines.iter().any(|l| l.contains(word)), "no `{word}` line");
    }
    let tour: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("orbit.json")).unwrap()).unwrap();
    let tour = tour["frames"].as_array().unwrap().clone();
    let frame_png = |i: usize| out.join("frames").join(format!("frame_{i:05}.png"));
    for i in 0..tour.len() {
        assert!(frame_png(i).is_file(), "{} missing", frame_png(i).display());
    }
    assert!(!frame_png(tour.len()).exists(), "more frames than the tour");
    let video_line = lines
        .iter()
        .find(|l| l.trim_start().starts_with("video "))
        .unwrap();
    let mp4 = out.join("orbit.mp4");
    if Command::new("ffmpeg").arg("-version").output().is_ok() {
        assert!(
            mp4.is_file() && std::fs::metadata(&mp4).unwrap().len() > 0,
            "{video_line}"
        );
        assert!(video_line.contains("orbit.mp4"), "{video_line}");
    } else {
        assert!(
            !mp4.exists() && video_line.contains("no MP4"),
            "{video_line}"
        );
    }
    let (sw, sh, _) = read_rgb(&out.join("strip.png"));
    assert_eq!((sw, sh), (5 * 48 + 4 * 4, 36), "strip of 5 frames");

    // The printed command and URLs: the same file, and the running server's page.
    let browser = find("in a browser:");
    assert!(
        browser.contains(&format!("msth serve {}", scene.display()))
            && browser.contains("http://127.0.0.1:8080/?model=scene.msth"),
        "{browser}"
    );
    let serving = lines.last().unwrap();
    let page = serving
        .split_whitespace()
        .find(|w| w.starts_with("http://") && w.contains("/?model=scene.msth"))
        .unwrap_or_else(|| panic!("no page URL in `{serving}`"));
    let rest = page.trim_start_matches("http://");
    let (addr, path) = rest.split_at(rest.find('/').unwrap());
    let (status, body) = http_get(addr, path);
    assert!(status.contains(" 200 "), "{page}: {status}");
    assert!(
        body.contains("<title>msth player</title>"),
        "{page}: not the web player: {body:.200}"
    );
    let (status, listing) = http_get(addr, "/models");
    assert!(
        status.contains(" 200 ") && listing.contains("scene.msth"),
        "{status} {listing}"
    );

    // Ctrl-C stops the server and the demo ends cleanly.
    let pid = demo.0.id().to_string();
    assert!(Command::new("kill")
        .args(["-INT", &pid])
        .status()
        .unwrap()
        .success());
    let stop = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(s) = demo.0.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < stop, "msth demo did not stop on Ctrl-C");
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(status.success(), "msth demo after Ctrl-C: {status}");
    assert!(
        TcpStream::connect(addr).is_err(),
        "the server still answers after Ctrl-C"
    );

    // Every played frame against `msth render` of the checkpoint at its camera and time.
    let work = dir.path().join("render");
    std::fs::create_dir_all(&work).unwrap();
    let mut worst = f64::INFINITY;
    let (mut renders, mut plays) = (Vec::new(), Vec::new());
    for (i, f) in tour.iter().enumerate() {
        let cam = work.join(format!("camera_{i}.json"));
        std::fs::write(&cam, serde_json::to_vec(f).unwrap()).unwrap();
        let png = work.join(format!("render_{i}.png"));
        let time = f["time"].as_f64().unwrap().to_string();
        msth_cli::run([
            "msth",
            "render",
            ckpt.to_str().unwrap(),
            "--camera",
            cam.to_str().unwrap(),
            "--time",
            &time,
            "-o",
            png.to_str().unwrap(),
        ])
        .unwrap();
        let (w, h, rendered) = read_rgb(&png);
        let (pw, ph, played) = read_rgb(&frame_png(i));
        assert_eq!((pw, ph), (w, h), "frame {i}: size");
        let p = psnr(&played, &rendered);
        println!("frame {i}: t = {time}, {p:.2} dB against msth render");
        worst = worst.min(p);
        renders.push(rendered);
        plays.push(played);
    }
    assert!(
        worst >= Q5_FLOOR_DB,
        "a played frame is {worst:.2} dB from msth render (floor {Q5_FLOOR_DB} dB)"
    );
    // The comparison tells viewpoints apart: each played frame is closer to the render at its
    // own camera than to the render of any frame of the tour at another camera (a frame played
    // from the wrong pose fails here even within the floor). Times are not compared this way:
    // a 30-step model barely changes over time.
    for (i, played) in plays.iter().enumerate() {
        let own = psnr(played, &renders[i]);
        for (j, other) in renders.iter().enumerate() {
            if tour[j]["transform_matrix"] == tour[i]["transform_matrix"] {
                continue;
            }
            let p = psnr(played, other);
            assert!(
                own > p,
                "frame {i}: {own:.2} dB against its own render, {p:.2} dB against frame {j}'s"
            );
        }
    }
}
