// MSTH renderer kernels: one invocation renders one ray (or evaluates one point), exactly as the
// CPU renderer does at render time (msth-core `pipeline::render_chunk`): ray limits against the
// scene box (or contraction), proposal samples, proposal field density, proposal resampling,
// main samples, masked space-time encoding (3D hash grid, 4D hash grid, dense mask), density and
// colour decoders, SH direction encoding, volume compositing and background.
//
// Shared by the native player (wgpu, `player/src/gpu/`) and the browser (WebGPU, `web/`): WebGPU
// core only (no push constants, no f64, no optional features, default limits). Bindings, struct
// layouts and dispatch sizes: `web/shaders/README.md`.

// ---- Limits (the host rejects models beyond them with a clear error) ----------------------

const MAX_PROPOSAL_SAMPLES: u32 = 256u;
const MAX_SAMPLES: u32 = 128u;
const MAX_HIDDEN: u32 = 128u;
const MAX_GEO: u32 = 31u;
const MAX_LEVELS: u32 = 32u;
const MAX_FEATURES: u32 = 8u;
const WORKGROUP: u32 = 64u;

// Rendering constants of msth-core (pipeline.rs).
const VISIBLE_TRANSMITTANCE: f32 = 1e-3;
const TAU_HIDDEN: f32 = 9.210340372; // ln(1 / HIDDEN_TRANSMITTANCE), HIDDEN_TRANSMITTANCE = 1e-4

// Hash primes for (x, y, z, t).
fn prime(a: u32) -> u32 {
    switch a {
        case 0u: {
            return 1u;
        }
        case 1u: {
            return 2654435761u;
        }
        case 2u: {
            return 805459861u;
        }
        default: {
            return 3674653429u;
        }
    }
}

// ---- Uniforms -------------------------------------------------------------------------------

struct Level {
    // scale_a per axis (unused axes 0).
    scale: vec4<f32>,
    // Dense strides per axis (dense levels only).
    stride: vec4<u32>,
    // x: offset of this level's table in floats inside the grid's buffer; y: 1 = dense;
    // z: rows; w: unused.
    info: vec4<u32>,
}

struct Grid {
    // x: dims (3 or 4), y: features per level, z: levels, w: hash mask (table size - 1).
    shape: vec4<u32>,
    // x: buffer (0 = tab3, 1 = tab4, 2 = rest), y: index of level 0 in Model.levels,
    // z: 1 = present, w: unused.
    loc: vec4<u32>,
}

struct Encoding {
    // x: blend (0 mst, 1 mt, 2 add, 3 4d, 4 static), y: 1 = has mask, z: mask resolution,
    // w: mask offset (floats) in `rest`.
    mode: vec4<u32>,
    // x: output dim (levels * features), yzw: unused.
    dims: vec4<u32>,
    // x: mask value when there is no mask, y: static cutoff (skip h4 when 1 - m < cutoff), zw: 0.
    consts: vec4<f32>,
    h3: Grid,
    h4: Grid,
}

struct Model {
    // x: proposal samples, y: samples, z: spacing (0 linear, 1 lindisp), w: bounds (0 box, 1 contracted).
    sampler: vec4<u32>,
    // x: near, y: far, z: histogram padding, w: spacing unit.
    limits: vec4<f32>,
    // Box: min (xyz). Contracted: centre (xyz), radius (w).
    bounds_a: vec4<f32>,
    // Box: max (xyz).
    bounds_b: vec4<f32>,
    // rgb, w: 1 = constant colour, 0 = last sample's colour.
    background: vec4<f32>,
    // Field density MLP: x offset in `rest`, y input dim, z hidden, w output dim (1 + geo).
    density: vec4<u32>,
    // Field colour MLP: x offset in `rest`, y hidden width, z hidden layers, w geo features.
    color: vec4<u32>,
    // Proposal density MLP: x offset in `rest`, y input dim, z hidden, w unused.
    proposal: vec4<u32>,
    field: Encoding,
    prop: Encoding,
    levels: array<Level, 128>,
}

