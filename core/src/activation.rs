//! Scalar activations used by the decoders, with their derivatives.
//!
//! `trunc_exp` is instant-ngp's density activation: `exp(x)` forward, and a backward pass that
//! uses `exp(clamp(x, -15, 15))` so that a large pre-activation cannot produce an infinite
//! gradient.

/// `1 / (1 + exp(-x))`, stable for large `|x|`.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// Derivative of the sigmoid expressed through its output `s = sigmoid(x)`.
#[inline]
pub fn sigmoid_grad_from_output(s: f32) -> f32 {
    s * (1.0 - s)
}

/// Forward of truncated exp: plain `exp`, clamped to `f32::MAX` so it never returns infinity.
#[inline]
pub fn trunc_exp(x: f32) -> f32 {
    x.min(88.0).exp()
}

/// Derivative used for `trunc_exp`'s backward pass.
#[inline]
pub fn trunc_exp_grad(x: f32) -> f32 {
    x.clamp(-15.0, 15.0).exp()
}

/// `ln(1 + exp(x))`, stable for large `|x|`.
#[inline]
pub fn softplus(x: f32) -> f32 {
    if x > 20.0 {
        x
    } else if x < -20.0 {
        x.exp()
    } else {
        x.exp().ln_1p()
    }
}

/// Derivative of softplus: the sigmoid.
#[inline]
pub fn softplus_grad(x: f32) -> f32 {
    sigmoid(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fd(f: impl Fn(f64) -> f64, x: f64) -> f64 {
        let h = 1e-4;
        (f(x + h) - f(x - h)) / (2.0 * h)
    }

    #[test]
    fn sigmoid_is_stable_and_matches_fd() {
        assert_eq!(sigmoid(1000.0), 1.0);
        assert_eq!(sigmoid(-1000.0), 0.0);
        for &x in &[-3.0f32, -0.5, 0.0, 0.7, 4.0] {
            let g = sigmoid_grad_from_output(sigmoid(x)) as f64;
            let n = fd(|v| 1.0 / (1.0 + (-v).exp()), x as f64);
            assert!((g - n).abs() < 1e-5, "{x}: {g} vs {n}");
        }
    }

    #[test]
    fn trunc_exp_grad_matches_exp_inside_and_is_bounded_outside() {
        for &x in &[-2.0f32, 0.0, 3.0] {
            let n = fd(f64::exp, x as f64);
            assert!((trunc_exp_grad(x) as f64 - n).abs() / n < 1e-4);
        }
        assert!(trunc_exp(1e6).is_finite());
        assert_eq!(trunc_exp_grad(100.0), 15f32.exp());
    }

    #[test]
    fn softplus_matches_fd() {
        for &x in &[-30.0f32, -2.0, 0.0, 1.5, 30.0] {
            let n = fd(|v| (1.0 + v.exp()).ln(), x as f64);
            assert!((softplus_grad(x) as f64 - n).abs() < 1e-5);
            assert!(softplus(x).is_finite());
        }
    }
}
