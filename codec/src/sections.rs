//! Section payloads (format.md §6): what each section holds after decompression, how it is
//! written from a flat parameter buffer and read back into one.
//!
//! - MLP: blocks `field.density_mlp`, `field.color_mlp`, `proposal.density_mlp`.
//! - Proposal: the proposal's 3D table (one block per level), 4D table (one block per level, whole)
//!   and mask grid, each when the blend mode has it.
//! - Static: the field's 3D table (one block per level) and mask grid, each when present.
//! - Shared and dynamic chunk: `chunk: u32` ([`SHARED_TAG`] for the shared section),
//!   `levels: u32`, then per level of the field's 4D table
//!   `rows: u32`, the sorted row numbers as LEB128 varints of `row - previous - 1` (the first as
//!   is), and one block of `rows * features` values.

use std::ops::Range;

use msth_core::field::{EncodingLayout, ModelLayout};
use msth_core::grid::GridLayout;

use crate::error::DecodeError;
use crate::format::QuantMode;
use crate::quant::{max_block_bytes, BlockEncoding, Reader, Writer};

/// Block encodings of one file, derived from its quantisation mode.
#[derive(Clone, Copy, Debug)]
pub struct Encodings {
    /// Hashed table levels.
    pub tables: BlockEncoding,
    /// Densely indexed (coarse) table levels: few values, read by every point.
    pub dense_tables: BlockEncoding,
    pub mask: BlockEncoding,
    pub mlp: BlockEncoding,
}

impl Encodings {
    pub fn for_mode(mode: QuantMode) -> Self {
        let (tables, mask, mlp) = match mode {
            QuantMode::F32 => (BlockEncoding::F32, BlockEncoding::F32, BlockEncoding::F32),
            QuantMode::F16 => (BlockEncoding::F16, BlockEncoding::F16, BlockEncoding::F16),
            QuantMode::Q8 => (
                BlockEncoding::Affine { bits: 8 },
                BlockEncoding::Affine { bits: 8 },
                BlockEncoding::F16,
            ),
            QuantMode::Q6 => (
                BlockEncoding::Affine { bits: 6 },
                BlockEncoding::Affine { bits: 8 },
                BlockEncoding::F16,
            ),
            QuantMode::Q5 => (
                BlockEncoding::Affine { bits: 5 },
                BlockEncoding::Affine { bits: 6 },
                BlockEncoding::F16,
            ),
            QuantMode::Q4 => (
                BlockEncoding::Affine { bits: 4 },
                BlockEncoding::Affine { bits: 6 },
                BlockEncoding::F16,
            ),
            QuantMode::K4 => (
                BlockEncoding::Codebook { bits: 4 },
                BlockEncoding::Affine { bits: 6 },
                BlockEncoding::F16,
            ),
            QuantMode::K3 => (
                BlockEncoding::Codebook { bits: 3 },
                BlockEncoding::Affine { bits: 6 },
                BlockEncoding::F16,
            ),
        };
        let dense_tables = match tables {
            BlockEncoding::Affine { bits } if bits < 8 => BlockEncoding::Affine { bits: 8 },
            BlockEncoding::Codebook { .. } => BlockEncoding::Affine { bits: 8 },
            t => t,
        };
        Encodings {
            tables,
            dense_tables,
            mask,
            mlp,
        }
    }
}

