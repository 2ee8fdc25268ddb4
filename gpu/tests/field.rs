//! The main field chained from the per-sample kernels, against `msth_core::field::FieldLayout`
//! (forward `(sigma, rgb)` and the backward's gradient over every field slice of the flat
//! parameter buffer), at the demo model (fast preset, `BlendMode::Mt`, 3D and 4D hash grids, the
//! mask): hash grids, mask, blend, density MLP (trunc_exp), SH, the geometry-feature copy,
//! colour MLP (sigmoid); backward in reverse through the same buffers, every gradient added
//! into one flat buffer. Trained-looking parameters: tables U(-0.3, 0.3), mask logits
//! U(-3, 3), Glorot MLPs.
//!
//! The demo's blend (`Mt`) and the paper's (`Mst`).
//!
//! Tolerances: sigma |gpu - cpu| <= 1e-5 sigma + 1e-6, rgb 2e-6 absolute; gradients per named
//! slice: max |gpu - cpu| <= 1e-5 x max |cpu| over the slice (f32 sums in other orders,
//! atomics in any order, the GPU's `exp`; lavapipe: within 4e-7).
//!
//! Without an adapter they are reported as ignored, with the reason, unless `MSTH_REQUIRE_GPU=1`
//! (then they fail): this binary runs on `msth-testkit`'s harness (`harness = false`), and
//! [`main`] lists every test.

mod common;

use msth_core::config::{BlendMode, Preset};
use msth_core::field::{FieldLayout, FieldScratch, ModelLayout};
use msth_core::rng::Rng;
use msth_core::sh::{sh4, SH_COEFFS};
use msth_gpu::device::ComputeDevice;
use msth_gpu::glue::{Blend, Columns, GlueKernels};
use msth_gpu::hashgrid::{AtomicMode, GpuGrid, HashGridKernels};
use msth_gpu::mask::{GpuMask, MaskKernels};
use msth_gpu::mlp::{GpuMlp, MlpKernels, OutputActivation};
use msth_gpu::presets::reference_model;
use msth_gpu::sh::ShKernel;
use msth_testkit::Tests;

use common::{device, gpu_need};

fn main() -> std::process::ExitCode {
    let gpu = gpu_need();
    Tests::new(file!())
        .needs(
            &[&gpu],
            "field_chain_matches_the_cpu_field",
            field_chain_matches_the_cpu_field,
        )
        .run()
}

fn field_chain_matches_the_cpu_field() {
    let dev = device();
    let model = ModelLayout::new(&reference_model(Preset::Fast));
    // The demo's blend (the reference code's) and the paper's.
    for blend in [BlendMode::Mt, BlendMode::Mst] {
        let mut field = model.field.clone();
        field.encoding.blend = blend;
        chain(&dev, &model, &field);
    }
}

