//! The encoder: a model configuration, its flat parameter buffer and playback cameras in, a
//! `.msth` file and a report of what went where out.

use std::time::Instant;

use msth_core::config::ModelConfig;
use msth_core::field::ModelLayout;
use msth_core::Camera;

use crate::dynamic_rows::{dynamic_region, reached_rows};
use crate::error::EncodeError;
use crate::format::{
    index_offset, prefix_size, write_entry, ChunkSpan, FixedHeader, LayerLevels, Metadata,
    PlaySampleCounts, QuantMode, SectionEntry, SectionKind, SectionQuant, ALIGN, FIXED_HEADER,
    LAYERED_VERSION, UNLAYERED_VERSION,
};
use crate::occupancy::{
    OccupancyGrid, DEFAULT_OCCUPANCY_ALPHA, DEFAULT_OCCUPANCY_RESOLUTION, MAX_OCCUPANCY_RESOLUTION,
};
use crate::sections::{write_chunk, write_static, Encodings, StaticPart, SHARED_TAG};

/// What the encoder is asked to do.
#[derive(Clone, Debug, PartialEq)]
pub struct EncodeOptions {
    /// The mode of every part, unless `sections` says otherwise.
    pub quant: QuantMode,
    /// Each part's mode (metadata `section_quant`); `None`: every part in `quant`.
    pub sections: Option<SectionQuant>,
    /// The samples per ray (proposal, main) players use by default (metadata `play_samples`);
    /// `None`: the model's own.
    pub play_samples: Option<PlaySampleCounts>,
    /// Frames per dynamic chunk.
    pub chunk_frames: usize,
    /// A mask vertex is dynamic when `1 - sigmoid(logit) >= dynamic_threshold`.
    pub dynamic_threshold: f32,
    /// Playback frame rate written to the metadata.
    pub frame_rate: Option<f32>,
    /// zstd level for every section.
    pub zstd_level: i32,
    /// Occupancy grid cells per axis (format.md §6.5), 1..=512.
    pub occupancy_resolution: u32,
    /// Opacity budget of the occupancy threshold: a ray crossing the grid's diagonal through
    /// density just below the threshold would reach this opacity
    /// ([`crate::occupancy::density_threshold`]).
    pub occupancy_alpha: f32,
    /// A grid computed beforehand (e.g. once for several encodings of one model); `None`: the
    /// encoder computes it from the parameters.
    pub occupancy: Option<std::sync::Arc<OccupancyGrid>>,
    /// Progressive layers (format.md §6.6), 1..=16: the field's table levels split coarse to
    /// fine ([`msth_core::layers::layer_level_ends`]). 1 writes a version-3 file without layers.
    pub layers: usize,
}

impl Default for EncodeOptions {
    fn default() -> Self {
        EncodeOptions {
            quant: QuantMode::Q5,
            sections: None,
            play_samples: None,
            chunk_frames: 10,
            dynamic_threshold: 0.3,
            frame_rate: None,
            zstd_level: 9,
            occupancy_resolution: DEFAULT_OCCUPANCY_RESOLUTION,
            occupancy_alpha: DEFAULT_OCCUPANCY_ALPHA,
            occupancy: None,
            layers: 1,
        }
    }
}

/// Bytes of one section.
#[derive(Clone, Debug, PartialEq)]
pub struct SectionReport {
    pub name: String,
    pub stored_bytes: u64,
    pub raw_bytes: u64,
    /// Parameter values held.
    pub values: u64,
}

/// Bytes and contents of one dynamic chunk.
#[derive(Clone, Debug, PartialEq)]
pub struct ChunkReport {
    pub span: ChunkSpan,
    pub stored_bytes: u64,
    pub raw_bytes: u64,
    /// 4D values (rows x features) the chunk's time span reaches: what a player holds for it
    /// (shared section + this chunk).
    pub reached_values: u64,
    /// 4D values stored in the chunk itself (those no other chunk needs).
    pub kept_values: u64,
}

