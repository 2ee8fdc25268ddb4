// Mask forward: m = sigmoid(trilinear logit) per sample. Needs `mask.wgsl` before it.

@group(0) @binding(2) var<storage, read> logits: array<f32>;
@group(0) @binding(3) var<storage, read_write> m_out: array<f32>;

@compute @workgroup_size(64)
fn mask_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    if i < mask.run.x {
        var c = mask_cell(points[i]);
        var v = 0.0;
        for (var k = 0u; k < 8u; k++) {
            v = v + c.w[k] * logits[c.idx[k]];
        }
        m_out[i] = sigmoid(v);
    }
}
