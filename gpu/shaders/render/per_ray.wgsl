// per_ray: one invocation per ray (`render`) or per point (`eval_points`), exactly as the CPU
// renderer at render time (msth-core `pipeline::render_chunk`): ray limits against the scene
// box (or contraction), proposal samples, proposal field density, proposal resampling, main
// samples, masked space-time encoding (3D hash grid, 4D hash grid, dense mask), density and
// colour decoders, SH direction encoding, volume compositing and background. The per-sample
// passes (`passes`) render the same frames with bounded work per invocation.

// #import common
// #import bindings
// #import io
// #import camera
// #import sh
// #import field

// Per-invocation scratch of `render_ray`: the proposal weights and the main samples' edges.
var<private> w_prop: array<f32, MAX_PROPOSAL_SAMPLES>;
var<private> s_main: array<f32, 129>; // MAX_SAMPLES + 1

struct RayResult {
    rgb: vec3<f32>,
    visible_depth: f32,
}

fn render_ray(o: vec3<f32>, d: vec3<f32>, time_in: f32) -> RayResult {
    let np = model.sampler.x;
    let nf = model.sampler.y;
    let lim = ray_limits(o, d);
    let near = lim.x;
    let far = lim.y;
    let time = select(0.0, min(time_in, 1.0), time_in >= 0.0);
    let cutoff3 = model.field.consts.y;
    let cutoff_p = model.prop.consts.y;
    sh4(normalize(d));

    // Proposal samples: uniform in s, midpoints in distance; weights by volume rendering.
    var tau_sum = 0.0;
    var t_prev = t_of_s(0.0, near, far);
    for (var k = 0u; k < np; k++) {
        let t_next = t_of_s(f32(k + 1u) / f32(np), near, far);
        let delta = max(t_next - t_prev, 0.0);
        let sigma = proposal_sigma(sample_point(o, d, t_prev, t_next, time), cutoff_p);
        let tau = tau_of(sigma, delta);
        w_prop[k] = exp(-tau_sum) * -expm1(-tau);
        tau_sum += tau;
        t_prev = t_next;
    }

    // Resample (deterministic inverse-CDF of the padded histogram), nf + 1 edges in s.
    let m_out = nf + 1u;
    let pad = model.limits.z;
    var total = 0.0;
    for (var k = 0u; k < np; k++) {
        total += sanitize(w_prop[k]) + pad;
    }
    if !(total > 0.0 && total <= 3.40282346e38) {
        for (var k = 0u; k < m_out; k++) {
            s_main[k] = f32(k) / f32(max(m_out - 1u, 1u));
        }
    } else {
        let inv = 1.0 / total;
        var bin = 0u;
        var cdf_lo = 0.0;
        var cdf_hi = (sanitize(w_prop[0]) + pad) * inv;
        for (var k = 0u; k < m_out; k++) {
            let u = f32(k) / f32(max(m_out - 1u, 1u));
            while u > cdf_hi && bin + 1u < np {
                bin += 1u;
                cdf_lo = cdf_hi;
                cdf_hi += (sanitize(w_prop[bin]) + pad) * inv;
            }
            let span = cdf_hi - cdf_lo;
            var frac = 0.0;
            if span > 0.0 {
                frac = clamp((u - cdf_lo) / span, 0.0, 1.0);
            }
            let e0 = f32(bin) / f32(np);
            let e1 = f32(bin + 1u) / f32(np);
            s_main[k] = e0 + frac * (e1 - e0);
        }
        for (var k = 1u; k < m_out; k++) {
            if s_main[k] < s_main[k - 1u] {
                s_main[k] = s_main[k - 1u];
            }
        }
    }

    // Main samples: density everywhere, colour where light still arrives; composite in order.
    var rgb = vec3<f32>(0.0);
    var last_rgb = vec3<f32>(0.0);
    tau_sum = 0.0;
    var acc = 0.0;
    var visible = -1.0;
    var t0 = t_of_s(s_main[0], near, far);
    var t1 = t0;
    for (var k = 0u; k < nf; k++) {
        t1 = t_of_s(s_main[k + 1u], near, far);
        let delta = max(t1 - t0, 0.0);
        var m = 1.0;
        let sigma = field_density(sample_point(o, d, t0, t1, time), cutoff3, &m);
        var c = vec3<f32>(0.0);
        if tau_sum <= TAU_HIDDEN {
            c = field_color();
        }
        let tau = tau_of(sigma, delta);
        let w = exp(-tau_sum) * -expm1(-tau);
        tau_sum += tau;
        rgb += w * c;
        last_rgb = c;
        acc += w;
        if visible < 0.0 && 1.0 - acc < VISIBLE_TRANSMITTANCE {
            visible = t1;
        }
        t0 = t1;
    }
    let t_final = exp(-tau_sum);
    var bg = model.background.xyz;
    if model.background.w == 0.0 {
        bg = select(vec3<f32>(0.0), last_rgb, nf > 0u);
    }
    rgb += t_final * bg;
    if visible < 0.0 {
        visible = t1;
    }
    return RayResult(rgb, visible);
}

// ---- Entry points -----------------------------------------------------------------------------

// Renders view.size.z rays: pixel i, or pixel list[i] with flag bit 0. Writes
// (r, g, b, visible depth) to frame[pixel], or frame[i] with flag bit 1. Rays that miss the scene
// box under a constant background get the background without evaluation and the visible depth
// MISSED (negative; a rendered ray's is at least the sampler's near >= 0), so that whoever reads
// the frame back counts them without recomputing the rays.
@compute @workgroup_size(64)
fn render(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    if i < view.size.z {
        let flags = view.size.w;
        var pixel = i;
        if (flags & 1u) == 1u {
            pixel = list[i];
        }
        let out = select(pixel, i, (flags & 2u) == 2u);
        let o = view.c2w[3].xyz;
        let d = pixel_ray_dir(pixel);
        let lim = ray_limits(o, d);
        if !(lim.y > lim.x) && model.background.w == 1.0 {
            frame[out] = vec4<f32>(model.background.xyz, MISSED);
        } else {
            let r = render_ray(o, d, view.time.x);
            frame[out] = vec4<f32>(r.rgb, r.visible_depth);
        }
    }
}

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
