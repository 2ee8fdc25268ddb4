//! `msth inspect FILE|URL [--json] [--validate]`: what `ffprobe` is to a video, for `.msth`
//! files. Prints the fixed header, the metadata in readable form, every section (kind, offset,
//! stored and raw size, ratio), the chunk spans and the cameras; with the sections at hand also
//! the share of the 4D table's rows stored and the share of dynamic voxels. It validates the file
//! against docs/format.md on the way (every rule a decoder enforces, through msth-codec, and the
//! rules on writers) and fails with the first violation.
//!
//! A local file is always read and validated whole. Over HTTP only the prefix (header, metadata,
//! index) is fetched, with Range requests through the player's source, unless `--validate` asks
//! for every section; the whole inspection then has a deadline (`--deadline`) and every request a
//! stall deadline (`--stall-timeout`), and nothing past the length the header declares is read.

use std::path::Path;

use anyhow::anyhow;
use clap::Args;
use msth_codec::dynamic_rows::dynamic_region;
use msth_codec::format::FixedHeader;
use msth_codec::{decode_all_with_limits, DecodedModel, FileIndex, Limits};
use msth_player::source::{self, ByteSource, HttpOptions};
use serde_json::{json, Value};

#[derive(Args)]
pub struct InspectArgs {
    /// A `.msth` file or an `http://` URL.
    pub source: String,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// Over HTTP, fetch and validate every section too (a local file is always validated whole).
    #[arg(long)]
    pub validate: bool,
    /// Over HTTP: seconds the whole inspection may take, every request and retry included.
    #[arg(long, default_value_t = 120.0, value_name = "SECS")]
    pub deadline: f64,
    /// Over HTTP: seconds a request may go without receiving anything before it is given up
    /// (and retried while the deadline leaves time).
    #[arg(long, default_value_t = 15.0, value_name = "SECS")]
    pub stall_timeout: f64,
}

/// Bytes fetched first over HTTP: the prefix of a typical file fits.
const PROBE_BYTES: u64 = 16 << 10;

/// What inspecting one file found.
struct Inspection {
    source: String,
    file_bytes: u64,
    index: FileIndex,
    /// The decoded model, when every section was read (local, or `--validate`).
    model: Option<DecodedModel>,
    /// Bytes read from the source (all requests).
    bytes_read: u64,
}

pub fn run(args: InspectArgs) -> anyhow::Result<()> {
    let start = std::time::Instant::now();
    let deadline = crate::play::seconds("--deadline", args.deadline)?;
    let opts = HttpOptions {
        probe_bytes: PROBE_BYTES,
        read_timeout: crate::play::seconds("--stall-timeout", args.stall_timeout)?,
        request_timeout: deadline,
        deadline: Some(start + deadline),
        ..HttpOptions::default()
    };
    let report = inspect(&args.source, args.validate, &opts)?;
    let text = if args.json {
        serde_json::to_string_pretty(&report.to_json())? + "\n"
    } else {
        report.to_text()
    };
    // A closed stdout (`msth inspect F | head`) is not an error of the file.
    let _ = std::io::Write::write_all(&mut std::io::stdout(), text.as_bytes());
    Ok(())
}

fn inspect(location: &str, validate: bool, opts: &HttpOptions) -> anyhow::Result<Inspection> {
    let http = location.starts_with("http://") || location.starts_with("https://");
    let src = source::open(location, opts)?;
    let limits = Limits::default();
    let len = src.len();
    let violation = |e: msth_codec::DecodeError| anyhow!("{location}: not a valid .msth file: {e}");
    let first = src.read_range(0..len.min(PROBE_BYTES))?;
    let header = FixedHeader::parse(&first, &limits).map_err(violation)?;
    let hs = header.header_size as u64;
    if len < hs {
        return Err(violation(msth_codec::DecodeError::Truncated {
            what: "header and index".into(),
            needed: hs,
            have: len,
        }));
    }
    let prefix = if (first.len() as u64) < hs {
        src.read_range(0..hs)?
    } else {
        first
    };
    let index = FileIndex::parse(&prefix, &limits).map_err(violation)?;
    index.check_writer_rules().map_err(violation)?;
    let file_bytes = index.file_len();
    // From here on nothing past the header's length is read; a server that declared another
    // length is refused, naming both.
    src.limit_to(file_bytes)?;
    let len = src.len();
    let model = if !http || validate {
        Some(
            read_whole(src.as_ref(), &index, &limits).map_err(|e| match e {
                Whole::Decode(e) => violation(e),
                Whole::Source(e) => anyhow!(e),
            })?,
        )
    } else {
        None
    };
    Ok(Inspection {
        source: location.to_string(),
        file_bytes: len.max(file_bytes),
        index,
        model,
        bytes_read: src
            .stats()
            .bytes
            .max(if http { 0 } else { len.min(file_bytes) }),
    })
}

