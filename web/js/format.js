// The `.msth` format (docs/format.md, versions 1 to 4) for the browser and Node: the prefix
// (fixed header, metadata JSON, section index), section decoding (CRC-32, zstd through the
// `fzstd` npm package, blocks f32 / f16 / affine / codebook with the delta predictor, sparse 4D
// chunks, the occupancy grid of version 2, the progressive layers of version 4) and the model's
// flat parameter buffer layout (§7),
// mirroring msth-codec and msth-core's `ModelLayout`. Every count read from a file is checked
// before it is used to allocate or index. The constants both languages must agree on come from
// `generated/contract.js`, which tests/tests/web_contract.rs writes from the Rust code.

import { Decompress } from "fzstd";
import {
  MAGIC, VERSION, MIN_VERSION, FIXED_HEADER, INDEX_ENTRY, ALIGN, COMPRESSION_ZSTD, KIND, FIXED_SECTIONS,
  SHARED_TAG, LIMITS, OCCUPANCY, METADATA_KEYS, LAYERED_VERSION, MAX_LAYERS, METADATA_OPTIONAL_KEYS, QUANT_PARTS, QUANT_MODES, HASH_PRIMES, PARAM_ALIGN, SH_COEFFS,
} from "./generated/contract.js";

export { MAGIC, VERSION, MIN_VERSION, FIXED_HEADER, INDEX_ENTRY, KIND, LIMITS, HASH_PRIMES };
const KIND_NAME = Object.fromEntries(Object.entries(KIND).map(([name, code]) => [code, name]));

/** Index position of dynamic chunk 0 in a file of `version` (after its fixed sections and the shared one). */
export const firstChunk = (version) => FIXED_SECTIONS[version].length + 1;

/** A decoding failure: `what` names the part of the file, `truncated` asks for more bytes. */
export class FormatError extends Error {
  constructor(what, message, truncated = false) {
    super(`${what}: ${message}`);
    this.name = "FormatError";
    this.what = what;
    this.truncated = truncated;
  }
}

// ---------------------------------------------------------------- CRC-32 (ISO-HDLC, as zlib)

const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[n] = c >>> 0;
  }
  return t;
})();

/** Continues a CRC-32 over `bytes`; start with `crc = 0`. */
export function crc32(bytes, crc = 0) {
  let c = ~crc >>> 0;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
  return ~c >>> 0;
}

// ---------------------------------------------------------------- layout (msth-core)


// LLVM's powi (compiler-rt __powidf2): repeated squaring, as Rust's f64::powi.
function powi(a, b) {
  let r = 1;
  for (;;) {
    if (b & 1) r *= a;
    b = Math.trunc(b / 2);
    if (b === 0) break;
    a *= a;
  }
  return r;
}

/** A grid's levels (core/src/grid.rs `GridLayout::new`): scale, res, dense, rows, offset. */
export function gridLayout(cfg) {
  const d = cfg.base_resolution.length;
  const L = cfg.levels;
  const tableSize = 2 ** cfg.log2_table_size;
  const levels = [];
  let offset = 0;
  for (let l = 0; l < L; l++) {
    const scale = [];
    const res = [];
    let denseSize = 1;
    for (let a = 0; a < d; a++) {
      const b = Math.fround(cfg.base_resolution[a]);
      const f = Math.fround(cfg.finest_resolution[a]);
      const growth = L > 1 ? Math.exp((Math.log(f) - Math.log(b)) / (L - 1)) : 1;
      const s = Math.fround(Math.max(b * powi(growth, l) - 1, 0));
      scale.push(s);
      res.push(Math.ceil(s) + 1);
      denseSize *= res[a] + 1;
    }
    const dense = denseSize <= tableSize;
    const rows = dense ? Math.ceil(denseSize / 8) * 8 : tableSize;
    const stride = [0, 0, 0, 0];
    if (dense) {
      let s = 1;
      for (let a = 0; a < d; a++) {
        stride[a] = s;
        s *= res[a] + 1;
      }
    }
    levels.push({ scale, res, stride, rows, offset, dense });
    offset += rows * cfg.features_per_level;
  }
  return { dims: d, features: cfg.features_per_level, levels, numParams: offset, tableSize };
}


const usesH3 = (blend) => blend !== "four_d";
const usesH4 = (blend) => blend !== "static";
const usesMask = (blend) => blend === "mst" || blend === "mt";

function mlpLayout(dims) {
  const offsets = [];
  let off = 0;
  for (let k = 0; k < dims.length - 1; k++) {
    offsets.push(off);
    off += dims[k] * dims[k + 1];
  }
  return { dims, offsets, numParams: off };
}

/**
 * The flat parameter buffer's slices (format.md §7, msth-core `ModelLayout`): for the field and
 * the proposal `{ h3, h4, mask, density, color }` each `{ ..., start, end }` or null, and
 * `total` (= `param_count`).
 */
export function modelLayout(model) {
  let total = 0;
  const push = (len) => {
    const start = Math.ceil(total / PARAM_ALIGN) * PARAM_ALIGN;
    total = start + len;
    return { start, end: start + len };
  };
  const encoding = (cfg) => {
    const e = { blend: cfg.blend, h3: null, h4: null, mask: null };
    if (usesH3(cfg.blend)) {
      const g = gridLayout(cfg.grid3);
      e.h3 = { ...g, ...push(g.numParams) };
    }
    if (usesH4(cfg.blend)) {
      const g = gridLayout(cfg.grid4);
      e.h4 = { ...g, ...push(g.numParams) };
    }
    if (usesMask(cfg.blend)) {
      const res = cfg.mask_resolution;
      e.mask = { res, ...push(res * res * res) };
    }
    const g = e.h3 || e.h4;
    e.outDim = g ? g.levels.length * g.features : 0;
    return e;
  };
  const f = model.field;
  const fieldEnc = encoding(f.encoding);
  const dm = mlpLayout([fieldEnc.outDim, f.density_hidden, 1 + f.geo_features]);
  const density = { ...dm, ...push(dm.numParams) };
  const colorDims = [SH_COEFFS + f.geo_features];
  for (let i = 0; i < f.color_layers; i++) colorDims.push(f.color_hidden);
  colorDims.push(3);
  const cm = mlpLayout(colorDims);
  const color = { ...cm, ...push(cm.numParams) };
  const p = model.proposal;
  const propEnc = encoding(p.encoding);
  const pm = mlpLayout([propEnc.outDim, p.hidden, 1]);
  const pdensity = { ...pm, ...push(pm.numParams) };
  return {
    field: { encoding: fieldEnc, density, color },
    proposal: { encoding: propEnc, density: pdensity },
    total,
  };
}

