// The play-time volume in the page: the plan and the host side of the bake of msth-core's
// `volume` module (`core/src/volume/`: `bake.rs`, `views.rs`), the layout the `volume_march`
// kernel reads (`volume.wgsl`; msth-gpu `volume.rs`). The vertices are evaluated on the GPU by
// `eval_points` (renderer.js `evalPoints`), as the native GPU player does
// (`player/src/volume.rs`, `bake_set_on_device`): every vertex of every brick, the colour baked
// for the mean direction from the file's cameras.
//
// The plan is msth-core's, computed in f32 where msth-core computes in f32 (`Math.fround`), so
// that the page and the native players choose the same resolution and bricks for a file
// (`tests/tests/web_volume.rs` compares them).

import { f16ToF32 } from "./format.js";
import { toBinary16 } from "./renderer.js";
import { RENDER_STATIC_CUTOFF } from "./generated/contract.js";

export const EMPTY_BRICK = 0xffffffff;
export const OUTSIDE_BRICK = 0xfffffffe;
export const DYNAMIC_BRICK = 0x80000000;
const MIN_BRICK = 4;
const MAX_INDEX_RESOLUTION = 128;
const MIN_VOLUME_RESOLUTION = 32;
const MAX_VOLUME_RESOLUTION = 2048;
const MAX_SLICES = 4096;
const FALLBACK_ALPHA = 1e-2;
const FALLBACK_THRESHOLD_RESOLUTION = 128;
export const DEFAULT_MIN_PROPOSAL_ALPHA = 0.003;
// What becomes of the occupied bricks no camera of the file looks into (msth-core `OutsideViews`):
// "auto" bakes them where every brick fits, "exact" always leaves them to the exact path,
// "bake" always bakes them.
export const OUTSIDE_VIEWS = ["auto", "exact", "bake"];
/** Values per vertex (density pre-activation, red, green, blue), each binary16. */
const CHANNELS = 4;
const NEAR_CLIP = 1e-4;
const f = Math.fround;

const nextPow2 = (x) => 2 ** Math.ceil(Math.log2(Math.max(1, x)));

/** msth-core `VolumeGeometry::new`. */
export function geometry(resolution) {
  const r = nextPow2(Math.min(Math.max(resolution, MIN_VOLUME_RESOLUTION), MAX_VOLUME_RESOLUTION));
  const brick = Math.max(r / MAX_INDEX_RESOLUTION, MIN_BRICK);
  const perSide = r / brick;
  const v1 = brick + 1;
  const fw = Math.ceil(brick ** 3 / 32);
  return { resolution: r, brick, perSide, indexLen: perSide ** 3, nv: v1 ** 3, fw, slotBytes: v1 ** 3 * CHANNELS * 2 + fw * 8 };
}

/** msth-core `model_resolution`: the main 3D grid's finest resolution. */
export function modelResolution(model) {
  const fin = model.field.encoding.grid3.finest_resolution.slice(0, 3).reduce((a, b) => Math.max(a, b), 0);
  return geometry(Number.isFinite(fin) && fin > 0 ? Math.trunc(fin) : MIN_VOLUME_RESOLUTION).resolution;
}

/** msth-core `has_static_part`: a 3D grid, and no 4D grid or a mask. */
export function hasStaticPart(model) {
  const b = model.field.encoding.blend;
  return b !== "four_d" && (b === "static" || b === "mst" || b === "mt");
}

/** msth-core `SceneBounds::from_unit`. */
export function fromUnit(bounds, u) {
  const c = u.map((x) => Math.min(Math.max(x, 0), 1));
  if (bounds.kind === "box") return c.map((x, a) => f(bounds.min[a] + f(x * f(bounds.max[a] - bounds.min[a]))));
  const q = c.map((x) => f(x * 4 - 2));
  const n = Math.max(...q.map(Math.abs));
  let y = q;
  if (n > 1) {
    const nn = Math.min(n, 2 - 1e-4);
    const m = f(1 / (2 - nn));
    y = q.map((x) => f(f(x / nn) * m));
  }
  return y.map((x, a) => f(bounds.center[a] + f(x * bounds.radius)));
}

const cellWorldSize = (bounds, res) =>
  bounds.kind === "box" ? f(Math.min(...[0, 1, 2].map((a) => f(bounds.max[a] - bounds.min[a]))) / res) : f((4 * bounds.radius) / res);

