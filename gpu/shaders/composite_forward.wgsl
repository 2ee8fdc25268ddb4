// Compositing forward (after `composite.wgsl`): w per sample, (C, T_N) per ray.

@group(0) @binding(4) var<storage, read_write> w_out: array<f32>;
// (r, g, b, T_N) per ray.
@group(0) @binding(5) var<storage, read_write> ray_out: array<vec4<f32>>;
// The background per ray (FLAG_RAY_BG).
@group(0) @binding(6) var<storage, read> ray_bg: array<vec4<f32>>;

// The last sample's colour as it is composited (0 when hidden).
var<workgroup> last_color: vec4<f32>;

@compute @workgroup_size(64)
fn composite_forward(inv: Invocation) {
    let lid = inv.lid;
    let r = ray_index(inv);
    let start = ray_span(r, u.run.x).x;
    let end = ray_span(r, u.run.x).y;
    var carry = 0.0;
    var c = vec3<f32>(0.0);
    if lid == 0u {
        last_color = vec4<f32>(0.0);
    }
    for (var k = 0u; k < (end - start + CH - 1u) / CH; k++) {
        let i = start + k * CH + lid;
        let live = i < end;
        var tau = 0.0;
        if live {
            tau = tau_of(sd[i]);
        }
        scan(tau, lid);
        let tb = carry + before(lid);
        let t = exp(-tb);
        if live {
            let w = t * one_minus_exp_neg(tau);
            w_out[i] = w;
            var col = color(i);
            if hidden(tb) {
                col = vec3<f32>(0.0);
            }
            c += w * col;
            if i + 1u == end {
                last_color = vec4<f32>(col, 0.0);
            }
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
        var bg = u.bg.xyz;
        if has(FLAG_RAY_BG) {
            bg = ray_bg[r].xyz;
        }
        if has(FLAG_LAST_SAMPLE) {
            bg = last_color.xyz;
        }
        ray_out[r] = vec4<f32>(sh3[0].xyz + t_final * bg, t_final);
    }
}
