//! Baking a volume: which resolution fits the memory budget, which bricks can hold anything and
//! which of them are dynamic, and the field evaluated at their vertices.
//!
//! A bake is planned before anything large is allocated ([`plan`]): the bricks to bake are those
//! that overlap an occupied cell of the file's occupancy grid (format.md §6.5; every brick for a
//! file without one); the mask, read at their vertices, sorts them into static and dynamic
//! bricks; the resolution is the model's own ([`super::model_resolution`]) or the finest coarser
//! one whose static bricks and two time slices fit the budget.
//!
//! Baking a set of bricks (the static ones once, the dynamic ones per time slice) has three
//! phases, so that a caller can spread the costly one over threads or a GPU and show progress:
//! 1. [`eval_vertices`]: each brick evaluates the vertices it owns (its `B^3` lower corners) and
//!    the border vertices whose owner, the next brick along an axis, is not in the set;
//! 2. [`fill_borders`]: the other border vertices are copied from their owners;
//! 3. [`cell_bits`]: a cell can hold density when one of its corners reaches the threshold.
//!
//! A vertex is evaluated once, so a brick of `B = 4` costs about 64 field evaluations, not 125.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use crate::activation::{sigmoid, trunc_exp};
use crate::config::{BlendMode, ModelConfig};
use crate::field::{FieldScratch, ModelLayout};
use crate::mlp::MlpActivations;
use crate::scene::{cell_world_size, density_threshold};
use crate::sh::{sh4, SH_COEFFS};

use super::{
    channels_for, has_static_part, model_resolution, reference_direction, BakeStats, ColourMode,
    DynamicPart, Slice, Value, Volume, VolumeGeometry, DYNAMIC_BRICK, EMPTY_BRICK,
    MIN_VOLUME_RESOLUTION, OUTSIDE_BRICK, VOLUME_STATIC_CUTOFF,
};

/// The CPU renderer's default volume budget.
pub const DEFAULT_CPU_BUDGET: u64 = 512 << 20;

/// The default [`PlanOptions::min_cell_alpha`]: a cell that cannot reach this opacity is empty.
pub const DEFAULT_MIN_CELL_ALPHA: f32 = 0.0;
/// The default [`PlanOptions::min_proposal_alpha`].
pub const DEFAULT_MIN_PROPOSAL_ALPHA: f32 = 0.003;

/// The most time slices a volume keeps (one per frame of the model below this).
pub const MAX_SLICES: usize = 4096;

/// The opacity budget of the density threshold for files without an occupancy grid, as the
/// export's grid uses (`msth_codec::occupancy::DEFAULT_OCCUPANCY_ALPHA`).
const FALLBACK_ALPHA: f32 = 1e-2;

/// The resolution of the density threshold for files without an occupancy grid.
const FALLBACK_THRESHOLD_RESOLUTION: u32 = 128;

/// The file's occupancy grid, as the bake reads it (the codec's `OccupancyGrid` bit layout: cell
/// `(x, y, z)` is bit `x + R (y + R z)`, bit `i % 32` of word `i / 32`).
#[derive(Clone, Copy, Debug)]
pub struct Occupancy<'a> {
    pub resolution: u32,
    pub words: &'a [u32],
    /// The density (world units^-1) below which the export counted a vertex as empty.
    pub density_threshold: f32,
}

impl Occupancy<'_> {
    fn valid(&self) -> bool {
        let r = self.resolution as usize;
        r > 0 && r <= 4096 && self.words.len() >= (r * r * r).div_ceil(32)
    }

    fn cell(&self, x: usize, y: usize, z: usize) -> bool {
        let r = self.resolution as usize;
        let i = x + r * (y + r * z);
        (self.words[i >> 5] >> (i & 31)) & 1 == 1
    }

    /// Whether any cell overlapping the box of cells `[lo, hi)` of a grid of `res` cells per
    /// side is occupied.
    fn any_in(&self, lo: [u32; 3], hi: [u32; 3], res: u32) -> bool {
        let o = self.resolution as u64;
        let range = |a: usize| {
            let first = (lo[a] as u64 * o / res as u64) as usize;
            let last = ((hi[a] as u64 * o).div_ceil(res as u64) as usize).max(first + 1);
            first..last.min(o as usize)
        };
        let (rx, ry, rz) = (range(0), range(1), range(2));
        for z in rz {
            for y in ry.clone() {
                for x in rx.clone() {
                    if self.cell(x, y, z) {
                        return true;
                    }
                }
            }
        }
        false
    }
}

