//! `msth export --quant auto`: each part's quantisation mode, and the play-time samples per ray,
//! chosen from renders of the file's own cameras (no dataset). The searches render, so they live
//! here with the renderers; the codec (`msth_codec`) encodes and decodes the candidates.
//!
//! **The loss.** Renders of a few of the cameras (at a small resolution, each at another frame)
//! with the lossless (`f32`) file are the reference; a candidate is rendered the same way and its
//! mean squared difference `e` from the reference is turned into the drop of the model's PSNR
//! against ground truth it would cause if its error were independent of the model's own:
//! `10 log10(1 + e / m)`, with `m = 10^(-P/10)` the model's own squared error at its held-out
//! PSNR `P` ([`AutoOptions::reference_psnr`]). A better model (higher `P`) has less error to
//! hide quantisation noise in, so its budget in squared error is smaller.
//!
//! **The quantisation search** ([`choose_quant`]). Each part of [`SectionQuant`] has a ladder of
//! modes from the coarsest to `f32` (the modes that store that part differently). Every part
//! starts at its coarsest mode, its loss measured with every other part lossless; while the sum
//! of the parts' squared errors is over the budget, the part whose next finer mode with less
//! error removes the most squared error per estimated byte added moves up to that mode (one
//! render per mode measured). The whole
//! file is then encoded and measured; while that measurement is over the budget (the parts'
//! errors need not add up exactly), the part with the largest error moves up one step. `f32`
//! everywhere is lossless, so the search ends within the budget.
//!
//! **The samples search** ([`choose_samples`]). With the chosen file, the reference is its render
//! at the model's own samples per ray; main samples are lowered first, through 3/4, 2/3, 1/2, 1/3
//! and 1/4 of the model's count while the loss stays within half the budget, then proposal
//! samples through the same fractions while the loss with both lowered stays within the budget.

use std::time::Instant;

use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::pipeline::{render_chunk, RenderOutput, TimedRay, Workspace};
use msth_core::Camera;
use rayon::prelude::*;

use msth_codec::encode::{encode, frame_time, EncodeOptions};
use msth_codec::error::EncodeError;
use msth_codec::format::{PlaySampleCounts, QuantMode, QuantPart, SectionQuant};
use msth_codec::quant::BlockEncoding;
use msth_codec::sections::Encodings;
use msth_codec::{decode_all, DecodedModel};

/// The held-out PSNR assumed when the model's own is unknown: the top of what converged models
/// reach (docs/tradeoff.md), so the budget in squared error errs on the small side.
pub const DEFAULT_REFERENCE_PSNR: f64 = 35.0;
/// The default loss budget of both searches, dB.
pub const DEFAULT_MAX_LOSS_DB: f64 = 0.1;

/// How the searches measure.
#[derive(Clone, Debug, PartialEq)]
pub struct AutoOptions {
    /// The largest loss (dB of PSNR) a choice may cost.
    pub max_loss_db: f64,
    /// The model's held-out PSNR (dB), which turns squared error into loss (module docs).
    pub reference_psnr: f64,
    /// Cameras rendered (spread over the file's cameras).
    pub views: usize,
    /// Longest side of each render, pixels.
    pub side: u32,
}

impl Default for AutoOptions {
    fn default() -> Self {
        AutoOptions {
            max_loss_db: DEFAULT_MAX_LOSS_DB,
            reference_psnr: DEFAULT_REFERENCE_PSNR,
            views: 6,
            side: 48,
        }
    }
}

impl AutoOptions {
    fn check(&self) -> Result<(), EncodeError> {
        if !(self.max_loss_db.is_finite() && self.max_loss_db > 0.0) {
            return Err(EncodeError::InvalidOption(format!(
                "the loss budget must be a positive number of dB (got {})",
                self.max_loss_db
            )));
        }
        if !(self.reference_psnr.is_finite() && self.reference_psnr > 0.0) {
            return Err(EncodeError::InvalidOption(format!(
                "the reference PSNR must be a positive number of dB (got {})",
                self.reference_psnr
            )));
        }
        if self.views == 0 || self.side == 0 {
            return Err(EncodeError::InvalidOption(
                "the searches need at least one view of at least one pixel".into(),
            ));
        }
        Ok(())
    }