// ---------------------------------------------------------------- model validation

function checkModel(m) {
  const bad = (msg) => {
    throw new FormatError("metadata model", msg);
  };
  const int = (v, lo, hi, name) => {
    if (!Number.isInteger(v) || v < lo || v > hi) bad(`${name} = ${v} outside ${lo}..=${hi}`);
  };
  const finite = (v, name) => {
    if (typeof v !== "number" || !Number.isFinite(v)) bad(`${name} is not a finite number`);
  };
  const grid = (g, dims, name) => {
    if (!g || typeof g !== "object") bad(`${name} is missing`);
    int(g.levels, 1, 32, `${name}.levels`);
    if (![1, 2, 4, 8].includes(g.features_per_level)) bad(`${name}.features_per_level must be 1, 2, 4 or 8`);
    int(g.log2_table_size, 3, 24, `${name}.log2_table_size`);
    for (const k of ["base_resolution", "finest_resolution"]) {
      if (!Array.isArray(g[k]) || g[k].length !== dims) bad(`${name}.${k} needs ${dims} numbers`);
      g[k].forEach((v, a) => {
        finite(v, `${name}.${k}[${a}]`);
        if (v < 1 || v > 2 ** 20) bad(`${name}.${k}[${a}] = ${v} outside [1, 2^20]`);
      });
    }
    g.base_resolution.forEach((b, a) => {
      if (g.finest_resolution[a] < b) bad(`${name}: finest resolution below base on axis ${a}`);
    });
  };
  const encoding = (e, name) => {
    if (!e || typeof e !== "object") bad(`${name} is missing`);
    if (!["mst", "mt", "add", "four_d", "static"].includes(e.blend)) bad(`${name}.blend \`${e.blend}\` unknown`);
    if (usesH3(e.blend)) grid(e.grid3, 3, `${name}.grid3`);
    if (usesH4(e.blend)) grid(e.grid4, 4, `${name}.grid4`);
    if (usesH3(e.blend) && usesH4(e.blend)) {
      const a = e.grid3.levels * e.grid3.features_per_level;
      const b = e.grid4.levels * e.grid4.features_per_level;
      if (a !== b) bad(`${name}: grid3 and grid4 output ${a} vs ${b} features`);
    }
    if (usesMask(e.blend)) int(e.mask_resolution, 2, 1024, `${name}.mask_resolution`);
  };
  if (!m || typeof m !== "object") bad("missing");
  encoding(m.field?.encoding, "field.encoding");
  encoding(m.proposal?.encoding, "proposal.encoding");
  int(m.field.density_hidden, 1, 1024, "field.density_hidden");
  int(m.field.geo_features, 1, 1024, "field.geo_features");
  int(m.field.color_hidden, 1, 1024, "field.color_hidden");
  int(m.field.color_layers, 1, 8, "field.color_layers");
  int(m.proposal.hidden, 1, 1024, "proposal.hidden");
  int(m.num_frames, 1, 2 ** 31, "num_frames");
  const b = m.bounds;
  if (b?.kind === "box") {
    [...b.min, ...b.max].forEach((v, i) => finite(v, `bounds[${i}]`));
  } else if (b?.kind === "contracted") {
    [...b.center, b.radius].forEach((v, i) => finite(v, `bounds[${i}]`));
  } else bad("bounds.kind must be box or contracted");
}

// ---------------------------------------------------------------- prefix

const u16 = (b, o) => b[o] | (b[o + 1] << 8);
const u32 = (b, o) => (b[o] | (b[o + 1] << 8) | (b[o + 2] << 16) | (b[o + 3] << 24)) >>> 0;
const u64 = (b, o, what) => {
  const lo = u32(b, o);
  const hi = u32(b, o + 4);
  if (hi >= 2 ** 21) throw new FormatError(what, "a 64-bit value exceeds 2^53");
  return hi * 2 ** 32 + lo;
};
const align8 = (x) => Math.ceil(x / ALIGN) * ALIGN;

/** `header_size` from the first 32 bytes (the prefix a client fetches next). */
export function prefixLength(first, limits = LIMITS) {
  const n = Math.min(first.length, 4);
  for (let i = 0; i < n; i++) {
    if (first[i] !== MAGIC[i]) throw new FormatError("header", 'bad magic (expected "MSTH")');
  }
  if (first.length < FIXED_HEADER) throw new FormatError("fixed header", `needs ${FIXED_HEADER} bytes, have ${first.length}`, true);
  const version = u16(first, 4);
  if (version < MIN_VERSION || version > VERSION) throw new FormatError("version", `file is version ${version}, this decoder reads ${MIN_VERSION} to ${VERSION}`);
  if (u16(first, 6) !== 0) throw new FormatError("header", "reserved flag bits set");
  for (let i = 20; i < 28; i++) if (first[i] !== 0) throw new FormatError("header", "reserved bytes 20..28 must be zero");
  const headerSize = u32(first, 8);
  const metadataLength = u32(first, 12);
  const sectionCount = u32(first, 16);
  if (metadataLength > limits.maxMetadata) throw new FormatError("metadata length", `${metadataLength} exceeds the limit ${limits.maxMetadata}`);
  if (sectionCount > limits.maxSections) throw new FormatError("section count", `${sectionCount} exceeds the limit ${limits.maxSections}`);
  const expected = align8(FIXED_HEADER + metadataLength) + INDEX_ENTRY * sectionCount;
  if (headerSize !== expected) throw new FormatError("header", `header_size ${headerSize} disagrees with the metadata length and section count (expected ${expected})`);
  return headerSize;
}

