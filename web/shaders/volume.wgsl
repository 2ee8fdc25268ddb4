// Composed from WGSL modules by msth-gpu (`shaders::compose`), roots: volume.

// #module common
// common: the constants and small math every render kernel shares (limits, msth-core's
// rendering thresholds, clamps, activations, optical depth) and the invocation index of a
// dispatch.
//
// The render kernels are WGSL modules composed into one shader text (`msth_gpu::shaders`):
// each module names the modules it uses on `// #import NAME` lines, and the composer includes
// every module once, after those it imports. They run on the native player (wgpu, `msth-gpu`:
// `gpu/`) and in the browser (WebGPU, `web/`): WebGPU core only (no push constants, no f64, no
// optional features, default limits). Bindings, struct layouts and dispatch sizes:
// `web/shaders/README.md`.

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
// The visible depth written for a ray that misses the scene under a constant background.
const MISSED: f32 = -1.0;
const TAU_HIDDEN: f32 = 9.210340372; // ln(1 / HIDDEN_TRANSMITTANCE), HIDDEN_TRANSMITTANCE = 1e-4

// ---- Small functions --------------------------------------------------------------------------

// Loops are kept flat (one loop over (row, column) pairs rather than two nested ones) and
// functions return once at their end. Mesa's lavapipe ends every loop of an invocation after
// 65535 loop iterations in total; the native host refuses models whose invocations could exceed
// that there with an error (gpu/src/layout.rs, loop_iterations_per_invocation).

fn clamp_unit(x: f32) -> f32 {
    // NaN maps to 0 (as the CPU's `if x >= 0 { min(x, 1) } else { 0 }`).
    return select(0.0, min(x, 1.0), x >= 0.0);
}

fn clamp_unit3(x: vec3<f32>) -> vec3<f32> {
    return select(vec3<f32>(0.0), min(x, vec3<f32>(1.0)), x >= vec3<f32>(0.0));
}

fn clamp_unit4(x: vec4<f32>) -> vec4<f32> {
    return select(vec4<f32>(0.0), min(x, vec4<f32>(1.0)), x >= vec4<f32>(0.0));
}

fn sigmoid(x: f32) -> f32 {
    // 1 / (1 + e^-x) for x >= 0, e^x / (1 + e^x) otherwise, as on the CPU.
    let e = exp(-min(abs(x), 80.0));
    return select(e / (1.0 + e), 1.0 / (1.0 + e), x >= 0.0);
}

fn trunc_exp(x: f32) -> f32 {
    return exp(min(x, 88.0));
}

// exp(x) - 1 without cancellation for small |x|.
fn expm1(x: f32) -> f32 {
    let series = x + x * x * 0.5 + x * x * x * (1.0 / 6.0);
    return select(exp(x) - 1.0, series, abs(x) < 1e-3);
}

fn tau_of(sigma: f32, delta: f32) -> f32 {
    let t = sigma * delta;
    return select(0.0, min(t, 1e30), t >= 0.0);
}

// A histogram weight as the CPU's `sanitize`: w when positive and finite, else 0 (NaN fails
// both comparisons).
fn sanitize(w: f32) -> f32 {
    return select(0.0, w, w > 0.0 && w <= 3.40282346e38);
}

fn invocation(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * WORKGROUP;
}

// #module io
// io: the pixel list and output buffer of the render entry points (bindings 5 and 6).

// Pixel list (the passes) or packed points (eval_points).
@group(0) @binding(5) var<storage, read> list: array<u32>;
// Output: (r, g, b, visible depth) per pixel (the passes, volume_march) or (r, g, b, sigma) per
// point (eval_points).
@group(0) @binding(6) var<storage, read_write> frame: array<vec4<f32>>;