/// Why a model has no volume.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BakeError {
    /// Add and 4D-only models have nothing static; the exact renderer plays them.
    #[error("the model has no static part (blend mode {0:?}): every sample depends on time, so there is nothing to bake")]
    NoStaticPart(BlendMode),
    /// Not even the coarsest volume fits the budget.
    #[error("even a {resolution}^3 volume needs {:.1} MiB, more than its budget of {:.1} MiB (--volume-budget)", *.need as f64 / 1048576.0, *.budget as f64 / 1048576.0)]
    OverBudget {
        resolution: u32,
        need: u64,
        budget: u64,
    },
    /// The field is NaN or infinite somewhere (a corrupt file: the decoder's checks do not bound
    /// what the networks compute).
    #[error("the field is not finite at unit point ({:.4}, {:.4}, {:.4}): the file's parameters cannot be played", .0[0], .0[1], .0[2])]
    NotFinite([f32; 3]),
    #[error("the occupancy grid is malformed ({0})")]
    BadOccupancy(String),
    #[error("the bake was stopped")]
    Cancelled,
    /// The device that evaluated the vertices failed.
    #[error("the device could not bake: {0}")]
    Device(String),
}

/// Everything [`plan_with`] can be told.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanOptions {
    /// The most bytes the volume may take.
    pub budget: u64,
    /// Cells per side at most (`None`: the model's own).
    pub max_resolution: Option<u32>,
    /// A cell whose corners cannot reach this opacity over one cell counts as empty.
    pub min_cell_alpha: f32,
    /// A cell where the proposal network's density cannot reach this opacity over one cell
    /// counts as empty (0: no such test). The exact renderer places its samples where the
    /// proposal network's density is; the main field's density elsewhere (haze the proposal
    /// network learned to pass over) is never drawn by it, and a march through every cell would
    /// draw it.
    pub min_proposal_alpha: f32,
    pub colour: ColourMode,
    /// Camera centres the baked colours face (the file's cameras).
    pub eyes: Vec<glam::Vec3>,
    /// The cameras whose views the volume serves (the file's): [`PlanOptions::outside`] says
    /// what becomes of the bricks none of them looks into ([`super::views`]).
    pub views: Vec<crate::Camera>,
    pub outside: OutsideViews,
}

/// What a volume does with the occupied bricks that none of the file's cameras looks into
/// ([`PlanOptions::outside`]). A ray that reaches a brick left out is drawn by the exact path.
///
/// What they hold (haze and floaters above a forward-facing rig's images, say) no camera
/// constrained, and the two renderers draw it differently: the march reads every cell, the exact
/// renderer only where its proposal samples fall (docs/playback.md measures it on the demo).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutsideViews {
    /// Baked when every occupied brick fits the budget at a resolution; left out where that
    /// keeps a finer resolution.
    #[default]
    Auto,
    /// Always left out: the volume holds what the file's cameras saw, and the exact path draws
    /// the rest (frames as the exact renderer's, slower where a view looks beyond the cameras).
    Exact,
    /// Always baked, at a coarser resolution if need be; no ray goes to the exact path.
    Bake,
}

impl OutsideViews {
    /// The name `--volume-outside` and `?volume-outside=` take.
    pub fn name(self) -> &'static str {
        match self {
            OutsideViews::Auto => "auto",
            OutsideViews::Exact => "exact",
            OutsideViews::Bake => "bake",
        }
    }
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            budget: DEFAULT_CPU_BUDGET,
            max_resolution: None,
            min_cell_alpha: DEFAULT_MIN_CELL_ALPHA,
            min_proposal_alpha: DEFAULT_MIN_PROPOSAL_ALPHA,
            colour: ColourMode::default(),
            eyes: Vec::new(),
            views: Vec::new(),
            outside: OutsideViews::Auto,
        }
    }
}

/// What [`plan`] decided: the geometry, the bricks to bake and the memory they take at most.
#[derive(Clone, Debug, PartialEq)]
pub struct BakePlan {
    pub geometry: VolumeGeometry,
    /// The resolution the model asked for (the plan's is coarser when the budget says so).
    pub requested_resolution: u32,
    /// What the vertices hold besides the density.
    pub colour: ColourMode,
    /// Camera centres (world) the baked colours face ([`reference_direction`]).
    pub eyes: Vec<glam::Vec3>,
    pub geo: usize,
    pub channels: usize,
    /// Static bricks to bake, as index entries `x + I (y + I z)`, ascending.
    pub static_bricks: Vec<u32>,
    /// Dynamic bricks, ascending.
    pub dynamic_bricks: Vec<u32>,
    /// Per dynamic brick, the cells the mask leaves dynamic ([`DynamicPart::cells`]).
    pub dynamic_cells: Vec<u32>,
    /// The time slices' times.
    pub slice_times: Vec<f32>,
    /// How many slices may be held at once.
    pub resident_slices: usize,
    /// The density below which a cell is empty: the occupancy grid's, or the density at which
    /// one cell of the volume would reach [`BakePlan::min_cell_alpha`], whichever is larger.
    pub density_threshold: f32,
    /// The opacity one cell must be able to reach to count as occupied.
    pub min_cell_alpha: f32,
    /// The proposal network's density below which a cell is empty (0: no such test;
    /// [`PlanOptions::min_proposal_alpha`] over one cell).
    pub proposal_threshold: f32,
    /// The occupancy grid's words and resolution (cells outside it are empty), if any.
    occupancy: Option<(u32, Vec<u32>)>,
    /// Bytes of the volume before empty bricks are dropped, with its resident slices.
    pub bytes_bound: u64,
    pub budget: u64,
    /// Occupied bricks left out because no camera of [`PlanOptions::views`] looks into them
    /// (0 where everything fitted): [`BakePlan::outside_bricks`]`.len()`.
    pub outside_views: usize,
    /// Those bricks, ascending: the index marks them [`OUTSIDE_BRICK`].
    pub outside_bricks: Vec<u32>,
    /// What the plan was told to do with them.
    pub outside: OutsideViews,
}

