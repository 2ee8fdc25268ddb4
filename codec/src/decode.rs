//! The decoder: streaming ([`Decoder`]: the prefix first, then any section from its own bytes, in
//! any order) and whole-file ([`decode_all`] -> [`DecodedModel`]). Untrusted input: every size is
//! checked against [`Limits`] and the model before anything is allocated.

use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::Camera;

use crate::error::DecodeError;
use crate::format::{FileIndex, Limits, Metadata, SectionEntry, SectionKind};
use crate::occupancy::OccupancyGrid;
use crate::sections::{
    max_chunk_bytes, max_static_bytes, read_chunk_levels, read_static, SparseChunk, StaticPart,
    SHARED_TAG,
};

/// Checks a section's stored bytes (length, CRC-32, size limits) and decompresses them.
fn unpack(entry: &SectionEntry, stored: &[u8], max_raw: u64) -> Result<Vec<u8>, DecodeError> {
    let what = entry.label();
    if (stored.len() as u64) < entry.length {
        return Err(DecodeError::Truncated {
            what,
            needed: entry.length,
            have: stored.len() as u64,
        });
    }
    if stored.len() as u64 != entry.length {
        return Err(DecodeError::malformed(
            what,
            format!(
                "{} bytes given, the index says {}",
                stored.len(),
                entry.length
            ),
        ));
    }
    let computed = crc32fast::hash(stored);
    if computed != entry.crc32 && crate::error::VERIFY_CHECKSUMS {
        return Err(DecodeError::Checksum {
            what,
            stored: entry.crc32,
            computed,
        });
    }
    if entry.raw_length > max_raw {
        return Err(DecodeError::limit(
            format!("{what} raw length (largest possible for this model)"),
            entry.raw_length,
            max_raw,
        ));
    }
    check_single_frame(stored, &what)?;
    // The output buffer is bounded by raw_length: zstd fails rather than grow it.
    let raw = zstd::bulk::decompress(stored, entry.raw_length as usize).map_err(|e| {
        DecodeError::Zstd {
            what: what.clone(),
            message: e.to_string(),
        }
    })?;
    if raw.len() as u64 != entry.raw_length {
        return Err(DecodeError::malformed(
            what,
            format!(
                "decompressed to {} bytes, the index says {}",
                raw.len(),
                entry.raw_length
            ),
        ));
    }
    Ok(raw)
}

/// The magic number that opens a zstd frame (RFC 8878 §3.1.1), little-endian.
const ZSTD_MAGIC: [u8; 4] = [0x28, 0xb5, 0x2f, 0xfd];

/// format.md §1.1: a section's stored bytes are exactly one zstd frame. zstd itself would
/// decompress concatenated frames (and skip skippable ones) one after another, so a second frame
/// or any byte after the first would go unnoticed by it; a decoder written from the spec that
/// reads one frame would then disagree with this one.
fn check_single_frame(stored: &[u8], what: &str) -> Result<(), DecodeError> {
    if stored.len() < 4 || stored[..4] != ZSTD_MAGIC {
        return Err(DecodeError::Zstd {
            what: what.into(),
            message: "not a zstd frame (bad magic)".into(),
        });
    }
    // Walks the frame header and block headers only (no decompression, no allocation).
    let frame =
        zstd::zstd_safe::find_frame_compressed_size(stored).map_err(|code| DecodeError::Zstd {
            what: what.into(),
            message: zstd::zstd_safe::get_error_name(code).to_string(),
        })?;
    if frame != stored.len() {
        return Err(DecodeError::malformed(
            what,
            format!(
                "{} bytes after the zstd frame ({frame} of {} stored bytes): a section is exactly one frame",
                stored.len() - frame,
                stored.len()
            ),
        ));
    }
    Ok(())
}

/// A streaming decoder: built from the file's prefix, fed sections as their bytes arrive.
///
/// Of a layered file (version 4) it renders from what has arrived: the static section's layers
/// decoded so far (the finer levels' values 0), and each 4D layer whose shared section and
/// chunk have both arrived ([`Decoder::params_for_time_into`]).
#[derive(Clone, Debug)]
pub struct Decoder {
    index: FileIndex,
    /// MLPs, proposal and static tables; the 4D table stays zero here.
    base: Vec<f32>,
    /// Per index position: decoded.
    decoded: Vec<bool>,
    /// Per layer: the shared 4D rows of that layer.
    shared: Vec<Option<SparseChunk>>,
    /// Per layer, per chunk: the chunk's 4D rows of that layer.
    chunks: Vec<Vec<Option<SparseChunk>>>,
    /// The occupancy grid (version 2 files), once decoded.
    occupancy: Option<OccupancyGrid>,
    max_occupancy_resolution: u64,
}

