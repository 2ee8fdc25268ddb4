//! `msth play URL|FILE`: free-viewpoint playback of a `.msth` file, streamed over HTTP or read
//! locally, through `msth-player`. Prints one line per frame (time, rays re-rendered, render
//! time) and a summary (time to first frame, frames per second full and incremental, bytes
//! fetched); writes PNG frames and an MP4 with `--out`. `https://` URLs are checked against the
//! bundled Mozilla roots, or the certificates of `--ca-cert FILE` / `SSL_CERT_FILE`.

use std::ffi::OsString;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use msth_core::config::PlaySamples;
use msth_player::render::MAX_PARTITION_TIMES;
use msth_player::{
    play, BackendChoice, FrameRecord, HttpOptions, PlayOptions, PlayReport, RenderSettings, Reuse,
};

#[derive(Args)]
pub struct PlayArgs {
    /// An `http://` or `https://` URL (e.g. from `msth serve`) or a local `.msth` file.
    pub source: String,
    /// Camera path: N (file camera N, fixed), view:AZ,EL,DIST (fixed free viewpoint), orbit,
    /// spiral (closed loops: no pose shown twice), cameras (each file camera in turn) or a JSON
    /// file of poses and times.
    #[arg(long, default_value = "0")]
    pub path: String,
    /// Image size WxH (default: the cameras' own).
    #[arg(long, value_parser = parse_size)]
    pub size: Option<(u32, u32)>,
    /// Frames to render (default: the model's frame count).
    #[arg(long)]
    pub frames: Option<usize>,
    /// Normalised time range START:END (END < START plays backwards).
    #[arg(long, default_value = "0:1", value_parser = parse_range)]
    pub time: (f32, f32),
    /// Frame rate of the MP4 (default: the file's, else 30).
    #[arg(long)]
    pub fps: Option<f32>,
    /// Folder for frame_NNNNN.png and video.mp4 (default: render without writing).
    #[arg(long, short)]
    pub out: Option<PathBuf>,
    /// No MP4, PNG frames only.
    #[arg(long)]
    pub no_video: bool,
    /// Render on the CPU even when a GPU adapter exists.
    #[arg(long, conflicts_with = "gpu")]
    pub cpu: bool,
    /// Render on the GPU (any adapter, software ones such as Mesa's lavapipe included); fails
    /// when there is none. Default: the GPU when a hardware adapter exists, else the CPU
    /// (MSTH_GPU_SOFTWARE=1 lets the automatic choice use a software adapter).
    #[arg(long)]
    pub gpu: bool,
    /// Render every frame in full (no static-ray cache).
    #[arg(long)]
    pub no_incremental: bool,
    /// Evaluate every sample, also in the cells the file's occupancy grid marks empty.
    #[arg(long)]
    pub no_skip_empty: bool,
    /// Samples per ray: file (the counts the file stores for playback, which `msth export`
    /// chooses; the model's own when it stores none), full (the model's own), fast (2/3 of the
    /// proposal and 3/4 of the main samples), faster (half of each) or P,M. Fewer samples render
    /// faster and less accurately (docs/tradeoff.md); `msth eval --samples` measures the loss on
    /// held-out views
    #[arg(long, default_value = "file", value_parser = parse_samples)]
    pub samples: PlaySamples,
    /// GPU renderer: f16 or f32 hash tables on the device. Default: f32 for a lossless file
    /// (`--quant f32`), else f16: half the memory, one read per row of two features, a rounding
    /// below the file's quantisation step (docs/playback.md)
    #[arg(long)]
    pub gpu_tables: Option<msth_player::TableFormat>,
    /// A ray is static when the mask is at least this along its visible part.
    #[arg(long, default_value_t = RenderSettings::default().static_threshold)]
    pub static_threshold: f32,
    /// A static ray whose mask is at least this along its visible part is cached without probes;
    /// the probes test only the static rays below it (above 1: probe every static ray).
    #[arg(long, default_value_t = RenderSettings::default().trust_threshold)]
    pub trust_threshold: f32,
    /// Probe renders (times over [0, 1]) that must agree before a ray the mask is unsure of is
    /// cached as static.
    #[arg(long, default_value_t = RenderSettings::default().probes)]
    pub probes: usize,
    /// Largest colour change (0-1 scale) a static ray may show at a probe.
    #[arg(long, default_value_t = RenderSettings::default().probe_tolerance)]
    pub probe_tolerance: f32,
    #[command(flatten)]
    pub reuse: ReuseArgs,
    /// Over HTTP: seconds a request may go without receiving anything before it is given up
    /// and retried (the stall deadline).
    #[arg(
        long,
        visible_alias = "timeout",
        default_value_t = 15.0,
        value_name = "SECS"
    )]
    pub stall_timeout: f64,
    /// Over HTTP: the longest playback waits for data, retries included: for the file's header
    /// and index, then for each section a frame needs.
    #[arg(long, default_value_t = 120.0, value_name = "SECS")]
    pub deadline: f64,
    /// Retries per request.
    #[arg(long, default_value_t = 4)]
    pub retries: u32,
    /// PEM file of the certificates to trust for https:// instead of the bundled Mozilla roots
    /// (a private CA, or a self-signed server's own certificate). Default: $SSL_CERT_FILE when
    /// set, else the bundled roots.
    #[arg(long, value_name = "FILE.pem")]
    pub ca_cert: Option<PathBuf>,
    /// Draw frames from a play-time volume baked from the file when the file opens (CPU and GPU
    /// renderers): fewer operations per sample than the exact field (hash grids and MLPs per
    /// sample, the default and the reference). Its quality depends on the scene and the budget:
    /// held-out PSNR within 0.3 dB of the exact renderer's on the demo model, 0.43 dB below it on
    /// a balanced stage model at the CPU's default budget (0.12 dB above it with
    /// `--volume-resolution 2048 --volume-budget 2200`), several dB below it where the budget
    /// holds only a coarser volume (a software GPU's; docs/playback.md, "The play-time volume");
    /// `msth eval FILE.msth --renderer both` measures a file.
    #[arg(long)]
    pub volume: bool,
    #[command(flatten)]
    pub volume_args: VolumeArgs,
    /// With --volume: wait for the volume's bake before the first frame (else the first frames come from the
    /// exact field while it bakes).
    #[arg(long)]
    pub bake_first: bool,
    /// Write the playback report (per-frame statistics) as JSON.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Print only the summary.
    #[arg(long, short)]
    pub quiet: bool,
}