enum Whole {
    Decode(msth_codec::DecodeError),
    Source(source::SourceError),
}

/// Reads and decodes the whole file: every rule of a whole-file decoder (trailing bytes,
/// padding, every section). A file longer than its index says is rejected without reading the
/// extra bytes.
fn read_whole(
    src: &dyn ByteSource,
    index: &FileIndex,
    limits: &Limits,
) -> Result<DecodedModel, Whole> {
    let end = index.file_len();
    let len = src.len();
    if len > end {
        return Err(Whole::Decode(msth_codec::DecodeError::Malformed {
            what: "file".into(),
            message: format!("{} trailing bytes after the last section", len - end),
        }));
    }
    let bytes = src.read_range(0..len).map_err(Whole::Source)?;
    decode_all_with_limits(&bytes, limits).map_err(Whole::Decode)
}

fn ratio(raw: u64, stored: u64) -> f64 {
    raw as f64 / stored.max(1) as f64
}

/// Rows of the field's 4D table: per level, and in total.
fn h4_rows(index: &FileIndex) -> u64 {
    index
        .layout
        .field
        .encoding
        .h4
        .as_ref()
        .map_or(0, |(g, _)| g.levels.iter().map(|l| l.rows as u64).sum())
}

/// Per progressive layer: its cumulative levels, its stored bytes, and the bytes a player
/// fetches before the first frame (time 0) holding layers up to it (prefix included).
fn layer_bytes(index: &FileIndex) -> Vec<(msth_codec::LayerLevels, u64, u64)> {
    let first = index.chunk_for_time(0.0);
    let levels = index.metadata.layer_levels();
    levels
        .iter()
        .enumerate()
        .map(|(l, &lv)| {
            let own: u64 = index
                .sections
                .iter()
                .filter(|s| {
                    s.layer as usize == l
                        && matches!(
                            s.kind,
                            msth_codec::SectionKind::Proposal
                                | msth_codec::SectionKind::Static
                                | msth_codec::SectionKind::Shared
                                | msth_codec::SectionKind::Dynamic
                        )
                })
                .map(|s| s.length)
                .sum();
            let first_frame: u64 = index.header.header_size as u64
                + index
                    .sections_for(first, l + 1)
                    .iter()
                    .map(|&i| index.sections[i].length)
                    .sum::<u64>();
            (lv, own, first_frame)
        })
        .collect()
}

/// Stored bytes of chunk `c`, all its layers.
fn chunk_bytes(index: &FileIndex, c: usize) -> u64 {
    index
        .sections
        .iter()
        .filter(|s| s.kind == msth_codec::SectionKind::Dynamic && s.chunk as usize == c)
        .map(|s| s.length)
        .sum()
}

/// Rows stored by a sparse section.
fn rows_of(c: &msth_codec::sections::SparseChunk) -> u64 {
    c.levels.iter().map(|(r, _)| r.len() as u64).sum()
}

impl Inspection {
    /// Rows in the shared section and per chunk (`None` without the sections).
    fn stored_rows(&self) -> Option<(u64, Vec<u64>)> {
        let m = self.model.as_ref()?;
        Some((
            m.shared().map_or(0, rows_of),
            m.chunks().iter().map(rows_of).collect(),
        ))
    }

