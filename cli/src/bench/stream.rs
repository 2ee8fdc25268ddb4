//! `msth bench stream FILE.msth [BASELINE.msth]`: streaming over a throttled loopback link.
//!
//! 1. **Time to first picture.** For each file (a layered one and, as the baseline, the same
//!    model without layers), a fresh server on a loopback port paces every response to `--rate`
//!    (`msth serve --rate-limit`); the player opens the URL, its layer policy plays from time 0,
//!    and the clock stops when the first frame's parameters are in (the layers it has then are
//!    reported) and again once one CPU frame of `--size` from the file's camera 0 is drawn from
//!    them (the picture). Its PSNR against the frame drawn from every layer says how far the
//!    first picture is from full quality.
//! 2. **A changing link** (`--schedule`, e.g. `50mbit,3mbit@4,50mbit@12`): the player plays the
//!    layered file in real time at the file's frame rate (30 fps when it has none) for
//!    `--seconds`, without drawing; every frame due notes the layers it would be drawn with, or a
//!    stall until its chunk's layer 0 is in. Writes the layers and the measured rate over time
//!    (`stream.json`, `layers_over_time.png`).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use msth_core::pipeline::{render_chunk, RenderOutput, TimedRay, Workspace};
use msth_player::{HttpOptions, HttpSource, ModelStream};
use msth_server::throttle::RateSchedule;
use msth_server::{BackgroundServer, ServerConfig};
use rayon::prelude::*;
use serde_json::json;

