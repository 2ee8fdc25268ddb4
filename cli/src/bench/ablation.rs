//! `msth bench ablation DATA`: the paper's ablation (§4.4, Fig. 4) on one dataset. Every variant
//! of the encoding (4D grid only, `h3 + h4`, MSTH "mt", MSTH "mst", "mst" with uncertainty and
//! MINE) is trained with every batch sampler asked for (uniform, the paper's dynamics-aware one,
//! the reference code's static/dynamic one) on the same data, seed and step budget (or
//! wall-time budget with `--time-budget`), then evaluated on the held-out views.
//!
//! Written into `--out`: one folder per run (`VARIANT-SAMPLER/`: checkpoint, `result.json`,
//! `mask.png`), `ablation.json` and `ablation.md` (the table). Every file is written atomically.
//! A run whose `result.json` was made with the same settings is reused; an interrupted run
//! resumes from its checkpoint when the settings match, so the bench can be stopped and started.
//!
//! Figures per run: PSNR, SSIM and D-SSIM (`(1 - SSIM) / 2`) over the held-out views; PSNR inside
//! the dynamic region (held-out pixels whose colour varies over time: temporal std, RMS over the
//! channels, above `--dynamic-threshold`; multi-view video only); the fractions of mask voxels
//! below 0.1 and above 0.9 and the mean mask; the fractions of held-out rays that incremental
//! playback could skip (`m >= 0.9` at every sample carrying weight) among static and among
//! dynamic pixels; steps and training time. `mask.png` shows, for the middle held-out frame:
//! ground truth | render | volume-rendered `1 - m` (bright = dynamic, as the paper's Fig. 4) |
//! rays incremental playback would skip (white).
//!
//! Every variant uses the same proposal network (the preset's, "mt"), so the runs differ only
//! in the main field's encoding and in the sampler.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};

use msth_core::config::{BlendMode, ModelConfig, Preset};
use msth_core::field::ModelLayout;
use msth_dataset::imageio::{colormap, panel, save_png_atomic};
use msth_dataset::{Dataset, Image8};
use msth_trainer::checkpoint::{write_atomic, Checkpoint};
use msth_trainer::eval::render_image;
use msth_trainer::metrics::{dssim, psnr, psnr_from_mse, ssim};
use msth_trainer::ray_sampling::{tempered_weight, PixelStats, SamplingMode};
use msth_trainer::train::{train, TrainSettings};

use crate::data::{self, DataArgs};

/// Arguments of `msth bench ablation`.
#[derive(Args)]
pub struct AblationArgs {
    /// Dataset folder, or `builtin`.
    pub data: String,
    /// Output folder (runs, ablation.json, ablation.md).
    #[arg(long, default_value = "out/ablation")]
    pub out: PathBuf,
    /// fast | balanced | quality | paper
    #[arg(long, default_value = "fast")]
    pub preset: String,
    /// Training steps of every run (the comparison's budget).
    #[arg(long, default_value_t = 400)]
    pub iters: usize,
    /// Rays per step.
    #[arg(long, default_value_t = 512)]
    pub batch_rays: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// A wall-time budget instead: every run stops after this many seconds (or `--iters`
    /// steps). Depends on the machine's load; prefer steps when comparing on a shared machine.
    #[arg(long)]
    pub time_budget: Option<f64>,
    /// Comma-separated variants: 4d, add, mt, mst, full (mst + uncertainty + MINE).
    #[arg(long, default_value = "4d,add,mt,mst,full")]
    pub variants: String,
    /// Comma-separated samplers: uniform, dynamics (the paper), static_dynamic (reference code).
    #[arg(long, default_value = "uniform,dynamics")]
    pub samplers: String,
    /// Evaluate every N-th held-out view.
    #[arg(long, default_value_t = 1)]
    pub eval_stride: usize,
    /// A held-out pixel is dynamic when the temporal std of its colour exceeds this.
    #[arg(long, default_value_t = 0.02)]
    pub dynamic_threshold: f32,
    /// Extra settings for every run, as `msth train --set`.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    #[command(flatten)]
    pub dataset: DataArgs,
}

/// The encodings compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Variant {
    FourD,
    Add,
    Mt,
    Mst,
    Full,
}