    /// The squared error that costs `max_loss_db`.
    pub fn budget_mse(&self, max_loss_db: f64) -> f64 {
        self.model_mse() * (10f64.powf(max_loss_db / 10.0) - 1.0)
    }

    fn model_mse(&self) -> f64 {
        10f64.powf(-self.reference_psnr / 10.0)
    }

    /// The loss (dB) of a squared error `mse` against the reference renders.
    pub fn loss_db(&self, mse: f64) -> f64 {
        10.0 * (1.0 + mse / self.model_mse()).log10()
    }
}

/// The renders both searches compare: a few cameras at a small resolution, each at a time.
#[derive(Clone, Debug)]
pub struct Probe {
    pub views: Vec<(Camera, f32)>,
}

impl Probe {
    /// `opts.views` cameras spread evenly over `cameras` (all of them when there are fewer),
    /// resized to `opts.side` pixels on their longest side, at times spread evenly over the
    /// model's frames.
    pub fn new(model: &ModelConfig, cameras: &[Camera], opts: &AutoOptions) -> Self {
        let n = opts.views.min(cameras.len());
        let frames = model.num_frames.max(1);
        let views = (0..n)
            .map(|i| {
                let c = &cameras[i * cameras.len() / n];
                let long = c.width.max(c.height).max(1) as f32;
                let s = (opts.side as f32 / long).min(1.0);
                let w = ((c.width as f32 * s).round() as u32).max(1);
                let h = ((c.height as f32 * s).round() as u32).max(1);
                let f = if n > 1 { i * (frames - 1) / (n - 1) } else { 0 };
                (c.resized(w, h), frame_time(f, frames))
            })
            .collect();
        Probe { views }
    }

    /// Pixels over all views.
    pub fn pixels(&self) -> usize {
        self.views
            .iter()
            .map(|(c, _)| c.width as usize * c.height as usize)
            .sum()
    }

    /// The RGB of every view, one after another, with `params_at(t)` the parameters for time
    /// `t` (the plain renderer: no empty-space skipping).
    pub fn render(
        &self,
        model: &ModelConfig,
        layout: &ModelLayout,
        params_at: &dyn Fn(f32) -> Vec<f32>,
    ) -> Vec<[f32; 3]> {
        let mut out = Vec::with_capacity(self.pixels());
        for (camera, time) in &self.views {
            let params = params_at(*time);
            let w = camera.width as usize;
            let rays: Vec<TimedRay> = (0..camera.height as usize * w)
                .map(|i| {
                    let r = camera.pixel_ray((i % w) as u32, (i / w) as u32);
                    TimedRay {
                        origin: r.origin,
                        dir: r.dir,
                        time: *time,
                    }
                })
                .collect();
            let blocks: Vec<Vec<[f32; 3]>> = rays
                .par_chunks(64)
                .map_init(Workspace::default, |ws, c| {
                    let mut o = RenderOutput::default();
                    render_chunk(model, layout, &params, c, ws, &mut o);
                    o.rgb
                })
                .collect();
            out.extend(blocks.into_iter().flatten());
        }
        out
    }
}

/// Mean squared difference of two renders of one probe.
pub fn mse(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| {
            (0..3)
                .map(|k| {
                    let d = (x[k] - y[k]) as f64;
                    d * d
                })
                .sum::<f64>()
        })
        .sum();
    sum / (3 * a.len().max(1)) as f64
}

/// One measurement of the quantisation search.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantStep {
    /// The part changed (`None`: the whole file).
    pub part: Option<QuantPart>,
    pub modes: SectionQuant,
    pub loss_db: f64,
}