/** Parses and checks the prefix: `{ metadata, sections, layout, headerSize, fileLength }`. */
export function parsePrefix(bytes, limits = LIMITS) {
  const headerSize = prefixLength(bytes, limits);
  if (bytes.length < headerSize) throw new FormatError("header and index", `needs ${headerSize} bytes, have ${bytes.length}`, true);
  const stored = u32(bytes, 28);
  const computed = crc32(bytes.subarray(FIXED_HEADER, headerSize), crc32(bytes.subarray(0, 28)));
  if (stored !== computed) throw new FormatError("header and index", `CRC-32 mismatch (stored ${stored.toString(16)}, computed ${computed.toString(16)})`);
  const ml = u32(bytes, 12);
  const io = align8(FIXED_HEADER + ml);
  for (let i = FIXED_HEADER + ml; i < io; i++) if (bytes[i] !== 0) throw new FormatError("metadata", "padding must be zero");
  let metadata;
  try {
    metadata = JSON.parse(new TextDecoder("utf-8", { fatal: true }).decode(bytes.subarray(FIXED_HEADER, FIXED_HEADER + ml)));
  } catch (e) {
    throw new FormatError("metadata JSON", e.message);
  }
  const version = u16(bytes, 4);
  const layout = checkMetadata(metadata, version, limits);
  const count = u32(bytes, 16);
  const sections = [];
  for (let i = 0; i < count; i++) {
    const o = io + i * INDEX_ENTRY;
    const what = `index entry ${i}`;
    const kind = bytes[o];
    if (!KIND_NAME[kind]) throw new FormatError(what, `unsupported section kind ${kind}`);
    if (bytes[o + 1] !== COMPRESSION_ZSTD) throw new FormatError(what, `unsupported compression ${bytes[o + 1]} (zstd = ${COMPRESSION_ZSTD} is the only one)`);
    const layer = u16(bytes, o + 2);
    if ((version < LAYERED_VERSION && layer) || u32(bytes, o + 36)) throw new FormatError(what, "reserved fields must be zero");
    sections.push({
      kind,
      chunk: u32(bytes, o + 4),
      layer,
      offset: u64(bytes, o + 8, what),
      length: u64(bytes, o + 16, what),
      rawLength: u64(bytes, o + 24, what),
      crc32: u32(bytes, o + 32),
    });
  }
  const layers = layerLevels(metadata, layout);
  checkSections(sections, metadata, layout, version, headerSize, limits, layers.length);
  const fileLength = sections.reduce((m, s) => Math.max(m, s.offset + s.length), headerSize);
  const fixed = FIXED_SECTIONS[version].length;
  const beforeFirstFrame = metadata.chunks.length ? fixed + 1 : fixed;
  return { version, metadata, sections, layout, headerSize, fileLength, firstChunk: firstChunk(version), beforeFirstFrame, layers };
}

/** Every level of the model's four tables (0 for a table its blend mode lacks). */
function allLevels(layout) {
  const n = (g) => (g ? g.levels.length : 0);
  const [f, p] = [layout.field.encoding, layout.proposal.encoding];
  return { h3: n(f.h3), h4: n(f.h4), p3: n(p.h3), p4: n(p.h4) };
}

/** The layers' cumulative level counts `[{ h3, h4, p3, p4 }]` (format.md §6.6): `layers`, or one layer of every level. */
function layerLevels(metadata, layout) {
  if (metadata.layers !== undefined) return metadata.layers;
  return [allLevels(layout)];
}

/**
 * Index position of a section of `kind` for `chunk` (dynamic) and `layer` in a parsed prefix
 * (as msth-codec's `FileIndex::position`), or null when the file has none.
 */
export function sectionPosition(ix, kind, chunk, layer) {
  const chunks = ix.metadata.chunks.length;
  if (layer >= ix.layers.length || (kind === KIND.dynamic && chunk >= chunks)) return null;
  const fixed = FIXED_SECTIONS[ix.version];
  if (layer === 0) {
    if (kind === KIND.dynamic) return ix.firstChunk + chunk;
    if (kind === KIND.shared) return chunks ? fixed.length : null;
    const i = fixed.indexOf(kind);
    return i < 0 ? null : i;
  }
  const at = fixed.length + (chunks ? 1 + chunks : 0) + (layer - 1) * (chunks ? 3 + chunks : 2);
  if (kind === KIND.proposal) return at;
  if (kind === KIND.static) return at + 1;
  if (kind === KIND.shared) return chunks ? at + 2 : null;
  if (kind === KIND.dynamic) return at + 3 + chunk;
  return null;
}

/** The levels `[start, end)` layer `layer` holds of a table: `key` "h3" and "h4" the field's 3D
 * and 4D tables, "p3" and "p4" the proposal's. */
export function layerRange(layers, layer, key) {
  return [layer === 0 ? 0 : layers[layer - 1][key], layers[layer][key]];
}

const TOP_KEYS = METADATA_KEYS;

