//! The subcommands around a training run: `msth synth` (a dataset), `msth train`, `msth eval`
//! and `msth render` (a checkpoint's held-out views and frames).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use glam::{Mat4, Vec3};
use indicatif::{ProgressBar, ProgressStyle};

use msth_core::config::{PlaySamples, Preset};
use msth_core::field::ModelLayout;
use msth_core::{Camera, SceneBounds};
use msth_dataset::imageio::{colormap, save_png_atomic};
use msth_dataset::{dnerf, scale_camera, Dataset, Image8};
use msth_trainer::autosize::{autosize, setting_paths};
use msth_trainer::checkpoint::{write_atomic, Checkpoint};
use msth_trainer::device::TrainDevice;
use msth_trainer::eval::{evaluate, render_image, Metrics};
use msth_trainer::synth::{generate, SynthConfig};
use msth_trainer::train::{train as run_training, Progress, TrainOutcome, TrainSettings, Trainer};

use crate::{data, EvalArgs, RenderArgs, SynthArgs, TrainArgs};

pub fn synth(a: SynthArgs) -> Result<()> {
    if let Some(size) = &a.size {
        let (w, h) = parse_size(size)?;
        return synth(SynthArgs {
            size: None,
            width: Some(w),
            height: Some(h),
            ..a
        });
    }
    if a.gltf.is_some() {
        return crate::scenegen::synth_gltf(a);
    }
    if a.layout != "object" || a.supersample.is_some() || a.no_video {
        bail!("--layout, --supersample and --no-video apply to --gltf only");
    }
    let mut cfg = SynthConfig::default();
    if let Some(v) = a.width {
        cfg.width = v;
    }
    if let Some(v) = a.height {
        cfg.height = v;
    }
    if let Some(v) = a.frames {
        cfg.num_frames = v;
    }
    if let Some(v) = a.cameras {
        cfg.num_train_cams = v;
    }
    cfg.motion = !a.static_scene;
    if cfg.width == 0 || cfg.height == 0 || cfg.num_frames == 0 || cfg.num_train_cams == 0 {
        bail!("width, height, frames and cameras must all be at least 1");
    }
    if cfg.width as u64
        * cfg.height as u64
        * cfg.num_frames as u64
        * (cfg.num_train_cams as u64 + 1)
        > 2_000_000_000
    {
        bail!("that dataset would hold more than 2e9 pixels; choose a smaller size");
    }
    let t = Instant::now();
    let data = generate(&cfg);
    dnerf::write(&data, &a.out).with_context(|| format!("writing {}", a.out.display()))?;
    println!(
        "wrote the built-in scene to {} ({} training and {} test images of {}x{}, {} frames) in {:.1} s",
        a.out.display(),
        data.train.len(),
        data.test.len(),
        cfg.width,
        cfg.height,
        cfg.num_frames,
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Parses `WxH` (e.g. `200x150`).
fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("--size `{s}`: expected WxH, e.g. 200x150"))?;
    let parse = |v: &str| -> Result<u32> {
        v.trim()
            .parse()
            .with_context(|| format!("--size `{s}`: `{v}` is not a positive integer"))
    };
    Ok((parse(w)?, parse(h)?))
}

fn read_config_file(path: &Path) -> Result<serde_json::Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let is_json = path.extension().is_some_and(|e| e == "json");
    if is_json {
        serde_json::from_str(&text).with_context(|| format!("{}: malformed JSON", path.display()))
    } else {
        let v: toml::Value =
            toml::from_str(&text).with_context(|| format!("{}: malformed TOML", path.display()))?;
        Ok(serde_json::to_value(v)?)
    }
}

/// Prints the trainer's notes (`note: ...` on stderr, above the bar when there is one).
pub(crate) fn print_notes(pb: &ProgressBar, p: &Progress) {
    for note in &p.notes {
        pb.suspend(|| eprintln!("note: {note}"));
    }
}

/// Shows training progress: a bar with ETA on a terminal (loss, batch PSNR, throughput), a log
/// line every 5% otherwise, which also splits the loss into its terms.
pub(crate) fn report(pb: &ProgressBar, p: &Progress) -> bool {
    print_notes(pb, p);
    pb.set_position(p.step as u64);
    let rate = format!(
        "psnr {:.2} dB  {:.0}k samples/s",
        p.psnr,
        p.field_samples_per_sec / 1e3
    );
    if pb.is_hidden() {
        let every = (p.iters / 20).max(1);
        if p.step.is_multiple_of(every) || p.step == p.iters {
            let t = &p.terms;
            let free = if t.free_space > 0.0 {
                format!(" free space {:.5}", t.free_space)
            } else {
                String::new()
            };
            eprintln!(
                "step {}/{} [{:.1} s] loss {:.5} (rgb {:.5} interlevel {:.5} distortion {:.5} mask {:.5}{free})  {rate}",
                p.step, p.iters, p.elapsed_secs, p.loss, t.rgb, t.interlevel, t.distortion, t.mask
            );
        }
    } else if p.step.is_multiple_of(10) || p.step == p.iters {
        pb.set_message(format!("loss {:.5}  {rate}", p.loss));
    }
    if let Some(h) = p.held_out_psnr {
        pb.suspend(|| println!("step {}: held-out PSNR {h:.2} dB", p.step));
    }
    true
}

