//! `msth-codec`: the `.msth` streaming file format (normative spec: `docs/format.md`).
//!
//! A file is a prefix (fixed header, JSON metadata, section index) that one HTTP Range request
//! fetches, then zstd-compressed sections a client fetches by byte range: decoder MLPs, the
//! proposal field (the empty-space structure), the static part (3D table, mask grid) and the
//! dynamic part as time chunks, each holding only the 4D-table rows that dynamic voxels reach in
//! its time span, and (version 2) the occupancy grid renderers skip empty space with.
//!
//! - [`encode`]: model configuration + flat parameters + cameras -> bytes and an [`EncodeReport`];
//! - [`Decoder`]: streaming and random access (prefix first, then any section from its bytes);
//! - [`decode_all`] -> [`DecodedModel`]: the flat buffer `msth_core::pipeline::render_chunk`
//!   renders directly, and [`DecodedModel::params_for_time`] for a player's per-chunk buffer.
//!
//! Modules: [`format`] (header, metadata, index, limits), [`quant`] (value blocks and
//! quantisation), [`sections`] (section payloads), [`dynamic_rows`] (which 4D rows a chunk keeps),
//! [`occupancy`] (the occupancy grid and how export computes it), [`error`]. This crate knows the model's layout, not how it was trained.

pub mod decode;
pub mod dynamic_rows;
pub mod encode;
pub mod error;
pub mod format;
pub mod occupancy;
pub mod quant;
pub mod sections;

pub use decode::{decode_all, decode_all_with_limits, DecodedModel, Decoder};
pub use encode::{
    encode, split_layers, ChunkReport, EncodeOptions, EncodeReport, LayerReport, SectionReport,
};
pub use error::{DecodeError, EncodeError};
pub use format::{
    FileIndex, LayerLevels, Limits, Metadata, PlaySampleCounts, QuantMode, QuantPart, SectionEntry,
    SectionKind, SectionQuant,
};
pub use occupancy::OccupancyGrid;

#[cfg(test)]
mod tests;