/// The play-time volume's size (`msth play`, `msth eval FILE.msth`).
#[derive(Args, Clone, Debug, Default)]
pub struct VolumeArgs {
    /// The most memory the play-time volume may take, in MiB (default 512 on the CPU, a quarter
    /// of the GPU's buffer limit on the GPU); a model whose volume would not fit gets a coarser
    /// one, and a note.
    #[arg(long, value_name = "MIB")]
    pub volume_budget: Option<u64>,
    /// Cells per side of the volume at most (default: the model's finest grid resolution; a
    /// power of two from 32 to 2048). Above the model's own it samples the field between the
    /// finest grid's vertices: 2048 on a 1024 model costs about 6x the memory and bake time
    /// and brings its held-out PSNR to the exact renderer's.
    #[arg(long, value_name = "N")]
    pub volume_resolution: Option<u32>,
    /// Cells whose opacity cannot reach this value are left empty, so rays skip them (default
    /// 0: every cell the file's occupancy grid keeps; 0.01 costs the demo model 1 dB held-out).
    #[arg(long, value_name = "ALPHA")]
    pub volume_min_alpha: Option<f32>,
    /// Cells where the proposal network's density cannot reach this opacity are left empty
    /// (default 0.003; 0 keeps them): the exact renderer never samples there.
    #[arg(long, value_name = "ALPHA")]
    pub volume_min_proposal_alpha: Option<f32>,
    /// Step of the march through the volume, in cells (default 1): longer steps read fewer
    /// samples a ray and blur thin surfaces.
    #[arg(long, value_name = "CELLS")]
    pub volume_step: Option<f32>,
    /// The occupied bricks that none of the file's cameras looks into: `auto` bakes them where
    /// every brick fits the budget, and leaves them out where that keeps a finer resolution;
    /// `exact` always leaves them out, so that views beyond the cameras draw what the exact
    /// renderer draws there (what no camera constrained, which the two draw differently), slower;
    /// `bake` always bakes them, coarser if need be, and no ray goes to the exact path.
    /// A ray that reaches a brick left out is drawn by the exact path.
    #[arg(long, value_enum, value_name = "WHAT")]
    pub volume_outside: Option<VolumeOutside>,
    /// The same as `--volume-outside bake`.
    #[arg(long, hide = true, conflicts_with = "volume_outside")]
    pub volume_keep_outside: bool,
    /// When the CPU renderer bakes the time slices of the volume's dynamic bricks: `auto` once
    /// the exact evaluations of the frames waiting for them reach what baking costs (a
    /// playback that holds its time bakes, one whose time moves every frame evaluates them
    /// exactly), `always` before the first frame that needs them (default: auto; `always` in
    /// `msth eval`, whose figures are the slices' own).
    #[arg(long, value_enum)]
    pub volume_slices: Option<VolumeSlices>,
    /// Keep drawing from the volume while the camera holds still. By default a camera that
    /// holds goes to the exact renderer's incremental cache (it re-evaluates only the dynamic
    /// samples, far faster for a still camera) and the volume draws the camera while it moves.
    #[arg(long)]
    pub volume_still: bool,
}

