//! The host side of the render kernels' bindings (`shaders/render/bindings.wgsl`): the `Model` and
//! `View` uniforms byte for byte, and the split of the flat parameter buffer into the three
//! storage buffers the kernels read (`tab3`, `tab4`, `rest`). `web/shaders/README.md` documents
//! the same layout for the browser; keep the two in step.

use std::ops::Range;

use bytemuck::{Pod, Zeroable};
use msth_core::config::{Background, BlendMode, ModelConfig};
use msth_core::field::{EncodingLayout, ModelLayout};
use msth_core::grid::GridLayout;
use msth_core::pipeline::{render_histogram_padding, spacing_unit, RENDER_STATIC_CUTOFF};
use msth_core::sampling::Spacing;
use msth_core::{Camera, SceneBounds};

/// Largest number of proposal samples per ray the kernels hold (`MAX_PROPOSAL_SAMPLES`).
pub const MAX_PROPOSAL_SAMPLES: usize = 256;
/// Largest number of main samples per ray (`MAX_SAMPLES`).
pub const MAX_SAMPLES: usize = 128;
/// Largest MLP hidden width (`MAX_HIDDEN`).
pub const MAX_HIDDEN: usize = 128;
/// Largest number of geometry features passed from the density to the colour decoder.
pub const MAX_GEO: usize = 31;
/// Level slots in the `Model` uniform (4 grids of at most 32 levels).
pub const LEVEL_SLOTS: usize = 128;
/// Invocations per workgroup of every entry point.
pub const WORKGROUP: u32 = 64;

/// One grid level (48 bytes): `scale`, dense `stride`, `info = (offset, dense, rows, 0)`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct LevelU {
    pub scale: [f32; 4],
    pub stride: [u32; 4],
    pub info: [u32; 4],
}

/// One grid (32 bytes): `shape = (dims, features, levels, hash mask)`,
/// `loc = (buffer, first level slot, present, 0)`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct GridU {
    pub shape: [u32; 4],
    pub loc: [u32; 4],
}

/// One masked encoding (112 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct EncodingU {
    /// `(blend, has mask, mask resolution, mask offset in rest)`.
    pub mode: [u32; 4],
    /// `(output dim, 0, 0, 0)`.
    pub dims: [u32; 4],
    /// `(mask value without a mask, static cutoff, 0, 0)`.
    pub consts: [f32; 4],
    pub h3: GridU,
    pub h4: GridU,
}

/// The `Model` uniform (6496 bytes): everything that is fixed for a model.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct ModelU {
    pub sampler: [u32; 4],
    pub limits: [f32; 4],
    pub bounds_a: [f32; 4],
    pub bounds_b: [f32; 4],
    pub background: [f32; 4],
    pub density: [u32; 4],
    pub color: [u32; 4],
    pub proposal: [u32; 4],
    pub field: EncodingU,
    pub prop: EncodingU,
    pub levels: [LevelU; LEVEL_SLOTS],
}

/// The `View` uniform (112 bytes): camera, invocation count and flags, time.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct ViewU {
    pub c2w: [[f32; 4]; 4],
    pub intr: [f32; 4],
    pub size: [u32; 4],
    pub time: [f32; 4],
}

/// `View.size.w` bit: invocation `i` renders pixel `list[i]` (otherwise pixel `i`).
pub const FLAG_LIST: u32 = 1;
/// `View.size.w` bit: the result goes to `frame[i]` (otherwise `frame[pixel]`).
pub const FLAG_COMPACT: u32 = 2;

impl ViewU {
    /// The view of `camera` at `time` for `count` invocations with `flags`.
    pub fn new(camera: &Camera, time: f32, count: u32, flags: u32) -> Self {
        ViewU {
            c2w: camera.world_from_camera.to_cols_array_2d(),
            intr: [camera.fx, camera.fy, camera.cx, camera.cy],
            size: [camera.width, camera.height, count, flags],
            time: [time, 0.0, 0.0, 0.0],
        }
    }
}

