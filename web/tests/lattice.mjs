// The display pass's fill of a reduced frame (web/js/renderer.js, DISPLAY_WGSL), in JavaScript:
// what the browser test checks the canvas against, and what `bench_kernels.mjs --reduced 1`
// measures against the full-size frame.

/** Channel c of pixel (x, y) of the lattice of spacing s in `px` (RGBA8, w x h), filled in:
 * bilinear between its pixels, the last one's value past the last row or column. */
function filled(px, w, h, x, y, s, c) {
  const at = (x, y) => px[4 * (y * w + x) + c];
  if (s === 1) return at(x, y);
  const lx = Math.floor((w - 1) / s) * s;
  const ly = Math.floor((h - 1) / s) * s;
  const x0 = Math.min(Math.floor(x / s) * s, lx);
  const y0 = Math.min(Math.floor(y / s) * s, ly);
  const x1 = Math.min(x0 + s, lx);
  const y1 = Math.min(y0 + s, ly);
  const fx = x1 === x0 ? 0 : (x - x0) / s;
  const fy = y1 === y0 ? 0 : (y - y0) / s;
  const top = at(x0, y0) * (1 - fx) + at(x1, y0) * fx;
  const bottom = at(x0, y1) * (1 - fx) + at(x1, y1) * fx;
  return top * (1 - fy) + bottom * fy;
}

/**
 * A w x h frame of which only the pixels at multiples of s are rendered (`px`, RGBA8), filled
 * in as the display pass does and as it did before (`nearest`: each pixel the nearest rendered
 * one).
 */
export function fillLattice(px, w, h, s, nearest = false) {
  const out = new Array(4 * w * h).fill(255);
  const lx = Math.floor((w - 1) / s) * s;
  const ly = Math.floor((h - 1) / s) * s;
  const half = Math.floor(s / 2);
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      for (let c = 0; c < 3; c++) {
        out[4 * (y * w + x) + c] = nearest
          ? px[4 * (Math.min(Math.floor((y + half) / s) * s, ly) * w + Math.min(Math.floor((x + half) / s) * s, lx)) + c]
          : filled(px, w, h, x, y, s, c);
      }
    }
  }
  return out;
}

/**
 * What the display pass shows of `px` under its uniform `u` (`displayUniform`: w, h, s, coarse,
 * rows): the lattice of spacing s filled in where both lattice rows a pixel reads lie above
 * `rows`, the lattice of spacing `coarse` elsewhere (when `coarse` is not 0).
 */
export function fillShown(px, u) {
  const [w, h, s, coarse, rows] = u;
  const out = new Array(4 * w * h).fill(255);
  const ly = Math.floor((h - 1) / s) * s;
  for (let y = 0; y < h; y++) {
    const below = Math.min(Math.min(Math.floor(y / s) * s, ly) + s, ly);
    const st = coarse !== 0 && below >= rows ? coarse : s;
    for (let x = 0; x < w; x++) for (let c = 0; c < 3; c++) out[4 * (y * w + x) + c] = filled(px, w, h, x, y, st, c);
  }
  return out;
}
