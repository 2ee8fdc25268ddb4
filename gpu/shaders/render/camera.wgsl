// camera: a pixel's ray, its interval in the scene (box or contraction), the spacing of
// samples along it (`t_of_s`), and a sample's point in the grids' unit cube (`to_unit`).

// #import bindings

// Spacing: normalised s in [0, 1] to distance.
fn g_fwd(t: f32) -> f32 {
    return select(1.0 - 0.5 / max(t, 1.0), 0.5 * t, t < 1.0);
}

fn g_inv(y: f32) -> f32 {
    return select(0.5 / max(1.0 - y, 1e-7), 2.0 * y, y < 0.5);
}

fn t_of_s(s: f32, near: f32, far: f32) -> f32 {
    var t = near + s * (far - near);
    if model.sampler.z == 1u {
        let unit = model.limits.w;
        let a = g_fwd(near / unit);
        let b = g_fwd(far / unit);
        t = unit * g_inv(a + s * (b - a));
    }
    return select(near, t, far > near);
}

// World point to the unit cube.
fn to_unit(p: vec3<f32>) -> vec3<f32> {
    var u: vec3<f32>;
    if model.sampler.w == 0u {
        let lo = model.bounds_a.xyz;
        let hi = model.bounds_b.xyz;
        u = (p - lo) / (hi - lo);
    } else {
        let y = (p - model.bounds_a.xyz) / model.bounds_a.w;
        let n = max(max(abs(y.x), abs(y.y)), abs(y.z));
        var c: vec3<f32>;
        if !(n <= 3.40282346e38) {
            c = sign(y) * 2.0;
        } else if n < 1.0 {
            c = y;
        } else {
            c = (2.0 - 1.0 / n) * (y / n);
        }
        u = (c + 2.0) * 0.25;
    }
    return clamp(u, vec3<f32>(0.0), vec3<f32>(1.0));
}

// Ray interval [near, far]; empty (near == far == 0) when the ray misses the box.
fn ray_limits(o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    var near = model.limits.x;
    var far = model.limits.y;
    if model.sampler.w == 0u {
        var miss = false;
        let lo = model.bounds_a.xyz;
        let hi = model.bounds_b.xyz;
        for (var a = 0u; a < 3u; a++) {
            if d[a] == 0.0 {
                // Parallel to the slab: inside (or on it) leaves the interval alone.
                miss = miss || o[a] < lo[a] || o[a] > hi[a];
            } else {
                let inv = 1.0 / d[a];
                let t0 = (lo[a] - o[a]) * inv;
                let t1 = (hi[a] - o[a]) * inv;
                let tmin = min(t0, t1);
                let tmax = max(t0, t1);
                if tmin > near {
                    near = tmin;
                }
                if tmax < far {
                    far = tmax;
                }
            }
        }
        if miss || !(far > near) {
            near = 0.0;
            far = 0.0;
        }
    }
    return vec2<f32>(near, far);
}

// The ray through the centre of pixel `pixel` (row-major).
fn pixel_ray_dir(pixel: u32) -> vec3<f32> {
    let w = view.size.x;
    let px = f32(pixel % w) + 0.5;
    let py = f32(pixel / w) + 0.5;
    let d_cam = vec3<f32>((px - view.intr.z) / view.intr.x, -(py - view.intr.w) / view.intr.y, -1.0);
    let r = mat3x3<f32>(view.c2w[0].xyz, view.c2w[1].xyz, view.c2w[2].xyz);
    return normalize(r * d_cam);
}

// The unit-cube point and time of the sample between distances t0 and t1 on ray (o, d).
fn sample_point(o: vec3<f32>, d: vec3<f32>, t0: f32, t1: f32, time: f32) -> vec4<f32> {
    let u = to_unit(o + d * (0.5 * (t0 + t1)));
    return vec4<f32>(u, time);
}
