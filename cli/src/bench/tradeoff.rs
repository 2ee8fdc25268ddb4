//! `msth bench tradeoff DATA --out DIR`: the accuracy / cost trade-off of the knobs users turn.
//!
//! A one-factor-at-a-time sweep around a base preset (iterations, table size, levels, finest
//! resolution, samples per ray, image scale, mask resolution, proposal table size, quantisation
//! mode), plus the presets themselves. Every variant trains for a fixed step budget (steps, not
//! wall-clock time, so a busy machine does not bias the comparison; the training time is still
//! recorded), is evaluated on the held-out views, exported to a `.msth` file (whose decoded
//! parameters give the PSNR a user sees) and played on the CPU renderer for its full-frame FPS.
//!
//! Results are cached per trained variant in `DIR/runs/NAME/result.json` (written atomically,
//! reused when the variant's settings are unchanged), so a killed sweep resumes where it stopped.
//! The output is `tradeoff.{md,csv,json}` and three plots (`psnr_vs_time.png`,
//! `psnr_vs_size.png`, `fps_vs_psnr.png`) with the Pareto fronts marked (see [`pareto_front`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use msth_codec::{decode_all, encode, EncodeOptions, QuantMode};
use msth_core::config::Preset;
use msth_dataset::Dataset;
use msth_trainer::checkpoint::write_atomic;
use msth_trainer::eval::evaluate;
use msth_trainer::train::{playback_cameras, train as run_training, TrainSettings};

use super::tradeoff_report::{markdown_table, write_outputs, Meta};
use crate::data::{self, DataArgs};

#[derive(Args)]
pub struct TradeoffArgs {
    /// Dataset folder, or `builtin`.
    pub data: String,
    /// Output folder (tables, plots, and the per-variant cache in `runs/`).
    #[arg(long)]
    pub out: PathBuf,
    /// The preset the factors are varied around.
    #[arg(long, default_value = "fast")]
    pub base: String,
    /// Presets measured as they are (same step budget), comma-separated.
    #[arg(long, default_value = "fast,balanced")]
    pub presets: String,
    /// Training steps of every variant (default 600; 30 with --quick); with `--converge`, the
    /// cap (default 8000).
    #[arg(long)]
    pub iters: Option<usize>,
    /// Train each variant until converged: its held-out PSNR (every `--stride`-th view) is
    /// measured every `--converge-every` steps, and training stops once it gains less than
    /// `--min-gain` dB between two measurements, or at the cap (`--iters`). The `iters` factor
    /// is left out.
    #[arg(long)]
    pub converge: bool,
    /// Steps between two measurements of `--converge`.
    #[arg(long, default_value_t = 500)]
    pub converge_every: usize,
    /// The least gain (dB) between two measurements that keeps a `--converge` run going.
    #[arg(long, default_value_t = msth_trainer::train::DEFAULT_MIN_GAIN_DB)]
    pub min_gain: f64,
    /// Factors varied one at a time around the base, comma-separated, from: iters, table,
    /// levels, finest, samples, scale, mask, proposal, quant (default: all). A trailing `+`
    /// or `-` keeps only the costlier or the cheaper value (`table+,levels-`).
    #[arg(long)]
    pub factors: Option<String>,
    /// Which values of each factor: `down` (cheaper), `up` (costlier) or `both` (default;
    /// `down` with --quick).
    #[arg(long)]
    pub direction: Option<String>,
    /// A CI-sized sweep: 30 steps, presets fast and balanced, one value per factor, small FPS
    /// frames (explicit options still win).
    #[arg(long)]
    pub quick: bool,
    /// Evaluate every N-th held-out view.
    #[arg(long, default_value_t = 2)]
    pub stride: usize,
    /// Size (WxH) of the frames rendered for the FPS measurement.
    #[arg(long)]
    pub fps_size: Option<String>,
    /// Frames rendered (in full, from a fixed camera) for the FPS measurement.
    #[arg(long)]
    pub fps_frames: Option<usize>,
    /// An extra variant of the base preset, `LABEL:KEY=VALUE[;KEY=VALUE...]` (keys as in
    /// `msth train --set`), e.g. `grids 16x2^17:model.field.encoding.grid3.levels=16;...`;
    /// repeatable. For changes that go together, which one-factor sweeps cannot show.
    #[arg(long = "variant", value_name = "LABEL:SETS")]
    pub variants: Vec<String>,
    /// A variant's own step budget, `NAME=STEPS` (its `runs/NAME`; with `--converge`, its
    /// cap), for variants too costly for the common one; repeatable.
    #[arg(long = "cap", value_name = "NAME=STEPS")]
    pub caps: Vec<String>,
    /// Quantisation of every variant's file (the `quant` factor varies it on the base model).
    #[arg(long, default_value = "q5")]
    pub quant: String,
    /// Keep each variant's checkpoint and `.msth` file in `runs/NAME/` (default: deleted once
    /// measured; the results stay cached).
    #[arg(long)]
    pub keep_models: bool,
    #[command(flatten)]
    pub dataset: DataArgs,
}