    /// Dynamic and all mask voxels (`None`: no mask or no sections).
    fn dynamic_voxels(&self) -> Option<(u64, u64)> {
        let m = self.model.as_ref()?;
        dynamic_region(
            &m.layout.field.encoding,
            &m.params,
            m.metadata.dynamic_threshold,
        )
        .voxels
    }

    fn to_json(&self) -> Value {
        let ix = &self.index;
        let h = &ix.header;
        let meta = &ix.metadata;
        let total_rows = h4_rows(ix);
        let sections: Vec<Value> = ix
            .sections
            .iter()
            .enumerate()
            .map(|(i, s)| {
                json!({
                    "index": i, "kind": s.kind.name(), "label": s.label(), "chunk": s.chunk,
                    "layer": s.layer,
                    "offset": s.offset, "stored_bytes": s.length, "raw_bytes": s.raw_length,
                    "ratio": ratio(s.raw_length, s.length), "crc32": format!("{:08x}", s.crc32),
                })
            })
            .collect();
        let rows = self.stored_rows();
        let chunks: Vec<Value> = meta
            .chunks
            .iter()
            .enumerate()
            .map(|(c, span)| {
                let mut v = json!({
                    "chunk": c, "frame_start": span.frame_start, "frame_end": span.frame_end,
                    "t_start": span.t_start, "t_end": span.t_end,
                    "stored_bytes": chunk_bytes(ix, c),
                });
                if let Some((shared, per)) = &rows {
                    v["rows"] = json!(per[c]);
                    // What a player holds for this span: the shared rows and the chunk's own.
                    v["rows_share_held"] =
                        json!((shared + per[c]) as f64 / total_rows.max(1) as f64);
                }
                v
            })
            .collect();
        let cameras: Vec<Value> = meta
            .cameras
            .iter()
            .map(|c| {
                let p = c.world_from_camera.w_axis;
                json!({"width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx,
                       "cy": c.cy, "position": [p.x, p.y, p.z]})
            })
            .collect();
        let stored_share = rows.as_ref().map(|(shared, per)| {
            (shared + per.iter().sum::<u64>()) as f64 / total_rows.max(1) as f64
        });
        json!({
            "source": self.source,
            "file_bytes": self.file_bytes,
            "bytes_read": self.bytes_read,
            "validated": self.model.is_some(),
            "valid": true,
            "header": {
                "version": h.version, "flags": h.flags, "header_size": h.header_size,
                "metadata_length": h.metadata_length, "section_count": h.section_count,
                "prefix_crc32": format!("{:08x}", h.prefix_crc32),
            },
            "metadata": serde_json::to_value(meta).unwrap_or(Value::Null),
            "param_count": ix.layout.params.total,
            "sections": sections,
            "layers": layer_bytes(ix).iter().map(|(lv, own, first)| json!({
                "h3_levels": lv.h3, "h4_levels": lv.h4, "proposal_h3_levels": lv.p3,
                "proposal_h4_levels": lv.p4, "stored_bytes": own,
                "first_frame_bytes": first,
            })).collect::<Vec<_>>(),
            "chunks": chunks,
            "cameras": cameras,
            "h4_rows": total_rows,
            "h4_rows_shared": rows.as_ref().map(|r| r.0),
            "h4_rows_stored_share": stored_share,
            "dynamic_voxels": self.dynamic_voxels().map(|(d, n)| json!({
                "dynamic": d, "total": n, "share": d as f64 / n.max(1) as f64,
            })),
            "occupancy": self.model.as_ref().and_then(|m| m.occupancy.as_ref()).map(|g| json!({
                "resolution": g.resolution, "density_threshold": g.density_threshold,
                "frames": g.frames, "occupied_cells": g.occupied_cells(), "cells": g.cells(),
                "occupied_share": g.occupied_fraction(),
            })),
        })
    }

