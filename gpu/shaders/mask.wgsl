// The dense mask grid for training, one invocation per sample: exactly
// `msth_core::grid::DenseGrid3` followed by a sigmoid (`msth_core::field`'s mask).
//
// A res^3 grid of logits over the unit cube, vertex (x, y, z) at x + res * (y + res * z):
// pos_a = clamp01(x_a) * (res - 1), i_a = min(floor(pos_a), res - 2), fr_a = pos_a - i_a; the
// logit is the trilinear blend of the 8 corners (corner bit 0: x, 1: y, 2: z; weights
// multiplied x, y, z), m = sigmoid(logit). The entry points live in `mask_forward.wgsl` /
// `mask_backward.wgsl`, after this prelude.

struct Mask {
    // x: samples, y: res, z: offset of the logits in the table buffer (floats), w: 0.
    run: vec4<u32>,
}

@group(0) @binding(0) var<uniform> mask: Mask;
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;

const WORKGROUP: u32 = 64u;

fn invocation(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * WORKGROUP;
}

fn clamp_unit(x: f32) -> f32 {
    // NaN maps to 0 (as the CPU's `if x >= 0 { min(x, 1) } else { 0 }`).
    return select(0.0, min(x, 1.0), x >= 0.0);
}

fn sigmoid(x: f32) -> f32 {
    // 1 / (1 + e^-x) for x >= 0, e^x / (1 + e^x) otherwise, as on the CPU.
    let e = exp(-min(abs(x), 80.0));
    return select(e / (1.0 + e), 1.0 / (1.0 + e), x >= 0.0);
}

struct MaskCell {
    idx: array<u32, 8>,
    w: array<f32, 8>,
}

fn mask_cell(p: vec4<f32>) -> MaskCell {
    let r = mask.run.y;
    var pa = array<f32, 3>(p.x, p.y, p.z);
    var base = array<u32, 3>(0u, 0u, 0u);
    var fr = array<f32, 3>(0.0, 0.0, 0.0);
    for (var a = 0u; a < 3u; a++) {
        let q = clamp_unit(pa[a]) * f32(r - 1u);
        let i = min(u32(q), r - 2u); // q >= 0: truncation is floor
        base[a] = i;
        fr[a] = q - f32(i);
    }
    var c: MaskCell;
    for (var k = 0u; k < 8u; k++) {
        let bx = k & 1u;
        let by = (k >> 1u) & 1u;
        let bz = (k >> 2u) & 1u;
        c.idx[k] = mask.run.z + (base[0] + bx) + r * ((base[1] + by) + r * (base[2] + bz));
        c.w[k] = select(1.0 - fr[0], fr[0], bx == 1u) * select(1.0 - fr[1], fr[1], by == 1u)
            * select(1.0 - fr[2], fr[2], bz == 1u);
    }
    return c;
}
