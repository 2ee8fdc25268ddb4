// WebGPU rendering with the native renderer's kernels: `shaders/render.wgsl` is a checked copy of
// the shader the wgpu player compiles, composed from the modules of `gpu/shaders/render/` (one
// source of truth, served to the page by `msth serve`). This module is
// the browser's host side of its bindings, a port of `gpu/src/layout.rs` as documented in
// `shaders/README.md`: the `Model` uniform (6496 bytes), the `View` uniform (112 bytes), the
// split of the flat parameter buffer into `tab3` (field.h3, then proposal.h3), `tab4` (field.h4,
// then proposal.h4) and `rest` (everything after the field's tables), and the 2D dispatch of
// 64-wide workgroups.
//
// Frames are rendered through the per-sample passes (`pass_*` entry points; the host side of
// `gpu/src/passes.rs`, documented in `shaders/README.md`): per batch of pixels, ray setup,
// proposal densities per sample, resampling per ray, main-field density per sample, visibility
// per ray, colour per visible sample and compositing per ray, each a dispatch over a compacted
// list sized on the GPU (indirect dispatch).
//
// The passes write (r, g, b, depth) per pixel to a storage buffer; a small display pass (below,
// not part of the renderer: it only copies that buffer to the canvas, clamped to [0, 1]) draws it.
//
// Reduced frames are interlaced: a frame at 1/s of the size per side renders the pixels of the
// full-size camera whose coordinates are multiples of s (one ray per s x s block, through the
// block's first pixel), and the display pass fills the pixels between them by bilinear
// interpolation.
// The pixels are ordered coarsest lattice first (`interlacedOrder`), so refining a still view
// from 1/8 to 1/4, 1/2 and full size renders only the pixels the coarser frames did not: the
// full-size frame costs one frame's work in all, not 1/64 + 1/16 + 1/4 + 1.

import {
  LEVEL_SLOTS, LEVEL_BYTES, LEVEL_OFFSETS, ENCODING_OFFSETS, GRID_OFFSETS, MODEL_BYTES, MODEL_OFFSETS, VIEW_BYTES, WORKGROUP,
  MAX_PROPOSAL_SAMPLES, MAX_SAMPLES, MAX_HIDDEN, MAX_GEO, RENDER_STATIC_CUTOFF, RENDER_HISTOGRAM_PADDING, BLEND, VISIBLE_TRANSMITTANCE,
  FRAME_WORK_BYTES, PASS_ARGS as ARGS, PASS_BYTES, PASS_OFFSETS, PASS_FLAGS, SAMPLE_LEVELS,
} from "./generated/contract.js";
import { requestGpu } from "./early.js";
import { specialiseWgsl } from "./specialise.js";

/**
 * GPU time a batch of rays aims at, where a frame takes longer than that (software GPUs; on a
 * hardware GPU a frame is one batch): new input abandons a frame between batches, and each
 * batch costs its dispatches' fixed overhead (about 9 ms of CPU per batch on SwiftShader, where
 * 50 ms batches made a 256x256 frame 1.2x slower than 200 ms ones: docs/playback.md).
 */
const TILE_MS = 200;

/** The visible depth `volume_march` writes for a ray that reached a brick the volume left out. */
const OUTSIDE_DEPTH = -2;

/** Points one `eval_points` dispatch evaluates at most (the volume's bake). */
const EVAL_BATCH = 1 << 18;

/** Lattice spacings of reduced frames (pixels per side of a block), finest first. */
export const STRIDES = [1, 2, 4, 8];

/**
 * The pixels of a w x h frame (row-major indices) ordered coarsest lattice first: the pixels
 * whose x and y are multiples of 8, then those of the multiples of 4 not yet listed, then of 2,
 * then the rest. `ends[s]` is the length of the prefix that holds the whole lattice of spacing s.
 */
export function interlacedOrder(w, h) {
  const ids = new Uint32Array(w * h);
  const ends = {};
  let k = 0;
  for (let j = STRIDES.length - 1; j >= 0; j--) {
    const s = STRIDES[j];
    const coarser = j + 1 < STRIDES.length ? STRIDES[j + 1] : 0;
    for (let y = 0; y < h; y += s) {
      for (let x = 0; x < w; x += s) {
        if (coarser && x % coarser === 0 && y % coarser === 0) continue;
        ids[k++] = y * w + x;
      }
    }
    ends[s] = k;
  }
  return { ids, ends };
}

const PASS_ENTRIES = [
  "pass_setup", "pass_args", "pass_live_proposal", "pass_proposal", "pass_proposal3", "pass_resample", "pass_live_samples",
  "pass_density", "pass_density3", "pass_visible", "pass_color", "pass_composite",
];
/**
 * The dispatches of one batch, in order: entry point, and the offset of its indirect size
 * (`null`: direct). With an occupancy grid (`live`, as passes.rs `render_passes`) the proposal
 * and density passes run over the samples `pass_live_proposal` and `pass_live_samples` list:
 * `pass_proposal` and `pass_density` over those the mask leaves a 4D lookup, `pass_proposal3`
 * and `pass_density3` (compiled without it) over the others.
 */
function passSteps(live) {
  const listed = (entry, pairs) => (live ? [[entry, pairs], ["pass_args", null]] : []);
  const only3 = (entry, at) => (live ? [[entry, at]] : []);
  return [
    ["pass_setup", null],
    ["pass_args", null],
    ...listed("pass_live_proposal", ARGS.proposalPairs),
    ["pass_proposal", ARGS.proposal],
    ...only3("pass_proposal3", ARGS.proposal3),
    ["pass_resample", ARGS.rays],
    ...listed("pass_live_samples", ARGS.samplePairs),
    ["pass_density", ARGS.samples],
    ...only3("pass_density3", ARGS.samples3),
    ["pass_visible", ARGS.rays],
    ["pass_args", null],
    ["pass_color", ARGS.color],
    ["pass_composite", ARGS.rays],
  ];
}
const PASS_STEPS = passSteps(false);
const PASS_STEPS_LIVE = passSteps(true);
/** The passes over the samples whose mask skips the 4D lookup: compiled after the others (the
 * first frames run without them), dispatched once ready, with `PASS_FLAGS.split`. */
const PASS_ENTRIES_3D = ["pass_proposal3", "pass_density3"];
const PASS_STEPS_UNSPLIT = PASS_STEPS_LIVE.filter(([name]) => !PASS_ENTRIES_3D.includes(name));

/**
 * Word offsets of the `work` regions for `rays` rays of `samples` samples (passes.rs `regions`,
 * frame batches): rays, hist, edges, samp, geo, clist, then the live lists plist and slist;
 * and the words they take.
 */
export function passRegions(np, geo, rays, samples) {
  let at = 0;
  const take = (words) => {
    const o = at;
    at += Math.ceil(words / 4) * 4;
    return o;
  };
  const r = [take(4 * rays), take(np * rays), take((samples + 1) * rays), take(4 * samples * rays), take(geo * samples * rays), take(samples * rays)];
  const lists = [take(np * rays), take(samples * rays)];
  return { offsets: r, lists, words: Math.max(at, 4) };
}

/** Words of `work` per ray of a frame batch (passes.rs `words_per_ray`). */
function wordsPerRay(np, geo, samples) {
  return 4 + np + (samples + 1) + samples * (4 + geo + 1) + 16 + np + samples;
}

/** The browser has no usable WebGPU (the page says so instead of rendering). */
/**
 * Proposal and main samples per ray for `spec` and a model's `sampler`, as `msth play --samples`
 * (msth_core::config::PlaySamples): `file` (the file's `play_samples`, `stored`, or the model's
 * counts when it stores none), a level of SAMPLE_LEVELS (`full`, `fast`, `faster`: a fraction of
 * the model's counts, rounded up) or `P,M`; null when `spec` is none of these.
 */
export function playSamples(spec, sampler, stored = null) {
  if (spec === "file") return stored ? [stored.proposal, stored.main] : [sampler.num_proposal_samples, sampler.num_samples];
  if (Object.hasOwn(SAMPLE_LEVELS, spec ?? "")) {
    const [[pn, pd], [mn, md]] = SAMPLE_LEVELS[spec];
    const scale = (n, num, den) => Math.max(1, Math.ceil((n * num) / den));
    return [scale(sampler.num_proposal_samples, pn, pd), scale(sampler.num_samples, mn, md)];
  }
  const m = /^\s*\+?(\d+)\s*,\s*\+?(\d+)\s*$/.exec(spec ?? "");
  if (!m) return null;
  const [p, n] = [Number(m[1]), Number(m[2])];
  return p >= 1 && n >= 1 ? [p, n] : null;
}

