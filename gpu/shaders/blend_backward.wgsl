// Blend backward (after `blend.wgsl`).

@group(0) @binding(4) var<storage, read> d_enc: array<f32>;
@group(0) @binding(5) var<storage, read> d_m_extra: array<f32>;
@group(0) @binding(6) var<storage, read_write> d_h3: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_h4: array<f32>;
// (m, d m) per sample, for the mask backward.
@group(0) @binding(8) var<storage, read_write> m_dm: array<vec2<f32>>;

@compute @workgroup_size(64)
fn blend_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = sample_of(gid, groups);
    if i >= bl.run.x {
        return;
    }
    let e = bl.run.y;
    let m = m_in[i];
    let ab = coefficients(m);
    var dm = 0.0;
    for (var k = i * e; k < (i + 1u) * e; k++) {
        let d = d_enc[k] * level_factor(k - i * e);
        if (bl.run.z & 1u) != 0u {
            d_h3[k] = ab.x * d;
            if bl.coef.y != 0.0 {
                dm += d * bl.coef.y * h3[k];
            }
        }
        if (bl.run.z & 2u) != 0u {
            d_h4[k] = ab.y * d;
            if bl.coef.w != 0.0 {
                dm += d * bl.coef.w * h4[k];
            }
        }
    }
    if (bl.run.z & 4u) != 0u {
        dm += d_m_extra[i];
    }
    m_dm[i] = vec2<f32>(m, dm);
}
