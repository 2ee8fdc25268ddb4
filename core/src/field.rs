//! The masked space-time field: encoding (3D grid, 4D grid, mask, blend) followed by the
//! decoders, batched forward and backward over the points of a chunk of rays.
//!
//! Points arrive as `[n, 4]` rows `(x, y, z, t)` in the unit cube / unit time. The main field
//! returns density and colour; the proposal field density only.

use std::ops::Range;

use crate::activation::{sigmoid, sigmoid_grad_from_output, trunc_exp, trunc_exp_grad};
use crate::config::{BlendMode, EncodingConfig, FieldConfig, ModelConfig, ProposalConfig};
use crate::grid::{backward_pair, encode_pair, pairable, DenseGrid3, GridLayout};
use crate::mlp::{MlpActivations, MlpLayout};
use crate::params::ParamLayout;
use crate::rng::Rng;
use crate::sh::SH_COEFFS;

/// Where the masked encoding's parts live in the flat buffer.
#[derive(Clone, Debug, PartialEq)]
pub struct EncodingLayout {
    pub blend: BlendMode,
    pub h3: Option<(GridLayout, Range<usize>)>,
    pub h4: Option<(GridLayout, Range<usize>)>,
    pub mask: Option<(DenseGrid3, Range<usize>)>,
    pub mask_init: f32,
    pub out_dim: usize,
}

/// The coarse-to-fine factor of level `level` when `active` levels are on:
/// `clamp(active - level, 0, 1)` (1 for every level once `active` reaches the level count).
pub fn level_factor(active: f32, level: usize) -> f32 {
    (active - level as f32).clamp(0.0, 1.0)
}

/// Scratch buffers of one encoding pass.
#[derive(Clone, Debug, Default)]
pub struct EncodingScratch {
    pub h3: Vec<f32>,
    pub h4: Vec<f32>,
    /// `m = sigmoid(mask logit)` per point (1 where there is no mask).
    pub m: Vec<f32>,
    pub enc: Vec<f32>,
    /// Inference only: points whose dynamic weight `1 - m` is below this skip the 4D lookup
    /// (their `h4` is taken as 0, changing the encoding by less than `cutoff * |h4|`). 0, the
    /// default and what training uses, evaluates every point exactly.
    pub static_cutoff: f32,
    /// Training only: an extra `dL/dm` per point added in [`EncodingLayout::backward`] (the
    /// mutual-information term of mask learning); empty, the default, adds nothing.
    pub d_m_extra: Vec<f32>,
    /// Training only: the coarse-to-fine factor of [`crate::pipeline::StepSettings::active_levels`];
    /// `None`, the default, leaves every level on.
    pub active_levels: Option<f32>,
    /// `d_enc` scaled by the level factors (backward under `active_levels`).
    d_enc_ramped: Vec<f32>,
    d_h3: Vec<f32>,
    d_h4: Vec<f32>,
    /// Points that get a 4D lookup under `static_cutoff`, and their packed inputs and outputs.
    h4_active: Vec<u32>,
    h4_points: Vec<f32>,
    h4_packed: Vec<f32>,
}

