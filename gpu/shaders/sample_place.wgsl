// `place_samples` (after `sampling.wgsl`): one invocation per sample of a level.

@group(0) @binding(1) var<storage, read> rays: array<SampleRay>;
// The level's `ns + 1` edges per ray in `s`: read, or written with FLAG_UNIFORM_EDGES.
@group(0) @binding(2) var<storage, read_write> edges: array<f32>;
@group(0) @binding(3) var<storage, read_write> points: array<vec4<f32>>;
// (sigma, delta) per sample: delta is written, sigma left for the density pass.
@group(0) @binding(4) var<storage, read_write> sd: array<vec2<f32>>;
// (s_i, s_i+1) per sample.
@group(0) @binding(5) var<storage, read_write> intervals: array<vec2<f32>>;
// With FLAG_DIRS: the ray's unit direction per sample (3 floats; 0 for a direction that is
// not finite or zero), for the colour's direction encoding.
@group(0) @binding(6) var<storage, read_write> dirs: array<f32>;

// `uniform_edges`: edge k of n, jittered by j in [0, 1) (or k / n without jitter).
fn uniform_edge(k: u32, n: u32, j: f32) -> f32 {
    if (su.run.z & FLAG_JITTER) == 0u {
        return f32(k) / f32(n);
    }
    if k == 0u {
        return 0.0;
    }
    if k >= n {
        return 1.0;
    }
    return (f32(k) + (j - 0.5)) / f32(n);
}

@compute @workgroup_size(64)
fn place_samples(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = linear_index(gid, groups);
    let ns = su.run.y;
    if i >= su.run.x * ns {
        return;
    }
    let r = i / ns;
    let k = i % ns;
    let ray = rays[r];
    let e = r * (ns + 1u) + k;
    var s0: f32;
    var s1: f32;
    if (su.run.z & FLAG_UNIFORM_EDGES) != 0u {
        s0 = uniform_edge(k, ns, ray.lim.z);
        s1 = uniform_edge(k + 1u, ns, ray.lim.z);
        edges[e] = s0;
        if k + 1u == ns {
            edges[e + 1u] = s1;
        }
    } else {
        s0 = edges[e];
        s1 = edges[e + 1u];
    }
    let near = ray.lim.x;
    let far = ray.lim.y;
    let spacing = su.run.z & FLAG_LINDISP;
    var t0 = near;
    var t1 = near;
    if far > near {
        t0 = t_of_s(s0, near, far, spacing, su.f.x);
        t1 = t_of_s(s1, near, far, spacing, su.f.x);
    }
    let p = ray.o.xyz + ray.d.xyz * (0.5 * (t0 + t1));
    let bounds = (su.run.z & FLAG_CONTRACTED) >> 1u;
    points[i] = vec4<f32>(to_unit(p, bounds, su.b0, su.b1), ray.o.w);
    sd[i].y = max(t1 - t0, 0.0);
    intervals[i] = vec2<f32>(s0, s1);
    if (su.run.z & FLAG_DIRS) != 0u {
        // glam's `normalize_or_zero`: times the reciprocal length where that is finite.
        let rcp = 1.0 / length(ray.d.xyz);
        var d = vec3<f32>(0.0);
        if rcp > 0.0 && rcp < 3.4e38 {
            d = ray.d.xyz * rcp;
        }
        dirs[3u * i] = d.x;
        dirs[3u * i + 1u] = d.y;
        dirs[3u * i + 2u] = d.z;
    }
}
