//! `msth import`: from videos to a dataset `msth train` reads, with camera poses and intrinsics
//! estimated by COLMAP ([`msth_dataset::colmap`]).
//!
//! Two capture layouts:
//! - **rig**: several fixed cameras filming together (one video per camera, assumed to start
//!   together, or shifted by per-video offsets in frames). COLMAP sees the frames of a few time
//!   steps of all cameras ([`ImportOptions::sync_times`], default 1) and every frame of a camera
//!   gets that camera's pose (the average of its registered time steps);
//! - **monocular**: one moving camera; every frame is registered on its own.
//!
//! Output (built in a staging folder next to `out`, renamed at the end):
//! ```text
//! transforms.json        nerfstudio: OPENCV intrinsics + k1 k2 p1 p2, per-frame pose and time,
//!                        camera_id per rig camera (camera 0 is the held-out one by default)
//! camNN/TTTT.png         rig frames (camNN = the NN-th video, in the order given)
//! frames/TTTT.png        monocular frames
//! poses_bounds.npy       rig + a distortion-free camera model: DyNeRF rows with near/far
//! import.json            what COLMAP registered, errors, near/far per camera, the normalisation
//! colmap/                COLMAP's database, logs and binary models (sparse/seedS/N, one per
//!                        mapper run; import.json names the one used)
//! ```
//! The world is rotated so that the average camera up vector is +Z, centred on the point
//! closest to all optical axes (the mean camera centre when the axes are parallel) and scaled so
//! that the median camera distance to that centre is [`CAMERA_DISTANCE`]. Near/far per camera
//! are the 1st/99th percentiles of the depths of the sparse points it observes, x0.9 / x1.1.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{DMat3, DMat4, DQuat, DVec3, Mat4};
use msth_core::Camera;
use serde_json::{json, Value};

use msth_dataset::colmap::{
    mean_rotation, CameraModel, Colmap, ColmapError, Intrinsics, Matching, Model, RunOptions,
    Sharing, TrialSummary,
};
use msth_dataset::video::{self, Tools};
use msth_dataset::{dnerf, dynerf, DatasetError};

/// Median camera distance to the scene centre after normalisation (world units).
pub const CAMERA_DISTANCE: f64 = 4.0;

/// Video file extensions picked up from a folder.
pub const VIDEO_EXTENSIONS: [&str; 7] = ["mp4", "mov", "m4v", "mkv", "avi", "webm", "mpg"];

/// Monocular videos with more frames than this are matched sequentially, not exhaustively.
pub const EXHAUSTIVE_LIMIT: usize = 150;

/// COLMAP mapper runs compared by default (one mapping takes seconds on a small capture; on
/// the generated stage one run in seven converged to a wrong focal length, see docs/import.md).
pub const DEFAULT_MAPPER_RUNS: usize = 3;

/// One video per fixed camera, or one moving camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    Rig,
    Monocular,
}

/// A layout name that [`Layout`]'s `FromStr` does not know.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown layout `{0}` (expected rig or monocular)")]
pub struct UnknownLayout(pub String);

impl std::str::FromStr for Layout {
    type Err = UnknownLayout;
    fn from_str(s: &str) -> Result<Self, UnknownLayout> {
        match s {
            "rig" => Ok(Layout::Rig),
            "monocular" => Ok(Layout::Monocular),
            _ => Err(UnknownLayout(s.to_string())),
        }
    }
}

/// How to import.
#[derive(Clone, Debug)]
pub struct ImportOptions {
    /// `None`: monocular for one video, rig for several.
    pub layout: Option<Layout>,
    /// Frames to skip at the start of each video (empty: none; one value: the same for all).
    pub offsets: Vec<u64>,
    /// Use at most this many frames (time steps) per video.
    pub frames: Option<usize>,
    /// Rig: time steps (evenly spread) whose frames COLMAP reconstructs.
    pub sync_times: usize,
    pub camera_model: CameraModel,
    /// Rig: one set of intrinsics for all videos (`None`: when all have the same size).
    pub shared_intrinsics: Option<bool>,
    /// Fail when COLMAP registers fewer than this fraction of the cameras (rig) or frames
    /// (monocular).
    pub min_registered: f64,
    /// COLMAP mapper runs (random seeds) compared, the one agreeing best with the others kept
    /// (`None`: [`DEFAULT_MAPPER_RUNS`] up to [`EXHAUSTIVE_LIMIT`] images, else one).
    pub mapper_runs: Option<usize>,
    pub threads: usize,
    pub colmap: Colmap,
    pub tools: Tools,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            layout: None,
            offsets: Vec::new(),
            frames: None,
            sync_times: 1,
            camera_model: CameraModel::Opencv,
            shared_intrinsics: None,
            min_registered: 0.5,
            mapper_runs: None,
            threads: std::thread::available_parallelism().map_or(2, |n| n.get()),
            colmap: Colmap::default(),
            tools: Tools::default(),
        }
    }
}

