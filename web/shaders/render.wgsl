// Composed from WGSL modules by msth-gpu (`shaders::compose`), roots: points, passes.

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

// #module io
// io: the pixel list and output buffer of the render entry points (bindings 5 and 6).

// Pixel list (the passes) or packed points (eval_points).
@group(0) @binding(5) var<storage, read> list: array<u32>;
// Output: (r, g, b, visible depth) per pixel (the passes, volume_march) or (r, g, b, sigma) per
// point (eval_points).
@group(0) @binding(6) var<storage, read_write> frame: array<vec4<f32>>;

// #module sh
// sh: the view-direction encoding, 16 real spherical harmonics of a unit direction into
// `sh` (msth-core `sh::sh4`); also composed into the training kernels (`gpu/src/sh.rs`).

var<private> sh: array<f32, 16>;

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

// #module mask
// mask: the dense mask grid, trilinear and sigmoid: the weight m of the static encoding.

// Trilinear read of the dense mask grid (logit), `res^3` values at `off` in `rest`. Per-axis
// values in vectors, not indexed arrays (software adapters turn those into memory traffic).
fn mask_logit(off: u32, res: u32, x: vec3<f32>) -> f32 {
    let pos = clamp_unit3(x) * f32(res - 1u);
    let base = min(vec3<u32>(pos), vec3<u32>(res - 2u));
    let fr = pos - vec3<f32>(base);
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
    var m = e.consts.x;
    if e.mode.y == 1u {
        m = sigmoid(mask_logit(e.mode.w, e.mode.z, x));
    }
    return m;
}

// #module mlp
// mlp: the generic MLP layers of one sample (weights read from `rest`, activations in the
// private arrays below), as msth-core's decoders.

// MLP activations: the input (an encoding of at most MAX_LEVELS * MAX_FEATURES values) and
// hidden layers in `hid`, each layer's output in `hid2`.
var<private> hid: array<f32, 256>;
var<private> hid2: array<f32, MAX_HIDDEN>;
var<private> dout: array<f32, 32>; // 1 + MAX_GEO

// rest[b .. b + 4], the components at or beyond `left` read as 0.
fn w4(b: u32, left: u32) -> vec4<f32> {
    return vec4<f32>(
        select(0.0, rest[b], left > 0u),
        select(0.0, rest[b + 1u], left > 1u),
        select(0.0, rest[b + 2u], left > 2u),
        select(0.0, rest[b + 3u], left > 3u),
    );
}

// rest[b .. b + 4], unconditionally: in `dense_lanes` the components past a layer's last output
// are other parameters (or, past the buffer's end, what robust buffer access returns) and reach
// only outputs that are not stored.
fn r4(b: u32) -> vec4<f32> {
    return vec4<f32>(rest[b], rest[b + 1u], rest[b + 2u], rest[b + 3u]);
}

// a - b, or 0 when b > a.
fn sub_sat(a: u32, b: u32) -> u32 {
    return select(0u, a - b, a > b);
}

// hid2[0..nout] = hid[0..nin] W (W [nin, nout] row-major at `off` in `rest`), ReLU when `relu`;
// each output summed over the inputs in order, as on the CPU. Sixteen outputs at a time in four
// vec4 accumulators that stay in registers (indexed private memory only outside the inner loop:
// software rasterisers such as SwiftShader turn every indexed private access into a per-lane
// gather or scatter).
fn dense_layer(off: u32, nin: u32, nout: u32, relu: bool) {
    for (var o0 = 0u; o0 < nout; o0 += 16u) {
        let left = nout - o0;
        let l1 = sub_sat(left, 4u);
        let l2 = sub_sat(left, 8u);
        let l3 = sub_sat(left, 12u);
        var a0 = vec4<f32>(0.0);
        var a1 = vec4<f32>(0.0);
        var a2 = vec4<f32>(0.0);
        var a3 = vec4<f32>(0.0);
        var row = off + o0;
        for (var i = 0u; i < nin; i++) {
            let x = hid[i];
            a0 += x * w4(row, left);
            a1 += x * w4(row + 4u, l1);
            a2 += x * w4(row + 8u, l2);
            a3 += x * w4(row + 12u, l3);
            row += nout;
        }
        if relu {
            a0 = max(a0, vec4<f32>(0.0));
            a1 = max(a1, vec4<f32>(0.0));
            a2 = max(a2, vec4<f32>(0.0));
            a3 = max(a3, vec4<f32>(0.0));
        }
        let outs = array<vec4<f32>, 4>(a0, a1, a2, a3);
        for (var k = 0u; k < min(left, 16u); k++) {
            hid2[o0 + k] = outs[k >> 2u][k & 3u];
        }
    }
}

