//! The `msth` command as a library: argument parsing and the subcommands, each a thin layer over
//! the library crates. `main.rs` calls [`run`]; the end-to-end tests in `tests/` call it too.

#[cfg(feature = "bench")]
mod bench;
pub mod data;
mod demo;
mod evaluate;
mod export;
mod import;
mod inspect;
mod interrupt;
mod play;
mod scenegen;
mod serve;
mod training;
#[cfg(feature = "view")]
mod view;

/// The benches' public pieces under their historical paths (see [`bench`]).
#[cfg(feature = "bench")]
pub use bench::{tradeoff as bench_tradeoff, tradeoff_plot};

use std::ffi::OsString;
use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};
use msth_core::config::PlaySamples;

#[derive(Parser)]
#[command(
    name = "msth",
    version,
    about = "Masked Space-Time Hash encoding: reconstruct, compress and play dynamic 3D scenes"
)]
struct Cli {
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The whole flow on the built-in scene: train (fast preset, time-capped) -> evaluate ->
    /// export a `.msth` file -> serve it on loopback -> play a free-viewpoint path through the
    /// server -> MP4 and a strip picture; then the command and URL that show it in a browser.
    Demo(demo::DemoArgs),
    /// Write a dataset: the built-in procedural scene (D-NeRF JSON), or with `--gltf` an animated
    /// glTF model rendered in the object (D-NeRF) or stage (DyNeRF + JSON) layout.
    Synth(SynthArgs),
    /// Train a model on a dataset (a folder, or `builtin`).
    Train(TrainArgs),
    /// Evaluate a checkpoint on a dataset's held-out views.
    Eval(EvalArgs),
    /// Render one image from a checkpoint for any camera and time.
    Render(RenderArgs),
    /// Benchmarks (`msth bench step`).
    #[cfg(feature = "bench")]
    Bench(bench::BenchArgs),
    /// Encode a checkpoint into a streamable `.msth` file (or `--measure` the codec's modes).
    Export(export::ExportArgs),
    /// Serve `.msth` files over HTTP (Range requests) until Ctrl-C.
    Serve(serve::ServeArgs),
    /// Play a `.msth` file (URL or local) as free-viewpoint video: PNG frames, MP4, FPS.
    Play(play::PlayArgs),
    /// A window to fly through a `.msth` file (URL or local) while it plays: orbit and fly
    /// cameras, the file's cameras, a timeline, screenshots, recorded camera paths.
    #[cfg(feature = "view")]
    View(view::ViewArgs),
    /// Describe a `.msth` file (local or URL) and validate it against docs/format.md.
    Inspect(inspect::InspectArgs),
    /// Turn your own videos into a dataset: frames by ffmpeg, camera poses by COLMAP.
    Import(import::ImportArgs),
}

#[derive(Args)]
pub struct SynthArgs {
    #[arg(long)]
    pub out: PathBuf,
    /// Render this animated glTF model (.gltf or .glb) instead of the built-in scene.
    #[arg(long)]
    pub gltf: Option<PathBuf>,
    /// With --gltf: `object` (D-NeRF: model alone, RGBA, a random camera per time step) or
    /// `stage` (DyNeRF: model on a set, an arc of fixed cameras, cam00 held out).
    #[arg(long, default_value = "object")]
    pub layout: String,
    /// Image size as WxH (overrides --width / --height).
    #[arg(long)]
    pub size: Option<String>,
    #[arg(long)]
    pub width: Option<u32>,
    #[arg(long)]
    pub height: Option<u32>,
    /// Time steps.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Training cameras (built-in scene and stage layout; the stage adds the held-out cam00),
    /// or held-out test views (object layout).
    #[arg(long)]
    pub cameras: Option<usize>,
    /// With --gltf: samples per pixel along each axis (default 6, i.e. 36 per pixel, 1..=16).
    #[arg(long)]
    pub supersample: Option<u32>,
    /// With --gltf: seed of the random cameras and the stage textures.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// With --gltf --layout stage: do not write the camNN.mp4 videos.
    #[arg(long)]
    pub no_video: bool,
    /// Freeze every moving object (a static video; built-in scene only).
    #[arg(long = "static")]
    pub static_scene: bool,
}

