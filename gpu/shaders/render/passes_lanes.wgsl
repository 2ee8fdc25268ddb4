// passes_lanes: the per-sample passes' MLP activations of LANES samples at once (component k
// of a `vec4` for sample k), shared by the generic and the specialised MLPs.

// #import common
// #import mlp

// Samples per invocation of `pass_proposal`, `pass_density`, `pass_dynamic` and `pass_color`.
const LANES: u32 = 4u;
// Activations, component k for sample k: the MLPs' input in `hid4`, the density MLP's output in
// `out4` (the generic MLPs below also keep their hidden layers there).
var<private> hid4: array<vec4<f32>, MAX_HIDDEN>; // also the colour input: 16 + MAX_GEO < MAX_HIDDEN
var<private> out4: array<vec4<f32>, MAX_HIDDEN>;

fn sigmoid4(x: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(sigmoid(x.x), sigmoid(x.y), sigmoid(x.z), sigmoid(x.w));
}

// hid4[0..n] component `lane` = hid[0..n] (one sample's MLP input into its lane).
fn hid_to_lane(lane: u32, n: u32) {
    for (var q = 0u; q < n; q++) {
        hid4[q][lane] = hid[q];
    }
}
