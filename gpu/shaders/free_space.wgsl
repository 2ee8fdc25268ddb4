// The free-space loss for training (`msth_core::pipeline`'s `free_space_weight`): at random
// points of the volume, L = weight x sum_j (1 - exp(-sigma_j delta)), so
// dL/dsigma_j = weight x scale x delta x exp(-sigma_j delta), written as the field backward's
// d_sigma; each point's share of the loss beside it. One invocation per point; sigma is column 0
// of the density MLP's output rows (`run.y` floats each).

struct FreeSpace {
    // x: points, y: stride of the density rows, z, w: 0.
    run: vec4<u32>,
    // x: weight, y: weight x loss scale x delta, z: delta, w: 0.
    k: vec4<f32>,
}

@group(0) @binding(0) var<uniform> fsu: FreeSpace;
@group(0) @binding(1) var<storage, read> density: array<f32>;
@group(0) @binding(2) var<storage, read_write> d_sigma: array<f32>;
@group(0) @binding(3) var<storage, read_write> loss: array<f32>;

@compute @workgroup_size(64)
fn free_space(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if i >= fsu.run.x {
        return;
    }
    let e = exp(-density[i * fsu.run.y] * fsu.k.z);
    d_sigma[i] = fsu.k.y * e;
    loss[i] = (1.0 - e) * fsu.k.x;
}
