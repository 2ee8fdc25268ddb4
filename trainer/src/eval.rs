//! Rendering whole images from a model and evaluating held-out views: PSNR, SSIM, D-SSIM per
//! frame and averaged, written to `metrics.json`, plus "ground truth | render | error" pictures.

use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::pipeline::{render_chunk, RenderOutput, TimedRay, Workspace};
use msth_core::Camera;

use crate::checkpoint::write_atomic;
use crate::metrics::{dssim, psnr, ssim};
use msth_dataset::imageio::{error_map, panel, save_png_atomic};
use msth_dataset::{Dataset, Image8};

/// Everything a full-image render produces, row-major.
#[derive(Clone, Debug, Default)]
pub struct ImageRender {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub mask: Vec<f32>,
    pub min_mask: Vec<f32>,
}

/// Renders `camera` at `time`, rows in parallel.
pub fn render_image(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    camera: &Camera,
    time: f32,
) -> ImageRender {
    let (w, h) = (camera.width as usize, camera.height as usize);
    const ROWS: usize = 4;
    let blocks: Vec<RenderOutput> = (0..h.div_ceil(ROWS))
        .into_par_iter()
        .map_init(Workspace::default, |ws, b| {
            let y0 = b * ROWS;
            let y1 = (y0 + ROWS).min(h);
            let mut rays = Vec::with_capacity((y1 - y0) * w);
            for y in y0..y1 {
                for x in 0..w {
                    let r = camera.pixel_ray(x as u32, y as u32);
                    rays.push(TimedRay {
                        origin: r.origin,
                        dir: r.dir,
                        time,
                    });
                }
            }
            let mut out = RenderOutput::default();
            for c in rays.chunks(256) {
                render_chunk(cfg, layout, params, c, ws, &mut out);
            }
            out
        })
        .collect();
    let mut img = ImageRender {
        width: w as u32,
        height: h as u32,
        ..Default::default()
    };
    for b in blocks {
        img.rgb.extend(b.rgb.iter().flatten());
        img.depth.extend(b.depth);
        img.mask.extend(b.mask);
        img.min_mask.extend(b.min_mask);
    }
    img
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FrameMetrics {
    pub view: usize,
    pub time: f32,
    pub psnr: f64,
    pub ssim: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Metrics {
    pub dataset: String,
    pub psnr: f64,
    pub ssim: f64,
    /// `(1 - SSIM) / 2`.
    pub dssim: f64,
    pub dssim_convention: String,
    pub frames: Vec<FrameMetrics>,
    pub train_seconds: f64,
    pub train_steps: u64,
    pub field_samples_per_sec: f64,
    pub rays_per_sec: f64,
    pub render_seconds: f64,
    pub pictures: Vec<PathBuf>,
    /// Proposal and main samples per ray the views were rendered with (`msth eval --samples`
    /// may set fewer than the model's own).
    #[serde(default)]
    pub samples_per_ray: [usize; 2],
}

/// Evaluates every `stride`-th test view, writing pictures of three of them into `pictures_dir`.
pub fn evaluate(
    data: &Dataset,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    stride: usize,
    pictures_dir: Option<&Path>,
) -> std::io::Result<Metrics> {
    let start = std::time::Instant::now();
    let chosen: Vec<usize> = (0..data.test.len()).step_by(stride.max(1)).collect();
    let picture_at = [0, chosen.len() / 2, chosen.len().saturating_sub(1)];
    let mut frames = Vec::new();
    let mut pictures = Vec::new();
    if let Some(d) = pictures_dir {
        std::fs::create_dir_all(d)?;
    }
    for (k, &i) in chosen.iter().enumerate() {
        let v = &data.test[i];
        let r = render_image(cfg, layout, params, &v.camera, v.time);
        // One frame in memory at a time, whatever the size of the test set.
        let gt_image = v.image.loaded();
        let gt = gt_image.to_f32();
        let p = psnr(&r.rgb, &gt);
        let s = ssim(&r.rgb, &gt, r.width as usize, r.height as usize);
        frames.push(FrameMetrics {
            view: i,
            time: v.time,
            psnr: p,
            ssim: s,
        });
        if let Some(d) = pictures_dir {
            if picture_at.contains(&k)
                && !pictures
                    .iter()
                    .any(|p: &PathBuf| p.ends_with(format!("view_{i:03}.png")))
            {
                let pred = Image8::from_f32(r.width, r.height, &r.rgb);
                let err = error_map(&gt_image, &pred);
                let path = d.join(format!("view_{i:03}.png"));
                save_png_atomic(&path, &panel(&[&gt_image, &pred, &err]))?;
                pictures.push(path);
            }
        }
    }
    let n = frames.len().max(1) as f64;
    let mean_psnr = frames.iter().map(|f| f.psnr).sum::<f64>() / n;
    let mean_ssim = frames.iter().map(|f| f.ssim).sum::<f64>() / n;
    Ok(Metrics {
        dataset: data.name.clone(),
        psnr: mean_psnr,
        ssim: mean_ssim,
        dssim: dssim(mean_ssim),
        dssim_convention: "(1 - SSIM) / 2".into(),
        frames,
        train_seconds: 0.0,
        train_steps: 0,
        field_samples_per_sec: 0.0,
        rays_per_sec: 0.0,
        render_seconds: start.elapsed().as_secs_f64(),
        pictures,
        samples_per_ray: [cfg.sampler.num_proposal_samples, cfg.sampler.num_samples],
    })
}

impl Metrics {
    pub fn save(&self, path: &Path) -> std::io::Result<()> {
        let json = serde_json::to_vec_pretty(self).map_err(std::io::Error::other)?;
        write_atomic(path, &json)
    }
}
