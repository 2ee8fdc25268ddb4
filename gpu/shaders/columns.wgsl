// Column copies between row layouts, one invocation per value: `cols` columns of each of
// `rows` rows from `src[r * src_stride + src_col + c]` to `dst[r * dst_stride + dst_col + c]`
// (the density MLP's geometry features into the colour MLP's input rows; the colour MLP's
// input gradient and d sigma into the density MLP's output-gradient rows).

struct Columns {
    // x: rows, y: columns, z: src stride, w: src first column.
    a: vec4<u32>,
    // x: dst stride, y: dst first column, z, w: 0.
    b: vec4<u32>,
}

@group(0) @binding(0) var<uniform> cc: Columns;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(64)
fn copy_columns(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let j = gid.x + gid.y * groups.x * 64u;
    if j >= cc.a.x * cc.a.y {
        return;
    }
    let r = j / cc.a.y;
    let c = j % cc.a.y;
    dst[r * cc.b.x + cc.b.y + c] = src[r * cc.a.z + cc.a.w + c];
}