impl EncodingLayout {
    pub fn new(cfg: &EncodingConfig, prefix: &str, params: &mut ParamLayout) -> Self {
        let h3 = cfg.blend.uses_h3().then(|| {
            let g = GridLayout::new(&cfg.grid3);
            let r = params.push(&format!("{prefix}.h3"), g.num_params);
            (g, r)
        });
        let h4 = cfg.blend.uses_h4().then(|| {
            let g = GridLayout::new(&cfg.grid4);
            let r = params.push(&format!("{prefix}.h4"), g.num_params);
            (g, r)
        });
        let mask = cfg.blend.uses_mask().then(|| {
            let d = DenseGrid3 {
                res: cfg.mask_resolution,
            };
            let r = params.push(&format!("{prefix}.mask"), d.num_params());
            (d, r)
        });
        let out_dim = h3
            .as_ref()
            .or(h4.as_ref())
            .map(|(g, _)| g.output_dim())
            .unwrap_or(0);
        EncodingLayout {
            blend: cfg.blend,
            h3,
            h4,
            mask,
            mask_init: cfg.mask_init,
            out_dim,
        }
    }

    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        for (_, r) in self.h3.iter().chain(self.h4.iter()) {
            for v in &mut params[r.clone()] {
                *v = rng.range_f32(-1e-4, 1e-4);
            }
        }
        if let Some((_, r)) = &self.mask {
            params[r.clone()].fill(self.mask_init);
        }
    }

    /// Mask value `m` in `[0, 1]` at a unit-cube point (1 when the mode has no mask and h3 only,
    /// 0 for 4D only, 0.5 for addition, meaning "both").
    pub fn mask_at(&self, params: &[f32], x: &[f32]) -> f32 {
        match &self.mask {
            Some((d, r)) => sigmoid(d.sample(&params[r.clone()], x)),
            None => self.blend.no_mask_value(),
        }
    }

    /// Fractions of mask vertices with `m = sigmoid(logit)` below `lo` and above `hi` (how
    /// decided the mask is); `None` without a mask.
    pub fn mask_fractions(&self, params: &[f32], lo: f32, hi: f32) -> Option<(f64, f64)> {
        let (_, r) = self.mask.as_ref()?;
        let vals = &params[r.clone()];
        let (mut below, mut above) = (0usize, 0usize);
        for &v in vals {
            let m = sigmoid(v);
            below += (m < lo) as usize;
            above += (m > hi) as usize;
        }
        let n = vals.len().max(1) as f64;
        Some((below as f64 / n, above as f64 / n))
    }

    /// Plain reference encoding of one point `(x, y, z, t)`.
    pub fn encode_point_reference(&self, params: &[f32], p: &[f32]) -> (Vec<f32>, f32) {
        let h3 = self
            .h3
            .as_ref()
            .map(|(g, r)| g.encode_point_reference(&params[r.clone()], &p[..3]));
        let h4 = self
            .h4
            .as_ref()
            .map(|(g, r)| g.encode_point_reference(&params[r.clone()], &p[..4]));
        let m = self.mask_at(params, p);
        let mut enc = vec![0f32; self.out_dim];
        for k in 0..self.out_dim {
            let a = h3.as_ref().map(|v| v[k]).unwrap_or(0.0);
            let b = h4.as_ref().map(|v| v[k]).unwrap_or(0.0);
            let (ca, cb) = self.blend.coefficients(m);
            enc[k] = ca * a + cb * b;
        }
        (enc, m)
    }

    /// Batched forward over `n` points (`points: [n, 4]`); result in `s.enc` (`[n, out_dim]`).
    /// The same as [`EncodingLayout::forward_static`] then [`EncodingLayout::forward_dynamic`];
    /// where both grids share their spatial corners (every preset), h3 and h4 are looked up in
    /// one pass ([`crate::grid::encode_pair`], the same values).
    pub fn forward(&self, params: &[f32], points: &[f32], n: usize, s: &mut EncodingScratch) {
        let e = self.out_dim;
        match (&self.h3, &self.h4) {
            (Some((g3, r3)), Some((g4, r4))) if !self.skips_h4(s) && pairable(g3, g4) => {
                s.h3.resize(n * e, 0.0);
                s.h4.resize(n * e, 0.0);
                encode_pair(
                    g3,
                    &params[r3.clone()],
                    g4,
                    &params[r4.clone()],
                    &points[..n * 4],
                    4,
                    &mut s.h3,
                    &mut s.h4,
                    e,
                    0,
                );
                self.mask_values(params, points, n, s);
                self.blend_into(n, s);
            }
            _ => {
                self.forward_static(params, points, n, s);
                self.forward_dynamic(params, points, n, s);
            }
        }
        self.ramp_levels(n, s);
    }

    /// Scales `s.enc` of `n` points by the level factors of `s.active_levels` (training's
    /// coarse-to-fine ramp; nothing when every level is on).
    fn ramp_levels(&self, n: usize, s: &mut EncodingScratch) {
        let e = self.out_dim;
        if let Some(active) = self.ramp(s) {
            let f = self.features_per_level();
            for row in s.enc[..n * e].chunks_exact_mut(e) {
                for (k, v) in row.iter_mut().enumerate() {
                    *v *= level_factor(active, k / f);
                }
            }
        }
    }

    /// Features per level (of either grid: the blends need the same).
    fn features_per_level(&self) -> usize {
        let g = self.h3.as_ref().or(self.h4.as_ref());
        g.map(|(g, _)| g.features).unwrap_or(1).max(1)
    }

    /// `s.active_levels` where it turns some level down (below the level count), else `None`.
    fn ramp(&self, s: &EncodingScratch) -> Option<f32> {
        let levels = (self.out_dim / self.features_per_level()) as f32;
        s.active_levels.filter(|&a| a < levels)
    }

    /// The part of the encoding that does not depend on time: `s.h3` and the mask values `s.m`
    /// of `n` points (the time column of `points` is not read).
    pub fn forward_static(
        &self,
        params: &[f32],
        points: &[f32],
        n: usize,
        s: &mut EncodingScratch,
    ) {
        if let Some((g, r)) = &self.h3 {
            s.h3.resize(n * self.out_dim, 0.0);
            g.encode(
                &params[r.clone()],
                &points[..n * 4],
                4,
                &mut s.h3,
                self.out_dim,
                0,
            );
        }
        self.mask_values(params, points, n, s);
    }

    /// The part that depends on time, after [`EncodingLayout::forward_static`] on the same
    /// points: `s.h4` (only where the mask leaves a point dynamic under `s.static_cutoff`) and
    /// the blend into `s.enc`.
    pub fn forward_dynamic(
        &self,
        params: &[f32],
        points: &[f32],
        n: usize,
        s: &mut EncodingScratch,
    ) {
        let e = self.out_dim;
        if let Some((g, r)) = &self.h4 {
            s.h4.resize(n * e, 0.0);
            if self.skips_h4(s) {
                // Look up only the points the mask leaves dynamic, packed, then scatter.
                s.h4_active.clear();
                s.h4_active.extend((0..n as u32).filter(|&i| {
                    self.blend
                        .is_dynamic(true, s.m[i as usize], s.static_cutoff)
                }));
                s.h4_points.clear();
                for &i in &s.h4_active {
                    let i = i as usize;
                    s.h4_points.extend_from_slice(&points[i * 4..i * 4 + 4]);
                }
                let k = s.h4_active.len();
                s.h4_packed.resize(k * e, 0.0);
                g.encode(&params[r.clone()], &s.h4_points, 4, &mut s.h4_packed, e, 0);
                s.h4[..n * e].fill(0.0);
                for (j, &i) in s.h4_active.iter().enumerate() {
                    let i = i as usize;
                    s.h4[i * e..(i + 1) * e].copy_from_slice(&s.h4_packed[j * e..(j + 1) * e]);
                }
            } else {
                g.encode(&params[r.clone()], &points[..n * 4], 4, &mut s.h4, e, 0);
            }
        }
        self.blend_into(n, s);
    }

    /// Whether point `i` of the last forward pass needs the 4D grid under `s.static_cutoff`
    /// ([`BlendMode::is_dynamic`] at its mask value `s.m[i]`).
    pub fn is_dynamic(&self, s: &EncodingScratch, i: usize) -> bool {
        self.blend
            .is_dynamic(self.mask.is_some(), s.m[i], s.static_cutoff)
    }

    /// The time-independent part of point `i` of the last forward pass, kept to evaluate the
    /// point at other times with [`EncodingLayout::forward_dynamic_prescaled`]: appends the
    /// blend's static term `a(m) h3` (the 3D features already multiplied by the mask's static
    /// share; nothing without h3) to `static_term` and returns the 4D coefficient `b(m)`
    /// ([`BlendMode::coefficients`]).
    pub fn static_term(&self, s: &EncodingScratch, i: usize, static_term: &mut Vec<f32>) -> f32 {
        let (a, b) = self.blend.coefficients(s.m[i]);
        if self.h3.is_some() {
            let e = self.out_dim;
            static_term.extend(s.h3[i * e..(i + 1) * e].iter().map(|v| a * v));
        }
        b
    }

    /// [`EncodingLayout::forward_dynamic`] of `n` points from their kept static parts
    /// ([`EncodingLayout::static_term`]: `static_term: [n, out_dim]`, empty without h3, and
    /// `b: [n]`) instead of `s.h3` and `s.m`: the 4D lookup at every point, then
    /// `s.enc = b h4 + static_term`. The same bits as the blend of the full pass, whose products
    /// are the same.
    pub fn forward_dynamic_prescaled(
        &self,
        params: &[f32],
        points: &[f32],
        n: usize,
        static_term: &[f32],
        b: &[f32],
        s: &mut EncodingScratch,
    ) {
        let e = self.out_dim;
        s.enc.clear();
        s.enc.resize(n * e, 0.0);
        if let Some((g, r)) = &self.h4 {
            s.h4.resize(n * e, 0.0);
            g.encode(&params[r.clone()], &points[..n * 4], 4, &mut s.h4, e, 0);
            for i in 0..n {
                for k in i * e..(i + 1) * e {
                    s.enc[k] = b[i] * s.h4[k];
                }
            }
        }
        if self.h3.is_some() {
            for (v, h) in s.enc.iter_mut().zip(&static_term[..n * e]) {
                *v += h;
            }
        }
        self.ramp_levels(n, s);
    }

    /// Whether the 4D lookup is skipped for points the mask makes static (`s.static_cutoff`).
    fn skips_h4(&self, s: &EncodingScratch) -> bool {
        s.static_cutoff > 0.0
            && self.mask.is_some()
            && matches!(self.blend, BlendMode::Mst | BlendMode::Mt)
    }

    /// `s.m` of `n` points: the mask, or 1 without one (the scratch's documented filler; the
    /// blends without a mask do not read it, and [`EncodingLayout::mask_at`] reports
    /// [`BlendMode::no_mask_value`]).
    fn mask_values(&self, params: &[f32], points: &[f32], n: usize, s: &mut EncodingScratch) {
        s.m.clear();
        match &self.mask {
            Some((d, r)) => {
                let vals = &params[r.clone()];
                s.m.extend((0..n).map(|i| sigmoid(d.sample(vals, &points[i * 4..i * 4 + 3]))));
            }
            None => s.m.resize(n, 1.0),
        }
    }

    /// `s.enc = a(m) h3 + b(m) h4` ([`BlendMode::coefficients`]), written per mode so that a
    /// grid the mode does not use is never read.
    fn blend_into(&self, n: usize, s: &mut EncodingScratch) {
        let e = self.out_dim;
        s.enc.resize(n * e, 0.0);
        match self.blend {
            BlendMode::Mst => {
                for i in 0..n {
                    let m = s.m[i];
                    for k in i * e..(i + 1) * e {
                        s.enc[k] = m * s.h3[k] + (1.0 - m) * s.h4[k];
                    }
                }
            }
            BlendMode::Mt => {
                for i in 0..n {
                    let m = s.m[i];
                    for k in i * e..(i + 1) * e {
                        s.enc[k] = s.h3[k] + (1.0 - m) * s.h4[k];
                    }
                }
            }
            BlendMode::Add => {
                for k in 0..n * e {
                    s.enc[k] = s.h3[k] + s.h4[k];
                }
            }
            BlendMode::FourD => s.enc[..n * e].copy_from_slice(&s.h4[..n * e]),
            BlendMode::Static => s.enc[..n * e].copy_from_slice(&s.h3[..n * e]),
        }
    }

    /// Backward of the last forward given `d_enc: [n, out_dim]`; accumulates into `grad`.
    pub fn backward(
        &self,
        points: &[f32],
        n: usize,
        s: &mut EncodingScratch,
        d_enc: &[f32],
        grad: &mut [f32],
    ) {
        let e = self.out_dim;
        let mut ramped = std::mem::take(&mut s.d_enc_ramped);
        let d_enc = match self.ramp(s) {
            Some(active) => {
                let f = self.features_per_level();
                ramped.clear();
                ramped.extend(
                    d_enc[..n * e]
                        .iter()
                        .enumerate()
                        .map(|(k, &d)| d * level_factor(active, (k % e) / f)),
                );
                &ramped[..]
            }
            None => d_enc,
        };
        let (use3, use4) = (self.h3.is_some(), self.h4.is_some());
        if use3 {
            s.d_h3.resize(n * e, 0.0);
        }
        if use4 {
            s.d_h4.resize(n * e, 0.0);
        }
        for i in 0..n {
            let m = s.m[i];
            let row = i * e..(i + 1) * e;
            let mut dm = 0f32;
            match self.blend {
                BlendMode::Mst => {
                    for k in row {
                        s.d_h3[k] = m * d_enc[k];
                        s.d_h4[k] = (1.0 - m) * d_enc[k];
                        dm += d_enc[k] * (s.h3[k] - s.h4[k]);
                    }
                }
                BlendMode::Mt => {
                    for k in row {
                        s.d_h3[k] = d_enc[k];
                        s.d_h4[k] = (1.0 - m) * d_enc[k];
                        dm -= d_enc[k] * s.h4[k];
                    }
                }
                BlendMode::Add => {
                    for k in row {
                        s.d_h3[k] = d_enc[k];
                        s.d_h4[k] = d_enc[k];
                    }
                }
                BlendMode::FourD => s.d_h4[row.clone()].copy_from_slice(&d_enc[row]),
                BlendMode::Static => s.d_h3[row.clone()].copy_from_slice(&d_enc[row]),
            }
            if !s.d_m_extra.is_empty() {
                dm += s.d_m_extra[i];
            }
            if let Some((d, r)) = &self.mask {
                d.backward(
                    &points[i * 4..i * 4 + 3],
                    dm * sigmoid_grad_from_output(m),
                    &mut grad[r.clone()],
                );
            }
        }
        match (&self.h3, &self.h4) {
            (Some((g3, r3)), Some((g4, r4))) if pairable(g3, g4) => {
                // The two ranges are disjoint entries of one layout, in either order.
                let (grad3, grad4) = if r3.start < r4.start {
                    let (a, b) = grad.split_at_mut(r4.start);
                    (&mut a[r3.clone()], &mut b[..r4.len()])
                } else {
                    let (a, b) = grad.split_at_mut(r3.start);
                    (&mut b[..r3.len()], &mut a[r4.clone()])
                };
                backward_pair(
                    g3,
                    g4,
                    &points[..n * 4],
                    4,
                    &s.d_h3,
                    &s.d_h4,
                    e,
                    0,
                    grad3,
                    grad4,
                );
            }
            _ => {
                if let Some((g, r)) = &self.h3 {
                    g.backward(&points[..n * 4], 4, &s.d_h3, e, 0, &mut grad[r.clone()]);
                }
                if let Some((g, r)) = &self.h4 {
                    g.backward(&points[..n * 4], 4, &s.d_h4, e, 0, &mut grad[r.clone()]);
                }
            }
        }
        s.d_enc_ramped = ramped;
    }
}

