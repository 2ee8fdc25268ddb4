//! The file's container: the fixed header, the JSON metadata and the section index
//! (format.md §2–§4), with the limits a decoder enforces before allocating. Section payloads are
//! in [`crate::sections`].

use serde::{Deserialize, Serialize};

use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::Camera;

use crate::error::DecodeError;

/// `b"MSTH"`.
pub const MAGIC: [u8; 4] = *b"MSTH";
/// The newest format version this crate reads and writes (4: progressive layers). It writes the
/// oldest version that holds a file: [`UNLAYERED_VERSION`] for a file of one layer.
pub const VERSION: u16 = 4;
/// The version of files without layers (3: the metadata's `section_quant` and `play_samples`).
pub const UNLAYERED_VERSION: u16 = 3;
/// The first version with progressive layers (the metadata's `layers`, index entries' `layer`).
pub const LAYERED_VERSION: u16 = 4;
/// The oldest version this crate reads (version 1: no occupancy section).
pub const MIN_VERSION: u16 = 1;
/// Bytes of the fixed header.
pub const FIXED_HEADER: usize = 32;
/// Bytes of one index entry.
pub const INDEX_ENTRY: usize = 40;
/// Sections and the index start on multiples of this many bytes.
pub const ALIGN: u64 = 8;

/// What a section holds (index entry `kind`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SectionKind {
    /// Decoder MLP weights of the field and the proposal.
    Mlp = 1,
    /// The proposal field's tables and mask (the empty-space structure).
    Proposal = 2,
    /// The field's 3D table and mask grid.
    Static = 3,
    /// One time chunk of the field's 4D table, sparse: the rows only this chunk needs.
    Dynamic = 4,
    /// The 4D rows that two or more chunks need, stored once (present iff there are chunks).
    Shared = 5,
    /// The occupancy grid (version 2): where the field has density at any frame.
    Occupancy = 6,
}

impl SectionKind {
    fn from_u8(v: u8) -> Option<Self> {
        Some(match v {
            1 => SectionKind::Mlp,
            2 => SectionKind::Proposal,
            3 => SectionKind::Static,
            4 => SectionKind::Dynamic,
            5 => SectionKind::Shared,
            6 => SectionKind::Occupancy,
            _ => return None,
        })
    }
    pub fn name(self) -> &'static str {
        match self {
            SectionKind::Mlp => "mlp",
            SectionKind::Proposal => "proposal",
            SectionKind::Static => "static",
            SectionKind::Dynamic => "dynamic",
            SectionKind::Shared => "shared",
            SectionKind::Occupancy => "occupancy",
        }
    }
}

/// Index position of chunk 0 in a version-1 file (after MLP, proposal, static and shared); see
/// [`FileIndex::first_chunk`] for any version.
pub const FIRST_CHUNK: usize = 4;

/// The sections a version has before its optional shared section and chunks, in index order.
pub fn fixed_sections(version: u16) -> &'static [SectionKind] {
    if version >= 2 {
        &[
            SectionKind::Mlp,
            SectionKind::Proposal,
            SectionKind::Static,
            SectionKind::Occupancy,
        ]
    } else {
        &[SectionKind::Mlp, SectionKind::Proposal, SectionKind::Static]
    }
}

/// Section compression (index entry `compression`); version 1 has zstd only.
pub const COMPRESSION_ZSTD: u8 = 1;

/// One index entry: where a section lives and how to check it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SectionEntry {
    pub kind: SectionKind,
    /// The chunk number for dynamic sections, 0 otherwise.
    pub chunk: u32,
    /// The progressive layer (version 4; 0 in earlier versions and for the sections that are not
    /// layered: MLP, proposal, occupancy).
    pub layer: u16,
    /// Absolute byte offset of the stored (compressed) bytes.
    pub offset: u64,
    /// Stored bytes.
    pub length: u64,
    /// Bytes after decompression.
    pub raw_length: u64,
    /// CRC-32 (ISO-HDLC, as zlib) of the stored bytes.
    pub crc32: u32,
}

impl SectionEntry {
    pub fn range(&self) -> std::ops::Range<u64> {
        self.offset..self.offset + self.length
    }
    pub fn label(&self) -> String {
        let base = match self.kind {
            SectionKind::Dynamic => format!("dynamic chunk {}", self.chunk),
            SectionKind::Shared => "shared dynamic section".into(),
            k => format!("{} section", k.name()),
        };
        if self.layer > 0 {
            format!("{base}, layer {}", self.layer)
        } else {
            base
        }
    }
}

/// How the tables, masks and MLPs are quantised (the metadata's `quant`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum QuantMode {
    /// Lossless.
    F32,
    F16,
    /// Per-level affine, 8 bits.
    Q8,
    /// Per-level affine, 6 bits.
    Q6,
    /// Per-level affine, 5 bits.
    Q5,
    /// Per-level affine, 4 bits.
    Q4,
    /// Per-level 16-entry codebook (Lloyd-Max), 4 bits.
    K4,
    /// Per-level 8-entry codebook, 3 bits.
    K3,
}

