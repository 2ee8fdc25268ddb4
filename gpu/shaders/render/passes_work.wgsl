// passes_work: what the per-sample passes share: the `Pass` uniform, the work buffer and its
// counters (bindings 7-10), and the helpers that read rays, samples and the live lists.

// #import common
// #import bindings
// #import camera
// #import passes_lanes

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