// hid[0..n] = hid2[0..n].
fn hid2_to_hid(n: u32) {
    for (var j = 0u; j < n; j++) {
        hid[j] = hid2[j];
    }
}

// #module hashgrid
// hashgrid: one level of a multi-resolution hash grid (3D or 4D, dense or hashed) at a point:
// the interpolated features of its corners.

// Value i of the hash tables of buffer `buf` (0 tab3, 1 tab4).
fn table(buf: u32, i: u32) -> f32 {
    return table2(buf, i & ~1u)[i & 1u];
}

// The features of one level (at most MAX_FEATURES: `a` holds features 0..3, `b` 4..7).
struct Feat {
    a: vec4<f32>,
    b: vec4<f32>,
}

// Features of level l of grid g at point p (dims 3 or 4): multilinear interpolation of the 2^D
// corners, dense or hashed indexing; the table is in buffer `buf` (0 tab3, 1 tab4),
// a constant at every call site so that the compiler can drop `table`'s branches. Per-axis
// values in vectors and features in two vec4 (no indexed private arrays).
//
// Written for software adapters, where a shader's cost is about the operations it runs
// (SwiftShader runs each one for a group of invocations, both sides of every `if` included, and
// hoists nothing out of loops: docs/playback.md): what does not change from corner to corner is
// computed once before the corner loop, both row rules are computed and one is selected, and
// features 0 and 1 (every preset has 2 per level) are accumulated without the per-feature
// selects that features 2..7 need.
fn grid_level(g: Grid, l: u32, p: vec4<f32>, buf: u32) -> Feat {
    return grid_level_at(model.levels[g.loc.y + l], g.shape, p, buf);
}

// `grid_level` of level `lv` of a grid of shape `shape` (`Grid.shape`): the generic encoding
// reads both from the uniform, the specialised one (`encode_field4`) passes constants.
fn grid_level_at(lv: Level, shape: vec4<u32>, p: vec4<f32>, buf: u32) -> Feat {
    let four = shape.x == 4u;
    let nf = shape.y;
    let dense = lv.info.y == 1u;
    let q = clamp_unit4(p) * lv.scale + 0.5;
    let iv = vec4<u32>(q); // q >= 0.5: truncation is floor
    let fr = q - vec4<f32>(iv);
    // The weights of the low corner per axis; a 3D grid's fourth axis weighs 1 (its corners
    // never take the high side there).
    let gr = vec4<f32>(1.0 - fr.xyz, select(1.0, 1.0 - fr.w, four));
    let primes = vec4<u32>(1u, 2654435761u, 805459861u, 3674653429u);
    // A 3D grid: lv.stride.w = 0, and iv.w = 0 (scale.w = 0), so lo.w = 0.
    let lo = select(iv * primes, iv * lv.stride, dense);
    let hi = select((iv + 1u) * primes, lo + lv.stride, dense);
    let hash_mask = shape.w;
    let off = lv.info.x;
    let second = min(1u, nf - 1u); // feature 1, or feature 0 again when nf = 1 (then unused)
    var fa = vec4<f32>(0.0);
    var fb = vec4<f32>(0.0);
    let corners = select(8u, 16u, four);
    let bits = vec4<u32>(1u, 2u, 4u, 8u);
    for (var c = 0u; c < corners; c++) {
        let u = (vec4<u32>(c) & bits) != vec4<u32>(0u);
        let wv = select(gr, fr, u);
        let w = wv.x * wv.y * wv.z * wv.w; // the CPU's order; * 1 on a 3D grid is exact
        let cv = select(lo, hi, u);
        let row = select((cv.x ^ cv.y ^ cv.z ^ cv.w) & hash_mask, cv.x + cv.y + cv.z + cv.w, dense);
        let base = off + row * nf;
        // An even number of features per row: every row starts at an even index (levels too:
        // their sizes are rows x nf), so features 0 and 1 are one pair.
        if (nf & 1u) == 0u {
            let t = table2(buf, base);
            fa.x += w * t.x;
            fa.y += w * t.y;
        } else {
            fa.x += w * table(buf, base);
            fa.y += w * table(buf, base + second);
        }
        // Features 2.. (no trips at 1 or 2 features per level).
        for (var f = 2u; f < nf; f++) {
            let t = w * table(buf, base + f);
            let fv = vec4<u32>(f);
            fa = select(fa, fa + t, fv == vec4<u32>(0u, 1u, 2u, 3u));
            fb = select(fb, fb + t, fv == vec4<u32>(4u, 5u, 6u, 7u));
        }
    }
    return Feat(fa, fb);
}

