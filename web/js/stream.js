// Streaming a `.msth` file over HTTP Range requests, in the order of the native client
// (player/src/stream.rs): the first 32 bytes, the prefix (header, metadata, index), the sections
// every frame needs (MLP, proposal, static, shared) in one request when they are contiguous, then
// the chunk under the playhead, then the others in playback order from there, wrapping around.
// One difference: the MLP section, when it comes first, is a request of its own, so that the
// page compiles its kernels for the model (specialise.js) while the larger sections stream.
// Every response is checked (status 206, Content-Range equal to what was asked, exact length,
// If-Range with the first response's validator so a file replaced mid-stream is detected), and no
// response is read past what was asked for: before the header arrives a response is bounded by
// the prefix being read; once it is parsed, by the length the header declares (`limitTo`), and a
// length the server declared otherwise (Content-Range total, Content-Length) is an error naming
// both. A server that ignores Range requests (200) is read as a stream in file order, never
// buffered whole. Every read has a deadline and a stall deadline (`?deadline=`, `?stall=`, in
// seconds); either ends the stream with a message saying which bytes stalled.
// Sections are decoded as they arrive; `ranges` tells the loading bar what has streamed.
// What comes next is abr.js's choice, the native player's: of a layered file, layer 0 of the
// coming chunks first, then as many finer layers as the measured rate carries before each chunk
// plays (`setSpeed` tells it how fast playback runs).

import { Decoder, FIXED_HEADER, FormatError, KIND, prefixLength } from "./format.js";
import { nextRequest, RateMeter } from "./abr.js";
/** Bytes kept from the start of a body that ignores Range requests (as the native player). */
const PROBE = 64 << 10;
/** Default deadlines in seconds: one read of the file, and no byte received (as `msth play`). */
export const DEFAULT_DEADLINE = 120;
export const DEFAULT_STALL = 15;

/** The loader's deadlines from the page's URL parameters `deadline` and `stall` (seconds). */
export function loaderOptions(params) {
  const secs = (name, fallback) => {
    const v = Number(params.get(name));
    return params.has(name) && Number.isFinite(v) && v > 0 ? v : fallback;
  };
  return { deadline: secs("deadline", DEFAULT_DEADLINE), stall: secs("stall", DEFAULT_STALL) };
}

/** The error with the file's URL in front (HTTP errors already carry it). */
function named(url, e) {
  const msg = String(e && e.message ? e.message : e);
  return msg.startsWith(url) ? e : new Error(`${url}: ${msg}`);
}

const secsText = (ms) => String(Math.round(ms / 100) / 10);

class HttpSource {
  constructor(url, { deadline = DEFAULT_DEADLINE, stall = DEFAULT_STALL } = {}) {
    this.url = url;
    this.deadlineMs = deadline * 1000;
    this.stallMs = stall * 1000;
    this.validator = null;
    /** The file's length: declared by the server, `Infinity` while unknown, the header's after `limitTo`. */
    this.length = null;
    /** [length, how] as the server declared it. */
    this.declared = null;
    this.limited = false;
    /** A server that ignores Range requests: the first bytes of its body, and the body itself. */
    this.sequential = false;
    this.head = null;
    this.stream = null;
    this.requests = 0;
    this.bytes = 0;
  }

  fail(m) {
    throw new Error(`${this.url}: ${m}`);
  }

