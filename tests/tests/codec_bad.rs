//! Hostile and broken `.msth` files fail with an error, never a panic, hang or huge allocation:
//! every file in `tests/bad/` is rejected by the whole-file and the streaming decoder.
//!
//! The corpus is written by the ignored generator below, from a tiny valid file, with checksums
//! recomputed wherever a deeper check is the target. Regenerate with
//! `cargo test --release -p msth-tests --test codec_bad -- --ignored regenerate_bad_corpus`.

use msth_testkit::Tests;
use std::path::{Path, PathBuf};

use msth_codec::format::{index_offset, FIXED_HEADER, INDEX_ENTRY};
use msth_codec::occupancy::OCCUPANCY_HEADER;
use msth_codec::quant::{BlockEncoding, Writer};
use msth_codec::{decode_all, encode, Decoder, EncodeOptions, QuantMode};
use msth_core::config::{BlendMode, ModelConfig};
use msth_core::field::ModelLayout;

fn bad_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("bad")
}

/// A tiny model with a dynamic region, so that the file has chunks.
fn tiny_model() -> (ModelConfig, Vec<f32>) {
    let mut c = ModelConfig::fast_on_white(4);
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        enc.blend = BlendMode::Mt;
        enc.resize(2, 8, 16.0, 4);
    }
    c.resize_mlps(4, 4);
    c.field.color_layers = 1;
    let layout = ModelLayout::new(&c);
    let mut p = layout.init_params(1);
    if let Some((_, r)) = &layout.field.encoding.mask {
        for (i, v) in p[r.clone()].iter_mut().enumerate() {
            *v = if i == 21 { -4.0 } else { 4.0 };
        }
    }
    (c, p)
}

/// A valid file: q8 (affine blocks), two chunks.
fn valid_file() -> Vec<u8> {
    let (c, p) = tiny_model();
    let opts = EncodeOptions {
        quant: QuantMode::Q8,
        chunk_frames: 2,
        // The writer's default when the corpus was made (128 since 2026-11-30): the committed
        // files stay what the generator writes.
        occupancy_resolution: 64,
        ..Default::default()
    };
    encode(&c, &p, &[], &opts).unwrap().0
}

/// The valid file in two progressive layers (version 4): one hash level per layer.
fn layered_file() -> Vec<u8> {
    let (c, p) = tiny_model();
    let opts = EncodeOptions {
        quant: QuantMode::Q8,
        chunk_frames: 2,
        occupancy_resolution: 64,
        layers: 2,
        ..Default::default()
    };
    encode(&c, &p, &[], &opts).unwrap().0
}

struct File {
    bytes: Vec<u8>,
}

impl File {
    fn u32_at(&self, o: usize) -> u32 {
        u32::from_le_bytes(self.bytes[o..o + 4].try_into().unwrap())
    }
    fn meta_len(&self) -> usize {
        self.u32_at(12) as usize
    }
    fn header_size(&self) -> usize {
        self.u32_at(8) as usize
    }
    fn entry(&self, i: usize) -> usize {
        index_offset(self.meta_len() as u64) as usize + i * INDEX_ENTRY
    }
    fn u64_at(&self, o: usize) -> u64 {
        u64::from_le_bytes(self.bytes[o..o + 8].try_into().unwrap())
    }
    fn set_u64(&mut self, o: usize, v: u64) {
        self.bytes[o..o + 8].copy_from_slice(&v.to_le_bytes());
    }
    fn set_u32(&mut self, o: usize, v: u32) {
        self.bytes[o..o + 4].copy_from_slice(&v.to_le_bytes());
    }
    /// Recomputes the prefix CRC.
    fn fix_prefix(&mut self) {
        let hs = self.header_size();
        let mut h = crc32fast::Hasher::new();
        h.update(&self.bytes[..28]);
        h.update(&self.bytes[FIXED_HEADER..hs]);
        let crc = h.finalize();
        self.set_u32(28, crc);
    }
    /// Replaces the metadata JSON, moving everything after it and fixing every offset.
    fn set_metadata(&mut self, meta: &[u8]) {
        let old_ml = self.meta_len();
        let n = self.u32_at(16) as usize;
        let old_io = index_offset(old_ml as u64) as usize;
        let index = self.bytes[old_io..old_io + n * INDEX_ENTRY].to_vec();
        let body = self.bytes[self.header_size()..].to_vec();
        let new_io = index_offset(meta.len() as u64) as usize;
        let new_hs = new_io + n * INDEX_ENTRY;
        // Keep sections 8-aligned: shift by a multiple of 8.
        let old_hs = self.header_size();
        let shift = (new_hs as i64 - old_hs as i64).div_euclid(8) * 8 + 8;
        let mut b = self.bytes[..FIXED_HEADER].to_vec();
        b.extend_from_slice(meta);
        b.resize(new_io, 0);
        b.extend_from_slice(&index);
        b.resize((old_hs as i64 + shift) as usize, 0);
        b.extend_from_slice(&body);
        self.bytes = b;
        self.set_u32(8, new_hs as u32);
        self.set_u32(12, meta.len() as u32);
        for i in 0..n {
            let o = self.entry(i) + 8;
            let v = self.u64_at(o);
            self.set_u64(o, (v as i64 + shift) as u64);
        }
        self.fix_prefix();
    }
    fn metadata(&self) -> serde_json::Value {
        serde_json::from_slice(&self.bytes[FIXED_HEADER..FIXED_HEADER + self.meta_len()]).unwrap()
    }
    fn edit_metadata(&mut self, f: impl FnOnce(&mut serde_json::Value)) {
        let mut m = self.metadata();
        f(&mut m);
        self.set_metadata(&serde_json::to_vec(&m).unwrap());
    }
    fn section(&self, i: usize) -> (usize, usize) {
        let e = self.entry(i);
        (self.u64_at(e + 8) as usize, self.u64_at(e + 16) as usize)
    }
    fn payload(&self, i: usize) -> Vec<u8> {
        let (o, l) = self.section(i);
        zstd::bulk::decompress(&self.bytes[o..o + l], 1 << 24).unwrap()
    }
    /// Replaces section `i`'s stored bytes (the last section only, so offsets stay valid), with
    /// `raw_length` and CRC updated.
    fn set_stored(&mut self, i: usize, stored: &[u8], raw_len: u64) {
        let (o, l) = self.section(i);
        assert_eq!(
            o + l,
            self.bytes.len(),
            "only the last section can change size"
        );
        self.bytes.truncate(o);
        self.bytes.extend_from_slice(stored);
        let e = self.entry(i);
        self.set_u64(e + 16, stored.len() as u64);
        self.set_u64(e + 24, raw_len);
        self.set_u32(e + 32, crc32fast::hash(stored));
        self.fix_prefix();
    }
    /// Replaces the stored bytes of any section `i`, moving the sections after it (each on the
    /// next multiple of 8, as the writer places them) and fixing the index and the prefix CRC.
    fn replace_section(&mut self, i: usize, stored: &[u8], raw_len: u64) {
        let n = self.u32_at(16) as usize;
        let old: Vec<Vec<u8>> = (0..n)
            .map(|j| {
                let (o, l) = self.section(j);
                self.bytes[o..o + l].to_vec()
            })
            .collect();
        self.bytes.truncate(self.header_size());
        for (j, data) in old.iter().enumerate() {
            let at = self.bytes.len().div_ceil(8) * 8;
            self.bytes.resize(at, 0);
            let data: &[u8] = if j == i { stored } else { data };
            self.bytes.extend_from_slice(data);
            let e = self.entry(j);
            self.set_u64(e + 8, at as u64);
            if j == i {
                self.set_u64(e + 16, stored.len() as u64);
                self.set_u64(e + 24, raw_len);
                self.set_u32(e + 32, crc32fast::hash(stored));
            }
        }
        self.fix_prefix();
    }
    fn set_payload(&mut self, i: usize, raw: &[u8]) {
        let stored = zstd::bulk::compress(raw, 3).unwrap();
        self.set_stored(i, &stored, raw.len() as u64);
    }
}