// #module field
// field: the fields at one point: the masked space-time encoding (`encode`: mask, blend, 3D and
// 4D grids) and the decoders on it: the proposal field's density (`proposal_sigma`), the main
// field's density and geometry features (`field_density`) and its colour from those and the SH
// of the view direction (`field_color`). One point per call: `eval_points` calls them per point,
// the passes' sample cache and the generic encodings per sample, a per-pixel kernel can too.

// The blend of encoding `e` at a point of mask value m: `(k3, k4, read3, read4)`, the features
// being v = k3 f3 + k4 f4 (mst: m, 1 - m; mt: 1, 1 - m; add: 1, 1; 4d: 0, 1; static: 1, 0: the
// CPU's sums, since 1 x = x and a skipped lookup's features are 0; no branch per blend, since
// software adapters run every branch), and whether the 3D and 4D lookups are made (1) or
// skipped (0): the 4D one where the mask leaves (almost) nothing dynamic (Mst/Mt with a mask,
// `1 - m < cutoff`), and the lookup a blend does not read (static: 4D; 4d: 3D).
fn blend_of(e: Encoding, m: f32, cutoff: f32) -> vec4<f32> {
    let blend = e.mode.x;
    let skip4 = blend == 4u || (cutoff > 0.0 && e.mode.y == 1u && blend <= 1u && (1.0 - m) < cutoff);
    let skip3 = blend == 3u;
    let k3 = select(select(1.0, m, blend == 0u), 0.0, blend == 3u);
    let k4 = select(select(1.0 - m, 1.0, blend >= 2u), 0.0, blend == 4u);
    return vec4<f32>(k3, k4, select(1.0, 0.0, skip3), select(1.0, 0.0, skip4));
}

// Whether encoding e, at its own cutoff (`consts.y`, what the passes' encodings are given),
// makes the 4D lookup at unit-cube point x.
fn reads4(e: Encoding, x: vec3<f32>) -> bool {
    return blend_of(e, mask_at(e, x), e.consts.y).w != 0.0;
}

// Masked encoding at point p into hid[0 .. levels * features] (level-major, features within a
// level), the MLPs' input: the 3D tables in `tab3`, the 4D ones in `tab4` (both fields'). Returns
// the mask value m. `with4` false (a constant at the call site): no 4D lookup is compiled in,
// for points whose blend skips it (`reads4` false); the result is the same for those.
fn encode(e: Encoding, p: vec4<f32>, cutoff: f32, with4: bool) -> f32 {
    let m = mask_at(e, p.xyz);
    let use3 = e.h3.loc.z == 1u;
    let use4 = e.h4.loc.z == 1u;
    let b = blend_of(e, m, cutoff);
    let k3 = b.x;
    let k4 = b.y;
    let skip3 = b.z == 0.0;
    let skip4 = b.w == 0.0;
    var levels = 0u;
    var nf = 1u;
    if use3 {
        levels = e.h3.shape.z;
        nf = e.h3.shape.y;
    } else {
        levels = e.h4.shape.z;
        nf = e.h4.shape.y;
    }
    let second = min(1u, nf - 1u);
    let zero = Feat(vec4<f32>(0.0), vec4<f32>(0.0));
    for (var l = 0u; l < levels; l++) {
        var f3 = zero;
        var f4 = zero;
        if use3 && !skip3 {
            f3 = grid_level(e.h3, l, p, 0u);
        }
        if with4 && use4 && !skip4 {
            f4 = grid_level(e.h4, l, p, 1u);
        }
        let va = k3 * f3.a + k4 * f4.a;
        let at = l * nf;
        // Features 0 and 1 (with one feature per level, the second write puts feature 0 back).
        hid[at + second] = va.y;
        hid[at] = va.x;
        for (var f = 2u; f < nf; f++) {
            let vb = k3 * f3.b + k4 * f4.b;
            hid[at + f] = select(vb[f & 3u], va[f & 3u], f < 4u);
        }
    }
    return m;
}

