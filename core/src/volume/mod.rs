//! The play-time volume: the model's time-independent field baked once into a sparse grid, so
//! that a moving camera reads a few values per sample instead of evaluating hash grids and MLPs.
//!
//! # What is stored
//! The unit cube is cut into `R^3` cells, grouped into bricks of `B^3` cells (`B` =
//! [`VolumeGeometry::brick`]). A brick that can hold something visible gets a slot in the pool;
//! the others are empty and a ray skips them whole. A slot holds, at each of its `(B + 1)^3`
//! vertices (a brick keeps its own border vertices, so a sample never reads a neighbour), as
//! f32: the density MLP's pre-activation for the static encoding (`sigma = trunc_exp` of
//! it), then the colour ([`ColourMode::Baked`]: the colour MLP's output for a reference view
//! direction) or the geometry features the colour MLP reads (the other modes). With them, one
//! bit per cell says whether the cell can hold density (its 8 corners bound the interpolated
//! density: a cell whose corners all lie below the threshold is skipped), and one whether the
//! mask leaves it dynamic.
//!
//! # Static and dynamic bricks
//! A brick with a cell the mask leaves dynamic (at least [`RENDER_STATIC_CUTOFF`] of the 4D grid
//! at one of its corners, the exact renderer's own cutoff) is a *dynamic brick*: its values
//! depend on time, so it is baked once per *time slice* ([`DynamicPart`]), at the model's frame
//! times, when a frame first needs the slice. A sample there interpolates between the two slices
//! around the frame's time. Until those slices are baked, a dynamic brick's samples are the exact
//! field at the ray's time (3D and 4D grids, mask, density and colour MLPs). Every other brick is
//! baked once, for all times.
//!
//! Baking a slice costs the dynamic bricks' vertices once; evaluating the dynamic samples exactly
//! costs one field evaluation per sample, every frame. docs/playback.md measures both.
//!
//! # Colour: baked for a reference direction
//! The colour MLP takes the view direction. Baking it for one direction per vertex (the mean
//! direction from the file's cameras to the vertex, [`reference_direction`]) leaves no network
//! at all in a static sample: four values interpolated. The players' models are trained on
//! views around those cameras, where their colour varies little with the direction; what the
//! reference direction costs, and what the alternatives cost (the colour MLP per sample on
//! baked features, or once per ray on composited features, SNeRG's deferred shading), is
//! measured in docs/playback.md with `msth eval FILE.msth --renderer both --colour MODE`.
//!
//! # Modules
//! - [`bake`]: choosing the resolution for a memory budget, the bricks to bake, the bake;
//! - [`march`]: the renderer over a volume on the CPU; msth-gpu's `volume.wgsl` is the same
//!   march on the GPU (the native player's, and the web page's: `web/js/volume.js`).

use crate::config::ModelConfig;
use crate::pipeline::RENDER_STATIC_CUTOFF;

pub mod bake;
pub mod march;
pub mod views;

pub use bake::{
    plan, BakeError, BakePlan, BakeProgress, BakeScratch, Occupancy, OutsideViews,
    DEFAULT_CPU_BUDGET,
};
pub use march::{ColourMode, MarchOutput, MarchSettings, MarchWorkspace};

/// How a vertex value is held: binary16, half the memory of f32, so that a budget holds twice
/// the bricks. Its relative rounding (2^-11) moves a density by less than 0.3% at the
/// pre-activations trained models reach (below 6) and a colour by less than 1/2000.
pub type Value = half::f16;

/// The brick index's mark for a brick with nothing to draw.
pub const EMPTY_BRICK: u32 = u32::MAX;

/// The brick index's mark for an occupied brick the volume leaves out because none of the file's
/// cameras looks into it ([`bake::PlanOptions::views`]): a ray that reaches one is rendered by
/// the exact path instead ([`march::MarchOutput::outside`]).
pub const OUTSIDE_BRICK: u32 = u32::MAX - 1;

/// The smallest brick side, in cells.
pub const MIN_BRICK: u32 = 4;

/// The brick index is at most this many bricks per side (128^3 entries, 8 MiB), so finer volumes
/// get larger bricks.
pub const MAX_INDEX_RESOLUTION: u32 = 128;

/// The coarsest volume a bake falls back to under a small budget (cells per side).
pub const MIN_VOLUME_RESOLUTION: u32 = 32;

/// The finest volume (cells per side). A model asks for its finest grid's resolution
/// ([`model_resolution`]); `--volume-resolution` may ask for up to twice that of a 1024 grid,
/// whose cells then sample the field between its finest grid's vertices.
pub const MAX_VOLUME_RESOLUTION: u32 = 2048;

/// Values per vertex: the density pre-activation and the colour (4 values), or with features
/// the geometry features, padded to a whole number of 8 values. Each is held as binary16
/// ([`Value`]).
pub fn channels_for(colour: ColourMode, geo_features: usize) -> usize {
    match colour {
        ColourMode::Baked => 4,
        _ => (1 + geo_features).div_ceil(8) * 8,
    }
}

