// The web player's decoder (web/js/format.js) against the native bad corpus (tests/bad/): every
// file must be rejected with a FormatError, as msth-codec rejects it, except those whose only
// fault lies outside every section and the prefix (trailing bytes, padding between sections),
// which a streaming decoder never reads (format.md §1.1, §4). Each line says what happened.
// Run: node web/tests/decode_corpus.mjs DIR [NAME_ONLY_A_WHOLE_FILE_DECODER_SEES ...]
// (exit status 1 when a file is accepted that should not be, or fails other than cleanly).

import { readFileSync, readdirSync } from "node:fs";
import { Decoder, FormatError, prefixLength } from "../js/format.js";

const [dir, ...wholeFileOnly] = process.argv.slice(2);
if (!dir) {
  console.error("usage: node web/tests/decode_corpus.mjs DIR [NAME ...]");
  process.exit(2);
}
let failed = false;
const files = readdirSync(dir).filter((f) => f.endsWith(".msth")).sort();
for (const f of files) {
  const bytes = new Uint8Array(readFileSync(`${dir}/${f}`));
  let error = null;
  try {
    const hs = prefixLength(bytes.subarray(0, 32));
    if (bytes.length < hs) throw new FormatError("header and index", "truncated", true);
    const d = new Decoder(bytes.subarray(0, hs));
    d.sections.forEach((s, i) => d.decodeSection(i, bytes.subarray(s.offset, s.offset + s.length)));
  } catch (e) {
    error = e;
  }
  const expectAccept = wholeFileOnly.includes(f);
  const ok = expectAccept ? error === null : error instanceof FormatError;
  if (!ok) failed = true;
  console.log(`${ok ? "PASS" : "FAIL"} ${f}: ${error ? error.message : "accepted"}`);
}
console.log(`${files.length} files; ${failed ? "corpus test FAILED" : "corpus test passed"}`);
process.exit(failed || files.length === 0 ? 1 : 0);
