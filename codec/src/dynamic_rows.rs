//! "Model only what a scene requires": which rows of the field's 4D table the dynamic regions
//! reach in a time span (format.md §6.4).
//!
//! A mask vertex is dynamic when `1 - sigmoid(logit) >= threshold`. The mask is interpolated
//! trilinearly inside each cell of the mask grid, so a point's `1 - m` can reach the threshold only
//! inside a cell with at least one dynamic corner: those cells are the dynamic voxels. For every
//! level of the 4D grid, the rows read by any point of a dynamic voxel at any time of the span are
//! the grid corners covering the voxel's box and the span (the same `floor(x * scale + 0.5)`
//! arithmetic as [`GridLayout`]), mapped to rows by [`GridLayout::corner_row`]. Boxes are widened
//! by [`EPS`] so that rounding can only add rows, never miss one.

use msth_core::activation::sigmoid;
use msth_core::field::EncodingLayout;
use msth_core::grid::{clamp_unit, GridLayout, LevelLayout};

/// Widening of boxes and spans in unit coordinates.
pub const EPS: f32 = 1e-5;
/// Largest spatial corner set deduplicated through a bitset (bits).
const SPATIAL_BITSET_LIMIT: u64 = 1 << 28;

/// Axis-aligned boxes in the unit cube, `[lo, hi]` per axis.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DynamicRegion {
    pub boxes: Vec<[[f32; 2]; 3]>,
    /// Dynamic voxels (mask cells) and all voxels; `None` without a mask (everything dynamic).
    pub voxels: Option<(u64, u64)>,
}

/// The dynamic voxels of an encoding, merged into runs along x.
pub fn dynamic_region(enc: &EncodingLayout, params: &[f32], threshold: f32) -> DynamicRegion {
    if enc.h4.is_none() {
        return DynamicRegion::default();
    }
    let Some((grid, range)) = &enc.mask else {
        // No mask: the 4D table is read everywhere.
        return DynamicRegion {
            boxes: vec![[[0.0, 1.0]; 3]],
            voxels: None,
        };
    };
    let logits = &params[range.clone()];
    let r = grid.res;
    let cells = r - 1;
    let dynamic_vertex: Vec<bool> = logits
        .iter()
        .map(|&l| 1.0 - sigmoid(l) >= threshold)
        .collect();
    let v = |x: usize, y: usize, z: usize| dynamic_vertex[x + r * (y + r * z)];
    let unit = |i: usize| i as f32 / cells as f32;
    let mut boxes = Vec::new();
    let mut count = 0u64;
    for z in 0..cells {
        for y in 0..cells {
            let mut run: Option<usize> = None;
            for x in 0..=cells {
                let dynamic = x < cells
                    && (v(x, y, z)
                        || v(x + 1, y, z)
                        || v(x, y + 1, z)
                        || v(x + 1, y + 1, z)
                        || v(x, y, z + 1)
                        || v(x + 1, y, z + 1)
                        || v(x, y + 1, z + 1)
                        || v(x + 1, y + 1, z + 1));
                match (dynamic, run) {
                    (true, None) => run = Some(x),
                    (false, Some(x0)) => {
                        boxes.push([
                            [unit(x0), unit(x)],
                            [unit(y), unit(y + 1)],
                            [unit(z), unit(z + 1)],
                        ]);
                        run = None;
                    }
                    _ => {}
                }
                if dynamic {
                    count += 1;
                }
            }
        }
    }
    DynamicRegion {
        boxes,
        voxels: Some((count, (cells as u64).pow(3))),
    }
}

/// Corner range `[first, last]` on one axis for unit coordinates `[lo, hi]`.
fn corner_range(level: &LevelLayout, axis: usize, lo: f32, hi: f32) -> (u32, u32) {
    let s = level.scale[axis];
    let a = (clamp_unit(lo - EPS) * s + 0.5).floor() as u32;
    let b = (clamp_unit(hi + EPS) * s + 0.5).floor() as u32 + 1;
    (a, b.min(level.res[axis]))
}