/// Index positions, in a version-2 or version-3 file, of the occupancy and the shared section.
const OCCUPANCY: usize = 3;
const SHARED: usize = 4;

/// Index position of the last section (a dynamic chunk).
fn b_last(v: &[u8]) -> usize {
    u32::from_le_bytes(v[16..20].try_into().unwrap()) as usize - 1
}

fn corpus() -> Vec<(&'static str, Vec<u8>)> {
    let v = valid_file();
    let f = || File { bytes: v.clone() };
    let mut out: Vec<(&'static str, Vec<u8>)> = Vec::new();
    let mut add = |name: &'static str, b: Vec<u8>| out.push((name, b));

    add("empty", vec![]);
    add("short_magic", b"MS".to_vec());
    let mut b = f();
    b.bytes[0] = b'X';
    add("bad_magic", b.bytes);
    let mut b = f();
    b.bytes[4] = (msth_codec::format::VERSION + 1) as u8;
    b.fix_prefix();
    add("bad_version", b.bytes);
    let mut b = f();
    b.bytes[6] = 1;
    b.fix_prefix();
    add("nonzero_flags", b.bytes);
    let mut b = f();
    b.bytes[22] = 1;
    b.fix_prefix();
    add("nonzero_reserved_header", b.bytes);
    let mut b = f();
    let hs = b.header_size() as u32;
    b.set_u32(8, hs + 8);
    b.fix_prefix();
    add("header_size_mismatch", b.bytes);
    let mut b = f();
    b.bytes[29] ^= 0xff;
    add("bad_prefix_checksum", b.bytes);
    let b = f();
    add(
        "truncated_in_index",
        b.bytes[..b.header_size() - 3].to_vec(),
    );
    let mut b = f();
    b.set_metadata(b"{\"model\": [1, 2,");
    add("invalid_json", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["surprise"] = serde_json::json!(1));
    add("unknown_metadata_key", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["model"]["field"]["encoding"]["grid3"]["levels"] = 0.into());
    add("invalid_model_config", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        let n = m["param_count"].as_u64().unwrap();
        m["param_count"] = (n + 1).into();
    });
    add("wrong_param_count", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        for g in ["grid3", "grid4"] {
            let grid = &mut m["model"]["field"]["encoding"][g];
            grid["levels"] = 32.into();
            grid["log2_table_size"] = 24.into();
            grid["features_per_level"] = 8.into();
        }
    });
    add("huge_param_count", b.bytes);
    let mut b = f();
    b.set_u32(16, u32::MAX);
    b.fix_prefix();
    add("huge_section_count", b.bytes);
    let mut b = f();
    let e = b.entry(3);
    b.set_u64(e + 8, 1 << 40);
    b.fix_prefix();
    add("section_past_end", b.bytes);
    let mut b = f();
    let (o1, _) = b.section(1);
    let e = b.entry(2);
    b.set_u64(e + 8, o1 as u64);
    b.fix_prefix();
    add("overlapping_sections", b.bytes);
    let mut b = f();
    let e = b.entry(1);
    let o = b.u64_at(e + 8);
    b.set_u64(e + 8, o + 1);
    b.fix_prefix();
    add("unaligned_section", b.bytes);
    let mut b = f();
    let e = b.entry(0);
    b.set_u64(e + 24, 1 << 40);
    b.fix_prefix();
    add("huge_raw_length", b.bytes);
    let mut b = f();
    let e = b.entry(0);
    b.set_u64(e + 24, 1 << 20);
    b.fix_prefix();
    add("raw_length_beyond_model", b.bytes);
    let mut b = f();
    let e = b.entry(4);
    b.set_u64(e + 16, 1 << 40);
    b.fix_prefix();
    add("huge_section_length", b.bytes);
    let mut b = f();
    let (o, _) = b.section(2);
    b.bytes[o + 3] ^= 0x10;
    add("bad_section_checksum", b.bytes);
    let last = b_last(&v);
    let mut b = f();
    let (o, l) = b.section(last);
    let cut = b.bytes[o..o + l / 2].to_vec();
    let raw_len = b.u64_at(b.entry(last) + 24);
    b.set_stored(last, &cut, raw_len);
    add("truncated_zstd", b.bytes);
    let mut b = f();
    let raw = b.payload(last);
    let stored = zstd::bulk::compress(&raw[..raw.len() - 4], 3).unwrap();
    b.set_stored(last, &stored, raw.len() as u64);
    add("zstd_shorter_than_claimed", b.bytes);
    let mut b = f();
    let stored = zstd::bulk::compress(&[7u8; 4096], 3).unwrap();
    b.set_stored(last, &stored, 16);
    add("zstd_longer_than_claimed", b.bytes);
    let mut b = f();
    let (_, l) = b.section(last);
    let garbage: Vec<u8> = (0..l).map(|i| (i * 37 + 11) as u8).collect();
    b.set_stored(last, &garbage, 64);
    add("not_zstd", b.bytes);
    let mut b = f();
    b.bytes.extend_from_slice(&[0; 8]);
    add("trailing_bytes", b.bytes);
    let mut b = f();
    let e = b.entry(0);
    b.bytes[e] = 9;
    b.fix_prefix();
    add("unknown_section_kind", b.bytes);
    let mut b = f();
    let e = b.entry(0);
    b.bytes[e + 1] = 2;
    b.fix_prefix();
    add("unknown_compression", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        m["chunks"][1]["t_start"] = serde_json::json!(-1.0);
    });
    add("decreasing_chunk_times", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        m["chunks"].as_array_mut().unwrap().pop();
    });
    add("chunk_count_mismatch", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["frame_rate"] = serde_json::json!(-30.0));
    add("negative_frame_rate", b.bytes);
    let mut b = f();
    let (o1, l1) = b.section(1);
    let (o2, _) = b.section(2);
    if o1 + l1 < o2 {
        b.bytes[o1 + l1] = 1;
        add("nonzero_padding", b.bytes);
    } else {
        // No padding after section 1 in this file: pad the prefix instead.
        let hs = b.header_size();
        b.bytes[hs] = 1;
        add("nonzero_padding", b.bytes);
    }

    // Payload-level corruption with valid checksums: edit the last section (chunk 1).
    let (c, _) = tiny_model();
    let layout = ModelLayout::new(&c);
    let (g4, _) = layout.field.encoding.h4.clone().unwrap();
    let feats = g4.features;
    let chunk_payload = |level0_rows: &[u32], chunk: u32, block: &dyn Fn(&mut Writer, usize)| {
        let mut w = Writer::default();
        w.u32(chunk);
        w.u32(g4.levels.len() as u32);
        for l in 0..g4.levels.len() {
            let rows: &[u32] = if l == 0 { level0_rows } else { &[] };
            w.u32(rows.len() as u32);
            for &r in rows {
                w.varint(r);
            }
            block(&mut w, rows.len() * feats);
        }
        w.bytes
    };
    let ok_block = |w: &mut Writer, n: usize| w.block(&vec![0.5; n], BlockEncoding::F32);
    let mut b = f();
    b.set_payload(
        last,
        &chunk_payload(&[g4.levels[0].rows as u32 + 3], 1, &ok_block),
    );
    add("chunk_row_outside_table", b.bytes);
    let mut b = f();
    b.set_payload(last, &chunk_payload(&[0], 0, &ok_block));
    add("chunk_number_mismatch", b.bytes);
    let mut b = f();
    let mut raw = chunk_payload(&[], 1, &ok_block);
    raw[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    b.set_payload(last, &raw);
    add("chunk_huge_row_count", b.bytes);
    let mut b = f();
    let mut raw = chunk_payload(&[1], 1, &ok_block);
    // Replace the one-byte varint by an overlong one.
    raw.splice(12..13, [0x81, 0x80, 0x80, 0x80, 0x80, 0x00]);
    b.set_payload(last, &raw);
    add("chunk_overlong_varint", b.bytes);
    let mut b = f();
    b.set_payload(
        last,
        &chunk_payload(&[2], 1, &|w: &mut Writer, n: usize| {
            w.block(&vec![0.5; n + 1], BlockEncoding::F32)
        }),
    );
    add("block_wrong_count", b.bytes);
    let mut b = f();
    b.set_payload(
        last,
        &chunk_payload(&[2], 1, &|w: &mut Writer, n: usize| {
            w.block(&vec![f32::NAN; n], BlockEncoding::F32)
        }),
    );
    add("nan_value", b.bytes);
    let mut b = f();
    b.set_payload(
        last,
        &chunk_payload(&[2], 1, &|w: &mut Writer, n: usize| {
            let at = w.bytes.len();
            w.block(&vec![0.5; n], BlockEncoding::Affine { bits: 8 });
            if n > 0 {
                w.bytes[at + 12..at + 16].copy_from_slice(&f32::NAN.to_le_bytes());
            }
        }),
    );
    add("nan_scale", b.bytes);
    let mut b = f();
    b.set_payload(
        last,
        &chunk_payload(&[2], 1, &|w: &mut Writer, n: usize| {
            let at = w.bytes.len();
            w.block(
                &(0..n).map(|i| i as f32).collect::<Vec<_>>(),
                BlockEncoding::Affine { bits: 8 },
            );
            if n > 0 {
                w.bytes[at + 1] = 1; // claims 1 bit; codes up to 255 follow
            }
        }),
    );
    add("code_exceeds_bits", b.bytes);
    let mut b = f();
    b.set_payload(
        last,
        &chunk_payload(&[2], 1, &|w: &mut Writer, n: usize| {
            let at = w.bytes.len();
            w.block(&vec![0.5; n], BlockEncoding::F32);
            w.bytes[at] = 7;
        }),
    );
    add("unknown_block_encoding", b.bytes);
    let mut b = f();
    let mut raw = b.payload(last);
    raw.extend_from_slice(&[0, 0, 0]);
    b.set_payload(last, &raw);
    add("payload_trailing_bytes", b.bytes);

    // Issue #22: one zstd frame per section (format.md §1.1). Two frames that together
    // decompress to exactly the right payload: a decoder that reads concatenated frames would
    // accept this file.
    let mut b = f();
    let raw = b.payload(last);
    let mut two = zstd::bulk::compress(&raw[..raw.len() / 2], 3).unwrap();
    two.extend(zstd::bulk::compress(&raw[raw.len() / 2..], 3).unwrap());
    b.set_stored(last, &two, raw.len() as u64);
    add("zstd_two_frames", b.bytes);
    // A skippable frame (RFC 8878 §3.1.2) after the section's frame: zstd skips it silently.
    let mut b = f();
    let raw = b.payload(last);
    let mut stored = zstd::bulk::compress(&raw, 3).unwrap();
    stored.extend_from_slice(&[0x50, 0x2a, 0x4d, 0x18, 4, 0, 0, 0, 1, 2, 3, 4]);
    b.set_stored(last, &stored, raw.len() as u64);
    add("zstd_trailing_skippable_frame", b.bytes);
    let mut b = f();
    let raw = b.payload(last);
    let mut stored = zstd::bulk::compress(&raw, 3).unwrap();
    stored.extend_from_slice(&[0, 0, 0]);
    b.set_stored(last, &stored, raw.len() as u64);
    add("zstd_trailing_bytes", b.bytes);
    // Version 1 allows only time_range [0, 1] (format.md §3).
    let mut b = f();
    b.edit_metadata(|m| m["time_range"] = serde_json::json!([0.0, 2.0]));
    add("time_range_not_unit", b.bytes);
    // Sizes that drive the player's allocations (format.md §8, issue #22).
    let camera = |w: u32, h: u32| {
        serde_json::to_value(msth_core::Camera::look_at(
            w,
            h,
            0.8,
            glam::Vec3::new(0.0, -4.0, 1.0),
            glam::Vec3::ZERO,
            glam::Vec3::Z,
        ))
        .unwrap()
    };
    let mut b = f();
    b.edit_metadata(|m| m["cameras"] = serde_json::json!([camera(100_000, 100_000)]));
    add("huge_camera", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        m["model"]["sampler"]["num_proposal_samples"] = 4096.into();
        m["model"]["sampler"]["num_samples"] = 4096.into();
    });
    add("huge_sampler", b.bytes);
    // Both sides within the limit, the pixel count not (8K: 33.5 million pixels).
    let mut b = f();
    b.edit_metadata(|m| m["cameras"] = serde_json::json!([camera(8192, 4096)]));
    add("camera_too_many_pixels", b.bytes);
    // Cameras (format.md §3.2).
    let mut b = f();
    b.edit_metadata(|m| {
        let mut c = camera(16, 12);
        c["width"] = 0.into();
        m["cameras"] = serde_json::json!([c]);
    });
    add("camera_zero_width", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        let mut c = camera(16, 12);
        c["fx"] = serde_json::json!(-10.0);
        m["cameras"] = serde_json::json!([c]);
    });
    add("camera_negative_focal", b.bytes);
    // Chunk spans (format.md §3.3).
    let mut b = f();
    b.edit_metadata(|m| m["chunks"][0]["t_end"] = serde_json::json!(-0.5));
    add("chunk_span_reversed", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        let end = m["chunks"][0]["frame_end"].as_u64().unwrap();
        m["chunks"][0]["frame_start"] = (end + 1).into();
    });
    add("chunk_frames_reversed", b.bytes);
    let mut b = f();
    // JSON has no infinity: 1e39 overflows f32.
    b.edit_metadata(|m| m["chunks"][1]["t_end"] = serde_json::json!(1e39));
    add("chunk_span_infinite", b.bytes);
    // Header and index (format.md §2, §4).
    let mut b = f();
    b.set_u32(12, 0xffff_fff0);
    b.fix_prefix();
    add("huge_metadata_length", b.bytes);
    let mut b = f();
    let e = b.entry(0);
    b.bytes[e + 36] = 1;
    b.fix_prefix();
    add("index_reserved_nonzero", b.bytes);
    let mut b = f();
    let (e0, e1) = (b.entry(0), b.entry(1));
    b.bytes.swap(e0, e1);
    b.fix_prefix();
    add("index_wrong_order", b.bytes);
    let mut b = f();
    let e = b.entry(0);
    let inside = (b.header_size() as u64 / 8) * 8 - 8;
    b.set_u64(e + 8, inside);
    b.fix_prefix();
    add("section_inside_prefix", b.bytes);
    let mut b = f();
    let e = b.entry(last);
    b.set_u64(e + 8, u64::MAX - 7);
    b.fix_prefix();
    add("section_range_overflow", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        let mut enc = m["encoder"].as_str().unwrap().to_string();
        // Grow the metadata until padding follows it (the writer's metadata may end aligned).
        loop {
            let mut t = m.clone();
            t["encoder"] = enc.clone().into();
            if !(FIXED_HEADER + serde_json::to_vec(&t).unwrap().len()).is_multiple_of(8) {
                break;
            }
            enc.push('+');
        }
        m["encoder"] = enc.into();
    });
    let at = FIXED_HEADER + b.meta_len();
    b.bytes[at] = 1;
    b.fix_prefix();
    add("nonzero_metadata_padding", b.bytes);
    // Sparse 4D payloads (format.md §6.4).
    let mut b = f();
    let mut raw = chunk_payload(&[2], 1, &ok_block);
    let levels = u32::from_le_bytes(raw[4..8].try_into().unwrap());
    raw[4..8].copy_from_slice(&(levels + 1).to_le_bytes());
    b.set_payload(last, &raw);
    add("chunk_wrong_levels", b.bytes);
    let mut b = f();
    let mut raw = chunk_payload(&[1], 1, &ok_block);
    // A 5-byte varint of 2^35 - 1.
    raw.splice(12..13, [0xff, 0xff, 0xff, 0xff, 0x7f]);
    b.set_payload(last, &raw);
    add("varint_above_u32", b.bytes);
    let mut b = f();
    let shared = chunk_payload(&[2], 0, &ok_block);
    let stored = zstd::bulk::compress(&shared, 3).unwrap();
    b.replace_section(SHARED, &stored, shared.len() as u64);
    add("shared_wrong_tag", b.bytes);
    // Blocks (format.md §5.2), each in the last chunk's one stored row.
    let edited_block = |edit: &dyn Fn(&mut Vec<u8>, usize), enc: BlockEncoding| {
        let mut b = f();
        b.set_payload(
            last,
            &chunk_payload(&[2], 1, &|w: &mut Writer, n: usize| {
                let at = w.bytes.len();
                w.block(&(0..n).map(|i| i as f32 * 0.25).collect::<Vec<_>>(), enc);
                edit(&mut w.bytes, at);
            }),
        );
        b.bytes
    };
    add(
        "float_block_with_predictor",
        edited_block(&|b, at| b[at + 2] = 1, BlockEncoding::F32),
    );
    add(
        "block_reserved_nonzero",
        edited_block(&|b, at| b[at + 3] = 1, BlockEncoding::F16),
    );
    add(
        "unknown_predictor",
        edited_block(&|b, at| b[at + 2] = 2, BlockEncoding::Affine { bits: 8 }),
    );
    add(
        "affine_bits_out_of_range",
        edited_block(&|b, at| b[at + 1] = 9, BlockEncoding::Affine { bits: 8 }),
    );
    add(
        "negative_scale",
        edited_block(
            &|b, at| b[at + 12..at + 16].copy_from_slice(&(-1f32).to_le_bytes()),
            BlockEncoding::Affine { bits: 8 },
        ),
    );
    add(
        "affine_overflow",
        edited_block(
            &|b, at| {
                b[at + 8..at + 12].copy_from_slice(&3e38f32.to_le_bytes());
                b[at + 12..at + 16].copy_from_slice(&3e38f32.to_le_bytes());
            },
            BlockEncoding::Affine { bits: 8 },
        ),
    );
    add(
        "codebook_nan_entry",
        edited_block(
            &|b, at| b[at + 8..at + 12].copy_from_slice(&f32::NAN.to_le_bytes()),
            BlockEncoding::Codebook { bits: 4 },
        ),
    );

    // The occupancy section (format.md §6.5, version 2), index entry 3, with valid checksums.
    let occupancy = |edit: &dyn Fn(&mut Vec<u8>)| {
        let mut b = f();
        let mut raw = b.payload(OCCUPANCY);
        edit(&mut raw);
        let stored = zstd::bulk::compress(&raw, 3).unwrap();
        b.replace_section(OCCUPANCY, &stored, raw.len() as u64);
        b.bytes
    };
    add(
        "occupancy_resolution_zero",
        occupancy(&|r| r[0..4].copy_from_slice(&0u32.to_le_bytes())),
    );
    add(
        "occupancy_resolution_over_limit",
        occupancy(&|r| r[0..4].copy_from_slice(&600u32.to_le_bytes())),
    );
    add(
        "occupancy_wrong_length",
        occupancy(&|r| r.truncate(r.len() - 4)),
    );
    add(
        "occupancy_nan_threshold",
        occupancy(&|r| r[4..8].copy_from_slice(&f32::NAN.to_le_bytes())),
    );
    add("occupancy_reserved_nonzero", occupancy(&|r| r[12] = 1));
    // Resolution 3: 27 cells in one word, bit 27 is padding.
    add(
        "occupancy_padding_bit",
        occupancy(&|r| {
            r.truncate(OCCUPANCY_HEADER);
            r[0..4].copy_from_slice(&3u32.to_le_bytes());
            r.extend_from_slice(&(1u32 << 27 | 1).to_le_bytes());
        }),
    );
    let mut b = f();
    let e = b.entry(OCCUPANCY);
    b.set_u64(e + 24, 1 << 30);
    b.fix_prefix();
    add("occupancy_raw_length_beyond_limit", b.bytes);
    // A version-2 file is read with version 1's section order and the other way round. (The
    // base file is version 3: without its `section_quant` it is a version-2 file.)
    let mut b = f();
    b.edit_metadata(|m| {
        m.as_object_mut().unwrap().remove("section_quant");
    });
    b.bytes[4] = 1;
    b.fix_prefix();
    add("v2_file_marked_v1", b.bytes);
    let mut b = File {
        bytes: std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/v1.msth"))
            .unwrap(),
    };
    b.bytes[4] = 2;
    b.fix_prefix();
    add("v1_file_marked_v2", b.bytes);
    // Version 3's metadata keys (format.md §3.4, §5.4).
    let mut b = f();
    b.bytes[4] = 2;
    b.fix_prefix();
    add("v3_key_in_v2_file", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["play_samples"] = serde_json::json!({"proposal": 0, "main": 4}));
    add("play_samples_zero", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["play_samples"] = serde_json::json!({"proposal": 4, "main": 513}));
    add("play_samples_over_limit", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| {
        m["play_samples"] = serde_json::json!({"proposal": 4, "main": 4, "extra": 1})
    });
    add("play_samples_unknown_key", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["quant"] = serde_json::json!("q5"));
    add("quant_disagrees_with_section_quant", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["section_quant"]["mask"] = serde_json::json!("q7"));
    add("section_quant_unknown_mode", b.bytes);
    // Version 4's progressive layers (format.md §6.6): the layered file is MLP, proposal,
    // static, occupancy, shared, chunks 0 and 1 of layer 0, then static, shared, chunks 0 and
    // 1 of layer 1.
    let layered = || File {
        bytes: layered_file(),
    };
    let mut b = f();
    let e = b.entry(2);
    b.bytes[e + 2] = 1;
    b.fix_prefix();
    add("layer_in_v3_entry", b.bytes);
    let mut b = f();
    b.edit_metadata(|m| m["layers"] = serde_json::json!([{"h3": 1, "h4": 1, "p3": 1, "p4": 1}, {"h3": 2, "h4": 2, "p3": 2, "p4": 2}]));
    add("layers_key_in_v3_file", b.bytes);
    let mut b = layered();
    b.edit_metadata(|m| m["layers"] = serde_json::json!([{"h3": 1, "h4": 1, "p3": 1, "p4": 1}, {"h3": 1, "h4": 2, "p3": 2, "p4": 2}]));
    add("layers_last_short_of_the_levels", b.bytes);
    let mut b = layered();
    b.edit_metadata(|m| m["layers"] = serde_json::json!([{"h3": 2, "h4": 2, "p3": 2, "p4": 2}, {"h3": 2, "h4": 2, "p3": 2, "p4": 2}]));
    add("layers_add_no_level", b.bytes);
    let mut b = layered();
    b.edit_metadata(|m| {
        m["layers"] = serde_json::json!([{"h3": 1, "h4": 1, "p3": 1, "p4": 1, "h5": 0}, {"h3": 2, "h4": 2, "p3": 2, "p4": 2}])
    });
    add("layers_unknown_key", b.bytes);
    let mut b = layered();
    let n = b.u32_at(16) as usize;
    let e = b.entry(n - 1);
    b.bytes[e + 2] = 2;
    b.fix_prefix();
    add("layer_number_out_of_order", b.bytes);
    // A row of level 0 in layer 1's chunk 1 (the last section): a level the layer does not hold.
    let mut b = layered();
    let n = b.u32_at(16) as usize;
    b.set_payload(n - 1, &one_row_payload(1, 0, 0.5));
    add("layer_rows_outside_its_levels", b.bytes);
    out
}

