//! Uncertainty-guided mask learning (paper §3.3, method.md §3), training only.
//!
//! - An uncertainty voxel grid `u~` with `u(x) = u_min + softplus(u~(x))`.
//! - The ray uncertainty `U(r) = sum_i w_i u(x_i) + U_EPS` with the colour weights `w_i`
//!   (`U_EPS` keeps `U` away from 0 on empty rays).
//! - The loss `L_u = |C - C_s|^2 / (2 U^2) + log U` between the full colour `C` and the colour
//!   `C_s` of the time-agnostic static branch (`|.|^2` is the mean over channels).
//! - The MINE estimate of the mutual information of the mask and the uncertainty,
//!   `I = mean_j T(m_j, u_j) - log mean_j exp T(m_j, u_{perm(j)})`, with a small MLP `T` with two
//!   hidden layers on `(m, u, 1)`, computed with a stable log-mean-exp.
//!
//! None of these parameters belong to the model: they live in their own buffer
//! ([`AuxLayout`]), so the codec never sees them.

use std::ops::Range;

use serde::{Deserialize, Serialize};

use crate::activation::{softplus, softplus_grad};
use crate::grid::DenseGrid3;
use crate::mlp::{MlpActivations, MlpLayout};
use crate::params::ParamLayout;
use crate::rng::Rng;

/// Added to every ray uncertainty so that `1 / U^2` and `log U` stay finite on empty rays.
pub const U_EPS: f32 = 1e-3;

/// Settings of the uncertainty-guided mask learning; every term is off by default.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaskLearningConfig {
    /// Train the uncertainty grid and the static branch with `L_u`.
    pub uncertainty: bool,
    /// `lambda`, the weight of `L_u` (paper: 3e-5).
    pub uncertainty_weight: f32,
    /// `u_min`, the shift of `u = u_min + softplus(u~)`.
    pub uncertainty_min: f32,
    /// Vertices per side of the uncertainty grid.
    pub uncertainty_resolution: usize,
    /// Maximise `I(m, u)` with MINE (needs `uncertainty`).
    pub mine: bool,
    /// `gamma`, the weight of `-I` (paper: 3e-4).
    pub mine_weight: f32,
    /// Width of the two hidden layers of `T_theta`.
    pub mine_hidden: usize,
}

impl Default for MaskLearningConfig {
    fn default() -> Self {
        MaskLearningConfig {
            uncertainty: false,
            uncertainty_weight: 3e-5,
            uncertainty_min: 0.01,
            uncertainty_resolution: 64,
            mine: false,
            mine_weight: 3e-4,
            mine_hidden: 16,
        }
    }
}

/// Why a mask-learning configuration was rejected by [`MaskLearningConfig::validate`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct InvalidMaskLearning(pub String);

impl MaskLearningConfig {
    /// Whether any term is on.
    pub fn enabled(&self) -> bool {
        self.uncertainty || self.mine
    }

    pub fn validate(&self) -> Result<(), InvalidMaskLearning> {
        for (n, v) in [
            ("uncertainty_weight", self.uncertainty_weight),
            ("mine_weight", self.mine_weight),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(InvalidMaskLearning(format!(
                    "mask_learning.{n} must be finite and >= 0"
                )));
            }
        }
        if !(self.uncertainty_min.is_finite() && self.uncertainty_min >= 0.0) {
            return Err(InvalidMaskLearning(
                "mask_learning.uncertainty_min must be finite and >= 0".into(),
            ));
        }
        if !(2..=256).contains(&self.uncertainty_resolution) {
            return Err(InvalidMaskLearning(
                "mask_learning.uncertainty_resolution must be in 2..=256".into(),
            ));
        }
        if !(1..=256).contains(&self.mine_hidden) {
            return Err(InvalidMaskLearning(
                "mask_learning.mine_hidden must be in 1..=256".into(),
            ));
        }
        if self.mine && !self.uncertainty {
            return Err(InvalidMaskLearning(
                "mask_learning.mine needs mask_learning.uncertainty".into(),
            ));
        }
        Ok(())
    }
}

/// The auxiliary (training-only) parameter buffer: uncertainty grid and MINE network.
#[derive(Clone, Debug, PartialEq)]
pub struct AuxLayout {
    pub params: ParamLayout,
    pub grid: (DenseGrid3, Range<usize>),
    pub mine: (MlpLayout, Range<usize>),
    pub u_min: f32,
}

