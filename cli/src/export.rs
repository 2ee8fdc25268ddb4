//! `msth export`: a checkpoint -> a `.msth` file (through `msth-codec`), with a summary of what
//! went where (hash-table values no training ray reached are set to 0 first, see
//! [`msth_trainer::unreached`]); `--measure DATA` instead measures every quantisation mode and dynamic threshold
//! (size, PSNR drop on the held-out views, speed) and prints markdown tables.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;

use msth_codec::{decode_all, encode, EncodeOptions, EncodeReport, QuantMode, QuantPart};
use msth_core::config::{ModelConfig, PlaySamples};
use msth_core::field::ModelLayout;
use msth_dataset::Dataset;
use msth_player::quant_auto::AutoOptions;
use msth_trainer::checkpoint::{write_atomic, Checkpoint};
use msth_trainer::eval::render_image;
use msth_trainer::metrics::psnr;
use msth_trainer::unreached::zero_unreached;

use crate::data;

#[derive(Args)]
pub struct ExportArgs {
    pub checkpoint: PathBuf,
    /// Output file (required unless `--measure`).
    #[arg(short = 'o', long)]
    pub output: Option<PathBuf>,
    /// How the parameters are quantised: `auto` picks each section's mode, the smallest file
    /// whose loss against the lossless file stays within --max-loss on renders of the file's own
    /// cameras; a mode (f32 lossless, f16, q8, q6, q5, q4, k4, k3) is used for every section.
    #[arg(long, value_enum, default_value_t = QuantArg::Auto)]
    pub quant: QuantArg,
    /// The loss budget (dB of PSNR) of `--quant auto` and of `--play-samples auto`, each.
    #[arg(long, value_name = "DB", default_value_t = msth_player::quant_auto::DEFAULT_MAX_LOSS_DB)]
    pub max_loss: f64,
    /// The model's held-out PSNR (dB), which turns the renders' squared error into a loss
    /// (default: `psnr` of the metrics.json beside the checkpoint, else 35).
    #[arg(long, value_name = "DB")]
    pub reference_psnr: Option<f64>,
    /// The samples per ray players use by default: `auto` stores the fewest proposal and main
    /// samples whose loss against the model's own counts stays within --max-loss; `model`
    /// stores none (players use the model's own); `P,M` stores these.
    #[arg(long, default_value = "auto", value_parser = parse_play_samples)]
    pub play_samples: PlaySamplesArg,
    /// Cameras the searches of `auto` render (spread over the checkpoint's cameras).
    #[arg(long, value_name = "N", default_value_t = msth_player::quant_auto::AutoOptions::default().views)]
    pub auto_views: usize,
    /// Longest side (pixels) of the searches' renders.
    #[arg(long, value_name = "PX", default_value_t = msth_player::quant_auto::AutoOptions::default().side)]
    pub auto_side: u32,
    /// Frames per dynamic time chunk.
    #[arg(long, default_value_t = 10)]
    pub chunk_frames: usize,
    /// A mask voxel is dynamic when `1 - sigmoid(logit) >= X`; 4D rows no dynamic voxel reaches
    /// are dropped.
    #[arg(long, default_value_t = 0.3)]
    pub dynamic_threshold: f32,
    /// Playback frame rate stored in the file.
    #[arg(long)]
    pub fps: Option<f32>,
    #[arg(long, default_value_t = 9)]
    pub zstd_level: i32,
    /// Measure every mode and threshold on this dataset's held-out views (`builtin` or a folder)
    /// instead of writing a file.
    #[arg(long, value_name = "DATA")]
    pub measure: Option<String>,
    /// Evaluate every N-th held-out view when measuring.
    #[arg(long, default_value_t = 3)]
    pub stride: usize,
    /// Keep hash-table values no training ray reached (by default they are set to 0, which the
    /// codec stores almost for free; found from the checkpoint's optimiser state).
    #[arg(long)]
    pub keep_unreached: bool,
    /// Cells per axis of the occupancy grid stored for empty-space skipping (format.md §6.5).
    #[arg(long, default_value_t = msth_codec::occupancy::DEFAULT_OCCUPANCY_RESOLUTION)]
    pub occupancy_resolution: u32,
    /// Opacity budget of the occupancy threshold: a ray crossing the grid's diagonal through
    /// density just below it would reach this opacity (samples below it are skipped).
    #[arg(long, default_value_t = msth_codec::occupancy::DEFAULT_OCCUPANCY_ALPHA)]
    pub occupancy_alpha: f32,
    /// Which cells of the occupancy grid stay occupied: `cameras` keeps the cells with density
    /// that the checkpoint's training cameras see (a sample of rendering weight at least
    /// --seen-weight on one of their rays at some frame, dilated by one cell); `density` keeps
    /// every cell with density.
    #[arg(long, value_enum, default_value_t = OccupancyFrom::Cameras)]
    pub occupancy_from: OccupancyFrom,
    /// The rendering weight a sample must carry for its cell to count as seen
    /// (`--occupancy-from cameras`).
    #[arg(long, default_value_t = msth_player::seen::DEFAULT_SEEN_WEIGHT)]
    pub seen_weight: f32,
    /// Progressive layers (1..=16): the field's hash levels split coarse to fine, so a player
    /// draws from the first layers while the others arrive (docs/streaming.md). 1 writes a
    /// file without layers (format version 3, which every msth player reads).
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub layers: usize,
}