// #module bindings
// bindings: the model and view uniforms and the parameter buffers a field evaluation reads
// (bindings 0-4 of the render kernels' one bind group): the `Model` uniform (sampler, bounds,
// MLP shapes, both encodings and their levels), the `View` uniform (camera, frame size, time),
// the hash tables (`table2`) and `rest` (mask, decoders, proposal field). Host side:
// `gpu/src/layout.rs`.

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
    // x: buffer (0 = tab3, 1 = tab4), y: index of level 0 in Model.levels,
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
// ---- Hash tables: begin (msth-gpu `TableFormat`: for binary16 tables the host puts
// `tables_f16.wgsl` in the place of this region) ----
// The 3D hash tables: params range `field.h3`, then `proposal.h3` from an even index (msth-gpu
// layout.rs, `ParamSplit::tables`); read two values at a time where a grid's rows hold an even
// number of features (`table2`). The buffer holds whole pairs.
@group(0) @binding(2) var<storage, read> tab3: array<vec2<f32>>;
// The 4D hash tables (`field.h4`, then `proposal.h4`), likewise.
@group(0) @binding(3) var<storage, read> tab4: array<vec2<f32>>;

// Values i and i + 1 (i even) of the hash tables of buffer `buf` (0 tab3, 1 tab4): one `vec2`
// load. Mesa's lavapipe (22.x) turns each storage load at a per-invocation index into a loop
// over the SIMD lanes, with one step per component read, so reading a row's two features
// together nearly halves the encodings' cost there.
fn table2(buf: u32, i: u32) -> vec2<f32> {
    var v: vec2<f32>;
    if buf == 0u {
        v = tab3[i >> 1u];
    } else {
        v = tab4[i >> 1u];
    }
    return v;
}
// ---- Hash tables: end ----

// Everything after the field's tables: mask, decoders, the proposal field (its tables unread
// here).
@group(0) @binding(4) var<storage, read> rest: array<f32>;

// #module camera
// camera: a pixel's ray, its interval in the scene (box or contraction), the spacing of
// samples along it (`t_of_s`), and a sample's point in the grids' unit cube (`to_unit`).

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

// #module volume
// volume: rendering through the play-time volume (msth-core `volume::march`, the CPU's march):
// one invocation per pixel walks its ray through a brick pool baked from the file, so that a
// sample reads eight vertices instead of evaluating hash grids and MLPs. Entry point
// `volume_march`; its own shader text (`volume.wgsl`, natively and in the page), with the model
// and view uniforms (bindings 0-1), the pixel list (5, read with flag 1), the output `frame`
// (binding 6) and the volume at bindings 7-9. Host side: `gpu/src/volume.rs` (native), `web/js/volume.js` (the page).
//
// The volume (`Volume` in msth-core): `R^3` cells in bricks of `B^3`; a brick index of `I^3`
// entries (`I = R / B`): a static slot, `DYNAMIC | d` for dynamic brick `d`, or `EMPTY`. A slot
// holds `(B + 1)^3` vertices of (density pre-activation, red, green, blue), the colour baked for
// a reference view direction, each as binary16 (two per u32, the first in the low half), and
// one bit per cell saying whether the cell can hold density.
// A dynamic brick's values are in two time slices around the frame's time (regions A and B,
// blended with weight `f` on B), and a bit per cell says whether the mask leaves the cell
// dynamic (such a cell blends the slices; the others read A alone). The host binds the slices a
// frame's time needs: this kernel never evaluates the field.

struct VolumeU {
    // x: cells per side R, y: brick side B, z: bricks per side I, w: bit words per slot.
    geom: vec4<u32>,
    // Offsets in `vwords` (words): x static slots' cell bits, y dynamic bricks' dynamic-cell
    // bits, z slice A's cell bits, w slice B's.
    words: vec4<u32>,
    // Offsets in `vvalues` (vertices): x slice A's values, y slice B's; z: 1 = the volume has
    // dynamic bricks; w: unused.
    values: vec4<u32>,
    // x: step in cells, y: transmittance at which a ray stops, z: weight of slice B, w: unused.
    march: vec4<f32>,
}

@group(0) @binding(7) var<uniform> vol: VolumeU;
// The brick index (`I^3` words from 0), then the bit words at the offsets of `vol.words`.
@group(0) @binding(8) var<storage, read> vwords: array<u32>;
// Static slots from 0, then the slices' dynamic bricks at the offsets of `vol.values`: one
// vertex per element, its four binary16 values.
@group(0) @binding(9) var<storage, read> vvalues: array<vec2<u32>>;

