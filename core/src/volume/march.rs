//! Rendering rays through a baked volume on the CPU.
//!
//! Each ray walks from its near to its far bound ([`crate::pipeline::ray_limits`]) in steps of
//! [`MarchSettings::step`] cells of the volume, measured in the unit cube (for a contracted scene
//! the step in world units grows with the distance, as the contraction shrinks space). A step
//! whose midpoint lies in an empty brick or an empty cell jumps to where the ray leaves it; any
//! other step is a sample:
//! - in a static cell, the stored outputs interpolated trilinearly;
//! - in a dynamic brick, the values of the two time slices around the ray's time, blended (a
//!   cell the mask leaves static reads one slice, so its samples do not depend on the time);
//! - in a dynamic brick whose slices are not baked, the exact field at the ray's time, evaluated
//!   in one batch for a chunk of rays after the walk (the walk records the samples from a ray's
//!   first such one on, and composites them once the batch is back).
//!
//! A ray that reaches a brick the volume left out ([`super::OUTSIDE_BRICK`]: none of the file's
//! cameras looks into it) stops there and is marked ([`MarchOutput::outside`]): the players draw
//! it with the exact renderer.
//!
//! A ray stops once its transmittance falls below [`MarchSettings::stop_transmittance`]. A static
//! sample's colour is the baked one ([`ColourMode::Baked`]), a dynamic sample's the colour MLP's
//! at the ray's direction; they are composited as the exact renderer composites.
//!
//! A ray whose walk met no cell the mask leaves dynamic (holding density now or not) before it
//! stopped has a colour that does not depend on time ([`MarchOutput::dynamic`]): incremental playback keeps such pixels while the camera holds,
//! and its frames equal full frames exactly.

use glam::Vec3;

use crate::activation::{sigmoid, trunc_exp};
use crate::config::{Background, ModelConfig};
use crate::field::{FieldScratch, ModelLayout};
use crate::mlp::MlpActivations;
use crate::pipeline::{ray_limits, sample_time, TimedRay, VISIBLE_TRANSMITTANCE};
use crate::render::tau_of;
use crate::scene::SceneBounds;
use crate::sh::{sh4, SH_COEFFS};

use half::slice::HalfFloatSliceExt;

use super::{Value, Volume, DYNAMIC_BRICK, EMPTY_BRICK, OUTSIDE_BRICK, VOLUME_STATIC_CUTOFF};

/// What a volume's vertices hold besides the density, and so how a static sample gets its
/// colour. The volume is baked for one mode ([`super::bake::PlanOptions::colour`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ColourMode {
    /// The colour MLP's output for a reference direction ([`super::reference_direction`]),
    /// interpolated: no network per static sample (the players' mode).
    #[default]
    Baked,
    /// The geometry features, and the colour MLP on every sample that carries weight, at the
    /// ray's direction: what baking the colour costs (CPU only).
    PerSample,
    /// The geometry features composited with the rendering weights, and the colour MLP once
    /// per ray (SNeRG's deferred shading): the cheapest view-dependent colour (CPU only).
    Deferred,
}

/// How rays walk the volume.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MarchSettings {
    /// Step length in cells of the volume (unit-cube length `step / R`).
    pub step: f32,
    /// A ray stops once its transmittance falls below this.
    pub stop_transmittance: f32,
}

/// Default [`MarchSettings::step`]: one cell (half a cell reads twice the samples for 0.03 dB on
/// the demo model).
pub const DEFAULT_STEP: f32 = 1.0;

impl Default for MarchSettings {
    fn default() -> Self {
        MarchSettings {
            step: DEFAULT_STEP,
            stop_transmittance: VISIBLE_TRANSMITTANCE,
        }
    }
}

/// Samples below this weight add no features (and their weight is left out of the composite):
/// at most this much of a pixel per sample.
const MIN_FEATURE_WEIGHT: f32 = 1e-5;

/// What rendering through the volume returns, one entry per ray.
#[derive(Clone, Debug, Default)]
pub struct MarchOutput {
    pub rgb: Vec<[f32; 3]>,
    /// Distance at which the transmittance fell below the stop (the far bound if it never did).
    pub visible_depth: Vec<f32>,
    /// Whether the ray composited a dynamic sample: its colour may change with time.
    pub dynamic: Vec<bool>,
    /// Whether the ray reached a brick the volume left out ([`super::OUTSIDE_BRICK`]) before it
    /// stopped: its entry is not its colour, and the caller renders it with the exact path.
    pub outside: Vec<bool>,
    /// Samples composited (static and dynamic) over all rays.
    pub samples: usize,
    /// Of those, dynamic samples (exact field evaluations).
    pub dynamic_samples: usize,
    /// Steps taken, skips included.
    pub steps: usize,
}

impl MarchOutput {
    pub fn clear(&mut self) {
        *self = MarchOutput::default();
    }

