//! A reader for the small NumPy `.npy` arrays datasets ship (`poses_bounds.npy`): format
//! versions 1-3, little- or big-endian `f4`/`f8`, C or Fortran order, any number of dimensions.
//! Everything is checked against the file's length before anything is allocated.

use std::path::Path;

use crate::DatasetError;

/// Largest accepted array (elements); pose files are tiny.
const MAX_ELEMENTS: usize = 1 << 24;

/// A 2-D or N-D array of `f64` in C (row-major) order.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

/// What is wrong with the bytes of a `.npy` file ([`parse`]).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum NpyError {
    #[error("missing the \\x93NUMPY magic")]
    Magic,
    #[error("truncated header")]
    TruncatedHeader,
    #[error("unsupported format version {0}")]
    Version(u8),
    #[error("header of {header_len} bytes runs past the end of the file ({file_len} bytes)")]
    HeaderPastEnd { header_len: usize, file_len: usize },
    #[error("the header is not text")]
    HeaderNotText,
    #[error("dtype `{0}`: expected float32 or float64")]
    Dtype(String),
    #[error("fortran_order `{0}` is not True/False")]
    FortranOrder(String),
    #[error("shape `{0}` is not a tuple")]
    ShapeNotTuple(String),
    #[error("shape `{shape}`: `{part}` is not a size")]
    ShapeSize { shape: String, part: String },
    #[error("shape {shape:?} is too large")]
    TooLarge { shape: Vec<usize> },
    #[error("shape {shape:?} of {descr} needs {needed} bytes of data but the file holds {held} (truncated or padded)")]
    Payload {
        shape: Vec<usize>,
        descr: String,
        needed: usize,
        held: usize,
    },
    #[error("the header has no `{0}`")]
    MissingKey(String),
    #[error("malformed header near `{0}`")]
    MalformedNear(String),
}

/// Reads `path` (see the module docs).
pub fn read(path: &Path) -> Result<Array, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse(&bytes).map_err(|source| DatasetError::Npy {
        path: path.to_path_buf(),
        source,
    })
}