/// What an import did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ImportReport {
    pub layout: String,
    /// Cameras (rig: videos; monocular: frames) and how many COLMAP registered.
    pub cameras_total: usize,
    pub cameras_registered: usize,
    /// Images COLMAP was given and registered.
    pub images_total: usize,
    pub images_registered: usize,
    pub points: usize,
    pub mean_reprojection_error_px: f64,
    /// COLMAP made more than one model (only the largest is used).
    pub colmap_models: usize,
    /// Every mapper run (seed, registered, points, error, focal, disagreement with the others
    /// in degrees) and the seed of the one used.
    pub colmap_runs: Vec<TrialSummary>,
    pub colmap_seed: u32,
    pub colmap_seconds: f64,
    pub decode_seconds: f64,
    /// Time steps in the dataset and frames written.
    pub time_steps: usize,
    pub frames_written: usize,
    /// Names of the videos (rig) or frames (monocular) COLMAP could not register.
    pub unregistered: Vec<String>,
    /// Scale from COLMAP's units to the dataset's.
    pub scale: f64,
    pub near: f64,
    pub far: f64,
}

/// Why an import failed.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Colmap(#[from] ColmapError),
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("COLMAP registered {registered} of {total} {what} (at least {needed} needed){names}. {hint}")]
    TooFewRegistered {
        what: &'static str,
        registered: usize,
        total: usize,
        needed: usize,
        names: String,
        hint: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ImportError + '_ {
    move |source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The videos in `dir` (by extension, case-insensitive), in name order.
pub fn videos_in(dir: &Path) -> Result<Vec<PathBuf>, ImportError> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io(dir))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.is_file()
                && p.extension().is_some_and(|e| {
                    VIDEO_EXTENSIONS.contains(&e.to_string_lossy().to_ascii_lowercase().as_str())
                })
        })
        .collect();
    v.sort();
    if v.is_empty() {
        return Err(ImportError::Invalid(format!(
            "{}: no videos ({}) in this folder",
            dir.display(),
            VIDEO_EXTENSIONS.join(", ")
        )));
    }
    Ok(v)
}

/// A frame decoded to disk: which video, which time step, where.
struct Frame {
    video: usize,
    time: usize,
    /// Relative to the dataset folder.
    rel: String,
}