/// Where the three storage buffers come from in the flat parameter buffer.
///
/// The kernels read hash tables in pairs of values (`array<vec2<f32>>`, which software adapters
/// load in one go), so both fields' tables go to the `tab3` and `tab4` buffers: the field's
/// table first, the proposal field's after it from an even index ([`ParamSplit::tables`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ParamSplit {
    /// `field.h3` (empty: the kernels get a placeholder pair).
    pub tab3: Range<usize>,
    /// `field.h4` (empty likewise).
    pub tab4: Range<usize>,
    /// `proposal.h3`, which also lies in `rest` (empty without one).
    pub prop3: Range<usize>,
    /// `proposal.h4` (likewise).
    pub prop4: Range<usize>,
    /// Everything after the field's hash tables.
    pub rest: Range<usize>,
    /// The proposal, density and colour MLPs' weights, relative to `rest`'s start (msth-core's
    /// layout; what `crate::specialise` writes into a shader).
    pub mlps: [Range<usize>; 3],
}

/// The uniforms and buffer split of one model, or why the kernels cannot render it.
#[derive(Clone, Debug)]
pub struct GpuModel {
    pub model: ModelU,
    pub split: ParamSplit,
}

fn blend_code(b: BlendMode) -> u32 {
    match b {
        BlendMode::Mst => 0,
        BlendMode::Mt => 1,
        BlendMode::Add => 2,
        BlendMode::FourD => 3,
        BlendMode::Static => 4,
    }
}

/// Offsets must fit the kernels' u32 indices.
fn u32_of(v: usize, what: &str) -> Result<u32, GpuLayoutError> {
    u32::try_from(v).map_err(|_| GpuLayoutError::Index {
        what: what.to_string(),
        value: v,
    })
}

/// Why [`GpuModel::new`] refused a model: an invalid configuration or a limit of the kernels.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum GpuLayoutError {
    #[error(transparent)]
    Config(#[from] msth_core::config::ModelConfigError),
    #[error("{what} is {value}; the GPU renderer supports at most {max} (use --cpu)")]
    Limit {
        what: String,
        value: usize,
        max: usize,
    },
    #[error("field.color_layers is 0; the GPU renderer needs at least one hidden colour layer (use --cpu)")]
    NoColorLayers,
    #[error("{what} ({value}) does not fit the GPU kernels' 32-bit indices")]
    Index { what: String, value: usize },
    #[error("parameter `{0}` lies before the field's hash tables; the GPU renderer cannot split this layout")]
    Split(String),
    #[error("too many grid levels for the GPU renderer")]
    TooManyLevels,
    #[error("3D and 4D grids differ in levels or features")]
    GridMismatch,
}