/** msth-core `scene::density_threshold`. */
function densityThreshold(bounds, res, alpha) {
  const diagonal = f(f(Math.sqrt(3) * res) * cellWorldSize(bounds, res));
  return f(-Math.log(1 - Math.min(Math.max(alpha, 0), 0.999999)) / diagonal);
}

/** The file's occupancy grid (format.js `readOccupancy`) as the bake reads it. */
function occupancyView(grid) {
  if (!grid) return null;
  const r = grid.resolution;
  if (!(r > 0 && r <= 4096 && grid.words.length >= Math.ceil(r ** 3 / 32))) throw new Error(`the occupancy grid is malformed (${grid.words.length} words for resolution ${r})`);
  const cell = (x, y, z) => {
    const i = x + r * (y + r * z);
    return ((grid.words[i >>> 5] >>> (i & 31)) & 1) === 1;
  };
  /** Whether a cell overlapping the box `[lo, hi)` of a `res`-grid is occupied. */
  const anyIn = (lo, hi, res) => {
    const range = (a) => {
      const first = Math.floor((lo[a] * r) / res);
      const last = Math.max(Math.ceil((hi[a] * r) / res), first + 1);
      return [first, Math.min(last, r)];
    };
    const [[x0, x1], [y0, y1], [z0, z1]] = [range(0), range(1), range(2)];
    for (let z = z0; z < z1; z++) for (let y = y0; y < y1; y++) for (let x = x0; x < x1; x++) if (cell(x, y, z)) return true;
    return false;
  };
  return { resolution: r, anyIn, densityThreshold: grid.densityThreshold };
}

/** The mask's value at unit point `u` (msth-core `Encoding::mask_at`: trilinear logits, sigmoid). */
function maskAt(mask, params, u) {
  const r = mask.res;
  const base = [];
  const fr = [];
  for (let a = 0; a < 3; a++) {
    const p = f(Math.min(Math.max(u[a], 0), 1) * (r - 1));
    const i = Math.min(Math.trunc(p), r - 2);
    base.push(i);
    fr.push(f(p - i));
  }
  let v = 0;
  for (let c = 0; c < 8; c++) {
    const [bx, by, bz] = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
    const w = f(f((bx ? fr[0] : f(1 - fr[0])) * (by ? fr[1] : f(1 - fr[1]))) * (bz ? fr[2] : f(1 - fr[2])));
    v = f(v + f(w * params[mask.start + base[0] + bx + r * (base[1] + by + r * (base[2] + bz))]));
  }
  return v >= 0 ? f(1 / f(1 + f(Math.exp(-v)))) : f(f(Math.exp(v)) / f(1 + f(Math.exp(v))));
}

const brickOrigin = (g, b) => [(b % g.perSide) * g.brick, (Math.floor(b / g.perSide) % g.perSide) * g.brick, Math.floor(b / (g.perSide * g.perSide)) * g.brick];

/** msth-core `bake::sort_bricks`: static bricks, dynamic bricks and their dynamic cells. */
function sortBricks(g, model, layout, params, occ, candidates) {
  const enc = layout.field.encoding;
  const blend = model.field.encoding.blend;
  const b = g.brick;
  const v1 = b + 1;
  const res = g.resolution;
  const stat = [];
  const dyn = [];
  const cells = [];
  const vd = new Uint8Array(g.nv);
  const isDynamic = (m) => (blend === "static" ? false : blend === "add" || blend === "four_d" ? true : !enc.mask || 1 - m >= RENDER_STATIC_CUTOFF);
  for (const brick of candidates) {
    const o = brickOrigin(g, brick);
    let any = false;
    for (let z = 0; z < v1; z++)
      for (let y = 0; y < v1; y++)
        for (let x = 0; x < v1; x++) {
          const m = enc.mask ? maskAt(enc.mask, params, [f((o[0] + x) / res), f((o[1] + y) / res), f((o[2] + z) / res)]) : 1;
          const d = isDynamic(m);
          vd[x + v1 * (y + v1 * z)] = d ? 1 : 0;
          any ||= d;
        }
    if (!any) {
      stat.push(brick);
      continue;
    }
    const words = new Uint32Array(g.fw);
    let count = 0;
    for (let cz = 0; cz < b; cz++)
      for (let cy = 0; cy < b; cy++)
        for (let cx = 0; cx < b; cx++) {
          let corner = false;
          for (let c = 0; c < 8 && !corner; c++) corner = vd[cx + (c & 1) + v1 * (cy + ((c >> 1) & 1) + v1 * (cz + (c >> 2)))] === 1;
          const cell = [o[0] + cx, o[1] + cy, o[2] + cz];
          const seen = !occ || occ.anyIn(cell, [cell[0] + 1, cell[1] + 1, cell[2] + 1], res);
          if (corner && seen) {
            const bit = cx + b * (cy + b * cz);
            words[bit >>> 5] |= 1 << (bit & 31);
            count++;
          }
        }
    if (count === 0) stat.push(brick);
    else {
      dyn.push(brick);
      cells.push(...words);
    }
  }
  return { stat, dyn, cells: Uint32Array.from(cells) };
}