impl BakePlan {
    /// A line for the user when the budget made the volume coarser than the model's.
    pub fn note(&self) -> Option<String> {
        let mut notes = Vec::new();
        if self.outside_views > 0 && self.outside == OutsideViews::Exact {
            notes.push(format!(
                "{} occupied bricks that none of the file's cameras looks into are left out (--volume-outside exact); rays that reach them are rendered exactly",
                self.outside_views,
            ));
        } else if self.outside_views > 0 {
            notes.push(format!(
                "{} occupied bricks that none of the file's cameras looks into are left out, so that the volume can be {}^3 cells within {} MiB; rays that reach them are rendered exactly (--volume-outside bake keeps them at a coarser resolution)",
                self.outside_views,
                self.geometry.resolution,
                self.budget >> 20
            ));
        }
        if self.geometry.resolution < self.requested_resolution {
            notes.push(format!(
                "the volume is {}^3 cells instead of {}^3, which would not fit the budget of {} MiB (--volume-budget)",
                self.geometry.resolution,
                self.requested_resolution,
                self.budget >> 20
            ));
        }
        if self.resident_slices < self.slice_times.len() {
            notes.push(format!(
                "{} of the dynamic part's {} time slices fit the budget at once: the others are baked again when needed",
                self.resident_slices,
                self.slice_times.len()
            ));
        }
        (!notes.is_empty()).then(|| notes.join("; "))
    }

    fn occupancy(&self) -> Option<Occupancy<'_>> {
        self.occupancy.as_ref().map(|(r, w)| Occupancy {
            resolution: *r,
            words: w,
            density_threshold: self.density_threshold,
        })
    }

    /// Field evaluations one slice costs.
    pub fn slice_evaluations(&self) -> usize {
        owned_counts(&self.geometry, &self.dynamic_bricks)
            .iter()
            .sum()
    }
}

/// Plans the bake of `cfg`'s volume within `budget` bytes, at most `max_resolution` cells per
/// side (`None`: the model's own). The finest resolution that fits wins.
pub fn plan(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    occupancy: Option<Occupancy<'_>>,
    budget: u64,
    max_resolution: Option<u32>,
) -> Result<BakePlan, BakeError> {
    plan_with(
        cfg,
        layout,
        params,
        occupancy,
        &PlanOptions {
            budget,
            max_resolution,
            ..Default::default()
        },
    )
}

