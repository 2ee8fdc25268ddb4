// mask: the dense mask grid, trilinear and sigmoid: the weight m of the static encoding.

// #import common
// #import bindings

// Trilinear read of the dense mask grid (logit), `res^3` values at `off` in `rest`. Per-axis
// values in vectors, not indexed arrays (software adapters turn those into memory traffic).
fn mask_logit(off: u32, res: u32, x: vec3<f32>) -> f32 {
    let pos = clamp_unit3(x) * f32(res - 1u);
    let base = min(vec3<u32>(pos), vec3<u32>(res - 2u));
    let fr = pos - vec3<f32>(base);
    var v = 0.0;
    for (var c = 0u; c < 8u; c++) {
        let bx = c & 1u;
        let by = (c >> 1u) & 1u;
        let bz = (c >> 2u) & 1u;
        let idx = (base.x + bx) + res * ((base.y + by) + res * (base.z + bz));
        var w = select(1.0 - fr.x, fr.x, bx == 1u);
        w *= select(1.0 - fr.y, fr.y, by == 1u);
        w *= select(1.0 - fr.z, fr.z, bz == 1u);
        v += w * rest[off + idx];
    }
    return v;
}

// Mask value m in [0, 1] at a unit-cube point.
fn mask_at(e: Encoding, x: vec3<f32>) -> f32 {
    var m = e.consts.x;
    if e.mode.y == 1u {
        m = sigmoid(mask_logit(e.mode.w, e.mode.z, x));
    }
    return m;
}
