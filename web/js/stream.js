// Streaming a `.msth` file over HTTP Range requests, in the order of the native client
// (player/src/stream.rs): the first 32 bytes, the prefix (header, metadata, index), the sections
// every frame needs (MLP, proposal, static, shared) in one request when they are contiguous, then
// the chunk under the playhead, then the others in playback order from there, wrapping around.
// One difference: the MLP section, when it comes first, is a request of its own, so that the
// page compiles its kernels for the model (specialise.js) while the larger sections stream.
// Every response is checked (status 206, Content-Range equal to what was asked, exact length,
// If-Range with the first response's validator so a file replaced mid-stream is detected).
// Sections are decoded as they arrive; `ranges` tells the loading bar what has streamed.

import { Decoder, FIXED_HEADER, FormatError, KIND, prefixLength } from "./format.js";

/** Largest gap between two sections fetched in one request (as stream.rs). */
const MAX_GAP = 4096;
/** A server that ignores Range requests: largest file downloaded whole. */
const MAX_WHOLE = 1 << 30;

/** The error with the file's URL in front (HTTP errors already carry it). */
function named(url, e) {
  const msg = String(e && e.message ? e.message : e);
  return msg.startsWith(url) ? e : new Error(`${url}: ${msg}`);
}

class HttpSource {
  constructor(url) {
    this.url = url;
    this.validator = null;
    this.length = null;
    this.whole = null;
    this.requests = 0;
    this.bytes = 0;
  }

  /** Bytes `start..end` (end exclusive); `onBytes(n)` reports progress as they arrive. */
  async read(start, end, onBytes = () => {}) {
    if (this.whole) return this.whole.subarray(start, end);
    const headers = { Range: `bytes=${start}-${end - 1}` };
    if (this.validator) headers["If-Range"] = this.validator;
    this.requests++;
    const resp = await fetch(this.url, { headers, cache: "no-store" });
    const fail = (m) => {
      throw new Error(`${this.url}: ${m}`);
    };
    if (resp.status === 200 && this.length === null) {
      const n = Number(resp.headers.get("content-length"));
      if (n > MAX_WHOLE) fail(`the server ignores Range requests and the file is ${n} bytes`);
      this.whole = await readBody(resp, n || null, onBytes, fail);
      this.length = this.whole.length;
      this.bytes += this.whole.length;
      return this.whole.subarray(start, Math.min(end, this.length));
    }
    if (resp.status === 200) fail("the file changed on the server (200 to an If-Range request)");
    if (resp.status !== 206) fail(`HTTP ${resp.status} ${resp.statusText}`);
    const cr = resp.headers.get("content-range") || "";
    const m = /^bytes (\d+)-(\d+)\/(\d+|\*)$/.exec(cr.trim());
    if (!m) fail(`malformed Content-Range \`${cr}\``);
    const [a, b] = [Number(m[1]), Number(m[2])];
    if (this.length === null) {
      if (m[3] === "*") fail("the server does not tell the file length");
      this.length = Number(m[3]);
      const etag = resp.headers.get("etag");
      this.validator = etag && !etag.startsWith("W/") ? etag : resp.headers.get("last-modified");
    }
    if (a !== start || b !== Math.min(end, this.length) - 1) fail(`asked for bytes ${start}-${end - 1}, got Content-Range \`${cr}\``);
    const body = await readBody(resp, b + 1 - a, onBytes, fail);
    this.bytes += body.length;
    return body;
  }
}

async function readBody(resp, expected, onBytes, fail) {
  const reader = resp.body.getReader();
  const parts = [];
  let n = 0;
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    n += value.length;
    if (expected !== null && n > expected) fail(`body longer than the ${expected} bytes asked for`);
    if (n > MAX_WHOLE) fail("body too large");
    parts.push(value);
    onBytes(value.length);
  }
  if (expected !== null && n !== expected) fail(`body ended after ${n} of ${expected} bytes`);
  const out = new Uint8Array(n);
  let o = 0;
  for (const p of parts) {
    out.set(p, o);
    o += p.length;
  }
  return out;
}

/**
 * A `.msth` file being streamed. `open` reads the prefix; `start` runs the fetch loop in the
 * background. Listeners registered with `onChange` hear about every decoded section and every
 * received byte.
 */
export class ModelStream {
  static async open(url) {
    try {
      return await ModelStream.#open(url);
    } catch (e) {
      throw named(url, e);
    }
  }

