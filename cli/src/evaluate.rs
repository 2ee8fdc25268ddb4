//! `msth eval FILE.msth --data DATA`: the held-out views of a dataset rendered from a `.msth`
//! file as the players draw it (the decoded, quantised model), through the baked volume, the
//! exact field, or both side by side. `msth eval FILE.msth --path SPEC`: the frames of a camera
//! path (no dataset), the volume's against the exact renderer's.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{anyhow, bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use msth_codec::decode::decode_all;
use msth_core::Camera;
use msth_dataset::imageio::{error_map, panel, save_png_atomic};
use msth_dataset::Image8;
use msth_player::path::CameraPath;
use msth_player::render::{Frame, RenderSettings, Renderer};
use msth_player::volume::{bake, plan_bake};
use msth_trainer::metrics::{psnr, ssim};

use crate::{data, training, EvalArgs, EvalRenderer};

#[derive(Serialize)]
struct FrameScore {
    view: usize,
    time: f32,
    exact_psnr: Option<f64>,
    volume_psnr: Option<f64>,
    /// PSNR of the volume's frame against the exact one.
    volume_vs_exact: Option<f64>,
    exact_seconds: Option<f64>,
    volume_seconds: Option<f64>,
}

#[derive(Serialize)]
struct FileEval {
    file: PathBuf,
    data: String,
    views: usize,
    exact: Option<Summary>,
    volume: Option<Summary>,
    volume_vs_exact: Option<(f64, f64)>,
    bake: Option<serde_json::Value>,
    /// `--path`: seconds a frame, exact and volume (the volume's without its slices' bake).
    seconds_per_frame: Option<(f64, f64)>,
    frames: Vec<FrameScore>,
}

#[derive(Serialize, Clone, Copy)]
struct Summary {
    psnr: f64,
    ssim: f64,
    seconds_per_frame: f64,
}

