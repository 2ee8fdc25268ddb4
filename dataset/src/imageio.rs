//! Image files and pictures for humans: PNG encoding ([`encode_png`], [`save_png_atomic`]),
//! per-pixel error maps ([`error_map`]) and side-by-side panels ([`panel`]) for
//! "ground truth | render | error" figures.
//!
//! Everything works on [`Image8`] (8-bit RGB, row 0 at the top).

use std::io::{self, Write};
use std::path::Path;

use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder};

use crate::undistort::{undistort_image, Distortion, Intrinsics};
use crate::{DatasetError, Image8};

/// Width in pixels of the white gap between the images of a [`panel`].
pub const PANEL_GAP: u32 = 2;

/// Gain applied to the mean absolute error before colour mapping in [`error_map`].
pub const ERROR_GAIN: f32 = 4.0;

/// Encodes `image` as an 8-bit RGB PNG into `writer`.
///
/// Fails with [`io::ErrorKind::InvalidInput`] when `image.data` does not hold
/// `width * height * 3` bytes or the image is empty.
pub fn encode_png<W: Write>(writer: W, image: &Image8) -> io::Result<()> {
    let expected = image.width as usize * image.height as usize * 3;
    if image.data.len() != expected || expected == 0 {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "image is {}x{} but holds {} bytes (expected {expected}, non-zero)",
                image.width,
                image.height,
                image.data.len()
            ),
        ));
    }
    PngEncoder::new(writer)
        .write_image(
            &image.data,
            image.width,
            image.height,
            ExtendedColorType::Rgb8,
        )
        .map_err(io::Error::other)
}

/// Writes `image` as a PNG at `path` atomically: the bytes go to a temporary file in the same
/// folder, which is synced and then renamed over `path`. Readers never see a half-written file;
/// on failure the temporary file is removed and `path` is left untouched.
pub fn save_png_atomic(path: &Path, image: &Image8) -> io::Result<()> {
    crate::staging::write_atomic_with(path, &mut |w| encode_png(w, image))
}

/// Key points of the colour map used by [`error_map`]: an approximation of matplotlib's
/// `inferno` (black, purple, red, orange, pale yellow) by linear segments.
const INFERNO: [[f32; 3]; 6] = [
    [0.0, 0.0, 0.016],
    [0.258, 0.039, 0.408],
    [0.576, 0.149, 0.404],
    [0.867, 0.317, 0.227],
    [0.988, 0.647, 0.039],
    [0.988, 1.0, 0.643],
];

/// Maps `x` in `[0, 1]` (clamped; NaN counts as 0) through the piecewise-linear inferno map.
pub fn colormap(x: f32) -> [f32; 3] {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    let segments = (INFERNO.len() - 1) as f32;
    let s = x * segments;
    let i = (s.floor() as usize).min(INFERNO.len() - 2);
    let f = s - i as f32;
    let (a, b) = (INFERNO[i], INFERNO[i + 1]);
    [
        a[0] + (b[0] - a[0]) * f,
        a[1] + (b[1] - a[1]) * f,
        a[2] + (b[2] - a[2]) * f,
    ]
}

/// Per-pixel error picture: the absolute difference averaged over the three channels, multiplied
/// by [`ERROR_GAIN`] (so an error of 0.25 already saturates), shown with [`colormap`].
///
/// If the two images differ in size the map covers their overlap (the smaller width and height);
/// it never panics.
pub fn error_map(gt: &Image8, pred: &Image8) -> Image8 {
    let width = gt.width.min(pred.width);
    let height = gt.height.min(pred.height);
    let mut rgb = Vec::with_capacity(width as usize * height as usize * 3);
    for y in 0..height {
        for x in 0..width {
            let ig = (y as usize * gt.width as usize + x as usize) * 3;
            let ip = (y as usize * pred.width as usize + x as usize) * 3;
            let (Some(a), Some(b)) = (gt.data.get(ig..ig + 3), pred.data.get(ip..ip + 3)) else {
                rgb.extend_from_slice(&[0.0; 3]);
                continue;
            };
            let err: f32 = a
                .iter()
                .zip(b)
                .map(|(&p, &q)| (p as f32 - q as f32).abs() / 255.0)
                .sum::<f32>()
                / 3.0;
            rgb.extend_from_slice(&colormap(err * ERROR_GAIN));
        }
    }
    Image8::from_f32(width, height, &rgb)
}