/// The flat-buffer ranges a section's blocks fill, in order (tables: one per level).
fn section_ranges(layout: &ModelLayout, which: StaticPart) -> Vec<(String, Range<usize>, Part)> {
    let mut out = Vec::new();
    let table = |out: &mut Vec<(String, Range<usize>, Part)>,
                 name: &str,
                 g: &(GridLayout, Range<usize>),
                 levels: Range<usize>| {
        for (l, level) in g.0.levels.iter().enumerate() {
            if !levels.contains(&l) {
                continue;
            }
            let start = g.1.start + level.offset;
            out.push((
                format!("{name} level {l}"),
                start..start + level.rows * g.0.features,
                if level.dense {
                    Part::DenseTable
                } else {
                    Part::Table
                },
            ));
        }
    };
    let encoding = |out: &mut Vec<(String, Range<usize>, Part)>,
                    prefix: &str,
                    e: &EncodingLayout,
                    h4_levels: Option<Range<usize>>,
                    h3_levels: Range<usize>,
                    with_mask: bool| {
        if let Some(g) = &e.h3 {
            table(out, &format!("{prefix}.h3"), g, h3_levels);
        }
        if let Some(levels) = h4_levels {
            if let Some(g) = &e.h4 {
                table(out, &format!("{prefix}.h4"), g, levels);
            }
        }
        if let (Some((_, r)), true) = (&e.mask, with_mask) {
            out.push((format!("{prefix}.mask"), r.clone(), Part::Mask));
        }
    };
    match which {
        StaticPart::Mlp => {
            out.push((
                "field.density_mlp".into(),
                layout.field.density.1.clone(),
                Part::Mlp,
            ));
            out.push((
                "field.color_mlp".into(),
                layout.field.color.1.clone(),
                Part::Mlp,
            ));
            out.push((
                "proposal.density_mlp".into(),
                layout.proposal.field.density.1.clone(),
                Part::Mlp,
            ));
        }
        StaticPart::Proposal => encoding(
            &mut out,
            "proposal",
            &layout.proposal.field.encoding,
            Some(0..usize::MAX),
            0..usize::MAX,
            true,
        ),
        StaticPart::ProposalLayer { h3, h4, first } => encoding(
            &mut out,
            "proposal",
            &layout.proposal.field.encoding,
            Some(h4),
            h3,
            first,
        ),
        StaticPart::Static => encoding(
            &mut out,
            "field",
            &layout.field.encoding,
            None,
            0..usize::MAX,
            true,
        ),
        StaticPart::StaticLayer { levels, first } => encoding(
            &mut out,
            "field",
            &layout.field.encoding,
            None,
            levels,
            first,
        ),
    }
    out
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Part {
    Table,
    DenseTable,
    Mask,
    Mlp,
}

/// The sections that are not time chunks.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum StaticPart {
    Mlp,
    Proposal,
    /// The whole static section (a file of one layer).
    Static,
    /// One layer of a layered file's static section (format.md §6.6): the field's 3D table
    /// `levels`, and in the first layer the mask grid after them.
    StaticLayer {
        levels: Range<usize>,
        first: bool,
    },
    /// One layer of a layered file's proposal section: the proposal's 3D table levels `h3`, its
    /// 4D table levels `h4`, and in the first layer its mask grid.
    ProposalLayer {
        h3: Range<usize>,
        h4: Range<usize>,
        first: bool,
    },
}

/// Writes the payload of a non-chunk section.
pub fn write_static(
    layout: &ModelLayout,
    params: &[f32],
    which: StaticPart,
    enc: Encodings,
) -> (Vec<u8>, u64) {
    let mut w = Writer::default();
    let mut values = 0u64;
    for (_, r, part) in section_ranges(layout, which.clone()) {
        let e = match part {
            Part::Table => enc.tables,
            Part::DenseTable => enc.dense_tables,
            Part::Mask => enc.mask,
            Part::Mlp => enc.mlp,
        };
        values += r.len() as u64;
        w.block(&params[r], e);
    }
    (w.bytes, values)
}

/// Largest payload a non-chunk section can have for this model (checked before decompressing).
pub fn max_static_bytes(layout: &ModelLayout, which: StaticPart) -> u64 {
    section_ranges(layout, which)
        .iter()
        .map(|(_, r, _)| max_block_bytes(r.len()))
        .sum()
}

/// Reads a non-chunk section's payload into `params`.
pub fn read_static(
    layout: &ModelLayout,
    payload: &[u8],
    which: StaticPart,
    what: &str,
    params: &mut [f32],
) -> Result<(), DecodeError> {
    let mut r = Reader::new(payload, what);
    for (name, range, _) in section_ranges(layout, which) {
        r.block_into(&mut params[range], &name)?;
    }
    r.finish()
}

/// The `chunk` field of the shared section's payload.
pub const SHARED_TAG: u32 = u32::MAX;

/// The 4D rows of one chunk, per level, with their values (`rows * features` per level).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SparseChunk {
    pub levels: Vec<(Vec<u32>, Vec<f32>)>,
}

impl SparseChunk {
    /// Adds the rows of levels this chunk stores none of from `other` (another layer of the same
    /// chunk: layers hold disjoint levels).
    pub fn merge(&mut self, other: &SparseChunk) {
        if self.levels.len() < other.levels.len() {
            self.levels.resize(other.levels.len(), Default::default());
        }
        for (mine, theirs) in self.levels.iter_mut().zip(&other.levels) {
            if mine.0.is_empty() && !theirs.0.is_empty() {
                *mine = theirs.clone();
            }
        }
    }

    /// Stored table entries (values).
    pub fn entries(&self) -> u64 {
        self.levels.iter().map(|(_, v)| v.len() as u64).sum()
    }

    /// Writes the chunk's values into the field's 4D table in `params`.
    pub fn apply(&self, layout: &ModelLayout, params: &mut [f32]) {
        let Some((g, range)) = &layout.field.encoding.h4 else {
            return;
        };
        let f = g.features;
        for ((rows, values), level) in self.levels.iter().zip(&g.levels) {
            let base = range.start + level.offset;
            for (k, &row) in rows.iter().enumerate() {
                let at = base + row as usize * f;
                params[at..at + f].copy_from_slice(&values[k * f..(k + 1) * f]);
            }
        }
    }
}

