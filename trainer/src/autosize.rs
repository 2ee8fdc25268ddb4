//! Sizing the model from the data ("model only what a scene requires", issue #8 item 3).
//!
//! [`measure`] reads a few statistics off a loaded dataset; [`plan`] turns them into choices on
//! top of a preset's [`ModelConfig`]; [`autosize`] applies every choice the user did not set
//! themselves and returns a [`SizingReport`] (each choice, the statistic it came from and why),
//! which `msth train` prints and saves next to the checkpoint as `sizing.json`.
//!
//! The choices, in order:
//! 1. **Time resolution**: the finest time resolution of the 4D grids is the number of distinct
//!    frame times (one time cell per frame; coarsest `min(15, frames)`, the proposal's finest at
//!    most 150, as method.md).
//! 2. **Motion**: the dynamic fraction of the video decides the 4D table. No measurable motion
//!    (or a single frame) gives the `static` blend: no 4D table and no mask at all, in the
//!    trained model and in the exported file. Otherwise the 4D tables shrink with the fraction:
//!    `rows4 = rows3 * 2^round(log2 f)`, between 1/64 of the 3D table and all of it, at least
//!    2^10 rows (docs/sizing.md, "How many 4D rows": half the rows of the earlier rule `2 f`
//!    gained held-out PSNR once the mask decides).
//! 3. **Finest spatial resolution**: twice the number of pixel footprints across the scene (the
//!    footprint of the most detailed training camera at the scene centre), rounded up to a
//!    power of two, never above the preset's.
//! 4. **Table size**: one row per finest-level cell the training images can resolve, estimated as
//!    `4 W H min(cameras, 4)` (a footprint covers 2x2 finest cells; distinct cameras overlap, so
//!    at most four images' worth), rounded up to a power of two, at least 2^14, never above the
//!    preset's.
//!
//! The dynamic fraction is measured on multi-view video only (views sharing a fixed camera at
//! several times, `View::camera_id`): the fraction of sampled pixels whose colour varies over
//! time (temporal standard deviation above [`DYNAMIC_PIXEL_STD`]), pooled over cameras.
//! Monocular data (D-NeRF style, every frame from its own camera) has no pixel that keeps its
//! meaning over time, so nothing is measured there and the preset's 4D table is kept (the report
//! says so). Every choice only ever shrinks the preset.

use serde::{Deserialize, Serialize};

use msth_core::config::{BlendMode, EncodingConfig, ModelConfig};
use msth_core::SceneBounds;

use crate::train::TrainSettings;
use msth_dataset::{Dataset, View};

/// A pixel is dynamic when the standard deviation of its colour over time (the largest over the
/// three channels, values in `[0, 1]`) exceeds this: about 5/255, above video noise, far below
/// what a moving object or shadow does.
pub const DYNAMIC_PIXEL_STD: f32 = 0.02;
/// The grid extent the sizing scales a scene to: a box's longest side of 3 units (the D-NeRF
/// cube), a contraction radius of 1 (the grids then span 4 units).
pub const CANONICAL_BOX: f32 = 3.0;
pub const CANONICAL_RADIUS: f32 = 1.0;
/// Scenes within this factor of the canonical size keep their units (an order of magnitude:
/// measured scenes at 1/1000 stall, see docs/stability.md, while every shipped dataset lies
/// within it and keeps its units).
pub const SCALE_TOLERANCE: f32 = 10.0;
/// A video whose dynamic fraction is below this (0.2% of the pixels) counts as static.
pub const STATIC_FRACTION: f64 = 0.002;
/// Cameras, frames per camera and pixels per frame sampled to measure motion.
pub const MAX_MOTION_CAMERAS: usize = 16;
pub const MAX_MOTION_FRAMES: usize = 48;
pub const MAX_MOTION_PIXELS: usize = 16_384;
/// Smallest table the sizing picks (2^14 rows).
pub const MIN_LOG2_TABLE: u32 = 14;
/// Smallest finest spatial resolution the sizing picks.
pub const MIN_FINEST: f32 = 64.0;
/// The 4D table is at most this many times (2^6) smaller than the 3D one.
pub const MAX_H4_SHRINK_LOG2: i32 = 6;
/// Smallest 4D table the sizing picks (2^10 rows).
pub const MIN_LOG2_H4_TABLE: u32 = 10;

