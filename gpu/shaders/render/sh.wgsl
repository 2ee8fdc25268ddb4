// sh: the view-direction encoding, 16 real spherical harmonics of a unit direction into
// `sh` (msth-core `sh::sh4`); also composed into the training kernels (`gpu/src/sh.rs`).

var<private> sh: array<f32, 16>;

fn sh4(d: vec3<f32>) {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    let xx = x * x;
    let yy = y * y;
    let zz = z * z;
    let xy = x * y;
    let yz = y * z;
    let xz = x * z;
    sh[0] = 0.2820948;
    sh[1] = -0.48860252 * y;
    sh[2] = 0.48860252 * z;
    sh[3] = -0.48860252 * x;
    sh[4] = 1.0925484 * xy;
    sh[5] = -1.0925484 * yz;
    sh[6] = 0.9461747 * zz - 0.31539157;
    sh[7] = -1.0925484 * xz;
    sh[8] = 0.5462742 * (xx - yy);
    sh[9] = 0.5900436 * y * (-3.0 * xx + yy);
    sh[10] = 2.8906114 * xy * z;
    sh[11] = 0.4570458 * y * (1.0 - 5.0 * zz);
    sh[12] = 0.37317633 * z * (5.0 * zz - 3.0);
    sh[13] = 0.4570458 * x * (1.0 - 5.0 * zz);
    sh[14] = 1.4453057 * z * (xx - yy);
    sh[15] = 0.5900436 * x * (-xx + 3.0 * yy);
}
