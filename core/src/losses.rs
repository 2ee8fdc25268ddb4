//! Per-ray losses and their gradients: the proposal (interlevel) loss and the distortion loss of
//! mip-NeRF 360, and the mask loss of MSTH. All work in the normalised ray coordinate `s`.

/// The interlevel loss of one ray (mip-NeRF 360 `lossfun_outer`): for each main interval
/// `[c_i, c_{i+1}]` with weight `w_i` (held constant), the proposal must put at least that much
/// mass on the proposal intervals overlapping it:
/// `L = sum_i max(0, w_i - bound_i)^2 / (w_i + eps)`.
/// Returns `L` and adds `scale * dL/dw_prop` into `d_w_prop`.
pub fn interlevel(
    c: &[f32],
    w: &[f32],
    c_prop: &[f32],
    w_prop: &[f32],
    scale: f32,
    d_w_prop: &mut [f32],
) -> f32 {
    const EPS: f32 = 1e-7;
    let np = w_prop.len();
    // cumulative proposal weights: cw[k] = sum_{j<k} w_prop[j]
    let mut cw = Vec::with_capacity(np + 1);
    cw.push(0f32);
    for &v in w_prop {
        cw.push(cw.last().copied().unwrap_or(0.0) + v);
    }
    let mut loss = 0f32;
    let mut lo = 0usize;
    for i in 0..w.len() {
        let (t0, t1) = (c[i], c[i + 1]);
        // first proposal interval j with c_prop[j+1] > t0
        while lo < np && c_prop[lo + 1] <= t0 {
            lo += 1;
        }
        // last interval j with c_prop[j] < t1 -> hi exclusive
        let mut hi = lo;
        while hi < np && c_prop[hi] < t1 {
            hi += 1;
        }
        let bound = cw[hi] - cw[lo];
        let diff = w[i] - bound;
        if diff > 0.0 {
            loss += diff * diff / (w[i] + EPS);
            let g = -2.0 * diff / (w[i] + EPS) * scale;
            for d in &mut d_w_prop[lo..hi] {
                *d += g;
            }
        }
    }
    loss
}

/// The distortion loss of one ray over intervals with edges `s` and weights `w`:
/// `L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_{i+1} - s_i)` (midpoints `m`),
/// computed in O(n). Returns `L` and adds `scale * dL/dw` into `d_w`.
pub fn distortion(s: &[f32], w: &[f32], scale: f32, d_w: &mut [f32]) -> f32 {
    let n = w.len();
    let mid = |i: usize| 0.5 * (s[i] + s[i + 1]);
    let (mut w_tot, mut wm_tot) = (0f32, 0f32);
    for i in 0..n {
        w_tot += w[i];
        wm_tot += w[i] * mid(i);
    }
    let (mut w_before, mut wm_before) = (0f32, 0f32);
    let mut loss = 0f32;
    for i in 0..n {
        let m = mid(i);
        let d = s[i + 1] - s[i];
        let w_after = w_tot - w_before - w[i];
        let wm_after = wm_tot - wm_before - w[i] * m;
        // pair term: sum_j w_j |m_i - m_j| = m_i W_< - WM_< + WM_> - m_i W_>
        let pair = m * w_before - wm_before + wm_after - m * w_after;
        loss += w[i] * (m * w_before - wm_before) * 2.0 + w[i] * w[i] * d / 3.0;
        d_w[i] += scale * (2.0 * pair + 2.0 / 3.0 * w[i] * d);
        w_before += w[i];
        wm_before += w[i] * m;
    }
    loss
}