function checkMetadata(m, version, limits) {
  const bad = (msg) => {
    throw new FormatError("metadata", msg);
  };
  if (!m || typeof m !== "object" || Array.isArray(m)) bad("not a JSON object");
  for (const k of Object.keys(m)) {
    if (TOP_KEYS.includes(k)) continue;
    if (!METADATA_OPTIONAL_KEYS.includes(k)) bad(`unknown key \`${k}\``);
    if (version < 3) bad(`unknown key \`${k}\` (version ${version}; it exists from version 3)`);
  }
  for (const k of TOP_KEYS) if (!(k in m)) bad(`missing key \`${k}\``);
  // msth-codec reads every number as binary32 or an integer: one that overflows binary32 is out
  // of range (JSON has no infinity, so this is how a non-finite value would arrive).
  const outOfRange = (v) => (typeof v === "number" ? !Number.isFinite(Math.fround(v)) : v && typeof v === "object" && Object.values(v).some(outOfRange));
  if (outOfRange(m)) bad("a number is out of range (overflows binary32)");
  checkModel(m.model);
  const sampler = m.model.sampler;
  for (const [name, v, max] of [["model.sampler.num_proposal_samples", sampler.num_proposal_samples, limits.maxProposalSamples], ["model.sampler.num_samples", sampler.num_samples, limits.maxSamples]]) {
    if (v > max) bad(`${name} is ${v}, the limit is ${max}`);
  }
  const layout = modelLayout(m.model);
  if (layout.total > limits.maxParams) bad(`${layout.total} parameters exceed the limit ${limits.maxParams}`);
  if (m.param_count !== layout.total) bad(`param_count ${m.param_count} disagrees with the model (${layout.total})`);
  if (!Array.isArray(m.cameras)) bad("cameras must be an array");
  if (m.cameras.length > limits.maxCameras) bad(`${m.cameras.length} cameras exceed the limit ${limits.maxCameras}`);
  m.cameras.forEach((c, i) => {
    const ok =
      Number.isInteger(c?.width) && c.width >= 1 && Number.isInteger(c.height) && c.height >= 1 &&
      [c.fx, c.fy].every((v) => Number.isFinite(v) && v > 0) && [c.cx, c.cy].every(Number.isFinite) &&
      Array.isArray(c.world_from_camera) && c.world_from_camera.length === 16 && c.world_from_camera.every(Number.isFinite);
    if (!ok) bad(`cameras[${i}] is not a valid pinhole camera`);
    if (c.width > limits.maxImageSide || c.height > limits.maxImageSide) bad(`cameras[${i}] is ${c.width} x ${c.height} pixels, the limit per side is ${limits.maxImageSide}`);
    if (c.width * c.height > limits.maxImagePixels) bad(`cameras[${i}] has ${c.width} x ${c.height} pixels, the limit is ${limits.maxImagePixels}`);
  });
  if (!Array.isArray(m.chunks)) bad("chunks must be an array");
  let prev = -Infinity;
  m.chunks.forEach((c, i) => {
    const ok = [c?.t_start, c?.t_end].every(Number.isFinite) && c.t_start <= c.t_end && c.t_start >= prev && c.frame_start <= c.frame_end;
    if (!ok) bad(`chunks[${i}] is not a valid span`);
    prev = c.t_start;
  });
  if (m.frame_rate !== null && !(Number.isFinite(m.frame_rate) && m.frame_rate > 0)) bad("frame_rate must be null or > 0");
  if (!Array.isArray(m.time_range) || m.time_range.length !== 2 || !m.time_range.every(Number.isFinite)) bad("time_range must be two numbers");
  if (m.time_range[0] !== 0 || m.time_range[1] !== 1) bad(`time_range is [${m.time_range[0]}, ${m.time_range[1]}], version 1 allows only [0, 1]`);
  if (!QUANT_MODES.includes(m.quant)) bad(`unknown quantisation mode \`${m.quant}\``);
  if (m.section_quant !== undefined) {
    const q = m.section_quant;
    if (!q || typeof q !== "object" || Array.isArray(q)) bad("section_quant must be an object");
    for (const k of Object.keys(q)) if (!QUANT_PARTS.includes(k)) bad(`section_quant: unknown key \`${k}\``);
    for (const k of QUANT_PARTS) if (!QUANT_MODES.includes(q[k])) bad(`section_quant.${k}: unknown quantisation mode \`${q[k]}\``);
    // The finest mode (earliest in QUANT_MODES) of the parts is `quant`.
    const finest = QUANT_MODES[Math.min(...QUANT_PARTS.map((k) => QUANT_MODES.indexOf(q[k])))];
    if (finest !== m.quant) bad(`quant is ${m.quant} but the finest mode in section_quant is ${finest}`);
  }
  if (m.play_samples !== undefined) {
    const s = m.play_samples;
    if (!s || typeof s !== "object" || Array.isArray(s)) bad("play_samples must be an object");
    for (const k of Object.keys(s)) if (k !== "proposal" && k !== "main") bad(`play_samples: unknown key \`${k}\``);
    for (const [k, max] of [["proposal", limits.maxProposalSamples], ["main", limits.maxSamples]]) {
      const v = s[k];
      if (!Number.isInteger(v) || v < 0 || v > 0xffffffff) bad(`play_samples.${k} must be an integer`);
      if (v === 0) bad(`play_samples.${k} is 0: at least 1 sample per ray`);
      if (v > max) bad(`play_samples.${k} is ${v}, the limit is ${max}`);
    }
  }
  if (m.layers !== undefined) {
    if (version < LAYERED_VERSION) bad(`unknown key \`layers\` (version ${version}; it exists from version ${LAYERED_VERSION})`);
    const l = m.layers;
    if (!Array.isArray(l) || l.length < 1 || l.length > MAX_LAYERS) bad(`layers must be an array of 1 to ${MAX_LAYERS} entries`);
    const KEYS = ["h3", "h4", "p3", "p4"];
    const show = (e) => KEYS.map((k) => e[k]).join("/");
    const sum = (e) => KEYS.reduce((s, k) => s + e[k], 0);
    let prev = { h3: 0, h4: 0, p3: 0, p4: 0 };
    l.forEach((e, i) => {
      if (!e || typeof e !== "object" || Array.isArray(e)) bad(`layers[${i}] must be an object`);
      for (const k of Object.keys(e)) if (!KEYS.includes(k)) bad(`layers[${i}]: unknown key \`${k}\``);
      if (!KEYS.every((k) => Number.isInteger(e[k]) && e[k] >= 0 && e[k] <= 0xffffffff)) bad(`layers[${i}] must hold integer level counts h3, h4, p3, p4`);
      if (KEYS.some((k) => e[k] < prev[k]) || sum(e) === sum(prev)) bad(`layers[${i}] holds levels ${show(e)} after ${show(prev)}: each layer adds levels`);
      prev = e;
    });
    const full = allLevels(layout);
    if (KEYS.some((k) => prev[k] !== full[k])) bad(`the last layer holds levels ${show(prev)}, the model's tables have ${show(full)} (field 3D/4D, proposal 3D/4D)`);
  }
  if (!(Number.isFinite(m.dynamic_threshold) && m.dynamic_threshold >= 0 && m.dynamic_threshold <= 1)) bad("dynamic_threshold must lie in [0, 1]");
  if (!(Number.isInteger(m.chunk_frames) && m.chunk_frames >= 1)) bad("chunk_frames must be an integer >= 1");
  if (typeof m.encoder !== "string") bad("encoder must be a string");
  return layout;
}