impl GpuModel {
    /// Builds the uniforms of `cfg` (validated) and checks the kernels' limits; the error says
    /// which limit a model exceeds.
    pub fn new(cfg: &ModelConfig) -> Result<Self, GpuLayoutError> {
        cfg.validate()?;
        let layout = ModelLayout::new(cfg);
        let (np, nf) = (cfg.sampler.num_proposal_samples, cfg.sampler.num_samples);
        let check = |what: &str, v: usize, max: usize| {
            if v > max {
                Err(GpuLayoutError::Limit {
                    what: what.to_string(),
                    value: v,
                    max,
                })
            } else {
                Ok(())
            }
        };
        check("sampler.num_proposal_samples", np, MAX_PROPOSAL_SAMPLES)?;
        check("sampler.num_samples", nf, MAX_SAMPLES)?;
        check("field.density_hidden", cfg.field.density_hidden, MAX_HIDDEN)?;
        check("field.color_hidden", cfg.field.color_hidden, MAX_HIDDEN)?;
        check("proposal.hidden", cfg.proposal.hidden, MAX_HIDDEN)?;
        check("field.geo_features", cfg.field.geo_features, MAX_GEO)?;
        if cfg.field.color_layers == 0 {
            return Err(GpuLayoutError::NoColorLayers);
        }
        let split = Self::split(&layout)?;
        let mut levels = [LevelU::default(); LEVEL_SLOTS];
        let mut next_slot = 0usize;
        let field = encoding_u(
            &layout.field.encoding,
            &split,
            [0, 0],
            &mut levels,
            &mut next_slot,
        )?;
        let [[_, (_, p3, _)], [_, (_, p4, _)]] = split.tables();
        let prop = encoding_u(
            &layout.proposal.field.encoding,
            &split,
            [p3, p4],
            &mut levels,
            &mut next_slot,
        )?;
        let rest0 = split.rest.start;
        let rel = |r: &Range<usize>, what: &str| u32_of(r.start - rest0, what);
        let (dm, dr) = &layout.field.density;
        let (cm, cr) = &layout.field.color;
        let (pm, pr) = &layout.proposal.field.density;
        let (bounds_kind, bounds_a, bounds_b) = match cfg.bounds {
            SceneBounds::Box { min, max } => {
                (0, [min.x, min.y, min.z, 0.0], [max.x, max.y, max.z, 0.0])
            }
            SceneBounds::Contracted { center, radius } => {
                (1, [center.x, center.y, center.z, radius], [0.0; 4])
            }
        };
        let background = match cfg.background {
            Background::Color { rgb } => [rgb[0], rgb[1], rgb[2], 1.0],
            Background::LastSample => [0.0; 4],
        };
        let model = ModelU {
            sampler: [
                np as u32,
                nf as u32,
                match cfg.sampler.spacing {
                    Spacing::Linear => 0,
                    Spacing::LinDisp => 1,
                },
                bounds_kind,
            ],
            limits: [
                cfg.sampler.near,
                cfg.sampler.far,
                render_histogram_padding(&cfg.sampler),
                spacing_unit(&cfg.bounds),
            ],
            bounds_a,
            bounds_b,
            background,
            density: [
                rel(dr, "field.density_mlp offset")?,
                dm.dims[0] as u32,
                dm.dims[1] as u32,
                dm.dims[2] as u32,
            ],
            color: [
                rel(cr, "field.color_mlp offset")?,
                cfg.field.color_hidden as u32,
                cfg.field.color_layers as u32,
                cfg.field.geo_features as u32,
            ],
            proposal: [
                rel(pr, "proposal.density_mlp offset")?,
                pm.dims[0] as u32,
                pm.dims[1] as u32,
                0,
            ],
            field,
            prop,
            levels,
        };
        debug_assert_eq!(cm.dims.len(), cfg.field.color_layers + 2);
        Ok(GpuModel { model, split })
    }

    fn split(layout: &ModelLayout) -> Result<ParamSplit, GpuLayoutError> {
        let enc = &layout.field.encoding;
        let range = |g: &Option<(GridLayout, Range<usize>)>| {
            g.as_ref().map(|(_, r)| r.clone()).unwrap_or(0..0)
        };
        let (tab3, tab4) = (range(&enc.h3), range(&enc.h4));
        let penc = &layout.proposal.field.encoding;
        let (prop3, prop4) = (range(&penc.h3), range(&penc.h4));
        let rest_start = tab3.end.max(tab4.end);
        // The field's tables come first in the flat buffer (docs/format.md §7); everything the
        // kernels read from `rest` must lie after them.
        let others = layout
            .params
            .entries
            .iter()
            .filter(|e| e.name != "field.h3" && e.name != "field.h4");
        for e in others {
            if e.offset < rest_start {
                return Err(GpuLayoutError::Split(e.name.to_string()));
            }
        }
        Ok(ParamSplit {
            tab3,
            tab4,
            prop3,
            prop4,
            rest: rest_start..layout.params.total,
            mlps: [
                &layout.proposal.field.density.1,
                &layout.field.density.1,
                &layout.field.color.1,
            ]
            .map(|r| r.start - rest_start..r.end - rest_start),
        })
    }