/// `msth export --quant` (and `msth demo --quant`): `auto` or one mode for every section.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum QuantArg {
    Auto,
    F32,
    F16,
    Q8,
    Q6,
    Q5,
    Q4,
    K4,
    K3,
}

impl QuantArg {
    /// The mode, `None` for `auto`.
    pub fn mode(self) -> Option<QuantMode> {
        Some(match self {
            QuantArg::Auto => return None,
            QuantArg::F32 => QuantMode::F32,
            QuantArg::F16 => QuantMode::F16,
            QuantArg::Q8 => QuantMode::Q8,
            QuantArg::Q6 => QuantMode::Q6,
            QuantArg::Q5 => QuantMode::Q5,
            QuantArg::Q4 => QuantMode::Q4,
            QuantArg::K4 => QuantMode::K4,
            QuantArg::K3 => QuantMode::K3,
        })
    }
}

/// `msth export --play-samples`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlaySamplesArg {
    Auto,
    Model,
    Counts(u32, u32),
}

fn parse_play_samples(s: &str) -> Result<PlaySamplesArg, String> {
    match s {
        "auto" => Ok(PlaySamplesArg::Auto),
        "model" => Ok(PlaySamplesArg::Model),
        _ => match s.parse::<PlaySamples>() {
            Ok(PlaySamples::Counts(p, m)) => Ok(PlaySamplesArg::Counts(
                u32::try_from(p).map_err(|e| e.to_string())?,
                u32::try_from(m).map_err(|e| e.to_string())?,
            )),
            _ => Err(format!(
                "{s:?}: auto, model or P,M (proposal and main samples per ray, each at least 1)"
            )),
        },
    }
}

/// What `msth export` chooses from renders (`--quant auto`, `--play-samples`).
#[derive(Clone, Debug)]
pub(crate) struct Choices {
    /// Search the sections' modes (`--quant auto`).
    pub quant: bool,
    pub samples: PlaySamplesArg,
    /// The budget and reference PSNR (`None`: from metrics.json beside the checkpoint, else
    /// [`msth_player::quant_auto::DEFAULT_REFERENCE_PSNR`]).
    pub max_loss: f64,
    pub reference_psnr: Option<f64>,
    /// Views and their longest side (pixels) of the searches' renders.
    pub views: usize,
    pub side: u32,
}

impl Choices {
    /// The searches' options against a held-out PSNR of `reference_psnr`.
    fn auto_options(&self, reference_psnr: f64) -> AutoOptions {
        AutoOptions {
            max_loss_db: self.max_loss,
            reference_psnr,
            views: self.views,
            side: self.side,
        }
    }