/// Run on request (`-- --ignored regenerate_bad_corpus`): writes tests/bad/; run after a
/// format change.
fn regenerate_bad_corpus() {
    let dir = bad_dir();
    std::fs::create_dir_all(&dir).unwrap();
    for p in msth_testkit::files_with_extension(&dir, "msth") {
        std::fs::remove_file(p).unwrap();
    }
    for (i, (name, bytes)) in corpus().into_iter().enumerate() {
        std::fs::write(dir.join(format!("{i:02}_{name}.msth")), bytes).unwrap();
    }
}

/// The generator's valid base file decodes (so each bad file differs from a good one by its flaw).
fn corpus_base_file_is_valid() {
    decode_all(&valid_file()).unwrap();
}

fn bad_corpus_fails_cleanly() {
    let files = msth_testkit::files_with_extension(&bad_dir(), "msth");
    assert!(files.len() >= 20, "only {} files in tests/bad", files.len());
    for p in &files {
        let bytes = std::fs::read(p).unwrap();
        let err = decode_all(&bytes).expect_err(&p.display().to_string());
        println!("{}: {err}", p.file_name().unwrap().to_string_lossy());
        // The streaming decoder fails too: at the prefix, or on some section.
        let streaming = Decoder::new(&bytes).and_then(|mut d| {
            d.feed(&bytes)?;
            d.finish()
        });
        let name = p.file_name().unwrap().to_string_lossy();
        // Trailing bytes and padding are outside every section: only whole-file decoding sees them.
        let whole_file_only = name == "26_trailing_bytes.msth" || name == "32_nonzero_padding.msth";
        if !whole_file_only {
            assert!(streaming.is_err(), "{name}: streaming decoder accepted it");
        }
    }
}

