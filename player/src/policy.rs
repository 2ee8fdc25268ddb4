//! The interactive viewer policy: what resolution to draw at and when, and how the timeline
//! moves. One implementation for every native viewer (`msth view`), the same rules as the web page
//! (`web/js/main.js`, stated in `web/README.md`):
//!
//! - **Reduced resolution while the camera moves or the video plays**: frames are drawn at 1, 1/2,
//!   1/4 or 1/8 of the full size per side ([`SCALES`]), adapted frame by frame so that a frame
//!   fits its budget ([`MOVING_BUDGET`] while moving, one model frame while playing). While
//!   moving, full size only where the measured rate draws a full-size frame in half the budget,
//!   so that a drag answers at once.
//! - **Refinement when it stops**: [`STILL`] after the last input, paused, the view is drawn
//!   again one step finer per frame (1/8, 1/4, 1/2, full) until it is at full size. The first
//!   frame starts at 1/8 and is refined the same way.
//! - **The static cache under a still camera** (incremental rendering, [`crate::render`]): used
//!   only where its probe frames take at most [`CACHE_BUDGET`] at the measured rate, and while
//!   playing only where a full-size frame takes at most [`PLAY_CACHE_FRAMES`] model frames.
//! - **The timeline** ([`Timeline`]) advances with the clock at the model's frame rate (times a
//!   speed); frames the renderer cannot draw in time are dropped, not slowed down; it holds
//!   still while the chunk under the playhead is streaming.
//!
//! Everything here is plain arithmetic on times the caller passes in (seconds since any fixed
//! instant), so that it is deterministic and tested without a clock, a window or a GPU.

use msth_core::Camera;

/// Reduced sizes, as divisors per side, finest first.
pub const SCALES: [u32; 4] = [1, 2, 4, 8];
/// A frame's budget while the camera moves (seconds).
pub const MOVING_BUDGET: f64 = 1.0 / 30.0;
/// The camera counts as still this long after the last input (seconds).
pub const STILL: f64 = 0.25;
/// The static cache is built only where its probe frames take at most this long at the
/// measured rate (seconds).
pub const CACHE_BUDGET: f64 = 10.0;
/// While playing, the static cache is used only where a full-size frame takes at most this many
/// model frames at the measured rate.
pub const PLAY_CACHE_FRAMES: f64 = 4.0;
/// Frame rate of a file that states none (the page's too).
pub const DEFAULT_FRAME_RATE: f32 = 24.0;

/// Why a frame is drawn at its size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Activity {
    /// The camera moved less than [`STILL`] ago.
    Moving,
    /// The timeline plays under a still camera.
    Playing,
    /// Still and paused: one step finer than the last frame.
    Refining,
}

impl Activity {
    pub fn name(self) -> &'static str {
        match self {
            Activity::Moving => "moving",
            Activity::Playing => "playing",
            Activity::Refining => "refining",
        }
    }
}

/// What to draw next.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Step {
    /// Divisor per side of the full size (one of [`SCALES`]).
    pub divisor: u32,
    pub activity: Activity,
    /// Whether the renderer may keep its static cache for this frame (a still camera at full
    /// size where the cache fits its budgets); else the frame is rendered in full.
    pub incremental: bool,
}

/// The resolution policy's state (see the module docs).
#[derive(Clone, Debug)]
pub struct ResolutionPolicy {
    /// Index into [`SCALES`] while moving or playing, adapted to the budget; the first frames
    /// start at the coarsest.
    level: usize,
    /// Index into [`SCALES`] of the next frame drawn still and paused.
    refine_level: usize,
    /// The last frame was reduced: draw it again, one step finer, when still and paused.
    refine: bool,
    last_input: Option<f64>,
    /// A moving frame's budget (seconds; [`MOVING_BUDGET`] unless set).
    pub moving_budget: f64,
    /// The model's frame rate (frames per second).
    pub frame_rate: f32,
    /// Measured pixels per second of frames rendered in full (`None` before the first).
    rate: Option<f64>,
}