/// What [`choose_quant`] chose and measured.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantChoice {
    pub modes: SectionQuant,
    /// The whole file's loss, measured on the probe.
    pub loss_db: f64,
    /// Every measurement, in order.
    pub steps: Vec<QuantStep>,
    pub seconds: f64,
}

/// The modes that store `part` differently, coarsest first.
pub fn ladder(part: QuantPart) -> &'static [QuantMode] {
    use QuantMode::*;
    match part {
        // q8 to k3 all store the MLPs as f16.
        QuantPart::Mlp => &[F16, F32],
        // Modes of 5 bits and fewer store masks with 6 bits, q6 and q8 with 8.
        QuantPart::Mask => &[Q5, Q8, F16, F32],
        _ => &[K3, Q4, Q5, Q6, Q8, F16, F32],
    }
}

fn bits(e: BlockEncoding) -> f64 {
    match e {
        BlockEncoding::F32 => 32.0,
        BlockEncoding::F16 => 16.0,
        BlockEncoding::Affine { bits } | BlockEncoding::Codebook { bits } => bits as f64,
    }
}

/// Bits per value of `part` in `mode` (its hashed levels' encoding), for the search's size
/// estimate.
fn part_bits(part: QuantPart, mode: QuantMode) -> f64 {
    let e = Encodings::for_mode(mode);
    bits(match part {
        QuantPart::Mlp => e.mlp,
        QuantPart::Mask => e.mask,
        _ => e.tables,
    })
}

/// Values of each part a file stores (the search's size estimate; 0: the model has no such
/// part).
fn part_values(layout: &ModelLayout, part: QuantPart) -> u64 {
    let f = &layout.field;
    let len = |r: &std::ops::Range<usize>| r.len() as u64;
    match part {
        QuantPart::Mlp => {
            len(&f.density.1) + len(&f.color.1) + len(&layout.proposal.field.density.1)
        }
        QuantPart::Proposal => {
            let e = &layout.proposal.field.encoding;
            e.h3.as_ref().map_or(0, |g| len(&g.1))
                + e.h4.as_ref().map_or(0, |g| len(&g.1))
                + e.mask.as_ref().map_or(0, |g| len(&g.1))
        }
        QuantPart::StaticTable => f.encoding.h3.as_ref().map_or(0, |g| len(&g.1)),
        QuantPart::Mask => f.encoding.mask.as_ref().map_or(0, |g| len(&g.1)),
        QuantPart::Dynamic => f.encoding.h4.as_ref().map_or(0, |g| len(&g.1)),
    }
}

/// Encodes with `modes` (zstd's fastest level: only the values matter here) and decodes.
fn round_trip(
    model: &ModelConfig,
    params: &[f32],
    cameras: &[Camera],
    base: &EncodeOptions,
    modes: SectionQuant,
) -> Result<DecodedModel, EncodeError> {
    let opts = EncodeOptions {
        sections: Some(modes),
        zstd_level: -7,
        ..base.clone()
    };
    let (bytes, _) = encode(model, params, cameras, &opts)?;
    decode_all(&bytes).map_err(|e| {
        EncodeError::InvalidOption(format!("the encoder wrote a file it cannot read: {e}"))
    })
}

