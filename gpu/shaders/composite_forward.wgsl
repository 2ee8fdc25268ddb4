// Compositing forward (after `composite.wgsl`): w per sample, (C, T_N) per ray.

@group(0) @binding(4) var<storage, read_write> w_out: array<f32>;
// (r, g, b, T_N) per ray.
@group(0) @binding(5) var<storage, read_write> ray_out: array<vec4<f32>>;

@compute @workgroup_size(64)
fn composite_forward(inv: Invocation) {
    let lid = inv.lid;
    let r = ray_index(inv);
    let start = ray_span(r, u.run.x).x;
    let end = ray_span(r, u.run.x).y;
    var carry = 0.0;
    var c = vec3<f32>(0.0);
    for (var k = 0u; k < (end - start + CH - 1u) / CH; k++) {
        let i = start + k * CH + lid;
        let live = i < end;
        var tau = 0.0;
        if live {
            tau = tau_of(sd[i]);
        }
        scan(tau, lid);
        let t = exp(-(carry + before(lid)));
        if live {
            let w = t * one_minus_exp_neg(tau);
            w_out[i] = w;
            c += w * color(i);
        }
        carry += sh[CH - 1u];
    }
    // The ray's colour: a tree sum of the invocations' partial sums.
    workgroupBarrier();
    sh3[lid] = vec4<f32>(c, 0.0);
    for (var half = CH / 2u; half > 0u; half >>= 1u) {
        workgroupBarrier();
        if lid < half {
            sh3[lid] += sh3[lid + half];
        }
    }
    workgroupBarrier();
    if lid == 0u && r < u.run.x {
        let t_final = exp(-carry);
        ray_out[r] = vec4<f32>(sh3[0].xyz + t_final * u.bg.xyz, t_final);
    }
}