export class NoWebGpu extends Error {}

const DISPLAY_WGSL = `
// s: the lattice spacing of the frame (1: every pixel rendered). Each pixel shows the bilinear
// interpolation of the four rendered pixels around it (the lattice points at multiples of s;
// past the last one in a row or column, that one's value), so a reduced frame looks smooth
// rather than blocky; at s = 1 a pixel shows its own value. While a frame is still being
// rendered (batch by batch on a slow GPU), the lattice of spacing s is rendered in the rows
// above size.rows only: below, the pixels show the complete lattice of spacing size.coarse (when
// there is one) instead of what an older frame left in the buffer (displayUniform).
struct Size { w: u32, h: u32, s: u32, coarse: u32, rows: u32, pad0: u32, pad1: u32, pad2: u32 }
@group(0) @binding(0) var<storage, read> frame: array<vec4<f32>>;
@group(0) @binding(1) var<uniform> size: Size;
@vertex fn vs(@builtin(vertex_index) i: u32) -> @builtin(position) vec4<f32> {
  let p = vec2<f32>(f32((i << 1u) & 2u), f32(i & 2u));
  return vec4<f32>(p * 2.0 - 1.0, 0.0, 1.0);
}
fn rgb(x: u32, y: u32) -> vec3<f32> {
  return frame[y * size.w + x].rgb;
}
// Pixel p of the lattice of spacing s filled in.
fn fill(p: vec2<u32>, s: u32) -> vec3<f32> {
  if s == 1u {
    return rgb(p.x, p.y);
  }
  let last = (vec2<u32>(size.w, size.h) - 1u) / s * s;
  let p0 = min(p / s * s, last);
  let p1 = min(p0 + s, last);
  let f = select(vec2<f32>(p - p0) / f32(s), vec2<f32>(0.0), p1 == p0);
  let top = mix(rgb(p0.x, p0.y), rgb(p1.x, p0.y), f.x);
  let bottom = mix(rgb(p0.x, p1.y), rgb(p1.x, p1.y), f.x);
  return mix(top, bottom, f.y);
}
@fragment fn fs(@builtin(position) pos: vec4<f32>) -> @location(0) vec4<f32> {
  let s = max(size.s, 1u);
  let p = min(vec2<u32>(pos.xy), vec2<u32>(size.w, size.h) - 1u);
  // The lower of the two lattice rows this pixel reads.
  let below = min(min(p.y / s * s, (size.h - 1u) / s * s) + s, (size.h - 1u) / s * s);
  let st = select(s, size.coarse, size.coarse != 0u && below >= size.rows);
  return vec4<f32>(clamp(fill(p, st), vec3<f32>(0.0), vec3<f32>(1.0)), 1.0);
}`;

/**
 * The display pass's uniform (`Size` in DISPLAY_WGSL) for a w x h frame of lattice spacing
 * `stride` of which the first `k` entries of the pixel order (`interlacedOrder`'s `ids` and
 * `ends`) are rendered: the lattice rendered so far in the rows above `rows` and the finest
 * complete coarser one (`coarse`, 0 when none is) below them. The order lists a lattice's
 * pixels row by row, so the rows above the first pixel not yet rendered are complete.
 */
export function displayUniform(w, h, ids, ends, stride, k) {
  if (k >= ends[stride]) return new Uint32Array([w, h, stride, 0, h, 0, 0, 0]);
  const coarse = STRIDES.find((t) => t > stride && ends[t] <= k) ?? 0;
  const fine = coarse ? coarse / 2 : STRIDES[STRIDES.length - 1];
  return new Uint32Array([w, h, fine, coarse, Math.floor(ids[k] / w), 0, 0, 0]);
}

/**
 * The `Model` uniform and the parameter split of a model (layout.rs `GpuModel::new`). `layout`
 * is format.js's `modelLayout(model)`. Throws with the limit a model exceeds.
 */
export function gpuModel(cfg, layout) {
  const check = (what, v, max) => {
    if (v > max) throw new Error(`${what} is ${v}; the GPU renderer supports at most ${max}`);
  };
  check("sampler.num_proposal_samples", cfg.sampler.num_proposal_samples, MAX_PROPOSAL_SAMPLES);
  check("sampler.num_samples", cfg.sampler.num_samples, MAX_SAMPLES);
  check("field.density_hidden", cfg.field.density_hidden, MAX_HIDDEN);
  check("field.color_hidden", cfg.field.color_hidden, MAX_HIDDEN);
  check("proposal.hidden", cfg.proposal.hidden, MAX_HIDDEN);
  check("field.geo_features", cfg.field.geo_features, MAX_GEO);
  const fe = layout.field.encoding;
  const tab3 = fe.h3 ? [fe.h3.start, fe.h3.end] : [0, 0];
  const tab4 = fe.h4 ? [fe.h4.start, fe.h4.end] : [0, 0];
  const rest0 = Math.max(tab3[1], tab4[1]);
  const pe = layout.proposal.encoding;
  const prop3 = pe.h3 ? [pe.h3.start, pe.h3.end] : [0, 0];
  const prop4 = pe.h4 ? [pe.h4.start, pe.h4.end] : [0, 0];
  // What the tab3 and tab4 buffers hold (layout.rs `ParamSplit::tables`): [value index in the
  // buffer, params range] for the field's table (at 0) and the proposal field's (after it, from
  // an even index: the kernels read the tables in pairs).
  const after = (r) => 2 * Math.ceil((r[1] - r[0]) / 2);
  const tables = [
    [[0, tab3], [after(tab3), prop3]],
    [[0, tab4], [after(tab4), prop4]],
  ];
  const split = { tab3, tab4, prop3, prop4, tables, rest: [rest0, layout.total] };
  for (const s of [fe.mask, layout.field.density, layout.field.color, layout.proposal.density, layout.proposal.encoding.h3, layout.proposal.encoding.h4, layout.proposal.encoding.mask]) {
    if (s && s.start < rest0) throw new Error("a parameter lies before the field's hash tables; the GPU renderer cannot split this layout");
  }

  const buf = new ArrayBuffer(MODEL_BYTES);
  const u = new Uint32Array(buf);
  const f = new Float32Array(buf);
  // Word offsets of the struct members (the generated contract's byte offsets / 4).
  const M = Object.fromEntries(Object.entries(MODEL_OFFSETS).map(([k, v]) => [k, v / 4]));
  const [SAMPLER, LIMITS, BOUNDS_A, BOUNDS_B, BACKGROUND, DENSITY, COLOR, PROPOSAL] = [M.sampler, M.limits, M.boundsA, M.boundsB, M.background, M.density, M.color, M.proposal];
  const [FIELD, PROP, LEVELS] = [M.field, M.prop, M.levels];
  const LV = { scale: LEVEL_OFFSETS.scale / 4, stride: LEVEL_OFFSETS.stride / 4, info: LEVEL_OFFSETS.info / 4, words: LEVEL_BYTES / 4 };
  const EN = { mode: ENCODING_OFFSETS.mode / 4, dims: ENCODING_OFFSETS.dims / 4, consts: ENCODING_OFFSETS.consts / 4, h3: ENCODING_OFFSETS.h3 / 4, h4: ENCODING_OFFSETS.h4 / 4 };
  const GR = { shape: GRID_OFFSETS.shape / 4, loc: GRID_OFFSETS.loc / 4 };
  const s = cfg.sampler;
  const b = cfg.bounds;
  u.set([s.num_proposal_samples, s.num_samples, s.spacing === "lin_disp" ? 1 : 0, b.kind === "contracted" ? 1 : 0], SAMPLER);
  // The padding rendering resamples with (msth_core::pipeline::render_histogram_padding).
  const padding = Math.min(s.histogram_padding, RENDER_HISTOGRAM_PADDING);
  f.set([s.near, s.far, padding, b.kind === "contracted" ? b.radius : 1], LIMITS);
  if (b.kind === "box") {
    f.set([...b.min, 0], BOUNDS_A);
    f.set([...b.max, 0], BOUNDS_B);
  } else {
    f.set([...b.center, b.radius], BOUNDS_A);
  }
  const bg = cfg.background;
  f.set(bg.kind === "color" ? [...bg.rgb, 1] : [0, 0, 0, 0], BACKGROUND);
  const rel = (r) => r.start - rest0;
  const d = layout.field.density;
  const p = layout.proposal.density;
  // The MLPs' rows of the uniform and their weights' ranges relative to `rest` (`specialise.js`
  // reads them, and the uniform's levels).
  const mlps = {
    proposal: [rel(p), p.dims[0], p.dims[1]],
    density: [rel(d), d.dims[0], d.dims[1], d.dims[2]],
    color: [rel(layout.field.color), cfg.field.color_hidden, cfg.field.color_layers, cfg.field.geo_features],
    ranges: [p, d, layout.field.color].map((r) => [r.start - rest0, r.end - rest0]),
  };
  u.set(mlps.density, DENSITY);
  u.set(mlps.color, COLOR);
  u.set([...mlps.proposal, 0], PROPOSAL);

  let nextSlot = 0;
  const grid = (g, buffer, base, at) => {
    if (!g) return; // zeros: not present
    const first = nextSlot;
    if (first + g.levels.length > LEVEL_SLOTS) throw new Error("too many grid levels for the GPU renderer");
    g.levels.forEach((lv, k) => {
      const o = LEVELS + LV.words * (first + k);
      f.set([...lv.scale, 0, 0, 0, 0].slice(0, 4), o + LV.scale);
      u.set(lv.stride.slice(0, 4), o + LV.stride);
      u.set([base + lv.offset, lv.dense ? 1 : 0, lv.rows, 0], o + LV.info);
    });
    nextSlot += g.levels.length;
    u.set([g.dims, g.features, g.levels.length, g.tableSize - 1], at + GR.shape);
    u.set([buffer, first, 1, 0], at + GR.loc);
  };
  // `bases`: where the encoding's 3D and 4D tables start in the tab3 and tab4 buffers.
  const encoding = (e, bases, at) => {
    grid(e.h3, 0, bases[0], at + EN.h3);
    grid(e.h4, 1, bases[1], at + EN.h4);
    u.set(e.mask ? [BLEND[e.blend], 1, e.mask.res, e.mask.start - rest0] : [BLEND[e.blend], 0, 0, 0], at + EN.mode);
    u.set([e.outDim, 0, 0, 0], at + EN.dims);
    const noMask = e.blend === "static" ? 1 : e.blend === "four_d" ? 0 : 0.5;
    f.set([noMask, RENDER_STATIC_CUTOFF, 0, 0], at + EN.consts);
  };
  encoding(fe, [0, 0], FIELD);
  encoding(pe, [tables[0][1][0], tables[1][1][0]], PROP);
  return { uniform: buf, split, mlps };
}

