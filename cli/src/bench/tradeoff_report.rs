//! The outputs of `msth bench tradeoff`: `tradeoff.md`, `tradeoff.csv`, `tradeoff.json` and
//! the three plots with the Pareto fronts, each written atomically.

use std::path::Path;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use serde_json::json;

use msth_dataset::imageio::save_png_atomic;
use msth_trainer::checkpoint::write_atomic;

use super::tradeoff::Row;
use super::tradeoff_plot::{self, PlotPoint};

/// The sweep's context, written with the tables.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Meta {
    pub dataset: String,
    pub data: String,
    pub base: String,
    pub iters: usize,
    pub stride: usize,
    pub test_views: usize,
    pub fps_size: (u32, u32),
    pub fps_frames: usize,
    pub threads: usize,
    pub quant: String,
    /// `--converge`: (steps between measurements, least gain in dB).
    #[serde(default)]
    pub converge: Option<(usize, f64)>,
    /// `--cap`: variants with their own step budget (name, steps).
    #[serde(default)]
    pub caps: Vec<(String, usize)>,
}

impl Meta {
    /// How long each variant trained, for titles and text.
    fn schedule(&self) -> String {
        let base = match self.converge {
            Some((every, gain)) => format!(
                "until converged: less than {gain} dB gained in {every} steps, at most {} steps",
                self.iters
            ),
            None => format!("{} steps", self.iters),
        };
        let caps: Vec<String> = self
            .caps
            .iter()
            .map(|(name, n)| format!("{name} {n}"))
            .collect();
        if caps.is_empty() {
            base
        } else {
            format!("{base}; own budgets: {}", caps.join(", "))
        }
    }
}

fn mib(b: u64) -> String {
    format!("{:.2}", b as f64 / (1 << 20) as f64)
}

fn mark(b: bool) -> &'static str {
    if b {
        "**x**"
    } else {
        ""
    }
}

/// The rows as a markdown table (fronts marked **x**).
pub fn markdown_table(rows: &[Row]) -> String {
    let mut s = String::from(
        "| variant | factor | value | steps | batch | params | train s | PSNR f32 | PSNR file | SSIM f32 | quant | file MiB | FPS | FPS fixed | front time | front size | front FPS |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {:.1} | {:.2} | {:.2} | {:.4} | {} | {} | {:.2} | {:.1} | {} | {} | {} |\n",
            r.label,
            r.factor,
            r.value,
            r.steps,
            r.batch_rays,
            r.params,
            r.train_seconds,
            r.psnr_f32,
            r.psnr,
            r.ssim_f32,
            r.quant,
            mib(r.file_bytes),
            r.fps,
            r.fps_fixed,
            mark(r.front_time),
            mark(r.front_size),
            mark(r.front_fps)
        ));
    }
    s
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// The rows as CSV, one header line.
pub fn csv_table(rows: &[Row]) -> String {
    let mut s = String::from("name,label,factor,value,preset,quant,steps,batch_rays,params,train_seconds,psnr_f32,ssim_f32,psnr,file_bytes,fps,fps_fixed,front_time,front_size,front_fps\n");
    for r in rows {
        let f = [
            csv_field(&r.name),
            csv_field(&r.label),
            csv_field(&r.factor),
            csv_field(&r.value),
            csv_field(&r.preset),
            csv_field(&r.quant),
            r.steps.to_string(),
            r.batch_rays.to_string(),
            r.params.to_string(),
            format!("{:.3}", r.train_seconds),
            format!("{:.4}", r.psnr_f32),
            format!("{:.5}", r.ssim_f32),
            format!("{:.4}", r.psnr),
            r.file_bytes.to_string(),
            format!("{:.4}", r.fps),
            format!("{:.4}", r.fps_fixed),
            r.front_time.to_string(),
            r.front_size.to_string(),
            r.front_fps.to_string(),
        ];
        s.push_str(&f.join(","));
        s.push('\n');
    }
    s
}

