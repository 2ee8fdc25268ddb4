// Where a training step's samples go (`msth_core::pipeline`'s `place_proposal_samples`,
// `sample_pdf` and `place_samples`), as passes over the batch:
// - `place_samples`, one invocation per sample: its interval `(s_i, s_i+1)` in the normalised
//   ray coordinate (read from a level's edges, or, for the proposal level, the stratified edges
//   of `msth_core::sampling::uniform_edges`, one jitter per ray, written out), its distance
//   interval (the spacing function), `delta`, and its point `(x, y, z, t)` in the unit cube at
//   the interval's midpoint (the scene bounds' `to_unit`, contraction included);
// - `pdf_cdf`, one workgroup per ray (after `ray_scan.wgsl`, binding 1: the proposal level's
//   offsets): the annealed, padded proposal weights' running sums, normalised;
// - `pdf_sample`, one invocation per new edge: inverse-CDF resampling by bisection.
// Rays come from the host with their limits (`msth_core::pipeline::ray_limits`) and their two
// jitters (proposal edges, resampling) already drawn, so the device draws no random numbers.

struct Sampling {
    // x: rays, y: samples per ray of the level at hand (the proposal's for `pdf_cdf`, the new
    // level's for `pdf_sample`), z: flags (FLAG_*), w: the proposal's samples per ray.
    run: vec4<u32>,
    // x: the spacing unit, y: histogram padding, z: annealing exponent, w: 0.
    f: vec4<f32>,
    // Box: min (xyz); contracted: centre (xyz) and radius (w).
    b0: vec4<f32>,
    // Box: max (xyz).
    b1: vec4<f32>,
}

// One ray: origin and time, direction, and (near, far, proposal jitter, resampling jitter).
struct SampleRay {
    o: vec4<f32>,
    d: vec4<f32>,
    lim: vec4<f32>,
}

const FLAG_LINDISP: u32 = 1u;
const FLAG_CONTRACTED: u32 = 2u;
const FLAG_JITTER: u32 = 4u;
// `place_samples`: make the level's edges (uniform, jittered) instead of reading them.
const FLAG_UNIFORM_EDGES: u32 = 8u;
// `place_samples`: write each sample's unit direction.
const FLAG_DIRS: u32 = 16u;

@group(0) @binding(0) var<uniform> su: Sampling;

fn linear_index(gid: vec3<u32>, groups: vec3<u32>) -> u32 {
    return gid.x + gid.y * groups.x * 64u;
}

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

// `msth_core::sampling::Spacing::t_of_s`.
fn t_of_s(s: f32, near: f32, far: f32, spacing: u32, unit: f32) -> f32 {
    if spacing == 0u {
        return near + s * (far - near);
    }
    let a = g_fwd(near / unit);
    let b = g_fwd(far / unit);
    return unit * g_inv(a + s * (b - a));
}

// `msth_core::scene::SceneBounds::to_unit`.
fn to_unit(p: vec3<f32>, bounds: u32, b0: vec4<f32>, b1: vec4<f32>) -> vec3<f32> {
    if bounds == 0u {
        return clamp((p - b0.xyz) / (b1.xyz - b0.xyz), vec3<f32>(0.0), vec3<f32>(1.0));
    }
    let y = (p - b0.xyz) / b0.w;
    let a = abs(y);
    let n = max(a.x, max(a.y, a.z));
    var c = y;
    if n > 3.0e38 {
        c = sign(y) * 2.0;
    } else if n >= 1.0 {
        c = (2.0 - 1.0 / n) * (y / n);
    }
    return clamp((c + 2.0) * 0.25, vec3<f32>(0.0), vec3<f32>(1.0));
}
