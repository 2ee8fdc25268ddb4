//! Bounds-checked reading of glTF accessors (including sparse ones) into plain vectors.
//!
//! The `gltf` crate validates indices between objects but not byte ranges; everything here checks
//! that every byte it touches lies inside its buffer view and buffer, so a malformed file gives a
//! [`SceneGenError::Invalid`] naming the accessor, never a panic. Allocations are bounded by the
//! buffer sizes (an accessor cannot claim more elements than its bytes can hold).

use std::path::Path;

use gltf::accessor::{DataType, Dimensions};

use crate::error::{Result, SceneGenError};

/// The raw bytes of every buffer of a document, indexed like `document.buffers()`.
pub struct Buffers(pub Vec<Vec<u8>>);

fn invalid(path: &Path, what: String, message: impl Into<String>) -> SceneGenError {
    SceneGenError::Invalid {
        path: path.to_path_buf(),
        what,
        message: message.into(),
    }
}

fn component_count(d: Dimensions) -> usize {
    d.multiplicity()
}

/// Reads one component of type `ty` at `bytes[at..]` (little endian) as `f64`, raw (not
/// normalised).
fn read_component(bytes: &[u8], at: usize, ty: DataType) -> f64 {
    match ty {
        DataType::I8 => bytes[at] as i8 as f64,
        DataType::U8 => bytes[at] as f64,
        DataType::I16 => i16::from_le_bytes([bytes[at], bytes[at + 1]]) as f64,
        DataType::U16 => u16::from_le_bytes([bytes[at], bytes[at + 1]]) as f64,
        DataType::U32 => {
            u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]) as f64
        }
        DataType::F32 => {
            f32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]) as f64
        }
    }
}

/// The normalised value of an integer component (glTF 2.0 section 3.11), or the value itself.
fn normalise(v: f64, ty: DataType) -> f64 {
    match ty {
        DataType::I8 => (v / 127.0).max(-1.0),
        DataType::U8 => v / 255.0,
        DataType::I16 => (v / 32767.0).max(-1.0),
        DataType::U16 => v / 65535.0,
        DataType::U32 => v / 4294967295.0,
        DataType::F32 => v,
    }
}

/// The byte slice of a buffer view, checked against its buffer.
fn view_bytes<'b>(
    path: &Path,
    what: &str,
    view: &gltf::buffer::View,
    buffers: &'b Buffers,
) -> Result<&'b [u8]> {
    let buffer = buffers.0.get(view.buffer().index()).ok_or_else(|| {
        invalid(
            path,
            what.to_string(),
            format!("buffer {} is missing", view.buffer().index()),
        )
    })?;
    let start = view.offset();
    let end = start.saturating_add(view.length());
    buffer.get(start..end).ok_or_else(|| {
        invalid(
            path,
            format!("{what} (bufferView {})", view.index()),
            format!(
                "bytes {start}..{end} lie outside buffer {} of {} bytes",
                view.buffer().index(),
                buffer.len()
            ),
        )
    })
}

/// Checks that `count` elements of `elem_size` bytes at `offset` with `stride` fit in `len`
/// bytes; returns the stride actually used.
fn check_range(
    path: &Path,
    what: &str,
    offset: usize,
    count: usize,
    elem_size: usize,
    stride: Option<usize>,
    len: usize,
) -> Result<usize> {
    let stride = stride.unwrap_or(elem_size);
    if stride < elem_size {
        return Err(invalid(
            path,
            what.to_string(),
            format!("byteStride {stride} is smaller than the element size {elem_size}"),
        ));
    }
    if count == 0 {
        return Ok(stride);
    }
    let end = (count - 1)
        .checked_mul(stride)
        .and_then(|v| v.checked_add(offset))
        .and_then(|v| v.checked_add(elem_size));
    match end {
        Some(end) if end <= len => Ok(stride),
        _ => Err(invalid(
            path,
            what.to_string(),
            format!(
                "{count} elements of {elem_size} bytes (stride {stride}) from byte {offset} \
                 run past the end of its buffer view ({len} bytes)"
            ),
        )),
    }
}