/// Parses the bytes of a `.npy` file.
pub fn parse(bytes: &[u8]) -> Result<Array, NpyError> {
    if bytes.len() < 10 || &bytes[0..6] != b"\x93NUMPY" {
        return Err(NpyError::Magic);
    }
    let major = bytes[6];
    let (header_len, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10usize),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(NpyError::TruncatedHeader);
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(NpyError::Version(v)),
    };
    let end = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or(NpyError::HeaderPastEnd {
            header_len,
            file_len: bytes.len(),
        })?;
    let header = std::str::from_utf8(&bytes[start..end]).map_err(|_| NpyError::HeaderNotText)?;
    let descr = dict_value(header, "descr")?;
    let descr = descr.trim_matches(|c| c == '\'' || c == '"');
    let (big, size) = match descr {
        "<f8" | "=f8" | "float64" => (false, 8),
        ">f8" => (true, 8),
        "<f4" | "=f4" | "float32" => (false, 4),
        ">f4" => (true, 4),
        d => return Err(NpyError::Dtype(d.to_string())),
    };
    let fortran = match dict_value(header, "fortran_order")?.as_str() {
        "True" => true,
        "False" => false,
        v => return Err(NpyError::FortranOrder(v.to_string())),
    };
    let shape_s = dict_value(header, "shape")?;
    let inner = shape_s
        .strip_prefix('(')
        .and_then(|s| s.strip_suffix(')'))
        .ok_or_else(|| NpyError::ShapeNotTuple(shape_s.clone()))?;
    let mut shape = Vec::new();
    for part in inner.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        shape.push(part.parse::<usize>().map_err(|_| NpyError::ShapeSize {
            shape: shape_s.clone(),
            part: part.to_string(),
        })?);
    }
    let n = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .filter(|&n| n <= MAX_ELEMENTS)
        .ok_or_else(|| NpyError::TooLarge {
            shape: shape.clone(),
        })?;
    let payload = &bytes[end..];
    if payload.len() != n * size {
        return Err(NpyError::Payload {
            shape,
            descr: descr.to_string(),
            needed: n * size,
            held: payload.len(),
        });
    }
    let mut data: Vec<f64> = payload
        .chunks_exact(size)
        .map(|c| match (size, big) {
            (8, false) => f64::from_le_bytes(c.try_into().unwrap_or([0; 8])),
            (8, true) => f64::from_be_bytes(c.try_into().unwrap_or([0; 8])),
            (_, false) => f32::from_le_bytes(c.try_into().unwrap_or([0; 4])) as f64,
            (_, true) => f32::from_be_bytes(c.try_into().unwrap_or([0; 4])) as f64,
        })
        .collect();
    if fortran && shape.len() > 1 {
        // Column-major to row-major.
        let mut out = vec![0.0; n];
        let mut idx = vec![0usize; shape.len()];
        for x in out.iter_mut() {
            // idx is the row-major multi-index of this element.
            let mut f = 0usize;
            let mut stride = 1usize;
            for (d, &i) in idx.iter().enumerate() {
                f += i * stride;
                stride *= shape[d];
            }
            *x = data[f];
            for d in (0..shape.len()).rev() {
                idx[d] += 1;
                if idx[d] < shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        data = out;
    }
    Ok(Array { shape, data })
}

/// The raw text of `key`'s value in the header's Python dict literal.
fn dict_value(header: &str, key: &str) -> Result<String, NpyError> {
    let pat_a = format!("'{key}'");
    let pat_b = format!("\"{key}\"");
    let at = header
        .find(&pat_a)
        .map(|i| i + pat_a.len())
        .or_else(|| header.find(&pat_b).map(|i| i + pat_b.len()))
        .ok_or_else(|| NpyError::MissingKey(key.to_string()))?;
    let rest = header[at..].trim_start();
    let rest = rest
        .strip_prefix(':')
        .ok_or_else(|| NpyError::MalformedNear(key.to_string()))?
        .trim_start();
    let end = if rest.starts_with('(') {
        rest.find(')').map(|i| i + 1)
    } else {
        rest.find([',', '}'])
    }
    .ok_or_else(|| NpyError::MalformedNear(key.to_string()))?;
    Ok(rest[..end].trim().to_string())
}

/// Writes a C-order little-endian `f8` array (used by tests and tools to make fixtures).
pub fn write_f64(path: &Path, shape: &[usize], data: &[f64]) -> std::io::Result<()> {
    std::fs::write(path, encode_f64(shape, data))
}

/// The bytes of a C-order little-endian `f8` `.npy` file (version 1).
pub fn encode_f64(shape: &[usize], data: &[f64]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let tuple = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {tuple}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_orders() {
        let data: Vec<f64> = (0..6).map(|i| i as f64 * 0.5).collect();
        let a = parse(&encode_f64(&[2, 3], &data)).unwrap();
        assert_eq!(a.shape, [2, 3]);
        assert_eq!(a.data, data);
        // Fortran order and float32, big-endian.
        let mut header = "{'descr': '>f4', 'fortran_order': True, 'shape': (2, 3), }".to_string();
        header.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend_from_slice(&(header.len() as u16).to_le_bytes());
        b.extend_from_slice(header.as_bytes());
        // column-major of [[0, 1, 2], [3, 4, 5]]: 0 3 1 4 2 5
        for v in [0.0f32, 3.0, 1.0, 4.0, 2.0, 5.0] {
            b.extend_from_slice(&v.to_be_bytes());
        }
        let a = parse(&b).unwrap();
        assert_eq!(a.data, [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    }

    fn replace(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
        let at = bytes
            .windows(from.len())
            .position(|w| w == from.as_bytes())
            .unwrap();
        let mut out = bytes[..at].to_vec();
        out.extend_from_slice(to.as_bytes());
        out.extend_from_slice(&bytes[at + from.len()..]);
        out
    }

    fn raw(header: &str) -> Vec<u8> {
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend_from_slice(&(header.len() as u16).to_le_bytes());
        b.extend_from_slice(header.as_bytes());
        b
    }

    #[test]
    fn broken_files_are_named() {
        let good = encode_f64(&[2, 3], &[1.0; 6]);
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (good[..good.len() - 3].to_vec(), "truncated"),
            (b"PK\x03\x04 not numpy".to_vec(), "magic"),
            (good[..20].to_vec(), "runs past"),
            (replace(&good, "<f8", "<i8"), "dtype"),
            (replace(&good, "(2, 3)", "(2,,x)"), "not a size"),
            (
                raw("{'descr': '<f8', 'fortran_order': False, 'shape': (9999999999999, 99999), }"),
                "too large",
            ),
            (replace(&good, "False", "Maybe"), "fortran_order"),
        ];
        for (bytes, needle) in cases {
            let e = parse(&bytes).unwrap_err();
            assert!(
                e.to_string().contains(needle),
                "{e} should mention {needle}"
            );
        }
    }
}
