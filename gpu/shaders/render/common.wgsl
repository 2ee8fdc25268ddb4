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
