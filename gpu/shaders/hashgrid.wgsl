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
// concatenates them, after `const DIMS: u32` and `const NF: u32`: one compiled variant per
// grid shape). Loops run to those constants, 2^DIMS * NF <= 128 iterations per invocation, so
// compilers unroll them, keep the accumulators in registers and issue a level's table reads
// together.

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

// The cell of one sample on one level, per axis (x, y, z, t): the lower corner's index term
// (dense: i * stride, hashed: i * prime), the upper corner's, and the fraction. Vector
// operations, no per-axis loop: private arrays with dynamic indices are slow on some drivers
// (lavapipe spills them). For a 3D grid the t terms are 0 and corners never set bit 3.
struct Cell {
    lo: vec4<u32>,
    hi: vec4<u32>,
    fr: vec4<f32>,
}

fn cell(lv: Level, p: vec4<f32>, dims: u32) -> Cell {
    // clamp01 per axis, NaN to 0 (as the CPU's `if x >= 0 { min(x, 1) } else { 0 }`).
    let x = select(vec4<f32>(0.0), min(p, vec4<f32>(1.0)), p >= vec4<f32>(0.0));
    let q = x * lv.scale + vec4<f32>(0.5);
    let i = floor(q);
    var c: Cell;
    c.fr = q - i;
    let iu = vec4<u32>(i);
    if lv.info.y == 1u {
        c.lo = iu * lv.stride;
        c.hi = c.lo + lv.stride;
    } else {
        let primes = vec4<u32>(1u, 2654435761u, 805459861u, 3674653429u);
        c.lo = iu * primes;
        c.hi = (iu + vec4<u32>(1u)) * primes;
    }
    if dims == 3u {
        c.lo.w = 0u;
        c.hi.w = 0u;
        c.fr.w = 0.0;
    }
    return c;
}

// Row (within the level) and weight of corner `k` (bit a set: upper corner on axis a). The
// weight is the product over axes in axis order, as on the CPU (times an exact 1 on t in 3D).
struct Corner {
    row: u32,
    w: f32,
}

fn corner(c: Cell, k: u32, dense: bool, hash_mask: u32) -> Corner {
    let up = vec4<bool>((k & 1u) != 0u, (k & 2u) != 0u, (k & 4u) != 0u, (k & 8u) != 0u);
    let t = select(c.lo, c.hi, up);
    let wv = select(vec4<f32>(1.0) - c.fr, c.fr, up);
    let w = ((wv.x * wv.y) * wv.z) * wv.w;
    var row = (t.x ^ t.y ^ t.z ^ t.w) & hash_mask;
    if dense {
        row = t.x + t.y + t.z + t.w;
    }
    return Corner(row, w);
}