/// The committed corpus is what the generator writes (so it cannot silently go stale).
fn bad_corpus_matches_generator() {
    for (i, (name, bytes)) in corpus().into_iter().enumerate() {
        let p = bad_dir().join(format!("{i:02}_{name}.msth"));
        let on_disk = std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        assert!(
            on_disk == bytes,
            "{} differs from the generator",
            p.display()
        );
    }
}

/// Each fault added for issue #22 (and each MUST of format.md without a file before) fails with
/// an error that names what is wrong: the field, and for limits its value and the limit.
fn each_fault_names_its_violation() {
    let expect: &[(&str, &[&str])] = &[
        (
            "zstd_two_frames",
            &["dynamic chunk 1", "after the zstd frame"],
        ),
        ("zstd_trailing_skippable_frame", &["after the zstd frame"]),
        ("zstd_trailing_bytes", &["after the zstd frame"]),
        ("time_range_not_unit", &["time_range", "[0, 2]", "[0, 1]"]),
        ("huge_camera", &["cameras[0] width", "100000", "16384"]),
        (
            "huge_sampler",
            &["model.sampler.num_proposal_samples", "4096", "1024"],
        ),
        (
            "camera_too_many_pixels",
            &["cameras[0] pixels (8192 x 4096)", "33554432", "16777216"],
        ),
        ("camera_zero_width", &["camera 0", "image size"]),
        ("camera_negative_focal", &["camera 0", "focal"]),
        ("chunk_span_reversed", &["chunk 0", "bad span"]),
        ("chunk_frames_reversed", &["chunk 0", "bad span"]),
        // serde rejects a number that overflows f32: no span can hold a non-finite time.
        ("chunk_span_infinite", &["metadata JSON", "out of range"]),
        ("huge_metadata_length", &["metadata length", "16777216"]),
        ("index_reserved_nonzero", &["index entry 0", "reserved"]),
        ("index_wrong_order", &["entry 0", "expected Mlp"]),
        ("section_inside_prefix", &["mlp section", "overlaps"]),
        ("section_range_overflow", &["range overflows"]),
        ("nonzero_metadata_padding", &["metadata", "padding"]),
        ("chunk_wrong_levels", &["levels"]),
        ("varint_above_u32", &["varint exceeds 32 bits"]),
        (
            "shared_wrong_tag",
            &["shared dynamic section", "0xffffffff"],
        ),
        ("float_block_with_predictor", &["predictor must be 0"]),
        ("block_reserved_nonzero", &["reserved block byte"]),
        ("unknown_predictor", &["predictor 2"]),
        ("affine_bits_out_of_range", &["bits must be in 1..=8"]),
        ("negative_scale", &["scale -1"]),
        ("affine_overflow", &["not finite"]),
        ("codebook_nan_entry", &["codebook entry 0"]),
        (
            "occupancy_resolution_zero",
            &["occupancy section", "resolution 0"],
        ),
        (
            "occupancy_resolution_over_limit",
            &["occupancy section resolution", "600", "512"],
        ),
        ("occupancy_wrong_length", &["occupancy section", "needs"]),
        (
            "occupancy_nan_threshold",
            &["occupancy section", "threshold"],
        ),
        (
            "occupancy_reserved_nonzero",
            &["occupancy section", "reserved"],
        ),
        (
            "occupancy_padding_bit",
            &["occupancy section", "past the last cell"],
        ),
        (
            "occupancy_raw_length_beyond_limit",
            &["occupancy section raw length"],
        ),
        ("v2_file_marked_v1", &["index", "7 sections, expected 6"]),
        ("layer_in_v3_entry", &["index entry 2", "reserved"]),
        (
            "layers_key_in_v3_file",
            &["unknown key `layers`", "version 3"],
        ),
        (
            "layers_last_short_of_the_levels",
            &["last layer", "1/2/2/2", "2/2/2/2"],
        ),
        ("layers_add_no_level", &["layers[1]", "adds levels"]),
        ("layers_unknown_key", &["metadata JSON", "h5"]),
        (
            "layer_number_out_of_order",
            &["entry 11", "layer 2", "expected Dynamic chunk 1 layer 1"],
        ),
        (
            "layer_rows_outside_its_levels",
            &["dynamic chunk 1, layer 1", "level 0", "holds levels 1..2"],
        ),
        ("v1_file_marked_v2", &["index"]),
        (
            "v3_key_in_v2_file",
            &["section_quant", "version 2", "version 3"],
        ),
        ("play_samples_zero", &["play_samples.proposal is 0"]),
        (
            "play_samples_over_limit",
            &["play_samples.main", "513", "512"],
        ),
        ("play_samples_unknown_key", &["metadata JSON", "extra"]),
        (
            "quant_disagrees_with_section_quant",
            &["quant is q5", "finest mode in section_quant is q8"],
        ),
        ("section_quant_unknown_mode", &["metadata JSON", "q7"]),
    ];
    let corpus = corpus();
    for (name, needles) in expect {
        let (_, bytes) = corpus
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("{name} is not in the corpus"));
        let err = decode_all(bytes).expect_err(name).to_string();
        for n in *needles {
            assert!(err.contains(n), "{name}: `{err}` should mention `{n}`");
        }
    }
}

