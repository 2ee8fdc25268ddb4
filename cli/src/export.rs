//! `msth export`: a checkpoint -> a `.msth` file (through `msth-codec`), with a summary of what
//! went where (hash-table values no training ray reached are set to 0 first, see
//! [`msth_trainer::unreached`]); `--measure DATA` instead measures every quantisation mode and dynamic threshold
//! (size, PSNR drop on the held-out views, speed) and prints markdown tables.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;

use msth_codec::{decode_all, encode, EncodeOptions, EncodeReport, QuantMode};
use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_dataset::Dataset;
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
    /// f32 (lossless) | f16 | q8 | q6 | q5 | q4 | k4 | k3
    #[arg(long, default_value = "q5")]
    pub quant: String,
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
    #[arg(long, default_value_t = msth_codec::occupancy::DEFAULT_SEEN_WEIGHT)]
    pub seen_weight: f32,
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
    let quant: QuantMode = a.quant.parse().map_err(anyhow::Error::msg)?;
    let seen = a.carving_weight()?;
    let opts = EncodeOptions {
        quant,
        chunk_frames: a.chunk_frames,
        dynamic_threshold: a.dynamic_threshold,
        frame_rate: a.fps,
        zstd_level: a.zstd_level,
        occupancy_resolution: a.occupancy_resolution,
        occupancy_alpha: a.occupancy_alpha,
        occupancy: None,
    };
    if let Some(d) = &a.measure {
        let dir = a.checkpoint.parent().unwrap_or(std::path::Path::new("."));
        return measure(&ckpt, d, dir, a.stride, &opts, seen);
    }
    let Some(out) = &a.output else {
        bail!("-o OUTPUT is required (or --measure DATA)");
    };
    let (report, lines) = write_msth(&mut ckpt, &a.checkpoint, out, &opts, a.keep_unreached, seen)?;
    for line in lines {
        println!("{line}");
    }
    print_summary(&report, out);
    Ok(())
}

/// What `msth export CKPT -o OUT` does, without printing: zeroes the table values no training ray
/// reached (unless `keep_unreached`), restricts the occupancy grid to what the training cameras
/// see (with `seen_weight`, unless `opts` brings a grid), encodes `ckpt` (read from `ckpt_path`)
/// with `opts` and writes `out` atomically. Returns the encoder's report and lines saying what
/// was zeroed and how the grid was made.
pub(crate) fn write_msth(
    ckpt: &mut Checkpoint,
    ckpt_path: &Path,
    out: &Path,
    opts: &EncodeOptions,
    keep_unreached: bool,
    seen_weight: Option<f32>,
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
    let (bytes, report) = encode(
        &ckpt.header.model,
        &ckpt.params,
        &ckpt.header.cameras,
        &opts,
    )
    .with_context(|| format!("encoding {}", ckpt_path.display()))?;
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

/// The occupancy grid of `opts` (the density grid) restricted to the cells the checkpoint's
/// training cameras see with samples of weight `>= min_weight`, or that lie outside their views
/// ([`msth_codec::occupancy::seen_cells`]), and a line saying what was cast and kept. A
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
    let (seen, r) = msth_codec::occupancy::seen_cells(
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
            msth_codec::occupancy::MAX_FOOTPRINT_CELLS
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
        r.quant,
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
    data_arg: &str,
    ckpt_dir: &std::path::Path,
    stride: usize,
    base: &EncodeOptions,
    seen_weight: Option<f32>,
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
