//! `msth bench play FILE.msth`: playback speed, measured against baselines in the same run.
//!
//! 1. Serves the file's folder on a loopback port with the built-in server and times a plain
//!    download of the whole file (one GET): the baseline for time to first frame.
//! 2. Plays the URL with incremental rendering from a fixed camera: time to first frame, and the
//!    frames per second of the full and the incremental frames.
//! 3. Plays it again with every frame rendered in full (the baseline), and compares the two
//!    frame by frame: PSNR of the incremental frames against the full renders.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use msth_player::{play, ByteSource, HttpOptions, HttpSource, PlayOptions, PlayReport};
use msth_server::{BackgroundServer, ServerConfig};
use msth_trainer::metrics::{mse, psnr, psnr_from_mse};

#[derive(Args)]
pub struct BenchPlayArgs {
    /// The `.msth` file.
    pub file: PathBuf,
    /// Image size WxH.
    #[arg(long, default_value = "256x256")]
    pub size: String,
    /// Frames (default: the model's frame count).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Camera path (a fixed one: incremental rendering needs the camera to stand still).
    #[arg(long, default_value = "0")]
    pub path: String,
    /// Static threshold of the incremental renderer.
    #[arg(long)]
    pub static_threshold: Option<f32>,
    /// Mask value above which a static ray is cached without probes (see `msth play
    /// --trust-threshold`).
    #[arg(long)]
    pub trust_threshold: Option<f32>,
    /// Do not probe the rays the mask alone caches (by default they are probed too, only to
    /// count how often the probes disagree with the mask; they stay cached either way).
    #[arg(long)]
    pub no_audit: bool,
    /// Probe renders that must agree before a ray is cached (see `msth play --probes`).
    #[arg(long)]
    pub probes: Option<usize>,
    /// Largest colour change (0-1 scale) a static ray may show at a probe.
    #[arg(long)]
    pub probe_tolerance: Option<f32>,
    #[command(flatten)]
    pub reuse: crate::play::ReuseArgs,
    /// The file is a model of the built-in scene (default settings): also compare both
    /// playbacks with the scene's exact renders (ground truth) at the same cameras and times.
    #[arg(long)]
    pub builtin_truth: bool,
    /// Render on the CPU even when a GPU adapter exists.
    #[arg(long, conflicts_with = "gpu")]
    pub cpu: bool,
    /// Render on the GPU (any adapter, lavapipe included); fails when there is none.
    #[arg(long)]
    pub gpu: bool,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

fn run_play(opts: &PlayOptions) -> Result<(PlayReport, Vec<Vec<f32>>)> {
    let mut frames = Vec::new();
    let report = play(opts, &mut |_, f| frames.push(f.rgb.clone()))?;
    Ok((report, frames))
}

/// PSNR of the mean squared error of `frames` against `truth`.
/// Fraction of pixels whose colour (any channel) differs from the first frame's by more than
/// `tol` in some later frame.
fn changing_fraction(frames: &[Vec<f32>], tol: f32) -> f64 {
    let Some(first) = frames.first() else {
        return 0.0;
    };
    let pixels = first.len() / 3;
    if pixels == 0 {
        return 0.0;
    }
    let changing = (0..pixels)
        .filter(|&p| {
            frames[1..]
                .iter()
                .any(|f| (0..3).any(|c| (f[p * 3 + c] - first[p * 3 + c]).abs() > tol))
        })
        .count();
    changing as f64 / pixels as f64
}

fn mean_psnr(frames: &[Vec<f32>], truth: &[Vec<f32>]) -> f64 {
    let mean = frames
        .iter()
        .zip(truth)
        .map(|(a, b)| mse(a, b))
        .sum::<f64>()
        / frames.len().max(1) as f64;
    psnr_from_mse(mean)
}

pub fn run(a: BenchPlayArgs) -> Result<()> {
    let size = {
        let (w, h) = a
            .size
            .split_once('x')
            .context("--size: expected WxH, e.g. 256x256")?;
        (w.parse::<u32>()?, h.parse::<u32>()?)
    };
    let name = a
        .file
        .file_name()
        .and_then(|n| n.to_str())
        .filter(|n| n.ends_with(".msth"))
        .with_context(|| format!("{}: expected a .msth file", a.file.display()))?
        .to_string();
    if !a.file.is_file() {
        bail!("{}: no such file", a.file.display());
    }
    let server = BackgroundServer::start(ServerConfig {
        addr: "127.0.0.1:0".parse()?,
        ..ServerConfig::new(&a.file)
    })?;
    let url = format!("http://{}/models/{name}", server.addr());
    println!("msth bench play: {} served at {url}", a.file.display());

    // Baseline: the whole file in one request.
    let t = Instant::now();
    let src = HttpSource::open(
        &url,
        HttpOptions {
            probe_bytes: 1,
            ..HttpOptions::default()
        },
    )?;
    let bytes = src.read_range(0..src.len())?;
    let download = t.elapsed().as_secs_f64();
    println!(
        "full download: {} bytes in {:.1} ms",
        bytes.len(),
        download * 1e3
    );

    let mut opts = PlayOptions::new(url.clone());
    opts.path = a.path.clone();
    opts.size = Some(size);
    opts.frames = a.frames;
    opts.video = false;
    opts.section_timeout = Duration::from_secs(600);
    opts.backend = crate::play::backend_choice(a.cpu, a.gpu);
    if let Some(th) = a.static_threshold {
        opts.render.static_threshold = th;
    }
    if let Some(t) = a.trust_threshold {
        opts.render.trust_threshold = t;
    }
    opts.render.audit_mask = !a.no_audit;
    if let Some(p) = a.probes {
        opts.render.probes = p;
    }
    if let Some(t) = a.probe_tolerance {
        opts.render.probe_tolerance = t;
    }
    a.reuse.apply(&mut opts.render)?;
    let (inc, inc_frames) = run_play(&opts)?;
    println!(
        "renderer: {} ({}){}",
        inc.backend.kind,
        inc.backend.device,
        inc.backend
            .note
            .as_ref()
            .map_or(String::new(), |n| format!("; {n}"))
    );
    let mut full_opts = opts.clone();
    full_opts.render.incremental = false;
    let (full, full_frames) = run_play(&full_opts)?;
    let psnrs: Vec<f64> = inc_frames
        .iter()
        .zip(&full_frames)
        .skip(1)
        .map(|(a, b)| psnr(a, b))
        .collect();
    let min_psnr = psnrs.iter().copied().fold(f64::INFINITY, f64::min);
    let mean_vs_full = mean_psnr(&inc_frames[1..], &full_frames[1..]);
    let full_fps = full.fps().unwrap_or(0.0);
    let inc_fps = inc.incremental_fps().unwrap_or(0.0);
    let steady_fps = inc.steady_incremental_fps().unwrap_or(0.0);
    let dynamic = inc.dynamic_fraction.unwrap_or(1.0);
    let ideal = changing_fraction(&full_frames, 1.0 / 255.0);
    let ideal_coarse = changing_fraction(&full_frames, 8.0 / 255.0);
    println!(
        "time to first frame over HTTP: {:.3} s ({:.1}x the full download)",
        inc.time_to_first_frame,
        inc.time_to_first_frame / download.max(1e-9)
    );
    println!("| mode | frames | FPS | rays/frame |");
    println!("|---|---|---|---|");
    let rays = |r: &PlayReport, incremental: bool| {
        let f: Vec<_> = r
            .frames
            .iter()
            .filter(|f| !incremental || !f.stats.full)
            .collect();
        f.iter().map(|f| f.stats.rays_rendered).sum::<usize>() as f64 / f.len().max(1) as f64
    };
    println!(
        "| full (baseline) | {} | {full_fps:.2} | {:.0} |",
        full.frames.len(),
        rays(&full, false)
    );
    println!(
        "| incremental | {} | {inc_fps:.2} | {:.0} |",
        inc.frames.len() - 1,
        rays(&inc, true)
    );
    println!(
        "| incremental, cache built (steady state) | {} | {steady_fps:.2} | {:.0} |",
        inc.frames.len() - 1,
        rays(&inc, true)
    );
    println!(
        "speed-up {:.2}x ({:.2}x once the cache is built; building it took {:.2} s); {:.1}% of the pixels re-rendered; incremental vs full PSNR: mean {mean_vs_full:.2} dB, min {min_psnr:.2} dB",
        inc_fps / full_fps.max(1e-9),
        steady_fps / full_fps.max(1e-9),
        inc.cache_seconds(),
        100.0 * dynamic
    );
    let evaluated: Vec<_> = inc.frames.iter().filter(|f| !f.stats.full).collect();
    let samples_per_ray = evaluated
        .iter()
        .map(|f| f.stats.samples_evaluated as f64 / f.stats.rays_rendered.max(1) as f64)
        .sum::<f64>()
        / evaluated.len().max(1) as f64;
    let reuse = if inc.backend.kind == "cpu" && samples_per_ray > 0.0 {
        format!(
            "samples: {samples_per_ray:.1} samples evaluated per re-rendered ray, no proposal pass"
        )
    } else {
        "rays: re-rendered rays are rendered in full".to_string()
    };
    println!("reuse on the re-rendered rays: {reuse}");
    let classify = inc.frames.iter().find_map(|f| f.stats.classify);
    if let Some(c) = &classify {
        let pct = |n: usize| 100.0 * n as f64 / c.rays.max(1) as f64;
        println!(
            "mask: {:.1}% of the scene's rays cached by the mask alone (mask >= {}), {:.1}% probed (mask >= {}; {:.1}% kept by the probes), {:.1}% re-rendered",
            pct(c.trusted),
            opts.render.trust_threshold,
            pct(c.probed),
            opts.render.static_threshold,
            pct(c.probed_static),
            pct(c.rays - c.cached())
        );
        if let Some(d) = c.trusted_disagree {
            println!(
                "mask against probes: {d} of the {} rays the mask alone caches ({:.2}%) moved by more than {} at a probe time",
                c.trusted,
                100.0 * d as f64 / c.trusted.max(1) as f64,
                opts.render.probe_tolerance
            );
        }
    }
    println!(
        "the full renders change by more than 1/255 at {:.1}% of the pixels, by more than 8/255 at {:.1}%: the least a perfect static/dynamic split would re-render at those tolerances",
        100.0 * ideal,
        100.0 * ideal_coarse
    );
    let mut truth_psnr = None;
    if a.builtin_truth {
        let index = msth_codec::format::FileIndex::parse(&bytes, &msth_codec::Limits::default())?;
        let meta = &index.metadata;
        let path =
            msth_player::CameraPath::parse(&a.path, &meta.model.bounds, &meta.cameras, Some(size))
                .map_err(anyhow::Error::msg)?;
        let cfg = msth_trainer::synth::SynthConfig::default();
        let truth: Vec<Vec<f32>> = inc
            .frames
            .iter()
            .map(|f| {
                let (cam, _) = path.camera(f.index, inc.frames.len());
                msth_trainer::synth::render_gt(&cfg, &cam, f.time).to_f32()
            })
            .collect();
        let (pi, pf) = (
            mean_psnr(&inc_frames, &truth),
            mean_psnr(&full_frames, &truth),
        );
        println!(
            "against the built-in scene's exact renders: incremental {pi:.2} dB, full {pf:.2} dB"
        );
        truth_psnr = Some((pi, pf));
    }
    if let Some(p) = a.json {
        let v = serde_json::json!({
            "psnr_vs_truth_incremental": truth_psnr.map(|t| t.0),
            "psnr_vs_truth_full": truth_psnr.map(|t| t.1),
            "file": a.file, "size": [size.0, size.1], "threads": rayon::current_num_threads(),
            "backend": inc.backend.kind, "device": inc.backend.device, "backend_note": inc.backend.note,
            "download_seconds": download, "file_bytes": bytes.len(),
            "time_to_first_frame": inc.time_to_first_frame,
            "full_fps": full_fps, "incremental_fps": inc_fps,
            "speedup": inc_fps / full_fps.max(1e-9), "dynamic_fraction": dynamic,
            "steady_incremental_fps": steady_fps, "steady_speedup": steady_fps / full_fps.max(1e-9),
            "cache_seconds": inc.cache_seconds(), "changing_fraction_full": ideal, "changing_fraction_full_8": ideal_coarse,
            "static_threshold": opts.render.static_threshold, "trust_threshold": opts.render.trust_threshold,
            "classify": classify, "probes": opts.render.probes, "probe_tolerance": opts.render.probe_tolerance,
            "reuse": opts.render.reuse, "samples_per_rerendered_ray": samples_per_ray,
            "partition_times": opts.render.partition_times, "partition_samples": opts.render.partition_samples,
            "sample_cutoff": opts.render.sample_cutoff,
            "psnr_incremental_vs_full_mean": mean_vs_full, "psnr_incremental_vs_full_min": min_psnr,
        });
        std::fs::write(&p, serde_json::to_vec_pretty(&v)?)?;
        println!("wrote {}", p.display());
    }
    Ok(())
}
