// points: the `eval_points` entry point, one invocation per point: the fields at given points,
// exactly as the CPU's field evaluation (kernel tests; the play-time volume's bake).

// #import common
// #import bindings
// #import io
// #import sh
// #import mask
// #import mlp
// #import field

// Evaluates the fields at view.size.z points. Point j is 8 words of `list` read as f32: (x, y, z,
// t) in the unit cube / unit time, direction (dx, dy, dz) for the SH encoding, and what to
// evaluate:
//   0  the main field, exactly (no static cutoff): frame[j] = (r, g, b, sigma);
//   1  the proposal field, exactly: (m, 0, 0, sigma) with the proposal's mask value m;
//   2  the main field under the renderer's static cutoff, for the play-time volume's bake:
//      (r, g, b, density pre-activation);
//   3  the main field with no 4D lookup (a static brick's bake): as 2.
@compute @workgroup_size(64)
fn eval_points(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let j = invocation(gid, groups);
    if j < view.size.z {
        var v: array<f32, 8>;
        for (var k = 0u; k < 8u; k++) {
            v[k] = bitcast<f32>(list[j * 8u + k]);
        }
        let p = vec4<f32>(v[0], v[1], v[2], v[3]);
        if v[7] == 1.0 {
            let sigma = proposal_sigma(p, 0.0);
            frame[j] = vec4<f32>(mask_at(model.prop, p.xyz), 0.0, 0.0, sigma);
        } else {
            sh4(vec3<f32>(v[4], v[5], v[6]));
            var m = 1.0;
            var cutoff = 0.0;
            if v[7] == 2.0 {
                cutoff = model.field.consts.y;
            } else if v[7] == 3.0 {
                cutoff = 3.40282346e38;
            }
            let sigma = field_density(p, cutoff, &m);
            let c = field_color();
            frame[j] = vec4<f32>(c, select(sigma, dout[0], v[7] >= 2.0));
        }
    }
}