/// The 4D table's `log2` rows for a 3D table of `2^log2_3d` rows shrunk `2^shift` times: never
/// below [`MIN_LOG2_H4_TABLE`], unless the 3D table itself is smaller.
fn shrunk_h4(log2_3d: u32, shift: u32) -> u32 {
    log2_3d
        .saturating_sub(shift)
        .max(MIN_LOG2_H4_TABLE.min(log2_3d))
}
/// 4D rows per 3D row, per unit of dynamic fraction: `rows4 = rows3 * H4_ROWS_PER_DYNAMIC * f`
/// (rounded to a power of two in the log). The 4D table holds what moves and the mask keeps the
/// rest in 3D; measured on the built-in scene and `box_animated_stage` (docs/sizing.md, "How many
/// 4D rows"): 1 against the earlier 2, and 1/2 and 1/8 below it.
pub const H4_ROWS_PER_DYNAMIC: f64 = 1.0;

/// How the motion of the video was measured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Motion {
    /// One frame time: nothing can move.
    SingleFrame,
    /// Fixed cameras filming several frames: per-pixel temporal variance.
    MultiView {
        /// Fraction of the sampled pixels that vary over time.
        dynamic_fraction: f64,
        /// The largest fraction of any one camera.
        max_camera_fraction: f64,
        cameras: usize,
        frames_per_camera: usize,
        pixels_per_frame: usize,
    },
    /// Every frame from its own camera: temporal variance of a pixel is meaningless.
    Monocular,
}

/// The statistics the sizing is computed from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Measurements {
    /// Distinct frame times among the training views.
    pub num_frames: usize,
    pub motion: Motion,
    /// Distinct training cameras (by pose and size).
    pub cameras: usize,
    /// Width and height of the largest training image.
    pub image_size: [u32; 2],
    /// World size of one pixel at the scene centre, for the most detailed camera.
    pub pixel_footprint: f32,
    /// World extent the grids span along their longest axis (for a contracted scene, the full
    /// contracted cube in units of the inner one: 4 radii).
    pub grid_extent: f32,
}

/// One decision of the sizing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Choice {
    /// What is decided (e.g. "4D table").
    pub name: String,
    /// The settings it writes (dotted paths, as `--set` takes them).
    pub keys: Vec<String>,
    /// The value before sizing (the preset with the user's settings) and the chosen one, in
    /// words.
    pub preset: String,
    pub chosen: String,
    /// The measured statistic behind the choice.
    pub statistic: String,
    pub reason: String,
    /// `false` when the user set one of `keys` (the user's value wins).
    pub applied: bool,
}

/// Everything the sizing measured and chose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SizingReport {
    pub measurements: Measurements,
    pub choices: Vec<Choice>,
    /// Parameters of the preset's model and of the sized one.
    pub preset_parameters: usize,
    pub sized_parameters: usize,
}

impl SizingReport {
    /// Human-readable lines for `msth train`.
    pub fn lines(&self) -> Vec<String> {
        let mut out = vec![format!(
            "autosize: {} -> {} parameters ({:.1} -> {:.1} MB f32)",
            self.preset_parameters,
            self.sized_parameters,
            self.preset_parameters as f64 * 4e-6,
            self.sized_parameters as f64 * 4e-6
        )];
        for c in &self.choices {
            let state = if c.applied {
                String::new()
            } else {
                " [not applied: set by the user]".into()
            };
            out.push(format!(
                "  {}: {} (preset {}){state}\n    from: {}\n    why: {}",
                c.name, c.chosen, c.preset, c.statistic, c.reason
            ));
        }
        out
    }
}

fn same_camera(a: &View, b: &View) -> bool {
    a.camera.width == b.camera.width
        && a.camera.height == b.camera.height
        && a.camera
            .world_from_camera
            .abs_diff_eq(b.camera.world_from_camera, 1e-5)
}

/// `n` indices spread evenly over `0..len` (all of them when `len <= n`).
fn spread(len: usize, n: usize) -> Vec<usize> {
    if len <= n {
        return (0..len).collect();
    }
    (0..n).map(|i| i * len / n).collect()
}

