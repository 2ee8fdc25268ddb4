//! `msth demo`: the whole product on the built-in scene in one command, one line per stage with
//! its wall time:
//!
//! scene -> train (fast preset, time-capped) -> eval -> export `OUT/scene.msth` (what
//! `msth export` writes) -> serve it on a free loopback port (the server `msth serve` starts,
//! in-process) -> play a free-viewpoint tour through that server with the player library (what
//! `msth play` does: HTTP Range requests, incremental rendering while the camera holds still) ->
//! `OUT/orbit.mp4` (ffmpeg; PNG frames only without it) and `OUT/strip.png`; then time to first
//! frame, frame rates, bytes fetched, and the command and URL that show the file in a browser.
//! `--serve` keeps the server running at the end until Ctrl-C.
//!
//! The tour ([`Tour`]): three stops across the arc of the training cameras (its two ends, and
//! its middle seen from higher up and closer), joined by moves, while the timeline plays
//! throughout. While the camera moves every frame is rendered in full: new viewpoints at every
//! frame. While it holds, the player re-renders only the rays its static test leaves dynamic:
//! the incremental playback. The tour is written as `OUT/orbit.json`, a camera path that
//! `msth play --path` reads, so the playback can be repeated or compared with `msth render`.

use std::fmt::Display;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use serde::Serialize;

use msth_codec::{EncodeOptions, QuantMode};
use msth_core::config::Preset;
use msth_core::Camera;
use msth_dataset::imageio::save_png_atomic;
use msth_dataset::Image8;
use msth_player::path::Rig;
use msth_player::play::make_video;
use msth_player::{play, BackendChoice, Frame, PlayOptions, PlayReport};
use msth_server::BackgroundServer;
use msth_trainer::checkpoint::{write_atomic, Checkpoint};
use msth_trainer::synth::{generate, SynthConfig};
use msth_trainer::train::{train as run_training, TrainSettings};

use crate::export::{mb, write_msth, Choices, QuantArg};
use crate::play::parse_size;
use crate::serve::{server_config, ServeArgs};
use crate::training::{eval_trained, progress_bar, report};

/// Training-time budget of `msth demo` in seconds: with the other stages (about 25 s on 2 cores)
/// the whole demo ends within about 3.5 minutes.
pub const DEMO_TRAIN_SECONDS: f64 = 140.0;

/// The demo's batch: a quarter of the fast preset's 2048 rays, so four times the steps in the
/// same time.
pub const DEMO_BATCH_RAYS: usize = 512;
/// The demo's learning rate: twice the fast preset's.
pub const DEMO_LEARNING_RATE: f32 = 2e-2;

/// The demo's schedule: the fast preset's model, trained in smaller batches at twice the
/// learning rate, up to the preset's number of rays (4 x 1400 steps of 512). In a fixed time
/// this reaches a better model, most of all on a slow host, so the demo's quality follows the
/// machine less (docs/tuning.md, "The demo's schedule").
pub fn demo_schedule(settings: &mut TrainSettings) {
    let rays = settings.iters * settings.batch_rays;
    settings.batch_rays = DEMO_BATCH_RAYS;
    settings.iters = rays.div_ceil(DEMO_BATCH_RAYS);
    settings.anneal_steps = (settings.iters / 4).max(1);
    settings.adam.lr = DEMO_LEARNING_RATE;
}

/// Frame rate of `orbit.mp4`: one model frame per output frame, so the built-in scene's 20
/// frames take 1.6 s.
const VIDEO_FPS: f32 = 12.0;

/// The file name the demo exports to and serves.
const SCENE_FILE: &str = "scene.msth";