    /// Byte sizes of the three parameter buffers (`tab3`, `tab4`, `rest`), placeholders included,
    /// the tables held in `tables`' format ([`TableFormat::buffer_bytes`]).
    pub fn buffer_sizes(&self, tables: TableFormat) -> [(&'static str, u64); 3] {
        let bytes = |r: &Range<usize>| (r.len().max(1) * 4) as u64;
        let [t3, t4] = self.split.tables().map(|parts| {
            let values = parts.iter().map(|(_, at, r)| at + r.len()).max();
            tables.buffer_bytes(values.unwrap_or(0))
        });
        [
            ("3D hash tables (tab3)", t3),
            ("4D hash tables (tab4)", t4),
            (
                "decoders, mask and proposal field (rest)",
                bytes(&self.split.rest),
            ),
        ]
    }
}

/// The `render.wgsl` region that holds the hash tables as binary16 ([`TableFormat::F16`]).
pub const TABLES_F16_WGSL: &str = include_str!("../shaders/tables_f16.wgsl");

/// How the render kernels' hash-table buffers (`tab3`, `tab4`) hold the tables' values
/// ([`TableFormat::source`]). The rest of the parameters (mask, MLPs) stay f32.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TableFormat {
    /// The values as they are: frames as close to the CPU renderer's as the kernels get.
    #[default]
    F32,
    /// IEEE binary16, rounded to nearest (ties to even) after clamping to ±65504 (the largest
    /// finite binary16, as the codec's `f16` mode does), magnitudes that round below 2^-14 to
    /// zero (no subnormals): half the memory and uploads, and one
    /// 4-byte read per row's two features. A relative error of at most 2^-11 per value, below
    /// the step of every quantised `.msth` mode's tables (`docs/format.md` §5.3).
    F16,
}

impl TableFormat {
    /// `"f32"` or `"f16"`.
    pub fn name(self) -> &'static str {
        match self {
            TableFormat::F32 => "f32",
            TableFormat::F16 => "f16",
        }
    }

    /// Bytes a table buffer of `values` values takes: f32 in whole pairs (`vec2<f32>`),
    /// binary16 in whole words (`u32`), at least one.
    pub fn buffer_bytes(self, values: usize) -> u64 {
        let b = match self {
            TableFormat::F32 => values.div_ceil(2).max(1) * 8,
            TableFormat::F16 => values.div_ceil(2).max(1) * 4,
        };
        b as u64
    }

    /// `render.wgsl` (or a source of its bindings) with its hash tables held in this format:
    /// for f16 the region between the "Hash tables: begin" and "end" lines is replaced by
    /// `shaders/tables_f16.wgsl`; `None` when the source has no such region.
    pub fn source(self, wgsl: &str) -> Option<String> {
        match self {
            TableFormat::F32 => Some(wgsl.to_string()),
            TableFormat::F16 => {
                let begin = wgsl.find("// ---- Hash tables: begin")?;
                let end_mark = "// ---- Hash tables: end ----\n";
                let end = wgsl[begin..].find(end_mark)? + begin + end_mark.len();
                Some(format!(
                    "{}{}{}",
                    &wgsl[..begin],
                    TABLES_F16_WGSL,
                    &wgsl[end..]
                ))
            }
        }
    }

    /// Byte offset of value `at` (even) in a table buffer.
    pub fn byte_offset(self, at: usize) -> u64 {
        match self {
            TableFormat::F32 => 4 * at as u64,
            TableFormat::F16 => 2 * at as u64,
        }
    }

    /// `values` as a table buffer holds them, padded to whole 4-byte words (a trailing 0 for an
    /// odd count of binary16 values); f32 values are borrowed as they are.
    pub fn encode(self, values: &[f32]) -> std::borrow::Cow<'_, [u8]> {
        match self {
            TableFormat::F32 => std::borrow::Cow::Borrowed(bytemuck::cast_slice(values)),
            TableFormat::F16 => {
                let mut out = Vec::with_capacity(2 * values.len().next_multiple_of(2));
                for &v in values {
                    out.extend_from_slice(&f16_bits(v).to_le_bytes());
                }
                if values.len() % 2 == 1 {
                    out.extend_from_slice(&[0, 0]);
                }
                std::borrow::Cow::Owned(out)
            }
        }
    }

    /// How many of `values` [`TableFormat::encode`] clamps: magnitudes beyond binary16's
    /// largest finite value, 65504, for f16 (the kernels read ±65504 there); none for f32.
    pub fn clamped(self, values: &[f32]) -> usize {
        match self {
            TableFormat::F32 => 0,
            TableFormat::F16 => values.iter().filter(|v| v.abs() > F16_MAX).count(),
        }
    }

    /// The value the kernels read for a table value `v`.
    pub fn round(self, v: f32) -> f32 {
        match self {
            TableFormat::F32 => v,
            TableFormat::F16 => half::f16::from_bits(f16_bits(v)).to_f32(),
        }
    }
}