/// The parts' modes of the smallest file (by the search in the module docs) whose loss against
/// the lossless file stays within `auto.max_loss_db`, measured on `probe`. `base` gives
/// everything but the modes (its `occupancy` should be set: the search encodes many times).
pub fn choose_quant(
    model: &ModelConfig,
    params: &[f32],
    cameras: &[Camera],
    base: &EncodeOptions,
    probe: &Probe,
    auto: &AutoOptions,
) -> Result<QuantChoice, EncodeError> {
    auto.check()?;
    if probe.views.is_empty() {
        return Err(EncodeError::InvalidOption(
            "the file has no cameras to measure the loss on (use --quant MODE)".into(),
        ));
    }
    let start = Instant::now();
    let layout = ModelLayout::new(model);
    let mut base = base.clone();
    if base.occupancy.is_none() {
        base.occupancy = Some(std::sync::Arc::new(msth_codec::encode::occupancy_grid(
            model, &layout, params, &base,
        )));
    }
    let render = |modes: SectionQuant| -> Result<Vec<[f32; 3]>, EncodeError> {
        let d = round_trip(model, params, cameras, &base, modes)?;
        Ok(probe.render(model, &layout, &|t| d.params_for_time(t)))
    };
    let lossless = SectionQuant::uniform(QuantMode::F32);
    let reference = render(lossless)?;
    let budget = auto.budget_mse(auto.max_loss_db);
    let mut steps = Vec::new();

    // Per part: the ladder position and the squared error measured at each position.
    let parts: Vec<QuantPart> = QuantPart::ALL
        .into_iter()
        .filter(|&p| part_values(&layout, p) > 0)
        .collect();
    let mut modes = lossless;
    for p in QuantPart::ALL {
        if !parts.contains(&p) {
            // Absent: the coarsest mode, so that it does not raise the file's `quant`.
            modes.set(p, ladder(p)[0]);
        }
    }
    let mut pos = vec![0usize; parts.len()];
    let mut err: Vec<Vec<Option<f64>>> =
        parts.iter().map(|&p| vec![None; ladder(p).len()]).collect();
    let measure = |err: &mut Vec<Vec<Option<f64>>>,
                   i: usize,
                   at: usize,
                   steps: &mut Vec<QuantStep>|
     -> Result<f64, EncodeError> {
        if let Some(e) = err[i][at] {
            return Ok(e);
        }
        let p = parts[i];
        let mode = ladder(p)[at];
        let e = if mode == QuantMode::F32 {
            0.0
        } else {
            let mut m = lossless;
            m.set(p, mode);
            let e = mse(&render(m)?, &reference);
            steps.push(QuantStep {
                part: Some(p),
                modes: m,
                loss_db: auto.loss_db(e),
            });
            e
        };
        err[i][at] = Some(e);
        Ok(e)
    };
    let mut current = Vec::with_capacity(parts.len());
    for i in 0..parts.len() {
        current.push(measure(&mut err, i, 0, &mut steps)?);
    }
    while current.iter().sum::<f64>() > budget {
        // Per part, its next finer mode with less error (a coarser mode can beat a finer one:
        // 3-bit codebooks often beat 4-bit affine codes), and the error it removes per byte.
        let mut best: Option<(usize, usize, f64)> = None;
        for i in 0..parts.len() {
            let l = ladder(parts[i]);
            if current[i] <= 0.0 {
                continue;
            }
            let mut to = None;
            for j in pos[i] + 1..l.len() {
                if measure(&mut err, i, j, &mut steps)? < current[i] {
                    to = Some(j);
                    break;
                }
            }
            let Some(j) = to else { continue };
            let next = err[i][j].unwrap_or(0.0);
            let values = part_values(&layout, parts[i]) as f64;
            let added = values * (part_bits(parts[i], l[j]) - part_bits(parts[i], l[pos[i]])) / 8.0;
            let gain = (current[i] - next) / added.max(1.0);
            if best.is_none_or(|(_, _, g)| gain > g) {
                best = Some((i, j, gain));
            }
        }
        let Some((i, j, _)) = best else { break };
        pos[i] = j;
        current[i] = err[i][j].unwrap_or(0.0);
    }
    // The whole file, measured; finer while over the budget.
    loop {
        for (i, &p) in parts.iter().enumerate() {
            modes.set(p, ladder(p)[pos[i]]);
        }
        let e = if modes.single() == Some(QuantMode::F32) {
            0.0
        } else {
            mse(&render(modes)?, &reference)
        };
        steps.push(QuantStep {
            part: None,
            modes,
            loss_db: auto.loss_db(e),
        });
        if e <= budget {
            return Ok(QuantChoice {
                modes,
                loss_db: auto.loss_db(e),
                steps,
                seconds: start.elapsed().as_secs_f64(),
            });
        }
        // The part with the largest error that can still move up.
        let movable = (0..parts.len())
            .filter(|&i| pos[i] + 1 < ladder(parts[i]).len())
            .max_by(|&a, &b| current[a].total_cmp(&current[b]));
        let Some(i) = movable else {
            // Every part is f32: the file is lossless (unreachable with e > 0).
            return Err(EncodeError::InvalidOption(format!(
                "no encoding stays within {} dB (the lossless one measured {:.4} dB)",
                auto.max_loss_db,
                auto.loss_db(e)
            )));
        };
        pos[i] += 1;
        current[i] = measure(&mut err, i, pos[i], &mut steps)?;
    }
}

