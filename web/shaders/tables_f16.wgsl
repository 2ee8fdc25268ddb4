// The hash tables as binary16 (msth-gpu `TableFormat::F16`): the host puts this file in the place
// of the "Hash tables" region of `render.wgsl`. Value i of a table buffer is the binary16 in
// half (i & 1) of word i >> 1, the lower half first (`pack2x16float`'s order); a row's two
// features are one word, one 4-byte load. The buffer holds whole words.
@group(0) @binding(2) var<storage, read> tab3: array<u32>;
@group(0) @binding(3) var<storage, read> tab4: array<u32>;

// Values i and i + 1 (i even) of the hash tables of buffer `buf` (0 tab3, 1 tab4): one word.
fn table2(buf: u32, i: u32) -> vec2<f32> {
    var w: u32;
    if buf == 0u {
        w = tab3[i >> 1u];
    } else {
        w = tab4[i >> 1u];
    }
    return unpack2x16float(w);
}
