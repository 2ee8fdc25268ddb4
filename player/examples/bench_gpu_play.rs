//! Playback rates of the GPU renderer at a real video size (issue #17): frames per second of
//! the per-sample passes at W x H (default 1352x1014, the Plenoptic videos' size) for
//!
//! 1. full frames of a fixed camera, the timeline advancing (every pixel rendered each frame);
//! 2. a moving camera: the file's first camera orbiting the scene's centre (a yaw of up to
//!    +-10 degrees about the camera's up axis), the timeline advancing: every frame is a full
//!    frame, as while a user drags the view;
//! 3. incremental frames of a fixed camera (the static cache, sample-level reuse and probes:
//!    `RenderSettings::default()`), after the frame that builds the cache;
//!
//! and, as the check that the adapter computes the right frames, the GPU frame against the CPU
//! renderer's at a quarter of the size (PSNR) with both times.
//!
//! Frame times include the upload of the parameters for the frame's time and the read-back of
//! the whole frame (a viewer would present it instead); the parameters for each time are
//! decoded before the timed loop, as the player's streaming thread does ahead of playback.
//! The file's occupancy grid is used (`MSTH_BENCH_NO_SKIP=1` turns it off);
//! `MSTH_BENCH_SAMPLES=fast|faster|P,M` renders with fewer samples per ray than the model's;
//! `MSTH_BENCH_PROFILE=1` ends with one full frame whose passes are timed one by one;
//! `MSTH_BENCH_COMPARE_PARAMS=1` compares each frame's parameters with the device's copy
//! instead of passing the player's version of them (`GpuRenderer::set_params_version`);
//! `MSTH_BENCH_SCRATCH_MIB=N` lets a batch of rays take N MiB of scratch instead of the
//! adapter's default (1024 on a discrete GPU, else 128: `GpuRenderer::set_scratch_budget`);
//! `MSTH_BENCH_TABLES=f32|f16` holds the hash tables in that format (default: `msth play`'s
//! choice, f32 for a lossless file, else f16); `MSTH_BENCH_LANES=1|2|4` compiles the
//! per-sample passes for that many samples per invocation (default
//! `msth_gpu::DEFAULT_LANES`, 4).
//!
//! `cargo run --release -p msth-player --example bench_gpu_play -- FILE.msth [WxH] [FRAMES]`
//! (default 1352x1014, 24 frames per measurement). Any adapter is used (lavapipe included: use
//! a small size there).

use std::sync::Arc;
use std::time::Instant;

use glam::{Mat4, Vec3};
use msth_core::{Camera, SceneBounds};
use msth_player::gpu::{AdapterPolicy, GpuContext, GpuRenderer};
use msth_player::{RenderSettings, Renderer, TableFormat};

/// `cam` orbited by `degrees` about its own up axis through `pivot`.
fn orbited(cam: &Camera, pivot: Vec3, degrees: f32) -> Camera {
    let up = cam.world_from_camera.y_axis.truncate().normalize();
    let r = Mat4::from_translation(pivot)
        * Mat4::from_axis_angle(up, degrees.to_radians())
        * Mat4::from_translation(-pivot);
    Camera {
        world_from_camera: r * cam.world_from_camera,
        ..*cam
    }
}

fn stats(ms: &[f64]) -> String {
    if ms.is_empty() {
        return "no frames timed (give more FRAMES)".into();
    }
    let n = ms.len().max(1) as f64;
    let mean = ms.iter().sum::<f64>() / n;
    let mut s = ms.to_vec();
    s.sort_by(f64::total_cmp);
    let med = s.get(s.len() / 2).copied().unwrap_or(0.0);
    let worst = s.last().copied().unwrap_or(0.0);
    let fps = 1000.0 / mean.max(1e-9);
    // Below 1 FPS (software adapters at large sizes) one decimal would print 0.0.
    let digits = if fps < 1.0 { 3 } else { 1 };
    format!(
        "{fps:7.digits$} FPS (mean {mean:.2} ms, median {med:.2} ms, worst {worst:.2} ms over {} frames)",
        ms.len()
    )
}