#[derive(Args)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(long, default_value = "out/demo")]
    pub out: PathBuf,
    /// Keep the server running at the end and print the web page's URL (Ctrl-C stops it).
    #[arg(long)]
    pub serve: bool,
    /// Open the demo's file in a window at the end (`msth view OUT/scene.msth`).
    #[cfg(feature = "view")]
    #[arg(long)]
    pub view: bool,
    /// Address of the demo's server (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    pub addr: SocketAddr,
    /// Seconds of training (the learning rate decays over them, so a slower machine gets fewer
    /// steps).
    #[arg(long, default_value_t = DEMO_TRAIN_SECONDS)]
    pub time_limit: f64,
    /// Override the number of iterations of the fast preset.
    #[arg(long)]
    pub iters: Option<usize>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Play on the CPU renderer even when a GPU exists.
    #[arg(long)]
    pub cpu: bool,
    /// Playback image size WxH.
    #[arg(long, value_parser = parse_size, default_value = "160x120")]
    pub play_size: (u32, u32),
    /// Frames of the tour (three stops and the moves between them).
    #[arg(long, default_value_t = 40)]
    pub play_frames: usize,
    /// Built-in scene image size WxH (tests run a shortened demo).
    #[arg(long, hide = true, value_parser = parse_size)]
    pub size: Option<(u32, u32)>,
    /// Built-in scene time steps.
    #[arg(long, hide = true)]
    pub frames: Option<usize>,
    /// Built-in scene training cameras.
    #[arg(long, hide = true)]
    pub cameras: Option<usize>,
    /// Quantisation of the exported file (`msth export --quant`).
    #[arg(long, hide = true, value_enum, default_value_t = QuantArg::Auto)]
    pub quant: QuantArg,
}

/// Prints one stage's line: its name, wall time since `since`, and what it left.
fn stage(name: &str, since: Instant, msg: impl Display) {
    println!("  {name:<7}{:>6.1} s  {msg}", since.elapsed().as_secs_f64());
}