impl AuxLayout {
    pub fn new(cfg: &MaskLearningConfig) -> Self {
        let mut params = ParamLayout::default();
        let g = DenseGrid3 {
            res: cfg.uncertainty_resolution,
        };
        let gr = params.push("aux.uncertainty", g.num_params());
        let h = cfg.mine_hidden;
        let m = MlpLayout::new(&[3, h, h, 1]);
        let mr = params.push("aux.mine", m.num_params);
        AuxLayout {
            params,
            grid: (g, gr),
            mine: (m, mr),
            u_min: cfg.uncertainty_min,
        }
    }

    /// Initial parameters: uncertainty logits 0, MINE network Glorot-uniform.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut p = vec![0f32; self.params.total];
        let mut rng = Rng::stream(seed, 0xA0C5);
        self.mine.0.init(&mut p[self.mine.1.clone()], &mut rng);
        p
    }

    /// `u(x) = u_min + softplus(u~(x))` at a unit-cube point.
    pub fn uncertainty_at(&self, params: &[f32], x: &[f32]) -> f32 {
        let (g, r) = &self.grid;
        self.u_min + softplus(g.sample(&params[r.clone()], x))
    }

    /// Backward of [`AuxLayout::uncertainty_at`]: adds `d * du/du~` into the grid's gradient.
    pub fn uncertainty_backward(&self, params: &[f32], x: &[f32], d: f32, grad: &mut [f32]) {
        let (g, r) = &self.grid;
        let raw = g.sample(&params[r.clone()], x);
        g.backward(x, d * softplus_grad(raw), &mut grad[r.clone()]);
    }
}

/// `U = sum_i w_i u_i + U_EPS`.
pub fn ray_uncertainty(w: &[f32], u: &[f32]) -> f32 {
    w.iter().zip(u).map(|(a, b)| a * b).sum::<f32>() + U_EPS
}

/// Backward of [`ray_uncertainty`]: adds `d_u_ray * u_i` into `d_w` and `d_u_ray * w_i` into `d_u`.
pub fn ray_uncertainty_backward(
    w: &[f32],
    u: &[f32],
    d_u_ray: f32,
    d_w: &mut [f32],
    d_u: &mut [f32],
) {
    for i in 0..w.len() {
        d_w[i] += d_u_ray * u[i];
        d_u[i] += d_u_ray * w[i];
    }
}

/// Gradients of [`uncertainty_loss`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct UncertaintyGrad {
    pub d_c: [f32; 3],
    pub d_cs: [f32; 3],
    pub d_u: f32,
}

/// `L_u = mean_ch (C - C_s)^2 / (2 U^2) + log U` for one ray, and its gradient times `scale`.
/// `U` must be positive (it is at least [`U_EPS`] by construction); it is clamped there anyway.
pub fn uncertainty_loss(c: [f32; 3], cs: [f32; 3], u: f32, scale: f32) -> (f32, UncertaintyGrad) {
    let u = u.max(U_EPS);
    let mut se = 0f32;
    let mut g = UncertaintyGrad::default();
    let inv2 = 1.0 / (u * u);
    for ch in 0..3 {
        let d = c[ch] - cs[ch];
        se += d * d / 3.0;
        // d/dC of d^2 / (6 U^2)
        g.d_c[ch] = d / 3.0 * inv2 * scale;
        g.d_cs[ch] = -g.d_c[ch];
    }
    let loss = 0.5 * se * inv2 + u.ln();
    g.d_u = (-se * inv2 / u + 1.0 / u) * scale;
    (loss, g)
}

/// `log(mean(exp(x)))`, stable for any finite `x` (shifted by the maximum). Also writes the
/// softmax weights `exp(x_j) / sum exp(x)` (the gradient of the result times `n`) into `soft`.
pub fn log_mean_exp(x: &[f32], soft: &mut [f32]) -> f32 {
    let n = x.len();
    if n == 0 {
        return 0.0;
    }
    let mx = x.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut s = 0f64;
    for (j, &v) in x.iter().enumerate() {
        let e = ((v - mx) as f64).exp();
        soft[j] = e as f32;
        s += e;
    }
    for v in soft.iter_mut() {
        *v = (*v as f64 / s) as f32;
    }
    mx + (s / n as f64).ln() as f32
}