/** A 4x4 column-major matrix's inverse (null when singular or not finite). */
function invert(m) {
  const inv = new Float64Array(16);
  const [a00, a01, a02, a03, a10, a11, a12, a13, a20, a21, a22, a23, a30, a31, a32, a33] = m;
  const b00 = a00 * a11 - a01 * a10, b01 = a00 * a12 - a02 * a10, b02 = a00 * a13 - a03 * a10;
  const b03 = a01 * a12 - a02 * a11, b04 = a01 * a13 - a03 * a11, b05 = a02 * a13 - a03 * a12;
  const b06 = a20 * a31 - a21 * a30, b07 = a20 * a32 - a22 * a30, b08 = a20 * a33 - a23 * a30;
  const b09 = a21 * a32 - a22 * a31, b10 = a21 * a33 - a23 * a31, b11 = a22 * a33 - a23 * a32;
  const det = b00 * b11 - b01 * b10 + b02 * b09 + b03 * b08 - b04 * b07 + b05 * b06;
  if (!det || !Number.isFinite(det)) return null;
  const d = 1 / det;
  inv.set([
    (a11 * b11 - a12 * b10 + a13 * b09) * d, (a02 * b10 - a01 * b11 - a03 * b09) * d, (a31 * b05 - a32 * b04 + a33 * b03) * d, (a22 * b04 - a21 * b05 - a23 * b03) * d,
    (a12 * b08 - a10 * b11 - a13 * b07) * d, (a00 * b11 - a02 * b08 + a03 * b07) * d, (a32 * b02 - a30 * b05 - a33 * b01) * d, (a20 * b05 - a22 * b02 + a23 * b01) * d,
    (a10 * b10 - a11 * b08 + a13 * b06) * d, (a01 * b08 - a00 * b10 - a03 * b06) * d, (a30 * b04 - a31 * b02 + a33 * b00) * d, (a21 * b02 - a20 * b04 - a23 * b00) * d,
    (a11 * b07 - a10 * b09 - a12 * b06) * d, (a00 * b09 - a01 * b07 + a02 * b06) * d, (a31 * b01 - a30 * b03 - a32 * b00) * d, (a20 * b03 - a21 * b01 + a22 * b00) * d,
  ]);
  return inv.every(Number.isFinite) ? inv : null;
}

/** msth-core `views::bricks_in_view`: per brick, whether one of `cameras` sees part of it (of
 * `only`, when given, the bricks to test; the others read as unseen); null as soon as more than
 * `limit` are seen. */
export function bricksInView(g, bounds, cameras, only = null, limit = Infinity) {
  const i = g.perSide;
  const v = i + 1;
  const world = [];
  for (let k = 0; k < v * v * v; k++) world.push(fromUnit(bounds, [f((k % v) / i), f((Math.floor(k / v) % v) / i), f(Math.floor(k / (v * v)) / i)]));
  const seen = new Uint8Array(i * i * i);
  const bricks = only ?? Array.from(seen.keys());
  let count = 0;
  for (const cam of cameras) {
    const c = invert(cam.m);
    if (!c) continue;
    const local = world.map(([x, y, z]) => [c[0] * x + c[4] * y + c[8] * z + c[12], c[1] * x + c[5] * y + c[9] * z + c[13], c[2] * x + c[6] * y + c[10] * z + c[14]]);
    for (const b of bricks) {
      if (seen[b]) continue;
      const [x, y, z] = [b % i, Math.floor(b / i) % i, Math.floor(b / (i * i))];
      const corners = [];
      for (let k = 0; k < 8; k++) corners.push(local[x + (k & 1) + v * (y + ((k >> 1) & 1) + v * (z + (k >> 2)))]);
      if (hullInView(cam, corners)) {
        seen[b] = 1;
        if (++count > limit) return null;
      }
    }
  }
  return seen;
}

