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

// #import common
// #import io
// #import camera

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