/// Every factor the sweep knows, in table order.
pub const FACTORS: [&str; 9] = [
    "iters", "table", "levels", "finest", "samples", "scale", "mask", "proposal", "quant",
];

/// Which side of the base each factor is moved to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Direction {
    Down,
    Up,
    Both,
}

/// One trained model of the sweep.
#[derive(Clone, Debug)]
struct Variant {
    /// Unique, file-name safe (`runs/NAME`).
    name: String,
    /// Short plot label.
    label: String,
    /// `preset` or a factor name.
    factor: String,
    /// The factor's value, as text.
    value: String,
    preset: Preset,
    /// `key=value` overrides on top of the preset (as `msth train --set`).
    sets: Vec<String>,
    /// Extra downscale of the training images (1: none); evaluation stays at full size.
    train_downscale: u32,
    /// Quantisation modes this variant is exported with (first: the one its FPS is timed on).
    quants: Vec<QuantMode>,
}

/// What one file of one variant measured.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct QuantResult {
    quant: String,
    file_bytes: u64,
    /// Held-out PSNR of the decoded file's parameters.
    psnr: f64,
}

/// The cached result of one trained variant.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct VariantResult {
    /// Everything that decides the result; a cache entry is reused only when it is equal.
    fingerprint: Value,
    steps: usize,
    batch_rays: usize,
    params: usize,
    train_seconds: f64,
    /// Held-out PSNR / SSIM of the f32 parameters.
    psnr_f32: f64,
    ssim_f32: f64,
    /// Full-frame rendering rate of the player (first quant mode's file).
    fps: f64,
    /// Rendering rate of a fixed camera's incremental frames (the file's camera 0, its time
    /// moving), the static cache's one-off cost left out; `None` in results cached before it
    /// was measured (measured then from the kept file, if any).
    #[serde(default)]
    fps_fixed: Option<f64>,
    quants: Vec<QuantResult>,
    /// With `--converge`: the held-out PSNR measured during training, (step, dB).
    #[serde(default)]
    held_out: Vec<(usize, f64)>,
    /// With `--converge`: whether the run stopped for lack of gain (else at the cap).
    #[serde(default)]
    converged: bool,
}

/// One row of the tables: a variant exported with one quantisation mode.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Row {
    pub name: String,
    pub label: String,
    pub factor: String,
    pub value: String,
    pub preset: String,
    pub quant: String,
    pub steps: usize,
    pub batch_rays: usize,
    pub params: usize,
    pub train_seconds: f64,
    pub psnr_f32: f64,
    pub ssim_f32: f64,
    /// Held-out PSNR of the exported file (what a player shows).
    pub psnr: f64,
    pub file_bytes: u64,
    pub fps: f64,
    /// Incremental frames of a fixed camera per second (NaN where not measured).
    pub fps_fixed: f64,
    /// On the Pareto front of PSNR against training time.
    pub front_time: bool,
    /// On the front of PSNR against file size.
    pub front_size: bool,
    /// On the front of FPS against PSNR.
    pub front_fps: bool,
}

/// Which points of `points` are Pareto-optimal when both coordinates are to be maximised: a
/// point is on the front unless another point is at least as good in both and better in one.
/// Points with a NaN coordinate are never on the front and dominate nothing. Equal points are
/// all on the front.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<bool> {
    let valid = |p: &(f64, f64)| !p.0.is_nan() && !p.1.is_nan();
    points
        .iter()
        .map(|p| {
            valid(p)
                && !points
                    .iter()
                    .any(|q| valid(q) && q.0 >= p.0 && q.1 >= p.1 && (q.0 > p.0 || q.1 > p.1))
        })
        .collect()
}

/// Marks the three fronts on `rows` (time and size are minimised, PSNR and FPS maximised).
/// Rows of the `quant` factor share their model's training and rendering, so they take part in
/// the size front only.
pub fn mark_fronts(rows: &mut [Row]) {
    let nan = (f64::NAN, f64::NAN);
    let q = |r: &Row| r.factor == "quant";
    let time: Vec<_> = rows
        .iter()
        .map(|r| {
            if q(r) {
                nan
            } else {
                (-r.train_seconds, r.psnr)
            }
        })
        .collect();
    let size: Vec<_> = rows
        .iter()
        .map(|r| (-(r.file_bytes as f64), r.psnr))
        .collect();
    let fps: Vec<_> = rows
        .iter()
        .map(|r| if q(r) { nan } else { (r.psnr, r.fps) })
        .collect();
    for (i, ((t, s), f)) in pareto_front(&time)
        .into_iter()
        .zip(pareto_front(&size))
        .zip(pareto_front(&fps))
        .enumerate()
    {
        rows[i].front_time = t;
        rows[i].front_size = s;
        rows[i].front_fps = f;
    }
}

