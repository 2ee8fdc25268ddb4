//! Value blocks: how a run of `f32` values is stored inside a section (format.md §5), and the
//! little-endian byte reader/writer the sections are built from.
//!
//! A block is `encoding: u8, bits: u8, reserved: u16 = 0, count: u32`, then for the affine
//! encoding `min: f32, scale: f32`, then the payload: `f32` and `f16` values as byte planes (all
//! first bytes, then all second bytes, ...: zstd compresses the exponent plane well), affine codes
//! packed LSB-first, `bits` per value, decoded as `min + code * scale` in `f32`.

use half::f16;

use crate::error::DecodeError;

/// How the values of one block are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BlockEncoding {
    F32,
    F16,
    /// Per-block affine quantisation to `bits` (1..=8) bits.
    Affine {
        bits: u8,
    },
    /// Per-block codebook of `2^bits` values (1..=8 bits), fitted by Lloyd-Max (1D k-means).
    Codebook {
        bits: u8,
    },
}

pub const ENC_F32: u8 = 0;
pub const ENC_F16: u8 = 1;
pub const ENC_AFFINE: u8 = 2;
pub const ENC_CODEBOOK: u8 = 3;
/// Codes stored as they are.
pub const PRED_NONE: u8 = 0;
/// Codes stored as differences from the previous code, mod 256 (the first from 0).
pub const PRED_DELTA: u8 = 1;
/// Bytes of a block header (affine blocks add 8).
pub const BLOCK_HEADER: usize = 8;

/// Appends little-endian values to a byte vector.
#[derive(Default)]
pub struct Writer {
    pub bytes: Vec<u8>,
}

impl Writer {
    pub fn u8(&mut self, v: u8) {
        self.bytes.push(v);
    }
    pub fn u16(&mut self, v: u16) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    pub fn u32(&mut self, v: u32) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    pub fn u64(&mut self, v: u64) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f32(&mut self, v: f32) {
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }
    /// Unsigned LEB128.
    pub fn varint(&mut self, mut v: u32) {
        loop {
            let b = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                self.bytes.push(b);
                return;
            }
            self.bytes.push(b | 0x80);
        }
    }

    /// Writes one block of `values` in `enc`.
    pub fn block(&mut self, values: &[f32], enc: BlockEncoding) {
        let n = values.len();
        let header = |w: &mut Writer, e: u8, bits: u8, predictor: u8| {
            w.u8(e);
            w.u8(bits);
            w.u8(predictor);
            w.u8(0);
            w.u32(n as u32);
        };
        match enc {
            BlockEncoding::F32 => {
                header(self, ENC_F32, 0, PRED_NONE);
                let words: Vec<[u8; 4]> = values.iter().map(|v| v.to_le_bytes()).collect();
                for plane in 0..4 {
                    self.bytes.extend(words.iter().map(|w| w[plane]));
                }
            }
            BlockEncoding::F16 => {
                header(self, ENC_F16, 0, PRED_NONE);
                let words: Vec<[u8; 2]> = values
                    .iter()
                    .map(|&v| f16::from_f32(v.clamp(-65504.0, 65504.0)).to_le_bytes())
                    .collect();
                for plane in 0..2 {
                    self.bytes.extend(words.iter().map(|w| w[plane]));
                }
            }
            BlockEncoding::Affine { bits } => {
                let (min, scale) = affine_params(values, bits);
                let max_code = (1u32 << bits) - 1;
                let codes: Vec<u8> = values
                    .iter()
                    .map(|&v| {
                        if scale > 0.0 {
                            (((v - min) / scale).round() as i64).clamp(0, max_code as i64) as u8
                        } else {
                            0
                        }
                    })
                    .collect();
                let (predictor, stored) = choose_predictor(codes);
                header(self, ENC_AFFINE, bits, predictor);
                self.f32(min);
                self.f32(scale);
                self.bytes.extend_from_slice(&stored);
            }
            BlockEncoding::Codebook { bits } => {
                let book = lloyd_max(values, bits);
                // Decision thresholds: midpoints between neighbouring (sorted) entries, in f64:
                // `0.5 * (a + b)` in f32 overflows to infinity for entries near f32::MAX, which
                // sent every value to the lower entry (stability suite, docs/stability.md).
                let mids: Vec<f64> = book.windows(2).map(|w| midpoint(w[0], w[1])).collect();
                let codes: Vec<u8> = values
                    .iter()
                    .map(|&v| mids.partition_point(|&m| m < v as f64) as u8)
                    .collect();
                let (predictor, stored) = choose_predictor(codes);
                header(self, ENC_CODEBOOK, bits, predictor);
                for &c in &book {
                    self.f32(c);
                }
                self.bytes.extend_from_slice(&stored);
            }
        }
    }
}

