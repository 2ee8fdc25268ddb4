// passes_cache: the sample cache of incremental playback (msth-player's `samples.rs`): the
// per-bin maximum of proposal weights over several times, the cache's static samples evaluated
// once, and its dynamic samples' density per frame.

// #import common
// #import bindings
// #import camera
// #import sh
// #import mask
// #import field
// #import passes_work
// #import passes_lanes
// #import specialise
// #import passes_rays
// #import passes_shade

// Per ray (partition): weights of this time's densities, and their per-bin maximum over the
// times so far in `wmax`.
@compute @workgroup_size(64)
fn pass_wmax(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let r = invocation(gid, groups);
    if r < ray_count() {
        let rec = ray_rec(r);
        proposal_weights(r, rec.z, rec.w);
        let np = model.sampler.x;
        let first = pass_u.misc.y == 1.0;
        for (var k = 0u; k < np; k++) {
            let w = work[pass_u.reg0.y + r * np + k];
            let at = pass_u.reg1.z + r * np + k;
            work[at] = select(max(work[at], w), w, first);
        }
    }
}

// Per (ray, sample) of the cache (time 0, as msth-player's sample cache): a sample whose dynamic
// weight 1 - m is below the cutoff is static: its density and colour are evaluated once, with
// the 4D lookup skipped; the others keep their point and are listed for every frame.
// Dispatched as `pass_density` (LANES samples per invocation), one sample after the other.
@compute @workgroup_size(64)
fn pass_build(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    for (var k = 0u; k < LANES; k++) {
        build_sample(i * LANES + k);
    }
}

fn build_sample(j: u32) {
    let s = samples_per_ray();
    if j < ray_count() * s {
        let r = j / s;
        let rec = ray_rec(r);
        let iv = main_interval(r, j % s, rec.z, rec.w);
        let o = view.c2w[3].xyz;
        let d = pixel_ray_dir(ray_pixel(rec));
        let p = sample_point(o, d, iv.x, iv.y, 0.0);
        let cutoff = pass_u.misc.x;
        let e = model.field;
        let blend = e.mode.x;
        var is_dyn = blend == 2u || blend == 3u;
        if blend <= 1u {
            is_dyn = e.mode.y == 0u || 1.0 - mask_at(e, p.xyz) >= cutoff;
        }
        let at = pass_u.reg1.w + 4u * j;
        work[at] = p.x;
        work[at + 1u] = p.y;
        work[at + 2u] = p.z;
        work[at + 3u] = select(0.0, 1.0, is_dyn);
        let sp = pass_u.reg0.w + 4u * j;
        if is_dyn {
            let slot = atomicAdd(&ctrl[2], 1u);
            work[pass_u.reg2.x + slot] = bitcast<f32>(j);
            work[sp] = 0.0;
            work[sp + 1u] = 0.0;
            work[sp + 2u] = 0.0;
            work[sp + 3u] = 0.0;
        } else {
            var m = 1.0;
            let sigma = field_density(p, cutoff, &m);
            sh4(normalize(d));
            let c = field_color();
            work[sp] = c.x;
            work[sp + 1u] = c.y;
            work[sp + 2u] = c.z;
            work[sp + 3u] = sigma;
        }
    }
}

// Per invocation: LANES listed dynamic samples of the cache (entries LANES i .. of the list):
// density at the frame's time (the 4D lookup always), the density MLP for the LANES samples
// together, as `pass_density`.
@compute @workgroup_size(64)
fn pass_dynamic(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    let n = atomicLoad(&ctrl[2]);
    if i * LANES < n {
        let used = min(n - i * LANES, LANES);
        var js = vec4<u32>(0u);
        for (var k = 0u; k < LANES; k++) {
            let j = work_u(pass_u.reg2.x + lane_entry(i, k, used));
            js[k] = j;
            let at = pass_u.reg1.w + 4u * j;
            encode_field4(vec4<f32>(work[at], work[at + 1u], work[at + 2u], field_time()), 0.0, k, true);
        }
        density_mlp4();
        store_density_lanes(js, used);
    }
}