fn parse_list(s: &str) -> Vec<String> {
    s.split(',')
        .map(|x| x.trim().to_string())
        .filter(|x| !x.is_empty())
        .collect()
}

fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("--fps-size `{s}`: expected WxH, e.g. 160x120"))?;
    let w: u32 = w
        .trim()
        .parse()
        .with_context(|| format!("--fps-size `{s}`"))?;
    let h: u32 = h
        .trim()
        .parse()
        .with_context(|| format!("--fps-size `{s}`"))?;
    if !(1..=4096).contains(&w) || !(1..=4096).contains(&h) {
        bail!("--fps-size `{s}`: each side must be in 1..=4096");
    }
    Ok((w, h))
}

fn preset_name(p: Preset) -> &'static str {
    match p {
        Preset::Fast => "fast",
        Preset::Balanced => "balanced",
        Preset::Paper => "paper",
    }
}

/// The variants: the presets, then each factor's values around `base` (whose settings,
/// `base_settings`, give the values the factors scale).
fn variants(
    base: Preset,
    presets: &[Preset],
    factors: &[String],
    base_settings: &TrainSettings,
    iters: usize,
    default_quant: QuantMode,
    quick: bool,
    dir: Direction,
    extra: &[(String, Vec<String>)],
) -> Vec<Variant> {
    let bname = preset_name(base);
    let quant_sweep = factors.iter().any(|f| split_factor(f, dir).0 == "quant");
    let mut all_quants = vec![default_quant];
    if quant_sweep {
        let modes: &[QuantMode] = if quick {
            &[QuantMode::F32, QuantMode::K3]
        } else {
            &QuantMode::ALL
        };
        all_quants.extend(modes.iter().copied().filter(|q| *q != default_quant));
    }
    let mut out = Vec::new();
    let mut list: Vec<Preset> = presets.to_vec();
    if !list.contains(&base) {
        list.insert(0, base);
    }
    for p in list {
        out.push(Variant {
            name: preset_name(p).into(),
            label: preset_name(p).into(),
            factor: "preset".into(),
            value: preset_name(p).into(),
            preset: p,
            sets: vec![],
            train_downscale: 1,
            quants: if p == base {
                all_quants.clone()
            } else {
                vec![default_quant]
            },
        });
    }
    let m = &base_settings.model;
    let enc = &m.field.encoding;
    // Each factor lists its (down, up) values; `dir` keeps one side or both.
    let pick = |dir: Direction, down: i64, up: i64| -> Vec<i64> {
        match dir {
            Direction::Down => vec![down],
            Direction::Up => vec![up],
            Direction::Both => vec![down, up],
        }
    };
    let mut add = |factor: &str, value: String, label: String, sets: Vec<String>, ds: u32| {
        let safe: String = value
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || "+-^.".contains(c) {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        let name = format!("{bname}-{factor}-{safe}");
        out.push(Variant {
            name,
            label,
            factor: factor.into(),
            value,
            preset: base,
            sets,
            train_downscale: ds,
            quants: vec![default_quant],
        });
    };
    for spec in factors {
        let (f, dir) = split_factor(spec, dir);
        match f {
            "iters" => {
                for k in pick(dir, -1, 1) {
                    let n = if k < 0 { (iters / 2).max(1) } else { iters * 2 };
                    add(
                        "iters",
                        n.to_string(),
                        format!("{n} steps"),
                        vec![
                            format!("iters={n}"),
                            format!("anneal_steps={}", (n / 4).max(1)),
                        ],
                        1,
                    );
                }
            }
            "table" => {
                for d in pick(dir, -2, 2) {
                    let l = (enc.grid3.log2_table_size as i64 + d).clamp(10, 24);
                    add(
                        "table",
                        format!("2^{l}"),
                        format!("table 2^{l}"),
                        vec![
                            format!("model.field.encoding.grid3.log2_table_size={l}"),
                            format!("model.field.encoding.grid4.log2_table_size={l}"),
                        ],
                        1,
                    );
                }
            }
            "levels" => {
                for d in pick(dir, -4, 4) {
                    let l = (enc.grid3.levels as i64 + d).clamp(2, 32);
                    add(
                        "levels",
                        l.to_string(),
                        format!("{l} levels"),
                        vec![
                            format!("model.field.encoding.grid3.levels={l}"),
                            format!("model.field.encoding.grid4.levels={l}"),
                        ],
                        1,
                    );
                }
            }
            "finest" => {
                for k in pick(dir, -1, 1) {
                    let f0 = enc.grid3.finest_resolution[0];
                    let fr = if k < 0 { f0 / 2.0 } else { f0 * 2.0 };
                    let mut g4 = enc.grid4.finest_resolution.clone();
                    for v in g4.iter_mut().take(3) {
                        *v = fr;
                    }
                    add(
                        "finest",
                        format!("{fr}"),
                        format!("finest {fr}"),
                        vec![
                            format!(
                                "model.field.encoding.grid3.finest_resolution={}",
                                json!([fr, fr, fr])
                            ),
                            format!("model.field.encoding.grid4.finest_resolution={}", json!(g4)),
                        ],
                        1,
                    );
                }
            }
            "samples" => {
                let (np, nf) = (m.sampler.num_proposal_samples, m.sampler.num_samples);
                for k in pick(dir, -1, 1) {
                    let (a, b) = if k < 0 {
                        ((np / 2).max(1), (nf / 2).max(1))
                    } else {
                        (np * 2, nf * 2)
                    };
                    add(
                        "samples",
                        format!("{a}+{b}"),
                        format!("{a}+{b} samples"),
                        vec![
                            format!("model.sampler.num_proposal_samples={a}"),
                            format!("model.sampler.num_samples={b}"),
                        ],
                        1,
                    );
                }
            }
            "scale" => add("scale", "1/2".into(), "images 1/2".into(), vec![], 2),
            "mask" => {
                let r = enc.mask_resolution;
                for v in pick(dir, r as i64 / 2, r as i64 * 3 / 2) {
                    add(
                        "mask",
                        v.to_string(),
                        format!("mask {v}^3"),
                        vec![format!("model.field.encoding.mask_resolution={v}")],
                        1,
                    );
                }
            }
            "proposal" => {
                let l = m.proposal.encoding.grid3.log2_table_size as i64;
                for d in pick(dir, -2, 2) {
                    let v = (l + d).clamp(10, 24);
                    add(
                        "proposal",
                        format!("2^{v}"),
                        format!("proposal 2^{v}"),
                        vec![
                            format!("model.proposal.encoding.grid3.log2_table_size={v}"),
                            format!("model.proposal.encoding.grid4.log2_table_size={v}"),
                        ],
                        1,
                    );
                }
            }
            _ => {}
        }
    }
    for (label, sets) in extra {
        add("custom", label.clone(), label.clone(), sets.clone(), 1);
    }
    out
}

/// `NAME`, `NAME+` (costlier side only) or `NAME-` (cheaper side only) -> the name and the
/// side (`default` for a bare name).
fn split_factor(spec: &str, default: Direction) -> (&str, Direction) {
    if let Some(n) = spec.strip_suffix('+') {
        (n, Direction::Up)
    } else if let Some(n) = spec.strip_suffix('-') {
        (n, Direction::Down)
    } else {
        (spec, default)
    }
}

/// Parses `--variant LABEL:KEY=VALUE[;KEY=VALUE...]`.
fn parse_variant(s: &str) -> Result<(String, Vec<String>)> {
    let (label, sets) = s
        .split_once(':')
        .with_context(|| format!("--variant `{s}`: expected LABEL:KEY=VALUE[;KEY=VALUE...]"))?;
    let label = label.trim();
    if label.is_empty() || label.len() > 40 {
        bail!("--variant `{s}`: the label must have 1 to 40 characters");
    }
    let sets: Vec<String> = sets
        .split(';')
        .map(|x| x.trim().to_string())
        .filter(|x| !x.is_empty())
        .collect();
    if sets.is_empty() || sets.iter().any(|x| !x.contains('=')) {
        bail!("--variant `{s}`: expected KEY=VALUE pairs after the label");
    }
    Ok((label.to_string(), sets))
}

/// The settings of `v`: its preset's for `data`, the step budget, then its overrides.
/// How long each variant trains: a fixed number of steps, or until converged.
#[derive(Clone, Copy, Debug)]
struct Schedule {
    /// The steps, or the cap.
    iters: usize,
    /// `(every, min_gain_db, stride)` for `--converge`.
    converge: Option<(usize, f64, usize)>,
}

fn settings_for(v: &Variant, data: &Dataset, schedule: Schedule) -> Result<TrainSettings> {
    let iters = schedule.iters;
    let mut s = TrainSettings::for_preset(v.preset, data);
    let mut sets = vec![
        format!("iters={iters}"),
        format!("anneal_steps={}", (iters / 4).max(1)),
        "checkpoint_every=0".to_string(),
    ];
    if let Some((every, gain, stride)) = schedule.converge {
        sets.push(format!("converge_every={every}"));
        sets.push(format!("converge_min_gain_db={gain}"));
        sets.push(format!("eval_stride={stride}"));
    }
    sets.extend(v.sets.iter().cloned());
    s.apply_overrides(None, &sets)
        .map_err(|e| anyhow::anyhow!("variant {}: {e}", v.name))?;
    Ok(s)
}

/// `--cap NAME=STEPS`.
fn parse_cap(s: &str) -> Result<(String, usize)> {
    let (name, n) = s
        .split_once('=')
        .with_context(|| format!("--cap {s}: expected NAME=STEPS"))?;
    let n: usize = n
        .trim()
        .parse()
        .ok()
        .filter(|&n| n > 0)
        .with_context(|| format!("--cap {s}: STEPS must be a whole number of at least 1"))?;
    Ok((name.trim().to_string(), n))
}

fn load_cached(path: &Path, fingerprint: &Value) -> Option<VariantResult> {
    let bytes = std::fs::read(path).ok()?;
    match serde_json::from_slice::<VariantResult>(&bytes) {
        Ok(r) if &r.fingerprint == fingerprint => Some(r),
        Ok(_) => None,
        Err(e) => {
            eprintln!(
                "{}: unreadable cache entry ({e}); measuring again",
                path.display()
            );
            None
        }
    }
}

/// Everything one variant's measurement needs besides the variant.
struct Ctx<'a> {
    eval_data: &'a Dataset,
    stride: usize,
    fps_size: (u32, u32),
    fps_frames: usize,
    keep_models: bool,
}

