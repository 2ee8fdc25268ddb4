//! Pieces of the DyNeRF / LLFF on-disk layout: `poses_bounds.npy` rows ([`llff_row`], [`write_npy`],
//! [`read_npy`]) and per-camera H.264 videos through ffmpeg ([`encode_video`]).
//!
//! LLFF row convention (as in `shared/data/box_animated_stage/README.md`): a row-major 3x5
//! matrix `[R | t | hwf]` then `near, far`; the columns of `R` are `[-Y, X, Z]` of the OpenGL
//! camera-to-world matrix (LLFF's down, right, backwards axes), `t` is the camera centre and
//! `hwf = (height, width, focal in pixels)`. The standard LLFF loader step
//! `poses = cat([p[:,1:2], -p[:,0:1], p[:,2:]], 1)` recovers the OpenGL matrix.

use std::io::Write;
use std::path::Path;
use std::process::Command;

use glam::{Mat4, Vec3};
use msth_core::Camera;

use crate::error::{Result, SceneGenError};

/// The 17 values of one `poses_bounds.npy` row for `camera`.
pub fn llff_row(camera: &Camera, near: f64, far: f64) -> [f64; 17] {
    let m = camera.world_from_camera;
    let x = m.x_axis.truncate();
    let y = m.y_axis.truncate();
    let z = m.z_axis.truncate();
    let t = m.w_axis.truncate();
    let hwf = [camera.height as f64, camera.width as f64, camera.fx as f64];
    let mut row = [0.0f64; 17];
    for r in 0..3 {
        row[r * 5] = -y[r] as f64;
        row[r * 5 + 1] = x[r] as f64;
        row[r * 5 + 2] = z[r] as f64;
        row[r * 5 + 3] = t[r] as f64;
        row[r * 5 + 4] = hwf[r];
    }
    row[15] = near;
    row[16] = far;
    row
}

/// The OpenGL camera-to-world matrix of an LLFF row (the inverse of [`llff_row`]'s pose part).
pub fn c2w_from_llff_row(row: &[f64; 17]) -> Mat4 {
    let col = |c: usize| Vec3::new(row[c] as f32, row[5 + c] as f32, row[10 + c] as f32);
    let (down, right, back, t) = (col(0), col(1), col(2), col(3));
    Mat4::from_cols(
        right.extend(0.0),
        (-down).extend(0.0),
        back.extend(0.0),
        t.extend(1.0),
    )
}

/// Writes a 2-D little-endian float64 C-order `.npy` file (format version 1.0).
pub fn write_npy(path: &Path, rows: &[[f64; 17]]) -> Result<()> {
    let mut header = format!(
        "{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, 17), }}",
        rows.len()
    );
    // Magic (6) + version (2) + length (2) + header, padded with spaces to a multiple of 64,
    // ending in a newline.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut bytes = Vec::with_capacity(10 + header.len() + rows.len() * 17 * 8);
    bytes.extend_from_slice(b"\x93NUMPY\x01\x00");
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for row in rows {
        for v in row {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    let mut f = std::fs::File::create(path).map_err(SceneGenError::io(path))?;
    f.write_all(&bytes).map_err(SceneGenError::io(path))
}

/// Reads back an `N x 17` float64 `.npy` written by [`write_npy`] (or numpy with the same
/// dtype and order).
pub fn read_npy(path: &Path) -> Result<Vec<[f64; 17]>> {
    let bytes = std::fs::read(path).map_err(SceneGenError::io(path))?;
    let bad = |m: &str| SceneGenError::Format {
        path: path.to_path_buf(),
        message: m.to_string(),
    };
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" || bytes[6] != 1 {
        return Err(bad("not a version 1 .npy file"));
    }
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = bytes
        .get(10..10 + hlen)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| bad("truncated header"))?;
    if !header.contains("'descr': '<f8'") || !header.contains("'fortran_order': False") {
        return Err(bad("expected little-endian float64 in C order"));
    }
    let shape = header
        .split("'shape': (")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .ok_or_else(|| bad("no shape"))?;
    let dims: Vec<usize> = shape
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().map_err(|_| bad("bad shape")))
        .collect::<Result<_>>()?;
    if dims.len() != 2 || dims[1] != 17 {
        return Err(bad("expected shape (N, 17)"));
    }
    let data = &bytes[10 + hlen..];
    if data.len() != dims[0] * 17 * 8 {
        return Err(bad("data length does not match the shape"));
    }
    Ok(data
        .chunks_exact(17 * 8)
        .map(|r| {
            let mut row = [0.0; 17];
            for (k, v) in row.iter_mut().enumerate() {
                *v = f64::from_le_bytes(r[k * 8..k * 8 + 8].try_into().expect("8 bytes"));
            }
            row
        })
        .collect())
}