/// Concatenates images left to right with a [`PANEL_GAP`]-pixel white gap between them. Images of
/// different heights are top-aligned and padded with white. An empty list gives a 0x0 image.
pub fn panel(images: &[&Image8]) -> Image8 {
    if images.is_empty() {
        return Image8::new(0, 0);
    }
    let height = images.iter().map(|im| im.height).max().unwrap_or(0);
    let width =
        images.iter().map(|im| im.width).sum::<u32>() + PANEL_GAP * (images.len() as u32 - 1);
    let mut out = Image8 {
        width,
        height,
        data: vec![255; width as usize * height as usize * 3].into(),
    };
    let mut x0 = 0usize;
    for im in images {
        let row_bytes = im.width as usize * 3;
        for y in 0..im.height as usize {
            let src = y * row_bytes;
            let dst = (y * width as usize + x0) * 3;
            if let Some(row) = im.data.get(src..src + row_bytes) {
                out.data[dst..dst + row_bytes].copy_from_slice(row);
            }
        }
        x0 += im.width as usize + PANEL_GAP as usize;
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Reading dataset images

/// Area-filter (box) downscale of 8-bit RGB pixels of `width x height` by an integer factor;
/// the remainder of `size % factor` pixels at the right and bottom is cropped. Rounds to nearest.
pub fn downscale_rgb(rgb: &[u8], width: u32, height: u32, factor: u32) -> Vec<u8> {
    let f = factor.max(1) as usize;
    let (w, h) = (width as usize / f, height as usize / f);
    let n = (f * f) as u64;
    let mut out = vec![0u8; w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let mut acc = [0u64; 3];
            for dy in 0..f {
                let row = (y * f + dy) * width as usize;
                for dx in 0..f {
                    let i = (row + x * f + dx) * 3;
                    for c in 0..3 {
                        acc[c] += rgb[i + c] as u64;
                    }
                }
            }
            let o = (y * w + x) * 3;
            for c in 0..3 {
                out[o + c] = ((acc[c] + n / 2) / n) as u8;
            }
        }
    }
    out
}

/// Largest accepted image side (anything beyond is certainly a broken file).
pub const MAX_SIDE: u32 = 1 << 16;

/// An image read and prepared for the dataset.
pub struct LoadedImage {
    /// Size before downscaling.
    pub width: u32,
    pub height: u32,
    pub image: Image8,
    /// Some pixel had alpha < 255.
    pub transparent: bool,
    /// Alpha after downscaling, when the image had transparency.
    pub alpha: Option<Vec<u8>>,
}

/// Area-filter downscale by an integer factor; the remainder at the right/bottom is cropped.
pub fn downscale_box(img: &Image8, factor: u32) -> Image8 {
    if factor <= 1 {
        return img.clone();
    }
    Image8 {
        width: img.width / factor,
        height: img.height / factor,
        data: downscale_rgb(&img.data, img.width, img.height, factor).into(),
    }
}

/// Reads an image file, composites it on white and downscales it.
pub fn load_image(path: &Path, downscale: u32) -> Result<LoadedImage, DatasetError> {
    load_image_undistorted(path, downscale, None)
}

/// What [`load_image_undistorted`] needs to undistort an image of a given size: its pinhole
/// intrinsics and distortion model, or `None` to leave it as it is.
pub type UndistortFn<'a> = dyn Fn(u32, u32) -> Option<(Intrinsics, Distortion)> + 'a;

/// [`load_image`], undistorting the image to the pinhole camera first when `undistort` gives
/// intrinsics and a distortion model for the image's size (nerfstudio).
pub fn load_image_undistorted(
    path: &Path,
    downscale: u32,
    undistort: Option<&UndistortFn<'_>>,
) -> Result<LoadedImage, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let decoded = image::load_from_memory(&bytes).map_err(|e| DatasetError::Image {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let (width, height) = (decoded.width(), decoded.height());
    if width == 0 || height == 0 || width > MAX_SIDE || height > MAX_SIDE {
        return Err(DatasetError::Image {
            path: path.to_path_buf(),
            message: format!("unsupported image size {width}x{height}"),
        });
    }
    if width < downscale || height < downscale {
        return Err(DatasetError::Invalid {
            path: path.to_path_buf(),
            message: format!(
                "image {width}x{height} is smaller than the downscale factor {downscale}"
            ),
        });
    }
    let has_alpha = decoded.color().has_alpha();
    let mut rgba = decoded.to_rgba8();
    if let Some(undistort) = undistort {
        if let Some((pin, d)) = undistort(width, height) {
            // Undistort RGBA as two RGB images (colour, and alpha replicated).
            let mut colour = Image8::new(width, height);
            let mut alpha = Image8::new(width, height);
            let (cd, ad): (&mut [u8], &mut [u8]) = (&mut colour.data, &mut alpha.data);
            for ((c, a), p) in cd
                .chunks_exact_mut(3)
                .zip(ad.chunks_exact_mut(3))
                .zip(rgba.pixels())
            {
                c.copy_from_slice(&p.0[..3]);
                a.fill(p.0[3]);
            }
            let colour = undistort_image(&colour, &pin, &d);
            let alpha = undistort_image(&alpha, &pin, &d);
            for ((p, c), a) in rgba
                .pixels_mut()
                .zip(colour.data.chunks_exact(3))
                .zip(alpha.data.chunks_exact(3))
            {
                p.0 = [c[0], c[1], c[2], a[0]];
            }
        }
    }
    let mut image = Image8::new(width, height);
    let mut transparent = false;
    for (dst, src) in image.data.chunks_exact_mut(3).zip(rgba.pixels()) {
        let a = src.0[3] as u32;
        if has_alpha && a < 255 {
            transparent = true;
        }
        for c in 0..3 {
            // rgb * a + (1 - a) on white, in 8-bit fixed point with rounding.
            dst[c] = ((src.0[c] as u32 * a + 255 * (255 - a) + 127) / 255) as u8;
        }
    }
    let alpha = transparent.then(|| {
        // Box-filter the alpha channel the same way as the colours (through a grey image).
        let mut a = Image8::new(width, height);
        for (dst, src) in a.data.chunks_exact_mut(3).zip(rgba.pixels()) {
            dst.fill(src.0[3]);
        }
        downscale_box(&a, downscale)
            .data
            .chunks_exact(3)
            .map(|p| p[0])
            .collect()
    });
    Ok(LoadedImage {
        width,
        height,
        image: downscale_box(&image, downscale),
        transparent,
        alpha,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn solid(width: u32, height: u32, v: u8) -> Image8 {
        Image8 {
            width,
            height,
            data: vec![v; width as usize * height as usize * 3].into(),
        }
    }

    #[test]
    fn png_round_trip_atomic() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.png");
        let mut im = solid(5, 3, 10);
        im.data[7] = 200;
        save_png_atomic(&path, &im).unwrap();
        let back = image::open(&path).unwrap().to_rgb8();
        assert_eq!(back.dimensions(), (5, 3));
        assert_eq!(back.into_raw(), im.data);
        // Only the final file is left behind.
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
    }

    #[test]
    fn bad_image_is_an_error_not_a_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.png");
        let im = Image8 {
            width: 4,
            height: 4,
            data: vec![0; 5].into(),
        };
        let err = save_png_atomic(&path, &im).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::InvalidInput);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        assert!(save_png_atomic(&dir.path().join("no/such/dir.png"), &solid(1, 1, 0)).is_err());
    }

    #[test]
    fn colormap_ends_and_monotone_brightness() {
        assert_eq!(colormap(0.0), INFERNO[0]);
        assert_eq!(colormap(1.0), INFERNO[5]);
        assert_eq!(colormap(f32::NAN), INFERNO[0]);
        assert_eq!(colormap(7.0), INFERNO[5]);
        let mut last = -1.0;
        for i in 0..=100 {
            let c = colormap(i as f32 / 100.0);
            let lum = 0.3 * c[0] + 0.59 * c[1] + 0.11 * c[2];
            assert!(lum >= last - 1e-6);
            last = lum;
        }
    }

    #[test]
    fn error_map_zero_and_saturated() {
        let a = solid(3, 2, 100);
        let same = error_map(&a, &a);
        assert_eq!(same.width, 3);
        assert!(same.data.chunks(3).all(|p| p == [0, 0, 4]));
        let b = solid(4, 2, 255);
        let e = error_map(&a, &b);
        assert_eq!((e.width, e.height), (3, 2));
        assert!(e.data.chunks(3).all(|p| p == [252, 255, 164]));
    }

    #[test]
    fn panel_layout() {
        let a = solid(2, 2, 0);
        let b = solid(3, 1, 9);
        let p = panel(&[&a, &b]);
        assert_eq!((p.width, p.height), (2 + PANEL_GAP + 3, 2));
        assert_eq!(&p.data[0..6], &[0; 6]);
        assert_eq!(&p.data[6..12], &[255; 6]);
        assert_eq!(&p.data[12..15], &[9; 3]);
        // second row of `b` is padding
        let row1 = p.width as usize * 3;
        assert_eq!(&p.data[row1 + 12..row1 + 15], &[255; 3]);
        assert_eq!(panel(&[]).data.len(), 0);
    }
}