    pub fn append(&mut self, other: &MarchOutput) {
        self.rgb.extend_from_slice(&other.rgb);
        self.visible_depth.extend_from_slice(&other.visible_depth);
        self.dynamic.extend_from_slice(&other.dynamic);
        self.outside.extend_from_slice(&other.outside);
        self.samples += other.samples;
        self.dynamic_samples += other.dynamic_samples;
        self.steps += other.steps;
    }
}

/// One recorded sample of a ray that met an exact one.
#[derive(Clone, Copy, Debug)]
struct Entry {
    delta: f32,
    t_end: f32,
    /// Row of `values` holding the sample's outputs.
    row: u32,
    /// Evaluated exactly (the row is filled after the walk).
    exact: bool,
    /// In a cell whose values change with time.
    dynamic: bool,
}

/// Where a ray's walk stopped and what it accumulated.
#[derive(Clone, Debug, Default)]
struct RayState {
    transmittance: f32,
    /// Composited weight of the samples that added features.
    weight: f32,
    visible_depth: Option<f32>,
    far: f32,
    dynamic: bool,
    missed: bool,
    /// Reached a brick the volume left out.
    outside: bool,
    /// Recorded entries `entries[start..end]`.
    entries: (usize, usize),
    /// Row of the last composited sample's outputs in `last` (LastSample background).
    has_last: bool,
}

/// Reusable buffers of one thread.
#[derive(Clone, Debug, Default)]
pub struct MarchWorkspace {
    states: Vec<RayState>,
    /// `[rays, payload]` composited payloads: colours (baked) or features (deferred).
    features: Vec<f32>,
    /// `[rays, channels]` the last composited sample's outputs.
    last: Vec<f32>,
    entries: Vec<Entry>,
    /// `[rows, channels]` recorded samples' outputs.
    values: Vec<f32>,
    /// `[n, 4]` dynamic points and the rows they fill.
    dyn_points: Vec<f32>,
    dyn_rows: Vec<u32>,
    field: FieldScratch,
    /// Dynamic rows' rays (baked colour: the colour MLP at their direction).
    dyn_rays: Vec<u32>,
    colour_in: Vec<f32>,
    colour_acts: MlpActivations,
    /// Per-sample colour: `(ray, weight)` of each row of `colour_in`.
    per_sample: Vec<(u32, f32)>,
    sample: Vec<f32>,
}

/// The unit-cube velocity `d(to_unit(x + s d)) / ds` at world point `x` along unit direction
/// `d`: constant in a box, shrinking with the distance in a contracted scene.
#[inline]
pub fn unit_velocity(bounds: &SceneBounds, x: Vec3, d: Vec3) -> Vec3 {
    match *bounds {
        SceneBounds::Box { min, max } => d / (max - min),
        SceneBounds::Contracted { center, radius } => {
            let y = (x - center) / radius;
            let dy = d / radius;
            let a = y.abs();
            let n = a.max_element();
            let dc = if n < 1.0 || !n.is_finite() {
                dy
            } else {
                let k = if a.x >= a.y && a.x >= a.z {
                    0
                } else if a.y >= a.z {
                    1
                } else {
                    2
                };
                let dn = y[k].signum() * dy[k];
                dy * ((2.0 * n - 1.0) / (n * n)) - y * (2.0 * (n - 1.0) / (n * n * n) * dn)
            };
            dc * 0.25
        }
    }
}

/// Where `ray` crosses the inner cube of a scene contracted about `center` with `radius` (the
/// part of space the contraction leaves as it is): `(t0, t1, u0, v, step)` with the ray's unit
/// point `u0 + v t` for `t` in `[t0, t1]` and the world length `step` of a step of `h` unit
/// lengths there; `None` when the ray misses it.
#[inline(always)]
pub(crate) fn inner_segment(
    center: Vec3,
    radius: f32,
    ray: &TimedRay,
    h: f32,
) -> Option<(f32, f32, Vec3, Vec3, f32)> {
    let cube = SceneBounds::Box {
        min: center - radius,
        max: center + radius,
    };
    let ray3 = crate::camera::Ray {
        origin: ray.origin,
        dir: ray.dir,
    };
    let i = cube.ray_interval(&ray3, f32::NEG_INFINITY, f32::INFINITY)?;
    // `to_unit` there: `(y + 2) / 4` with `y = (x - center) / radius`.
    let v = ray.dir / radius * 0.25;
    let speed = v.length();
    let u0 = ((ray.origin - center) / radius + 2.0) * 0.25;
    (speed > 0.0 && speed.is_finite()).then(|| (i.near, i.far, u0, v, h / speed))
}

/// World distance along velocity `v` (unit cube per world unit) from unit point `p` to the exit
/// of the box `[lo, hi]`.
#[inline]
fn exit_distance(p: Vec3, v: Vec3, lo: Vec3, hi: Vec3) -> f32 {
    let mut t = f32::INFINITY;
    for a in 0..3 {
        if v[a] > 0.0 {
            t = t.min((hi[a] - p[a]) / v[a]);
        } else if v[a] < 0.0 {
            t = t.min((lo[a] - p[a]) / v[a]);
        }
    }
    t.max(0.0)
}