/// `--volume-outside`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum VolumeOutside {
    #[default]
    Auto,
    Exact,
    Bake,
}

impl From<VolumeOutside> for msth_core::volume::OutsideViews {
    fn from(v: VolumeOutside) -> Self {
        match v {
            VolumeOutside::Auto => msth_core::volume::OutsideViews::Auto,
            VolumeOutside::Exact => msth_core::volume::OutsideViews::Exact,
            VolumeOutside::Bake => msth_core::volume::OutsideViews::Bake,
        }
    }
}

/// `--volume-slices`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum VolumeSlices {
    #[default]
    Auto,
    Always,
}

impl From<VolumeSlices> for msth_player::SlicePolicy {
    fn from(v: VolumeSlices) -> Self {
        match v {
            VolumeSlices::Auto => msth_player::SlicePolicy::Auto,
            VolumeSlices::Always => msth_player::SlicePolicy::Always,
        }
    }
}

impl VolumeArgs {
    /// The march through the volume.
    pub fn march(&self) -> Result<msth_core::volume::MarchSettings> {
        let mut m = msth_core::volume::MarchSettings::default();
        if let Some(s) = self.volume_step {
            if !(0.05..=4.0).contains(&s) {
                bail!("--volume-step {s}: cells in 0.05..=4");
            }
            m.step = s;
        }
        Ok(m)
    }

    pub fn options(&self) -> Result<msth_player::volume::VolumeOptions> {
        let mut o = msth_player::volume::VolumeOptions::default();
        if let Some(m) = self.volume_budget {
            if !(1..=1 << 20).contains(&m) {
                bail!("--volume-budget {m}: MiB in 1..=1048576");
            }
            o.budget = Some(m << 20);
        }
        if let Some(r) = self.volume_resolution {
            if !(1..=1 << 16).contains(&r) {
                bail!("--volume-resolution {r}: cells per side, e.g. 256");
            }
            o.max_resolution = Some(r);
        }
        if let Some(a) = self.volume_min_alpha {
            if !(0.0..1.0).contains(&a) {
                bail!("--volume-min-alpha {a}: an opacity in [0, 1)");
            }
            o.min_cell_alpha = a;
        }
        if let Some(a) = self.volume_min_proposal_alpha {
            if !(0.0..1.0).contains(&a) {
                bail!("--volume-min-proposal-alpha {a}: an opacity in [0, 1)");
            }
            o.min_proposal_alpha = a;
        }
        o.outside = match (self.volume_outside, self.volume_keep_outside) {
            (Some(v), _) => v.into(),
            (None, true) => msth_core::volume::OutsideViews::Bake,
            (None, false) => msth_core::volume::OutsideViews::Auto,
        };
        Ok(o)
    }
}