/// Scratch of the batched MINE estimator.
#[derive(Clone, Debug, Default)]
pub struct MineScratch {
    input: Vec<f32>,
    acts: MlpActivations,
    t_marg: Vec<f32>,
    soft: Vec<f32>,
    d_out: Vec<f32>,
    d_in: Vec<f32>,
}

/// The MINE statistic network `T_theta(m, u)` of one pair (plain reference).
pub fn mine_t_reference(mlp: &MlpLayout, params: &[f32], m: f32, u: f32) -> f32 {
    mlp.forward_reference(params, &[m, u, 1.0])[0]
}

/// Plain reference of the MINE estimate: `mean_j T(m_j, u_j) - log mean_j exp T(m_j, u_perm(j))`.
pub fn mine_reference(
    mlp: &MlpLayout,
    params: &[f32],
    m: &[f32],
    u: &[f32],
    perm: &[usize],
) -> f64 {
    let n = m.len();
    let joint: f64 = (0..n)
        .map(|j| mine_t_reference(mlp, params, m[j], u[j]) as f64)
        .sum::<f64>()
        / n as f64;
    let marg: Vec<f64> = (0..n)
        .map(|j| mine_t_reference(mlp, params, m[j], u[perm[j]]) as f64)
        .collect();
    let mx = marg.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lme = mx + (marg.iter().map(|v| (v - mx).exp()).sum::<f64>() / n as f64).ln();
    joint - lme
}

/// Batched MINE estimate over `n` pairs with marginal pairs `(m_j, u_perm(j))`. Adds
/// `scale * dI/dtheta` into `grad` (the MLP's slice) and `scale * dI/dm`, `scale * dI/du` into
/// `d_m`, `d_u`; returns `I`.
#[allow(clippy::too_many_arguments)]
pub fn mine_estimate(
    mlp: &MlpLayout,
    params: &[f32],
    m: &[f32],
    u: &[f32],
    perm: &[usize],
    scale: f32,
    grad: &mut [f32],
    d_m: &mut [f32],
    d_u: &mut [f32],
    s: &mut MineScratch,
) -> f32 {
    let n = m.len();
    if n == 0 {
        return 0.0;
    }
    s.input.clear();
    for j in 0..n {
        s.input.extend_from_slice(&[m[j], u[j], 1.0]);
    }
    for j in 0..n {
        s.input.extend_from_slice(&[m[j], u[perm[j]], 1.0]);
    }
    mlp.forward(params, &s.input, 2 * n, &mut s.acts);
    let t = mlp.output(&s.acts);
    let joint = t[..n].iter().map(|&v| v as f64).sum::<f64>() / n as f64;
    s.t_marg.clear();
    s.t_marg.extend_from_slice(&t[n..2 * n]);
    s.soft.resize(n, 0.0);
    let lme = log_mean_exp(&s.t_marg, &mut s.soft);
    s.d_out.resize(2 * n, 0.0);
    for j in 0..n {
        s.d_out[j] = scale / n as f32;
        s.d_out[n + j] = -scale * s.soft[j];
    }
    s.d_in.resize(2 * n * 3, 0.0);
    mlp.backward(
        params,
        &s.input,
        2 * n,
        &mut s.acts,
        &s.d_out,
        grad,
        Some(&mut s.d_in),
    );
    for j in 0..n {
        d_m[j] += s.d_in[j * 3] + s.d_in[(n + j) * 3];
        d_u[j] += s.d_in[j * 3 + 1];
        d_u[perm[j]] += s.d_in[(n + j) * 3 + 1];
    }
    (joint - lme as f64) as f32
}

