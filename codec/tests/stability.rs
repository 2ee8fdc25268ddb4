//! Codec stability at the extremes (issue #8, part 2). Quantisation: f16 and 8-bit (and 1..8-bit
//! affine and codebook) blocks of huge, tiny, subnormal, constant and widely spread values
//! round-trip to finite values within their documented error; whole files with such parameters,
//! with 1 frame and with 10,000 frames, encode and decode; the rows a chunk keeps at finest
//! resolution 2^16 include every row its region reads.
//!
//! Documented errors (`codec/src/quant.rs`):
//! - f16: values are clamped to `±65504` (f16's largest finite value), then rounded: relative
//!   error `<= 2^-11` in f16's normal range, absolute error `<= 2^-25` below it (values under
//!   `2^-25`, e.g. 1e-8, become 0);
//! - affine with `b` bits over a block `[lo, hi]`: error `<= (hi - lo) / (2^b - 1) / 2` plus f32
//!   rounding; a block whose spread overflows f32 (values of both signs near `±f32::MAX`) is
//!   narrowed to `0.9998 f32::MAX` around its mid-range and the values outside clamp to it; next
//!   to `±f32::MAX` the top of the range may lose a few ulps so that decoding stays finite;
//! - codebook: every value decodes to the codebook entry nearest to it.

use msth_codec::quant::{affine_params, BlockEncoding, Reader, Writer};
use msth_testkit::proptest_config;
use proptest::prelude::*;

fn round_trip(values: &[f32], enc: BlockEncoding) -> (Vec<f32>, Vec<u8>) {
    let mut w = Writer::default();
    w.block(values, enc);
    let mut r = Reader::new(&w.bytes, "test");
    let mut out = vec![0f32; values.len()];
    let got = r
        .block_into(&mut out, "block")
        .unwrap_or_else(|e| panic!("{enc:?} of {values:?} does not decode: {e}"));
    assert_eq!(got, enc);
    r.finish().unwrap();
    (out, w.bytes)
}

/// Finite values of every magnitude: huge (up to `f32::MAX`), tiny, subnormal, zero.
fn extreme_value() -> impl Strategy<Value = f32> {
    prop_oneof![
        2 => prop::num::f32::NORMAL,
        1 => prop::num::f32::SUBNORMAL,
        1 => prop::num::f32::ZERO,
        1 => Just(f32::MAX),
        1 => Just(-f32::MAX),
        1 => Just(1e6f32),
        1 => Just(-1e6f32),
        1 => Just(1e-8f32),
        1 => Just(-1e-8f32),
        1 => Just(65504.0f32),
        1 => Just(65520.0f32),
        2 => -2.0f32..2.0,
    ]
}

/// A block: independent extremes, a constant block, or a narrow or wide band.
fn block() -> impl Strategy<Value = Vec<f32>> {
    prop_oneof![
        prop::collection::vec(extreme_value(), 1..64),
        (extreme_value(), 1usize..64).prop_map(|(v, n)| vec![v; n]),
        (extreme_value(), prop::collection::vec(0.0f32..1.0, 1..64)).prop_map(|(c, u)| {
            // c (1 + u eps): a spread of a few ulps around any value
            u.iter()
                .map(|&x| c + c * x * f32::EPSILON * 4.0)
                .filter(|v| v.is_finite())
                .collect()
        }),
    ]
    .prop_filter("non-empty", |v: &Vec<f32>| !v.is_empty())
}

/// One ulp of `x` (at least the smallest subnormal).
fn ulp(x: f64) -> f64 {
    (x.abs() * f32::EPSILON as f64).max(f32::from_bits(1) as f64)
}

fn f16_bound(v: f32) -> f64 {
    let c = v.clamp(-65504.0, 65504.0) as f64;
    if c.abs() >= 6.103_515_6e-5 {
        c.abs() * 2f64.powi(-11)
    } else {
        2f64.powi(-25)
    }
}