/// Order-0 entropy of a byte string, bits (the cost zstd's Huffman stage approaches).
fn entropy_bits(bytes: &[u8]) -> f64 {
    let mut hist = [0u64; 256];
    for &b in bytes {
        hist[b as usize] += 1;
    }
    let n = bytes.len() as f64;
    hist.iter()
        .filter(|&&c| c > 0)
        .map(|&c| -(c as f64) * (c as f64 / n).log2())
        .sum()
}

/// Keeps the codes as they are or replaces them by differences from the previous code (mod 256),
/// whichever has the lower order-0 entropy (smooth data such as the mask or dense levels).
fn choose_predictor(codes: Vec<u8>) -> (u8, Vec<u8>) {
    let mut prev = 0u8;
    let delta: Vec<u8> = codes
        .iter()
        .map(|&c| {
            let d = c.wrapping_sub(prev);
            prev = c;
            d
        })
        .collect();
    if entropy_bits(&delta) < 0.97 * entropy_bits(&codes) {
        (PRED_DELTA, delta)
    } else {
        (PRED_NONE, codes)
    }
}

/// A sorted codebook of `2^bits` entries minimising the squared error of `values` (Lloyd-Max:
/// quantile initialisation, then 25 rounds of "thresholds at midpoints, entries at means").
pub fn lloyd_max(values: &[f32], bits: u8) -> Vec<f32> {
    let k = 1usize << bits;
    if values.is_empty() {
        return vec![0.0; k];
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f32::total_cmp);
    let n = sorted.len();
    let mut prefix = Vec::with_capacity(n + 1);
    prefix.push(0f64);
    for &v in &sorted {
        prefix.push(prefix.last().copied().unwrap_or(0.0) + v as f64);
    }
    let mut book: Vec<f32> = (0..k)
        .map(|i| sorted[((2 * i + 1) * n / (2 * k)).min(n - 1)])
        .collect();
    for _ in 0..25 {
        let mut start = 0usize;
        for i in 0..k {
            let end = if i + 1 == k {
                n
            } else {
                let mid = midpoint(book[i], book[i + 1]);
                sorted.partition_point(|&v| v as f64 <= mid).max(start)
            };
            if end > start {
                book[i] = ((prefix[end] - prefix[start]) / (end - start) as f64) as f32;
            }
            start = end;
        }
        book.sort_by(f32::total_cmp);
    }
    book
}

/// The midpoint of two codebook entries, exact and without overflow.
#[inline]
fn midpoint(a: f32, b: f32) -> f64 {
    0.5 * (a as f64 + b as f64)
}

/// `(min, scale)` of the affine quantisation of `values` to `bits` bits.
///
/// The error is at most `scale / 2` (plus f32 rounding) for values in
/// `[min, min + (2^bits - 1) scale]`, which is the block's range `[lo, hi]` except in two extreme
/// cases: a spread `hi - lo` beyond `f32::MAX` (values of both signs near `±f32::MAX`) is narrowed
/// to `0.9998 f32::MAX` around the mid-range, the values outside clamping to its ends; and next
/// to `±f32::MAX` the top of the range may shrink by a few ulps so that decoding
/// (`min + code * scale` in f32) stays finite.
pub fn affine_params(values: &[f32], bits: u8) -> (f32, f32) {
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for &v in values {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !(lo.is_finite() && hi.is_finite()) {
        return (0.0, 0.0);
    }
    // `hi - lo` can overflow to infinity (e.g. -3e38..3e38), which used to give scale 0 and
    // collapse the whole block onto its minimum (stability suite, docs/stability.md).
    if !(hi - lo).is_finite() {
        let mid = 0.5 * lo + 0.5 * hi;
        // A little under f32::MAX / 2, so that rounding cannot push the new spread to infinity.
        let half = 0.4999 * f32::MAX;
        lo = lo.max(mid - half);
        hi = hi.min(mid + half);
    }
    let levels = ((1u32 << bits) - 1) as f32;
    let mut scale = (hi - lo) / levels;
    if !scale.is_finite() {
        return (lo, 0.0);
    }
    // The decoder computes the top code as `lo + levels * scale`; next to f32::MAX the rounding
    // of `scale` can push it to infinity, which the decoder rejects. Step `scale` down by ulps.
    while scale > 0.0 && !(lo + levels * scale).is_finite() {
        scale = f32::from_bits(scale.to_bits() - 1);
    }
    (lo, scale)
}

/// Reads little-endian values from a byte slice; every read is bounds-checked.
pub struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
    what: &'a str,
}

