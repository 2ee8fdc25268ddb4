// The encoding blend for training, one invocation per sample: `msth_core::field`'s
// enc = a(m) h3 + b(m) h4 (`BlendMode::coefficients`), a grid the mode does not use never read.
// Forward entry `blend_forward`, backward `blend_backward` (d h3 = a d_enc, d h4 = b d_enc,
// d m = sum_k d_enc (a'(m) h3 + b'(m) h4) + an optional extra d m per sample, written as the
// (m, d m) pairs the mask backward takes).

struct Blend {
    // x: samples, y: features per sample, z: flags (1: h3 used, 2: h4 used, 4: extra d m),
    // w: 0.
    run: vec4<u32>,
    // x, y: the per-mode constants of a(m) = x0 + x1 m, b(m) = y0 + y1 m as (a0, a1, b0, b1).
    coef: vec4<f32>,
    // Coarse-to-fine (`msth_core::field::level_factor`): x active levels, y features per level,
    // z level count; features are scaled only while x < z.
    ramp: vec4<f32>,
}

@group(0) @binding(0) var<uniform> bl: Blend;
@group(0) @binding(1) var<storage, read> h3: array<f32>;
@group(0) @binding(2) var<storage, read> h4: array<f32>;
@group(0) @binding(3) var<storage, read> m_in: array<f32>;

fn sample_of(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 64u;
}

// (a, b) at m: a = 1 exactly where the mode's a is 1 (Mt, Add, Static), as the CPU's `h3 + ..`.
fn coefficients(m: f32) -> vec2<f32> {
    return vec2<f32>(bl.coef.x + bl.coef.y * m, bl.coef.z + bl.coef.w * m);
}

// The coarse-to-fine factor of feature `j` of a sample: clamp(active - level, 0, 1).
fn level_factor(j: u32) -> f32 {
    if bl.ramp.x >= bl.ramp.z {
        return 1.0;
    }
    let level = f32(j / u32(bl.ramp.y));
    return clamp(bl.ramp.x - level, 0.0, 1.0);
}
