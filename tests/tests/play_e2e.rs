//! The user's flow end to end: built-in scene -> train (short) -> `msth export` -> `msth serve` on
//! a random loopback port -> `msth play` of that URL. The frames written must match direct renders
//! of the checkpoint (PSNR >= 40 dB at f32), and playing the local file gives the same frames.
//! Playback uses the default incremental mode (sample-level reuse after the first frame).

use std::path::Path;

use msth_core::field::ModelLayout;
use msth_server::{BackgroundServer, ServerConfig};
use msth_tests::{export_cmd, play_report, short_run, tiny_scene};
use msth_trainer::checkpoint::Checkpoint;
use msth_trainer::eval::render_image;
use msth_trainer::metrics::psnr;
use msth_trainer::train::train;

fn read_png(p: &Path) -> (u32, u32, Vec<f32>) {
    let img = image::open(p)
        .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
        .to_rgb8();
    let (w, h) = img.dimensions();
    (
        w,
        h,
        img.into_raw().iter().map(|&v| v as f32 / 255.0).collect(),
    )
}

fn quantise(v: &[f32]) -> Vec<f32> {
    v.iter()
        .map(|&x| ((x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8) as f32 / 255.0)
        .collect()
}

#[test]
fn train_export_serve_play_matches_the_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let (_, data) = tiny_scene();
    let s = short_run(&data, 40);
    let train_dir = dir.path().join("train");
    train(&data, s, &train_dir, None, &mut |_| true).unwrap();
    let ckpt_path = train_dir.join("model.ckpt");

    // Export at f32 into a served folder.
    let served = dir.path().join("models");
    std::fs::create_dir_all(&served).unwrap();
    let file = served.join("tiny.msth");
    export_cmd(
        &ckpt_path,
        &file,
        &["--quant", "f32", "--chunk-frames", "2"],
    )
    .unwrap();
    let server = BackgroundServer::start(ServerConfig {
        addr: "127.0.0.1:0".parse().unwrap(),
        ..ServerConfig::new(&served)
    })
    .unwrap();
    let url = format!("http://{}/models/tiny.msth", server.addr());

    // Play over HTTP and from the local file.
    let http_out = dir.path().join("http");
    let local_out = dir.path().join("local");
    play_report(&url, &http_out, &[]);
    // The report of the local playback is checked below.
    let r = play_report(file.to_str().unwrap(), &local_out, &[]);

    let ckpt = Checkpoint::load(&ckpt_path).unwrap();
    let model = &ckpt.header.model;
    let layout = ModelLayout::new(model);
    let camera = ckpt.header.cameras[0];
    let frames = model.num_frames;
    assert_eq!(r["frames"].as_array().unwrap().len(), frames);
    assert_eq!(r["frames"][0]["stats"]["full"], true);
    // The default incremental playback reuses samples on the re-rendered rays (fixed samples,
    // only the dynamic ones evaluated): the frames below hold it to the checkpoint's renders.
    let evaluated: Vec<u64> = r["frames"].as_array().unwrap()[1..]
        .iter()
        .map(|f| f["stats"]["samples_evaluated"].as_u64().unwrap())
        .collect();
    println!("samples evaluated per incremental frame: {evaluated:?}");
    assert!(evaluated.iter().all(|&n| n > 0), "{evaluated:?}");
    for i in 0..frames {
        let name = format!("frame_{i:05}.png");
        let (w, h, played) = read_png(&http_out.join(&name));
        assert_eq!((w, h), (camera.width, camera.height));
        let (_, _, local) = read_png(&local_out.join(&name));
        assert!(played == local, "{name}: HTTP and local playback differ");
        let t = i as f32 / (frames - 1) as f32;
        let direct = render_image(model, &layout, &ckpt.params, &camera, t);
        let p = psnr(&played, &quantise(&direct.rgb));
        println!("{name}: t = {t:.3}, PSNR against the checkpoint {p:.2} dB");
        assert!(p >= 40.0, "{name}: {p:.2} dB");
    }
}