  /** `fetch`, with a network error put in words: the browser says only "Failed to fetch", so a
   * second request that does not follow redirects tells a redirect loop from the rest. */
  async #fetch(init) {
    try {
      return await fetch(this.url, init);
    } catch (e) {
      if (init.signal.aborted) throw e;
      let redirect = false;
      try {
        redirect = (await fetch(this.url, { ...init, redirect: "manual" })).type === "opaqueredirect";
      } catch {
        // unreachable either way
      }
      this.fail(redirect ? "too many redirects, or a redirect the page cannot follow" : `network error (${e.message}): the server closed the connection or cannot be reached`);
    }
  }

  /** The next chunk of a body; a connection the server closed early is `ended()`'s message
   * (the browser says only "network error"). An abort (a deadline) passes through. */
  async #next(reader, ended) {
    try {
      return await reader.read();
    } catch (e) {
      if (e && e.name === "AbortError") throw e;
      this.fail(`${ended()} (${e && e.message ? e.message : e})`);
    }
  }

  /** Timers of one read of bytes `start..end`: the deadline and the stall deadline abort `ctl`. */
  #timers(start, end, ctl) {
    const t = { why: null, got: 0 };
    const stop = (why) => {
      if (!t.why) {
        t.why = why;
        ctl.abort();
      }
    };
    const deadline = setTimeout(() => stop(`not complete within the ${secsText(this.deadlineMs)} s deadline`), this.deadlineMs);
    let stall = null;
    t.touch = (n = 0) => {
      t.got += n;
      clearTimeout(stall);
      stall = setTimeout(() => stop(`stalled: nothing received for ${secsText(this.stallMs)} s`), this.stallMs);
    };
    t.done = () => {
      clearTimeout(deadline);
      clearTimeout(stall);
    };
    /** The error to report for `e`: the timer's reason when one fired. */
    t.error = (e) => {
      if (!t.why) return e;
      return new Error(`${this.url}: bytes ${start}-${end - 1}: ${t.why} (${t.got} of ${end - start} bytes received)`);
    };
    t.touch();
    return t;
  }

  /** The server's length disagrees with the header's: an error naming both. */
  limitTo(n) {
    if (this.declared && this.declared[0] !== n) this.fail(`the server says the file is ${this.declared[0]} bytes (${this.declared[1]}), its header says ${n}`);
    this.length = n;
    this.limited = true;
  }

  /** Bytes `start..end` (end exclusive); `onBytes(n)` reports progress as they arrive. */
  async read(start, end, onBytes = () => {}) {
    if (this.sequential) return this.#streamRead(start, end, onBytes);
    const headers = { Range: `bytes=${start}-${end - 1}` };
    if (this.validator) headers["If-Range"] = this.validator;
    this.requests++;
    const ctl = new AbortController();
    const t = this.#timers(start, end, ctl);
    try {
      const resp = await this.#fetch({ headers, cache: "no-store", signal: ctl.signal });
      if (resp.status === 200 && this.length === null) return await this.#startStream(resp, ctl, t, start, end, onBytes);
      if (resp.status === 200) this.fail("the file changed on the server (200 to an If-Range request)");
      if (resp.status !== 206) this.fail(`HTTP ${resp.status} ${resp.statusText}`);
      const cr = resp.headers.get("content-range") || "";
      const m = /^bytes (\d+)-(\d+)\/(\d+|\*)$/.exec(cr.trim());
      if (!m) this.fail(`malformed Content-Range \`${cr}\``);
      const [a, b] = [Number(m[1]), Number(m[2])];
      if (this.length === null) {
        if (m[3] === "*") this.fail("the server does not tell the file length");
        this.length = Number(m[3]);
        this.declared = [this.length, `Content-Range \`${cr}\``];
        const etag = resp.headers.get("etag");
        this.validator = etag && !etag.startsWith("W/") ? etag : resp.headers.get("last-modified");
      } else if (m[3] !== "*" && Number(m[3]) !== this.length) {
        this.fail(`the server says the file is ${m[3]} bytes (Content-Range \`${cr}\`), ${this.limited ? "its header" : "the first response"} says ${this.length}`);
      }
      if (a !== start || b !== Math.min(end, this.length) - 1) this.fail(`asked for bytes ${start}-${end - 1}, got Content-Range \`${cr}\``);
      const body = await this.#readBody(resp, b + 1 - a, t, onBytes);
      this.bytes += body.length;
      return body;
    } catch (e) {
      ctl.abort();
      throw t.error(e);
    } finally {
      t.done();
    }
  }

  /** Exactly `expected` bytes of a body that must end there (no more is read). */
  async #readBody(resp, expected, t, onBytes) {
    const reader = resp.body.getReader();
    // Kept as it comes, not allocated up front: a length the server never sends costs nothing.
    const parts = [];
    let n = 0;
    for (;;) {
      const { done, value } = await this.#next(reader, () => `body ended after ${n} of ${expected} bytes`);
      if (done) break;
      if (n + value.length > expected) this.fail(`body longer than the ${expected} bytes asked for`);
      parts.push(value);
      n += value.length;
      t.touch(value.length);
      onBytes(value.length);
    }
    if (n !== expected) this.fail(`body ended after ${n} of ${expected} bytes`);
    if (parts.length === 1) return parts[0];
    const out = new Uint8Array(n);
    let o = 0;
    for (const p of parts) {
      out.set(p, o);
      o += p.length;
    }
    return out;
  }

  /** The first response is a 200: the server ignores Range. Keep the first PROBE bytes and the
   * body, which later reads go on with in file order. */
  async #startStream(resp, ctl, t, start, end, onBytes) {
    this.sequential = true;
    const cl = resp.headers.get("content-length");
    const declared = cl === null ? null : Number(cl);
    const etag = resp.headers.get("etag");
    this.validator = etag && !etag.startsWith("W/") ? etag : resp.headers.get("last-modified");
    const s = { reader: resp.body.getReader(), ctl, pos: 0, pending: null, declared };
    const head = new Uint8Array(PROBE);
    let n = 0;
    let ended = false;
    while (n < PROBE) {
      const { done, value } = await s.reader.read();
      if (done) {
        ended = true;
        break;
      }
      const k = Math.min(value.length, PROBE - n);
      head.set(value.subarray(0, k), n);
      n += k;
      s.pos += k;
      if (k < value.length) s.pending = value.subarray(k);
      t.touch(k);
      onBytes(k);
    }
    this.bytes += n;
    this.head = head.subarray(0, n);
    if (ended) {
      if (declared !== null && declared !== n) this.fail(`body ended after ${n} of ${declared} bytes`);
      this.length = n;
      this.declared = [n, "the length of its body"];
    } else {
      this.length = declared ?? Infinity;
      this.declared = declared === null ? null : [declared, "Content-Length"];
      this.stream = s;
    }
    return this.head.subarray(start, Math.min(end, n));
  }

  /** Bytes `start..end` from the kept first bytes and the streaming body, which is only read
   * forward (a read behind it starts the download again). */
  async #streamRead(start, end, onBytes) {
    const out = new Uint8Array(end - start);
    let o = 0;
    if (start < this.head.length) {
      const part = this.head.subarray(start, Math.min(end, this.head.length));
      out.set(part);
      o = part.length;
    }
    let at = start + o;
    if (at === end) return out;
    // A body that has streamed past `at` is dropped and started again.
    if (this.stream && this.stream.pos > at) this.close();
    const ctl = this.stream ? this.stream.ctl : new AbortController();
    const t = this.#timers(start, end, ctl);
    try {
      if (!this.stream) await this.#restart(ctl);
      const s = this.stream;
      while (at < end) {
        if (!s.pending || s.pending.length === 0) {
          const { done, value } = await this.#next(s.reader, () => `bytes ${start}-${end - 1}: the body ended at byte ${s.pos}`);
          if (done) this.fail(`bytes ${start}-${end - 1}: the body ended at byte ${s.pos}`);
          s.pending = value;
          t.touch(value.length);
          this.bytes += value.length;
        }
        const k = Math.min((s.pos < at ? at : end) - s.pos, s.pending.length);
        if (s.pos >= at) {
          out.set(s.pending.subarray(0, k), o);
          o += k;
          at += k;
          onBytes(k);
        }
        s.pos += k;
        s.pending = s.pending.subarray(k);
      }
      return out;
    } catch (e) {
      ctl.abort();
      this.stream = null;
      throw t.error(e);
    } finally {
      t.done();
    }
  }

  /** The body again from the start; it must be the same file. */
  async #restart(ctl) {
    this.requests++;
    const resp = await this.#fetch({ cache: "no-store", signal: ctl.signal });
    if (resp.status !== 200) this.fail(`HTTP ${resp.status} ${resp.statusText} to a request for the whole file`);
    const etag = resp.headers.get("etag");
    const validator = etag && !etag.startsWith("W/") ? etag : resp.headers.get("last-modified");
    const cl = resp.headers.get("content-length");
    const declared = this.declared && this.declared[1] === "Content-Length" ? this.declared[0] : null;
    if (validator !== this.validator || (cl === null ? null : Number(cl)) !== declared) this.fail("the file changed on the server while it was being streamed; load the page again");
    this.stream = { reader: resp.body.getReader(), ctl, pos: 0, pending: null };
  }

  /** Stops a body still streaming. */
  close() {
    if (this.stream) this.stream.ctl.abort();
    this.stream = null;
  }
}