pub fn run(a: DemoArgs) -> Result<()> {
    if !(a.time_limit.is_finite() && a.time_limit > 0.0) {
        bail!(
            "--time-limit {}: a positive number of seconds",
            a.time_limit
        );
    }
    if !(7..=100_000).contains(&a.play_frames) {
        bail!("--play-frames {}: between 7 and 100000", a.play_frames);
    }
    let (pw, ph) = a.play_size;
    if pw == 0 || ph == 0 || pw > 4096 || ph > 4096 {
        bail!("--play-size {pw}x{ph}: sides must lie in 1..=4096");
    }
    let t0 = Instant::now();
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    println!(
        "msth demo: the built-in scene trained, exported, served and played back; outputs in {}",
        a.out.display()
    );

    // Scene.
    let t = Instant::now();
    let mut cfg = SynthConfig::default();
    if let Some((w, h)) = a.size {
        cfg.width = w;
        cfg.height = h;
    }
    if let Some(f) = a.frames {
        cfg.num_frames = f;
    }
    if let Some(c) = a.cameras {
        cfg.num_train_cams = c;
    }
    if cfg.width == 0
        || cfg.height == 0
        || cfg.width > 1024
        || cfg.height > 1024
        || !(1..=1000).contains(&cfg.num_frames)
        || !(1..=100).contains(&cfg.num_train_cams)
    {
        bail!("--size, --frames, --cameras: sides 1..=1024, 1..=1000 frames, 1..=100 cameras");
    }
    let data = generate(&cfg);
    stage(
        "scene",
        t,
        format!(
            "{} cameras x {} frames of {}x{} + a held-out camera (the built-in scene)",
            cfg.num_train_cams, cfg.num_frames, cfg.width, cfg.height
        ),
    );

    // Train.
    let t = Instant::now();
    let mut settings = TrainSettings::for_preset(Preset::Fast, &data);
    demo_schedule(&mut settings);
    settings.seed = a.seed;
    settings.time_limit_secs = a.time_limit;
    if let Some(i) = a.iters {
        settings.iters = i;
        settings.anneal_steps = (i / 4).max(1);
    }
    settings.validate().map_err(anyhow::Error::msg)?;
    let pb = progress_bar(settings.iters);
    let stride = settings.eval_stride;
    let (trainer, outcome) = run_training(&data, settings, &a.out, None, &mut |p| report(&pb, p))?;
    pb.finish_and_clear();
    stage(
        "train",
        t,
        format!(
            "{} steps of {DEMO_BATCH_RAYS} rays, the fast preset's model ({:.0} s budget, {:.0} rays/s): {}",
            outcome.steps,
            a.time_limit,
            outcome.rays_per_sec,
            outcome.checkpoint.display()
        ),
    );

    // Evaluate.
    let t = Instant::now();
    let m = eval_trained(&data, &trainer, stride, &a.out, &outcome)?;
    drop((trainer, data));
    stage(
        "eval",
        t,
        format!(
            "held-out PSNR {:.2} dB, SSIM {:.4} over {} views: {}, pictures in {}",
            m.psnr,
            m.ssim,
            m.frames.len(),
            a.out.join("metrics.json").display(),
            a.out.join("eval").display()
        ),
    );

    // Export, as `msth export CKPT -o OUT/scene.msth`.
    let t = Instant::now();
    let ckpt_path = outcome.checkpoint.clone();
    let mut ckpt = Checkpoint::load(&ckpt_path)?;
    let scene = a.out.join(SCENE_FILE);
    let opts = EncodeOptions {
        quant: a.quant.mode().unwrap_or(QuantMode::Q5),
        ..EncodeOptions::default()
    };
    let choices = Choices {
        quant: a.quant == QuantArg::Auto,
        ..Choices::auto()
    };
    let (enc, lines) = write_msth(
        &mut ckpt,
        &ckpt_path,
        &scene,
        &opts,
        false,
        Some(msth_player::seen::DEFAULT_SEEN_WEIGHT),
        &choices,
    )?;
    stage(
        "export",
        t,
        format!(
            "{}: {} ({} bytes), {:.1}x smaller than the raw f32 parameters ({}); {}, {} time chunk(s)",
            scene.display(),
            mb(enc.file_bytes),
            enc.file_bytes,
            enc.ratio(),
            mb(enc.raw_param_bytes),
            enc.section_quant,
            enc.chunks.len()
        ),
    );
    for line in lines.iter().filter(|l| {
        l.starts_with("quant auto") || l.starts_with("play-time") || l.starts_with("  measured")
    }) {
        println!("         {line}");
    }

    // Serve, as `msth serve OUT/scene.msth --addr 127.0.0.1:0`.
    let t = Instant::now();
    let config = server_config(&ServeArgs {
        path: scene.clone(),
        addr: a.addr,
        web: None,
        max_connections: msth_server::Limits::default().max_connections,
        max_connections_per_ip: msth_server::Limits::default().max_connections_per_ip,
        header_timeout_secs: msth_server::Limits::default()
            .header_read_timeout
            .as_secs_f64(),
        cache_mib: msth_server::DEFAULT_CACHE_BYTES >> 20,
        rate_limit: None,
    })?;
    let web_page = config.web_dir.is_some();
    let server =
        BackgroundServer::start(config).with_context(|| format!("serving {}", scene.display()))?;
    let url = server.url(&format!("/models/{SCENE_FILE}"));
    stage(
        "serve",
        t,
        format!("{url} (the built-in server, in-process, on a free loopback port)"),
    );

    // Play the tour through the server.
    let t = Instant::now();
    let template = ckpt
        .header
        .cameras
        .first()
        .map(|c| c.resized(pw, ph))
        .context("the checkpoint has no cameras to place the tour around")?;
    let rig = Rig::new(&ckpt.header.model.bounds, &ckpt.header.cameras, template);
    let tour = Tour::new(&rig, ckpt.header.model.num_frames, a.play_frames);
    let path_file = a.out.join("orbit.json");
    write_atomic(&path_file, &serde_json::to_vec_pretty(&tour.path_json())?)
        .with_context(|| format!("writing {}", path_file.display()))?;
    let frames_dir = a.out.join("frames");
    remove_frames(&frames_dir)?;
    let mut opts = PlayOptions::new(url.clone());
    opts.path = path_file.to_string_lossy().into_owned();
    opts.out = Some(frames_dir.clone());
    opts.video = false;
    opts.fps = Some(VIDEO_FPS);
    opts.backend = if a.cpu {
        BackendChoice::Cpu
    } else {
        BackendChoice::Auto
    };
    let mut strip: Vec<Option<Frame>> = vec![None; tour.strip.len()];
    let played = play(&opts, &mut |r, frame| {
        if let Some(k) = tour.strip.iter().position(|&i| i == r.index) {
            strip[k] = Some(frame.clone());
        }
    })?;
    stage(
        "play",
        t,
        format!(
            "{} frames of {pw}x{ph} over HTTP along {} ({}: 3 stops of {} frames, moves of {} and {}): {}",
            played.frames.len(),
            path_file.display(),
            renderer_name(&played),
            tour.hold,
            tour.step,
            2 * tour.step,
            frames_dir.join("frame_*.png").display()
        ),
    );

    // Video.
    let t = Instant::now();
    let video = a.out.join("orbit.mp4");
    match std::fs::remove_file(&video) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            return Err(e).with_context(|| format!("removing the old {}", video.display()))
        }
        _ => {}
    }
    match make_video(&frames_dir, VIDEO_FPS) {
        Ok(made) => {
            std::fs::rename(&made, &video)
                .with_context(|| format!("moving {} to {}", made.display(), video.display()))?;
            stage(
                "video",
                t,
                format!(
                    "{} ({} frames at {VIDEO_FPS} fps, H.264)",
                    video.display(),
                    played.frames.len()
                ),
            );
        }
        Err(note) => stage(
            "video",
            t,
            format!("no MP4: {note}; the frames are in {}", frames_dir.display()),
        ),
    }

    // Strip picture.
    let t = Instant::now();
    let strip_path = a.out.join("strip.png");
    let frames: Vec<Frame> = strip.into_iter().flatten().collect();
    write_strip(&strip_path, &frames)?;
    stage(
        "strip",
        t,
        format!(
            "{} ({} frames of the tour side by side: stop, move, stop, move, stop)",
            strip_path.display(),
            frames.len()
        ),
    );

    print_playback(&played);
    println!("demo done in {:.1} s", t0.elapsed().as_secs_f64());
    let page_query = format!("/?model={SCENE_FILE}");
    println!(
        "in a browser: `msth serve {}` (from the repository root, which holds web/), then open http://{}{page_query}",
        scene.display(),
        msth_server::DEFAULT_ADDR
    );
    if !Path::new("web/node_modules/fzstd").is_dir() {
        println!("  the page needs its npm packages once: npm ci --prefix web");
    }
    #[cfg(feature = "view")]
    if a.view {
        println!("in a window: msth view {}", scene.display());
        let mut opts = msth_viewer::ViewOptions::new(scene.to_string_lossy());
        opts.out = a.out.clone();
        if a.cpu {
            opts.backend = msth_player::BackendChoice::Cpu;
        }
        msth_viewer::run(&opts).context("msth view")?;
    } else {
        println!(
            "in a window: msth view {} (or msth demo --view)",
            scene.display()
        );
    }
    if a.serve {
        if !web_page {
            println!("  (no web/ folder in the current directory: the server shows a placeholder page; run from the repository root)");
        }
        println!(
            "serving {} at {}{page_query} (the web page) and {url}; Ctrl-C stops",
            scene.display(),
            server.url("")
        );
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .context("starting the tokio runtime")?;
        runtime.block_on(async {
            let _ = tokio::signal::ctrl_c().await;
        });
        println!("Ctrl-C: stopping the server");
    }
    server.stop().context("stopping the server")?;
    Ok(())
}