impl Decoder {
    /// Decodes the prefix (header, metadata, index) with the default limits. `bytes` is the start
    /// of the file: [`FileIndex::prefix_len`] of them are enough.
    pub fn new(bytes: &[u8]) -> Result<Self, DecodeError> {
        Self::with_limits(bytes, &Limits::default())
    }

    pub fn with_limits(bytes: &[u8], limits: &Limits) -> Result<Self, DecodeError> {
        let index = FileIndex::parse(bytes, limits)?;
        let base = vec![0f32; index.layout.params.total];
        let layers = index.layer_count();
        let chunks = vec![vec![None; index.metadata.chunks.len()]; layers];
        Ok(Decoder {
            base,
            decoded: vec![false; index.sections.len()],
            shared: vec![None; layers],
            chunks,
            index,
            occupancy: None,
            max_occupancy_resolution: limits.max_occupancy_resolution,
        })
    }

    pub fn index(&self) -> &FileIndex {
        &self.index
    }
    pub fn metadata(&self) -> &Metadata {
        &self.index.metadata
    }
    pub fn layout(&self) -> &ModelLayout {
        &self.index.layout
    }

    /// Whether section `i` (index order) has been decoded.
    pub fn is_decoded(&self, i: usize) -> bool {
        self.decoded.get(i).copied().unwrap_or(false)
    }

    /// How many layers, from the first, of chunk `chunk` (`None`: of a file without chunks)
    /// have arrived with the static and shared sections of the same layers: the layers a frame
    /// of that chunk is drawn with. 0 until the static sections and the chunk's layer 0 are in.
    pub fn layers_ready(&self, chunk: Option<usize>) -> usize {
        if !self.static_ready() {
            return 0;
        }
        let ix = &self.index;
        (0..ix.layer_count())
            .take_while(|&l| {
                let ok = |kind, c| ix.position(kind, c, l).is_none_or(|i| self.is_decoded(i));
                ok(SectionKind::Proposal, 0)
                    && ok(SectionKind::Static, 0)
                    && ok(SectionKind::Shared, 0)
                    && chunk.is_none_or(|c| ok(SectionKind::Dynamic, c))
            })
            .count()
    }

    /// Every section before the first chunk decoded (MLPs, proposal, static, the occupancy grid
    /// of a version-2 file and, when there are chunks, the shared section): frames can be
    /// rendered once their chunk is.
    pub fn static_ready(&self) -> bool {
        (0..self.index.before_first_frame()).all(|i| self.is_decoded(i))
    }

    /// The occupancy grid: `None` before its section is decoded and for version-1 files (which
    /// have none: a renderer then skips nothing).
    pub fn occupancy(&self) -> Option<&OccupancyGrid> {
        self.occupancy.as_ref()
    }

    /// Decodes section `i` (index order) from exactly its stored bytes.
    pub fn decode_section(&mut self, i: usize, stored: &[u8]) -> Result<(), DecodeError> {
        let entry = self
            .index
            .sections
            .get(i)
            .cloned()
            .ok_or_else(|| DecodeError::malformed("request", format!("no section {i}")))?;
        let layout = &self.index.layout;
        let what = entry.label();
        let layer = entry.layer as usize;
        let levels = self.index.metadata.layer_levels();
        // The levels of layer `layer` of one of the tables.
        let range_of = |end: &dyn Fn(&crate::format::LayerLevels) -> u32| {
            let start = if layer == 0 {
                0
            } else {
                end(&levels[layer - 1]) as usize
            };
            start..end(&levels[layer]) as usize
        };
        let level_range = |h4: bool| {
            if h4 {
                range_of(&|e| e.h4)
            } else {
                range_of(&|e| e.h3)
            }
        };
        let layered = self.index.metadata.layers.is_some();
        match entry.kind {
            SectionKind::Dynamic => {
                let raw = unpack(&entry, stored, max_chunk_bytes(layout))?;
                let chunk = read_chunk_levels(layout, &raw, entry.chunk, level_range(true), &what)?;
                self.chunks[layer][entry.chunk as usize] = Some(chunk);
            }
            SectionKind::Shared => {
                let raw = unpack(&entry, stored, max_chunk_bytes(layout))?;
                self.shared[layer] = Some(read_chunk_levels(
                    layout,
                    &raw,
                    SHARED_TAG,
                    level_range(true),
                    &what,
                )?);
            }
            SectionKind::Occupancy => {
                let max = self.max_occupancy_resolution;
                let raw = unpack(&entry, stored, OccupancyGrid::payload_len(max))?;
                self.occupancy = Some(OccupancyGrid::from_payload(&raw, max, &what)?);
            }
            kind => {
                let part = match kind {
                    SectionKind::Mlp => StaticPart::Mlp,
                    SectionKind::Proposal if layered => StaticPart::ProposalLayer {
                        h3: range_of(&|e| e.p3),
                        h4: range_of(&|e| e.p4),
                        first: layer == 0,
                    },
                    SectionKind::Proposal => StaticPart::Proposal,
                    _ if layered => StaticPart::StaticLayer {
                        levels: level_range(false),
                        first: layer == 0,
                    },
                    _ => StaticPart::Static,
                };
                let raw = unpack(&entry, stored, max_static_bytes(layout, part.clone()))?;
                // Decode into a copy so that a failure leaves the decoder unchanged.
                let mut params = self.base.clone();
                read_static(layout, &raw, part, &what, &mut params)?;
                self.base = params;
            }
        }
        self.decoded[i] = true;
        Ok(())
    }