/// [`plan`] with every option.
pub fn plan_with(
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    occupancy: Option<Occupancy<'_>>,
    o: &PlanOptions,
) -> Result<BakePlan, BakeError> {
    if !has_static_part(cfg) {
        return Err(BakeError::NoStaticPart(cfg.field.encoding.blend));
    }
    if let Some(occ) = &occupancy {
        if !occ.valid() {
            return Err(BakeError::BadOccupancy(format!(
                "{} words for resolution {}",
                occ.words.len(),
                occ.resolution
            )));
        }
    }
    let requested = o
        .max_resolution
        .map(|r| VolumeGeometry::new(r).resolution)
        .unwrap_or_else(|| model_resolution(cfg));
    let geo = cfg.field.geo_features;
    let channels = channels_for(o.colour, geo);
    let file_threshold = match &occupancy {
        Some(occ) if occ.density_threshold.is_finite() && occ.density_threshold > 0.0 => {
            occ.density_threshold
        }
        _ => density_threshold(&cfg.bounds, FALLBACK_THRESHOLD_RESOLUTION, FALLBACK_ALPHA),
    };
    let frames = cfg.num_frames.clamp(1, MAX_SLICES);
    // The plan of `candidates` at geometry `g`, or the bytes it needs at the least.
    let fit = |g: VolumeGeometry, candidates: &[u32], outside: Vec<u32>| -> Result<BakePlan, u64> {
        let slot = g.slot_bytes(channels);
        let index = g.index_len() as u64 * 4;
        // Bound the cheapest outcome first: every candidate a static slot.
        let floor = index + candidates.len() as u64 * slot;
        if floor > o.budget {
            return Err(floor);
        }
        let (static_bricks, dynamic_bricks, dynamic_cells) =
            sort_bricks(&g, layout, params, occupancy.as_ref(), candidates);
        let fixed = index
            + static_bricks.len() as u64 * slot
            + dynamic_cells.len() as u64 * 4
            + dynamic_bricks.len() as u64 * 4;
        let per_slice = dynamic_bricks.len() as u64 * slot;
        let slices = if dynamic_bricks.is_empty() {
            0
        } else {
            frames.max(2)
        };
        // At least the two slices around a frame's time must fit.
        let resident = o
            .budget
            .saturating_sub(fixed)
            .checked_div(per_slice)
            .map_or(slices, |n| n.min(slices as u64) as usize);
        if fixed > o.budget || (slices > 0 && resident < 2) {
            return Err(fixed + per_slice * slices.min(2) as u64);
        }
        let cell = cell_world_size(&cfg.bounds, g.resolution);
        let alpha = o.min_cell_alpha.clamp(0.0, 0.999_999);
        let from_alpha = -(1.0 - alpha).ln() / cell;
        let slice_times = (0..slices)
            .map(|k| k as f32 / (slices - 1).max(1) as f32)
            .collect();
        Ok(BakePlan {
            geometry: g,
            requested_resolution: requested,
            colour: o.colour,
            eyes: o.eyes.clone(),
            geo,
            channels,
            static_bricks,
            dynamic_bricks,
            dynamic_cells,
            slice_times,
            resident_slices: resident,
            density_threshold: file_threshold.max(from_alpha),
            min_cell_alpha: alpha,
            proposal_threshold: -(1.0 - o.min_proposal_alpha.clamp(0.0, 0.999_999)).ln() / cell,
            occupancy: occupancy.map(|occ| (occ.resolution, occ.words.to_vec())),
            bytes_bound: fixed + resident as u64 * per_slice,
            budget: o.budget,
            outside_views: outside.len(),
            outside_bricks: outside,
            outside: o.outside,
        })
    };
    let mut r = requested;
    loop {
        let g = VolumeGeometry::new(r);
        let candidates = candidates(&g, occupancy.as_ref());
        let leave_out = o.outside != OutsideViews::Bake && !o.views.is_empty();
        // Every occupied brick first, unless those outside the views always go.
        let mut need = u64::MAX;
        if !(leave_out && o.outside == OutsideViews::Exact) {
            match fit(g, &candidates, Vec::new()) {
                Ok(plan) => return Ok(plan),
                Err(n) => need = n,
            }
        }
        if leave_out {
            let in_view = super::views::bricks_in_view(&g, &cfg.bounds, &o.views);
            let (seen, outside): (Vec<u32>, Vec<u32>) =
                candidates.iter().partition(|&&b| in_view[b as usize]);
            // (With none outside, `Auto` has tried these bricks above.)
            if !outside.is_empty() || o.outside == OutsideViews::Exact {
                match fit(g, &seen, outside) {
                    Ok(plan) => return Ok(plan),
                    Err(n) => need = need.min(n),
                }
            }
        }
        if r <= MIN_VOLUME_RESOLUTION {
            return Err(BakeError::OverBudget {
                resolution: r,
                need,
                budget: o.budget,
            });
        }
        r /= 2;
    }
}

/// The bricks of `g` that overlap an occupied cell (every brick without a grid).
fn candidates(g: &VolumeGeometry, occupancy: Option<&Occupancy<'_>>) -> Vec<u32> {
    let i = g.bricks_per_side();
    let n = g.index_len();
    match occupancy {
        None => (0..n as u32).collect(),
        Some(o) => {
            let mut out = Vec::new();
            for z in 0..i {
                for y in 0..i {
                    for x in 0..i {
                        if o.any_in([x, y, z], [x + 1, y + 1, z + 1], i) {
                            out.push(x + i * (y + i * z));
                        }
                    }
                }
            }
            out
        }
    }
}

/// The cell `(x, y, z)` of brick `brick` in cells of the volume.
fn brick_origin(g: &VolumeGeometry, brick: u32) -> [u32; 3] {
    let i = g.bricks_per_side();
    let b = g.brick;
    [
        (brick % i) * b,
        ((brick / i) % i) * b,
        (brick / (i * i)) * b,
    ]
}

/// Sorts `candidates` into static and dynamic bricks by the mask at their vertices: a cell is
/// dynamic when the mask leaves at least [`VOLUME_STATIC_CUTOFF`] to the 4D grid at one of its
/// corners (and the occupancy grid has it). Returns the static bricks, the dynamic ones and their
/// dynamic cells.
fn sort_bricks(
    g: &VolumeGeometry,
    layout: &ModelLayout,
    params: &[f32],
    occupancy: Option<&Occupancy<'_>>,
    candidates: &[u32],
) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
    let enc = &layout.field.encoding;
    let has_mask = enc.mask.is_some();
    let blend = enc.blend;
    let b = g.brick as usize;
    let v1 = b + 1;
    let fw = g.flag_words();
    let res = g.resolution as f32;
    let (mut stat, mut dyn_bricks, mut dyn_cells) = (Vec::new(), Vec::new(), Vec::new());
    let mut vertex_dynamic = vec![false; g.vertices_per_brick()];
    for &brick in candidates {
        let o = brick_origin(g, brick);
        let mut any = false;
        for z in 0..v1 {
            for y in 0..v1 {
                for x in 0..v1 {
                    let u = [
                        (o[0] as usize + x) as f32 / res,
                        (o[1] as usize + y) as f32 / res,
                        (o[2] as usize + z) as f32 / res,
                    ];
                    let m = if has_mask {
                        enc.mask_at(params, &u)
                    } else {
                        1.0
                    };
                    let d = blend.is_dynamic(has_mask, m, VOLUME_STATIC_CUTOFF);
                    vertex_dynamic[x + v1 * (y + v1 * z)] = d;
                    any |= d;
                }
            }
        }
        if !any {
            stat.push(brick);
            continue;
        }
        let mut words = vec![0u32; fw];
        let mut count = 0;
        for cz in 0..b {
            for cy in 0..b {
                for cx in 0..b {
                    let corner_dynamic = (0..8).any(|c| {
                        let (dx, dy, dz) = (c & 1, (c >> 1) & 1, c >> 2);
                        vertex_dynamic[(cx + dx) + v1 * ((cy + dy) + v1 * (cz + dz))]
                    });
                    let cell = [o[0] + cx as u32, o[1] + cy as u32, o[2] + cz as u32];
                    let seen = occupancy.is_none_or(|occ| {
                        occ.any_in(cell, [cell[0] + 1, cell[1] + 1, cell[2] + 1], g.resolution)
                    });
                    if corner_dynamic && seen {
                        let bit = cx + b * (cy + b * cz);
                        words[bit >> 5] |= 1 << (bit & 31);
                        count += 1;
                    }
                }
            }
        }
        if count == 0 {
            stat.push(brick);
        } else {
            dyn_bricks.push(brick);
            dyn_cells.extend_from_slice(&words);
        }
    }
    (stat, dyn_bricks, dyn_cells)
}

