// Browser test of the web player: headless Chromium driven by playwright-core against a real
// `msth serve`. Started by tests/tests/web_player.rs (which trains and exports the model, starts
// the server and renders the native references with `msth play`), or by hand:
//
//   node web/tests/browser.mjs --base http://127.0.0.1:8080 --model demo.msth \
//     --view 30,25,4 --size 64x48 --native0 t0.png --native1 t1.png [--screenshot page.png] \
//     [--screenshot-model NAME] [--screenshot-camera K] \
//     [--model2 NAME --native2 t0.png] [--model-wide NAME --wide-clamped N] \
//     [--bench-size 256x256] [--out results.json] \
//     [--chromium /usr/bin/chromium]
//
// `--native0` / `--native1` are `msth play FILE --path view:VIEW --size SIZE --frames 1
// --time T:T --samples fast` frames at t = 0 and t = 1 (the page starts at `fast` on a software
// adapter, as in headless Chromium here). Checks, each printed as PASS/FAIL with its figures:
//  1. the page loads the model from the server and the first frame appears (in the renderer's
//     output and on the canvas);
//  2. the first frame matches the native render of the same camera and time (PSNR >= 35 dB);
//     frames reduced to 1/2 and 1/4 per side are shown interpolated between their pixels, and a
//     frame in progress shows no pixel of the view before it;
//  3. dragging on the canvas orbits the camera (the pixels change), at full size where a
//     full-size frame fits half the moving budget and reduced where not; touch orbits (one finger),
//     pinches and pans (two); the wheel zooms and right-drag pans; back at the URL's view the
//     first frame comes back;
//  4. scrubbing the timeline to t = 1 changes the dynamic pixels (those that differ between the
//     native renders at t = 0 and 1) and not the static ones, and matches the native t = 1 frame;
//     the still camera's frames come from the static cache (only dynamic pixels re-rendered);
//  5. with `--model2`: a second model (the Rust test's balanced-preset file) matches its native
//     render (`--native2`, same view, t = 0; PSNR >= 35 dB); with `--native2-faster` (the same
//     render with `msth play --samples faster`), the samples menu's `faster` matches it;
//  6. with `--model-wide NAME --wide-clamped N`: a quantised file whose hash tables hold N
//     values beyond binary16's ±65504: the page holds them clamped and says so (N, as msth-gpu
//     counts), and with `?tables=f32` holds none clamped;
//  7. without WebGPU the page says so.
// Also reports time to first frame and frames per second at `--bench-size` (for the record:
// timing decides nothing). Exit status 1 when a check fails, 2 on a usage or setup error.

