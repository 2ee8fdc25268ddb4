//! Image quality metrics used for evaluation: MSE, PSNR, SSIM and D-SSIM.
//!
//! Images are flat `f32` slices, values in `[0, 1]` (data range 1). SSIM follows the usual NeRF
//! evaluation code and `skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
//! use_sample_covariance=False, data_range=1, channel_axis=2)`: an 11x11 Gaussian window with
//! sigma 1.5 (separable), `K1 = 0.01`, `K2 = 0.03`, "valid" filtering (only windows that lie fully
//! inside the image), computed per channel and averaged. All sums are done in `f64`.
//!
//! Conventions for degenerate input: empty images give `NaN` (so a bug shows up in the averages);
//! slices of different lengths are a programming error and panic (documented per function).

/// PSNR reported for identical images (where the true value is +infinity).
pub const PSNR_CAP: f64 = 100.0;

/// Side of the SSIM window (odd).
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM Gaussian window, in pixels.
pub const SSIM_SIGMA: f64 = 1.5;
const SSIM_K1: f64 = 0.01;
const SSIM_K2: f64 = 0.03;

/// Mean squared error over all values. `NaN` for empty input.
///
/// # Panics
/// If `a` and `b` have different lengths.
pub fn mse(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "mse: slices of different lengths");
    if a.is_empty() {
        return f64::NAN;
    }
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum();
    sum / a.len() as f64
}

/// Peak signal-to-noise ratio in dB for data range 1: `-10 log10(mse)`.
///
/// Identical images (`mse == 0`) give the finite cap [`PSNR_CAP`] (100 dB) instead of +infinity,
/// so averages over test views stay finite. `NaN` for empty input.
///
/// # Panics
/// If `a` and `b` have different lengths.
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    psnr_from_mse(mse(a, b))
}

/// PSNR (data range 1) from an MSE, with the same cap as [`psnr`].
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse.is_nan() {
        return f64::NAN;
    }
    if mse <= 0.0 {
        return PSNR_CAP;
    }
    (-10.0 * mse.log10()).min(PSNR_CAP)
}

/// Normalised 1D Gaussian weights of odd length `len` and standard deviation [`SSIM_SIGMA`].
fn gaussian_window(len: usize) -> Vec<f64> {
    let r = (len / 2) as f64;
    let w: Vec<f64> = (0..len)
        .map(|i| {
            let x = i as f64 - r;
            (-0.5 * x * x / (SSIM_SIGMA * SSIM_SIGMA)).exp()
        })
        .collect();
    let s: f64 = w.iter().sum();
    w.into_iter().map(|v| v / s).collect()
}

/// "Valid" separable filtering of a `width x height` plane with the 1D window `w`:
/// output is `(width - n + 1) x (height - n + 1)`.
fn filter_valid(plane: &[f64], width: usize, height: usize, w: &[f64]) -> Vec<f64> {
    let n = w.len();
    let ow = width + 1 - n;
    let oh = height + 1 - n;
    let mut horiz = vec![0.0; ow * height];
    for y in 0..height {
        let row = &plane[y * width..(y + 1) * width];
        for x in 0..ow {
            horiz[y * ow + x] = row[x..x + n].iter().zip(w).map(|(a, b)| a * b).sum();
        }
    }
    let mut out = vec![0.0; ow * oh];
    for y in 0..oh {
        for (k, &wk) in w.iter().enumerate() {
            let src = &horiz[(y + k) * ow..(y + k + 1) * ow];
            let dst = &mut out[y * ow..(y + 1) * ow];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += wk * s;
            }
        }
    }
    out
}

/// Mean structural similarity of two interleaved RGB images (`width * height * 3` values in
/// `[0, 1]`), see the module header for the exact definition. 1.0 for identical images.
///
/// Images smaller than the 11x11 window use the largest odd window that fits
/// (`min(width, height)` rounded down to odd, Gaussian sigma 1.5 truncated and renormalised),
/// down to 1x1. Empty images give `NaN`.
///
/// # Panics
/// If `a` or `b` does not hold `width * height * 3` values.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize) -> f64 {
    let n = width * height;
    assert_eq!(a.len(), n * 3, "ssim: first image has the wrong length");
    assert_eq!(b.len(), n * 3, "ssim: second image has the wrong length");
    if n == 0 {
        return f64::NAN;
    }
    let mut win = SSIM_WINDOW.min(width).min(height);
    if win.is_multiple_of(2) {
        win -= 1;
    }
    let w = gaussian_window(win);
    let c1 = (SSIM_K1 * 1.0).powi(2);
    let c2 = (SSIM_K2 * 1.0).powi(2);
    let mut total = 0.0;
    for c in 0..3 {
        let x: Vec<f64> = (0..n).map(|i| a[i * 3 + c] as f64).collect();
        let y: Vec<f64> = (0..n).map(|i| b[i * 3 + c] as f64).collect();
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
        let ux = filter_valid(&x, width, height, &w);
        let uy = filter_valid(&y, width, height, &w);
        let uxx = filter_valid(&xx, width, height, &w);
        let uyy = filter_valid(&yy, width, height, &w);
        let uxy = filter_valid(&xy, width, height, &w);
        let mut sum = 0.0;
        for i in 0..ux.len() {
            let (mx, my) = (ux[i], uy[i]);
            let vx = uxx[i] - mx * mx;
            let vy = uyy[i] - my * my;
            let vxy = uxy[i] - mx * my;
            let num = (2.0 * mx * my + c1) * (2.0 * vxy + c2);
            let den = (mx * mx + my * my + c1) * (vx + vy + c2);
            sum += num / den;
        }
        total += sum / ux.len() as f64;
    }
    total / 3.0
}

