// Mask backward: d logit = d m * m * (1 - m), scattered to the 8 corners with weight w through
// `add_grad` (an atomic variant declares it and the `grad` binding, here 3). Needs `mask.wgsl`
// and the atomic variant before it; binding 2 holds (m, d m) per sample.

@group(0) @binding(2) var<storage, read> m_dm: array<vec2<f32>>;

@compute @workgroup_size(64)
fn mask_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    if i < mask.run.x {
        let md = m_dm[i];
        let d = md.y * md.x * (1.0 - md.x);
        // A sample with no gradient issues no atomics (as the CPU skips d == 0).
        if d != 0.0 {
            var c = mask_cell(points[i]);
            for (var k = 0u; k < 8u; k++) {
                let g = c.w[k] * d;
                if g != 0.0 {
                    add_grad(c.idx[k], g);
                }
            }
        }
    }
}