proptest! {
    #![proptest_config(proptest_config(256))]

    /// f16 blocks: finite, saturated at ±65504, within the rounding error of the clamped value.
    #[test]
    fn f16_round_trip_is_finite_within_documented_error(values in block()) {
        let (out, _) = round_trip(&values, BlockEncoding::F16);
        for (v, d) in values.iter().zip(&out) {
            prop_assert!(d.is_finite());
            let c = v.clamp(-65504.0, 65504.0) as f64;
            prop_assert!(
                (*d as f64 - c).abs() <= f16_bound(*v),
                "{v} -> {d} (clamped {c})"
            );
        }
    }

    /// Affine blocks of 1..=8 bits over any finite values: finite, within half a step (plus f32
    /// rounding) of the value clamped into the block's representable range.
    #[test]
    fn affine_round_trip_is_finite_within_documented_error(
        values in block(),
        bits in 1u8..=8,
    ) {
        let enc = BlockEncoding::Affine { bits };
        let (out, _) = round_trip(&values, enc);
        let (min, scale) = affine_params(&values, bits);
        prop_assert!(min.is_finite() && scale.is_finite() && scale >= 0.0);
        let levels = ((1u32 << bits) - 1) as f64;
        // The top code, computed as the decoder does (in f32), is finite.
        let top32 = min + levels as f32 * scale;
        prop_assert!(top32.is_finite(), "top code {top32}");
        let top = top32 as f64;
        let lo = values.iter().copied().fold(f32::INFINITY, f32::min) as f64;
        let hi = values.iter().copied().fold(f32::NEG_INFINITY, f32::max) as f64;
        let spread = hi - lo;
        let max_abs = lo.abs().max(hi.abs());
        // The stored range covers the block, or f32::MAX of it when the spread overflows f32,
        // up to subnormal underflow of the step and a few ulps next to f32::MAX.
        let narrowed = spread > f32::MAX as f64;
        let covered = top - min as f64;
        prop_assert!(
            covered >= spread.min(0.9998 * f32::MAX as f64) * 0.999 - levels * ulp(0.0),
            "{bits} bits: range {lo}..{hi} stored as {min} + {levels} x {scale}"
        );
        for (v, d) in values.iter().zip(&out) {
            prop_assert!(d.is_finite(), "{v} -> {d}");
            let (v, d) = (*v as f64, *d as f64);
            // Within half a step of the value; when the spread overflows f32 the values outside
            // the stored range clamp to its ends.
            let target = if narrowed { v.clamp(min as f64, top) } else { v };
            let step = if scale > 0.0 { scale as f64 } else { spread };
            let tol = 0.5 * step + 8.0 * ulp(max_abs) + 256.0 * ulp(0.0);
            prop_assert!(
                (d - target).abs() <= tol,
                "{bits} bits: {v} -> {d} (range {lo}..{hi}, min {min}, scale {scale})"
            );
        }
    }

    /// Codebook blocks: finite, and every value decodes to its nearest codebook entry.
    #[test]
    fn codebook_round_trip_decodes_to_the_nearest_entry(
        values in block(),
        bits in prop_oneof![Just(1u8), Just(3u8), Just(4u8)],
    ) {
        let enc = BlockEncoding::Codebook { bits };
        let (out, bytes) = round_trip(&values, enc);
        let k = 1usize << bits;
        let book: Vec<f32> = (0..k)
            .map(|i| f32::from_le_bytes(bytes[8 + 4 * i..12 + 4 * i].try_into().unwrap()))
            .collect();
        prop_assert!(book.iter().all(|c| c.is_finite()));
        for (v, d) in values.iter().zip(&out) {
            prop_assert!(d.is_finite());
            let best = book
                .iter()
                .map(|c| (*c as f64 - *v as f64).abs())
                .fold(f64::INFINITY, f64::min);
            let err = (*d as f64 - *v as f64).abs();
            prop_assert!(
                err <= best * (1.0 + 1e-6) + ulp(*v as f64),
                "{v} -> {d}, nearest entry is {best} away (book {book:?})"
            );
        }
    }
}

