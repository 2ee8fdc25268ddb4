//! Where samples go along a ray: the spacing function between world distance `t` and the
//! normalised coordinate `s in [0, 1]`, stratified uniform bins, and inverse-CDF resampling from
//! proposal weights (mip-NeRF 360's proposal sampler).

use serde::{Deserialize, Serialize};

use crate::rng::Rng;

/// How `s in [0, 1]` maps to distance along the ray between `near` and `far`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Spacing {
    /// `t = near + s (far - near)`: bounded (box) scenes.
    Linear,
    /// Linear in `t` up to 1 (the contraction radius), linear in disparity beyond:
    /// `g(t) = t/2` for `t < 1`, `1 - 1/(2t)` otherwise; `s` is uniform in `g`.
    /// Distances are in units of the contraction radius.
    LinDisp,
}

#[inline]
fn g(t: f32) -> f32 {
    if t < 1.0 {
        0.5 * t
    } else {
        1.0 - 0.5 / t
    }
}

#[inline]
fn g_inv(y: f32) -> f32 {
    if y < 0.5 {
        2.0 * y
    } else {
        0.5 / (1.0 - y).max(1e-7)
    }
}

impl Spacing {
    /// Distance along the ray for normalised coordinate `s`.
    #[inline]
    pub fn t_of_s(self, s: f32, near: f32, far: f32, unit: f32) -> f32 {
        match self {
            Spacing::Linear => near + s * (far - near),
            Spacing::LinDisp => {
                let (a, b) = (g(near / unit), g(far / unit));
                unit * g_inv(a + s * (b - a))
            }
        }
    }
}

/// `n + 1` bin edges over `[0, 1]`; with `rng`, the interior edges are jittered inside their
/// half-bin neighbourhood (stratified sampling), keeping them sorted.
pub fn uniform_edges(n: usize, rng: Option<&mut Rng>, edges: &mut [f32]) {
    match rng {
        None => {
            for k in 0..=n {
                edges[k] = k as f32 / n as f32;
            }
        }
        Some(rng) => {
            let jitter = rng.f32() - 0.5;
            edges[0] = 0.0;
            for k in 1..n {
                edges[k] = (k as f32 + jitter) / n as f32;
            }
            edges[n] = 1.0;
        }
    }
}

/// Inverse-CDF resampling (nerfstudio's `PDFSampler`, `include_original = false`): draws
/// `out.len()` sorted edges in `[0, 1]` from the piecewise-constant density whose bins are
/// `edges` and whose masses are `weights` (already annealed), with `padding` added to every bin
/// so that no bin has zero probability. With `rng`, draws are stratified and jittered.
pub fn sample_pdf(
    edges: &[f32],
    weights: &[f32],
    padding: f32,
    rng: Option<&mut Rng>,
    out: &mut [f32],
) {
    let nb = weights.len();
    debug_assert_eq!(edges.len(), nb + 1);
    let m = out.len();
    let mut total = 0f32;
    for &w in weights {
        total += sanitize(w) + padding;
    }
    if !(total > 0.0 && total.is_finite()) {
        // Degenerate weights: fall back to uniform edges.
        for (k, o) in out.iter_mut().enumerate() {
            *o = k as f32 / (m - 1).max(1) as f32;
        }
        return;
    }
    let inv = 1.0 / total;
    let jitter = rng.map(|r| r.f32());
    // u_k in [0, 1], sorted: stratified with one jitter offset per ray, or uniform.
    let mut bin = 0usize;
    let mut cdf_lo = 0f32;
    let mut cdf_hi = (sanitize(weights[0]) + padding) * inv;
    for k in 0..m {
        let u = match jitter {
            Some(j) => ((k as f32 + j) / m as f32).min(1.0),
            None => k as f32 / (m - 1).max(1) as f32,
        };
        while u > cdf_hi && bin + 1 < nb {
            bin += 1;
            cdf_lo = cdf_hi;
            cdf_hi += (sanitize(weights[bin]) + padding) * inv;
        }
        let span = cdf_hi - cdf_lo;
        let frac = if span > 0.0 {
            ((u - cdf_lo) / span).clamp(0.0, 1.0)
        } else {
            0.0
        };
        out[k] = edges[bin] + frac * (edges[bin + 1] - edges[bin]);
    }
    // Guard monotonicity against rounding.
    for k in 1..m {
        if out[k] < out[k - 1] {
            out[k] = out[k - 1];
        }
    }
}

#[inline]
fn sanitize(w: f32) -> f32 {
    if w > 0.0 && w.is_finite() {
        w
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lindisp_is_monotone_and_hits_ends() {
        let (near, far) = (0.05, 1000.0);
        let mut prev = 0.0;
        for k in 0..=100 {
            let t = Spacing::LinDisp.t_of_s(k as f32 / 100.0, near, far, 1.0);
            assert!(t >= prev);
            prev = t;
        }
        assert!((Spacing::LinDisp.t_of_s(0.0, near, far, 1.0) - near).abs() < 1e-5);
        assert!((Spacing::LinDisp.t_of_s(1.0, near, far, 1.0) - far).abs() / far < 1e-2);
    }

    #[test]
    fn pdf_samples_concentrate_on_mass() {
        let edges: Vec<f32> = (0..=10).map(|k| k as f32 / 10.0).collect();
        let mut w = vec![0f32; 10];
        w[7] = 1.0;
        let mut out = vec![0f32; 33];
        sample_pdf(&edges, &w, 0.0, None, &mut out);
        let inside = out.iter().filter(|&&s| (0.7..=0.8).contains(&s)).count();
        assert!(inside >= 31, "{out:?}");
        let mut rng = Rng::new(1);
        sample_pdf(&edges, &w, 0.01, Some(&mut rng), &mut out);
        assert!(out.windows(2).all(|p| p[0] <= p[1]));
        assert!(out.iter().all(|s| (0.0..=1.0).contains(s)));
        // NaN and zero weights fall back to something sorted and finite.
        sample_pdf(&edges, &[f32::NAN; 10], 0.0, None, &mut out);
        assert!(out.iter().all(|s| s.is_finite()) && out.windows(2).all(|p| p[0] <= p[1]));
    }

    #[test]
    fn jittered_edges_sorted() {
        let mut rng = Rng::new(3);
        let mut e = vec![0f32; 65];
        for _ in 0..100 {
            uniform_edges(64, Some(&mut rng), &mut e);
            assert!(e.windows(2).all(|p| p[0] <= p[1]));
            assert_eq!(e[0], 0.0);
            assert_eq!(e[64], 1.0);
        }
    }
}
