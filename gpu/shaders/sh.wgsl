// The view-direction encoding for training, one invocation per direction: exactly
// `msth_core::sh::sh4` (real spherical harmonics, bands 0 to 3, 16 coefficients, the same f32
// constants). Directions are 3 floats each (unit length, as the CPU's rays); the 16 values of
// direction i go to `out[i * stride + column ..]`, so they can land straight in the colour
// MLP's input rows. No gradient: the direction encoding has no parameters and the directions
// are fixed (the CPU computes none either).

struct Sh {
    // x: directions, y: row stride of `out` in floats, z: first column, w: 0.
    run: vec4<u32>,
}

@group(0) @binding(0) var<uniform> sh: Sh;
@group(0) @binding(1) var<storage, read> dirs: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(64)
fn sh_encode(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if i >= sh.run.x {
        return;
    }
    let x = dirs[i * 3u];
    let y = dirs[i * 3u + 1u];
    let z = dirs[i * 3u + 2u];
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    let xy = x * y;
    let yz = y * z;
    let xz = x * z;
    var v: array<f32, 16>;
    v[0] = 0.2820948;
    v[1] = -0.48860252 * y;
    v[2] = 0.48860252 * z;
    v[3] = -0.48860252 * x;
    v[4] = 1.0925484 * xy;
    v[5] = -1.0925484 * yz;
    v[6] = 0.9461747 * zz - 0.31539157;
    v[7] = -1.0925484 * xz;
    v[8] = 0.5462742 * (xx - yy);
    v[9] = 0.5900436 * y * (-3.0 * xx + yy);
    v[10] = 2.8906114 * xy * z;
    v[11] = 0.4570458 * y * (1.0 - 5.0 * zz);
    v[12] = 0.37317633 * z * (5.0 * zz - 3.0);
    v[13] = 0.4570458 * x * (1.0 - 5.0 * zz);
    v[14] = 1.4453057 * z * (xx - yy);
    v[15] = 0.5900436 * x * (-xx + 3.0 * yy);
    let base = i * sh.run.y + sh.run.z;
    for (var k = 0u; k < 16u; k++) {
        out[base + k] = v[k];
    }
}