/// The main field: encoding + density MLP + colour MLP.
#[derive(Clone, Debug, PartialEq)]
pub struct FieldLayout {
    pub encoding: EncodingLayout,
    pub density: (MlpLayout, Range<usize>),
    pub color: (MlpLayout, Range<usize>),
    pub geo_features: usize,
}

/// Scratch of one main-field pass over `n` points.
#[derive(Clone, Debug, Default)]
pub struct FieldScratch {
    pub enc: EncodingScratch,
    pub density_acts: MlpActivations,
    pub color_acts: MlpActivations,
    pub color_in: Vec<f32>,
    /// Points that got a colour in the last forward pass.
    pub active: Vec<u32>,
    pub sigma: Vec<f32>,
    pub rgb: Vec<f32>,
    d_density_out: Vec<f32>,
    d_color_in: Vec<f32>,
    d_color_out: Vec<f32>,
    d_enc: Vec<f32>,
}

impl FieldLayout {
    pub fn new(cfg: &FieldConfig, params: &mut ParamLayout) -> Self {
        let encoding = EncodingLayout::new(&cfg.encoding, "field", params);
        let dm = MlpLayout::new(&[encoding.out_dim, cfg.density_hidden, 1 + cfg.geo_features]);
        let dr = params.push("field.density_mlp", dm.num_params);
        let mut dims = vec![SH_COEFFS + cfg.geo_features];
        dims.extend(std::iter::repeat_n(cfg.color_hidden, cfg.color_layers));
        dims.push(3);
        let cm = MlpLayout::new(&dims);
        let cr = params.push("field.color_mlp", cm.num_params);
        FieldLayout {
            encoding,
            density: (dm, dr),
            color: (cm, cr),
            geo_features: cfg.geo_features,
        }
    }

    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.encoding.init(params, rng);
        self.density
            .0
            .init(&mut params[self.density.1.clone()], rng);
        self.color.0.init(&mut params[self.color.1.clone()], rng);
    }

    /// Plain reference: `(sigma, rgb, m)` at one point with direction encoding `sh`.
    pub fn eval_point_reference(
        &self,
        params: &[f32],
        p: &[f32],
        sh: &[f32],
    ) -> (f32, [f32; 3], f32) {
        let (enc, m) = self.encoding.encode_point_reference(params, p);
        let d = self
            .density
            .0
            .forward_reference(&params[self.density.1.clone()], &enc);
        let mut cin = sh.to_vec();
        cin.extend_from_slice(&d[1..]);
        let c = self
            .color
            .0
            .forward_reference(&params[self.color.1.clone()], &cin);
        (
            trunc_exp(d[0]),
            [sigmoid(c[0]), sigmoid(c[1]), sigmoid(c[2])],
            m,
        )
    }

    /// Density only (the first half of [`FieldLayout::forward`]): fills `s.sigma`.
    pub fn forward_density(&self, params: &[f32], points: &[f32], n: usize, s: &mut FieldScratch) {
        self.encoding.forward(params, points, n, &mut s.enc);
        self.decode_density(params, n, s);
    }

    /// [`FieldLayout::forward_density`] of points whose static part was kept: the encoding by
    /// [`EncodingLayout::forward_dynamic_prescaled`] (same arguments), then the density MLP.
    /// [`FieldLayout::forward_color`] may follow.
    pub fn forward_density_prescaled(
        &self,
        params: &[f32],
        points: &[f32],
        n: usize,
        static_term: &[f32],
        b: &[f32],
        s: &mut FieldScratch,
    ) {
        self.encoding
            .forward_dynamic_prescaled(params, points, n, static_term, b, &mut s.enc);
        self.decode_density(params, n, s);
    }

    /// The density MLP on the encoding `s.enc.enc` of `n` points: fills `s.sigma`.
    fn decode_density(&self, params: &[f32], n: usize, s: &mut FieldScratch) {
        let (dm, dr) = &self.density;
        dm.forward(&params[dr.clone()], &s.enc.enc, n, &mut s.density_acts);
        let out = dm.output(&s.density_acts);
        let w = dm.output_dim();
        s.sigma.resize(n, 0.0);
        for i in 0..n {
            s.sigma[i] = trunc_exp(out[i * w]);
        }
    }

    /// Forward over `n` points; `sh_index(i)` gives the row of `sh` (direction encodings) for
    /// point `i`. Fills `s.sigma` (`[n]`) and `s.rgb` (`[n, 3]`).
    pub fn forward(
        &self,
        params: &[f32],
        points: &[f32],
        sh: &[f32],
        sh_index: &dyn Fn(usize) -> usize,
        n: usize,
        s: &mut FieldScratch,
    ) {
        self.forward_density(params, points, n, s);
        self.forward_color(params, sh, sh_index, None, n, s);
    }

    /// The colour half of [`FieldLayout::forward`], after [`FieldLayout::forward_density`].
    /// With `active`, only those points get a colour (the others get 0 and no gradient): the
    /// pipeline skips samples hidden behind opaque matter, whose colour cannot matter.
    pub fn forward_color(
        &self,
        params: &[f32],
        sh: &[f32],
        sh_index: &dyn Fn(usize) -> usize,
        active: Option<&[u32]>,
        n: usize,
        s: &mut FieldScratch,
    ) {
        s.active.clear();
        match active {
            Some(a) => s.active.extend_from_slice(a),
            None => s.active.extend(0..n as u32),
        }
        let m = s.active.len();
        let (dm, _) = &self.density;
        let w = dm.output_dim();
        let g = self.geo_features;
        let cw = SH_COEFFS + g;
        s.color_in.resize(m * cw, 0.0);
        let out = dm.output(&s.density_acts);
        for (k, &i) in s.active.iter().enumerate() {
            let i = i as usize;
            let j = sh_index(i);
            s.color_in[k * cw..k * cw + SH_COEFFS]
                .copy_from_slice(&sh[j * SH_COEFFS..(j + 1) * SH_COEFFS]);
            s.color_in[k * cw + SH_COEFFS..(k + 1) * cw]
                .copy_from_slice(&out[i * w + 1..i * w + 1 + g]);
        }
        let (cm, cr) = &self.color;
        cm.forward(&params[cr.clone()], &s.color_in, m, &mut s.color_acts);
        let c = cm.output(&s.color_acts);
        s.rgb.clear();
        s.rgb.resize(n * 3, 0.0);
        for (k, &i) in s.active.iter().enumerate() {
            for ch in 0..3 {
                s.rgb[i as usize * 3 + ch] = sigmoid(c[k * 3 + ch]);
            }
        }
    }

    /// Backward of the last [`FieldLayout::forward`] given `d_sigma: [n]` and `d_rgb: [n, 3]`
    /// (`d_rgb` of points without a colour is ignored).
    pub fn backward(
        &self,
        params: &[f32],
        points: &[f32],
        n: usize,
        s: &mut FieldScratch,
        d_sigma: &[f32],
        d_rgb: &[f32],
        grad: &mut [f32],
    ) {
        let (cm, cr) = &self.color;
        let (dm, _) = &self.density;
        let g = self.geo_features;
        let m = s.active.len();
        s.d_color_out.resize(m * 3, 0.0);
        for (k, &i) in s.active.iter().enumerate() {
            for ch in 0..3 {
                let idx = i as usize * 3 + ch;
                s.d_color_out[k * 3 + ch] = d_rgb[idx] * sigmoid_grad_from_output(s.rgb[idx]);
            }
        }
        // Only the geometry features need an input gradient (the direction encoding is fixed).
        s.d_color_in.resize(m * g, 0.0);
        cm.backward_partial(
            &params[cr.clone()],
            &s.color_in,
            m,
            &mut s.color_acts,
            &s.d_color_out,
            &mut grad[cr.clone()],
            Some((SH_COEFFS, &mut s.d_color_in)),
        );
        let w = dm.output_dim();
        s.d_density_out.clear();
        s.d_density_out.resize(n * w, 0.0);
        let out = dm.output(&s.density_acts);
        for i in 0..n {
            s.d_density_out[i * w] = d_sigma[i] * trunc_exp_grad(out[i * w]);
        }
        for (k, &i) in s.active.iter().enumerate() {
            let i = i as usize;
            s.d_density_out[i * w + 1..(i + 1) * w]
                .copy_from_slice(&s.d_color_in[k * g..(k + 1) * g]);
        }
        self.backward_density_mlp(params, n, s, grad);
        self.encoding
            .backward(points, n, &mut s.enc, &s.d_enc, grad);
    }

    fn backward_density_mlp(
        &self,
        params: &[f32],
        n: usize,
        s: &mut FieldScratch,
        grad: &mut [f32],
    ) {
        let (dm, dr) = &self.density;
        s.d_enc.resize(n * self.encoding.out_dim, 0.0);
        dm.backward(
            &params[dr.clone()],
            &s.enc.enc,
            n,
            &mut s.density_acts,
            &s.d_density_out,
            &mut grad[dr.clone()],
            Some(&mut s.d_enc),
        );
    }

    /// Backward of [`FieldLayout::forward_density`] alone (used by the proposal field).
    pub fn backward_density(
        &self,
        params: &[f32],
        points: &[f32],
        n: usize,
        s: &mut FieldScratch,
        d_sigma: &[f32],
        grad: &mut [f32],
    ) {
        let (dm, _) = &self.density;
        let w = dm.output_dim();
        s.d_density_out.resize(n * w, 0.0);
        let out = dm.output(&s.density_acts);
        for i in 0..n {
            s.d_density_out[i * w] = d_sigma[i] * trunc_exp_grad(out[i * w]);
            for k in 1..w {
                s.d_density_out[i * w + k] = 0.0;
            }
        }
        self.backward_density_mlp(params, n, s, grad);
        self.encoding
            .backward(points, n, &mut s.enc, &s.d_enc, grad);
    }
}

