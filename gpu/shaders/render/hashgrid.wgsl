// hashgrid: one level of a multi-resolution hash grid (3D or 4D, dense or hashed) at a point:
// the interpolated features of its corners.

// #import common
// #import bindings

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