/// Structural dissimilarity `(1 - ssim) / 2`, in `[0, 1]`.
pub fn dssim(ssim: f64) -> f64 {
    (1.0 - ssim) * 0.5
}

#[cfg(test)]
mod tests {
    use super::*;

    /// xorshift64* in `[0, 1)`, easy to reproduce in Python (see `skimage_reference`).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            let v = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D);
            (v >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// A smooth RGB test picture with some texture.
    fn picture(width: usize, height: usize) -> Vec<f32> {
        let mut out = Vec::with_capacity(width * height * 3);
        for y in 0..height {
            for x in 0..width {
                let (fx, fy) = (x as f32, y as f32);
                out.push(0.5 + 0.4 * (fx * 0.3).sin() * (fy * 0.2).cos());
                out.push(fy / height as f32);
                out.push(if (x / 4 + y / 4) % 2 == 0 { 0.8 } else { 0.2 });
            }
        }
        out
    }

    #[test]
    fn identical_images() {
        let a = picture(32, 24);
        assert_eq!(mse(&a, &a), 0.0);
        assert_eq!(psnr(&a, &a), PSNR_CAP);
        assert!((ssim(&a, &a, 32, 24) - 1.0).abs() < 1e-12);
        assert_eq!(dssim(1.0), 0.0);
    }

    #[test]
    fn constant_offset_psnr_is_analytic() {
        let a = picture(16, 16);
        let b: Vec<f32> = a.iter().map(|v| v + 0.1).collect();
        // mse = 0.01 -> 20 dB
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-4, "{}", psnr(&a, &b));
        assert!((psnr_from_mse(1e-3) - 30.0).abs() < 1e-9);
        assert_eq!(psnr_from_mse(1e-30), PSNR_CAP);
    }

    #[test]
    fn ssim_decreases_with_noise() {
        let a = picture(40, 30);
        let mut rng = Rng(7);
        let noise: Vec<f32> = (0..a.len()).map(|_| rng.next() - 0.5).collect();
        let mut last = 1.0;
        for amp in [0.02, 0.05, 0.1, 0.3] {
            let b: Vec<f32> = a.iter().zip(&noise).map(|(v, n)| v + amp * n).collect();
            let s = ssim(&a, &b, 40, 30);
            assert!(s < last && s > -1.0, "amp {amp}: {s} !< {last}");
            last = s;
        }
        assert!(dssim(last) > 0.0);
    }

    #[test]
    fn small_and_empty_images() {
        let a = picture(5, 8);
        let b: Vec<f32> = a.iter().map(|v| v * 0.9).collect();
        let s = ssim(&a, &b, 5, 8);
        assert!(s.is_finite() && s < 1.0 && s > 0.0);
        assert!((ssim(&a, &a, 5, 8) - 1.0).abs() < 1e-12);
        let one = [0.2f32, 0.3, 0.4];
        assert!(ssim(&one, &one, 1, 1).is_finite());
        assert!(ssim(&[], &[], 0, 0).is_nan());
        assert!(mse(&[], &[]).is_nan());
        assert!(psnr(&[], &[]).is_nan());
    }

    /// Cross-check against scikit-image 0.26.0 (numpy 2.4), computed once with:
    ///
    /// ```python
    /// import numpy as np
    /// from skimage.metrics import structural_similarity
    /// M = (1 << 64) - 1
    /// def rng(s):
    ///     while True:
    ///         s ^= s >> 12; s ^= (s << 25) & M; s ^= s >> 27
    ///         yield np.float32(((s * 0x2545F4914F6CDD1D) & M) >> 40) / np.float32(1 << 24)
    /// r = rng(12345); w, h = 37, 29
    /// a = np.array([next(r) for _ in range(w * h * 3)], np.float32).reshape(h, w, 3)
    /// b = np.clip(a + np.float32(0.2) * (np.array([next(r) for _ in range(w * h * 3)],
    ///             np.float32).reshape(h, w, 3) - np.float32(0.5)), 0, 1)
    /// # smooth `a` a little (3-tap box along x) so the pair is not pure noise:
    /// a = (a + np.roll(a, 1, axis=1) + np.roll(a, -1, axis=1)) / np.float32(3)
    /// print(structural_similarity(a.astype(np.float64), b.astype(np.float64), channel_axis=2,
    ///       gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1))
    /// ```
    /// which printed `0.47763644316753756` (the Rust side below builds exactly the same arrays in
    /// `f32`).
    #[test]
    fn skimage_reference() {
        const SKIMAGE_SSIM: f64 = 0.477_636_443_167_537_56;
        let (w, h) = (37usize, 29usize);
        let mut rng = Rng(12345);
        let raw: Vec<f32> = (0..w * h * 3).map(|_| rng.next()).collect();
        let noise: Vec<f32> = (0..w * h * 3).map(|_| rng.next()).collect();
        let b: Vec<f32> = raw
            .iter()
            .zip(&noise)
            .map(|(v, n)| (v + 0.2 * (n - 0.5)).clamp(0.0, 1.0))
            .collect();
        let mut a = vec![0.0f32; raw.len()];
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let at = |xx: usize| raw[(y * w + xx) * 3 + c];
                    a[(y * w + x) * 3 + c] = (at(x) + at((x + w - 1) % w) + at((x + 1) % w)) / 3.0;
                }
            }
        }
        let s = ssim(&a, &b, w, h);
        println!("ours: {s:.12}");
        assert!(
            (s - SKIMAGE_SSIM).abs() < 1e-6,
            "ours {s} vs skimage {SKIMAGE_SSIM}"
        );
    }
}
