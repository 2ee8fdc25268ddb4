// Hash-grid backward: scatters d loss / d features of every (sample, level) pair into the
// gradient of the table rows it read, w * d per corner and feature, through `add_grad` (native
// f32 atomics or a compare-exchange loop: `atomic_native.wgsl` / `atomic_cas.wgsl`, which also
// declare the `grad` binding 3). Needs `hashgrid.wgsl` before it.

@group(0) @binding(2) var<storage, read> d_features: array<f32>;

@compute @workgroup_size(64)
fn encode_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let idx = invocation(gid, groups);
    let dims = DIMS;
    let nf = NF;
    let nl = grid.shape.z;
    if idx < grid.run.x * nl {
        let i = idx / nl;
        let l = idx % nl;
        let lv = grid.levels[l];
        let dense = lv.info.y == 1u;
        let o = (i * nl + l) * nf;
        var d = array<f32, 8>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        var any = false;
        for (var f = 0u; f < NF; f++) {
            d[f] = d_features[o + f];
            any = any || d[f] != 0.0;
        }
        // A sample whose features get no gradient (masked out, zero loss weight) issues no atomics.
        if any {
            let c = cell(lv, points[i], dims);
            let base = grid.run.y + lv.info.x;
            for (var k = 0u; k < (1u << DIMS); k++) {
                let cr = corner(c, k, dense, grid.shape.w);
                let at = base + cr.row * nf;
                for (var f = 0u; f < NF; f++) {
                    let g = cr.w * d[f];
                    if g != 0.0 {
                        add_grad(at + f, g);
                    }
                }
            }
        }
    }
}
