//! Adam over the flat parameter buffer (lr 1e-2, eps 1e-15 by default, exponential decay), with
//! the MSTH mask loss fused into the update of the mask slices: its gradient is elementwise, so
//! adding it where every mask parameter is already visited costs nothing extra.

use std::ops::Range;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use msth_core::activation::sigmoid;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    pub lr: f32,
    /// Learning rate reached at the last step (exponential decay in between).
    pub lr_final: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        AdamConfig {
            lr: 1e-2,
            lr_final: 2e-4,
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-15,
        }
    }
}

impl AdamConfig {
    /// Learning rate at a fraction `f` of the run (0 at the start, 1 at the end).
    pub fn lr_at_fraction(&self, f: f32) -> f32 {
        self.lr * (self.lr_final / self.lr).powf(f.clamp(0.0, 1.0))
    }
}

/// Gradients are clamped to this magnitude before the moments are updated, so that `g^2` stays
/// finite in f32 (see docs/stability.md). Adam's step does not depend on the gradient's scale.
pub const MAX_GRADIENT: f32 = 1e18;

/// Optimiser state: first and second moments, one float each per parameter.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub step: u64,
}

/// A slice of the parameter buffer whose Adam step is scaled by `lr_scale` (1: the common
/// learning rate) and, where `weight > 0` (the mask grids), whose parameters also receive the
/// mask loss `weight * d/dx mean(1 - sigmoid(x))`. The trainer gives the mask grids one
/// (`mask_lr_scale`, `mask_loss_weight`) and, when `proposal_lr_scale` is not 1, the proposal
/// network's slices another (weight 0).
///
/// Why a separate scale for the mask: Adam moves a parameter by at most about the learning rate per step
/// whatever its gradient, so over a run a mask logit moves by at most `sum_t lr_t` (about
/// `0.0025 * iters` with the default schedule). From the initial logit -1 (m = 0.27) a voxel
/// needs +3.2 to pass m = 0.9 and -1.2 to fall below 0.1: short runs cannot decide the mask,
/// whatever the mask loss weight (see docs/mask-learning.md).
#[derive(Clone, Debug)]
pub struct ScaledSlice {
    pub range: Range<usize>,
    pub weight: f32,
    pub lr_scale: f32,
    /// Weight decay as a loss term: `decay * x` is added to each parameter's gradient
    /// (the gradient of `decay / 2 * sum x^2`); 0: none.
    pub decay: f32,
}

impl Adam {
    pub fn new(n: usize) -> Self {
        Adam {
            m: vec![0.0; n],
            v: vec![0.0; n],
            step: 0,
        }
    }

    /// One update with learning rate `lr`; returns the mask loss value (weighted sum over slices).
    pub fn update(
        &mut self,
        cfg: &AdamConfig,
        lr: f32,
        params: &mut [f32],
        grad: &[f32],
        slices: &[ScaledSlice],
    ) -> f32 {
        let blocks: Vec<Block> = grad.chunks(CHUNK).map(Block::One).collect();
        self.update_blocks(cfg, lr, params, blocks, slices)
    }

    /// [`Adam::update`] on the sum of `grads` (summed in their order, `grads[0] + grads[1] +
    /// ...`, so the same values as summing them first), leaving every buffer zeroed for the next
    /// step's accumulation. One pass: each block of the buffers is summed, used and cleared while
    /// it is in cache, instead of a pass to clear, one to sum and one for Adam, each over memory.
    pub fn update_summed_and_clear(
        &mut self,
        cfg: &AdamConfig,
        lr: f32,
        params: &mut [f32],
        grads: &mut [&mut [f32]],
        slices: &[ScaledSlice],
    ) -> f32 {
        assert!(!grads.is_empty() && grads.iter().all(|g| g.len() == params.len()));
        let mut blocks: Vec<Vec<&mut [f32]>> = (0..params.len().div_ceil(CHUNK))
            .map(|_| Vec::with_capacity(grads.len()))
            .collect();
        for g in grads.iter_mut() {
            for (c, gc) in g.chunks_mut(CHUNK).enumerate() {
                blocks[c].push(gc);
            }
        }
        let blocks = blocks.into_iter().map(Block::Summed).collect();
        self.update_blocks(cfg, lr, params, blocks, slices)
    }

