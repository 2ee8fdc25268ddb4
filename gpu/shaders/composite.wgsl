// Volume rendering for training (`msth_core::render`): per ray, tau_i = sigma_i delta_i (made
// safe as `tau_of`), T_i = exp(-sum_{j<i} tau_j), w_i = T_i (1 - exp(-tau_i)),
// C = sum w_i c_i + T_N bg; and the backward d sigma_k = delta_k (d_w_k T_{k+1}
// - sum_{i>k} d_w_i w_i - d_T T_N), with d_w_i = extra_i + dC . c_i, d c_i = dC w_i,
// d_T = dC . bg.
//
// Flags (`run.y`) for training steps: FLAG_EXTRA_DW, an extra per-sample d_w (the losses on
// the weights); FLAG_RAY_BG, a background per ray (forward: binding 6; backward: d_T comes
// with dC as the `w` of each ray's d_ray, the colour loss having computed dC . bg);
// FLAG_LAST_SAMPLE, the last sample's colour as the background (`Background::LastSample`);
// FLAG_HIDE, samples behind optical depth `bg.w` get colour 0 and no colour gradient (as the
// CPU, which evaluates no colour there: `HIDDEN_TRANSMITTANCE`).
//
// After `ray_scan.wgsl` (one workgroup per ray, scans along it).

struct Composite {
    // x: rays, y: flags, z, w: 0.
    run: vec4<u32>,
    // rgb: background colour; w: the optical depth beyond which colours are hidden.
    bg: vec4<f32>,
}

const FLAG_EXTRA_DW: u32 = 1u;
const FLAG_RAY_BG: u32 = 2u;
const FLAG_LAST_SAMPLE: u32 = 4u;
const FLAG_HIDE: u32 = 8u;

fn has(flag: u32) -> bool {
    return (u.run.y & flag) != 0u;
}

// Whether a sample whose optical depth before it is `before_tau` has its colour hidden.
fn hidden(before_tau: f32) -> bool {
    return has(FLAG_HIDE) && before_tau > u.bg.w;
}

@group(0) @binding(0) var<uniform> u: Composite;
// (sigma, delta) per sample.
@group(0) @binding(2) var<storage, read> sd: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> rgb: array<f32>;

var<workgroup> sh3: array<vec4<f32>, 64>;

fn tau_of(s: vec2<f32>) -> f32 {
    // As the CPU: negative or NaN count as 0, infinite as a wall of 1e30.
    let t = s.x * s.y;
    return select(0.0, min(t, 1e30), t >= 0.0);
}

// 1 - exp(-tau) for tau >= 0 without cancellation for small tau (the CPU's -expm1(-tau)).
fn one_minus_exp_neg(tau: f32) -> f32 {
    if tau < 0.1 {
        return tau * (1.0 - tau / 2.0 * (1.0 - tau / 3.0 * (1.0 - tau / 4.0 * (1.0 - tau / 5.0))));
    }
    return 1.0 - exp(-tau);
}

fn color(i: u32) -> vec3<f32> {
    return vec3<f32>(rgb[3u * i], rgb[3u * i + 1u], rgb[3u * i + 2u]);
}
