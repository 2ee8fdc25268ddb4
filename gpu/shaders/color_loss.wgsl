// The colour loss for training (as `msth_core::pipeline::train`): per ray the mean squared
// error over rgb of the composited colour C against the target, and dC = 2 (C - target) / 3
// times the loss scale, written where the compositing backward reads it. One invocation per
// ray.

struct ColorLoss {
    // x: rays, y, z, w: 0.
    run: vec4<u32>,
    // x: loss scale, y, z, w: 0.
    scale: vec4<f32>,
}

@group(0) @binding(0) var<uniform> cl: ColorLoss;
// (r, g, b, T_N) per ray: the compositing forward's output.
@group(0) @binding(1) var<storage, read> ray_out: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> targets: array<f32>;
// (dC, 0) per ray.
@group(0) @binding(3) var<storage, read_write> d_ray: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> sq_err: array<f32>;

@compute @workgroup_size(64)
fn color_loss(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = gid.x + gid.y * groups.x * 64u;
    if r >= cl.run.x {
        return;
    }
    let c = ray_out[r];
    var se = 0.0;
    var dc = vec4<f32>(0.0);
    for (var ch = 0u; ch < 3u; ch++) {
        let diff = c[ch] - targets[3u * r + ch];
        se += diff * diff;
        dc[ch] = 2.0 * diff / 3.0 * cl.scale.x;
    }
    d_ray[r] = dc;
    sq_err[r] = se / 3.0;
}