/// One measurement of the samples search.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SamplesStep {
    pub samples: (usize, usize),
    pub loss_db: f64,
}

/// What [`choose_samples`] chose and measured.
#[derive(Clone, Debug, PartialEq)]
pub struct SamplesChoice {
    /// Proposal and main samples per ray.
    pub samples: PlaySampleCounts,
    pub loss_db: f64,
    pub steps: Vec<SamplesStep>,
    pub seconds: f64,
}

/// The counts tried for a model count `n`, fewest first: `n` times 1/4, 1/3, 1/2, 2/3, 3/4 and
/// 1, rounded up, distinct.
pub fn sample_candidates(n: usize) -> Vec<usize> {
    let mut v: Vec<usize> = [(1, 4), (1, 3), (1, 2), (2, 3), (3, 4), (1, 1)]
        .iter()
        .map(|&(a, b)| (n * a).div_ceil(b).max(1))
        .collect();
    v.dedup();
    v
}

/// The fewest of [`sample_candidates`] of `own`, from the most down while `ok` (fewer samples
/// lose more): `own` when the first fails.
fn fewest(own: usize, mut ok: impl FnMut(usize) -> bool) -> usize {
    let mut best = own;
    for n in sample_candidates(own).into_iter().rev() {
        if n == own {
            continue;
        }
        if !ok(n) {
            break;
        }
        best = n;
    }
    best
}

/// The fewest samples per ray (module docs) whose renders of `decoded` stay within
/// `auto.max_loss_db` of its renders at the model's own counts.
pub fn choose_samples(
    decoded: &DecodedModel,
    probe: &Probe,
    auto: &AutoOptions,
) -> Result<SamplesChoice, EncodeError> {
    auto.check()?;
    let start = Instant::now();
    let model = &decoded.metadata.model;
    let layout = ModelLayout::new(model);
    let own = (
        model.sampler.num_proposal_samples,
        model.sampler.num_samples,
    );
    let render = |(p, m): (usize, usize)| {
        let mut cfg = model.clone();
        cfg.sampler.set_samples(p, m);
        probe.render(&cfg, &layout, &|t| decoded.params_for_time(t))
    };
    let reference = render(own);
    let mut steps = Vec::new();
    let test = |s: (usize, usize), budget_db: f64, steps: &mut Vec<SamplesStep>| {
        if s == own {
            return true;
        }
        if let Some(done) = steps.iter().find(|d| d.samples == s) {
            return done.loss_db <= budget_db;
        }
        let loss_db = auto.loss_db(mse(&render(s), &reference));
        steps.push(SamplesStep {
            samples: s,
            loss_db,
        });
        loss_db <= budget_db
    };
    let main = fewest(own.1, |m| {
        test((own.0, m), auto.max_loss_db / 2.0, &mut steps)
    });
    let proposal = fewest(own.0, |p| test((p, main), auto.max_loss_db, &mut steps));
    let loss_db = steps
        .iter()
        .find(|s| s.samples == (proposal, main))
        .map_or(0.0, |s| s.loss_db);
    Ok(SamplesChoice {
        samples: PlaySampleCounts {
            proposal: proposal as u32,
            main: main as u32,
        },
        loss_db,
        steps,
        seconds: start.elapsed().as_secs_f64(),
    })
}