/// Bytes of one progressive layer.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerReport {
    /// The table levels layers `0..=l` hold.
    pub levels: LayerLevels,
    /// Stored bytes of the layer's proposal section.
    pub proposal_bytes: u64,
    /// Stored bytes of the layer's static section.
    pub static_bytes: u64,
    /// Stored bytes of the layer's shared section and chunks.
    pub dynamic_bytes: u64,
    /// Stored bytes of the layer's part of chunk 0 (with the shared section's): what it adds to
    /// the first frame.
    pub first_chunk_bytes: u64,
}

/// What went where.
#[derive(Clone, Debug, PartialEq)]
pub struct EncodeReport {
    /// The finest mode of any part (the metadata's `quant`).
    pub quant: QuantMode,
    /// Each part's mode.
    pub section_quant: SectionQuant,
    pub file_bytes: u64,
    /// Header, metadata and index.
    pub prefix_bytes: u64,
    /// `4 * parameter count`: the raw f32 parameters of the checkpoint.
    pub raw_param_bytes: u64,
    /// The sections that are not chunks (each summed over its layers).
    pub sections: Vec<SectionReport>,
    /// The chunks (each summed over its layers).
    pub chunks: Vec<ChunkReport>,
    /// The progressive layers, coarse first (one for a file without layers).
    pub layers: Vec<LayerReport>,
    /// Values of the field's 4D table (0 without one).
    pub h4_values: u64,
    /// Distinct 4D values kept by at least one chunk.
    pub h4_kept_union: u64,
    /// Dynamic and total mask voxels (`None`: no mask, everything is dynamic).
    pub dynamic_voxels: Option<(u64, u64)>,
    pub num_frames: usize,
    /// Occupied and total cells of the occupancy grid.
    pub occupied_cells: (u64, u64),
    pub encode_seconds: f64,
}

impl EncodeReport {
    /// Bytes a player fetches before the first frame when it takes layers `0..layers`: the
    /// prefix, the sections that are not layered (MLPs, occupancy), and those layers' proposal,
    /// static, shared and chunk-0 parts.
    pub fn first_frame_bytes(&self, layers: usize) -> u64 {
        let fixed: u64 = self
            .sections
            .iter()
            .filter(|s| !["proposal", "static", "shared"].contains(&s.name.as_str()))
            .map(|s| s.stored_bytes)
            .sum();
        self.prefix_bytes
            + fixed
            + self
                .layers
                .iter()
                .take(layers)
                .map(|l| l.proposal_bytes + l.static_bytes + l.first_chunk_bytes)
                .sum::<u64>()
    }

    /// Stored bytes of layer `l`'s sections (proposal, static, shared, chunks).
    pub fn layer_bytes(&self, l: usize) -> u64 {
        self.layers
            .get(l)
            .map_or(0, |r| r.proposal_bytes + r.static_bytes + r.dynamic_bytes)
    }

    /// Bytes of the file a player holding layers `0..layers` of every chunk has fetched: the
    /// whole file less the later layers' sections.
    pub fn bytes_through(&self, layers: usize) -> u64 {
        self.file_bytes
            - (layers..self.layers.len())
                .map(|l| self.layer_bytes(l))
                .sum::<u64>()
    }

    pub fn ratio(&self) -> f64 {
        self.raw_param_bytes as f64 / self.file_bytes.max(1) as f64
    }
    pub fn bytes_per_frame(&self) -> f64 {
        self.file_bytes as f64 / self.num_frames.max(1) as f64
    }
    /// Chunk bytes per frame (the streaming rate once the static and shared parts are loaded).
    pub fn dynamic_bytes_per_frame(&self) -> f64 {
        self.chunks.iter().map(|c| c.stored_bytes).sum::<u64>() as f64
            / self.num_frames.max(1) as f64
    }
}

/// Normalised time of frame `f` of `n`.
pub fn frame_time(f: usize, n: usize) -> f32 {
    if n > 1 {
        (f.min(n - 1)) as f32 / (n - 1) as f32
    } else {
        0.0
    }
}