impl FieldLayout {
    /// The time-agnostic static branch of mask learning: the same decoders (same parameter
    /// slices) applied to the 3D encoding `h3` alone. `None` when the encoding has no `h3`.
    pub fn static_branch(&self) -> Option<FieldLayout> {
        let h3 = self.encoding.h3.clone()?;
        Some(FieldLayout {
            encoding: EncodingLayout {
                blend: BlendMode::Static,
                h3: Some(h3),
                h4: None,
                mask: None,
                mask_init: self.encoding.mask_init,
                out_dim: self.encoding.out_dim,
            },
            density: self.density.clone(),
            color: self.color.clone(),
            geo_features: self.geo_features,
        })
    }
}

/// The proposal field: the same structure with a density-only decoder. It reuses
/// [`FieldLayout`]'s density path with an empty colour MLP.
#[derive(Clone, Debug, PartialEq)]
pub struct ProposalLayout {
    pub field: FieldLayout,
}

impl ProposalLayout {
    pub fn new(cfg: &ProposalConfig, params: &mut ParamLayout) -> Self {
        let encoding = EncodingLayout::new(&cfg.encoding, "proposal", params);
        let dm = MlpLayout::new(&[encoding.out_dim, cfg.hidden, 1]);
        let dr = params.push("proposal.density_mlp", dm.num_params);
        ProposalLayout {
            field: FieldLayout {
                encoding,
                density: (dm, dr),
                color: (MlpLayout::new(&[1, 1]), 0..0),
                geo_features: 0,
            },
        }
    }

    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.field.encoding.init(params, rng);
        self.field
            .density
            .0
            .init(&mut params[self.field.density.1.clone()], rng);
    }
}