/// Trains, evaluates, exports and plays one variant.
fn measure(
    v: &Variant,
    settings: TrainSettings,
    train_data: &Dataset,
    dir: &Path,
    ctx: &Ctx,
    fingerprint: Value,
    on_step: &mut dyn FnMut(usize),
) -> Result<VariantResult> {
    let batch_rays = settings.batch_rays;
    let (trainer, outcome) = run_training(train_data, settings, dir, None, &mut |p| {
        for note in &p.notes {
            eprintln!("note: {note}");
        }
        on_step(p.step);
        true
    })
    .with_context(|| format!("training variant {}", v.name))?;
    let cfg = &trainer.settings.model;
    let m = evaluate(
        ctx.eval_data,
        cfg,
        &trainer.layout,
        &trainer.params,
        ctx.stride,
        None,
    )
    .with_context(|| format!("evaluating variant {}", v.name))?;
    let cameras = playback_cameras(train_data);
    let mut quants = Vec::new();
    let (mut fps, mut fps_fixed) = (f64::NAN, f64::NAN);
    for (k, &q) in v.quants.iter().enumerate() {
        let opts = EncodeOptions {
            quant: q,
            ..EncodeOptions::default()
        };
        let (bytes, report) = encode(cfg, &trainer.params, &cameras, &opts)
            .with_context(|| format!("encoding variant {} ({q})", v.name))?;
        let decoded = decode_all(&bytes).with_context(|| format!("decoding variant {}", v.name))?;
        let psnr =
            crate::export::held_out_psnr(ctx.eval_data, cfg, &trainer.layout, ctx.stride, &|t| {
                decoded.params_for_time(t)
            });
        if k == 0 {
            let file = dir.join("model.msth");
            write_atomic(&file, &bytes).with_context(|| format!("writing {}", file.display()))?;
            (fps, fps_fixed) = play_fps(&file, ctx.fps_size, ctx.fps_frames)?;
            if !ctx.keep_models {
                let _ = std::fs::remove_file(&file);
            }
        }
        quants.push(QuantResult {
            quant: q.to_string(),
            file_bytes: report.file_bytes,
            psnr,
        });
    }
    if !ctx.keep_models {
        let _ = std::fs::remove_file(&outcome.checkpoint);
    }
    Ok(VariantResult {
        fingerprint,
        steps: outcome.steps,
        batch_rays,
        params: trainer.params.len(),
        train_seconds: outcome.train_seconds,
        psnr_f32: m.psnr,
        ssim_f32: m.ssim,
        fps,
        fps_fixed: Some(fps_fixed),
        quants,
        held_out: outcome.held_out.clone(),
        converged: outcome.converged,
    })
}