/// The chunk spans of a model: `ceil(frames / chunk_frames)` chunks, contiguous in time and
/// covering `[0, 1]`.
pub fn chunk_spans(num_frames: usize, chunk_frames: usize) -> Vec<ChunkSpan> {
    let n = num_frames.max(1);
    let count = n.div_ceil(chunk_frames);
    (0..count)
        .map(|c| {
            let f0 = c * chunk_frames;
            let f1 = ((c + 1) * chunk_frames).min(n);
            ChunkSpan {
                frame_start: f0 as u32,
                frame_end: f1 as u32,
                t_start: if c == 0 { 0.0 } else { frame_time(f0, n) },
                t_end: if c + 1 == count {
                    1.0
                } else {
                    frame_time(f1, n)
                },
            }
        })
        .collect()
}

/// Row numbers per level of the field's 4D table.
type RowsPerLevel = Vec<Vec<u32>>;

/// The layers' cumulative level counts for `layers` requested layers: each of the model's four
/// tables (the field's and the proposal's 3D and 4D tables) split evenly by level count
/// ([`msth_core::layers::level_end`]), at most one layer per level of the field's tables.
pub fn split_layers(model: &ModelConfig, layers: usize) -> Vec<LayerLevels> {
    let all = LayerLevels::all(model);
    let n = msth_core::layers::layer_count(all.h3.max(all.h4) as usize, layers);
    let end = |levels: u32, l: usize| msth_core::layers::level_end(levels as usize, n, l) as u32;
    (0..n)
        .map(|l| LayerLevels {
            h3: end(all.h3, l),
            h4: end(all.h4, l),
            p3: end(all.p3, l),
            p4: end(all.p4, l),
        })
        .collect()
}

fn compress(raw: &[u8], level: i32) -> Result<Vec<u8>, EncodeError> {
    zstd::bulk::compress(raw, level).map_err(EncodeError::Compress)
}

/// The occupancy grid [`encode`] stores when `opts.occupancy` is `None`
/// ([`crate::occupancy::compute`] at `opts.occupancy_resolution` and `opts.occupancy_alpha`).
/// Compute it once for several encodings of one model and pass it as `opts.occupancy`.
pub fn occupancy_grid(
    model: &ModelConfig,
    layout: &ModelLayout,
    params: &[f32],
    opts: &EncodeOptions,
) -> OccupancyGrid {
    crate::occupancy::compute(
        model,
        layout,
        params,
        opts.occupancy_resolution,
        opts.occupancy_alpha,
    )
}