    /// What `msth export` does by default: both searches, 0.1 dB each.
    pub fn auto() -> Self {
        Choices {
            quant: true,
            samples: PlaySamplesArg::Auto,
            max_loss: msth_player::quant_auto::DEFAULT_MAX_LOSS_DB,
            reference_psnr: None,
            views: AutoOptions::default().views,
            side: AutoOptions::default().side,
        }
    }
}

/// The held-out PSNR the searches assume, and where it came from: `given`, else `psnr` of the
/// metrics.json beside the checkpoint, else the default.
fn reference_psnr(given: Option<f64>, ckpt_path: &Path) -> Result<(f64, String)> {
    if let Some(p) = given {
        if !(p.is_finite() && p > 0.0) {
            bail!("--reference-psnr {p}: a positive number of dB");
        }
        return Ok((p, "--reference-psnr".into()));
    }
    let path = ckpt_path
        .parent()
        .unwrap_or(Path::new("."))
        .join("metrics.json");
    let found = std::fs::read(&path)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| v.get("psnr").and_then(|p| p.as_f64()))
        .filter(|p| p.is_finite() && *p > 0.0);
    Ok(match found {
        Some(p) => (p, format!("the held-out PSNR in {}", path.display())),
        None => (
            msth_player::quant_auto::DEFAULT_REFERENCE_PSNR,
            "assumed: no metrics.json with a PSNR beside the checkpoint (--reference-psnr sets it)"
                .into(),
        ),
    })
}

/// Where `msth export`'s occupancy grid comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum OccupancyFrom {
    Cameras,
    Density,
}

impl ExportArgs {
    /// The weight of `--occupancy-from cameras`, `None` for `density`.
    fn carving_weight(&self) -> Result<Option<f32>> {
        if !(self.seen_weight.is_finite() && (0.0..1.0).contains(&self.seen_weight)) {
            bail!("--seen-weight {}: must lie in [0, 1)", self.seen_weight);
        }
        Ok((self.occupancy_from == OccupancyFrom::Cameras).then_some(self.seen_weight))
    }
}

pub fn export(a: ExportArgs) -> Result<()> {
    let mut ckpt = Checkpoint::load(&a.checkpoint)?;
    let seen = a.carving_weight()?;
    if !(a.max_loss.is_finite() && a.max_loss > 0.0) {
        bail!("--max-loss {}: a positive number of dB", a.max_loss);
    }
    let choices = Choices {
        quant: a.quant == QuantArg::Auto,
        samples: a.play_samples,
        max_loss: a.max_loss,
        reference_psnr: a.reference_psnr,
        views: a.auto_views,
        side: a.auto_side,
    };
    let opts = EncodeOptions {
        quant: a.quant.mode().unwrap_or(QuantMode::Q5),
        sections: None,
        play_samples: None,
        chunk_frames: a.chunk_frames,
        dynamic_threshold: a.dynamic_threshold,
        frame_rate: a.fps,
        zstd_level: a.zstd_level,
        occupancy_resolution: a.occupancy_resolution,
        occupancy_alpha: a.occupancy_alpha,
        occupancy: None,
        layers: a.layers,
    };
    if let Some(d) = &a.measure {
        let dir = a.checkpoint.parent().unwrap_or(std::path::Path::new("."));
        return measure(
            &ckpt,
            &a.checkpoint,
            d,
            dir,
            a.stride,
            &opts,
            seen,
            &choices,
        );
    }
    let Some(out) = &a.output else {
        bail!("-o OUTPUT is required (or --measure DATA)");
    };
    let (report, lines) = write_msth(
        &mut ckpt,
        &a.checkpoint,
        out,
        &opts,
        a.keep_unreached,
        seen,
        &choices,
    )?;
    for line in lines {
        println!("{line}");
    }
    print_summary(&report, out);
    Ok(())
}