/// Measures the motion of multi-view video: see the module docs.
pub fn measure_motion(data: &Dataset) -> Motion {
    let mut times: Vec<f32> = data.train.iter().map(|v| v.time).collect();
    times.sort_by(f32::total_cmp);
    times.dedup();
    if times.len() <= 1 {
        return Motion::SingleFrame;
    }
    // Group training views by camera: the loader's id when it has one, else identical poses.
    let mut groups: Vec<Vec<&View>> = Vec::new();
    for v in &data.train {
        let g = groups
            .iter_mut()
            .find(|g| match (g[0].camera_id, v.camera_id) {
                (Some(a), Some(b)) => a == b && same_camera(g[0], v),
                _ => same_camera(g[0], v),
            });
        match g {
            Some(g) => g.push(v),
            None => groups.push(vec![v]),
        }
    }
    let mut video: Vec<Vec<&View>> = groups
        .into_iter()
        .filter_map(|mut g| {
            g.sort_by(|a, b| a.time.total_cmp(&b.time));
            g.dedup_by(|a, b| a.time == b.time);
            (g.len() >= 2).then_some(g)
        })
        .collect();
    if video.is_empty() {
        return Motion::Monocular;
    }
    let cams = spread(video.len(), MAX_MOTION_CAMERAS);
    let video: Vec<Vec<&View>> = cams
        .into_iter()
        .map(|i| std::mem::take(&mut video[i]))
        .collect();
    let (mut dynamic, mut total) = (0u64, 0u64);
    let mut max_camera = 0.0f64;
    let mut frames_used = 0;
    let mut pixels_used = 0;
    for g in &video {
        let frames: Vec<&View> = spread(g.len(), MAX_MOTION_FRAMES)
            .into_iter()
            .map(|i| g[i])
            .collect();
        let (w, h) = (g[0].image.width as usize, g[0].image.height as usize);
        let stride = ((w * h) as f64 / MAX_MOTION_PIXELS as f64)
            .sqrt()
            .ceil()
            .max(1.0) as usize;
        let pixels: Vec<usize> = (0..h)
            .step_by(stride)
            .flat_map(|y| (0..w).step_by(stride).map(move |x| y * w + x))
            .collect();
        let n = frames.len() as f64;
        let mut sum = vec![[0f64; 3]; pixels.len()];
        let mut sq = vec![[0f64; 3]; pixels.len()];
        for f in &frames {
            for (k, &p) in pixels.iter().enumerate() {
                let c = f.image.data.rgb_at(p * 3);
                for ch in 0..3 {
                    let v = c[ch] as f64 / 255.0;
                    sum[k][ch] += v;
                    sq[k][ch] += v * v;
                }
            }
        }
        let thr = (DYNAMIC_PIXEL_STD as f64).powi(2);
        let d = (0..pixels.len())
            .filter(|&k| {
                (0..3).any(|ch| {
                    let mean = sum[k][ch] / n;
                    sq[k][ch] / n - mean * mean > thr
                })
            })
            .count();
        dynamic += d as u64;
        total += pixels.len() as u64;
        max_camera = max_camera.max(d as f64 / pixels.len().max(1) as f64);
        frames_used = frames_used.max(frames.len());
        pixels_used = pixels_used.max(pixels.len());
    }
    Motion::MultiView {
        dynamic_fraction: dynamic as f64 / total.max(1) as f64,
        max_camera_fraction: max_camera,
        cameras: video.len(),
        frames_per_camera: frames_used,
        pixels_per_frame: pixels_used,
    }
}

/// The world extent the grids span along their longest axis (a contracted scene's grids span
/// 4 radii).
pub fn grid_extent(bounds: &SceneBounds) -> f32 {
    match *bounds {
        SceneBounds::Box { min, max } => (max - min).max_element(),
        SceneBounds::Contracted { radius, .. } => 4.0 * radius,
    }
}

/// Everything [`plan`] needs from the dataset.
pub fn measure(data: &Dataset) -> Measurements {
    let mut times: Vec<f32> = data.train.iter().map(|v| v.time).collect();
    times.sort_by(f32::total_cmp);
    times.dedup();
    let (lo, hi) = data.bounds.extent();
    let centre = 0.5 * (lo + hi);
    let grid_extent = grid_extent(&data.bounds);
    let mut distinct: Vec<&View> = Vec::new();
    for v in &data.train {
        if !distinct.iter().any(|d| same_camera(d, v)) {
            distinct.push(v);
        }
        if distinct.len() >= 4096 {
            break;
        }
    }
    let mut footprint = f32::INFINITY;
    let mut size = [0u32; 2];
    for v in &distinct {
        let c = &v.camera;
        let dist = (c.center() - centre).length();
        let f = dist / c.fx.max(c.fy).max(1e-6);
        if f.is_finite() && f > 0.0 {
            footprint = footprint.min(f);
        }
        if c.width as u64 * c.height as u64 > size[0] as u64 * size[1] as u64 {
            size = [c.width, c.height];
        }
    }
    Measurements {
        num_frames: times.len().max(1),
        motion: measure_motion(data),
        cameras: distinct.len(),
        image_size: size,
        pixel_footprint: footprint,
        grid_extent,
    }
}