/// Encodes a model into `.msth` bytes.
pub fn encode(
    model: &ModelConfig,
    params: &[f32],
    cameras: &[Camera],
    opts: &EncodeOptions,
) -> Result<(Vec<u8>, EncodeReport), EncodeError> {
    let start = Instant::now();
    model
        .validate()
        .map_err(|e| EncodeError::InvalidConfig(e.to_string()))?;
    // Never write a file the decoder's default limits refuse.
    let limits = crate::Limits::default();
    limits
        .check_model(model)
        .map_err(|e| EncodeError::InvalidConfig(e.to_string()))?;
    let layout = ModelLayout::new(model);
    if params.len() != layout.params.total {
        return Err(EncodeError::ParamCount {
            got: params.len(),
            expected: layout.params.total,
        });
    }
    for e in &layout.params.entries {
        if let Some(i) = params[e.range()].iter().position(|v| !v.is_finite()) {
            return Err(EncodeError::NonFinite {
                slice: e.name.clone(),
                index: i,
            });
        }
    }
    if opts.chunk_frames == 0 {
        return Err(EncodeError::InvalidOption(
            "chunk_frames must be at least 1".into(),
        ));
    }
    if !(opts.dynamic_threshold.is_finite() && (0.0..=1.0).contains(&opts.dynamic_threshold)) {
        return Err(EncodeError::InvalidOption(format!(
            "dynamic_threshold must be in [0, 1] (got {})",
            opts.dynamic_threshold
        )));
    }
    if let Some(r) = opts.frame_rate {
        if !(r.is_finite() && r > 0.0) {
            return Err(EncodeError::InvalidOption(format!(
                "frame_rate must be positive (got {r})"
            )));
        }
    }
    if !(-7..=22).contains(&opts.zstd_level) {
        return Err(EncodeError::InvalidOption(format!(
            "zstd_level must be in -7..=22 (got {})",
            opts.zstd_level
        )));
    }
    for (index, c) in cameras.iter().enumerate() {
        c.validate().map_err(|e| EncodeError::InvalidCamera {
            index,
            message: e.to_string(),
        })?;
        limits
            .check_image(&format!("cameras[{index}]"), c.width, c.height)
            .map_err(|e| EncodeError::InvalidCamera {
                index,
                message: e.to_string(),
            })?;
    }
    if !(1..=MAX_OCCUPANCY_RESOLUTION).contains(&(opts.occupancy_resolution as u64)) {
        return Err(EncodeError::InvalidOption(format!(
            "occupancy_resolution must be in 1..={MAX_OCCUPANCY_RESOLUTION} (got {})",
            opts.occupancy_resolution
        )));
    }
    if !(opts.occupancy_alpha.is_finite() && (0.0..1.0).contains(&opts.occupancy_alpha)) {
        return Err(EncodeError::InvalidOption(format!(
            "occupancy_alpha must be in [0, 1) (got {})",
            opts.occupancy_alpha
        )));
    }
    if let Some(s) = opts.play_samples {
        let limits = crate::Limits::default();
        if !(1..=limits.max_proposal_samples).contains(&(s.proposal as u64))
            || !(1..=limits.max_samples).contains(&(s.main as u64))
        {
            return Err(EncodeError::InvalidOption(format!(
                "play_samples {},{}: proposal samples must lie in 1..={} and main samples in 1..={}",
                s.proposal, s.main, limits.max_proposal_samples, limits.max_samples
            )));
        }
    }
    let parts = opts
        .sections
        .unwrap_or_else(|| SectionQuant::uniform(opts.quant));
    let static_enc = Encodings {
        mask: Encodings::for_mode(parts.mask).mask,
        ..Encodings::for_mode(parts.static_table)
    };
    let dyn_enc = Encodings::for_mode(parts.dynamic);
    if !(1..=msth_core::layers::MAX_LAYERS).contains(&opts.layers) {
        return Err(EncodeError::InvalidOption(format!(
            "layers must be in 1..={} (got {})",
            msth_core::layers::MAX_LAYERS,
            opts.layers
        )));
    }
    let layer_levels = split_layers(model, opts.layers);
    let layered = layer_levels.len() > 1;
    // Level ranges of layer l in one of the tables.
    let range_of = |l: usize, end: &dyn Fn(&LayerLevels) -> u32| {
        let start = if l == 0 {
            0
        } else {
            end(&layer_levels[l - 1]) as usize
        };
        start..end(&layer_levels[l]) as usize
    };
    let level_range = |l: usize, h4: bool| {
        if h4 {
            range_of(l, &|e| e.h4)
        } else {
            range_of(l, &|e| e.h3)
        }
    };
    let proposal_part = |l: usize| StaticPart::ProposalLayer {
        h3: range_of(l, &|e| e.p3),
        h4: range_of(l, &|e| e.p4),
        first: l == 0,
    };
    // Rows of `rows` (per level) that layer l holds.
    let rows_of_layer = |rows: &[Vec<u32>], l: usize| -> Vec<Vec<u32>> {
        let r = level_range(l, true);
        rows.iter()
            .enumerate()
            .map(|(k, v)| {
                if r.contains(&k) {
                    v.clone()
                } else {
                    Vec::new()
                }
            })
            .collect()
    };

    // Each payload: kind, chunk, layer, and where its bytes count in the report.
    let mut payloads: Vec<(SectionKind, u32, u16, Vec<u8>)> = Vec::new();
    let mut sections = Vec::new();
    let static_part = if layered {
        StaticPart::StaticLayer {
            levels: level_range(0, false),
            first: true,
        }
    } else {
        StaticPart::Static
    };
    for (kind, part, enc) in [
        (
            SectionKind::Mlp,
            StaticPart::Mlp,
            Encodings::for_mode(parts.mlp),
        ),
        (
            SectionKind::Proposal,
            if layered {
                proposal_part(0)
            } else {
                StaticPart::Proposal
            },
            Encodings::for_mode(parts.proposal),
        ),
        (SectionKind::Static, static_part, static_enc),
    ] {
        let (raw, values) = write_static(&layout, params, part, enc);
        sections.push(SectionReport {
            name: kind.name().into(),
            stored_bytes: 0,
            raw_bytes: raw.len() as u64,
            values,
        });
        payloads.push((kind, 0, 0, raw));
    }
    let occupancy = match &opts.occupancy {
        Some(g) => {
            let raw = g.to_payload();
            OccupancyGrid::from_payload(&raw, MAX_OCCUPANCY_RESOLUTION, "occupancy option")
                .map_err(|e| EncodeError::InvalidOption(e.to_string()))?;
            (**g).clone()
        }
        None => occupancy_grid(model, &layout, params, opts),
    };
    let raw = occupancy.to_payload();
    sections.push(SectionReport {
        name: SectionKind::Occupancy.name().into(),
        stored_bytes: 0,
        raw_bytes: raw.len() as u64,
        values: 0,
    });
    payloads.push((SectionKind::Occupancy, 0, 0, raw));

    let region = dynamic_region(&layout.field.encoding, params, opts.dynamic_threshold);
    let mut chunks = Vec::new();
    let mut spans = Vec::new();
    let mut h4_values = 0;
    let mut h4_kept_union = 0;
    // The 4D rows of the shared section and of each chunk, per level, for the later layers.
    let mut dynamic_rows: Option<(RowsPerLevel, Vec<RowsPerLevel>)> = None;
    if let Some((g, _)) = &layout.field.encoding.h4 {
        h4_values = g.num_params as u64;
        if !region.boxes.is_empty() {
            spans = chunk_spans(model.num_frames, opts.chunk_frames);
            // How many chunks need each row (rows needed by two or more go to the shared
            // section) and which chunk reached it first (its owner when it is the only one).
            // Rows are counted chunk by chunk and not kept per chunk: with 10,000 frames the
            // per-chunk row lists took chunks x rows x 4 bytes (1.1 GB for the fast preset,
            // tens of GB for the paper's), see docs/stability.md.
            let mut users: Vec<Vec<u16>> = g.levels.iter().map(|l| vec![0; l.rows]).collect();
            let mut owner: Vec<Vec<u32>> = g.levels.iter().map(|l| vec![0; l.rows]).collect();
            let mut reached_per_chunk = Vec::with_capacity(spans.len());
            for (c, span) in spans.iter().enumerate() {
                let mut reached = 0u64;
                for (l, (u, o)) in users.iter_mut().zip(&mut owner).enumerate() {
                    let rows = reached_rows(g, l, &region, span.t_start, span.t_end);
                    reached += rows.len() as u64;
                    for row in rows {
                        let row = row as usize;
                        if u[row] == 0 {
                            o[row] = c as u32;
                        }
                        u[row] = u[row].saturating_add(1);
                    }
                }
                reached_per_chunk.push(reached);
            }
            // Each chunk's own rows (reached by it alone), sorted: at most one list entry per row.
            let mut own_rows: Vec<Vec<Vec<u32>>> =
                vec![vec![Vec::new(); g.levels.len()]; spans.len()];
            for (l, (u, o)) in users.iter().zip(&owner).enumerate() {
                for row in 0..u.len() {
                    if u[row] == 1 {
                        own_rows[o[row] as usize][l].push(row as u32);
                    }
                }
            }
            drop(owner);
            let shared: Vec<Vec<u32>> = users
                .iter()
                .map(|u| {
                    (0..u.len() as u32)
                        .filter(|&r| u[r as usize] >= 2)
                        .collect()
                })
                .collect();
            let shared_values: u64 =
                shared.iter().map(|r| r.len() as u64).sum::<u64>() * g.features as u64;
            let raw = write_chunk(
                &layout,
                params,
                SHARED_TAG,
                &rows_of_layer(&shared, 0),
                dyn_enc,
            );
            sections.push(SectionReport {
                name: SectionKind::Shared.name().into(),
                stored_bytes: 0,
                raw_bytes: raw.len() as u64,
                values: shared_values,
            });
            payloads.push((SectionKind::Shared, 0, 0, raw));
            for (c, (span, own)) in spans.iter().zip(&own_rows).enumerate() {
                let reached = reached_per_chunk[c];
                let kept: u64 = own.iter().map(|r| r.len() as u64).sum();
                let raw = write_chunk(&layout, params, c as u32, &rows_of_layer(own, 0), dyn_enc);
                chunks.push(ChunkReport {
                    span: span.clone(),
                    stored_bytes: 0,
                    raw_bytes: raw.len() as u64,
                    reached_values: reached * g.features as u64,
                    kept_values: kept * g.features as u64,
                });
                payloads.push((SectionKind::Dynamic, c as u32, 0, raw));
            }
            dynamic_rows = Some((shared, own_rows));
            h4_kept_union = users
                .iter()
                .map(|u| u.iter().filter(|&&n| n > 0).count() as u64)
                .sum::<u64>()
                * g.features as u64;
        }
    }

    // The later layers: each its proposal and static sections, then its shared section and
    // chunks.
    let static_report = sections
        .iter()
        .position(|s| s.name == SectionKind::Static.name())
        .unwrap_or(0);
    let proposal_report = sections
        .iter()
        .position(|s| s.name == SectionKind::Proposal.name())
        .unwrap_or(0);
    for l in 1..layer_levels.len() {
        let (raw, values) = write_static(
            &layout,
            params,
            proposal_part(l),
            Encodings::for_mode(parts.proposal),
        );
        sections[proposal_report].raw_bytes += raw.len() as u64;
        sections[proposal_report].values += values;
        payloads.push((SectionKind::Proposal, 0, l as u16, raw));
        let part = StaticPart::StaticLayer {
            levels: level_range(l, false),
            first: false,
        };
        let (raw, values) = write_static(&layout, params, part, static_enc);
        sections[static_report].raw_bytes += raw.len() as u64;
        sections[static_report].values += values;
        payloads.push((SectionKind::Static, 0, l as u16, raw));
        if let Some((shared, own_rows)) = &dynamic_rows {
            let raw = write_chunk(
                &layout,
                params,
                SHARED_TAG,
                &rows_of_layer(shared, l),
                dyn_enc,
            );
            if let Some(s) = sections.iter_mut().find(|s| s.name == "shared") {
                s.raw_bytes += raw.len() as u64;
            }
            payloads.push((SectionKind::Shared, 0, l as u16, raw));
            for (c, own) in own_rows.iter().enumerate() {
                let raw = write_chunk(&layout, params, c as u32, &rows_of_layer(own, l), dyn_enc);
                chunks[c].raw_bytes += raw.len() as u64;
                payloads.push((SectionKind::Dynamic, c as u32, l as u16, raw));
            }
        }
    }

    let metadata = Metadata {
        model: model.clone(),
        param_count: layout.params.total as u64,
        frame_rate: opts.frame_rate,
        time_range: [0.0, 1.0],
        cameras: cameras.to_vec(),
        quant: parts.finest(),
        section_quant: Some(parts),
        play_samples: opts.play_samples,
        dynamic_threshold: opts.dynamic_threshold,
        chunk_frames: opts.chunk_frames as u32,
        chunks: spans,
        layers: layered.then(|| layer_levels.clone()),
        encoder: format!("msth-codec {}", env!("CARGO_PKG_VERSION")),
    };
    let meta = serde_json::to_vec(&metadata)
        .map_err(|e| EncodeError::InvalidOption(format!("metadata does not serialise: {e}")))?;

    let compressed: Vec<Vec<u8>> = payloads
        .iter()
        .map(|(_, _, _, raw)| compress(raw, opts.zstd_level))
        .collect::<Result<_, _>>()?;
    let header_size = prefix_size(meta.len() as u64, payloads.len() as u64);
    let mut entries = Vec::with_capacity(payloads.len());
    let mut offset = header_size;
    for ((kind, chunk, layer, raw), stored) in payloads.iter().zip(&compressed) {
        offset = offset.div_ceil(ALIGN) * ALIGN;
        entries.push(SectionEntry {
            kind: *kind,
            chunk: *chunk,
            layer: *layer,
            offset,
            length: stored.len() as u64,
            raw_length: raw.len() as u64,
            crc32: crc32fast::hash(stored),
        });
        offset += stored.len() as u64;
    }
    let header_size_u32 = u32::try_from(header_size)
        .map_err(|_| EncodeError::InvalidOption("metadata too large".into()))?;
    let mut out = Vec::with_capacity(offset as usize);
    out.extend_from_slice(&[0u8; FIXED_HEADER]);
    out.extend_from_slice(&meta);
    out.resize(index_offset(meta.len() as u64) as usize, 0);
    for e in &entries {
        write_entry(&mut out, e);
    }
    let mut header = FixedHeader {
        version: if layered {
            LAYERED_VERSION
        } else {
            UNLAYERED_VERSION
        },
        flags: 0,
        header_size: header_size_u32,
        metadata_length: meta.len() as u32,
        section_count: entries.len() as u32,
        prefix_crc32: 0,
    };
    let bytes = header.to_bytes();
    let mut crc = crc32fast::Hasher::new();
    crc.update(&bytes[..28]);
    crc.update(&out[FIXED_HEADER..]);
    header.prefix_crc32 = crc.finalize();
    out[..FIXED_HEADER].copy_from_slice(&header.to_bytes());
    for (e, stored) in entries.iter().zip(&compressed) {
        out.resize(e.offset as usize, 0);
        out.extend_from_slice(stored);
    }

    let mut layers: Vec<LayerReport> = layer_levels
        .iter()
        .map(|&levels| LayerReport {
            levels,
            proposal_bytes: 0,
            static_bytes: 0,
            dynamic_bytes: 0,
            first_chunk_bytes: 0,
        })
        .collect();
    for e in &entries {
        let layer = &mut layers[e.layer as usize];
        match e.kind {
            SectionKind::Dynamic => {
                chunks[e.chunk as usize].stored_bytes += e.length;
                layer.dynamic_bytes += e.length;
                if e.chunk == 0 {
                    layer.first_chunk_bytes += e.length;
                }
            }
            kind => {
                if let Some(s) = sections.iter_mut().find(|s| s.name == kind.name()) {
                    s.stored_bytes += e.length;
                }
                match kind {
                    SectionKind::Proposal => layer.proposal_bytes += e.length,
                    SectionKind::Static => layer.static_bytes += e.length,
                    SectionKind::Shared => {
                        layer.dynamic_bytes += e.length;
                        layer.first_chunk_bytes += e.length;
                    }
                    _ => {}
                }
            }
        }
    }
    let report = EncodeReport {
        quant: parts.finest(),
        section_quant: parts,
        file_bytes: out.len() as u64,
        prefix_bytes: header_size,
        raw_param_bytes: 4 * layout.params.total as u64,
        sections,
        chunks,
        layers,
        h4_values,
        h4_kept_union,
        dynamic_voxels: region.voxels,
        occupied_cells: (occupancy.occupied_cells(), occupancy.cells()),
        num_frames: model.num_frames,
        encode_seconds: start.elapsed().as_secs_f64(),
    };
    Ok((out, report))
}