/// The owner of border vertex `(x, y, z)` of brick `brick` (a coordinate equal to `B` belongs to
/// the next brick along that axis): the owner brick and the vertex in it; `None` past the last
/// brick.
fn owner(g: &VolumeGeometry, brick: u32, v: [usize; 3]) -> Option<(u32, [usize; 3])> {
    let i = g.bricks_per_side();
    let b = g.brick as usize;
    let mut bc = [brick % i, (brick / i) % i, brick / (i * i)];
    let mut local = v;
    for a in 0..3 {
        if v[a] == b {
            if bc[a] + 1 >= i {
                return None;
            }
            bc[a] += 1;
            local[a] = 0;
        }
    }
    Some((bc[0] + i * (bc[1] + i * bc[2]), local))
}

/// Per brick of the sorted set `bricks`, the vertices it evaluates itself: its own and the border
/// vertices whose owner is not in the set.
fn owned_counts(g: &VolumeGeometry, bricks: &[u32]) -> Vec<usize> {
    let v1 = g.brick as usize + 1;
    bricks
        .iter()
        .map(|&brick| {
            let mut n = 0;
            for z in 0..v1 {
                for y in 0..v1 {
                    for x in 0..v1 {
                        if evaluates(g, bricks, brick, [x, y, z]) {
                            n += 1;
                        }
                    }
                }
            }
            n
        })
        .collect()
}

/// Whether `brick` of the sorted set `bricks` evaluates its vertex `v` itself.
fn evaluates(g: &VolumeGeometry, bricks: &[u32], brick: u32, v: [usize; 3]) -> bool {
    let b = g.brick as usize;
    if v.iter().all(|&c| c < b) {
        return true;
    }
    match owner(g, brick, v) {
        Some((o, _)) => bricks.binary_search(&o).is_err(),
        None => true,
    }
}

/// Per-thread scratch of [`eval_vertices`].
#[derive(Clone, Debug, Default)]
pub struct BakeScratch {
    points: Vec<f32>,
    vertex: Vec<usize>,
    field: FieldScratch,
    colour_in: Vec<f32>,
    colour_acts: MlpActivations,
}

/// Progress of a bake shared between threads: bricks done, and a flag that stops it.
#[derive(Debug, Default)]
pub struct BakeProgress {
    pub done: AtomicUsize,
    pub cancel: AtomicBool,
}

impl BakeProgress {
    pub fn done(&self) -> usize {
        self.done.load(Ordering::Relaxed)
    }

    pub fn cancel(&self) {
        self.cancel.store(true, Ordering::Relaxed);
    }

    fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }
}

/// One set of bricks baked at one time: the static bricks (no 4D lookup), or the dynamic
/// bricks at a slice's time.
#[derive(Clone, Copy, Debug)]
pub struct BrickSet<'a> {
    /// Sorted brick index entries.
    pub bricks: &'a [u32],
    /// The set's time (a slice's; the static set's is unused).
    pub time: f32,
    /// Whether points the mask leaves dynamic get their 4D lookup (a slice), or none does (the
    /// static set, whose dynamic vertices are never read).
    pub dynamic: bool,
}