#[derive(Args)]
#[command(after_long_help = DATASETS_HELP)]
pub struct TrainArgs {
    /// Dataset folder (layout detected, see below), or `builtin`.
    pub data: String,
    #[arg(long)]
    pub out: PathBuf,
    /// fast | balanced | quality | paper
    #[arg(long, default_value = "balanced")]
    pub preset: String,
    #[arg(long)]
    pub iters: Option<usize>,
    #[arg(long)]
    pub batch_rays: Option<usize>,
    #[arg(long)]
    pub seed: Option<u64>,
    /// Stop after this many seconds of training.
    #[arg(long)]
    pub time_limit: Option<f64>,
    /// A TOML or JSON file of settings (any field of the settings, nested).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override one setting by its dotted path, e.g. `--set model.sampler.num_samples=32`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    /// Continue from OUT/model.ckpt (give the settings of the interrupted run again: its
    /// command with --resume added).
    #[arg(long)]
    pub resume: bool,
    /// Write OUT/model.ckpt every this many steps (default 1000; 0: only at the end). Each write
    /// is atomic: a crash leaves the previous checkpoint or the new one, never half of one.
    #[arg(long, value_name = "STEPS")]
    pub checkpoint_every: Option<usize>,
    /// Also write it when this many seconds have passed since the last one (default 600; 0: by
    /// steps only).
    #[arg(long, value_name = "SECS")]
    pub checkpoint_secs: Option<f64>,
    /// Where the steps run: `auto` (a hardware GPU when there is one, else the CPU), `cpu`, or
    /// `gpu` (any GPU adapter, software ones included; an error without one). Checkpoints are
    /// the same either way: a run resumes on either device.
    #[arg(long, default_value = "auto")]
    pub device: String,
    #[command(flatten)]
    pub dataset: data::DataArgs,
    /// Skip the evaluation at the end.
    #[arg(long)]
    pub no_eval: bool,
    /// Print the resolved settings as JSON and exit.
    #[arg(long)]
    pub print_settings: bool,
    /// Train the preset's model as set, without sizing it from the data (time resolution,
    /// spatial resolution, table sizes, 4D table; see docs/sizing.md). Single choices are
    /// overridden by setting their keys with --set or --config instead.
    #[arg(long)]
    pub no_autosize: bool,
}

#[derive(Args)]
pub struct EvalArgs {
    pub checkpoint: PathBuf,
    /// Dataset folder, or `builtin`.
    #[arg(long, required_unless_present = "path")]
    pub data: Option<String>,
    /// A `.msth` file: instead of a dataset's held-out views, the frames of a `msth play
    /// --path` (`orbit`, `spiral`, `cameras`, `N`, `view:AZ,EL,DIST` or a JSON file), drawn by
    /// the volume and by the exact renderer: the volume's frames against the exact ones, and the
    /// worst frame as a picture (exact | volume | error map, as `msth eval` draws errors).
    #[arg(long, value_name = "PATH", conflicts_with = "data")]
    pub path: Option<String>,
    /// With `--path`: frames (default 8, or the path file's).
    #[arg(long, requires = "path")]
    pub frames: Option<usize>,
    /// With `--path`: image size WxH (default: the file's cameras').
    #[arg(long, requires = "path", value_parser = play::parse_size)]
    pub size: Option<(u32, u32)>,
    /// With `--path`: normalised time range START:END over the frames.
    #[arg(long, requires = "path", default_value = "0:1", value_parser = play::parse_range)]
    pub time: (f32, f32),
    /// Output folder for metrics.json and pictures (default: the checkpoint's folder; with
    /// `--samples` other than the model's own, its subfolder `eval-samples-P-M`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Evaluate every N-th test view.
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    /// Samples per ray: file (a `.msth` file's play-time counts, the model's own without them or
    /// for a checkpoint), full (the model's own), fast, faster or P,M, as `msth play --samples`:
    /// measures what fewer samples cost on the held-out views.
    #[arg(long, default_value = "file", value_parser = play::parse_samples)]
    pub samples: PlaySamples,
    /// A `.msth` file: which renderer draws the views (the baked volume, the exact field, or
    /// both, with the volume's frames compared to the exact ones).
    #[arg(long, value_enum, default_value_t = EvalRenderer::Volume)]
    pub renderer: EvalRenderer,
    #[command(flatten)]
    pub volume: play::VolumeArgs,
    /// A `.msth` file: the volume's colour: `baked` for a reference direction (what the players
    /// draw), the colour MLP `per-sample` at the ray's direction, or `deferred` once per ray.
    #[arg(long, value_enum, default_value_t = EvalColour::Baked)]
    pub colour: EvalColour,
    /// A `.msth` file: the world scale the model was trained at (`train.scene_scale` of its
    /// checkpoint; 1 unless `msth train` printed another).
    #[arg(long, default_value_t = 1.0)]
    pub scene_scale: f32,
    #[command(flatten)]
    pub dataset: data::DataArgs,
}

