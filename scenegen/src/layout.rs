//! The two dataset layouts and their writers.
//!
//! - **Object** (D-NeRF style): the model alone, normalised into the unit sphere at the origin,
//!   one image per time step from a new random camera on the upper hemisphere (distance
//!   [`OBJECT_CAMERA_DISTANCE`], D-NeRF's field of view), RGBA with straight alpha over a
//!   transparent background, plus held-out views at random times. Written with
//!   `msth_dataset::dnerf::write` (train / test / val JSON), after which the PNGs are
//!   replaced by their RGBA versions.
//! - **Stage** (DyNeRF style): the model (radius [`STAGE_MODEL_RADIUS`], standing on the floor)
//!   in the [`crate::stage`] set, filmed by a forward-facing arc of fixed cameras at every time
//!   step, `cam00` in the middle of the arc held out. Written as `camNN/TTTT.png`,
//!   `camNN.mp4`, `poses_bounds.npy` (row `i` = `camNN`, row 0 = the held-out camera),
//!   `poses_bounds_train.npy`, `cameras.json` and `transforms_{train,val,test}.json` pointing at
//!   the same frames, following `shared/data/box_animated_stage/README.md`.
//!
//! Time: `t = frame / (frames - 1)` maps linearly onto the animation's full keyframe range.
//! World: +Z up (glTF +Y up is rotated as Blender's importer does). Both layouts write
//! `render_meta.json` with the settings, the normalisation and the notes. Output goes to a
//! staging folder next to `out` that is renamed at the end: a failure leaves nothing behind.

use std::path::{Path, PathBuf};
use std::time::Instant;

use glam::{Mat4, Vec3};
use msth_core::{Camera, SceneBounds};
use msth_dataset::staging::{StagingDir, StagingError};
use msth_dataset::{dnerf, imageio, Dataset, View};
use rayon::prelude::*;
use serde_json::{json, Value};

use crate::dynerf;
use crate::error::{Result, SceneGenError};
use crate::model::Model;
use crate::scene::{self, Lighting, Normalisation, Placement, RenderOptions, RgbaImage8, Scene};
use crate::stage;
use crate::texture::srgb;

/// D-NeRF's horizontal field of view (radians).
pub const OBJECT_FOV_X: f32 = 0.691_111_2;
/// Distance of the object layout's cameras from the origin.
pub const OBJECT_CAMERA_DISTANCE: f32 = 4.0311;
/// Radius the object layout fits the model into.
pub const OBJECT_MODEL_RADIUS: f32 = 1.0;
/// Radius the stage layout fits the model into.
pub const STAGE_MODEL_RADIUS: f32 = 1.25;
/// Point the stage cameras look at.
pub const STAGE_LOOK_AT: Vec3 = Vec3::new(0.0, 0.3, 0.9);
/// Horizontal distance of the stage cameras from [`STAGE_LOOK_AT`].
pub const STAGE_ARC_RADIUS: f32 = 4.6;
/// Azimuth span of the training arc (degrees).
pub const STAGE_ARC_DEG: f32 = 70.0;
/// Heights of the lower / upper training cameras and of the held-out camera.
pub const STAGE_HEIGHTS: [f32; 3] = [1.25, 1.85, 1.55];
/// Horizontal field of view of the stage cameras (radians).
pub const STAGE_FOV_X: f32 = 0.95;
/// Largest number of pixels a dataset may hold.
pub const MAX_TOTAL_PIXELS: u64 = 2_000_000_000;

/// A camera and the normalised time it films.
pub type TimedCamera = (Camera, f32);

/// Which dataset layout to write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    Object,
    Stage,
}

/// Settings of a generated dataset.
#[derive(Clone, Debug, PartialEq)]
pub struct SynthSettings {
    pub layout: Layout,
    pub width: u32,
    pub height: u32,
    /// Time steps (object: training images; stage: frames per camera), at most 10000.
    pub frames: usize,
    /// Stage: training cameras on the arc (the held-out `cam00` comes on top). Object: number
    /// of held-out test views (at random times and cameras).
    pub cameras: usize,
    /// Samples per pixel along each axis.
    pub supersample: u32,
    pub seed: u64,
    /// Frame rate of the stage videos.
    pub fps: u32,
    /// The ffmpeg program for the stage videos; `None` skips the videos.
    pub ffmpeg: Option<PathBuf>,
}

