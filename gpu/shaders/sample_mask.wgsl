// The per-sample mask loss for training (`msth_core::pipeline`'s `sample_mask_weight`):
// L = weight x sum_i f_r(i) w_i (1 - m_i) with the rendering weights w_i held constant and f_r
// the factor of sample i's ray r (0 for rays through pixels that change over time), so
// dL/dm_i = -weight x scale x f_r x w_i, written where the blend backward adds it to the mask's
// gradient; each sample's share of the loss beside it. One invocation per sample.

struct SampleMask {
    // x: samples, y: samples per ray, z, w: 0.
    run: vec4<u32>,
    // x: weight, y: weight x loss scale, z, w: 0.
    k: vec4<f32>,
}

@group(0) @binding(0) var<uniform> smu: SampleMask;
@group(0) @binding(1) var<storage, read> w: array<f32>;
@group(0) @binding(2) var<storage, read> m: array<f32>;
@group(0) @binding(3) var<storage, read_write> d_m: array<f32>;
@group(0) @binding(4) var<storage, read_write> loss: array<f32>;
@group(0) @binding(5) var<storage, read> ray_factor: array<f32>;

@compute @workgroup_size(64)
fn sample_mask(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if i >= smu.run.x {
        return;
    }
    let f = ray_factor[i / smu.run.y];
    d_m[i] = -smu.k.y * f * w[i];
    loss[i] = f * w[i] * (1.0 - m[i]) * smu.k.x;
}
