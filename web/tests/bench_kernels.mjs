// The page's kernels in headless Chromium on SwiftShader: its first frame of a model at a size,
// view and time, in a fresh browser. Prints the time to the first full-size frame (navigation to
// frame) and its render time (compiled pipelines to frame) and the time to the first picture
// (pages since the progressive start draw their first frame at 1/8 of the size per side and
// refine it; older pages draw it at full size). For the record only: nothing passes or fails on
// timing.
//
//   node web/tests/bench_kernels.mjs --base http://127.0.0.1:8080 --model demo.msth \
//     [--size 256x256] [--timeout-s 1800] [--chromium /usr/bin/chromium]
//     [--profile 1]   (each pass its own submission, timed: `?profile=1`)
//     [--first-only 1]   (stop at the first picture, however small; no full-size frame)
//     [--query K=V&...]   (more URL parameters for the page, e.g. an experiment's switch)
//     [--playback N]   (then N time steps of the still camera, timed: incremental playback)
//     [--frames N]   (then N more full-size frames of the same view, back to back, timed: the
//                     steady state, once the page's later passes are compiled)
//     [--throttle-kbps N]   (the page's network limited to N kbit/s down, 20 ms latency:
//                            Chromium's network emulation; the milestones show what waits)
//     [--reduced 1]   (how far the frames drawn at 1/2, 1/4 and 1/8 per side, as the display
//                      pass fills them in, are from the full-size frame: PSNR, bilinear fill
//                      and the nearest-pixel fill of earlier pages; from the page's own frame)
//
// On SwiftShader (a fallback adapter) the page starts at `fast` samples per ray: `--query
// samples=full` times the model's own counts. The line printed names the samples used.
//
// Needs a running `msth serve --web web DIR` and `npm ci --prefix web`.

import { mkdtempSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { chromium } from "playwright-core";
import { fillLattice } from "./lattice.mjs";

const FLAGS = [...(process.env.MSTH_CHROMIUM_EXTRA ? process.env.MSTH_CHROMIUM_EXTRA.split(" ") : []), "--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-gpu-sandbox", "--enable-unsafe-webgpu", "--enable-features=Vulkan", "--use-vulkan=swiftshader", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--use-webgpu-adapter=swiftshader"];

const a = {};
const argv = process.argv.slice(2);
for (let i = 0; i < argv.length; i += 2) a[argv[i].replace(/^--/, "")] = argv[i + 1];
if (!a.base || !a.model) {
  console.error("usage: node web/tests/bench_kernels.mjs --base URL --model NAME [--size WxH] [--timeout-s S]");
  process.exit(2);
}
const size = a.size || "256x256";
const timeout = 1000 * Number(a["timeout-s"] || 1800);

async function firstFrame() {
  const dir = mkdtempSync(join(tmpdir(), "msth-bench-"));
  const ctx = await chromium.launchPersistentContext(dir, { executablePath: a.chromium || process.env.MSTH_CHROMIUM || "/usr/bin/chromium", headless: true, args: FLAGS });
  try {
    const page = await ctx.newPage();
    if (a["throttle-kbps"]) {
      const cdp = await ctx.newCDPSession(page);
      const bytesPerS = (1000 * Number(a["throttle-kbps"])) / 8;
      await cdp.send("Network.enable");
      await cdp.send("Network.emulateNetworkConditions", { offline: false, latency: 20, downloadThroughput: bytesPerS, uploadThroughput: bytesPerS });
    }
    const logs = [];
    page.on("console", (m) => logs.push(m.text()));
    const q = (a.profile === "1" ? "&profile=1" : "") + (a.query ? `&${a.query}` : "");
    await page.goto(`${a.base}/?model=${encodeURIComponent(a.model)}&size=${size}&play=0&t=0${q}`);
    // The frame timed: the first full-size one (pages before the progressive start draw their
    // first frame at full size and have no `firstFullFrameMs`), or with --first-only the first one.
    const firstOnly = a["first-only"] === "1";
    const r = await page.waitForFunction(
      (only) => {
        const m = window.msth;
        if (!m) return null;
        const ttff = only || m.firstFullFrameMs === undefined ? m.firstFrameMs : m.firstFullFrameMs;
        if (ttff === null && !m.error && !m.noWebGpu) return null;
        return { ttff, firstPicture: m.firstFrameMs, firstSize: m.firstFrameSize, pipeline: m.timings && m.timings.pipeline, timings: m.timings, passMs: m.renderer && m.renderer.passMs, passCounts: m.renderer && m.renderer.passCounts, error: m.error, samples: m.samples, samplesSpec: m.samplesSpec };
      },
      firstOnly,
      { timeout, polling: 250 },
    ).then((h) => h.jsonValue());
    if (r.error || r.ttff === null) throw new Error(`${r.error || "no WebGPU"}\n${logs.join("\n")}`);
    const px = await page.evaluate(() => window.msth.readPixels());
    // --playback N: then N frames of the still camera at t = 0.5, 0.5 + 0.4/N, ... (the first one
    // builds the page's static cache unless `--query incremental=0`), each timed from the time
    // change to the finished frame.
    const steps = Number(a.playback || 0);
    let playback = null;
    if (steps > 0) {
      playback = { ms: [], rays: [] };
      for (let i = 0; i < steps; i++) {
        const t = 0.5 + (0.4 * i) / steps;
        const f = await page.evaluate(async (t) => {
          const m = window.msth;
          const t0 = performance.now();
          m.setTime(t);
          await m.nextFrame();
          while (m.state.dirty || m.state.rendering || m.state.refine) await new Promise((r) => setTimeout(r, 5));
          return { ms: performance.now() - t0, rays: m.lastRays, incremental: m.lastIncremental, cache: m.cache };
        }, t);
        playback.ms.push(f.ms);
        playback.rays.push(f.rays);
        playback.cache = f.cache;
      }
    }
    // --frames N: N full frames back to back (`hooks.benchmark`), once the passes the page
    // compiles later (`pass_proposal3`, `pass_density3`; `compileLater`, where the page has it)
    // are compiled or refused.
    let frames = null;
    if (Number(a.frames || 0) > 0) {
      frames = await page.evaluate(async (n) => {
        await window.msth.renderer.compileLater?.();
        return window.msth.benchmark(n);
      }, Number(a.frames));
    }
    return { ...r, px: Array.from(px), playback, frames };
  } finally {
    await ctx.close();
    rmSync(dir, { recursive: true, force: true });
  }
}

const r = await firstFrame();
const render = r.pipeline ? r.ttff - r.pipeline : NaN;
const samples = r.samples ? ` (samples ${r.samplesSpec}: ${r.samples.join(" + ")} per ray)` : "";
console.log(`passes${samples}: ${size} first ${a["first-only"] === "1" ? "frame drawn" : "full-size frame"} ${(r.ttff / 1000).toFixed(1)} s after navigation, ${(render / 1000).toFixed(1)} s of it rendering; first picture (${r.firstSize ? r.firstSize.join("x") : size}) after ${(r.firstPicture / 1000).toFixed(1)} s`);
// Milestones (s since navigation): adapter, prefix, module, pipeline, params, firstFrame.
const ms = Object.entries(r.timings || {}).sort((x, y) => x[1] - y[1]);
console.log(`  milestones: ${ms.map(([n, v]) => `${n} ${(v / 1000).toFixed(2)} s`).join(", ")}`);
if (r.playback) {
  const [first, ...rest] = r.playback.ms;
  const mean = rest.length ? rest.reduce((x, y) => x + y, 0) / rest.length : NaN;
  const c = r.playback.cache;
  console.log(`  playback (--playback ${r.playback.ms.length}): first time step ${(first / 1000).toFixed(2)} s, then ${(mean / 1000).toFixed(3)} s per frame on average (${rest.map((v) => (v / 1000).toFixed(3)).join(", ")} s); rays per frame ${r.playback.rays.join(", ")}${c ? `; static cache: ${c.dynamic} of ${c.pixels} pixels dynamic, built in ${(c.ms / 1000).toFixed(2)} s` : "; no static cache"}`);
}
if (a.reduced === "1") {
  // The full-size frame against its own lattices filled in: what a reduced frame of this view
  // shows (each lattice pixel is the full frame's pixel there).
  const [w, h] = size.split("x").map(Number);
  const psnr = (x, y) => {
    let se = 0;
    for (let i = 0; i < w * h; i++) for (let c = 0; c < 3; c++) se += ((x[4 * i + c] - y[4 * i + c]) / 255) ** 2;
    return se === 0 ? Infinity : -10 * Math.log10(se / (3 * w * h));
  };
  const rows = [2, 4, 8].map((st) => `1/${st}: ${psnr(fillLattice(r.px, w, h, st), r.px).toFixed(2)} dB (nearest pixel ${psnr(fillLattice(r.px, w, h, st, true), r.px).toFixed(2)} dB)`);
  console.log(`  reduced frames against the full-size frame (--reduced 1): ${rows.join(", ")}`);
}
if (r.frames) console.log(`  --frames ${r.frames.frames}: ${((1000 * r.frames.seconds) / r.frames.frames).toFixed(0)} ms per full frame (${r.frames.width}x${r.frames.height}, back to back)`);
if (r.passMs && Object.keys(r.passMs).length) console.log(`  per pass (--profile 1): ${Object.entries(r.passMs).map(([n, v]) => `${n} ${(v / 1000).toFixed(2)} s`).join(", ")}`);
if (r.passCounts && Object.keys(r.passCounts).length) console.log(`  lists (--profile 1, every frame): ${Object.entries(r.passCounts).map(([n, v]) => `${n} ${v}`).join(", ")}`);