/// "CPU renderer, 2 threads" or the GPU adapter.
fn renderer_name(r: &PlayReport) -> String {
    format!(
        "{} renderer, {}",
        r.backend.kind.to_uppercase(),
        r.backend.device
    )
}

/// The closing figures of the playback: time to first frame, frame rates, bytes fetched.
fn print_playback(r: &PlayReport) {
    let fps = |v: Option<f64>| v.map_or("-".to_string(), |f| format!("{f:.1}"));
    let held: Vec<_> = r.frames.iter().filter(|f| !f.stats.full).collect();
    let rerendered = held
        .iter()
        .map(|f| f.stats.rays_rendered as f64 / f.stats.rays_total.max(1) as f64)
        .sum::<f64>()
        / held.len().max(1) as f64;
    println!(
        "playback: time to first frame {:.2} s; {} FPS overall: {} FPS for the frames rendered in full (the camera moves), {} FPS for the incremental ones (the camera holds; {:.0}% of the pixels re-rendered, {} FPS once the static cache is built); fetched {} ({} bytes; the file is {}) in {} HTTP requests",
        r.time_to_first_frame,
        fps(r.fps()),
        fps(r.full_fps()),
        fps(r.incremental_fps()),
        100.0 * rerendered,
        fps(r.steady_incremental_fps()),
        mb(r.transfer.bytes),
        r.transfer.bytes,
        mb(r.file_len),
        r.transfer.requests
    );
}