struct View {
    // Camera-to-world (OpenGL camera axes: looks down -Z), column-major.
    c2w: mat4x4<f32>,
    // fx, fy, cx, cy (pixels).
    intr: vec4<f32>,
    // x: width, y: height, z: invocations (rays or points), w: flags
    // (bit 0: ray i renders pixel list[i], otherwise pixel i;
    //  bit 1: write frame[i], otherwise frame[pixel]).
    size: vec4<u32>,
    // x: normalised time, yzw: unused.
    time: vec4<f32>,
}

@group(0) @binding(0) var<uniform> model: Model;
@group(0) @binding(1) var<uniform> view: View;
// Field 3D hash table (params range `field.h3`).
@group(0) @binding(2) var<storage, read> tab3: array<f32>;
// Field 4D hash table (params range `field.h4`).
@group(0) @binding(3) var<storage, read> tab4: array<f32>;
// Everything after the field tables: mask, decoders, proposal field.
@group(0) @binding(4) var<storage, read> rest: array<f32>;
// Pixel list (render) or packed points (eval_points).
@group(0) @binding(5) var<storage, read> list: array<u32>;
// Output: (r, g, b, visible depth) per pixel (render) or (r, g, b, sigma) per point.
@group(0) @binding(6) var<storage, read_write> frame: array<vec4<f32>>;

// ---- Per-invocation scratch -------------------------------------------------------------------

var<private> w_prop: array<f32, MAX_PROPOSAL_SAMPLES>;
var<private> s_main: array<f32, 129>; // MAX_SAMPLES + 1
var<private> hid: array<f32, MAX_HIDDEN>;
var<private> hid2: array<f32, MAX_HIDDEN>;
var<private> dout: array<f32, 32>; // 1 + MAX_GEO
var<private> cin: array<f32, 47>; // 16 + MAX_GEO
var<private> feat3: array<f32, MAX_FEATURES>;
var<private> feat4: array<f32, MAX_FEATURES>;
var<private> sh: array<f32, 16>;

// ---- Small functions --------------------------------------------------------------------------

fn clamp_unit(x: f32) -> f32 {
    // NaN maps to 0 (as the CPU's `if x >= 0 { min(x, 1) } else { 0 }`).
    if x >= 0.0 {
        return min(x, 1.0);
    }
    return 0.0;
}

fn sigmoid(x: f32) -> f32 {
    if x >= 0.0 {
        return 1.0 / (1.0 + exp(-min(x, 80.0)));
    }
    let e = exp(max(x, -80.0));
    return e / (1.0 + e);
}

fn trunc_exp(x: f32) -> f32 {
    return exp(min(x, 88.0));
}

// exp(x) - 1 without cancellation for small |x|.
fn expm1(x: f32) -> f32 {
    if abs(x) < 1e-3 {
        return x + x * x * 0.5 + x * x * x * (1.0 / 6.0);
    }
    return exp(x) - 1.0;
}

fn tau_of(sigma: f32, delta: f32) -> f32 {
    let t = sigma * delta;
    if t >= 0.0 {
        return min(t, 1e30);
    }
    return 0.0;
}

fn is_finite(x: f32) -> bool {
    return x == x && abs(x) <= 3.40282346e38;
}

fn table(buf: u32, i: u32) -> f32 {
    switch buf {
        case 0u: {
            return tab3[i];
        }
        case 1u: {
            return tab4[i];
        }
        default: {
            return rest[i];
        }
    }
}

// Spacing: normalised s in [0, 1] to distance.
fn g_fwd(t: f32) -> f32 {
    if t < 1.0 {
        return 0.5 * t;
    }
    return 1.0 - 0.5 / t;
}

fn g_inv(y: f32) -> f32 {
    if y < 0.5 {
        return 2.0 * y;
    }
    return 0.5 / max(1.0 - y, 1e-7);
}

