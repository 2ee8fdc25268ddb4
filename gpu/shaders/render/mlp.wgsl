// mlp: the generic MLP layers of one sample (weights read from `rest`, activations in the
// private arrays below), as msth-core's decoders.

// #import common
// #import bindings

// MLP activations: the input (an encoding of at most MAX_LEVELS * MAX_FEATURES values) and
// hidden layers in `hid`, each layer's output in `hid2`.
var<private> hid: array<f32, 256>;
var<private> hid2: array<f32, MAX_HIDDEN>;
var<private> dout: array<f32, 32>; // 1 + MAX_GEO

// rest[b .. b + 4], the components at or beyond `left` read as 0.
fn w4(b: u32, left: u32) -> vec4<f32> {
    return vec4<f32>(
        select(0.0, rest[b], left > 0u),
        select(0.0, rest[b + 1u], left > 1u),
        select(0.0, rest[b + 2u], left > 2u),
        select(0.0, rest[b + 3u], left > 3u),
    );
}

// rest[b .. b + 4], unconditionally: in `dense_lanes` the components past a layer's last output
// are other parameters (or, past the buffer's end, what robust buffer access returns) and reach
// only outputs that are not stored.
fn r4(b: u32) -> vec4<f32> {
    return vec4<f32>(rest[b], rest[b + 1u], rest[b + 2u], rest[b + 3u]);
}

// a - b, or 0 when b > a.
fn sub_sat(a: u32, b: u32) -> u32 {
    return select(0u, a - b, a > b);
}

// hid2[0..nout] = hid[0..nin] W (W [nin, nout] row-major at `off` in `rest`), ReLU when `relu`;
// each output summed over the inputs in order, as on the CPU. Sixteen outputs at a time in four
// vec4 accumulators that stay in registers (indexed private memory only outside the inner loop:
// software rasterisers such as SwiftShader turn every indexed private access into a per-lane
// gather or scatter).
fn dense_layer(off: u32, nin: u32, nout: u32, relu: bool) {
    for (var o0 = 0u; o0 < nout; o0 += 16u) {
        let left = nout - o0;
        let l1 = sub_sat(left, 4u);
        let l2 = sub_sat(left, 8u);
        let l3 = sub_sat(left, 12u);
        var a0 = vec4<f32>(0.0);
        var a1 = vec4<f32>(0.0);
        var a2 = vec4<f32>(0.0);
        var a3 = vec4<f32>(0.0);
        var row = off + o0;
        for (var i = 0u; i < nin; i++) {
            let x = hid[i];
            a0 += x * w4(row, left);
            a1 += x * w4(row + 4u, l1);
            a2 += x * w4(row + 8u, l2);
            a3 += x * w4(row + 12u, l3);
            row += nout;
        }
        if relu {
            a0 = max(a0, vec4<f32>(0.0));
            a1 = max(a1, vec4<f32>(0.0));
            a2 = max(a2, vec4<f32>(0.0));
            a3 = max(a3, vec4<f32>(0.0));
        }
        let outs = array<vec4<f32>, 4>(a0, a1, a2, a3);
        for (var k = 0u; k < min(left, 16u); k++) {
            hid2[o0 + k] = outs[k >> 2u][k & 3u];
        }
    }
}

// hid[0..n] = hid2[0..n].
fn hid2_to_hid(n: u32) {
    for (var j = 0u; j < n; j++) {
        hid[j] = hid2[j];
    }
}
