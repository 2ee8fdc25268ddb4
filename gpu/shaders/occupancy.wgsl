// Occupancy lookup (docs/format.md §6.5, format version 2): the file's occupancy grid as bound
// by a renderer, `R^3` bits over the grids' unit cube, cell `i = x + R (y + R z)` is bit
// `i % 32` of word `i / 32`. A set bit: something may be there at some frame; a clear bit: the
// main field's density is below the export's threshold at every frame, so a sample there may be
// skipped (density 0, no colour). Same arithmetic as msth-codec's `OccupancyGrid::occupied_unit`
// and web/js/format.js `occupiedUnit`.
//
// Self-contained: a kernel that uses it declares the binding itself, e.g.
//   @group(0) @binding(N) var<storage, read> occupancy_words: array<u32>;
// and passes the resolution (0 when the file has no grid: then every cell counts as occupied,
// and a one-word dummy buffer is bound).

fn occupancy_cell(p: vec3<f32>, r: u32) -> u32 {
  let c = min(vec3<u32>(clamp(p, vec3<f32>(0.0), vec3<f32>(1.0)) * f32(r)), vec3<u32>(r - 1u));
  return c.x + r * (c.y + r * c.z);
}

// Whether `cell` (from `occupancy_cell`) is occupied, given its word `occupancy_words[cell >> 5]`
// (the caller indexes its own binding: a function cannot take a runtime-sized storage array).
fn occupancy_bit(word: u32, cell: u32) -> bool {
  return ((word >> (cell & 31u)) & 1u) == 1u;
}

// Typical use in a per-sample pass:
//   let cell = occupancy_cell(p_unit, res);
//   if (res != 0u && !occupancy_bit(occupancy_words[cell >> 5u], cell)) { sigma = 0.0; skip; }