    /// Decodes every section that lies wholly inside `file_prefix` (the first bytes of the file)
    /// and is not decoded yet; returns their index positions. Sections not yet complete are left
    /// for a later call.
    pub fn feed(&mut self, file_prefix: &[u8]) -> Result<Vec<usize>, DecodeError> {
        let mut done = Vec::new();
        for i in 0..self.index.sections.len() {
            if self.is_decoded(i) {
                continue;
            }
            let e = &self.index.sections[i];
            let end = e.offset + e.length;
            if end > file_prefix.len() as u64 {
                continue;
            }
            let stored = &file_prefix[e.offset as usize..end as usize];
            self.decode_section(i, stored)?;
            done.push(i);
        }
        Ok(done)
    }

    /// The decoded chunk `c` (its layer 0), if it has arrived.
    pub fn chunk(&self, c: usize) -> Option<&SparseChunk> {
        self.chunks[0].get(c).and_then(|c| c.as_ref())
    }

    /// Writes the parameters for normalised time `t` into `out`: the static part and the rows of
    /// the chunk covering `t` (other 4D rows 0). Needs the static sections and that chunk (its
    /// layer 0); of a layered file, the static layers that have arrived and the 4D layers of
    /// [`Decoder::layers_ready`].
    pub fn params_for_time_into(&self, t: f32, out: &mut Vec<f32>) -> Result<(), DecodeError> {
        self.params_for_layers_into(t, usize::MAX, out)
    }

    /// [`Decoder::params_for_time_into`] with at most `layers` layers: the static section's
    /// finer layers are left out (their levels 0) even if they have arrived. What a player
    /// holding `layers` layers draws; `usize::MAX`: every layer that has arrived.
    pub fn params_for_layers_into(
        &self,
        t: f32,
        layers: usize,
        out: &mut Vec<f32>,
    ) -> Result<(), DecodeError> {
        if !self.static_ready() {
            let missing = (0..self.index.before_first_frame())
                .find(|&i| !self.is_decoded(i))
                .unwrap_or(0);
            return Err(not_loaded(&self.index.sections[missing]));
        }
        out.clear();
        out.extend_from_slice(&self.base);
        let layout = &self.index.layout;
        if layers < self.index.layer_count() {
            // Zero the levels of the layers left out: the field's 3D table and the proposal's
            // tables (the field's 4D rows come from the chunks' layers below).
            let keep = self.index.metadata.layer_levels()[layers.max(1) - 1];
            let prop = &layout.proposal.field.encoding;
            for (grid, keep) in [
                (&layout.field.encoding.h3, keep.h3),
                (&prop.h3, keep.p3),
                (&prop.h4, keep.p4),
            ] {
                if let Some((g, range)) = grid {
                    for level in g.levels.iter().skip(keep as usize) {
                        let start = range.start + level.offset;
                        out[start..start + level.rows * g.features].fill(0.0);
                    }
                }
            }
        }
        let chunk = self.index.chunk_for_time(t);
        if let Some(c) = chunk {
            if self.chunk(c).is_none() {
                return Err(not_loaded(
                    &self.index.sections[self.index.first_chunk() + c],
                ));
            }
            for l in 0..self.layers_ready(chunk).min(layers.max(1)) {
                if let Some(shared) = &self.shared[l] {
                    shared.apply(layout, out);
                }
                if let Some(part) = &self.chunks[l][c] {
                    part.apply(layout, out);
                }
            }
        }
        Ok(())
    }

    pub fn params_for_time(&self, t: f32) -> Result<Vec<f32>, DecodeError> {
        let mut out = Vec::new();
        self.params_for_time_into(t, &mut out)?;
        Ok(out)
    }