/// A random permutation of `0..n` (Fisher-Yates) for the marginal samples.
pub fn shuffle(n: usize, rng: &mut Rng, perm: &mut Vec<usize>) {
    perm.clear();
    perm.extend(0..n);
    for i in (1..n).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        perm.swap(i, j);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fd(f: impl Fn(f64) -> f64, x: f64, h: f64) -> f64 {
        (f(x + h) - f(x - h)) / (2.0 * h)
    }

    #[test]
    fn uncertainty_grid_lookup_and_backward_match_fd() {
        let cfg = MaskLearningConfig {
            uncertainty_resolution: 5,
            ..Default::default()
        };
        let aux = AuxLayout::new(&cfg);
        let mut rng = Rng::new(3);
        let mut p = aux.init_params(1);
        for v in &mut p[aux.grid.1.clone()] {
            *v = rng.range_f32(-3.0, 3.0);
        }
        let x = [0.31f32, 0.62, 0.77];
        let mut g = vec![0f32; p.len()];
        aux.uncertainty_backward(&p, &x, 1.0, &mut g);
        // reference: softplus of the trilinear value, in f64
        assert!(aux.uncertainty_at(&p, &x) >= cfg.uncertainty_min);
        let mut checked = 0;
        for i in aux.grid.1.clone() {
            if g[i] == 0.0 {
                continue;
            }
            let f = |v: f64| {
                let mut q = p.clone();
                q[i] = v as f32;
                aux.uncertainty_at(&q, &x) as f64
            };
            let d = fd(f, p[i] as f64, 1e-2);
            assert!((d - g[i] as f64).abs() < 1e-3, "{i}: {d} vs {}", g[i]);
            checked += 1;
        }
        assert_eq!(checked, 8);
    }

    #[test]
    fn ray_uncertainty_backward_matches_fd() {
        let mut rng = Rng::new(4);
        let n = 7;
        let w: Vec<f32> = (0..n).map(|_| rng.f32() * 0.2).collect();
        let u: Vec<f32> = (0..n).map(|_| rng.f32() + 0.01).collect();
        let mut dw = vec![0f32; n];
        let mut du = vec![0f32; n];
        ray_uncertainty_backward(&w, &u, 0.7, &mut dw, &mut du);
        for k in 0..n {
            let fw = |v: f64| {
                let mut a = w.clone();
                a[k] = v as f32;
                0.7 * ray_uncertainty(&a, &u) as f64
            };
            let fu = |v: f64| {
                let mut a = u.clone();
                a[k] = v as f32;
                0.7 * ray_uncertainty(&w, &a) as f64
            };
            assert!((fd(fw, w[k] as f64, 1e-2) - dw[k] as f64).abs() < 1e-4);
            assert!((fd(fu, u[k] as f64, 1e-2) - du[k] as f64).abs() < 1e-4);
        }
    }

    #[test]
    fn uncertainty_loss_backward_matches_fd_and_extremes_are_finite() {
        let c = [0.2f32, 0.7, 0.4];
        let cs = [0.5f32, 0.1, 0.45];
        let u = 0.8f32;
        let (_, g) = uncertainty_loss(c, cs, u, 1.0);
        for ch in 0..3 {
            let f = |v: f64| {
                let mut a = c;
                a[ch] = v as f32;
                uncertainty_loss(a, cs, u, 1.0).0 as f64
            };
            assert!((fd(f, c[ch] as f64, 1e-3) - g.d_c[ch] as f64).abs() < 1e-3);
            let f = |v: f64| {
                let mut a = cs;
                a[ch] = v as f32;
                uncertainty_loss(c, a, u, 1.0).0 as f64
            };
            assert!((fd(f, cs[ch] as f64, 1e-3) - g.d_cs[ch] as f64).abs() < 1e-3);
        }
        let f = |v: f64| uncertainty_loss(c, cs, v as f32, 1.0).0 as f64;
        assert!((fd(f, u as f64, 1e-3) - g.d_u as f64).abs() < 1e-3);
        // U at and below its floor, huge U, maximal colour differences.
        for &u in &[0.0f32, -1.0, U_EPS, 1e-2, 1.0, 1e6, f32::MAX] {
            for (c, cs) in [([0.0; 3], [1.0; 3]), ([0.5; 3], [0.5; 3])] {
                let (l, g) = uncertainty_loss(c, cs, u, 1.0);
                assert!(l.is_finite(), "U {u}: {l}");
                assert!(
                    g.d_u.is_finite() && g.d_c.iter().all(|v| v.is_finite()),
                    "U {u}"
                );
            }
        }
    }

    #[test]
    fn log_mean_exp_is_stable() {
        let mut soft = vec![0f32; 3];
        let l = log_mean_exp(&[1000.0, 1000.0, 1000.0], &mut soft);
        assert!((l - 1000.0).abs() < 1e-3);
        assert!(soft.iter().all(|&s| (s - 1.0 / 3.0).abs() < 1e-6));
        let l = log_mean_exp(&[-1000.0, 0.0, 80.0], &mut soft);
        assert!((l - (80.0 - 3f32.ln())).abs() < 1e-3, "{l}");
        assert!(soft[2] > 0.999 && soft.iter().all(|v| v.is_finite()));
        let l = log_mean_exp(&[0.3, -0.2, 0.1], &mut soft);
        let direct = ((0.3f64.exp() + (-0.2f64).exp() + 0.1f64.exp()) / 3.0).ln();
        assert!((l as f64 - direct).abs() < 1e-6);
    }

    fn mine_setup(n: usize, seed: u64) -> (AuxLayout, Vec<f32>, Vec<f32>, Vec<f32>, Vec<usize>) {
        let cfg = MaskLearningConfig {
            mine_hidden: 6,
            uncertainty_resolution: 2,
            ..Default::default()
        };
        let aux = AuxLayout::new(&cfg);
        let p = aux.init_params(seed);
        let mut rng = Rng::new(seed + 7);
        let m: Vec<f32> = (0..n).map(|_| rng.f32()).collect();
        let u: Vec<f32> = (0..n).map(|_| rng.range_f32(0.01, 2.0)).collect();
        let mut perm = Vec::new();
        shuffle(n, &mut rng, &mut perm);
        (aux, p, m, u, perm)
    }

    /// [`mine_estimate`] at scale 1 into fresh buffers: the estimate and its gradients in `p`
    /// (the MINE slice written, the rest 0), in `m` and in `u`.
    fn estimate(
        aux: &AuxLayout,
        p: &[f32],
        m: &[f32],
        u: &[f32],
        perm: &[usize],
    ) -> (f32, Vec<f32>, Vec<f32>, Vec<f32>) {
        let (mlp, r) = &aux.mine;
        let mut grad = vec![0f32; p.len()];
        let (mut dm, mut du) = (vec![0f32; m.len()], vec![0f32; u.len()]);
        let i = mine_estimate(
            mlp,
            &p[r.clone()],
            m,
            u,
            perm,
            1.0,
            &mut grad[r.clone()],
            &mut dm,
            &mut du,
            &mut MineScratch::default(),
        );
        (i, grad, dm, du)
    }

    #[test]
    fn mine_matches_reference_and_fd_in_weights_and_inputs() {
        let n = 9;
        let (aux, p, m, u, perm) = mine_setup(n, 2);
        let (mlp, r) = &aux.mine;
        let (i, grad, dm, du) = estimate(&aux, &p, &m, &u, &perm);
        let reference = mine_reference(mlp, &p[r.clone()], &m, &u, &perm);
        assert!((i as f64 - reference).abs() < 1e-5, "{i} vs {reference}");
        let h = 1e-3;
        let close = |what: String, d: f64, g: f32| {
            assert!(
                (d - g as f64).abs() < 2e-3 + 1e-2 * d.abs(),
                "{what}: {d} vs {g}"
            );
        };
        for k in r.clone() {
            let f = |v: f64| {
                let mut q = p.clone();
                q[k] = v as f32;
                mine_reference(mlp, &q[r.clone()], &m, &u, &perm)
            };
            close(format!("w{k}"), fd(f, p[k] as f64, h), grad[k]);
        }
        for j in 0..n {
            let f = |v: f64| {
                let mut a = m.clone();
                a[j] = v as f32;
                mine_reference(mlp, &p[r.clone()], &a, &u, &perm)
            };
            close(format!("m{j}"), fd(f, m[j] as f64, h), dm[j]);
            let f = |v: f64| {
                let mut a = u.clone();
                a[j] = v as f32;
                mine_reference(mlp, &p[r.clone()], &m, &a, &perm)
            };
            close(format!("u{j}"), fd(f, u[j] as f64, h), du[j]);
        }
    }

    /// Saturated statistics (huge weights, huge inputs) give a finite estimate and gradients.
    #[test]
    fn mine_extremes_stay_finite() {
        let n = 16;
        let (aux, mut p, m, _, perm) = mine_setup(n, 5);
        for v in &mut p[aux.mine.1.clone()] {
            *v *= 40.0;
        }
        for u_val in [U_EPS, 1.0, 1e4] {
            let u = vec![u_val; n];
            let (i, grad, dm, du) = estimate(&aux, &p, &m, &u, &perm);
            assert!(i.is_finite(), "u {u_val}: {i}");
            assert!(grad.iter().chain(&dm).chain(&du).all(|v| v.is_finite()));
        }
    }
}