/// How incremental frames reuse work on the rays they re-render (`msth play`, `msth bench play`).
#[derive(Args, Clone, Debug, Default)]
pub struct ReuseArgs {
    /// What incremental frames re-evaluate on dynamic rays: `samples` (fixed samples per ray,
    /// only those the mask leaves dynamic; the default) or `rays` (the whole ray as a full frame
    /// does: frames equal full renders). The GPU renderer always re-renders rays.
    #[arg(long, value_parser = ["rays", "samples"])]
    pub reuse: Option<String>,
    /// With `--reuse samples`: times at which the fixed samples are placed (default: the
    /// model's frame count, at most 8; at most 32).
    #[arg(long)]
    pub partition_times: Option<usize>,
    /// With `--reuse samples`: fixed samples per dynamic ray (default: the model's main samples).
    #[arg(long)]
    pub partition_samples: Option<usize>,
    /// With `--reuse samples`: samples whose dynamic weight 1 - m is below this are evaluated
    /// once (default 0.05; 0.001 is what full rendering treats as static).
    #[arg(long)]
    pub sample_cutoff: Option<f32>,
}

impl ReuseArgs {
    /// Writes the given options into `r`, checking them.
    pub fn apply(&self, r: &mut RenderSettings) -> Result<()> {
        match self.reuse.as_deref() {
            Some("rays") => r.reuse = Reuse::Rays,
            Some("samples") => r.reuse = Reuse::Samples,
            Some(other) => bail!("--reuse {other}: rays or samples"),
            None => {}
        }
        if let Some(k) = self.partition_times {
            if !(1..=MAX_PARTITION_TIMES).contains(&k) {
                bail!("--partition-times {k}: must lie in 1..={MAX_PARTITION_TIMES}");
            }
            r.partition_times = k;
        }
        if let Some(n) = self.partition_samples {
            if !(1..=1024).contains(&n) {
                bail!("--partition-samples {n}: must lie in 1..=1024");
            }
            r.partition_samples = n;
        }
        if let Some(c) = self.sample_cutoff {
            if !(c.is_finite() && (0.0..=1.0).contains(&c)) {
                bail!("--sample-cutoff {c}: must lie in [0, 1]");
            }
            r.sample_cutoff = c;
        }
        Ok(())
    }
}

pub(crate) fn parse_samples(s: &str) -> Result<PlaySamples, String> {
    s.parse()
}

/// The line saying that `now` (proposal, main samples per ray) are not the model's `own`.
pub(crate) fn samples_note(now: (usize, usize), own: (usize, usize)) -> Option<String> {
    (now != own).then(|| {
        format!(
            "samples per ray: {} proposal + {} main (the model's: {} + {})",
            now.0, now.1, own.0, own.1
        )
    })
}

pub(crate) fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected WxH, e.g. 256x256"))?;
    let p = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("`{s}`: expected WxH"))
    };
    Ok((p(w)?, p(h)?))
}

