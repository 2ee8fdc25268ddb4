// passes_rays: the passes up to each ray's main samples: ray setup, dispatch sizes, the live
// lists of an occupancy grid, the proposal field's densities and the resampling.

// #import common
// #import bindings
// #import io
// #import camera
// #import field
// #import passes_work
// #import passes_lanes
// #import specialise

@compute @workgroup_size(64)
fn pass_setup(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    if i < pass_u.tile.y {
        let g = pass_u.tile.x + i;
        let flags = pass_u.tile.z;
        var pixel = g;
        if (flags & FLAG_P_LIST) != 0u {
            pixel = list[g];
        }
        let out = select(pixel, g, (flags & FLAG_P_COMPACT) != 0u);
        let o = view.c2w[3].xyz;
        let d = pixel_ray_dir(pixel);
        let lim = ray_limits(o, d);
        if !(lim.y > lim.x) && model.background.w == 1.0 {
            frame[out] = vec4<f32>(model.background.xyz, MISSED);
        } else {
            let slot = atomicAdd(&ctrl[0], 1u);
            let at = pass_u.reg0.x + 4u * slot;
            work[at] = bitcast<f32>(out);
            work[at + 1u] = bitcast<f32>(pixel);
            work[at + 2u] = lim.x;
            work[at + 3u] = lim.y;
        }
    }
}

// Indirect dispatch sizes, 3 words each: [0] proposal samples / LANES, [3] rays,
// [6] main samples / LANES, [9] colour list / LANES, [12] dynamic samples / LANES, [15] rays x proposal
// samples, [18] rays x S, [21] 3D-only proposal samples / LANES, [24] 3D-only main samples /
// LANES. With an occupancy grid (`Pass.reg2.y` != 0) [0] and [6] count the live samples with a
// 4D lookup, [21] and [24] those without, as `pass_live_proposal` and `pass_live_samples`
// listed them (`ctrl[3]`, `ctrl[4]`, `ctrl[5]`, `ctrl[6]`); without a grid [0] and [6] count
// every (ray, sample) pair, and [21] and [24] nothing.
@compute @workgroup_size(1)
fn pass_args() {
    let n = atomicLoad(&ctrl[0]);
    var np = n * model.sampler.x;
    var ns = n * samples_per_ray();
    write_groups(15u, np);
    write_groups(18u, ns);
    var np3 = 0u;
    var ns3 = 0u;
    if pass_u.reg2.y != 0u {
        np = atomicLoad(&ctrl[3]);
        ns = atomicLoad(&ctrl[4]);
        np3 = atomicLoad(&ctrl[5]);
        ns3 = atomicLoad(&ctrl[6]);
    }
    write_groups(0u, (np + LANES - 1u) / LANES);
    write_groups(3u, n);
    write_groups(6u, (ns + LANES - 1u) / LANES);
    write_groups(9u, (atomicLoad(&ctrl[1]) + LANES - 1u) / LANES);
    write_groups(12u, (atomicLoad(&ctrl[2]) + LANES - 1u) / LANES);
    write_groups(21u, (np3 + LANES - 1u) / LANES);
    write_groups(24u, (ns3 + LANES - 1u) / LANES);
}

// With an occupancy grid, per (ray, proposal sample): a sample in an occupied cell is appended
// to the live list (`Pass.reg2.z`) that `pass_proposal` (samples whose mask leaves them a 4D
// lookup, `ctrl[3]`) and `pass_proposal3` (the others, `ctrl[5]`) evaluate; the others get
// density 0 here. So the proposal passes cost what the occupied space costs, however the empty
// samples fall among neighbouring invocations, and the 4D lookups cost what the dynamic space
// costs: an invocation's lanes run both sides of a branch on software adapters (and diverge on
// hardware) when any of them takes it, however few.
@compute @workgroup_size(64)
fn pass_live_proposal(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let e = invocation(gid, groups);
    let total = ray_count() * model.sampler.x;
    if e < total {
        let p = proposal_point(e).xyz;
        if occupied(p) {
            live_append(pass_u.reg2.z, total, e, !split_lists() || reads4(model.prop, p), 3u);
        } else {
            work[pass_u.reg0.y + e] = 0.0;
        }
    }
}

// With an occupancy grid, per (ray, main sample): the live list of `pass_density` and
// `pass_density3` (`Pass.reg2.w`, `ctrl[4]` and `ctrl[6]`), as `pass_live_proposal`'s; a
// sample in an empty cell gets density 0 here.
@compute @workgroup_size(64)
fn pass_live_samples(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let j = invocation(gid, groups);
    let s = samples_per_ray();
    let total = ray_count() * s;
    if j < total {
        let r = j / s;
        let p = main_point(r, j % s, ray_rec(r)).xyz;
        if occupied(p) {
            live_append(pass_u.reg2.w, total, j, !split_lists() || reads4(model.field, p), 4u);
        } else {
            work[pass_u.reg0.w + 4u * j + 3u] = 0.0;
        }
    }
}