/// Removes `dir/frame_*.png` left by an earlier run (a shorter tour must not inherit them).
fn remove_frames(dir: &Path) -> Result<()> {
    let entries = match std::fs::read_dir(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        r => r.with_context(|| format!("reading {}", dir.display()))?,
    };
    for e in entries {
        let e = e.with_context(|| format!("reading {}", dir.display()))?;
        let name = e.file_name();
        let name = name.to_string_lossy();
        if name.starts_with("frame_") && name.ends_with(".png") {
            std::fs::remove_file(e.path())
                .with_context(|| format!("removing {}", e.path().display()))?;
        }
    }
    Ok(())
}

/// Writes `frames` side by side with 4 white pixels between them.
fn write_strip(path: &Path, frames: &[Frame]) -> Result<()> {
    const GAP: u32 = 4;
    let Some(h) = frames.iter().map(|f| f.height).max() else {
        bail!("no frames for the strip picture");
    };
    let w = frames.iter().map(|f| f.width).sum::<u32>() + GAP * (frames.len() as u32 - 1);
    let mut rgb = vec![1f32; (w * h * 3) as usize];
    let mut x0 = 0u32;
    for f in frames {
        for y in 0..f.height {
            for x in 0..f.width {
                let src = ((y * f.width + x) * 3) as usize;
                let dst = ((y * w + x0 + x) * 3) as usize;
                rgb[dst..dst + 3].copy_from_slice(&f.rgb[src..src + 3]);
            }
        }
        x0 += f.width + GAP;
    }
    save_png_atomic(path, &Image8::from_f32(w, h, &rgb))
        .with_context(|| format!("writing {}", path.display()))
}

/// A viewpoint around the rig: azimuth and elevation in radians, distance in world units.
#[derive(Clone, Copy, Debug, PartialEq)]
struct View {
    azimuth: f32,
    elevation: f32,
    distance: f32,
}

impl View {
    fn lerp(self, to: View, s: f32) -> View {
        View {
            azimuth: self.azimuth + (to.azimuth - self.azimuth) * s,
            elevation: self.elevation + (to.elevation - self.elevation) * s,
            distance: self.distance + (to.distance - self.distance) * s,
        }
    }
}

/// The demo's camera path: stop A (one end of the cameras' arc), a move to stop B (the middle,
/// higher and closer), a move to stop C (the other end), a move back to A so the video loops.
/// Each stop holds `hold` frames, the moves take `step`, `step` and `2 step` frames. The time
/// runs forwards and backwards over the clip, one model frame per output frame.
struct Tour {
    frames: Vec<(Camera, f32)>,
    hold: usize,
    step: usize,
    /// The frames of the strip picture: the middle of each stop and of the first two moves.
    strip: Vec<usize>,
}

/// A `msth play --path` JSON file.
#[derive(Serialize)]
struct PathFile {
    frames: Vec<PathFrame>,
}

/// One frame of a `msth play --path` JSON file.
#[derive(Serialize)]
struct PathFrame {
    transform_matrix: [[f32; 4]; 4],
    time: f32,
    fl_x: f32,
    fl_y: f32,
    cx: f32,
    cy: f32,
    w: u32,
    h: u32,
}

impl Tour {
    /// About `total` frames (at least 7) around `rig`, for a model of `model_frames` frames.
    fn new(rig: &Rig, model_frames: usize, total: usize) -> Tour {
        let step = (total as f32 / 10.0).round().max(1.0) as usize;
        let hold = (total.saturating_sub(4 * step) / 3).max(2);
        let (mut lo, mut hi) = rig.azimuth_span;
        if hi - lo < 10f32.to_radians() {
            // One camera, or cameras in a line: swing 40 degrees around them.
            let mid = 0.5 * (lo + hi);
            (lo, hi) = (mid - 20f32.to_radians(), mid + 20f32.to_radians());
        }
        let stops = [
            View {
                azimuth: lo,
                elevation: rig.elevation,
                distance: rig.radius,
            },
            View {
                azimuth: 0.5 * (lo + hi),
                elevation: (rig.elevation + 8f32.to_radians()).min(80f32.to_radians()),
                distance: 0.85 * rig.radius,
            },
            View {
                azimuth: hi,
                elevation: rig.elevation,
                distance: rig.radius,
            },
        ];
        let mut views = Vec::new();
        let mut strip = Vec::new();
        for k in 0..3 {
            strip.push(views.len() + hold / 2);
            views.extend(std::iter::repeat_n(stops[k], hold));
            let n = if k == 2 { 2 * step } else { step };
            if k < 2 {
                strip.push(views.len() + n / 2);
            }
            let (from, to) = (stops[k], stops[(k + 1) % 3]);
            views.extend((1..=n).map(|j| {
                let s = j as f32 / (n + 1) as f32;
                from.lerp(to, s * s * (3.0 - 2.0 * s))
            }));
        }
        let dt = if model_frames > 1 {
            1.0 / (model_frames - 1) as f32
        } else {
            0.0
        };
        let frames = views
            .iter()
            .enumerate()
            .map(|(i, v)| {
                // Forwards over [0, 1], then backwards: no jump in the motion.
                let x = (i as f32 * dt) % 2.0;
                let time = if x > 1.0 { 2.0 - x } else { x };
                (
                    rig.view(v.azimuth, v.elevation, v.distance),
                    time.clamp(0.0, 1.0),
                )
            })
            .collect();
        Tour {
            frames,
            hold,
            step,
            strip,
        }
    }