/// What `msth export CKPT -o OUT` does, without printing: zeroes the table values no training ray
/// reached (unless `keep_unreached`), restricts the occupancy grid to what the training cameras
/// see (with `seen_weight`, unless `opts` brings a grid), makes the `choices` (each section's
/// mode, the play-time samples), encodes `ckpt` (read from `ckpt_path`) with `opts` and writes
/// `out` atomically. Returns the encoder's report and lines saying what was zeroed, how the grid
/// was made and what was chosen.
pub(crate) fn write_msth(
    ckpt: &mut Checkpoint,
    ckpt_path: &Path,
    out: &Path,
    opts: &EncodeOptions,
    keep_unreached: bool,
    seen_weight: Option<f32>,
    choices: &Choices,
) -> Result<(EncodeReport, Vec<String>)> {
    let mut lines: Vec<String> = drop_unreached(ckpt, keep_unreached, ckpt_path)?
        .into_iter()
        .collect();
    let mut opts = opts.clone();
    if let (None, Some(w)) = (&opts.occupancy, seen_weight) {
        let (grid, line) = seen_occupancy(ckpt, &opts, w);
        opts.occupancy = Some(std::sync::Arc::new(grid));
        lines.push(line);
    }
    lines.extend(choose(ckpt, ckpt_path, &mut opts, choices)?);
    let (bytes, report) = encode(
        &ckpt.header.model,
        &ckpt.params,
        &ckpt.header.cameras,
        &opts,
    )
    .with_context(|| format!("encoding {}", ckpt_path.display()))?;
    if report.layers.len() > 1 {
        lines.extend(layer_lines(ckpt, ckpt_path, &bytes, &report, choices)?);
    }
    // Atomic: a full disk or a crash leaves the file that was there (if any) as it was.
    let kept = if out.exists() {
        "the file there before is unchanged"
    } else {
        "nothing was written"
    };
    write_atomic(out, &bytes)
        .with_context(|| format!("writing {} failed ({kept})", out.display()))?;
    Ok((report, lines))
}

/// Makes `choices` into `opts` (`sections`, `play_samples`); the lines saying what was chosen
/// and measured.
pub(crate) fn choose(
    ckpt: &Checkpoint,
    ckpt_path: &Path,
    opts: &mut EncodeOptions,
    choices: &Choices,
) -> Result<Vec<String>> {
    use msth_player::quant_auto::{choose_quant, choose_samples, Probe};
    let mut lines = Vec::new();
    if let PlaySamplesArg::Counts(p, m) = choices.samples {
        opts.play_samples = Some(msth_codec::PlaySampleCounts {
            proposal: p,
            main: m,
        });
    }
    if !choices.quant && choices.samples != PlaySamplesArg::Auto {
        return Ok(lines);
    }
    if opts.occupancy.is_none() {
        let layout = ModelLayout::new(&ckpt.header.model);
        opts.occupancy = Some(std::sync::Arc::new(msth_codec::encode::occupancy_grid(
            &ckpt.header.model,
            &layout,
            &ckpt.params,
            opts,
        )));
    }
    let (psnr, source) = reference_psnr(choices.reference_psnr, ckpt_path)?;
    let auto = choices.auto_options(psnr);
    let model = &ckpt.header.model;
    let cameras = &ckpt.header.cameras;
    let probe = Probe::new(model, cameras, &auto);
    if probe.views.is_empty() {
        bail!("the checkpoint lists no cameras to measure --quant auto and --play-samples auto on: give --quant MODE and --play-samples model or P,M");
    }
    let what = format!(
        "{} views of at most {} px at {} frames, against a held-out PSNR of {psnr:.2} dB ({source})",
        probe.views.len(),
        auto.side,
        probe.views.len().min(model.num_frames),
    );
    if choices.quant {
        let c = choose_quant(model, &ckpt.params, cameras, opts, &probe, &auto)
            .with_context(|| format!("choosing the quantisation of {}", ckpt_path.display()))?;
        opts.sections = Some(c.modes);
        let renders = c.steps.len() + 1;
        lines.push(format!(
            "quant auto: {}: loss {:.3} dB against the lossless file (budget {} dB; {renders} renders of {what}, {:.1} s)",
            QuantPart::ALL
                .into_iter()
                .map(|p| format!("{} {}", p.name(), c.modes.get(p)))
                .collect::<Vec<_>>()
                .join(", "),
            c.loss_db,
            auto.max_loss_db,
            c.seconds
        ));
        let steps: Vec<String> = c
            .steps
            .iter()
            .map(|s| match s.part {
                Some(p) => format!("{} {} {:.3}", p.name(), s.modes.get(p), s.loss_db),
                None => format!("whole file {:.3}", s.loss_db),
            })
            .collect();
        lines.push(format!("  measured (dB): {}", steps.join(", ")));
    }
    if choices.samples == PlaySamplesArg::Auto {
        let (bytes, _) = encode(
            model,
            &ckpt.params,
            cameras,
            &EncodeOptions {
                zstd_level: 1,
                ..opts.clone()
            },
        )?;
        let decoded = decode_all(&bytes)?;
        let c = choose_samples(&decoded, &probe, &auto)?;
        opts.play_samples = Some(c.samples);
        let s = &model.sampler;
        lines.push(format!(
            "play-time samples per ray: {} proposal + {} main (the model's: {} + {}): loss {:.3} dB against the model's own counts (budget {} dB; {} renders, {:.1} s)",
            c.samples.proposal,
            c.samples.main,
            s.num_proposal_samples,
            s.num_samples,
            c.loss_db,
            auto.max_loss_db,
            c.steps.len() + 1,
            c.seconds
        ));
        let steps: Vec<String> = c
            .steps
            .iter()
            .map(|s| format!("{} + {} {:.3}", s.samples.0, s.samples.1, s.loss_db))
            .collect();
        lines.push(format!("  measured (dB): {}", steps.join(", ")));
    }
    Ok(lines)
}