/// The mean host time of the frames (`FrameStats::host_seconds`: reading the output back and
/// converting it), appended to a timed line.
fn host(ms: &[f64]) -> String {
    if ms.is_empty() {
        return String::new();
    }
    let mean = ms.iter().sum::<f64>() / ms.len() as f64;
    format!("; host {mean:.2} ms of it")
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        return Err("usage: bench_gpu_play FILE.msth [WxH] [FRAMES]".into());
    };
    let (w, h) = match args.get(1) {
        Some(s) => {
            let (a, b) = s.split_once('x').ok_or("size: WxH, e.g. 1352x1014")?;
            (a.parse::<u32>()?, b.parse::<u32>()?)
        }
        None => (1352, 1014),
    };
    let frames: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(24);
    let bytes = std::fs::read(path)?;
    let decoded = msth_codec::decode_all(&bytes)?;
    // `MSTH_BENCH_SAMPLES=fast|faster|P,M`: fewer samples per ray than the model's, as `msth
    // play --samples`.
    let samples: msth_core::config::PlaySamples = std::env::var("MSTH_BENCH_SAMPLES")
        .unwrap_or_else(|_| "full".into())
        .parse()?;
    let cfg = samples.apply(
        &decoded.metadata.model,
        decoded
            .metadata
            .play_samples
            .map(|s| (s.proposal as usize, s.main as usize)),
        1024,
        512,
    )?;
    let cam0 = *decoded
        .metadata
        .cameras
        .first()
        .ok_or("the file has no cameras")?;
    let grid = decoded
        .occupancy
        .clone()
        .map(Arc::new)
        .filter(|_| std::env::var("MSTH_BENCH_NO_SKIP").as_deref() != Ok("1"));
    let pivot = match cfg.bounds {
        SceneBounds::Box { min, max } => 0.5 * (min + max),
        SceneBounds::Contracted { center, .. } => center,
    };
    let cam = cam0.resized(w, h);
    println!(
        "model {path}: {} proposal + {} main samples per ray, {} levels; {w}x{h} ({} pixels); occupancy grid: {}",
        cfg.sampler.num_proposal_samples,
        cfg.sampler.num_samples,
        cfg.field.encoding.grid3.levels,
        w * h,
        match &grid {
            Some(g) => format!("{:.1}% of {}^3 cells occupied", 100.0 * g.occupied_fraction(), g.resolution),
            None => "none".into(),
        }
    );
    let times: Vec<f32> = (0..frames)
        .map(|i| i as f32 / frames.max(2).saturating_sub(1) as f32)
        .collect();
    let t = Instant::now();
    let params: Vec<Vec<f32>> = times.iter().map(|&t| decoded.params_for_time(t)).collect();
    // One version per time chunk, as the player gives the renderer (its buffer changes with the
    // chunk); `MSTH_BENCH_COMPARE_PARAMS=1`: none, every frame compares the parameters instead.
    let versions: Option<Vec<u64>> =
        (std::env::var("MSTH_BENCH_COMPARE_PARAMS").as_deref() != Ok("1")).then(|| {
            times
                .iter()
                .map(|&t| decoded.chunk_for_time(t).map_or(0, |c| c as u64 + 1))
                .collect()
        });
    let version = |r: &mut GpuRenderer, i: usize| {
        if let Some(v) = &versions {
            r.set_params_version(v[i]);
        }
    };
    println!(
        "parameters for {frames} times decoded ahead: {:.2} ms each (host)",
        1000.0 * t.elapsed().as_secs_f64() / frames.max(1) as f64
    );

    let full = RenderSettings {
        incremental: false,
        ..Default::default()
    };
    let tables = match std::env::var("MSTH_BENCH_TABLES") {
        Ok(v) => v.parse()?,
        Err(_) => msth_player::play::gpu_tables_for(decoded.metadata.quant),
    };
    let lanes: Option<u32> = match std::env::var("MSTH_BENCH_LANES") {
        Ok(v) => Some(v.parse().map_err(|_| "MSTH_BENCH_LANES: 1, 2 or 4")?),
        Err(_) => None,
    };
    let ctx = GpuContext::open_with_kernels(AdapterPolicy::any(), tables, lanes)?;
    let mib = |t| {
        let [(_, a), (_, b), _] = msth_player::gpu::GpuModel::new(&cfg)
            .map(|m| m.buffer_sizes(t))
            .unwrap_or_default();
        (a + b) as f64 / (1 << 20) as f64
    };
    println!(
        "adapter: {}; {} samples per invocation; hash tables {} ({:.1} MiB on the device; f32 {:.1}, f16 {:.1})",
        ctx.adapter_name(),
        ctx.lanes(),
        tables.name(),
        mib(tables),
        mib(TableFormat::F32),
        mib(TableFormat::F16)
    );

    let scratch_mib: Option<u64> = match std::env::var("MSTH_BENCH_SCRATCH_MIB") {
        Ok(v) => Some(
            v.parse()
                .ok()
                .filter(|&m| (1..=1 << 20).contains(&m))
                .ok_or("MSTH_BENCH_SCRATCH_MIB: a whole number of MiB, 1 to 1048576")?,
        ),
        Err(_) => None,
    };

    // Correctness on this adapter: GPU against CPU at a quarter of the size.
    let small = cam0.resized((w / 4).max(1), (h / 4).max(1));
    let mut cpu = Renderer::new(&cfg, full);
    cpu.set_occupancy(grid.clone());
    let t = Instant::now();
    let reference = cpu.render(&small, 0.0, &params[0]);
    let cpu_s = t.elapsed().as_secs_f64();
    let mut gpu = GpuRenderer::new(ctx, &cfg, full)?;
    gpu.set_occupancy(grid.clone())?;
    if let Some(mib) = scratch_mib {
        gpu.set_scratch_budget(mib << 20);
    }
    gpu.render(&small, 0.0, &params[0])?;
    let t = Instant::now();
    let f = gpu.render(&small, 0.0, &params[0])?;
    let gpu_s = t.elapsed().as_secs_f64();
    println!(
        "check at {}x{}: gpu vs cpu {:.1} dB; cpu {:.3} s ({} threads), gpu {:.4} s ({:.2}x as fast)",
        small.width,
        small.height,
        f.psnr_displayed(&reference),
        cpu_s,
        rayon::current_num_threads(),
        gpu_s,
        cpu_s / gpu_s.max(1e-9)
    );

    // 1. Full frames, fixed camera.
    version(&mut gpu, 0);
    let t = Instant::now();
    let first = gpu.render(&cam, times[0], &params[0])?;
    let batch = gpu.batch_rays().unwrap_or(0).max(1) as usize;
    println!(
        "first full frame {w}x{h}: {:.1} ms (scratch allocation included); {} rays rendered, {} empty; {} batches of up to {batch} rays ({} MiB of scratch per batch at most)",
        1000.0 * t.elapsed().as_secs_f64(),
        first.stats.rays_rendered,
        first.stats.rays_empty,
        (w as usize * h as usize).div_ceil(batch),
        gpu.scratch_budget() >> 20,
    );
    let (mut ms, mut host_ms) = (Vec::new(), Vec::new());
    for (i, &tm) in times.iter().enumerate() {
        version(&mut gpu, i);
        let t = Instant::now();
        let f = gpu.render(&cam, tm, &params[i])?;
        ms.push(1000.0 * t.elapsed().as_secs_f64());
        host_ms.push(1000.0 * f.stats.host_seconds);
    }
    println!(
        "full frames, fixed camera:   {}{}",
        stats(&ms),
        host(&host_ms)
    );

    // 2. Moving camera.
    let (mut ms, mut host_ms) = (Vec::new(), Vec::new());
    for (i, &tm) in times.iter().enumerate() {
        let phase = i as f32 / frames.max(1) as f32 * std::f32::consts::TAU;
        let c = orbited(&cam, pivot, 10.0 * phase.sin());
        version(&mut gpu, i);
        let t = Instant::now();
        let f = gpu.render(&c, tm, &params[i])?;
        ms.push(1000.0 * t.elapsed().as_secs_f64());
        host_ms.push(1000.0 * f.stats.host_seconds);
    }
    println!(
        "full frames, moving camera:  {}{}",
        stats(&ms),
        host(&host_ms)
    );

    // 3. Incremental frames, fixed camera.
    let ctx = GpuContext::open_with_kernels(AdapterPolicy::any(), tables, lanes)?;
    let mut inc = GpuRenderer::new(ctx, &cfg, RenderSettings::default())?;
    inc.set_occupancy(grid.clone())?;
    if let Some(mib) = scratch_mib {
        inc.set_scratch_budget(mib << 20);
    }
    let (mut ms, mut host_ms) = (Vec::new(), Vec::new());
    let (mut build_ms, mut rendered, mut samples) = (0.0, 0, 0);
    for (i, &tm) in times.iter().enumerate() {
        version(&mut inc, i);
        let t = Instant::now();
        let f = inc.render(&cam, tm, &params[i])?;
        let e = 1000.0 * t.elapsed().as_secs_f64();
        match i {
            0 => {}
            1 => build_ms = e,
            _ => {
                ms.push(e);
                host_ms.push(1000.0 * f.stats.host_seconds);
                rendered = f.stats.rays_rendered;
                samples = f.stats.samples_evaluated;
            }
        }
    }
    // The counts come from the timed frames (the third on): none with fewer frames.
    let counts = if ms.is_empty() {
        String::new()
    } else {
        format!("; {rendered} dynamic rays, {samples} samples per frame")
    };
    println!(
        "incremental, fixed camera:   {}{} (cache built in {build_ms:.1} ms{counts})",
        stats(&ms),
        host(&host_ms)
    );

    // MSTH_BENCH_PROFILE=1: one more full frame with every pass timed on its own (stderr).
    if std::env::var("MSTH_BENCH_PROFILE").as_deref() == Ok("1") {
        std::env::set_var("MSTH_GPU_PASS_PROFILE", "1");
        version(&mut gpu, 0);
        gpu.render(&cam, times[0], &params[0])?;
    }
    Ok(())
}