impl std::str::FromStr for TableFormat {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f32" => Ok(TableFormat::F32),
            "f16" => Ok(TableFormat::F16),
            _ => Err(format!("unknown table format {s:?}: f32 or f16")),
        }
    }
}

/// The largest finite binary16 value.
const F16_MAX: f32 = 65504.0;

/// `v` as binary16 bits: clamped to ±65504, rounded to nearest, ties to even, a subnormal
/// result (below 2^-14 in magnitude) flushed to zero of the same sign, since WGSL lets
/// `unpack2x16float` flush those (a NaN stays NaN).
fn f16_bits(v: f32) -> u16 {
    let h = half::f16::from_f32(v.clamp(-F16_MAX, F16_MAX)).to_bits();
    if h & 0x7c00 == 0 {
        h & 0x8000
    } else {
        h
    }
}

impl ParamSplit {
    /// What the `tab3` and `tab4` buffers hold: `(what, value index in the buffer, params
    /// range)` for the field's table (at 0) and the proposal field's (right after it, from an
    /// even index, so that every row of an even number of features is a whole pair; msth-core's
    /// tables already have an even length, their rows being rounded up to 8).
    pub fn tables(&self) -> [[(&'static str, usize, Range<usize>); 2]; 2] {
        let after = |r: &Range<usize>| r.len().next_multiple_of(2);
        [
            [
                ("field.h3", 0, self.tab3.clone()),
                ("proposal.h3", after(&self.tab3), self.prop3.clone()),
            ],
            [
                ("field.h4", 0, self.tab4.clone()),
                ("proposal.h4", after(&self.tab4), self.prop4.clone()),
            ],
        ]
    }
}

/// The uniform of one encoding; `bases`: where its 3D and 4D tables start in the `tab3` and
/// `tab4` buffers (value indices).
fn encoding_u(
    e: &EncodingLayout,
    split: &ParamSplit,
    bases: [usize; 2],
    levels: &mut [LevelU; LEVEL_SLOTS],
    next_slot: &mut usize,
) -> Result<EncodingU, GpuLayoutError> {
    let rest0 = split.rest.start;
    let mut grid =
        |g: &Option<(GridLayout, Range<usize>)>, buffer: u32| -> Result<GridU, GpuLayoutError> {
            let Some((gl, _)) = g else {
                return Ok(GridU::default());
            };
            let base = bases[buffer as usize];
            let first = *next_slot;
            if first + gl.levels.len() > LEVEL_SLOTS {
                return Err(GpuLayoutError::TooManyLevels);
            }
            for (k, lv) in gl.levels.iter().enumerate() {
                levels[first + k] = LevelU {
                    scale: lv.scale,
                    stride: lv.stride,
                    info: [
                        u32_of(base + lv.offset, "grid table offset")?,
                        lv.dense as u32,
                        u32_of(lv.rows, "grid rows")?,
                        0,
                    ],
                };
            }
            *next_slot += gl.levels.len();
            Ok(GridU {
                shape: [
                    gl.dims as u32,
                    gl.features as u32,
                    gl.levels.len() as u32,
                    (gl.table_size - 1) as u32,
                ],
                loc: [buffer, first as u32, 1, 0],
            })
        };
    let h3 = grid(&e.h3, 0)?;
    let h4 = grid(&e.h4, 1)?;
    if let (Some((a, _)), Some((b, _))) = (&e.h3, &e.h4) {
        if a.levels.len() != b.levels.len() || a.features != b.features {
            return Err(GpuLayoutError::GridMismatch);
        }
    }
    let (has_mask, mask_res, mask_off) = match &e.mask {
        Some((d, r)) => (1, d.res as u32, u32_of(r.start - rest0, "mask offset")?),
        None => (0, 0, 0),
    };
    let no_mask_value = match e.blend {
        BlendMode::Static => 1.0,
        BlendMode::FourD => 0.0,
        _ => 0.5,
    };
    Ok(EncodingU {
        mode: [blend_code(e.blend), has_mask, mask_res, mask_off],
        dims: [e.out_dim as u32, 0, 0, 0],
        consts: [no_mask_value, RENDER_STATIC_CUTOFF, 0.0, 0.0],
        h3,
        h4,
    })
}

/// Loop iterations of one field evaluation in the kernels, counted generously: the proposal
/// density, the main density and the colour decoder.
fn evaluation_loops(cfg: &ModelConfig) -> (u64, u64, u64) {
    let encode = |e: &msth_core::config::EncodingConfig, hidden: usize| -> u64 {
        let (use3, use4) = (e.blend.uses_h3(), e.blend.uses_h4());
        let g = if use3 { &e.grid3 } else { &e.grid4 };
        let (levels, f, h) = (g.levels as u64, g.features_per_level as u64, hidden as u64);
        let grid = |dims: u64| dims + 1 + (1u64 << dims) * f + 1 + f + 1;
        let per_level =
            9 + if use3 { grid(3) } else { 0 } + if use4 { grid(4) } else { 0 } + f + 1 + f * h + 1;
        8 + 3 + 2 * (h + 1) + levels * per_level + 1
    };
    let proposal =
        encode(&cfg.proposal.encoding, cfg.proposal.hidden) + cfg.proposal.hidden as u64 + 1;
    let f = &cfg.field;
    let (hd, g, hc, layers) = (
        f.density_hidden as u64,
        f.geo_features as u64,
        f.color_hidden as u64,
        f.color_layers as u64,
    );
    let dense = |i: u64, o: u64| 3 * (o + 1) + i * o + 1;
    let density = encode(&f.encoding, f.density_hidden) + dense(hd, 1 + g) + g + 2;
    let nin = 16 + g;
    let color = 16
        + g
        + nin
        + 3
        + dense(nin, hc)
        + layers.saturating_sub(1) * (hc + 1 + dense(hc, hc) + 1)
        + hc
        + 1
        + dense(hc, 3);
    (proposal, density, color)
}

/// Loop iterations of the longest invocation of the per-sample passes for `cfg` (one sample's
/// density and colour in `pass_build`; a ray's histogram and samples in `pass_resample`), with
/// the sample cache's fixed samples up to `MAX_SAMPLES` (every loop counted generously): Mesa's
/// lavapipe stops all loops of an invocation after [`LAVAPIPE_LOOP_ITERATIONS`] in total, so
/// larger models would render wrongly there. Far below that budget for every preset.
pub fn loop_iterations_per_invocation(cfg: &ModelConfig) -> u64 {
    let (proposal, density, color) = evaluation_loops(cfg);
    let s = &cfg.sampler;
    let np = s.num_proposal_samples as u64;
    let samples = (s.num_samples.max(MAX_SAMPLES)) as u64 + 1;
    let resample = 3 * np + 2 * samples + 8;
    proposal.max(density + color + 16).max(resample)
}

/// Loop iterations Mesa's lavapipe (llvmpipe's `LP_MAX_TGSI_LOOP_ITERATIONS`) runs per
/// invocation before it ends every loop.
pub const LAVAPIPE_LOOP_ITERATIONS: u64 = 65535;

/// Workgroup counts `(x, y)` for `count` invocations: `x` at most `max_per_dim`.
pub fn dispatch_size(count: u32, max_per_dim: u32) -> Option<(u32, u32)> {
    let groups = count.div_ceil(WORKGROUP).max(1);
    let x = groups.min(max_per_dim);
    let y = groups.div_ceil(x);
    (y <= max_per_dim).then_some((x, y))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_sizes_match_the_wgsl_layout() {
        assert_eq!(std::mem::size_of::<LevelU>(), 48);
        assert_eq!(std::mem::size_of::<GridU>(), 32);
        assert_eq!(std::mem::size_of::<EncodingU>(), 112);
        assert_eq!(std::mem::size_of::<ModelU>(), 352 + 48 * LEVEL_SLOTS);
        assert_eq!(std::mem::size_of::<ViewU>(), 112);
    }

    #[test]
    fn presets_fit_lavapipe_and_very_deep_colour_mlps_do_not() {
        use msth_core::config::Preset;
        // The per-sample passes fit every preset.
        for p in [Preset::Fast, Preset::Balanced, Preset::Paper] {
            let cfg = ModelConfig::preset(
                p,
                SceneBounds::dnerf_default(),
                Background::Color { rgb: [1.0; 3] },
                300,
            );
            let n = loop_iterations_per_invocation(&cfg);
            assert!(n < LAVAPIPE_LOOP_ITERATIONS / 4, "{p:?}: {n}");
        }
        // Five hidden colour layers of the widest MLP the kernels take exceed it: one sample's
        // colour alone loops over more than 4 x 128 x 128 weights.
        let mut deep = ModelConfig::preset(
            Preset::Fast,
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
            10,
        );
        deep.field.color_hidden = MAX_HIDDEN;
        deep.field.color_layers = 5;
        assert!(loop_iterations_per_invocation(&deep) > LAVAPIPE_LOOP_ITERATIONS);
    }

    /// The fast preset with small grids: dense coarse levels, hashed fine ones.
    fn small_fast_config() -> ModelConfig {
        use msth_core::config::Preset;
        let mut cfg = ModelConfig::preset(
            Preset::Fast,
            SceneBounds::dnerf_default(),
            Background::Color { rgb: [1.0; 3] },
            10,
        );
        for enc in [&mut cfg.field.encoding, &mut cfg.proposal.encoding] {
            enc.resize(3, 10, 64.0, 4);
        }
        cfg
    }

    #[test]
    fn both_fields_tables_share_the_pair_buffers() {
        for features in [1, 2, 4] {
            let mut cfg = small_fast_config();
            for enc in [&mut cfg.field.encoding, &mut cfg.proposal.encoding] {
                enc.grid3.features_per_level = features;
                enc.grid4.features_per_level = features;
            }
            let gm = GpuModel::new(&cfg).unwrap();
            let layout = ModelLayout::new(&cfg);
            let s = &gm.split;
            let [[(_, f3, t3), (_, p3, r3)], [(_, f4, t4), (_, p4, r4)]] = s.tables();
            assert_eq!((f3, f4), (0, 0));
            assert_eq!((t3.clone(), t4.clone()), (s.tab3.clone(), s.tab4.clone()));
            let pe = &layout.proposal.field.encoding;
            assert_eq!(Some(&r3), pe.h3.as_ref().map(|(_, r)| r));
            assert_eq!(Some(&r4), pe.h4.as_ref().map(|(_, r)| r));
            // The proposal's tables start at the next even index after the field's.
            assert_eq!(p3, t3.len() + t3.len() % 2);
            assert_eq!(p4, t4.len() + t4.len() % 2);
            // Its levels' offsets point there; the buffers hold both in whole pairs.
            let prop = gm.model.prop;
            let first3 = gm.model.levels[prop.h3.loc[1] as usize].info[0] as usize;
            let first4 = gm.model.levels[prop.h4.loc[1] as usize].info[0] as usize;
            assert_eq!((first3, first4), (p3, p4));
            assert_eq!((prop.h3.loc[0], prop.h4.loc[0]), (0, 1));
            let [(_, b3), (_, b4), _] = gm.buffer_sizes(TableFormat::F32);
            assert_eq!(b3, (4 * (p3 + r3.len())).next_multiple_of(8) as u64);
            assert_eq!(b4, (4 * (p4 + r4.len())).next_multiple_of(8) as u64);
            let [(_, h3), (_, h4), _] = gm.buffer_sizes(TableFormat::F16);
            assert_eq!(h3, (2 * (p3 + r3.len())).next_multiple_of(4) as u64);
            assert_eq!(h4, (2 * (p4 + r4.len())).next_multiple_of(4) as u64);
        }
    }

    /// The passes resample with the render padding (`msth_core::pipeline::
    /// render_histogram_padding`), as the CPU renderer does, not the model's training one.
    #[test]
    fn the_model_uniform_holds_the_render_histogram_padding() {
        use msth_core::pipeline::RENDER_HISTOGRAM_PADDING;
        let mut cfg = small_fast_config();
        for (trained, rendered) in [
            (0.01, RENDER_HISTOGRAM_PADDING),
            (RENDER_HISTOGRAM_PADDING, RENDER_HISTOGRAM_PADDING),
            (2e-4, 2e-4),
            (0.0, 0.0),
        ] {
            cfg.sampler.histogram_padding = trained;
            let gm = GpuModel::new(&cfg).unwrap();
            assert_eq!(gm.model.limits[2], rendered, "trained with {trained}");
        }
    }

    #[test]
    fn binary16_tables_round_clamp_flush_and_pad() {
        let f = TableFormat::F16;
        // Exact values stay; ties go to the even neighbour; the range clamps; no subnormals.
        assert_eq!(f.round(1.5), 1.5);
        assert_eq!(f.round(-0.25), -0.25);
        assert_eq!(f.round(1.0 + 2f32.powi(-11)), 1.0);
        assert_eq!(f.round(1.0 + 3.0 * 2f32.powi(-11)), 1.0 + 2f32.powi(-9));
        assert_eq!(f.round(1e6), 65504.0);
        assert_eq!(f.round(f32::MIN), -65504.0);
        assert_eq!(f.round(2f32.powi(-14)), 2f32.powi(-14));
        assert_eq!(f.round(1e-6).to_bits(), 0);
        assert_eq!(f.round(-1e-6).to_bits(), (-0f32).to_bits());
        assert!(f.round(f32::NAN).is_nan());
        // What the clamp changes is counted: beyond ±65504 (infinities included), not at it.
        let wide = [
            65504.0,
            -65504.0,
            65504.5,
            -1e6,
            f32::INFINITY,
            f32::NAN,
            3.0,
        ];
        assert_eq!(f.clamped(&wide), 3);
        assert_eq!(TableFormat::F32.clamped(&wide), 0);
        for v in [0.1f32, -3.7, 1234.5, 7e-3] {
            let r = f.round(v);
            assert!((r - v).abs() <= v.abs() * 2f32.powi(-11), "{v} -> {r}");
            assert_eq!(TableFormat::F32.round(v), v);
        }
        // Two values per little-endian word, the lower half first; an odd count padded.
        assert_eq!(
            *f.encode(&[1.0, -2.0, 0.5]),
            [0x00, 0x3c, 0x00, 0xc0, 0x00, 0x38, 0, 0]
        );
        assert_eq!(*TableFormat::F32.encode(&[1.0]), 1f32.to_le_bytes());
        assert_eq!(
            (f.buffer_bytes(0), f.buffer_bytes(3), f.buffer_bytes(4)),
            (4, 8, 8)
        );
        assert_eq!(TableFormat::F32.buffer_bytes(3), 16);
        assert_eq!(
            (f.byte_offset(6), TableFormat::F32.byte_offset(6)),
            (12, 24)
        );
        assert_eq!("f16".parse(), Ok(f));
        assert!("f8"
            .parse::<TableFormat>()
            .unwrap_err()
            .contains("f32 or f16"));
    }

    #[test]
    fn binary16_source_replaces_the_table_region_only() {
        let src = crate::render::RENDER_WGSL;
        assert_eq!(TableFormat::F32.source(src).as_deref(), Some(src));
        let half = TableFormat::F16.source(src).unwrap();
        assert!(half.contains("var<storage, read> tab3: array<u32>;"));
        assert!(half.contains("unpack2x16float"));
        assert!(!half.contains("array<vec2<f32>>;"));
        assert!(!half.contains("Hash tables: begin"));
        // Everything outside the region is kept.
        let (a, b) = src.split_once("// ---- Hash tables: begin").unwrap();
        assert!(half.starts_with(a));
        let after = b.split_once("// ---- Hash tables: end ----\n").unwrap().1;
        assert!(half.ends_with(after));
        assert_eq!(TableFormat::F16.source("fn main() {}"), None);
    }

    #[test]
    fn dispatch_covers_every_invocation() {
        assert_eq!(dispatch_size(1, 65535), Some((1, 1)));
        assert_eq!(dispatch_size(64 * 65535 + 1, 65535), Some((65535, 2)));
        let (x, y) = dispatch_size(10_000_000, 65535).unwrap();
        assert!(x as u64 * y as u64 * 64 >= 10_000_000);
        assert_eq!(dispatch_size(u32::MAX, 10), None);
    }
}