/// What each prefix of a layered file's layers costs and draws: the bytes before the first
/// frame and in all, and the loss against the whole file on the renders `--quant auto`
/// measures on (the file's cameras; none without cameras).
fn layer_lines(
    ckpt: &Checkpoint,
    ckpt_path: &Path,
    bytes: &[u8],
    report: &EncodeReport,
    choices: &Choices,
) -> Result<Vec<String>> {
    let model = &ckpt.header.model;
    let (psnr, _) = reference_psnr(choices.reference_psnr, ckpt_path)?;
    let auto = choices.auto_options(psnr);
    let probe = msth_player::quant_auto::Probe::new(model, &ckpt.header.cameras, &auto);
    let mut decoder = msth_codec::Decoder::new(bytes)?;
    decoder.feed(bytes)?;
    let layout = decoder.layout().clone();
    let n = report.layers.len();
    let render = |k: usize| {
        probe.render(model, &layout, &|t| {
            let mut out = Vec::new();
            // Every section is decoded: this cannot fail.
            let _ = decoder.params_for_layers_into(t, k, &mut out);
            out
        })
    };
    let full = (!probe.views.is_empty()).then(|| render(n));
    let mut lines = vec![format!(
        "progressive layers ({n}): what a player holding the first k has; loss against the whole file on {} renders of at most {} px, as an estimate of held-out PSNR from {psnr:.2} dB",
        probe.views.len(),
        auto.side
    )];
    for k in 1..=n {
        let l = &report.layers[k - 1];
        let loss = match &full {
            Some(full) if k < n => {
                let mse = msth_player::quant_auto::mse(&render(k), full);
                format!(
                    "loss {:.2} dB (~{:.2} dB)",
                    auto.loss_db(mse),
                    psnr - auto.loss_db(mse)
                )
            }
            Some(_) => format!("the whole file (~{psnr:.2} dB)"),
            None => "no cameras to measure on".into(),
        };
        lines.push(format!(
            "  layers 0..{k} (levels {}/{}/{}/{} of the field's 3D/4D and the proposal's 3D/4D tables): first frame {}, all frames {}: {loss}",
            l.levels.h3,
            l.levels.h4,
            l.levels.p3,
            l.levels.p4,
            mb(report.first_frame_bytes(k)),
            mb(report.bytes_through(k)),
        ));
    }
    Ok(lines)
}

