//! Finite-difference helpers shared by the gradient tests of the crate's modules (compiled for
//! tests only).

/// The central difference of `loss` along entry `i` of `p`: `p_i + h`, then `- 2h` from there
/// (the order the gradient tests have always stepped in), divided by `2h`.
pub fn central_difference(loss: impl Fn(&[f32]) -> f64, p: &[f32], i: usize, h: f32) -> f64 {
    let mut q = p.to_vec();
    q[i] += h;
    let lp = loss(&q);
    q[i] -= 2.0 * h;
    let lm = loss(&q);
    (lp - lm) / (2.0 * h as f64)
}

/// The indices of `range`, largest `|grad|` first (ties keep their order).
pub fn largest_first(range: std::ops::Range<usize>, grad: impl Fn(usize) -> f64) -> Vec<usize> {
    let mut idx: Vec<usize> = range.collect();
    idx.sort_by(|&a, &b| grad(b).abs().partial_cmp(&grad(a).abs()).unwrap());
    idx
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn central_difference_of_a_quadratic_is_its_slope() {
        let loss = |q: &[f32]| q.iter().map(|&v| (v as f64).powi(2)).sum::<f64>();
        let p = [0.5f32, -2.0, 3.0];
        for (i, &v) in p.iter().enumerate() {
            let fd = central_difference(loss, &p, i, 1e-2);
            assert!((fd - 2.0 * v as f64).abs() < 1e-4, "{i}: {fd}");
        }
    }

    #[test]
    fn largest_first_orders_by_magnitude() {
        let g = [0.1, -3.0, 2.0, -0.5];
        assert_eq!(largest_first(0..4, |i| g[i]), [1, 2, 3, 0]);
        assert_eq!(largest_first(2..4, |i| g[i]), [2, 3]);
    }
}
