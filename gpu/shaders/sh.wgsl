// The view-direction encoding for training, one invocation per direction: `sh4` of the render
// kernels (their module `render/sh.wgsl`, the one WGSL copy of `msth_core::sh::sh4`'s constants:
// real spherical harmonics, bands 0 to 3, 16 coefficients into the private array `sh`), which
// the host composes before this file. Directions are 3 floats each (unit length, as the CPU's rays); the 16
// values of direction i go to `out[i * stride + column ..]`, so they can land straight in the
// colour MLP's input rows. No gradient: the direction encoding has no parameters and the
// directions are fixed (the CPU computes none either).

struct ShEncode {
    // x: directions, y: row stride of `out` in floats, z: first column, w: 0.
    run: vec4<u32>,
}

@group(0) @binding(0) var<uniform> enc: ShEncode;
@group(0) @binding(1) var<storage, read> dirs: array<f32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(64)
fn sh_encode(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.x + gid.y * groups.x * 64u;
    if i >= enc.run.x {
        return;
    }
    sh4(vec3<f32>(dirs[i * 3u], dirs[i * 3u + 1u], dirs[i * 3u + 2u]));
    let base = i * enc.run.y + enc.run.z;
    for (var k = 0u; k < 16u; k++) {
        out[base + k] = sh[k];
    }
}