/// Phase 1: evaluates the vertices that `set.bricks[first..first + n]` own (plus the border
/// vertices no brick of the set owns) into their slots `values` (`n` slots). Returns the field
/// evaluations made.
#[allow(clippy::too_many_arguments)]
pub fn eval_vertices(
    plan: &BakePlan,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    set: &BrickSet<'_>,
    first: usize,
    values: &mut [Value],
    scratch: &mut BakeScratch,
    progress: &BakeProgress,
) -> Result<usize, BakeError> {
    let g = plan.geometry;
    let v1 = g.brick as usize + 1;
    let nv = g.vertices_per_brick();
    let ch = plan.channels;
    let n = values.len() / (nv * ch);
    let (dm, _) = &layout.field.density;
    let out_w = dm.output_dim();
    let geo = plan.geo.min(out_w.saturating_sub(1));
    let res = g.resolution as f32;
    let time = crate::pipeline::sample_time(set.time);
    let mut evaluated = 0;
    for k in 0..n {
        if progress.cancelled() {
            return Err(BakeError::Cancelled);
        }
        let brick = set.bricks[first + k];
        let o = brick_origin(&g, brick);
        scratch.points.clear();
        scratch.vertex.clear();
        for z in 0..v1 {
            for y in 0..v1 {
                for x in 0..v1 {
                    if evaluates(&g, set.bricks, brick, [x, y, z]) {
                        scratch.points.extend_from_slice(&[
                            (o[0] as usize + x) as f32 / res,
                            (o[1] as usize + y) as f32 / res,
                            (o[2] as usize + z) as f32 / res,
                            time,
                        ]);
                        scratch.vertex.push(x + v1 * (y + v1 * z));
                    }
                }
            }
        }
        let m = scratch.vertex.len();
        // The static set skips every 4D lookup: a static vertex's encoding is then what the
        // exact renderer computes under its cutoff. A slice looks up the dynamic ones.
        scratch.field.enc.static_cutoff = if set.dynamic {
            VOLUME_STATIC_CUTOFF
        } else {
            f32::INFINITY
        };
        layout
            .field
            .forward_density(params, &scratch.points, m, &mut scratch.field);
        evaluated += m;
        let out = dm.output(&scratch.field.density_acts);
        for j in 0..m {
            if out[j * out_w..j * out_w + 1 + geo]
                .iter()
                .any(|x| !x.is_finite())
            {
                let p = &scratch.points[j * 4..j * 4 + 3];
                return Err(BakeError::NotFinite([p[0], p[1], p[2]]));
            }
        }
        if plan.colour == ColourMode::Baked {
            // The colour MLP once per vertex, facing the reference direction.
            scratch.colour_in.clear();
            let mut sh = [0f32; SH_COEFFS];
            for j in 0..m {
                let p = &scratch.points[j * 4..j * 4 + 3];
                let x = cfg.bounds.from_unit(glam::Vec3::new(p[0], p[1], p[2]));
                let d = reference_direction(&plan.eyes, x);
                sh4([d.x, d.y, d.z], &mut sh);
                scratch.colour_in.extend_from_slice(&sh);
                scratch
                    .colour_in
                    .extend_from_slice(&out[j * out_w + 1..j * out_w + 1 + geo]);
            }
            let (cm, cr) = &layout.field.color;
            cm.forward(
                &params[cr.clone()],
                &scratch.colour_in,
                m,
                &mut scratch.colour_acts,
            );
        }
        let slot = &mut values[k * nv * ch..(k + 1) * nv * ch];
        for (j, &v) in scratch.vertex.iter().enumerate() {
            let row = &out[j * out_w..(j + 1) * out_w];
            let dst = &mut slot[v * ch..(v + 1) * ch];
            dst.fill(Value::ZERO);
            dst[0] = Value::from_f32(row[0]);
            if plan.colour == ColourMode::Baked {
                let c = &layout.field.color.0.output(&scratch.colour_acts)[j * 3..j * 3 + 3];
                for (d, &x) in dst[1..4].iter_mut().zip(c) {
                    let rgb = sigmoid(x);
                    if !rgb.is_finite() {
                        let p = &scratch.points[j * 4..j * 4 + 3];
                        return Err(BakeError::NotFinite([p[0], p[1], p[2]]));
                    }
                    *d = Value::from_f32(rgb);
                }
            } else {
                for (d, &x) in dst[1..1 + geo].iter_mut().zip(&row[1..1 + geo]) {
                    *d = Value::from_f32(x);
                }
            }
        }
        progress.done.fetch_add(1, Ordering::Relaxed);
    }
    Ok(evaluated)
}

/// Phase 2: copies into every slot of `set` the border vertices that another brick of the set
/// owns (`values`: every slot of the set, in set order).
pub fn fill_borders(plan: &BakePlan, set: &BrickSet<'_>, values: &mut [Value]) {
    let g = plan.geometry;
    let v1 = g.brick as usize + 1;
    let b = g.brick as usize;
    let nv = g.vertices_per_brick();
    let ch = plan.channels;
    for (k, &brick) in set.bricks.iter().enumerate() {
        for z in 0..v1 {
            for y in 0..v1 {
                for x in 0..v1 {
                    if x < b && y < b && z < b {
                        continue;
                    }
                    let Some((o, local)) = owner(&g, brick, [x, y, z]) else {
                        continue;
                    };
                    let Ok(j) = set.bricks.binary_search(&o) else {
                        continue;
                    };
                    let src = (j * nv + local[0] + v1 * (local[1] + v1 * local[2])) * ch;
                    let dst = (k * nv + x + v1 * (y + v1 * z)) * ch;
                    values.copy_within(src..src + ch, dst);
                }
            }
        }
    }
}