pub(crate) fn progress_bar(iters: usize) -> ProgressBar {
    let pb = ProgressBar::new(iters as u64);
    pb.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise} / ETA {eta}] {bar:30} {pos}/{len} {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb
}

/// Trains (and evaluates unless told not to); returns the metrics when evaluated.
pub fn train(a: TrainArgs) -> Result<Option<Metrics>> {
    let preset: Preset = a.preset.parse().map_err(anyhow::Error::msg)?;
    let device: TrainDevice = a.device.parse().map_err(anyhow::Error::msg)?;
    let t_load = Instant::now();
    let mut data = data::load(&a.data, &a.dataset, &a.out)?;
    let load_secs = t_load.elapsed().as_secs_f64();
    let mut settings = TrainSettings::for_preset(preset, &data);
    let resume = if a.resume {
        let p = a.out.join("model.ckpt");
        let c =
            Checkpoint::load(&p).with_context(|| format!("--resume: reading {}", p.display()))?;
        // A resumed run continues in the world scale the checkpoint was trained at.
        settings.scene_scale = c.header.scene_scale();
        Some(c)
    } else {
        None
    };
    let mut sets = a.sets.clone();
    if let Some(v) = a.iters {
        sets.push(format!("iters={v}"));
    }
    if let Some(v) = a.batch_rays {
        sets.push(format!("batch_rays={v}"));
    }
    if let Some(v) = a.seed {
        sets.push(format!("seed={v}"));
    }
    if let Some(v) = a.time_limit {
        sets.push(format!("time_limit_secs={v}"));
    }
    if let Some(v) = a.checkpoint_every {
        sets.push(format!("checkpoint_every={v}"));
    }
    if let Some(v) = a.checkpoint_secs {
        sets.push(format!("checkpoint_secs={v}"));
    }
    let file = a.config.as_deref().map(read_config_file).transpose()?;
    let mut user_keys: Vec<String> = file.as_ref().map(setting_paths).unwrap_or_default();
    user_keys.extend(
        sets.iter()
            .map(|s| s.split('=').next().unwrap_or("").to_string()),
    );
    settings
        .apply_overrides(file, &sets)
        .map_err(anyhow::Error::msg)?;
    // Size the model from the data on top of the preset and the user's settings (which win).
    let sizing = if a.no_autosize || a.resume {
        None
    } else {
        let r = autosize(&data, &mut settings, &user_keys);
        settings.validate().map_err(|e| {
            anyhow::anyhow!("the sized model is invalid ({e}); --no-autosize trains the preset")
        })?;
        Some(r)
    };
    if a.print_settings {
        println!("{}", serde_json::to_string_pretty(&settings)?);
        return Ok(None);
    }
    settings.scale_world(&mut data);
    settings.device = device;
    let layout = ModelLayout::new(&settings.model);
    match &sizing {
        Some(r) => {
            for l in r.lines() {
                println!("{l}");
            }
            std::fs::create_dir_all(&a.out)
                .with_context(|| format!("creating {}", a.out.display()))?;
            let path = a.out.join("sizing.json");
            write_atomic(&path, &serde_json::to_vec_pretty(r)?)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        None if a.resume => println!("autosize: off (resumed: the checkpoint's model is used)"),
        None => println!("autosize: off (--no-autosize): the preset's model as set"),
    }
    println!(
        "dataset {}: {} training views, {} test views, {} frames, loaded in {load_secs:.1} s",
        data.name,
        data.train.len(),
        data.test.len(),
        data.num_frames
    );
    println!(
        "model: {:?} blend, {} parameters ({:.1} MB f32); {} iterations of {} rays, {} -> {} samples per ray",
        settings.model.field.encoding.blend,
        layout.params.total,
        layout.params.total as f64 * 4e-6,
        settings.iters,
        settings.batch_rays,
        settings.model.sampler.num_proposal_samples,
        settings.model.sampler.num_samples
    );
    println!(
        "rays: {:?} spacing from {:.3} to {:.0} world units{}",
        settings.model.sampler.spacing,
        settings.model.sampler.near,
        settings.model.sampler.far,
        match msth_trainer::train::capture_near(&data, &settings.model) {
            Some(n) if n == settings.model.sampler.near => " (the capture's near bound)",
            _ => "",
        }
    );
    println!(
        "schedule: {:?} ray sampling, proposal annealing over {} steps{}{}{}{}",
        settings.sampling.mode,
        settings.anneal_steps,
        match settings.level_ramp_steps {
            0 => String::new(),
            n => format!(
                ", coarse-to-fine over {n} steps (from {:.0}% of the levels)",
                100.0 * settings.level_ramp_start
            ),
        },
        match settings.free_space_weight {
            w if w > 0.0 => format!(", free-space loss {w}"),
            _ => String::new(),
        },
        match settings.distortion_ramp_start {
            0 => String::new(),
            a => format!(
                ", distortion loss {} -> {} over steps {a}-{}",
                settings.distortion_weight,
                settings.distortion_late_weight,
                a + settings.distortion_ramp_steps
            ),
        },
        match settings.grid_decay {
            w if w > 0.0 => format!(", hash-table weight decay {w}"),
            _ => String::new(),
        }
    );
    let pb = progress_bar(settings.iters);
    let stride = settings.eval_stride;
    let iters = settings.iters;
    // Ctrl-C stops after the step in progress, which is then checkpointed.
    crate::interrupt::arm();
    let (trainer, outcome) = run_training(&data, settings, &a.out, resume, &mut |p| {
        report(&pb, p) && !crate::interrupt::pending()
    })?;
    pb.finish();
    print_outcome(&outcome);
    if crate::interrupt::pending() && trainer.step < iters {
        bail!(
            "interrupted at step {} of {iters}: the checkpoint {} holds it; run the same `msth train` command \
             with --resume added to go on from there",
            trainer.step,
            outcome.checkpoint.display()
        );
    }
    if a.no_eval {
        return Ok(None);
    }
    let m = eval_trained(&data, &trainer, stride, &a.out, &outcome)?;
    print_metrics(&m, &a.out.join("metrics.json"));
    Ok(Some(m))
}

fn print_outcome(o: &TrainOutcome) {
    if o.converged {
        println!(
            "converged: the held-out PSNR gained less than the threshold in the last {} steps",
            o.held_out.windows(2).last().map_or(0, |w| w[1].0 - w[0].0)
        );
    }
    println!(
        "trained {} steps in {:.1} s ({:.0} field samples/s, {:.0} rays/s); checkpoint {}",
        o.steps,
        o.train_seconds,
        o.field_samples_per_sec,
        o.rays_per_sec,
        o.checkpoint.display()
    );
}

/// Evaluates a trained model on the held-out views, writing `out/metrics.json` and the pictures
/// in `out/eval/` (printing nothing).
pub(crate) fn eval_trained(
    data: &Dataset,
    trainer: &Trainer,
    stride: usize,
    out: &Path,
    outcome: &TrainOutcome,
) -> Result<Metrics> {
    let s = &trainer.settings;
    eval_and_save(
        data,
        &s.model,
        &trainer.layout,
        &trainer.params,
        stride,
        out,
        outcome,
    )
}

fn eval_and_save(
    data: &Dataset,
    cfg: &msth_core::config::ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    stride: usize,
    out: &Path,
    outcome: &TrainOutcome,
) -> Result<Metrics> {
    let mut m = evaluate(data, cfg, layout, params, stride, Some(&out.join("eval")))
        .context("evaluating")?;
    m.train_seconds = outcome.train_seconds;
    m.train_steps = outcome.steps as u64;
    m.field_samples_per_sec = outcome.field_samples_per_sec;
    m.rays_per_sec = outcome.rays_per_sec;
    let path = out.join("metrics.json");
    m.save(&path)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(m)
}

fn print_metrics(m: &Metrics, path: &Path) {
    println!(
        "held-out: PSNR {:.2} dB, SSIM {:.4}, D-SSIM {:.4} over {} views (rendered in {:.1} s)",
        m.psnr,
        m.ssim,
        m.dssim,
        m.frames.len(),
        m.render_seconds
    );
    println!("metrics: {}", path.display());
    for p in &m.pictures {
        println!("picture (ground truth | render | error): {}", p.display());
    }
}

/// `model` rendered with `samples` per ray (`--samples`; `stored`: the counts a `.msth` file
/// stores for playback), within the bounds of a checkpoint's own sampler, and the counts when they differ from the model's (which it then prints).
pub(crate) fn with_samples(
    model: &msth_core::config::ModelConfig,
    stored: Option<(usize, usize)>,
    samples: PlaySamples,
) -> Result<(msth_core::config::ModelConfig, Option<(usize, usize)>)> {
    let max = msth_core::config::MAX_SAMPLES_PER_RAY;
    let m = samples
        .apply(model, stored, max, max)
        .map_err(|e| anyhow::anyhow!("--{e}"))?;
    let counts = |s: &msth_core::config::SamplerConfig| (s.num_proposal_samples, s.num_samples);
    let fewer = crate::play::samples_note(counts(&m.sampler), counts(&model.sampler)).map(|note| {
        println!("{note}");
        counts(&m.sampler)
    });
    Ok((m, fewer))
}

pub fn eval(a: EvalArgs) -> Result<()> {
    if a.checkpoint.extension().is_some_and(|e| e == "msth") {
        return crate::evaluate::eval_file(&a);
    }
    let mut ckpt = Checkpoint::load(&a.checkpoint)?;
    let (model, fewer) = with_samples(&ckpt.header.model, None, a.samples)?;
    ckpt.header.model = model;
    let out = a.out.clone().unwrap_or_else(|| {
        let dir = a
            .checkpoint
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_else(|| PathBuf::from("."));
        // Other samples than the model's own: a subfolder, so that the checkpoint's own
        // metrics.json (from training) is not replaced.
        match fewer {
            Some((p, m)) => dir.join(format!("eval-samples-{p}-{m}")),
            None => dir,
        }
    });
    let Some(spec) = &a.data else {
        bail!("--path needs a .msth file; a checkpoint is evaluated on --data");
    };
    let mut data = data::load(spec, &a.dataset, &out)?;
    data.rescale(ckpt.header.scene_scale());
    let layout = ModelLayout::new(&ckpt.header.model);
    let outcome = TrainOutcome {
        checkpoint: a.checkpoint.clone(),
        steps: ckpt.header.step as usize,
        train_seconds: ckpt.header.train_seconds,
        field_samples_per_sec: 0.0,
        rays_per_sec: 0.0,
        last_loss: f32::NAN,
        held_out: Vec::new(),
        converged: false,
    };
    let m = eval_and_save(
        &data,
        &ckpt.header.model,
        &layout,
        &ckpt.params,
        a.stride,
        &out,
        &outcome,
    )?;
    print_metrics(&m, &out.join("metrics.json"));
    Ok(())
}

fn parse_camera(spec: &str, ckpt: &Checkpoint) -> Result<Camera> {
    let cams = &ckpt.header.cameras;
    if let Ok(i) = spec.parse::<usize>() {
        return cams.get(i).copied().with_context(|| {
            format!(
                "--camera {i}: the checkpoint has {} cameras (0..{})",
                cams.len(),
                cams.len()
            )
        });
    }
    let template = cams
        .first()
        .copied()
        .unwrap_or_else(|| Camera::from_fov_x(256, 256, 0.8, Mat4::IDENTITY));
    if let Some(rest) = spec.strip_prefix("orbit:") {
        let v: Vec<f32> = rest
            .split(',')
            .map(|s| s.trim().parse::<f32>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("--camera {spec}: expected orbit:AZ,EL,DIST"))?;
        if v.len() != 3 || !v.iter().all(|x| x.is_finite()) || v[2] <= 0.0 {
            bail!("--camera {spec}: expected orbit:AZ,EL,DIST with finite numbers and DIST > 0");
        }
        let (lo, hi) = ckpt.header.model.bounds.extent();
        let centre = match ckpt.header.model.bounds {
            SceneBounds::Box { .. } => 0.5 * (lo + hi),
            SceneBounds::Contracted { center, .. } => center,
        };
        let (az, el) = (v[0].to_radians(), v[1].to_radians());
        let dist = v[2] * ckpt.header.scene_scale();
        let eye = centre + dist * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        let fov = 2.0 * (0.5 * template.width as f32 / template.fx).atan();
        return Ok(Camera::look_at(
            template.width,
            template.height,
            fov,
            eye,
            centre,
            Vec3::Z,
        ));
    }
    let path = Path::new(spec);
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("--camera {spec}: not an index, orbit: spec or readable file"))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{spec}: malformed JSON"))?;
    let m = v
        .get("transform_matrix")
        .and_then(|m| serde_json::from_value::<[[f32; 4]; 4]>(m.clone()).ok())
        .with_context(|| {
            format!("{spec}: field `transform_matrix` must be a 4x4 array of numbers")
        })?;
    let rows = Mat4::from_cols_array_2d(&m).transpose();
    let w = v
        .get("w")
        .and_then(|x| x.as_u64())
        .map(|x| x as u32)
        .unwrap_or(template.width);
    let h = v
        .get("h")
        .and_then(|x| x.as_u64())
        .map(|x| x as u32)
        .unwrap_or(template.height);
    let cam = if let Some(fx) = v.get("fl_x").and_then(|x| x.as_f64()) {
        let fy = v.get("fl_y").and_then(|x| x.as_f64()).unwrap_or(fx);
        Camera {
            width: w,
            height: h,
            fx: fx as f32,
            fy: fy as f32,
            cx: v
                .get("cx")
                .and_then(|x| x.as_f64())
                .unwrap_or(w as f64 / 2.0) as f32,
            cy: v
                .get("cy")
                .and_then(|x| x.as_f64())
                .unwrap_or(h as f64 / 2.0) as f32,
            world_from_camera: rows,
        }
    } else if let Some(a) = v.get("camera_angle_x").and_then(|x| x.as_f64()) {
        Camera::from_fov_x(w, h, a as f32, rows)
    } else {
        bail!("{spec}: needs `fl_x` or `camera_angle_x`");
    };
    cam.validate().map_err(|e| anyhow::anyhow!("{spec}: {e}"))?;
    // The file is in the dataset's world; the model may live in a scaled one.
    Ok(scale_camera(cam, ckpt.header.scene_scale()))
}