/**
 * A `.msth` file being streamed. `open` reads the prefix; `start` runs the fetch loop in the
 * background. Listeners registered with `onChange` hear about every decoded section and every
 * received byte.
 */
export class ModelStream {
  /** Opens `url`; `options`: `{ deadline, stall }` in seconds (`loaderOptions`). */
  static async open(url, options = {}) {
    try {
      return await ModelStream.#open(url, options);
    } catch (e) {
      throw named(url, e);
    }
  }

  static async #open(url, options) {
    const src = new HttpSource(url, options);
    const s = new ModelStream(src);
    const first = await src.read(0, FIXED_HEADER, (n) => s.#received(n));
    const hs = prefixLength(first);
    if (hs > src.length) throw new FormatError("header and index", `the file is ${src.length} bytes, its prefix ${hs}`, true);
    const began = performance.now();
    const prefix = await src.read(0, hs, (n) => s.#received(n));
    s.meter.add(hs, (performance.now() - began) / 1000);
    s.decoder = new Decoder(prefix);
    if (s.decoder.fileLength > src.length) throw new FormatError("file", `the index points past its end (${s.decoder.fileLength} > ${src.length} bytes)`, true);
    s.fileLength = s.decoder.fileLength;
    // Nothing past the header's length is read from here on.
    src.limitTo(s.fileLength);
    s.ranges.push([0, hs]);
    s.bytesReady = hs;
    return s;
  }

  constructor(source) {
    this.source = source;
    this.decoder = null;
    this.want = null;
    /** The playhead and the playback speed the layer policy plans with (abr.js). */
    this.playback = { time: 0, secondsPerUnit: 0 };
    this.meter = new RateMeter();
    /** Wakes a fetch loop that waits for the playhead or the speed to move. */
    this.wake = null;
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
    this.playback.time = t;
    if (c !== this.want) {
      this.want = c;
      this.wake?.();
    }
  }

  /** How fast playback runs: seconds per unit of normalised time, 0 when paused. */
  setSpeed(secondsPerUnit) {
    const s = Number.isFinite(secondsPerUnit) ? Math.max(secondsPerUnit, 0) : 0;
    if (s !== this.playback.secondsPerUnit) {
      this.playback.secondsPerUnit = s;
      this.wake?.();
    }
  }

  /** The progressive layers a frame at time `t` is drawn with now (0: not ready). */
  layersFor(t) {
    return this.decoder.layersReady(this.decoder.chunkForTime(t));
  }

  /** The measured throughput, bytes per second (null before the first request). */
  rate() {
    return this.meter.rate();
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
    this.source.close();
  }

  #nextRequest() {
    const d = this.decoder;
    const secs = d.sections;
    if (this.source.sequential) {
      // File order, one section at a time: the body of a server without ranges only goes forward.
      let next = -1;
      secs.forEach((s, i) => {
        if (!d.decoded[i] && (next < 0 || s.offset < secs[next].offset)) next = i;
      });
      return next < 0 ? null : [next, next + 1];
    }
    const req = nextRequest(d, d.decoded, this.playback, this.meter.rate());
    // The MLP section alone first: the kernels are compiled from it (renderer.js `create`
    // waits for it) while the other sections stream.
    if (req && secs[req[0]].kind === KIND.mlp) return [req[0], req[0] + 1];
    return req;
  }

  async #loop() {
    for (;;) {
      if (this.stopped) return;
      const req = this.#nextRequest();
      if (!req) {
        if (this.decoder.decoded.every(Boolean)) {
          // The whole file is in: a body still streaming (a server without ranges) is not read on.
          this.source.close();
          return;
        }
        // The policy holds back until the playhead or the speed moves.
        await new Promise((r) => {
          const t = setTimeout(r, 200);
          this.wake = () => {
            clearTimeout(t);
            r();
          };
        });
        this.wake = null;
        continue;
      }
      const entries = this.decoder.sections.slice(req[0], req[1]);
      const start = entries[0].offset;
      const end = Math.max(...entries.map((e) => e.offset + e.length));
      this.inflight = { start, end, got: 0 };
      const began = performance.now();
      const bytes = await this.source.read(start, end, (n) => this.#received(n));
      this.meter.add(end - start, (performance.now() - began) / 1000);
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