/// What one step's midpoint finds.
enum Lookup {
    /// Nothing to draw up to world distance `.0` from the midpoint; `.1` when the empty cell is
    /// one the mask leaves dynamic (it may hold something at another time).
    Skip(f32, bool),
    /// A sample read from baked values: from a static slot, or lerped between two slices of a
    /// dynamic brick; `dynamic` when the cell is one the mask leaves dynamic.
    Baked {
        at: Source,
        local: Vec3,
        dynamic: bool,
    },
    /// A sample of a dynamic brick whose slices are not baked: the exact field at this unit
    /// point.
    Exact(Vec3),
    /// A brick the volume left out: the ray goes to the exact path.
    Outside,
}

/// Where a baked sample's values are.
#[derive(Clone, Copy)]
enum Source {
    Static(u32),
    /// Dynamic brick `d`, slices `k0` and `k1` with weight `f` on the second.
    Slices {
        d: u32,
        k0: usize,
        k1: usize,
        f: f32,
    },
}

/// The slices a frame's time reads, when they are baked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimeSlices {
    pub k0: usize,
    pub k1: usize,
    pub f: f32,
}

impl Volume {
    /// Values per vertex after the density: 3 (a colour) or the geometry features.
    pub fn payload(&self) -> usize {
        match self.colour {
            ColourMode::Baked => 3,
            _ => self.geo,
        }
    }

    /// The baked slices for time `t` (`None`: dynamic bricks are evaluated exactly at `t`).
    pub fn slices_for(&self, t: f32) -> Option<TimeSlices> {
        if !self.dynamic.ready_for(t) {
            return None;
        }
        self.dynamic
            .around(t)
            .map(|(k0, k1, f)| TimeSlices { k0, k1, f })
    }

    /// Interpolates the values of slot `slot` of `values` at brick-local cell coordinates
    /// `local`, adding `weight` times them into `out[..n]` (`n = 1`: the density alone).
    #[inline(always)]
    fn interpolate_into<const F16C: bool>(
        &self,
        values: &[Value],
        slot: usize,
        local: Vec3,
        weight: f32,
        out: &mut [f32],
        n: usize,
    ) {
        let b = self.geometry.brick;
        let v1 = b as usize + 1;
        let ch = self.channels;
        // `as u32` truncates and saturates (negative and NaN to 0): the floor of a local
        // coordinate, which is never below 0 but for a rounding.
        let i = [
            (local.x as u32).min(b - 1) as usize,
            (local.y as u32).min(b - 1) as usize,
            (local.z as u32).min(b - 1) as usize,
        ];
        let f = [
            (local.x - i[0] as f32).clamp(0.0, 1.0),
            (local.y - i[1] as f32).clamp(0.0, 1.0),
            (local.z - i[2] as f32).clamp(0.0, 1.0),
        ];
        let base =
            (slot * self.geometry.vertices_per_brick() + i[0] + v1 * (i[1] + v1 * i[2])) * ch;
        let (sx, sy, sz) = (ch, v1 * ch, v1 * v1 * ch);
        let (gx, gy, gz) = (1.0 - f[0], 1.0 - f[1], 1.0 - f[2]);
        let w = [
            weight * gx * gy * gz,
            weight * f[0] * gy * gz,
            weight * gx * f[1] * gz,
            weight * f[0] * f[1] * gz,
            weight * gx * gy * f[2],
            weight * f[0] * gy * f[2],
            weight * gx * f[1] * f[2],
            weight * f[0] * f[1] * f[2],
        ];
        let offsets = [
            base,
            base + sx,
            base + sy,
            base + sx + sy,
            base + sz,
            base + sx + sz,
            base + sy + sz,
            base + sx + sy + sz,
        ];
        if n == 4 && ch == 4 {
            // A vertex's 4 values are one 8-byte load.
            let (quads, _) = values.as_chunks::<4>();
            let mut h = [[Value::ZERO; 4]; 8];
            for (q, &o) in h.iter_mut().zip(&offsets) {
                *q = quads[o / 4];
            }
            #[cfg(target_arch = "x86_64")]
            let acc = if F16C {
                // SAFETY: `F16C` is true only within `x86::march_chunk`, which runs where the CPU
                // has AVX2, FMA and F16C.
                unsafe { x86::sum8x4(&h, &w) }
            } else {
                sum8x4(&h, &w)
            };
            #[cfg(not(target_arch = "x86_64"))]
            let acc = sum8x4(&h, &w);
            for c in 0..4 {
                out[c] += acc[c];
            }
            return;
        }
        for (&o, &wc) in offsets.iter().zip(&w) {
            for (x, &v) in out[..n].iter_mut().zip(&values[o..o + n]) {
                *x += wc * v.to_f32();
            }
        }
    }

