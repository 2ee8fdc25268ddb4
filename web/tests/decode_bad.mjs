// Bad input to the web player's decoder (web/js/format.js): every damaged copy of a good `.msth`
// file must be rejected with one FormatError naming the part of the file, never a crash, a hang
// or a huge allocation. Run: node web/tests/decode_bad.mjs FILE.msth (exit status 1 on failure).

import { readFileSync } from "node:fs";
import { Decoder, FormatError, prefixLength, VERSION } from "../js/format.js";

const file = process.argv[2];
if (!file) {
  console.error("usage: node web/tests/decode_bad.mjs FILE.msth");
  process.exit(2);
}
const good = new Uint8Array(readFileSync(file));

/** Decodes a whole file as the page does: prefix, then every section from its own bytes. */
function decode(bytes) {
  const hs = prefixLength(bytes.subarray(0, 32));
  if (bytes.length < hs) throw new FormatError("header and index", "truncated", true);
  const d = new Decoder(bytes.subarray(0, hs));
  d.sections.forEach((s, i) => d.decodeSection(i, bytes.subarray(s.offset, s.offset + s.length)));
  return d;
}

let failed = false;
function expectError(name, bytes, pattern) {
  try {
    decode(bytes);
    console.log(`FAIL ${name}: accepted`);
    failed = true;
  } catch (e) {
    const ok = e instanceof FormatError && pattern.test(e.message);
    console.log(`${ok ? "PASS" : "FAIL"} ${name}: ${e.message}`);
    if (!ok) failed = true;
  }
}

decode(good);
const d = decode(good);
const edit = (f) => {
  const b = good.slice();
  f(b);
  return b;
};
const view = (b) => new DataView(b.buffer);
expectError("bad magic", edit((b) => (b[0] = 0x4e)), /magic/);
expectError("unknown version", edit((b) => view(b).setUint16(4, VERSION + 1, true)), new RegExp(`version ${VERSION + 1}`));
expectError("reserved flags", edit((b) => (b[6] = 1)), /flag/);
expectError("truncated header", good.slice(0, 20), /fixed header/);
expectError("truncated prefix", good.slice(0, d.headerSize - 1), /header and index/);
expectError("huge metadata length", edit((b) => view(b).setUint32(12, 0xfffffff0, true)), /metadata length/);
expectError("prefix CRC", edit((b) => (b[40] ^= 1)), /CRC-32/);
d.sections.forEach((s, i) => {
  expectError(`section ${i} CRC`, edit((b) => (b[s.offset + (s.length >> 1)] ^= 0x10)), /CRC-32/);
  expectError(`section ${i} truncated`, good.slice(0, s.offset + s.length - 1), /needs|ends early|bytes/);
});
// A consistent prefix (CRC recomputed) whose section claims a huge raw length.
expectError(
  "raw length above the model's maximum",
  edit((b) => {
    const io = Math.ceil((32 + view(b).getUint32(12, true)) / 8) * 8;
    view(b).setUint32(io + 24, 0x7fffffff, true);
    fixCrc(b);
  }),
  /raw length/,
);
expectError(
  "metadata with an unknown key",
  edit((b) => {
    const ml = view(b).getUint32(12, true);
    const text = new TextDecoder().decode(b.subarray(32, 32 + ml));
    const bad = text.replace('"encoder"', '"encodeR"');
    b.set(new TextEncoder().encode(bad), 32);
    fixCrc(b);
  }),
  /unknown key/,
);

function crcOf(bytes) {
  let c = 0xffffffff;
  for (const x of bytes) {
    c ^= x;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
  }
  return ~c >>> 0;
}

function fixCrc(b) {
  const hs = view(b).getUint32(8, true);
  let c = 0xffffffff;
  const feed = (x) => {
    c ^= x;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
  };
  for (let i = 0; i < 28; i++) feed(b[i]);
  for (let i = 32; i < hs; i++) feed(b[i]);
  view(b).setUint32(28, ~c >>> 0, true);
}

// A damaged zstd frame under a matching CRC (the frame magic, the frame header): the
// decompressor's failure is reported for that section. (Damaged entropy-coded bytes may decode
// to other valid values: zstd frames here carry no checksum of their own, the index's CRC-32 is
// what catches them, as the "section CRC" cases show.)
for (const [what, at, x] of [["frame magic", 0, 0xff], ["frame header descriptor", 4, 0xc0]]) {
  expectError(
    `static section with a damaged ${what}, CRC matching`,
    edit((b) => {
      const s = d.sections[2];
      b[s.offset + at] ^= x;
      const io = Math.ceil((32 + view(b).getUint32(12, true)) / 8) * 8;
      view(b).setUint32(io + 2 * 40 + 32, crcOf(b.subarray(s.offset, s.offset + s.length)), true);
      fixCrc(b);
    }),
    /static section/,
  );
}

// format.md §1.1: a section is exactly one zstd frame. Append to the last section, with its
// length, its CRC-32 and the prefix CRC fixed, so that only the extra bytes are wrong: an empty
// second frame (decoding both frames still gives exactly `raw_length` bytes), a skippable
// frame, and plain trailing bytes.
const EMPTY_FRAME = [0x28, 0xb5, 0x2f, 0xfd, 0x20, 0x00, 0x01, 0x00, 0x00];
const SKIPPABLE_FRAME = [0x50, 0x2a, 0x4d, 0x18, 4, 0, 0, 0, 1, 2, 3, 4];
for (const [what, extra] of [["a second (empty) zstd frame", EMPTY_FRAME], ["a skippable frame", SKIPPABLE_FRAME], ["trailing bytes", [0, 0, 0]]]) {
  const last = d.sections.length - 1;
  const s = d.sections[last];
  expectError(
    `last section followed by ${what}`,
    (() => {
      const b = new Uint8Array(good.length + extra.length);
      b.set(good);
      b.set(extra, good.length);
      const io = Math.ceil((32 + view(b).getUint32(12, true)) / 8) * 8;
      view(b).setUint32(io + last * 40 + 16, s.length + extra.length, true);
      view(b).setUint32(io + last * 40 + 32, crcOf(b.subarray(s.offset, s.offset + s.length + extra.length)), true);
      fixCrc(b);
      return b;
    })(),
    /after the zstd frame/,
  );
}
// format.md §3: time_range is [0, 1] in version 1.
expectError(
  "time_range [0, 2]",
  edit((b) => {
    const ml = view(b).getUint32(12, true);
    const text = new TextDecoder().decode(b.subarray(32, 32 + ml));
    const bad = text.replace(/"time_range":\[0(\.0)?,1(\.0)?\]/, (m) => m.replace(/,1/, ",2"));
    if (bad === text) throw new Error("no time_range [0, 1] in the metadata");
    b.set(new TextEncoder().encode(bad), 32);
    fixCrc(b);
  }),
  /time_range is \[0, 2\]/,
);

console.log(failed ? "bad-input test FAILED" : "bad-input test passed");
process.exit(failed ? 1 : 0);
