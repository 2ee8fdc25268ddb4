//! Unit tests across the codec's modules on a tiny model: round trips, streaming, hostile bytes.

use msth_core::config::{BlendMode, ModelConfig};
use msth_core::field::ModelLayout;

use crate::format::{FileIndex, Limits};
use crate::{decode_all, encode, DecodeError, Decoder, EncodeOptions, QuantMode};

fn tiny(blend: BlendMode, frames: usize) -> ModelConfig {
    let mut c = ModelConfig::fast_on_white(frames);
    for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
        enc.blend = blend;
        enc.resize(4, 14, 64.0, 8);
        enc.grid3.log2_table_size = 10;
    }
    c.field.density_hidden = 16;
    c.field.color_hidden = 16;
    c
}

/// Parameters with a dynamic blob in the mask (logit -3 near the centre, +3 elsewhere).
fn params_for(c: &ModelConfig) -> Vec<f32> {
    let layout = ModelLayout::new(c);
    let mut p = layout.init_params(3);
    for (i, v) in p.iter_mut().enumerate() {
        *v += ((i as f32) * 0.013).sin() * 0.01;
    }
    if let Some((g, r)) = &layout.field.encoding.mask {
        let res = g.res;
        for (i, v) in p[r.clone()].iter_mut().enumerate() {
            let (x, y, z) = (i % res, (i / res) % res, i / (res * res));
            let centre = [x, y, z].iter().all(|&a| (3..=4).contains(&a));
            *v = if centre { -3.0 } else { 3.0 };
        }
    }
    p
}

#[test]
fn f32_round_trip_is_bit_exact_where_stored() {
    let c = tiny(BlendMode::Mt, 12);
    let p = params_for(&c);
    let opts = EncodeOptions {
        quant: QuantMode::F32,
        chunk_frames: 4,
        ..Default::default()
    };
    let (bytes, report) = encode(&c, &p, &[], &opts).unwrap();
    assert_eq!(report.chunks.len(), 3);
    assert!(report.h4_kept_union < report.h4_values, "{report:?}");
    let d = decode_all(&bytes).unwrap();
    assert_eq!(d.config, c);
    let layout = ModelLayout::new(&c);
    let h4 = layout.field.encoding.h4.as_ref().unwrap().1.clone();
    let mut zero = 0;
    for i in 0..p.len() {
        if h4.contains(&i) && d.params[i] == 0.0 {
            zero += 1;
            continue;
        }
        assert_eq!(d.params[i].to_bits(), p[i].to_bits(), "index {i}");
    }
    assert!(zero > 0);
    // Per time: only the covering chunk's rows, others zero.
    let t = d.params_for_time(0.9);
    assert_eq!(d.chunk_for_time(0.9), Some(2));
    for i in h4.clone() {
        assert!(t[i] == 0.0 || t[i].to_bits() == p[i].to_bits());
    }
}

#[test]
fn every_mode_decodes_within_its_error() {
    let c = tiny(BlendMode::Mst, 5);
    let p = params_for(&c);
    for (mode, tol) in [
        (QuantMode::F32, 0.0),
        (QuantMode::F16, 1e-3),
        (QuantMode::Q8, 0.05),
        (QuantMode::Q6, 0.1),
        (QuantMode::Q5, 0.2),
        (QuantMode::Q4, 0.5),
        (QuantMode::K4, 0.5),
        (QuantMode::K3, 1.0),
    ] {
        let opts = EncodeOptions {
            quant: mode,
            dynamic_threshold: 0.0,
            ..Default::default()
        };
        let (bytes, _) = encode(&c, &p, &[], &opts).unwrap();
        let d = decode_all(&bytes).unwrap();
        let h4 = d.layout.field.encoding.h4.as_ref().unwrap().1.clone();
        // 4D rows that no point reaches are not stored (decoded as 0).
        let worst = (0..p.len())
            .filter(|i| !(h4.contains(i) && d.params[*i] == 0.0))
            .map(|i| (d.params[i] - p[i]).abs())
            .fold(0f32, f32::max);
        assert!(worst <= tol, "{mode}: worst error {worst}");
    }
}