/// One stored 4D row (level 0, `row`) with every feature `value`, tagged `tag`.
fn one_row_payload(tag: u32, row: u32, value: f32) -> Vec<u8> {
    let (c, _) = tiny_model();
    let layout = ModelLayout::new(&c);
    let (g4, _) = layout.field.encoding.h4.clone().unwrap();
    let mut w = Writer::default();
    w.u32(tag);
    w.u32(g4.levels.len() as u32);
    for l in 0..g4.levels.len() {
        let rows: &[u32] = if l == 0 { &[row] } else { &[] };
        w.u32(rows.len() as u32);
        for &r in rows {
            w.varint(r);
        }
        w.block(&vec![value; rows.len() * g4.features], BlockEncoding::F32);
    }
    w.bytes
}

/// format.md §6.4: decoders MUST NOT rely on the writer's split of rows between the shared
/// section and the chunks: a row stored in both takes the chunk's values (later writes win), in
/// the whole-file and the streaming decoder.
fn a_row_in_shared_and_chunk_takes_the_chunks_values() {
    let mut b = File {
        bytes: valid_file(),
    };
    let last = b_last(&b.bytes);
    let put = |b: &mut File, i: usize, raw: Vec<u8>| {
        let stored = zstd::bulk::compress(&raw, 3).unwrap();
        b.replace_section(i, &stored, raw.len() as u64);
    };
    let row = 2;
    put(&mut b, SHARED, one_row_payload(u32::MAX, row, 0.5));
    put(&mut b, SHARED + 1, one_row_payload(0, row + 1, 0.25));
    put(&mut b, last, one_row_payload(1, row, 0.75));
    let (c, _) = tiny_model();
    let layout = ModelLayout::new(&c);
    let (g4, r4) = layout.field.encoding.h4.clone().unwrap();
    let at = r4.start + g4.levels[0].offset + row as usize * g4.features;
    let feats = at..at + g4.features;
    let d = decode_all(&b.bytes).unwrap();
    let spans = d.metadata.chunks.clone();
    let mut stream = Decoder::new(&b.bytes).unwrap();
    stream.feed(&b.bytes).unwrap();
    for (t, want) in [(spans[0].t_start, 0.5), (spans[1].t_start, 0.75)] {
        let whole = d.params_for_time(t);
        let streamed = stream.params_for_time(t).unwrap();
        assert!(whole[feats.clone()].iter().all(|&v| v == want), "t = {t}");
        assert_eq!(whole, streamed, "t = {t}");
    }
}