function checkSections(sections, metadata, layout, version, headerSize, limits, layerCount) {
  const chunks = metadata.chunks.length;
  const fixed = FIXED_SECTIONS[version];
  const first = fixed.length + 1;
  const firstLayer = chunks ? first + chunks : fixed.length;
  const perLayer = chunks ? 3 + chunks : 2;
  const expected = firstLayer + (layerCount - 1) * perLayer;
  if (sections.length !== expected) throw new FormatError("index", `${sections.length} sections, the metadata implies ${expected}`);
  const order = [...fixed, KIND.shared];
  let end = headerSize;
  sections.forEach((s, i) => {
    const what = `index entry ${i}`;
    let kind, chunk, layer;
    if (i < firstLayer) [kind, chunk, layer] = [i < first ? order[i] : KIND.dynamic, i < first ? 0 : i - first, 0];
    else {
      const k = (i - firstLayer) % perLayer;
      layer = Math.floor((i - firstLayer) / perLayer) + 1;
      [kind, chunk] = k === 0 ? [KIND.proposal, 0] : k === 1 ? [KIND.static, 0] : k === 2 ? [KIND.shared, 0] : [KIND.dynamic, k - 3];
    }
    if (s.kind !== kind || s.chunk !== chunk || s.layer !== layer) throw new FormatError(what, `expected a ${KIND_NAME[kind]} section${kind === KIND.dynamic ? ` for chunk ${chunk}` : ""}${layer ? ` of layer ${layer}` : ""}`);
    if (s.length > limits.maxSectionBytes || s.rawLength > limits.maxSectionBytes) throw new FormatError(what, "section exceeds the 2 GiB limit");
    if (s.rawLength > maxPayload(layout, s.kind, limits)) throw new FormatError(what, `raw length ${s.rawLength} exceeds what the model allows`);
    if (s.offset % 8 !== 0) throw new FormatError(what, "offset is not a multiple of 8");
    if (s.offset < end) throw new FormatError(what, "sections overlap");
    end = s.offset + s.length;
  });
}

// ---------------------------------------------------------------- blocks and payloads

const maxBlockBytes = (count) => 8 + 4 * 256 + 4 * count;

/** The flat-buffer ranges of a section's blocks; of one layer of a layered file, `levels`:
 * `[start, end)` of the field's 3D table (a static section) or `{ h3, h4 }` ranges of the
 * proposal's tables (a proposal section), the mask in layer 0 only. */
function staticRanges(layout, kind, levels = null, withMask = true) {
  const out = [];
  const table = (name, g, range) => g.levels.forEach((lv, l) => {
    if (range && (l < range[0] || l >= range[1])) return;
    const start = g.start + lv.offset;
    out.push([`${name} level ${l}`, start, start + lv.rows * g.features]);
  });
  const encoding = (prefix, e, h4Range, range = null, mask = true) => {
    if (e.h3) table(`${prefix}.h3`, e.h3, range);
    if (h4Range !== false && e.h4) table(`${prefix}.h4`, e.h4, h4Range);
    if (e.mask && mask) out.push([`${prefix}.mask`, e.mask.start, e.mask.end]);
  };
  if (kind === KIND.mlp) {
    out.push(["field.density_mlp", layout.field.density.start, layout.field.density.end]);
    out.push(["field.color_mlp", layout.field.color.start, layout.field.color.end]);
    out.push(["proposal.density_mlp", layout.proposal.density.start, layout.proposal.density.end]);
  } else if (kind === KIND.proposal) {
    encoding("proposal", layout.proposal.encoding, levels ? levels.h4 : null, levels ? levels.h3 : null, withMask);
  } else {
    encoding("field", layout.field.encoding, false, levels, withMask);
  }
  return out;
}

/** Bytes of an occupancy payload of `resolution` cells per axis (format.md §6.5). */
export const occupancyPayloadLength = (resolution) => OCCUPANCY.headerBytes + 4 * Math.ceil(resolution ** 3 / 32);

function maxPayload(layout, kind, limits = LIMITS) {
  if (kind === KIND.occupancy) return occupancyPayloadLength(limits.maxOccupancyResolution);
  if (kind === KIND.dynamic || kind === KIND.shared) {
    const g = layout.field.encoding.h4;
    if (!g) return 0;
    return 8 + g.levels.reduce((s, l) => s + 4 + 5 * l.rows + maxBlockBytes(l.rows * g.features), 0);
  }
  return staticRanges(layout, kind).reduce((s, [, a, b]) => s + maxBlockBytes(b - a), 0);
}

class Reader {
  constructor(bytes, what) {
    this.b = bytes;
    this.pos = 0;
    this.what = what;
    this.view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  }
  take(n) {
    if (n > this.b.length - this.pos) throw new FormatError(this.what, `payload ends early (needs ${n} more bytes, ${this.b.length - this.pos} left)`);
    const s = this.b.subarray(this.pos, this.pos + n);
    this.pos += n;
    return s;
  }
  u8() {
    return this.take(1)[0];
  }
  u32() {
    const s = this.take(4);
    return u32(s, 0);
  }
  f32() {
    this.take(4);
    return this.view.getFloat32(this.pos - 4, true);
  }
  remaining() {
    return this.b.length - this.pos;
  }
  varint() {
    let v = 0;
    for (let i = 0; i < 5; i++) {
      const byte = this.u8();
      v += (byte & 0x7f) * 2 ** (7 * i);
      if (!(byte & 0x80)) {
        if (v > 0xffffffff) throw new FormatError(this.what, "varint above 2^32 - 1");
        return v;
      }
    }
    throw new FormatError(this.what, "varint longer than 5 bytes");
  }
  finish() {
    if (this.pos !== this.b.length) throw new FormatError(this.what, `${this.b.length - this.pos} trailing bytes`);
  }