impl QuantMode {
    pub const ALL: [QuantMode; 8] = [
        QuantMode::F32,
        QuantMode::F16,
        QuantMode::Q8,
        QuantMode::Q6,
        QuantMode::Q5,
        QuantMode::Q4,
        QuantMode::K4,
        QuantMode::K3,
    ];
    pub fn name(self) -> &'static str {
        match self {
            QuantMode::F32 => "f32",
            QuantMode::F16 => "f16",
            QuantMode::Q8 => "q8",
            QuantMode::Q6 => "q6",
            QuantMode::Q5 => "q5",
            QuantMode::Q4 => "q4",
            QuantMode::K4 => "k4",
            QuantMode::K3 => "k3",
        }
    }
}

impl QuantMode {
    /// The finer (less lossy) of two modes: the earlier in [`QuantMode::ALL`].
    pub fn finer(self, other: QuantMode) -> QuantMode {
        let rank = |m: QuantMode| QuantMode::ALL.iter().position(|&x| x == m).unwrap_or(0);
        if rank(other) < rank(self) {
            other
        } else {
            self
        }
    }
}

/// How each part of a file is quantised (the metadata's `section_quant`, version 3): each field
/// is the mode whose block encodings (format.md §5.3) that part uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SectionQuant {
    /// The MLP section (modes `q8` to `k3` all store the MLPs as f16).
    pub mlp: QuantMode,
    /// The proposal section: the proposal field's tables and mask.
    pub proposal: QuantMode,
    /// The static section's 3D table levels.
    #[serde(rename = "static")]
    pub static_table: QuantMode,
    /// The static section's mask grid (the mode's mask column of §5.3).
    pub mask: QuantMode,
    /// The field's 4D rows in the shared section and the chunks.
    pub dynamic: QuantMode,
}

/// One part of [`SectionQuant`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QuantPart {
    Mlp,
    Proposal,
    StaticTable,
    Mask,
    Dynamic,
}

impl QuantPart {
    pub const ALL: [QuantPart; 5] = [
        QuantPart::Mlp,
        QuantPart::Proposal,
        QuantPart::StaticTable,
        QuantPart::Mask,
        QuantPart::Dynamic,
    ];
    /// The part's key in the metadata's `section_quant`.
    pub fn name(self) -> &'static str {
        match self {
            QuantPart::Mlp => "mlp",
            QuantPart::Proposal => "proposal",
            QuantPart::StaticTable => "static",
            QuantPart::Mask => "mask",
            QuantPart::Dynamic => "dynamic",
        }
    }
}

impl SectionQuant {
    /// Every part in `mode`: what a file of one mode stores.
    pub fn uniform(mode: QuantMode) -> Self {
        SectionQuant {
            mlp: mode,
            proposal: mode,
            static_table: mode,
            mask: mode,
            dynamic: mode,
        }
    }
    pub fn get(&self, part: QuantPart) -> QuantMode {
        match part {
            QuantPart::Mlp => self.mlp,
            QuantPart::Proposal => self.proposal,
            QuantPart::StaticTable => self.static_table,
            QuantPart::Mask => self.mask,
            QuantPart::Dynamic => self.dynamic,
        }
    }
    pub fn set(&mut self, part: QuantPart, mode: QuantMode) {
        match part {
            QuantPart::Mlp => self.mlp = mode,
            QuantPart::Proposal => self.proposal = mode,
            QuantPart::StaticTable => self.static_table = mode,
            QuantPart::Mask => self.mask = mode,
            QuantPart::Dynamic => self.dynamic = mode,
        }
    }
    /// The finest mode of any part (the metadata's `quant` of a version-3 file).
    pub fn finest(&self) -> QuantMode {
        QuantPart::ALL
            .into_iter()
            .map(|p| self.get(p))
            .fold(QuantMode::K3, QuantMode::finer)
    }
    /// The finest mode of the hash-table parts (proposal, static, dynamic): what decides how
    /// precisely a GPU renderer needs to hold the tables.
    pub fn finest_table(&self) -> QuantMode {
        [self.proposal, self.static_table, self.dynamic]
            .into_iter()
            .fold(QuantMode::K3, QuantMode::finer)
    }
    /// `mode` when every part uses it.
    pub fn single(&self) -> Option<QuantMode> {
        let m = self.mlp;
        QuantPart::ALL
            .into_iter()
            .all(|p| self.get(p) == m)
            .then_some(m)
    }
}

impl std::fmt::Display for SectionQuant {
    /// `mlp f16, proposal q8, static q6, mask q5, dynamic q5`, or the mode alone when every part
    /// uses it.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if let Some(m) = self.single() {
            return write!(f, "{m}");
        }
        let parts: Vec<String> = QuantPart::ALL
            .into_iter()
            .map(|p| format!("{} {}", p.name(), self.get(p)))
            .collect();
        f.write_str(&parts.join(", "))
    }
}

/// The samples per ray a file asks players to use by default (the metadata's `play_samples`,
/// version 3).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaySampleCounts {
    /// Proposal samples per ray.
    pub proposal: u32,
    /// Main samples per ray.
    pub main: u32,
}

impl std::str::FromStr for QuantMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        QuantMode::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                format!(
                    "unknown quantisation mode `{s}` (expected f32, f16, q8, q6, q5, q4, k4 or k3)"
                )
            })
    }
}