// Per invocation: the proposal field's density at LANES (ray, proposal sample) pairs, entries
// LANES i .. LANES i + LANES - 1 of the batch's pairs (ray-major), or of the live list's
// samples with a 4D lookup when the pass has an occupancy grid (`pass_live_proposal` gave the
// empty ones density 0); encodings one by one, the MLP for the LANES samples together
// (`dense_lanes`).
@compute @workgroup_size(64)
fn pass_proposal(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    proposal_lanes(invocation(gid, groups), true);
}

// `pass_proposal` over the live list's samples whose mask skips the 4D lookup, with no 4D
// lookup compiled in (dispatched only with an occupancy grid and `FLAG_P_SPLIT`).
@compute @workgroup_size(64)
fn pass_proposal3(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    proposal_lanes(invocation(gid, groups), false);
}

// Invocation i of `pass_proposal` (`with4`, a constant) or `pass_proposal3`.
fn proposal_lanes(i: u32, with4: bool) {
    let live = pass_u.reg2.y != 0u;
    let total = ray_count() * model.sampler.x;
    var n = total;
    if live {
        n = atomicLoad(&ctrl[select(5u, 3u, with4)]);
    }
    if i * LANES < n {
        let used = min(n - i * LANES, LANES);
        var es = vec4<u32>(0u);
        for (var k = 0u; k < LANES; k++) {
            var e = lane_entry(i, k, used);
            if live {
                e = live_entry(pass_u.reg2.z, total, e, with4);
            }
            es[k] = e;
            encode_proposal4(proposal_point(e), model.prop.consts.y, k, with4);
        }
        let sum = proposal_mlp4();
        for (var k = 0u; k < used; k++) {
            work[pass_u.reg0.y + es[k]] = trunc_exp(sum[k]);
        }
    }
}

// Proposal weights of ray r from its densities (in place in `hist`), as msth-core's
// `render::weights`.
fn proposal_weights(r: u32, near: f32, far: f32) {
    let np = model.sampler.x;
    let base = pass_u.reg0.y + r * np;
    var tau_sum = 0.0;
    var t_prev = t_of_s(0.0, near, far);
    for (var k = 0u; k < np; k++) {
        let t_next = t_of_s(f32(k + 1u) / f32(np), near, far);
        let tau = tau_of(work[base + k], max(t_next - t_prev, 0.0));
        work[base + k] = exp(-tau_sum) * -expm1(-tau);
        tau_sum += tau;
        t_prev = t_next;
    }
}

// Per ray: the deterministic inverse CDF of the padded histogram (msth-core `sample_pdf`),
// S + 1 edges in s.
@compute @workgroup_size(64)
fn pass_resample(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = invocation(gid, groups);
    if r < ray_count() {
        let np = model.sampler.x;
        let m_out = samples_per_ray() + 1u;
        let rec = ray_rec(r);
        var hist = pass_u.reg0.y + r * np;
        if (pass_u.tile.z & FLAG_P_WMAX) != 0u {
            hist = pass_u.reg1.z + r * np;
        } else {
            proposal_weights(r, rec.z, rec.w);
        }
        let out = pass_u.reg0.z + r * m_out;
        let pad = model.limits.z;
        var total = 0.0;
        for (var k = 0u; k < np; k++) {
            total += sanitize(work[hist + k]) + pad;
        }
        if !(total > 0.0 && total <= 3.40282346e38) {
            for (var k = 0u; k < m_out; k++) {
                work[out + k] = f32(k) / f32(max(m_out - 1u, 1u));
            }
        } else {
            let inv = 1.0 / total;
            var bin = 0u;
            var cdf_lo = 0.0;
            var cdf_hi = (sanitize(work[hist]) + pad) * inv;
            var prev = 0.0;
            for (var k = 0u; k < m_out; k++) {
                let u = f32(k) / f32(max(m_out - 1u, 1u));
                while u > cdf_hi && bin + 1u < np {
                    bin += 1u;
                    cdf_lo = cdf_hi;
                    cdf_hi += (sanitize(work[hist + bin]) + pad) * inv;
                }
                let span = cdf_hi - cdf_lo;
                var frac = 0.0;
                if span > 0.0 {
                    frac = clamp((u - cdf_lo) / span, 0.0, 1.0);
                }
                let e0 = f32(bin) / f32(np);
                let e1 = f32(bin + 1u) / f32(np);
                var s = e0 + frac * (e1 - e0);
                if k > 0u && s < prev {
                    s = prev;
                }
                work[out + k] = s;
                prev = s;
            }
        }
    }
}