/// Phase 3: the cells of `set.bricks[first..]` that can hold density (`occupied`: `n` slots'
/// words; `values`: the same `n` slots), where the occupancy grid has them.
///
/// With a proposal threshold ([`BakePlan::proposal_threshold`]), the proposal network is
/// evaluated at the bricks' vertices (at the set's time, from `params`), and a cell whose corners'
/// proposal density stays below it is empty too.
#[allow(clippy::too_many_arguments)]
pub fn cell_bits(
    plan: &BakePlan,
    layout: &ModelLayout,
    params: &[f32],
    set: &BrickSet<'_>,
    first: usize,
    values: &[Value],
    occupied: &mut [u32],
) {
    let g = plan.geometry;
    let b = g.brick as usize;
    let v1 = b + 1;
    let nv = g.vertices_per_brick();
    let fw = g.flag_words();
    let ch = plan.channels;
    let occupancy = plan.occupancy();
    let n = occupied.len() / fw;
    let gate = plan.proposal_threshold > 0.0;
    let mut scratch = FieldScratch::default();
    scratch.enc.static_cutoff = crate::pipeline::RENDER_STATIC_CUTOFF;
    let mut points = Vec::new();
    let res = g.resolution as f32;
    for k in 0..n {
        let o = brick_origin(&g, set.bricks[first + k]);
        let words = &mut occupied[k * fw..(k + 1) * fw];
        words.fill(0);
        let logit = |v: usize| values[(k * nv + v) * ch].to_f32();
        let proposal: &[f32] = if gate {
            points.clear();
            for z in 0..v1 {
                for y in 0..v1 {
                    for x in 0..v1 {
                        points.extend_from_slice(&[
                            (o[0] as usize + x) as f32 / res,
                            (o[1] as usize + y) as f32 / res,
                            (o[2] as usize + z) as f32 / res,
                            set.time,
                        ]);
                    }
                }
            }
            let pf = &layout.proposal.field;
            pf.forward_density(params, &points, nv, &mut scratch);
            pf.density.0.output(&scratch.density_acts)
        } else {
            &[]
        };
        for cz in 0..b {
            for cy in 0..b {
                for cx in 0..b {
                    let mut max = f32::NEG_INFINITY;
                    let mut max_p = f32::NEG_INFINITY;
                    for c in 0..8 {
                        let (dx, dy, dz) = (c & 1, (c >> 1) & 1, c >> 2);
                        let v = (cx + dx) + v1 * ((cy + dy) + v1 * (cz + dz));
                        max = max.max(logit(v));
                        if gate {
                            // NaN counts as dense: the test never hides a broken field.
                            let p = proposal[v];
                            max_p = max_p.max(if p.is_nan() { f32::INFINITY } else { p });
                        }
                    }
                    if trunc_exp(max) < plan.density_threshold
                        || (gate && trunc_exp(max_p) < plan.proposal_threshold)
                    {
                        continue;
                    }
                    let cell = [o[0] + cx as u32, o[1] + cy as u32, o[2] + cz as u32];
                    let seen = occupancy.as_ref().is_none_or(|occ| {
                        occ.any_in(cell, [cell[0] + 1, cell[1] + 1, cell[2] + 1], g.resolution)
                    });
                    if seen {
                        let bit = cx + b * (cy + b * cz);
                        words[bit >> 5] |= 1 << (bit & 31);
                    }
                }
            }
        }
    }
}

impl Volume {
    /// A volume for `plan` before its static bricks are baked: index, the dynamic bricks and no
    /// slice yet.
    pub fn allocate(plan: &BakePlan) -> Volume {
        let g = plan.geometry;
        let mut index = vec![EMPTY_BRICK; g.index_len()];
        for &brick in &plan.outside_bricks {
            index[brick as usize] = OUTSIDE_BRICK;
        }
        for (d, &brick) in plan.dynamic_bricks.iter().enumerate() {
            index[brick as usize] = DYNAMIC_BRICK | d as u32;
        }
        let dynamic_cells = plan
            .dynamic_cells
            .iter()
            .map(|w| w.count_ones() as usize)
            .sum();
        Volume {
            geometry: g,
            colour: plan.colour,
            geo: plan.geo,
            channels: plan.channels,
            density_threshold: plan.density_threshold,
            index,
            occupied: Vec::new(),
            values: Vec::new(),
            dynamic: DynamicPart {
                bricks: plan.dynamic_bricks.clone(),
                cells: plan.dynamic_cells.clone(),
                times: plan.slice_times.clone(),
                slices: vec![None; plan.slice_times.len()],
            },
            stats: BakeStats {
                candidate_bricks: plan.static_bricks.len() + plan.dynamic_bricks.len(),
                dynamic_bricks: plan.dynamic_bricks.len(),
                dynamic_cells,
                slices: plan.slice_times.len(),
                ..Default::default()
            },
        }
    }

