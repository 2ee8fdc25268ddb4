// Starts what the page needs first from the GPU, before the page's other modules have loaded:
// the WebGPU adapter and device (on a software adapter the adapter alone takes about 0.4 s) and
// the kernels' WGSL. index.html loads this module on its own (`async`), so that it runs as soon
// as it arrives; `Renderer.adapter` (renderer.js) takes the requests over from
// `globalThis.msthEarlyGpu`, or makes them itself where this did not run.

/**
 * Requests the adapter and device and downloads the WGSL: `{adapter, device, error, shaders}`,
 * `error` saying why there is no WebGPU adapter, `shaders` a promise of the texts of
 * render.wgsl, tables_f16.wgsl and volume.wgsl. A device the adapter refuses rejects.
 */
export async function requestGpu() {
  const text = async (name) => {
    const resp = await fetch(`shaders/${name}`, { cache: "no-store" });
    if (!resp.ok) throw new Error(`shaders/${name}: HTTP ${resp.status}`);
    return resp.text();
  };
  const shaders = Promise.all([text("render.wgsl"), text("tables_f16.wgsl"), text("volume.wgsl")]);
  // Awaited by the taker; a failure here must not be reported as unhandled before then.
  shaders.catch(() => {});
  if (!("gpu" in navigator) || !navigator.gpu) return { error: "navigator.gpu is missing", shaders };
  let adapter = null;
  try {
    adapter = await navigator.gpu.requestAdapter();
  } catch (e) {
    return { error: `requestAdapter failed: ${e.message}`, shaders };
  }
  if (!adapter) return { error: "no WebGPU adapter is available", shaders };
  const al = adapter.limits;
  const device = await adapter.requestDevice({
    requiredLimits: { maxStorageBufferBindingSize: al.maxStorageBufferBindingSize, maxBufferSize: al.maxBufferSize },
  });
  return { adapter, device, shaders };
}

// In the page only (not where node imports renderer.js for its tests). A rejection is the
// taker's to report (`Renderer.adapter` awaits this promise), not an unhandled one.
if (typeof document !== "undefined" && !globalThis.msthEarlyGpu) {
  globalThis.msthEarlyGpu = requestGpu();
  globalThis.msthEarlyGpu.catch(() => {});
}