const EMPTY_BRICK: u32 = 0xffffffffu;
// An occupied brick left out of the volume: a ray that reaches one goes to the exact path.
const OUTSIDE_BRICK: u32 = 0xfffffffeu;
const DYNAMIC_BRICK: u32 = 0x80000000u;
// The visible depth of a ray that reached an OUTSIDE_BRICK (msth-core `MarchOutput::outside`):
// its colour is not written, and the host draws it with the per-sample passes.
const OUTSIDE: f32 = -2.0;
// Samples below this weight add no colour (msth-core `MIN_FEATURE_WEIGHT`).
const MIN_COLOUR_WEIGHT: f32 = 1e-5;
const INF: f32 = 3.40282346e38;

// The unit-cube velocity d(to_unit(x + s d)) / ds at world point x along d (msth-core
// `unit_velocity`): constant in a box, shrinking with the distance in a contracted scene.
fn unit_velocity(x: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    var v: vec3<f32>;
    if model.sampler.w == 0u {
        v = d / (model.bounds_b.xyz - model.bounds_a.xyz);
    } else {
        let r = model.bounds_a.w;
        let y = (x - model.bounds_a.xyz) / r;
        let dy = d / r;
        let a = abs(y);
        let n = max(max(a.x, a.y), a.z);
        var dc = dy;
        if n >= 1.0 && n <= INF {
            var k = 2u;
            if a.x >= a.y && a.x >= a.z {
                k = 0u;
            } else if a.y >= a.z {
                k = 1u;
            }
            let dn = select(-1.0, 1.0, y[k] >= 0.0) * dy[k];
            dc = dy * ((2.0 * n - 1.0) / (n * n)) - y * (2.0 * (n - 1.0) / (n * n * n) * dn);
        }
        v = dc * 0.25;
    }
    return v;
}

// World distance along velocity v from unit point p to the exit of the box [lo, hi] (no loop:
// lavapipe counts every loop iteration of an invocation).
fn exit_distance(p: vec3<f32>, v: vec3<f32>, lo: vec3<f32>, hi: vec3<f32>) -> f32 {
    let up = select(vec3<f32>(INF), (hi - p) / v, v > vec3<f32>(0.0));
    let t = select(up, (lo - p) / v, v < vec3<f32>(0.0));
    return max(min(min(t.x, t.y), t.z), 0.0);
}

// Trilinear interpolation of the slot starting at vertex `base` at brick-local cell
// coordinates `local` (cell `i` of the brick, fraction `f`).
fn vertex(i: u32) -> vec4<f32> {
    let w = vvalues[i];
    return vec4<f32>(unpack2x16float(w.x), unpack2x16float(w.y));
}

fn interpolate(base: u32, i: vec3<u32>, f: vec3<f32>) -> vec4<f32> {
    let v1 = vol.geom.y + 1u;
    let o = base + i.x + v1 * (i.y + v1 * i.z);
    let sy = v1;
    let sz = v1 * v1;
    let g = vec3<f32>(1.0) - f;
    let c00 = vertex(o) * g.x + vertex(o + 1u) * f.x;
    let c10 = vertex(o + sy) * g.x + vertex(o + sy + 1u) * f.x;
    let c01 = vertex(o + sz) * g.x + vertex(o + sz + 1u) * f.x;
    let c11 = vertex(o + sy + sz) * g.x + vertex(o + sy + sz + 1u) * f.x;
    return (c00 * g.y + c10 * f.y) * g.z + (c01 * g.y + c11 * f.y) * f.z;
}

fn bit_set(word: u32, bit: u32) -> bool {
    return (vwords[word] & (1u << (bit & 31u))) != 0u;
}

struct Step {
    // 1 = a sample, 0 = a skip of `skip` from the step's midpoint, 2 = an OUTSIDE_BRICK.
    kind: u32,
    skip: f32,
    value: vec4<f32>,
}