impl SynthSettings {
    /// The defaults of a layout: object 200x200, 100 frames, 20 test views; stage 200x150,
    /// 30 frames, 8 training cameras. Both 6x6 supersampling (`scene::sample_pattern`), 30 fps,
    /// `ffmpeg` from `PATH`.
    pub fn new(layout: Layout) -> Self {
        let (width, height, frames, cameras) = match layout {
            Layout::Object => (200, 200, 100, 20),
            Layout::Stage => (200, 150, 30, 8),
        };
        SynthSettings {
            layout,
            width,
            height,
            frames,
            cameras,
            supersample: 6,
            seed: 0,
            fps: 30,
            ffmpeg: Some(PathBuf::from("ffmpeg")),
        }
    }

    /// Number of images the settings render.
    pub fn total_images(&self) -> usize {
        match self.layout {
            Layout::Object => self.frames + self.cameras,
            Layout::Stage => self.frames * (self.cameras + 1),
        }
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(SceneGenError::Settings(m));
        if self.width == 0 || self.height == 0 || self.width > 16384 || self.height > 16384 {
            return bad(format!(
                "image size {}x{} must be 1..=16384 per side",
                self.width, self.height
            ));
        }
        if self.frames == 0 || self.frames > 10000 {
            return bad(format!("frames = {} must be 1..=10000", self.frames));
        }
        if self.cameras == 0 || self.cameras > 99 {
            return bad(format!("cameras = {} must be 1..=99", self.cameras));
        }
        if self.supersample == 0 || self.supersample > 16 {
            return bad(format!("supersample = {} must be 1..=16", self.supersample));
        }
        if self.fps == 0 {
            return bad("fps must be at least 1".into());
        }
        let pixels = self.width as u64 * self.height as u64 * self.total_images() as u64;
        if pixels > MAX_TOTAL_PIXELS {
            return bad(format!(
                "{pixels} pixels is more than the limit of {MAX_TOTAL_PIXELS}"
            ));
        }
        Ok(())
    }
}

/// What [`generate`] did.
#[derive(Clone, Debug)]
pub struct Summary {
    pub images: usize,
    pub render_secs: f64,
    /// `None` when videos were written (or the layout has none), else why not.
    pub videos_skipped: Option<String>,
    pub notes: Vec<String>,
}

/// Normalised time of frame `j` of `n`.
pub fn frame_time(j: usize, n: usize) -> f32 {
    if n <= 1 {
        0.0
    } else {
        j as f32 / (n - 1) as f32
    }
}

/// SplitMix64 stream for camera placement.
struct Rng(u64);

