// The web player's page: picks a model from `/models`, streams it (stream.js), keeps the
// decoded flat parameter buffer on the GPU (renderer.js, the native renderer's WGSL) and drives
// the UI: the file's cameras as starting views, orbit / pan / zoom with mouse and touch, a
// timeline with play/pause and scrubbing, a loading bar of the streamed byte ranges, and the
// frame rate and the resolution being drawn.
//
// Resolution policy (stated on the page): while the camera moves or the timeline plays, frames
// are drawn at a reduced resolution, 1, 1/2, 1/4 or 1/8 of the full size per side, adapted
// frame by frame so that a frame fits its budget (1/30 s while moving, one model frame while
// playing); while moving, full size only where the GPU's measured rate draws a full-size frame
// in half the budget (so that a drag answers at once);
// when the camera stops (STILL_MS after the last input) and playback is paused, the view is
// drawn again one step finer per frame (1/8, 1/4, 1/2, full) until it is at full resolution.
// The page's first frame is drawn at 1/8 and refined the same way, so that a slow GPU shows a
// picture after 1/64 of a full frame's work instead of nothing until the full frame is done.
// Reduced frames are interlaced (renderer.js): a still view refined from 1/8 to full size
// renders each pixel once, so its full-size frame costs what a frame drawn at full size at once
// costs.
// The timeline advances with the clock at the model's frame
// rate; when the GPU cannot keep up even at 1/8, frames are dropped, not slowed down.
// Incremental playback (stated on the page): when the time moves (playing or scrubbing) under a
// camera that has been still for STILL_MS, the page renders PROBES.count full-size probe frames
// at times spread over [0, 1] (`msth play`'s probes); pixels whose colour moves by at most
// PROBES.tolerance from the first probe's at every other probe keep the first probe's colour, and
// every frame of that camera re-renders only the others, at full size. Moving the camera drops
// the cache. Only where the probes take at most CACHE_BUDGET_MS at the GPU's measured rate (on a
// software GPU, small sizes only), and while playing only where a full-size frame takes at most
// PLAY_CACHE_FRAMES model frames (the frame rate comes first; paused, scrubbing uses it).
// Play-time volume (stated on the page): once the view has reached full size (at once when the
// video plays or the view moves), the page bakes the file's
// static field into a sparse volume on the GPU (volume.js: the native players' plan and bake;
// `eval_points` evaluates the vertices), within a quarter of the GPU's storage buffer limit. Once
// it is ready, the frames of a moving camera or of playing video (but the incremental frames of
// a still camera) are drawn through it (`volume_march`, the native `volume.wgsl`): a few reads a
// sample instead of the hash grids and MLPs, at the resolution the policy above adapts to the
// volume's own frame times; a view that comes to rest is drawn again exactly, as the native
// players do. The dynamic bricks' time slices are baked when a frame first needs them, and rays
// that reach a brick the volume left out are drawn exactly. `exact=1` keeps every frame on the
// exact path.
// Samples per ray (also stated on the page): the model's own on a hardware GPU, `fast` (fewer,
// docs/tradeoff.md) on a fallback (software) adapter; the samples menu changes them.
//
// URL parameters: `model=NAME` (a name from /models), `camera=K` (start at the file's camera K,
// the default: camera 0), `view=AZ,EL,DIST` (degrees, degrees, distance: the same viewpoint as
// `msth play --path view:AZ,EL,DIST`, instead of a file camera), `t=T` (normalised time, starts
// paused there), `size=WxH` (render size, as `msth play --size`), `play=0|1`, `skip=0` (evaluate
// every sample: the file's occupancy grid unused, as `msth play --no-skip-empty`),
// `samples=file|full|fast|faster|P,M` (samples per ray, as `msth play --samples`; the samples menu;
// default file: the counts the file stores for playback, the model's own without them),
// `incremental=0` (no static cache: every frame re-renders every pixel), `exact=1` (no play-time
// volume: every frame from the hash grids and MLPs, as `msth play --exact`), `volume-budget=MIB`
// (the volume's memory budget, as `msth play --volume-budget`), `volume-outside=auto|exact|bake`
// (the bricks no file camera looks into, as `msth play --volume-outside`), `volume=wait` (bake the volume
// before the first frame: tests and benchmarks), `deadline=S` and
// `stall=S` (the loader's deadlines in seconds, as `msth play --deadline` and `--stall-timeout`).
//
// `window.msth` exposes the player's state to tests and to the console (see `hooks` below).

import { loaderOptions, ModelStream } from "./stream.js";
import { cameraFromJson, makeRig, Orbit, templateCamera } from "./camera.js";
import { Renderer, NoWebGpu, playSamples } from "./renderer.js";
import { bakeSlice, bakeVolume, planNote, planVolume, sliceAround, volumeLayout } from "./volume.js";
import { KIND, LIMITS, PROBES, SAMPLE_LEVELS } from "./generated/contract.js";

const $ = (id) => document.getElementById(id);
/** Reduced resolutions (per side) while moving or playing, finest first. */
const SCALES = [1, 1 / 2, 1 / 4, 1 / 8];
/** Frame budget while the camera moves (ms). */
const MOVING_BUDGET_MS = 1000 / 30;
/** The play-time volume's default budget (MiB) on a software adapter (SwiftShader): a quarter of
 * lavapipe's 128 MiB binding limit, as `msth play --gpu` gets there; at the hardware default (a
 * quarter of SwiftShader's 1 GiB) the demo model's bake takes about 8 minutes there. */
const SOFTWARE_VOLUME_MIB = 32;
/** The camera counts as still this long after the last input (ms). */
const STILL_MS = 250;
/** The static cache (incremental playback) is built only where its probe frames take at most
 * this long at the GPU's measured rate (ms). */
const CACHE_BUDGET_MS = 10_000;
/** While playing, the static cache is used only where a full-size frame takes at most this many
 * model frames at the GPU's measured rate. */
const PLAY_CACHE_FRAMES = 4;
const params = new URLSearchParams(location.search);