impl ResolutionPolicy {
    /// A policy for a model played at `frame_rate` (`None`: [`DEFAULT_FRAME_RATE`]).
    pub fn new(frame_rate: Option<f32>) -> Self {
        ResolutionPolicy {
            level: SCALES.len() - 1,
            refine_level: SCALES.len() - 1,
            refine: true,
            last_input: None,
            moving_budget: MOVING_BUDGET,
            frame_rate: frame_rate
                .filter(|r| r.is_finite() && *r > 0.0)
                .unwrap_or(DEFAULT_FRAME_RATE),
            rate: None,
        }
    }

    /// The camera moved at `now`.
    pub fn input(&mut self, now: f64) {
        self.last_input = Some(now);
    }

    /// Whether the camera moved less than [`STILL`] before `now`.
    pub fn moving(&self, now: f64) -> bool {
        self.last_input.is_some_and(|t| now - t < STILL)
    }

    /// Measured pixels per second of full renders, if any.
    pub fn rate(&self) -> Option<f64> {
        self.rate
    }

    /// One model frame (seconds).
    pub fn frame_budget(&self) -> f64 {
        1.0 / self.frame_rate as f64
    }

    /// Whether a full-size frame of `pixels` is expected within `seconds` at the measured rate.
    fn fits(&self, pixels: u64, seconds: f64) -> bool {
        self.rate
            .is_some_and(|r| r > 0.0 && pixels as f64 / r <= seconds)
    }

    /// Whether the static cache may serve a still camera whose full size has `pixels`, built
    /// from `probes` probe frames.
    pub fn cache_fits(&self, pixels: u64, probes: usize, playing: bool) -> bool {
        self.fits(pixels * probes.max(1) as u64, CACHE_BUDGET)
            && (!playing || self.fits(pixels, PLAY_CACHE_FRAMES * self.frame_budget()))
    }

    /// The next frame of a view whose full size has `pixels` pixels, at `now`; `probes`: the
    /// static cache's probe frames (0: no incremental rendering).
    pub fn next(&self, now: f64, playing: bool, pixels: u64, probes: usize) -> Step {
        let moving = self.moving(now);
        if !moving && probes > 0 && self.cache_fits(pixels, probes, playing) {
            return Step {
                divisor: 1,
                activity: if playing {
                    Activity::Playing
                } else {
                    Activity::Refining
                },
                incremental: true,
            };
        }
        let (level, activity) = if moving {
            let full_fits = self.fits(pixels, 0.5 * self.moving_budget);
            (
                self.level.max(if full_fits { 0 } else { 1 }),
                Activity::Moving,
            )
        } else if playing {
            (self.level, Activity::Playing)
        } else {
            (self.refine_level, Activity::Refining)
        };
        Step {
            divisor: SCALES[level],
            activity,
            incremental: false,
        }
    }

    /// Whether a reduced frame waits to be refined now (still and paused).
    pub fn wants_refine(&self, now: f64, playing: bool) -> bool {
        self.refine && !playing && !self.moving(now)
    }

    /// Records a drawn frame: `step` took `seconds` for `pixels` pixels (`full`: every pixel
    /// rendered, not an incremental frame).
    pub fn done(&mut self, step: Step, seconds: f64, pixels: u64, full: bool) {
        if full && seconds > 0.0 {
            self.rate = Some(pixels as f64 / seconds);
        }
        if step.incremental {
            self.refine = false;
            self.refine_level = 0;
            return;
        }
        let level = SCALES.iter().position(|&s| s == step.divisor).unwrap_or(0);
        if step.activity != Activity::Refining {
            let budget = match step.activity {
                Activity::Moving => self.moving_budget,
                _ => self.frame_budget(),
            };
            if seconds > budget && self.level < SCALES.len() - 1 {
                self.level += 1;
            } else if seconds * 4.0 < 0.7 * budget && self.level > 0 {
                self.level -= 1;
            }
        }
        self.refine_level = level.saturating_sub(1);
        self.refine = step.divisor != 1;
    }
}

