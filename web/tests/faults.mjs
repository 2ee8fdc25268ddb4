// The web page against servers that misbehave: headless Chromium (playwright-core) loads the page
// from each server given, one fresh browser context per server, and waits until the page shows an
// error or has streamed the whole file. Started by cli/tests/faults.rs (which runs a loopback
// server per fault mode, each serving the page too), or by hand:
//
//   node web/tests/faults.mjs [--out results.json] [--chromium /usr/bin/chromium] \
//     MODE=URL [MODE=URL ...]
//
// URL is the page with its parameters, e.g. http://127.0.0.1:PORT/?model=scene.msth&deadline=6&stall=2.
// For each mode it prints and writes (as JSON, keyed by mode): `error` (the page's message, or
// null), `complete` (every section streamed and decoded), `ms` (from navigation to the error or
// to the whole file), `peakMiB` (the highest memory of the page's renderer processes of their own:
// private pages, not the libraries and shared memory they map with the rest of the browser;
// sampled every 50 ms), `rssMiB` (the same, resident, shared pages included), `heapMiB` (the
// highest JavaScript heap, from the DevTools protocol) and `browserMiB` (the highest resident
// memory of the whole browser, every process, shared pages counted in each). Exit status 2
// on a usage or setup error, else 0: the Rust test decides what each mode must end with.

import { readFileSync, readdirSync, writeFileSync } from "node:fs";
import { chromium } from "playwright-core";

const BASE_FLAGS = ["--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-gpu-sandbox"];
const WEBGPU_FLAGS = ["--enable-unsafe-webgpu", "--enable-features=Vulkan", "--use-vulkan=swiftshader", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--use-webgpu-adapter=swiftshader"];
/** Longest wait for one mode (the Rust test's deadlines are seconds). */
const MODE_TIMEOUT_MS = 120_000;

function usage(msg) {
  console.error(`faults.mjs: ${msg}\nusage: node web/tests/faults.mjs [--out JSON] [--chromium PATH] MODE=URL...`);
  process.exit(2);
}

const args = process.argv.slice(2);
const opts = { out: null, chromium: process.env.MSTH_CHROMIUM || "/usr/bin/chromium" };
const modes = [];
for (let i = 0; i < args.length; i++) {
  const a = args[i];
  if (a === "--out") opts.out = args[++i];
  else if (a === "--chromium") opts.chromium = args[++i];
  else if (a.includes("=") && !a.startsWith("--")) {
    const k = a.indexOf("=");
    modes.push([a.slice(0, k), a.slice(k + 1)]);
  } else usage(`unexpected argument ${a}`);
}
if (!modes.length) usage("no MODE=URL given");

/** Processes of the browser: pid -> { ppid, cmd }. */
function processes() {
  const out = new Map();
  for (const d of readdirSync("/proc")) {
    if (!/^\d+$/.test(d)) continue;
    try {
      const stat = readFileSync(`/proc/${d}/stat`, "utf8");
      const ppid = Number(stat.slice(stat.lastIndexOf(")") + 2).split(" ")[1]);
      const cmd = readFileSync(`/proc/${d}/cmdline`, "utf8");
      out.set(Number(d), { ppid, cmd });
    } catch {
      // gone meanwhile
    }
  }
  return out;
}

/** Resident memory of a process, MiB: all of it (RSS) and its own pages only (USS: private
 * clean and dirty, not the libraries and shared memory it maps with other processes). */
function residentMiB(pid) {
  try {
    const t = readFileSync(`/proc/${pid}/smaps_rollup`, "utf8");
    const kb = (name) => Number((new RegExp(`^${name}:\\s+(\\d+) kB`, "m").exec(t) || [0, 0])[1]);
    return { rss: kb("Rss") / 1024, uss: (kb("Private_Clean") + kb("Private_Dirty")) / 1024 };
  } catch {
    return { rss: 0, uss: 0 };
  }
}

/** Memory of the browser's renderer processes (USS and RSS) and of all its processes (RSS), MiB. */
function memory(root) {
  const all = processes();
  const tree = new Set([root]);
  let grew = true;
  while (grew) {
    grew = false;
    for (const [pid, p] of all) {
      if (!tree.has(pid) && tree.has(p.ppid)) {
        tree.add(pid);
        grew = true;
      }
    }
  }
  const m = { renderers: 0, renderersRss: 0, total: 0 };
  tree.delete(root);
  for (const pid of tree) {
    const r = residentMiB(pid);
    m.total += r.rss;
    if (all.get(pid)?.cmd.includes("--type=renderer")) {
      m.renderers += r.uss;
      m.renderersRss += r.rss;
    }
  }
  return m;
}

const browser = await chromium.launch({ executablePath: opts.chromium, headless: true, args: [...BASE_FLAGS, ...WEBGPU_FLAGS] });
// Chromium runs as this script's child: its processes are this process's descendants.
const root = process.pid;
const results = {};
for (const [mode, url] of modes) {
  const ctx = await browser.newContext({ viewport: { width: 640, height: 480 } });
  const page = await ctx.newPage();
  const cdp = await ctx.newCDPSession(page);
  await cdp.send("Performance.enable");
  const r = { error: null, complete: false, ms: null, peakMiB: 0, rssMiB: 0, heapMiB: 0, browserMiB: 0 };
  let sampling = true;
  const sampler = (async () => {
    while (sampling) {
      const m = memory(root);
      r.peakMiB = Math.max(r.peakMiB, m.renderers);
      r.rssMiB = Math.max(r.rssMiB, m.renderersRss);
      r.browserMiB = Math.max(r.browserMiB, m.total);
      try {
        const { metrics } = await cdp.send("Performance.getMetrics");
        const heap = metrics.find((x) => x.name === "JSHeapUsedSize");
        if (heap) r.heapMiB = Math.max(r.heapMiB, heap.value / 2 ** 20);
      } catch {
        // the page is navigating
      }
      await new Promise((res) => setTimeout(res, 50));
    }
  })();
  const t0 = Date.now();
  try {
    await page.goto(url, { waitUntil: "load", timeout: MODE_TIMEOUT_MS });
    await page.waitForFunction(
      () => window.msth && (window.msth.error || window.msth.noWebGpu || (window.msth.stream && window.msth.stream.progress().complete)),
      null,
      { timeout: MODE_TIMEOUT_MS, polling: 20 },
    );
    r.ms = Date.now() - t0;
    const st = await page.evaluate(() => ({ error: window.msth.error, noWebGpu: window.msth.noWebGpu, complete: !!(window.msth.stream && window.msth.stream.progress().complete) }));
    if (st.noWebGpu) {
      console.error("faults.mjs: this Chromium has no WebGPU adapter (the page loads models only with one)");
      process.exit(2);
    }
    r.error = st.error;
    r.complete = st.complete;
  } catch (e) {
    r.ms = Date.now() - t0;
    r.error = `faults.mjs: ${e.message.split("\n")[0]}`;
  }
  sampling = false;
  await sampler;
  await ctx.close();
  results[mode] = r;
  const what = r.error ? `error: ${r.error}` : r.complete ? "streamed the whole file" : "?";
  console.log(`${mode.padEnd(19)} ${(r.ms / 1000).toFixed(2).padStart(6)} s  renderer ${r.peakMiB.toFixed(1)} MiB own (${r.rssMiB.toFixed(1)} MiB resident), JS heap ${r.heapMiB.toFixed(1)} MiB, browser ${r.browserMiB.toFixed(1)} MiB  ${what}`);
}
await browser.close();
if (opts.out) writeFileSync(opts.out, JSON.stringify(results, null, 2));