function hullInView(cam, corners) {
  const front = (p) => p[2] <= -NEAR_CLIP;
  let [lx, ly, hx, hy] = [Infinity, Infinity, -Infinity, -Infinity];
  const add = (p) => {
    const qx = cam.cx + (cam.fx * p[0]) / -p[2];
    const qy = cam.cy - (cam.fy * p[1]) / -p[2];
    lx = Math.min(lx, qx);
    ly = Math.min(ly, qy);
    hx = Math.max(hx, qx);
    hy = Math.max(hy, qy);
  };
  let any = false;
  for (const p of corners) if (front(p)) (add(p), (any = true));
  if (!any) return false;
  for (let a = 0; a < 8; a++)
    for (const bit of [1, 2, 4]) {
      if (a & bit) continue;
      const [p, q] = [corners[a], corners[a | bit]];
      if (front(p) !== front(q)) {
        const t = (-NEAR_CLIP - p[2]) / (q[2] - p[2]);
        add(p.map((x, k) => x + (q[k] - x) * t));
      }
    }
  return hx >= 0 && lx <= cam.width && hy >= 0 && ly <= cam.height;
}

/**
 * Plans the volume of a file (msth-core `bake::plan_with` with the players' defaults): `model`
 * the file's model config, `layout` format.js's, `params` the flat buffer with at least the
 * static part, `occupancy` format.js's grid or null, `cameras` camera.js cameras, `budget` bytes.
 * Throws with the reason when no volume can be made (no static part, over the budget).
 */
export function planVolume({ model, layout, params, occupancy, cameras, budget, maxResolution = null, minProposalAlpha = DEFAULT_MIN_PROPOSAL_ALPHA, outside: outsidePolicy = "auto" }) {
  if (!OUTSIDE_VIEWS.includes(outsidePolicy)) throw new Error(`volume-outside=${outsidePolicy}: one of ${OUTSIDE_VIEWS.join(", ")}`);
  if (!hasStaticPart(model)) throw new Error(`the model has no static part (blend mode ${model.field.encoding.blend}): every sample depends on time, so there is nothing to bake`);
  const occ = occupancyView(occupancy);
  const requested = maxResolution ? geometry(maxResolution).resolution : modelResolution(model);
  const fileThreshold = occ && occ.densityThreshold > 0 && Number.isFinite(occ.densityThreshold) ? occ.densityThreshold : densityThreshold(model.bounds, FALLBACK_THRESHOLD_RESOLUTION, FALLBACK_ALPHA);
  const frames = Math.min(Math.max(model.num_frames, 1), MAX_SLICES);
  const eyes = cameras.map((c) => [c.m[12], c.m[13], c.m[14]]);
  const fit = (g, candidates, outside) => {
    const index = g.indexLen * 4;
    const floor = index + candidates.length * g.slotBytes;
    if (floor > budget) return { need: floor };
    const { stat, dyn, cells } = sortBricks(g, model, layout, params, occ, candidates);
    const fixed = index + stat.length * g.slotBytes + cells.length * 4 + dyn.length * 4;
    const perSlice = dyn.length * g.slotBytes;
    const slices = dyn.length ? Math.max(frames, 2) : 0;
    const resident = perSlice ? Math.min(Math.floor(Math.max(budget - fixed, 0) / perSlice), slices) : slices;
    if (fixed > budget || (slices > 0 && resident < 2)) return { need: fixed + perSlice * Math.min(slices, 2) };
    const cell = cellWorldSize(model.bounds, g.resolution);
    return {
      plan: {
        geometry: g,
        requested,
        eyes,
        bounds: model.bounds,
        staticBricks: stat,
        dynamicBricks: dyn,
        dynamicCells: cells,
        sliceTimes: Array.from({ length: slices }, (_, k) => f(k / Math.max(slices - 1, 1))),
        residentSlices: resident,
        densityThreshold: Math.max(fileThreshold, 0),
        proposalThreshold: f(f(-Math.log(f(1 - f(Math.min(Math.max(minProposalAlpha, 0), 0.999999))))) / cell),
        occupancy: occ,
        bytesBound: fixed + resident * perSlice,
        budget,
        outsideBricks: outside,
        outside: outsidePolicy,
      },
    };
  };
  for (let r = requested; ; r /= 2) {
    const g = geometry(r);
    // The index alone over the budget: no plan at this resolution (as `fit` finds, sooner).
    if (g.indexLen * 4 > budget && r > MIN_VOLUME_RESOLUTION) continue;
    const candidates = [];
    for (let z = 0; z < g.perSide; z++)
      for (let y = 0; y < g.perSide; y++)
        for (let x = 0; x < g.perSide; x++) if (!occ || occ.anyIn([x, y, z], [x + 1, y + 1, z + 1], g.perSide)) candidates.push(x + g.perSide * (y + g.perSide * z));
    const leaveOut = outsidePolicy !== "bake" && cameras.length > 0;
    // Every occupied brick first, unless those outside the views always go.
    let need = Infinity;
    let res;
    if (!(leaveOut && outsidePolicy === "exact")) {
      res = fit(g, candidates, []);
      if (res.plan) return res.plan;
      need = res.need;
    }
    if (leaveOut) {
      // More bricks in view than the budget holds slots for: no plan with them either.
      const slots = r > MIN_VOLUME_RESOLUTION ? Math.floor((budget - g.indexLen * 4) / g.slotBytes) : Infinity;
      const inView = bricksInView(g, model.bounds, cameras, candidates, slots);
      const seen = inView ? candidates.filter((b) => inView[b]) : [];
      const outside = inView ? candidates.filter((b) => !inView[b]) : [];
      // (With none outside, "auto" has tried these bricks above.)
      if (outside.length || (inView && outsidePolicy === "exact")) {
        res = fit(g, seen, outside);
        if (res.plan) return res.plan;
        need = Math.min(need, res.need);
      }
    }
    if (r <= MIN_VOLUME_RESOLUTION) {
      throw new Error(`even a ${r}^3 volume needs ${(need / 1048576).toFixed(1)} MiB, more than its budget of ${(budget / 1048576).toFixed(1)} MiB (?volume-budget=MiB)`);
    }
  }
}