impl<'a> Reader<'a> {
    pub fn new(bytes: &'a [u8], what: &'a str) -> Self {
        Reader {
            bytes,
            pos: 0,
            what,
        }
    }
    pub fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }
    pub fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        if n > self.remaining() {
            return Err(DecodeError::malformed(
                self.what,
                format!(
                    "payload ends early: {n} bytes wanted at offset {}, {} left",
                    self.pos,
                    self.remaining()
                ),
            ));
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    pub fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.take(1)?[0])
    }
    pub fn u16(&mut self) -> Result<u16, DecodeError> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }
    pub fn u32(&mut self) -> Result<u32, DecodeError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    pub fn f32(&mut self) -> Result<f32, DecodeError> {
        Ok(f32::from_bits(self.u32()?))
    }
    pub fn varint(&mut self) -> Result<u32, DecodeError> {
        let mut v: u64 = 0;
        for i in 0..5 {
            let b = self.u8()?;
            v |= ((b & 0x7f) as u64) << (7 * i);
            if b & 0x80 == 0 {
                return u32::try_from(v).map_err(|_| {
                    DecodeError::malformed(self.what, "varint exceeds 32 bits".to_string())
                });
            }
        }
        Err(DecodeError::malformed(
            self.what,
            "varint longer than 5 bytes".to_string(),
        ))
    }
    /// Fails unless every byte was consumed.
    pub fn finish(&self) -> Result<(), DecodeError> {
        if self.remaining() != 0 {
            return Err(DecodeError::malformed(
                self.what,
                format!("{} unexpected trailing bytes", self.remaining()),
            ));
        }
        Ok(())
    }

    /// Reads one block that must hold exactly `expected` values into `out` (`out.len() ==
    /// expected`). Non-finite decoded values are rejected.
    pub fn block_into(
        &mut self,
        out: &mut [f32],
        what: &str,
    ) -> Result<BlockEncoding, DecodeError> {
        let expected = out.len();
        let enc = self.u8()?;
        let bits = self.u8()?;
        let predictor = self.u8()?;
        let reserved = self.u8()?;
        let count = self.u32()? as usize;
        let section = self.what;
        let bad = |m: String| DecodeError::malformed(format!("{section} ({what})"), m);
        if reserved != 0 {
            return Err(bad(format!(
                "reserved block byte is {reserved:#x}, must be 0"
            )));
        }
        if count != expected {
            return Err(bad(format!(
                "block holds {count} values, the model needs {expected}"
            )));
        }
        let quantised = enc == ENC_AFFINE || enc == ENC_CODEBOOK;
        if quantised && !(1..=8).contains(&bits) {
            return Err(bad(format!("bits must be in 1..=8 (got {bits})")));
        }
        if !quantised && (bits != 0 || predictor != PRED_NONE) && enc <= ENC_F16 {
            return Err(bad(format!(
                "bits and predictor must be 0 for float blocks (got {bits}, {predictor})"
            )));
        }
        if predictor > PRED_DELTA {
            return Err(DecodeError::Unsupported {
                what: format!("{section} ({what})"),
                message: format!("predictor {predictor}"),
            });
        }
        let encoding = match enc {
            ENC_F32 => {
                let b = self.take(count.checked_mul(4).ok_or_else(|| bad("overflow".into()))?)?;
                for (i, o) in out.iter_mut().enumerate() {
                    *o = f32::from_le_bytes([
                        b[i],
                        b[count + i],
                        b[2 * count + i],
                        b[3 * count + i],
                    ]);
                }
                BlockEncoding::F32
            }
            ENC_F16 => {
                let b = self.take(count.checked_mul(2).ok_or_else(|| bad("overflow".into()))?)?;
                for (i, o) in out.iter_mut().enumerate() {
                    *o = f16::from_le_bytes([b[i], b[count + i]]).to_f32();
                }
                BlockEncoding::F16
            }
            ENC_AFFINE | ENC_CODEBOOK => {
                let mut book = [0f32; 256];
                let k = 1usize << bits;
                if enc == ENC_AFFINE {
                    let min = self.f32()?;
                    let scale = self.f32()?;
                    if !(min.is_finite() && scale.is_finite() && scale >= 0.0) {
                        return Err(bad(format!(
                            "affine min {min} / scale {scale} must be finite, scale >= 0"
                        )));
                    }
                    for (code, v) in book.iter_mut().take(k).enumerate() {
                        *v = min + code as f32 * scale;
                    }
                } else {
                    for (i, c) in book.iter_mut().take(k).enumerate() {
                        *c = self.f32()?;
                        if !c.is_finite() {
                            return Err(bad(format!("codebook entry {i} is not finite")));
                        }
                    }
                }
                let b = self.take(count)?;
                let mut prev = 0u8;
                for (i, (o, &s)) in out.iter_mut().zip(b).enumerate() {
                    let code = if predictor == PRED_DELTA {
                        prev = prev.wrapping_add(s);
                        prev
                    } else {
                        s
                    };
                    if code as usize >= k {
                        return Err(bad(format!("code {code} of value {i} exceeds {bits} bits")));
                    }
                    *o = book[code as usize];
                }
                if enc == ENC_AFFINE {
                    BlockEncoding::Affine { bits }
                } else {
                    BlockEncoding::Codebook { bits }
                }
            }
            other => {
                return Err(DecodeError::Unsupported {
                    what: format!("{} ({what})", self.what),
                    message: format!("block encoding {other}"),
                })
            }
        };
        if let Some(i) = out.iter().position(|v| !v.is_finite()) {
            return Err(bad(format!("value {i} is not finite")));
        }
        Ok(encoding)
    }
}

