// Inverse-CDF resampling (after `ray_scan.wgsl` and `sampling.wgsl`), as
// `msth_core::sampling::sample_pdf` with nerfstudio's conventions: every proposal weight
// annealed (`w^a`), made safe (negative, NaN and infinite count as 0) and padded; `pdf_cdf`
// writes the running sums normalised by the ray's total (one workgroup per ray, a scan per
// chunk of 64 bins with a carry), `pdf_sample` places each new edge by bisection.

@group(0) @binding(2) var<storage, read> rays: array<SampleRay>;
// The proposal weights, and the proposal level's edges (`np + 1` per ray).
@group(0) @binding(3) var<storage, read> w_prop: array<f32>;
@group(0) @binding(4) var<storage, read> edges_prop: array<f32>;
// The normalised running sums per proposal bin; a ray whose total is not positive and finite
// gets -1 in its first bin (uniform edges, as the CPU's fallback).
@group(0) @binding(5) var<storage, read_write> cdf: array<f32>;
// The new level's `ns + 1` edges per ray.
@group(0) @binding(6) var<storage, read_write> edges_out: array<f32>;

fn mass(w: f32) -> f32 {
    var a = w;
    if su.f.z != 1.0 {
        a = pow(max(w, 0.0), su.f.z);
    }
    // Positive and finite, else 0.
    let ok = a > 0.0 && a < 3.4e38;
    return select(0.0, a, ok) + su.f.y;
}

@compute @workgroup_size(64)
fn pdf_cdf(inv: Invocation) {
    let lid = inv.lid;
    let r = ray_index(inv);
    let span = ray_span(r, su.run.x);
    let chunks = (span.y - span.x + CH - 1u) / CH;
    var total = 0.0;
    for (var k = 0u; k < chunks; k++) {
        let i = span.x + k * CH + lid;
        var m = 0.0;
        if i < span.y {
            m = mass(w_prop[i]);
        }
        scan(m, lid);
        total += sh[CH - 1u];
    }
    let ok = total > 0.0 && total < 3.4e38;
    let inv_total = 1.0 / total;
    var carry = 0.0;
    for (var k = 0u; k < chunks; k++) {
        let i = span.x + k * CH + lid;
        var m = 0.0;
        if i < span.y {
            m = mass(w_prop[i]);
        }
        let incl = scan(m, lid);
        if i < span.y {
            cdf[i] = select(-1.0, (carry + incl) * inv_total, ok);
        }
        carry += sh[CH - 1u];
    }
}

@compute @workgroup_size(64)
fn pdf_sample(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    // m = ns + 1 new edges per ray.
    let m = su.run.y + 1u;
    if i >= su.run.x * m {
        return;
    }
    let r = i / m;
    let k = i % m;
    let nb = su.run.w;
    let c0 = r * nb;
    if cdf[c0] < 0.0 {
        edges_out[i] = f32(k) / f32(max(m - 1u, 1u));
        return;
    }
    var u: f32;
    if (su.run.z & FLAG_JITTER) != 0u {
        u = min((f32(k) + rays[r].lim.w) / f32(m), 1.0);
    } else {
        u = f32(k) / f32(max(m - 1u, 1u));
    }
    // The first bin whose running sum reaches u (the last bin at most).
    var lo = 0u;
    var hi = nb - 1u;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if u > cdf[c0 + mid] {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    let b = lo;
    let hi_c = cdf[c0 + b];
    var lo_c = 0.0;
    if b > 0u {
        lo_c = cdf[c0 + b - 1u];
    }
    let span = hi_c - lo_c;
    var frac = 0.0;
    if span > 0.0 {
        frac = clamp((u - lo_c) / span, 0.0, 1.0);
    }
    let e = r * (nb + 1u) + b;
    edges_out[i] = edges_prop[e] + frac * (edges_prop[e + 1u] - edges_prop[e]);
}
