// Decodes a `.msth` file with the web player's decoder (web/js/format.js) section by section, as
// the page streams it, and compares the flat parameter buffer at given times with reference
// buffers written by msth-codec (raw little-endian f32). Run from anywhere:
//   node web/tests/decode.mjs FILE.msth [T=REF.f32 | T@K=REF.f32 ...]
// `T@K`: the buffer with the first K progressive layers (version 4), checked twice: from the
// whole file asked for K layers, and from a decoder fed only the sections of those layers.
// Without references it prints a summary of the decoded file. Exit status 1 on any mismatch.

import { readFileSync } from "node:fs";
import { Decoder, prefixLength } from "../js/format.js";

const [file, ...refs] = process.argv.slice(2);
if (!file) {
  console.error("usage: node web/tests/decode.mjs FILE.msth [T=REF.f32 ...]");
  process.exit(2);
}
const bytes = new Uint8Array(readFileSync(file));
const hs = prefixLength(bytes.subarray(0, 32));
const dec = new Decoder(bytes.subarray(0, hs));
dec.sections.forEach((s, i) => dec.decodeSection(i, bytes.subarray(s.offset, s.offset + s.length)));
console.log(`${file}: ${dec.sections.length} sections, ${dec.layout.total} parameters, quant ${dec.metadata.quant}`);
let failed = false;
for (const spec of refs) {
  const [key, path] = spec.split("=");
  const [t, k] = key.split("@");
  const ref = new Float32Array(new Uint8Array(readFileSync(path)).slice().buffer);
  const layers = k === undefined ? Infinity : Number(k);
  const got = dec.paramsForTime(Number(t), undefined, layers);
  if (k !== undefined) {
    // Only the sections of the first k layers, as a player that stopped there holds them.
    const part = new Decoder(bytes.subarray(0, hs));
    const c = part.chunkForTime(Number(t));
    for (const i of part.sectionsFor(c, layers)) {
      const s = part.sections[i];
      part.decodeSection(i, bytes.subarray(s.offset, s.offset + s.length));
    }
    if (part.layersReady(c) !== Math.min(layers, part.layers.length)) {
      console.log(`t=${t}@${k}: ${part.layersReady(c)} layers ready from the prefix's sections`);
      failed = true;
    }
    const fromPrefix = part.paramsForTime(Number(t));
    const a = new Uint32Array(fromPrefix.buffer);
    const b = new Uint32Array(got.buffer);
    const differ = a.findIndex((v, i) => v !== b[i]);
    if (differ >= 0) {
      console.log(`t=${t}@${k}: the prefix's decoder differs from the whole file's at ${differ}`);
      failed = true;
    }
  }
  if (ref.length !== got.length) {
    console.log(`t=${t}: length ${got.length}, reference ${ref.length}`);
    failed = true;
    continue;
  }
  let diff = 0;
  let first = -1;
  const gb = new Uint32Array(got.buffer);
  const rb = new Uint32Array(ref.buffer);
  for (let i = 0; i < got.length; i++) {
    if (gb[i] !== rb[i]) {
      diff++;
      if (first < 0) first = i;
    }
  }
  console.log(`t=${t}: ${diff} of ${got.length} values differ from ${path}${diff ? ` (first at ${first}: ${got[first]} vs ${ref[first]})` : " (bit-exact)"}`);
  if (diff) failed = true;
}
process.exit(failed ? 1 : 0);