#[test]
fn static_scene_has_no_chunks() {
    for blend in [BlendMode::Static, BlendMode::Mt] {
        let c = tiny(blend, 8);
        let mut p = params_for(&c);
        if let Some((_, r)) = &ModelLayout::new(&c).field.encoding.mask {
            p[r.clone()].fill(8.0); // m ~ 1 everywhere: nothing dynamic
        }
        let (bytes, report) = encode(&c, &p, &[], &EncodeOptions::default()).unwrap();
        assert!(report.chunks.is_empty(), "{blend:?}");
        let d = decode_all(&bytes).unwrap();
        assert_eq!(d.chunk_for_time(0.5), None);
        assert_eq!(d.params_for_time(0.5), d.params);
    }
}

#[test]
fn every_prefix_streams_cleanly() {
    let c = tiny(BlendMode::Mt, 6);
    let p = params_for(&c);
    let opts = EncodeOptions {
        quant: QuantMode::Q8,
        chunk_frames: 2,
        ..Default::default()
    };
    let (bytes, _) = encode(&c, &p, &[], &opts).unwrap();
    let full = decode_all(&bytes).unwrap();
    let index = FileIndex::parse(&bytes, &Limits::default()).unwrap();
    let hs = index.header.header_size as usize;
    let mut stream: Option<Decoder> = None;
    for n in 0..=bytes.len() {
        let prefix = &bytes[..n];
        match Decoder::new(prefix) {
            Ok(_) => assert!(n >= hs),
            Err(e) => {
                assert!(n < hs && e.is_truncated(), "{n}: {e}");
            }
        }
        if n < bytes.len() {
            assert!(decode_all(prefix).unwrap_err().is_truncated());
        }
        if stream.is_none() && n >= hs {
            stream = Some(Decoder::new(prefix).unwrap());
        }
        if let Some(s) = &mut stream {
            for i in s.feed(prefix).unwrap() {
                let e = &s.index().sections[i];
                assert!(e.offset + e.length <= n as u64);
            }
            for (i, e) in s.index().sections.iter().enumerate() {
                assert_eq!(s.is_decoded(i), e.offset + e.length <= n as u64);
            }
        }
    }
    let s = stream.unwrap();
    // Random access: chunk 1 alone, from its own bytes (version 2: MLP, proposal, static,
    // occupancy, shared, chunk 0, chunk 1).
    let mut r = Decoder::new(&bytes[..hs]).unwrap();
    assert_eq!(r.index().first_chunk(), 5);
    for i in [6, 2, 0, 4, 3, 1] {
        let e = r.index().sections[i].clone();
        r.decode_section(i, &bytes[e.offset as usize..(e.offset + e.length) as usize])
            .unwrap();
    }
    let t = 0.5; // frames 2..4 (t 0.4..0.8) -> chunk 1
    assert_eq!(r.index().chunk_for_time(t), Some(1));
    assert_eq!(r.params_for_time(t).unwrap(), full.params_for_time(t));
    assert!(r.params_for_time(0.9).unwrap_err().is_truncated());
    assert_eq!(s.finish().unwrap().params, full.params);
}

#[test]
fn corruption_and_limits_fail_cleanly() {
    let c = tiny(BlendMode::Mt, 4);
    let p = params_for(&c);
    let (bytes, _) = encode(&c, &p, &[], &EncodeOptions::default()).unwrap();
    // Every single-byte flip is caught (prefix CRC, section CRCs) without a panic.
    for i in (0..bytes.len()).step_by(7) {
        let mut b = bytes.clone();
        b[i] ^= 0x24;
        assert!(decode_all(&b).is_err(), "flip at {i}");
    }
    let small = Limits {
        max_params: 1000,
        ..Limits::default()
    };
    assert!(matches!(
        crate::decode_all_with_limits(&bytes, &small),
        Err(DecodeError::Limit { .. })
    ));
    let mut trailing = bytes.clone();
    trailing.push(0);
    assert!(decode_all(&trailing).is_err());
}

