// The page's binary16 hash tables, for `tests/tests/web_specialise.rs` to compare with msth-gpu's
// `TableFormat::F16`:
//   node web/tests/binary16.mjs VALUES.f32 OUT.bin OUT.wgsl
// writes `toBinary16` of the little-endian f32 values in VALUES.f32 to OUT.bin, and
// `tablesSource` of the page's `render.wgsl` and `tables_f16.wgsl` to OUT.wgsl; prints the
// count of values the clamp changed as JSON (`{"clamped": N}`).

import { readFileSync, writeFileSync } from "node:fs";
import { tablesSource, toBinary16 } from "../js/renderer.js";

const [input, bin, wgsl] = process.argv.slice(2);
if (!wgsl) {
  console.error("usage: node web/tests/binary16.mjs VALUES.f32 OUT.bin OUT.wgsl");
  process.exit(2);
}
const bytes = readFileSync(input);
const values = new Float32Array(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength));
const bits = toBinary16(values);
writeFileSync(bin, new Uint8Array(bits.buffer));
console.log(JSON.stringify({ clamped: bits.clamped }));
const shader = (name) => readFileSync(new URL(`../shaders/${name}`, import.meta.url), "utf8");
writeFileSync(wgsl, tablesSource(shader("render.wgsl"), shader("tables_f16.wgsl")));