/** The `View` uniform for `cam` (camera.js) at time `t`, `count` invocations, `flags`. */
export function viewUniform(cam, t, count, flags = 0) {
  const buf = new ArrayBuffer(VIEW_BYTES);
  const f = new Float32Array(buf);
  const u = new Uint32Array(buf);
  f.set(cam.m, 0);
  f.set([cam.fx, cam.fy, cam.cx, cam.cy], 16);
  u.set([cam.width, cam.height, count, flags], 20);
  f.set([t, 0, 0, 0], 24);
  return buf;
}

/** Workgroups `[x, y]` for `count` invocations, `x` at most `maxPerDim` (layout.rs). */
export function dispatchSize(count, maxPerDim) {
  const groups = Math.max(1, Math.ceil(count / WORKGROUP));
  const x = Math.min(groups, maxPerDim);
  const y = Math.ceil(groups / x);
  return y <= maxPerDim ? [x, y] : null;
}

/**
 * `source` (a `render.wgsl`) with its "Hash tables" region replaced by `region`
 * (`shaders/tables_f16.wgsl`): the kernels then read binary16 tables (msth-gpu
 * `TableFormat::source`).
 */
export function tablesSource(source, region) {
  const begin = source.indexOf("// ---- Hash tables: begin");
  const endMark = "// ---- Hash tables: end ----\n";
  const end = begin < 0 ? -1 : source.indexOf(endMark, begin);
  if (end < 0) throw new Error("render.wgsl has no \"Hash tables\" region");
  return source.slice(0, begin) + region + source.slice(end + endMark.length);
}

/**
 * `values` (a Float32Array) as the binary16 table words the kernels read (msth-gpu
 * `TableFormat::F16`): clamped to ±65504, rounded to nearest (ties to even), results below
 * 2^-14 in magnitude flushed to a zero of the same sign, an odd count padded with one 0.
 * Returns the Uint16Array of the bits (by hand rather than `Float16Array`, which older
 * browsers and node 20 lack; `tests/tests/web_specialise.rs` checks it against the Rust
 * encoder), with the count of values the clamp changed as its `clamped` property
 * (`TableFormat::clamped`).
 */
export function toBinary16(values) {
  const n = values.length;
  const out = new Uint16Array(n + (n & 1));
  const f = new Float32Array(1);
  const u = new Uint32Array(f.buffer);
  const smallest = 2 ** -14 - 2 ** -25; // at or above: rounds to 2^-14, the least normal
  let clamped = 0;
  for (let i = 0; i < n; i++) {
    const v = values[i];
    if (v > 65504 || v < -65504) clamped++;
    f[0] = v > 65504 ? 65504 : v < -65504 ? -65504 : v;
    const x = u[0];
    const sign = (x >>> 16) & 0x8000;
    const exp = (x >>> 23) & 0xff;
    const mant = x & 0x7fffff;
    let h;
    if (exp === 0xff) {
      h = sign | 0x7e00; // NaN (no infinity after the clamp)
    } else if (exp <= 112) {
      h = Math.abs(f[0]) >= smallest ? sign | 0x0400 : sign;
    } else {
      let e = exp - 112;
      let m = mant >>> 13;
      const rest = mant & 0x1fff;
      if (rest > 0x1000 || (rest === 0x1000 && (m & 1) === 1)) {
        m += 1;
        if (m === 0x400) {
          m = 0;
          e += 1;
        }
      }
      h = sign | (e << 10) | m;
    }
    out[i] = h;
  }
  out.clamped = clamped;
  return out;
}

/** A WebGPU device and the compiled kernels; `create` binds them to a canvas and a model. */
export class Renderer {
  /**
   * Requests an adapter and device and fetches the WGSL; throws `NoWebGpu` without WebGPU. The
   * page starts both before its other modules load (early.js): this takes them over, or makes
   * them where that did not run.
   */
  static async adapter() {
    const early = globalThis.msthEarlyGpu;
    globalThis.msthEarlyGpu = undefined;
    const { adapter, device, error, shaders } = await (early ?? requestGpu());
    if (error) throw new NoWebGpu(error);
    const [source, tablesF16, volume] = await shaders;
    return new Renderer(adapter, device, source, tablesF16, volume);
  }

  constructor(adapter, device, source, tablesF16, volume = null) {
    this.adapter = adapter;
    this.device = device;
    this.source = source;
    /** The region of `render.wgsl` that holds the hash tables as binary16 (`tablesSource`). */
    this.tablesF16 = tablesF16;
    /** `volume.wgsl`: the march through the play-time volume (`GpuScene.setVolume`). */
    this.volumeSource = volume;
    this.lost = null;
    device.lost.then((info) => {
      this.lost = `the GPU device was lost: ${info.message || info.reason}`;
    });
  }