/// The web player's decoder rejects the same files (`web/tests/decode_corpus.mjs`), so that a
/// page and `msth play` agree on what a valid file is. Needs `node` and `npm ci --prefix web`
/// (the `browser` need of [`main`]).
fn web_decoder_rejects_the_bad_corpus() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    // What only a whole-file decoder sees (bad_corpus_fails_cleanly lets these through the
    // streaming decoder too).
    let out = std::process::Command::new("node")
        .current_dir(&root)
        .args([
            "web/tests/decode_corpus.mjs",
            bad_dir().to_str().unwrap(),
            "26_trailing_bytes.msth",
            "32_nonzero_padding.msth",
        ])
        .output()
        .expect("node runs");
    let text =
        String::from_utf8_lossy(&out.stdout).to_string() + &String::from_utf8_lossy(&out.stderr);
    println!("{text}");
    assert!(out.status.success(), "the web decoder disagrees:\n{text}");
}

fn main() -> std::process::ExitCode {
    // The web decoder runs in Node with the page's npm packages.
    let node = msth_tests::web_decoder_need();
    Tests::new(file!())
        .test("corpus_base_file_is_valid", corpus_base_file_is_valid)
        .test("bad_corpus_fails_cleanly", bad_corpus_fails_cleanly)
        .test("bad_corpus_matches_generator", bad_corpus_matches_generator)
        .test(
            "each_fault_names_its_violation",
            each_fault_names_its_violation,
        )
        .test(
            "a_row_in_shared_and_chunk_takes_the_chunks_values",
            a_row_in_shared_and_chunk_takes_the_chunks_values,
        )
        .needs(
            &[&node],
            "web_decoder_rejects_the_bad_corpus",
            web_decoder_rejects_the_bad_corpus,
        )
        .on_request(&[], "regenerate_bad_corpus", regenerate_bad_corpus)
        .run()
}