    /// Takes the baked static bricks (every slot of `plan.static_bricks`, in order): keeps the
    /// slots with an occupied cell and indexes them.
    pub fn set_static(&mut self, plan: &BakePlan, mut values: Vec<Value>, mut occupied: Vec<u32>) {
        let g = self.geometry;
        let (fw, sv) = (g.flag_words(), g.vertices_per_brick() * self.channels);
        let mut kept = 0usize;
        let mut occupied_cells = 0;
        for (k, &brick) in plan.static_bricks.iter().enumerate() {
            let o: usize = occupied[k * fw..(k + 1) * fw]
                .iter()
                .map(|w| w.count_ones() as usize)
                .sum();
            if o == 0 {
                continue;
            }
            occupied_cells += o;
            if kept != k {
                occupied.copy_within(k * fw..(k + 1) * fw, kept * fw);
                values.copy_within(k * sv..(k + 1) * sv, kept * sv);
            }
            self.index[brick as usize] = kept as u32;
            kept += 1;
        }
        occupied.truncate(kept * fw);
        values.truncate(kept * sv);
        self.occupied = occupied;
        self.values = values;
        self.stats.bricks = kept + self.dynamic.bricks.len();
        self.stats.occupied_cells = occupied_cells;
    }

    /// Keeps slice `k`, dropping the slice farthest in time from it when `resident` are held.
    pub fn set_slice(&mut self, k: usize, slice: Slice, resident: usize) {
        let d = &mut self.dynamic;
        while d.baked() >= resident.max(1) {
            let far = (0..d.slices.len())
                .filter(|&j| d.slices[j].is_some())
                .max_by_key(|&j| j.abs_diff(k));
            match far {
                Some(j) => d.slices[j] = None,
                None => break,
            }
        }
        d.slices[k] = Some(slice);
    }
}

/// Bakes `set` on this thread into slots (values, then cell bits): the three phases in order.
#[allow(clippy::too_many_arguments)]
pub fn bake_set(
    plan: &BakePlan,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    set: &BrickSet<'_>,
    progress: &BakeProgress,
) -> Result<(Vec<Value>, Vec<u32>, usize), BakeError> {
    let g = plan.geometry;
    let n = set.bricks.len();
    let mut values = vec![Value::ZERO; n * g.vertices_per_brick() * plan.channels];
    let mut occupied = vec![0u32; n * g.flag_words()];
    let mut scratch = BakeScratch::default();
    let evaluated = eval_vertices(
        plan,
        cfg,
        layout,
        params,
        set,
        0,
        &mut values,
        &mut scratch,
        progress,
    )?;
    fill_borders(plan, set, &mut values);
    cell_bits(plan, layout, params, set, 0, &values, &mut occupied);
    Ok((values, occupied, evaluated))
}

/// What bakes one set of bricks: its values, cell words and field evaluations ([`bake_set`] on
/// this thread; the player spreads the same phases over threads).
pub type SetBaker<'a> =
    dyn FnMut(&BrickSet<'_>) -> Result<(Vec<Value>, Vec<u32>, usize), BakeError> + 'a;

/// Bakes `plan`'s static bricks with `bake_set`; the slices are baked when needed
/// ([`bake_slice_with`]).
pub fn bake_with(plan: &BakePlan, bake_set: &mut SetBaker<'_>) -> Result<Volume, BakeError> {
    let start = std::time::Instant::now();
    let mut vol = Volume::allocate(plan);
    let set = BrickSet {
        bricks: &plan.static_bricks,
        time: 0.0,
        dynamic: false,
    };
    let (values, occupied, evaluated) = bake_set(&set)?;
    vol.set_static(plan, values, occupied);
    vol.stats.vertices_evaluated = evaluated;
    vol.stats.seconds = start.elapsed().as_secs_f64();
    Ok(vol)
}

/// Bakes slice `k` of `vol` with `bake_set` (given the flat buffer at the slice's time); returns
/// the field evaluations made.
pub fn bake_slice_with(
    vol: &mut Volume,
    plan: &BakePlan,
    k: usize,
    bake_set: &mut SetBaker<'_>,
) -> Result<usize, BakeError> {
    let set = BrickSet {
        bricks: &plan.dynamic_bricks,
        time: plan.slice_times[k],
        dynamic: true,
    };
    let (values, occupied, evaluated) = bake_set(&set)?;
    vol.set_slice(k, Slice { occupied, values }, plan.resident_slices);
    Ok(evaluated)
}

/// Bakes `plan`'s static bricks on this thread (tests and small models).
pub fn bake(
    plan: &BakePlan,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    progress: &BakeProgress,
) -> Result<Volume, BakeError> {
    bake_with(plan, &mut |set| {
        bake_set(plan, cfg, layout, params, set, progress)
    })
}

/// Bakes slice `k` of `vol` with `params` (the flat buffer at the slice's time) on this thread.
pub fn bake_slice(
    vol: &mut Volume,
    plan: &BakePlan,
    k: usize,
    cfg: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
) -> Result<(), BakeError> {
    bake_slice_with(vol, plan, k, &mut |set| {
        bake_set(plan, cfg, layout, params, set, &BakeProgress::default())
    })
    .map(drop)
}
