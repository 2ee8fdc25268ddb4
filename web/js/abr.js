// What the page fetches next, and how many progressive layers (docs/format.md §6.6) each time
// chunk gets: the adaptive-bitrate policy of msth-player's `abr` module, the same function in
// the same arithmetic (f32 where the Rust code computes in f32), so that the page and `msth
// play` choose the same requests on the same link (tests/tests/web_layers.rs runs `simulate`
// in both). Read player/src/abr.rs for the rules; in short:
// 1. layer 0 of the static part; 2. layer 0 of the chunks needed within BASE_AHEAD seconds;
// 3. per chunk in playback order, the finer layers whose bytes fit before it plays at SAFETY
//    times the measured rate, never pushing a later chunk's layer 0 late; 4. paused or
//    unmeasured: every layer of the chunk on screen first; 5. then the rest, coarse first,
//    unless a request could delay a missing layer 0.

import { KIND, sectionPosition, chunkForTime } from "./format.js";

export const SAFETY = 0.8;
export const BASE_AHEAD = 10.0;
export const MAX_GAP = 4096;
const f32 = Math.fround;

/** Chunks in playback order from the one covering `playback.time`, with the seconds until each
 * is needed (null when paused). `ix`: a parsed prefix or a `Decoder`. */
function chunkOrder(ix, playback) {
  const spans = ix.metadata.chunks;
  const n = spans.length;
  const time = playback ? f32(playback.time) : 0;
  const first = chunkForTime(ix.metadata, time) ?? 0;
  const out = [];
  for (let j = 0; j < n; j++) {
    const c = (first + j) % n;
    let wait = null;
    if (playback && playback.secondsPerUnit > 0) {
      if (j === 0) wait = Math.max(f32(f32(spans[c].t_end) - time), 0) * playback.secondsPerUnit;
      else {
        let ahead = f32(f32(spans[c].t_start) - time);
        if (ahead < 0) ahead = f32(ahead + 1);
        wait = ahead * playback.secondsPerUnit;
      }
    }
    out.push([c, wait]);
  }
  return out;
}

/** Index positions chunk `c` needs for layer `l`. */
function layerSections(ix, c, l) {
  const out = [];
  const add = (i) => i !== null && out.push(i);
  if (l > 0) {
    add(sectionPosition(ix, KIND.proposal, 0, l));
    add(sectionPosition(ix, KIND.static, 0, l));
    add(sectionPosition(ix, KIND.shared, 0, l));
  }
  add(sectionPosition(ix, KIND.dynamic, c, l));
  return out;
}

/** `[[chunk, layers], ...]` in playback order (msth-player's `plan_layers`). */
export function planLayers(ix, decoded, playback, rate) {
  const layers = ix.layers.length;
  const missing = (i) => !decoded[i];
  const order = chunkOrder(ix, playback);
  const n = order.length;
  const budget = order.map(([, wait]) => (wait !== null && rate !== null ? SAFETY * rate * wait : Infinity));
  const base = order.map(([c]) => layerSections(ix, c, 0).filter(missing).reduce((s, i) => s + ix.sections[i].length, 0));
  const slack = new Array(n).fill(Infinity);
  for (let j = n - 2; j >= 0; j--) slack[j] = Math.min(budget[j + 1], slack[j + 1]) - base[j + 1];
  const counted = new Set();
  let pending = 0;
  return order.map(([c], j) => {
    let chosen = 0;
    for (let l = 0; l < layers; l++) {
      const added = layerSections(ix, c, l).filter((i) => missing(i) && !counted.has(i));
      const bytes = added.reduce((s, i) => s + ix.sections[i].length, 0);
      const total = pending + bytes;
      if (l > 0 && (total > budget[j] || total > slack[j])) break;
      pending = total;
      for (const i of added) counted.add(i);
      chosen = l + 1;
    }
    return [c, chosen];
  });
}

/** The next request `[start, end)` of index positions, or null (msth-player's `next_request`).
 * `playback`: `{ time, secondsPerUnit }` or null; `rate`: bytes/s or null. */
export function nextRequest(ix, decoded, playback, rate) {
  const missing = (i) => !decoded[i];
  const statics = [];
  for (let i = 0; i < ix.beforeFirstFrame; i++) if (missing(i)) statics.push(i);
  if (statics.length) {
    const first = statics[0];
    const last = statics[statics.length - 1];
    let contiguous = statics.length === last - first + 1;
    for (let i = first; contiguous && i < last; i++) {
      const a = ix.sections[i];
      const b = ix.sections[i + 1];
      contiguous = b.offset >= a.offset + a.length && b.offset - (a.offset + a.length) <= MAX_GAP;
    }
    return contiguous ? [first, last + 1] : [first, first + 1];
  }
  if (ix.metadata.chunks.length === 0) {
    for (let l = 1; l < ix.layers.length; l++) {
      for (const kind of [KIND.proposal, KIND.static]) {
        const i = sectionPosition(ix, kind, 0, l);
        if (i !== null && missing(i)) return [i, i + 1];
      }
    }
    return null;
  }
  const order = chunkOrder(ix, playback);
  for (const [c, wait] of order) {
    if (wait === null || wait <= BASE_AHEAD) {
      const i = sectionPosition(ix, KIND.dynamic, c, 0);
      if (i !== null && missing(i)) return [i, i + 1];
    }
    if (wait === null) break;
  }
  for (const [c, k] of planLayers(ix, decoded, playback, rate)) {
    for (let l = 0; l < k; l++) {
      const i = layerSections(ix, c, l).find(missing);
      if (i !== undefined) return [i, i + 1];
    }
  }
  const firstMissingBase = order.find(([c]) => {
    const i = sectionPosition(ix, KIND.dynamic, c, 0);
    return i !== null && missing(i);
  });
  for (let l = 0; l < ix.layers.length; l++) {
    for (const [c] of order) {
      for (const i of layerSections(ix, c, l)) {
        if (!missing(i)) continue;
        let fits = true;
        if (firstMissingBase && firstMissingBase[1] !== null && rate !== null) fits = ix.sections[i].length <= SAFETY * rate * firstMissingBase[1];
        return fits ? [i, i + 1] : null;
      }
    }
  }
  return null;
}

