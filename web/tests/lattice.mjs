// The display pass's fill of a reduced frame (web/js/renderer.js, DISPLAY_WGSL), in JavaScript:
// what the browser test checks the canvas against, and what `bench_kernels.mjs --reduced 1`
// measures against the full-size frame.

/**
 * A w x h frame of which only the pixels at multiples of s are rendered (`px`, RGBA8), filled
 * in as the display pass does (bilinear between those pixels, the last one's value past the
 * last row or column) and as it did before (`nearest`: each pixel the nearest rendered one).
 */
export function fillLattice(px, w, h, s, nearest = false) {
  const out = new Array(4 * w * h).fill(255);
  const lx = Math.floor((w - 1) / s) * s;
  const ly = Math.floor((h - 1) / s) * s;
  const at = (x, y, c) => px[4 * (y * w + x) + c];
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      for (let c = 0; c < 3; c++) {
        let v;
        if (nearest) {
          v = at(Math.min(Math.floor((x + Math.floor(s / 2)) / s) * s, lx), Math.min(Math.floor((y + Math.floor(s / 2)) / s) * s, ly), c);
        } else {
          const x0 = Math.min(Math.floor(x / s) * s, lx);
          const y0 = Math.min(Math.floor(y / s) * s, ly);
          const x1 = Math.min(x0 + s, lx);
          const y1 = Math.min(y0 + s, ly);
          const fx = x1 === x0 ? 0 : (x - x0) / s;
          const fy = y1 === y0 ? 0 : (y - y0) / s;
          const top = at(x0, y0, c) * (1 - fx) + at(x1, y0, c) * fx;
          const bottom = at(x0, y1, c) * (1 - fx) + at(x1, y1, c) * fx;
          v = top * (1 - fy) + bottom * fy;
        }
        out[4 * (y * w + x) + c] = v;
      }
    }
  }
  return out;
}