/// Rendering rates of the player on `file` from the first camera, its time moving: full frames
/// (every pixel rendered: a moving camera's cost), and a fixed camera's incremental frames
/// (`frames` of them after the first, the static cache's one-off cost left out).
fn play_fps(file: &Path, size: (u32, u32), frames: usize) -> Result<(f64, f64)> {
    let run = |incremental: bool, frames: usize| {
        let mut opts = msth_player::PlayOptions::new(file.display().to_string());
        opts.size = Some(size);
        opts.frames = Some(frames);
        opts.video = false;
        opts.render.incremental = incremental;
        msth_player::play(&opts, &mut |_, _| {})
            .with_context(|| format!("playing {}", file.display()))
    };
    let moving = run(false, frames.max(1))?.fps().unwrap_or(f64::NAN);
    let fixed = run(true, frames.max(1) + 1)?
        .steady_incremental_fps()
        .unwrap_or(f64::NAN);
    Ok((moving, fixed))
}

pub fn run(a: TradeoffArgs) -> Result<()> {
    let base: Preset = a.base.parse().map_err(anyhow::Error::msg)?;
    let presets: Vec<Preset> = parse_list(&a.presets)
        .iter()
        .map(|p| p.parse::<Preset>().map_err(anyhow::Error::msg))
        .collect::<Result<_>>()?;
    let mut factors = match &a.factors {
        Some(f) => parse_list(f),
        None => FACTORS.iter().map(|s| s.to_string()).collect(),
    };
    if a.converge {
        // Converged runs choose their own steps.
        factors.retain(|f| split_factor(f, Direction::Both).0 != "iters");
        if a.converge_every == 0 {
            bail!("--converge-every must be at least 1");
        }
        if !(a.min_gain.is_finite() && a.min_gain >= 0.0) {
            bail!("--min-gain must be a finite number of dB, 0 or more");
        }
    }
    for f in &factors {
        if !FACTORS.contains(&split_factor(f, Direction::Both).0) {
            bail!(
                "--factors: unknown factor `{f}` (known: {})",
                FACTORS.join(", ")
            );
        }
    }
    let iters = a.iters.unwrap_or(match (a.quick, a.converge) {
        (true, _) => 30,
        (false, true) => 8000,
        (false, false) => 600,
    });
    if iters == 0 {
        bail!("--iters must be at least 1");
    }
    if a.stride == 0 {
        bail!("--stride must be at least 1");
    }
    let schedule = Schedule {
        iters,
        converge: a
            .converge
            .then_some((a.converge_every, a.min_gain, a.stride)),
    };
    let fps_size =
        parse_size(
            a.fps_size
                .as_deref()
                .unwrap_or(if a.quick { "48x36" } else { "160x120" }),
        )?;
    let fps_frames = a.fps_frames.unwrap_or(if a.quick { 2 } else { 4 });
    let default_quant: QuantMode = a.quant.parse().map_err(anyhow::Error::msg)?;
    let direction = match a.direction.as_deref() {
        None if a.quick => Direction::Down,
        None | Some("both") => Direction::Both,
        Some("down") => Direction::Down,
        Some("up") => Direction::Up,
        Some(d) => bail!("--direction {d}: expected down, up or both"),
    };
    let extra: Vec<(String, Vec<String>)> = a
        .variants
        .iter()
        .map(|v| parse_variant(v))
        .collect::<Result<_>>()?;
    std::fs::create_dir_all(a.out.join("runs"))
        .with_context(|| format!("creating {}", a.out.display()))?;

    let data = data::load(&a.data, &a.dataset, &a.out)?;
    if data.test.is_empty() {
        bail!(
            "{}: the dataset has no held-out views to measure on",
            a.data
        );
    }
    let base_settings = settings_for(
        &Variant {
            name: "base".into(),
            label: String::new(),
            factor: String::new(),
            value: String::new(),
            preset: base,
            sets: vec![],
            train_downscale: 1,
            quants: vec![],
        },
        &data,
        schedule,
    )?;
    let mut vs = variants(
        base,
        &presets,
        &factors,
        &base_settings,
        iters,
        default_quant,
        a.quick,
        direction,
        &extra,
    );
    let caps: Vec<(String, usize)> = a.caps.iter().map(|c| parse_cap(c)).collect::<Result<_>>()?;
    for (name, n) in &caps {
        let Some(v) = vs.iter_mut().find(|v| &v.name == name) else {
            bail!(
                "--cap {name}={n}: no variant `{name}` (variants: {})",
                vs.iter()
                    .map(|v| v.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        };
        v.sets.push(format!("iters={n}"));
        v.sets.push(format!("anneal_steps={}", (n / 4).max(1)));
    }
    for (i, v) in vs.iter().enumerate() {
        if vs[..i].iter().any(|w| w.name == v.name) {
            bail!(
                "two variants are both named `{}` (check --variant labels)",
                v.name
            );
        }
    }
    let threads = rayon::current_num_threads();
    println!(
        "msth bench tradeoff: {} ({} training / {} test views), base {}, {}, {} variants, {threads} threads",
        data.name,
        data.train.len(),
        data.test.len(),
        preset_name(base),
        match schedule.converge {
            Some((every, gain, _)) => format!(
                "each variant until it gains less than {gain} dB in {every} steps (at most {iters})"
            ),
            None => format!("{iters} steps per variant"),
        },
        vs.len()
    );

    // Resolve settings and cache state first, so the progress bar knows the work left.
    let mut plan = Vec::new();
    for v in &vs {
        let s = settings_for(v, &data, schedule)?;
        let fingerprint = json!({
            "settings": serde_json::to_value(&s)?,
            "data": a.data, "dataset": data.name, "downscale": a.dataset.downscale,
            "train_downscale": v.train_downscale, "stride": a.stride,
            "fps_size": [fps_size.0, fps_size.1], "fps_frames": fps_frames,
            "quants": v.quants.iter().map(|q| q.to_string()).collect::<Vec<_>>(),
        });
        let dir = a.out.join("runs").join(&v.name);
        let cached = load_cached(&dir.join("result.json"), &fingerprint);
        plan.push((v, s, fingerprint, dir, cached));
    }
    let todo_steps: u64 = plan
        .iter()
        .filter(|p| p.4.is_none())
        .map(|p| p.1.iters as u64)
        .sum();
    let done_already = plan.iter().filter(|p| p.4.is_some()).count();
    if done_already > 0 {
        println!("{done_already} variants cached in {}/runs", a.out.display());
    }
    let pb = ProgressBar::new(todo_steps);
    pb.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise} / ETA {eta}] {bar:30} {pos}/{len} steps {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let ctx = Ctx {
        eval_data: &data,
        stride: a.stride,
        fps_size,
        fps_frames,
        keep_models: a.keep_models,
    };
    let mut small: Option<Dataset> = None;
    let mut results = Vec::new();
    let mut steps_done = 0u64;
    let n = plan.len();
    for (i, (v, s, fingerprint, dir, cached)) in plan.into_iter().enumerate() {
        let r = match cached {
            Some(mut r) => {
                // Results cached before the fixed camera's rate was measured: measured now from
                // the kept file, where there is one.
                let file = dir.join("model.msth");
                if r.fps_fixed.is_none() && file.exists() {
                    r.fps_fixed = Some(play_fps(&file, fps_size, fps_frames)?.1);
                    let path = dir.join("result.json");
                    write_atomic(&path, &serde_json::to_vec_pretty(&r)?)
                        .with_context(|| format!("writing {}", path.display()))?;
                }
                r
            }
            None => {
                pb.set_message(format!("[{}/{n}] {}", i + 1, v.name));
                if pb.is_hidden() {
                    eprintln!("[{}/{n}] {}: {} steps", i + 1, v.name, s.iters);
                }
                let train_data = if v.train_downscale > 1 {
                    if small.is_none() {
                        let mut args = a.dataset.clone();
                        args.downscale = a.dataset.downscale * v.train_downscale;
                        small = Some(data::load(&a.data, &args, &a.out)?);
                    }
                    small.as_ref().expect("loaded above")
                } else {
                    &data
                };
                let iters_v = s.iters as u64;
                let t = Instant::now();
                let r = measure(v, s, train_data, &dir, &ctx, fingerprint, &mut |step| {
                    pb.set_position(steps_done + step as u64)
                })?;
                steps_done += iters_v;
                pb.set_position(steps_done);
                let path = dir.join("result.json");
                write_atomic(&path, &serde_json::to_vec_pretty(&r)?)
                    .with_context(|| format!("writing {}", path.display()))?;
                pb.suspend(|| {
                    println!(
                        "{}: {:.2} dB (f32 {:.2} dB) after {} steps{} in {:.1} s, {} bytes, {:.2} FPS ({:.0} s in all)",
                        v.name,
                        r.quants.first().map(|q| q.psnr).unwrap_or(f64::NAN),
                        r.psnr_f32,
                        r.steps,
                        match (schedule.converge, r.converged) {
                            (Some(_), true) => " (converged)",
                            (Some(_), false) => " (the cap)",
                            (None, _) => "",
                        },
                        r.train_seconds,
                        r.quants.first().map(|q| q.file_bytes).unwrap_or(0),
                        r.fps,
                        t.elapsed().as_secs_f64()
                    )
                });
                r
            }
        };
        results.push((v.clone(), r));
    }
    pb.finish_and_clear();

    let mut rows = Vec::new();
    for (v, r) in &results {
        for (k, q) in r.quants.iter().enumerate() {
            let is_default = k == 0;
            rows.push(Row {
                name: if is_default {
                    v.name.clone()
                } else {
                    format!("{}-{}", v.name, q.quant)
                },
                label: if is_default {
                    v.label.clone()
                } else {
                    format!("{} {}", v.label, q.quant)
                },
                factor: if is_default {
                    v.factor.clone()
                } else {
                    "quant".into()
                },
                value: if is_default {
                    v.value.clone()
                } else {
                    q.quant.clone()
                },
                preset: preset_name(v.preset).into(),
                quant: q.quant.clone(),
                steps: r.steps,
                batch_rays: r.batch_rays,
                params: r.params,
                train_seconds: r.train_seconds,
                psnr_f32: r.psnr_f32,
                ssim_f32: r.ssim_f32,
                psnr: q.psnr,
                file_bytes: q.file_bytes,
                fps: r.fps,
                fps_fixed: r.fps_fixed.unwrap_or(f64::NAN),
                front_time: false,
                front_size: false,
                front_fps: false,
            });
        }
    }
    mark_fronts(&mut rows);
    let meta = Meta {
        dataset: data.name.clone(),
        data: a.data.clone(),
        base: preset_name(base).into(),
        iters,
        stride: a.stride,
        test_views: data.test.len(),
        fps_size,
        fps_frames,
        threads,
        quant: default_quant.to_string(),
        converge: a.converge.then_some((a.converge_every, a.min_gain)),
        caps,
    };
    write_outputs(&a.out, &meta, &rows)?;
    println!("{}", markdown_table(&rows));
    println!(
        "wrote {}/tradeoff.md, tradeoff.csv, tradeoff.json and the plots",
        a.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caps_name_a_variant_and_a_positive_step_count() {
        assert_eq!(parse_cap("paper=1500").unwrap(), ("paper".into(), 1500));
        assert_eq!(parse_cap(" fast = 20 ").unwrap(), ("fast".into(), 20));
        for bad in ["paper", "paper=0", "paper=-3", "paper=many", "=x"] {
            assert!(parse_cap(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn pareto_front_marks_the_non_dominated_points() {
        let pts = [
            (1.0, 5.0),      // front (best y)
            (2.0, 4.0),      // front
            (2.0, 3.0),      // dominated by (2, 4)
            (3.0, 1.0),      // front (best x)
            (0.5, 0.5),      // dominated
            (f64::NAN, 9.0), // never on the front
            (2.0, 4.0),      // equal to a front point: on it too
        ];
        let f = pareto_front(&pts);
        assert_eq!(f, vec![true, true, false, true, false, false, true]);
        // Brute-force check on random points: front points are not dominated, others are.
        let mut rng = msth_core::rng::Rng::new(7);
        let pts: Vec<(f64, f64)> = (0..200)
            .map(|_| ((rng.f32() * 10.0).round() as f64, rng.f32() as f64))
            .collect();
        let f = pareto_front(&pts);
        for (i, p) in pts.iter().enumerate() {
            let dominated = pts
                .iter()
                .any(|q| q.0 >= p.0 && q.1 >= p.1 && (q.0 > p.0 || q.1 > p.1));
            assert_eq!(f[i], !dominated, "point {i} {p:?}");
        }
        assert!(f.iter().any(|&x| x));
        assert!(pareto_front(&[]).is_empty());
    }

    #[test]
    fn fronts_minimise_time_and_size() {
        let row = |t: f64, psnr: f64, bytes: u64, fps: f64| Row {
            name: String::new(),
            label: String::new(),
            factor: String::new(),
            value: String::new(),
            preset: String::new(),
            quant: String::new(),
            steps: 1,
            batch_rays: 1,
            params: 1,
            train_seconds: t,
            psnr_f32: psnr,
            ssim_f32: 0.0,
            psnr,
            file_bytes: bytes,
            fps,
            fps_fixed: f64::NAN,
            front_time: false,
            front_size: false,
            front_fps: false,
        };
        let mut rows = vec![
            row(10.0, 20.0, 100, 5.0),
            row(20.0, 25.0, 50, 1.0),
            row(30.0, 24.0, 200, 0.5),
        ];
        mark_fronts(&mut rows);
        assert_eq!(
            rows.iter().map(|r| r.front_time).collect::<Vec<_>>(),
            [true, true, false]
        );
        assert_eq!(
            rows.iter().map(|r| r.front_size).collect::<Vec<_>>(),
            [false, true, false]
        );
        assert_eq!(
            rows.iter().map(|r| r.front_fps).collect::<Vec<_>>(),
            [true, true, false]
        );
    }
}