#[test]
fn encoder_rejects_bad_input() {
    let c = tiny(BlendMode::Mt, 4);
    let mut p = params_for(&c);
    assert!(encode(&c, &p[1..], &[], &EncodeOptions::default()).is_err());
    let opts = EncodeOptions {
        chunk_frames: 0,
        ..Default::default()
    };
    assert!(encode(&c, &p, &[], &opts).is_err());
    p[5] = f32::NAN;
    assert!(encode(&c, &p, &[], &EncodeOptions::default()).is_err());
}

#[test]
fn encoder_output_follows_the_writer_rules() {
    // format.md §3.3: spans contiguous, the first from 0, the last to 1 (any frame count).
    for (frames, chunk_frames) in [(4, 2), (7, 3), (1, 1), (10, 4)] {
        let c = tiny(BlendMode::Mt, frames);
        let p = params_for(&c);
        let opts = EncodeOptions {
            chunk_frames,
            ..Default::default()
        };
        let (bytes, _) = encode(&c, &p, &[], &opts).unwrap();
        let index = FileIndex::parse(&bytes, &Limits::default()).unwrap();
        index.check_writer_rules().unwrap();
        if index.metadata.chunks.len() > 1 {
            let mut gap = index.clone();
            gap.metadata.chunks[1].t_start += 0.01;
            let err = gap.check_writer_rules().unwrap_err().to_string();
            assert!(err.contains("contiguous"), "{err}");
            let mut late = index.clone();
            late.metadata.chunks[0].t_start = 0.1;
            assert!(late.check_writer_rules().is_err());
        }
    }
}

#[test]
fn encoder_refuses_what_the_decoder_limits_refuse() {
    let mut c = tiny(BlendMode::Mt, 4);
    let p = params_for(&c);
    c.sampler.num_samples = crate::format::MAX_SAMPLES as usize + 1;
    let err = encode(&c, &p, &[], &EncodeOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("model.sampler.num_samples"), "{err}");
    let c = tiny(BlendMode::Mt, 4);
    let big: msth_core::Camera = serde_json::from_value(serde_json::json!({
        "width": 5000, "height": 5000, "fx": 4000.0, "fy": 4000.0, "cx": 2500.0, "cy": 2500.0,
        "world_from_camera": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 4, 1]
    }))
    .unwrap();
    let err = encode(&c, &p, &[big], &EncodeOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("cameras[0] pixels (5000 x 5000)"), "{err}");
    // 4K UHD and the Plenoptic Video sizes are within the limits.
    let limits = Limits::default();
    for (w, h) in [(3840, 2160), (4096, 2160), (2704, 2028), (1352, 1014)] {
        limits.check_image("camera", w, h).unwrap();
    }
}