  /** Reads one block (format.md §5.2) into `out` (a Float32Array of the expected length). */
  blockInto(out, name) {
    const bad = (m) => {
      throw new FormatError(`${this.what} (${name})`, m);
    };
    const enc = this.u8();
    const bits = this.u8();
    const predictor = this.u8();
    const reserved = this.u8();
    const count = this.u32();
    if (reserved !== 0) bad("reserved block byte must be 0");
    if (count !== out.length) bad(`block holds ${count} values, the model needs ${out.length}`);
    const quantised = enc === 2 || enc === 3;
    if (quantised && !(bits >= 1 && bits <= 8)) bad(`bits must be in 1..=8 (got ${bits})`);
    if (!quantised && enc <= 1 && (bits !== 0 || predictor !== 0)) bad("bits and predictor must be 0 for float blocks");
    if (predictor > 1) bad(`unsupported predictor ${predictor}`);
    if (enc === 0) {
      const b = this.take(4 * count);
      const word = new Uint8Array(4);
      const wv = new DataView(word.buffer);
      for (let i = 0; i < count; i++) {
        word[0] = b[i];
        word[1] = b[count + i];
        word[2] = b[2 * count + i];
        word[3] = b[3 * count + i];
        out[i] = wv.getFloat32(0, true);
      }
    } else if (enc === 1) {
      const b = this.take(2 * count);
      for (let i = 0; i < count; i++) out[i] = f16ToF32(b[i] | (b[count + i] << 8));
    } else if (quantised) {
      const k = 1 << bits;
      const book = new Float32Array(k);
      if (enc === 2) {
        const min = this.f32();
        const scale = this.f32();
        if (!(Number.isFinite(min) && Number.isFinite(scale) && scale >= 0)) bad(`affine min ${min} / scale ${scale} must be finite, scale >= 0`);
        for (let c = 0; c < k; c++) book[c] = Math.fround(min + Math.fround(c * scale));
      } else {
        for (let c = 0; c < k; c++) {
          book[c] = this.f32();
          if (!Number.isFinite(book[c])) bad(`codebook entry ${c} is not finite`);
        }
      }
      const b = this.take(count);
      let prev = 0;
      for (let i = 0; i < count; i++) {
        let code = b[i];
        if (predictor === 1) {
          prev = (prev + code) & 0xff;
          code = prev;
        }
        if (code >= k) bad(`code ${code} of value ${i} exceeds ${bits} bits`);
        out[i] = book[code];
      }
    } else {
      bad(`unsupported block encoding ${enc}`);
    }
    for (let i = 0; i < count; i++) if (!Number.isFinite(out[i])) bad(`value ${i} is not finite`);
  }
}

/** IEEE binary16 bits to a number (exact). */
export function f16ToF32(h) {
  const s = h & 0x8000 ? -1 : 1;
  const e = (h >> 10) & 0x1f;
  const m = h & 0x3ff;
  if (e === 0) return s * m * 2 ** -24;
  if (e === 31) return m ? NaN : s * Infinity;
  return s * (1 + m / 1024) * 2 ** (e - 15);
}

/** A section's label as msth-codec names it in errors. */
export function sectionLabel(s) {
  const base = s.kind === KIND.dynamic ? `dynamic chunk ${s.chunk}` : s.kind === KIND.shared ? "shared dynamic section" : `${KIND_NAME[s.kind]} section`;
  return s.layer ? `${base}, layer ${s.layer}` : base;
}

/** Checks the stored bytes' length and CRC-32 and decompresses into exactly `rawLength` bytes. */
export function unpack(entry, stored) {
  const what = sectionLabel(entry);
  if (stored.length < entry.length) throw new FormatError(what, `needs ${entry.length} bytes, have ${stored.length}`, true);
  if (stored.length !== entry.length) throw new FormatError(what, `${stored.length} bytes given, the index says ${entry.length}`);
  const computed = crc32(stored);
  if (computed !== entry.crc32) throw new FormatError(what, `CRC-32 mismatch (stored ${entry.crc32.toString(16)}, computed ${computed.toString(16)})`);
  checkZstdFrame(stored, entry.rawLength, what);
  const out = new Uint8Array(entry.rawLength);
  let n = 0;
  let over = false;
  const d = new Decompress((chunk) => {
    if (n + chunk.length > out.length) over = true;
    else out.set(chunk, n);
    n += chunk.length;
  });
  try {
    d.push(stored, true);
  } catch (e) {
    throw new FormatError(what, `zstd: ${e.message || e}`);
  }
  if (over || n !== out.length) throw new FormatError(what, `decompressed to ${n} bytes, the index says ${entry.rawLength}`);
  return out;
}

/**
 * Reads the zstd frame header (RFC 8878 §3.1.1.1) before decompressing: the magic, the declared
 * content size (must equal the index's `raw_length`) and the window size, which bounds what the
 * decompressor allocates (at most twice `raw_length`, or 8 MiB for small sections).
 */
function checkZstdFrame(b, rawLength, what) {
  const bad = (m) => {
    throw new FormatError(what, `zstd: ${m}`);
  };
  if (b.length < 6 || u32(b, 0) !== 0xfd2fb528) bad("not a zstd frame (bad magic)");
  const fhd = b[4];
  const fcsFlag = fhd >> 6;
  const single = (fhd >> 5) & 1;
  if (fhd & 0x08) bad("reserved frame header bit set");
  let o = 5;
  let window = null;
  if (!single) {
    const wd = b[o++];
    const base = 2 ** (10 + (wd >> 3));
    window = base + (base / 8) * (wd & 7);
  }
  o += [0, 1, 2, 4][fhd & 3]; // dictionary id
  const fcsBytes = [single ? 1 : 0, 2, 4, 8][fcsFlag];
  if (b.length < o + fcsBytes) bad("truncated frame header");
  let fcs = null;
  if (fcsBytes === 1) fcs = b[o];
  else if (fcsBytes === 2) fcs = (b[o] | (b[o + 1] << 8)) + 256;
  else if (fcsBytes === 4) fcs = u32(b, o);
  else if (fcsBytes === 8) fcs = u32(b, o) + u32(b, o + 4) * 2 ** 32;
  if (fcs !== null && fcs !== rawLength) bad(`frame content size ${fcs}, the index says ${rawLength}`);
  if (window === null) window = fcs;
  if (window > Math.max(2 * rawLength, 8 << 20)) bad(`window of ${window} bytes for ${rawLength} bytes of content`);
  // format.md §1.1: a section is exactly one frame. Walk the block headers (§3.1.1.2) to the
  // frame's end: a second frame or any trailing byte is rejected, as msth-codec does.
  o += fcsBytes;
  for (;;) {
    if (o + 3 > b.length) bad("truncated block header");
    const h = b[o] | (b[o + 1] << 8) | (b[o + 2] << 16);
    const type = (h >> 1) & 3;
    if (type === 3) bad("reserved block type");
    o += 3 + (type === 1 ? 1 : h >>> 3);
    if (h & 1) break;
  }
  if (fhd & 0x04) o += 4; // content checksum
  if (o > b.length) bad("truncated frame");
  if (o < b.length) throw new FormatError(what, `${b.length - o} bytes after the zstd frame (${o} of ${b.length} stored bytes): a section is exactly one frame`);
}

