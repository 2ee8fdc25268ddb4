// specialise: the per-sample passes' encodings and MLPs, the region that hosts replace for one
// model.

// #import common
// #import bindings
// #import mask
// #import hashgrid
// #import mlp
// #import field
// #import passes_work
// #import passes_lanes

// The passes' encodings (`encode_field4`, `encode_proposal4`), MLPs (`proposal_mlp4`,
// `density_mlp4`, `color_mlp4`) and geometry-feature transfers (`geo_to_work`, `geo_from_work`)
// lie between the two `specialise` lines. These generic versions read the level values from the
// uniform and the weights from `rest`, and loop over the geometry features; hosts replace the
// region by versions generated for one model, with those values as constants, the activations in
// named values and the transfers unrolled (msth-gpu `specialise.rs`, the page's
// `specialise.js`), which software adapters run without a gather per read. (A loop over a count
// read from the uniform indexes `hid4` and `out4` at run time, which makes Mesa's lavapipe keep
// those arrays in memory in every pass that does so, for every access.)
// ---- specialise: begin

// out4[0..nout] = hid4[0..nin] W per sample (W [nin, nout] row-major at `off` in `rest`), ReLU
// when `relu`; each output summed over the inputs in order, as on the CPU. Eight outputs at a
// time in registers: one read of a weight serves the LANES samples; the weights are read
// without bounds selects (`r4`).
fn dense_lanes(off: u32, nin: u32, nout: u32, relu: bool) {
    for (var o0 = 0u; o0 < nout; o0 += 8u) {
        let left = nout - o0;
        var a0 = vec4<f32>(0.0);
        var a1 = vec4<f32>(0.0);
        var a2 = vec4<f32>(0.0);
        var a3 = vec4<f32>(0.0);
        var a4 = vec4<f32>(0.0);
        var a5 = vec4<f32>(0.0);
        var a6 = vec4<f32>(0.0);
        var a7 = vec4<f32>(0.0);
        var row = off + o0;
        for (var i = 0u; i < nin; i++) {
            let x = hid4[i];
            let w = r4(row);
            let v = r4(row + 4u);
            a0 += x * w.x;
            a1 += x * w.y;
            a2 += x * w.z;
            a3 += x * w.w;
            a4 += x * v.x;
            a5 += x * v.y;
            a6 += x * v.z;
            a7 += x * v.w;
            row += nout;
        }
        var outs = array<vec4<f32>, 8>(a0, a1, a2, a3, a4, a5, a6, a7);
        for (var k = 0u; k < min(left, 8u); k++) {
            var v = outs[k];
            if relu {
                v = max(v, vec4<f32>(0.0));
            }
            out4[o0 + k] = v;
        }
    }
}

// hid4[0..n] = out4[0..n].
fn out4_to_hid4(n: u32) {
    for (var j = 0u; j < n; j++) {
        hid4[j] = out4[j];
    }
}

// The colours of the LANES samples whose colour inputs (SH coefficients, then the geo
// features) are in hid4, as `field_color`: red, green, blue, component k for sample k.
fn color_mlp4() -> array<vec4<f32>, 3> {
    let c = model.color;
    let hidden = c.y;
    let nin = 16u + c.w;
    var off = c.x;
    dense_lanes(off, nin, hidden, true);
    off += nin * hidden;
    for (var k = 1u; k < c.z; k++) {
        out4_to_hid4(hidden);
        dense_lanes(off, hidden, hidden, true);
        off += hidden * hidden;
    }
    out4_to_hid4(hidden);
    dense_lanes(off, hidden, 3u, false);
    return array<vec4<f32>, 3>(sigmoid4(out4[0]), sigmoid4(out4[1]), sigmoid4(out4[2]));
}

// The field's encoding of point p into lane k of hid4 (`hid4[i][k]`, i < levels * features), as
// `encode` (`with4` a constant at the call site); returns the mask value.
fn encode_field4(p: vec4<f32>, cutoff: f32, k: u32, with4: bool) -> f32 {
    let m = encode(model.field, p, cutoff, with4);
    hid_to_lane(k, model.density.y);
    return m;
}

// The proposal field's encoding of point p into lane k of hid4, as `encode`.
fn encode_proposal4(p: vec4<f32>, cutoff: f32, k: u32, with4: bool) {
    encode(model.prop, p, cutoff, with4);
    hid_to_lane(k, model.proposal.y);
}

// The proposal density MLP of the LANES samples whose encodings are in hid4: the log density
// (before `trunc_exp`), component k for sample k.
fn proposal_mlp4() -> vec4<f32> {
    let d = model.proposal;
    dense_lanes(d.x, d.y, d.z, true);
    let w2 = d.x + d.y * d.z;
    var sum = vec4<f32>(0.0);
    for (var j = 0u; j < d.z; j++) {
        sum += out4[j] * rest[w2 + j];
    }
    return sum;
}

// The density MLP of the LANES samples whose encodings are in hid4: out4[0] the log density,
// out4[1 ..= geo] the geometry features.
fn density_mlp4() {
    let d = model.density;
    dense_lanes(d.x, d.y, d.z, true);
    out4_to_hid4(d.z);
    dense_lanes(d.x + d.y * d.z, d.z, d.w, false);
}

// Sample j's geometry features, out4[1 ..= geo] component k, into the work buffer.
fn geo_to_work(j: u32, k: u32) {
    let geo = model.color.w;
    for (var q = 0u; q < geo; q++) {
        work[pass_u.reg1.x + j * geo + q] = out4[1u + q][k];
    }
}

// Sample j's geometry features from the work buffer into the colour MLP's inputs,
// hid4[16 ..] component k.
fn geo_from_work(j: u32, k: u32) {
    let geo = model.color.w;
    for (var q = 0u; q < geo; q++) {
        hid4[16u + q][k] = work[pass_u.reg1.x + j * geo + q];
    }
}
// ---- specialise: end