/// Whether `ffmpeg` runs (`ffmpeg -version` succeeds).
pub fn ffmpeg_available(ffmpeg: &Path) -> bool {
    Command::new(ffmpeg)
        .arg("-version")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .map(|s| s.success())
        .unwrap_or(false)
}

/// Encodes `frames_dir/%04d.png` into `output` (H.264 through libx264, yuv420p, CRF 12,
/// `fps` frames per second; odd sizes are padded by one pixel, which yuv420p requires).
pub fn encode_video(ffmpeg: &Path, frames_dir: &Path, output: &Path, fps: u32) -> Result<()> {
    let pattern = frames_dir.join("%04d.png");
    let result = Command::new(ffmpeg)
        .args([
            "-nostdin",
            "-hide_banner",
            "-loglevel",
            "error",
            "-y",
            "-framerate",
        ])
        .arg(fps.to_string())
        .arg("-i")
        .arg(&pattern)
        .args([
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
            "-crf",
            "12",
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-movflags",
            "+faststart",
        ])
        .arg(output)
        .output()
        .map_err(SceneGenError::io(ffmpeg))?;
    if !result.status.success() {
        let err = String::from_utf8_lossy(&result.stderr);
        let tail: String = err.lines().rev().take(5).collect::<Vec<_>>().join(" | ");
        return Err(SceneGenError::Ffmpeg {
            path: output.to_path_buf(),
            message: format!("{} ({tail})", result.status),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn llff_row_round_trips_and_matches_the_shared_convention() {
        let cam = Camera::look_at(
            200,
            150,
            0.95,
            Vec3::new(0.0, -4.3, 1.55),
            Vec3::new(0.0, 0.3, 0.9),
            Vec3::Z,
        );
        let row = llff_row(&cam, 2.5, 9.0);
        // Shared box_animated_stage row 0 (same camera): R row 0 = [-0, 1, -0], hwf = 150, 200, f.
        assert_eq!(&row[0..5], &[-0.0, 1.0, -0.0, 0.0, 150.0]);
        assert_eq!(row[9], 200.0);
        assert!((row[14] - 194.449587).abs() < 1e-3);
        assert!((row[5] + 0.139914).abs() < 1e-5 && (row[7] + 0.990164).abs() < 1e-5);
        let back = c2w_from_llff_row(&row);
        assert!(back.abs_diff_eq(cam.world_from_camera, 1e-6));
        // The LLFF loader step [p1, -p0, p2] gives the OpenGL axes.
        let p = |r: usize, c: usize| row[r * 5 + c];
        for r in 0..3 {
            assert_eq!(p(r, 1) as f32, cam.world_from_camera.x_axis[r]);
            assert_eq!(-p(r, 0) as f32, cam.world_from_camera.y_axis[r]);
        }
    }

    #[test]
    fn npy_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.npy");
        let rows: Vec<[f64; 17]> = (0..3)
            .map(|i| std::array::from_fn(|k| (i * 17 + k) as f64 * 0.5))
            .collect();
        write_npy(&path, &rows).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        // Header + data is a multiple of 64 before the data, as numpy writes it.
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        assert_eq!(read_npy(&path).unwrap(), rows);
    }
}