/** A line for the user when the budget made the plan coarser or left bricks out (msth-core
 * `BakePlan::note`), or null. */
export function planNote(plan) {
  const notes = [];
  const mib = Math.floor(plan.budget / 1048576);
  if (plan.outsideBricks.length && plan.outside === "exact") notes.push(`${plan.outsideBricks.length} occupied bricks no camera of the file looks into are left out (?volume-outside=exact); rays that reach them are rendered exactly`);
  else if (plan.outsideBricks.length) notes.push(`${plan.outsideBricks.length} occupied bricks no camera of the file looks into are left out, so that the volume can be ${plan.geometry.resolution}^3 cells within ${mib} MiB; rays that reach them are rendered exactly (?volume-outside=bake keeps them at a coarser resolution)`);
  if (plan.geometry.resolution < plan.requested) notes.push(`the volume is ${plan.geometry.resolution}^3 cells instead of ${plan.requested}^3, which would not fit ${mib} MiB`);
  if (plan.residentSlices < plan.sliceTimes.length) notes.push(`${plan.residentSlices} of ${plan.sliceTimes.length} time slices fit at once`);
  return notes.length ? notes.join("; ") : null;
}

/** msth-core `reference_direction`: the mean direction from the cameras to world point `x`. */
function referenceDirection(eyes, x) {
  const s = [0, 0, 0];
  let first = null;
  for (const e of eyes) {
    const d = [x[0] - e[0], x[1] - e[1], x[2] - e[2]];
    const n = Math.hypot(...d);
    const u = n > 0 ? d.map((v) => v / n) : [0, 0, 0];
    first ??= u;
    for (let k = 0; k < 3; k++) s[k] += u[k];
  }
  const n = Math.hypot(...s);
  if (n > 0.1 * eyes.length && n > 0) return s.map((v) => v / n);
  if (first && Math.hypot(...first) > 0) return first;
  return [0, 0, -1];
}

/** Index of `x` in the ascending array `a`, or -1. */
function search(a, x) {
  let [lo, hi] = [0, a.length];
  while (lo < hi) {
    const m = (lo + hi) >>> 1;
    if (a[m] < x) lo = m + 1;
    else hi = m;
  }
  return lo < a.length && a[lo] === x ? lo : -1;
}

/** msth-core `bake::owner`: the brick and local vertex that own border vertex `v` of `brick`
 * (a coordinate equal to `B` belongs to the next brick along that axis), or null past the last. */
