//! The GPU renderer against the CPU renderer on a real model: built-in scene -> train (short) ->
//! `msth export` (quantised, as shipped) -> playback from the file, decoded by the player.
//!
//! One check runs per backend, as its own test (the model and the CPU reference are built once
//! and shared): the CPU always; the GPU when an adapter exists (Mesa's lavapipe in CI). Full and
//! incremental playbacks of a fixed camera must match the CPU renderer's full renders of the same
//! decoded parameters at PSNR >= 40 dB. Without an adapter the GPU test is reported as ignored
//! (with the reason), unless `MSTH_REQUIRE_GPU=1` (then it fails): this binary runs on
//! `msth-testkit`'s harness (`harness = false`), and [`main`] lists its tests.

use std::sync::{Arc, OnceLock};

use msth_player::{play, BackendChoice, PlayOptions, PlayReport};
use msth_testkit::Tests;
use msth_tests::{export_cmd, gpu_need, short_run, tiny_scene};
use msth_trainer::metrics::psnr;
use msth_trainer::train::train;

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    let shared = Arc::new(OnceLock::new());
    let cpu_fixture = Arc::clone(&shared);
    Tests::new(file!())
        .test(
            "cpu_playback_of_a_decoded_model_matches_full_cpu_renders",
            move || check_backend(cpu_fixture.get_or_init(Fixture::new), BackendChoice::Cpu),
        )
        .needs(
            &[&gpu],
            "gpu_playback_of_a_decoded_model_matches_full_cpu_renders",
            move || check_backend(shared.get_or_init(Fixture::new), BackendChoice::Gpu),
        )
        .run()
}

/// Plays `opts` on `backend`.
fn play_on(opts: &PlayOptions, backend: BackendChoice) -> (PlayReport, Vec<Vec<f32>>) {
    let mut o = opts.clone();
    o.backend = backend;
    let mut frames = Vec::new();
    match play(&o, &mut |_, f| frames.push(f.rgb.clone())) {
        Ok(r) => (r, frames),
        Err(e) => panic!("{backend:?}: {e}"),
    }
}

/// The exported model, the playback options (incremental and full) and the reference frames:
/// the CPU renderer, every frame in full.
struct Fixture {
    _dir: tempfile::TempDir,
    opts: PlayOptions,
    full_opts: PlayOptions,
    reference: Vec<Vec<f32>>,
}

impl Fixture {
    fn new() -> Fixture {
        let dir = tempfile::tempdir().unwrap();
        let (_, data) = tiny_scene();
        let mut s = short_run(&data, 40);
        // A small model: quick to train, and to render on a software adapter (Mesa's lavapipe,
        // the CI's GPU).
        let m = &mut s.model;
        m.field.encoding.resize(4, 12, 128.0, 16);
        m.proposal.encoding.resize(2, 10, 32.0, 16);
        m.resize_mlps(16, 8);
        m.field.geo_features = 7;
        m.sampler.set_samples(24, 12);
        let train_dir = dir.path().join("train");
        train(&data, s, &train_dir, None, &mut |_| true).unwrap();
        let file = dir.path().join("tiny.msth");
        export_cmd(
            &train_dir.join("model.ckpt"),
            &file,
            &["--chunk-frames", "2"],
        )
        .unwrap();

        let mut opts = PlayOptions::new(file.to_str().unwrap());
        opts.path = "view:30,20,4".into();
        // MSTH_GPU_E2E_SIZE=WxH and MSTH_GPU_E2E_FRAMES=N change the size and frame count (for the
        // printed frame rates; timing never decides the test).
        let env = |k: &str| std::env::var(k).ok();
        opts.size = Some(
            env("MSTH_GPU_E2E_SIZE")
                .and_then(|v| {
                    let (w, h) = v.split_once('x')?;
                    Some((w.parse().ok()?, h.parse().ok()?))
                })
                .unwrap_or((40, 32)),
        );
        opts.frames = Some(
            env("MSTH_GPU_E2E_FRAMES")
                .and_then(|v| v.parse().ok())
                .unwrap_or(6),
        );
        opts.video = false;
        // Let the probes decide (the short-trained mask is soft), so that some rays are cached and the
        // incremental frames mix cached and re-rendered pixels.
        opts.render.static_threshold = 0.0;
        // Whole dynamic rays on both backends (sample-level reuse places fixed samples, whose
        // frames differ from full renders), so that every frame can be held to the full render.
        opts.render.reuse = msth_player::Reuse::Rays;
        // Strict probes (five, within 1/255), so that the soft mask leaves rays of both kinds.
        opts.render.probes = 5;
        opts.render.probe_tolerance = 1.0 / 255.0;
        let mut full_opts = opts.clone();
        full_opts.render.incremental = false;
        let (_, reference) = play_on(&full_opts, BackendChoice::Cpu);
        Fixture {
            _dir: dir,
            opts,
            full_opts,
            reference,
        }
    }
}

/// Full and incremental playbacks on `backend` against the reference.
fn check_backend(fx: &Fixture, backend: BackendChoice) {
    let (opts, full_opts, reference) = (&fx.opts, &fx.full_opts, &fx.reference);
    let (full_report, full) = play_on(full_opts, backend);
    let (inc_report, inc) = play_on(opts, backend);
    let kind = if backend == BackendChoice::Cpu {
        "cpu"
    } else {
        "gpu"
    };
    assert_eq!(full_report.backend.kind, kind);
    assert_eq!(inc_report.backend.kind, kind);
    assert!(full_report.frames.iter().all(|f| f.stats.full));
    assert!(inc_report.frames[0].stats.full);
    assert!(inc_report.frames[1..].iter().all(|f| !f.stats.full));
    let cached: usize = inc_report.frames[1..]
        .iter()
        .map(|f| f.stats.rays_cached)
        .sum();
    let rendered: usize = inc_report.frames[1..]
        .iter()
        .map(|f| f.stats.rays_rendered)
        .sum();
    println!(
        "{kind} ({}): full {:.1} FPS, incremental {:.1} FPS; {cached} rays cached, {rendered} re-rendered over the incremental frames",
        full_report.backend.device,
        full_report.full_fps().unwrap_or(0.0),
        inc_report.incremental_fps().unwrap_or(0.0),
    );
    for f in &inc_report.frames {
        println!(
            "{kind} incremental playback frame {}: {} rays rendered, {:.1} ms ({:.1} ms of it classifying)",
            f.index,
            f.stats.rays_rendered,
            1e3 * f.stats.seconds,
            1e3 * f.stats.cache_seconds
        );
    }
    assert!(
        cached > 0 && rendered > 0,
        "{cached} cached, {rendered} rendered"
    );
    for (i, r) in reference.iter().enumerate() {
        let pf = psnr(&full[i], r);
        let pi = psnr(&inc[i], r);
        println!("{kind} frame {i}: full {pf:.2} dB, incremental {pi:.2} dB against the CPU");
        assert!(pf >= 40.0, "{kind} frame {i}: full render {pf:.2} dB");
        assert!(
            pi >= 40.0,
            "{kind} frame {i}: incremental render {pi:.2} dB"
        );
    }
}