/// The view direction a vertex's colour is baked for ([`ColourMode::Baked`]): the mean of the
/// unit directions from `eyes` (the file's camera centres) to world point `x`; where those
/// cancel out (a point at the centre of a ring of cameras), the direction from the first.
pub fn reference_direction(eyes: &[glam::Vec3], x: glam::Vec3) -> glam::Vec3 {
    let sum: glam::Vec3 = eyes.iter().map(|&e| (x - e).normalize_or_zero()).sum();
    if sum.length() > 0.1 * eyes.len() as f32 {
        sum.normalize()
    } else {
        eyes.first()
            .map(|&e| (x - e).normalize_or_zero())
            .filter(|d| *d != glam::Vec3::ZERO)
            .unwrap_or(glam::Vec3::NEG_Z)
    }
}

/// Cells per side, brick side and the index's resolution of one volume.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct VolumeGeometry {
    /// Cells per side of the unit cube (`R`), a multiple of `brick`.
    pub resolution: u32,
    /// Cells per side of a brick (`B`).
    pub brick: u32,
}

impl VolumeGeometry {
    /// The geometry of a volume of `resolution` cells per side (rounded up to a power of two
    /// within [`MIN_VOLUME_RESOLUTION`]..=[`MAX_VOLUME_RESOLUTION`]): bricks of
    /// [`MIN_BRICK`] cells, larger where the index would exceed [`MAX_INDEX_RESOLUTION`].
    pub fn new(resolution: u32) -> Self {
        let r = resolution
            .clamp(MIN_VOLUME_RESOLUTION, MAX_VOLUME_RESOLUTION)
            .next_power_of_two();
        let brick = (r / MAX_INDEX_RESOLUTION).max(MIN_BRICK);
        VolumeGeometry {
            resolution: r,
            brick,
        }
    }

    /// Bricks per side (`I = R / B`).
    pub fn bricks_per_side(&self) -> u32 {
        self.resolution / self.brick
    }

    /// Entries of the brick index (`I^3`).
    pub fn index_len(&self) -> usize {
        (self.bricks_per_side() as usize).pow(3)
    }

    /// Vertices a slot holds (`(B + 1)^3`).
    pub fn vertices_per_brick(&self) -> usize {
        (self.brick as usize + 1).pow(3)
    }

    /// Cells of one brick (`B^3`).
    pub fn cells_per_brick(&self) -> usize {
        (self.brick as usize).pow(3)
    }

    /// 32-bit words of one of a slot's cell bitsets.
    pub fn flag_words(&self) -> usize {
        self.cells_per_brick().div_ceil(32)
    }

    /// Bytes of one slot with `channels` binary16 values per vertex (values and both bitsets).
    pub fn slot_bytes(&self, channels: usize) -> u64 {
        (self.vertices_per_brick() * channels * 2 + self.flag_words() * 8) as u64
    }
}

/// The volume a model asks for: its main grid's finest spatial resolution, within the bounds
/// above (the bake may take less for the memory budget).
pub fn model_resolution(cfg: &ModelConfig) -> u32 {
    let g = &cfg.field.encoding.grid3;
    let finest = g
        .finest_resolution
        .iter()
        .take(3)
        .fold(0f32, |a, &b| a.max(b));
    let finest = if finest.is_finite() && finest > 0.0 {
        finest as u32
    } else {
        MIN_VOLUME_RESOLUTION
    };
    VolumeGeometry::new(finest).resolution
}

/// Whether a volume can help `cfg` at all: it needs a static part, i.e. a 3D grid and either no
/// 4D grid or a mask that can leave points to the 3D grid alone.
pub fn has_static_part(cfg: &ModelConfig) -> bool {
    let blend = cfg.field.encoding.blend;
    blend.uses_h3() && (!blend.uses_h4() || blend.uses_mask())
}

/// What a bake produced and what it cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct BakeStats {
    /// Bricks the occupancy grid left to bake.
    pub candidate_bricks: usize,
    /// Bricks kept (something visible or dynamic in them).
    pub bricks: usize,
    /// Cells of the kept bricks that can hold density.
    pub occupied_cells: usize,
    /// Of those bricks, the dynamic ones (baked per time slice).
    pub dynamic_bricks: usize,
    /// Cells of the dynamic bricks the mask leaves dynamic.
    pub dynamic_cells: usize,
    /// Time slices the dynamic bricks get (the model's frames, or fewer under the budget).
    pub slices: usize,
    /// Field evaluations the bake made.
    pub vertices_evaluated: usize,
    /// Wall time of the bake, seconds.
    pub seconds: f64,
}

/// [`Volume::index`]'s mark of a dynamic brick: the low bits are its number in
/// [`DynamicPart::bricks`].
pub const DYNAMIC_BRICK: u32 = 1 << 31;