/// The whole model's parameter layout.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelLayout {
    pub params: ParamLayout,
    pub field: FieldLayout,
    pub proposal: ProposalLayout,
}

impl ModelLayout {
    pub fn new(cfg: &ModelConfig) -> Self {
        let mut params = ParamLayout::default();
        let field = FieldLayout::new(&cfg.field, &mut params);
        let proposal = ProposalLayout::new(&cfg.proposal, &mut params);
        ModelLayout {
            params,
            field,
            proposal,
        }
    }

    /// Freshly initialised parameters for `seed`.
    pub fn init_params(&self, seed: u64) -> Vec<f32> {
        let mut p = vec![0f32; self.params.total];
        let mut rng = Rng::stream(seed, 0x1417);
        self.field.init(&mut p, &mut rng);
        self.proposal.init(&mut p, &mut rng);
        p
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{central_difference, largest_first};

    fn small_config(blend: BlendMode) -> ModelConfig {
        let mut c = ModelConfig::fast_on_white(10);
        for enc in [&mut c.field.encoding, &mut c.proposal.encoding] {
            enc.blend = blend;
            enc.resize(3, 8, 40.0, 6);
            enc.grid4.finest_resolution[3] = 10.0;
        }
        c.field.density_hidden = 8;
        c.field.color_hidden = 8;
        c.field.geo_features = 4;
        c
    }

    /// Random parameters of a visible size so that gradients are not dominated by rounding.
    fn params(layout: &ModelLayout, seed: u64) -> Vec<f32> {
        let mut p = layout.init_params(seed);
        let mut rng = Rng::new(seed + 1);
        for e in &layout.params.entries {
            if e.name.ends_with("h3") || e.name.ends_with("h4") {
                for v in &mut p[e.range()] {
                    *v = rng.range_f32(-0.5, 0.5);
                }
            }
            if e.name.ends_with("mask") {
                for v in &mut p[e.range()] {
                    *v = rng.range_f32(-2.0, 2.0);
                }
            }
        }
        p
    }

    #[test]
    fn batched_matches_reference_every_blend() {
        for blend in BlendMode::ALL {
            let cfg = small_config(blend);
            cfg.validate().unwrap();
            let layout = ModelLayout::new(&cfg);
            let p = params(&layout, 1);
            let mut rng = Rng::new(2);
            let n = 23;
            let pts: Vec<f32> = (0..n * 4).map(|_| rng.f32()).collect();
            let mut sh = vec![0f32; SH_COEFFS];
            crate::sh::sh4([0.0, 0.6, 0.8], &mut sh);
            let mut s = FieldScratch::default();
            layout.field.forward(&p, &pts, &sh, &|_| 0, n, &mut s);
            for i in 0..n {
                let (sig, rgb, _) =
                    layout
                        .field
                        .eval_point_reference(&p, &pts[i * 4..i * 4 + 4], &sh);
                assert!((sig - s.sigma[i]).abs() <= 1e-4 * sig.max(1.0), "{blend:?}");
                for c in 0..3 {
                    assert!((rgb[c] - s.rgb[i * 3 + c]).abs() < 1e-5);
                }
            }
        }
    }

    /// With a static cutoff, points the mask leaves dynamic encode exactly as the reference does,
    /// and the others as the reference with `h4 = 0`; the cutoff 0 path is the exact one.
    #[test]
    fn static_cutoff_skips_only_static_points() {
        for blend in [BlendMode::Mst, BlendMode::Mt] {
            let cfg = small_config(blend);
            let layout = ModelLayout::new(&cfg);
            let mut p = params(&layout, 3);
            // A mask that is static on one half of the box and dynamic on the other.
            let (grid, r) = layout.field.encoding.mask.clone().unwrap();
            for (k, v) in p[r.clone()].iter_mut().enumerate() {
                let x = k % grid.res;
                *v = if x < grid.res / 2 { 12.0 } else { -2.0 };
            }
            let enc = &layout.field.encoding;
            let mut rng = Rng::new(4);
            let n = 64;
            let pts: Vec<f32> = (0..n * 4).map(|_| rng.f32()).collect();
            let mut s = EncodingScratch {
                static_cutoff: 1e-3,
                ..Default::default()
            };
            enc.forward(&p, &pts, n, &mut s);
            let mut skipped = 0;
            for i in 0..n {
                let x = &pts[i * 4..i * 4 + 4];
                let (full, m) = enc.encode_point_reference(&p, x);
                let mut expect = full.clone();
                if 1.0 - m < 1e-3 {
                    skipped += 1;
                    let h3 = enc
                        .h3
                        .as_ref()
                        .map(|(g, r)| g.encode_point_reference(&p[r.clone()], &x[..3]));
                    for (k, e) in expect.iter_mut().enumerate() {
                        let a = h3.as_ref().map_or(0.0, |v| v[k]);
                        *e = if blend == BlendMode::Mst { m * a } else { a };
                    }
                }
                for k in 0..enc.out_dim {
                    let got = s.enc[i * enc.out_dim + k];
                    assert!((got - expect[k]).abs() < 1e-5, "{blend:?} point {i}");
                    assert!((got - full[k]).abs() <= 1e-3 * 0.5 * enc.out_dim as f32 + 1e-5);
                }
            }
            assert!(skipped > 0 && skipped < n, "{skipped} of {n} skipped");
        }
    }

    /// Colouring a subset of points gives those points the same colours and the same gradients
    /// as colouring all of them (with zero upstream gradient on the others).
    #[test]
    fn colouring_a_subset_matches_colouring_all() {
        let cfg = small_config(BlendMode::Mt);
        let layout = ModelLayout::new(&cfg);
        let p = params(&layout, 5);
        let mut rng = Rng::new(6);
        let n = 17;
        let pts: Vec<f32> = (0..n * 4).map(|_| rng.f32()).collect();
        let mut sh = vec![0f32; SH_COEFFS];
        crate::sh::sh4([0.0, 0.0, 1.0], &mut sh);
        let active: Vec<u32> = (0..n as u32).filter(|i| i % 3 != 1).collect();
        let d_sigma: Vec<f32> = (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let mut d_rgb: Vec<f32> = (0..n * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        for i in 0..n {
            if !active.contains(&(i as u32)) {
                d_rgb[i * 3..i * 3 + 3].fill(0.0);
            }
        }
        let mut all = FieldScratch::default();
        layout.field.forward(&p, &pts, &sh, &|_| 0, n, &mut all);
        let mut g_all = vec![0f32; p.len()];
        layout
            .field
            .backward(&p, &pts, n, &mut all, &d_sigma, &d_rgb, &mut g_all);
        let mut sub = FieldScratch::default();
        layout.field.forward_density(&p, &pts, n, &mut sub);
        layout
            .field
            .forward_color(&p, &sh, &|_| 0, Some(&active), n, &mut sub);
        let mut g_sub = vec![0f32; p.len()];
        layout
            .field
            .backward(&p, &pts, n, &mut sub, &d_sigma, &d_rgb, &mut g_sub);
        for &i in &active {
            let i = i as usize;
            assert_eq!(all.rgb[i * 3..i * 3 + 3], sub.rgb[i * 3..i * 3 + 3]);
        }
        for (a, b) in g_all.iter().zip(&g_sub) {
            assert!((a - b).abs() <= 1e-5 * (1.0 + a.abs()), "{a} vs {b}");
        }
    }

    /// Finite differences of `L = sum a_i sigma_i + b_i . rgb_i` through the whole field, for
    /// a sample of parameters in every named slice.
    #[test]
    fn field_backward_matches_finite_differences() {
        for blend in BlendMode::ALL {
            let cfg = small_config(blend);
            let layout = ModelLayout::new(&cfg);
            let p = params(&layout, 3);
            let mut rng = Rng::new(4);
            let n = 6;
            let pts: Vec<f32> = (0..n * 4).map(|_| rng.range_f32(0.05, 0.95)).collect();
            let mut sh = vec![0f32; SH_COEFFS];
            crate::sh::sh4([0.6, 0.0, 0.8], &mut sh);
            let a: Vec<f32> = (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect();
            let b: Vec<f32> = (0..n * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect();
            let loss = |p: &[f32]| -> f64 {
                let mut l = 0f64;
                for i in 0..n {
                    let (sig, rgb, _) =
                        layout
                            .field
                            .eval_point_reference(p, &pts[i * 4..i * 4 + 4], &sh);
                    l += a[i] as f64 * sig as f64;
                    for c in 0..3 {
                        l += b[i * 3 + c] as f64 * rgb[c] as f64;
                    }
                }
                l
            };
            let mut s = FieldScratch::default();
            layout.field.forward(&p, &pts, &sh, &|_| 0, n, &mut s);
            let mut grad = vec![0f32; p.len()];
            layout
                .field
                .backward(&p, &pts, n, &mut s, &a, &b, &mut grad);
            for e in &layout.params.entries {
                if !e.name.starts_with("field") {
                    continue;
                }
                // the parameters with the largest gradients, plus a few arbitrary ones
                let mut checked = 0;
                for &i in largest_first(e.range(), |i| grad[i] as f64).iter().take(12) {
                    let fd = central_difference(loss, &p, i, 3e-4);
                    let tol = 2e-3 + 2e-2 * fd.abs();
                    assert!(
                        (fd - grad[i] as f64).abs() < tol,
                        "{blend:?} {} [{}]: fd {fd} vs {}",
                        e.name,
                        i - e.offset,
                        grad[i]
                    );
                    checked += 1;
                }
                assert!(checked > 0);
            }
        }
    }

    #[test]
    fn mask_fractions_count_decided_vertices() {
        let layout = ModelLayout::new(&small_config(BlendMode::Mst));
        let mut p = layout.init_params(1);
        let r = layout.params.get("field.mask").unwrap().range();
        let n = r.len();
        for (k, v) in p[r].iter_mut().enumerate() {
            *v = match k % 4 {
                0 => -5.0,
                1 | 2 => 5.0,
                _ => 0.0,
            };
        }
        let (lo, hi) = layout.field.encoding.mask_fractions(&p, 0.1, 0.9).unwrap();
        let expect = |c: usize| {
            (0..n)
                .filter(|k| c == 0 && k % 4 == 0 || c == 1 && (k % 4 == 1 || k % 4 == 2))
                .count() as f64
                / n as f64
        };
        assert_eq!((lo, hi), (expect(0), expect(1)));
        let plain = ModelLayout::new(&small_config(BlendMode::Add));
        assert!(plain.field.encoding.mask_fractions(&p, 0.1, 0.9).is_none());
    }

    /// The static branch is the field with `m = 1` everywhere in MST mode (same decoders, h3
    /// alone), and its backward matches finite differences into h3 and both MLPs.
    #[test]
    fn static_branch_is_the_all_static_field_and_fd() {
        let cfg = small_config(BlendMode::Mst);
        let layout = ModelLayout::new(&cfg);
        let mut p = params(&layout, 7);
        let sf = layout.field.static_branch().unwrap();
        assert!(sf.encoding.h4.is_none() && sf.encoding.mask.is_none());
        let mut rng = Rng::new(8);
        let n = 5;
        let pts: Vec<f32> = (0..n * 4).map(|_| rng.range_f32(0.05, 0.95)).collect();
        let mut sh = vec![0f32; SH_COEFFS];
        crate::sh::sh4([0.0, 0.6, 0.8], &mut sh);
        let mut s = FieldScratch::default();
        sf.forward(&p, &pts, &sh, &|_| 0, n, &mut s);
        // the static branch does not depend on time
        let mut pts_t = pts.clone();
        for i in 0..n {
            pts_t[i * 4 + 3] = 1.0 - pts[i * 4 + 3];
        }
        let mut st = FieldScratch::default();
        sf.forward(&p, &pts_t, &sh, &|_| 0, n, &mut st);
        assert_eq!(s.sigma, st.sigma);
        // the full field with a saturated static mask (m = 1 up to rounding)
        let mask = layout.params.get("field.mask").unwrap().range();
        p[mask].fill(30.0);
        for i in 0..n {
            let (sig, rgb, m) = layout
                .field
                .eval_point_reference(&p, &pts[i * 4..i * 4 + 4], &sh);
            assert_eq!(m, 1.0);
            assert!((sig - s.sigma[i]).abs() <= 1e-4 * sig.max(1.0));
            for c in 0..3 {
                assert!((rgb[c] - s.rgb[i * 3 + c]).abs() < 1e-5);
            }
        }
        let a: Vec<f32> = (0..n).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let b: Vec<f32> = (0..n * 3).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let mut grad = vec![0f32; p.len()];
        sf.backward(&p, &pts, n, &mut s, &a, &b, &mut grad);
        let loss = |q: &[f32]| -> f64 {
            let mut l = 0f64;
            for i in 0..n {
                let (sig, rgb, _) = sf.eval_point_reference(q, &pts[i * 4..i * 4 + 4], &sh);
                l += a[i] as f64 * sig as f64;
                for c in 0..3 {
                    l += b[i * 3 + c] as f64 * rgb[c] as f64;
                }
            }
            l
        };
        for name in ["field.h3", "field.density_mlp", "field.color_mlp"] {
            let e = layout.params.get(name).unwrap();
            let idx = largest_first(e.range(), |i| grad[i] as f64);
            assert!(grad[idx[0]] != 0.0, "{name}");
            for &i in idx.iter().take(8) {
                let fd = central_difference(loss, &p, i, 3e-4);
                assert!(
                    (fd - grad[i] as f64).abs() < 2e-3 + 2e-2 * fd.abs(),
                    "{name}: fd {fd} vs {}",
                    grad[i]
                );
            }
        }
        // h4 and the mask get nothing from the static branch
        for name in ["field.h4", "field.mask"] {
            let e = layout.params.get(name).unwrap();
            assert!(grad[e.range()].iter().all(|&v| v == 0.0), "{name}");
        }
    }
}
