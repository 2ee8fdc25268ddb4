// The bias-free MLPs for training (`msth_core::mlp::MlpLayout`): ReLU on hidden layers, the raw
// last layer followed by an output activation, weights of layer k row-major [dims[k], dims[k+1]]
// at `woff(k)` inside the MLP's slice of the flat parameter buffer.
//
// One workgroup of GROUP invocations takes a tile of GROUP samples, one invocation per sample;
// a layer's whole weight matrix is staged in workgroup memory (`tile`, 16 KiB: every width is
// at most 4 * W4 = 64, so a layer holds at most 64 rows of 16 vec4) and read there as vec4
// broadcasts (every invocation reads the same address). Entry points: `mlp_forward.wgsl`,
// `mlp_backward.wgsl`, after this prelude.

struct Mlp {
    // x: samples, y: layers, z: offset of the MLP's weights in the parameter (and gradient)
    // buffer in floats, w: flags (FLAG_*).
    run: vec4<u32>,
    // x: output activation (ACT_*), y: floats per sample in `acts`, z: first input column that
    // gets a gradient, w: 0.
    info: vec4<u32>,
    // dims[0..=layers], weight offsets per layer, offset of layer k's output in an `acts` row.
    dims: array<vec4<u32>, 3>,
    woff: array<vec4<u32>, 3>,
    aoff: array<vec4<u32>, 3>,
}

@group(0) @binding(0) var<uniform> mlp: Mlp;
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read> input: array<f32>;

const GROUP: u32 = 256u;
const W4: u32 = 16u;
const FLAG_ACTS: u32 = 1u;
const FLAG_D_INPUT: u32 = 2u;
const ACT_SIGMOID: u32 = 1u;
const ACT_DENSITY: u32 = 2u;

var<workgroup> tile: array<vec4<f32>, 1024>;

fn dim(k: u32) -> u32 {
    return mlp.dims[k / 4u][k % 4u];
}

fn woff(k: u32) -> u32 {
    return mlp.woff[k / 4u][k % 4u];
}

fn aoff(k: u32) -> u32 {
    return mlp.aoff[k / 4u][k % 4u];
}

// The builtins both entry points take.
struct Invocation {
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
}

// The first sample of the invocation's workgroup (a dispatch tiled into 2D).
fn tile_start(inv: Invocation) -> u32 {
    return (inv.wid.x + inv.wid.y * inv.groups.x) * GROUP;
}

// The layers the workgroup runs through: none for workgroups past the last sample (the 2D
// tiling's spares), which so skip all work with no early exit, every barrier staying in
// uniform control flow.
fn tile_layers(inv: Invocation) -> u32 {
    return select(0u, mlp.run.y, tile_start(inv) < mlp.run.x);
}

// 1 / (1 + e^-x), as `msth_core::activation::sigmoid` (no overflow for large |x|).
fn logistic(x: f32) -> f32 {
    let e = exp(-abs(x));
    return select(e / (1.0 + e), 1.0 / (1.0 + e), x >= 0.0);
}

// Layer k's weights into `tile`: row r at r * fo4, zero-padded to a multiple of 4 columns and
// of 4 rows (kernels read rows 4 at a time).
fn stage_weights(k: u32, lid: u32) {
    let fi = dim(k);
    let fo = dim(k + 1u);
    let fo4 = (fo + 3u) / 4u;
    let base = mlp.run.z + woff(k);
    for (var e = lid; e < (fi + 3u) / 4u * 4u * fo4; e += GROUP) {
        let r = e / fo4;
        let c = (e % fo4) * 4u;
        var v = vec4<f32>(0.0);
        for (var j = 0u; j < 4u; j++) {
            if r < fi && c + j < fo {
                v[j] = params[base + r * fo + c + j];
            }
        }
        tile[e] = v;
    }
}

// x[4 i4 + r] (i4 < fi4) times rows 4 i4 + r of the staged weights, summed: output block o4.
fn rows_times(x: vec4<f32>, i4: u32, fo4: u32, o4: u32, acc: vec4<f32>) -> vec4<f32> {
    let r = 4u * i4 * fo4 + o4;
    var a = fma(vec4<f32>(x.x), tile[r], acc);
    a = fma(vec4<f32>(x.y), tile[r + fo4], a);
    a = fma(vec4<f32>(x.z), tile[r + 2u * fo4], a);
    return fma(vec4<f32>(x.w), tile[r + 3u * fo4], a);
}

// Inputs 4 i4 .. 4 i4 + 3 of sample s (zero past the width d0).
fn input4(s: u32, i4: u32, d0: u32) -> vec4<f32> {
    var v = vec4<f32>(0.0);
    for (var j = 0u; j < 4u; j++) {
        if 4u * i4 + j < d0 {
            v[j] = input[s * d0 + 4u * i4 + j];
        }
    }
    return v;
}

// Element j < 4 of v without dynamic component indexing.
fn lane(v: vec4<f32>, j: u32) -> f32 {
    return select(select(v.x, v.y, j == 1u), select(v.z, v.w, j == 3u), j >= 2u);
}