/// Writes a chunk payload: rows of the field's 4D table taken from `params`.
pub fn write_chunk(
    layout: &ModelLayout,
    params: &[f32],
    chunk: u32,
    rows: &[Vec<u32>],
    enc: Encodings,
) -> Vec<u8> {
    let (g, range) = layout
        .field
        .encoding
        .h4
        .as_ref()
        .expect("chunks need a 4D table");
    let f = g.features;
    let mut w = Writer::default();
    w.u32(chunk);
    w.u32(g.levels.len() as u32);
    for (level, rows) in g.levels.iter().zip(rows) {
        w.u32(rows.len() as u32);
        let mut prev: Option<u32> = None;
        for &row in rows {
            w.varint(match prev {
                None => row,
                Some(p) => row - p - 1,
            });
            prev = Some(row);
        }
        let base = range.start + level.offset;
        let values: Vec<f32> = rows
            .iter()
            .flat_map(|&row| {
                params[base + row as usize * f..base + (row as usize + 1) * f]
                    .iter()
                    .copied()
            })
            .collect();
        w.block(
            &values,
            if level.dense {
                enc.dense_tables
            } else {
                enc.tables
            },
        );
    }
    w.bytes
}

/// Largest chunk payload for this model.
pub fn max_chunk_bytes(layout: &ModelLayout) -> u64 {
    let Some((g, _)) = &layout.field.encoding.h4 else {
        return 0;
    };
    8 + g
        .levels
        .iter()
        .map(|l| 4 + 5 * l.rows as u64 + max_block_bytes(l.rows * g.features))
        .sum::<u64>()
}

/// Reads a chunk payload, checking every count against the table before allocating.
pub fn read_chunk(
    layout: &ModelLayout,
    payload: &[u8],
    chunk: u32,
    what: &str,
) -> Result<SparseChunk, DecodeError> {
    read_chunk_levels(layout, payload, chunk, 0..usize::MAX, what)
}

/// [`read_chunk`] for one layer of a layered file (format.md §6.6): levels outside `levels`
/// MUST store no rows.
pub fn read_chunk_levels(
    layout: &ModelLayout,
    payload: &[u8],
    chunk: u32,
    allowed: Range<usize>,
    what: &str,
) -> Result<SparseChunk, DecodeError> {
    let Some((g, _)) = &layout.field.encoding.h4 else {
        return Err(DecodeError::malformed(what, "the model has no 4D table"));
    };
    let mut r = Reader::new(payload, what);
    let stored_chunk = r.u32()?;
    if stored_chunk != chunk {
        return Err(DecodeError::malformed(
            what,
            format!("payload is tagged {stored_chunk:#x}, expected {chunk:#x}"),
        ));
    }
    let n_levels = r.u32()? as usize;
    if n_levels != g.levels.len() {
        return Err(DecodeError::malformed(
            what,
            format!("{n_levels} levels, the 4D grid has {}", g.levels.len()),
        ));
    }
    let mut levels = Vec::with_capacity(n_levels);
    for (l, level) in g.levels.iter().enumerate() {
        let n = r.u32()? as usize;
        if n > 0 && !allowed.contains(&l) {
            return Err(DecodeError::malformed(
                what,
                format!(
                    "level {l}: {n} rows stored, but this layer holds levels {}..{}",
                    allowed.start, allowed.end
                ),
            ));
        }
        if n > level.rows {
            return Err(DecodeError::malformed(
                what,
                format!("level {l}: {n} rows stored, the table has {}", level.rows),
            ));
        }
        // Each row takes at least one byte: reject counts the payload cannot hold.
        if n > r.remaining() {
            return Err(DecodeError::malformed(
                what,
                format!("level {l}: {n} rows but {} bytes left", r.remaining()),
            ));
        }
        let mut rows = Vec::with_capacity(n);
        let mut next: u64 = 0;
        for _ in 0..n {
            let row = next + r.varint()? as u64;
            if row >= level.rows as u64 {
                return Err(DecodeError::malformed(
                    what,
                    format!(
                        "level {l}: row {row} outside the table ({} rows)",
                        level.rows
                    ),
                ));
            }
            rows.push(row as u32);
            next = row + 1;
        }
        let mut values = vec![0f32; n * g.features];
        r.block_into(&mut values, &format!("field.h4 level {l}"))?;
        levels.push((rows, values));
    }
    r.finish()?;
    Ok(SparseChunk { levels })
}