fn t_of_s(s: f32, near: f32, far: f32) -> f32 {
    if !(far > near) {
        return near;
    }
    if model.sampler.z == 0u {
        return near + s * (far - near);
    }
    let unit = model.limits.w;
    let a = g_fwd(near / unit);
    let b = g_fwd(far / unit);
    return unit * g_inv(a + s * (b - a));
}

// World point to the unit cube.
fn to_unit(p: vec3<f32>) -> vec3<f32> {
    if model.sampler.w == 0u {
        let lo = model.bounds_a.xyz;
        let hi = model.bounds_b.xyz;
        return clamp((p - lo) / (hi - lo), vec3<f32>(0.0), vec3<f32>(1.0));
    }
    let y = (p - model.bounds_a.xyz) / model.bounds_a.w;
    let n = max(max(abs(y.x), abs(y.y)), abs(y.z));
    var c: vec3<f32>;
    if !is_finite(n) {
        c = sign(y) * 2.0;
    } else if n < 1.0 {
        c = y;
    } else {
        c = (2.0 - 1.0 / n) * (y / n);
    }
    return clamp((c + 2.0) * 0.25, vec3<f32>(0.0), vec3<f32>(1.0));
}

// Ray interval [near, far]; empty (near == far == 0) when the ray misses the box.
fn ray_limits(o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    let near0 = model.limits.x;
    let far0 = model.limits.y;
    if model.sampler.w == 1u {
        return vec2<f32>(near0, far0);
    }
    var near = near0;
    var far = far0;
    let lo = model.bounds_a.xyz;
    let hi = model.bounds_b.xyz;
    for (var a = 0u; a < 3u; a++) {
        if d[a] == 0.0 {
            // Parallel to the slab: inside (or on it) leaves the interval alone.
            if o[a] < lo[a] || o[a] > hi[a] {
                return vec2<f32>(0.0, 0.0);
            }
            continue;
        }
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
    if far > near {
        return vec2<f32>(near, far);
    }
    return vec2<f32>(0.0, 0.0);
}

fn sh4(d: vec3<f32>) {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    let xy = x * y;
    let yz = y * z;
    let xz = x * z;
    sh[0] = 0.2820948;
    sh[1] = -0.48860252 * y;
    sh[2] = 0.48860252 * z;
    sh[3] = -0.48860252 * x;
    sh[4] = 1.0925484 * xy;
    sh[5] = -1.0925484 * yz;
    sh[6] = 0.9461747 * zz - 0.31539157;
    sh[7] = -1.0925484 * xz;
    sh[8] = 0.5462742 * (xx - yy);
    sh[9] = 0.5900436 * y * (-3.0 * xx + yy);
    sh[10] = 2.8906114 * xy * z;
    sh[11] = 0.4570458 * y * (1.0 - 5.0 * zz);
    sh[12] = 0.37317633 * z * (5.0 * zz - 3.0);
    sh[13] = 0.4570458 * x * (1.0 - 5.0 * zz);
    sh[14] = 1.4453057 * z * (xx - yy);
    sh[15] = 0.5900436 * x * (-xx + 3.0 * yy);
}

// ---- Encoding ---------------------------------------------------------------------------------

// Trilinear read of the dense mask grid (logit), `res^3` values at `off` in `rest`.
fn mask_logit(off: u32, res: u32, x: vec3<f32>) -> f32 {
    var base: vec3<u32>;
    var fr: vec3<f32>;
    let rm1 = f32(res - 1u);
    for (var a = 0u; a < 3u; a++) {
        let p = clamp_unit(x[a]) * rm1;
        let i = min(u32(p), res - 2u);
        base[a] = i;
        fr[a] = p - f32(i);
    }
    var v = 0.0;
    for (var c = 0u; c < 8u; c++) {
        let bx = c & 1u;
        let by = (c >> 1u) & 1u;
        let bz = (c >> 2u) & 1u;
        let idx = (base.x + bx) + res * ((base.y + by) + res * (base.z + bz));
        var w = select(1.0 - fr.x, fr.x, bx == 1u);
        w *= select(1.0 - fr.y, fr.y, by == 1u);
        w *= select(1.0 - fr.z, fr.z, bz == 1u);
        v += w * rest[off + idx];
    }
    return v;
}

// Mask value m in [0, 1] at a unit-cube point.
fn mask_at(e: Encoding, x: vec3<f32>) -> f32 {
    if e.mode.y == 1u {
        return sigmoid(mask_logit(e.mode.w, e.mode.z, x));
    }
    return e.consts.x;
}

// Features of one level of one grid at point p (dims 3 or 4) into `out` (feat3 or feat4):
// multilinear interpolation of the 2^D corners, dense or hashed indexing.
fn grid_level(g: Grid, l: u32, p: vec4<f32>, into4: bool) {
    let lv = model.levels[g.loc.y + l];
    let dims = g.shape.x;
    let nf = g.shape.y;
    let dense = lv.info.y == 1u;
    var lo: vec4<u32>;
    var hi: vec4<u32>;
    var fr: vec4<f32>;
    for (var a = 0u; a < dims; a++) {
        let q = clamp_unit(p[a]) * lv.scale[a] + 0.5;
        let i = u32(q); // q >= 0.5: truncation is floor
        fr[a] = q - f32(i);
        if dense {
            lo[a] = i * lv.stride[a];
            hi[a] = lo[a] + lv.stride[a];
        } else {
            lo[a] = i * prime(a);
            hi[a] = (i + 1u) * prime(a);
        }
    }
    for (var f = 0u; f < nf; f++) {
        if into4 {
            feat4[f] = 0.0;
        } else {
            feat3[f] = 0.0;
        }
    }
    let corners = 1u << dims;
    for (var c = 0u; c < corners; c++) {
        var row = 0u;
        var w = 1.0;
        for (var a = 0u; a < dims; a++) {
            let up = ((c >> a) & 1u) == 1u;
            let v = select(lo[a], hi[a], up);
            if dense {
                row += v;
            } else {
                row ^= v;
            }
            w *= select(1.0 - fr[a], fr[a], up);
        }
        if !dense {
            row &= g.shape.w;
        }
        let base = lv.info.x + row * nf;
        for (var f = 0u; f < nf; f++) {
            let t = table(g.loc.x, base + f);
            if into4 {
                feat4[f] += w * t;
            } else {
                feat3[f] += w * t;
            }
        }
    }
}

// Masked encoding at point p fused into the first layer of an MLP: hid[j] = relu(sum_k enc_k W[k, j])
// with W ([in, hidden], row-major) at `w_off` in `rest`. Returns the mask value m.
fn encode_into_hidden(e: Encoding, p: vec4<f32>, cutoff: f32, w_off: u32, hidden: u32) -> f32 {
    let m = mask_at(e, p.xyz);
    let blend = e.mode.x;
    let use3 = e.h3.loc.z == 1u;
    let use4 = e.h4.loc.z == 1u;
    // Skip the 4D lookup where the mask leaves (almost) nothing dynamic (Mst/Mt with a mask).
    let skip4 = cutoff > 0.0 && e.mode.y == 1u && blend <= 1u && (1.0 - m) < cutoff;
    var levels = 0u;
    var nf = 1u;
    if use3 {
        levels = e.h3.shape.z;
        nf = e.h3.shape.y;
    } else {
        levels = e.h4.shape.z;
        nf = e.h4.shape.y;
    }
    for (var j = 0u; j < hidden; j++) {
        hid[j] = 0.0;
    }
    for (var l = 0u; l < levels; l++) {
        if use3 {
            grid_level(e.h3, l, p, false);
        } else {
            for (var f = 0u; f < nf; f++) {
                feat3[f] = 0.0;
            }
        }
        if use4 && !skip4 {
            grid_level(e.h4, l, p, true);
        } else {
            for (var f = 0u; f < nf; f++) {
                feat4[f] = 0.0;
            }
        }
        for (var f = 0u; f < nf; f++) {
            let a = feat3[f];
            let b = feat4[f];
            var v: f32;
            switch blend {
                case 0u: {
                    v = m * a + (1.0 - m) * b;
                }
                case 1u: {
                    v = a + (1.0 - m) * b;
                }
                case 2u: {
                    v = a + b;
                }
                case 3u: {
                    v = b;
                }
                default: {
                    v = a;
                }
            }
            let row = w_off + (l * nf + f) * hidden;
            for (var j = 0u; j < hidden; j++) {
                hid[j] += v * rest[row + j];
            }
        }
    }
    for (var j = 0u; j < hidden; j++) {
        hid[j] = max(hid[j], 0.0);
    }
    return m;
}

// Proposal density at p.
fn proposal_sigma(p: vec4<f32>, cutoff: f32) -> f32 {
    let d = model.proposal;
    let off = d.x;
    let hidden = d.z;
    encode_into_hidden(model.prop, p, cutoff, off, hidden);
    let w2 = off + d.y * hidden;
    var s = 0.0;
    for (var j = 0u; j < hidden; j++) {
        s += hid[j] * rest[w2 + j];
    }
    return trunc_exp(s);
}

// Main-field density at p: returns sigma; geo features in dout[1..=geo]; mask value in *m.
fn field_density(p: vec4<f32>, cutoff: f32, m: ptr<function, f32>) -> f32 {
    let d = model.density;
    let off = d.x;
    let hidden = d.z;
    let nout = d.w;
    *m = encode_into_hidden(model.field, p, cutoff, off, hidden);
    let w2 = off + d.y * hidden;
    for (var o = 0u; o < nout; o++) {
        var s = 0.0;
        for (var j = 0u; j < hidden; j++) {
            s += hid[j] * rest[w2 + j * nout + o];
        }
        dout[o] = s;
    }
    return trunc_exp(dout[0]);
}

// Main-field colour from `sh` and the geo features of the last field_density call.
fn field_color() -> vec3<f32> {
    let c = model.color;
    let geo = c.w;
    let hidden = c.y;
    let layers = c.z;
    let nin = 16u + geo;
    for (var k = 0u; k < 16u; k++) {
        cin[k] = sh[k];
    }
    for (var k = 0u; k < geo; k++) {
        cin[16u + k] = dout[1u + k];
    }
    var off = c.x;
    // First hidden layer.
    for (var j = 0u; j < hidden; j++) {
        var s = 0.0;
        for (var i = 0u; i < nin; i++) {
            s += cin[i] * rest[off + i * hidden + j];
        }
        hid[j] = max(s, 0.0);
    }
    off += nin * hidden;
    // Further hidden layers, alternating hid -> hid2 -> hid.
    for (var k = 1u; k < layers; k++) {
        if (k & 1u) == 1u {
            for (var j = 0u; j < hidden; j++) {
                var s = 0.0;
                for (var i = 0u; i < hidden; i++) {
                    s += hid[i] * rest[off + i * hidden + j];
                }
                hid2[j] = max(s, 0.0);
            }
        } else {
            for (var j = 0u; j < hidden; j++) {
                var s = 0.0;
                for (var i = 0u; i < hidden; i++) {
                    s += hid2[i] * rest[off + i * hidden + j];
                }
                hid[j] = max(s, 0.0);
            }
        }
        off += hidden * hidden;
    }
    let last_in_hid2 = layers >= 2u && (layers & 1u) == 0u;
    var rgb: vec3<f32>;
    for (var o = 0u; o < 3u; o++) {
        var s = 0.0;
        for (var i = 0u; i < hidden; i++) {
            let x = select(hid[i], hid2[i], last_in_hid2);
            s += x * rest[off + i * 3u + o];
        }
        rgb[o] = sigmoid(s);
    }
    return rgb;
}

// ---- One ray ----------------------------------------------------------------------------------

struct RayResult {
    rgb: vec3<f32>,
    visible_depth: f32,
}

fn sample_point(o: vec3<f32>, d: vec3<f32>, t0: f32, t1: f32, time: f32) -> vec4<f32> {
    let u = to_unit(o + d * (0.5 * (t0 + t1)));
    return vec4<f32>(u, time);
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
        let w = w_prop[k];
        total += select(0.0, w, w > 0.0 && is_finite(w)) + pad;
    }
    if !(total > 0.0 && is_finite(total)) {
        for (var k = 0u; k < m_out; k++) {
            s_main[k] = f32(k) / f32(max(m_out - 1u, 1u));
        }
    } else {
        let inv = 1.0 / total;
        var bin = 0u;
        var cdf_lo = 0.0;
        let w0 = w_prop[0];
        var cdf_hi = (select(0.0, w0, w0 > 0.0 && is_finite(w0)) + pad) * inv;
        for (var k = 0u; k < m_out; k++) {
            let u = f32(k) / f32(max(m_out - 1u, 1u));
            while u > cdf_hi && bin + 1u < np {
                bin += 1u;
                cdf_lo = cdf_hi;
                let wb = w_prop[bin];
                cdf_hi += (select(0.0, wb, wb > 0.0 && is_finite(wb)) + pad) * inv;
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

// The ray through the centre of pixel `pixel` (row-major).
fn pixel_ray_dir(pixel: u32) -> vec3<f32> {
    let w = view.size.x;
    let px = f32(pixel % w) + 0.5;
    let py = f32(pixel / w) + 0.5;
    let d_cam = vec3<f32>((px - view.intr.z) / view.intr.x, -(py - view.intr.w) / view.intr.y, -1.0);
    let r = mat3x3<f32>(view.c2w[0].xyz, view.c2w[1].xyz, view.c2w[2].xyz);
    return normalize(r * d_cam);
}

fn invocation(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * WORKGROUP;
}

// ---- Entry points -----------------------------------------------------------------------------

// Renders view.size.z rays: pixel i, or pixel list[i] with flag bit 0. Writes
// (r, g, b, visible depth) to frame[pixel], or frame[i] with flag bit 1. Rays that miss the scene
// box under a constant background get the background without evaluation.
@compute @workgroup_size(64)
fn render(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    if i >= view.size.z {
        return;
    }
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
        frame[out] = vec4<f32>(model.background.xyz, lim.y);
        return;
    }
    let r = render_ray(o, d, view.time.x);
    frame[out] = vec4<f32>(r.rgb, r.visible_depth);
}

// Evaluates the fields at view.size.z points, exactly (no static cutoff). Point j is 8 words of
// `list` read as f32: (x, y, z, t) in the unit cube / unit time, direction (dx, dy, dz) for the
// SH encoding, and 0 = main field or 1 = proposal field. Writes frame[j] = (r, g, b, sigma)
// (proposal: (m, 0, 0, sigma) with the proposal's mask value m; main: rgb, sigma).
@compute @workgroup_size(64)
fn eval_points(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let j = invocation(gid, groups);
    if j >= view.size.z {
        return;
    }
    var v: array<f32, 8>;
    for (var k = 0u; k < 8u; k++) {
        v[k] = bitcast<f32>(list[j * 8u + k]);
    }
    let p = vec4<f32>(v[0], v[1], v[2], v[3]);
    if v[7] == 1.0 {
        let sigma = proposal_sigma(p, 0.0);
        frame[j] = vec4<f32>(mask_at(model.prop, p.xyz), 0.0, 0.0, sigma);
        return;
    }
    sh4(vec3<f32>(v[4], v[5], v[6]));
    var m = 1.0;
    let sigma = field_density(p, 0.0, &m);
    let c = field_color();
    frame[j] = vec4<f32>(c, sigma);
}
