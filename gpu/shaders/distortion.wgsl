// The distortion loss of mip-NeRF 360 for training (`msth_core::losses::distortion`), after
// `ray_scan.wgsl`: per ray, L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_{i+1} - s_i)
// over intervals [s_i, s_{i+1}] with midpoints m_i, in O(n) from the sums of w and w m before
// and after each sample; adds scale * dL/dw_i into `d_w` (each sample's entry belongs to one
// invocation: no atomics) and writes L per ray.

struct Distortion {
    // x: rays, y, z, w: 0.
    run: vec4<u32>,
    // x: scale of the gradient (the loss weight), y, z, w: 0.
    scale: vec4<f32>,
}

@group(0) @binding(0) var<uniform> dl: Distortion;
// (s_i, s_{i+1}) per sample: its interval in the normalised ray coordinate.
@group(0) @binding(2) var<storage, read> intervals: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> w_in: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_w: array<f32>;
@group(0) @binding(5) var<storage, read_write> loss: array<f32>;

@compute @workgroup_size(64)
fn distortion(inv: Invocation) {
    let lid = inv.lid;
    let r = ray_index(inv);
    let span = ray_span(r, dl.run.x);
    let chunks = (span.y - span.x + CH - 1u) / CH;
    // The ray's totals of w and w m.
    var w_tot = 0.0;
    var wm_tot = 0.0;
    for (var k = 0u; k < chunks; k++) {
        let i = span.x + k * CH + lid;
        var w = 0.0;
        var m = 0.0;
        if i < span.y {
            w = w_in[i];
            m = 0.5 * (intervals[i].x + intervals[i].y);
        }
        scan(w, lid);
        w_tot += sh[CH - 1u];
        scan(w * m, lid);
        wm_tot += sh[CH - 1u];
    }
    // Each sample with the sums before it (exclusive scans) and after it (the rest).
    var w_carry = 0.0;
    var wm_carry = 0.0;
    var l = 0.0;
    for (var k = 0u; k < chunks; k++) {
        let i = span.x + k * CH + lid;
        let live = i < span.y;
        var w = 0.0;
        var s = vec2<f32>(0.0);
        if live {
            w = w_in[i];
            s = intervals[i];
        }
        let m = 0.5 * (s.x + s.y);
        scan(w, lid);
        let w_before = w_carry + before(lid);
        w_carry += sh[CH - 1u];
        scan(w * m, lid);
        let wm_before = wm_carry + before(lid);
        wm_carry += sh[CH - 1u];
        if live {
            let d = s.y - s.x;
            let w_after = w_tot - w_before - w;
            let wm_after = wm_tot - wm_before - w * m;
            let pair = m * w_before - wm_before + wm_after - m * w_after;
            l += w * (m * w_before - wm_before) * 2.0 + w * w * d / 3.0;
            d_w[i] += dl.scale.x * (2.0 * pair + 2.0 / 3.0 * w * d);
        }
    }
    scan(l, lid);
    if lid == 0u && r < dl.run.x {
        loss[r] = sh[CH - 1u];
    }
}
