// Compositing backward (after `composite.wgsl`): from dC per ray (and, with flag 1, an extra
// d loss / d w per sample, from the losses on the weights), d sigma and d rgb per sample.

@group(0) @binding(4) var<storage, read> w_in: array<f32>;
// The forward's (r, g, b, T_N) per ray (T_N is read).
@group(0) @binding(5) var<storage, read> ray_out: array<vec4<f32>>;
// dC per ray (rgb; w: d_T with FLAG_RAY_BG).
@group(0) @binding(6) var<storage, read> d_ray: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> d_w_extra: array<f32>;
// (d sigma, d r, d g, d b) per sample; `.x` first holds T_{i+1} between the two sweeps, `.y`
// 1 where the colour is hidden.
@group(0) @binding(8) var<storage, read_write> d_sample: array<vec4<f32>>;

// The last sample's colour as it was composited (0 when hidden).
var<workgroup> last_color: vec4<f32>;

@compute @workgroup_size(64)
fn composite_backward(inv: Invocation) {
    let lid = inv.lid;
    // Workgroups past the last ray read the last ray's values and write nothing.
    let r = min(ray_index(inv), max(u.run.x, 1u) - 1u);
    let span = ray_span(ray_index(inv), u.run.x);
    let start = span.x;
    let end = span.y;
    let chunks = (end - start + CH - 1u) / CH;
    let dc = d_ray[r].xyz;
    let t_final = ray_out[r].w;
    if lid == 0u {
        last_color = vec4<f32>(0.0);
    }
    // Front to back: T_{i+1} = exp(-sum_{j<=i} tau_j).
    var carry = 0.0;
    for (var k = 0u; k < chunks; k++) {
        let i = start + k * CH + lid;
        var tau = 0.0;
        if i < end {
            tau = tau_of(sd[i]);
        }
        let incl = scan(tau, lid);
        if i < end {
            let hide = hidden(carry + before(lid));
            d_sample[i] = vec4<f32>(exp(-(carry + incl)), select(0.0, 1.0, hide), 0.0, 0.0);
            if i + 1u == end && !hide {
                last_color = vec4<f32>(color(i), 0.0);
            }
        }
        carry += sh[CH - 1u];
    }
    workgroupBarrier();
    var d_t = dot(dc, u.bg.xyz);
    if has(FLAG_RAY_BG) {
        d_t = d_ray[r].w;
    }
    if has(FLAG_LAST_SAMPLE) {
        d_t = dot(dc, last_color.xyz);
    }
    // Back to front: suffix_i = sum_{j>i} d_w_j w_j, invocation lid at the lid-th sample from
    // the end of the chunk.
    var suffix = 0.0;
    for (var k = 0u; k < chunks; k++) {
        let back = k * CH + lid;
        let live = back < end - start;
        let i = end - 1u - min(back, end - start - 1u);
        var dw = 0.0;
        var w = 0.0;
        var hide = false;
        if live {
            w = w_in[i];
            hide = d_sample[i].y != 0.0;
            if !hide {
                dw = dot(dc, color(i));
            }
            if has(FLAG_EXTRA_DW) {
                dw += d_w_extra[i];
            }
        }
        scan(dw * w, lid);
        let after = suffix + before(lid);
        if live {
            let s = sd[i];
            let t_next = d_sample[i].x;
            let d_tau = dw * t_next - after - d_t * t_final;
            let p = s.x * s.y;
            let valid = p >= 0.0 && p < 1e30;
            var d_rgb = dc * w;
            if has(FLAG_LAST_SAMPLE) && i + 1u == end {
                d_rgb += dc * t_final;
            }
            d_sample[i] = vec4<f32>(select(0.0, d_tau * s.y, valid), select(d_rgb, vec3<f32>(0.0), hide));
        }
        suffix += sh[CH - 1u];
    }
}
