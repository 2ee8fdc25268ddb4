//! `msth bench layers CKPT... --data DATA --out DIR`: quality against bytes of progressive
//! layers. Each checkpoint is exported as `msth export --layers N` does (its file is kept in
//! `DIR`), and every prefix of its layers (layers `0..k`) is measured: the bytes a player fetches
//! before the first frame and in all, and the held-out PSNR of the frames drawn from it. Writes
//! `layers.md`, `layers.json` and `psnr_vs_bytes.png` (one curve per checkpoint).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use msth_core::field::ModelLayout;
use msth_trainer::checkpoint::Checkpoint;
use serde_json::json;

use crate::data;
use crate::export::{held_out_psnr, write_msth, Choices};

#[derive(Args)]
pub struct BenchLayersArgs {
    /// Checkpoints (`model.ckpt`): each is one curve, named by its folder.
    #[arg(required = true)]
    pub checkpoints: Vec<PathBuf>,
    /// The dataset the held-out views come from (a folder, or `builtin`).
    #[arg(long)]
    pub data: String,
    /// Progressive layers of the files.
    #[arg(long, default_value_t = 4)]
    pub layers: usize,
    /// Every this many held-out views.
    #[arg(long, default_value_t = 2)]
    pub stride: usize,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: BenchLayersArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out)?;
    let mut rows = Vec::new();
    let mut curves: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    let mut md = String::from(
        "| model | layers | levels (field 3D/4D, proposal 3D/4D) | bytes before the first frame | bytes in all | held-out PSNR | against every layer |\n|---|---|---|---|---|---|---|\n",
    );
    for ckpt_path in &a.checkpoints {
        let name = ckpt_path
            .parent()
            .and_then(|p| p.file_name())
            .map_or("model".into(), |n| n.to_string_lossy().to_string());
        let mut ckpt = Checkpoint::load(ckpt_path)?;
        let dir = ckpt_path.parent().unwrap_or(std::path::Path::new("."));
        let mut data = data::load(&a.data, &data::DataArgs::with_downscale(1), dir)?;
        data.rescale(ckpt.header.scene_scale());
        let file = a.out.join(format!("{name}.msth"));
        let opts = msth_codec::EncodeOptions {
            layers: a.layers,
            ..Default::default()
        };
        let (report, _) = write_msth(
            &mut ckpt,
            ckpt_path,
            &file,
            &opts,
            false,
            Some(msth_player::seen::DEFAULT_SEEN_WEIGHT),
            &Choices::auto(),
        )
        .with_context(|| format!("exporting {}", ckpt_path.display()))?;
        let bytes = std::fs::read(&file)?;
        let mut d = msth_codec::Decoder::new(&bytes)?;
        d.feed(&bytes)?;
        let model = &d.metadata().model.clone();
        let layout = ModelLayout::new(model);
        let n = report.layers.len();
        let psnrs: Vec<f64> = (1..=n)
            .map(|k| {
                held_out_psnr(&data, model, &layout, a.stride, &|t| {
                    let mut out = Vec::new();
                    // Every section is decoded: this cannot fail.
                    let _ = d.params_for_layers_into(t, k, &mut out);
                    out
                })
            })
            .collect();
        let mut curve = Vec::new();
        for k in 1..=n {
            let l = &report.layers[k - 1];
            let all = report.bytes_through(k);
            let first = report.first_frame_bytes(k);
            let line = format!(
                "| {name} | 0..{k} | {}/{}/{}/{} | {first} | {all} | {:.2} dB | {:+.2} dB |\n",
                l.levels.h3,
                l.levels.h4,
                l.levels.p3,
                l.levels.p4,
                psnrs[k - 1],
                psnrs[k - 1] - psnrs[n - 1]
            );
            print!("{line}");
            md.push_str(&line);
            rows.push(json!({
                "model": name, "layers": k, "h3_levels": l.levels.h3, "h4_levels": l.levels.h4,
                "proposal_h3_levels": l.levels.p3, "proposal_h4_levels": l.levels.p4,
                "first_frame_bytes": first, "bytes": all, "psnr": psnrs[k - 1],
            }));
            curve.push((all as f64 / (1 << 20) as f64, psnrs[k - 1]));
        }
        curves.push((name, curve));
    }
    std::fs::write(a.out.join("layers.md"), &md)?;
    std::fs::write(
        a.out.join("layers.json"),
        serde_json::to_vec_pretty(&json!({"data": a.data, "stride": a.stride, "rows": rows}))?,
    )?;
    plot(&curves, &a.data, &a.out.join("psnr_vs_bytes.png"))?;
    println!("wrote {}", a.out.join("layers.md").display());
    Ok(())
}

/// Held-out PSNR against MiB, one curve per model, each point a prefix of the layers.
fn plot(curves: &[(String, Vec<(f64, f64)>)], data: &str, path: &std::path::Path) -> Result<()> {
    use plotters::prelude::*;
    if super::tradeoff_plot::ensure_font().is_none() {
        println!("no font for the plot labels: {} skipped", path.display());
        return Ok(());
    }
    let pts = curves.iter().flat_map(|(_, c)| c.iter().copied());
    let (mut x1, mut y0, mut y1) = (0.0f64, f64::INFINITY, f64::NEG_INFINITY);
    for (x, y) in pts.filter(|p| p.1.is_finite()) {
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    let pad = ((y1 - y0) * 0.08).max(0.5);
    let (w, h) = (900u32, 480u32);
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let e = |e: &dyn std::fmt::Debug| anyhow::anyhow!("drawing {}: {e:?}", path.display());
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(&x))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("Held-out PSNR against bytes, by layers ({data})"),
                ("sans-serif", 20),
            )
            .margin(14)
            .x_label_area_size(40)
            .y_label_area_size(56)
            .build_cartesian_2d(0.0..x1 * 1.05, (y0 - pad)..(y1 + pad))
            .map_err(|x| e(&x))?;
        chart
            .configure_mesh()
            .x_desc("MiB fetched (every chunk, the layers 0..k)")
            .y_desc("held-out PSNR (dB)")
            .label_style(("sans-serif", 13))
            .draw()
            .map_err(|x| e(&x))?;
        let colours = [
            RGBColor(200, 30, 30),
            RGBColor(40, 90, 180),
            RGBColor(30, 140, 60),
            RGBColor(150, 80, 160),
        ];
        for (k, (name, c)) in curves.iter().enumerate() {
            let col = colours[k % colours.len()];
            chart
                .draw_series(LineSeries::new(c.clone(), col.stroke_width(2)))
                .map_err(|x| e(&x))?
                .label(name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], col.stroke_width(2))
                });
            chart
                .draw_series(c.iter().map(|&p| Circle::new(p, 4, col.filled())))
                .map_err(|x| e(&x))?;
            // Each point is labelled with its layer count, beside it.
            chart
                .draw_series(c.iter().enumerate().map(|(i, &p)| {
                    EmptyElement::at(p)
                        + Text::new(
                            format!("{}", i + 1),
                            (6, -16),
                            ("sans-serif", 12).into_font(),
                        )
                }))
                .map_err(|x| e(&x))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 13))
            .draw()
            .map_err(|x| e(&x))?;
        root.present().map_err(|x| e(&x))?;
    }
    super::tradeoff_plot::save_rgb(path, w, h, buf)
}
