// Blend forward (after `blend.wgsl`).

@group(0) @binding(4) var<storage, read_write> enc: array<f32>;

@compute @workgroup_size(64)
fn blend_forward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = sample_of(gid, groups);
    if i >= bl.run.x {
        return;
    }
    let e = bl.run.y;
    let ab = coefficients(m_in[i]);
    for (var k = i * e; k < (i + 1u) * e; k++) {
        var v = 0.0;
        if (bl.run.z & 1u) != 0u {
            v = ab.x * h3[k];
        }
        if (bl.run.z & 2u) != 0u {
            v += ab.y * h4[k];
        }
        enc[k] = v * level_factor(k - i * e);
    }
}
