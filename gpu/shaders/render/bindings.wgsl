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