/// A baked volume: the brick index, the static slots' cell bitsets and vertex values, and the
/// dynamic bricks.
#[derive(Clone, Debug, PartialEq)]
pub struct Volume {
    pub geometry: VolumeGeometry,
    /// What the vertices hold besides the density.
    pub colour: ColourMode,
    /// Geometry features per vertex (the colour MLP's input besides the direction).
    pub geo: usize,
    /// Binary16 values per vertex ([`channels_for`]).
    pub channels: usize,
    /// Density (world units^-1) below which a cell counts as empty.
    pub density_threshold: f32,
    /// `I^3` entries, brick `(x, y, z)` at `x + I (y + I z)`: a static slot, [`DYNAMIC_BRICK`]
    /// `| d` for dynamic brick `d`, [`OUTSIDE_BRICK`] or [`EMPTY_BRICK`].
    pub index: Vec<u32>,
    /// Per static slot, [`VolumeGeometry::flag_words`] words: cell `(x, y, z)` of the brick at
    /// bit `x + B (y + B z)` can hold density.
    pub occupied: Vec<u32>,
    /// Per static slot, `(B + 1)^3` vertices (vertex `(x, y, z)` at
    /// `x + (B + 1) (y + (B + 1) z)`), each `channels` values: the density
    /// pre-activation, then the colour (red, green, blue in `[0, 1]`) or the geometry features,
    /// then zeros.
    pub values: Vec<Value>,
    pub dynamic: DynamicPart,
    /// How the bake went.
    pub stats: BakeStats,
}

/// The dynamic bricks: which they are, which of their cells the mask leaves dynamic, and their
/// time slices as far as they are baked.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DynamicPart {
    /// Brick index entry (`x + I (y + I z)`) of each dynamic brick.
    pub bricks: Vec<u32>,
    /// Per dynamic brick, [`VolumeGeometry::flag_words`] words: the cells the mask leaves
    /// dynamic (a ray that composites a sample there has a colour that changes with time).
    pub cells: Vec<u32>,
    /// The slices' times, evenly over `[0, 1]` (the model's frame times when they fit).
    pub times: Vec<f32>,
    /// Per time, the slice once baked.
    pub slices: Vec<Option<Slice>>,
}

/// The dynamic bricks at one time: per brick, the cells that can hold density then and the
/// vertex values (layouts as the static slots').
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Slice {
    pub occupied: Vec<u32>,
    pub values: Vec<Value>,
}

impl DynamicPart {
    /// The slices on either side of time `t` and the weight of the second, `(k0, k1, f)`
    /// (`k0 == k1` at a slice's own time); `None` without slices.
    pub fn around(&self, t: f32) -> Option<(usize, usize, f32)> {
        let k = self.times.len();
        if k == 0 {
            return None;
        }
        if k == 1 {
            return Some((0, 0, 0.0));
        }
        let s = crate::pipeline::sample_time(t) * (k - 1) as f32;
        let k0 = (s.floor() as usize).min(k - 1);
        let f = s - k0 as f32;
        if f <= 1e-6 || k0 + 1 >= k {
            Some((k0, k0, 0.0))
        } else if f >= 1.0 - 1e-6 {
            Some((k0 + 1, k0 + 1, 0.0))
        } else {
            Some((k0, k0 + 1, f))
        }
    }

    /// Whether the slices around `t` are baked (always, without dynamic bricks).
    pub fn ready_for(&self, t: f32) -> bool {
        if self.bricks.is_empty() {
            return true;
        }
        self.around(t)
            .is_some_and(|(a, b, _)| self.slices[a].is_some() && self.slices[b].is_some())
    }

    /// The slices `t` needs that are not baked yet.
    pub fn missing_for(&self, t: f32) -> Vec<usize> {
        if self.bricks.is_empty() {
            return Vec::new();
        }
        let Some((a, b, _)) = self.around(t) else {
            return Vec::new();
        };
        let mut v: Vec<usize> = [a, b]
            .into_iter()
            .filter(|&k| self.slices[k].is_none())
            .collect();
        v.dedup();
        v
    }

    /// Slices baked.
    pub fn baked(&self) -> usize {
        self.slices.iter().filter(|s| s.is_some()).count()
    }
}

impl Volume {
    /// Static slots in the pool.
    pub fn slots(&self) -> usize {
        self.occupied.len() / self.geometry.flag_words().max(1)
    }

    /// Bytes the volume holds now (index, bitsets, values, the slices baked so far).
    pub fn bytes(&self) -> u64 {
        let d = &self.dynamic;
        let slices: usize = d
            .slices
            .iter()
            .flatten()
            .map(|s| s.occupied.len() * 4 + s.values.len() * 2)
            .sum();
        (self.index.len() * 4
            + self.occupied.len() * 4
            + self.values.len() * 2
            + d.bricks.len() * 4
            + d.cells.len() * 4
            + slices) as u64
    }

    /// Bytes one baked slice takes.
    pub fn slice_bytes(&self) -> u64 {
        self.dynamic.bricks.len() as u64 * self.geometry.slot_bytes(self.channels)
    }

    /// Whether any brick is dynamic (the volume alone then does not describe every time).
    pub fn has_dynamic(&self) -> bool {
        !self.dynamic.bricks.is_empty()
    }
}

/// A point whose mask leaves at least this to the 4D grid is evaluated exactly by the volume
/// renderer: the exact renderer's own cutoff, so a static cell's stored values are what the exact
/// renderer computes at its vertices.
pub const VOLUME_STATIC_CUTOFF: f32 = RENDER_STATIC_CUTOFF;

#[cfg(test)]
mod tests;