// Proposal density at p.
fn proposal_sigma(p: vec4<f32>, cutoff: f32) -> f32 {
    let d = model.proposal;
    let off = d.x;
    let hidden = d.z;
    encode(model.prop, p, cutoff, true);
    dense_layer(off, d.y, hidden, true);
    let w2 = off + d.y * hidden;
    var s = 0.0;
    for (var j = 0u; j < hidden; j++) {
        s += hid2[j] * rest[w2 + j];
    }
    return trunc_exp(s);
}

// Main-field density at p: returns sigma; geo features in dout[1..=geo]; mask value in *m.
fn field_density(p: vec4<f32>, cutoff: f32, m: ptr<function, f32>) -> f32 {
    let d = model.density;
    let off = d.x;
    let hidden = d.z;
    let nout = d.w;
    *m = encode(model.field, p, cutoff, true);
    dense_layer(off, d.y, hidden, true);
    hid2_to_hid(hidden);
    let w2 = off + d.y * hidden;
    dense_layer(w2, hidden, nout, false);
    for (var o = 0u; o < nout; o++) {
        dout[o] = hid2[o];
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
    // Constant indices: plain registers, no indexed private memory.
    hid[0] = sh[0];
    hid[1] = sh[1];
    hid[2] = sh[2];
    hid[3] = sh[3];
    hid[4] = sh[4];
    hid[5] = sh[5];
    hid[6] = sh[6];
    hid[7] = sh[7];
    hid[8] = sh[8];
    hid[9] = sh[9];
    hid[10] = sh[10];
    hid[11] = sh[11];
    hid[12] = sh[12];
    hid[13] = sh[13];
    hid[14] = sh[14];
    hid[15] = sh[15];
    for (var k = 0u; k < geo; k++) {
        hid[16u + k] = dout[1u + k];
    }
    var off = c.x;
    dense_layer(off, nin, hidden, true);
    off += nin * hidden;
    for (var k = 1u; k < layers; k++) {
        hid2_to_hid(hidden);
        dense_layer(off, hidden, hidden, true);
        off += hidden * hidden;
    }
    hid2_to_hid(hidden);
    dense_layer(off, hidden, 3u, false);
    let rgb = vec3<f32>(sigmoid(hid2[0]), sigmoid(hid2[1]), sigmoid(hid2[2]));
    return rgb;
}

// #module points
// points: the `eval_points` entry point, one invocation per point: the fields at given points,
// exactly as the CPU's field evaluation (kernel tests; the play-time volume's bake).

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

// #module passes_lanes
// passes_lanes: the per-sample passes' MLP activations of LANES samples at once (component k
// of a `vec4` for sample k), shared by the generic and the specialised MLPs.

// Samples per invocation of `pass_proposal`, `pass_density`, `pass_dynamic` and `pass_color`.
const LANES: u32 = 4u;
// Activations, component k for sample k: the MLPs' input in `hid4`, the density MLP's output in
// `out4` (the generic MLPs below also keep their hidden layers there).
var<private> hid4: array<vec4<f32>, MAX_HIDDEN>; // also the colour input: 16 + MAX_GEO < MAX_HIDDEN
var<private> out4: array<vec4<f32>, MAX_HIDDEN>;

fn sigmoid4(x: vec4<f32>) -> vec4<f32> {
    return vec4<f32>(sigmoid(x.x), sigmoid(x.y), sigmoid(x.z), sigmoid(x.w));
}

// hid4[0..n] component `lane` = hid[0..n] (one sample's MLP input into its lane).
fn hid_to_lane(lane: u32, n: u32) {
    for (var q = 0u; q < n; q++) {
        hid4[q][lane] = hid[q];
    }
}

// #module passes_work
// passes_work: what the per-sample passes share: the `Pass` uniform, the work buffer and its
// counters (bindings 7-10), and the helpers that read rays, samples and the live lists.

// Work buffer regions (offsets in 4-byte words, from `Pass`): rays (4 words per ray: output
// index, pixel, near, far), hist (proposal sigma, then weights: np per ray), edges (S + 1
// normalised edges per ray), samp (r, g, b, sigma per sample), geo (geo features per sample),
// clist (colour list: a sample index per entry), wmax (np per ray), pts (x, y, z, dynamic flag per
// sample), dlist (dynamic samples' indices). Samples are ray-major (`ray * S + k`): the
// neighbouring invocations of a pass evaluate neighbouring points of one ray, which share hash
// rows and cache lines.

struct Pass {
    // x: first entry of this batch in the pixel order, y: pixels in the batch, z: flags
    // (bit 0: pixel list[first + i], else pixel first + i; bit 1: output to frame[first + i],
    // else frame[pixel]; bit 2: cache (only samples flagged dynamic get colours); bit 3:
    // resample from the `wmax` histogram; bit 4: the live lists put the samples whose mask
    // skips the 4D lookup apart, for `pass_proposal3` and `pass_density3`, else every live
    // sample goes to `pass_proposal` and `pass_density`), w: samples per ray S.
    tile: vec4<u32>,
    // Word offsets: x rays, y hist, z edges, w samp.
    reg0: vec4<u32>,
    // Word offsets: x geo, y clist, z wmax, w pts.
    reg1: vec4<u32>,
    // x: dlist, y: occupancy resolution R (0: no grid, every sample is evaluated), z: the live
    // proposal samples' list, w: the live main samples' list (word offsets; with a grid; each
    // list holds the samples with a 4D lookup from its front, the others from its back).
    reg2: vec4<u32>,
    // x: static cutoff of `pass_build`, y: 1 = first time of `pass_wmax`, zw: 0.
    misc: vec4<f32>,
}

// Scratch of the passes (regions above); f32 words, u32 values stored as bit patterns.
@group(0) @binding(7) var<storage, read_write> work: array<f32>;
// Counters: [0] rays, [1] colour list, [2] dynamic samples.
@group(0) @binding(8) var<storage, read_write> ctrl: array<atomic<u32>>;
@group(0) @binding(9) var<uniform> pass_u: Pass;
// The file's occupancy grid (docs/format.md §6.5): `R^3` bits over the grids' unit cube, cell
// `i = x + R (y + R z)` is bit `i % 32` of word `i / 32`; a placeholder word without a grid.
@group(0) @binding(10) var<storage, read> occupancy_words: array<u32>;

const FLAG_P_LIST: u32 = 1u;
const FLAG_P_COMPACT: u32 = 2u;
const FLAG_P_CACHE: u32 = 4u;
const FLAG_P_WMAX: u32 = 8u;
const FLAG_P_SPLIT: u32 = 16u;
// Largest workgroup count per dimension the indirect dispatches use (WebGPU's default limit).
const MAX_GROUPS: u32 = 65535u;

fn work_u(i: u32) -> u32 {
    return bitcast<u32>(work[i]);
}

fn ray_count() -> u32 {
    return atomicLoad(&ctrl[0]);
}

fn samples_per_ray() -> u32 {
    return pass_u.tile.w;
}

// Ray r's record: (output index, pixel, near, far).
fn ray_rec(r: u32) -> vec4<f32> {
    let o = pass_u.reg0.x + 4u * r;
    return vec4<f32>(work[o], work[o + 1u], work[o + 2u], work[o + 3u]);
}

fn ray_pixel(rec: vec4<f32>) -> u32 {
    return bitcast<u32>(rec.y);
}

// Whether the main field is evaluated at unit-cube point p: its occupancy cell is set (cell
// `min(floor(clamp(p, 0, 1) R), R - 1)` per axis, as msth-codec's `occupied_unit`), or the
// pass skips nothing (R = 0). A clear cell's samples get density 0 and no colour, as in the CPU
// renderer's `skip.rs`.
fn occupied(p: vec3<f32>) -> bool {
    let r = pass_u.reg2.y;
    var bit = true;
    if r != 0u {
        let c = min(vec3<u32>(clamp(p, vec3<f32>(0.0), vec3<f32>(1.0)) * f32(r)), vec3<u32>(r - 1u));
        let i = c.x + r * (c.y + r * c.z);
        bit = ((occupancy_words[i >> 5u] >> (i & 31u)) & 1u) == 1u;
    }
    return bit;
}

fn field_time() -> f32 {
    let t = view.time.x;
    return select(0.0, min(t, 1.0), t >= 0.0);
}

// Main-sample interval k of ray r (distances t0, t1) from the ray's edges.
fn main_interval(r: u32, k: u32, near: f32, far: f32) -> vec2<f32> {
    let e = pass_u.reg0.z + r * (samples_per_ray() + 1u) + k;
    return vec2<f32>(t_of_s(work[e], near, far), t_of_s(work[e + 1u], near, far));
}

// The list entry of lane k of invocation i, `used` of whose LANES lanes hold entries: lanes past
// the list's end repeat its last entry (and store nothing).
fn lane_entry(i: u32, k: u32, used: u32) -> u32 {
    return i * LANES + min(k, used - 1u);
}

// Workgroups (x, y, 1) for `n` invocations, written at `at` in `work` (bound to `args`).
fn write_groups(at: u32, n: u32) {
    let groups = (n + WORKGROUP - 1u) / WORKGROUP;
    let x = min(groups, MAX_GROUPS);
    var y = 0u;
    if x > 0u {
        y = (groups + x - 1u) / x;
    }
    work[at] = bitcast<f32>(x);
    work[at + 1u] = bitcast<f32>(y);
    work[at + 2u] = bitcast<f32>(1u);
}

// Proposal sample e (ray-major over the batch's rays): its unit-cube point at the frame's time.
fn proposal_point(e: u32) -> vec4<f32> {
    let np = model.sampler.x;
    let rec = ray_rec(e / np);
    let ks = e % np;
    let dir = pixel_ray_dir(ray_pixel(rec));
    let t0 = t_of_s(f32(ks) / f32(np), rec.z, rec.w);
    let t1 = t_of_s(f32(ks + 1u) / f32(np), rec.z, rec.w);
    return sample_point(view.c2w[3].xyz, dir, t0, t1, field_time());
}

// Whether the live lists put the samples without a 4D lookup apart (`FLAG_P_SPLIT`; a host sets
// it once it has the passes that evaluate them).
fn split_lists() -> bool {
    return (pass_u.tile.z & FLAG_P_SPLIT) != 0u;
}

// Appends entry `x` to the live list at word `region` of `total` entries: from the front when
// the sample makes the 4D lookup (`with4`, counted in `ctrl[c4]`), from the back when its mask
// skips it (`ctrl[c4 + 2]`). Both fit, since every entry goes to one end or none.
fn live_append(region: u32, total: u32, x: u32, with4: bool, c4: u32) {
    if with4 {
        let slot = atomicAdd(&ctrl[c4], 1u);
        work[region + slot] = bitcast<f32>(x);
    } else {
        let slot = atomicAdd(&ctrl[c4 + 2u], 1u);
        work[region + total - 1u - slot] = bitcast<f32>(x);
    }
}

// Entry `x` of the live list at `region` of `total` entries: of its front (samples with a 4D
// lookup) when `with4`, else of its back (`live_append`).
fn live_entry(region: u32, total: u32, x: u32, with4: bool) -> u32 {
    return work_u(select(region + total - 1u - x, region + x, with4));
}

// Main sample k of ray r (record `rec`): the unit-cube point at the frame's time.
fn main_point(r: u32, k: u32, rec: vec4<f32>) -> vec4<f32> {
    let iv = main_interval(r, k, rec.z, rec.w);
    let d = pixel_ray_dir(ray_pixel(rec));
    return sample_point(view.c2w[3].xyz, d, iv.x, iv.y, field_time());
}

// #module specialise
// specialise: the per-sample passes' encodings and MLPs, the region that hosts replace for one
// model.

// The passes' encodings (`encode_field4`, `encode_proposal4`), MLPs (`proposal_mlp4`,
// `density_mlp4`, `color_mlp4`) and geometry-feature transfers (`geo_to_work`, `geo_from_work`)
// lie between the two `specialise` lines. These generic versions read the level values from the
// uniform and the weights from `rest`, and loop over the geometry features; hosts replace the
// region by versions generated for one model, with those values as constants, the activations in
// named values and the transfers unrolled (msth-gpu `specialise.rs`, the page's
// `specialise.js`), which software adapters run without a gather per read. (A loop over a count
// read from the uniform indexes `hid4` and `out4` at run time, which makes Mesa's lavapipe keep
// those arrays in memory in every pass that does so, for every access.)
// ---- specialise: begin

// out4[0..nout] = hid4[0..nin] W per sample (W [nin, nout] row-major at `off` in `rest`), ReLU
// when `relu`; each output summed over the inputs in order, as on the CPU. Eight outputs at a
// time in registers: one read of a weight serves the LANES samples; the weights are read
// without bounds selects (`r4`).
fn dense_lanes(off: u32, nin: u32, nout: u32, relu: bool) {
    for (var o0 = 0u; o0 < nout; o0 += 8u) {
        let left = nout - o0;
        var a0 = vec4<f32>(0.0);
        var a1 = vec4<f32>(0.0);
        var a2 = vec4<f32>(0.0);
        var a3 = vec4<f32>(0.0);
        var a4 = vec4<f32>(0.0);
        var a5 = vec4<f32>(0.0);
        var a6 = vec4<f32>(0.0);
        var a7 = vec4<f32>(0.0);
        var row = off + o0;
        for (var i = 0u; i < nin; i++) {
            let x = hid4[i];
            let w = r4(row);
            let v = r4(row + 4u);
            a0 += x * w.x;
            a1 += x * w.y;
            a2 += x * w.z;
            a3 += x * w.w;
            a4 += x * v.x;
            a5 += x * v.y;
            a6 += x * v.z;
            a7 += x * v.w;
            row += nout;
        }
        var outs = array<vec4<f32>, 8>(a0, a1, a2, a3, a4, a5, a6, a7);
        for (var k = 0u; k < min(left, 8u); k++) {
            var v = outs[k];
            if relu {
                v = max(v, vec4<f32>(0.0));
            }
            out4[o0 + k] = v;
        }
    }
}

// hid4[0..n] = out4[0..n].
fn out4_to_hid4(n: u32) {
    for (var j = 0u; j < n; j++) {
        hid4[j] = out4[j];
    }
}

// The colours of the LANES samples whose colour inputs (SH coefficients, then the geo
// features) are in hid4, as `field_color`: red, green, blue, component k for sample k.
fn color_mlp4() -> array<vec4<f32>, 3> {
    let c = model.color;
    let hidden = c.y;
    let nin = 16u + c.w;
    var off = c.x;
    dense_lanes(off, nin, hidden, true);
    off += nin * hidden;
    for (var k = 1u; k < c.z; k++) {
        out4_to_hid4(hidden);
        dense_lanes(off, hidden, hidden, true);
        off += hidden * hidden;
    }
    out4_to_hid4(hidden);
    dense_lanes(off, hidden, 3u, false);
    return array<vec4<f32>, 3>(sigmoid4(out4[0]), sigmoid4(out4[1]), sigmoid4(out4[2]));
}

// The field's encoding of point p into lane k of hid4 (`hid4[i][k]`, i < levels * features), as
// `encode` (`with4` a constant at the call site); returns the mask value.
fn encode_field4(p: vec4<f32>, cutoff: f32, k: u32, with4: bool) -> f32 {
    let m = encode(model.field, p, cutoff, with4);
    hid_to_lane(k, model.density.y);
    return m;
}

// The proposal field's encoding of point p into lane k of hid4, as `encode`.
fn encode_proposal4(p: vec4<f32>, cutoff: f32, k: u32, with4: bool) {
    encode(model.prop, p, cutoff, with4);
    hid_to_lane(k, model.proposal.y);
}

// The proposal density MLP of the LANES samples whose encodings are in hid4: the log density
// (before `trunc_exp`), component k for sample k.
fn proposal_mlp4() -> vec4<f32> {
    let d = model.proposal;
    dense_lanes(d.x, d.y, d.z, true);
    let w2 = d.x + d.y * d.z;
    var sum = vec4<f32>(0.0);
    for (var j = 0u; j < d.z; j++) {
        sum += out4[j] * rest[w2 + j];
    }
    return sum;
}

// The density MLP of the LANES samples whose encodings are in hid4: out4[0] the log density,
// out4[1 ..= geo] the geometry features.
fn density_mlp4() {
    let d = model.density;
    dense_lanes(d.x, d.y, d.z, true);
    out4_to_hid4(d.z);
    dense_lanes(d.x + d.y * d.z, d.z, d.w, false);
}

// Sample j's geometry features, out4[1 ..= geo] component k, into the work buffer.
fn geo_to_work(j: u32, k: u32) {
    let geo = model.color.w;
    for (var q = 0u; q < geo; q++) {
        work[pass_u.reg1.x + j * geo + q] = out4[1u + q][k];
    }
}

// Sample j's geometry features from the work buffer into the colour MLP's inputs,
// hid4[16 ..] component k.
fn geo_from_work(j: u32, k: u32) {
    let geo = model.color.w;
    for (var q = 0u; q < geo; q++) {
        hid4[16u + q][k] = work[pass_u.reg1.x + j * geo + q];
    }
}
// ---- specialise: end

// #module passes_rays
// passes_rays: the passes up to each ray's main samples: ray setup, dispatch sizes, the live
// lists of an occupancy grid, the proposal field's densities and the resampling.

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

// #module passes_shade
// passes_shade: the passes from a ray's main samples to its pixel: density, which samples light
// reaches, their colours, and compositing.

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

// #module passes_cache
// passes_cache: the sample cache of incremental playback (msth-player's `samples.rs`): the
// per-bin maximum of proposal weights over several times, the cache's static samples evaluated
// once, and its dynamic samples' density per frame.

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

// #module passes
// passes: the per-sample passes' entry points (`pass_*`): the CPU renderer's rendering (msth-core
// `pipeline::render_chunk`), split into dispatches over compacted work lists, so that no
// invocation loops over a whole ray's field evaluations. One frame (or one batch of rays of it)
// is, in order:
//
//   pass_setup      one per pixel of the batch: ray limits; a ray that misses the scene under a
//                   constant background writes the background, the others are appended to the
//                   ray list (`ctrl[0]`);
//   pass_args       one invocation: indirect dispatch sizes from the counters (bound with the
//                   `args` buffer in the `work` slot);
//   pass_proposal   one per (ray, proposal sample): the proposal field's density;
//   pass_resample   one per ray: proposal weights and the inverse CDF, `S + 1` edges (short
//                   loops over the ray's histogram, no field evaluation);
//   pass_density    one per (ray, main sample): encoding, mask blend, density MLP; sigma and the
//                   geometry features;
//
// With the file's occupancy grid, `pass_live_proposal` and `pass_live_samples` first list the
// samples in occupied cells, split by the mask: those it leaves a 4D lookup go to
// `pass_proposal` and `pass_density`, those whose 4D lookup it skips to `pass_proposal3` and
// `pass_density3`, compiled without the 4D lookup (a static sample then costs its 3D lookup,
// wherever it falls among its neighbours);
//   pass_visible    one per ray: which samples light still reaches: those get a colour and are
//                   appended to the colour list (`ctrl[1]`);
//   pass_args       again (the colour list's size);
//   pass_color      one per listed sample: SH of the ray direction + colour MLP;
//   pass_composite  one per ray: volume compositing and the background into `frame`.
//
// Incremental playback with sample-level reuse (msth-player's `samples.rs`) runs the same passes
// on a persistent cache: `pass_wmax` (the per-bin maximum of the proposal weights over several
// times), `pass_resample` from that histogram, `pass_build` (static samples evaluated once,
// dynamic ones listed in `ctrl[2]`), then per frame `pass_dynamic` (the dynamic samples' density
// at the frame's time), `pass_visible`, `pass_color` and `pass_composite`.