/// The MSTH mask loss over a whole mask grid, `mean(1 - sigmoid(logit))`, pushing voxels toward
/// static. Adds `scale * dL/dlogit` into `grad` and returns the loss.
pub fn mask_loss(logits: &[f32], scale: f32, grad: &mut [f32]) -> f32 {
    let n = logits.len() as f32;
    let mut loss = 0f64;
    for (g, &x) in grad.iter_mut().zip(logits) {
        let s = crate::activation::sigmoid(x);
        loss += (1.0 - s) as f64;
        *g += -scale * s * (1.0 - s) / n;
    }
    (loss / n as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// `(f(x + h e_k) - f(x - h e_k)) / 2h`: the central difference of `f` along entry `k`.
    fn central_difference(f: impl Fn(&[f32]) -> f64, x: &[f32], k: usize, h: f64) -> f64 {
        let mut plus = x.to_vec();
        plus[k] += h as f32;
        let mut minus = x.to_vec();
        minus[k] -= h as f32;
        (f(&plus) - f(&minus)) / (2.0 * h)
    }

    fn sorted(n: usize, rng: &mut Rng) -> Vec<f32> {
        let mut v: Vec<f32> = (0..n + 1).map(|_| rng.f32()).collect();
        v[0] = 0.0;
        v[n] = 1.0;
        v.sort_by(|a, b| a.partial_cmp(b).unwrap());
        v
    }

    #[test]
    fn distortion_matches_quadratic_form_and_fd() {
        let mut rng = Rng::new(5);
        let n = 9;
        let s = sorted(n, &mut rng);
        let w: Vec<f32> = (0..n).map(|_| rng.f32() * 0.3).collect();
        let brute = |w: &[f32]| -> f64 {
            let mut l = 0f64;
            for i in 0..n {
                for j in 0..n {
                    let mi = 0.5 * (s[i] + s[i + 1]) as f64;
                    let mj = 0.5 * (s[j] + s[j + 1]) as f64;
                    l += w[i] as f64 * w[j] as f64 * (mi - mj).abs();
                }
                l += (w[i] as f64).powi(2) * (s[i + 1] - s[i]) as f64 / 3.0;
            }
            l
        };
        let mut d = vec![0f32; n];
        let l = distortion(&s, &w, 1.0, &mut d);
        assert!((l as f64 - brute(&w)).abs() < 1e-5);
        for k in 0..n {
            let fd = central_difference(brute, &w, k, 1e-3);
            assert!((fd - d[k] as f64).abs() < 1e-3, "{k}: {fd} vs {}", d[k]);
        }
    }

    #[test]
    fn interlevel_brute_force_and_fd() {
        let mut rng = Rng::new(6);
        let (n, np) = (7, 11);
        let c = sorted(n, &mut rng);
        let cp = sorted(np, &mut rng);
        let w: Vec<f32> = (0..n).map(|_| rng.f32() * 0.4).collect();
        let wp: Vec<f32> = (0..np).map(|_| rng.f32() * 0.2).collect();
        let brute = |wp: &[f32]| -> f64 {
            let mut l = 0f64;
            for i in 0..n {
                let mut bound = 0f64;
                for j in 0..np {
                    if cp[j + 1] > c[i] && cp[j] < c[i + 1] {
                        bound += wp[j] as f64;
                    }
                }
                let d = (w[i] as f64 - bound).max(0.0);
                l += d * d / (w[i] as f64 + 1e-7);
            }
            l
        };
        let mut d = vec![0f32; np];
        let l = interlevel(&c, &w, &cp, &wp, 1.0, &mut d);
        assert!((l as f64 - brute(&wp)).abs() < 1e-5);
        for k in 0..np {
            let fd = central_difference(brute, &wp, k, 1e-4);
            assert!((fd - d[k] as f64).abs() < 1e-2, "{k}: {fd} vs {}", d[k]);
        }
    }

    #[test]
    fn mask_loss_gradient() {
        let logits = [-3.0f32, -1.0, 0.0, 2.0];
        let mut g = [0f32; 4];
        let l = mask_loss(&logits, 1.0, &mut g);
        for k in 0..4 {
            let mut a = logits;
            a[k] += 1e-3;
            let mut b = logits;
            b[k] -= 1e-3;
            let mut scratch = [0f32; 4];
            let fd = (mask_loss(&a, 1.0, &mut scratch) - mask_loss(&b, 1.0, &mut scratch)) / 2e-3;
            assert!((fd - g[k]).abs() < 1e-3);
        }
        assert!(l > 0.0 && l < 1.0);
    }
}