/// `camera` reduced to 1/`divisor` of its size per side (at least one pixel): the same view,
/// its intrinsics scaled per axis.
pub fn reduced_camera(camera: &Camera, divisor: u32) -> Camera {
    if divisor <= 1 {
        return *camera;
    }
    let w = camera.width.div_ceil(divisor).max(1);
    let h = camera.height.div_ceil(divisor).max(1);
    let sx = w as f32 / camera.width as f32;
    let sy = h as f32 / camera.height as f32;
    Camera {
        width: w,
        height: h,
        fx: camera.fx * sx,
        fy: camera.fy * sy,
        cx: camera.cx * sx,
        cy: camera.cy * sy,
        world_from_camera: camera.world_from_camera,
    }
}

/// The playhead: normalised time `t` in `[0, 1]`, advanced with the clock at the model's frame
/// rate times `speed`.
#[derive(Clone, Debug, PartialEq)]
pub struct Timeline {
    pub t: f32,
    pub playing: bool,
    /// At the end: wrap to the start (else stop there).
    pub looping: bool,
    /// Playback speed, 1 = the model's frame rate.
    pub speed: f32,
    /// The model's frame count.
    pub frames: usize,
    pub frame_rate: f32,
}

impl Timeline {
    pub fn new(frames: usize, frame_rate: Option<f32>) -> Self {
        Timeline {
            t: 0.0,
            playing: true,
            looping: true,
            speed: 1.0,
            frames: frames.max(1),
            frame_rate: frame_rate
                .filter(|r| r.is_finite() && *r > 0.0)
                .unwrap_or(DEFAULT_FRAME_RATE),
        }
    }

    /// Seconds one pass over `[0, 1]` lasts at speed 1 (the page's: at least two frames).
    pub fn duration(&self) -> f64 {
        self.frames.max(2) as f64 / self.frame_rate as f64
    }

    /// Moves the playhead by `dt` seconds of wall time while playing; `ready`: whether the
    /// chunk under the playhead has arrived (playback holds still while it streams). Returns
    /// whether `t` changed.
    pub fn advance(&mut self, dt: f64, ready: bool) -> bool {
        if !self.playing || !ready || dt <= 0.0 {
            return false;
        }
        let next = self.t as f64 + dt * self.speed as f64 / self.duration();
        self.t = if (0.0..1.0).contains(&next) {
            next as f32
        } else if self.looping {
            next.rem_euclid(1.0) as f32
        } else {
            self.playing = false;
            next.clamp(0.0, 1.0) as f32
        };
        true
    }

    /// The model frame nearest `t` (0-based).
    pub fn frame(&self) -> usize {
        (self.t * (self.frames.max(1) - 1) as f32).round() as usize
    }

    /// Moves to model frame `i` (clamped), pausing.
    pub fn step_to(&mut self, i: isize) {
        let last = self.frames.max(1) - 1;
        let i = i.clamp(0, last as isize) as usize;
        self.playing = false;
        self.t = if last > 0 {
            i as f32 / last as f32
        } else {
            0.0
        };
    }