    /// The values at a baked sample into `out[..n]` (`n = 1`: the density alone).
    #[inline(always)]
    fn interpolate<const F16C: bool>(&self, at: Source, local: Vec3, out: &mut [f32], n: usize) {
        out[..n].fill(0.0);
        match at {
            Source::Static(slot) => {
                self.interpolate_into::<F16C>(&self.values, slot as usize, local, 1.0, out, n)
            }
            Source::Slices { d, k0, k1, f } => {
                let s = &self.dynamic.slices;
                let (Some(a), Some(b)) = (&s[k0], &s[k1]) else {
                    return;
                };
                self.interpolate_into::<F16C>(&a.values, d as usize, local, 1.0 - f, out, n);
                if f > 0.0 {
                    self.interpolate_into::<F16C>(&b.values, d as usize, local, f, out, n);
                }
            }
        }
    }

    /// What the step whose midpoint is at unit point `u` finds, with the frame's slices.
    #[inline(always)]
    fn lookup(&self, u: Vec3, v: Vec3, slices: Option<TimeSlices>) -> Lookup {
        let g = self.geometry;
        let r = g.resolution;
        let rf = r as f32;
        let cell = [
            ((u.x * rf) as u32).min(r - 1),
            ((u.y * rf) as u32).min(r - 1),
            ((u.z * rf) as u32).min(r - 1),
        ];
        let b = g.brick;
        // Brick and index sides are powers of two ([`VolumeGeometry::new`]): shifts, not
        // divisions, on every step.
        debug_assert!(b.is_power_of_two() && g.bricks_per_side().is_power_of_two());
        let bs = b.trailing_zeros();
        let is = g.bricks_per_side().trailing_zeros();
        let brick = [cell[0] >> bs, cell[1] >> bs, cell[2] >> bs];
        let entry = self.index[(brick[0] | ((brick[1] | (brick[2] << is)) << is)) as usize];
        let cell_len = 1.0 / rf;
        if entry == OUTSIDE_BRICK {
            return Lookup::Outside;
        }
        if entry == EMPTY_BRICK {
            let lo = Vec3::new(brick[0] as f32, brick[1] as f32, brick[2] as f32) * (b as f32);
            return Lookup::Skip(
                exit_distance(u, v, lo * cell_len, (lo + b as f32) * cell_len),
                false,
            );
        }
        let lc = [cell[0] & (b - 1), cell[1] & (b - 1), cell[2] & (b - 1)];
        let bit = (lc[0] | ((lc[1] | (lc[2] << bs)) << bs)) as usize;
        let fw = g.flag_words();
        let mask = 1u32 << (bit & 31);
        let origin = Vec3::new(
            (brick[0] * b) as f32,
            (brick[1] * b) as f32,
            (brick[2] * b) as f32,
        );
        let local = u * rf - origin;
        let skip_cell = || {
            let lo = Vec3::new(cell[0] as f32, cell[1] as f32, cell[2] as f32);
            Lookup::Skip(
                exit_distance(u, v, lo * cell_len, (lo + 1.0) * cell_len),
                false,
            )
        };
        if entry & DYNAMIC_BRICK == 0 {
            let word = entry as usize * fw + (bit >> 5);
            if self.occupied[word] & mask == 0 {
                return skip_cell();
            }
            return Lookup::Baked {
                at: Source::Static(entry),
                local,
                dynamic: false,
            };
        }
        let d = (entry & !DYNAMIC_BRICK) as usize;
        let Some(TimeSlices { k0, k1, f }) = slices else {
            return Lookup::Exact(u);
        };
        let word = d * fw + (bit >> 5);
        let s = &self.dynamic.slices;
        let occupied = |k: usize| s[k].as_ref().is_some_and(|x| x.occupied[word] & mask != 0);
        let dynamic = self.dynamic.cells[word] & mask != 0;
        if !(occupied(k0) || f > 0.0 && occupied(k1)) {
            // A dynamic cell empty now may hold something at another time: the ray depends on
            // the time all the same.
            return match skip_cell() {
                Lookup::Skip(d, _) => Lookup::Skip(d, dynamic),
                other => other,
            };
        }
        // A cell the mask leaves static holds the same values in every slice: read one, so that
        // its samples do not depend on the time even by a rounding.
        let (k1, f) = if dynamic { (k1, f) } else { (k0, 0.0) };
        Lookup::Baked {
            at: Source::Slices {
                d: d as u32,
                k0,
                k1,
                f,
            },
            local,
            dynamic,
        }
    }
}

/// Renders `rays` through `vol` (one thread's chunk): appends one entry per ray to `out`.
/// `params` is the flat buffer for the rays' time (the dynamic samples read its 4D rows).
///
/// Where the CPU has AVX2, FMA and F16C (checked once, at run time) the walk is compiled for
/// them ([`x86::march_chunk`]); the outputs are the same to the bit as the portable walk's
/// ([`march_chunk_portable`]), which every other CPU runs.
#[allow(clippy::too_many_arguments)]
pub fn march_chunk(
    vol: &Volume,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    settings: &MarchSettings,
    ws: &mut MarchWorkspace,
    out: &mut MarchOutput,
) {
    #[cfg(target_arch = "x86_64")]
    if x86::available() {
        // SAFETY: the CPU has the features `x86::march_chunk` is compiled for.
        unsafe { x86::march_chunk(vol, cfg, layout, params, rays, settings, ws, out) };
        return;
    }
    march_chunk_portable(vol, cfg, layout, params, rays, settings, ws, out);
}