function owner(g, brick, v) {
  const bc = [brick % g.perSide, Math.floor(brick / g.perSide) % g.perSide, Math.floor(brick / (g.perSide * g.perSide))];
  const local = v.slice();
  for (let a = 0; a < 3; a++) {
    if (v[a] !== g.brick) continue;
    if (bc[a] + 1 >= g.perSide) return null;
    bc[a]++;
    local[a] = 0;
  }
  return [bc[0] + g.perSide * (bc[1] + g.perSide * bc[2]), local];
}

/**
 * The `eval_points` input for `bricks[first..first + n]` of the ascending set `bricks` at time
 * `time` (8 values a point: unit point, time, reference direction, kind): the vertices each
 * brick evaluates itself (msth-core `bake::evaluates`: its own `B^3` and the border vertices no
 * brick of the set owns), then with `proposal` the same vertices again as kind 1 (the proposal
 * field's density, for the cell bits). Returns `{ points, slots }`: `slots[j]` the flat vertex
 * (`brick in set * (B + 1)^3 + x + (B + 1) (y + (B + 1) z)`) point `j` fills.
 */
export function bakePoints(plan, bricks, first, n, time, dynamic, proposal) {
  const g = plan.geometry;
  const v1 = g.brick + 1;
  const slots = [];
  const us = [];
  for (let k = first; k < first + n; k++) {
    const o = brickOrigin(g, bricks[k]);
    for (let z = 0; z < v1; z++)
      for (let y = 0; y < v1; y++)
        for (let x = 0; x < v1; x++) {
          if (x === g.brick || y === g.brick || z === g.brick) {
            const own = owner(g, bricks[k], [x, y, z]);
            if (own && search(bricks, own[0]) >= 0) continue;
          }
          slots.push(k * g.nv + x + v1 * (y + v1 * z));
          us.push([f((o[0] + x) / g.resolution), f((o[1] + y) / g.resolution), f((o[2] + z) / g.resolution)]);
        }
  }
  const m = slots.length;
  const points = new Float32Array(m * 8 * (proposal ? 2 : 1));
  const t = Math.min(Math.max(time, 0), 1);
  const kind = dynamic ? 2 : 3;
  us.forEach((u, j) => {
    const d = referenceDirection(plan.eyes, fromUnit(plan.bounds, u));
    points.set([u[0], u[1], u[2], t, d[0], d[1], d[2], kind], j * 8);
    if (proposal) points.set([u[0], u[1], u[2], time, d[0], d[1], d[2], 1], (m + j) * 8);
  });
  return { points, slots: Uint32Array.from(slots) };
}

/**
 * Stores `eval_points`'s output for `bakePoints` into the set's vertex arrays: `values` (4
 * binary16 a vertex, as the volume holds them: density pre-activation, red, green, blue) and,
 * with the proposal, `prop` (its density, f32). Throws on a value that is not finite.
 */
export function storeVertices(slots, evaluated, values, prop) {
  const m = slots.length;
  const ordered = new Float32Array(m * 4);
  for (let j = 0; j < m; j++) {
    const e = evaluated.subarray(j * 4, j * 4 + 4);
    if (!e.every(Number.isFinite)) throw new Error("the field is not finite at a vertex of the volume: the file's parameters cannot be played");
    ordered.set([e[3], e[0], e[1], e[2]], j * 4);
    if (prop) prop[slots[j]] = evaluated[(m + j) * 4 + 3];
  }
  const h = toBinary16(ordered);
  for (let j = 0; j < m; j++) values.set(h.subarray(j * 4, j * 4 + 4), slots[j] * 4);
}

/** msth-core `bake::fill_borders`: every border vertex another brick of the set owns, copied
 * from it (`vals`, 4 values a vertex, and `prop`, 1 a vertex, when given). */
export function fillBorders(plan, bricks, vals, prop) {
  const g = plan.geometry;
  const v1 = g.brick + 1;
  for (let k = 0; k < bricks.length; k++)
    for (let z = 0; z < v1; z++)
      for (let y = 0; y < v1; y++)
        for (let x = 0; x < v1; x++) {
          if (x < g.brick && y < g.brick && z < g.brick) continue;
          const own = owner(g, bricks[k], [x, y, z]);
          if (!own) continue;
          const j = search(bricks, own[0]);
          if (j < 0) continue;
          const src = j * g.nv + own[1][0] + v1 * (own[1][1] + v1 * own[1][2]);
          const dst = k * g.nv + x + v1 * (y + v1 * z);
          vals.copyWithin(dst * 4, src * 4, src * 4 + 4);
          if (prop) prop[dst] = prop[src];
        }
}

