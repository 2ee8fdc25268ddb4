//! Finding and loading a dataset from a command-line argument.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use msth_dataset::cache::FrameStorage;
use msth_dataset::dynerf::{FrameSource, Normalization};
use msth_dataset::{detect, Dataset, Format, LoadOptions};
use msth_trainer::synth::{generate, SynthConfig};

/// Frames larger than this (in bytes, all views) go to a frame cache on disk by default.
pub const MEMORY_LIMIT: u64 = 2 << 30;

/// How to read a dataset folder (shared by `train` and `eval`).
#[derive(Args, Clone, Debug)]
pub struct DataArgs {
    /// Downscale images by an integer factor on load (area filter).
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Dataset layout: dnerf | nerfstudio | dynerf (default: detected from the folder).
    #[arg(long)]
    pub format: Option<String>,
    /// Held-out camera: NN of camNN for DyNeRF (default 0), camera index for multi-camera
    /// nerfstudio captures.
    #[arg(long)]
    pub test_camera: Option<usize>,
    /// Folder for the frame cache. With it, decoded frames always go to DIR/NAME-dsF.frames;
    /// without it, they stay in memory up to 2 GiB and otherwise go to a cache in the output
    /// folder's `cache/`. A valid cache is reused without decoding. Images with transparency
    /// always stay in memory.
    #[arg(long, value_name = "DIR")]
    pub cache: Option<PathBuf>,
    /// DyNeRF frames from: auto | videos | images (auto: videos when every camera has one).
    #[arg(long, default_value = "auto")]
    pub frame_source: String,
    /// DyNeRF pose normalisation: llff (scale by the near bound, recentre on the mean camera)
    /// | none (keep the file's world).
    #[arg(long, default_value = "llff")]
    pub poses: String,
}

impl DataArgs {
    /// Only a downscale factor, everything else default.
    pub fn with_downscale(downscale: u32) -> Self {
        DataArgs {
            downscale,
            format: None,
            test_camera: None,
            cache: None,
            frame_source: "auto".into(),
            poses: "llff".into(),
        }
    }
}

/// A progress bar (a line every 5% when stderr is not a terminal) for decoding frames into
/// memory or into a frame cache; it appears on the first frame.
fn decode_progress() -> Arc<msth_dataset::cache::ProgressFn> {
    let bar: Mutex<Option<ProgressBar>> = Mutex::new(None);
    Arc::new(move |done, total| {
        let Ok(mut guard) = bar.lock() else { return };
        let pb = guard.get_or_insert_with(|| {
            let pb = ProgressBar::new(total);
            pb.set_style(
                ProgressStyle::with_template(
                    "decoding frames [{elapsed_precise} / ETA {eta}] {bar:30} {pos}/{len}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
            );
            pb
        });
        pb.set_position(done);
        if pb.is_hidden() && (done % (total / 20).max(1) == 0 || done == total) {
            eprintln!("decoding frames: {done}/{total}");
        }
        if done == total {
            pb.finish();
        }
    })
}

/// `builtin` is the procedural scene (generated in memory); anything else is a folder.
/// `out` is the run's output folder (the default place of a frame cache).
pub fn load(arg: &str, args: &DataArgs, out: &Path) -> Result<Dataset> {
    let downscale = args.downscale;
    if arg == "builtin" {
        let mut cfg = SynthConfig::default();
        if downscale > 1 {
            cfg.width = (cfg.width / downscale).max(1);
            cfg.height = (cfg.height / downscale).max(1);
        }
        return Ok(generate(&cfg));
    }
    let dir = Path::new(arg);
    if !dir.is_dir() {
        bail!("{arg}: no such dataset folder (or use `builtin` for the built-in scene)");
    }
    let format: Option<Format> = args
        .format
        .as_deref()
        .map(str::parse)
        .transpose()
        .map_err(anyhow::Error::msg)?;
    let Some(format) = format.or_else(|| detect(dir)) else {
        bail!("{arg}: not a dataset folder I can read (expected transforms_train.json for D-NeRF / Blender, transforms.json for nerfstudio, or poses_bounds.npy for DyNeRF / Plenoptic Video)")
    };
    let name = dir
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| "dataset".into());
    let file = format!("{name}-ds{downscale}.frames");
    let storage = match &args.cache {
        Some(d) => FrameStorage::Disk(d.join(file)),
        None => FrameStorage::Auto {
            file: out.join("cache").join(file),
            memory_limit: MEMORY_LIMIT,
        },
    };
    let opts = LoadOptions {
        format: Some(format),
        downscale,
        test_camera: args.test_camera,
        storage,
        frames: match args.frame_source.as_str() {
            "auto" => FrameSource::Auto,
            "videos" => FrameSource::Videos,
            "images" => FrameSource::Images,
            s => bail!("--frame-source {s}: expected auto, videos or images"),
        },
        normalization: match args.poses.as_str() {
            "llff" => Normalization::Llff,
            "none" => Normalization::None,
            s => bail!("--poses {s}: expected llff or none"),
        },
        progress: Some(decode_progress()),
        ..Default::default()
    };
    msth_dataset::load(dir, &opts)
        .with_context(|| format!("loading dataset {arg} ({format:?} layout)"))
}