impl Rng {
    fn next_f32(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A random camera on the upper hemisphere (uniform in area for height/radius in
/// [0.05, 0.95]) looking at the origin.
fn hemisphere_camera(rng: &mut Rng, width: u32, height: u32) -> Camera {
    let z = 0.05 + 0.9 * rng.next_f32();
    let phi = std::f32::consts::TAU * rng.next_f32();
    let s = (1.0 - z * z).sqrt();
    let eye = Vec3::new(s * phi.cos(), s * phi.sin(), z) * OBJECT_CAMERA_DISTANCE;
    Camera::look_at(width, height, OBJECT_FOV_X, eye, Vec3::ZERO, Vec3::Z)
}

/// The object layout's views: `(camera, time)` for training (one per frame) and test.
pub fn object_views(s: &SynthSettings) -> (Vec<TimedCamera>, Vec<TimedCamera>) {
    let mut rng = Rng(s.seed ^ 0x000B_1EC7);
    let train = (0..s.frames)
        .map(|j| {
            (
                hemisphere_camera(&mut rng, s.width, s.height),
                frame_time(j, s.frames),
            )
        })
        .collect();
    let test = (0..s.cameras)
        .map(|_| {
            let c = hemisphere_camera(&mut rng, s.width, s.height);
            (c, rng.next_f32())
        })
        .collect();
    (train, test)
}

/// The stage cameras: index 0 = `cam00`, the held-out camera at the middle of the arc
/// (azimuth 0, middle height); then `n_train` cameras with azimuths evenly spread over
/// [`STAGE_ARC_DEG`] (left to right), alternating lower / upper heights. Azimuth 0 looks along
/// +Y from -Y. Returns the cameras and their azimuths in degrees.
pub fn stage_cameras(n_train: usize, width: u32, height: u32) -> Vec<(Camera, f32)> {
    let mut out = Vec::with_capacity(n_train + 1);
    let make = |az_deg: f32, h: f32| {
        let a = az_deg.to_radians();
        let eye = STAGE_LOOK_AT + Vec3::new(a.sin(), -a.cos(), 0.0) * STAGE_ARC_RADIUS;
        let eye = Vec3::new(eye.x, eye.y, h);
        Camera::look_at(width, height, STAGE_FOV_X, eye, STAGE_LOOK_AT, Vec3::Z)
    };
    out.push((make(0.0, STAGE_HEIGHTS[2]), 0.0));
    for i in 0..n_train {
        let az = if n_train == 1 {
            0.0
        } else {
            -0.5 * STAGE_ARC_DEG + STAGE_ARC_DEG * i as f32 / (n_train - 1) as f32
        };
        out.push((make(az, STAGE_HEIGHTS[i % 2]), az));
    }
    out
}

fn object_scene(model: &Model, norm: &Normalisation, t: f32) -> Scene {
    let time_secs = model.animation.as_ref().map_or(0.0, |a| a.time_secs(t));
    Scene {
        triangles: scene::posed_triangles(model, time_secs, norm.root_transform, 0),
        materials: scene::model_materials(model),
        lighting: Lighting::default(),
        background: None,
    }
}

/// Linear colour of the stage's background (seen over the walls).
fn stage_sky() -> Vec3 {
    srgb(0.72, 0.80, 0.88)
}

fn stage_scene(model: &Model, norm: &Normalisation, set: &stage::StageSet, t: f32) -> Scene {
    let time_secs = model.animation.as_ref().map_or(0.0, |a| a.time_secs(t));
    let mut triangles = scene::posed_triangles(model, time_secs, norm.root_transform, 0);
    triangles.extend(set.triangles.iter().cloned());
    let mut materials = scene::model_materials(model);
    materials.extend(set.materials.iter().cloned());
    Scene {
        triangles,
        materials,
        lighting: Lighting::default(),
        background: Some(stage_sky()),
    }
}

fn io<T>(path: &Path, r: std::io::Result<T>) -> Result<T> {
    r.map_err(SceneGenError::io(path))
}

fn write_json(path: &Path, v: &Value) -> Result<()> {
    let mut bytes = serde_json::to_vec_pretty(v).expect("JSON values serialise");
    bytes.push(b'\n');
    io(path, std::fs::write(path, bytes))
}

fn mat_rows(m: &Mat4) -> Value {
    json!(m.transpose().to_cols_array_2d())
}

fn write_rgba_png(path: &Path, img: &RgbaImage8) -> Result<()> {
    let out = image::RgbaImage::from_raw(img.width, img.height, img.data.clone())
        .expect("buffer size matches");
    out.save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| SceneGenError::Io {
            path: path.to_path_buf(),
            error: std::io::Error::other(e.to_string()),
        })
}

/// A staging folder next to `out` ([`StagingDir`]), with the generator's messages.
fn staging(out: &Path) -> Result<StagingDir> {
    StagingDir::new(out).map_err(|e| match e {
        StagingError::NotEmpty(_) => SceneGenError::Settings(format!(
            "{}: exists and is not an empty folder; refusing to write a dataset there",
            out.display()
        )),
        StagingError::NotAFolderName(_) => {
            SceneGenError::Settings(format!("{}: not a folder name", out.display()))
        }
        StagingError::Io { path, source } => SceneGenError::Io {
            path,
            error: source,
        },
    })
}

fn commit(staging: StagingDir) -> Result<()> {
    staging.commit().map_err(|e| match e {
        StagingError::Io { path, source } => SceneGenError::Io {
            path,
            error: source,
        },
        e => SceneGenError::Settings(e.to_string()),
    })
}

fn meta_common(model: &Model, s: &SynthSettings, norm: &Normalisation, kind: &str) -> Value {
    let (start, end, channels) = match &model.animation {
        Some(a) => (a.start, a.end, a.channels.len()),
        None => (0.0, 0.0, 0),
    };
    json!({
        "generator": "msth synth --gltf (msth-scenegen rasteriser)",
        "source": model.source.display().to_string(),
        "kind": kind,
        "time": {
            "definition": "time = frame / (frames - 1) over the animation's keyframe range",
            "animation_start_secs": start,
            "animation_end_secs": end,
            "channels": channels,
        },
        "world": "+Z up (glTF +Y up mapped by (x, y, z) -> (x, -z, y)); transform_matrix = camera-to-world, OpenGL camera axes (-Z forward, +Y up, +X right)",
        "normalisation": {
            "scale": norm.scale,
            "translation": norm.translation.to_array(),
            "bbox_min": norm.bbox_min.to_array(),
            "bbox_max": norm.bbox_max.to_array(),
        },
        "render": {
            "width": s.width,
            "height": s.height,
            "supersample": s.supersample,
            "pixel_samples": "supersample^2 per pixel, one per cell of the supersample grid with distinct positions along each axis (multi-jittered canonical arrangement), averaged in linear light",
            "shading": "Lambert: one directional light + hemispheric ambient, no shadows; sRGB output",
            "seed": s.seed,
        },
        "notes": model.notes,
    })
}

/// Renders and writes the dataset of `settings.layout` for `model` into `out` (which must not
/// exist or be empty). `progress` is called once per finished image, from worker threads.
pub fn generate(
    model: &Model,
    settings: &SynthSettings,
    out: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<Summary> {
    settings.validate()?;
    if scene::posed_triangles(model, 0.0, Mat4::IDENTITY, 0).is_empty() {
        return Err(SceneGenError::Invalid {
            path: model.source.clone(),
            what: "scene".into(),
            message: "the displayed scene holds no triangles (no mesh under its root nodes)".into(),
        });
    }
    match settings.layout {
        Layout::Object => generate_object(model, settings, out, progress),
        Layout::Stage => generate_stage(model, settings, out, progress),
    }
}

fn generate_object(
    model: &Model,
    s: &SynthSettings,
    out: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<Summary> {
    let norm = Normalisation::fit(model, OBJECT_MODEL_RADIUS, Placement::Centred, 97);
    let (train, test) = object_views(s);
    let opts = RenderOptions {
        supersample: s.supersample,
        ..RenderOptions::default()
    };
    let started = Instant::now();
    let render_all = |views: &[(Camera, f32)]| -> Vec<RgbaImage8> {
        views
            .par_iter()
            .map(|(cam, t)| {
                let img = scene::render(&object_scene(model, &norm, *t), cam, &opts);
                progress();
                img
            })
            .collect()
    };
    let train_rgba = render_all(&train);
    let test_rgba = render_all(&test);
    let render_secs = started.elapsed().as_secs_f64();
    let to_views = |views: &[(Camera, f32)], imgs: &[RgbaImage8], split: &str| -> Vec<View> {
        views
            .iter()
            .zip(imgs)
            .enumerate()
            .map(|(i, ((cam, t), img))| {
                let (image, alpha) = img.composite_on_white();
                View {
                    camera: *cam,
                    time: *t,
                    image,
                    source: PathBuf::from(format!("{split}/{i}")),
                    camera_id: None,
                    alpha,
                }
            })
            .collect()
    };
    let dataset = Dataset {
        name: model
            .source
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default(),
        train: to_views(&train, &train_rgba, "train"),
        test: to_views(&test, &test_rgba, "test"),
        bounds: SceneBounds::dnerf_default(),
        background: [1.0, 1.0, 1.0],
        num_frames: s.frames,
        near: None,
    };
    let staging = staging(out)?;
    dnerf::write(&dataset, staging.path())?;
    // dnerf::write stores RGB composited on white; replace each image by its RGBA original,
    // found through the file paths of the transforms files (same order as the views).
    for (json_name, imgs) in [
        ("transforms_train.json", &train_rgba),
        ("transforms_test.json", &test_rgba),
    ] {
        let json_path = staging.path().join(json_name);
        let text = io(&json_path, std::fs::read_to_string(&json_path))?;
        let v: Value = serde_json::from_str(&text).map_err(|e| SceneGenError::Format {
            path: json_path.clone(),
            message: e.to_string(),
        })?;
        let frames = v["frames"].as_array().cloned().unwrap_or_default();
        if frames.len() != imgs.len() {
            return Err(SceneGenError::Settings(format!(
                "{}: {} frames written for {} images",
                json_path.display(),
                frames.len(),
                imgs.len()
            )));
        }
        frames
            .par_iter()
            .zip(imgs.par_iter())
            .map(|(f, img)| {
                let rel = f["file_path"].as_str().unwrap_or_default();
                let mut path = staging.path().join(rel.trim_start_matches("./"));
                if path.extension().is_none() {
                    path.set_extension("png");
                }
                write_rgba_png(&path, img)
            })
            .collect::<Result<Vec<()>>>()?;
    }
    let mut meta = meta_common(model, s, &norm, "object");
    meta["cameras"] = json!({
        "layout": "random on the upper hemisphere (z/r uniform in [0.05, 0.95]) looking at the origin, +Z up",
        "distance": OBJECT_CAMERA_DISTANCE,
        "camera_angle_x": OBJECT_FOV_X,
        "model_radius": OBJECT_MODEL_RADIUS,
    });
    meta["images"] = json!("RGBA PNG, straight alpha, transparent background (composite on white)");
    meta["counts"] =
        json!({"train": train.len(), "test": test.len(), "val": test.len().div_ceil(3)});
    meta["render_seconds"] = json!(render_secs);
    write_json(&staging.path().join("render_meta.json"), &meta)?;
    commit(staging)?;
    Ok(Summary {
        images: train.len() + test.len(),
        render_secs,
        videos_skipped: None,
        notes: model.notes.clone(),
    })
}

/// Near / far along the viewing axis for each camera: the 0.1st and 99.9th percentiles of the
/// depths seen at a 40-pixel-wide resolution at 5 times, times 0.9 / 1.1.
fn near_far(scenes_at: &dyn Fn(f32) -> Scene, cameras: &[(Camera, f32)]) -> Vec<(f64, f64)> {
    let probes: Vec<Scene> = (0..5).map(|k| scenes_at(k as f32 / 4.0)).collect();
    cameras
        .par_iter()
        .map(|(cam, _)| {
            let small = cam.scaled(40.0 / cam.width as f32);
            let mut d: Vec<f32> = probes
                .iter()
                .flat_map(|sc| scene::depths(sc, &small, 0.05))
                .collect();
            if d.is_empty() {
                return (0.1, 100.0);
            }
            d.sort_by(f32::total_cmp);
            let pick = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize] as f64;
            (pick(0.001) * 0.9, pick(0.999) * 1.1)
        })
        .collect()
}

fn generate_stage(
    model: &Model,
    s: &SynthSettings,
    out: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<Summary> {
    let norm = Normalisation::fit(model, STAGE_MODEL_RADIUS, Placement::OnFloor, 97);
    let set = stage::build(model.materials.len() as u32 + 1, s.seed);
    let cameras = stage_cameras(s.cameras, s.width, s.height);
    let times: Vec<f32> = (0..s.frames).map(|j| frame_time(j, s.frames)).collect();
    let opts = RenderOptions {
        supersample: s.supersample,
        ..RenderOptions::default()
    };
    let staging = staging(out)?;
    for c in 0..cameras.len() {
        let d = staging.path().join(format!("cam{c:02}"));
        io(&d, std::fs::create_dir(&d))?;
    }
    let started = Instant::now();
    let scenes: Vec<Scene> = times
        .par_iter()
        .map(|&t| stage_scene(model, &norm, &set, t))
        .collect();
    let jobs: Vec<(usize, usize)> = (0..s.frames)
        .flat_map(|j| (0..cameras.len()).map(move |c| (j, c)))
        .collect();
    jobs.par_iter()
        .map(|&(j, c)| {
            let img = scene::render(&scenes[j], &cameras[c].0, &opts);
            let (rgb, _) = img.composite_on_white();
            let path = staging.path().join(format!("cam{c:02}/{j:04}.png"));
            let file = io(&path, std::fs::File::create(&path))?;
            imageio::encode_png(std::io::BufWriter::new(file), &rgb)
                .map_err(SceneGenError::io(&path))?;
            progress();
            Ok(())
        })
        .collect::<Result<Vec<()>>>()?;
    let render_secs = started.elapsed().as_secs_f64();
    drop(scenes);

    let bounds = near_far(&|t| stage_scene(model, &norm, &set, t), &cameras);
    let name = |c: usize| format!("cam{c:02}");
    // poses_bounds.npy: every camera, row i = camNN; poses_bounds_train.npy: rows 1..
    let rows: Vec<[f64; 17]> = cameras
        .iter()
        .zip(&bounds)
        .map(|((cam, _), &(n, f))| dynerf::llff_row(cam, n, f))
        .collect();
    dynerf::write_npy(&staging.path().join("poses_bounds.npy"), &rows)?;
    dynerf::write_npy(&staging.path().join("poses_bounds_train.npy"), &rows[1..])?;

    // transforms_{train,val,test}.json pointing at the frame folders.
    let frame = |c: usize, j: usize| {
        json!({
            "file_path": format!("./{}/{j:04}", name(c)),
            "time": times[j],
            "transform_matrix": mat_rows(&cameras[c].0.world_from_camera),
        })
    };
    let train_frames: Vec<Value> = (1..cameras.len())
        .flat_map(|c| (0..s.frames).map(move |j| (c, j)))
        .map(|(c, j)| frame(c, j))
        .collect();
    let test_frames: Vec<Value> = (0..s.frames).map(|j| frame(0, j)).collect();
    let val_frames: Vec<Value> = (0..s.frames).step_by(3).map(|j| frame(0, j)).collect();
    for (file, frames) in [
        ("transforms_train.json", train_frames),
        ("transforms_test.json", test_frames),
        ("transforms_val.json", val_frames),
    ] {
        write_json(
            &staging.path().join(file),
            &json!({"camera_angle_x": STAGE_FOV_X, "frames": frames}),
        )?;
    }
    let cams_json: Vec<Value> = cameras
        .iter()
        .zip(&bounds)
        .enumerate()
        .map(|(c, ((cam, az), &(n, f)))| {
            json!({
                "name": name(c),
                "role": if c == 0 { "test" } else { "train" },
                "azimuth_deg": az,
                "transform_matrix": mat_rows(&cam.world_from_camera),
                "camera_angle_x": STAGE_FOV_X,
                "w": cam.width, "h": cam.height,
                "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy,
                "near": n, "far": f,
            })
        })
        .collect();
    write_json(
        &staging.path().join("cameras.json"),
        &json!({
            "convention": "transform_matrix = camera-to-world, OpenGL/Blender camera axes (-Z forward, +Y up, +X right); world +Z up",
            "look_at": STAGE_LOOK_AT.to_array(),
            "n_frames": s.frames,
            "times": times,
            "cameras": cams_json,
        }),
    )?;

    // Videos.
    let videos_skipped = match &s.ffmpeg {
        None => Some("videos not requested".to_string()),
        Some(ff) if !dynerf::ffmpeg_available(ff) => Some(format!(
            "`{}` is not installed or does not run; camNN.mp4 not written (the PNG frames are complete)",
            ff.display()
        )),
        Some(ff) => {
            (0..cameras.len())
                .into_par_iter()
                .map(|c| {
                    dynerf::encode_video(
                        ff,
                        &staging.path().join(name(c)),
                        &staging.path().join(format!("{}.mp4", name(c))),
                        s.fps,
                    )
                })
                .collect::<Result<Vec<()>>>()?;
            None
        }
    };

    let mut meta = meta_common(model, s, &norm, "stage");
    meta["cameras"] = json!({
        "layout": "forward-facing arc, two staggered heights, held-out camera cam00 in the middle",
        "arc_deg": STAGE_ARC_DEG,
        "radius": STAGE_ARC_RADIUS,
        "heights": STAGE_HEIGHTS,
        "look_at": STAGE_LOOK_AT.to_array(),
        "camera_angle_x": STAGE_FOV_X,
        "n_train_cams": s.cameras,
        "test_cam": "cam00",
        "model_radius": STAGE_MODEL_RADIUS,
        "near_far": "0.1st / 99.9th percentile of rasterised depths (40 px wide, 5 times) x0.9 / x1.1",
    });
    meta["videos"] = match &videos_skipped {
        None => json!(format!(
            "camNN.mp4: H.264 (libx264), yuv420p, CRF 12, {} fps",
            s.fps
        )),
        Some(why) => json!(format!("skipped: {why}")),
    };
    meta["counts"] = json!({
        "train": s.cameras * s.frames,
        "test": s.frames,
        "val": s.frames.div_ceil(3),
        "n_frames": s.frames,
    });
    meta["render_seconds"] = json!(render_secs);
    write_json(&staging.path().join("render_meta.json"), &meta)?;
    commit(staging)?;
    Ok(Summary {
        images: jobs.len(),
        render_secs,
        videos_skipped,
        notes: model.notes.clone(),
    })
}