const hooks = {
  /** Set once the first frame (drawn at 1/8 of the full size per side) has been rendered (ms since navigation start). */
  firstFrameMs: null,
  /** Set once the first frame at full size has been rendered (ms since navigation start). */
  firstFullFrameMs: null,
  /** The size the first frame was drawn at. */
  firstFrameSize: null,
  /** Frames rendered so far. */
  frames: 0,
  /** Whether the last frame's live lists put the samples whose mask skips the 4D lookup apart,
   * for `pass_proposal3` and `pass_density3` (false until those are compiled; `?split=wait`). */
  lastSplit3: false,
  /** How the GPU holds the hash tables, `"f32"` or `"f16"` (`?tables=`), once the kernels exist. */
  tables: null,
  /** The most hash-table values held clamped at once (binary16 tables: beyond ±65504). */
  clampedTables: 0,
  error: null,
  state: null,
  /** Milestones in ms since navigation start: adapter, prefix, pipeline, params, firstFrame. */
  timings: {},
  noWebGpu: false,
  /** The play-time volume: `{ state: "off" | "waiting" | "baking" | "ready" | "failed", progress,
   * note, error, resolution, bytes, ms, evaluated, slices }` (set once the kernels exist). */
  volume: null,
  /** Whether the last frame was drawn through the volume, and how many of its rays exactly. */
  lastVolume: false,
  lastOutside: 0,
  /** Frames drawn through the volume so far. */
  volumeFrames: 0,
};
window.msth = hooks;

function showMessage(text) {
  const m = $("message");
  m.textContent = text;
  m.hidden = false;
}

function fail(e) {
  console.error(e);
  hooks.error = String(e && e.message ? e.message : e);
  showMessage(hooks.error);
}

function parseSize(s) {
  const m = /^(\d+)[xX](\d+)$/.exec(s || "");
  if (!m) return null;
  const [w, h] = [Number(m[1]), Number(m[2])];
  return w >= 1 && h >= 1 && w <= 4096 && h <= 4096 ? [w, h] : null;
}

function parseView(s) {
  if (!s) return null;
  const v = s.split(",").map(Number);
  return v.length === 3 && v.every(Number.isFinite) && v[2] > 0 ? v : null;
}

async function listModels() {
  const sel = $("model");
  try {
    const resp = await fetch("models", { cache: "no-store" });
    if (!resp.ok) throw new Error(`/models: HTTP ${resp.status}`);
    const rows = await resp.json();
    sel.innerHTML = "";
    if (!rows.length) sel.append(new Option("no models served", ""));
    for (const r of rows) sel.append(new Option(`${r.name} (${(r.bytes / 1e6).toFixed(2)} MB)`, r.name));
    return rows;
  } catch (e) {
    sel.innerHTML = "";
    sel.append(new Option("cannot list models", ""));
    throw e;
  }
}

function formatBytes(n) {
  return n >= 1e6 ? `${(n / 1e6).toFixed(2)} MB` : `${(n / 1e3).toFixed(1)} kB`;
}

function drawLoading(stream) {
  const p = stream.progress();
  const box = $("loading-ranges");
  const spans = stream.ranges.map(([a, b]) => [a, b, ""]);
  if (stream.inflight) {
    const { start, end, got } = stream.inflight;
    spans.push([start, Math.min(end, start + got), "inflight"]);
  }
  box.replaceChildren(
    ...spans.map(([a, b, cls]) => {
      const s = document.createElement("span");
      s.style.left = `${(100 * a) / p.fileLength}%`;
      s.style.width = `${Math.max((100 * (b - a)) / p.fileLength, 0.2)}%`;
      if (cls) s.className = cls;
      return s;
    }),
  );
  const total = stream.decoder.layers.length;
  const layers = total > 1 ? ` · layers ${stream.layersFor(stream.playback.time)}/${total}` : "";
  const rate = stream.rate();
  const mbit = rate ? ` · ${((8 * rate) / 1e6).toFixed(1)} Mbit/s` : "";
  $("loading-text").textContent = `${formatBytes(p.bytesReady)} / ${formatBytes(p.fileLength)} · ${p.sectionsReady}/${p.sections} sections${layers}${mbit}`;
  $("loading").dataset.complete = p.complete ? "1" : "0";
}

