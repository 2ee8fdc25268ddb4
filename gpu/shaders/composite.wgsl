// Volume rendering for training (`msth_core::render`): per ray, tau_i = sigma_i delta_i (made
// safe as `tau_of`), T_i = exp(-sum_{j<i} tau_j), w_i = T_i (1 - exp(-tau_i)),
// C = sum w_i c_i + T_N bg; and the backward d sigma_k = delta_k (d_w_k T_{k+1}
// - sum_{i>k} d_w_i w_i - d_T T_N), with d_w_i = extra_i + dC . c_i, d c_i = dC w_i,
// d_T = dC . bg.
//
// One workgroup per ray, one invocation per sample: the ray's samples (rays are contiguous
// ranges `offsets[r] .. offsets[r + 1]` of the ray-major sample buffers) go through in chunks
// of 64, and the sums along the ray are scans in workgroup memory (6 steps per chunk) with a
// carry between chunks: no invocation loops over the ray's samples.

struct Composite {
    // x: rays, y: flags (1: extra per-sample d_w given), z, w: 0.
    run: vec4<u32>,
    // rgb: background colour.
    bg: vec4<f32>,
}

@group(0) @binding(0) var<uniform> u: Composite;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
// (sigma, delta) per sample.
@group(0) @binding(2) var<storage, read> sd: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> rgb: array<f32>;

const CH: u32 = 64u;

var<workgroup> sh: array<f32, 64>;
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

// Inclusive scan of v over the workgroup's 64 invocations; sh[63] holds the total after.
fn scan(v: f32, lid: u32) -> f32 {
    workgroupBarrier();
    sh[lid] = v;
    for (var off = 1u; off < CH; off <<= 1u) {
        workgroupBarrier();
        let add = select(0.0, sh[max(lid, off) - off], lid >= off);
        workgroupBarrier();
        sh[lid] += add;
    }
    workgroupBarrier();
    return sh[lid];
}

// The scan's value for the invocation before `lid` (0 for the first): the exclusive scan with
// the very same additions as the inclusive one.
fn before(lid: u32) -> f32 {
    return select(0.0, sh[max(lid, 1u) - 1u], lid > 0u);
}

fn color(i: u32) -> vec3<f32> {
    return vec3<f32>(rgb[3u * i], rgb[3u * i + 1u], rgb[3u * i + 2u]);
}

// The builtins both entry points take.
struct Invocation {
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
}

// The workgroup's ray (a dispatch tiled into 2D).
fn ray_index(inv: Invocation) -> u32 {
    return inv.wid.x + inv.wid.y * inv.groups.x;
}

// Ray r's samples `[start, end)`; empty for workgroups past the last ray, which run through
// doing nothing (no early exit: every barrier stays in uniform control flow).
fn ray_span(r: u32) -> vec2<u32> {
    if r >= u.run.x {
        return vec2<u32>(0u);
    }
    let start = offsets[r];
    return vec2<u32>(start, max(offsets[r + 1u], start));
}