/// Imports `videos` into the dataset folder `out` (which must not exist, or be empty).
/// `progress` receives a line at the start of each long step.
pub fn import(
    videos: &[PathBuf],
    out: &Path,
    opts: &ImportOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<ImportReport, ImportError> {
    let layout = match (opts.layout, videos.len()) {
        (_, 0) => return Err(ImportError::Invalid("no videos given".into())),
        (Some(Layout::Monocular), n) if n > 1 => {
            return Err(ImportError::Invalid(format!(
                "the monocular layout takes one video, got {n} (use --layout rig for a multi-camera capture)"
            )))
        }
        (Some(Layout::Rig), 1) => {
            return Err(ImportError::Invalid(
                "the rig layout needs at least two videos (one per camera)".into(),
            ))
        }
        (Some(l), _) => l,
        (None, 1) => Layout::Monocular,
        (None, _) => Layout::Rig,
    };
    let offsets: Vec<u64> = match opts.offsets.len() {
        0 => vec![0; videos.len()],
        1 => vec![opts.offsets[0]; videos.len()],
        n if n == videos.len() => opts.offsets.clone(),
        n => {
            return Err(ImportError::Invalid(format!(
                "{n} offsets for {} videos (give one per video, or one for all)",
                videos.len()
            )))
        }
    };
    if !(0.0..=1.0).contains(&opts.min_registered) {
        return Err(ImportError::Invalid(
            "the minimum registered fraction must be in [0, 1]".into(),
        ));
    }
    if opts.sync_times == 0 || opts.frames == Some(0) || opts.mapper_runs == Some(0) {
        return Err(ImportError::Invalid(
            "--frames, --sync-times and --colmap-runs must be at least 1".into(),
        ));
    }
    if out.exists() && (!out.is_dir() || std::fs::read_dir(out).map_err(io(out))?.next().is_some())
    {
        return Err(ImportError::Invalid(format!(
            "{}: exists and is not an empty folder (choose a new --out)",
            out.display()
        )));
    }
    opts.colmap.check()?;
    if !opts.tools.available() {
        return Err(ImportError::Invalid(format!(
            "`{}` / `{}` cannot be started: install ffmpeg (Debian/Ubuntu: `apt-get install ffmpeg`) or set MSTH_FFMPEG / MSTH_FFPROBE",
            opts.tools.ffmpeg.display(),
            opts.tools.ffprobe.display()
        )));
    }
    // Sizes and lengths.
    let mut infos = Vec::new();
    for (v, off) in videos.iter().zip(&offsets) {
        let info = video::probe(&opts.tools, v)?;
        if info.frames <= *off {
            return Err(ImportError::Invalid(format!(
                "{}: offset {off} skips all of its {} frames",
                v.display(),
                info.frames
            )));
        }
        infos.push(info);
    }
    let mut steps = infos
        .iter()
        .zip(&offsets)
        .map(|(i, o)| (i.frames - o) as usize)
        .min()
        .unwrap_or(0);
    if let Some(n) = opts.frames {
        steps = steps.min(n);
    }
    let staging = staging_dir(out)?;
    let result = (|| {
        let report = build(
            videos, &infos, &offsets, steps, layout, &staging, opts, progress,
        )?;
        if out.exists() {
            std::fs::remove_dir(out).map_err(io(out))?;
        }
        std::fs::rename(&staging, out).map_err(io(out))?;
        Ok(report)
    })();
    if result.is_err() {
        // Keep COLMAP's logs (not the half-made dataset) for the user to read.
        let logs = staging.join("colmap");
        let kept = logs_dir(out);
        let mut moved = false;
        if logs.is_dir() {
            let _ = std::fs::remove_dir_all(&kept);
            if std::fs::create_dir_all(&kept).is_ok() {
                for e in std::fs::read_dir(&logs).into_iter().flatten().flatten() {
                    if e.path().extension().is_some_and(|x| x == "log") {
                        moved |= std::fs::rename(e.path(), kept.join(e.file_name())).is_ok();
                    }
                }
            }
            if !moved {
                let _ = std::fs::remove_dir(&kept);
            }
        }
        let _ = std::fs::remove_dir_all(&staging);
        if moved {
            return result.map_err(|e| redirect_logs(e, &logs, &kept));
        }
    }
    result
}

/// Where the COLMAP logs of a failed import into `out` are kept: `OUT.colmap-logs` next to it.
pub fn logs_dir(out: &Path) -> PathBuf {
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    out.with_file_name(format!("{name}.colmap-logs"))
}

/// `e` with paths under the staging `from` folder pointing into `to`.
fn redirect_logs(e: ImportError, from: &Path, to: &Path) -> ImportError {
    let fix = |p: PathBuf| match p.strip_prefix(from) {
        Ok(rel) => to.join(rel),
        Err(_) => p,
    };
    match e {
        ImportError::Colmap(ColmapError::Failed { step, message, log }) => {
            ImportError::Colmap(ColmapError::Failed {
                step,
                message,
                log: fix(log),
            })
        }
        ImportError::Colmap(ColmapError::NoModel { why, log }) => {
            ImportError::Colmap(ColmapError::NoModel { why, log: fix(log) })
        }
        ImportError::TooFewRegistered {
            what,
            registered,
            total,
            needed,
            names,
            hint,
        } => ImportError::TooFewRegistered {
            what,
            registered,
            total,
            needed,
            names,
            hint: hint.replace(&from.display().to_string(), &to.display().to_string()),
        },
        e => e,
    }
}

fn staging_dir(out: &Path) -> Result<PathBuf, ImportError> {
    let name = out
        .file_name()
        .ok_or_else(|| ImportError::Invalid(format!("{}: not a folder name", out.display())))?
        .to_string_lossy()
        .into_owned();
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let tmp = out.with_file_name(format!("{name}.tmp-{}-{nanos}", std::process::id()));
    std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
    Ok(tmp)
}

/// Links (or copies) `from` to `to`.
fn link(from: &Path, to: &Path) -> Result<(), ImportError> {
    if let Some(p) = to.parent() {
        std::fs::create_dir_all(p).map_err(io(p))?;
    }
    if std::fs::hard_link(from, to).is_err() {
        std::fs::copy(from, to).map_err(io(to))?;
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn build(
    videos: &[PathBuf],
    infos: &[video::VideoInfo],
    offsets: &[u64],
    steps: usize,
    layout: Layout,
    dir: &Path,
    opts: &ImportOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<ImportReport, ImportError> {
    // 1. Decode the frames.
    let t0 = Instant::now();
    let mut frames: Vec<Frame> = Vec::new();
    for (vi, (v, info)) in videos.iter().zip(infos).enumerate() {
        progress(&format!(
            "decoding {} ({}x{}, frames {}..{} of {})",
            v.display(),
            info.width,
            info.height,
            offsets[vi],
            offsets[vi] + steps as u64,
            info.frames
        ));
        let first = offsets[vi] as usize;
        let mut each = |index: usize, rgb: &[u8]| -> Result<(), DatasetError> {
            if index < first || index >= first + steps {
                return Ok(());
            }
            let t = index - first;
            let rel = match layout {
                Layout::Rig => format!("cam{vi:02}/{t:04}.png"),
                Layout::Monocular => format!("frames/{t:04}.png"),
            };
            let path = dir.join(&rel);
            if let Some(p) = path.parent() {
                std::fs::create_dir_all(p).map_err(|source| DatasetError::Io {
                    path: p.to_path_buf(),
                    source,
                })?;
            }
            image::RgbImage::from_raw(info.width, info.height, rgb.to_vec())
                .ok_or_else(|| DatasetError::Invalid {
                    path: v.clone(),
                    message: "decoded frame of the wrong size".into(),
                })?
                .save(&path)
                .map_err(|e| DatasetError::Image {
                    path: path.clone(),
                    message: e.to_string(),
                })?;
            frames.push(Frame {
                video: vi,
                time: t,
                rel,
            });
            Ok(())
        };
        video::decode(&opts.tools, v, info, &mut each)?;
    }
    let decode_seconds = t0.elapsed().as_secs_f64();

    // 2. The images COLMAP sees (hard links to the frames), named so that each maps back.
    let work = dir.join("colmap");
    let images = work.join("images");
    let mut colmap_names: BTreeMap<String, usize> = BTreeMap::new(); // name -> frame index
    let times: Vec<usize> = match layout {
        Layout::Monocular => (0..steps).collect(),
        Layout::Rig => {
            let k = opts.sync_times.min(steps);
            if k == 1 {
                vec![0]
            } else {
                (0..k).map(|i| i * (steps - 1) / (k - 1)).collect()
            }
        }
    };
    for (fi, f) in frames.iter().enumerate() {
        if !times.contains(&f.time) {
            continue;
        }
        let name = match layout {
            Layout::Rig => format!("cam{:02}/t{:04}.png", f.video, f.time),
            Layout::Monocular => format!("{:04}.png", f.time),
        };
        link(&dir.join(&f.rel), &images.join(&name))?;
        colmap_names.insert(name, fi);
    }
    let same_size = infos
        .iter()
        .all(|i| (i.width, i.height) == (infos[0].width, infos[0].height));
    let shared = opts.shared_intrinsics.unwrap_or(same_size);
    if shared && !same_size {
        return Err(ImportError::Invalid(
            "shared intrinsics need videos of one size".into(),
        ));
    }
    let run = RunOptions {
        camera_model: opts.camera_model,
        sharing: if layout == Layout::Rig && !shared {
            Sharing::PerFolder
        } else {
            Sharing::All
        },
        matching: if colmap_names.len() > EXHAUSTIVE_LIMIT {
            Matching::Sequential { overlap: 15 }
        } else {
            Matching::Exhaustive
        },
        threads: opts.threads,
        mapper_runs: opts
            .mapper_runs
            .unwrap_or(if colmap_names.len() > EXHAUSTIVE_LIMIT {
                1
            } else {
                DEFAULT_MAPPER_RUNS
            }),
    };
    progress(&format!(
        "COLMAP: {} images ({} camera model, {})",
        colmap_names.len(),
        opts.camera_model.name(),
        match run.sharing {
            Sharing::All => "one set of intrinsics",
            Sharing::PerFolder => "intrinsics per video",
        }
    ));
    let rec = opts.colmap.reconstruct(&images, &work, &run, progress);
    let rec = match rec {
        Ok(r) => r,
        // Nothing registered: the same message as too few registered.
        Err(ColmapError::NoModel { .. }) => Default::default(),
        Err(e) => return Err(e.into()),
    };
    let model = &rec.model;

    // 3. Poses per registered image, grouped per camera (rig) or frame (monocular).
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new(); // camera / frame -> images
    for (ii, im) in model.images.iter().enumerate() {
        let Some(&fi) = colmap_names.get(&im.name) else {
            continue;
        };
        let key = match layout {
            Layout::Rig => frames[fi].video,
            Layout::Monocular => fi,
        };
        groups.entry(key).or_default().push(ii);
    }
    let (total, what) = match layout {
        Layout::Rig => (videos.len(), "cameras"),
        Layout::Monocular => (frames.len(), "frames"),
    };
    let unregistered: Vec<String> = (0..total)
        .filter(|k| !groups.contains_key(k))
        .map(|k| match layout {
            Layout::Rig => videos[k]
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            Layout::Monocular => frames[k].rel.clone(),
        })
        .collect();
    let needed = ((opts.min_registered * total as f64).ceil() as usize)
        .max(2)
        .min(total);
    if groups.len() < needed {
        let shown: Vec<&str> = unregistered.iter().take(8).map(String::as_str).collect();
        return Err(ImportError::TooFewRegistered {
            what,
            registered: groups.len(),
            total,
            needed,
            names: if shown.is_empty() {
                String::new()
            } else {
                format!(
                    "; not registered: {}{}",
                    shown.join(", "),
                    if unregistered.len() > shown.len() { ", ..." } else { "" }
                )
            },
            hint: format!(
                "Check that the views overlap and show textured, static surfaces; try more --sync-times, another --camera-model, or larger frames. COLMAP's logs are in {}",
                work.display()
            ),
        });
    }
    let mut poses: BTreeMap<usize, DMat4> = BTreeMap::new();
    for (&k, ims) in &groups {
        let mats: Vec<DMat4> = ims
            .iter()
            .map(|&i| Model::world_from_camera(&model.images[i]))
            .collect();
        poses.insert(k, average_pose(&mats));
    }

    // 4. Normalise: up = +Z, centre, scale.
    let up = poses
        .values()
        .map(|m| m.y_axis.truncate())
        .sum::<DVec3>()
        .normalize_or_zero();
    let up = if up == DVec3::ZERO { DVec3::Z } else { up };
    let rot = DMat3::from_quat(DQuat::from_rotation_arc(up, DVec3::Z));
    let rotated: Vec<Camera> = poses
        .values()
        .map(|m| camera_of(&(DMat4::from_mat3(rot) * *m)))
        .collect();
    let center = match dnerf::contracted_bounds_from_cameras(&rotated) {
        msth_core::SceneBounds::Contracted { center, .. } => center.as_dvec3(),
        _ => DVec3::ZERO,
    };
    let mut dists: Vec<f64> = rotated
        .iter()
        .map(|c| (c.center().as_dvec3() - center).length())
        .collect();
    dists.sort_by(f64::total_cmp);
    let median = dists[dists.len() / 2];
    let scale = if median > 1e-9 {
        CAMERA_DISTANCE / median
    } else {
        1.0
    };
    let world = |p: DVec3| (rot * p - center) * scale;
    let normalise = |m: &DMat4| -> DMat4 {
        let r = rot * DMat3::from_mat4(*m);
        let c = world(m.w_axis.truncate());
        DMat4::from_cols(
            r.x_axis.extend(0.0),
            r.y_axis.extend(0.0),
            r.z_axis.extend(0.0),
            c.extend(1.0),
        )
    };
    let poses: BTreeMap<usize, DMat4> = poses.iter().map(|(&k, m)| (k, normalise(m))).collect();

    // 5. Near / far from the depths of the observed points.
    let mut bounds: BTreeMap<usize, (f64, f64)> = BTreeMap::new();
    let mut all_depths = Vec::new();
    for (&k, ims) in &groups {
        let pose = poses[&k];
        let inv = pose.inverse();
        let mut depths: Vec<f64> = ims
            .iter()
            .flat_map(|&i| model.images[i].point_ids.iter())
            .filter_map(|id| model.points.get(id))
            .map(|p| -(inv.transform_point3(world(p.position))).z)
            .filter(|d| *d > 0.0 && d.is_finite())
            .collect();
        depths.sort_by(f64::total_cmp);
        all_depths.extend_from_slice(&depths);
        if !depths.is_empty() {
            bounds.insert(
                k,
                (
                    percentile(&depths, 0.01) * 0.9,
                    percentile(&depths, 0.99) * 1.1,
                ),
            );
        }
    }
    all_depths.sort_by(f64::total_cmp);
    let (near, far) = if all_depths.is_empty() {
        (0.1 * CAMERA_DISTANCE, 4.0 * CAMERA_DISTANCE)
    } else {
        (
            percentile(&all_depths, 0.01) * 0.9,
            percentile(&all_depths, 0.99) * 1.1,
        )
    };

    // 6. transforms.json (+ poses_bounds.npy for distortion-free rigs).
    let intrinsics_of = |k: usize| -> Intrinsics {
        let im = &model.images[groups[&k][0]];
        model.cameras[&im.camera_id].intrinsics()
    };
    let intr_json = |k: &Intrinsics, w: u32, h: u32| {
        json!({"fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": w, "h": h,
               "k1": k.k1, "k2": k.k2, "p1": k.p1, "p2": k.p2})
    };
    let denom = (steps.max(2) - 1) as f64;
    let mut json_frames = Vec::new();
    let mut per_camera = Vec::new();
    let mut dropped_frames = 0;
    let key_of = |fi: usize| match layout {
        Layout::Rig => frames[fi].video,
        Layout::Monocular => fi,
    };
    for (fi, f) in frames.iter().enumerate() {
        let key = key_of(fi);
        let Some(pose) = poses.get(&key) else {
            dropped_frames += 1;
            continue;
        };
        let info = &infos[f.video];
        let mut fr = json!({
            "file_path": f.rel,
            "transform_matrix": pose.transpose().to_cols_array_2d(),
            "time": if steps > 1 { f.time as f64 / denom } else { 0.0 },
        });
        if layout == Layout::Rig {
            fr["camera_id"] = json!(f.video);
        }
        if !(shared || layout == Layout::Monocular) {
            if let (Value::Object(a), Value::Object(b)) = (
                &mut fr,
                intr_json(&intrinsics_of(key), info.width, info.height),
            ) {
                a.extend(b);
            }
        }
        json_frames.push(fr);
    }
    // Frames of unregistered cameras / images are not part of the dataset.
    for (fi, f) in frames.iter().enumerate() {
        if !poses.contains_key(&key_of(fi)) {
            let _ = std::fs::remove_file(dir.join(&f.rel));
        }
    }
    let mut root = json!({"camera_model": "OPENCV", "frames": json_frames});
    if shared || layout == Layout::Monocular {
        let first = *groups.keys().next().unwrap_or(&0);
        let vi = match layout {
            Layout::Rig => first,
            Layout::Monocular => 0,
        };
        if let (Value::Object(a), Value::Object(b)) = (
            &mut root,
            intr_json(&intrinsics_of(first), infos[vi].width, infos[vi].height),
        ) {
            a.extend(b);
        }
    }
    write_json(&dir.join("transforms.json"), &root)?;
    let pinhole = matches!(
        opts.camera_model,
        CameraModel::Pinhole | CameraModel::SimplePinhole
    );
    if layout == Layout::Rig && pinhole {
        let cams: Vec<(Camera, f64, f64)> = poses
            .iter()
            .map(|(&k, pose)| {
                let ki = intrinsics_of(k);
                let mut c = camera_of(pose);
                c.width = infos[k].width;
                c.height = infos[k].height;
                c.fx = ki.fx as f32;
                c.fy = ki.fy as f32;
                c.cx = ki.cx as f32;
                c.cy = ki.cy as f32;
                let (n, f) = bounds.get(&k).copied().unwrap_or((near, far));
                (c, n, f)
            })
            .collect();
        let p = dir.join("poses_bounds.npy");
        dynerf::write_poses_bounds(&p, &cams).map_err(io(&p))?;
    }
    for (&k, pose) in &poses {
        let ki = intrinsics_of(k);
        let (n, f) = bounds.get(&k).copied().unwrap_or((near, far));
        per_camera.push(json!({
            "name": match layout { Layout::Rig => format!("cam{k:02}"), Layout::Monocular => frames[k].rel.clone() },
            "images_registered": groups[&k].len(),
            "center": pose.w_axis.truncate().to_array(),
            "near": n, "far": f,
            "fx": ki.fx, "fy": ki.fy, "cx": ki.cx, "cy": ki.cy,
            "k1": ki.k1, "k2": ki.k2, "p1": ki.p1, "p2": ki.p2,
        }));
    }
    let report = ImportReport {
        layout: match layout {
            Layout::Rig => "rig".into(),
            Layout::Monocular => "monocular".into(),
        },
        cameras_total: total,
        cameras_registered: groups.len(),
        images_total: colmap_names.len(),
        images_registered: model
            .images
            .iter()
            .filter(|i| colmap_names.contains_key(&i.name))
            .count(),
        points: model.points.len(),
        mean_reprojection_error_px: model.mean_reprojection_error_px(),
        colmap_models: rec.num_models,
        colmap_runs: rec.trials.clone(),
        colmap_seed: rec.trials.get(rec.chosen).map_or(0, |t| t.seed),
        colmap_seconds: rec.wall.as_secs_f64(),
        decode_seconds,
        time_steps: steps,
        frames_written: frames.len() - dropped_frames,
        unregistered,
        scale,
        near,
        far,
    };
    let mut summary = serde_json::to_value(&report).unwrap_or(Value::Null);
    summary["videos"] = json!(videos
        .iter()
        .zip(offsets)
        .map(|(v, o)| json!({"path": v.display().to_string(), "offset_frames": o}))
        .collect::<Vec<_>>());
    summary["cameras"] = Value::Array(per_camera);
    summary["normalisation"] = json!({
        "note": "dataset = scale * (rotation * colmap - center); rotation takes the mean camera up to +Z",
        "rotation_row_major": rot.transpose().to_cols_array_2d(),
        "center": center.to_array(),
        "scale": scale,
    });
    write_json(&dir.join("import.json"), &summary)?;
    // The COLMAP image links are only needed while it runs.
    let _ = std::fs::remove_dir_all(&images);
    Ok(report)
}

fn write_json(path: &Path, v: &Value) -> Result<(), ImportError> {
    let bytes = serde_json::to_vec_pretty(v).map_err(|e| ImportError::Invalid(e.to_string()))?;
    std::fs::write(path, bytes).map_err(io(path))
}

/// `sorted[q * (n - 1)]` (nearest rank).
fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// The mean of camera-to-world poses: mean centre and the chordal mean rotation (sign-aligned
/// quaternions averaged and normalised).
pub fn average_pose(poses: &[DMat4]) -> DMat4 {
    let rotations: Vec<DQuat> = poses.iter().map(DQuat::from_mat4).collect();
    let c = poses.iter().map(|p| p.w_axis.truncate()).sum::<DVec3>();
    let mut m = DMat4::from_quat(mean_rotation(&rotations));
    m.w_axis = (c / poses.len() as f64).extend(1.0);
    m
}

fn camera_of(pose: &DMat4) -> Camera {
    Camera {
        width: 1,
        height: 1,
        fx: 1.0,
        fy: 1.0,
        cx: 0.5,
        cy: 0.5,
        world_from_camera: Mat4::from_cols_array(&pose.to_cols_array().map(|v| v as f32)),
    }
}

/// A similarity transform `y = scale * rotation * x + translation`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity3 {
    pub scale: f64,
    pub rotation: DMat3,
    pub translation: DVec3,
}

impl Similarity3 {
    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.scale * (self.rotation * p) + self.translation
    }
}

/// The least-squares similarity taking `from[i]` to `to[i]` (Umeyama's scale with Horn's
/// closed-form rotation: the top eigenvector of a 4x4 symmetric matrix, by Jacobi rotations).
/// `None` with fewer than 3 pairs or all `from` points equal.
pub fn fit_similarity(from: &[DVec3], to: &[DVec3]) -> Option<Similarity3> {
    let n = from.len();
    if n < 3 || to.len() != n {
        return None;
    }
    let ma = from.iter().sum::<DVec3>() / n as f64;
    let mb = to.iter().sum::<DVec3>() / n as f64;
    let mut s = [[0.0f64; 3]; 3]; // s[i][j] = sum a_i b_j
    let mut var_a = 0.0;
    for (a, b) in from.iter().zip(to) {
        let (a, b) = (*a - ma, *b - mb);
        var_a += a.length_squared();
        let (aa, bb) = (a.to_array(), b.to_array());
        for i in 0..3 {
            for j in 0..3 {
                s[i][j] += aa[i] * bb[j];
            }
        }
    }
    if var_a < 1e-18 {
        return None;
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let mut m = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (vals, vecs) = jacobi4(&mut m);
    let k = (0..4).max_by(|&i, &j| vals[i].total_cmp(&vals[j]))?;
    let q = DQuat::from_xyzw(vecs[1][k], vecs[2][k], vecs[3][k], vecs[0][k]).normalize();
    let rotation = DMat3::from_quat(q);
    let mut num = 0.0;
    for (a, b) in from.iter().zip(to) {
        num += (*b - mb).dot(rotation * (*a - ma));
    }
    let scale = num / var_a;
    Some(Similarity3 {
        scale,
        rotation,
        translation: mb - scale * (rotation * ma),
    })
}

/// Eigenvalues and eigenvectors (columns of the second result) of a symmetric 4x4 matrix.
fn jacobi4(a: &mut [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..100 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).map(move |j| (i, j)))
            .filter(|(i, j)| i != j)
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        if off < 1e-30 {
            break;
        }
        for p in 0..4 {
            for q in p + 1..4 {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let sign = if theta >= 0.0 { 1.0 } else { -1.0 };
                let t = sign / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..4 {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..4 {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for k in 0..4 {
                    let (vkp, vkq) = (v[k][p], v[k][q]);
                    v[k][p] = c * vkp - s * vkq;
                    v[k][q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2], a[3][3]], v)
}

/// The angle in degrees of the rotation taking `a` to `b`.
pub fn rotation_angle_deg(a: DMat3, b: DMat3) -> f64 {
    let r = a.transpose() * b;
    let cos = ((r.x_axis.x + r.y_axis.y + r.z_axis.z - 1.0) * 0.5).clamp(-1.0, 1.0);
    cos.acos().to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn similarity_fit_recovers_a_known_transform() {
        let truth = Similarity3 {
            scale: 2.5,
            rotation: DMat3::from_quat(DQuat::from_axis_angle(
                DVec3::new(1.0, -2.0, 0.5).normalize(),
                2.1,
            )),
            translation: DVec3::new(3.0, -1.0, 7.0),
        };
        let from: Vec<DVec3> = (0..9)
            .map(|i| {
                let a = i as f64 * 0.7;
                DVec3::new(a.cos() * 4.0, a.sin() * 3.0, (i % 3) as f64)
            })
            .collect();
        let to: Vec<DVec3> = from.iter().map(|&p| truth.apply(p)).collect();
        let fit = fit_similarity(&from, &to).unwrap();
        assert!((fit.scale - 2.5).abs() < 1e-9, "{fit:?}");
        assert!(rotation_angle_deg(fit.rotation, truth.rotation) < 1e-6);
        assert!((fit.translation - truth.translation).length() < 1e-8);
        // Degenerate input.
        assert!(fit_similarity(&from[..2], &to[..2]).is_none());
        assert!(fit_similarity(&[DVec3::ONE; 4], &to[..4]).is_none());
    }

    #[test]
    fn pose_average_of_nearby_poses() {
        let a = DMat4::from_rotation_translation(
            DQuat::from_rotation_z(0.1),
            DVec3::new(1.0, 0.0, 0.0),
        );
        let b = DMat4::from_rotation_translation(
            DQuat::from_rotation_z(0.3),
            DVec3::new(3.0, 0.0, 0.0),
        );
        let m = average_pose(&[a, b]);
        let want = DMat3::from_quat(DQuat::from_rotation_z(0.2));
        assert!(rotation_angle_deg(DMat3::from_mat4(m), want) < 1e-9);
        assert!((m.w_axis.truncate() - DVec3::new(2.0, 0.0, 0.0)).length() < 1e-12);
    }

    #[test]
    fn bad_arguments_are_refused_before_any_work() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let v = vec![dir.path().join("a.mp4"), dir.path().join("b.mp4")];
        let mut p = |_: &str| {};
        let opts = ImportOptions {
            layout: Some(Layout::Monocular),
            ..Default::default()
        };
        let e = import(&v, &out, &opts, &mut p).unwrap_err().to_string();
        assert!(e.contains("monocular layout takes one video, got 2"), "{e}");
        let opts = ImportOptions {
            offsets: vec![1, 2, 3],
            ..Default::default()
        };
        let e = import(&v, &out, &opts, &mut p).unwrap_err().to_string();
        assert!(e.contains("3 offsets for 2 videos"), "{e}");
        let e = import(&[], &out, &Default::default(), &mut p)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no videos"), "{e}");
        let opts = ImportOptions {
            colmap: Colmap {
                program: "/nonexistent/colmap".into(),
            },
            ..Default::default()
        };
        let e = import(&v, &out, &opts, &mut p).unwrap_err().to_string();
        assert!(e.contains("apt-get install colmap"), "{e}");
        assert!(!out.exists());
        let e = videos_in(dir.path()).unwrap_err().to_string();
        assert!(e.contains("no videos"), "{e}");
    }
}