fn set_time(enc: &mut EncodingConfig, finest_cap: f32, frames: usize) {
    let finest_t = (frames.max(1) as f32).max(2.0).min(finest_cap);
    let base_t = finest_t.min(15.0);
    enc.grid4.finest_resolution[3] = finest_t;
    enc.grid4.base_resolution[3] = base_t;
}

fn log2_ceil(x: f64) -> u32 {
    if x <= 1.0 {
        0
    } else {
        x.log2().ceil() as u32
    }
}

/// A planned choice: the report entry and what it does to the model.
struct Planned {
    choice: Choice,
    apply: Box<dyn Fn(&mut TrainSettings)>,
}

fn planned(
    name: &str,
    keys: &[&str],
    preset: String,
    chosen: String,
    statistic: String,
    reason: &str,
    apply: impl Fn(&mut ModelConfig) + 'static,
) -> Planned {
    planned_settings(name, keys, preset, chosen, statistic, reason, move |s| {
        apply(&mut s.model)
    })
}

fn planned_settings(
    name: &str,
    keys: &[&str],
    preset: String,
    chosen: String,
    statistic: String,
    reason: &str,
    apply: impl Fn(&mut TrainSettings) + 'static,
) -> Planned {
    Planned {
        choice: Choice {
            name: name.into(),
            keys: keys.iter().map(|k| k.to_string()).collect(),
            preset,
            chosen,
            statistic,
            reason: reason.into(),
            applied: true,
        },
        apply: Box::new(apply),
    }
}

const F_GRID3: &str = "model.field.encoding.grid3";
const F_GRID4: &str = "model.field.encoding.grid4";
const P_GRID4: &str = "model.proposal.encoding.grid4";