pub fn render(a: RenderArgs) -> Result<()> {
    let ckpt = Checkpoint::load(&a.checkpoint)?;
    if a.list_cameras {
        for (i, c) in ckpt.header.cameras.iter().enumerate() {
            let p = c.center();
            println!(
                "{i}: {}x{} at ({:.3}, {:.3}, {:.3})",
                c.width, c.height, p.x, p.y, p.z
            );
        }
        return Ok(());
    }
    if !(a.time.is_finite() && (0.0..=1.0).contains(&a.time)) {
        bail!("--time {} must be in [0, 1]", a.time);
    }
    let mut cam = parse_camera(&a.camera, &ckpt)?;
    if a.width.is_some() || a.height.is_some() {
        let w = a.width.unwrap_or(cam.width);
        let sx = w as f32 / cam.width as f32;
        let h = a.height.unwrap_or((cam.height as f32 * sx).round() as u32);
        if w == 0 || h == 0 || w > 16384 || h > 16384 {
            bail!("image size {w}x{h} must be between 1 and 16384 per side");
        }
        cam = cam.resized(w, h);
    }
    let (model, _) = with_samples(&ckpt.header.model, None, a.samples)?;
    let layout = ModelLayout::new(&model);
    let t = Instant::now();
    let r = render_image(&model, &layout, &ckpt.params, &cam, a.time);
    let secs = t.elapsed().as_secs_f64();
    let img = Image8::from_f32(r.width, r.height, &r.rgb);
    save_png_atomic(&a.output, &img).with_context(|| format!("writing {}", a.output.display()))?;
    println!(
        "rendered {}x{} at t = {} in {:.2} s: {}",
        r.width,
        r.height,
        a.time,
        secs,
        a.output.display()
    );
    if a.extras {
        let stem = a.output.with_extension("");
        // The colour scale ends at the 98th percentile: a few rays that see through to the far
        // plane (thousands of units on a contracted scene) would otherwise make the rest black.
        let mut sorted: Vec<f32> = r.depth.iter().copied().filter(|d| d.is_finite()).collect();
        sorted.sort_by(f32::total_cmp);
        let maxd = sorted
            .get((sorted.len() * 98 / 100).min(sorted.len().saturating_sub(1)))
            .copied()
            .unwrap_or(1.0)
            .max(1e-6);
        let depth: Vec<f32> = r
            .depth
            .iter()
            .flat_map(|d| colormap((d / maxd).min(1.0)))
            .collect();
        let mask: Vec<f32> = r.mask.iter().flat_map(|m| colormap(1.0 - m)).collect();
        let dp = PathBuf::from(format!("{}_depth.png", stem.display()));
        let mp = PathBuf::from(format!("{}_dynamic.png", stem.display()));
        save_png_atomic(&dp, &Image8::from_f32(r.width, r.height, &depth))?;
        save_png_atomic(&mp, &Image8::from_f32(r.width, r.height, &mask))?;
        println!(
            "depth (0 to {maxd:.3} scene units, the 98th percentile): {}\ndynamic weight (1 - mask, bright = dynamic): {}",
            dp.display(),
            mp.display()
        );
    }
    Ok(())
}