impl Variant {
    fn parse(s: &str) -> Result<Self> {
        Ok(match s.trim() {
            "4d" => Variant::FourD,
            "add" => Variant::Add,
            "mt" => Variant::Mt,
            "mst" => Variant::Mst,
            "full" => Variant::Full,
            o => bail!("--variants: unknown variant `{o}` (expected 4d, add, mt, mst, full)"),
        })
    }
    fn name(self) -> &'static str {
        match self {
            Variant::FourD => "4d",
            Variant::Add => "add",
            Variant::Mt => "mt",
            Variant::Mst => "mst",
            Variant::Full => "full",
        }
    }
    fn label(self) -> &'static str {
        match self {
            Variant::FourD => "4D grid only",
            Variant::Add => "h3 + h4",
            Variant::Mt => "MSTH mt",
            Variant::Mst => "MSTH mst",
            Variant::Full => "MSTH mst + uncertainty + MINE",
        }
    }
    fn apply(self, s: &mut TrainSettings) {
        let enc = &mut s.model.field.encoding;
        enc.blend = match self {
            Variant::FourD => BlendMode::FourD,
            Variant::Add => BlendMode::Add,
            Variant::Mt => BlendMode::Mt,
            Variant::Mst | Variant::Full => BlendMode::Mst,
        };
        let full = self == Variant::Full;
        s.mask_learning.uncertainty = full;
        s.mask_learning.mine = full;
    }
}

fn parse_sampler(s: &str) -> Result<SamplingMode> {
    Ok(match s.trim() {
        "uniform" => SamplingMode::Uniform,
        "dynamics" => SamplingMode::Dynamics,
        "static_dynamic" => SamplingMode::StaticDynamic,
        o => {
            bail!("--samplers: unknown sampler `{o}` (expected uniform, dynamics, static_dynamic)")
        }
    })
}

fn sampler_name(m: SamplingMode) -> &'static str {
    match m {
        SamplingMode::Uniform => "uniform",
        SamplingMode::Dynamics => "dynamics",
        SamplingMode::StaticDynamic => "static_dynamic",
    }
}

/// What one run measured (`RUN/result.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunResult {
    pub name: String,
    pub variant: String,
    pub label: String,
    pub sampler: String,
    /// The settings and evaluation options the figures belong to, as JSON text (the reuse key;
    /// compared as text, since numbers read back from JSON need not be bit-identical).
    pub fingerprint: String,
    pub steps: u64,
    pub train_seconds: f64,
    pub field_samples_per_sec: f64,
    /// Loss of the last step trained (`None` when nothing was left to train).
    pub last_loss: Option<f32>,
    pub psnr: f64,
    pub ssim: f64,
    /// `(1 - SSIM) / 2`.
    pub dssim: f64,
    /// PSNR over the held-out dynamic region (per frame, averaged); `None` without one.
    pub dynamic_psnr: Option<f64>,
    /// Share of held-out pixels in the dynamic region.
    pub dynamic_pixel_fraction: Option<f64>,
    pub mask_below_0_1: Option<f64>,
    pub mask_above_0_9: Option<f64>,
    pub mean_mask: Option<f64>,
    /// Held-out rays with `m >= 0.9` at every weighted sample, among static pixels.
    pub skippable_static_rays: Option<f64>,
    /// The same among dynamic pixels (skipping these would freeze motion).
    pub skippable_dynamic_rays: Option<f64>,
    /// Expected share of training rays drawn in dynamic training pixels (temporal std above the
    /// threshold) under this run's sampler; `None` for monocular data or the static/dynamic one.
    pub train_dynamic_ray_share: Option<f64>,
    pub eval_views: usize,
    pub eval_seconds: f64,
    pub picture: PathBuf,
}

/// The whole bench (`ablation.json`).
#[derive(Debug, Serialize)]
struct Report {
    dataset: String,
    preset: String,
    iters: usize,
    batch_rays: usize,
    seed: u64,
    time_budget_secs: Option<f64>,
    threads: usize,
    eval_stride: usize,
    dynamic_threshold: f32,
    extra_settings: Vec<String>,
    runs: Vec<RunResult>,
}

