// passes_shade: the passes from a ray's main samples to its pixel: density, which samples light
// reaches, their colours, and compositing.

// #import common
// #import bindings
// #import io
// #import camera
// #import sh
// #import passes_work
// #import passes_lanes
// #import specialise

// The density and geometry features of the LANES samples `js` (the first `used` of them) from
// `density_mlp4`'s output.
fn store_density_lanes(js: vec4<u32>, used: u32) {
    for (var k = 0u; k < used; k++) {
        let j = js[k];
        work[pass_u.reg0.w + 4u * j + 3u] = trunc_exp(out4[0][k]);
        geo_to_work(j, k);
    }
}

// Per invocation: the main field's density and geometry features at LANES (ray, sample) pairs,
// entries LANES i .. of the batch's samples (ray-major), or of the live list's samples with a
// 4D lookup when the pass has an occupancy grid (`pass_live_samples` gave the empty ones
// density 0); encodings one by one, the density MLP for the LANES samples together.
@compute @workgroup_size(64)
fn pass_density(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    density_lanes(invocation(gid, groups), true);
}

// `pass_density` over the live list's samples whose mask skips the 4D lookup, with no 4D
// lookup compiled in (dispatched only with an occupancy grid and `FLAG_P_SPLIT`).
@compute @workgroup_size(64)
fn pass_density3(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    density_lanes(invocation(gid, groups), false);
}

// Invocation i of `pass_density` (`with4`, a constant) or `pass_density3`.
fn density_lanes(i: u32, with4: bool) {
    let s = samples_per_ray();
    let live = pass_u.reg2.y != 0u;
    let total = ray_count() * s;
    var n = total;
    if live {
        n = atomicLoad(&ctrl[select(6u, 4u, with4)]);
    }
    if i * LANES < n {
        let used = min(n - i * LANES, LANES);
        var js = vec4<u32>(0u);
        for (var k = 0u; k < LANES; k++) {
            var j = lane_entry(i, k, used);
            if live {
                j = live_entry(pass_u.reg2.w, total, j, with4);
            }
            js[k] = j;
            let r = j / s;
            encode_field4(main_point(r, j % s, ray_rec(r)), model.field.consts.y, k, with4);
        }
        density_mlp4();
        store_density_lanes(js, used);
    }
}

// Per ray: the samples light still reaches (optical depth before them at most ln(1e4)) go to
// the colour list; the others, and those in empty occupancy cells, get colour 0, as in the CPU
// renderer. With the cache flag only dynamic samples are considered (static ones keep their
// colour) and the occupancy grid is not used (as the CPU renderer's sample cache).
@compute @workgroup_size(64)
fn pass_visible(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = invocation(gid, groups);
    if r < ray_count() {
        let s = samples_per_ray();
        let rec = ray_rec(r);
        let cache = (pass_u.tile.z & FLAG_P_CACHE) != 0u;
        var tau = 0.0;
        var t0 = t_of_s(work[pass_u.reg0.z + r * (s + 1u)], rec.z, rec.w);
        for (var k = 0u; k < s; k++) {
            let j = r * s + k;
            let t1 = t_of_s(work[pass_u.reg0.z + r * (s + 1u) + k + 1u], rec.z, rec.w);
            let sp = pass_u.reg0.w + 4u * j;
            let is_dyn = !cache || work[pass_u.reg1.w + 4u * j + 3u] == 1.0;
            if is_dyn {
                if tau <= TAU_HIDDEN && (cache || pass_u.reg2.y == 0u || occupied(main_point(r, k, rec).xyz)) {
                    let slot = atomicAdd(&ctrl[1], 1u);
                    work[pass_u.reg1.y + slot] = bitcast<f32>(j);
                } else {
                    work[sp] = 0.0;
                    work[sp + 1u] = 0.0;
                    work[sp + 2u] = 0.0;
                }
            }
            tau += tau_of(work[sp + 3u], max(t1 - t0, 0.0));
            t0 = t1;
        }
    }
}

// Per invocation: the colours of LANES listed samples (entries LANES i .. LANES i + LANES - 1 of
// the colour list), their colour MLPs evaluated together: component k of a vec4 is sample k, so
// that every weight read from `rest` serves LANES samples (weight reads dominate the pass on
// software adapters, which gather every per-invocation storage read lane by lane).
@compute @workgroup_size(64)
fn pass_color(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    let n = atomicLoad(&ctrl[1]);
    if i * LANES < n {
        let used = min(n - i * LANES, LANES);
        var js = vec4<u32>(0u);
        for (var k = 0u; k < LANES; k++) {
            let j = work_u(pass_u.reg1.y + lane_entry(i, k, used));
            js[k] = j;
            let rec = ray_rec(j / samples_per_ray());
            sh4(normalize(pixel_ray_dir(ray_pixel(rec))));
            hid4[0][k] = sh[0];
            hid4[1][k] = sh[1];
            hid4[2][k] = sh[2];
            hid4[3][k] = sh[3];
            hid4[4][k] = sh[4];
            hid4[5][k] = sh[5];
            hid4[6][k] = sh[6];
            hid4[7][k] = sh[7];
            hid4[8][k] = sh[8];
            hid4[9][k] = sh[9];
            hid4[10][k] = sh[10];
            hid4[11][k] = sh[11];
            hid4[12][k] = sh[12];
            hid4[13][k] = sh[13];
            hid4[14][k] = sh[14];
            hid4[15][k] = sh[15];
            geo_from_work(j, k);
        }
        let c = color_mlp4();
        for (var k = 0u; k < used; k++) {
            let sp = pass_u.reg0.w + 4u * js[k];
            work[sp] = c[0][k];
            work[sp + 1u] = c[1][k];
            work[sp + 2u] = c[2][k];
        }
    }
}

// Per ray: C = sum w_k c_k + T * background, and the visible depth, into frame[output index].
@compute @workgroup_size(64)
fn pass_composite(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = invocation(gid, groups);
    if r < ray_count() {
        let s = samples_per_ray();
        let rec = ray_rec(r);
        var rgb = vec3<f32>(0.0);
        var last_rgb = vec3<f32>(0.0);
        var tau_sum = 0.0;
        var acc = 0.0;
        var visible = -1.0;
        let e = pass_u.reg0.z + r * (s + 1u);
        var t0 = t_of_s(work[e], rec.z, rec.w);
        var t1 = t0;
        for (var k = 0u; k < s; k++) {
            t1 = t_of_s(work[e + k + 1u], rec.z, rec.w);
            let sp = pass_u.reg0.w + 4u * (r * s + k);
            let c = vec3<f32>(work[sp], work[sp + 1u], work[sp + 2u]);
            let tau = tau_of(work[sp + 3u], max(t1 - t0, 0.0));
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
        var bg = model.background.xyz;
        if model.background.w == 0.0 {
            bg = select(vec3<f32>(0.0), last_rgb, s > 0u);
        }
        rgb += exp(-tau_sum) * bg;
        if visible < 0.0 {
            visible = t1;
        }
        frame[bitcast<u32>(rec.x)] = vec4<f32>(rgb, visible);
    }
}