/// The occupancy grid of `opts` (the density grid) restricted to the cells the checkpoint's
/// training cameras see with samples of weight `>= min_weight`, or that lie outside their views
/// ([`msth_player::seen::seen_cells`]), and a line saying what was cast and kept. A
/// checkpoint that does not list every training camera keeps the density grid.
pub(crate) fn seen_occupancy(
    ckpt: &Checkpoint,
    opts: &EncodeOptions,
    min_weight: f32,
) -> (msth_codec::OccupancyGrid, String) {
    let t = Instant::now();
    let model = &ckpt.header.model;
    let layout = ModelLayout::new(model);
    let mut grid = msth_codec::encode::occupancy_grid(model, &layout, &ckpt.params, opts);
    let dense = grid.occupied_cells();
    let Some(cams) = ckpt.header.training_cameras() else {
        let line = format!(
            "occupancy grid from density alone ({dense} of {} cells): this checkpoint does not list every \
             training camera (written before 2026-11-28, or more than 64 training poses), so what they saw is unknown",
            grid.cells()
        );
        return (grid, line);
    };
    let (seen, r) = msth_player::seen::seen_cells(
        model,
        &layout,
        &ckpt.params,
        cams,
        grid.resolution,
        min_weight,
    );
    grid.intersect(&seen);
    let clipped = if r.clipped_footprints > 0 {
        format!(
            " ({} samples stood for more than {} cells per side and marked only those around them)",
            r.clipped_footprints,
            msth_player::seen::MAX_FOOTPRINT_CELLS
        )
    } else {
        String::new()
    };
    let line = format!(
        "occupancy grid from what the training cameras see: {} cells lie wholly in their views; {} rays ({} cameras x {} times, \
         every {} pixel per side) put weight >= {min_weight} on samples that stand for {} cells{clipped}; with density: {dense} -> {} of {} cells ({:.1}%), in {:.1} s",
        r.covered_cells,
        r.rays,
        r.cameras,
        r.times,
        ordinal(r.stride),
        r.seen_cells,
        grid.occupied_cells(),
        grid.cells(),
        100.0 * grid.occupied_fraction(),
        t.elapsed().as_secs_f64()
    );
    (grid, line)
}

/// `1st`, `2nd`, `3rd`, `4th`, ...
fn ordinal(n: u32) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

/// Zeroes the hash-table values no training ray reached (unless `keep`); the line saying how
/// many.
fn drop_unreached(ckpt: &mut Checkpoint, keep: bool, path: &Path) -> Result<Option<String>> {
    if keep {
        return Ok(None);
    }
    let Some(adam) = &ckpt.adam else {
        return Ok(Some(
            "unreached table values: kept (the checkpoint has no optimiser state)".into(),
        ));
    };
    let layout = ModelLayout::new(&ckpt.header.model);
    let report = zero_unreached(&layout, &mut ckpt.params, adam)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let parts: Vec<String> = report
        .iter()
        .map(|t| {
            format!(
                "{} {} of {} ({:.1}%)",
                t.name,
                t.unreached,
                t.values,
                100.0 * t.unreached as f64 / t.values.max(1) as f64
            )
        })
        .collect();
    Ok(Some(format!(
        "unreached table values set to 0 (no training ray read them): {}",
        parts.join(", ")
    )))
}

/// A byte count in KiB or MiB.
pub(crate) fn mb(b: u64) -> String {
    if b >= 1 << 20 {
        format!("{:.2} MiB", b as f64 / (1 << 20) as f64)
    } else {
        format!("{:.1} KiB", b as f64 / 1024.0)
    }
}