    /// Sets the time (clamped to `[0, 1]`), as a scrub does.
    pub fn seek(&mut self, t: f32) {
        if t.is_finite() {
            self.t = t.clamp(0.0, 1.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FULL: u64 = 256 * 256;

    #[test]
    fn the_first_frame_is_coarse_and_refines_step_by_step_when_still() {
        let mut p = ResolutionPolicy::new(Some(30.0));
        let mut divisors = Vec::new();
        for i in 0..5 {
            let now = 10.0 + i as f64;
            if i > 0 && !p.wants_refine(now, false) {
                break;
            }
            let s = p.next(now, false, FULL, 0);
            divisors.push(s.divisor);
            p.done(s, 0.01, FULL / (s.divisor * s.divisor) as u64, true);
        }
        assert_eq!(divisors, [8, 4, 2, 1]);
        assert!(!p.wants_refine(20.0, false));
    }

    #[test]
    fn moving_adapts_the_size_to_the_budget() {
        let mut p = ResolutionPolicy::new(None);
        p.input(0.0);
        // A slow renderer: 1/2 takes 50 ms (over 1/30 s): the next moving frame is coarser.
        let s = p.next(0.01, false, FULL, 0);
        assert_eq!(s.activity, Activity::Moving);
        let s = Step { divisor: 2, ..s };
        p.level = 1;
        p.done(s, 0.05, FULL / 4, true);
        assert_eq!(p.next(0.02, false, FULL, 0).divisor, 4);
        // A fast one: full size when a full frame takes under half the budget.
        let mut fast = ResolutionPolicy::new(None);
        fast.done(
            Step {
                divisor: 1,
                activity: Activity::Refining,
                incremental: false,
            },
            0.001,
            FULL,
            true,
        );
        fast.level = 0;
        fast.input(1.0);
        assert_eq!(fast.next(1.1, false, FULL, 0).divisor, 1);
        // Still after STILL seconds.
        assert!(fast.moving(1.0 + STILL * 0.9));
        assert!(!fast.moving(1.0 + STILL * 1.1));
    }

    #[test]
    fn the_static_cache_needs_a_rate_that_fits_its_budgets() {
        let mut p = ResolutionPolicy::new(Some(24.0));
        assert!(!p.cache_fits(FULL, 3, false), "no rate measured yet");
        let s = p.next(5.0, false, FULL, 3);
        assert!(!s.incremental);
        // 65536 pixels in 0.1 s: three probes in 0.3 s fit 10 s; a full frame (0.1 s) fits
        // four model frames (0.167 s) too.
        p.done(s, 0.1, FULL, true);
        assert!(p.cache_fits(FULL, 3, true));
        let s = p.next(5.0, true, FULL, 3);
        assert!(s.incremental && s.divisor == 1);
        // Half as fast: fine paused, not while playing.
        p.done(s, 0.2, FULL, true);
        assert!(p.cache_fits(FULL, 3, false));
        assert!(!p.cache_fits(FULL, 3, true));
    }

    #[test]
    fn the_timeline_runs_at_the_frame_rate_and_loops_or_stops() {
        let mut t = Timeline::new(25, Some(25.0));
        assert_eq!(t.duration(), 1.0);
        assert!(t.advance(0.5, true));
        assert!((t.t - 0.5).abs() < 1e-6);
        assert!(!t.advance(0.25, false), "holds while streaming");
        t.speed = 2.0;
        t.advance(0.3, true);
        assert!((t.t - 0.1).abs() < 1e-5, "wrapped: {}", t.t);
        t.looping = false;
        t.advance(1.0, true);
        assert_eq!((t.t, t.playing), (1.0, false));
        t.step_to(3);
        assert_eq!(t.frame(), 3);
        t.step_to(-4);
        assert_eq!(t.t, 0.0);
    }

    #[test]
    fn reduced_cameras_keep_the_view() {
        let c = Camera::look_at(
            101,
            50,
            0.8,
            glam::Vec3::new(3.0, 0.0, 1.0),
            glam::Vec3::ZERO,
            glam::Vec3::Z,
        );
        let r = reduced_camera(&c, 4);
        assert_eq!((r.width, r.height), (26, 13));
        // The ray through the centre of the image is the same.
        let a = c.ray_at(0.5 * c.width as f32, 0.5 * c.height as f32);
        let b = r.ray_at(0.5 * r.width as f32, 0.5 * r.height as f32);
        assert!((a.dir - b.dir).length() < 1e-5);
        assert_eq!(reduced_camera(&c, 1), c);
    }
}