/// Evaluates `a.checkpoint`, a `.msth` file, on the held-out views of `a.data`.
pub fn eval_file(a: &EvalArgs) -> Result<()> {
    let bytes = std::fs::read(&a.checkpoint)
        .with_context(|| format!("reading {}", a.checkpoint.display()))?;
    let model =
        decode_all(&bytes).with_context(|| format!("decoding {}", a.checkpoint.display()))?;
    let (cfg, fewer) = training::with_samples(
        &model.config,
        model
            .metadata
            .play_samples
            .map(|s| (s.proposal as usize, s.main as usize)),
        a.samples,
    )?;
    let out = a.out.clone().unwrap_or_else(|| {
        let stem = a
            .checkpoint
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "file".into());
        let dir = a
            .checkpoint
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_default();
        match fewer {
            Some((p, m)) => dir.join(format!("eval-{stem}-samples-{p}-{m}")),
            None => dir.join(format!("eval-{stem}")),
        }
    });
    // A path's frames, or the dataset's held-out views.
    let (path_frames, data) = match (&a.path, &a.data) {
        (Some(spec), _) => (Some(path_frames(a, spec, &model)?), None),
        (None, Some(spec)) => {
            let mut data = data::load(spec, &a.dataset, &out)?;
            data.rescale(a.scene_scale);
            if data.test.is_empty() {
                bail!("{spec}: the dataset has no held-out views");
            }
            (None, Some(data))
        }
        (None, None) => bail!("--data DATA or --path SPEC"),
    };
    std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
    let occupancy = model.occupancy.clone().map(Arc::new);
    // A path compares the two renderers, whatever --renderer says.
    let both = path_frames.is_some();
    let want_exact = both || matches!(a.renderer, EvalRenderer::Exact | EvalRenderer::Both);
    let want_volume = both || matches!(a.renderer, EvalRenderer::Volume | EvalRenderer::Both);
    // By default the slices are baked for every view (their time is reported apart), so that
    // the volume's figures are the volume's own.
    let settings = RenderSettings {
        incremental: false,
        march: a.volume.march()?,
        slices: a
            .volume
            .volume_slices
            .unwrap_or(crate::play::VolumeSlices::Always)
            .into(),
        ..Default::default()
    };
    let mut exact = want_exact.then(|| {
        let mut r = Renderer::new(
            &cfg,
            RenderSettings {
                exact: true,
                ..settings
            },
        );
        r.set_occupancy(occupancy.clone());
        r
    });
    let mut bake_json = None;
    let mut volume = if want_volume {
        let mut options = a.volume.options()?;
        options.colour = a.colour.into();
        let plan = plan_bake(
            &cfg,
            &model.params,
            model.occupancy.as_ref(),
            &model.cameras,
            &options,
        )?;
        if let Some(n) = plan.note() {
            eprintln!("note: {n}");
        }
        let progress = msth_core::volume::BakeProgress::default();
        let bar = ProgressBar::new(plan.static_bricks.len() as u64).with_style(
            ProgressStyle::with_template("bake {bar:30} {pos}/{len} bricks {elapsed}")
                .expect("template"),
        );
        let layout = msth_core::field::ModelLayout::new(&cfg);
        let vol = std::thread::scope(|s| {
            let h = s.spawn(|| bake(&plan, &cfg, &layout, &model.params, &progress));
            while !h.is_finished() {
                bar.set_position(progress.done() as u64);
                std::thread::sleep(std::time::Duration::from_millis(100));
            }
            h.join().expect("bake thread")
        })?;
        bar.finish_and_clear();
        let st = vol.stats;
        println!(
            "volume: {}^3 cells in bricks of {}^3: {} of {} candidate bricks kept ({} dynamic, {} dynamic cells, {} time slices of {:.1} MiB and {} field evaluations each), {} occupied cells, {:.1} MiB, baked in {:.2} s ({} field evaluations)",
            vol.geometry.resolution,
            vol.geometry.brick,
            st.bricks,
            st.candidate_bricks,
            st.dynamic_bricks,
            st.dynamic_cells,
            st.slices,
            vol.slice_bytes() as f64 / (1 << 20) as f64,
            plan.slice_evaluations(),
            st.occupied_cells,
            vol.bytes() as f64 / (1 << 20) as f64,
            st.seconds,
            st.vertices_evaluated
        );
        bake_json = Some(serde_json::json!({
            "geometry": vol.geometry, "stats": st, "bytes": vol.bytes(),
            "requested_resolution": plan.requested_resolution,
        }));
        let mut r = Renderer::new(&cfg, settings);
        r.set_occupancy(occupancy.clone());
        r.set_volume(Some(msth_player::volume::BakedVolume {
            volume: vol,
            plan: Arc::new(plan),
        }));
        Some(r)
    } else {
        None
    };

    if let (Some(frames), Some(exact), Some(volume)) = (&path_frames, &mut exact, &mut volume) {
        return eval_path(a, &model, frames, exact, volume, bake_json, &out);
    }
    let data = data.expect("a dataset unless --path");
    let chosen: Vec<usize> = (0..data.test.len()).step_by(a.stride.max(1)).collect();
    let mut frames = Vec::new();
    let (mut sums_e, mut sums_v) = ([0f64; 3], [0f64; 3]);
    let mut vs = Vec::new();
    let mut worst: Option<(f64, usize, Frame, Frame)> = None;
    let mut slice_seconds = 0f64;
    for &i in &chosen {
        let v = &data.test[i];
        let params = model.params_for_time(v.time);
        let gt_image = v.image.loaded();
        let gt = gt_image.to_f32();
        let score = |f: &Frame| {
            (
                psnr(&f.rgb, &gt),
                ssim(&f.rgb, &gt, f.width as usize, f.height as usize),
            )
        };
        let mut fs = FrameScore {
            view: i,
            time: v.time,
            exact_psnr: None,
            volume_psnr: None,
            volume_vs_exact: None,
            exact_seconds: None,
            volume_seconds: None,
        };
        let fe = exact.as_mut().map(|r| {
            r.invalidate();
            r.render(&v.camera, v.time, &params)
        });
        let fv = volume.as_mut().map(|r| {
            r.invalidate();
            r.render_probing(&v.camera, v.time, &params, &mut |t| {
                Some(model.params_for_time(t))
            })
        });
        if let Some(f) = &fe {
            let (p, s) = score(f);
            sums_e[0] += p;
            sums_e[1] += s;
            sums_e[2] += f.stats.seconds;
            fs.exact_psnr = Some(p);
            fs.exact_seconds = Some(f.stats.seconds);
        }
        if let Some(f) = &fv {
            let (p, s) = score(f);
            let render = f.stats.seconds - f.stats.slice_seconds;
            sums_v[0] += p;
            sums_v[1] += s;
            sums_v[2] += render;
            slice_seconds += f.stats.slice_seconds;
            fs.volume_psnr = Some(p);
            fs.volume_seconds = Some(render);
        }
        if let (Some(e), Some(vf)) = (fe, fv) {
            let d = vf.psnr_displayed(&e);
            vs.push(d);
            fs.volume_vs_exact = Some(d);
            if worst.as_ref().is_none_or(|w| d < w.0) {
                worst = Some((d, i, e, vf));
            }
        }
        frames.push(fs);
    }
    let n = chosen.len() as f64;
    let summary = |s: [f64; 3]| Summary {
        psnr: s[0] / n,
        ssim: s[1] / n,
        seconds_per_frame: s[2] / n,
    };
    let report = FileEval {
        file: a.checkpoint.clone(),
        data: a.data.clone().unwrap_or_default(),
        views: chosen.len(),
        exact: want_exact.then(|| summary(sums_e)),
        volume: want_volume.then(|| summary(sums_v)),
        volume_vs_exact: (!vs.is_empty()).then(|| {
            (
                vs.iter().copied().fold(f64::INFINITY, f64::min),
                vs.iter().sum::<f64>() / vs.len() as f64,
            )
        }),
        bake: bake_json,
        seconds_per_frame: None,
        frames,
    };
    for (name, s) in [("exact", report.exact), ("volume", report.volume)] {
        if let Some(s) = s {
            println!(
                "held-out ({name}): PSNR {:.3} dB, SSIM {:.4} over {} views, {:.3} s a frame",
                s.psnr, s.ssim, report.views, s.seconds_per_frame
            );
        }
    }
    if want_volume && slice_seconds > 0.0 {
        println!("  (the volume's time slices took {slice_seconds:.2} s to bake, left out of its frame times)");
    }
    if let Some((min, mean)) = report.volume_vs_exact {
        println!("volume against exact frames: {mean:.2} dB mean, {min:.2} dB worst");
    }
    if let Some((d, i, e, v)) = worst {
        let gt = data.test[i].image.loaded();
        let ei = Image8::from_f32(e.width, e.height, &e.rgb);
        let vi = Image8::from_f32(v.width, v.height, &v.rgb);
        let path = out.join(format!("worst_view_{i:03}.png"));
        save_png_atomic(&path, &panel(&[&gt, &ei, &vi]))?;
        println!(
            "worst view {i} ({d:.2} dB against exact; ground truth | exact | volume): {}",
            path.display()
        );
    }
    let path = out.join("eval-file.json");
    msth_trainer::checkpoint::write_atomic(&path, &serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", path.display()))?;
    println!("report: {}", path.display());
    Ok(())
}