/// A layered file (version 4) decodes to the same parameters as the file of one layer, bit for
/// bit, for every blend mode and a static scene; a decoder holding the first `k` layers renders
/// the finer levels as 0 and every stored coarser value exactly; its index lists each layer's
/// sections where `FileIndex::position` says.
#[test]
fn layers_decode_like_one_layer_and_prefixes_zero_the_finer_levels() {
    for (blend, frames) in [
        (BlendMode::Mst, 12),
        (BlendMode::Mt, 12),
        (BlendMode::Add, 5),
        (BlendMode::Mst, 1),
    ] {
        let c = tiny(blend, frames);
        let p = params_for(&c);
        let layout = ModelLayout::new(&c);
        let one = EncodeOptions {
            quant: QuantMode::Q5,
            chunk_frames: 4,
            ..Default::default()
        };
        let (flat, flat_report) = encode(&c, &p, &[], &one).unwrap();
        let (bytes, report) = encode(
            &c,
            &p,
            &[],
            &EncodeOptions {
                layers: 3,
                ..one.clone()
            },
        )
        .unwrap();
        assert_eq!(&flat[4..6], &3u16.to_le_bytes());
        assert_eq!(&bytes[4..6], &4u16.to_le_bytes());
        assert_eq!(report.layers.len(), 3, "{blend:?}");
        assert_eq!(flat_report.layers.len(), 1);
        assert_eq!(report.file_bytes, bytes.len() as u64);
        assert_eq!(report.chunks.len(), flat_report.chunks.len());
        let a = decode_all(&flat).unwrap();
        let b = decode_all(&bytes).unwrap();
        assert_eq!(a.params.len(), b.params.len());
        assert!(
            a.params
                .iter()
                .zip(&b.params)
                .all(|(x, y)| x.to_bits() == y.to_bits()),
            "{blend:?}"
        );
        for t in [0.0, 0.4, 1.0] {
            let (x, y) = (a.params_for_time(t), b.params_for_time(t));
            assert!(
                x.iter().zip(&y).all(|(x, y)| x.to_bits() == y.to_bits()),
                "{blend:?} t {t}"
            );
        }
        let ix = FileIndex::parse(&bytes, &Limits::default()).unwrap();
        for (i, e) in ix.sections.iter().enumerate() {
            let chunk = e.chunk as usize;
            assert_eq!(
                ix.position(e.kind, chunk, e.layer as usize),
                Some(i),
                "{e:?}"
            );
        }
        // Prefixes: a decoder fed layers 0..k only.
        let chunk = ix.chunk_for_time(0.9);
        let levels = ix.metadata.layer_levels();
        for k in 1..=3 {
            let mut d = Decoder::new(&bytes).unwrap();
            for i in ix.sections_for(chunk, k) {
                let e = &ix.sections[i];
                d.decode_section(i, &bytes[e.offset as usize..(e.offset + e.length) as usize])
                    .unwrap();
            }
            assert_eq!(d.layers_ready(chunk), k);
            let got = d.params_for_time(0.9).unwrap();
            let full = b.params_for_time(0.9);
            let mut kept = 0;
            let prop = &layout.proposal.field.encoding;
            for (name, grid, keep) in [
                ("h3", &layout.field.encoding.h3, levels[k - 1].h3),
                ("h4", &layout.field.encoding.h4, levels[k - 1].h4),
                ("p3", &prop.h3, levels[k - 1].p3),
                ("p4", &prop.h4, levels[k - 1].p4),
            ] {
                let Some((g, range)) = grid else { continue };
                for (l, level) in g.levels.iter().enumerate() {
                    let s = range.start + level.offset
                        ..range.start + level.offset + level.rows * g.features;
                    if l < keep as usize {
                        kept += 1;
                        assert!(
                            got[s.clone()]
                                .iter()
                                .zip(&full[s])
                                .all(|(x, y)| x.to_bits() == y.to_bits()),
                            "{name} {l}"
                        );
                    } else {
                        assert!(
                            got[s].iter().all(|&v| v == 0.0),
                            "{blend:?} {name} level {l} of prefix {k}"
                        );
                    }
                }
            }
            assert!(kept > 0);
            // The full decoder asked for k layers draws the same.
            let mut all = Decoder::new(&bytes).unwrap();
            all.feed(&bytes).unwrap();
            let mut same = Vec::new();
            all.params_for_layers_into(0.9, k, &mut same).unwrap();
            assert!(
                same.iter()
                    .zip(&got)
                    .all(|(x, y)| x.to_bits() == y.to_bits()),
                "{blend:?} {k}"
            );
        }
        // Each layer's bytes add up to the layered sections.
        let layered: u64 = report
            .layers
            .iter()
            .map(|l| l.static_bytes + l.dynamic_bytes)
            .sum();
        let listed: u64 = ix
            .sections
            .iter()
            .filter(|e| {
                matches!(
                    e.kind,
                    crate::SectionKind::Static
                        | crate::SectionKind::Shared
                        | crate::SectionKind::Dynamic
                )
            })
            .map(|e| e.length)
            .sum();
        assert_eq!(layered, listed);
        assert!(report.first_frame_bytes(1) < report.first_frame_bytes(3));
    }
}