fn plan(settings: &TrainSettings, m: &Measurements) -> Vec<Planned> {
    let mut out = Vec::new();
    let preset = &settings.model;
    let f = &preset.field.encoding;
    let frames = m.num_frames;

    // 0. Scene scale: densities are per world unit, so a scene far from unit size trains slowly
    //    (docs/stability.md); bring it to the canonical size.
    let (canonical, what) = match preset.bounds {
        SceneBounds::Box { .. } => (CANONICAL_BOX, "the box's longest side"),
        SceneBounds::Contracted { .. } => (4.0 * CANONICAL_RADIUS, "4 contraction radii"),
    };
    let needed = canonical / m.grid_extent;
    let scale = if needed.is_finite()
        && needed > 0.0
        && !(1.0 / SCALE_TOLERANCE..=SCALE_TOLERANCE).contains(&needed)
    {
        needed
    } else {
        1.0
    };
    let before = settings.scene_scale;
    out.push(planned_settings(
        "scene scale",
        &["scene_scale"],
        format!("{before}"),
        format!("{}", before * scale),
        format!("grid extent {} world units ({what})", m.grid_extent),
        "densities and sample steps are per world unit: a scene far from unit size starts almost transparent (or opaque) and learns slowly; scenes within 10x of the canonical size (a 3-unit box, a contraction radius of 1) keep their units",
        move |s| s.scene_scale = before * scale,
    ));

    // 1. Time resolution.
    out.push(planned(
        "finest time resolution",
        &[
            &format!("{F_GRID4}.finest_resolution"),
            &format!("{F_GRID4}.base_resolution"),
            &format!("{P_GRID4}.finest_resolution"),
            &format!("{P_GRID4}.base_resolution"),
        ],
        format!(
            "{} (proposal {})",
            f.grid4.finest_resolution[3], preset.proposal.encoding.grid4.finest_resolution[3]
        ),
        format!(
            "{} (proposal {})",
            (frames as f32).max(2.0),
            (frames as f32).clamp(2.0, 150.0)
        ),
        format!("{frames} distinct frame times in the training views"),
        "one time cell per frame: a finer grid has cells no frame constrains, a coarser one blurs motion between frames",
        move |c| {
            set_time(&mut c.field.encoding, f32::MAX, frames);
            set_time(&mut c.proposal.encoding, 150.0, frames);
        },
    ));

    // 2. Finest spatial resolution from the pixel footprint.
    let preset_finest = f.grid3.finest_resolution[0];
    let needed = 2.0 * m.grid_extent / m.pixel_footprint;
    let finest = if needed.is_finite() && needed > 0.0 {
        (needed.ceil() as u64)
            .next_power_of_two()
            .clamp(MIN_FINEST as u64, 1 << 20) as f32
    } else {
        preset_finest
    };
    let finest = finest.min(preset_finest).max(f.grid3.base_resolution[0]);
    out.push(planned(
        "finest spatial resolution",
        &[
            &format!("{F_GRID3}.finest_resolution"),
            &format!("{F_GRID4}.finest_resolution"),
        ],
        format!("{preset_finest}"),
        format!("{finest}"),
        format!(
            "pixel footprint {:.4} at the scene centre (finest camera), grid extent {:.3}: {:.0} footprints across",
            m.pixel_footprint,
            m.grid_extent,
            m.grid_extent / m.pixel_footprint
        ),
        "two cells per pixel footprint resolve everything the images show; finer levels only fit noise between rays (rounded up to a power of two, at most the preset's)",
        move |c| {
            let e = &mut c.field.encoding;
            for r in e.grid3.finest_resolution.iter_mut().take(3) {
                *r = finest;
            }
            for r in e.grid4.finest_resolution.iter_mut().take(3) {
                *r = finest;
            }
        },
    ));

    // 3. Table size from the resolvable cells.
    let [w, h] = m.image_size;
    let cells = 4.0 * w as f64 * h as f64 * m.cameras.clamp(1, 4) as f64;
    let preset_log2 = f.grid3.log2_table_size;
    let dense_finest = 3.0 * ((finest as f64) + 1.0).log2();
    let log2 = log2_ceil(cells)
        .max(MIN_LOG2_TABLE)
        .min(preset_log2)
        .min(dense_finest.ceil().max(MIN_LOG2_TABLE as f64) as u32);
    out.push(planned(
        "3D table rows",
        &[&format!("{F_GRID3}.log2_table_size")],
        format!("2^{preset_log2}"),
        format!("2^{log2}"),
        format!(
            "{} distinct cameras of {w}x{h}: about {cells:.0} resolvable finest cells",
            m.cameras
        ),
        "one row per cell the images can resolve (2x2 cells per pixel footprint, overlapping cameras counted at most four times); more rows are never trained apart (at least 2^14, at most the preset's)",
        move |c| c.field.encoding.grid3.log2_table_size = log2,
    ));

    // 4. Motion: static, or a 4D table sized by the dynamic fraction.
    let blend_keys = [
        "model.field.encoding.blend",
        "model.proposal.encoding.blend",
    ];
    let h4_keys = [
        &format!("{F_GRID4}.log2_table_size") as &str,
        &format!("{P_GRID4}.log2_table_size"),
    ];
    match m.motion {
        Motion::SingleFrame => out.push(planned(
            "4D table",
            &blend_keys,
            format!("{:?} blend", f.blend).to_lowercase(),
            "none (static blend: 3D table only, no mask)".into(),
            "a single frame time".into(),
            "nothing can move in one frame",
            |c| {
                c.field.encoding.blend = BlendMode::Static;
                c.proposal.encoding.blend = BlendMode::Static;
            },
        )),
        Motion::MultiView {
            dynamic_fraction: df,
            max_camera_fraction,
            cameras,
            frames_per_camera,
            pixels_per_frame,
        } => {
            let stat = format!(
                "dynamic fraction {:.4} ({:.2}% of {} sampled pixels x {} frames x {} cameras vary over time with std > {:.3}; busiest camera {:.2}%)",
                df,
                100.0 * df,
                pixels_per_frame,
                frames_per_camera,
                cameras,
                DYNAMIC_PIXEL_STD,
                100.0 * max_camera_fraction
            );
            if df < STATIC_FRACTION {
                out.push(planned(
                    "4D table",
                    &blend_keys,
                    format!("{:?} blend", f.blend).to_lowercase(),
                    "none (static blend: 3D table only, no mask)".into(),
                    stat,
                    "no measurable motion (below 0.2% of the pixels): a 4D table and mask would model nothing",
                    |c| {
                        c.field.encoding.blend = BlendMode::Static;
                        c.proposal.encoding.blend = BlendMode::Static;
                    },
                ));
            } else {
                let shift = (H4_ROWS_PER_DYNAMIC * df)
                    .log2()
                    .round()
                    .clamp(-(MAX_H4_SHRINK_LOG2 as f64), 0.0) as i32;
                let shift_u = (-shift) as u32;
                let p3 = preset.proposal.encoding.grid3.log2_table_size;
                out.push(planned(
                    "4D table rows",
                    &h4_keys,
                    format!(
                        "2^{} (proposal 2^{})",
                        f.grid4.log2_table_size, preset.proposal.encoding.grid4.log2_table_size
                    ),
                    format!(
                        "3D rows / 2^{shift_u} (proposal 2^{})",
                        shrunk_h4(p3, shift_u)
                    ),
                    stat,
                    "only the dynamic part of the scene needs the 4D table (the mask keeps the rest in 3D): rows scale with the dynamic fraction, rounded to a power of two, at most 64 times fewer than the 3D table, at least 2^10",
                    move |c| {
                        let l3 = c.field.encoding.grid3.log2_table_size;
                        c.field.encoding.grid4.log2_table_size = shrunk_h4(l3, shift_u);
                        let p3 = c.proposal.encoding.grid3.log2_table_size;
                        c.proposal.encoding.grid4.log2_table_size = shrunk_h4(p3, shift_u);
                    },
                ));
            }
        }
        Motion::Monocular => out.push(planned(
            "4D table rows",
            &h4_keys,
            format!("2^{}", f.grid4.log2_table_size),
            "the 3D table's rows".into(),
            "monocular video: every frame has its own camera, so no pixel can be followed over time".into(),
            "motion cannot be told from camera motion without a reconstruction; the 4D table keeps the 3D table's size (not measured)",
            |c| c.field.encoding.grid4.log2_table_size = c.field.encoding.grid3.log2_table_size,
        )),
    }
    out
}

