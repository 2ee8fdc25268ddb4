//! Pieces of the DyNeRF / LLFF on-disk layout as the generator uses them: `poses_bounds.npy` rows
//! ([`llff_row`], [`write_npy`], [`read_npy`]) and per-camera H.264 videos ([`encode_video`]),
//! each a thin layer over `msth_dataset` (its `dynerf`, `npy` and `video` modules), which reads
//! and writes the format.
//!
//! LLFF row convention (as in `shared/data/box_animated_stage/README.md`): a row-major 3x5
//! matrix `[R | t | hwf]` then `near, far`; the columns of `R` are `[-Y, X, Z]` of the OpenGL
//! camera-to-world matrix (LLFF's down, right, backwards axes), `t` is the camera centre and
//! `hwf = (height, width, focal in pixels)`. The standard LLFF loader step
//! `poses = cat([p[:,1:2], -p[:,0:1], p[:,2:]], 1)` recovers the OpenGL matrix.

use std::path::Path;

use msth_dataset::npy;
use msth_dataset::video::{self, EncodeError};

pub use msth_dataset::dynerf::{c2w_from_llff_row, llff_row};

use crate::error::{Result, SceneGenError};

/// Writes the rows as a 2-D little-endian float64 C-order `.npy` file (format version 1.0).
pub fn write_npy(path: &Path, rows: &[[f64; 17]]) -> Result<()> {
    let data: Vec<f64> = rows.iter().flatten().copied().collect();
    npy::write_f64(path, &[rows.len(), 17], &data).map_err(SceneGenError::io(path))
}

/// Reads back an `N x 17` float64 `.npy` written by [`write_npy`] (or numpy with the same
/// dtype and order).
pub fn read_npy(path: &Path) -> Result<Vec<[f64; 17]>> {
    let a = npy::read(path)?;
    if a.shape.len() != 2 || a.shape[1] != 17 {
        return Err(SceneGenError::Format {
            path: path.to_path_buf(),
            message: "expected shape (N, 17)".into(),
        });
    }
    Ok(a.data
        .chunks_exact(17)
        .map(|r| r.try_into().expect("17 values"))
        .collect())
}

/// Whether `ffmpeg` runs (`ffmpeg -version` succeeds).
pub fn ffmpeg_available(ffmpeg: &Path) -> bool {
    video::runs(ffmpeg)
}

/// Encodes `frames_dir/%04d.png` into `output` (H.264 through libx264, yuv420p, CRF 12,
/// `fps` frames per second; odd sizes are padded by one pixel, which yuv420p requires).
pub fn encode_video(ffmpeg: &Path, frames_dir: &Path, output: &Path, fps: u32) -> Result<()> {
    let pattern = frames_dir.join("%04d.png");
    video::encode_png_sequence(ffmpeg, &pattern, fps as f32, 12, output).map_err(|e| match e {
        EncodeError::NotInstalled { program } => SceneGenError::Io {
            path: program,
            error: std::io::ErrorKind::NotFound.into(),
        },
        EncodeError::Spawn { program, source } => SceneGenError::Io {
            path: program,
            error: source,
        },
        e @ EncodeError::Failed { .. } => SceneGenError::Ffmpeg {
            path: output.to_path_buf(),
            message: e.to_string(),
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use msth_core::Camera;

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