/// Most frames `--path` evaluates.
const MAX_PATH_FRAMES: usize = 4096;

/// The cameras and times of `--path SPEC` (`--frames`, default 8; `--size`; `--time`), as
/// `msth play` places them.
fn path_frames(
    a: &EvalArgs,
    spec: &str,
    model: &msth_codec::decode::DecodedModel,
) -> Result<Vec<(Camera, f32)>> {
    CameraPath::check_options(a.time, a.size, &msth_codec::Limits::default())
        .map_err(|e| anyhow!(e))?;
    let path = CameraPath::parse(spec, &model.config.bounds, &model.cameras, a.size)
        .map_err(|e| anyhow!("--path {spec}: {e}"))?;
    let n = path
        .frames(a.frames, 8, MAX_PATH_FRAMES)
        .map_err(|e| anyhow!(e))?;
    Ok((0..n)
        .map(|i| (path.camera(i, n).0, path.frame_time(i, n, a.time)))
        .collect())
}

/// `--path`: every frame drawn by both renderers; the volume's against the exact one's, the
/// worst as a picture (exact | volume | error map).
fn eval_path(
    a: &EvalArgs,
    model: &msth_codec::decode::DecodedModel,
    path: &[(Camera, f32)],
    exact: &mut Renderer,
    volume: &mut Renderer,
    bake_json: Option<serde_json::Value>,
    out: &Path,
) -> Result<()> {
    let mut frames = Vec::new();
    let mut worst: Option<(f64, usize, Frame, Frame)> = None;
    let (mut exact_s, mut volume_s) = (0f64, 0f64);
    let bar = ProgressBar::new(path.len() as u64).with_style(
        ProgressStyle::with_template("frames {bar:30} {pos}/{len} {elapsed}").expect("template"),
    );
    for (i, (camera, time)) in path.iter().enumerate() {
        let params = model.params_for_time(*time);
        exact.invalidate();
        let e = exact.render(camera, *time, &params);
        volume.invalidate();
        let v = volume.render_probing(camera, *time, &params, &mut |t| {
            Some(model.params_for_time(t))
        });
        let d = v.psnr_displayed(&e);
        let render = v.stats.seconds - v.stats.slice_seconds;
        exact_s += e.stats.seconds;
        volume_s += render;
        frames.push(FrameScore {
            view: i,
            time: *time,
            exact_psnr: None,
            volume_psnr: None,
            volume_vs_exact: Some(d),
            exact_seconds: Some(e.stats.seconds),
            volume_seconds: Some(render),
        });
        if worst.as_ref().is_none_or(|w| d < w.0) {
            worst = Some((d, i, e, v));
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let n = path.len() as f64;
    let vs: Vec<f64> = frames.iter().filter_map(|f| f.volume_vs_exact).collect();
    let (min, mean) = (
        vs.iter().copied().fold(f64::INFINITY, f64::min),
        vs.iter().sum::<f64>() / n,
    );
    println!(
        "{} frames of --path {}: exact {:.3} s a frame, volume {:.3} s ({:.1}x)",
        path.len(),
        a.path.as_deref().unwrap_or_default(),
        exact_s / n,
        volume_s / n,
        exact_s / volume_s.max(1e-9)
    );
    println!("volume against exact frames: {mean:.2} dB mean, {min:.2} dB worst");
    if let Some((d, i, e, v)) = worst {
        let ei = Image8::from_f32(e.width, e.height, &e.rgb);
        let vi = Image8::from_f32(v.width, v.height, &v.rgb);
        let file = out.join(format!("worst_frame_{i:03}.png"));
        save_png_atomic(&file, &panel(&[&ei, &vi, &error_map(&ei, &vi)]))?;
        println!(
            "worst frame {i} (t = {:.3}, {d:.2} dB against exact; exact | volume | error): {}",
            path[i].1,
            file.display()
        );
    }
    let report = FileEval {
        file: a.checkpoint.clone(),
        data: format!("path:{}", a.path.as_deref().unwrap_or_default()),
        views: path.len(),
        exact: None,
        volume: None,
        volume_vs_exact: Some((min, mean)),
        bake: bake_json,
        seconds_per_frame: Some((exact_s / n, volume_s / n)),
        frames,
    };
    let file = out.join("eval-path.json");
    msth_trainer::checkpoint::write_atomic(&file, &serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", file.display()))?;
    println!("report: {}", file.display());
    Ok(())
}