    fn update_blocks(
        &mut self,
        cfg: &AdamConfig,
        lr: f32,
        params: &mut [f32],
        grads: Vec<Block>,
        slices: &[ScaledSlice],
    ) -> f32 {
        assert_eq!(grads.len(), params.len().div_ceil(CHUNK));
        self.step += 1;
        let t = self.step as i32;
        let bc1 = 1.0 - cfg.beta1.powi(t);
        let bc2 = 1.0 - cfg.beta2.powi(t);
        let step_size = lr / bc1;
        let inv_sqrt_bc2 = 1.0 / bc2.sqrt();
        let (b1, b2, eps) = (cfg.beta1, cfg.beta2, cfg.eps);
        let mask_loss: f64 = params
            .par_chunks_mut(CHUNK)
            .zip(grads.into_par_iter())
            .zip(self.m.par_chunks_mut(CHUNK))
            .zip(self.v.par_chunks_mut(CHUNK))
            .enumerate()
            .map(|(c, (((p, block), m), v))| {
                let base = c * CHUNK;
                let update = |g: &[f32]| -> f64 {
                    let mut loss = 0f64;
                    // Which slice (if any) overlaps this chunk: handle per element.
                    let overl: Vec<&ScaledSlice> = slices
                        .iter()
                        .filter(|s| s.range.start < base + p.len() && s.range.end > base)
                        .collect();
                    // A block that no slice touches (the common case), or that lies inside one
                    // slice without a mask loss (the hash tables' weight decay, the proposal's
                    // learning rate): one scale and decay for the whole block, in a loop the
                    // compiler vectorises; the same operations in the same order as below.
                    let whole = match overl[..] {
                        [] => Some((1.0, 0.0)),
                        [s] if s.weight == 0.0
                            && s.range.start <= base
                            && s.range.end >= base + p.len() =>
                        {
                            Some((s.lr_scale, s.decay))
                        }
                        _ => None,
                    };
                    if let Some((scale, decay)) = whole {
                        for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m).zip(v) {
                            let gi = if decay != 0.0 { g + decay * *p } else { g };
                            let gi = gi.clamp(-MAX_GRADIENT, MAX_GRADIENT);
                            *m = b1 * *m + (1.0 - b1) * gi;
                            *v = b2 * *v + (1.0 - b2) * gi * gi;
                            let denom = v.sqrt() * inv_sqrt_bc2 + eps;
                            *p -= step_size * scale * *m / denom;
                        }
                        return loss;
                    }
                    for i in 0..p.len() {
                        let mut gi = g[i];
                        let mut scale = 1.0f32;
                        let idx = base + i;
                        for s in &overl {
                            if s.range.contains(&idx) {
                                scale = s.lr_scale;
                                if s.decay != 0.0 {
                                    gi += s.decay * p[i];
                                }
                                // Weight 0: a slice with its own learning rate and no mask loss.
                                if s.weight != 0.0 {
                                    let sg = sigmoid(p[i]);
                                    let n = s.range.len() as f32;
                                    gi += -s.weight * sg * (1.0 - sg) / n;
                                    loss += (s.weight * (1.0 - sg) / n) as f64;
                                }
                            }
                        }
                        // Adam only sees the gradient's scale through m / sqrt(v); beyond
                        // ~1.8e19, gi * gi overflows to infinity and froze the parameter for
                        // good (m / sqrt(inf) = 0 forever). Clamping keeps the direction and
                        // the step.
                        let gi = gi.clamp(-MAX_GRADIENT, MAX_GRADIENT);
                        m[i] = b1 * m[i] + (1.0 - b1) * gi;
                        v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                        let denom = v[i].sqrt() * inv_sqrt_bc2 + eps;
                        p[i] -= step_size * scale * m[i] / denom;
                    }
                    loss
                };
                match block {
                    Block::One(g) => update(g),
                    Block::Summed(mut gs) => {
                        // Sum into the first buffer, clearing the others, while all are in cache.
                        let (first, rest) = gs.split_first_mut().expect("one buffer at least");
                        for r in rest.iter_mut() {
                            first.iter_mut().zip(r.iter_mut()).for_each(|(a, b)| {
                                *a += *b;
                                *b = 0.0;
                            });
                        }
                        let loss = update(first);
                        first.fill(0.0);
                        loss
                    }
                }
            })
            .sum();
        mask_loss as f32
    }
}