/// Whether [`march_chunk`] runs the walk compiled for AVX2, FMA and F16C on this CPU.
pub fn simd_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        x86::available()
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// [`march_chunk`] compiled for the baseline of the target: the reference the x86 walk is tested
/// against.
#[allow(clippy::too_many_arguments)]
pub fn march_chunk_portable(
    vol: &Volume,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    settings: &MarchSettings,
    ws: &mut MarchWorkspace,
    out: &mut MarchOutput,
) {
    march_chunk_with::<false>(vol, cfg, layout, params, rays, settings, ws, out);
}

/// The walk of [`march_chunk`]; `F16C` reads the vertices with F16C instructions (only within
/// [`x86::march_chunk`]).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn march_chunk_with<const F16C: bool>(
    vol: &Volume,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    settings: &MarchSettings,
    ws: &mut MarchWorkspace,
    out: &mut MarchOutput,
) {
    let n = rays.len();
    let payload = vol.payload();
    let nch = 1 + payload;
    let per_sample = vol.colour == ColourMode::PerSample;
    let last_sample_bg = matches!(cfg.background, Background::LastSample);
    ws.states.clear();
    ws.states.resize(n, RayState::default());
    ws.features.clear();
    ws.features.resize(n * payload, 0.0);
    ws.last.clear();
    ws.last.resize(n * nch, 0.0);
    ws.entries.clear();
    ws.values.clear();
    ws.dyn_points.clear();
    ws.dyn_rows.clear();
    ws.dyn_rays.clear();
    ws.colour_in.clear();
    ws.per_sample.clear();
    ws.sample.resize(nch, 0.0);
    let res = vol.geometry.resolution as f32;
    let h = settings.step.max(1e-3) / res;
    let stop = settings.stop_transmittance;
    let max_steps = 16 * vol.geometry.resolution as usize + 64;
    let mut samples = 0usize;
    let mut steps = 0usize;

    // Walk: composite static samples directly until a ray's first dynamic sample, then record.
    for (ri, ray) in rays.iter().enumerate() {
        let (near, far) = ray_limits(cfg, ray);
        let st = &mut ws.states[ri];
        st.transmittance = 1.0;
        st.far = far;
        if far <= near {
            st.missed = true;
            continue;
        }
        let time = sample_time(ray.time);
        let slices = vol.slices_for(time);
        let mut t = near;
        let mut recording = false;
        // Transmittance of the recorded static samples alone: the walk stops when it is spent
        // (dynamic samples count as transparent until they are evaluated).
        let mut t_rec = 1.0f32;
        let entries_start = ws.entries.len();
        let mut k = 0usize;
        // Where the unit point moves at one velocity, `u0 + v t` for `t` in `[t0, t1]` (with the
        // world length of a step there): along the whole ray in a box, inside the inner cube of
        // a contracted scene (the contraction is the identity there).
        let affine = match cfg.bounds {
            SceneBounds::Box { min, max } => {
                let v = unit_velocity(&cfg.bounds, ray.origin, ray.dir);
                let speed = v.length();
                if !(speed > 0.0 && speed.is_finite()) {
                    st.missed = true;
                    continue;
                }
                let u0 = (ray.origin - min) / (max - min);
                Some((f32::NEG_INFINITY, f32::INFINITY, u0, v, h / speed))
            }
            SceneBounds::Contracted { center, radius } => inner_segment(center, radius, ray, h),
        };
        while t < far && k < max_steps {
            k += 1;
            let along = affine.and_then(|(t0, t1, u0, v, step)| {
                let dt = step.min(far - t).max(1e-7 * t.abs().max(1.0));
                let tm = t + 0.5 * dt;
                (t >= t0 && tm <= t1).then(|| (dt, (u0 + v * tm).clamp(Vec3::ZERO, Vec3::ONE), v))
            });
            let (dt, um, vm) = match along {
                Some(s) => s,
                None => {
                    let x = ray.origin + ray.dir * t;
                    let v = unit_velocity(&cfg.bounds, x, ray.dir);
                    let speed = v.length();
                    if !(speed > 0.0 && speed.is_finite()) {
                        break;
                    }
                    let dt = (h / speed).min(far - t).max(1e-7 * t.abs().max(1.0));
                    let xm = ray.origin + ray.dir * (t + 0.5 * dt);
                    (
                        dt,
                        cfg.bounds.to_unit(xm),
                        unit_velocity(&cfg.bounds, xm, ray.dir),
                    )
                }
            };
            let tm = t + 0.5 * dt;
            match vol.lookup(um, vm, slices) {
                Lookup::Skip(d, dynamic) => {
                    st.dynamic |= dynamic;
                    // Past the boundary by a hair, and never backwards.
                    t = (tm + d + 1e-3 * dt).max(t + 1e-3 * dt);
                    continue;
                }
                Lookup::Outside => {
                    st.outside = true;
                    break;
                }
                Lookup::Exact(u) => {
                    recording = true;
                    let row = (ws.values.len() / nch) as u32;
                    ws.values.resize(ws.values.len() + nch, 0.0);
                    ws.dyn_points.extend_from_slice(&[u.x, u.y, u.z, time]);
                    ws.dyn_rows.push(row);
                    ws.dyn_rays.push(ri as u32);
                    ws.entries.push(Entry {
                        delta: dt,
                        t_end: t + dt,
                        row,
                        exact: true,
                        dynamic: true,
                    });
                }
                Lookup::Baked { at, local, dynamic } => {
                    // The density alone first where features are costly to interpolate.
                    let n_density = if !recording && nch > 4 { 1 } else { nch };
                    vol.interpolate::<F16C>(at, local, &mut ws.sample, n_density);
                    let tau = tau_of(trunc_exp(ws.sample[0]), dt);
                    if recording {
                        let row = (ws.values.len() / nch) as u32;
                        ws.values.extend_from_slice(&ws.sample[..nch]);
                        ws.entries.push(Entry {
                            delta: dt,
                            t_end: t + dt,
                            row,
                            exact: false,
                            dynamic,
                        });
                        t_rec *= (-tau).exp();
                    } else {
                        samples += 1;
                        st.dynamic |= dynamic;
                        let alpha = 1.0 - (-tau).exp();
                        let w = st.transmittance * alpha;
                        if w >= MIN_FEATURE_WEIGHT || last_sample_bg {
                            if n_density == 1 {
                                vol.interpolate::<F16C>(at, local, &mut ws.sample, nch);
                            }
                            if last_sample_bg {
                                ws.last[ri * nch..(ri + 1) * nch].copy_from_slice(&ws.sample);
                                st.has_last = true;
                            }
                            if w >= MIN_FEATURE_WEIGHT {
                                add_payload(
                                    per_sample,
                                    ri,
                                    w,
                                    &ws.sample,
                                    &mut ws.features[ri * payload..(ri + 1) * payload],
                                    &mut ws.colour_in,
                                    &mut ws.per_sample,
                                );
                                st.weight += w;
                            }
                        }
                        st.transmittance *= 1.0 - alpha;
                        if st.transmittance < stop {
                            st.visible_depth = Some(t + dt);
                            break;
                        }
                    }
                }
            }
            t += dt;
            if recording && st.transmittance * t_rec < stop {
                break;
            }
        }
        steps += k;
        st.entries = (entries_start, ws.entries.len());
    }

    evaluate_dynamic(vol, layout, params, rays, ws, nch);

    // Composite the recorded samples in order.
    let mut dynamic_samples = 0usize;
    for ri in 0..n {
        let st = &mut ws.states[ri];
        let (a, b) = st.entries;
        for e in &ws.entries[a..b] {
            if st.transmittance < stop {
                break;
            }
            samples += 1;
            st.dynamic |= e.dynamic;
            if e.exact {
                dynamic_samples += 1;
            }
            let vals = &ws.values[e.row as usize * nch..(e.row as usize + 1) * nch];
            let tau = tau_of(trunc_exp(vals[0]), e.delta);
            let alpha = -(-tau).exp_m1();
            let w = st.transmittance * alpha;
            if last_sample_bg {
                ws.last[ri * nch..(ri + 1) * nch].copy_from_slice(vals);
                st.has_last = true;
            }
            if w >= MIN_FEATURE_WEIGHT {
                add_payload(
                    per_sample,
                    ri,
                    w,
                    vals,
                    &mut ws.features[ri * payload..(ri + 1) * payload],
                    &mut ws.colour_in,
                    &mut ws.per_sample,
                );
                st.weight += w;
            }
            st.transmittance *= 1.0 - alpha;
            if st.transmittance < stop && st.visible_depth.is_none() {
                st.visible_depth = Some(e.t_end);
            }
        }
    }

    colour(vol, cfg, layout, params, rays, ws, out);
    for st in &ws.states {
        out.visible_depth.push(
            st.visible_depth
                .unwrap_or(if st.missed { 0.0 } else { st.far }),
        );
        out.dynamic.push(st.dynamic);
        out.outside.push(st.outside);
    }
    out.samples += samples;
    out.dynamic_samples += dynamic_samples;
    out.steps += steps;
}

