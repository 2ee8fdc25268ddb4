// The colour loss for training (as `msth_core::pipeline::train`): per ray the mean squared
// error over rgb of the composited colour C against the target, and dC = 2 (C - target) / 3
// times the loss scale, written where the compositing backward reads it, with d_T = dC . bg
// beside it (the background: one colour, or one per ray with flag 1). One invocation per ray.

struct ColorLoss {
    // x: rays, y: 1 with a background per ray, z, w: 0.
    run: vec4<u32>,
    // x: loss scale, yzw: the background colour.
    scale: vec4<f32>,
}

@group(0) @binding(0) var<uniform> cl: ColorLoss;
// (r, g, b, T_N) per ray: the compositing forward's output.
@group(0) @binding(1) var<storage, read> ray_out: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> targets: array<f32>;
// (dC, d_T) per ray.
@group(0) @binding(3) var<storage, read_write> d_ray: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> sq_err: array<f32>;
@group(0) @binding(5) var<storage, read> ray_bg: array<vec4<f32>>;

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
    var bg = cl.scale.yzw;
    if cl.run.y == 1u {
        bg = ray_bg[r].xyz;
    }
    dc.w = dot(dc.xyz, bg);
    d_ray[r] = dc;
    sq_err[r] = se / 3.0;
}
