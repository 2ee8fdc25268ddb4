//! One full frame and incremental frames of the GPU renderer's per-sample passes against the CPU
//! renderer on the same model, camera and adapter: full-frame time and PSNR against the CPU,
//! then incremental frames of a fixed camera (sample-level reuse) on the CPU and the GPU.
//!
//! `cargo run --release -p msth-player --example bench_gpu_render -- FILE.msth [SIZE] [FRAMES]`
//! (default 256 pixels square, 4 incremental frames). `FILE` may be `small` instead: a model
//! with random parameters, quick on software adapters (the size of the end-to-end GPU test's
//! model). The camera is the file's first camera: SIZE `N` makes it N x N, its intrinsics scaled
//! by N over its larger side; `WxH` resizes it keeping its horizontal field of view
//! (`Camera::resized`; the training cameras' own aspect shows what they see). Any adapter is used
//! (lavapipe included).
//!
//! Old against new: `MSTH_BENCH_OLD_WGSL=FILE` also times the passes compiled from another
//! version of `render.wgsl` (e.g. `git show a04e488:gpu/shaders/render.wgsl`, the passes before
//! they were optimised; a file from 67e1290 or before reads the proposal field's tables from
//! `rest`, where the uniform no longer points: run it with a binary of its time; the passes of a
//! file from 83ea3f1 or before call the compiled encodings without their `with4` argument, so
//! this binary compiles them generic: give those call sites `, true` to time them compiled), its
//! tables f32; `MSTH_BENCH_OLD_KERNELS=generic` times the generic passes (level values and
//! weights read from buffers; of that file, or of this binary) against the passes compiled for
//! the model (`msth_gpu::specialise`; lavapipe compiles at the first dispatch, so the first new
//! frame includes compiling them). `MSTH_BENCH_REPEAT=N` times N more frames of the new passes,
//! each after one of the old ones, and reports the fastest of each;
//! `MSTH_BENCH_SKIP_INCREMENTAL=1` stops after the full frames. A file's occupancy grid is used
//! by every renderer (CPU and GPU, as `msth play` does; `MSTH_BENCH_NO_SKIP=1` turns it off),
//! and the CPU frame without it is the quality reference printed beside. Timings include the
//! read-back of the frame; "cpu" is this process's CPU time over the same span (all threads:
//! lavapipe's included), which a busy machine inflates less than the wall time. The new passes
//! hold the hash tables as binary16, as `msth play` does for quantised files
//! (`MSTH_BENCH_TABLES=f32` for f32).

use std::time::Instant;

use glam::Vec3;
use msth_codec::OccupancyGrid;
use msth_core::config::{Background, ModelConfig, Preset};
use msth_core::field::ModelLayout;
use msth_core::rng::Rng;
use msth_core::{Camera, SceneBounds};
use msth_player::gpu::{AdapterPolicy, GpuContext, GpuMlps, GpuRenderer};
use msth_player::{RenderSettings, Renderer};
use std::sync::Arc;

/// CPU seconds this process has used (user + system, all threads; Linux `/proc/self/stat`,
/// 100 ticks per second), 0 where unavailable.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    // Fields after the command name (which may hold spaces) in parentheses.
    let rest = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name.
    (ticks(11) + ticks(12)) / 100.0
}

type Loaded = (
    ModelConfig,
    Camera,
    Box<dyn Fn(f32) -> Vec<f32>>,
    Option<Arc<OccupancyGrid>>,
);