/** Throughput over the last requests (msth-player's `RateMeter`). */
export class RateMeter {
  static WINDOW = 1.0;
  constructor() {
    this.samples = [];
  }
  add(bytes, seconds) {
    if (!(Number.isFinite(seconds) && seconds >= 0)) return;
    this.samples.unshift([bytes, Math.max(seconds, 1e-6)]);
    let total = 0;
    let keep = 0;
    for (const [, s] of this.samples) {
      keep++;
      total += s;
      if (total >= RateMeter.WINDOW) break;
    }
    this.samples.length = keep;
  }
  rate() {
    if (!this.samples.length) return null;
    let b = 0;
    let s = 0;
    for (const [bb, ss] of this.samples) {
      b += bb;
      s += ss;
    }
    return b / s;
  }
}

/** The layers a frame at time `t` is drawn with, from `decoded` (0: not ready). */
function readyLayers(ix, decoded, t) {
  for (let i = 0; i < ix.beforeFirstFrame; i++) if (!decoded[i]) return 0;
  const c = chunkForTime(ix.metadata, t);
  let n = 0;
  while (n < ix.layers.length) {
    const need = c === null ? [KIND.proposal, KIND.static].map((k) => sectionPosition(ix, k, 0, n)).filter((i) => i !== null) : layerSections(ix, c, n);
    if (!need.every((i) => decoded[i])) break;
    n++;
  }
  return n;
}

/**
 * A player on a simulated link (msth-player's `simulate`): `rateAt(t)` bytes/s at wall-clock
 * time t, `latency` seconds per request, `frames` frames at `fps`, looping over the model's
 * frames. Returns `{ requests: [{at, sections: [s, e], bytes, rate}], frames: [{at, time,
 * layers}], firstFrame, stalls: [[start, length]] }`.
 */
export function simulate(ix, rateAt, latency, frames, fps) {
  const trace = { requests: [], frames: [], firstFrame: 0, stalls: [] };
  const decoded = new Array(ix.sections.length).fill(false);
  const meter = new RateMeter();
  const transfer = (start, bytes) => {
    let t = start + latency;
    let left = bytes;
    while (left > 0) {
      const r = Math.max(rateAt(t), 1);
      const step = 0.01;
      if (left <= r * step) {
        t += left / r;
        left = 0;
      } else {
        left -= r * step;
        t += step;
      }
    }
    return t;
  };
  let now = transfer(0, ix.headerSize);
  meter.add(ix.headerSize, now);
  const clip = Math.max(ix.metadata.model.num_frames, 1);
  const secondsPerUnit = clip / Math.max(fps, 1e-3);
  const frameTime = (f) => (clip > 1 ? f32(f32(f % clip) / f32(clip - 1)) : 0);
  const st = { next: 0, due: null, stalledSince: null };
  const show = (until) => {
    while (st.next < frames) {
      const at = st.stalledSince !== null ? until : st.due !== null ? st.due : until;
      if (at > until) return;
      const t = frameTime(st.next);
      const layers = readyLayers(ix, decoded, t);
      if (layers === 0) {
        if (st.due !== null && st.stalledSince === null) st.stalledSince = at;
        return;
      }
      if (st.stalledSince !== null) {
        trace.stalls.push([st.stalledSince, at - st.stalledSince]);
        st.stalledSince = null;
      }
      if (!trace.frames.length) trace.firstFrame = at;
      trace.frames.push({ at, time: t, layers });
      st.next++;
      st.due = at + 1 / fps;
    }
  };
  let guard = 0;
  while (st.next < frames && guard < 1000000) {
    guard++;
    show(now);
    if (st.next >= frames) break;
    const playback = { time: frameTime(st.next), secondsPerUnit };
    const r = nextRequest(ix, decoded, playback, meter.rate());
    if (r) {
      let bytes = 0;
      for (let i = r[0]; i < r[1]; i++) bytes += ix.sections[i].length;
      const end = transfer(now, bytes);
      trace.requests.push({ at: now, sections: r, bytes, rate: meter.rate() });
      if (st.due !== null) show(end);
      meter.add(bytes, end - now);
      for (let i = r[0]; i < r[1]; i++) decoded[i] = true;
      now = end;
    } else {
      now = st.due !== null ? Math.max(st.due, now) : now;
    }
  }
  return trace;
}