    /// The tour as a `msth play --path` file (`{"frames": [...]}`, full intrinsics per frame).
    fn path_json(&self) -> PathFile {
        let frames: Vec<PathFrame> = self
            .frames
            .iter()
            .map(|(c, time)| PathFrame {
                transform_matrix: c.world_from_camera.transpose().to_cols_array_2d(),
                time: *time,
                fl_x: c.fx,
                fl_y: c.fy,
                cx: c.cx,
                cy: c.cy,
                w: c.width,
                h: c.height,
            })
            .collect();
        PathFile { frames }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::SceneBounds;

    fn rig() -> Rig {
        let cams: Vec<Camera> = (0..5)
            .map(|k| {
                let a = (k as f32 * 10.0).to_radians();
                Camera::look_at(
                    40,
                    30,
                    0.8,
                    Vec3::new(4.0 * a.cos(), 4.0 * a.sin(), 1.5),
                    Vec3::ZERO,
                    Vec3::Z,
                )
            })
            .collect();
        Rig::new(&SceneBounds::dnerf_default(), &cams, cams[0])
    }

    #[test]
    fn tour_holds_still_at_three_stops_and_moves_between() {
        let tour = Tour::new(&rig(), 20, 80);
        assert_eq!((tour.hold, tour.step), (16, 8));
        assert_eq!(tour.frames.len(), 3 * 16 + 4 * 8);
        // Held frames repeat one camera exactly (what makes the player render incrementally);
        // moving frames differ from their neighbours.
        let same = |i: usize| tour.frames[i].0 == tour.frames[i + 1].0;
        let held = (0..tour.frames.len() - 1).filter(|&i| same(i)).count();
        assert_eq!(held, 3 * (16 - 1));
        assert!(!same(16) && !same(20));
        // The time moves one model frame per output frame, forwards then backwards, in [0, 1].
        let times: Vec<f32> = tour.frames.iter().map(|f| f.1).collect();
        assert_eq!(times[0], 0.0);
        assert!((times[19] - 1.0).abs() < 1e-5 && (times[20] - 18.0 / 19.0).abs() < 1e-5);
        assert!(times.iter().all(|t| (0.0..=1.0).contains(t)));
        assert_eq!(tour.strip, vec![8, 20, 32, 44, 56]);
        // The file round-trips through the player's path parser to the same cameras.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("orbit.json");
        std::fs::write(&p, serde_json::to_vec(&tour.path_json()).unwrap()).unwrap();
        let r = rig();
        let path = msth_player::CameraPath::parse(
            p.to_str().unwrap(),
            &SceneBounds::dnerf_default(),
            &[r.template],
            None,
        )
        .unwrap();
        for (i, (cam, t)) in tour.frames.iter().enumerate() {
            assert_eq!(path.camera(i, tour.frames.len()), (*cam, Some(*t)));
        }
    }

    #[test]
    fn short_tours_keep_their_shape() {
        let tour = Tour::new(&rig(), 1, 7);
        assert_eq!((tour.hold, tour.step), (2, 1));
        assert_eq!(tour.frames.len(), 10);
        assert!(tour.frames.iter().all(|f| f.1 == 0.0));
        assert_eq!(tour.strip.len(), 5);
        assert!(tour.strip.iter().all(|&i| i < tour.frames.len()));
    }
}