/// Whether the user's setting `user` (a dotted path) touches `key`: equal, or one contains the
/// other.
fn overlaps(user: &str, key: &str) -> bool {
    user == key || key.starts_with(&format!("{user}.")) || user.starts_with(&format!("{key}."))
}

/// Dotted paths of every key a JSON settings object sets (objects and leaves).
pub fn setting_paths(v: &serde_json::Value) -> Vec<String> {
    fn walk(v: &serde_json::Value, path: &str, out: &mut Vec<String>) {
        if let serde_json::Value::Object(map) = v {
            for (k, c) in map {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                out.push(p.clone());
                walk(c, &p, out);
            }
        }
    }
    let mut out = Vec::new();
    walk(v, "", &mut out);
    out
}

/// Measures `data`, applies to `model` every choice none of whose keys the user set
/// (`user_keys`: dotted paths as `--set` takes them), and reports.
pub fn autosize(
    data: &Dataset,
    settings: &mut TrainSettings,
    user_keys: &[String],
) -> SizingReport {
    let mut m = measure(data);
    // The bounds the model will use (the loader's, or the user's).
    m.grid_extent = grid_extent(&settings.model.bounds);
    autosize_with(m, settings, user_keys)
}

/// [`autosize`] from given measurements.
pub fn autosize_with(
    m: Measurements,
    settings: &mut TrainSettings,
    user_keys: &[String],
) -> SizingReport {
    let preset_parameters = msth_core::field::ModelLayout::new(&settings.model)
        .params
        .total;
    let mut choices = Vec::new();
    for p in plan(settings, &m) {
        let mut c = p.choice;
        c.applied = !c
            .keys
            .iter()
            .any(|k| user_keys.iter().any(|u| overlaps(u, k)));
        if c.applied {
            (p.apply)(settings);
        }
        choices.push(c);
    }
    let sized_parameters = msth_core::field::ModelLayout::new(&settings.model)
        .params
        .total;
    SizingReport {
        measurements: m,
        choices,
        preset_parameters,
        sized_parameters,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::config::{Background, Preset};
    use msth_core::Camera;
    use msth_dataset::Image8;
    use std::path::PathBuf;

    /// Three fixed cameras filming `frames` frames of 64x48; the pixels with `x < dynamic_cols`
    /// change colour every frame, the rest stay put (plus `noise` of +-1 level per frame).
    fn video(frames: usize, dynamic_cols: u32, noise: bool) -> Dataset {
        let (w, h) = (64u32, 48u32);
        let mut train = Vec::new();
        for cam in 0..3 {
            let camera = Camera::look_at(
                w,
                h,
                0.9,
                Vec3::new(cam as f32 - 1.0, -4.0, 0.5),
                Vec3::ZERO,
                Vec3::Z,
            );
            for f in 0..frames {
                let mut img = Image8::new(w, h);
                for y in 0..h {
                    for x in 0..w {
                        let i = ((y * w + x) * 3) as usize;
                        let base = ((x * 3 + y * 5) % 200) as u8 + 20;
                        let v = if x < dynamic_cols {
                            ((f * 97 + x as usize) % 256) as u8
                        } else if noise {
                            base + (f % 2) as u8
                        } else {
                            base
                        };
                        img.data[i..i + 3].copy_from_slice(&[v, base, v]);
                    }
                }
                train.push(View {
                    camera,
                    time: if frames > 1 {
                        f as f32 / (frames - 1) as f32
                    } else {
                        0.0
                    },
                    image: img,
                    source: PathBuf::from(format!("cam{cam}/{f}")),
                    camera_id: Some(cam),
                    alpha: None,
                });
            }
        }
        Dataset {
            name: "video".into(),
            train,
            test: vec![],
            bounds: SceneBounds::dnerf_default(),
            background: [1.0; 3],
            num_frames: frames,
            near: None,
        }
    }

    fn paper(frames: usize) -> TrainSettings {
        let m = ModelConfig::preset(
            Preset::Paper,
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
            frames,
        );
        TrainSettings::for_model(Preset::Paper, m)
    }

    #[test]
    fn static_video_gets_no_4d_table() {
        let d = video(10, 0, true);
        let mut st = paper(10);
        let r = autosize(&d, &mut st, &[]);
        let m = &st.model;
        match r.measurements.motion {
            Motion::MultiView {
                dynamic_fraction, ..
            } => assert_eq!(dynamic_fraction, 0.0),
            ref o => panic!("{o:?}"),
        }
        assert_eq!(m.field.encoding.blend, BlendMode::Static);
        assert_eq!(m.proposal.encoding.blend, BlendMode::Static);
        m.validate().unwrap();
        let layout = msth_core::field::ModelLayout::new(m);
        assert!(layout
            .params
            .entries
            .iter()
            .all(|e| !e.name.ends_with(".h4") && !e.name.ends_with(".mask")));
        assert!(r.sized_parameters < r.preset_parameters);
    }

    #[test]
    fn small_dynamic_region_shrinks_the_4d_table() {
        // 4 of 64 columns move: 6.25% -> 2^-4.
        let d = video(10, 4, true);
        let mut st = paper(10);
        // Keep the 3D table at the preset's 2^19 (as a user setting) to see the shift whole.
        let keep = ["model.field.encoding.grid3.log2_table_size".to_string()];
        let r = autosize(&d, &mut st, &keep);
        let m = &st.model;
        let Motion::MultiView {
            dynamic_fraction, ..
        } = r.measurements.motion
        else {
            panic!()
        };
        assert!(
            (dynamic_fraction - 0.0625).abs() < 0.01,
            "{dynamic_fraction}"
        );
        let e = &m.field.encoding;
        assert_eq!(e.blend, BlendMode::Mt);
        assert_eq!(e.grid3.log2_table_size, 19);
        assert_eq!(e.grid4.log2_table_size, 15);
        assert_eq!(m.proposal.encoding.grid4.log2_table_size, 14);
        m.validate().unwrap();
        // With the sized 3D table (2^16) the shift is the same.
        let mut st = paper(10);
        autosize(&d, &mut st, &[]);
        let m = &st.model;
        assert_eq!(m.field.encoding.grid3.log2_table_size, 16);
        assert_eq!(m.field.encoding.grid4.log2_table_size, 12);
        // One column of 64 moves: 1.6% -> 2^-6, the most the sizing shrinks.
        let d = video(10, 1, true);
        let mut st = paper(10);
        autosize(&d, &mut st, &keep);
        let m = &st.model;
        assert_eq!(m.field.encoding.grid4.log2_table_size, 19 - 6);
        // A user's 2^14 3D table: 2^8 would be below the 2^10 floor.
        let mut st = paper(10);
        st.model.field.encoding.grid3.log2_table_size = 14;
        autosize(&d, &mut st, &keep);
        assert_eq!(
            st.model.field.encoding.grid4.log2_table_size,
            MIN_LOG2_H4_TABLE
        );
    }

    #[test]
    fn fully_dynamic_video_keeps_the_4d_table() {
        let d = video(10, 64, false);
        let mut st = paper(10);
        autosize(&d, &mut st, &[]);
        let m = &st.model;
        let e = &m.field.encoding;
        assert_eq!(e.blend, BlendMode::Mt);
        assert_eq!(e.grid4.log2_table_size, e.grid3.log2_table_size);
        assert_eq!(e.grid4.finest_resolution[3], 10.0);
    }

    #[test]
    fn sizes_follow_the_images() {
        // 64x48 images, 3 cameras: 4 * 3072 * 3 = 36864 cells -> 2^16 rows; footprint about
        // 4.1 / 55 -> 2 * 3 / 0.075 = 80 -> 128.
        let d = video(4, 0, false);
        let mut st = paper(4);
        let r = autosize(&d, &mut st, &[]);
        let m = &st.model;
        let e = &m.field.encoding;
        assert_eq!(e.grid3.log2_table_size, 16, "{:#?}", r);
        assert_eq!(e.grid3.finest_resolution, vec![128.0; 3]);
        assert_eq!(&e.grid4.finest_resolution[..3], &[128.0; 3]);
        // Never above the preset: a fast preset keeps its smaller table.
        let mut fast = TrainSettings::for_model(Preset::Fast, ModelConfig::fast_on_white(4));
        autosize(&d, &mut fast, &[]);
        assert_eq!(fast.model.field.encoding.grid3.log2_table_size, 15);
    }

    #[test]
    fn user_settings_win() {
        let d = video(10, 0, false);
        let mut st = paper(10);
        let keys = vec![
            "model.field.encoding.blend".to_string(),
            "model.field.encoding.grid3".to_string(),
        ];
        let r = autosize(&d, &mut st, &keys);
        let m = &st.model;
        assert_eq!(m.field.encoding.blend, BlendMode::Mt);
        assert_eq!(m.field.encoding.grid3.log2_table_size, 19);
        let applied: Vec<(&str, bool)> = r
            .choices
            .iter()
            .map(|c| (c.name.as_str(), c.applied))
            .collect();
        assert_eq!(
            applied,
            [
                ("scene scale", true),
                ("finest time resolution", true),
                ("finest spatial resolution", false),
                ("3D table rows", false),
                ("4D table", false),
            ]
        );
        // Paths from a config file count too.
        let file =
            serde_json::json!({"model": {"field": {"encoding": {"blend": "mst"}}}, "iters": 3});
        let p = setting_paths(&file);
        assert!(p.contains(&"model.field.encoding.blend".to_string()));
        assert!(p.contains(&"iters".to_string()));
    }

    #[test]
    fn scene_scale_brings_far_off_scenes_to_unit_size() {
        // The same video 1000 times smaller: scaled back by 1000; the other choices are the
        // same as at unit size (they depend on ratios only).
        let unit = video(10, 4, true);
        let mut st = paper(10);
        autosize(&unit, &mut st, &[]);
        assert_eq!(st.scene_scale, 1.0);
        let mut tiny = unit.clone();
        tiny.rescale(1e-3);
        let mut small = paper(10);
        small.model.bounds = tiny.bounds;
        let r = autosize(&tiny, &mut small, &[]);
        assert!((small.scene_scale - 1e3).abs() < 1e-1, "{r:#?}");
        assert_eq!(small.model.field, st.model.field);
        // Applying it gives back the unit scene's world (up to rounding).
        let mut data = tiny.clone();
        assert_eq!(small.scale_world(&mut data), small.scene_scale);
        assert!(small
            .model
            .bounds
            .extent()
            .1
            .abs_diff_eq(st.model.bounds.extent().1, 1e-4));
        let (a, b) = (data.train[5].camera.center(), unit.train[5].camera.center());
        assert!(a.abs_diff_eq(b, 1e-4), "{a} vs {b}");
        // A 3x smaller scene is within tolerance: kept as it is.
        let mut third = unit.clone();
        third.rescale(1.0 / 3.0);
        let mut s3 = paper(10);
        s3.model.bounds = third.bounds;
        autosize(&third, &mut s3, &[]);
        assert_eq!(s3.scene_scale, 1.0);
    }

    #[test]
    fn monocular_and_single_frame() {
        let mut d = video(6, 64, false);
        // Every view its own camera: move each one a little.
        for (i, v) in d.train.iter_mut().enumerate() {
            v.camera_id = None;
            v.camera.world_from_camera.w_axis.x += 0.01 * i as f32;
        }
        let mut st = paper(6);
        let r = autosize(&d, &mut st, &[]);
        let m = &st.model;
        assert_eq!(r.measurements.motion, Motion::Monocular);
        assert_eq!(m.field.encoding.blend, BlendMode::Mt);
        let one = video(1, 64, false);
        let mut st = paper(1);
        let r = autosize(&one, &mut st, &[]);
        let m = &st.model;
        assert_eq!(r.measurements.motion, Motion::SingleFrame);
        assert_eq!(m.field.encoding.blend, BlendMode::Static);
        m.validate().unwrap();
    }
}