/// `sum_j w[j] h[j]` of 8 vertices' 4 binary16 values, in vertex order, a multiply and an add
/// per term (what [`x86::sum8x4`] computes to the bit).
#[inline(always)]
fn sum8x4(h: &[[Value; 4]; 8], w: &[f32; 8]) -> [f32; 4] {
    let mut v = [0f32; 32];
    h.as_flattened().convert_to_f32_slice(&mut v);
    let mut acc = [0f32; 4];
    for (j, &wc) in w.iter().enumerate() {
        for c in 0..4 {
            acc[c] += wc * v[j * 4 + c];
        }
    }
    acc
}

/// The walk compiled for AVX2, FMA and F16C. Rust never contracts a multiply and an add into an
/// FMA, so the walk computes what the portable one computes, with wider registers and the
/// binary16 conversions inlined.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::*;

    /// Whether this CPU runs [`march_chunk`] (cached by the standard library).
    pub fn available() -> bool {
        is_x86_feature_detected!("avx2")
            && is_x86_feature_detected!("fma")
            && is_x86_feature_detected!("f16c")
    }

    /// [`super::march_chunk`] for a CPU with AVX2, FMA and F16C.
    ///
    /// # Safety
    /// The CPU must have AVX2, FMA and F16C ([`available`]).
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2,fma,f16c")]
    pub unsafe fn march_chunk(
        vol: &Volume,
        cfg: &ModelConfig,
        layout: &ModelLayout,
        params: &[f32],
        rays: &[TimedRay],
        settings: &MarchSettings,
        ws: &mut MarchWorkspace,
        out: &mut MarchOutput,
    ) {
        march_chunk_with::<true>(vol, cfg, layout, params, rays, settings, ws, out);
    }

    /// [`super::sum8x4`] with one F16C conversion per vertex and the channels in one register.
    ///
    /// # Safety
    /// The CPU must have F16C.
    #[inline]
    #[target_feature(enable = "avx2,fma,f16c")]
    pub unsafe fn sum8x4(h: &[[Value; 4]; 8], w: &[f32; 8]) -> [f32; 4] {
        let mut acc = _mm_setzero_ps();
        for (q, &wc) in h.iter().zip(w) {
            // SAFETY: `q` is 4 binary16 values, 8 bytes, read unaligned.
            let bits = unsafe { _mm_loadl_epi64(q.as_ptr().cast::<__m128i>()) };
            let v = _mm_cvtph_ps(bits);
            acc = _mm_add_ps(acc, _mm_mul_ps(_mm_set1_ps(wc), v));
        }
        let mut out = [0f32; 4];
        // SAFETY: `out` holds 4 floats.
        unsafe { _mm_storeu_ps(out.as_mut_ptr(), acc) };
        out
    }
}