  static async #open(url) {
    const src = new HttpSource(url);
    const s = new ModelStream(src);
    const first = await src.read(0, FIXED_HEADER, (n) => s.#received(n));
    const hs = prefixLength(first);
    if (hs > src.length) throw new FormatError("header and index", `the file is ${src.length} bytes, its prefix ${hs}`, true);
    const prefix = await src.read(0, hs, (n) => s.#received(n));
    s.decoder = new Decoder(prefix);
    if (s.decoder.fileLength > src.length) throw new FormatError("file", `the index points past its end (${s.decoder.fileLength} > ${src.length} bytes)`, true);
    s.fileLength = s.decoder.fileLength;
    s.ranges.push([0, hs]);
    s.bytesReady = hs;
    return s;
  }

  constructor(source) {
    this.source = source;
    this.decoder = null;
    this.want = null;
    this.error = null;
    this.bytesReady = 0;
    this.bytesReceived = 0;
    /** Byte ranges decoded so far, `[start, end)`, and the one being fetched. */
    this.ranges = [];
    this.inflight = null;
    this.listeners = new Set();
    this.stopped = false;
    this.openedAt = performance.now();
  }

  #received(n) {
    this.bytesReceived += n;
    if (this.inflight) this.inflight.got += n;
    this.#notify();
  }

  #notify() {
    for (const f of this.listeners) f(this);
  }

  onChange(f) {
    this.listeners.add(f);
    return () => this.listeners.delete(f);
  }

  get metadata() {
    return this.decoder.metadata;
  }

  /** Moves the playhead: the chunk for time `t` is fetched next. */
  seek(t) {
    const c = this.decoder.chunkForTime(t);
    if (c !== this.want) this.want = c;
  }

  readyFor(t) {
    return this.decoder.readyFor(t);
  }

  /** Resolves when the parameters for time `t` can be assembled (and moves the playhead). */
  waitFor(t) {
    this.seek(t);
    return this.#until(() => this.decoder.readyFor(t));
  }

  /**
   * Resolves when every section of `kind` (format.js `KIND`) is decoded: the MLP section, for
   * compiling the kernels with the model's weights (renderer.js `create`), comes in the first
   * request after the prefix.
   */
  waitForKind(kind) {
    return this.#until(() => this.decoder.sections.every((s, i) => s.kind !== kind || this.decoder.decoded[i]));
  }

  /** Resolves when `done()` holds, checked at every change; rejects on the stream's error. */
  #until(done) {
    return new Promise((resolve, reject) => {
      const check = () => {
        if (this.error) {
          off();
          reject(this.error);
        } else if (done()) {
          off();
          resolve();
        }
      };
      const off = this.onChange(check);
      check();
    });
  }

  /** Runs the fetch loop until the whole file is in, an error, or `stop()`. */
  start() {
    this.done = this.#loop().catch((e) => {
      this.error = named(this.source.url, e);
      this.#notify();
    });
    return this;
  }

  stop() {
    this.stopped = true;
  }

  #nextRequest() {
    const d = this.decoder;
    const secs = d.sections;
    const nStatic = Math.min(d.firstChunk, secs.length);
    const missing = [];
    for (let i = 0; i < nStatic; i++) if (!d.decoded[i]) missing.push(i);
    if (missing.length) {
      const first = missing[0];
      const last = missing[missing.length - 1];
      let contiguous = missing.length === last - first + 1;
      for (let i = first; contiguous && i < last; i++) {
        const end = secs[i].offset + secs[i].length;
        contiguous = secs[i + 1].offset >= end && secs[i + 1].offset - end <= MAX_GAP;
      }
      // The MLP section alone first: the kernels are compiled from it (renderer.js `create`
      // waits for it) while the other sections stream.
      if (secs[first].kind === KIND.mlp || !contiguous) return [first, first + 1];
      return [first, last + 1];
    }
    const chunks = secs.length - nStatic;
    if (chunks === 0) return null;
    const start = Math.min(this.want ?? 0, chunks - 1);
    for (let k = 0; k < chunks; k++) {
      const c = (start + k) % chunks;
      if (!d.chunks[c]) return [d.firstChunk + c, d.firstChunk + c + 1];
    }
    return null;
  }

  async #loop() {
    for (;;) {
      if (this.stopped) return;
      const req = this.#nextRequest();
      if (!req) return;
      const entries = this.decoder.sections.slice(req[0], req[1]);
      const start = entries[0].offset;
      const end = Math.max(...entries.map((e) => e.offset + e.length));
      this.inflight = { start, end, got: 0 };
      const bytes = await this.source.read(start, end, (n) => this.#received(n));
      this.inflight = null;
      entries.forEach((e, k) => {
        const lo = e.offset - start;
        this.decoder.decodeSection(req[0] + k, bytes.subarray(lo, lo + e.length));
        this.bytesReady += e.length;
        this.ranges.push([e.offset, e.offset + e.length]);
      });
      this.#notify();
    }
  }

  /** Sections decoded / total, bytes decoded / file, HTTP requests made. */
  progress() {
    const d = this.decoder;
    return {
      sectionsReady: d.decoded.filter(Boolean).length,
      sections: d.sections.length,
      bytesReady: this.bytesReady,
      bytesReceived: this.bytesReceived,
      fileLength: this.fileLength,
      requests: this.source.requests,
      complete: d.decoded.every(Boolean),
    };
  }
}