fn print_summary(r: &EncodeReport, out: &std::path::Path) {
    println!(
        "wrote {} ({}, {} bytes): {:.1}x smaller than the raw f32 parameters ({}), {} per frame, quant {}, encoded in {:.2} s",
        out.display(),
        mb(r.file_bytes),
        r.file_bytes,
        r.ratio(),
        mb(r.raw_param_bytes),
        mb(r.bytes_per_frame() as u64),
        r.section_quant,
        r.encode_seconds
    );
    println!(
        "  {:<10} {:>12} {:>12} {:>10}",
        "section", "stored", "raw", "values"
    );
    println!(
        "  {:<10} {:>12} {:>12} {:>10}",
        "prefix",
        mb(r.prefix_bytes),
        "",
        ""
    );
    for s in &r.sections {
        println!(
            "  {:<10} {:>12} {:>12} {:>10}",
            s.name,
            mb(s.stored_bytes),
            mb(s.raw_bytes),
            s.values
        );
    }
    for (i, c) in r.chunks.iter().enumerate() {
        let frames = (c.span.frame_end - c.span.frame_start).max(1) as u64;
        println!(
            "  chunk {:<4} {:>12} {:>12} {:>10}  frames {}..{} (t {:.3}..{:.3}), {} per frame; reaches {:.1}% of the 4D table with the shared rows",
            i,
            mb(c.stored_bytes),
            mb(c.raw_bytes),
            c.kept_values,
            c.span.frame_start,
            c.span.frame_end,
            c.span.t_start,
            c.span.t_end,
            mb(c.stored_bytes / frames),
            100.0 * c.reached_values as f64 / r.h4_values.max(1) as f64
        );
    }
    match r.dynamic_voxels {
        Some((d, n)) => println!(
            "  dynamic voxels: {d} of {n} ({:.1}%); 4D values stored (shared + chunks): {} of {} ({:.1}%)",
            100.0 * d as f64 / n.max(1) as f64,
            r.h4_kept_union,
            r.h4_values,
            100.0 * r.h4_kept_union as f64 / r.h4_values.max(1) as f64
        ),
        None if r.h4_values > 0 => println!("  no mask: the whole 4D table is dynamic"),
        None => println!("  no 4D table: no dynamic chunks"),
    }
    let (occupied, cells) = r.occupied_cells;
    println!(
        "  occupancy grid: {occupied} of {cells} cells occupied ({:.1}%): renderers skip samples in the others",
        100.0 * occupied as f64 / cells.max(1) as f64
    );
    if r.chunks.is_empty() {
        println!("  no dynamic chunks (static scene or no dynamic voxels)");
    } else {
        println!(
            "  dynamic stream: {} per frame after the static and shared parts",
            mb(r.dynamic_bytes_per_frame() as u64)
        );
    }
}

/// Mean PSNR over every `stride`-th test view; `params_at(t)` gives the buffer for time `t`.
pub(crate) fn held_out_psnr(
    data: &Dataset,
    model: &ModelConfig,
    layout: &ModelLayout,
    stride: usize,
    params_at: &dyn Fn(f32) -> Vec<f32>,
) -> f64 {
    let views: Vec<_> = data.test.iter().step_by(stride.max(1)).collect();
    let mut sum = 0.0;
    for v in &views {
        let p = params_at(v.time);
        let r = render_image(model, layout, &p, &v.camera, v.time);
        sum += psnr(&r.rgb, &v.image.to_f32());
    }
    sum / views.len().max(1) as f64
}

