// field: the fields at one point: the masked space-time encoding (`encode`: mask, blend, 3D and
// 4D grids) and the decoders on it: the proposal field's density (`proposal_sigma`), the main
// field's density and geometry features (`field_density`) and its colour from those and the SH
// of the view direction (`field_color`). One point per call: `eval_points` calls them per point,
// the passes' sample cache and the generic encodings per sample, a per-pixel kernel can too.

// #import common
// #import bindings
// #import mask
// #import hashgrid
// #import mlp
// #import sh

// The blend of encoding `e` at a point of mask value m: `(k3, k4, read3, read4)`, the features
// being v = k3 f3 + k4 f4 (mst: m, 1 - m; mt: 1, 1 - m; add: 1, 1; 4d: 0, 1; static: 1, 0: the
// CPU's sums, since 1 x = x and a skipped lookup's features are 0; no branch per blend, since
// software adapters run every branch), and whether the 3D and 4D lookups are made (1) or
// skipped (0): the 4D one where the mask leaves (almost) nothing dynamic (Mst/Mt with a mask,
// `1 - m < cutoff`), and the lookup a blend does not read (static: 4D; 4d: 3D).
fn blend_of(e: Encoding, m: f32, cutoff: f32) -> vec4<f32> {
    let blend = e.mode.x;
    let skip4 = blend == 4u || (cutoff > 0.0 && e.mode.y == 1u && blend <= 1u && (1.0 - m) < cutoff);
    let skip3 = blend == 3u;
    let k3 = select(select(1.0, m, blend == 0u), 0.0, blend == 3u);
    let k4 = select(select(1.0 - m, 1.0, blend >= 2u), 0.0, blend == 4u);
    return vec4<f32>(k3, k4, select(1.0, 0.0, skip3), select(1.0, 0.0, skip4));
}

// Whether encoding e, at its own cutoff (`consts.y`, what the passes' encodings are given),
// makes the 4D lookup at unit-cube point x.
fn reads4(e: Encoding, x: vec3<f32>) -> bool {
    return blend_of(e, mask_at(e, x), e.consts.y).w != 0.0;
}

// Masked encoding at point p into hid[0 .. levels * features] (level-major, features within a
// level), the MLPs' input: the 3D tables in `tab3`, the 4D ones in `tab4` (both fields'). Returns
// the mask value m. `with4` false (a constant at the call site): no 4D lookup is compiled in,
// for points whose blend skips it (`reads4` false); the result is the same for those.
fn encode(e: Encoding, p: vec4<f32>, cutoff: f32, with4: bool) -> f32 {
    let m = mask_at(e, p.xyz);
    let use3 = e.h3.loc.z == 1u;
    let use4 = e.h4.loc.z == 1u;
    let b = blend_of(e, m, cutoff);
    let k3 = b.x;
    let k4 = b.y;
    let skip3 = b.z == 0.0;
    let skip4 = b.w == 0.0;
    var levels = 0u;
    var nf = 1u;
    if use3 {
        levels = e.h3.shape.z;
        nf = e.h3.shape.y;
    } else {
        levels = e.h4.shape.z;
        nf = e.h4.shape.y;
    }
    let second = min(1u, nf - 1u);
    let zero = Feat(vec4<f32>(0.0), vec4<f32>(0.0));
    for (var l = 0u; l < levels; l++) {
        var f3 = zero;
        var f4 = zero;
        if use3 && !skip3 {
            f3 = grid_level(e.h3, l, p, 0u);
        }
        if with4 && use4 && !skip4 {
            f4 = grid_level(e.h4, l, p, 1u);
        }
        let va = k3 * f3.a + k4 * f4.a;
        let at = l * nf;
        // Features 0 and 1 (with one feature per level, the second write puts feature 0 back).
        hid[at + second] = va.y;
        hid[at] = va.x;
        for (var f = 2u; f < nf; f++) {
            let vb = k3 * f3.b + k4 * f4.b;
            hid[at + f] = select(vb[f & 3u], va[f & 3u], f < 4u);
        }
    }
    return m;
}

// Proposal density at p.
fn proposal_sigma(p: vec4<f32>, cutoff: f32) -> f32 {
    let d = model.proposal;
    let off = d.x;
    let hidden = d.z;
    encode(model.prop, p, cutoff, true);
    dense_layer(off, d.y, hidden, true);
    let w2 = off + d.y * hidden;
    var s = 0.0;
    for (var j = 0u; j < hidden; j++) {
        s += hid2[j] * rest[w2 + j];
    }
    return trunc_exp(s);
}

// Main-field density at p: returns sigma; geo features in dout[1..=geo]; mask value in *m.
fn field_density(p: vec4<f32>, cutoff: f32, m: ptr<function, f32>) -> f32 {
    let d = model.density;
    let off = d.x;
    let hidden = d.z;
    let nout = d.w;
    *m = encode(model.field, p, cutoff, true);
    dense_layer(off, d.y, hidden, true);
    hid2_to_hid(hidden);
    let w2 = off + d.y * hidden;
    dense_layer(w2, hidden, nout, false);
    for (var o = 0u; o < nout; o++) {
        dout[o] = hid2[o];
    }
    return trunc_exp(dout[0]);
}

// Main-field colour from `sh` and the geo features of the last field_density call.
fn field_color() -> vec3<f32> {
    let c = model.color;
    let geo = c.w;
    let hidden = c.y;
    let layers = c.z;
    let nin = 16u + geo;
    // Constant indices: plain registers, no indexed private memory.
    hid[0] = sh[0];
    hid[1] = sh[1];
    hid[2] = sh[2];
    hid[3] = sh[3];
    hid[4] = sh[4];
    hid[5] = sh[5];
    hid[6] = sh[6];
    hid[7] = sh[7];
    hid[8] = sh[8];
    hid[9] = sh[9];
    hid[10] = sh[10];
    hid[11] = sh[11];
    hid[12] = sh[12];
    hid[13] = sh[13];
    hid[14] = sh[14];
    hid[15] = sh[15];
    for (var k = 0u; k < geo; k++) {
        hid[16u + k] = dout[1u + k];
    }
    var off = c.x;
    dense_layer(off, nin, hidden, true);
    off += nin * hidden;
    for (var k = 1u; k < layers; k++) {
        hid2_to_hid(hidden);
        dense_layer(off, hidden, hidden, true);
        off += hidden * hidden;
    }
    hid2_to_hid(hidden);
    dense_layer(off, hidden, 3u, false);
    let rgb = vec3<f32>(sigmoid(hid2[0]), sigmoid(hid2[1]), sigmoid(hid2[2]));
    return rgb;
}
