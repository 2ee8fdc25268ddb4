// Hash-grid forward: features of every (sample, level) pair. Needs `hashgrid.wgsl` before it.

@group(0) @binding(2) var<storage, read> table: array<f32>;
@group(0) @binding(3) var<storage, read_write> features: array<f32>;

@compute @workgroup_size(64)
fn encode_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let idx = invocation(gid, groups);
    let dims = DIMS;
    let nf = NF;
    let nl = grid.shape.z;
    if idx < grid.run.x * nl {
        let i = idx / nl;
        let l = idx % nl;
        let lv = grid.levels[l];
        let dense = lv.info.y == 1u;
        let c = cell(lv, points[i], dims);
        var acc = array<f32, 8>(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let base = grid.run.y + lv.info.x;
        for (var k = 0u; k < (1u << DIMS); k++) {
            let cr = corner(c, k, dense, grid.shape.w);
            let at = base + cr.row * nf;
            for (var f = 0u; f < NF; f++) {
                acc[f] = acc[f] + cr.w * table[at + f];
            }
        }
        let o = (i * nl + l) * nf;
        for (var f = 0u; f < NF; f++) {
            features[o + f] = acc[f];
        }
    }
}