/** Decodes a non-chunk section's payload into the flat buffer `params`; `levels`: the 3D
 * levels of a layered static section's layer (`layerRange`). */
export function readStatic(layout, payload, entry, params, levels = null) {
  const r = new Reader(payload, sectionLabel(entry));
  for (const [name, a, b] of staticRanges(layout, entry.kind, levels, entry.layer === 0)) r.blockInto(params.subarray(a, b), name);
  r.finish();
}

/**
 * Decodes an occupancy payload (format.md §6.5) strictly: `{ resolution, densityThreshold,
 * frames, words }`, `words` a Uint32Array where bit `i % 32` of word `i >> 5` is cell
 * `i = x + R (y + R z)` of the unit cube (set: something is there at some frame).
 */
export function readOccupancy(payload, entry, limits = LIMITS) {
  const what = sectionLabel(entry);
  if (payload.length < OCCUPANCY.headerBytes) throw new FormatError(what, `${payload.length} bytes, the occupancy header needs ${OCCUPANCY.headerBytes}`);
  const view = new DataView(payload.buffer, payload.byteOffset, payload.byteLength);
  const resolution = view.getUint32(0, true);
  const densityThreshold = view.getFloat32(4, true);
  const frames = view.getUint32(8, true);
  if (resolution === 0) throw new FormatError(what, "occupancy resolution 0");
  if (resolution > limits.maxOccupancyResolution) throw new FormatError(what, `resolution ${resolution} exceeds the limit ${limits.maxOccupancyResolution}`);
  if (!(Number.isFinite(densityThreshold) && densityThreshold >= 0)) throw new FormatError(what, `density threshold ${densityThreshold} is not finite and >= 0`);
  if (view.getUint32(12, true) !== 0) throw new FormatError(what, "reserved field must be zero");
  const need = occupancyPayloadLength(resolution);
  if (payload.length !== need) throw new FormatError(what, `${payload.length} bytes, resolution ${resolution} needs ${need}`);
  const words = new Uint32Array(need / 4 - OCCUPANCY.headerBytes / 4);
  for (let i = 0; i < words.length; i++) words[i] = view.getUint32(OCCUPANCY.headerBytes + 4 * i, true);
  const tail = resolution ** 3 % 32;
  if (tail && words[words.length - 1] >>> tail) throw new FormatError(what, "bits past the last cell must be zero");
  return { resolution, densityThreshold, frames, words };
}

/** Whether the occupancy cell holding unit-cube point `p` is set (as msth-codec's `occupied_unit`). */
export function occupiedUnit(grid, p) {
  const r = grid.resolution;
  const c = (v) => Math.min(Math.trunc(Math.fround(Math.min(Math.max(v, 0), 1) * r)), r - 1);
  const i = c(p[0]) + r * (c(p[1]) + r * c(p[2]));
  return ((grid.words[i >>> 5] >>> (i & 31)) & 1) === 1;
}

/** Decodes a shared or chunk payload: per 4D level `{ rows: Uint32Array, values: Float32Array }`;
 * `allowed` `[start, end)`: the levels of its layer (the others must store no rows). */
export function readChunk(layout, payload, entry, allowed = [0, Infinity]) {
  const what = sectionLabel(entry);
  const g = layout.field.encoding.h4;
  if (!g) throw new FormatError(what, "the model has no 4D table");
  const r = new Reader(payload, what);
  const tag = r.u32();
  const want = entry.kind === KIND.shared ? SHARED_TAG : entry.chunk;
  if (tag !== want) throw new FormatError(what, `payload is tagged ${tag.toString(16)}, expected ${want.toString(16)}`);
  const n = r.u32();
  if (n !== g.levels.length) throw new FormatError(what, `${n} levels, the 4D grid has ${g.levels.length}`);
  const levels = [];
  g.levels.forEach((level, l) => {
    const count = r.u32();
    if (count > 0 && (l < allowed[0] || l >= allowed[1])) throw new FormatError(what, `level ${l}: ${count} rows stored, but this layer holds levels ${allowed[0]}..${allowed[1]}`);
    if (count > level.rows) throw new FormatError(what, `level ${l}: ${count} rows stored, the table has ${level.rows}`);
    if (count > r.remaining()) throw new FormatError(what, `level ${l}: ${count} rows but ${r.remaining()} bytes left`);
    const rows = new Uint32Array(count);
    let next = 0;
    for (let k = 0; k < count; k++) {
      const row = next + r.varint();
      if (row >= level.rows) throw new FormatError(what, `level ${l}: row ${row} outside the table (${level.rows} rows)`);
      rows[k] = row;
      next = row + 1;
    }
    const values = new Float32Array(count * g.features);
    r.blockInto(values, `field.h4 level ${l}`);
    levels.push({ rows, values });
  });
  r.finish();
  return levels;
}

/** Writes a sparse chunk's rows into the field's 4D table in `params`. */
export function applyChunk(layout, levels, params) {
  const g = layout.field.encoding.h4;
  if (!g) return;
  const f = g.features;
  levels.forEach(({ rows, values }, l) => {
    const base = g.start + g.levels[l].offset;
    for (let k = 0; k < rows.length; k++) params.set(values.subarray(k * f, (k + 1) * f), base + rows[k] * f);
  });
}