impl std::fmt::Display for QuantMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One dynamic chunk's span (the metadata's `chunks[i]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChunkSpan {
    /// First frame (inclusive) and end frame (exclusive) the chunk is meant for.
    pub frame_start: u32,
    pub frame_end: u32,
    /// Normalised times the stored rows cover: every point of a dynamic voxel at any time in
    /// `[t_start, t_end]` reads only stored rows.
    pub t_start: f32,
    pub t_end: f32,
}

/// Everything in the metadata JSON (format.md §3).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Metadata {
    /// The model: grids, mask, blend mode, MLP shapes, sampler, scene bounds, frame count.
    pub model: ModelConfig,
    /// Length of the flat parameter buffer the model needs (a consistency check).
    pub param_count: u64,
    /// Frames per second for playback (`null`: unknown).
    pub frame_rate: Option<f32>,
    /// Normalised time of frame `f` is `f / (num_frames - 1)` (0 for one frame).
    pub time_range: [f32; 2],
    /// Suggested playback cameras.
    pub cameras: Vec<Camera>,
    /// The quantisation mode (version 3: the finest mode of any part, `section_quant` has each).
    pub quant: QuantMode,
    /// Each part's mode (version 3; absent in versions 1 and 2, whose files use `quant`
    /// throughout).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub section_quant: Option<SectionQuant>,
    /// The samples per ray players use unless told otherwise (version 3; absent: the model's
    /// own, `model.sampler`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub play_samples: Option<PlaySampleCounts>,
    /// A mask vertex is dynamic when `1 - sigmoid(logit) >= dynamic_threshold`.
    pub dynamic_threshold: f32,
    /// Frames per dynamic chunk.
    pub chunk_frames: u32,
    /// One span per dynamic section, in chunk order (empty: no dynamic sections).
    pub chunks: Vec<ChunkSpan>,
    /// The progressive layers (version 4; absent: one layer, the whole field), coarse first.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layers: Option<Vec<LayerLevels>>,
    /// Free-form producer string.
    pub encoder: String,
}

/// What layers `0..=l` of a layered file hold (the metadata's `layers[l]`, version 4): the
/// field's 3D and 4D table levels `0..h3` and `0..h4`, the proposal's `0..p3` and `0..p4`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LayerLevels {
    pub h3: u32,
    pub h4: u32,
    pub p3: u32,
    pub p4: u32,
}

impl LayerLevels {
    /// Every level of the model's four tables (0 for a table its blend mode lacks).
    pub fn all(model: &ModelConfig) -> Self {
        let n = |e: &msth_core::config::EncodingConfig, h4: bool| {
            if h4 && e.blend.uses_h4() {
                e.grid4.levels as u32
            } else if !h4 && e.blend.uses_h3() {
                e.grid3.levels as u32
            } else {
                0
            }
        };
        let (f, p) = (&model.field.encoding, &model.proposal.encoding);
        LayerLevels {
            h3: n(f, false),
            h4: n(f, true),
            p3: n(p, false),
            p4: n(p, true),
        }
    }
    fn sum(&self) -> u64 {
        self.h3 as u64 + self.h4 as u64 + self.p3 as u64 + self.p4 as u64
    }
}

impl Metadata {
    /// The layers' cumulative level counts: `layers`, or one layer of every level.
    pub fn layer_levels(&self) -> Vec<LayerLevels> {
        match &self.layers {
            Some(l) => l.clone(),
            None => vec![LayerLevels::all(&self.model)],
        }
    }
    /// Progressive layers: 1 for a file without `layers`.
    pub fn layer_count(&self) -> usize {
        self.layers.as_ref().map_or(1, |l| l.len())
    }
    /// How each part is quantised: `section_quant`, or `quant` throughout (versions 1 and 2).
    pub fn parts_quant(&self) -> SectionQuant {
        self.section_quant
            .unwrap_or_else(|| SectionQuant::uniform(self.quant))
    }
    /// The samples per ray players use by default: `play_samples`, or the model's own.
    pub fn default_samples(&self) -> (usize, usize) {
        match self.play_samples {
            Some(s) => (s.proposal as usize, s.main as usize),
            None => (
                self.model.sampler.num_proposal_samples,
                self.model.sampler.num_samples,
            ),
        }
    }
}

/// Sizes the decoder accepts; everything is checked before anything is allocated. Besides the
/// sizes the decoder itself allocates from, the limits bound every size a file declares that
/// drives a player's allocations (format.md §8): pixels per camera image and samples per ray.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Largest metadata JSON, bytes.
    pub max_metadata: u64,
    /// Most index entries.
    pub max_sections: u64,
    /// Largest flat parameter buffer, floats.
    pub max_params: u64,
    /// Largest stored or decompressed section, bytes.
    pub max_section_bytes: u64,
    /// Most playback cameras.
    pub max_cameras: u64,
    /// Longest side of a camera image, pixels.
    pub max_image_side: u64,
    /// Most pixels of one camera image (width x height).
    pub max_image_pixels: u64,
    /// Most proposal samples per ray (`model.sampler.num_proposal_samples`).
    pub max_proposal_samples: u64,
    /// Most main samples per ray (`model.sampler.num_samples`).
    pub max_samples: u64,
    /// Largest occupancy grid resolution (cells per axis).
    pub max_occupancy_resolution: u64,
}

/// [`Limits::max_image_side`]'s default: 16384 pixels (the largest `msth play --size` side).
pub const MAX_IMAGE_SIDE: u64 = 1 << 14;
/// [`Limits::max_image_pixels`]'s default: 2^24 = 16.8 million pixels (4096 x 4096). A 4K UHD
/// frame (3840 x 2160) is 8.3 million, the Plenoptic Video cameras (2704 x 2028) 5.5 million and
/// their half-resolution training images (1352 x 1014) 1.4 million.
pub const MAX_IMAGE_PIXELS: u64 = 1 << 24;
/// [`Limits::max_proposal_samples`]'s default: 8x the paper's 128 proposal samples per ray (and
/// 4x the largest real proposal stage we know, 2 x 128 or 256 samples).
pub const MAX_PROPOSAL_SAMPLES: u64 = 1024;
/// [`Limits::max_samples`]'s default: more than 10x the paper's 48 main samples per ray.
pub const MAX_SAMPLES: u64 = 512;

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_metadata: 16 << 20,
            max_sections: 1 << 16,
            max_params: 1 << 27,
            max_section_bytes: 2 << 30,
            max_cameras: 4096,
            max_image_side: MAX_IMAGE_SIDE,
            max_image_pixels: MAX_IMAGE_PIXELS,
            max_proposal_samples: MAX_PROPOSAL_SAMPLES,
            max_samples: MAX_SAMPLES,
            max_occupancy_resolution: crate::occupancy::MAX_OCCUPANCY_RESOLUTION,
        }
    }
}

impl Limits {
    /// Checks an image size against [`Limits::max_image_side`] and
    /// [`Limits::max_image_pixels`]; `what` names where it comes from (`cameras[0]`, `--size`).
    pub fn check_image(&self, what: &str, width: u32, height: u32) -> Result<(), DecodeError> {
        for (side, v) in [("width", width), ("height", height)] {
            if v as u64 > self.max_image_side {
                return Err(DecodeError::limit(
                    format!("{what} {side} (pixels)"),
                    v as u64,
                    self.max_image_side,
                ));
            }
        }
        let pixels = width as u64 * height as u64;
        if pixels > self.max_image_pixels {
            return Err(DecodeError::limit(
                format!("{what} pixels ({width} x {height})"),
                pixels,
                self.max_image_pixels,
            ));
        }
        Ok(())
    }

    /// Checks the sizes of a model configuration that drive a renderer's memory: samples per
    /// ray (the parameter count is checked against [`Limits::max_params`] separately).
    pub fn check_model(&self, model: &ModelConfig) -> Result<(), DecodeError> {
        let s = &model.sampler;
        for (what, v, limit) in [
            (
                "model.sampler.num_proposal_samples",
                s.num_proposal_samples as u64,
                self.max_proposal_samples,
            ),
            (
                "model.sampler.num_samples",
                s.num_samples as u64,
                self.max_samples,
            ),
        ] {
            if v > limit {
                return Err(DecodeError::limit(what, v, limit));
            }
        }
        Ok(())
    }
}

/// The fixed header (format.md §2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FixedHeader {
    pub version: u16,
    pub flags: u16,
    /// Bytes of fixed header + metadata + padding + index: the prefix a client fetches first.
    pub header_size: u32,
    pub metadata_length: u32,
    pub section_count: u32,
    pub prefix_crc32: u32,
}

impl FixedHeader {
    pub fn to_bytes(&self) -> [u8; FIXED_HEADER] {
        let mut b = [0u8; FIXED_HEADER];
        b[0..4].copy_from_slice(&MAGIC);
        b[4..6].copy_from_slice(&self.version.to_le_bytes());
        b[6..8].copy_from_slice(&self.flags.to_le_bytes());
        b[8..12].copy_from_slice(&self.header_size.to_le_bytes());
        b[12..16].copy_from_slice(&self.metadata_length.to_le_bytes());
        b[16..20].copy_from_slice(&self.section_count.to_le_bytes());
        // 20..28 reserved, zero
        b[28..32].copy_from_slice(&self.prefix_crc32.to_le_bytes());
        b
    }

    /// Parses and checks the fixed header from the first 32 bytes (or fewer: `Truncated`).
    pub fn parse(bytes: &[u8], limits: &Limits) -> Result<Self, DecodeError> {
        let n = bytes.len().min(4);
        if bytes[..n] != MAGIC[..n] {
            return Err(DecodeError::malformed(
                "header",
                format!("bad magic {:02x?} (expected \"MSTH\")", &bytes[..n]),
            ));
        }
        if bytes.len() < FIXED_HEADER {
            return Err(DecodeError::Truncated {
                what: "fixed header".into(),
                needed: FIXED_HEADER as u64,
                have: bytes.len() as u64,
            });
        }
        let u16_at = |o: usize| u16::from_le_bytes([bytes[o], bytes[o + 1]]);
        let u32_at =
            |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        let h = FixedHeader {
            version: u16_at(4),
            flags: u16_at(6),
            header_size: u32_at(8),
            metadata_length: u32_at(12),
            section_count: u32_at(16),
            prefix_crc32: u32_at(28),
        };
        if !(MIN_VERSION..=VERSION).contains(&h.version) {
            return Err(DecodeError::Unsupported {
                what: "version".into(),
                message: format!(
                    "file is version {}, this decoder reads {MIN_VERSION} to {VERSION}",
                    h.version
                ),
            });
        }
        if h.flags != 0 {
            return Err(DecodeError::malformed(
                "header",
                format!("reserved flag bits set: {:#06x}", h.flags),
            ));
        }
        if bytes[20..28].iter().any(|&b| b != 0) {
            return Err(DecodeError::malformed(
                "header",
                "reserved bytes 20..28 must be zero",
            ));
        }
        if h.metadata_length as u64 > limits.max_metadata {
            return Err(DecodeError::limit(
                "metadata length",
                h.metadata_length as u64,
                limits.max_metadata,
            ));
        }
        if h.section_count as u64 > limits.max_sections {
            return Err(DecodeError::limit(
                "section count",
                h.section_count as u64,
                limits.max_sections,
            ));
        }
        let expected = prefix_size(h.metadata_length as u64, h.section_count as u64);
        if h.header_size as u64 != expected {
            return Err(DecodeError::malformed(
                "header",
                format!(
                    "header_size {} disagrees with metadata length {} and {} sections (expected {expected})",
                    h.header_size, h.metadata_length, h.section_count
                ),
            ));
        }
        Ok(h)
    }
}

/// Offset of the index for a metadata length.
pub fn index_offset(metadata_length: u64) -> u64 {
    (FIXED_HEADER as u64 + metadata_length).div_ceil(ALIGN) * ALIGN
}

/// Bytes of the prefix (fixed header, metadata, padding, index).
pub fn prefix_size(metadata_length: u64, sections: u64) -> u64 {
    index_offset(metadata_length) + sections * INDEX_ENTRY as u64
}

pub fn write_entry(out: &mut Vec<u8>, e: &SectionEntry) {
    out.push(e.kind as u8);
    out.push(COMPRESSION_ZSTD);
    out.extend_from_slice(&e.layer.to_le_bytes());
    out.extend_from_slice(&e.chunk.to_le_bytes());
    out.extend_from_slice(&e.offset.to_le_bytes());
    out.extend_from_slice(&e.length.to_le_bytes());
    out.extend_from_slice(&e.raw_length.to_le_bytes());
    out.extend_from_slice(&e.crc32.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
}

fn parse_entry(b: &[u8], i: usize, version: u16) -> Result<SectionEntry, DecodeError> {
    let what = format!("index entry {i}");
    let u32_at = |o: usize| u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
    let u64_at = |o: usize| {
        let mut a = [0u8; 8];
        a.copy_from_slice(&b[o..o + 8]);
        u64::from_le_bytes(a)
    };
    let kind = SectionKind::from_u8(b[0]).ok_or_else(|| DecodeError::Unsupported {
        what: what.clone(),
        message: format!("section kind {}", b[0]),
    })?;
    if b[1] != COMPRESSION_ZSTD {
        return Err(DecodeError::Unsupported {
            what,
            message: format!("compression {} (zstd = 1 is the only one)", b[1]),
        });
    }
    let layer = u16::from_le_bytes([b[2], b[3]]);
    if (version < LAYERED_VERSION && layer != 0) || u32_at(36) != 0 {
        return Err(DecodeError::malformed(what, "reserved fields must be zero"));
    }
    Ok(SectionEntry {
        kind,
        chunk: u32_at(4),
        layer,
        offset: u64_at(8),
        length: u64_at(16),
        raw_length: u64_at(24),
        crc32: u32_at(32),
    })
}

/// Everything in the file's prefix, checked: the first thing a streaming client decodes.
#[derive(Clone, Debug, PartialEq)]
pub struct FileIndex {
    pub header: FixedHeader,
    pub metadata: Metadata,
    pub sections: Vec<SectionEntry>,
    /// The model's parameter layout (derived from `metadata.model`).
    pub layout: ModelLayout,
}

impl FileIndex {
    /// How many bytes from the start of the file the prefix needs (from its first 32 bytes).
    pub fn prefix_len(first_bytes: &[u8], limits: &Limits) -> Result<u64, DecodeError> {
        Ok(FixedHeader::parse(first_bytes, limits)?.header_size as u64)
    }

    /// Decodes and checks the prefix. `bytes` may be the whole file or any prefix of it that
    /// holds at least `header_size` bytes; sections need not be present.
    pub fn parse(bytes: &[u8], limits: &Limits) -> Result<Self, DecodeError> {
        let header = FixedHeader::parse(bytes, limits)?;
        let hs = header.header_size as usize;
        if bytes.len() < hs {
            return Err(DecodeError::Truncated {
                what: "header and index".into(),
                needed: hs as u64,
                have: bytes.len() as u64,
            });
        }
        let mut crc = crc32fast::Hasher::new();
        crc.update(&bytes[..28]);
        crc.update(&bytes[FIXED_HEADER..hs]);
        let computed = crc.finalize();
        if computed != header.prefix_crc32 && crate::error::VERIFY_CHECKSUMS {
            return Err(DecodeError::Checksum {
                what: "header and index".into(),
                stored: header.prefix_crc32,
                computed,
            });
        }
        let ml = header.metadata_length as usize;
        let meta_bytes = &bytes[FIXED_HEADER..FIXED_HEADER + ml];
        let io = index_offset(ml as u64) as usize;
        if bytes[FIXED_HEADER + ml..io].iter().any(|&b| b != 0) {
            return Err(DecodeError::malformed("metadata", "padding must be zero"));
        }
        let metadata: Metadata = serde_json::from_slice(meta_bytes)
            .map_err(|e| DecodeError::malformed("metadata JSON", e.to_string()))?;
        let layout = check_metadata(&metadata, header.version, limits)?;
        let mut sections = Vec::with_capacity(header.section_count as usize);
        for i in 0..header.section_count as usize {
            let o = io + i * INDEX_ENTRY;
            sections.push(parse_entry(&bytes[o..o + INDEX_ENTRY], i, header.version)?);
        }
        check_sections(&sections, &metadata, header.version, hs as u64, limits)?;
        Ok(FileIndex {
            header,
            metadata,
            sections,
            layout,
        })
    }

    /// Total file length the index implies (end of the last section).
    pub fn file_len(&self) -> u64 {
        self.sections
            .iter()
            .map(|s| s.offset + s.length)
            .max()
            .unwrap_or(self.header.header_size as u64)
    }

    /// Index position of chunk 0: after the version's fixed sections and the shared section.
    pub fn first_chunk(&self) -> usize {
        fixed_sections(self.header.version).len() + 1
    }

    /// The sections a player needs before the first frame (index positions `0..n`): the fixed
    /// sections and, with chunks, the shared section; of a layered file, layer 0 of them.
    pub fn before_first_frame(&self) -> usize {
        let fixed = fixed_sections(self.header.version).len();
        if self.metadata.chunks.is_empty() {
            fixed
        } else {
            fixed + 1
        }
    }

    /// Progressive layers (1 for a file without them).
    pub fn layer_count(&self) -> usize {
        self.metadata.layer_count()
    }

    /// Index entries of each layer after the first: the proposal and static sections, and with
    /// chunks the shared section and every chunk.
    fn per_layer(&self) -> usize {
        let chunks = self.metadata.chunks.len();
        if chunks == 0 {
            2
        } else {
            3 + chunks
        }
    }

    /// Index position of a section of layer `layer` (`chunk` for kind dynamic, else 0); `None`
    /// when the file has no such section.
    pub fn position(&self, kind: SectionKind, chunk: usize, layer: usize) -> Option<usize> {
        let chunks = self.metadata.chunks.len();
        if layer >= self.layer_count() || (kind == SectionKind::Dynamic && chunk >= chunks) {
            return None;
        }
        let fixed = fixed_sections(self.header.version);
        if layer == 0 {
            return match kind {
                SectionKind::Dynamic => Some(self.first_chunk() + chunk),
                SectionKind::Shared => (chunks > 0).then_some(fixed.len()),
                k => fixed.iter().position(|&f| f == k),
            };
        }
        let base = fixed.len() + if chunks > 0 { 1 + chunks } else { 0 };
        let at = base + (layer - 1) * self.per_layer();
        match kind {
            SectionKind::Proposal => Some(at),
            SectionKind::Static => Some(at + 1),
            SectionKind::Shared if chunks > 0 => Some(at + 2),
            SectionKind::Dynamic => Some(at + 3 + chunk),
            _ => None,
        }
    }

    /// Layer 0 of a section of that kind (the first of its kind for chunks).
    pub fn section(&self, kind: SectionKind) -> Option<&SectionEntry> {
        self.sections.iter().find(|s| s.kind == kind)
    }

    /// Layer 0 of chunk `chunk`.
    pub fn chunk(&self, chunk: usize) -> Option<&SectionEntry> {
        self.position(SectionKind::Dynamic, chunk, 0)
            .and_then(|i| self.sections.get(i))
    }

    /// The index positions a player holding layers `0..layers` of chunk `chunk` (`None`: the
    /// static file's sections) has decoded: everything before the first frame, the chunk's
    /// layer 0 and, for each further layer, the proposal, static and shared sections and the
    /// chunk of that layer.
    pub fn sections_for(&self, chunk: Option<usize>, layers: usize) -> Vec<usize> {
        let mut out: Vec<usize> = (0..self.before_first_frame()).collect();
        for l in 0..layers.min(self.layer_count()) {
            if l > 0 {
                out.extend(self.position(SectionKind::Proposal, 0, l));
                out.extend(self.position(SectionKind::Static, 0, l));
                out.extend(self.position(SectionKind::Shared, 0, l));
            }
            if let Some(c) = chunk {
                out.extend(self.position(SectionKind::Dynamic, c, l));
            }
        }
        out
    }

    /// The rules format.md puts on writers that a decoder need not enforce, for validators
    /// (`msth inspect`): chunk spans are contiguous in time, the first starts at 0 and the last
    /// ends at 1 (§3.3).
    pub fn check_writer_rules(&self) -> Result<(), DecodeError> {
        let spans = &self.metadata.chunks;
        let bad = |m: String| Err(DecodeError::malformed("metadata (writer rule, §3.3)", m));
        if let (Some(first), Some(last)) = (spans.first(), spans.last()) {
            if first.t_start != 0.0 {
                return bad(format!("chunk 0 starts at t = {}, not 0", first.t_start));
            }
            if last.t_end != 1.0 {
                return bad(format!(
                    "the last chunk ({}) ends at t = {}, not 1",
                    spans.len() - 1,
                    last.t_end
                ));
            }
        }
        for (c, w) in spans.windows(2).enumerate() {
            if w[0].t_end != w[1].t_start {
                return bad(format!(
                    "chunk {c} ends at t = {} but chunk {} starts at t = {}: spans must be contiguous",
                    w[0].t_end,
                    c + 1,
                    w[1].t_start
                ));
            }
        }
        Ok(())
    }

    /// The chunk a player uses at normalised time `t`: the last chunk whose `t_start <= t`
    /// (chunk 0 before the first); `None` when the file has no dynamic chunks.
    pub fn chunk_for_time(&self, t: f32) -> Option<usize> {
        let spans = &self.metadata.chunks;
        if spans.is_empty() {
            return None;
        }
        Some(spans.iter().rposition(|c| c.t_start <= t).unwrap_or(0))
    }
}

fn check_metadata(m: &Metadata, version: u16, limits: &Limits) -> Result<ModelLayout, DecodeError> {
    m.model
        .validate()
        .map_err(|e| DecodeError::Model(e.to_string()))?;
    limits.check_model(&m.model)?;
    if version < 3 {
        for (key, present) in [
            ("section_quant", m.section_quant.is_some()),
            ("play_samples", m.play_samples.is_some()),
        ] {
            if present {
                return Err(DecodeError::malformed(
                    "metadata",
                    format!("unknown key `{key}` (version {version}; it exists from version 3)"),
                ));
            }
        }
    }
    if let Some(layers) = &m.layers {
        check_layers(m, layers, version)?;
    }
    if let Some(q) = m.section_quant {
        if q.finest() != m.quant {
            return Err(DecodeError::malformed(
                "metadata",
                format!(
                    "quant is {} but the finest mode in section_quant is {}",
                    m.quant,
                    q.finest()
                ),
            ));
        }
    }
    if let Some(s) = m.play_samples {
        for (what, v, limit) in [
            (
                "play_samples.proposal",
                s.proposal as u64,
                limits.max_proposal_samples,
            ),
            ("play_samples.main", s.main as u64, limits.max_samples),
        ] {
            if v == 0 {
                return Err(DecodeError::malformed(
                    "metadata",
                    format!("{what} is 0: at least 1 sample per ray"),
                ));
            }
            if v > limit {
                return Err(DecodeError::limit(what, v, limit));
            }
        }
    }
    // Bound the layout's size before building it: the parameter count of every grid is at most
    // levels * table rows * features, and ModelLayout::new allocates nothing per row.
    let layout = ModelLayout::new(&m.model);
    let total = layout.params.total as u64;
    if total > limits.max_params {
        return Err(DecodeError::limit(
            "parameter count",
            total,
            limits.max_params,
        ));
    }
    if m.param_count != total {
        return Err(DecodeError::Model(format!(
            "metadata says {} parameters, the configuration needs {total}",
            m.param_count
        )));
    }
    if m.cameras.len() as u64 > limits.max_cameras {
        return Err(DecodeError::limit(
            "camera count",
            m.cameras.len() as u64,
            limits.max_cameras,
        ));
    }
    for (i, c) in m.cameras.iter().enumerate() {
        c.validate()
            .map_err(|e| DecodeError::malformed("metadata", format!("camera {i}: {e}")))?;
        limits.check_image(&format!("cameras[{i}]"), c.width, c.height)?;
    }
    if let Some(r) = m.frame_rate {
        if !(r.is_finite() && r > 0.0) {
            return Err(DecodeError::malformed(
                "metadata",
                format!("frame_rate must be positive and finite (got {r})"),
            ));
        }
    }
    if !(m.dynamic_threshold.is_finite() && (0.0..=1.0).contains(&m.dynamic_threshold)) {
        return Err(DecodeError::malformed(
            "metadata",
            "dynamic_threshold must be in [0, 1]",
        ));
    }
    // Version 1 covers normalised time [0, 1] only (format.md §3): another range would mean
    // something a version-1 player cannot show, so it needs a new version.
    if m.time_range != [0.0, 1.0] {
        return Err(DecodeError::malformed(
            "metadata",
            format!(
                "time_range is [{}, {}], version 1 allows only [0, 1]",
                m.time_range[0], m.time_range[1]
            ),
        ));
    }
    if m.chunk_frames == 0 {
        return Err(DecodeError::malformed(
            "metadata",
            "chunk_frames must be >= 1",
        ));
    }
    if !m.chunks.is_empty() && !m.model.field.encoding.blend.uses_h4() {
        return Err(DecodeError::malformed(
            "metadata",
            "dynamic chunks in a model without a 4D table",
        ));
    }
    let mut prev = f32::NEG_INFINITY;
    for (i, c) in m.chunks.iter().enumerate() {
        if !(c.t_start.is_finite() && c.t_end.is_finite() && c.t_start <= c.t_end)
            || c.t_start < prev
            || c.frame_start > c.frame_end
        {
            return Err(DecodeError::malformed(
                "metadata",
                format!("chunk {i}: bad span {c:?}"),
            ));
        }
        prev = c.t_start;
    }
    Ok(layout)
}

/// The metadata's `layers` (version 4): 1..=16 entries, each holding more levels than the one
/// before, the last every level of the field's tables (0 for a table the blend mode lacks).
fn check_layers(m: &Metadata, layers: &[LayerLevels], version: u16) -> Result<(), DecodeError> {
    let bad = |msg: String| Err(DecodeError::malformed("metadata", msg));
    if version < LAYERED_VERSION {
        return bad(format!(
            "unknown key `layers` (version {version}; it exists from version {LAYERED_VERSION})"
        ));
    }
    let max = msth_core::layers::MAX_LAYERS;
    if layers.is_empty() || layers.len() > max {
        return bad(format!(
            "layers has {} entries, expected 1 to {max}",
            layers.len()
        ));
    }
    let full = LayerLevels::all(&m.model);
    let show = |e: &LayerLevels| format!("{}/{}/{}/{}", e.h3, e.h4, e.p3, e.p4);
    let mut prev = LayerLevels {
        h3: 0,
        h4: 0,
        p3: 0,
        p4: 0,
    };
    for (l, &e) in layers.iter().enumerate() {
        if e.h3 < prev.h3
            || e.h4 < prev.h4
            || e.p3 < prev.p3
            || e.p4 < prev.p4
            || e.sum() == prev.sum()
        {
            return bad(format!(
                "layers[{l}] holds levels {} after {}: each layer adds levels",
                show(&e),
                show(&prev)
            ));
        }
        prev = e;
    }
    if prev != full {
        return bad(format!(
            "the last layer holds levels {}, the model's tables have {} (field 3D/4D, proposal 3D/4D)",
            show(&prev),
            show(&full)
        ));
    }
    Ok(())
}

fn check_sections(
    s: &[SectionEntry],
    m: &Metadata,
    version: u16,
    header_size: u64,
    limits: &Limits,
) -> Result<(), DecodeError> {
    let n_chunks = m.chunks.len();
    let fixed = fixed_sections(version);
    let per_layer = if n_chunks == 0 { 2 } else { 3 + n_chunks };
    let first_layer = if n_chunks == 0 {
        fixed.len()
    } else {
        fixed.len() + 1 + n_chunks
    };
    let expected = first_layer + (m.layer_count() - 1) * per_layer;
    if s.len() != expected {
        return Err(DecodeError::malformed(
            "index",
            format!(
                "{} sections, expected {expected} for {n_chunks} chunks in the metadata",
                s.len()
            ),
        ));
    }
    let mut end = header_size;
    for (i, e) in s.iter().enumerate() {
        let (kind, chunk, layer) = match i {
            i if i < fixed.len() => (fixed[i], 0, 0),
            i if i == fixed.len() && n_chunks > 0 => (SectionKind::Shared, 0, 0),
            i if i < first_layer => (SectionKind::Dynamic, (i - fixed.len() - 1) as u32, 0),
            i => {
                let (layer, k) = (
                    (i - first_layer) / per_layer + 1,
                    (i - first_layer) % per_layer,
                );
                match k {
                    0 => (SectionKind::Proposal, 0, layer as u16),
                    1 => (SectionKind::Static, 0, layer as u16),
                    2 => (SectionKind::Shared, 0, layer as u16),
                    c => (SectionKind::Dynamic, (c - 3) as u32, layer as u16),
                }
            }
        };
        if e.kind != kind || e.chunk != chunk || e.layer != layer {
            return Err(DecodeError::malformed(
                "index",
                format!(
                    "entry {i} is {:?} chunk {} layer {}, expected {kind:?} chunk {chunk} layer {layer}",
                    e.kind, e.chunk, e.layer
                ),
            ));
        }
        for (what, v) in [("length", e.length), ("raw_length", e.raw_length)] {
            if v > limits.max_section_bytes {
                return Err(DecodeError::limit(
                    format!("{} {what}", e.label()),
                    v,
                    limits.max_section_bytes,
                ));
            }
        }
        if e.offset % ALIGN != 0 || e.offset < end {
            return Err(DecodeError::malformed(
                "index",
                format!(
                    "{} at offset {} overlaps the previous data (ends at {end}) or is not {ALIGN}-aligned",
                    e.label(),
                    e.offset
                ),
            ));
        }
        end = e.offset.checked_add(e.length).ok_or_else(|| {
            DecodeError::malformed("index", format!("{} range overflows", e.label()))
        })?;
    }
    Ok(())
}