#[derive(Args)]
pub struct BenchStreamArgs {
    /// The layered `.msth` file (`msth export --layers N`).
    pub file: PathBuf,
    /// The same model without layers, the baseline of the time to first picture.
    pub baseline: Option<PathBuf>,
    /// Link rates for the time to first picture (bytes/s, or `10mbit`, `2mbit`, ...).
    #[arg(long, value_delimiter = ',', default_value = "10mbit,2mbit")]
    pub rate: Vec<String>,
    /// The changing link of the playback run (`msth serve --rate-limit` syntax); none: skipped.
    #[arg(long)]
    pub schedule: Option<String>,
    /// Seconds of real-time playback on the changing link.
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Size of the first picture, WxH.
    #[arg(long, default_value = "160x120")]
    pub size: String,
    /// Where to write stream.json and the plot.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Serves `file`'s folder at `rate` and opens it.
fn serve(file: &std::path::Path, schedule: RateSchedule) -> Result<(BackgroundServer, String)> {
    let dir = file
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(std::path::Path::new("."));
    let name = file
        .file_name()
        .context("the file has no name")?
        .to_string_lossy()
        .to_string();
    let server = BackgroundServer::start(ServerConfig {
        addr: "127.0.0.1:0".parse().unwrap(),
        rate_limit: Some(schedule),
        ..ServerConfig::new(dir)
    })?;
    let url = format!("http://{}/models/{name}", server.addr());
    Ok((server, url))
}

/// One CPU frame of camera 0 resized to `w x h` at time `t`.
fn picture(meta: &msth_codec::Metadata, params: &[f32], w: u32, h: u32) -> Vec<[f32; 3]> {
    let model = &meta.model;
    let layout = msth_core::field::ModelLayout::new(model);
    let Some(cam) = meta.cameras.first() else {
        return Vec::new();
    };
    let cam = cam.resized(w, h);
    let rays: Vec<TimedRay> = (0..(w * h) as usize)
        .map(|i| {
            let r = cam.pixel_ray((i % w as usize) as u32, (i / w as usize) as u32);
            TimedRay {
                origin: r.origin,
                dir: r.dir,
                time: 0.0,
            }
        })
        .collect();
    rays.par_chunks(64)
        .map_init(Workspace::default, |ws, c| {
            let mut o = RenderOutput::default();
            render_chunk(model, &layout, params, c, ws, &mut o);
            o.rgb
        })
        .collect::<Vec<_>>()
        .into_iter()
        .flatten()
        .collect()
}

fn psnr(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let mse = msth_player::quant_auto::mse(a, b);
    if mse <= 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// Time to the first frame's parameters and to its picture at `rate`.
fn first_picture(file: &std::path::Path, rate: f64, size: (u32, u32)) -> Result<serde_json::Value> {
    let (server, url) = serve(file, RateSchedule::constant(rate))?;
    let t0 = Instant::now();
    let source = HttpSource::open(&url, HttpOptions::default())?;
    let stream = ModelStream::open(Box::new(source), &msth_codec::Limits::default())?;
    let meta = stream.index().metadata.clone();
    let frames = meta.model.num_frames.max(1) as f64;
    stream.set_speed(frames / meta.frame_rate.unwrap_or(30.0) as f64);
    let mut params = Vec::new();
    let (_, layers) = stream.params_progressive(0.0, &mut params, Duration::from_secs(600))?;
    let ready = t0.elapsed().as_secs_f64();
    let bytes = stream.progress().bytes_ready;
    let first = picture(&meta, &params, size.0, size.1);
    let pictured = t0.elapsed().as_secs_f64();
    // Full quality: every layer of the same frame.
    stream.params_for_time(0.0, &mut params, Duration::from_secs(600))?;
    let all = t0.elapsed().as_secs_f64();
    let full = picture(&meta, &params, size.0, size.1);
    drop(stream);
    drop(server);
    Ok(json!({
        "file": file.display().to_string(),
        "rate_bytes_per_s": rate,
        "file_bytes": std::fs::metadata(file)?.len(),
        "layers": layers,
        "layer_count": meta.layer_count(),
        "bytes_before_first_frame": bytes,
        "first_frame_data_s": ready,
        "first_picture_s": pictured,
        "every_layer_s": all,
        "first_picture_psnr_vs_full_db": psnr(&first, &full),
    }))
}

pub fn run(a: BenchStreamArgs) -> Result<()> {
    let size = crate::play::parse_size(&a.size).map_err(anyhow::Error::msg)?;
    let mut firsts = Vec::new();
    println!("| file | link | layers | bytes before the first frame | first frame's data | first picture ({}x{}, CPU) | every layer of it | first picture against full quality |", size.0, size.1);
    println!("|---|---|---|---|---|---|---|---|");
    for r in &a.rate {
        let rate = msth_server::throttle::parse_rate(r).map_err(anyhow::Error::msg)?;
        for f in std::iter::once(&a.file).chain(a.baseline.as_ref()) {
            let v = first_picture(f, rate, size)
                .with_context(|| format!("streaming {} at {r}", f.display()))?;
            println!(
                "| {} | {r} | {}/{} | {} | {:.2} s | {:.2} s | {:.2} s | {:.1} dB |",
                f.file_name().unwrap_or_default().to_string_lossy(),
                v["layers"],
                v["layer_count"],
                v["bytes_before_first_frame"],
                v["first_frame_data_s"].as_f64().unwrap_or(f64::NAN),
                v["first_picture_s"].as_f64().unwrap_or(f64::NAN),
                v["every_layer_s"].as_f64().unwrap_or(f64::NAN),
                v["first_picture_psnr_vs_full_db"]
                    .as_f64()
                    .unwrap_or(f64::INFINITY)
            );
            firsts.push(v);
        }
    }
    let mut playback = serde_json::Value::Null;
    if let Some(text) = &a.schedule {
        let schedule = RateSchedule::parse(text).map_err(anyhow::Error::msg)?;
        playback = play_through(&a.file, schedule.clone(), a.seconds)?;
        let stalls = playback["stalls"].as_array().map_or(0, |s| s.len());
        let longest = playback["stalls"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|s| s[1].as_f64())
            .fold(0.0, f64::max);
        let frames = playback["frames"].as_array().map_or(0, |f| f.len());
        println!(
            "\nplayback on `{text}` for {} s: {frames} frames, {stalls} stalls (longest {longest:.2} s), first frame after {:.2} s",
            a.seconds,
            playback["first_frame_s"].as_f64().unwrap_or(f64::NAN)
        );
        if let Some(out) = &a.out {
            std::fs::create_dir_all(out)?;
            plot_layers(&playback, text, &out.join("layers_over_time.png"))?;
        }
    }
    if let Some(out) = &a.out {
        std::fs::create_dir_all(out)?;
        let path = out.join("stream.json");
        let v = json!({"first_picture": firsts, "playback": playback});
        std::fs::write(&path, serde_json::to_vec_pretty(&v)?)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

/// Real-time playback on a changing link, without drawing.
fn play_through(
    file: &std::path::Path,
    schedule: RateSchedule,
    seconds: f64,
) -> Result<serde_json::Value> {
    let (server, url) = serve(file, schedule.clone())?;
    let t0 = Instant::now();
    let source = HttpSource::open(&url, HttpOptions::default())?;
    let stream = ModelStream::open(Box::new(source), &msth_codec::Limits::default())?;
    let meta = stream.index().metadata.clone();
    let clip = meta.model.num_frames.max(1);
    let fps = meta.frame_rate.unwrap_or(30.0) as f64;
    stream.set_speed(clip as f64 / fps);
    let mut frames = Vec::new();
    let mut stalls: Vec<(f64, f64)> = Vec::new();
    let mut first = None;
    let mut due: Option<f64> = None;
    let mut f = 0usize;
    loop {
        let now = t0.elapsed().as_secs_f64();
        if now > seconds {
            break;
        }
        let t = msth_codec::encode::frame_time(f % clip, clip);
        stream.seek(t);
        if let Some(d) = due {
            if now < d {
                std::thread::sleep(Duration::from_secs_f64((d - now).min(0.05)));
                continue;
            }
        }
        let layers = stream.layers_for(t);
        if layers == 0 {
            // A stall: wait for the chunk's layer 0.
            let began = t0.elapsed().as_secs_f64();
            let mut p = Vec::new();
            stream.params_progressive(t, &mut p, Duration::from_secs_f64(seconds + 60.0))?;
            let at = t0.elapsed().as_secs_f64();
            if first.is_some() {
                stalls.push((began, at - began));
            }
            continue;
        }
        let at = t0.elapsed().as_secs_f64();
        first.get_or_insert(at);
        frames.push(json!({
            "at": at, "time": t, "layers": layers,
            "rate_mbit": stream.rate().map(|r| 8.0 * r / 1e6),
            "link_mbit": 8.0 * schedule.rate_at(at) / 1e6,
        }));
        f += 1;
        due = Some(due.map_or(at, |d| d.max(at - 0.5 / fps)) + 1.0 / fps);
    }
    let complete = stream.progress();
    drop(stream);
    drop(server);
    Ok(json!({
        "file": file.display().to_string(),
        "fps": fps,
        "first_frame_s": first,
        "frames": frames,
        "stalls": stalls,
        "bytes_ready": complete.bytes_ready,
        "file_bytes": complete.file_len,
    }))
}

/// Layers drawn and the link's and the measured rates over time.
fn plot_layers(playback: &serde_json::Value, schedule: &str, path: &std::path::Path) -> Result<()> {
    use plotters::prelude::*;
    if super::tradeoff_plot::ensure_font().is_none() {
        println!("no font for the plot labels: {} skipped", path.display());
        return Ok(());
    }
    let frames = playback["frames"].as_array().cloned().unwrap_or_default();
    if frames.is_empty() {
        bail!("no frames were played");
    }
    let xs = |k: &str| -> Vec<(f64, f64)> {
        frames
            .iter()
            .filter_map(|f| Some((f["at"].as_f64()?, f[k].as_f64()?)))
            .collect()
    };
    let layers = xs("layers");
    let link = xs("link_mbit");
    let measured = xs("rate_mbit");
    let t1 = layers.last().map_or(1.0, |p| p.0).max(1.0);
    let max_layers = layers.iter().map(|p| p.1).fold(1.0, f64::max);
    // The axis follows the link; a measurement above 1.5x its fastest rate (a short request the
    // pacing lets through in one piece) is drawn at the top.
    let max_rate = link.iter().map(|p| p.1).fold(1.0, f64::max) * 1.5;
    let measured: Vec<(f64, f64)> = measured
        .into_iter()
        .map(|(t, r)| (t, r.min(max_rate)))
        .collect();
    let (w, h) = (900u32, 420u32);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("Layers drawn on a changing link ({schedule})"),
                ("sans-serif", 20),
            )
            .margin(14)
            .x_label_area_size(40)
            .y_label_area_size(56)
            .right_y_label_area_size(56)
            .build_cartesian_2d(0.0..t1, 0.0..max_layers + 0.5)
            .map_err(|e| anyhow::anyhow!("{e:?}"))?
            .set_secondary_coord(0.0..t1, 0.0..max_rate);
        chart
            .configure_mesh()
            .x_desc("seconds")
            .y_desc("layers drawn")
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        chart
            .configure_secondary_axes()
            .y_desc("Mbit/s")
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        let red = RGBColor(200, 30, 30);
        let blue = RGBColor(40, 90, 180);
        let grey = RGBColor(120, 120, 120);
        chart
            .draw_series(LineSeries::new(layers, red.stroke_width(2)))
            .map_err(|e| anyhow::anyhow!("{e:?}"))?
            .label("layers drawn")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], red.stroke_width(2)));
        chart
            .draw_secondary_series(LineSeries::new(link, grey.stroke_width(2)))
            .map_err(|e| anyhow::anyhow!("{e:?}"))?
            .label("link (Mbit/s)")
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], grey.stroke_width(2))
            });
        chart
            .draw_secondary_series(LineSeries::new(measured, blue.stroke_width(1)))
            .map_err(|e| anyhow::anyhow!("{e:?}"))?
            .label("measured (Mbit/s)")
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], blue.stroke_width(1))
            });
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(|e| anyhow::anyhow!("{e:?}"))?;
        root.present().map_err(|e| anyhow::anyhow!("{e:?}"))?;
    }
    super::tradeoff_plot::save_rgb(path, w, h, buf)
}