/** The chunk for normalised time `t` (format.md §3.3), or null without chunks. */
export function chunkForTime(metadata, t) {
  const spans = metadata.chunks;
  if (!spans.length) return null;
  const tf = Math.fround(t);
  for (let c = spans.length - 1; c >= 0; c--) if (Math.fround(spans[c].t_start) <= tf) return c;
  return 0;
}

/**
 * A streaming decoder: the prefix first, then sections in any order from their own bytes
 * (as msth-codec's `Decoder`). `paramsForTime` assembles the flat buffer for a time.
 */
export class Decoder {
  constructor(prefix, limits = LIMITS) {
    Object.assign(this, parsePrefix(prefix, limits));
    this.limits = limits;
    this.base = new Float32Array(this.layout.total);
    this.decoded = new Array(this.sections.length).fill(false);
    /** Per layer: the shared section's rows, and per chunk the chunk's rows. */
    this.sharedLayers = this.layers.map(() => null);
    this.chunkLayers = this.layers.map(() => new Array(this.metadata.chunks.length).fill(null));
    /** Layer 0 of each chunk. */
    this.chunks = this.chunkLayers[0];
    /** The occupancy grid (`readOccupancy`) once decoded; stays null for a version-1 file. */
    this.occupancy = null;
  }

  /** Decodes index entry `i` from its stored bytes. */
  decodeSection(i, stored) {
    const e = this.sections[i];
    const payload = unpack(e, stored);
    const layered = this.metadata.layers !== undefined;
    if (e.kind === KIND.shared) this.sharedLayers[e.layer] = readChunk(this.layout, payload, e, layerRange(this.layers, e.layer, "h4"));
    else if (e.kind === KIND.dynamic) this.chunkLayers[e.layer][e.chunk] = readChunk(this.layout, payload, e, layerRange(this.layers, e.layer, "h4"));
    else if (e.kind === KIND.occupancy) this.occupancy = readOccupancy(payload, e, this.limits);
    else if (e.kind === KIND.static && layered) {
      // Into a copy: a failure leaves the decoder as it was.
      const next = this.base.slice();
      readStatic(this.layout, payload, e, next, layerRange(this.layers, e.layer, "h3"));
      this.base = next;
    } else if (e.kind === KIND.proposal && layered) {
      const next = this.base.slice();
      readStatic(this.layout, payload, e, next, { h3: layerRange(this.layers, e.layer, "p3"), h4: layerRange(this.layers, e.layer, "p4") });
      this.base = next;
    } else readStatic(this.layout, payload, e, this.base);
    this.decoded[i] = true;
  }

  /** Layer 0 of the shared section (null before it arrives, and without chunks). */
  get shared() {
    return this.sharedLayers[0];
  }

  /** Index position of a section (`sectionPosition`). */
  position(kind, chunk, layer) {
    return sectionPosition(this, kind, chunk, layer);
  }

  /**
   * The index positions a player holding layers `0..layers` of chunk `c` (null: a file without
   * chunks) has decoded (msth-codec's `FileIndex::sections_for`).
   */
  sectionsFor(c, layers) {
    const out = [];
    for (let i = 0; i < this.beforeFirstFrame; i++) out.push(i);
    for (let l = 0; l < Math.min(layers, this.layers.length); l++) {
      const add = (i) => i !== null && out.push(i);
      if (l > 0) {
        add(this.position(KIND.proposal, 0, l));
        add(this.position(KIND.static, 0, l));
        add(this.position(KIND.shared, 0, l));
      }
      if (c !== null) add(this.position(KIND.dynamic, c, l));
    }
    return out;
  }

  /** Whether the sections every frame needs are decoded. */
  staticReady() {
    return this.decoded.slice(0, this.beforeFirstFrame).every(Boolean);
  }

  /**
   * How many layers, from the first, of chunk `c` (null: a file without chunks) have arrived
   * with the static and shared sections of the same layers (as msth-codec's `layers_ready`).
   */
  layersReady(c) {
    if (!this.staticReady()) return 0;
    let n = 0;
    const ok = (kind, chunk, l) => {
      const i = this.position(kind, chunk, l);
      return i === null || this.decoded[i];
    };
    while (n < this.layers.length && ok(KIND.proposal, 0, n) && ok(KIND.static, 0, n) && ok(KIND.shared, 0, n) && (c === null || ok(KIND.dynamic, c, n))) n++;
    return n;
  }

  chunkForTime(t) {
    return chunkForTime(this.metadata, t);
  }

  /** Whether the parameters for time `t` can be assembled now. */
  readyFor(t) {
    const c = this.chunkForTime(t);
    return this.staticReady() && (c === null || this.chunks[c] !== null);
  }

  /**
   * The flat parameter buffer for time `t` (into `out` when given): the static layers that have
   * arrived and the 4D layers of `layersReady`, at most `layers` of each (msth-codec's
   * `params_for_layers_into`).
   */
  paramsForTime(t, out = new Float32Array(this.layout.total), layers = Infinity) {
    if (!this.readyFor(t)) throw new FormatError("decoder", `the sections for time ${t} are not loaded`);
    out.set(this.base);
    if (layers < this.layers.length) {
      // The levels of the layers left out: the field's 3D table, the proposal's tables.
      const keep = this.layers[Math.max(layers, 1) - 1];
      const p = this.layout.proposal.encoding;
      for (const [g, k] of [[this.layout.field.encoding.h3, keep.h3], [p.h3, keep.p3], [p.h4, keep.p4]]) {
        if (g) g.levels.slice(k).forEach((lv) => out.fill(0, g.start + lv.offset, g.start + lv.offset + lv.rows * g.features));
      }
    }
    const c = this.chunkForTime(t);
    if (c !== null) {
      const n = Math.min(this.layersReady(c), Math.max(layers, 1));
      for (let l = 0; l < n; l++) {
        if (this.sharedLayers[l]) applyChunk(this.layout, this.sharedLayers[l], out);
        if (this.chunkLayers[l][c]) applyChunk(this.layout, this.chunkLayers[l][c], out);
      }
    }
    return out;
  }
}
