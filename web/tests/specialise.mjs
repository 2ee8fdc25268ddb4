// Prints the `specialise` region web/js/specialise.js writes for a `.msth` file (decoded with the
// page's decoder, split with the page's `gpuModel`), for `tests/tests/web_specialise.rs` to
// compare with msth-gpu's `specialise.rs`:
//   node web/tests/specialise.mjs FILE.msth > REGION.wgsl
// An error (a model whose MLPs are not specialised) is printed as `error: MESSAGE`.

import { readFileSync } from "node:fs";
import { Decoder, prefixLength } from "../js/format.js";
import { gpuModel } from "../js/renderer.js";
import { specialisedRegion } from "../js/specialise.js";

const [file] = process.argv.slice(2);
if (!file) {
  console.error("usage: node web/tests/specialise.mjs FILE.msth");
  process.exit(2);
}
const bytes = new Uint8Array(readFileSync(file));
const dec = new Decoder(bytes.subarray(0, prefixLength(bytes.subarray(0, 32))));
dec.sections.forEach((s, i) => dec.decodeSection(i, bytes.subarray(s.offset, s.offset + s.length)));
const gm = gpuModel(dec.metadata.model, dec.layout);
try {
  process.stdout.write(specialisedRegion(gm, dec.paramsForTime(0).subarray(gm.split.rest[0])));
} catch (e) {
  process.stdout.write(`error: ${e.message}\n`);
}