/// The model, its first camera and its parameters at a time: from a file, or `small`.
fn load(path: &str) -> Result<Loaded, Box<dyn std::error::Error>> {
    if path == "small" {
        let mut cfg = ModelConfig::preset(
            Preset::Fast,
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
            10,
        );
        let m = &mut cfg;
        m.field.encoding.resize(4, 12, 128.0, 16);
        m.proposal.encoding.resize(2, 10, 32.0, 16);
        m.field.density_hidden = 16;
        m.field.color_hidden = 16;
        m.field.geo_features = 7;
        m.proposal.hidden = 8;
        m.sampler.num_proposal_samples = 24;
        m.sampler.num_samples = 12;
        let layout = ModelLayout::new(&cfg);
        let mut p = layout.init_params(1);
        let mut rng = Rng::new(2);
        for e in &layout.params.entries {
            if e.name.ends_with("h3") || e.name.ends_with("h4") || e.name.ends_with("mask") {
                for v in &mut p[e.range()] {
                    *v = rng.range_f32(-1.0, 1.0);
                }
            }
        }
        let cam = Camera::look_at(64, 64, 0.9, Vec3::new(0.3, -3.5, 1.2), Vec3::ZERO, Vec3::Z);
        return Ok((cfg, cam, Box::new(move |_| p.clone()), None));
    }
    let bytes = std::fs::read(path)?;
    let decoded = msth_codec::decode_all(&bytes)?;
    let meta = &decoded.metadata;
    let cfg = meta.model.clone();
    let cam = *meta.cameras.first().ok_or("the file has no cameras")?;
    let grid = decoded.occupancy.clone().map(Arc::new);
    Ok((
        cfg,
        cam,
        Box::new(move |t| decoded.params_for_time(t)),
        grid,
    ))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        return Err("usage: bench_gpu_render FILE.msth [N | WxH] [FRAMES]".into());
    };
    // SIZE: N (N x N, the camera's intrinsics scaled by N over its larger side) or WxH (the
    // camera resized, its horizontal field of view kept: `Camera::resized`).
    let size = args.get(1).map(String::as_str).unwrap_or("256");
    let frames: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(4);
    let (cfg, mut cam, params_at, grid) = load(path)?;
    let grid = grid.filter(|_| std::env::var("MSTH_BENCH_NO_SKIP").as_deref() != Ok("1"));
    if let Some((w, h)) = size.split_once('x') {
        cam = cam.resized(w.parse()?, h.parse()?);
    } else {
        let n: u32 = size.parse()?;
        let s = n as f32 / cam.width.max(cam.height) as f32;
        cam.fx *= s;
        cam.fy *= s;
        cam.width = n;
        cam.height = n;
        cam.cx = 0.5 * n as f32;
        cam.cy = 0.5 * n as f32;
    }
    let size = format!("{}x{}", cam.width, cam.height);
    let params0 = params_at(0.0);
    println!(
        "model {path}: {} proposal + {} main samples per ray, {} levels; {size}",
        cfg.sampler.num_proposal_samples, cfg.sampler.num_samples, cfg.field.encoding.grid3.levels
    );

    let full = RenderSettings {
        incremental: false,
        ..Default::default()
    };
    let mut cpu_r = Renderer::new(&cfg, full);
    cpu_r.set_occupancy(grid.clone());
    let t = Instant::now();
    let reference = cpu_r.render(&cam, 0.0, &params0);
    let cpu_s = t.elapsed().as_secs_f64();
    match &grid {
        Some(g) => {
            let unskipped = Renderer::new(&cfg, full).render(&cam, 0.0, &params0);
            println!(
                "cpu full frame:                 {cpu_s:8.3} s (occupancy grid: {:.1}% of {}^3 cells occupied; {:.1} dB vs the frame without it, {:.3} s)",
                100.0 * g.occupied_fraction(),
                g.resolution,
                reference.psnr_displayed(&unskipped),
                unskipped.stats.seconds
            )
        }
        None => println!("cpu full frame:                 {cpu_s:8.3} s (no occupancy grid)"),
    }

    let tables: msth_gpu::TableFormat = std::env::var("MSTH_BENCH_TABLES")
        .as_deref()
        .unwrap_or("f16")
        .parse()?;
    let old_source = match std::env::var_os("MSTH_BENCH_OLD_WGSL") {
        Some(p) => Some(std::fs::read_to_string(&p)?),
        None => None,
    };
    let generic = std::env::var("MSTH_BENCH_OLD_KERNELS").as_deref() == Ok("generic");
    let mut old_s = None;
    let mut old_r = None;
    if old_source.is_some() || generic {
        let what = if generic {
            "passes, generic kernels"
        } else {
            "per-sample passes"
        };
        let ctx = match &old_source {
            Some(src) => GpuContext::open_with_source(AdapterPolicy::any(), src)?,
            None => GpuContext::open_with_tables(AdapterPolicy::any(), tables)?,
        };
        match GpuRenderer::new(ctx, &cfg, full) {
            Ok(mut old) => {
                if generic {
                    old.set_mlps(GpuMlps::Generic);
                }
                old.set_occupancy(grid.clone())?;
                let (t, c) = (Instant::now(), cpu_seconds());
                let f = old.render(&cam, 0.0, &params0)?;
                let (secs, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
                println!(
                    "gpu full frame, {what} (old{}):    {secs:8.3} s (cpu {cpu:.1} s)  {:.1} dB vs cpu",
                    if old_source.is_some() { ", MSTH_BENCH_OLD_WGSL" } else { "" },
                    f.psnr_displayed(&reference)
                );
                old_s = Some((secs, cpu));
                old_r = Some(old);
            }
            Err(e) => println!("gpu {what} (old): refused: {e}"),
        }
    }
    let ctx = GpuContext::open_with_tables(AdapterPolicy::any(), tables)?;
    println!(
        "adapter: {}; new kernels: hash tables {}",
        ctx.adapter_name(),
        tables.name()
    );
    let mut new = GpuRenderer::new(ctx, &cfg, full)?;
    new.set_occupancy(grid.clone())?;
    // The first frame compiles nothing more (pipelines are made with the context), but pays
    // the scratch allocation: time the first and a second frame.
    let (t, c) = (Instant::now(), cpu_seconds());
    let f = new.render(&cam, 0.0, &params0)?;
    let (first_s, first_cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
    // Then `MSTH_BENCH_REPEAT` frames (default 1), each after one of the old kernels when there
    // are old kernels and more than one frame (old and new alternate, so that a host whose speed
    // drifts slows both alike); the fastest of each is reported, since a busy host only ever
    // slows a frame down.
    let repeat: usize = std::env::var("MSTH_BENCH_REPEAT")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1)
        .max(1);
    let timed = |r: &mut GpuRenderer| -> Result<(f64, f64), Box<dyn std::error::Error>> {
        let (t, c) = (Instant::now(), cpu_seconds());
        r.render(&cam, 0.0, &params0)?;
        Ok((t.elapsed().as_secs_f64(), cpu_seconds() - c))
    };
    let (mut new_s, mut new_cpu) = (f64::INFINITY, 0.0);
    let (mut all, mut all_old) = (Vec::new(), Vec::new());
    for _ in 0..repeat {
        if let (Some(old), true) = (old_r.as_mut(), repeat > 1) {
            let (s, cpu) = timed(old)?;
            all_old.push(s);
            if old_s.is_none_or(|(o, _)| s < o) {
                old_s = Some((s, cpu));
            }
        }
        let (s, cpu) = timed(&mut new)?;
        all.push(s);
        if s < new_s {
            (new_s, new_cpu) = (s, cpu);
        }
    }
    let spread = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        format!(
            "fastest {:.3} s, median {:.3} s, slowest {:.3} s",
            v[0],
            v[v.len() / 2],
            v[v.len() - 1]
        )
    };
    if repeat > 1 {
        println!("{repeat} more frames, new: {}", spread(&mut all));
        if !all_old.is_empty() {
            println!(
                "{repeat} more frames, old (alternating with new): {}",
                spread(&mut all_old)
            );
        }
    }
    println!(
        "gpu full frame, per-sample passes (new): {first_s:8.3} s first (cpu {first_cpu:.1} s), {new_s:.3} s next (cpu {new_cpu:.1} s)  {:.1} dB vs cpu; {}",
        f.psnr_displayed(&reference),
        new.mlp_status()
    );
    if let Some((o, oc)) = old_s {
        println!(
            "speed-up of a full frame, new vs old: {:.1}x wall, {:.1}x cpu (first frame {:.1}x wall, {:.1}x cpu)",
            o / new_s,
            oc / new_cpu.max(1e-9),
            o / first_s,
            oc / first_cpu.max(1e-9)
        );
    }
    println!("cpu / new gpu full frame: {:.2}x", cpu_s / new_s);
    if std::env::var("MSTH_BENCH_SKIP_INCREMENTAL").as_deref() == Ok("1") {
        return Ok(());
    }

    // Incremental frames of a fixed camera, default settings (sample-level reuse, probes).
    let inc = RenderSettings::default();
    let times: Vec<f32> = (0..=frames)
        .map(|i| i as f32 / frames.max(1) as f32)
        .collect();
    let mut cpu = Renderer::new(&cfg, inc);
    cpu.set_occupancy(grid.clone());
    let ctx = GpuContext::open_with_tables(AdapterPolicy::any(), tables)?;
    let mut gpu = GpuRenderer::new(ctx, &cfg, inc)?;
    gpu.set_occupancy(grid.clone())?;
    let mut full_r = Renderer::new(&cfg, full);
    full_r.set_occupancy(grid.clone());
    let (mut cs, mut gs, mut worst) = (Vec::new(), Vec::new(), f64::INFINITY);
    for (i, &tm) in times.iter().enumerate() {
        let p = params_at(tm);
        let a = cpu.render(&cam, tm, &p);
        let b = gpu.render(&cam, tm, &p)?;
        if i >= 2 {
            cs.push(a.stats.seconds);
            gs.push(b.stats.seconds);
        }
        let g = full_r.render(&cam, tm, &p);
        let pg = b.psnr_displayed(&a);
        worst = worst.min(pg);
        println!(
            "t = {tm:.2}: cpu {:.3} s, gpu {:.3} s ({} rays, {} samples; classify/build {:.3} s); gpu vs cpu incremental {pg:.1} dB, vs cpu full {:.1} dB",
            a.stats.seconds,
            b.stats.seconds,
            b.stats.rays_rendered,
            b.stats.samples_evaluated,
            b.stats.cache_seconds,
            b.psnr_displayed(&g)
        );
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    if !gs.is_empty() {
        println!(
            "incremental frames (after the cache is built): cpu {:.3} s, gpu {:.3} s mean; worst gpu vs cpu {worst:.1} dB",
            mean(&cs),
            mean(&gs)
        );
    }
    Ok(())
}