/// Writes the tables and the plots into `out` (each file atomically).
pub fn write_outputs(out: &Path, meta: &Meta, rows: &[Row]) -> Result<()> {
    let w = |name: &str, bytes: &[u8]| -> Result<()> {
        let p = out.join(name);
        write_atomic(&p, bytes).with_context(|| format!("writing {}", p.display()))
    };
    w(
        "tradeoff.json",
        &serde_json::to_vec_pretty(&json!({"meta": meta, "rows": rows}))?,
    )?;
    w("tradeoff.csv", csv_table(rows).as_bytes())?;
    // (file, title, x axis, y axis, log x, quant rows too, the point)
    type Pick = fn(&Row) -> (f64, f64, bool);
    let plots: [(&str, &str, &str, &str, bool, bool, Pick); 3] = [
        (
            "psnr_vs_time.png",
            "Held-out PSNR against training time",
            "training time (s, log)",
            "PSNR of the file (dB)",
            true,
            false,
            |r| (r.train_seconds, r.psnr, r.front_time),
        ),
        (
            "psnr_vs_size.png",
            "Held-out PSNR against file size",
            "file size (MiB, log)",
            "PSNR of the file (dB)",
            true,
            true,
            |r| (r.file_bytes as f64 / (1 << 20) as f64, r.psnr, r.front_size),
        ),
        (
            "fps_vs_psnr.png",
            "Rendering rate against held-out PSNR",
            "PSNR of the file (dB)",
            "full frames per second",
            false,
            false,
            |r| (r.psnr, r.fps, r.front_fps),
        ),
    ];
    let font = tradeoff_plot::ensure_font();
    let mut plot_note = String::new();
    for (file, title, xl, yl, logx, with_quant, f) in plots {
        if font.is_none() {
            break;
        }
        let points: Vec<PlotPoint> = rows
            .iter()
            .filter(|r| with_quant || r.factor != "quant")
            .map(|r| {
                let (x, y, front) = f(r);
                PlotPoint {
                    x,
                    y,
                    label: r.label.clone(),
                    front,
                }
            })
            .collect();
        let title = match meta.converge {
            Some(_) => format!("{title} ({}, until converged)", meta.dataset),
            None => format!("{title} ({}, {} steps)", meta.dataset, meta.iters),
        };
        let img = tradeoff_plot::scatter(&title, xl, yl, logx, &points)?;
        let p = out.join(file);
        save_png_atomic(&p, &img).with_context(|| format!("writing {}", p.display()))?;
    }
    match &font {
        Some(p) => plot_note.push_str(&format!(
            "![PSNR against training time](psnr_vs_time.png)\n\n![PSNR against file size](psnr_vs_size.png)\n\n![FPS against PSNR](fps_vs_psnr.png)\n\n(labels drawn with {})\n",
            p.display()
        )),
        None => {
            eprintln!("no TrueType font found (set MSTH_FONT=FILE.ttf): plots skipped");
            plot_note.push_str("Plots skipped: no TrueType font found (set `MSTH_FONT=FILE.ttf`).\n");
        }
    }
    let md = format!(
        "# Trade-off: {} (base preset {}, {} per variant)\n\n\
         `msth bench tradeoff {}`: each variant trains {} ({} threads), is evaluated on every \
         {}th of the {} held-out views (PSNR f32: the trained parameters; PSNR file: the decoded \
         `.msth` file, {} unless the row says otherwise), and its file is played from the first \
         camera at {}x{} ({} full frames, no incremental rendering) for the FPS. Training times \
         and FPS are wall-clock on a shared machine and noisy; PSNR and sizes are not. **x** marks \
         the Pareto fronts: PSNR against training time, PSNR against file size, FPS against PSNR.\n\n{}\n{}",
        meta.dataset,
        meta.base,
        meta.schedule(),
        meta.data,
        meta.schedule(),
        meta.threads,
        meta.stride,
        meta.test_views,
        meta.quant,
        meta.fps_size.0,
        meta.fps_size.1,
        meta.fps_frames,
        markdown_table(rows),
        plot_note
    );
    w("tradeoff.md", md.as_bytes())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_quotes_fields_with_commas() {
        assert_eq!(csv_field("a,b"), "\"a,b\"");
        assert_eq!(csv_field("plain"), "plain");
        assert_eq!(csv_field("say \"x\""), "\"say \"\"x\"\"\"");
        assert_eq!(csv_field("q\"1,2"), "\"q\"\"1,2\"");
    }
}