/// A layered file's structure is checked like the rest: a layer field in an older version, a
/// `layers` list that does not end at the tables' levels or adds none, rows of a level outside
/// the layer.
#[test]
fn layered_files_are_checked() {
    let c = tiny(BlendMode::Mst, 12);
    let p = params_for(&c);
    let opts = EncodeOptions {
        chunk_frames: 4,
        layers: 2,
        ..Default::default()
    };
    let (bytes, _) = encode(&c, &p, &[], &opts).unwrap();
    let ix = FileIndex::parse(&bytes, &Limits::default()).unwrap();
    // A version-3 file with a layer number in an entry.
    let (flat, _) = encode(
        &c,
        &p,
        &[],
        &EncodeOptions {
            layers: 1,
            ..opts.clone()
        },
    )
    .unwrap();
    let mut bad = flat.clone();
    let io = crate::format::index_offset(
        FileIndex::parse(&flat, &Limits::default())
            .unwrap()
            .header
            .metadata_length as u64,
    ) as usize;
    bad[io + 2] = 1;
    refix_prefix_crc(&mut bad);
    let e = decode_all(&bad).unwrap_err().to_string();
    assert!(e.contains("reserved"), "{e}");
    // `layers` that do not reach every level, or repeat one.
    for layers in [
        r#"[{"h3":2,"h4":2,"p3":2,"p4":2}]"#,
        r#"[{"h3":2,"h4":2,"p3":2,"p4":2},{"h3":2,"h4":2,"p3":2,"p4":2},{"h3":4,"h4":4,"p3":4,"p4":4}]"#,
    ] {
        let mut m = ix.metadata.clone();
        m.layers = Some(serde_json::from_str(layers).unwrap());
        let e = crate::format::FileIndex::parse(&with_metadata(&bytes, &m), &Limits::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("layer"), "{e}");
    }
    // Layer 1's shared rows read as layer 0's: rows in levels the layer does not hold.
    let e1 = &ix.sections[ix.position(crate::SectionKind::Shared, 0, 1).unwrap()];
    let stored = &bytes[e1.offset as usize..(e1.offset + e1.length) as usize];
    let payload = zstd::bulk::decompress(stored, e1.raw_length as usize).unwrap();
    let layer0 = 0..ix.metadata.layer_levels()[0].h4 as usize;
    let e = crate::sections::read_chunk_levels(
        &ix.layout,
        &payload,
        crate::sections::SHARED_TAG,
        layer0,
        "shared",
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("this layer holds levels"), "{e}");
}

/// Rewrites the prefix CRC after an edit of the prefix.
fn refix_prefix_crc(b: &mut [u8]) {
    let hs = u32::from_le_bytes([b[8], b[9], b[10], b[11]]) as usize;
    let mut crc = crc32fast::Hasher::new();
    crc.update(&b[..28]);
    crc.update(&b[32..hs]);
    let v = crc.finalize();
    b[28..32].copy_from_slice(&v.to_le_bytes());
}

/// The file's prefix with other metadata (offsets unchanged: only the index is read).
fn with_metadata(bytes: &[u8], m: &crate::Metadata) -> Vec<u8> {
    let ix = FileIndex::parse(bytes, &Limits::default()).unwrap();
    let meta = serde_json::to_vec(m).unwrap();
    let io = crate::format::index_offset(meta.len() as u64) as usize;
    let mut out = bytes[..32].to_vec();
    out.extend_from_slice(&meta);
    out.resize(io, 0);
    for e in &ix.sections {
        crate::format::write_entry(&mut out, e);
    }
    let hs = out.len() as u32;
    out[8..12].copy_from_slice(&hs.to_le_bytes());
    out[12..16].copy_from_slice(&(meta.len() as u32).to_le_bytes());
    refix_prefix_crc(&mut out);
    out
}