fn chain(dev: &ComputeDevice, model: &ModelLayout, field: &FieldLayout) {
    let enc = &field.encoding;
    let (g3, r3) = enc.h3.clone().unwrap();
    let (g4, r4) = enc.h4.clone().unwrap();
    let (mg, rm) = enc.mask.clone().unwrap();
    let (dm, dr) = field.density.clone();
    let (cm, cr) = field.color.clone();
    let e = enc.out_dim;
    let geo = field.geo_features;
    let cw = SH_COEFFS + geo;
    let mut rng = Rng::new(41);
    let mut params = model.init_params(3);
    for r in [&r3, &r4] {
        for v in &mut params[r.clone()] {
            *v = rng.range_f32(-0.3, 0.3);
        }
    }
    for v in &mut params[rm.clone()] {
        *v = rng.range_f32(-3.0, 3.0);
    }
    let n = 600;
    let points: Vec<f32> = (0..4 * n).map(|_| rng.f32()).collect();
    let dirs: Vec<[f32; 3]> = (0..n)
        .map(|_| {
            let v = [rng.range_f32(-1.0, 1.0), rng.range_f32(-1.0, 1.0), 0.5];
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            [v[0] / l, v[1] / l, v[2] / l]
        })
        .collect();
    let mut sh = vec![0f32; n * SH_COEFFS];
    for (i, d) in dirs.iter().enumerate() {
        sh4(*d, &mut sh[i * SH_COEFFS..(i + 1) * SH_COEFFS]);
    }
    let d_sigma: Vec<f32> = (0..n).map(|_| rng.range_f32(-0.1, 0.1)).collect();
    let d_rgb: Vec<f32> = (0..3 * n).map(|_| rng.range_f32(-1.0, 1.0)).collect();

    // CPU.
    let mut s = FieldScratch::default();
    field.forward(&params, &points, &sh, &|i| i, n, &mut s);
    let (sigma_cpu, rgb_cpu) = (s.sigma.clone(), s.rgb.clone());
    let mut grad_cpu = vec![0f32; params.len()];
    field.backward(&params, &points, n, &mut s, &d_sigma, &d_rgb, &mut grad_cpu);

    // GPU: forward.
    let mode = AtomicMode::best(dev);
    let grid_k = HashGridKernels::new(dev, mode).unwrap();
    let mask_k = MaskKernels::new(dev, mode).unwrap();
    let mlp_k = MlpKernels::new(dev, mode).unwrap();
    let glue = GlueKernels::new(dev).unwrap();
    let sh_k = ShKernel::new(dev).unwrap();
    let buf = |what: &str, v: &[f32]| dev.buffer_f32(what, v).unwrap();
    let zeros = |what: &str, len: usize| dev.zeros_f32(what, len).unwrap();
    let p_b = buf("params", &params);
    let pts_b = buf("points", &points);
    let dirs_b = buf("dirs", bytemuck::cast_slice(&dirs));
    let (grid3, grid4) = (
        GpuGrid::new(&g3, r3.start).unwrap(),
        GpuGrid::new(&g4, r4.start).unwrap(),
    );
    let mask = GpuMask::new(mg, rm.start).unwrap();
    let density = GpuMlp::new(&dm, dr.start, OutputActivation::Density).unwrap();
    let colour = GpuMlp::new(&cm, cr.start, OutputActivation::Sigmoid).unwrap();
    let (h3_b, h4_b, m_b, enc_b) = (
        zeros("h3", n * e),
        zeros("h4", n * e),
        zeros("m", n),
        zeros("enc", n * e),
    );
    grid_k.forward(dev, &grid3, &p_b, &pts_b, n, &h3_b).unwrap();
    grid_k.forward(dev, &grid4, &p_b, &pts_b, n, &h4_b).unwrap();
    mask_k.forward(dev, &mask, &p_b, &pts_b, n, &m_b).unwrap();
    let blend = Blend {
        mode: field.encoding.blend,
        samples: n,
        features: e,
        h3: &h3_b,
        h4: &h4_b,
        m: &m_b,
    };
    glue.blend_forward(dev, &blend, &enc_b).unwrap();
    let dw = dm.output_dim();
    let (dens_b, dens_acts_b) = (
        zeros("density out", n * dw),
        zeros("density acts", n * density.acts_stride()),
    );
    mlp_k
        .forward(dev, &density, &p_b, &enc_b, n, &dens_b, Some(&dens_acts_b))
        .unwrap();
    let cin_b = zeros("colour in", n * cw);
    sh_k.encode(dev, &dirs_b, n, &cin_b, cw, 0).unwrap();
    let at = |stride, first| Columns { stride, first };
    glue.copy_columns(dev, n, geo, &dens_b, at(dw, 1), &cin_b, at(cw, SH_COEFFS))
        .unwrap();
    let (rgb_b, col_acts_b) = (
        zeros("rgb", 3 * n),
        zeros("colour acts", n * colour.acts_stride()),
    );
    mlp_k
        .forward(dev, &colour, &p_b, &cin_b, n, &rgb_b, Some(&col_acts_b))
        .unwrap();
    let dens = dev.read_f32(&dens_b, n * dw).unwrap();
    let rgb = dev.read_f32(&rgb_b, 3 * n).unwrap();
    let (mut worst_sigma, mut worst_rgb) = (0f32, 0f32);
    for i in 0..n {
        let (g, c) = (dens[i * dw], sigma_cpu[i]);
        assert!(
            (g - c).abs() <= 1e-4 * c + 1e-6,
            "sigma {i}: gpu {g} cpu {c}"
        );
        worst_sigma = worst_sigma.max((g - c).abs() / (1e-4 * c + 1e-6));
        for ch in 0..3 {
            let (g, c) = (rgb[3 * i + ch], rgb_cpu[3 * i + ch]);
            assert!((g - c).abs() <= 2e-6, "rgb {i}.{ch}: gpu {g} cpu {c}");
            worst_rgb = worst_rgb.max((g - c).abs() / 2e-6);
        }
    }

    // GPU: backward, into one flat gradient.
    let grad_b = zeros("grad", params.len());
    let (d_rgb_b, d_sigma_b) = (buf("d rgb", &d_rgb), buf("d sigma", &d_sigma));
    let d_geo_b = zeros("d geo", n * geo);
    mlp_k
        .backward(
            dev,
            &colour,
            &p_b,
            &cin_b,
            &col_acts_b,
            &d_rgb_b,
            n,
            &grad_b,
            Some((SH_COEFFS, &d_geo_b)),
        )
        .unwrap();
    let d_dens_b = zeros("d density out", n * dw);
    glue.copy_columns(dev, n, 1, &d_sigma_b, at(1, 0), &d_dens_b, at(dw, 0))
        .unwrap();
    glue.copy_columns(dev, n, geo, &d_geo_b, at(geo, 0), &d_dens_b, at(dw, 1))
        .unwrap();
    let d_enc_b = zeros("d enc", n * e);
    mlp_k
        .backward(
            dev,
            &density,
            &p_b,
            &enc_b,
            &dens_acts_b,
            &d_dens_b,
            n,
            &grad_b,
            Some((0, &d_enc_b)),
        )
        .unwrap();
    let (d_h3_b, d_h4_b, m_dm_b) = (
        zeros("d h3", n * e),
        zeros("d h4", n * e),
        zeros("m dm", 2 * n),
    );
    glue.blend_backward(dev, &blend, &d_enc_b, None, (&d_h3_b, &d_h4_b, &m_dm_b))
        .unwrap();
    grid_k
        .backward(dev, &grid3, &pts_b, &d_h3_b, n, &grad_b)
        .unwrap();
    grid_k
        .backward(dev, &grid4, &pts_b, &d_h4_b, n, &grad_b)
        .unwrap();
    mask_k
        .backward(dev, &mask, &pts_b, &m_dm_b, n, &grad_b)
        .unwrap();
    let grad = dev.read_f32(&grad_b, params.len()).unwrap();
    for (name, r) in [
        ("h3", &r3),
        ("h4", &r4),
        ("mask", &rm),
        ("density_mlp", &dr),
        ("color_mlp", &cr),
    ] {
        let scale = grad_cpu[r.clone()].iter().fold(0f32, |a, v| a.max(v.abs()));
        assert!(scale > 0.0, "{name}: no gradient on the CPU");
        let mut worst = 0f32;
        for i in r.clone() {
            let err = (grad[i] - grad_cpu[i]).abs();
            assert!(
                err <= 1e-5 * scale,
                "{name}[{}]: gpu {} cpu {} (slice max {scale})",
                i - r.start,
                grad[i],
                grad_cpu[i]
            );
            worst = worst.max(err / scale);
        }
        println!(
            "field {:?} gradient {name}: worst |gpu - cpu| / slice max {worst:.2e}",
            field.encoding.blend
        );
    }
    // Nothing outside the field's slices (the proposal's) was written.
    let field_slices = [&r3, &r4, &rm, &dr, &cr];
    assert!((0..params.len())
        .filter(|i| !field_slices.iter().any(|r| r.contains(i)))
        .all(|i| grad[i] == 0.0));
    println!(
        "field {:?} forward: worst sigma error / tolerance {worst_sigma:.3}, rgb {worst_rgb:.3} ({mode:?})",
        field.encoding.blend
    );
}