fn measure(
    ckpt: &Checkpoint,
    ckpt_path: &Path,
    data_arg: &str,
    ckpt_dir: &std::path::Path,
    stride: usize,
    base: &EncodeOptions,
    seen_weight: Option<f32>,
    choices: &Choices,
) -> Result<()> {
    let mut data = data::load(data_arg, &data::DataArgs::with_downscale(1), ckpt_dir)?;
    data.rescale(ckpt.header.scene_scale());
    let model = &ckpt.header.model;
    let layout = ModelLayout::new(model);
    // One occupancy grid for every encoding below.
    let grid = match seen_weight {
        Some(w) => {
            let (grid, line) = seen_occupancy(ckpt, base, w);
            println!("{line}");
            grid
        }
        None => msth_codec::encode::occupancy_grid(model, &layout, &ckpt.params, base),
    };
    let base = &EncodeOptions {
        occupancy: Some(std::sync::Arc::new(grid)),
        ..base.clone()
    };
    let reference = held_out_psnr(&data, model, &layout, stride, &|_| ckpt.params.clone());
    let raw = 4 * ckpt.params.len() as u64;
    println!(
        "checkpoint {}: {} parameters ({}), held-out PSNR {reference:.3} dB (every {stride}th test view of {} views)\n",
        data.name,
        ckpt.params.len(),
        mb(raw),
        data.test.len()
    );
    println!("| mode | file | bytes/frame | dynamic bytes/frame | ratio to raw f32 | PSNR drop (dB) | encode MB/s | decode MB/s |");
    println!("|---|---|---|---|---|---|---|---|");
    for quant in QuantMode::ALL {
        let opts = EncodeOptions {
            quant,
            ..base.clone()
        };
        let (bytes, report) = encode(model, &ckpt.params, &ckpt.header.cameras, &opts)?;
        let t = Instant::now();
        let decoded = decode_all(&bytes)?;
        let decode_s = t.elapsed().as_secs_f64();
        let p = held_out_psnr(&data, model, &layout, stride, &|t| {
            decoded.params_for_time(t)
        });
        println!(
            "| {quant} | {} | {} | {} | {:.1}x | {:.3} | {:.0} | {:.0} |",
            mb(report.file_bytes),
            mb(report.bytes_per_frame() as u64),
            mb(report.dynamic_bytes_per_frame() as u64),
            report.ratio(),
            reference - p,
            raw as f64 / 1e6 / report.encode_seconds,
            raw as f64 / 1e6 / decode_s
        );
    }
    // `--quant auto` (with the budget and reference of the command line) and the play-time
    // samples it would store.
    let mut opts = base.clone();
    let lines = choose(ckpt, ckpt_path, &mut opts, choices)?;
    let (bytes, report) = encode(model, &ckpt.params, &ckpt.header.cameras, &opts)?;
    let decoded = decode_all(&bytes)?;
    let p = held_out_psnr(&data, model, &layout, stride, &|t| {
        decoded.params_for_time(t)
    });
    println!(
        "| auto ({}) | {} | {} | {} | {:.1}x | {:.3} | | |",
        report.section_quant,
        mb(report.file_bytes),
        mb(report.bytes_per_frame() as u64),
        mb(report.dynamic_bytes_per_frame() as u64),
        report.ratio(),
        reference - p,
    );
    println!();
    for line in &lines {
        println!("{line}");
    }
    if let Some(s) = decoded.metadata.play_samples {
        let mut fewer = model.clone();
        fewer
            .sampler
            .set_samples(s.proposal as usize, s.main as usize);
        let q = held_out_psnr(&data, &fewer, &layout, stride, &|t| {
            decoded.params_for_time(t)
        });
        println!(
            "held-out PSNR of the auto file at its play-time samples ({} + {}): {q:.3} dB, {:.3} dB below its {p:.3} dB at the model's own ({} + {})",
            s.proposal,
            s.main,
            p - q,
            model.sampler.num_proposal_samples,
            model.sampler.num_samples
        );
    }
    println!("\nSparse dynamic section ({} chunk frames), f32 (lossless) so only the dropped 4D rows count:\n", base.chunk_frames);
    println!("| dynamic threshold | dynamic voxels | 4D values stored | reached per chunk (mean) | 4D table values | file (f32) | PSNR drop (dB) |");
    println!("|---|---|---|---|---|---|---|");
    for th in [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7] {
        let opts = EncodeOptions {
            quant: QuantMode::F32,
            dynamic_threshold: th,
            ..base.clone()
        };
        let (bytes, r) = encode(model, &ckpt.params, &ckpt.header.cameras, &opts)?;
        let decoded = decode_all(&bytes)?;
        let p = held_out_psnr(&data, model, &layout, stride, &|t| {
            decoded.params_for_time(t)
        });
        let per_chunk = r.chunks.iter().map(|c| c.reached_values).sum::<u64>() as f64
            / r.chunks.len().max(1) as f64;
        let voxels = match r.dynamic_voxels {
            Some((d, n)) => format!("{d} / {n} ({:.1}%)", 100.0 * d as f64 / n.max(1) as f64),
            None => "no mask".into(),
        };
        println!(
            "| {th} | {voxels} | {} ({:.1}%) | {:.0} ({:.1}%) | {} | {} | {:.3} |",
            r.h4_kept_union,
            100.0 * r.h4_kept_union as f64 / r.h4_values.max(1) as f64,
            per_chunk,
            100.0 * per_chunk / r.h4_values.max(1) as f64,
            r.h4_values,
            mb(r.file_bytes),
            reference - p
        );
    }
    Ok(())
}
