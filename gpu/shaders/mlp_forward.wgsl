// MLP forward (after `mlp.wgsl`): `output` [n, dims[L]] gets the activated outputs; with
// FLAG_ACTS, `acts` [n, info.y] gets every hidden layer's output (after the ReLU) and the raw
// last layer, which the backward reads.

@group(0) @binding(3) var<storage, read_write> output: array<f32>;
@group(0) @binding(4) var<storage, read_write> acts: array<f32>;

@compute @workgroup_size(256)
fn mlp_forward(inv: Invocation) {
    let lid = inv.lid;
    let s = tile_start(inv) + lid;
    let live = s < mlp.run.x;
    let store = (mlp.run.w & FLAG_ACTS) != 0u;
    let layers = tile_layers(inv);
    let d0 = dim(0u);
    // The current layer's input, 4 units per vec4 (zero past the width).
    var x: array<vec4<f32>, W4>;
    if live {
        for (var i4 = 0u; i4 < (d0 + 3u) / 4u; i4++) {
            x[i4] = input4(s, i4, d0);
        }
    }
    for (var k = 0u; k < layers; k++) {
        workgroupBarrier();
        stage_weights(k, lid);
        workgroupBarrier();
        let fi4 = (dim(k) + 3u) / 4u;
        let fo = dim(k + 1u);
        let fo4 = (fo + 3u) / 4u;
        let hidden = k + 1u < layers;
        var y: array<vec4<f32>, W4>;
        for (var o4 = 0u; o4 < fo4; o4++) {
            var a = vec4<f32>(0.0);
            for (var i4 = 0u; i4 < fi4; i4++) {
                a = rows_times(x[i4], i4, fo4, o4, a);
            }
            if hidden {
                // As the CPU's `v.max(0.0)`: NaN gives 0.
                a = select(vec4<f32>(0.0), a, a > vec4<f32>(0.0));
            }
            y[o4] = a;
            if live && store {
                let at = s * mlp.info.y + aoff(k) + 4u * o4;
                for (var j = 0u; j < min(4u, fo - 4u * o4); j++) {
                    acts[at + j] = lane(a, j);
                }
            }
        }
        x = y;
    }
    if live {
        let fl = dim(layers);
        for (var o = 0u; o < fl; o++) {
            var y = lane(x[o / 4u], o % 4u);
            if mlp.info.x == ACT_SIGMOID {
                y = logistic(y);
            } else if mlp.info.x == ACT_DENSITY && o == 0u {
                y = exp(min(y, 88.0)); // trunc_exp
            }
            output[s * fl + o] = y;
        }
    }
}