/// The cases the issue names, spelled out: f16 of 1e6 and 1e-8, q8 of huge, tiny and zero
/// spreads.
#[test]
fn named_extremes_round_trip() {
    let (f16, _) = round_trip(&[1e6, -1e6, 1e-8, -1e-8, 0.1, 65504.0], BlockEncoding::F16);
    assert_eq!(f16[..4], [65504.0, -65504.0, 0.0, -0.0]);
    assert!((f16[4] - 0.1).abs() < 0.1 * 2f32.powi(-11));
    assert_eq!(f16[5], 65504.0);

    let q8 = BlockEncoding::Affine { bits: 8 };
    // Zero spread, any magnitude: exact.
    for c in [0.0f32, 1e-40, -1e-8, 1e6, 3e38, -f32::MAX] {
        assert_eq!(round_trip(&[c; 9], q8).0, vec![c; 9], "constant {c}");
    }
    // Tiny values with a tiny spread.
    let tiny = [1e-8f32, 2e-8, 3e-8, 1.5e-8];
    for (a, b) in round_trip(&tiny, q8).0.iter().zip(&tiny) {
        assert!((a - b).abs() <= 2e-8 / 255.0 / 2.0 * 1.01, "{a} vs {b}");
    }
    // Huge spread that still fits in f32: half a step of 2e38 / 255.
    let huge = [-1e38f32, 1e38, 0.0, 5e37, 1.0];
    for (a, b) in round_trip(&huge, q8).0.iter().zip(&huge) {
        assert!(
            ((a - b).abs() as f64) <= 2e38 / 255.0 / 2.0 * 1.001,
            "{a} vs {b}"
        );
    }
    // The widest possible spread, -f32::MAX..f32::MAX, overflows f32: the block is narrowed to
    // a spread of f32::MAX around its mid-range. Values inside keep half a step of f32::MAX / 255;
    // the outliers clamp to about ±f32::MAX / 2.
    let widest = [-f32::MAX, f32::MAX, 0.0, 1e37, -3e37, 1e38];
    let (out, _) = round_trip(&widest, q8);
    assert!(out.iter().all(|v| v.is_finite()), "{out:?}");
    let step = f32::MAX as f64 / 255.0;
    for i in 2..widest.len() {
        assert!(
            ((out[i] - widest[i]).abs() as f64) <= step * 0.51,
            "{} -> {}",
            widest[i],
            out[i]
        );
    }
    assert!(out[0] < -1.6e38 && out[1] > 1.6e38, "{out:?}");
    // Next to f32::MAX: the top code still decodes finite.
    for bits in 1..=8u8 {
        let (out, _) = round_trip(&[0.0, f32::MAX, 3e38], BlockEncoding::Affine { bits });
        assert!(out.iter().all(|v| v.is_finite()), "{bits}: {out:?}");
        assert!(out[1] as f64 >= f32::MAX as f64 * 0.999, "{bits}: {out:?}");
    }
    // Codebook entries near f32::MAX: the value at f32::MAX decodes to itself, not to the lower
    // entry (the midpoint of the two entries used to overflow to infinity).
    let (out, _) = round_trip(&[f32::MAX, 1.35e35], BlockEncoding::Codebook { bits: 1 });
    assert_eq!(out, vec![f32::MAX, 1.35e35]);
}

mod files {
    use msth_codec::{decode_all, encode, EncodeOptions, QuantMode};
    use msth_core::config::{BlendMode, ModelConfig};
    use msth_core::field::ModelLayout;