/// Sorted rows of level `l` read by any point of `region` at any time in `[t0, t1]`.
pub fn reached_rows(
    grid: &GridLayout,
    l: usize,
    region: &DynamicRegion,
    t0: f32,
    t1: f32,
) -> Vec<u32> {
    let level = &grid.levels[l];
    let rows = level.rows;
    let mut hit = vec![0u64; rows.div_ceil(64)];
    let mut count = 0usize;
    let (ta, tb) = corner_range(level, 3, t0, t1);
    let mut mark = |row: usize, hit: &mut [u64]| {
        let (w, b) = (row / 64, row % 64);
        if hit[w] >> b & 1 == 0 {
            hit[w] |= 1 << b;
            count += 1;
        }
        count == rows
    };
    let dims = [
        level.res[0] as u64 + 1,
        level.res[1] as u64 + 1,
        level.res[2] as u64 + 1,
    ];
    let spatial = dims[0] * dims[1] * dims[2];
    let ranges = |b: &[[f32; 2]; 3]| [0, 1, 2].map(|a| corner_range(level, a, b[a][0], b[a][1]));
    if spatial <= SPATIAL_BITSET_LIMIT {
        // Deduplicate spatial corners first: neighbouring voxels share most of their corners.
        let mut seen = vec![0u64; (spatial as usize).div_ceil(64)];
        for b in &region.boxes {
            let [rx, ry, rz] = ranges(b);
            for z in rz.0..=rz.1 {
                for y in ry.0..=ry.1 {
                    let base = (z as u64 * dims[1] + y as u64) * dims[0];
                    for x in rx.0..=rx.1 {
                        let i = (base + x as u64) as usize;
                        seen[i / 64] |= 1 << (i % 64);
                    }
                }
            }
        }
        'words: for (w, &word) in seen.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let i = (w * 64 + bits.trailing_zeros() as usize) as u64;
                bits &= bits - 1;
                let x = (i % dims[0]) as u32;
                let y = ((i / dims[0]) % dims[1]) as u32;
                let z = (i / (dims[0] * dims[1])) as u32;
                for t in ta..=tb {
                    if mark(grid.corner_row(level, &[x, y, z, t]), &mut hit) {
                        break 'words;
                    }
                }
            }
        }
    } else {
        'boxes: for b in &region.boxes {
            let [rx, ry, rz] = ranges(b);
            for z in rz.0..=rz.1 {
                for y in ry.0..=ry.1 {
                    for x in rx.0..=rx.1 {
                        for t in ta..=tb {
                            if mark(grid.corner_row(level, &[x, y, z, t]), &mut hit) {
                                break 'boxes;
                            }
                        }
                    }
                }
            }
        }
    }
    let mut out = Vec::with_capacity(count);
    for (w, &word) in hit.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            out.push((w * 64 + bits.trailing_zeros() as usize) as u32);
            bits &= bits - 1;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use msth_core::grid::GridConfig;

    /// Every row a point inside the region reads at a time inside the span is selected.
    #[test]
    fn selection_covers_every_row_a_point_reads() {
        for log2 in [6, 12] {
            let cfg = GridConfig {
                levels: 4,
                features_per_level: 2,
                log2_table_size: log2,
                base_resolution: vec![4.0, 4.0, 4.0, 3.0],
                finest_resolution: vec![40.0, 40.0, 40.0, 10.0],
            };
            let grid = GridLayout::new(&cfg);
            let region = DynamicRegion {
                boxes: vec![[[0.2, 0.35], [0.5, 0.6], [0.0, 0.1]], [[0.9, 1.0]; 3]],
                voxels: None,
            };
            let (t0, t1) = (0.3, 0.55);
            let sel: Vec<Vec<u32>> = (0..4)
                .map(|l| reached_rows(&grid, l, &region, t0, t1))
                .collect();
            let mut rng = msth_core::rng::Rng::stream(7, 1);
            for _ in 0..20_000 {
                let b = &region.boxes[rng.below(2) as usize];
                let mut x: Vec<f32> = (0..3)
                    .map(|a| b[a][0] + (b[a][1] - b[a][0]) * rng.range_f32(0.0, 1.0))
                    .collect();
                x.push(t0 + (t1 - t0) * rng.range_f32(0.0, 1.0));
                grid.visit_rows(&x, |l, row| {
                    assert!(
                        sel[l].binary_search(&(row as u32)).is_ok(),
                        "level {l} row {row} at {x:?} not selected"
                    );
                });
            }
            // The selection is much smaller than the table on fine dense levels.
            if log2 == 12 {
                assert!(sel[3].len() < grid.levels[3].rows);
            }
        }
    }
}
