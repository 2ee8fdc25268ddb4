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