/// The dynamic samples of the whole chunk in one pass of the exact field: their density and,
/// for a baked volume, their colour at their ray's direction (else their features).
fn evaluate_dynamic(
    vol: &Volume,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    ws: &mut MarchWorkspace,
    nch: usize,
) {
    let nd = ws.dyn_rows.len();
    if nd == 0 {
        return;
    }
    ws.field.enc.static_cutoff = VOLUME_STATIC_CUTOFF;
    layout
        .field
        .forward_density(params, &ws.dyn_points, nd, &mut ws.field);
    let (dm, _) = &layout.field.density;
    let w = dm.output_dim();
    let geo = vol.geo;
    let o = dm.output(&ws.field.density_acts);
    if vol.colour != ColourMode::Baked {
        for (j, &row) in ws.dyn_rows.iter().enumerate() {
            let dst = &mut ws.values[row as usize * nch..(row as usize + 1) * nch];
            dst.copy_from_slice(&o[j * w..j * w + nch]);
        }
        return;
    }
    let cw = SH_COEFFS + geo;
    ws.colour_in.clear();
    ws.colour_in.reserve(nd * cw);
    let mut sh = [0f32; SH_COEFFS];
    for (j, &ri) in ws.dyn_rays.iter().enumerate() {
        dir_sh(&rays[ri as usize], &mut sh);
        ws.colour_in.extend_from_slice(&sh);
        ws.colour_in
            .extend_from_slice(&o[j * w + 1..j * w + 1 + geo]);
    }
    let (cm, cr) = &layout.field.color;
    cm.forward(&params[cr.clone()], &ws.colour_in, nd, &mut ws.colour_acts);
    let c = cm.output(&ws.colour_acts);
    for (j, &row) in ws.dyn_rows.iter().enumerate() {
        let dst = &mut ws.values[row as usize * nch..(row as usize + 1) * nch];
        dst[0] = o[j * w];
        for k in 0..3 {
            dst[1 + k] = sigmoid(c[j * 3 + k]);
        }
    }
    ws.colour_in.clear();
}

/// The direction encoding of a ray.
fn dir_sh(ray: &TimedRay, sh: &mut [f32; SH_COEFFS]) {
    let d = if ray.dir.is_finite() {
        ray.dir.normalize_or_zero()
    } else {
        Vec3::ZERO
    };
    sh4([d.x, d.y, d.z], sh);
}

/// Adds a sample's payload with weight `w`: into the ray's sum (a colour, or features for
/// deferred shading) or as a row of the colour MLP's input (per sample).
#[inline]
fn add_payload(
    per_sample: bool,
    ray: usize,
    w: f32,
    vals: &[f32],
    sum: &mut [f32],
    colour_in: &mut Vec<f32>,
    rows: &mut Vec<(u32, f32)>,
) {
    if per_sample {
        colour_in.extend(std::iter::repeat_n(0.0, SH_COEFFS));
        colour_in.extend_from_slice(&vals[1..]);
        rows.push((ray as u32, w));
    } else {
        for (s, &x) in sum.iter_mut().zip(&vals[1..]) {
            *s += w * x;
        }
    }
}

