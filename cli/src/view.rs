//! `msth view URL|FILE`: a window to fly through the scene while it plays (`msth-viewer`).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Result};
use clap::Args;
use msth_core::config::PlaySamples;
use msth_player::HttpOptions;
use msth_viewer::{Script, ViewOptions};

use crate::play::{backend_choice, ca_cert_file, parse_samples, parse_size, VolumeArgs};

#[derive(Args)]
pub struct ViewArgs {
    /// An `http://` or `https://` URL (e.g. from `msth serve`) or a local `.msth` file.
    pub source: String,
    /// The file camera shown first.
    #[arg(long, default_value_t = 0)]
    pub camera: usize,
    /// Start paused at this normalised time (default: play from the start).
    #[arg(long)]
    pub time: Option<f32>,
    /// Full render size WxH (default: the cameras' own).
    #[arg(long, value_parser = parse_size)]
    pub size: Option<(u32, u32)>,
    /// Samples per ray at the start: file (the file's play-time counts, the model's own when it
    /// stores none), full, fast, faster or P,M (the samples menu changes them).
    #[arg(long, default_value = "file", value_parser = parse_samples)]
    pub samples: PlaySamples,
    /// Start with the play-time volume on (CPU renderer; V and the panel's switch turn it off and
    /// on): it is baked in the background once the file's static part has arrived, frames come
    /// from the exact field meanwhile. Its quality depends on the scene and the budget: held-out
    /// PSNR within 0.3 dB of the exact renderer's on the demo model, 0.43 dB below it on a
    /// balanced stage model (0.12 dB above it with `--volume-resolution 2048 --volume-budget
    /// 2200`; several dB below where the budget holds only a coarser volume); `msth eval
    /// FILE.msth --renderer both` measures a file (docs/viewer.md).
    #[arg(long)]
    pub volume: bool,
    #[command(flatten)]
    pub volume_args: VolumeArgs,
    /// Render on the CPU even when a GPU adapter exists.
    #[arg(long, conflicts_with = "gpu")]
    pub cpu: bool,
    /// Render on the GPU, software adapters such as lavapipe included.
    #[arg(long)]
    pub gpu: bool,
    /// GPU renderer: f16 or f32 hash tables on the device (default as `msth play`).
    #[arg(long)]
    pub gpu_tables: Option<msth_player::TableFormat>,
    /// No static-ray cache under a still camera: every frame renders every pixel.
    #[arg(long)]
    pub no_incremental: bool,
    /// Evaluate every sample, also in the cells the file's occupancy grid marks empty.
    #[arg(long)]
    pub no_skip_empty: bool,
    /// Folder for screenshots (P) and recorded camera paths (R).
    #[arg(long, short, default_value = ".")]
    pub out: PathBuf,
    /// Window size WxH in logical pixels (default: fits the picture and the controls).
    #[arg(long, value_parser = parse_size)]
    pub window: Option<(u32, u32)>,
    /// Play a JSON script of input steps (keys, drags, waits, screenshots; docs/viewer.md).
    #[arg(long, value_name = "FILE.json")]
    pub script: Option<PathBuf>,
    /// Write a JSON report of the session (frames shown, screenshots, paths, benches).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Seconds without data before a request is retried.
    #[arg(long, default_value_t = 15.0)]
    pub timeout: f64,
    /// PEM file of the certificates to trust for https:// (as `msth play --ca-cert`).
    #[arg(long, value_name = "FILE.pem")]
    pub ca_cert: Option<PathBuf>,
}

pub fn options(a: &ViewArgs) -> Result<ViewOptions> {
    if !(a.timeout.is_finite() && a.timeout > 0.0 && a.timeout <= 3600.0) {
        bail!("--timeout {}: seconds in (0, 3600]", a.timeout);
    }
    let mut o = ViewOptions::new(a.source.clone());
    o.camera = a.camera;
    o.time = a.time;
    o.size = a.size;
    o.samples = a.samples;
    o.volume = a.volume;
    o.volume_options = a.volume_args.options()?;
    o.march = a.volume_args.march()?;
    o.backend = backend_choice(a.cpu, a.gpu);
    o.gpu_tables = a.gpu_tables;
    o.incremental = !a.no_incremental;
    o.skip_empty = !a.no_skip_empty;
    o.out = a.out.clone();
    o.window_size = a.window;
    o.report = a.report.clone();
    o.script = a.script.as_deref().map(Script::load).transpose()?;
    let ssl_cert_file = if a.source.starts_with("https://") {
        std::env::var_os("SSL_CERT_FILE")
    } else {
        None
    };
    o.http = HttpOptions {
        read_timeout: Duration::from_secs_f64(a.timeout),
        ca_cert_file: ca_cert_file(a.ca_cert.clone(), ssl_cert_file)?,
        ..HttpOptions::default()
    };
    Ok(o)
}

pub fn run(a: ViewArgs) -> Result<()> {
    let opts = options(&a)?;
    let report = msth_viewer::run(&opts)?;
    if let Some(b) = &report.backend {
        println!(
            "renderer: {} ({}); window: {}; {} frames shown in {:.1} s",
            b.kind,
            b.device,
            report.window_adapter,
            report.frames.len(),
            report.seconds
        );
    }
    if let Some(v) = &report.volume {
        println!(
            "volume: {}^3 cells, {} bricks, {:.1} MiB, baked in {:.2} s; {} frames drawn from it",
            v.resolution,
            v.bricks,
            v.bytes as f64 / (1 << 20) as f64,
            v.seconds,
            report.frames.iter().filter(|f| f.volume).count()
        );
    }
    if let Some(e) = &report.volume_error {
        println!("note: no play-time volume: {e}");
    }
    Ok(())
}