// What the step whose midpoint is at unit point u (moving at v) finds (msth-core
// `Volume::lookup`, with the slices bound).
fn lookup(u: vec3<f32>, v: vec3<f32>) -> Step {
    var s = Step(0u, 0.0, vec4<f32>(0.0));
    let r = vol.geom.x;
    let b = vol.geom.y;
    let nb = vol.geom.z;
    let fw = vol.geom.w;
    let rf = f32(r);
    let cell = min(vec3<u32>(u * rf), vec3<u32>(r - 1u));
    let brick = cell / b;
    let entry = vwords[brick.x + nb * (brick.y + nb * brick.z)];
    let cell_len = 1.0 / rf;
    if entry == OUTSIDE_BRICK {
        s.kind = 2u;
    } else if entry == EMPTY_BRICK {
        let lo = vec3<f32>(brick * b);
        s.skip = exit_distance(u, v, lo * cell_len, (lo + f32(b)) * cell_len);
    } else {
        let lc = cell - brick * b;
        let bit = lc.x + b * (lc.y + b * lc.z);
        let local = u * rf - vec3<f32>(brick * b);
        let i = min(vec3<u32>(max(local, vec3<f32>(0.0))), vec3<u32>(b - 1u));
        let f = clamp(local - vec3<f32>(i), vec3<f32>(0.0), vec3<f32>(1.0));
        let nv = (b + 1u) * (b + 1u) * (b + 1u);
        var occupied = false;
        if (entry & DYNAMIC_BRICK) == 0u {
            occupied = bit_set(vol.words.x + entry * fw + (bit >> 5u), bit);
            if occupied {
                s.value = interpolate(entry * nv, i, f);
            }
        } else {
            let d = entry & ~DYNAMIC_BRICK;
            let word = d * fw + (bit >> 5u);
            let w = vol.march.z;
            let in_a = bit_set(vol.words.z + word, bit);
            let in_b = w > 0.0 && bit_set(vol.words.w + word, bit);
            occupied = in_a || in_b;
            if occupied {
                let a = interpolate(vol.values.x + d * nv, i, f);
                // A cell the mask leaves static holds the same values in every slice: A alone.
                if w > 0.0 && bit_set(vol.words.y + word, bit) {
                    s.value = a * (1.0 - w) + interpolate(vol.values.y + d * nv, i, f) * w;
                } else {
                    s.value = a;
                }
            }
        }
        if occupied {
            s.kind = 1u;
        } else {
            let lo = vec3<f32>(cell);
            s.skip = exit_distance(u, v, lo * cell_len, (lo + 1.0) * cell_len);
        }
    }
    return s;
}

struct March {
    rgb: vec3<f32>,
    visible_depth: f32,
}