    fn tiny(frames: usize) -> ModelConfig {
        let mut c = ModelConfig::fast_on_white(frames);
        for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
            enc.blend = BlendMode::Mt;
            enc.resize(3, 12, 32.0, 6);
        }
        c.resize_mlps(8, 4);
        c
    }

    /// Parameters of every magnitude: 1e6 and 1e-8 in the MLPs (stored as f16 in the quantised
    /// modes), a table level of constants, a table level of huge values, the mask half dynamic.
    fn extreme_params(c: &ModelConfig) -> Vec<f32> {
        let layout = ModelLayout::new(c);
        let mut p = layout.init_params(1);
        for e in &layout.params.entries {
            let r = e.range();
            if e.name.ends_with("mlp") {
                for (i, v) in p[r].iter_mut().enumerate() {
                    *v = match i % 4 {
                        0 => 1e6,
                        1 => -1e-8,
                        2 => 0.0,
                        _ => -3.5,
                    };
                }
            } else if e.name.ends_with(".mask") {
                for (i, v) in p[r].iter_mut().enumerate() {
                    *v = if i % 2 == 0 { -30.0 } else { 30.0 };
                }
            } else if e.name == "field.h3" {
                let (g, _) = layout.field.encoding.h3.as_ref().unwrap();
                let l0 = &g.levels[0];
                p[r.start..r.start + l0.rows * g.features].fill(7.25);
                let l1 = &g.levels[1];
                let s = r.start + l1.offset;
                for (i, v) in p[s..s + l1.rows * g.features].iter_mut().enumerate() {
                    *v = if i % 3 == 0 { 1e30 } else { -1e30 };
                }
            }
        }
        p
    }

    /// Files with extreme parameters, 1 frame and 10,000 frames, every quantisation mode: the
    /// encoder accepts them, the decoder reads them back finite, the stored constants are exact
    /// and f16 values saturate at ±65504.
    #[test]
    fn extreme_parameters_and_frame_counts_round_trip_through_files() {
        for frames in [1usize, 10_000] {
            let c = tiny(frames);
            c.validate().unwrap();
            let p = extreme_params(&c);
            for quant in [QuantMode::F32, QuantMode::F16, QuantMode::Q8, QuantMode::K3] {
                let opts = EncodeOptions {
                    quant,
                    chunk_frames: if frames > 1 { 100 } else { 1 },
                    ..Default::default()
                };
                let (bytes, report) = encode(&c, &p, &[], &opts)
                    .unwrap_or_else(|e| panic!("{frames} frames {quant}: {e}"));
                assert_eq!(report.chunks.len(), frames.div_ceil(opts.chunk_frames));
                let d = decode_all(&bytes).unwrap();
                assert!(d.params.iter().all(|v| v.is_finite()));
                assert_eq!(d.config.num_frames, frames);
                let mlp = d.layout.params.get("field.density_mlp").unwrap().range();
                let expect_big = if quant == QuantMode::F32 {
                    1e6
                } else {
                    65504.0
                };
                assert_eq!(d.params[mlp.start], expect_big, "{quant}");
                let h3 = d.layout.params.get("field.h3").unwrap().range();
                assert_eq!(d.params[h3.start], 7.25, "{quant}");
                for t in [0.0f32, 1.0, 0.5] {
                    let at = d.params_for_time(t);
                    assert!(at.iter().all(|v| v.is_finite()));
                }
            }
        }
    }
}

mod selection {
    use msth_codec::dynamic_rows::{reached_rows, DynamicRegion};
    use msth_core::grid::{GridConfig, GridLayout};
    use msth_core::rng::Rng;

    /// Finest resolution 2^16 per spatial axis and 10,000 time cells: every row a point of the
    /// dynamic region reads in a time span (including `t` exactly 0 and 1) is selected, and the
    /// selection stays inside the table.
    #[test]
    fn selection_at_finest_2_16_covers_every_row_read() {
        let cfg = GridConfig {
            levels: 4,
            features_per_level: 2,
            log2_table_size: 14,
            base_resolution: vec![16.0, 16.0, 16.0, 15.0],
            finest_resolution: vec![65536.0, 65536.0, 65536.0, 10_000.0],
        };
        cfg.validate("t").unwrap();
        let grid = GridLayout::new(&cfg);
        let region = DynamicRegion {
            boxes: vec![
                [[0.5, 0.5 + 1.0 / 1023.0], [0.25, 0.26], [0.0, 0.001]],
                [[1.0 - 1e-4, 1.0], [1.0 - 1e-4, 1.0], [1.0 - 1e-4, 1.0]],
            ],
            voxels: None,
        };
        let mut rng = Rng::new(3);
        for (t0, t1) in [(0.0f32, 0.001f32), (0.3, 0.55), (0.999, 1.0)] {
            let sel: Vec<Vec<u32>> = (0..4)
                .map(|l| reached_rows(&grid, l, &region, t0, t1))
                .collect();
            for (l, rows) in sel.iter().enumerate() {
                assert!(rows.iter().all(|&r| (r as usize) < grid.levels[l].rows));
            }
            for k in 0..4000 {
                let b = &region.boxes[k % 2];
                let mut x: Vec<f32> = (0..3)
                    .map(|a| b[a][0] + (b[a][1] - b[a][0]) * rng.f32())
                    .collect();
                x.push(match k % 4 {
                    0 => t0,
                    1 => t1,
                    _ => t0 + (t1 - t0) * rng.f32(),
                });
                grid.visit_rows(&x, |l, row| {
                    assert!(
                        sel[l].binary_search(&(row as u32)).is_ok(),
                        "level {l} row {row} at {x:?} not selected"
                    );
                });
            }
        }
    }
}
