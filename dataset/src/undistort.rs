//! Lens distortion (the OpenCV / nerfstudio `OPENCV` model: radial `k1, k2, k3`, tangential
//! `p1, p2`) and undistortion of images to the pinhole camera with the same intrinsics.
//!
//! With normalised coordinates `x = (u - cx) / fx`, `y = (v - cy) / fy` (pixel centres at
//! `+0.5`, `v` down), the distorted point is
//! `x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)` and
//! `y' = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y`, `r^2 = x^2 + y^2`.
//! [`undistort_image`] fills every pixel of the pinhole image with the distorted image sampled
//! bilinearly at the distorted position (edge pixels repeated outside the source).

use crate::Image8;

/// Distortion coefficients of the OpenCV model.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Distortion {
    pub k1: f64,
    pub k2: f64,
    pub k3: f64,
    pub p1: f64,
    pub p2: f64,
}

impl Distortion {
    /// Whether all coefficients are zero (no distortion).
    pub fn is_identity(&self) -> bool {
        *self == Distortion::default()
    }

    /// The distorted normalised point of the undistorted `(x, y)`.
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// The undistorted point whose distortion is `(xd, yd)` (Newton's method on the 2x2 system;
    /// `None` when it does not converge, e.g. beyond the model's fold-over radius).
    pub fn undistort_point(&self, xd: f64, yd: f64) -> Option<(f64, f64)> {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let (fx, fy) = self.distort(x, y);
            let (ex, ey) = (fx - xd, fy - yd);
            if ex.abs() < 1e-13 && ey.abs() < 1e-13 {
                return Some((x, y));
            }
            // Jacobian by central differences (smooth polynomial; plenty accurate).
            let h = 1e-7;
            let (ax, ay) = self.distort(x + h, y);
            let (bx, by) = self.distort(x - h, y);
            let (cx, cy) = self.distort(x, y + h);
            let (dx, dy) = self.distort(x, y - h);
            let (j00, j10) = ((ax - bx) / (2.0 * h), (ay - by) / (2.0 * h));
            let (j01, j11) = ((cx - dx) / (2.0 * h), (cy - dy) / (2.0 * h));
            let det = j00 * j11 - j01 * j10;
            if !det.is_finite() || det.abs() < 1e-12 {
                return None;
            }
            x -= (j11 * ex - j01 * ey) / det;
            y -= (-j10 * ex + j00 * ey) / det;
        }
        let (fx, fy) = self.distort(x, y);
        ((fx - xd).abs() < 1e-9 && (fy - yd).abs() < 1e-9).then_some((x, y))
    }
}

/// Pinhole intrinsics in pixels (principal point in the `+0.5` pixel-centre convention).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// Bilinear sample of `img` at continuous pixel coordinates (pixel `i`'s centre at `i + 0.5`),
/// clamped to the edge.
#[inline]
fn bilinear(img: &Image8, u: f64, v: f64, out: &mut [u8]) {
    let (w, h) = (img.width as i64, img.height as i64);
    let fu = (u - 0.5).clamp(0.0, (w - 1) as f64);
    let fv = (v - 0.5).clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (fu.floor() as i64, fv.floor() as i64);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (fu - x0 as f64, fv - y0 as f64);
    let px = |x: i64, y: i64, c: usize| img.data[((y * w + x) * 3) as usize + c] as f64;
    for c in 0..3 {
        let top = px(x0, y0, c) * (1.0 - ax) + px(x1, y0, c) * ax;
        let bot = px(x0, y1, c) * (1.0 - ax) + px(x1, y1, c) * ax;
        out[c] = (top * (1.0 - ay) + bot * ay).round().clamp(0.0, 255.0) as u8;
    }
}

