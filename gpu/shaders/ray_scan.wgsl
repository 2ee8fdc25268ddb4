// Per-ray scans for training (compositing, the distortion loss): one workgroup of CH
// invocations per ray, one invocation per sample, the ray's samples (rays are contiguous ranges
// `offsets[r] .. offsets[r + 1]` of ray-major per-sample buffers) in chunks of CH, sums along
// the ray as scans in workgroup memory (6 steps per chunk) with a carry between chunks: no
// invocation loops over the ray's samples. The kernels that include this declare binding 0
// (their uniform) and bindings from 2.

@group(0) @binding(1) var<storage, read> offsets: array<u32>;

const CH: u32 = 64u;

var<workgroup> sh: array<f32, 64>;

// The builtins both entry points take.
struct Invocation {
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
}

// The workgroup's ray (a dispatch tiled into 2D).
fn ray_index(inv: Invocation) -> u32 {
    return inv.wid.x + inv.wid.y * inv.groups.x;
}

// Ray r's samples `[start, end)`; empty for workgroups past the last ray, which run through
// doing nothing (no early exit: every barrier stays in uniform control flow).
fn ray_span(r: u32, rays: u32) -> vec2<u32> {
    if r >= rays {
        return vec2<u32>(0u);
    }
    let start = offsets[r];
    return vec2<u32>(start, max(offsets[r + 1u], start));
}

// Inclusive scan of v over the workgroup's 64 invocations; sh[63] holds the total after.
fn scan(v: f32, lid: u32) -> f32 {
    workgroupBarrier();
    sh[lid] = v;
    for (var off = 1u; off < CH; off <<= 1u) {
        workgroupBarrier();
        let add = select(0.0, sh[max(lid, off) - off], lid >= off);
        workgroupBarrier();
        sh[lid] += add;
    }
    workgroupBarrier();
    return sh[lid];
}

// The scan's value for the invocation before `lid` (0 for the first): the exclusive scan with
// the very same additions as the inclusive one.
fn before(lid: u32) -> f32 {
    return select(0.0, sh[max(lid, 1u) - 1u], lid > 0u);
}
