//! `msth import`: videos (or a folder of them) to a dataset, through ffmpeg and COLMAP
//! (`msth_trainer::import`), with progress lines and a summary of what COLMAP registered.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use msth_trainer::import::{import, videos_in, ImportOptions, Layout};

#[derive(Args)]
#[command(after_long_help = IMPORT_HELP)]
pub struct ImportArgs {
    /// Video files (one per fixed camera, or one moving camera), or one folder of videos
    /// (mp4, mov, m4v, mkv, avi, webm, mpg; taken in name order).
    #[arg(required = true)]
    pub videos: Vec<PathBuf>,
    /// The dataset folder to write (must not exist, or be empty).
    #[arg(long)]
    pub out: PathBuf,
    /// `rig` (fixed cameras filming together) or `monocular` (one moving camera); default:
    /// monocular for one video, rig for several.
    #[arg(long)]
    pub layout: Option<String>,
    /// Frames to skip at the start of each video to synchronise them: one value per video,
    /// comma-separated, or one for all.
    #[arg(long, value_delimiter = ',')]
    pub offsets: Vec<u64>,
    /// Use at most this many frames (time steps) of each video.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Rig: how many time steps (spread evenly) COLMAP reconstructs the cameras from.
    #[arg(long, default_value_t = 1)]
    pub sync_times: usize,
    /// COLMAP camera model: opencv (k1 k2 p1 p2), radial, simple_radial, pinhole,
    /// simple_pinhole. Pinhole models also write poses_bounds.npy for rigs.
    #[arg(long, default_value = "opencv")]
    pub camera_model: String,
    /// Rig: intrinsics per video even when all videos have the same size.
    #[arg(long)]
    pub per_video_intrinsics: bool,
    /// Fail when COLMAP registers fewer than this fraction of the cameras (rig) or frames
    /// (monocular).
    #[arg(long, default_value_t = 0.5)]
    pub min_registered: f64,
    /// COLMAP mapper runs (different random seeds) to compare; the one agreeing best with the
    /// others is kept. Default: 3, or 1 above 150 images.
    #[arg(long)]
    pub colmap_runs: Option<usize>,
}

const IMPORT_HELP: &str = "\
Needs `ffmpeg`/`ffprobe` and `colmap` (Debian/Ubuntu: apt-get install ffmpeg colmap), or their \
paths in MSTH_FFMPEG, MSTH_FFPROBE, MSTH_COLMAP. COLMAP runs on the CPU without a display.

Writes DIR/transforms.json (nerfstudio: OPENCV intrinsics and distortion, a pose and a time per \
frame, camera_id per rig camera), the frames (camNN/TTTT.png or frames/TTTT.png), import.json \
(what COLMAP registered, near/far per camera) and colmap/ (database, logs, models). Then: \
msth train DIR --out RUN. Rigs hold out camera 0 (the first video) for evaluation; monocular \
captures every 8th frame. See docs/import.md.";

pub fn run(a: ImportArgs) -> Result<()> {
    let videos = if a.videos.len() == 1 && a.videos[0].is_dir() {
        videos_in(&a.videos[0])?
    } else {
        a.videos.clone()
    };
    let layout = a
        .layout
        .as_deref()
        .map(str::parse::<Layout>)
        .transpose()
        .map_err(anyhow::Error::msg)?;
    if !(0.0..=1.0).contains(&a.min_registered) {
        bail!("--min-registered must be in [0, 1]");
    }
    let opts = ImportOptions {
        layout,
        offsets: a.offsets.clone(),
        frames: a.frames,
        sync_times: a.sync_times,
        camera_model: a.camera_model.parse().map_err(anyhow::Error::msg)?,
        shared_intrinsics: a.per_video_intrinsics.then_some(false),
        min_registered: a.min_registered,
        mapper_runs: a.colmap_runs,
        threads: rayon::current_num_threads(),
        ..Default::default()
    };
    let start = Instant::now();
    let mut progress = |line: &str| {
        eprintln!("[{:6.1} s] {line}", start.elapsed().as_secs_f64());
    };
    let r = import(&videos, &a.out, &opts, &mut progress)
        .with_context(|| format!("importing into {}", a.out.display()))?;
    println!(
        "COLMAP registered {} of {} {} ({} of {} images), {} points, mean reprojection error {:.3} px, in {:.1} s{}",
        r.cameras_registered,
        r.cameras_total,
        if r.layout == "rig" { "cameras" } else { "frames" },
        r.images_registered,
        r.images_total,
        r.points,
        r.mean_reprojection_error_px,
        r.colmap_seconds,
        if r.colmap_models > 1 {
            format!(" ({} separate models; the largest is used)", r.colmap_models)
        } else {
            String::new()
        }
    );
    if r.colmap_runs.len() > 1 {
        let runs: Vec<String> = r
            .colmap_runs
            .iter()
            .map(|t| {
                format!(
                    "seed {}: {} images, focal {:.1} px, {:.3} px, {:.2} deg off the others",
                    t.seed,
                    t.images_registered,
                    t.focal_px,
                    t.mean_reprojection_error_px,
                    t.disagreement_deg.unwrap_or(0.0)
                )
            })
            .collect();
        println!(
            "COLMAP mapper runs compared ({}); kept seed {}",
            runs.join("; "),
            r.colmap_seed
        );
    }
    if !r.unregistered.is_empty() {
        eprintln!(
            "warning: left out (not registered): {}",
            r.unregistered.join(", ")
        );
    }
    println!(
        "wrote {} ({} layout, {} frames over {} time steps, near {:.2} far {:.2}) in {:.1} s; next: msth train {} --out RUN",
        a.out.display(),
        r.layout,
        r.frames_written,
        r.time_steps,
        r.near,
        r.far,
        start.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}