/// Upper bound on the bytes of one block of `n` values (any encoding).
pub fn max_block_bytes(n: usize) -> u64 {
    (BLOCK_HEADER + 4 * 256) as u64 + 4 * n as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(values: &[f32], enc: BlockEncoding) -> Vec<f32> {
        let mut w = Writer::default();
        w.block(values, enc);
        let mut r = Reader::new(&w.bytes, "test");
        let mut out = vec![0f32; values.len()];
        assert_eq!(r.block_into(&mut out, "b").unwrap(), enc);
        r.finish().unwrap();
        out
    }

    #[test]
    fn blocks_round_trip_within_their_error() {
        let values: Vec<f32> = (0..1001).map(|i| ((i as f32) * 0.37).sin() * 3.0).collect();
        assert_eq!(round_trip(&values, BlockEncoding::F32), values);
        for (a, b) in round_trip(&values, BlockEncoding::F16).iter().zip(&values) {
            assert!((a - b).abs() <= 3.0 / 1024.0);
        }
        for bits in 1..=8u8 {
            let step = 6.0 / ((1u32 << bits) - 1) as f32;
            for (a, b) in round_trip(&values, BlockEncoding::Affine { bits })
                .iter()
                .zip(&values)
            {
                assert!((a - b).abs() <= 0.5 * step + 1e-5, "{bits}: {a} vs {b}");
            }
        }
        // A codebook is about as good as affine on uniform-ish data (it wins on peaked data).
        for bits in [2u8, 4, 6] {
            let err = |enc| {
                round_trip(&values, enc)
                    .iter()
                    .zip(&values)
                    .map(|(a, b)| ((a - b) as f64).powi(2))
                    .sum::<f64>()
            };
            let (k, a) = (
                err(BlockEncoding::Codebook { bits }),
                err(BlockEncoding::Affine { bits }),
            );
            assert!(k <= a * 1.5, "{bits}: codebook {k} vs affine {a}");
        }
        // A constant block has scale 0 and decodes exactly.
        assert_eq!(
            round_trip(&[0.25; 7], BlockEncoding::Affine { bits: 4 }),
            vec![0.25; 7]
        );
        assert!(round_trip(&[], BlockEncoding::Affine { bits: 3 }).is_empty());
        assert_eq!(
            round_trip(&[0.25; 7], BlockEncoding::Codebook { bits: 2 }),
            vec![0.25; 7]
        );
    }

    #[test]
    fn varints_round_trip_and_reject_overlong() {
        let mut w = Writer::default();
        for v in [0, 1, 127, 128, 300, u32::MAX] {
            w.varint(v);
        }
        let mut r = Reader::new(&w.bytes, "v");
        for v in [0, 1, 127, 128, 300, u32::MAX] {
            assert_eq!(r.varint().unwrap(), v);
        }
        let mut r = Reader::new(&[0xff, 0xff, 0xff, 0xff, 0x7f], "v");
        assert!(r.varint().is_err());
        let mut r = Reader::new(&[0x80; 6], "v");
        assert!(r.varint().is_err());
    }

    #[test]
    fn bad_blocks_fail() {
        let mut w = Writer::default();
        w.block(&[1.0, 2.0], BlockEncoding::Affine { bits: 8 });
        let mut nan = w.bytes.clone();
        nan[12..16].copy_from_slice(&f32::NAN.to_le_bytes());
        let mut out = [0f32; 2];
        assert!(Reader::new(&nan, "x").block_into(&mut out, "b").is_err());
        let mut wrong = [0f32; 3];
        assert!(Reader::new(&w.bytes, "x")
            .block_into(&mut wrong, "b")
            .is_err());
        assert!(Reader::new(&w.bytes[..w.bytes.len() - 1], "x")
            .block_into(&mut out, "b")
            .is_err());
    }
}
