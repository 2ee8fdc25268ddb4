//! Volume rendering along one ray (method.md §2) and its backward pass.
//!
//! With `tau_i = sigma_i * delta_i`, `T_i = exp(-sum_{j<i} tau_j)`, `alpha_i = 1 - exp(-tau_i)`,
//! `w_i = T_i alpha_i`: `C = sum_i w_i c_i + T_N * bg` where `T_N = exp(-sum tau)` is the
//! transmittance left at the end of the ray.
//!
//! Backward, for upstream `g_i = dL/dw_i` and `g_T = dL/dT_N`:
//! `dL/dtau_k = g_k T_{k+1} - sum_{i>k} g_i w_i - g_T T_N`, `dL/dsigma_k = dL/dtau_k * delta_k`.
//! Optical depth is accumulated in f32 and every exponential is of a non-positive number, so
//! `sigma = 1e8` or `delta = 1e3` give `alpha = 1` exactly and `T = 0`, never NaN.

/// Weights `w_i` and the final transmittance `T_N` from densities and interval lengths.
pub fn weights(sigmas: &[f32], deltas: &[f32], w: &mut [f32]) -> f32 {
    let mut tau_sum = 0f32;
    for i in 0..sigmas.len() {
        let tau = tau_of(sigmas[i], deltas[i]);
        let t = (-tau_sum).exp();
        w[i] = t * -(-tau).exp_m1();
        tau_sum += tau;
    }
    (-tau_sum).exp()
}

/// `sigma * delta`, made safe: negative or NaN inputs count as 0, infinite as a wall.
#[inline]
pub fn tau_of(sigma: f32, delta: f32) -> f32 {
    let t = sigma * delta;
    if t >= 0.0 {
        t.min(1e30)
    } else {
        0.0
    }
}

/// Backward of [`weights`]: given `dL/dw` and `dL/dT_N`, writes `dL/dsigma`.
pub fn weights_backward(
    sigmas: &[f32],
    deltas: &[f32],
    w: &[f32],
    t_final: f32,
    d_w: &[f32],
    d_t_final: f32,
    d_sigma: &mut [f32],
) {
    let n = sigmas.len();
    // T_{k+1} = exp(-sum_{j<=k} tau_j), computed forwards (backwards from T_N would overflow)
    // into `d_sigma`, which the backward loop then overwrites entry by entry.
    let mut tau_sum = 0f32;
    for k in 0..n {
        tau_sum += tau_of(sigmas[k], deltas[k]);
        d_sigma[k] = (-tau_sum).exp();
    }
    // suffix = sum_{i>k} g_i w_i
    let mut suffix = 0f32;
    for k in (0..n).rev() {
        let t_next = d_sigma[k];
        let d_tau = d_w[k] * t_next - suffix - d_t_final * t_final;
        let valid = sigmas[k] * deltas[k] >= 0.0 && sigmas[k] * deltas[k] < 1e30;
        d_sigma[k] = if valid { d_tau * deltas[k] } else { 0.0 };
        suffix += d_w[k] * w[k];
    }
}

/// Colour compositing: `C = sum w_i c_i + T_N * bg`.
pub fn composite(w: &[f32], rgb: &[f32], t_final: f32, bg: [f32; 3]) -> [f32; 3] {
    let mut c = [0f32; 3];
    for i in 0..w.len() {
        for ch in 0..3 {
            c[ch] += w[i] * rgb[i * 3 + ch];
        }
    }
    for ch in 0..3 {
        c[ch] += t_final * bg[ch];
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn loss(sig: &[f64], del: &[f32], rgb: &[f32], bg: [f32; 3], gc: [f32; 3], gw: &[f32]) -> f64 {
        let s32: Vec<f32> = sig.iter().map(|&v| v as f32).collect();
        let mut w = vec![0f32; sig.len()];
        let t = weights(&s32, del, &mut w);
        let c = composite(&w, rgb, t, bg);
        let mut l = 0f64;
        for ch in 0..3 {
            l += c[ch] as f64 * gc[ch] as f64;
        }
        for i in 0..w.len() {
            l += w[i] as f64 * gw[i] as f64;
        }
        l
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = Rng::new(11);
        let n = 12;
        let mut sig: Vec<f64> = (0..n).map(|_| rng.range_f32(0.0, 3.0) as f64).collect();
        let del: Vec<f32> = (0..n).map(|_| rng.range_f32(0.05, 0.3)).collect();
        let rgb: Vec<f32> = (0..3 * n).map(|_| rng.f32()).collect();
        let bg = [1.0, 0.5, 0.2];
        let gc = [0.3, -0.7, 0.5];
        let gw: Vec<f32> = (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let s32: Vec<f32> = sig.iter().map(|&v| v as f32).collect();
        let mut w = vec![0f32; n];
        let t = weights(&s32, &del, &mut w);
        let mut d_w = vec![0f32; n];
        for i in 0..n {
            d_w[i] = gw[i] + (0..3).map(|ch| gc[ch] * rgb[i * 3 + ch]).sum::<f32>();
        }
        let d_t = (0..3).map(|ch| gc[ch] * bg[ch]).sum::<f32>();
        let mut d_sigma = vec![0f32; n];
        weights_backward(&s32, &del, &w, t, &d_w, d_t, &mut d_sigma);
        for k in 0..n {
            let h = 1e-3;
            let v = sig[k];
            sig[k] = v + h;
            let lp = loss(&sig, &del, &rgb, bg, gc, &gw);
            sig[k] = v - h;
            let lm = loss(&sig, &del, &rgb, bg, gc, &gw);
            sig[k] = v;
            let fd = (lp - lm) / (2.0 * h);
            assert!(
                (fd - d_sigma[k] as f64).abs() < 2e-3,
                "{k}: {fd} vs {}",
                d_sigma[k]
            );
        }
    }

    #[test]
    fn extremes_stay_finite() {
        for &sigma in &[0.0f32, 1e-8, 1.0, 1e8, f32::INFINITY, f32::NAN, -5.0] {
            for &delta in &[1e-8f32, 1e-3, 1.0, 1e3] {
                let s = vec![sigma; 8];
                let d = vec![delta; 8];
                let mut w = vec![0f32; 8];
                let t = weights(&s, &d, &mut w);
                assert!(t.is_finite() && (0.0..=1.0).contains(&t));
                let sum: f32 = w.iter().sum::<f32>() + t;
                assert!(w.iter().all(|v| v.is_finite() && *v >= 0.0));
                assert!(
                    (sum - 1.0).abs() < 1e-4,
                    "sigma {sigma} delta {delta}: {sum}"
                );
                let mut ds = vec![0f32; 8];
                weights_backward(&s, &d, &w, t, &[1.0; 8], 1.0, &mut ds);
                assert!(ds.iter().all(|v| v.is_finite()), "{sigma} {delta}: {ds:?}");
            }
        }
        // A wall: alpha = 1 exactly on the first sample.
        let mut w = vec![0f32; 3];
        let t = weights(&[1e8, 1.0, 1.0], &[1e3, 1.0, 1.0], &mut w);
        assert_eq!(w[0], 1.0);
        assert_eq!(t, 0.0);
    }
}