    fn to_text(&self) -> String {
        use std::fmt::Write;
        let ix = &self.index;
        let h = &ix.header;
        let meta = &ix.metadata;
        let m = &meta.model;
        let mut o = String::new();
        let name = Path::new(&self.source)
            .file_name()
            .map_or(self.source.clone(), |n| n.to_string_lossy().to_string());
        let _ = writeln!(
            o,
            "{name}: .msth version {}, {} bytes ({} read), {}",
            h.version,
            self.file_bytes,
            self.bytes_read,
            if self.model.is_some() {
                "valid (every section decoded and checked)"
            } else {
                "prefix valid (sections not fetched; --validate reads them)"
            }
        );
        let _ = writeln!(
            o,
            "header      {} bytes: {} B metadata, {} sections, prefix CRC-32 {:08x}",
            h.header_size, h.metadata_length, h.section_count, h.prefix_crc32
        );
        let grid = |g: &msth_core::grid::GridConfig| {
            format!(
                "{} levels x {} features, 2^{} rows, resolution {:?} .. {:?}",
                g.levels,
                g.features_per_level,
                g.log2_table_size,
                g.base_resolution,
                g.finest_resolution
            )
        };
        let enc = &m.field.encoding;
        let _ = writeln!(
            o,
            "model       {:?} blend, {} frames, {} parameters, encoder \"{}\"",
            enc.blend, m.num_frames, ix.layout.params.total, meta.encoder
        );
        let _ = writeln!(o, "  grid3     {}", grid(&enc.grid3));
        let _ = writeln!(o, "  grid4     {}", grid(&enc.grid4));
        let _ = writeln!(
            o,
            "  mask      {}^3 vertices; MLPs density {} -> {} -> {}, colour {} x {}, proposal {} levels, hidden {}",
            enc.mask_resolution,
            enc.grid3.levels * enc.grid3.features_per_level,
            m.field.density_hidden,
            1 + m.field.geo_features,
            m.field.color_hidden,
            m.field.color_layers,
            m.proposal.encoding.grid3.levels,
            m.proposal.hidden
        );
        let s = &m.sampler;
        let _ = writeln!(
            o,
            "  sampler   {} proposal + {} samples per ray, {:?} spacing, near {} far {}",
            s.num_proposal_samples, s.num_samples, s.spacing, s.near, s.far
        );
        let _ = writeln!(
            o,
            "  scene     {}; background {}",
            serde_json::to_string(&m.bounds).unwrap_or_default(),
            serde_json::to_string(&m.background).unwrap_or_default()
        );
        let _ = writeln!(
            o,
            "playback    frame rate {}, time {:?}, quantisation {}, dynamic threshold {}, {} frames per chunk",
            meta.frame_rate
                .map_or("unknown".to_string(), |r| format!("{r} fps")),
            meta.time_range,
            meta.quant,
            meta.dynamic_threshold,
            meta.chunk_frames
        );
        let parts = meta.parts_quant();
        let _ = writeln!(
            o,
            "quant       {}{}",
            msth_codec::QuantPart::ALL
                .into_iter()
                .map(|p| format!("{} {}", p.name(), parts.get(p)))
                .collect::<Vec<_>>()
                .join(", "),
            if meta.section_quant.is_none() {
                " (version 1 and 2 files: one mode throughout)"
            } else {
                ""
            }
        );
        let (p, m) = meta.default_samples();
        let _ = writeln!(
            o,
            "samples     players use {p} proposal + {m} main samples per ray by default ({})",
            if meta.play_samples.is_some() {
                "stored in the file; the model's own are its sampler's"
            } else {
                "the model's own: the file stores no play-time counts"
            }
        );
        if ix.layer_count() > 1 {
            let parts: Vec<String> = layer_bytes(ix)
                .iter()
                .enumerate()
                .map(|(l, (lv, own, first))| {
                    format!(
                        "{l}: levels to {}/{}/{}/{}, {own} bytes, first frame {first} bytes",
                        lv.h3, lv.h4, lv.p3, lv.p4
                    )
                })
                .collect();
            let _ = writeln!(
                o,
                "layers      {} progressive (levels of the field's 3D/4D and the proposal's 3D/4D tables held up to each; first frame: bytes before it holding layers 0..=l): {}",
                ix.layer_count(),
                parts.join("; ")
            );
        } else {
            let _ = writeln!(o, "layers      1 (no progressive layers)");
        }
        let _ = writeln!(
            o,
            "sections    #  kind       offset      stored        raw   ratio  crc32"
        );
        for (i, sec) in ix.sections.iter().enumerate() {
            let mut kind = match sec.kind {
                msth_codec::SectionKind::Dynamic => format!("chunk {}", sec.chunk),
                k => k.name().to_string(),
            };
            if sec.layer > 0 {
                kind = format!("{kind} L{}", sec.layer);
            }
            let _ = writeln!(
                o,
                "           {i:>2}  {kind:<9} {:>8} {:>10} {:>10} {:>6.2}  {:08x}",
                sec.offset,
                sec.length,
                sec.raw_length,
                ratio(sec.raw_length, sec.length),
                sec.crc32
            );
        }
        let rows = self.stored_rows();
        let total_rows = h4_rows(ix);
        if meta.chunks.is_empty() {
            let _ = writeln!(o, "chunks      none (no dynamic part stored)");
        }
        for (c, span) in meta.chunks.iter().enumerate() {
            let held = rows.as_ref().map_or(String::new(), |(shared, per)| {
                format!(
                    ", {} rows (+{} shared: {:.1}% of the 4D table held)",
                    per[c],
                    shared,
                    100.0 * (shared + per[c]) as f64 / total_rows.max(1) as f64
                )
            });
            let _ = writeln!(
                o,
                "chunk {c:<5} frames {}..{}, t {:.4}..{:.4}, {} bytes{held}",
                span.frame_start,
                span.frame_end,
                span.t_start,
                span.t_end,
                chunk_bytes(ix, c)
            );
        }
        let _ = writeln!(o, "cameras     {}", meta.cameras.len());
        for (i, c) in meta.cameras.iter().enumerate() {
            let p = c.world_from_camera.w_axis;
            let _ = writeln!(
                o,
                "  {i:>3}       {} x {}, f {:.1} {:.1}, centre {:.1} {:.1}, at ({:.3}, {:.3}, {:.3})",
                c.width, c.height, c.fx, c.fy, c.cx, c.cy, p.x, p.y, p.z
            );
        }
        match &rows {
            Some((shared, per)) => {
                let stored = shared + per.iter().sum::<u64>();
                let _ = writeln!(
                    o,
                    "4D rows     {stored} of {total_rows} stored ({:.1}%; {shared} shared)",
                    100.0 * stored as f64 / total_rows.max(1) as f64
                );
            }
            None => {
                let _ = writeln!(
                    o,
                    "4D rows     {total_rows} in the table (stored share: needs the sections, --validate)"
                );
            }
        }
        match (self.model.is_some(), self.dynamic_voxels()) {
            (_, Some((d, n))) => {
                let _ = writeln!(
                    o,
                    "dynamic     {d} of {n} voxels ({:.1}%) at threshold {}",
                    100.0 * d as f64 / n.max(1) as f64,
                    meta.dynamic_threshold
                );
            }
            (true, None) if ix.layout.field.encoding.h4.is_none() => {
                let _ = writeln!(o, "dynamic     none: no 4D table (a static model)");
            }
            (true, None) => {
                let _ = writeln!(o, "dynamic     no mask: the whole scene counts as dynamic");
            }
            (false, None) => {
                let _ = writeln!(o, "dynamic     needs the sections (--validate)");
            }
        }
        match (
            self.model.as_ref().map(|m| m.occupancy.as_ref()),
            ix.section(msth_codec::SectionKind::Occupancy),
        ) {
            (Some(Some(g)), _) => {
                let _ = writeln!(
                    o,
                    "occupancy   {r}^3 cells, {} occupied ({:.1}%), density >= {:.4} at any of {} frames, dilated by one cell",
                    g.occupied_cells(),
                    100.0 * g.occupied_fraction(),
                    g.density_threshold,
                    g.frames,
                    r = g.resolution
                );
            }
            (_, None) => {
                let _ = writeln!(
                    o,
                    "occupancy   none (a version-1 file: renderers skip no empty space)"
                );
            }
            (_, Some(_)) => {
                let _ = writeln!(o, "occupancy   needs the sections (--validate)");
            }
        }
        o
    }
}
