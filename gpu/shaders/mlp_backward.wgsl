// MLP backward (after `mlp.wgsl` and an atomic variant, which declares `grad` at binding 3 and
// `add_grad`): from d loss / d (activated outputs) and the forward's `acts`, adds the weight
// gradients into `grad` and, with FLAG_D_INPUT, writes d loss / d input columns info.z.. into
// `d_input` [n, dims[0] - info.z].
//
// Per layer, last to first: (B) the weight gradient sum_s x[s, i] dy[s, o] of the workgroup's
// GROUP samples, in chunks of CHUNK samples staged in `tile`; invocation t owns the 4x4 block
// (rows 4 (t / fo4).., columns 4 (t % fo4)..) and keeps it in registers over the whole tile,
// then adds it with one `add_grad` per entry: one atomic per weight and workgroup. (A) the
// input gradient dx = W dy with the layer's weights staged in `tile`, masked by the ReLU.

@group(0) @binding(4) var<storage, read> acts: array<f32>;
@group(0) @binding(5) var<storage, read> d_output: array<f32>;
@group(0) @binding(6) var<storage, read_write> d_input: array<f32>;

const CHUNK: u32 = 32u;

// Inputs 4 i4 .. 4 i4 + 3 of layer k for sample s: the network's input (k = 0) or hidden
// layer k - 1's output (zero past the width).
fn layer_input4(k: u32, s: u32, i4: u32) -> vec4<f32> {
    if k == 0u {
        return input4(s, i4, dim(0u));
    }
    let fi = dim(k);
    let at = s * mlp.info.y + aoff(k - 1u);
    var v = vec4<f32>(0.0);
    for (var j = 0u; j < 4u; j++) {
        if 4u * i4 + j < fi {
            v[j] = acts[at + 4u * i4 + j];
        }
    }
    return v;
}

@compute @workgroup_size(256)
fn mlp_backward(inv: Invocation) {
    let lid = inv.lid;
    let s = tile_start(inv) + lid;
    let live = s < mlp.run.x;
    let layers = tile_layers(inv);
    // d loss / d raw output: through the output activation, as the CPU field does.
    var dy: array<vec4<f32>, W4>;
    if live {
        let fl = dim(layers);
        let raw_at = s * mlp.info.y + aoff(layers - 1u);
        for (var o4 = 0u; o4 < (fl + 3u) / 4u; o4++) {
            var d4 = vec4<f32>(0.0);
            for (var j = 0u; j < 4u; j++) {
                let o = 4u * o4 + j;
                if o < fl {
                    let raw = acts[raw_at + o];
                    var d = d_output[s * fl + o];
                    if mlp.info.x == ACT_SIGMOID {
                        let y = logistic(raw);
                        d *= y * (1.0 - y);
                    } else if mlp.info.x == ACT_DENSITY && o == 0u {
                        d *= exp(clamp(raw, -15.0, 15.0)); // trunc_exp_grad
                    }
                    d4[j] = d;
                }
            }
            dy[o4] = d4;
        }
    }
    for (var kk = 0u; kk < layers; kk++) {
        let k = layers - 1u - kk;
        let fi = dim(k);
        let fo = dim(k + 1u);
        let fi4 = (fi + 3u) / 4u;
        let fo4 = (fo + 3u) / 4u;
        // (B) weight gradient of layer k over the tile.
        let own = lid < fi4 * fo4;
        let ib = lid / fo4;
        let ob = lid % fo4;
        var gw: array<vec4<f32>, 4>;
        for (var c = 0u; c < GROUP / CHUNK; c++) {
            workgroupBarrier();
            if lid / CHUNK == c {
                let j = lid % CHUNK;
                for (var i4 = 0u; i4 < fi4; i4++) {
                    var v = vec4<f32>(0.0);
                    if live {
                        v = layer_input4(k, s, i4);
                    }
                    tile[j * W4 + i4] = v;
                }
                for (var o4 = 0u; o4 < fo4; o4++) {
                    tile[(CHUNK + j) * W4 + o4] = dy[o4];
                }
            }
            workgroupBarrier();
            if own {
                for (var j = 0u; j < CHUNK; j++) {
                    let xv = tile[j * W4 + ib];
                    let d = tile[(CHUNK + j) * W4 + ob];
                    gw[0] = fma(vec4<f32>(xv.x), d, gw[0]);
                    gw[1] = fma(vec4<f32>(xv.y), d, gw[1]);
                    gw[2] = fma(vec4<f32>(xv.z), d, gw[2]);
                    gw[3] = fma(vec4<f32>(xv.w), d, gw[3]);
                }
            }
        }
        if own {
            let base = mlp.run.z + woff(k);
            for (var r = 0u; r < 4u; r++) {
                let i = ib * 4u + r;
                for (var c = 0u; c < 4u; c++) {
                    let o = ob * 4u + c;
                    let v = lane(gw[r], c);
                    // Zero contributions (dead ReLUs, padding) issue no atomic.
                    if i < fi && o < fo && v != 0.0 {
                        add_grad(base + i * fo + o, v);
                    }
                }
            }
        }
        // (A) input gradient of layer k: 4 rows of W times dy at a time.
        if k > 0u || (mlp.run.w & FLAG_D_INPUT) != 0u {
            workgroupBarrier();
            stage_weights(k, lid);
            workgroupBarrier();
            let first = select(0u, mlp.info.z, k == 0u);
            var dx: array<vec4<f32>, W4>;
            if live {
                for (var i4 = first / 4u; i4 < fi4; i4++) {
                    var d = vec4<f32>(0.0);
                    let r = 4u * i4 * fo4;
                    for (var o4 = 0u; o4 < fo4; o4++) {
                        let y = dy[o4];
                        d += vec4<f32>(
                            dot(tile[r + o4], y),
                            dot(tile[r + fo4 + o4], y),
                            dot(tile[r + 2u * fo4 + o4], y),
                            dot(tile[r + 3u * fo4 + o4], y),
                        );
                    }
                    if k > 0u {
                        // The ReLU: no gradient where the unit was off (as the CPU's select).
                        d = select(vec4<f32>(0.0), d, layer_input4(k, s, i4) > vec4<f32>(0.0));
                    } else {
                        for (var j = 0u; j < 4u; j++) {
                            let i = 4u * i4 + j;
                            if i >= first && i < fi {
                                d_input[s * (fi - first) + i - first] = lane(d, j);
                            }
                        }
                    }
                    dx[i4] = d;
                }
            }
            dy = dx;
        }
    }
}