/**
 * The cell bits of the set `bricks` from its vertex arrays (`storeVertices`, `fillBorders`:
 * `values` binary16, 4 a vertex): msth-core `cell_bits`, a cell can hold density when a corner
 * reaches the plan's threshold, and the proposal's, and the occupancy grid has it.
 */
export function cellBits(plan, bricks, values, prop) {
  const g = plan.geometry;
  const b = g.brick;
  const v1 = b + 1;
  const occupied = new Uint32Array(bricks.length * g.fw);
  const gate = prop && plan.proposalThreshold > 0;
  for (let k = 0; k < bricks.length; k++) {
    const o = brickOrigin(g, bricks[k]);
    for (let cz = 0; cz < b; cz++)
      for (let cy = 0; cy < b; cy++)
        for (let cx = 0; cx < b; cx++) {
          let max = -Infinity;
          let maxP = -Infinity;
          for (let c = 0; c < 8; c++) {
            const v = k * g.nv + cx + (c & 1) + v1 * (cy + ((c >> 1) & 1) + v1 * (cz + (c >> 2)));
            max = Math.max(max, f16ToF32(values[v * 4]));
            // NaN counts as dense: the test never hides a broken field.
            if (gate) maxP = Math.max(maxP, Number.isNaN(prop[v]) ? Infinity : prop[v]);
          }
          if (Math.exp(Math.min(max, 88)) < plan.densityThreshold || (gate && maxP < plan.proposalThreshold)) continue;
          const cell = [o[0] + cx, o[1] + cy, o[2] + cz];
          if (plan.occupancy && !plan.occupancy.anyIn(cell, [cell[0] + 1, cell[1] + 1, cell[2] + 1], g.resolution)) continue;
          const bit = cx + b * (cy + b * cz);
          occupied[k * g.fw + (bit >>> 5)] |= 1 << (bit & 31);
        }
  }
  return occupied;
}

const popcount = (w) => {
  let n = 0;
  for (let x = w >>> 0; x; x &= x - 1) n++;
  return n;
};

/**
 * The volume from the plan and its baked static bricks (msth-core `Volume::allocate` and
 * `set_static`): the brick index, the kept slots' bits and values, the dynamic bricks' cells.
 */
export function assembleVolume(plan, baked) {
  const g = plan.geometry;
  const index = new Uint32Array(g.indexLen).fill(EMPTY_BRICK);
  for (const b of plan.outsideBricks) index[b] = OUTSIDE_BRICK;
  plan.dynamicBricks.forEach((b, d) => (index[b] = (DYNAMIC_BRICK | d) >>> 0));
  const keep = [];
  let occupiedCells = 0;
  plan.staticBricks.forEach((b, k) => {
    let o = 0;
    for (let w = 0; w < g.fw; w++) o += popcount(baked.occupied[k * g.fw + w]);
    if (!o) return;
    occupiedCells += o;
    index[b] = keep.length;
    keep.push(k);
  });
  const occupied = new Uint32Array(keep.length * g.fw);
  const values = new Uint16Array(keep.length * g.nv * 4);
  keep.forEach((k, s) => {
    occupied.set(baked.occupied.subarray(k * g.fw, (k + 1) * g.fw), s * g.fw);
    values.set(baked.values.subarray(k * g.nv * 4, (k + 1) * g.nv * 4), s * g.nv * 4);
  });
  return {
    geometry: g,
    index,
    occupied,
    values,
    slots: keep.length,
    /** Occupied bricks left out (rays that reach them are drawn exactly). */
    outside: plan.outsideBricks.length,
    dynamic: { bricks: plan.dynamicBricks, cells: plan.dynamicCells, times: plan.sliceTimes, slices: plan.sliceTimes.map(() => null) },
    stats: { bricks: keep.length + plan.dynamicBricks.length, occupiedCells, dynamicBricks: plan.dynamicBricks.length, slices: plan.sliceTimes.length },
  };
}