/// How `msth eval FILE.msth` colours the volume's rays.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EvalColour {
    Baked,
    PerSample,
    Deferred,
}

impl From<EvalColour> for msth_core::volume::ColourMode {
    fn from(c: EvalColour) -> Self {
        match c {
            EvalColour::Baked => msth_core::volume::ColourMode::Baked,
            EvalColour::Deferred => msth_core::volume::ColourMode::Deferred,
            EvalColour::PerSample => msth_core::volume::ColourMode::PerSample,
        }
    }
}

/// Which renderer `msth eval FILE.msth` measures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum EvalRenderer {
    Volume,
    Exact,
    Both,
}

/// The dataset section of `msth train --help`.
const DATASETS_HELP: &str = "\
Datasets (the layout is detected from the folder, first match wins; --format overrides):
  transforms_train.json  D-NeRF / Blender JSON: transforms_{train,test}.json, images per frame
                         (camera_angle_x or nerfstudio intrinsics fl_x, fl_y, cx, cy, w, h).
  transforms.json        nerfstudio: one file, intrinsics, optional OpenCV distortion k1 k2 k3
                         p1 p2 (images are undistorted on load) and per-frame time. Split:
                         test_filenames/val_filenames if listed; else for multi-camera video the
                         camera --test-camera (default 0) is held out; else every 8th frame.
  poses_bounds.npy       Plenoptic Video / DyNeRF: N x 17 LLFF rows with camNN.mp4 videos
                         (decoded with ffmpeg) or camNN/ image folders; camNN with NN =
                         --test-camera (default 0) is held out. Poses are normalised LLFF-style
                         (--poses none keeps them); --frame-source picks videos or images.
--downscale F reduces every layout's images by F with an area filter. Decoded frames of more
than 2 GiB go to a frame cache file (OUT/cache/, or --cache DIR to always use one), rebuilt when
the sources change, so the dataset is bounded by disk rather than RAM (images with transparency
stay in memory with their alpha).";

#[derive(Args)]
pub struct RenderArgs {
    pub checkpoint: PathBuf,
    /// A camera index into the checkpoint's cameras (`msth render CKPT --list-cameras`), a JSON
    /// file with `transform_matrix` and `camera_angle_x` or `fl_x`, or `orbit:AZ,EL,DIST` in
    /// degrees and scene units around the scene centre (+Z up).
    #[arg(long, default_value = "0")]
    pub camera: String,
    /// Normalised time in [0, 1].
    #[arg(long, default_value_t = 0.0)]
    pub time: f32,
    #[arg(short = 'o', long, default_value = "render.png")]
    pub output: PathBuf,
    #[arg(long)]
    pub width: Option<u32>,
    #[arg(long)]
    pub height: Option<u32>,
    /// Also write the depth and the mask (1 = static) as pictures next to the output.
    #[arg(long)]
    pub extras: bool,
    /// Samples per ray: file (a `.msth` file's play-time counts, the model's own without them or
    /// for a checkpoint), full (the model's own), fast, faster or P,M, as `msth play --samples`.
    #[arg(long, default_value = "file", value_parser = play::parse_samples)]
    pub samples: PlaySamples,
    #[arg(long)]
    pub list_cameras: bool,
}

/// Parses `args` (including the program name) and runs the subcommand.
pub fn run<I, T>(args: I) -> anyhow::Result<()>
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let cli = match Cli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) if !e.use_stderr() => {
            // --help and --version
            print!("{e}");
            return Ok(());
        }
        Err(e) => return Err(anyhow::anyhow!("{e}")),
    };
    if let Some(t) = cli.threads {
        // The global pool can be set once per process; a second request keeps the first.
        let _ = rayon::ThreadPoolBuilder::new()
            .num_threads(t.max(1))
            .build_global();
    }
    match cli.command {
        Command::Demo(a) => demo::run(a),
        Command::Synth(a) => training::synth(a),
        Command::Train(a) => training::train(a).map(|_| ()),
        Command::Eval(a) => training::eval(a),
        Command::Render(a) => training::render(a),
        #[cfg(feature = "bench")]
        Command::Bench(a) => bench::run(a),
        Command::Export(a) => export::export(a),
        Command::Serve(a) => serve::serve(a),
        Command::Play(a) => play::run(a),
        #[cfg(feature = "view")]
        Command::View(a) => view::run(a),
        Command::Inspect(a) => inspect::run(a),
        Command::Import(a) => import::run(a),
    }
}