    /// The whole model; every section must have been decoded.
    pub fn finish(self) -> Result<DecodedModel, DecodeError> {
        if let Some(i) = (0..self.index.sections.len()).find(|&i| !self.is_decoded(i)) {
            return Err(not_loaded(&self.index.sections[i]));
        }
        // Each chunk and the shared section with all their layers.
        let mut layers = self.chunks.into_iter();
        let mut chunks: Vec<SparseChunk> = layers
            .next()
            .unwrap_or_default()
            .into_iter()
            .flatten()
            .collect();
        for layer in layers {
            for (c, part) in chunks.iter_mut().zip(layer.into_iter().flatten()) {
                c.merge(&part);
            }
        }
        let mut shared_layers = self.shared.into_iter().flatten();
        let shared = shared_layers.next().map(|mut s| {
            for part in shared_layers {
                s.merge(&part);
            }
            s
        });
        let mut base = self.base;
        if let Some(shared) = &shared {
            shared.apply(&self.index.layout, &mut base);
        }
        let mut params = base.clone();
        for c in &chunks {
            c.apply(&self.index.layout, &mut params);
        }
        Ok(DecodedModel {
            config: self.index.metadata.model.clone(),
            cameras: self.index.metadata.cameras.clone(),
            layout: self.index.layout.clone(),
            metadata: self.index.metadata,
            occupancy: self.occupancy,
            params,
            base,
            shared,
            chunks,
        })
    }
}

fn not_loaded(e: &SectionEntry) -> DecodeError {
    DecodeError::Truncated {
        what: format!(
            "{} (bytes {}..{})",
            e.label(),
            e.offset,
            e.offset + e.length
        ),
        needed: e.offset + e.length,
        have: 0,
    }
}

/// A whole decoded model.
#[derive(Clone, Debug)]
pub struct DecodedModel {
    pub config: ModelConfig,
    pub layout: ModelLayout,
    /// The full flat buffer in [`ModelLayout`] order: the static part, the shared 4D rows and
    /// the union of every chunk's 4D rows (4D rows the file does not store are 0).
    pub params: Vec<f32>,
    pub cameras: Vec<Camera>,
    pub metadata: Metadata,
    /// The occupancy grid (`None` for a version-1 file).
    pub occupancy: Option<OccupancyGrid>,
    /// Static part plus the shared 4D rows.
    base: Vec<f32>,
    shared: Option<SparseChunk>,
    chunks: Vec<SparseChunk>,
}

impl DecodedModel {
    /// The chunk a player uses at normalised time `t` (`None`: no dynamic chunks).
    pub fn chunk_for_time(&self, t: f32) -> Option<usize> {
        let spans = &self.metadata.chunks;
        if spans.is_empty() {
            return None;
        }
        Some(spans.iter().rposition(|c| c.t_start <= t).unwrap_or(0))
    }

    pub fn chunks(&self) -> &[SparseChunk] {
        &self.chunks
    }

    /// The 4D rows stored once for several chunks (`None` without chunks).
    pub fn shared(&self) -> Option<&SparseChunk> {
        self.shared.as_ref()
    }

    /// What a streaming player renders at time `t`: the static part, the shared 4D rows and the
    /// covering chunk's rows; other 4D rows 0.
    pub fn params_for_time_into(&self, t: f32, out: &mut Vec<f32>) {
        out.clear();
        out.extend_from_slice(&self.base);
        if let Some(c) = self.chunk_for_time(t) {
            self.chunks[c].apply(&self.layout, out);
        }
    }

    pub fn params_for_time(&self, t: f32) -> Vec<f32> {
        let mut out = Vec::new();
        self.params_for_time_into(t, &mut out);
        out
    }
}

/// Decodes a whole file with the default limits.
pub fn decode_all(bytes: &[u8]) -> Result<DecodedModel, DecodeError> {
    decode_all_with_limits(bytes, &Limits::default())
}

/// Decodes a whole file; the file must end exactly where its last section ends.
pub fn decode_all_with_limits(bytes: &[u8], limits: &Limits) -> Result<DecodedModel, DecodeError> {
    let mut d = Decoder::with_limits(bytes, limits)?;
    let end = d.index.file_len();
    if (bytes.len() as u64) < end {
        return Err(DecodeError::Truncated {
            what: "file".into(),
            needed: end,
            have: bytes.len() as u64,
        });
    }
    if bytes.len() as u64 > end {
        return Err(DecodeError::malformed(
            "file",
            format!(
                "{} trailing bytes after the last section",
                bytes.len() as u64 - end
            ),
        ));
    }
    // Padding between sections is not covered by any checksum: it must be zero.
    let mut at = d.index.header.header_size as u64;
    for e in &d.index.sections {
        if bytes[at as usize..e.offset as usize]
            .iter()
            .any(|&b| b != 0)
        {
            return Err(DecodeError::malformed(
                "file",
                format!("nonzero padding before {}", e.label()),
            ));
        }
        at = e.offset + e.length;
    }
    d.feed(bytes)?;
    d.finish()
}