/** msth-core `DynamicPart::around`: the slices either side of `t` and the second's weight. */
export function sliceAround(times, t) {
  const k = times.length;
  if (!k) return null;
  if (k === 1) return [0, 0, 0];
  const s = Math.min(Math.max(t, 0), 1) * (k - 1);
  const k0 = Math.min(Math.floor(s), k - 1);
  const w = s - k0;
  if (w <= 1e-6 || k0 + 1 >= k) return [k0, k0, 0];
  if (w >= 1 - 1e-6) return [k0 + 1, k0 + 1, 0];
  return [k0, k0 + 1, w];
}

/**
 * The two buffers `volume_march` reads and the offsets of its `VolumeU` uniform (msth-gpu
 * `GpuVolume::new`): `words` (index, static bits, dynamic cells, slice regions A and B) and
 * `values` (static slots, slice regions A and B; 4 binary16 a vertex).
 */
export function volumeLayout(vol) {
  const g = vol.geometry;
  const nd = vol.dynamic.bricks.length;
  const atOccupied = vol.index.length;
  const atCells = atOccupied + vol.slots * g.fw;
  const atA = atCells + nd * g.fw;
  const atB = atA + nd * g.fw;
  const words = atB + nd * g.fw;
  const values = vol.slots * g.nv + 2 * nd * g.nv;
  return { atOccupied, atCells, regionWords: [atA, atB], regionValues: [vol.slots * g.nv, (vol.slots + nd) * g.nv], words, values };
}

/** Points one step of a bake evaluates at most (the page stays responsive between steps). */
const BAKE_POINTS = 1 << 17;

/** Bakes the ascending set `bricks` at `time` (`dynamic`: a slice, with the 4D lookups the
 * mask asks for) through `scene.evalPoints`, a batch at a time: `{ values, occupied, evaluated }`,
 * or null on `abort()`. */
async function bakeSet(scene, plan, bricks, time, dynamic, onProgress, abort) {
  const g = plan.geometry;
  const gate = plan.proposalThreshold > 0;
  const per = Math.max(1, Math.floor(BAKE_POINTS / (g.nv * (gate ? 2 : 1))));
  // Binary16 from the start: the set's values take what the volume will (within the budget).
  const values = new Uint16Array(bricks.length * g.nv * 4);
  const prop = gate ? new Float32Array(bricks.length * g.nv) : null;
  let evaluated = 0;
  for (let first = 0; first < bricks.length; first += per) {
    if (abort()) return null;
    const n = Math.min(per, bricks.length - first);
    const { points, slots } = bakePoints(plan, bricks, first, n, time, dynamic, gate);
    storeVertices(slots, await scene.evalPoints(points), values, prop);
    evaluated += points.length / 8;
    onProgress((first + n) / bricks.length);
  }
  fillBorders(plan, bricks, values, prop);
  return { values, occupied: cellBits(plan, bricks, values, prop), evaluated };
}

/**
 * Bakes the plan's static bricks on the GPU (`scene`: renderer.js's, with the file's static
 * parameters uploaded): the volume (`assembleVolume`) with `stats.evaluated`, or null when
 * `abort()` stopped it. `onProgress(fraction)` follows it.
 */
export async function bakeVolume(scene, plan, { onProgress = () => {}, abort = () => false } = {}) {
  const t0 = performance.now();
  const baked = await bakeSet(scene, plan, plan.staticBricks, 0, false, onProgress, abort);
  if (!baked) return null;
  const vol = assembleVolume(plan, baked);
  vol.stats.evaluated = baked.evaluated;
  vol.stats.ms = performance.now() - t0;
  vol.residentSlices = plan.residentSlices;
  return vol;
}

/**
 * Bakes time slice `k` of `vol`'s dynamic bricks; `scene` must hold the parameters at the
 * slice's time (its chunk's 4D table). Keeps at most the plan's resident slices, dropping the
 * one farthest from `k` (msth-core `Volume::set_slice`). Resolves to the points evaluated.
 */
export async function bakeSlice(scene, plan, vol, k) {
  const baked = await bakeSet(scene, plan, plan.dynamicBricks, plan.sliceTimes[k], true, () => {}, () => false);
  const d = vol.dynamic;
  for (;;) {
    const held = d.slices.map((s, j) => (s ? j : -1)).filter((j) => j >= 0);
    if (held.length < Math.max(vol.residentSlices, 1)) break;
    const far = held.reduce((a, j) => (Math.abs(j - k) > Math.abs(a - k) ? j : a), held[0]);
    d.slices[far] = null;
  }
  d.slices[k] = { values: baked.values, occupied: baked.occupied };
  return baked.evaluated;
}
