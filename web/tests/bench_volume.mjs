// Benchmark: the page's play-time volume against its exact path, in headless Chromium on
// SwiftShader (or whatever WebGPU adapter the browser has). For a model served by `msth serve`:
// the bake (plan, points evaluated, time, memory), then along an orbit of `--views` viewpoints
// (every `--step` degrees of azimuth from `--view`, or without it from the file's camera 0's
// azimuth, elevation and distance about the rig's centre), each frame drawn at full size exactly and
// through the volume: the time of each and the volume frame's PSNR against the exact one (8-bit
// frames). The worst frame is written as PNGs (volume and exact) with `--worst DIR`. Prints JSON.
//
//   msth serve DIR --web web --addr 127.0.0.1:8765 &
//   node web/tests/bench_volume.mjs --base http://127.0.0.1:8765 --model demo.msth \
//     --size 256x256 [--view 30,20,4] --views 4 --step 30 [--budget MIB] [--outside auto|exact|bake] [--samples full] [--worst DIR]

import { mkdtempSync, rmSync, writeFileSync } from "node:fs";
import { tmpdir } from "node:os";
import { join } from "node:path";
import { chromium } from "playwright-core";

const a = { samples: "full", views: "4", step: "30", size: "256x256" };
for (let i = 2; i < process.argv.length; i += 2) a[process.argv[i].replace(/^--/, "")] = process.argv[i + 1];
if (!a.base || !a.model) {
  console.error("usage: node web/tests/bench_volume.mjs --base URL --model NAME [--size WxH] [--view AZ,EL,DIST] [--views N] [--step DEG] [--budget MIB] [--outside auto|exact|bake] [--samples S] [--worst DIR]");
  process.exit(2);
}
const FLAGS = ["--no-sandbox", "--disable-gpu-sandbox", "--enable-unsafe-webgpu", "--enable-features=Vulkan", "--use-vulkan=swiftshader", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--use-webgpu-adapter=swiftshader"];
const dir = mkdtempSync(join(tmpdir(), "msth-bench-volume-"));
const ctx = await chromium.launchPersistentContext(dir, { executablePath: process.env.MSTH_CHROMIUM || "/usr/bin/chromium", headless: true, args: FLAGS, viewport: { width: 1000, height: 760 } });
try {
  const page = await ctx.newPage();
  page.on("pageerror", (e) => console.error(`pageerror: ${e.message}`));
  const budget = (a.budget ? `&volume-budget=${a.budget}` : "") + (a.outside ? `&volume-outside=${a.outside}` : "");
  const t0 = Date.now();
  const start = a.view ? `view=${a.view}` : "camera=0";
  await page.goto(`${a.base}/?model=${encodeURIComponent(a.model)}&${start}&t=0.5&size=${a.size}&play=0&samples=${a.samples}&volume=wait${budget}`);
  await page.waitForFunction(() => window.msth && (window.msth.firstFrameMs !== null || window.msth.error), null, { timeout: 3_600_000, polling: 500 });
  const err = await page.evaluate(() => window.msth.error);
  if (err) throw new Error(err);
  const volume = await page.evaluate(() => ({ ...window.msth.volume, compileMs: window.msth.renderer.evalCompileMs, limit: window.msth.renderer.device.limits.maxStorageBufferBindingSize }));
  if (volume.state !== "ready") throw new Error(`the volume is ${volume.state}: ${volume.error}`);
  await page.evaluate(() => window.msth.hold());
  const [az0, el, dist] = a.view ? a.view.split(",").map(Number) : await page.evaluate(() => [window.msth.orbit.az, window.msth.orbit.el, window.msth.orbit.dist]);
  const [w, h] = a.size.split("x").map(Number);
  const frames = [];
  let worst = null;
  for (let k = 0; k < Number(a.views); k++) {
    await page.evaluate(([az, el, dist]) => window.msth.setView(az, el, dist), [az0 + k * Number(a.step), el, dist]);
    // The slices for this time first (a frame's first draw bakes them), then timed draws.
    await page.evaluate(() => window.msth.drawVolumeHeld(1));
    const tv = Date.now();
    const outside = await page.evaluate(() => window.msth.drawVolumeHeld(1));
    const volumeMs = Date.now() - tv;
    const vol = await page.evaluate(() => window.msth.readPixels());
    const te = Date.now();
    await page.evaluate(() => window.msth.drawHeld(1));
    const exactMs = Date.now() - te;
    const ex = await page.evaluate(() => window.msth.readPixels());
    let se = 0;
    for (let i = 0; i < w * h; i++) for (let c = 0; c < 3; c++) se += (vol[4 * i + c] - ex[4 * i + c]) ** 2;
    const psnr = se ? 10 * Math.log10((255 * 255 * 3 * w * h) / se) : 99;
    frames.push({ azimuth: az0 + k * Number(a.step), exact_ms: exactMs, volume_ms: volumeMs, psnr, outside });
    if (!worst || psnr < worst.psnr) worst = { k, psnr, vol, ex };
  }
  if (a.worst && worst) {
    const png = async (px, name) => {
      const b64 = await page.evaluate(
        ([px, w, h]) => {
          const c = document.createElement("canvas");
          c.width = w;
          c.height = h;
          c.getContext("2d").putImageData(new ImageData(new Uint8ClampedArray(px), w, h), 0, 0);
          return c.toDataURL("image/png").split(",")[1];
        },
        [px, w, h],
      );
      writeFileSync(join(a.worst, name), Buffer.from(b64, "base64"));
    };
    await png(worst.vol, "worst_volume.png");
    await png(worst.ex, "worst_exact.png");
  }
  const sum = (k) => frames.reduce((s, f) => s + f[k], 0);
  console.log(
    JSON.stringify(
      {
        model: a.model,
        size: a.size,
        samples: a.samples,
        volume,
        frames,
        exact_ms_mean: sum("exact_ms") / frames.length,
        volume_ms_mean: sum("volume_ms") / frames.length,
        speedup: sum("exact_ms") / sum("volume_ms"),
        psnr_min: Math.min(...frames.map((f) => f.psnr)),
        worst_view: worst?.k,
        seconds: (Date.now() - t0) / 1000,
      },
      null,
      1,
    ),
  );
} finally {
  await ctx.close();
  rmSync(dir, { recursive: true, force: true });
}
