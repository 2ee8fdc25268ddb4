// The interlevel (proposal) loss of mip-NeRF 360 for training (`msth_core::losses::interlevel`),
// after `ray_scan.wgsl` (binding 1: the main samples' ray offsets): for each main interval
// [t0, t1] with weight w (held constant), bound = the proposal weight on the proposal intervals
// overlapping it, L = sum max(0, w - bound)^2 / (w + eps), and each overlapping proposal weight
// gets g = -2 max(0, w - bound) / (w + eps) x scale. One workgroup per ray: first one
// invocation per main interval (its bound by a binary search and a walk over the few proposal
// intervals it overlaps; the ray's loss by a scan), then one per proposal interval, which
// gathers the g of the main intervals overlapping it in order (no scatter, no atomics).

struct Interlevel {
    // x: rays, y, z, w: 0.
    run: vec4<u32>,
    // x: scale of the gradient (the loss weight), y, z, w: 0.
    scale: vec4<f32>,
}

@group(0) @binding(0) var<uniform> il: Interlevel;
// (t0, t1) per main sample and its (held) weight.
@group(0) @binding(2) var<storage, read> main_iv: array<vec2<f32>>;
@group(0) @binding(3) var<storage, read> w_main: array<f32>;
// The proposal samples: their ray offsets, intervals and weights.
@group(0) @binding(4) var<storage, read> prop_offsets: array<u32>;
@group(0) @binding(5) var<storage, read> prop_iv: array<vec2<f32>>;
@group(0) @binding(6) var<storage, read> w_prop: array<f32>;
@group(0) @binding(7) var<storage, read_write> d_w_prop: array<f32>;
@group(0) @binding(8) var<storage, read_write> loss: array<f32>;

const EPS: f32 = 1e-7;

// The end of interval k of the main (level 0) or proposal (level 1) samples.
fn interval_end(level: u32, k: u32) -> f32 {
    if level == 0u {
        return main_iv[k].y;
    }
    return prop_iv[k].y;
}

// The first of the intervals [first, end) of `level` that ends after x (their ends increase),
// by bisection; `end` if none.
fn first_ending_after(level: u32, first: u32, end: u32, x: f32) -> u32 {
    var lo = first;
    var hi = end;
    while lo < hi {
        let mid = (lo + hi) / 2u;
        if interval_end(level, mid) <= x {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// max(0, w - bound) of main sample i against the proposal samples [p0, p1): from the first
// proposal interval ending after t0, the ones starting before t1.
fn excess(i: u32, p0: u32, p1: u32) -> f32 {
    let t = main_iv[i];
    let lo = first_ending_after(1u, p0, p1, t.x);
    var bound = 0.0;
    for (var j = lo; j < p1 && prop_iv[j].x < t.y; j++) {
        bound += w_prop[j];
    }
    return max(w_main[i] - bound, 0.0);
}

@compute @workgroup_size(64)
fn interlevel(inv: Invocation) {
    let lid = inv.lid;
    let r = ray_index(inv);
    let span = ray_span(r, il.run.x);
    var prop = vec2<u32>(0u);
    if r < il.run.x {
        prop = vec2<u32>(prop_offsets[r], max(prop_offsets[r + 1u], prop_offsets[r]));
    }
    // The loss: one invocation per main interval.
    var l = 0.0;
    for (var k = 0u; k < (span.y - span.x + CH - 1u) / CH; k++) {
        let i = span.x + k * CH + lid;
        if i < span.y {
            let d = excess(i, prop.x, prop.y);
            l += d * d / (w_main[i] + EPS);
        }
    }
    scan(l, lid);
    if lid == 0u && r < il.run.x {
        loss[r] = sh[CH - 1u];
    }
    // The gradient: one invocation per proposal interval, gathering the main intervals that
    // overlap it (t0 < its end, t1 > its start), in order.
    for (var k = 0u; k < (prop.y - prop.x + CH - 1u) / CH; k++) {
        let j = prop.x + k * CH + lid;
        if j < prop.y {
            let p = prop_iv[j];
            let lo = first_ending_after(0u, span.x, span.y, p.x);
            var acc = d_w_prop[j];
            for (var i = lo; i < span.y && main_iv[i].x < p.y; i++) {
                let d = excess(i, prop.x, prop.y);
                if d > 0.0 {
                    acc += -2.0 * d / (w_main[i] + EPS) * il.scale.x;
                }
            }
            d_w_prop[j] = acc;
        }
    }
}