// The march of one ray (msth-core `march_chunk` for a volume whose dynamic bricks' slices are
// baked): steps of `vol.march.x` cells, empty bricks and cells skipped whole, stopping once the
// transmittance falls below `vol.march.y`.
fn march_ray(o: vec3<f32>, d: vec3<f32>) -> March {
    let lim = ray_limits(o, d);
    let near = lim.x;
    let far = lim.y;
    var rgb = vec3<f32>(0.0);
    var trans = 1.0;
    var last = vec3<f32>(0.0);
    var visible = -1.0;
    let res = f32(vol.geom.x);
    let h = max(vol.march.x, 1e-3) / res;
    let stop = vol.march.y;
    let max_steps = 16u * vol.geom.x + 64u;
    let boxed = model.sampler.w == 0u;
    // Where the unit point moves at one velocity, `ua + va t` for t in [t_a0, t_a1], with steps
    // `step_a` long there: along the whole ray in a box, inside the inner cube of a contracted
    // scene, where the contraction is the identity (msth-core's march, `inner_segment`).
    var t_a0 = 1.0;
    var t_a1 = 0.0;
    var ua = vec3<f32>(0.0);
    var va = vec3<f32>(0.0);
    var step_a = 0.0;
    var ok = far > near;
    if boxed {
        let lo = model.bounds_a.xyz;
        let hi = model.bounds_b.xyz;
        va = unit_velocity(o, d);
        let speed = length(va);
        if speed > 0.0 && speed <= INF {
            t_a0 = -INF;
            t_a1 = INF;
            ua = (o - lo) / (hi - lo);
            step_a = h / speed;
        } else {
            ok = false;
        }
    } else {
        let y0 = (o - model.bounds_a.xyz) / model.bounds_a.w;
        let dy = d / model.bounds_a.w;
        var a0 = -INF;
        var a1 = INF;
        for (var a = 0u; a < 3u; a++) {
            if dy[a] != 0.0 {
                let p = (-1.0 - y0[a]) / dy[a];
                let q = (1.0 - y0[a]) / dy[a];
                a0 = max(a0, min(p, q));
                a1 = min(a1, max(p, q));
            } else if abs(y0[a]) >= 1.0 {
                a1 = -INF;
            }
        }
        va = dy * 0.25;
        let speed = length(va);
        if a0 < a1 && speed > 0.0 && speed <= INF {
            t_a0 = a0;
            t_a1 = a1;
            ua = (y0 + 2.0) * 0.25;
            step_a = h / speed;
        }
    }
    var t = near;
    var k = 0u;
    while ok && t < far && k < max_steps {
        k += 1u;
        var dt: f32;
        var um: vec3<f32>;
        var vm: vec3<f32>;
        let hair = 1e-7 * max(abs(t), 1.0);
        let dt_a = max(min(step_a, far - t), hair);
        if t >= t_a0 && t + 0.5 * dt_a <= t_a1 {
            dt = dt_a;
            um = clamp(ua + va * (t + 0.5 * dt), vec3<f32>(0.0), vec3<f32>(1.0));
            vm = va;
        } else {
            let x = o + d * t;
            let speed = length(unit_velocity(x, d));
            if !(speed > 0.0 && speed <= INF) {
                break;
            }
            dt = max(min(h / speed, far - t), hair);
            let xm = o + d * (t + 0.5 * dt);
            um = to_unit(xm);
            vm = unit_velocity(xm, d);
        }
        let tm = t + 0.5 * dt;
        let s = lookup(um, vm);
        if s.kind == 2u {
            return March(vec3<f32>(0.0), OUTSIDE);
        }
        if s.kind == 0u {
            // Past the boundary by a hair, and never backwards.
            t = max(tm + s.skip + 1e-3 * dt, t + 1e-3 * dt);
            continue;
        }
        let tau = tau_of(trunc_exp(s.value.x), dt);
        let alpha = 1.0 - exp(-tau);
        let w = trans * alpha;
        if w >= MIN_COLOUR_WEIGHT {
            rgb += w * s.value.yzw;
        }
        last = s.value.yzw;
        trans *= 1.0 - alpha;
        if trans < stop {
            visible = t + dt;
            break;
        }
        t += dt;
    }
    if model.background.w == 1.0 {
        rgb += trans * model.background.xyz;
    } else {
        // The transmittance left takes the last sample's colour (0 without one).
        rgb += trans * last;
    }
    if visible < 0.0 {
        visible = select(0.0, far, ok);
    }
    return March(rgb, visible);
}

// One invocation per pixel of the `view.size.x` by `view.size.y` frame (`view.size.z` pixels),
// or with flag 1 (`view.size.w`) per entry of the pixel list: invocation `i` draws pixel
// `list[i]` (the page's interlaced lattices of reduced frames). Writes (r, g, b, visible depth) to
// frame[pixel]; a ray that misses the scene under a constant background gets the background and
// the visible depth MISSED, one that reaches a brick the volume left out the visible depth
// OUTSIDE.
// A whole frame's invocations walk it in 8x8 tiles, a workgroup per tile (the host dispatches
// `tile_invocations`): neighbouring rays cross the same bricks, so they share the cache and
// stop at similar depths. A pixel list is walked in its own order.
const TILE: u32 = 8u;

@compute @workgroup_size(64)
fn volume_march(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = invocation(gid, groups);
    var p = i;
    var inside = i < view.size.z;
    if (view.size.w & 1u) != 0u {
        if inside {
            p = list[i];
        }
    } else {
        let tiles_x = (view.size.x + TILE - 1u) / TILE;
        let tile = i / (TILE * TILE);
        let j = i % (TILE * TILE);
        let x = (tile % tiles_x) * TILE + j % TILE;
        let y = (tile / tiles_x) * TILE + j / TILE;
        inside = x < view.size.x && y < view.size.y;
        p = y * view.size.x + x;
    }
    if inside {
        let o = view.c2w[3].xyz;
        let d = pixel_ray_dir(p);
        let lim = ray_limits(o, d);
        if !(lim.y > lim.x) && model.background.w == 1.0 {
            frame[p] = vec4<f32>(model.background.xyz, MISSED);
        } else {
            let m = march_ray(o, d);
            frame[p] = vec4<f32>(m.rgb, m.visible_depth);
        }
    }
}