import { mkdtempSync, readFileSync, writeFileSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { chromium } from "playwright-core";
import { fillLattice, fillShown } from "./lattice.mjs";

const BASE_FLAGS = ["--no-sandbox", "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-gpu-sandbox"];
const WEBGPU_FLAGS = ["--enable-unsafe-webgpu", "--enable-features=Vulkan", "--use-vulkan=swiftshader", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--use-webgpu-adapter=swiftshader"];
const PSNR_MIN = 35;
/** The least PSNR of a frame through the play-time volume against the exact frame of the same
 * view (the issue's aim for frames along an orbit). */
const VOLUME_PSNR_MIN = 35;

function parseArgs(argv) {
  const a = {};
  for (let i = 0; i < argv.length; i++) {
    const k = argv[i];
    if (!k.startsWith("--")) usage(`unexpected argument ${k}`);
    a[k.slice(2)] = argv[++i];
  }
  for (const k of ["base", "model", "view", "size", "native0", "native1"]) if (!a[k]) usage(`--${k} is required`);
  a.chromium ||= process.env.MSTH_CHROMIUM || "/usr/bin/chromium";
  return a;
}

function usage(msg) {
  console.error(`browser.mjs: ${msg}\nusage: node web/tests/browser.mjs --base URL --model NAME --view AZ,EL,DIST --size WxH --native0 PNG --native1 PNG [--screenshot PNG] [--bench-size WxH] [--out JSON] [--chromium PATH]`);
  process.exit(2);
}

const results = { checks: [], figures: {} };
let failed = false;
function check(name, ok, detail) {
  results.checks.push({ name, ok, detail });
  console.log(`${ok ? "PASS" : "FAIL"} ${name}: ${detail}`);
  if (!ok) failed = true;
}

function psnr(a, b, n) {
  // a, b: RGBA8 arrays of n pixels; RGB only, as msth's metrics (0..1 scale).
  let se = 0;
  for (let i = 0; i < n; i++) for (let c = 0; c < 3; c++) se += ((a[4 * i + c] - b[4 * i + c]) / 255) ** 2;
  const mse = se / (3 * n);
  return mse === 0 ? Infinity : -10 * Math.log10(mse);
}

const maxDiff = (a, b, i) => Math.max(...[0, 1, 2].map((c) => Math.abs(a[4 * i + c] - b[4 * i + c])));
const meanDiff = (a, b, i) => [0, 1, 2].reduce((s, c) => s + Math.abs(a[4 * i + c] - b[4 * i + c]), 0) / 3;

async function launch(chromiumPath, webgpu) {
  const dir = mkdtempSync(join(tmpdir(), "msth-chromium-"));
  const ctx = await chromium.launchPersistentContext(dir, {
    executablePath: chromiumPath,
    headless: true,
    args: webgpu ? [...BASE_FLAGS, ...WEBGPU_FLAGS] : BASE_FLAGS,
    viewport: { width: 1000, height: 760 },
    hasTouch: true,
  });
  return { ctx, close: async () => { await ctx.close(); rmSync(dir, { recursive: true, force: true }); } };
}

/** Decodes a PNG into RGBA8 with the browser's own decoder (no extra npm package). */
async function decodePng(page, path) {
  const b64 = readFileSync(path).toString("base64");
  return page.evaluate(async (b64) => {
    const img = new Image();
    img.src = `data:image/png;base64,${b64}`;
    await img.decode();
    const c = document.createElement("canvas");
    c.width = img.naturalWidth;
    c.height = img.naturalHeight;
    const g = c.getContext("2d", { colorSpace: "srgb" });
    g.drawImage(img, 0, 0);
    return { w: c.width, h: c.height, px: Array.from(g.getImageData(0, 0, c.width, c.height).data) };
  }, b64);
}

async function waitFirstFrame(page, timeout = 300_000) {
  await page.waitForFunction(() => window.msth && (window.msth.firstFrameMs !== null || window.msth.error || window.msth.noWebGpu), null, { timeout, polling: 100 });
  const st = await page.evaluate(() => ({ ttff: window.msth.firstFrameMs, error: window.msth.error, noWebGpu: window.msth.noWebGpu }));
  if (st.error || st.noWebGpu) throw new Error(`the page failed before its first frame: ${st.error || "no WebGPU"}`);
  return st.ttff;
}

/** Waits until a frame has been rendered after this call with nothing left to render. */
async function settled(page) {
  await page.evaluate(() => window.msth.nextFrame());
  await page.waitForFunction(() => !window.msth.state.dirty && !window.msth.state.refine && !window.msth.state.rendering, null, { timeout: 120_000, polling: 50 });
}

const pixels = (page) => page.evaluate(() => window.msth.readPixels());

/** The canvas as shown on screen: the element's screenshot, sampled at the canvas's pixel
 * centres, as RGBA8 (the HUD and the loading bar, which overlap it, hidden meanwhile). */
async function shownPixels(page) {
  await page.evaluate(() => ["hud", "loading"].forEach((id) => (document.getElementById(id).style.visibility = "hidden")));
  const shot = await page.locator("#view").screenshot();
  await page.evaluate(() => ["hud", "loading"].forEach((id) => (document.getElementById(id).style.visibility = "")));
  return page.evaluate(async (b64) => {
    const img = new Image();
    img.src = `data:image/png;base64,${b64}`;
    await img.decode();
    const c = document.createElement("canvas");
    const cv = document.getElementById("view");
    c.width = cv.width;
    c.height = cv.height;
    const g = c.getContext("2d");
    g.imageSmoothingEnabled = false;
    g.drawImage(img, 0, 0, c.width, c.height);
    return Array.from(g.getImageData(0, 0, c.width, c.height).data);
  }, shot.toString("base64"));
}

async function main() {
  const a = parseArgs(process.argv.slice(2));
  const [w, h] = a.size.split("x").map(Number);
  const n = w * h;
  const pageUrl = `${a.base}/?model=${encodeURIComponent(a.model)}&view=${a.view}&t=0&size=${a.size}&exact=1`;

  // ---- with WebGPU (SwiftShader)
  const gpu = await launch(a.chromium, true);
  try {
    const page = await gpu.ctx.newPage();
    const logs = [];
    page.on("console", (m) => logs.push(m.text()));
    page.on("pageerror", (e) => logs.push(`pageerror: ${e.message}`));
    await page.goto(pageUrl);
    let ttff;
    try {
      ttff = await waitFirstFrame(page);
    } catch (e) {
      check("first frame", false, `${e.message}\npage log:\n${logs.join("\n")}`);
      throw e;
    }
    results.figures.time_to_first_frame_ms = Math.round(ttff);
    const exactOnly = await page.evaluate(() => window.msth.volume?.state);
    const net = await page.evaluate(() => window.msth.stream.progress());
    results.figures.first_load = net;
    // Progressive start: the first frame at 1/8 of the size per side, then refined step by step.
    const firstSize = await page.evaluate(() => window.msth.firstFrameSize);
    await settled(page);
    const full = await page.evaluate(() => ({ ms: window.msth.firstFullFrameMs, size: window.msth.lastSize, frames: window.msth.frames, rays: window.msth.renderer.rays }));
    results.figures.time_to_full_frame_ms = Math.round(full.ms);
    results.figures.rays_to_full_frame = full.rays;
    // Interlaced refinement: the frames up to full size render each pixel once (w x h rays in
    // all, where drawing 1/8, 1/4, 1/2 and full size anew would take 1 + 1/4 + 1/16 + 1/64 times that).
    check(
      "the first frame is drawn small, then refined to full size",
      firstSize && firstSize[0] === Math.ceil(w / 8) && firstSize[1] === Math.ceil(h / 8) && full.size[0] === w && full.size[1] === h && full.frames >= 4 && full.rays === n,
      `first frame ${firstSize ? firstSize.join("x") : "?"} after ${ttff.toFixed(0)} ms, full size ${full.size.join("x")} after ${full.ms.toFixed(0)} ms, ${full.frames} frames in all, ${full.rays} rays rendered for ${n} pixels`,
    );
    // The first picture comes from the generic kernels, compiled while the MLP section streams;
    // the kernels compiled for the model take over after it (`?kernels=wait`: before it).
    await page.waitForFunction(() => !window.msth.mlpNote.startsWith("generic kernels until"), null, { timeout: 120_000 });
    const kern = await page.evaluate(() => ({ t: window.msth.timings, note: window.msth.mlpNote, fallback: window.msth.fallbackAdapter }));
    results.figures.kernels_for_the_model_ms = Math.round(kern.t.specialised ?? -1);
    check(
      "the first picture comes from the generic kernels, then the kernels compiled for the model",
      kern.note === "kernels compiled for this model" && kern.t.pipelines <= kern.t.firstFrame && kern.t.specialised > kern.t.firstFrame && (!kern.fallback || kern.t.specialised <= kern.t.firstFullFrame),
      `first picture after ${kern.t.firstFrame?.toFixed(0)} ms, kernels for the model in use after ${kern.t.specialised?.toFixed(0)} ms${kern.fallback ? " (a software adapter: the refinement waited for them)" : ""}, full size after ${kern.t.firstFullFrame?.toFixed(0)} ms; "${kern.note}"`,
    );
    const nat0 = await decodePng(page, a.native0);
    const nat1 = await decodePng(page, a.native1);
    if (nat0.w !== w || nat0.h !== h || nat1.w !== w || nat1.h !== h) throw new Error(`native frames are ${nat0.w}x${nat0.h}, expected ${a.size}`);
    const px0 = await pixels(page);
    const nonBackground = px0.length === 4 * n;
    // The canvas shows the frame.
    const shown = await shownPixels(page);
    const pShown = psnr(shown, px0, n);
    check("first frame appears", nonBackground && pShown >= 30, `after ${ttff.toFixed(0)} ms (navigation to frame; full size after ${full.ms.toFixed(0)} ms), ${net.requests} Range requests, ${net.bytesReceived} bytes; the canvas on screen matches the renderer's output at ${pShown.toFixed(1)} dB`);
    // The samples per ray the page starts at: `fast` on a software adapter (SwiftShader here;
    // the native references are rendered with `--samples fast`), the file's (`file`: its
    // play_samples, else the model's own) on a hardware one.
    const st = await page.evaluate(() => ({ fallback: window.msth.fallbackAdapter, spec: window.msth.samplesSpec, samples: window.msth.samples, model: window.msth.modelSamples, menu: document.getElementById("samples").value, policy: document.getElementById("policy").textContent }));
    const want = [Math.ceil((2 * st.model[0]) / 3), Math.ceil((3 * st.model[1]) / 4)];
    check(
      "the page starts at the samples its GPU calls for",
      st.spec === (st.fallback ? "fast" : "file") && st.menu === st.spec && (!st.fallback || (st.samples.join() === want.join() && st.policy.includes("software one, so the page started at fast"))),
      `${st.fallback ? "software" : "hardware"} adapter: ${st.spec}, ${st.samples.join(" + ")} samples per ray of the model's ${st.model.join(" + ")}`,
    );
    check("?exact=1 bakes no volume", exactOnly === "off", `volume state "${exactOnly}"`);
    const p0 = psnr(px0, nat0.px, n);
    results.figures.psnr_vs_native_t0 = Math.min(p0, 99);
    check("first frame matches the native render", p0 >= PSNR_MIN, `PSNR ${p0.toFixed(2)} dB against msth play at view:${a.view} t=0 (>= ${PSNR_MIN})`);

    // ---- a reduced frame (what the page draws while the camera moves) on screen: interpolated
    // between its rendered pixels, not blocks of the nearest one.
    await page.evaluate(() => window.msth.hold());
    for (const s of [2, 4]) {
      await page.evaluate((s) => window.msth.drawHeld(s), s);
      const onScreen = await shownPixels(page);
      const lattice = await pixels(page);
      const bilinear = fillLattice(lattice, w, h, s);
      const nearest = fillLattice(lattice, w, h, s, true);
      const [pb, pn, apart] = [psnr(onScreen, bilinear, n), psnr(onScreen, nearest, n), psnr(bilinear, nearest, n)];
      check(
        `a frame at 1/${s} is shown interpolated between its pixels`,
        pb >= 30 && pb >= apart + 6,
        `the canvas against the bilinear fill of the ${Math.ceil(w / s)}x${Math.ceil(h / s)} rendered pixels ${pb.toFixed(1)} dB, against the nearest-pixel fill ${pn.toFixed(1)} dB (the two fills ${apart.toFixed(1)} dB apart)`,
      );
    }
    // ---- a frame in progress (a slow GPU draws a frame batch by batch): a new view, its 1/4
    // lattice drawn, then the first batch of its 1/2 lattice. The frame buffer's other 1/2
    // lattice pixels still hold the previous view; the canvas must show none of them.
    {
      const [az, el, dist] = a.view.split(",").map(Number);
      await page.evaluate(([az, el, dist]) => window.msth.setView(az, el, dist), [az + 25, el, dist]);
      await page.evaluate(() => window.msth.drawHeld(4));
      const u = await page.evaluate(() => window.msth.drawHeld(2, 4, 64));
      const onScreen = await shownPixels(page);
      const buffer = await pixels(page);
      await page.evaluate(() => window.msth.drawHeld(1));
      const fresh = await pixels(page);
      await page.evaluate(([az, el, dist]) => window.msth.setView(az, el, dist), [az, el, dist]);
      await page.evaluate(() => window.msth.release());
      // What the canvas must show, from the new view's pixels alone; and what filling the whole
      // 1/2 lattice would show (the previous view's pixels where the batch did not reach).
      const want = fillShown(fresh, u);
      const [pb, stale] = [psnr(onScreen, want, n), psnr(fillLattice(buffer, w, h, 2), want, n)];
      check(
        "a frame in progress shows the new view only",
        u[2] === 2 && u[3] === 4 && u[4] > 0 && u[4] < h && pb >= 30 && pb >= stale + 6,
        `1/2 lattice drawn above row ${u[4]} of ${h}, the 1/4 lattice below (display uniform s ${u[2]}, coarse ${u[3]}): the canvas ${pb.toFixed(1)} dB from that fill of the new view's pixels; filling the whole 1/2 lattice from the frame buffer would be ${stale.toFixed(1)} dB from it`,
      );
    }
    await settled(page);

    // ---- drag to orbit
    const box = await page.locator("#view").boundingBox();
    const cx = box.x + box.width / 2;
    const cy = box.y + box.height / 2;
    const az0 = await page.evaluate(() => window.msth.orbit.az);
    await page.mouse.move(cx, cy);
    await page.mouse.down();
    for (let k = 1; k <= 8; k++) await page.mouse.move(cx + k * 12, cy + k * 2);
    await page.mouse.up();
    await settled(page);
    const pxDrag = await pixels(page);
    const az1 = await page.evaluate(() => window.msth.orbit.az);
    let changed = 0;
    for (let i = 0; i < n; i++) if (maxDiff(pxDrag, px0, i) > 8) changed++;
    check("dragging orbits the camera", az1 !== az0 && changed >= 0.02 * n, `azimuth ${az0.toFixed(1)} -> ${az1.toFixed(1)} degrees, ${((100 * changed) / n).toFixed(1)}% of pixels changed by more than 8/255`);

    // ---- touch (pointer events from a touch screen): one finger orbits, two pinch and pan
    const cdp = await gpu.ctx.newCDPSession(page);
    const touch = (type, pts) => cdp.send("Input.dispatchTouchEvent", { type, touchPoints: pts.map(([x, y], id) => ({ x, y, id })) });
    const o0 = await page.evaluate(() => ({ az: window.msth.orbit.az, dist: window.msth.orbit.dist }));
    await touch("touchStart", [[cx, cy]]);
    for (let k = 1; k <= 6; k++) await touch("touchMove", [[cx - k * 10, cy]]);
    await touch("touchEnd", []);
    await settled(page);
    const pxTouch = await pixels(page);
    const o1 = await page.evaluate(() => ({ az: window.msth.orbit.az, dist: window.msth.orbit.dist, pan: window.msth.orbit.pan }));
    await touch("touchStart", [[cx - 20, cy], [cx + 20, cy]]);
    for (let k = 1; k <= 6; k++) await touch("touchMove", [[cx - 20 - k * 10, cy + k * 3], [cx + 20 + k * 10, cy + k * 3]]);
    await touch("touchEnd", []);
    await settled(page);
    const pxPinch = await pixels(page);
    const o2 = await page.evaluate(() => ({ az: window.msth.orbit.az, dist: window.msth.orbit.dist, pan: window.msth.orbit.pan }));
    const frac = (x, y) => {
      let c = 0;
      for (let i = 0; i < n; i++) if (maxDiff(x, y, i) > 8) c++;
      return c / n;
    };
    check(
      "touch orbits, pinches and pans",
      o1.az !== o0.az && o2.dist < o1.dist && o2.pan.some((v) => v !== 0) && frac(pxTouch, pxDrag) >= 0.02 && frac(pxPinch, pxTouch) >= 0.02,
      `one finger: azimuth ${o0.az.toFixed(1)} -> ${o1.az.toFixed(1)}; two fingers apart: distance ${o1.dist.toFixed(3)} -> ${o2.dist.toFixed(3)}, target moved by (${o2.pan.map((v) => v.toFixed(3)).join(", ")}); ${(100 * frac(pxTouch, pxDrag)).toFixed(1)}% and ${(100 * frac(pxPinch, pxTouch)).toFixed(1)}% of pixels changed`,
    );
    // Mouse wheel: zoom out; right-drag: pan.
    await page.mouse.move(cx, cy);
    await page.mouse.wheel(0, 400);
    await settled(page);
    await page.mouse.down({ button: "right" });
    await page.mouse.move(cx + 40, cy + 20, { steps: 4 });
    await page.mouse.up({ button: "right" });
    await settled(page);
    const o3 = await page.evaluate(() => ({ dist: window.msth.orbit.dist, pan: window.msth.orbit.pan }));
    check("the wheel zooms and right-drag pans", o3.dist > o2.dist && o3.pan.some((v, k) => Math.abs(v - o2.pan[k]) > 1e-6), `distance ${o2.dist.toFixed(3)} -> ${o3.dist.toFixed(3)}, target (${o2.pan.map((v) => v.toFixed(3)).join(", ")}) -> (${o3.pan.map((v) => v.toFixed(3)).join(", ")})`);

    // ---- the resolution while the camera moves: full size where the GPU's measured rate draws
    // a full-size frame in half the moving budget, else reduced. The budget is set (huge, tiny)
    // so that what is checked is the rule, not this machine's speed.
    const dragScales = async (budget) => {
      await page.evaluate((b) => window.msth.setMovingBudget(b), budget);
      await settled(page);
      const scales = [];
      await page.mouse.move(cx, cy);
      await page.mouse.down();
      for (let k = 1; k <= 8; k++) {
        await page.mouse.move(cx + k * 4, cy);
        // The next frame starts right after this input: a moving frame.
        await page.evaluate(() => window.msth.nextFrame());
        scales.push(await page.evaluate(() => window.msth.lastScale));
      }
      await page.mouse.up();
      return scales;
    };
    const roomy = await dragScales(10_000);
    const tight = await dragScales(0.001);
    await page.evaluate(() => window.msth.setMovingBudget());
    check(
      "moving frames are full size where they fit, reduced where not",
      roomy[roomy.length - 1] === 1 && tight.every((v) => v < 1),
      `scales of the frames drawn while dragging: with a 10 s budget ${roomy.join(", ")}; with 0.001 ms ${tight.join(", ")}`,
    );

    // Back to the view: the same frame again.
    const [vaz, vel, vdist] = a.view.split(",").map(Number);
    await page.evaluate(([x, y, z]) => window.msth.setView(x, y, z), [vaz, vel, vdist]);
    await settled(page);
    const pxBack = await pixels(page);
    const pBack = psnr(pxBack, px0, n);
    check("returning to the view reproduces the first frame", pBack >= 50, `PSNR ${pBack === Infinity ? "inf" : pBack.toFixed(1)} dB`);

    // ---- scrub the timeline: drag its thumb, then End (t = 1) with the keyboard
    const slider = page.locator("#scrub");
    const sb = await slider.boundingBox();
    await page.mouse.move(sb.x + 4, sb.y + sb.height / 2);
    await page.mouse.down();
    await page.mouse.move(sb.x + sb.width * 0.5, sb.y + sb.height / 2, { steps: 5 });
    await page.mouse.up();
    await settled(page);
    const tMid = await page.evaluate(() => window.msth.state.t);
    await slider.focus();
    await page.keyboard.press("End");
    await settled(page);
    const st1 = await page.evaluate(() => ({ t: window.msth.state.t, playing: window.msth.state.playing, last: window.msth.lastTime }));
    const px1 = await pixels(page);
    check("the timeline scrubs", tMid > 0.2 && tMid < 0.8 && st1.t === 1 && st1.last === 1 && !st1.playing, `dragging the slider to its middle gave t = ${tMid.toFixed(3)}; End gave t = ${st1.t}`);
    // The scrub moved the time under a still camera: the page built its static cache (the
    // probes) and drew t = 1 re-rendering only the dynamic pixels.
    const inc = await page.evaluate(() => ({ last: window.msth.lastIncremental, rays: window.msth.lastRays, cache: window.msth.cache, builds: window.msth.cacheBuilds, res: document.getElementById("res").textContent }));
    results.figures.incremental = inc.cache ? { dynamic_pixels: inc.cache.dynamic, pixels: inc.cache.pixels, cache_ms: Math.round(inc.cache.ms), builds: inc.builds } : null;
    check(
      "a still camera plays incrementally: only the dynamic pixels are re-rendered",
      inc.last && inc.cache && inc.cache.dynamic > 0 && inc.cache.dynamic < n && inc.rays === inc.cache.dynamic && inc.builds === 1 && inc.res.includes(`incremental: ${inc.cache.dynamic} of ${n} pixels`),
      inc.cache ? `${inc.cache.dynamic} of ${n} pixels dynamic after ${inc.builds} cache build(s) (${inc.cache.ms.toFixed(0)} ms: the probes); the frame at t = 1 rendered ${inc.rays} rays; HUD "${inc.res}"` : `no static cache (${JSON.stringify(inc)})`,
    );
    const p1 = psnr(px1, nat1.px, n);
    results.figures.psnr_vs_native_t1 = Math.min(p1, 99);
    check("the frame at t = 1 matches the native render", p1 >= PSNR_MIN, `PSNR ${p1.toFixed(2)} dB (>= ${PSNR_MIN})`);
    // Static pixels: equal in the native renders at t = 0 and t = 1; dynamic: clearly different.
    const stat = [];
    const dyn = [];
    for (let i = 0; i < n; i++) {
      const d = maxDiff(nat0.px, nat1.px, i);
      if (d <= 1) stat.push(i);
      else if (d >= 24) dyn.push(i);
    }
    const mean = (idx, x, y) => idx.reduce((s, i) => s + meanDiff(x, y, i), 0) / Math.max(idx.length, 1);
    const pct = (idx, q) => {
      const v = idx.map((i) => maxDiff(px0, px1, i)).sort((x, y) => x - y);
      return v.length ? v[Math.min(v.length - 1, Math.floor(q * v.length))] : 0;
    };
    const enough = stat.length >= 0.01 * n && dyn.length >= 0.005 * n;
    const sMean = mean(stat, px0, px1);
    const s99 = pct(stat, 0.99);
    const dMean = mean(dyn, px0, px1);
    const dNative = mean(dyn, nat0.px, nat1.px);
    results.figures.scrub = { static_pixels: stat.length, dynamic_pixels: dyn.length, static_mean_change: sMean, static_p99_change: s99, dynamic_mean_change: dMean, dynamic_native_mean_change: dNative };
    check("scrubbing leaves static pixels alone", enough && sMean <= 1 && s99 <= 3, `${stat.length} static pixels (native t=0 vs t=1 within 1/255): mean change ${sMean.toFixed(3)}/255, 99th percentile ${s99}/255`);
    check("scrubbing changes dynamic pixels", enough && dMean >= 0.5 * dNative, `${dyn.length} dynamic pixels (native change >= 24/255): mean change ${dMean.toFixed(1)}/255 in the page, ${dNative.toFixed(1)}/255 natively`);

    // ---- the first model in progressive layers (format version 4): the page draws from the
    // first layers, refines as the others arrive, and with every layer shows what the file of
    // one layer shows (the two decode to the same parameters)
    if (a["model-layered"]) {
      await page.goto(`${a.base}/?model=${encodeURIComponent(a["model-layered"])}&view=${a.view}&t=0&size=${a.size}&exact=1`);
      await waitFirstFrame(page);
      await page.waitForFunction(() => window.msth.state.loadedLayers === window.msth.stream.decoder.layers.length && window.msth.stream.decoder.layers.length > 1, null, { timeout: 120_000 });
      await settled(page);
      const pxL = await pixels(page);
      const pL = pxL.length === 4 * n ? psnr(pxL, px0, n) : 0;
      const info = await page.evaluate(() => ({ layers: window.msth.stream.decoder.layers.length, text: document.getElementById("loading-text").textContent }));
      // JSON has no infinity: identical frames are reported as 99 dB.
      results.figures.psnr_layered_vs_one_layer = Math.min(pL, 99);
      check("a layered file plays and refines to the picture of the same model in one layer", pL >= 40 && /layers \d+\/\d+/.test(info.text), `${info.layers} layers; every layer drawn matches the one-layer file's frame at ${pL.toFixed(1)} dB; status "${info.text}"`);
    }

    // ---- a second model at the same view and time (the Rust test passes a balanced-preset
    // file: its layout, 16 levels, 2^17-row tables and 96 + 32 samples per ray, renders in the
    // page as natively)
    if (a.model2) {
      await page.goto(`${a.base}/?model=${encodeURIComponent(a.model2)}&view=${a.view}&t=0&size=${a.size}&exact=1&play=0&samples=full`);
      await waitFirstFrame(page);
      await settled(page);
      const nat2 = await decodePng(page, a.native2);
      const full2 = await page.evaluate(() => ({ ms: window.msth.firstFullFrameMs, size: window.msth.lastSize, split3: window.msth.lastSplit3 }));
      const px2 = await pixels(page);
      const p2 = px2.length === 4 * n && nat2.w === w && nat2.h === h ? psnr(px2, nat2.px, n) : 0;
      // Not a blank frame: the share of pixels more than 8/255 from the corner pixel's colour.
      let busy = 0;
      for (let i = 0; i < 4 * n; i += 4) if ([0, 1, 2].some((c) => Math.abs(nat2.px[i + c] - nat2.px[c]) > 8)) busy++;
      results.figures.model2_busy_pixels = busy / n;
      results.figures.psnr_model2_vs_native = Math.min(p2, 99);
      results.figures.model2_time_to_full_frame_ms = Math.round(full2.ms);
      check(`${a.model2} matches the native render`, p2 >= PSNR_MIN && busy >= 0.1 * n, `PSNR ${p2.toFixed(2)} dB against msth play at view:${a.view} t=0 (>= ${PSNR_MIN}); ${(100 * busy / n).toFixed(1)}% of the native frame's pixels differ from its corner's colour (>= 10%); full size (${full2.size.join("x")}) after ${full2.ms.toFixed(0)} ms`);

      // ---- the samples menu: `faster` renders the model with half its samples per ray, as
      // `msth play --samples faster` does (`--native2-faster`)
      if (a["native2-faster"]) {
        const before = await page.evaluate(() => window.msth.samples.slice());
        await page.selectOption("#samples", "faster");
        await settled(page);
        const after = await page.evaluate(() => ({ samples: window.msth.samples.slice(), res: document.getElementById("res").textContent }));
        const natF = await decodePng(page, a["native2-faster"]);
        const pxF = await pixels(page);
        const pF = pxF.length === 4 * n && natF.w === w && natF.h === h ? psnr(pxF, natF.px, n) : 0;
        const pFull = psnr(pxF, px2, n);
        results.figures.psnr_model2_faster_vs_native = Math.min(pF, 99);
        results.figures.psnr_model2_faster_vs_full = Math.min(pFull, 99);
        const halved = after.samples[0] === Math.ceil(before[0] / 2) && after.samples[1] === Math.ceil(before[1] / 2);
        check(
          "the samples menu renders with fewer samples, as msth play --samples does",
          halved && pF >= PSNR_MIN && pFull < pF && after.res.includes(`${after.samples[0]} + ${after.samples[1]} samples`),
          `${before.join(" + ")} -> ${after.samples.join(" + ")} samples per ray; PSNR ${pF.toFixed(2)} dB against msth play --samples faster (>= ${PSNR_MIN}), ${pFull.toFixed(2)} dB against the page's full-samples frame (lower: the menu changed the frame); HUD "${after.res}"`,
        );
      }

      // ---- the kernels compiled for the model (specialise.js: encodings and MLPs) render what the
      // generic ones do
      // The first picture comes from the generic kernels; those compiled for the model follow.
      await page.waitForFunction(() => !window.msth.mlpNote.startsWith("generic kernels until"), null, { timeout: 120000 });
      const note2 = await page.evaluate(() => window.msth.mlpNote);
      const tables2 = await page.evaluate(() => window.msth.tables);
      await page.goto(`${a.base}/?model=${encodeURIComponent(a.model2)}&view=${a.view}&t=0&size=${a.size}&exact=1&play=0&samples=full&mlp=generic`);
      await waitFirstFrame(page);
      await settled(page);
      const generic = await page.evaluate(() => ({ note: window.msth.mlpNote, info: document.getElementById("info").textContent }));
      const pxG = await pixels(page);
      const pG = pxG.length === 4 * n ? psnr(pxG, px2, n) : 0;
      const pGn = pxG.length === 4 * n && nat2.w === w && nat2.h === h ? psnr(pxG, nat2.px, n) : 0;
      results.figures.psnr_model2_generic_vs_specialised = Math.min(pG, 99);
      check(
        "the kernels compiled for the model render what the generic kernels do",
        note2 === "kernels compiled for this model" && /generic kernels/.test(generic.note) && generic.info.includes(generic.note) && pG >= 50 && pGn >= PSNR_MIN,
        `"${note2}" against "${generic.note}" (?mlp=generic): PSNR ${pG.toFixed(2)} dB between them (>= 50), generic ${pGn.toFixed(2)} dB against msth play`,
      );

      // ---- hash tables as binary16 (the default for a quantised file, as `msth play`) against f32
      // (`?tables=f32`): the same picture up to binary16's rounding, both near the native one
      await page.goto(`${a.base}/?model=${encodeURIComponent(a.model2)}&view=${a.view}&t=0&size=${a.size}&exact=1&play=0&samples=full&tables=f32`);
      await waitFirstFrame(page);
      await settled(page);
      const f32 = await page.evaluate(() => ({ tables: window.msth.tables, info: document.getElementById("info").textContent }));
      const pxT = await pixels(page);
      const pT = pxT.length === 4 * n ? psnr(pxT, px2, n) : 0;
      const pTn = pxT.length === 4 * n && nat2.w === w && nat2.h === h ? psnr(pxT, nat2.px, n) : 0;
      results.figures.psnr_model2_f32_tables_vs_f16 = Math.min(pT, 99);
      check(
        "binary16 hash tables render what f32 tables do",
        tables2 === "f16" && f32.tables === "f32" && f32.info.includes("hash tables f32") && pT >= 50 && pTn >= PSNR_MIN,
        `the quantised file's page held them as ${tables2}, ?tables=f32 as ${f32.tables}: PSNR ${pT.toFixed(2)} dB between them (>= 50), f32 ${pTn.toFixed(2)} dB against msth play`,
      );

      // ---- the passes without the 4D lookup (compiled after the others; `?split=wait` makes the
      // first frame wait for them) render what the first frame without them did
      await page.goto(`${a.base}/?model=${encodeURIComponent(a.model2)}&view=${a.view}&t=0&size=${a.size}&exact=1&play=0&samples=full&split=wait&profile=1`);
      await waitFirstFrame(page);
      await settled(page);
      const split3 = await page.evaluate(() => ({ used: window.msth.lastSplit3, ready: window.msth.timings.passes3, counts: window.msth.renderer.passCounts }));
      const lists = split3.counts ?? {};
      const pxS = await pixels(page);
      const pS = pxS.length === 4 * n ? psnr(pxS, px2, n) : 0;
      results.figures.psnr_model2_split_vs_first = Math.min(pS, 99);
      check(
        "the passes without a 4D lookup render what the others do",
        split3.used === true && pS >= 50 && lists.samples3 > 0 && lists.samples4 > 0 && lists.proposal3 > 0 && lists.proposal4 > 0,
        `?split=wait: the frame used them (${split3.used}, compiled ${split3.ready?.toFixed(0)} ms after navigation); live main samples ${lists.samples3} without and ${lists.samples4} with a 4D lookup, proposal samples ${lists.proposal3} and ${lists.proposal4} (every frame of the page; each > 0); PSNR ${pS.toFixed(2)} dB against the page's first frame of ${a.model2}, which used them: ${full2.split3} (>= 50)`,
      );

      // ---- a device that refuses the kernels compiled for the model: the page falls back to the
      // generic ones and says why (served here: a render.wgsl whose generic kernels call a renamed
      // `blend_of`, which the compiled encodings still call)
      await page.route("**/shaders/render.wgsl", async (route) => {
        const resp = await route.fetch();
        await route.fulfill({ response: resp, body: (await resp.text()).replaceAll("blend_of", "blend_of_generic") });
      });
      await page.goto(`${a.base}/?model=${encodeURIComponent(a.model2)}&view=${a.view}&t=0&size=${a.size}&exact=1&play=0&samples=full`);
      await waitFirstFrame(page);
      await page.waitForFunction(() => !window.msth.mlpNote.startsWith("generic kernels until"), null, { timeout: 120000 });
      await settled(page);
      const refused = await page.evaluate(() => window.msth.mlpNote);
      const pxR = await pixels(page);
      const pR = pxR.length === 4 * n ? psnr(pxR, px2, n) : 0;
      await page.unroute("**/shaders/render.wgsl");
      check(
        "kernels the device refuses fall back to the generic ones",
        refused.startsWith("generic kernels (compiling them for the model failed: ") && refused.includes("blend_of") && pR >= 50,
        `"${refused.slice(0, 160)}"; PSNR ${pR.toFixed(2)} dB against the compiled kernels' frame (>= 50)`,
      );
    }

    // ---- a file whose hash tables hold values beyond binary16's range: held clamped, and said
    if (a["model-wide"]) {
      const want = Number(a["wide-clamped"]);
      const held = {};
      for (const tables of ["f16", "f32"]) {
        await page.goto(`${a.base}/?model=${encodeURIComponent(a["model-wide"])}&view=${a.view}&t=0&size=${a.size}&exact=1&play=0&tables=${tables}`);
        await waitFirstFrame(page);
        held[tables] = await page.evaluate(() => ({ n: window.msth.clampedTables, tables: window.msth.tables, info: document.getElementById("info").textContent }));
      }
      const f16 = held.f16;
      check(
        "binary16 tables say how many values they hold clamped",
        f16.tables === "f16" && f16.n === want && f16.info.includes(`${want} values beyond binary16's ±65504 held clamped`) && held.f32.tables === "f32" && held.f32.n === 0 && !held.f32.info.includes("clamped"),
        `${a["model-wide"]}: ${f16.n} values clamped (msth-gpu counts ${want}), "${f16.info.split("; ").pop()}"; with ?tables=f32: ${held.f32.n}, "${held.f32.info.split("; ").pop()}"`,
      );
    }

    // ---- a still view reaches full size before the page starts the volume's bake (a budget of
    // 10 KiB: the plan refuses the file at once, so the check costs no bake)
    if (a["model-volume"]) {
      await page.goto(`${a.base}/?model=${encodeURIComponent(a["model-volume"])}&camera=0&t=0.37&play=0&samples=full&volume-budget=0.01`);
      await waitFirstFrame(page);
      await settled(page);
      await page.waitForFunction(() => window.msth.volume.state !== "waiting", null, { timeout: 120_000 });
      const order = await page.evaluate(() => ({ t: window.msth.timings, state: window.msth.volume.state, error: window.msth.volume.error }));
      check(
        "a still view reaches full size before the volume's bake starts",
        order.t.bake >= order.t.firstFullFrame && order.state === "failed" && /budget|MiB/.test(order.error ?? ""),
        `first picture ${order.t.firstFrame?.toFixed(0)} ms, full size ${order.t.firstFullFrame?.toFixed(0)} ms, bake started ${order.t.bake?.toFixed(0)} ms; volume ${order.state}: "${order.error}"`,
      );
    }

    // ---- the play-time volume (`--model-volume`, drawn natively by `msth play --cpu --volume`
    // into `--native-volume` at its camera 0 and t = 0.37, between two time slices): baked
    // before the first frame (`volume=wait`) within the native run's budget
    if (a["model-volume"]) {
      await page.goto(`${a.base}/?model=${encodeURIComponent(a["model-volume"])}&camera=0&t=0.37&play=0&samples=full&volume=wait&volume-budget=64`);
      await waitFirstFrame(page);
      await settled(page);
      const vol = await page.evaluate(() => window.msth.volume);
      results.figures.volume = vol;
      const native = await decodePng(page, a["native-volume"]);
      const m = native.w * native.h;
      await page.evaluate(() => window.msth.hold());
      await page.evaluate(() => window.msth.drawHeld(1));
      const exact = await pixels(page);
      const outside = await page.evaluate(() => window.msth.drawVolumeHeld(1));
      const through = await pixels(page);
      const shown = await shownPixels(page);
      await page.evaluate(() => window.msth.drawVolumeHeld(2));
      const half = await pixels(page);
      const halfShown = await shownPixels(page);
      await page.evaluate(() => window.msth.release());
      const sized = through.length === 4 * m;
      const [pNative, pExact, pShown] = [psnr(through, native.px, m), psnr(through, exact, m), psnr(shown, through, m)];
      const pHalf = psnr(halfShown, fillLattice(half, native.w, native.h, 2), m);
      results.figures.psnr_volume_vs_native_volume = Math.min(pNative, 99);
      results.figures.psnr_volume_vs_exact = Math.min(pExact, 99);
      check(
        "the page's volume draws what the native volume draws",
        vol.state === "ready" && sized && pNative >= PSNR_MIN && pShown >= 30 && pHalf >= 30,
        `${vol.resolution}^3 cells, ${(vol.bytes / 1048576).toFixed(2)} MiB, baked in ${vol.ms.toFixed(0)} ms (plan ${vol.planMs.toFixed(0)} ms, ${vol.evaluated} points evaluated, ${vol.slices} slices); its ${native.w}x${native.h} frame ${pNative.toFixed(2)} dB against msth play --cpu --volume (>= ${PSNR_MIN}), ${outside} rays drawn exactly; on the canvas ${pShown.toFixed(1)} dB; at 1/2 shown interpolated ${pHalf.toFixed(1)} dB`,
      );
      check(
        "the page's volume frame is close to its exact frame",
        pExact >= VOLUME_PSNR_MIN,
        `${pExact.toFixed(2)} dB against the exact path's frame of the same view (>= ${VOLUME_PSNR_MIN}; msth play measures 37.1-37.8 dB on this file's camera, tests/tests/play_volume.rs)`,
      );
      // A drag draws through the volume; the view it stops at is drawn again exactly.
      const box = await page.locator("#view").boundingBox();
      const [cx, cy] = [box.x + box.width / 2, box.y + box.height / 2];
      const before = await page.evaluate(() => window.msth.volumeFrames);
      await page.mouse.move(cx, cy);
      await page.mouse.down();
      for (let k = 1; k <= 8; k++) {
        await page.mouse.move(cx - k * 10, cy + k);
        await page.evaluate(() => window.msth.nextFrame());
      }
      await page.mouse.up();
      const during = (await page.evaluate(() => window.msth.volumeFrames)) - before;
      await settled(page);
      const after = await page.evaluate(() => ({ volume: window.msth.lastVolume, scale: window.msth.lastScale, res: document.getElementById("res").textContent }));
      check(
        "a moving camera is drawn through the volume, a still one exactly",
        during >= 1 && !after.volume && after.scale === 1,
        `${during} frames through the volume during the drag; after it the last frame ${after.volume ? "through the volume" : "exact"} at scale ${after.scale} ("${after.res}")`,
      );
      // `volume-outside` reaches the plan (web/tests/volume_plan.mjs checks the plans it makes
      // against msth-player's); a value it does not know is refused by name.
      for (const [value, ok] of [["exact", true], ["sideways", false]]) {
        await page.goto(`${a.base}/?model=${encodeURIComponent(a["model-volume"])}&camera=0&t=0.37&play=0&samples=full&volume=wait&volume-budget=64&volume-outside=${value}`);
        await page.waitForFunction(() => window.msth && window.msth.volume && ["ready", "failed"].includes(window.msth.volume.state), null, { timeout: 300_000 });
        const v = await page.evaluate(() => ({ state: window.msth.volume.state, error: window.msth.volume.error, note: window.msth.volume.note }));
        check(
          `?volume-outside=${value} ${ok ? "plans the volume" : "is refused by name"}`,
          ok ? v.state === "ready" : v.state === "failed" && /volume-outside=sideways/.test(v.error || ""),
          `state ${v.state}${v.error ? `: ${v.error}` : ""}${v.note ? `; note: ${v.note}` : ""}`,
        );
      }
    }

    // ---- for the record: frames per second at the bench size, and the README screenshot
    if (a["bench-size"]) {
      const url = `${a.base}/?model=${encodeURIComponent(a.model)}&size=${a["bench-size"]}&play=0&t=0.5&exact=1`;
      await page.goto(url);
      const t = await waitFirstFrame(page);
      await settled(page);
      const tFull = await page.evaluate(() => window.msth.firstFullFrameMs);
      const bench = await page.evaluate(() => window.msth.benchmark(10));
      results.figures.bench = { ...bench, time_to_first_frame_ms: Math.round(t), time_to_full_frame_ms: Math.round(tFull) };
      console.log(`bench: ${bench.width}x${bench.height}: ${bench.fps.toFixed(2)} frames per second (${bench.frames} frames in ${bench.seconds.toFixed(2)} s), time to first frame ${t.toFixed(0)} ms (1/8 size), to the first full-size frame ${tFull.toFixed(0)} ms`);
    }
    if (a.screenshot) {
      // Paused: while SwiftShader renders, the page cannot composite a screenshot. The default
      // view: the file's camera 0 (the first training camera of files exported since the
      // trainer lists them first), or `--screenshot-camera K`, at its own size.
      const cam = a["screenshot-camera"] ? `&camera=${Number(a["screenshot-camera"])}` : "";
      const url = `${a.base}/?model=${encodeURIComponent(a["screenshot-model"] || a.model)}&t=0.5&play=0${cam}`;
      await page.goto(url);
      await waitFirstFrame(page);
      await page.waitForFunction(() => window.msth.stream.progress().complete, null, { timeout: 300_000 });
      await settled(page);
      await page.screenshot({ path: a.screenshot });
      console.log(`screenshot: ${a.screenshot}`);
    }
  } finally {
    await gpu.close();
  }

  // ---- without WebGPU
  const plain = await launch(a.chromium, false);
  try {
    const page = await plain.ctx.newPage();
    await page.goto(pageUrl);
    await page.waitForFunction(() => window.msth && (window.msth.noWebGpu || window.msth.firstFrameMs !== null || window.msth.error), null, { timeout: 60_000 });
    const st = await page.evaluate(() => ({ no: window.msth.noWebGpu, visible: !document.getElementById("message").hidden, text: document.getElementById("message").textContent }));
    check("a clear message without WebGPU", st.no && st.visible && /WebGPU/.test(st.text), `"${st.text}"`);
  } finally {
    await plain.close();
  }

  if (a.out) writeFileSync(a.out, JSON.stringify(results, null, 2));
  console.log(failed ? "browser test FAILED" : "browser test passed");
  process.exit(failed ? 1 : 0);
}

main().catch((e) => {
  console.error(`browser test error: ${e.stack || e}`);
  if (a_out()) writeFileSync(a_out(), JSON.stringify({ ...results, error: String(e) }, null, 2));
  process.exit(1);
});

function a_out() {
  const i = process.argv.indexOf("--out");
  return i > 0 ? process.argv[i + 1] : null;
}
