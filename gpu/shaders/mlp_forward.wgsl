// MLP forward (after `mlp.wgsl`): `output` [n, dims[L]] gets the activated outputs; with
// FLAG_ACTS, `acts` [n, info.y] gets every hidden layer's output (after the ReLU) and the raw
// last layer, which the backward reads.

@group(0) @binding(3) var<storage, read_write> output: array<f32>;
@group(0) @binding(4) var<storage, read_write> acts: array<f32>;

@compute @workgroup_size(256)
fn mlp_forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = group_index(wid, groups);
    if g * GROUP >= mlp.run.x {
        return;
    }
    let s = g * GROUP + lid;
    let live = s < mlp.run.x;
    let store = (mlp.run.w & FLAG_ACTS) != 0u;
    let layers = mlp.run.y;
    let d0 = dim(0u);
    var x: array<f32, 64>;
    if live {
        for (var i = 0u; i < d0; i++) {
            x[i] = input[s * d0 + i];
        }
    }
    var acc: array<vec4<f32>, W4>;
    for (var k = 0u; k < layers; k++) {
        workgroupBarrier();
        stage_weights(k, lid);
        workgroupBarrier();
        let fi = dim(k);
        let fo = dim(k + 1u);
        let fo4 = (fo + 3u) / 4u;
        for (var o = 0u; o < W4; o++) {
            acc[o] = vec4<f32>(0.0);
        }
        for (var i = 0u; i < fi; i++) {
            let xi = vec4<f32>(x[i]);
            for (var o = 0u; o < W4; o++) {
                if o < fo4 {
                    acc[o] = fma(xi, tile[i * fo4 + o], acc[o]);
                }
            }
        }
        let hidden = k + 1u < layers;
        for (var o = 0u; o < fo; o++) {
            var v = acc[o / 4u][o % 4u];
            if hidden {
                // As the CPU's `v.max(0.0)`: NaN gives 0.
                v = select(0.0, v, v > 0.0);
            }
            x[o] = v;
            if live && store {
                acts[s * mlp.info.y + aoff(k) + o] = v;
            }
        }
    }
    if live {
        let fl = dim(layers);
        for (var o = 0u; o < fl; o++) {
            var y = x[o];
            if mlp.info.x == ACT_SIGMOID {
                y = logistic(y);
            } else if mlp.info.x == ACT_DENSITY && o == 0u {
                y = exp(min(y, 88.0)); // trunc_exp
            }
            output[s * fl + o] = y;
        }
    }
}