async function main() {
  const models = listModels().catch((e) => {
    fail(e);
    return [];
  });
  let renderer;
  try {
    renderer = await Renderer.adapter();
    hooks.timings.adapter = performance.now();
  } catch (e) {
    if (e instanceof NoWebGpu) {
      hooks.noWebGpu = true;
      showMessage(`This browser has no WebGPU (${e.message}). The msth player needs it: use a recent Chrome, Edge or Safari, or Firefox with WebGPU enabled.`);
      $("loading").hidden = true;
      await models;
      return;
    }
    throw e;
  }
  const rows = await models;
  let name = params.get("model");
  if (!name && rows.length) {
    name = (rows.find((r) => /demo/.test(r.name)) || rows[0]).name;
  }
  if (!name) {
    showMessage("No model is served here: start `msth serve DIR` with a folder of .msth files.");
    return;
  }
  const sel = $("model");
  if (![...sel.options].some((o) => o.value === name)) sel.append(new Option(name, name));
  sel.value = name;
  sel.onchange = () => {
    const q = new URLSearchParams(location.search);
    q.set("model", sel.value);
    location.search = q.toString();
  };
  const url = `models/${encodeURIComponent(name)}`;
  $("status").textContent = "loading…";
  const stream = await ModelStream.open(url, loaderOptions(params));
  hooks.timings.prefix = performance.now();
  const meta = stream.metadata;
  const size = parseSize(params.get("size"));
  const cameras = meta.cameras.map(cameraFromJson);
  const template = templateCamera(cameras, size);
  const rig = makeRig(meta.model.bounds, cameras, template);
  const view = parseView(params.get("view"));
  const orbit = view ? new Orbit(rig, view[0], view[1], view[2]) : new Orbit(rig);
  // The default view is one of the file's cameras: camera 0, the first training camera (the
  // trainer lists the training cameras first, the held-out ones after them).
  const camSel = $("camera");
  cameras.forEach((c, i) => camSel.append(new Option(`camera ${i} (${c.width}x${c.height})`, String(i))));
  camSel.append(new Option("free orbit", "free"));
  const camParam = Number(params.get("camera") ?? 0);
  const startCamera = Number.isInteger(camParam) && camParam >= 0 && camParam < cameras.length ? camParam : 0;
  if (!view && cameras.length) orbit.setCamera(cameras[startCamera]);
  camSel.value = orbit.fixed ? String(startCamera) : "free";
  const canvas = $("view");
  canvas.width = template.width;
  canvas.height = template.height;
  // Small renders are shown enlarged (pixelated) so that they can be handled.
  const shown = Math.max(1, Math.floor(Math.min(640 / template.width, 480 / template.height)));
  canvas.style.width = `${template.width * shown}px`;
  canvas.style.height = `${template.height * shown}px`;
  $("info").textContent = `${name}: ${meta.model.num_frames} frames, ${meta.param_count.toLocaleString()} parameters, ${meta.section_quant ? Object.entries(meta.section_quant).map(([k, v]) => `${k} ${v}`).join(" ") : meta.quant}, ${meta.chunks.length} chunks`;
  const modelFps = meta.frame_rate || 24;
  $("policy").textContent =
    `Resolution: while you move the camera, frames are drawn at 1/2 to 1/8 of ${template.width}x${template.height} per side (interpolated in between), ` +
    `adapted so that a frame takes at most ${MOVING_BUDGET_MS.toFixed(0)} ms, or at full size where the GPU draws one in half that; while the video plays, at full size when a frame fits one model frame ` +
    `(${(1000 / modelFps).toFixed(0)} ms at ${modelFps} fps), else reduced the same way; ` +
    `${STILL_MS} ms after the camera stops, paused, the view is refined one step per frame (1/8, 1/4, 1/2, full) up to full resolution; ` +
    `the first frame starts at 1/8 the same way. ` +
    `The timeline runs at the model's ${modelFps} fps: frames the GPU cannot draw in time are skipped. ` +
    `When the time moves under a still camera, the page renders ${PROBES.count} probe frames (t = 0 to 1) and then re-renders only the pixels whose colour changes by more than ${PROBES.tolerance} ` +
    `(where the GPU draws those frames within ${CACHE_BUDGET_MS / 1000} s; while the video plays, only where a full-size frame takes at most ${PLAY_CACHE_FRAMES} model frames).`;

  const tParam = params.get("t");
  const state = {
    t: tParam !== null && Number.isFinite(Number(tParam)) ? Math.min(1, Math.max(0, Number(tParam))) : 0,
    playing: params.get("play") === "1" || (tParam === null && params.get("play") !== "0"),
    /** A moving frame's budget (ms; `setMovingBudget`). */
    movingBudget: MOVING_BUDGET_MS,
    dirty: true,
    loadedChunk: undefined,
    /** Progressive layers in the uploaded parameters (a layered file refines as they come). */
    loadedLayers: 0,
    rendering: false,
    /** When the camera last moved (ms, performance.now()). */
    lastInput: -Infinity,
    /** Index into SCALES used while moving or playing (adapted to the frame budget); the
     * first frames start at the coarsest. */
    level: SCALES.length - 1,
    /** Index into SCALES of the next frame drawn while the camera is still and the video
     * paused: one step finer than the last frame, down to 0 (full size). */
    refineLevel: SCALES.length - 1,
    /** Per-side scale of the last frame drawn. */
    scale: 1,
    /** The last frame was reduced: draw it again, one step finer, when the camera is still. */
    refine: false,
    /** The view (camera and time) the frame buffer holds a finished lattice of, and its
     * spacing: a refinement of the same view renders only the pixels that lattice lacks. */
    drawnKey: null,
    drawnStride: 0,
    /** Parameter uploads so far (part of a view's key: new parameters, a new frame). */
    uploads: 0,
    /** The camera and samples of the last finished frame, and its time: the static cache is
     * built when the time moves under a still camera. */
    drawnCamKey: null,
    drawnT: null,
    /** The static cache: `{ camKey, dynamic, pixels }` (camKey: the camera and samples it
     * belongs to), or null. */
    cache: null,
    /** Index into SCALES of frames drawn through the play-time volume (adapted to the frame
     * budget as `level` is). */
    volumeLevel: 0,
  };
  hooks.state = state;
  hooks.orbit = orbit;
  hooks.stream = stream;
  stream.seek(state.t);
  stream.onChange(drawLoading);
  stream.start();
  drawLoading(stream);

  // ---- samples per ray (the menu, `?samples=`): the model's own or fewer, for speed
  const sampleSel = $("samples");
  const model = meta.model.sampler;
  // The file's play-time counts (format.md §3.4; the model's own when it stores none) first.
  const stored = meta.play_samples ?? null;
  for (const level of ["file", ...Object.keys(SAMPLE_LEVELS)]) {
    const [p, m] = playSamples(level, model, stored);
    sampleSel.append(new Option(`${level} (${p} + ${m})`, level));
  }
  // A fallback adapter (a software GPU such as Chromium's SwiftShader) starts at `fast`, where
  // a frame takes about two thirds of the time for 0.1-0.2 dB less on held-out views
  // (docs/tradeoff.md); a hardware GPU starts at the model's own counts.
  const fallback = Boolean(renderer.adapter.info?.isFallbackAdapter);
  hooks.fallbackAdapter = fallback;
  hooks.modelSamples = [model.num_proposal_samples, model.num_samples];
  let samplesSpec = params.get("samples") ?? (fallback ? "fast" : "file");
  let samples = playSamples(samplesSpec, model, stored);
  if (!samples || samples[0] > LIMITS.maxProposalSamples || samples[1] > LIMITS.maxSamples) {
    throw new Error(`samples=${samplesSpec}: file, full, fast, faster or P,M (proposal and main samples per ray, at most ${LIMITS.maxProposalSamples} and ${LIMITS.maxSamples})`);
  }
  if (samplesSpec !== "file" && !Object.hasOwn(SAMPLE_LEVELS, samplesSpec)) sampleSel.append(new Option(`${samples[0]} + ${samples[1]}`, samplesSpec));
  sampleSel.value = samplesSpec;
  hooks.samples = samples;
  hooks.samplesSpec = samplesSpec;
  $("policy").textContent +=
    ` Samples per ray (menu): file is the file's play-time counts (${stored ? `${stored.proposal} + ${stored.main}, chosen at export` : "none stored: the model's own"}); full is the model's own ${model.num_proposal_samples} proposal + ${model.num_samples} main samples; ` +
    `fast and faster render with fewer, faster and less accurately (docs/tradeoff.md)` +
    (fallback && params.get("samples") === null ? `; this GPU is a software one, so the page started at fast.` : ".");
  const withSamples = (cfg, [p, m]) => ({ ...cfg, sampler: { ...cfg.sampler, num_proposal_samples: p, num_samples: m } });

  // Hash tables as binary16 unless the file is lossless (as `msth play`); `?tables=f32|f16`.
  // f32 tables when a hash-table part of the file is lossless (format.md §5.4), else binary16.
  const tableParts = meta.section_quant ? [meta.section_quant.proposal, meta.section_quant.static, meta.section_quant.dynamic] : [meta.quant];
  const tables = params.get("tables") ?? (tableParts.includes("f32") ? "f32" : "f16");
  // The first picture comes from the generic kernels: they compile while the MLP section
  // streams. The kernels compiled with the model's level values and weights as constants
  // (specialise.js) wait for it (a few KiB, in the first request after the prefix) and replace
  // them after the first picture (renderer.js `create`).
  if (params.get("kernels") !== "wait") renderer.compileGeneric(tables, hooks.timings);
  await stream.waitForKind(KIND.mlp);
  hooks.timings.mlp = performance.now();
  const gpu = await renderer.create(canvas, withSamples(meta.model, samples), stream.decoder.layout, hooks.timings, stream.decoder.base, tables);
  hooks.mlpNote = gpu.mlpNote;
  hooks.tables = gpu.tables;
  const infoBase = $("info").textContent;
  let infoText = `${infoBase}; ${gpu.mlpNote}; hash tables ${gpu.tables}`;
  $("info").textContent = infoText;
  // The kernels compiled for the model replace the generic ones after the first picture.
  gpu.onKernels = (note) => {
    hooks.mlpNote = note;
    infoText = `${infoBase}; ${note}; hash tables ${gpu.tables}`;
    hooks.clampedTables = undefined;
    noteClamped();
  };
  /** Says on the info line when binary16 tables hold values clamped (beyond ±65504), as `msth
   * play`'s summary does. */
  const noteClamped = () => {
    const n = gpu.clampedTables ?? 0;
    if (n === hooks.clampedTables) return;
    hooks.clampedTables = n;
    $("info").textContent = n ? `${infoText} (${n} values beyond binary16's ±65504 held clamped: ?tables=f32 renders them as they are)` : infoText;
  };
  hooks.renderer = gpu;
  hooks.timings.pipeline = performance.now();
  $("policy").textContent += params.get("exact") === "1"
    ? " Every frame is drawn from the hash grids and MLPs (?exact=1)."
    : ` Once the view has reached full size (at once when the video plays or the view moves), the page bakes the file's static field into a play-time volume on the GPU (within a quarter of its storage buffer limit, ${SOFTWARE_VOLUME_MIB} MiB at most on a software GPU; ?volume-budget=MiB); once it is ready, a moving camera and playing video (but a still camera's incremental frames) are drawn through it, a few reads per sample instead of the hash grids and MLPs, at the resolution adapted to its own frame times, and rays that reach a part the volume left out are drawn exactly; a view at rest is drawn again exactly (?exact=1 draws every frame exactly).`;
  const paramBuf = new Float32Array(stream.decoder.layout.total);

  // ---- the play-time volume (top of this file)
  const exactOnly = params.get("exact") === "1";
  const volume = { state: exactOnly ? "off" : "waiting", progress: 0, note: null, error: null, resolution: null, bytes: 0, ms: null, evaluated: 0, slices: 0, sliceMs: 0 };
  hooks.volume = volume;
  let volumeData = null;
  let volumePlan = null;
  /** Plans and bakes the volume from the uploaded static parameters (`paramBuf` holds them). */
  async function bakeVolumeNow() {
    volume.state = "baking";
    const t0 = performance.now();
    hooks.timings.bake = t0;
    try {
      const limits = renderer.device.limits;
      const mib = Number(params.get("volume-budget"));
      // A quarter of the storage buffer limit (as msth play on a GPU); on a software adapter at
      // most SOFTWARE_VOLUME_MIB, whose bake it evaluates in about a minute.
      const quarter = Math.floor(Math.min(limits.maxStorageBufferBindingSize, limits.maxBufferSize) / 4);
      const budget = mib > 0 ? Math.floor(mib * 1048576) : fallback ? Math.min(quarter, SOFTWARE_VOLUME_MIB * 1048576) : quarter;
      const plan = planVolume({ model: meta.model, layout: stream.decoder.layout, params: paramBuf, occupancy: stream.decoder.occupancy, cameras, budget, outside: params.get("volume-outside") ?? "auto" });
      volume.planMs = performance.now() - t0;
      volume.note = planNote(plan);
      volume.resolution = plan.geometry.resolution;
      const vol = await bakeVolume(gpu, plan, { onProgress: (f) => (volume.progress = f) });
      volume.bytes = await gpu.setVolume(vol, volumeLayout(vol));
      volume.evaluated = vol.stats.evaluated;
      volumePlan = plan;
      volumeData = vol;
      volume.ms = performance.now() - t0;
      volume.progress = 1;
      volume.state = "ready";
      state.dirty = true;
      console.log(`play-time volume: ${plan.geometry.resolution}^3, ${vol.stats.bricks} bricks, ${(volume.bytes / 1048576).toFixed(1)} MiB, baked in ${volume.ms.toFixed(0)} ms${volume.note ? ` (${volume.note})` : ""}`);
    } catch (e) {
      volume.state = "failed";
      volume.error = e.message;
      console.log(`play-time volume: ${e.message}; frames are drawn exactly`);
    }
  }

  // ---- timeline
  const scrub = $("scrub");
  const playBtn = $("play");
  const frames = meta.model.num_frames;
  const duration = Math.max(frames, 2) / modelFps;
  const setPlaying = (p) => {
    state.playing = p;
    // The layer policy plans each chunk against the playback speed (paused: every layer of the
    // chunk on screen first).
    stream.setSpeed(p ? duration : 0);
    playBtn.textContent = p ? "❚❚" : "▶";
    playBtn.setAttribute("aria-label", p ? "pause" : "play");
  };
  setPlaying(state.playing);
  playBtn.onclick = () => setPlaying(!state.playing);
  const setTime = (t) => {
    state.t = Math.min(1, Math.max(0, t));
    stream.seek(state.t);
    state.dirty = true;
  };
  scrub.addEventListener("input", () => {
    setPlaying(false);
    setTime(Number(scrub.value) / 1000);
  });
  hooks.setTime = (t) => {
    setPlaying(false);
    setTime(t);
  };

  // ---- orbit / pan / zoom: mouse, wheel, touch (one finger orbits, two pan and pinch)
  const pointers = new Map();
  let pinch = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, button: e.button, shift: e.shiftKey });
  });
  const moved = () => {
    state.dirty = true;
    state.lastInput = performance.now();
    if (!orbit.fixed) camSel.value = "free";
  };
  camSel.onchange = () => {
    const k = Number(camSel.value);
    if (camSel.value !== "free" && cameras[k]) orbit.setCamera(cameras[k]);
    state.dirty = true;
  };
  const scale = () => canvas.width / canvas.getBoundingClientRect().width;
  canvas.addEventListener("pointermove", (e) => {
    const p = pointers.get(e.pointerId);
    if (!p) return;
    // Orbiting turns by screen distance; panning moves by image pixels (so that the scene
    // follows the pointer whatever the canvas is enlarged by).
    const sx = e.clientX - p.x;
    const sy = e.clientY - p.y;
    const k = scale();
    p.x = e.clientX;
    p.y = e.clientY;
    if (pointers.size === 2) {
      const [a, b] = [...pointers.values()];
      const d = Math.hypot(a.x - b.x, a.y - b.y);
      if (pinch) orbit.zoom(pinch / Math.max(d, 1));
      pinch = d;
      orbit.panBy((sx * k) / 2, (sy * k) / 2);
    } else if (p.button === 2 || p.button === 1 || p.shift) {
      orbit.panBy(sx * k, sy * k);
    } else {
      orbit.rotate(sx, sy);
    }
    moved();
  });
  const up = (e) => {
    pointers.delete(e.pointerId);
    if (pointers.size < 2) pinch = null;
  };
  canvas.addEventListener("pointerup", up);
  canvas.addEventListener("pointercancel", up);
  canvas.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      orbit.zoom(Math.exp(e.deltaY * 0.001));
      moved();
    },
    { passive: false },
  );
  hooks.setView = (az, el, dist) => {
    orbit.az = az;
    orbit.el = el;
    orbit.dist = dist;
    orbit.pan = [0, 0, 0];
    orbit.fixed = null;
    camSel.value = "free";
    state.dirty = true;
  };
  /** Renders with samples `spec` (`file`, `full`, `fast`, `faster` or `P,M`) from the next frame on, as the samples menu does. */
  const setSamples = (spec) => {
    const next = playSamples(spec, model, stored);
    if (!next) throw new Error(`samples ${spec}: file, full, fast, faster or P,M`);
    gpu.setSamples(next[0], next[1]);
    samplesSpec = spec;
    samples = next;
    hooks.samples = next;
    hooks.samplesSpec = spec;
    if (sampleSel.value !== spec) {
      if (![...sampleSel.options].some((o) => o.value === spec)) sampleSel.append(new Option(`${next[0]} + ${next[1]}`, spec));
      sampleSel.value = spec;
    }
    state.dirty = true;
  };
  sampleSel.onchange = () => {
    try {
      setSamples(sampleSel.value);
    } catch (e) {
      fail(e);
    }
  };
  hooks.setSamples = setSamples;
  /** Shows the file's camera `k`, as the view menu does. */
  hooks.setCamera = (k) => {
    orbit.setCamera(cameras[k]);
    camSel.value = String(k);
    state.dirty = true;
  };

  // ---- frame loop
  const incremental = params.get("incremental") !== "0";
  let last = performance.now();
  const recent = [];
  const frameDone = [];
  async function renderNow() {
    const chunk = stream.decoder.chunkForTime(state.t);
    const layers = stream.layersFor(state.t);
    const finer = chunk === state.loadedChunk && layers > state.loadedLayers;
    if (chunk !== state.loadedChunk || finer) {
      stream.decoder.paramsForTime(state.t, paramBuf);
      // After the first upload a new chunk changes the field's 4D table alone; finer layers
      // change the 3D table too, and nothing the static cache holds stays true.
      gpu.setParams(paramBuf, state.loadedChunk !== undefined && !finer);
      if (finer) state.cache = null;
      state.loadedLayers = layers;
      hooks.layers = layers;
      // The occupancy section is one of the sections every frame needs: decoded by now.
      if (state.loadedChunk === undefined && params.get("skip") !== "0") gpu.setOccupancy(stream.decoder.occupancy);
      state.loadedChunk = chunk;
      state.uploads++;
      hooks.timings.params ??= performance.now();
    }
    if (volume.state === "waiting" && params.get("volume") === "wait" && state.loadedLayers === stream.decoder.layers.length) await bakeVolumeNow();
    const full = orbit.camera();
    // The resolution policy (top of this file): reduced while moving or playing, refined step by
    // step to full size when still.
    const moving = performance.now() - state.lastInput < STILL_MS;
    // Incremental playback (top of this file): a still camera whose time moves re-renders only
    // the pixels the probes found dynamic.
    const camKey = JSON.stringify([full, samples]);
    if (state.cache && (state.cache.camKey !== camKey || moving || !gpu.hasStaticCache)) state.cache = null;
    if (!moving && incremental && (state.cache || wantCache(camKey, full))) {
      await renderIncremental(full, camKey);
      return;
    }
    // Through the play-time volume while the camera moves or the video plays; a still view is
    // refined on the exact path.
    if (volume.state === "ready" && (moving || state.playing) && (await renderVolumeFrame(full, camKey, moving))) return;
    // Moving: at most half size per side unless the GPU's measured rate draws a full-size frame
    // in half the moving budget (a drag should answer at once); playing: full size as long as a
    // frame fits one model frame; still and paused: one step finer than the last frame
    // (progressive refinement).
    const fullFits = gpu.raysPerMs > 0 && (full.width * full.height) / gpu.raysPerMs <= 0.5 * state.movingBudget;
    const level = moving ? Math.max(state.level, fullFits ? 0 : 1) : state.playing ? state.level : state.refineLevel;
    const scale = SCALES[level];
    // Reduced frames render every stride-th pixel per side of the full-size camera (the
    // renderer's interlaced lattice): w x h of them.
    const stride = Math.round(1 / scale);
    const w = Math.ceil(full.width / stride);
    const h = Math.ceil(full.height / stride);
    const key = frameKey(camKey);
    const done = key === state.drawnKey ? state.drawnStride : 0;
    const t0 = performance.now();
    // New input (orbit, zoom, scrub) abandons a frame still in progress (and what the frame
    // buffer holds then is no finished lattice).
    state.drawnKey = null;
    if (!(await gpu.render(full, state.t, () => state.dirty, stride, done))) return;
    const t1 = performance.now();
    state.drawnKey = key;
    state.drawnStride = Math.min(stride, done || stride);
    state.drawnCamKey = camKey;
    state.drawnT = state.t;
    state.scale = scale;
    if (moving || state.playing) {
      const budget = moving ? state.movingBudget : 1000 / modelFps;
      const ms = t1 - t0;
      if (ms > budget && state.level < SCALES.length - 1) state.level++;
      else if (ms * 4 < 0.7 * budget && state.level > 0) state.level--;
    }
    // A reduced frame is drawn again, one step finer, once the camera stops and playback is
    // paused.
    state.refineLevel = Math.max(level - 1, 0);
    state.refine = scale !== 1;
    hooks.lastRays = w * h - (done ? Math.ceil(full.width / done) * Math.ceil(full.height / done) : 0);
    hooks.lastIncremental = false;
    hooks.lastVolume = false;
    finishFrame(full, scale, w, h, t0, t1);
  }

  /**
   * Bakes the volume's time slices around `t` that are not baked yet (uploading their chunk's
   * parameters for it): `sliceAround`'s `[k0, k1, w]`, or null when a chunk has not arrived.
   */
  async function bakeSlicesFor(t) {
    const d = volumeData.dynamic;
    const around = sliceAround(d.times, t);
    if (d.bricks.length) {
      const missing = [...new Set([around[0], around[1]])].filter((k) => !d.slices[k]);
      if (!missing.every((k) => stream.readyFor(d.times[k]))) return null;
      for (const k of missing) {
        const ts = performance.now();
        const tk = d.times[k];
        const own = stream.decoder.chunkForTime(tk) === state.loadedChunk;
        if (!own) {
          const scratch = new Float32Array(stream.decoder.layout.total);
          stream.decoder.paramsForTime(tk, scratch);
          gpu.setParams(scratch, true);
        }
        try {
          await bakeSlice(gpu, volumePlan, volumeData, k);
        } finally {
          if (!own) gpu.setParams(paramBuf, true);
        }
        volume.slices++;
        volume.sliceMs += performance.now() - ts;
      }
    }
    return around;
  }

  /**
   * A frame through the play-time volume (the lattice of the volume's resolution level),
   * baking the time slices it needs first; false (nothing drawn) when a slice's chunk has not
   * arrived.
   */
  async function renderVolumeFrame(full, camKey, moving) {
    const level = state.volumeLevel;
    const scale = SCALES[level];
    const stride = Math.round(1 / scale);
    const around = await bakeSlicesFor(state.t);
    if (!around) return false;
    gpu.bindSlices(around);
    const t0 = performance.now();
    state.drawnKey = null;
    const out = await gpu.renderVolume(full, state.t, () => state.dirty, stride);
    if (!out) return true;
    const t1 = performance.now();
    // The same resolution policy as the exact path's, adapted on the volume's own frame times.
    const budget = moving ? state.movingBudget : 1000 / modelFps;
    if (t1 - t0 > budget && level < SCALES.length - 1) state.volumeLevel++;
    else if ((t1 - t0) * 4 < 0.7 * budget && level > 0) state.volumeLevel--;
    // The frame buffer holds no lattice of the exact path: a still view is drawn again exactly,
    // at full size, shown as it progresses.
    state.drawnCamKey = camKey;
    state.drawnT = state.t;
    state.scale = scale;
    state.refine = true;
    state.refineLevel = 0;
    const [w, h] = [Math.ceil(full.width / stride), Math.ceil(full.height / stride)];
    hooks.lastRays = w * h;
    hooks.lastIncremental = false;
    hooks.lastVolume = true;
    hooks.lastOutside = out.outside;
    hooks.volumeFrames++;
    finishFrame(full, scale, w, h, t0, t1);
    return true;
  }

  /** The bookkeeping after any finished frame: hooks, first-frame marks, the FPS window. */
  function finishFrame(full, scale, w, h, t0, t1) {
    noteClamped();
    hooks.lastScale = scale;
    hooks.lastSplit3 = hooks.renderer?.lastSplit3 ?? false;
    hooks.lastSize = [w, h];
    hooks.frames++;
    hooks.lastFrameMs = t1 - t0;
    hooks.lastTime = state.t;
    hooks.lastCamera = full;
    if (hooks.firstFrameMs === null) {
      hooks.firstFrameMs = t1;
      hooks.timings.firstFrame = t1;
      hooks.firstFrameSize = [w, h];
      console.log(`first frame (${w}x${h}) after ${t1.toFixed(0)} ms`);
      // The passes compiled later (renderer.js `compileLater`): after the first picture.
      hooks.renderer?.compileLater?.();
    }
    if (hooks.firstFullFrameMs === null && scale === 1) {
      hooks.firstFullFrameMs = t1;
      hooks.timings.firstFullFrame = t1;
      console.log(`first full-size frame (${w}x${h}) after ${t1.toFixed(0)} ms`);
    }
    recent.push(t1);
    while (recent.length && recent[0] < t1 - 1000) recent.shift();
    for (const f of frameDone.splice(0)) f();
  }
  /** What a finished frame of `camKey` (its camera and samples) holds: also its time and parameters. */
  const frameKey = (camKey) => JSON.stringify([camKey, state.t, state.uploads]);
  /** The probe times: PROBES.count times spread over [0, 1], ends included (as `msth play`'s
   * probes over the time range played). */
  const probeTimes = Array.from({ length: PROBES.count }, (_, j) => (PROBES.count > 1 ? j / (PROBES.count - 1) : 0.5));
  /**
   * Whether to build the static cache for `camKey` now: the last finished frame showed this very
   * camera (still since) at another time, the probes' chunks have arrived, and the probes fit
   * CACHE_BUDGET_MS at the GPU's measured rate (a software GPU at a large
   * size keeps drawing whole frames instead).
   */
  function wantCache(camKey, full) {
    if (state.drawnCamKey !== camKey || state.drawnT === state.t) return false;
    if (!probeTimes.every((t) => stream.readyFor(t))) return false;
    const n = full.width * full.height;
    if (!(gpu.raysPerMs > 0 && (PROBES.count * n) / gpu.raysPerMs <= CACHE_BUDGET_MS)) return false;
    // While the video plays, the frame rate comes first (the resolution policy): the cache's
    // full-size frames are used only where a whole full-size frame takes at most PLAY_CACHE_FRAMES
    // model frames (incremental frames re-render a fraction of it); else playback stays at the
    // reduced resolutions, and the cache is built when paused and scrubbed.
    return !state.playing || n / gpu.raysPerMs <= (PLAY_CACHE_FRAMES * 1000) / modelFps;
  }

  /** A frame of the still camera `full` from the static cache, building the cache first (the
   * probe frames) when there is none. */
  async function renderIncremental(full, camKey) {
    const inputAt = state.lastInput;
    const samplesAt = samples;
    const abort = () => state.lastInput !== inputAt || samples !== samplesAt;
    const w = full.width;
    const h = full.height;
    const t0 = performance.now();
    if (!state.cache) {
      hooks.cacheBuilds = (hooks.cacheBuilds || 0) + 1;
      $("status").textContent = `caching the static pixels (${PROBES.count} probe frames)…`;
      // The probes overwrite the frame buffer: no finished lattice until the cache is built.
      state.drawnKey = null;
      const scratch = new Float32Array(stream.decoder.layout.total);
      const probes = probeTimes.map((t) => ({
        t,
        params: stream.decoder.chunkForTime(t) === state.loadedChunk ? null : () => (stream.decoder.paramsForTime(t, scratch), scratch),
      }));
      const built = await gpu.buildStaticCache(full, probes, PROBES.tolerance, abort, () => gpu.setParams(paramBuf, true));
      if (!built) return;
      state.cache = { camKey, ...built };
      hooks.cache = { ...built, ms: performance.now() - t0 };
    }
    // The frame at this time: the dynamic pixels over the first probe's static ones.
    if (!(await gpu.renderDynamic(full, state.t, abort))) return;
    hooks.lastRays = state.cache.dynamic;
    const t1 = performance.now();
    state.drawnKey = frameKey(camKey);
    state.drawnStride = 1;
    state.drawnCamKey = camKey;
    state.drawnT = state.t;
    state.scale = 1;
    state.refine = false;
    state.refineLevel = 0;
    hooks.lastIncremental = true;
    hooks.lastVolume = false;
    finishFrame(full, 1, w, h, t0, t1);
  }

  // Resolves after the next frame that starts after this call.
  hooks.nextFrame = () => new Promise((r) => frameDone.push(r));

  async function tick(now) {
    const dt = (now - last) / 1000;
    last = now;
    if (stream.error && !hooks.error) fail(stream.error);
    // Finer layers of the chunk on screen: draw again; the volume is baked from every layer.
    if (state.loadedChunk !== undefined && stream.layersFor(state.t) > state.loadedLayers) state.dirty = true;
    // The play-time volume is baked once the view has reached full size, or at once when the
    // video plays or the view moves (what the volume draws faster): a bake running beside the
    // refinement of a still view shares the GPU with it (on SwiftShader the first full-size
    // frame came after 67-97 s instead of 13-16 s).
    const bakeDue = hooks.firstFullFrameMs !== null || state.playing || state.lastInput > -Infinity;
    if (volume.state === "waiting" && hooks.firstFrameMs !== null && bakeDue && state.loadedLayers === stream.decoder.layers.length && !state.rendering) bakeVolumeNow();
    // Playback holds still while the chunk under the playhead is streaming.
    if (state.playing && stream.readyFor(state.t)) {
      setTime((state.t + dt / duration) % 1);
      scrub.value = String(Math.round(state.t * 1000));
    }
    $("time").textContent = `t = ${state.t.toFixed(3)} · frame ${Math.round(state.t * (frames - 1))}`;
    // A pending refinement waits until the camera has been still for STILL_MS.
    // On a software GPU, where compiling and rendering share the CPU, the refinement after the
    // first picture waits for the kernels compiled for the model (renderer.js `kernelsReady`):
    // the generic kernels render 1.8x slower, and drawing with them while the others compile
    // delayed the first full-size frame by 3-10 s.
    const compiling = fallback && hooks.renderer?.kernelsPending;
    const refine = state.refine && !state.playing && now - state.lastInput >= STILL_MS && !compiling;
    if (!state.rendering && (state.dirty || state.playing || frameDone.length || refine)) {
      if (stream.readyFor(state.t)) {
        state.rendering = true;
        state.dirty = false;
        try {
          await renderNow();
          $("status").textContent = "";
        } catch (e) {
          fail(e);
        }
        state.rendering = false;
      } else {
        $("status").textContent = "buffering…";
      }
    }
    const n = recent.length;
    $("fps").textContent = n > 1 ? `${n} fps · ${hooks.lastFrameMs.toFixed(1)} ms/frame` : hooks.lastFrameMs ? `${hooks.lastFrameMs.toFixed(1)} ms/frame` : "– fps";
    if (hooks.lastSize) {
      const [rw, rh] = hooks.lastSize;
      const s = state.scale;
      const why = state.playing ? "playing" : performance.now() - state.lastInput < STILL_MS ? "moving" : "refining";
      const fewer = samples[0] !== model.num_proposal_samples || samples[1] !== model.num_samples;
      const shown = hooks.lastIncremental && state.cache ? ` (full, incremental: ${state.cache.dynamic} of ${state.cache.pixels} pixels re-rendered)` : s === 1 ? " (full)" : ` (1/${Math.round(1 / s)}, ${why})`;
      const vs = volume.state === "baking" ? ` · baking the volume ${Math.round(100 * volume.progress)}%` : hooks.lastVolume ? ` · volume ${volume.resolution}³${hooks.lastOutside ? `, ${hooks.lastOutside} rays exact` : ""}` : "";
      $("res").textContent = `· ${rw}x${rh}${shown}${fewer && !hooks.lastVolume ? ` · ${samples[0]} + ${samples[1]} samples` : ""}${vs}`;
    }
    if (performance.now() - (recent[n - 1] ?? 0) > 1000) recent.length = 0;
    if (!hooks.error) requestAnimationFrame(tick);
  }
  scrub.value = String(Math.round(state.t * 1000));
  requestAnimationFrame(tick);

  /** Renders `n` frames back to back at the current view: frames per second (GPU complete). */
  hooks.benchmark = async (n = 30) => {
    setPlaying(false);
    while (state.rendering) await new Promise((r) => setTimeout(r, 5));
    state.rendering = true;
    const cam = orbit.camera();
    const t0 = performance.now();
    for (let i = 0; i < n; i++) await gpu.render(cam, state.t);
    const s = (performance.now() - t0) / 1000;
    state.rendering = false;
    return { frames: n, seconds: s, fps: n / s, width: canvas.width, height: canvas.height };
  };
  /**
   * Renders `n` frames of a camera moving around the orbit (`step` degrees of azimuth a frame)
   * back to back, through the volume (`useVolume`, once baked) or exactly, at full size: per
   * frame ms, GPU complete, and the mean frames per second. Restores the view after.
   */
  hooks.orbitBenchmark = async (n = 8, step = 5, useVolume = true) => {
    setPlaying(false);
    while (state.rendering) await new Promise((r) => setTimeout(r, 5));
    if (useVolume && volume.state !== "ready") throw new Error(`the volume is ${volume.state}${volume.error ? `: ${volume.error}` : ""}`);
    state.rendering = true;
    const az0 = orbit.az;
    const around = useVolume ? await bakeSlicesFor(state.t) : null;
    if (useVolume && !around) throw new Error("the chunks of the volume's time slices have not arrived");
    const ms = [];
    let outside = 0;
    try {
      for (let i = 0; i < n; i++) {
        orbit.az = az0 + (i + 1) * step;
        const cam = orbit.camera();
        const t0 = performance.now();
        if (useVolume) {
          gpu.bindSlices(around);
          outside += (await gpu.renderVolume(cam, state.t)).outside;
        } else await gpu.render(cam, state.t);
        ms.push(performance.now() - t0);
      }
    } finally {
      orbit.az = az0;
      state.rendering = false;
      state.dirty = true;
    }
    return { ms, fps: (1000 * n) / ms.reduce((a, b) => a + b, 0), outside, width: canvas.width, height: canvas.height };
  };
  /**
   * Test hooks. `hold()` pauses and stops the page drawing (after the frame in progress).
   * `drawHeld(stride, done, rays)` then draws the current view reduced to 1/`stride` per side
   * and keeps it on the canvas: `done`, the coarser lattice of this very view the frame buffer
   * already holds (as a refinement step); `rays` > 0, only the first batch, of that many rays
   * (a frame in progress on a slow GPU). Resolves to the display's uniform (`displayUniform`).
   * `release()` lets the page draw again.
   */
  hooks.hold = async () => {
    setPlaying(false);
    while (state.rendering) await new Promise((r) => setTimeout(r, 5));
    state.rendering = true;
    state.drawnKey = null;
  };
  hooks.drawHeld = async (stride, done = 0, rays = 0) => {
    if (rays > 0) gpu.tile = rays;
    await gpu.render(orbit.camera(), state.t, () => rays > 0, stride, done);
    return Array.from(gpu.shownSize);
  };
  /** Held (after `hold()`): draws the current view through the play-time volume at 1/`stride`
   * per side (its slices baked first) and keeps it on the canvas; resolves to the rays drawn
   * exactly because they reached a brick the volume left out. */
  hooks.drawVolumeHeld = async (stride = 1) => {
    if (volume.state !== "ready") throw new Error(`the volume is ${volume.state}${volume.error ? `: ${volume.error}` : ""}`);
    const around = await bakeSlicesFor(state.t);
    if (!around) throw new Error("the chunks of the volume's time slices have not arrived");
    gpu.bindSlices(around);
    return (await gpu.renderVolume(orbit.camera(), state.t, () => false, stride)).outside;
  };
  hooks.release = () => {
    state.rendering = false;
    state.dirty = true;
  };
  /** Sets a moving frame's budget (ms; the default without an argument), for tests of the
   * resolution policy that do not depend on the GPU's speed. */
  hooks.setMovingBudget = (ms = MOVING_BUDGET_MS) => {
    state.movingBudget = ms;
  };
  /** The last rendered frame's RGBA8 pixels (the renderer's own output, not a screenshot). */
  hooks.readPixels = async () => Array.from(await gpu.readPixels());
}

main().catch(fail);