/// Reads every element of `accessor` as `f64` components, `count * components` values, with
/// integer components normalised when the accessor says so (and `apply_normalised`).
pub fn read_f64(
    path: &Path,
    accessor: &gltf::Accessor,
    buffers: &Buffers,
    apply_normalised: bool,
) -> Result<Vec<f64>> {
    let what = match accessor.name() {
        Some(n) => format!("accessor {} ({n})", accessor.index()),
        None => format!("accessor {}", accessor.index()),
    };
    let ty = accessor.data_type();
    let n_comp = component_count(accessor.dimensions());
    let comp_size = ty.size();
    let count = accessor.count();
    if matches!(accessor.dimensions(), Dimensions::Mat2 | Dimensions::Mat3) && comp_size < 4 {
        return Err(SceneGenError::Unsupported {
            path: path.to_path_buf(),
            what,
            message: "matrices of 8- or 16-bit components (column padding)".into(),
        });
    }
    let elem_size = comp_size * n_comp;
    let mut out = match accessor.view() {
        Some(view) => {
            let bytes = view_bytes(path, &what, &view, buffers)?;
            let stride = check_range(
                path,
                &what,
                accessor.offset(),
                count,
                elem_size,
                view.stride(),
                bytes.len(),
            )?;
            let mut out = Vec::with_capacity(count * n_comp);
            for i in 0..count {
                let base = accessor.offset() + i * stride;
                for c in 0..n_comp {
                    out.push(read_component(bytes, base + c * comp_size, ty));
                }
            }
            out
        }
        None => {
            // No buffer view: all zeros (then usually overridden by sparse values). The count is
            // only trusted up to a limit, since no bytes back it.
            if count.saturating_mul(n_comp) > MAX_VIEWLESS_VALUES {
                return Err(invalid(
                    path,
                    what,
                    format!("{count} elements without a bufferView is implausibly many"),
                ));
            }
            vec![0.0; count * n_comp]
        }
    };
    if let Some(sparse) = accessor.sparse() {
        let n = sparse.count();
        let idx = sparse.indices();
        let idx_ty = match idx.index_type() {
            gltf::accessor::sparse::IndexType::U8 => DataType::U8,
            gltf::accessor::sparse::IndexType::U16 => DataType::U16,
            gltf::accessor::sparse::IndexType::U32 => DataType::U32,
        };
        let sw = format!("{what} sparse indices");
        let ibytes = view_bytes(path, &sw, &idx.view(), buffers)?;
        check_range(
            path,
            &sw,
            idx.offset(),
            n,
            idx_ty.size(),
            None,
            ibytes.len(),
        )?;
        let vw = format!("{what} sparse values");
        let values = sparse.values();
        let vbytes = view_bytes(path, &vw, &values.view(), buffers)?;
        check_range(path, &vw, values.offset(), n, elem_size, None, vbytes.len())?;
        for k in 0..n {
            let target = read_component(ibytes, idx.offset() + k * idx_ty.size(), idx_ty) as usize;
            if target >= count {
                return Err(invalid(
                    path,
                    sw,
                    format!("index {target} is out of range (count {count})"),
                ));
            }
            for c in 0..n_comp {
                out[target * n_comp + c] =
                    read_component(vbytes, values.offset() + k * elem_size + c * comp_size, ty);
            }
        }
    }
    if apply_normalised && accessor.normalized() {
        for v in &mut out {
            *v = normalise(*v, ty);
        }
    }
    Ok(out)
}

/// Largest number of values accepted for an accessor that has no buffer view.
const MAX_VIEWLESS_VALUES: usize = 1 << 24;

/// Reads a float accessor that must have `n_comp` components per element; integer components
/// are normalised when the accessor is `normalized` (glTF allows that for colours, UVs, weights).
pub fn read_floats(
    path: &Path,
    accessor: &gltf::Accessor,
    buffers: &Buffers,
    n_comp: usize,
    what: &str,
) -> Result<Vec<f32>> {
    let got = component_count(accessor.dimensions());
    if got != n_comp {
        return Err(invalid(
            path,
            format!("{what} (accessor {})", accessor.index()),
            format!("expected {n_comp} components per element, found {got}"),
        ));
    }
    let raw = read_f64(path, accessor, buffers, true)?;
    let mut out = Vec::with_capacity(raw.len());
    for (i, v) in raw.into_iter().enumerate() {
        if !v.is_finite() {
            return Err(invalid(
                path,
                format!("{what} (accessor {})", accessor.index()),
                format!("element {} is not finite ({v})", i / n_comp),
            ));
        }
        out.push(v as f32);
    }
    Ok(out)
}

/// Reads an unsigned integer accessor (indices, joints) of `n_comp` components.
pub fn read_uints(
    path: &Path,
    accessor: &gltf::Accessor,
    buffers: &Buffers,
    n_comp: usize,
    what: &str,
) -> Result<Vec<u32>> {
    let got = component_count(accessor.dimensions());
    let w = format!("{what} (accessor {})", accessor.index());
    if got != n_comp {
        return Err(invalid(
            path,
            w,
            format!("expected {n_comp} components per element, found {got}"),
        ));
    }
    if !matches!(
        accessor.data_type(),
        DataType::U8 | DataType::U16 | DataType::U32
    ) {
        return Err(invalid(
            path,
            w,
            format!(
                "expected unsigned integer components, found {:?}",
                accessor.data_type()
            ),
        ));
    }
    Ok(read_f64(path, accessor, buffers, false)?
        .into_iter()
        .map(|v| v as u32)
        .collect())
}
