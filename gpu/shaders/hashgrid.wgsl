// Multi-resolution hash-grid encoding (3D and 4D) for training, one invocation per
// (sample, level) pair: exactly the geometry of `msth_core::grid` (method.md section 1).
//
// Per level l and axis a: q_a = clamp01(x_a) * scale_a + 0.5, i_a = floor(q_a), fr_a = q_a - i_a;
// the 2^D corners c_a in {i_a, i_a + 1} weigh prod_a (fr_a or 1 - fr_a). A dense level indexes
// row = sum_a c_a * stride_a; a hashed one row = (XOR_a c_a * prime_a) & hash_mask (u32 wrapping).
// Table rows are [rows, F] row-major, level after level, starting at run.y floats into the table
// (the grid's slice of the flat parameter buffer); features of sample i are
// out[i * L * F + l * F + f].
//
// This prelude is shared by `hashgrid_forward.wgsl` and `hashgrid_backward.wgsl` (the host
// concatenates them). Loops are bounded by 2^D * F <= 128 iterations per invocation.

struct Level {
    scale: vec4<f32>,
    stride: vec4<u32>,
    // x: offset of the level's table in floats (from the grid's start), y: 1 when dense,
    // z: rows, w: 0.
    info: vec4<u32>,
}

struct Grid {
    // x: dims (3 or 4), y: features per level (1, 2, 4 or 8), z: levels, w: hash mask.
    shape: vec4<u32>,
    // x: samples, y: offset of the grid in the table buffer (floats), z, w: 0.
    run: vec4<u32>,
    levels: array<Level, 32>,
}

@group(0) @binding(0) var<uniform> grid: Grid;
// (x, y, z, t) per sample in the unit cube / unit time; 3D grids read x, y, z.
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;

const WORKGROUP: u32 = 64u;

fn invocation(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * WORKGROUP;
}

fn clamp_unit(x: f32) -> f32 {
    // NaN maps to 0 (as the CPU's `if x >= 0 { min(x, 1) } else { 0 }`).
    return select(0.0, min(x, 1.0), x >= 0.0);
}

fn prime(a: u32) -> u32 {
    var p = 1u;
    if a == 1u {
        p = 2654435761u;
    } else if a == 2u {
        p = 805459861u;
    } else if a == 3u {
        p = 3674653429u;
    }
    return p;
}

// The cell of one sample on one level: per axis the lower corner's index term (dense: i * stride,
// hashed: i * prime), the upper corner's, and the fraction.
struct Cell {
    lo: array<u32, 4>,
    hi: array<u32, 4>,
    fr: array<f32, 4>,
}

fn cell(lv: Level, p: vec4<f32>, dims: u32) -> Cell {
    let dense = lv.info.y == 1u;
    var pa = array<f32, 4>(p.x, p.y, p.z, p.w);
    var scale = array<f32, 4>(lv.scale.x, lv.scale.y, lv.scale.z, lv.scale.w);
    var stride = array<u32, 4>(lv.stride.x, lv.stride.y, lv.stride.z, lv.stride.w);
    var c: Cell;
    for (var a = 0u; a < 4u; a++) {
        c.lo[a] = 0u;
        c.hi[a] = 0u;
        c.fr[a] = 0.0;
        if a < dims {
            let q = clamp_unit(pa[a]) * scale[a] + 0.5;
            let i = floor(q);
            c.fr[a] = q - i;
            let iu = u32(i);
            if dense {
                c.lo[a] = iu * stride[a];
                c.hi[a] = c.lo[a] + stride[a];
            } else {
                c.lo[a] = iu * prime(a);
                c.hi[a] = (iu + 1u) * prime(a);
            }
        }
    }
    return c;
}

// Row (within the level) and weight of corner `k` (bit a set: upper corner on axis a). The
// weight is the product over axes in axis order, as on the CPU.
struct Corner {
    row: u32,
    w: f32,
}

fn corner(c_in: Cell, k: u32, dims: u32, dense: bool, hash_mask: u32) -> Corner {
    // Dynamic indices into a function-local copy (not into a value).
    var c = c_in;
    var row = 0u;
    var w = 1.0;
    for (var a = 0u; a < dims; a++) {
        let up = ((k >> a) & 1u) == 1u;
        let term = select(c.lo[a], c.hi[a], up);
        w = w * select(1.0 - c.fr[a], c.fr[a], up);
        if dense {
            row = row + term;
        } else {
            row = row ^ term;
        }
    }
    if !dense {
        row = row & hash_mask;
    }
    return Corner(row, w);
}
