// Adam over the flat parameter buffer, one invocation per parameter: exactly the trainer's
// `msth_trainer::adam::Adam::update` (same operations in the same order): the mask loss's
// elementwise gradient and a slice's weight decay (`decay * x`) added in the slices, the
// gradient clamped to +-max_gradient, the moments, the bias-corrected step (step size and
// 1 / sqrt(bias correction 2) computed on the host as the CPU does), a per-slice learning-rate
// scale. Each workgroup also writes the sum of
// its parameters' mask-loss terms to `partials[workgroup]` (the host adds them in f64).

struct MaskSlice {
    // x: first parameter, y: one past the last.
    range: vec4<u32>,
    // x: loss weight, y: learning-rate scale, z: parameters in the slice (as f32), w: weight decay.
    vals: vec4<f32>,
}

struct Adam {
    // x: parameters, y: mask slices, z, w: 0.
    run: vec4<u32>,
    // x: step size (lr / bias correction 1), y: 1 / sqrt(bias correction 2), z: beta1, w: beta2.
    coef: vec4<f32>,
    // x: eps, y: max gradient, z, w: 0.
    more: vec4<f32>,
    slices: array<MaskSlice, 8>,
}

@group(0) @binding(0) var<uniform> adam: Adam;
@group(0) @binding(1) var<storage, read> grad: array<f32>;
@group(0) @binding(2) var<storage, read_write> params: array<f32>;
@group(0) @binding(3) var<storage, read_write> m1: array<f32>;
@group(0) @binding(4) var<storage, read_write> m2: array<f32>;
@group(0) @binding(5) var<storage, read_write> partials: array<f32>;

var<workgroup> part: array<f32, 64>;

fn sigmoid(x: f32) -> f32 {
    let e = exp(-abs(x));
    return select(e / (1.0 + e), 1.0 / (1.0 + e), x >= 0.0);
}

@compute @workgroup_size(64)
fn adam_step(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let i = gid.x + gid.y * groups.x * 64u;
    var loss = 0.0;
    if i < adam.run.x {
        var p = params[i];
        var gi = grad[i];
        var scale = 1.0;
        for (var k = 0u; k < adam.run.y; k++) {
            let s = adam.slices[k];
            if i >= s.range.x && i < s.range.y {
                scale = s.vals.y;
                if s.vals.w != 0.0 {
                    gi += s.vals.w * p;
                }
                let sg = sigmoid(p);
                gi += -s.vals.x * sg * (1.0 - sg) / s.vals.z;
                loss += s.vals.x * (1.0 - sg) / s.vals.z;
            }
        }
        gi = clamp(gi, -adam.more.y, adam.more.y);
        let b1 = adam.coef.z;
        let b2 = adam.coef.w;
        let m = b1 * m1[i] + (1.0 - b1) * gi;
        let v = b2 * m2[i] + (1.0 - b2) * gi * gi;
        let denom = sqrt(v) * adam.coef.y + adam.more.x;
        p -= adam.coef.x * scale * m / denom;
        m1[i] = m;
        m2[i] = v;
        params[i] = p;
    }
    part[lid] = loss;
    for (var w = 32u; w > 0u; w >>= 1u) {
        workgroupBarrier();
        if lid < w {
            part[lid] += part[lid + w];
        }
    }
    if lid == 0u {
        partials[wid.x + wid.y * groups.x] = part[0];
    }
}