/// The pinhole image (same size and intrinsics `k`) of the distorted image `img`.
pub fn undistort_image(img: &Image8, k: &Intrinsics, d: &Distortion) -> Image8 {
    let mut out = Image8::new(img.width, img.height);
    let w = img.width as usize;
    let data: &mut [u8] = &mut out.data;
    for (i, px) in data.chunks_exact_mut(3).enumerate() {
        let (u, v) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let (x, y) = ((u - k.cx) / k.fx, (v - k.cy) / k.fy);
        let (xd, yd) = d.distort(x, y);
        bilinear(img, xd * k.fx + k.cx, yd * k.fy + k.cy, px);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth pattern over normalised coordinates (the "scene").
    fn pattern(x: f64, y: f64) -> [f64; 3] {
        [
            127.5 + 100.0 * (12.0 * x).sin() * (9.0 * y).cos(),
            127.5 + 100.0 * (10.0 * (x + y)).cos(),
            127.5 + 80.0 * (14.0 * y - 4.0 * x).sin(),
        ]
    }

    fn render(
        w: u32,
        h: u32,
        k: &Intrinsics,
        f: impl Fn(f64, f64) -> Option<(f64, f64)>,
    ) -> Image8 {
        let mut img = Image8::new(w, h);
        let data: &mut [u8] = &mut img.data;
        for (i, px) in data.chunks_exact_mut(3).enumerate() {
            let u = (i % w as usize) as f64 + 0.5;
            let v = (i / w as usize) as f64 + 0.5;
            let (x, y) = f((u - k.cx) / k.fx, (v - k.cy) / k.fy).unwrap();
            let c = pattern(x, y);
            for ch in 0..3 {
                px[ch] = c[ch].round() as u8;
            }
        }
        img
    }

    fn psnr(a: &Image8, b: &Image8) -> f64 {
        let n = a.data.len() as f64;
        let mse: f64 = a
            .data
            .iter()
            .zip(b.data.iter())
            .map(|(&p, &q)| (p as f64 - q as f64).powi(2))
            .sum::<f64>()
            / n;
        10.0 * (255.0f64.powi(2) / mse.max(1e-12)).log10()
    }

    #[test]
    fn point_round_trip() {
        let d = Distortion {
            k1: -0.2,
            k2: 0.05,
            k3: 0.01,
            p1: 0.002,
            p2: -0.003,
        };
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.5, 0.4), (0.6, 0.45)] {
            let (xd, yd) = d.distort(x, y);
            let (bx, by) = d.undistort_point(xd, yd).unwrap();
            assert!((bx - x).abs() < 1e-9 && (by - y).abs() < 1e-9);
        }
        assert_eq!(Distortion::default().distort(0.3, 0.2), (0.3, 0.2));
    }

    /// The reference: a distorted image rendered analytically (each distorted pixel shows the
    /// pattern at its undistorted position), undistorted by [`undistort_image`], against the
    /// pinhole image rendered directly.
    #[test]
    fn undistortion_matches_the_analytic_pinhole_image() {
        let (w, h) = (96, 72);
        let k = Intrinsics {
            fx: 80.0,
            fy: 82.0,
            cx: 48.5,
            cy: 35.0,
        };
        let d = Distortion {
            k1: -0.3,
            k2: 0.08,
            k3: 0.0,
            p1: 0.001,
            p2: -0.002,
        };
        let distorted = render(w, h, &k, |x, y| d.undistort_point(x, y));
        let pinhole = render(w, h, &k, |x, y| Some((x, y)));
        let fixed = undistort_image(&distorted, &k, &d);
        // Compare away from the border, where the pinhole view needs pixels the distorted
        // image does not have (barrel distortion pulls the corners in).
        let crop = |im: &Image8| {
            let mut c = Image8::new(w - 16, h - 16);
            let data: &mut [u8] = &mut c.data;
            for y in 0..(h - 16) as usize {
                for x in 0..(w - 16) as usize * 3 {
                    data[y * (w as usize - 16) * 3 + x] =
                        im.data[(y + 8) * w as usize * 3 + 24 + x];
                }
            }
            c
        };
        let before = psnr(&crop(&distorted), &crop(&pinhole));
        let after = psnr(&crop(&fixed), &crop(&pinhole));
        println!("PSNR vs analytic pinhole: distorted {before:.1} dB, undistorted {after:.1} dB");
        assert!(after > 38.0, "{after}");
        assert!(before < 30.0, "{before}");
        // No distortion: the image is unchanged.
        let same = undistort_image(&pinhole, &k, &Distortion::default());
        assert_eq!(same, pinhole);
    }
}