  /** One explicit layout for every entry point (web/shaders/README.md, "Bindings"). */
  #layouts() {
    if (!this.bindLayout) {
      const C = GPUShaderStage.COMPUTE;
      const kinds = ["uniform", "uniform", "read-only-storage", "read-only-storage", "read-only-storage", "read-only-storage", "storage", "storage", "storage", "uniform", "read-only-storage"];
      this.bindLayout = this.device.createBindGroupLayout({
        label: "msth render bindings",
        entries: kinds.map((type, binding) => ({ binding, visibility: C, buffer: { type } })),
      });
      this.pipelineLayout = this.device.createPipelineLayout({ bindGroupLayouts: [this.bindLayout] });
    }
    return { bindLayout: this.bindLayout, pl: this.pipelineLayout };
  }

  /**
   * The module of `code` and the pipelines of the passes a first frame needs, or an Error saying
   * what the device refused. The error scope is pushed and popped around the synchronous calls
   * alone, so that a build in the background (`kernelsReady`) cannot take the place of a batch's
   * scope. `marks.module`: when the WGSL compiled.
   */
  async #build(code, marks) {
    const device = this.device;
    const { pl } = this.#layouts();
    const names = PASS_ENTRIES.filter((n) => !PASS_ENTRIES_3D.includes(n));
    let module = null;
    let made = null;
    device.pushErrorScope("validation");
    const make = (entryPoint) => device.createComputePipelineAsync({ layout: pl, compute: { module, entryPoint } });
    try {
      module = device.createShaderModule({ code, label: "render.wgsl" });
      made = Promise.all(names.map(make));
    } catch (e) {
      made = Promise.reject(e);
    }
    const scope = device.popErrorScope();
    made.catch(() => {});
    let failure = null;
    try {
      const info = await module?.getCompilationInfo();
      const errors = (info?.messages ?? []).filter((m) => m.type === "error");
      if (errors.length) failure = errors.map((m) => `${m.lineNum}:${m.linePos} ${m.message}`).join("; ");
      else marks.module ??= performance.now();
      const pipelines = {};
      if (!failure) {
        const all = await made;
        names.forEach((n, i) => (pipelines[n] = all[i]));
      }
      const err = await scope;
      failure ??= err && err.message;
      if (failure) throw new Error(failure);
      /** The `eval_points` pipeline (the play-time volume's bake), compiled when first asked. */
      pipelines.evalPoints = () => make("eval_points");
      // Compiled once asked (after the first picture); a refusal only leaves them out.
      pipelines.later = () =>
        Promise.all(PASS_ENTRIES_3D.map(make)).then(
          (m) => Object.fromEntries(PASS_ENTRIES_3D.map((n, i) => [n, m[i]])),
          () => null,
        );
      return pipelines;
    } catch (e) {
      throw new Error(`render.wgsl: ${failure ?? e.message}`);
    }
  }

  /** The WGSL of the generic kernels with hash tables held as `tables` (`"f32"` or `"f16"`). */
  #source(tables) {
    if (tables !== "f32" && tables !== "f16") throw new Error(`hash tables ${tables}: f32 or f16`);
    return tables === "f16" ? tablesSource(this.source, this.tablesF16) : this.source;
  }

  /**
   * Starts compiling the generic kernels for hash tables held as `tables`, before the model's
   * MLP section has arrived (the first picture comes from them; `create` takes them over).
   */
  compileGeneric(tables, marks = {}) {
    if (this.generic?.tables !== tables) {
      // A `tables` that is neither rejects the promise (`create` says so for the same value).
      const promise = Promise.resolve().then(() => this.#build(this.#source(tables), marks));
      promise.catch(() => {});
      this.generic = { tables, promise };
    }
    return this.generic.promise;
  }

  /**
   * Binds the kernels to `canvas` for a model (`cfg` its config, `layout` format.js's). `marks`,
   * when given, receives `module` (ms since navigation start: the WGSL compiled),
   * `pipelines` (the first picture's pipelines created) and `specialised` (the kernels compiled
   * for the model in use). `params`, when given, is the parameter buffer with at least the MLP
   * section decoded: the passes' encodings and MLPs are then compiled with the model's level
   * values and weights as constants (`specialise.js`), unless `?mlp=generic` or the model's MLPs
   * are too large; `mlpNote` on the scene says which. `tables`: `"f32"` or `"f16"`, how the
   * device holds the hash tables (msth-gpu `TableFormat`); `tables` on the scene says what it
   * got.
   *
   * The kernels compiled for the model take two to three times as long to compile as the generic
   * ones (a software adapter on two cores: 3.5-5 s against 1.4-1.7 s), so the first picture
   * comes from the generic ones and the others replace them once compiled (`kernelsReady`; the
   * frames are the same, web_player.rs checks both). `?kernels=wait` compiles them first.
   */
  async create(canvas, cfg, layout, marks = {}, params = null, tables = "f32") {
    const { uniform, split, mlps } = gpuModel(cfg, layout);
    const query = typeof location !== "undefined" ? new URLSearchParams(location.search) : new URLSearchParams();
    const source = this.#source(tables);
    let code = source;
    let mlpNote = "generic kernels";
    if (query.get("mlp") === "generic") mlpNote = "generic kernels (?mlp=generic)";
    else if (params) {
      try {
        code = specialiseWgsl(source, { mlps, uniform }, params.subarray(split.rest[0]));
        mlpNote = "kernels compiled for this model";
      } catch (e) {
        mlpNote = `generic kernels (${e.message})`;
      }
    }
    const { bindLayout } = this.#layouts();
    const later = PASS_ENTRIES_3D;
    const specialised = code !== source;
    const deferred = specialised && query.get("kernels") !== "wait";
    let pipelines;
    let pending = null;
    if (deferred || !specialised) {
      pipelines = await this.compileGeneric(tables, marks);
      if (deferred) {
        pending = code;
        mlpNote = "generic kernels until the kernels compiled for this model are ready";
      }
    } else {
      try {
        pipelines = await this.#build(code, marks);
      } catch (e) {
        // Kernels compiled for the model that the device refuses: the generic ones, and why.
        if (this.lost) throw e;
        mlpNote = `generic kernels (compiling them for the model failed: ${e.message})`;
        pipelines = await this.compileGeneric(tables, marks);
      }
    }
    // The scene's own table: `kernelsReady` and `compileLater` write into it.
    pipelines = { ...pipelines };
    marks.pipelines = performance.now();
    const scene = new GpuScene(this, canvas, { layout: bindLayout, pipelines }, uniform, { ...split, f16: tables === "f16" }, cfg);
    /** How the passes run the MLPs (compiled for the model, or generic and why). */
    scene.mlpNote = mlpNote;
    /** Called with the new `mlpNote` when the kernels compiled for the model replace the generic
     * ones, or fail to. */
    scene.onKernels = null;
    const setNote = (note) => {
      scene.mlpNote = note;
      scene.onKernels?.(note);
    };
    /** Whether the kernels compiled for the model are still to come (`kernelsReady`). */
    scene.kernelsPending = deferred;
    let better = null;
    /** Compiles the kernels for the model when the first picture came from the generic ones
     * (once), and uses them from the next batch on; resolves when they are in use or refused. */
    scene.kernelsReady = () =>
      (better ??= (async () => {
        if (!pending || this.lost) return;
        try {
          Object.assign(pipelines, await this.#build(pending, {}));
          marks.specialised = performance.now();
          setNote("kernels compiled for this model");
        } catch (e) {
          setNote(`generic kernels (compiling them for the model failed: ${e.message})`);
        }
        scene.kernelsPending = false;
      })());
    let ready = null;
    /** Compiles what the first picture did without (once; the page asks after its first picture,
     * so that the compile does not delay it) and uses it from the next batch on: the kernels
     * compiled for the model, then `pass_proposal3` and `pass_density3` from the same module. */
    scene.compileLater = () =>
      (ready ??= scene.kernelsReady().then(async () => {
        const more = await pipelines.later();
        if (more && later.length) {
          Object.assign(pipelines, more);
          scene.split3 = true;
          marks.passes3 = performance.now();
        }
      }));
    // `?split=wait`: the first frame waits for them (tests, benchmarks).
    if (query.get("split") === "wait") await scene.compileLater();
    /** How the device holds the hash tables: `"f32"` or `"f16"`. */
    scene.tables = tables;
    return scene;
  }
}

class GpuScene {
  constructor(r, canvas, kernels, modelUniform, split, cfg) {
    const device = r.device;
    this.r = r;
    this.device = device;
    this.canvas = canvas;
    this.kernels = kernels;
    this.split = split;
    /** Whether `pass_proposal3` and `pass_density3` are compiled (the live lists then put the
     * samples without a 4D lookup apart for them). */
    this.split3 = false;
    /** Whether the last batch rendered used them. */
    this.lastSplit3 = false;
    this.np = cfg.sampler.num_proposal_samples;
    this.samples = cfg.sampler.num_samples;
    this.geo = cfg.field.geo_features;
    const limit = device.limits.maxStorageBufferBindingSize;
    const buffer = (bytes, usage, label) => {
      if (bytes > limit) throw new Error(`${label} needs ${bytes} bytes, more than this GPU's storage buffer limit ${limit}`);
      return device.createBuffer({ size: Math.max(4, Math.ceil(bytes / 4) * 4), usage, label });
    };
    const len = (r) => r[1] - r[0];
    const S = GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST;
    // Both fields' tables, read in pairs: f32 in whole `vec2<f32>` pairs, binary16 in whole
    // words (two values each); at least one (layout.rs `TableFormat::buffer_bytes`).
    const pairs = (parts) => (split.f16 ? 4 : 8) * Math.max(1, Math.ceil(Math.max(...parts.map(([at, r]) => at + len(r))) / 2));
    this.tab3 = buffer(pairs(split.tables[0]), S, "3D hash tables (tab3)");
    this.tab4 = buffer(pairs(split.tables[1]), S, "4D hash tables (tab4)");
    this.rest = buffer(4 * len(split.rest), S, "decoders, mask and proposal field (rest)");
    this.model = device.createBuffer({ size: modelUniform.byteLength, usage: GPUBufferUsage.UNIFORM | GPUBufferUsage.COPY_DST, label: "Model" });
    device.queue.writeBuffer(this.model, 0, modelUniform);
    this.view = device.createBuffer({ size: VIEW_BYTES, usage: GPUBufferUsage.UNIFORM | GPUBufferUsage.COPY_DST, label: "View" });
    this.size = device.createBuffer({ size: 32, usage: GPUBufferUsage.UNIFORM | GPUBufferUsage.COPY_DST, label: "display size" });
    this.pass = device.createBuffer({ size: PASS_BYTES, usage: GPUBufferUsage.UNIFORM | GPUBufferUsage.COPY_DST, label: "Pass" });
    const small = (usage, label) => device.createBuffer({ size: ARGS.bytes, usage, label });
    this.ctrl = small(GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST | GPUBufferUsage.COPY_SRC, "pass counters");
    this.args = small(GPUBufferUsage.STORAGE | GPUBufferUsage.INDIRECT, "pass dispatch sizes");
    /** The file's occupancy grid (`setOccupancy`); a placeholder and resolution 0 without one. */
    this.noOccupancy = small(GPUBufferUsage.STORAGE, "no occupancy grid");
    this.occupancy = this.noOccupancy;
    this.occupancyResolution = 0;
    this.storageLimit = limit;
    this.context = canvas.getContext("webgpu");
    this.format = navigator.gpu.getPreferredCanvasFormat();
    this.context.configure({ device, format: this.format, alphaMode: "opaque" });
    const dmod = device.createShaderModule({ code: DISPLAY_WGSL, label: "display" });
    this.display = device.createRenderPipeline({
      layout: "auto",
      vertex: { module: dmod, entryPoint: "vs" },
      fragment: { module: dmod, entryPoint: "fs", targets: [{ format: this.format }] },
      primitive: { topology: "triangle-list" },
    });
    this.frameSize = null;
    /** The sample counts changed (`setSamples`): the next frame sizes its buffers anew. */
    this.stale = false;
    /** The static cache (`buildStaticCache`): its probe frame, its dynamic pixels and their
     * count (-1: no cache). */
    this.probeFrame = null;
    this.dynOrder = null;
    this.dynamicCount = -1;
    /** Rays per millisecond of the last batch (the measured rate the page plans with). */
    this.raysPerMs = 0;
    /** Rays per batch (adapted after each). */
    this.tile = 4096;
    this.work = null;
    this.capacity = 0;
    this.profile = typeof location !== "undefined" && new URLSearchParams(location.search).get("profile") === "1";
    /** With `?profile=1`: milliseconds spent per entry point, summed over frames. */
    this.passMs = {};
    /** With `?profile=1`: the sizes of the passes' lists, summed over batches (passes.rs
     * `PassCounts`): rays, colour, and the live proposal and main samples with (`proposal4`,
     * `samples4`) and without (`proposal3`, `samples3`) a 4D lookup. */
    this.passCounts = {};
    /** Rays rendered so far, all frames together. */
    this.rays = 0;
  }

  /**
   * Renders with `np` proposal and `samples` main samples per ray from the next frame on (the
   * page's samples menu); the frame buffers are sized anew, so the next frame is drawn whole.
   */
  setSamples(np, samples) {
    if (np > MAX_PROPOSAL_SAMPLES || samples > MAX_SAMPLES || np < 1 || samples < 1) {
      throw new Error(`samples ${np},${samples}: the GPU renderer supports 1..${MAX_PROPOSAL_SAMPLES} proposal and 1..${MAX_SAMPLES} main samples per ray`);
    }
    if (np === this.np && samples === this.samples) return;
    this.np = np;
    this.samples = samples;
    this.device.queue.writeBuffer(this.model, MODEL_OFFSETS.sampler, new Uint32Array([np, samples]));
    this.stale = true;
  }

  /** Sizes the frame buffers for w x h; true when they were (re)created (their content lost). */
  #ensureFrame(w, h) {
    if (!this.stale && this.frameSize && this.frameSize[0] === w && this.frameSize[1] === h) return false;
    this.stale = false;
    const device = this.device;
    this.frame?.destroy();
    this.readback?.destroy();
    const bytes = w * h * 16;
    this.frame = device.createBuffer({ size: bytes, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_SRC, label: "frame" });
    this.readback = device.createBuffer({ size: bytes, usage: GPUBufferUsage.MAP_READ | GPUBufferUsage.COPY_DST, label: "readback" });
    this.order?.destroy();
    this.work?.destroy();
    this.work = null;
    // The static cache belongs to the frame it was built on.
    this.probeFrame?.destroy();
    this.dynOrder?.destroy();
    this.probeFrame = null;
    this.dynOrder = null;
    this.dynamicCount = -1;
    // The pixel list of every frame: coarsest lattice first (each batch or tile renders a range).
    const { ids, ends } = interlacedOrder(w, h);
    this.order = device.createBuffer({ size: 4 * w * h, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST, label: "pixel order" });
    device.queue.writeBuffer(this.order, 0, ids);
    this.orderEnds = ends;
    this.orderIds = ids;
    // Scratch of one batch: as many rays as fit FRAME_WORK_BYTES and the binding limit.
    const rayBytes = 4 * wordsPerRay(this.np, this.geo, this.samples);
    const fit = Math.floor(Math.min(FRAME_WORK_BYTES, this.storageLimit) / rayBytes);
    if (fit < 1) throw new Error(`one ray's scratch needs ${rayBytes} bytes, more than this GPU's storage buffer limit ${this.storageLimit}`);
    this.capacity = Math.min(w * h, fit);
    const reg = passRegions(this.np, this.geo, this.capacity, this.samples);
    this.regions = reg.offsets;
    this.lists = reg.lists;
    this.work = device.createBuffer({ size: 4 * reg.words, usage: GPUBufferUsage.STORAGE, label: "work" });
    this.displayBind = device.createBindGroup({
      layout: this.display.getBindGroupLayout(0),
      entries: [
        { binding: 0, resource: { buffer: this.frame } },
        { binding: 1, resource: { buffer: this.size } },
      ],
    });
    this.frameSize = [w, h];
    this.groups = null;
    if (this.canvas.width !== w || this.canvas.height !== h) {
      this.canvas.width = w;
      this.canvas.height = h;
    }
    return true;
  }

  /**
   * Uses the file's occupancy grid (format.js `readOccupancy`: `{ resolution, words }`), or none
   * (`null`: a version-1 file, or skipping off): the per-sample passes then evaluate the main
   * field only at samples in occupied cells, as the native renderers do.
   */
  setOccupancy(grid) {
    if (this.occupancy !== this.noOccupancy) this.occupancy.destroy();
    this.occupancy = this.noOccupancy;
    this.occupancyResolution = 0;
    if (grid) {
      const bytes = grid.words.byteLength;
      if (bytes > this.storageLimit) throw new Error(`the occupancy grid needs ${bytes} bytes, more than this GPU's storage buffer limit ${this.storageLimit}`);
      this.occupancy = this.device.createBuffer({ size: Math.max(16, Math.ceil(bytes / 16) * 16), usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST, label: "occupancy grid" });
      this.device.queue.writeBuffer(this.occupancy, 0, grid.words.buffer, grid.words.byteOffset, bytes);
      this.occupancyResolution = grid.resolution;
    }
    this.groups = null;
  }

  /**
   * Uploads the flat parameter buffer (a Float32Array of `param_count` values). `only4d`: the
   * caller promises that only the field's 4D table differs from the last upload (another time
   * chunk of the same file: `format.js` `applyChunk` writes nothing else), so only that table is
   * converted and sent, as the native renderer does (`GpuScene::update`).
   */
  setParams(params, only4d = false) {
    const q = this.device.queue;
    const put = (buf, at, [a, b]) => {
      if (b > a) q.writeBuffer(buf, 4 * at, params.buffer, params.byteOffset + 4 * a, 4 * (b - a));
    };
    // Per table buffer and part, the values the binary16 clamp changed in the last upload.
    this.clampedParts ??= [[0, 0], [0, 0]];
    const putTable = (buf, b, p) => {
      const [at, [lo, hi]] = this.split.tables[b][p];
      if (hi <= lo) return;
      if (!this.split.f16) return put(buf, at, [lo, hi]);
      const h = toBinary16(params.subarray(lo, hi));
      this.clampedParts[b][p] = h.clamped;
      q.writeBuffer(buf, 2 * at, h.buffer, 0, h.byteLength);
    };
    if (only4d) {
      putTable(this.tab4, 1, 0);
    } else {
      for (const p of [0, 1]) putTable(this.tab3, 0, p);
      for (const p of [0, 1]) putTable(this.tab4, 1, p);
      put(this.rest, 0, this.split.rest);
    }
    /** The most hash-table values held clamped at once (binary16: beyond ±65504, read as
     * ±65504; msth-gpu `GpuScene::clamped_table_values`). */
    this.clampedTables = Math.max(this.clampedTables ?? 0, this.clampedParts.flat().reduce((x, y) => x + y, 0));
  }

  /**
   * Renders `cam` at time `t` to the canvas; resolves when the GPU has finished, to `true`, or
   * to `false` when `abort()` (checked between tiles) asked to stop early.
   *
   * `stride` (one of STRIDES): render the lattice of that spacing (a frame reduced to 1/stride
   * per side), shown interpolated between its pixels. `done` (a coarser stride, or 0): the frame
   * buffer already holds that lattice of this very camera, time and parameters (the previous
   * frame, not aborted), so only the pixels it lacks are rendered.
   *
   * A frame is rendered in tiles, each a run of consecutive entries of the interlaced pixel
   * order (the kernels' pixel-list mode) and its own submission, and the canvas is
   * updated after each: a slow GPU (SwiftShader) then keeps the page responsive and shows the
   * frame as it progresses. The tile size adapts to about TILE_MS of GPU work; on a real GPU a
   * frame is one tile. Two tiles are queued at a time, so an abandoned frame still finishes the
   * tile after the one in flight.
   */
  async render(cam, t, abort = () => false, stride = 1, done = 0) {
    if (this.r.lost) throw new Error(this.r.lost);
    if (!STRIDES.includes(stride)) throw new Error(`render: stride ${stride} is not one of ${STRIDES.join(", ")}`);
    const { width: w, height: h } = cam;
    const fresh = this.#ensureFrame(w, h);
    // A full or refining frame overwrites what the static cache's pixels hold.
    this.dynamicCount = -1;
    // The display uniform follows each batch (`displayUniform`).
    this.displayStride = stride;
    const end = this.orderEnds[stride];
    const keep = !fresh && done > stride && this.orderEnds[done] !== undefined;
    const begin = keep ? this.orderEnds[done] : 0;
    return this.#renderPasses(cam, t, abort, begin, end);
  }

  /**
   * Bind groups of the passes for a `target`: `frame` (the interlaced pixel order into the frame
   * buffer), `probe` (the same order into the probe buffer) or `dynamic` (the static cache's
   * dynamic pixels into the frame buffer); each `main` (work at binding 7) and `args` (the
   * dispatch sizes there).
   */
  #passGroups(target = "frame") {
    this.groups ??= {};
    if (this.groups[target]) return this.groups[target];
    const order = target === "dynamic" ? this.dynOrder : target === "outside" ? this.outsideOrder : this.order;
    const frame = target === "probe" ? this.probeFrame : this.frame;
    const group = (work) =>
      this.device.createBindGroup({
        layout: this.kernels.layout,
        entries: [this.model, this.view, this.tab3, this.tab4, this.rest, order, frame, work, this.ctrl, this.pass, this.occupancy].map((buffer, binding) => ({ binding, resource: { buffer } })),
      });
    this.groups[target] = { main: group(this.work), args: group(this.args) };
    return this.groups[target];
  }

  async #renderPasses(cam, t, abort, begin, end, target = "frame") {
    const [w, h] = this.frameSize;
    const n = w * h;
    const device = this.device;
    const p = this.kernels.pipelines;
    const { main, args } = this.#passGroups(target);
    const maxDim = device.limits.maxComputeWorkgroupsPerDimension;
    device.queue.writeBuffer(this.view, 0, viewUniform(cam, t, n, 0));
    // Two batches at a time: the next one is submitted before the page waits for the one before
    // it, so the GPU does not idle while the page learns of a completion and prepares the next
    // batch (on SwiftShader about 1.1x sooner full-size frames, less than the host's noise in
    // one of three comparisons: docs/playback.md). The queue runs the batches in order, so they
    // share the pass uniform and the work buffers.
    let queued = null; // the batch submitted before the last one: { done, t0, count }
    let lastDone = 0;
    const finish = async (b) => {
      await b.done;
      // Its GPU time: from its submission, or from the end of the batch before it.
      const now = performance.now();
      const ms = Math.max(now - Math.max(b.t0, lastDone), 0.1);
      lastDone = now;
      this.#adaptTile(b.count, ms);
    };
    let start = begin;
    while (start < end) {
      const count = Math.min(this.tile, this.capacity, end - start);
      const groups = dispatchSize(count, maxDim);
      if (!groups) throw new Error(`${count} rays exceed this GPU's dispatch limits`);
      const pass = new Uint32Array(PASS_BYTES / 4);
      // Rays render the pixels order[start ..] (the pixel list), each into frame[pixel].
      // With the grid and the 3D passes compiled, the live lists put the samples without a 4D
      // lookup apart for them.
      const split = this.split3 && this.occupancyResolution !== 0;
      this.lastSplit3 = split;
      pass.set([start, count, PASS_FLAGS.list | (split ? PASS_FLAGS.split : 0), this.samples], PASS_OFFSETS.tile / 4);
      // reg0, reg1: rays, hist, edges, samp, geo, clist (no cache regions); reg2: the occupancy
      // resolution and the live lists.
      pass.set(this.regions, PASS_OFFSETS.reg0 / 4);
      pass[PASS_OFFSETS.reg2 / 4 + 1] = this.occupancyResolution;
      pass.set(this.lists, PASS_OFFSETS.reg2 / 4 + 2);
      device.queue.writeBuffer(this.pass, 0, pass);
      if (target === "frame") {
        this.shownSize = displayUniform(w, h, this.orderIds, this.orderEnds, this.displayStride, start + count);
        device.queue.writeBuffer(this.size, 0, this.shownSize);
      }
      device.pushErrorScope("validation");
      let enc = device.createCommandEncoder();
      enc.clearBuffer(this.ctrl);
      const t0 = performance.now();
      // `?profile=1`: every dispatch its own submission, timed into `passMs` (ms per entry point).
      const steps = this.occupancyResolution ? (split ? PASS_STEPS_LIVE : PASS_STEPS_UNSPLIT) : PASS_STEPS;
      for (let k = 0; k < steps.length; ) {
        const end = this.profile ? k + 1 : steps.length;
        const cp = enc.beginComputePass();
        for (const [name, at] of steps.slice(k, end)) {
          cp.setBindGroup(0, name === "pass_args" ? args : main);
          cp.setPipeline(p[name]);
          if (at !== null) cp.dispatchWorkgroupsIndirect(this.args, at);
          else if (name === "pass_setup") cp.dispatchWorkgroups(groups[0], groups[1], 1);
          else cp.dispatchWorkgroups(1);
        }
        cp.end();
        if (end === steps.length) this.#present(enc);
        const ts = performance.now();
        device.queue.submit([enc.finish()]);
        if (this.profile) {
          await device.queue.onSubmittedWorkDone();
          const name = steps[k][0];
          this.passMs[name] = (this.passMs[name] || 0) + performance.now() - ts;
          enc = device.createCommandEncoder();
        }
        k = end;
      }
      if (this.profile) await this.#countLists();
      const err = await device.popErrorScope();
      if (err) throw new Error(`render: ${err.message}`);
      const batch = { done: device.queue.onSubmittedWorkDone(), t0, count };
      start += count;
      this.rays += count;
      if (queued) await finish(queued);
      queued = batch;
      if (start < end && abort()) break;
    }
    if (queued) await finish(queued);
    return start >= end;
  }

  /** Adds the last batch's list sizes (the counters) to `passCounts` (`?profile=1`). */
  async #countLists() {
    const device = this.device;
    const bytes = 28;
    const read = device.createBuffer({ size: bytes, usage: GPUBufferUsage.MAP_READ | GPUBufferUsage.COPY_DST, label: "counters read back" });
    const enc = device.createCommandEncoder();
    enc.copyBufferToBuffer(this.ctrl, 0, read, 0, bytes);
    device.queue.submit([enc.finish()]);
    await read.mapAsync(GPUMapMode.READ);
    const c = new Uint32Array(read.getMappedRange().slice(0));
    read.destroy();
    const now = { rays: c[0], colour: c[1], proposal4: c[3], samples4: c[4], proposal3: c[5], samples3: c[6] };
    for (const [k, v] of Object.entries(now)) this.passCounts[k] = (this.passCounts[k] || 0) + v;
  }

  /** Sizes the next batches to about TILE_MS of GPU work, from `count` rays that took `ms`
   * (multiples of 64 rays: whole workgroups). */
  #adaptTile(count, ms) {
    this.raysPerMs = count / ms;
    this.tile = Math.min(1 << 22, Math.max(64, Math.round((count * TILE_MS) / ms / 64) * 64));
  }

  /**
   * Builds the static cache of `cam` (incremental playback; `msth play`'s probes without its
   * mask test). Each of `probes` (`{ t, params }`: a time and, when that time's chunk is not the
   * one uploaded, a function that returns its flat parameter buffer) renders the whole frame:
   * the first one into the frame buffer (the base: the colour the static pixels keep), the others
   * into a second buffer. A pixel whose colour differs from the base by more than `tolerance` in
   * a channel at any later probe is dynamic. `restore()` uploads the current parameters again
   * afterwards. Resolves to `{ dynamic, pixels }`, or null when `abort()` stopped it (no cache).
   * `renderDynamic` then re-renders only the dynamic pixels; any other `render` call, a new size
   * or new samples drop the cache.
   */
  async buildStaticCache(cam, probes, tolerance, abort, restore) {
    if (this.r.lost) throw new Error(this.r.lost);
    const { width: w, height: h } = cam;
    this.#ensureFrame(w, h);
    // The first probe renders the full frame in the pixel order, shown as it progresses (the
    // finest lattice complete so far, `displayUniform`); the others render off screen.
    this.displayStride = 1;
    const n = w * h;
    this.dynamicCount = -1;
    if (!this.probeFrame) {
      this.probeFrame = this.device.createBuffer({ size: n * 16, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_SRC, label: "probe frame" });
      this.dynOrder = this.device.createBuffer({ size: n * 4, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST, label: "dynamic pixels" });
      if (this.groups) {
        delete this.groups.probe;
        delete this.groups.dynamic;
      }
    }
    let base = null;
    const dynamic = new Uint8Array(n);
    let foreign = false; // another time's parameters are uploaded
    try {
      for (const probe of probes) {
        const params = probe.params ? probe.params() : null;
        if (params) this.setParams(params, true);
        else if (foreign) restore();
        foreign = Boolean(params);
        const target = base ? "probe" : "frame";
        if (!(await this.#renderPasses(cam, probe.t, abort, 0, n, target))) return null;
        const px = await this.#readFrame(target === "frame" ? this.frame : this.probeFrame);
        if (!base) {
          base = px;
          continue;
        }
        for (let i = 0; i < n; i++) {
          if (dynamic[i]) continue;
          for (let c = 0; c < 3; c++) {
            if (Math.abs(px[4 * i + c] - base[4 * i + c]) > tolerance) {
              dynamic[i] = 1;
              break;
            }
          }
        }
      }
    } finally {
      if (foreign) restore();
    }
    const list = new Uint32Array(n);
    let k = 0;
    for (let i = 0; i < n; i++) if (dynamic[i]) list[k++] = i;
    if (k) this.device.queue.writeBuffer(this.dynOrder, 0, list.buffer, 0, 4 * k);
    this.dynamicCount = k;
    return { dynamic: k, pixels: n };
  }

  /** Whether `buildStaticCache` built a cache for the current frame buffer. */
  get hasStaticCache() {
    return this.dynamicCount >= 0;
  }

  /**
   * An incremental frame: `cam` (the camera of the static cache) at time `t`, re-rendering only
   * the cache's dynamic pixels; the others keep the base frame's colour. Resolves like `render`.
   */
  async renderDynamic(cam, t, abort = () => false) {
    if (this.r.lost) throw new Error(this.r.lost);
    if (!this.hasStaticCache) throw new Error("renderDynamic: no static cache");
    const [w, h] = this.frameSize;
    this.device.queue.writeBuffer(this.size, 0, (this.shownSize = new Uint32Array([w, h, 1, 0, h, 0, 0, 0])));
    if (this.dynamicCount === 0) {
      const enc = this.device.createCommandEncoder();
      this.#present(enc);
      this.device.queue.submit([enc.finish()]);
      await this.device.queue.onSubmittedWorkDone();
      return true;
    }
    return this.#renderPasses(cam, t, abort, 0, this.dynamicCount, "dynamic");
  }

  /**
   * The fields at `points` (8 values a point: unit point, time, direction, kind; the
   * `eval_points` kernel, web/shaders/README.md) with the parameters uploaded: one `vec4` a
   * point, in batches of EVAL_BATCH points. The play-time volume's bake (volume.js).
   */
  async evalPoints(points) {
    if (this.r.lost) throw new Error(this.r.lost);
    if (points.length % 8) throw new Error(`evalPoints: ${points.length} values are not whole points of 8`);
    const device = this.device;
    if (!this.evalPipeline) {
      // The bake evaluates with the kernels compiled for the model (1.8x faster on SwiftShader).
      await this.kernelsReady?.();
      const t0 = performance.now();
      this.evalPipeline = await this.kernels.pipelines.evalPoints();
      /** Milliseconds the `eval_points` pipeline took to compile. */
      this.evalCompileMs = performance.now() - t0;
    }
    const n = points.length / 8;
    const out = new Float32Array(n * 4);
    const batch = Math.min(EVAL_BATCH, Math.max(n, 1));
    if (!this.evalBuffers || this.evalBuffers.batch < batch) {
      if (this.evalBuffers) for (const b of ["list", "out", "read"]) this.evalBuffers[b].destroy();
      this.evalBuffers = {
        batch,
        list: device.createBuffer({ size: batch * 32, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST, label: "eval points" }),
        out: device.createBuffer({ size: batch * 16, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_SRC, label: "eval output" }),
        read: device.createBuffer({ size: batch * 16, usage: GPUBufferUsage.MAP_READ | GPUBufferUsage.COPY_DST, label: "eval read back" }),
        view: device.createBuffer({ size: VIEW_BYTES, usage: GPUBufferUsage.UNIFORM | GPUBufferUsage.COPY_DST, label: "eval View" }),
      };
      const e = this.evalBuffers;
      e.group = device.createBindGroup({
        layout: this.kernels.layout,
        entries: [this.model, e.view, this.tab3, this.tab4, this.rest, e.list, e.out, this.args, this.ctrl, this.pass, this.noOccupancy].map((buffer, binding) => ({ binding, resource: { buffer } })),
      });
    }
    const e = this.evalBuffers;
    const maxDim = device.limits.maxComputeWorkgroupsPerDimension;
    for (let first = 0; first < n; first += batch) {
      const count = Math.min(batch, n - first);
      device.queue.writeBuffer(e.list, 0, points.buffer, points.byteOffset + first * 32, count * 32);
      const view = new Uint32Array(VIEW_BYTES / 4);
      view[22] = count;
      device.queue.writeBuffer(e.view, 0, view);
      device.pushErrorScope("validation");
      const enc = device.createCommandEncoder();
      const cp = enc.beginComputePass();
      cp.setPipeline(this.evalPipeline);
      cp.setBindGroup(0, e.group);
      const [gx, gy] = dispatchSize(count, maxDim);
      cp.dispatchWorkgroups(gx, gy, 1);
      cp.end();
      enc.copyBufferToBuffer(e.out, 0, e.read, 0, count * 16);
      device.queue.submit([enc.finish()]);
      const err = await device.popErrorScope();
      if (err) throw new Error(`eval_points: ${err.message}`);
      await e.read.mapAsync(GPUMapMode.READ, 0, count * 16);
      out.set(new Float32Array(e.read.getMappedRange(0, count * 16)), first * 4);
      e.read.unmap();
    }
    return out;
  }

  /**
   * Uploads a baked play-time volume (volume.js `assembleVolume`, `volumeLayout`): the brick
   * index, the static slots and the dynamic bricks' cells; slices follow with `bindSlices`.
   * Throws when it exceeds this GPU's storage buffer limit.
   */
  async setVolume(vol, layout) {
    const device = this.device;
    this.dropVolume();
    if (!this.r.volumeSource) throw new Error("volume.wgsl was not loaded");
    this.volumePipeline ??= await device.createComputePipelineAsync({
      layout: "auto",
      compute: { module: device.createShaderModule({ code: this.r.volumeSource, label: "volume.wgsl" }), entryPoint: "volume_march" },
    });
    const wordsBytes = layout.words * 4;
    const valuesBytes = Math.max(layout.values, 1) * 8;
    for (const [what, bytes] of [["the volume's index and cell bits", wordsBytes], ["the volume's vertex values", valuesBytes]]) {
      if (bytes > this.storageLimit) throw new Error(`${what} need ${bytes} bytes, more than this GPU's storage buffer limit ${this.storageLimit}`);
    }
    const S = GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST;
    const words = device.createBuffer({ size: wordsBytes, usage: S, label: "volume words" });
    const values = device.createBuffer({ size: valuesBytes, usage: S, label: "volume values" });
    const q = device.queue;
    q.writeBuffer(words, 0, vol.index);
    if (vol.occupied.length) q.writeBuffer(words, layout.atOccupied * 4, vol.occupied);
    if (vol.dynamic.cells.length) q.writeBuffer(words, layout.atCells * 4, vol.dynamic.cells);
    if (vol.values.length) q.writeBuffer(values, 0, vol.values);
    const uniform = device.createBuffer({ size: 64, usage: GPUBufferUsage.UNIFORM | GPUBufferUsage.COPY_DST, label: "VolumeU" });
    const g = vol.geometry;
    const u = new ArrayBuffer(64);
    new Uint32Array(u, 0, 12).set([g.resolution, g.brick, g.perSide, g.fw, layout.atOccupied, layout.atCells, layout.regionWords[0], layout.regionWords[0], layout.regionValues[0], layout.regionValues[0], vol.dynamic.bricks.length ? 1 : 0, 0]);
    // March: steps of one cell, stopping where the exact path does.
    new Float32Array(u, 48, 4).set([1, VISIBLE_TRANSMITTANCE, 0, 0]);
    this.volume = { vol, layout, words, values, uniform, u, held: [null, null], bytes: wordsBytes + valuesBytes };
    this.volumeFrame = null;
    return this.volume.bytes;
  }

  /** Forgets the play-time volume. */
  dropVolume() {
    if (!this.volume) return;
    this.volume.words.destroy();
    this.volume.values.destroy();
    this.volume.uniform.destroy();
    this.volume = null;
  }

  /**
   * Binds the time slices `[k0, k1, w]` of the volume's dynamic bricks (volume.js
   * `sliceAround`), uploading those the two regions do not hold (msth-gpu
   * `GpuVolume::bind_slices`); each must be baked (`vol.dynamic.slices[k]`).
   */
  bindSlices(around) {
    const v = this.volume;
    const d = v.vol.dynamic;
    const f32 = new Float32Array(v.u, 48, 4);
    const u32 = new Uint32Array(v.u, 0, 12);
    if (!d.bricks.length) {
      f32[2] = 0;
      return;
    }
    if (!around) throw new Error("the volume's time slices for this frame are not baked");
    let [k0, k1, w] = around;
    if (!(w > 0)) k1 = k0;
    const region = (k, keep) => {
      const at = v.held.indexOf(k);
      if (at >= 0) return at;
      const s = d.slices[k];
      if (!s) throw new Error(`time slice ${k} of the volume is not baked`);
      const r = keep === 0 ? 1 : keep === 1 ? 0 : Math.max(v.held.indexOf(null), 0);
      this.device.queue.writeBuffer(v.words, v.layout.regionWords[r] * 4, s.occupied);
      if (s.values.length) this.device.queue.writeBuffer(v.values, v.layout.regionValues[r] * 8, s.values);
      v.held[r] = k;
      return r;
    };
    const ra = region(k0, null);
    const rb = k1 === k0 ? ra : region(k1, ra);
    u32[6] = v.layout.regionWords[ra];
    u32[7] = v.layout.regionWords[rb];
    u32[8] = v.layout.regionValues[ra];
    u32[9] = v.layout.regionValues[rb];
    f32[2] = k1 === k0 ? 0 : w;
  }

  /**
   * Draws `cam` at time `t` through the play-time volume (`volume_march`, one invocation a
   * pixel) with the slices last bound, then the rays that reached a brick the volume left out
   * with the per-sample passes (the exact path), and shows the frame. `stride` (one of STRIDES)
   * draws the lattice of that spacing, as `render` does (the interlaced pixel order), shown
   * interpolated. Resolves to `{ outside }` (the rays drawn exactly), or null when `abort()`
   * stopped it.
   */
  async renderVolume(cam, t, abort = () => false, stride = 1) {
    if (this.r.lost) throw new Error(this.r.lost);
    const v = this.volume;
    if (!v) throw new Error("renderVolume: no volume");
    if (!STRIDES.includes(stride)) throw new Error(`renderVolume: stride ${stride} is not one of ${STRIDES.join(", ")}`);
    const { width: w, height: h } = cam;
    this.#ensureFrame(w, h);
    this.dynamicCount = -1;
    const device = this.device;
    const count = this.orderEnds[stride];
    device.queue.writeBuffer(this.view, 0, viewUniform(cam, t, count, PASS_FLAGS.list));
    device.queue.writeBuffer(v.uniform, 0, v.u);
    this.displayStride = stride;
    this.shownSize = displayUniform(w, h, this.orderIds, this.orderEnds, stride, count);
    device.queue.writeBuffer(this.size, 0, this.shownSize);
    if (this.volumeFrame !== this.frame) {
      v.group = device.createBindGroup({
        layout: this.volumePipeline.getBindGroupLayout(0),
        entries: [
          [0, this.model],
          [1, this.view],
          [5, this.order],
          [6, this.frame],
          [7, v.uniform],
          [8, v.words],
          [9, v.values],
        ].map(([binding, buffer]) => ({ binding, resource: { buffer } })),
      });
      this.volumeFrame = this.frame;
    }
    device.pushErrorScope("validation");
    const enc = device.createCommandEncoder();
    const cp = enc.beginComputePass();
    cp.setPipeline(this.volumePipeline);
    cp.setBindGroup(0, v.group);
    const [gx, gy] = dispatchSize(count, device.limits.maxComputeWorkgroupsPerDimension);
    cp.dispatchWorkgroups(gx, gy, 1);
    cp.end();
    const hasOutside = v.vol.outside > 0;
    if (!hasOutside) this.#present(enc);
    device.queue.submit([enc.finish()]);
    const err = await device.popErrorScope();
    if (err) throw new Error(`volume_march: ${err.message}`);
    let outside = 0;
    if (hasOutside) {
      // The rays that reached a brick left out: their visible depth is OUTSIDE.
      const px = await this.#readFrame(this.frame);
      const list = new Uint32Array(count);
      for (let k = 0; k < count; k++) {
        const i = this.orderIds[k];
        if (px[4 * i + 3] === OUTSIDE_DEPTH) list[outside++] = i;
      }
      if (outside) {
        if (!this.outsideOrder || this.outsideOrder.size < w * h * 4) {
          this.outsideOrder?.destroy();
          this.outsideOrder = device.createBuffer({ size: w * h * 4, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST, label: "rays beyond the volume" });
          if (this.groups) delete this.groups.outside;
        }
        device.queue.writeBuffer(this.outsideOrder, 0, list.buffer, 0, outside * 4);
        if (!(await this.#renderPasses(cam, t, abort, 0, outside, "outside"))) return null;
      }
      const enc2 = device.createCommandEncoder();
      this.#present(enc2);
      device.queue.submit([enc2.finish()]);
    }
    await device.queue.onSubmittedWorkDone();
    this.rays += count;
    return { outside };
  }

  /** The RGBA f32 values of a frame-sized buffer. */
  async #readFrame(buffer) {
    const [w, h] = this.frameSize;
    const enc = this.device.createCommandEncoder();
    enc.copyBufferToBuffer(buffer, 0, this.readback, 0, w * h * 16);
    this.device.queue.submit([enc.finish()]);
    await this.readback.mapAsync(GPUMapMode.READ);
    const px = new Float32Array(this.readback.getMappedRange().slice(0));
    this.readback.unmap();
    return px;
  }

  #present(enc) {
    const rp = enc.beginRenderPass({
      colorAttachments: [{ view: this.context.getCurrentTexture().createView(), loadOp: "clear", storeOp: "store", clearValue: [0, 0, 0, 1] }],
    });
    rp.setPipeline(this.display);
    rp.setBindGroup(0, this.displayBind);
    rp.draw(3);
    rp.end();
  }

  /** The last frame as RGBA8, quantised as `msth play` writes PNGs (round to nearest). */
  async readPixels() {
    const [w, h] = this.frameSize;
    const enc = this.device.createCommandEncoder();
    enc.copyBufferToBuffer(this.frame, 0, this.readback, 0, w * h * 16);
    this.device.queue.submit([enc.finish()]);
    await this.readback.mapAsync(GPUMapMode.READ);
    const src = new Float32Array(this.readback.getMappedRange().slice(0));
    this.readback.unmap();
    const out = new Uint8Array(w * h * 4);
    for (let i = 0; i < w * h; i++) {
      for (let c = 0; c < 3; c++) {
        const v = src[4 * i + c];
        out[4 * i + c] = Math.floor(Math.min(1, Math.max(0, v >= 0 ? v : 0)) * 255 + 0.5);
      }
      out[4 * i + 3] = 255;
    }
    return out;
  }
}
