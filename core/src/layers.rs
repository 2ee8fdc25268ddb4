//! Progressive layers: the hash-grid levels of the main field and of the proposal field split,
//! coarse to fine, into the layers a layered `.msth` file stores (format.md §6.6) and nested
//! dropout trains the networks for. Layer `l` holds the levels `ends[l - 1]..ends[l]` (`0..ends[0]`
//! for layer 0) of each table; a player holding layers `0..k` renders with the finer levels'
//! features at 0.

/// The most layers a file may have.
pub const MAX_LAYERS: usize = 16;

/// How many of `levels` levels layers `0..=l` hold, for each layer `l` of `layers`: an even split
/// by level count, `ceil(levels * (l + 1) / layers)`. Coarse levels are small (dense or few
/// rows) and fine ones large, so the first layers are a small share of the bytes. `layers` is
/// clamped to `1..=levels.max(1)`; the last end is `levels`.
pub fn layer_level_ends(levels: usize, layers: usize) -> Vec<usize> {
    let layers = layers.clamp(1, levels.max(1));
    (0..layers).map(|l| level_end(levels, layers, l)).collect()
}

/// The layers a file of `requested` layers has: one per level of the main field at most
/// (`field_levels`, the larger of its two tables' level counts).
pub fn layer_count(field_levels: usize, requested: usize) -> usize {
    requested.clamp(1, field_levels.max(1))
}

/// How many of a table's `levels` levels layers `0..=l` of `layers` hold: `ceil(levels (l + 1)
/// / layers)`. For the proposal's tables, which have fewer levels than the main field's, two
/// layers may hold the same count (the later one adds none of them).
pub fn level_end(levels: usize, layers: usize, l: usize) -> usize {
    (levels * (l + 1)).div_ceil(layers.max(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ends_split_levels_evenly_and_end_at_the_level_count() {
        assert_eq!(layer_level_ends(16, 4), vec![4, 8, 12, 16]);
        assert_eq!(layer_level_ends(12, 5), vec![3, 5, 8, 10, 12]);
        assert_eq!(layer_level_ends(3, 8), vec![1, 2, 3]);
        assert_eq!(layer_level_ends(7, 1), vec![7]);
        assert_eq!(layer_level_ends(0, 3), vec![0]);
        for levels in 1..=20 {
            for layers in 1..=MAX_LAYERS {
                let e = layer_level_ends(levels, layers);
                assert_eq!(*e.last().unwrap(), levels);
                assert!(e.windows(2).all(|w| w[0] < w[1]), "{levels} {layers} {e:?}");
                assert!(e[0] >= 1);
            }
        }
    }
}