/// The colour of every ray of the chunk, appended to `out.rgb`.
fn colour(
    vol: &Volume,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    rays: &[TimedRay],
    ws: &mut MarchWorkspace,
    out: &mut MarchOutput,
) {
    let payload = vol.payload();
    let nch = 1 + payload;
    let cw = SH_COEFFS + vol.geo;
    let (cm, cr) = &layout.field.color;
    let bg = match cfg.background {
        Background::Color { rgb } => Some(rgb),
        Background::LastSample => None,
    };
    let mut sh = [0f32; SH_COEFFS];
    match vol.colour {
        ColourMode::Baked => {
            for (ri, st) in ws.states.iter().enumerate() {
                let f = &ws.features[ri * 3..ri * 3 + 3];
                let rest = match bg {
                    Some(c) => c,
                    // The transmittance left takes the last sample's colour, as the exact
                    // renderer.
                    None if st.has_last => {
                        let l = &ws.last[ri * nch + 1..ri * nch + 4];
                        [l[0], l[1], l[2]]
                    }
                    None => [0.0; 3],
                };
                out.rgb.push([
                    f[0] + st.transmittance * rest[0],
                    f[1] + st.transmittance * rest[1],
                    f[2] + st.transmittance * rest[2],
                ]);
            }
        }
        ColourMode::PerSample => {
            // Rows so far: the weighted samples; then the last sample of LastSample rays,
            // weighted by the transmittance left.
            for (ri, st) in ws.states.iter().enumerate() {
                if bg.is_none() && st.has_last && st.transmittance > 0.0 {
                    ws.colour_in.extend(std::iter::repeat_n(0.0, SH_COEFFS));
                    ws.colour_in
                        .extend_from_slice(&ws.last[ri * nch + 1..(ri + 1) * nch]);
                    ws.per_sample.push((ri as u32, st.transmittance));
                }
            }
            for (k, &(ri, _)) in ws.per_sample.iter().enumerate() {
                dir_sh(&rays[ri as usize], &mut sh);
                ws.colour_in[k * cw..k * cw + SH_COEFFS].copy_from_slice(&sh);
            }
            let m = ws.per_sample.len();
            let mut rgb: Vec<[f32; 3]> = ws
                .states
                .iter()
                .map(|st| match bg {
                    Some(c) => [
                        st.transmittance * c[0],
                        st.transmittance * c[1],
                        st.transmittance * c[2],
                    ],
                    None => [0.0; 3],
                })
                .collect();
            if m > 0 {
                cm.forward(&params[cr.clone()], &ws.colour_in, m, &mut ws.colour_acts);
                let o = cm.output(&ws.colour_acts);
                for (k, &(ri, w)) in ws.per_sample.iter().enumerate() {
                    for c in 0..3 {
                        rgb[ri as usize][c] += w * sigmoid(o[k * 3 + c]);
                    }
                }
            }
            out.rgb.extend_from_slice(&rgb);
        }
        ColourMode::Deferred => {
            let geo = vol.geo;
            ws.colour_in.clear();
            let mut rows: Vec<u32> = Vec::with_capacity(rays.len());
            for (ri, st) in ws.states.iter().enumerate() {
                let f = &ws.features[ri * geo..(ri + 1) * geo];
                let (total, mut g) = (st.weight, f.to_vec());
                let total = match bg {
                    Some(_) => total,
                    None => {
                        // The transmittance left takes the last sample's features.
                        if st.has_last {
                            for (x, &l) in g.iter_mut().zip(&ws.last[ri * nch + 1..(ri + 1) * nch])
                            {
                                *x += st.transmittance * l;
                            }
                            total + st.transmittance
                        } else {
                            total
                        }
                    }
                };
                if total > 0.0 {
                    dir_sh(&rays[ri], &mut sh);
                    ws.colour_in.extend_from_slice(&sh);
                    ws.colour_in.extend(g.iter().map(|x| x / total));
                    rows.push(ri as u32);
                }
            }
            let mut rgb: Vec<[f32; 3]> = ws
                .states
                .iter()
                .map(|st| match bg {
                    Some(c) => [
                        st.transmittance * c[0],
                        st.transmittance * c[1],
                        st.transmittance * c[2],
                    ],
                    None => [0.0; 3],
                })
                .collect();
            if !rows.is_empty() {
                cm.forward(
                    &params[cr.clone()],
                    &ws.colour_in,
                    rows.len(),
                    &mut ws.colour_acts,
                );
                let o = cm.output(&ws.colour_acts);
                for (k, &ri) in rows.iter().enumerate() {
                    let st = &ws.states[ri as usize];
                    let scale = if bg.is_some() { st.weight } else { 1.0 };
                    for c in 0..3 {
                        rgb[ri as usize][c] += scale * sigmoid(o[k * 3 + c]);
                    }
                }
            }
            out.rgb.extend_from_slice(&rgb);
        }
    }
}