/// Runs the bench; returns the results in table order.
pub fn run(a: AblationArgs) -> Result<Vec<RunResult>> {
    let preset: Preset = a.preset.parse().map_err(anyhow::Error::msg)?;
    let variants: Vec<Variant> = a
        .variants
        .split(',')
        .map(Variant::parse)
        .collect::<Result<_>>()?;
    let samplers: Vec<SamplingMode> = a
        .samplers
        .split(',')
        .map(parse_sampler)
        .collect::<Result<_>>()?;
    if a.iters == 0 || a.eval_stride == 0 {
        bail!("--iters and --eval-stride must be at least 1");
    }
    if !(a.dynamic_threshold.is_finite() && a.dynamic_threshold >= 0.0) {
        bail!("--dynamic-threshold must be finite and >= 0");
    }
    if let Some(b) = a.time_budget {
        if !(b.is_finite() && b > 0.0) {
            bail!("--time-budget must be a positive number of seconds");
        }
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let data = data::load(&a.data, &a.dataset, &a.out)?;
    if data.test.is_empty() {
        bail!("{}: the dataset has no held-out views to evaluate", a.data);
    }
    let test_stats = PixelStats::new(&data.test, false).map_err(anyhow::Error::msg)?;
    let train_stats = PixelStats::new(&data.train, false).map_err(anyhow::Error::msg)?;
    let threads = rayon::current_num_threads();

    let mut specs = Vec::new();
    for &v in &variants {
        for &m in &samplers {
            let mut s = TrainSettings::for_preset(preset, &data);
            // The bench's own settings first, then the user's `--set`s, which win (an
            // `--set anneal_steps=N` used to be overwritten). The proposal annealing keeps the
            // preset's length, as `msth train --iters N` does: annealing over a quarter of a
            // short budget instead (250 of 1000 steps) left `box_animated_stage` in a fog at
            // 14.9 dB where 1000 steps of annealing reach 30.5 (docs/convergence.md).
            let mut sets = vec![
                format!("iters={}", a.iters),
                format!("batch_rays={}", a.batch_rays),
                format!("seed={}", a.seed),
                format!("checkpoint_every={}", (a.iters / 4).max(25)),
                format!("eval_stride={}", a.eval_stride),
                format!("time_limit_secs={}", a.time_budget.unwrap_or(0.0)),
            ];
            sets.extend(a.sets.iter().cloned());
            s.apply_overrides(None, &sets)
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            v.apply(&mut s);
            s.sampling.mode = m;
            s.validate().map_err(anyhow::Error::msg)?;
            specs.push((v, m, s));
        }
    }

    let total = (specs.len() * a.iters) as u64;
    let pb = ProgressBar::new(total);
    pb.set_style(
        ProgressStyle::with_template(
            "ablation [{elapsed_precise} / ETA {eta}] {bar:30} {pos}/{len} steps {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut results = Vec::new();
    for (k, (v, m, s)) in specs.into_iter().enumerate() {
        let name = format!("{}-{}", v.name(), sampler_name(m));
        let dir = a.out.join(&name);
        let base = (k * a.iters) as u64;
        pb.set_position(base);
        pb.set_message(name.clone());
        if pb.is_hidden() {
            eprintln!(
                "ablation: run {}/{}: {name}",
                k + 1,
                variants.len() * samplers.len()
            );
        }
        let fingerprint = serde_json::json!({
            "settings": serde_json::to_value(&s)?,
            "dataset": data.name, "downscale": a.dataset.downscale,
            "dynamic_threshold": a.dynamic_threshold,
        })
        .to_string();
        let share = dynamic_share(&train_stats, &s, a.dynamic_threshold);
        let r = run_one(
            &data,
            &test_stats,
            share,
            &a,
            v,
            m,
            s,
            &name,
            &dir,
            fingerprint,
            &pb,
            base,
        )
        .with_context(|| format!("ablation run {name}"))?;
        results.push(r);
        write_report(&a, &data, threads, &results)?;
    }
    pb.finish_and_clear();
    let md = a.out.join("ablation.md");
    print!("{}", std::fs::read_to_string(&md).unwrap_or_default());
    println!(
        "wrote {} and {}",
        md.display(),
        a.out.join("ablation.json").display()
    );
    Ok(results)
}

#[allow(clippy::too_many_arguments)]
fn run_one(
    data: &Dataset,
    test_stats: &PixelStats,
    share: Option<f64>,
    a: &AblationArgs,
    v: Variant,
    m: SamplingMode,
    s: TrainSettings,
    name: &str,
    dir: &Path,
    fingerprint: String,
    pb: &ProgressBar,
    base: u64,
) -> Result<RunResult> {
    let result_path = dir.join("result.json");
    if let Ok(bytes) = std::fs::read(&result_path) {
        if let Ok(r) = serde_json::from_slice::<RunResult>(&bytes) {
            if r.fingerprint == fingerprint {
                say(pb, format!("{name}: reusing {}", result_path.display()));
                return Ok(r);
            }
        }
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let ckpt_path = dir.join("model.ckpt");
    let settings_json = serde_json::to_value(&s)?;
    // Continue an interrupted run of the same settings (fixed steps only: a time-limited run is
    // not repeatable anyway).
    let resume = if a.time_budget.is_none() {
        Checkpoint::load(&ckpt_path)
            .ok()
            .filter(|c| c.header.train == settings_json && c.header.step as usize <= s.iters)
    } else {
        None
    };
    if let Some(c) = &resume {
        say(pb, format!("{name}: resuming at step {}", c.header.step));
    }
    let every = (s.iters / 10).max(1);
    let (trainer, outcome) = train(data, s, dir, resume, &mut |p| {
        crate::training::print_notes(pb, p);
        pb.set_position(base + p.step as u64);
        if p.step.is_multiple_of(10) {
            pb.set_message(format!("{name}: loss {:.5}", p.loss));
        }
        if pb.is_hidden() && (p.step.is_multiple_of(every) || p.step == p.iters) {
            eprintln!(
                "  {name}: step {}/{} [{:.1} s] loss {:.5}",
                p.step, p.iters, p.elapsed_secs, p.loss
            );
        }
        true
    })?;
    pb.set_message(format!("{name}: evaluating"));
    let t = Instant::now();
    let cfg = &trainer.settings.model;
    let ev = evaluate_run(
        data,
        test_stats,
        a.dynamic_threshold,
        cfg,
        &trainer.layout,
        &trainer.params,
        a.eval_stride,
        &dir.join("mask.png"),
    )?;
    let enc = &trainer.layout.field.encoding;
    let fr = enc.mask_fractions(&trainer.params, 0.1, 0.9);
    let mean_mask = enc.mask.as_ref().map(|(_, r)| {
        let vals = &trainer.params[r.clone()];
        vals.iter()
            .map(|&x| msth_core::activation::sigmoid(x) as f64)
            .sum::<f64>()
            / vals.len().max(1) as f64
    });
    let r = RunResult {
        name: name.to_string(),
        variant: v.name().into(),
        label: v.label().into(),
        sampler: sampler_name(m).into(),
        fingerprint,
        steps: trainer.step as u64,
        train_seconds: outcome.train_seconds,
        field_samples_per_sec: outcome.field_samples_per_sec,
        last_loss: outcome.last_loss.is_finite().then_some(outcome.last_loss),
        psnr: ev.psnr,
        ssim: ev.ssim,
        dssim: dssim(ev.ssim),
        dynamic_psnr: ev.dynamic_psnr,
        dynamic_pixel_fraction: ev.dynamic_fraction,
        mask_below_0_1: fr.map(|f| f.0),
        mask_above_0_9: fr.map(|f| f.1),
        mean_mask,
        skippable_static_rays: ev.skip_static,
        skippable_dynamic_rays: ev.skip_dynamic,
        train_dynamic_ray_share: share,
        eval_views: ev.views,
        eval_seconds: t.elapsed().as_secs_f64(),
        picture: dir.join("mask.png"),
    };
    write_atomic(&result_path, &serde_json::to_vec_pretty(&r)?)
        .with_context(|| format!("writing {}", result_path.display()))?;
    Ok(r)
}

/// The share of training rays a sampler draws in pixels whose temporal std exceeds `threshold`.
fn dynamic_share(stats: &PixelStats, s: &TrainSettings, threshold: f32) -> Option<f64> {
    if !stats.has_video() {
        return None;
    }
    let max = stats.std.iter().fold(0f32, |a, &b| a.max(b)) as f64;
    let weight = |x: f32| match s.sampling.mode {
        SamplingMode::Uniform => Some(1.0),
        SamplingMode::Dynamics => Some(tempered_weight(x as f64, max, s.sampling.tau1 as f64)),
        SamplingMode::StaticDynamic => None,
    };
    let (mut dynamic, mut all) = (0f64, 0f64);
    for &x in &stats.std {
        let w = weight(x)?;
        all += w;
        if x > threshold {
            dynamic += w;
        }
    }
    Some(dynamic / all.max(f64::MIN_POSITIVE))
}

/// A line above the progress bar, or on stderr when the bar is hidden.
fn say(pb: &ProgressBar, msg: String) {
    if pb.is_hidden() {
        eprintln!("{msg}");
    } else {
        pb.println(msg);
    }
}

struct EvalFigures {
    psnr: f64,
    ssim: f64,
    dynamic_psnr: Option<f64>,
    dynamic_fraction: Option<f64>,
    skip_static: Option<f64>,
    skip_dynamic: Option<f64>,
    views: usize,
}

/// The dynamic region of each held-out view (`None`: no temporal history for that view).
fn dynamic_region(stats: &PixelStats, view: usize, threshold: f32) -> Option<Vec<bool>> {
    let g = stats.groups.iter().find(|g| g.views.contains(&view))?;
    if g.frames() < 2 {
        return None;
    }
    let s = &stats.std[g.pixel_offset..g.pixel_offset + g.pixels()];
    Some(s.iter().map(|&v| v > threshold).collect())
}

#[allow(clippy::too_many_arguments)]
fn evaluate_run(
    data: &Dataset,
    stats: &PixelStats,
    threshold: f32,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    stride: usize,
    picture: &Path,
) -> Result<EvalFigures> {
    let chosen: Vec<usize> = (0..data.test.len()).step_by(stride).collect();
    let pic_at = chosen[chosen.len() / 2];
    let has_mask = cfg.field.encoding.blend.uses_mask();
    let (mut psnrs, mut ssims, mut dyn_psnrs) = (Vec::new(), Vec::new(), Vec::new());
    let (mut dyn_px, mut all_px) = (0usize, 0usize);
    let (mut skip_s, mut n_s, mut skip_d, mut n_d) = (0usize, 0usize, 0usize, 0usize);
    let mut any_region = false;
    for &i in &chosen {
        let v = &data.test[i];
        let r = render_image(cfg, layout, params, &v.camera, v.time);
        let gt_img = v.image.loaded();
        let gt = gt_img.to_f32();
        psnrs.push(psnr(&r.rgb, &gt));
        ssims.push(ssim(&r.rgb, &gt, r.width as usize, r.height as usize));
        let region = dynamic_region(stats, i, threshold);
        let n = (r.width * r.height) as usize;
        if let Some(reg) = &region {
            any_region = true;
            let (mut se, mut cnt) = (0f64, 0usize);
            for p in 0..n {
                let skippable = r.min_mask[p] >= 0.9;
                if reg[p] {
                    for ch in 0..3 {
                        se += ((r.rgb[p * 3 + ch] - gt[p * 3 + ch]) as f64).powi(2);
                    }
                    cnt += 1;
                    n_d += 1;
                    skip_d += skippable as usize;
                } else {
                    n_s += 1;
                    skip_s += skippable as usize;
                }
            }
            dyn_px += cnt;
            all_px += n;
            if cnt > 0 {
                dyn_psnrs.push(psnr_from_mse(se / (3 * cnt) as f64));
            }
        } else {
            n_s += n;
            skip_s += r.min_mask.iter().filter(|&&m| m >= 0.9).count();
        }
        if i == pic_at {
            let pred = Image8::from_f32(r.width, r.height, &r.rgb);
            let dynamic: Vec<f32> = r.mask.iter().flat_map(|m| colormap(1.0 - m)).collect();
            let skip: Vec<f32> = (0..n)
                .flat_map(|p| {
                    let on = r.min_mask[p] >= 0.9;
                    let in_region = region.as_ref().is_some_and(|reg| reg[p]);
                    // white: skipped; red tint: a dynamic pixel that would be skipped (wrong);
                    // grey: dynamic pixel re-rendered; black: static pixel re-rendered.
                    match (on, in_region) {
                        (true, false) => [1.0, 1.0, 1.0],
                        (true, true) => [1.0, 0.2, 0.2],
                        (false, true) => [0.45, 0.45, 0.45],
                        (false, false) => [0.0, 0.0, 0.0],
                    }
                })
                .collect();
            let pics = [
                gt_img.as_ref().clone(),
                pred,
                Image8::from_f32(r.width, r.height, &dynamic),
                Image8::from_f32(r.width, r.height, &skip),
            ];
            let refs: Vec<&Image8> = pics.iter().collect();
            save_png_atomic(picture, &panel(&refs))
                .with_context(|| format!("writing {}", picture.display()))?;
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let frac = |a: usize, b: usize| (b > 0).then(|| a as f64 / b as f64);
    Ok(EvalFigures {
        psnr: mean(&psnrs),
        ssim: mean(&ssims),
        dynamic_psnr: (!dyn_psnrs.is_empty()).then(|| mean(&dyn_psnrs)),
        dynamic_fraction: any_region.then(|| dyn_px as f64 / all_px.max(1) as f64),
        skip_static: if has_mask { frac(skip_s, n_s) } else { None },
        skip_dynamic: if has_mask && any_region {
            frac(skip_d, n_d)
        } else {
            None
        },
        views: chosen.len(),
    })
}

fn pct(v: Option<f64>) -> String {
    v.map_or("-".into(), |x| format!("{:.1}%", 100.0 * x))
}

fn write_report(
    a: &AblationArgs,
    data: &Dataset,
    threads: usize,
    runs: &[RunResult],
) -> Result<()> {
    let report = Report {
        dataset: data.name.clone(),
        preset: a.preset.clone(),
        iters: a.iters,
        batch_rays: a.batch_rays,
        seed: a.seed,
        time_budget_secs: a.time_budget,
        threads,
        eval_stride: a.eval_stride,
        dynamic_threshold: a.dynamic_threshold,
        extra_settings: a.sets.clone(),
        runs: runs.to_vec(),
    };
    let p = a.out.join("ablation.json");
    write_atomic(&p, &serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", p.display()))?;
    let budget = match a.time_budget {
        Some(b) => format!("{b} s of training (at most {} steps)", a.iters),
        None => format!("{} steps", a.iters),
    };
    let mut md = format!(
        "Ablation on `{}`: preset {}, {budget} of {} rays, seed {}, {threads} threads{}. \
         Held-out views: every {}-th; dynamic region: held-out pixels with temporal std > {}. \
         D-SSIM = (1 - SSIM) / 2. Skippable rays: `m >= 0.9` at every weighted sample.\n\n",
        data.name,
        a.preset,
        a.batch_rays,
        a.seed,
        if a.sets.is_empty() {
            String::new()
        } else {
            format!(", `--set {}`", a.sets.join(" "))
        },
        a.eval_stride,
        a.dynamic_threshold
    );
    md.push_str("| variant | sampler | steps | train s | PSNR | SSIM | D-SSIM | dynamic PSNR | mask < 0.1 | mask > 0.9 | mean m | skippable static rays | skippable dynamic rays | rays drawn in dynamic pixels | mask picture |\n");
    md.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for r in runs {
        let pic = r
            .picture
            .strip_prefix(&a.out)
            .unwrap_or(&r.picture)
            .display()
            .to_string();
        md.push_str(&format!(
            "| {} | {} | {} | {:.0} | {:.2} | {:.4} | {:.4} | {} | {} | {} | {} | {} | {} | {} | [{pic}]({pic}) |\n",
            r.label,
            r.sampler,
            r.steps,
            r.train_seconds,
            r.psnr,
            r.ssim,
            r.dssim,
            r.dynamic_psnr.map_or("-".into(), |x| format!("{x:.2}")),
            pct(r.mask_below_0_1),
            pct(r.mask_above_0_9),
            r.mean_mask.map_or("-".into(), |x| format!("{x:.3}")),
            pct(r.skippable_static_rays),
            pct(r.skippable_dynamic_rays),
            pct(r.train_dynamic_ray_share),
        ));
    }
    let p = a.out.join("ablation.md");
    write_atomic(&p, md.as_bytes()).with_context(|| format!("writing {}", p.display()))?;
    Ok(())
}