pub(crate) fn parse_range(s: &str) -> Result<(f32, f32), String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}`: expected START:END, e.g. 0:1"))?;
    let p = |v: &str| {
        v.trim()
            .parse::<f32>()
            .map_err(|_| format!("`{s}`: expected START:END"))
    };
    Ok((p(a)?, p(b)?))
}

/// A number of seconds given as `flag`: in (0, 86400].
pub(crate) fn seconds(flag: &str, v: f64) -> Result<Duration> {
    if !(v.is_finite() && v > 0.0 && v <= 86_400.0) {
        bail!("{flag} {v}: seconds in (0, 86400]");
    }
    Ok(Duration::from_secs_f64(v))
}

pub fn options(a: &PlayArgs) -> Result<PlayOptions> {
    let stall = seconds("--stall-timeout", a.stall_timeout)?;
    let deadline = seconds("--deadline", a.deadline)?;
    if !(a.static_threshold.is_finite() && (0.0..=1.0).contains(&a.static_threshold)) {
        bail!(
            "--static-threshold {}: must lie in [0, 1]",
            a.static_threshold
        );
    }
    if !(a.trust_threshold.is_finite() && a.trust_threshold >= 0.0) {
        bail!(
            "--trust-threshold {}: a non-negative number (above 1: probe every static ray)",
            a.trust_threshold
        );
    }
    if let Some(f) = a.fps {
        if !(f.is_finite() && f > 0.0 && f <= 1000.0) {
            bail!("--fps {f}: must lie in (0, 1000]");
        }
    }
    let mut o = PlayOptions::new(a.source.clone());
    o.path = a.path.clone();
    o.size = a.size;
    o.frames = a.frames;
    o.time_range = a.time;
    o.fps = a.fps;
    o.out = a.out.clone();
    o.video = !a.no_video;
    o.render.incremental = !a.no_incremental;
    o.skip_empty = !a.no_skip_empty;
    o.samples = a.samples;
    o.gpu_tables = a.gpu_tables;
    o.backend = backend_choice(a.cpu, a.gpu);
    o.render.static_threshold = a.static_threshold;
    o.render.trust_threshold = a.trust_threshold;
    if a.probes > 64 {
        bail!("--probes {}: at most 64", a.probes);
    }
    if !(a.probe_tolerance.is_finite() && a.probe_tolerance >= 0.0) {
        bail!(
            "--probe-tolerance {}: a non-negative number",
            a.probe_tolerance
        );
    }
    o.render.probes = a.probes;
    o.render.exact = !a.volume;
    o.volume = a.volume_args.options()?;
    o.render.march = a.volume_args.march()?;
    o.render.slices = a.volume_args.volume_slices.unwrap_or_default().into();
    o.render.volume_when_still = a.volume_args.volume_still;
    o.bake_first = a.bake_first;
    a.reuse.apply(&mut o.render)?;
    o.render.probe_tolerance = a.probe_tolerance;
    // SSL_CERT_FILE matters (and is checked) only where TLS is spoken.
    let ssl_cert_file = if a.source.starts_with("https://") {
        std::env::var_os("SSL_CERT_FILE")
    } else {
        None
    };
    o.section_timeout = deadline;
    o.http = HttpOptions {
        read_timeout: stall,
        request_timeout: deadline,
        retries: a.retries,
        ca_cert_file: ca_cert_file(a.ca_cert.clone(), ssl_cert_file)?,
        ..HttpOptions::default()
    };
    Ok(o)
}

/// The certificate file for https: `--ca-cert`, else a non-empty `SSL_CERT_FILE` (which must name
/// a file: a stale variable is reported as such, not as a missing `--ca-cert`), else none.
pub fn ca_cert_file(flag: Option<PathBuf>, env: Option<OsString>) -> Result<Option<PathBuf>> {
    if flag.is_some() {
        return Ok(flag);
    }
    match env.filter(|v| !v.is_empty()).map(PathBuf::from) {
        Some(p) if !p.is_file() => bail!(
            "SSL_CERT_FILE={}: not a file (unset it, or give --ca-cert FILE.pem)",
            p.display()
        ),
        p => Ok(p),
    }
}

/// The backend `--cpu` / `--gpu` ask for.
pub fn backend_choice(cpu: bool, gpu: bool) -> BackendChoice {
    match (cpu, gpu) {
        (true, _) => BackendChoice::Cpu,
        (false, true) => BackendChoice::Gpu,
        (false, false) => BackendChoice::Auto,
    }
}

fn frame_line(r: &FrameRecord, n: usize) -> String {
    let s = &r.stats;
    format!(
        "frame {:>4}/{n}  t={:.3}  {} {}  rays {:>7}/{} ({:5.1}%)  {:7.1} ms",
        r.index + 1,
        r.time,
        if s.full { "full" } else { "incr" },
        if s.volume { "volume" } else { "exact " },
        s.rays_rendered,
        s.rays_total,
        100.0 * s.rays_rendered as f64 / s.rays_total.max(1) as f64,
        1e3 * s.seconds
    ) + &volume_detail(s)
}

/// What a volume frame spent: samples per ray read from the volume (counted on the CPU),
/// samples evaluated from the field, rays drawn by the exact path, and the time slices baked
/// for it.
fn volume_detail(s: &msth_player::FrameStats) -> String {
    if !s.volume {
        return String::new();
    }
    let mut parts = Vec::new();
    if s.volume_samples > 0 {
        parts.push(format!(
            "{:.0} samples/ray",
            s.volume_samples as f64 / s.rays_rendered.max(1) as f64
        ));
    }
    if s.volume_steps > 0 {
        parts.push(format!(
            "{:.0} steps/ray",
            s.volume_steps as f64 / s.rays_rendered.max(1) as f64
        ));
    }
    if s.samples_evaluated > 0 {
        parts.push(format!("{} field samples", s.samples_evaluated));
    }
    if s.rays_exact > 0 {
        parts.push(format!(
            "{} rays exact (outside the file's views) in {:.0} ms",
            s.rays_exact,
            1e3 * s.exact_seconds
        ));
    }
    if s.slice_seconds > 0.0 {
        parts.push(format!("slices baked in {:.0} ms", 1e3 * s.slice_seconds));
    }
    if parts.is_empty() {
        String::new()
    } else {
        format!("  {}", parts.join(", "))
    }
}

fn summary(r: &PlayReport, threshold: f32) {
    let fps = |v: Option<f64>| v.map_or("-".to_string(), |f| format!("{f:.1}"));
    let n = r.frames.len();
    let rays: usize = r.frames.iter().map(|f| f.stats.rays_rendered).sum();
    println!(
        "renderer: {} ({}){}{}{}",
        r.backend.kind,
        r.backend.device,
        r.backend
            .note
            .as_ref()
            .map_or(String::new(), |n| format!("; {n}")),
        r.backend
            .mlps
            .as_ref()
            .map_or(String::new(), |n| format!("; {n}")),
        r.backend
            .tables
            .map_or(String::new(), |t| match r.backend.tables_clamped {
                0 => format!("; hash tables {t}"),
                n => format!(
                    "; hash tables {t} ({n} values beyond binary16's ±65504 held clamped: \
                 --gpu-tables f32 renders them as they are)"
                ),
            })
    );
    if let Some(note) = samples_note(r.samples, r.model_samples) {
        println!("{note}");
    }
    if let Some(b) = &r.bake {
        println!(
            "volume: {}^3 cells, {} bricks ({} dynamic cells), {:.1} MiB, baked in {:.2} s; frames from frame {} on",
            b.geometry.resolution,
            b.stats.bricks,
            b.stats.dynamic_cells,
            b.bytes as f64 / (1 << 20) as f64,
            b.stats.seconds,
            b.first_frame + 1
        );
        if let Some(n) = &b.note {
            println!("note: {n}");
        }
    }
    if let Some(n) = &r.volume_note {
        println!("note: {n}");
    }
    println!(
        "{n} frames in {:.2} s; time to first frame {:.3} s",
        r.seconds, r.time_to_first_frame
    );
    println!(
        "render FPS: {} overall, {} full frames, {} incremental frames; {:.0} rays/frame on average",
        fps(r.fps()),
        fps(r.full_fps()),
        fps(r.incremental_fps()),
        rays as f64 / n.max(1) as f64
    );
    if let Some(d) = r.dynamic_fraction {
        println!(
            "static-ray cache: {:.1}% of the fixed camera's pixels re-rendered per frame",
            100.0 * d
        );
        let reused: Vec<_> = r
            .frames
            .iter()
            .filter(|f| !f.stats.full && f.stats.samples_evaluated > 0)
            .collect();
        if !reused.is_empty() {
            let samples: usize = reused.iter().map(|f| f.stats.samples_evaluated).sum();
            let rays: usize = reused.iter().map(|f| f.stats.rays_rendered).sum();
            println!(
                "sample reuse: {:.1} samples evaluated per re-rendered ray (fixed samples, no \
                 proposal pass; --reuse rays renders them in full)",
                samples as f64 / rays.max(1) as f64
            );
        }
        if d > 0.9 {
            println!(
                "  (the model's mask calls few rays static at --static-threshold {}: masks trained \
                 without the uncertainty term stay soft; --static-threshold 0 leaves the choice to \
                 the probes, which cache only rays whose colour stays within --probe-tolerance)",
                threshold
            );
        }
    }
    println!(
        "fetched {} of {} bytes in {} requests ({} retries)",
        r.transfer.bytes, r.file_len, r.transfer.requests, r.transfer.retries
    );
    if let Some(v) = &r.video {
        println!("video: {}", v.display());
    }
    if let Some(n) = &r.video_note {
        println!("no video: {n}");
    }
}

pub fn run(a: PlayArgs) -> Result<()> {
    let opts = options(&a)?;
    let quiet = a.quiet;
    let mut total = 0usize;
    let report = play(&opts, &mut |r, _| {
        total = total.max(r.index + 1);
        if !quiet {
            let n = opts.frames.unwrap_or(0).max(total);
            println!("{}", frame_line(r, n));
        }
    })?;
    summary(&report, opts.render.static_threshold);
    if let Some(dir) = &a.out {
        println!("frames: {}", dir.join("frame_*.png").display());
    }
    if let Some(p) = &a.report {
        let json = serde_json::to_vec_pretty(&report)?;
        let tmp = p.with_extension("json.tmp");
        std::fs::write(&tmp, json)
            .and_then(|_| std::fs::rename(&tmp, p))
            .with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ca_cert_flag_then_ssl_cert_file() {
        let dir = std::env::temp_dir();
        let flag = PathBuf::from("/flag.pem");
        let file = std::env::current_exe().unwrap(); // any existing file
        assert_eq!(
            ca_cert_file(Some(flag.clone()), Some(file.clone().into())).unwrap(),
            Some(flag)
        );
        assert_eq!(
            ca_cert_file(None, Some(file.clone().into())).unwrap(),
            Some(file)
        );
        assert_eq!(ca_cert_file(None, Some(OsString::new())).unwrap(), None);
        assert_eq!(ca_cert_file(None, None).unwrap(), None);
        let stale = dir.join("msth-no-such-ca-file.pem");
        let e = ca_cert_file(None, Some(stale.into()))
            .unwrap_err()
            .to_string();
        assert!(e.contains("SSL_CERT_FILE="), "{e}");
    }

    /// `--volume-outside` reaches the plan's options; the older `--volume-keep-outside` still
    /// means `bake`, and the two together are refused.
    #[test]
    fn volume_outside_and_its_older_name() {
        use clap::Parser;
        use msth_core::volume::OutsideViews;
        #[derive(Parser)]
        struct Cmd {
            #[command(flatten)]
            volume: VolumeArgs,
        }
        let outside = |args: &[&str]| {
            Cmd::try_parse_from(std::iter::once("msth").chain(args.iter().copied()))
                .map(|c| c.volume.options().unwrap().outside)
        };
        assert_eq!(outside(&[]).unwrap(), OutsideViews::Auto);
        for (name, want) in [
            ("auto", OutsideViews::Auto),
            ("exact", OutsideViews::Exact),
            ("bake", OutsideViews::Bake),
        ] {
            assert_eq!(outside(&["--volume-outside", name]).unwrap(), want);
            assert_eq!(want.name(), name);
        }
        assert_eq!(
            outside(&["--volume-keep-outside"]).unwrap(),
            OutsideViews::Bake
        );
        assert!(outside(&["--volume-keep-outside", "--volume-outside", "exact"]).is_err());
        assert!(outside(&["--volume-outside", "sideways"]).is_err());
    }
}