/// Parameters per block of Adam's pass (64 KiB of each buffer: the gradient buffers of a block
/// stay in L2 between their sum and the update).
const CHUNK: usize = 1 << 14;

/// One block of Adam's pass: the gradient, read only, or the same block of several buffers,
/// summed, used and cleared.
enum Block<'a> {
    One(&'a [f32]),
    Summed(Vec<&'a mut [f32]>),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minimises_a_quadratic() {
        let cfg = AdamConfig {
            lr: 0.05,
            lr_final: 0.01,
            ..Default::default()
        };
        let target: Vec<f32> = (0..100).map(|i| (i as f32 * 0.37).sin()).collect();
        let mut p = vec![0f32; 100];
        let mut adam = Adam::new(100);
        for s in 0..600 {
            let g: Vec<f32> = p.iter().zip(&target).map(|(a, b)| 2.0 * (a - b)).collect();
            adam.update(&cfg, cfg.lr_at_fraction(s as f32 / 599.0), &mut p, &g, &[]);
        }
        for (a, b) in p.iter().zip(&target) {
            assert!((a - b).abs() < 1e-2, "{a} vs {b}");
        }
    }

    #[test]
    fn mask_loss_pushes_logits_up() {
        let cfg = AdamConfig::default();
        let mut p = vec![-1f32; 40_000];
        let g = vec![0f32; 40_000];
        let mut adam = Adam::new(p.len());
        let masks = [ScaledSlice {
            range: 100..30_000,
            weight: 1.0,
            lr_scale: 1.0,
            decay: 0.0,
        }];
        let l0 = adam.update(&cfg, 1e-2, &mut p, &g, &masks);
        for _ in 0..50 {
            adam.update(&cfg, 1e-2, &mut p, &g, &masks);
        }
        assert!((l0 - (1.0 - sigmoid(-1.0))).abs() < 1e-3);
        assert!(p[100] > -0.6 && p[29_999] > -0.6);
        assert_eq!(p[99], -1.0);
        assert_eq!(p[30_000], -1.0);
    }

    /// `lr_scale` multiplies the step of the slice only: with a pure mask-loss gradient every
    /// step moves a logit by about `lr * lr_scale`.
    #[test]
    fn mask_lr_scale_scales_the_mask_step_only() {
        let cfg = AdamConfig::default();
        let mut p = vec![-1f32; 200];
        let mut g = vec![0f32; 200];
        g[150] = 1.0;
        let mut adam = Adam::new(p.len());
        let masks = [ScaledSlice {
            range: 0..100,
            weight: 1.0,
            lr_scale: 10.0,
            decay: 0.0,
        }];
        for _ in 0..20 {
            adam.update(&cfg, 1e-2, &mut p, &g, &masks);
        }
        // 20 steps of lr 1e-2 x 10 upwards for the mask (about 2: the mask loss gradient
        // changes a little as the logit moves, so Adam's step is not exactly lr), 20 steps of
        // exactly 1e-2 downwards for the constant gradient elsewhere.
        assert!((p[0] - (-1.0 + 2.0)).abs() < 0.05, "{}", p[0]);
        assert!((p[150] - (-1.0 - 0.2)).abs() < 1e-3, "{}", p[150]);
        assert_eq!(p[120], -1.0);
    }

    /// The fused pass gives the values of "sum the buffers in order, then update" to the bit,
    /// with and without mask slices (blocks that straddle a slice's ends, a last short block),
    /// and leaves every buffer zeroed.
    /// A slice's `decay` is `decay * x` added to its gradient before the moments, inside the
    /// slice only, to the bit; blocks the slice covers whole (a vectorised loop) and blocks it
    /// shares (the element-wise loop) give the same values, with a learning-rate scale too.
    #[test]
    fn decay_adds_decay_times_x_to_the_gradient() {
        let n = 3 * CHUNK + 31;
        let cfg = AdamConfig::default();
        // Partial blocks at both ends, one whole block inside.
        let range = CHUNK - 9..2 * CHUNK + 500;
        for lr_scale in [1.0, 3.0] {
            let slice = ScaledSlice {
                range: range.clone(),
                weight: 0.0,
                lr_scale,
                decay: 0.2,
            };
            // The same slice plus one that changes nothing, so every block is element-wise.
            let split = [
                slice.clone(),
                ScaledSlice {
                    decay: 0.0,
                    ..slice.clone()
                },
            ];
            let mut rng = msth_core::rng::Rng::new(5);
            let mut pa: Vec<f32> = (0..n).map(|_| rng.f32() - 0.5).collect();
            let (mut pb, mut pc) = (pa.clone(), pa.clone());
            let (mut a, mut b, mut c) = (Adam::new(n), Adam::new(n), Adam::new(n));
            for _ in 0..3 {
                let g: Vec<f32> = (0..n).map(|_| (rng.f32() - 0.5) * 1e-3).collect();
                let mut with_decay = g.clone();
                for i in range.clone() {
                    with_decay[i] += 0.2 * pb[i];
                }
                a.update(&cfg, 1e-2, &mut pa, &g, std::slice::from_ref(&slice));
                b.update(&cfg, 1e-2, &mut pb, &with_decay, &[]);
                c.update(&cfg, 1e-2, &mut pc, &g, &split);
                assert!(pa.iter().zip(&pc).all(|(x, y)| x.to_bits() == y.to_bits()));
                if lr_scale == 1.0 {
                    assert!(pa.iter().zip(&pb).all(|(x, y)| x.to_bits() == y.to_bits()));
                }
            }
        }
    }

    #[test]
    fn summed_update_equals_sum_then_update_and_clears() {
        let n = 3 * CHUNK + 777;
        let cfg = AdamConfig::default();
        let slices = [ScaledSlice {
            range: CHUNK - 5..CHUNK + 300,
            weight: 0.3,
            lr_scale: 7.0,
            decay: 0.0,
        }];
        for workers in 1..=3 {
            let mut rng = msth_core::rng::Rng::new(workers as u64);
            let mut pa: Vec<f32> = (0..n).map(|_| rng.f32() - 0.5).collect();
            let mut pb = pa.clone();
            let (mut a, mut b) = (Adam::new(n), Adam::new(n));
            for step in 0..3 {
                let mut grads: Vec<Vec<f32>> = (0..workers)
                    .map(|_| (0..n).map(|_| (rng.f32() - 0.5) * 1e-3).collect())
                    .collect();
                let mut sum = grads[0].clone();
                for g in &grads[1..] {
                    sum.iter_mut().zip(g).for_each(|(x, y)| *x += y);
                }
                let la = a.update(&cfg, 1e-2, &mut pa, &sum, &slices);
                let mut refs: Vec<&mut [f32]> = grads.iter_mut().map(|g| &mut g[..]).collect();
                let lb = b.update_summed_and_clear(&cfg, 1e-2, &mut pb, &mut refs, &slices);
                assert_eq!(la.to_bits(), lb.to_bits(), "workers {workers} step {step}");
                assert!(pa.iter().zip(&pb).all(|(x, y)| x.to_bits() == y.to_bits()));
                assert_eq!((a.m == b.m, a.v == b.v), (true, true));
                assert!(grads.iter().all(|g| g.iter().all(|&x| x == 0.0)));
            }
        }
    }
}
