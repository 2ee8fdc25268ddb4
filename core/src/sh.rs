//! Real spherical harmonics of a unit direction, degrees 0..=3 ("degree 4" in tiny-cuda-nn's
//! naming: 16 coefficients), used as the colour MLP's view-direction encoding.

/// Number of coefficients for SH "degree 4" (bands 0 to 3).
pub const SH_COEFFS: usize = 16;

/// Evaluates the 16 real SH basis functions at unit direction `d` into `out`.
#[inline]
pub fn sh4(d: [f32; 3], out: &mut [f32]) {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let (xy, yz, xz) = (x * y, y * z, x * z);
    out[0] = 0.282_094_8;
    out[1] = -0.488_602_52 * y;
    out[2] = 0.488_602_52 * z;
    out[3] = -0.488_602_52 * x;
    out[4] = 1.092_548_4 * xy;
    out[5] = -1.092_548_4 * yz;
    out[6] = 0.946_174_7 * zz - 0.315_391_57;
    out[7] = -1.092_548_4 * xz;
    out[8] = 0.546_274_2 * (xx - yy);
    out[9] = 0.590_043_6 * y * (-3.0 * xx + yy);
    out[10] = 2.890_611_4 * xy * z;
    out[11] = 0.457_045_8 * y * (1.0 - 5.0 * zz);
    out[12] = 0.373_176_33 * z * (5.0 * zz - 3.0);
    out[13] = 0.457_045_8 * x * (1.0 - 5.0 * zz);
    out[14] = 1.445_305_7 * z * (xx - yy);
    out[15] = 0.590_043_6 * x * (-xx + 3.0 * yy);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The basis is orthonormal on the sphere: check by Monte Carlo-free quadrature on a
    /// Fibonacci lattice.
    #[test]
    fn basis_is_orthonormal() {
        let n = 20_000;
        let mut gram = [[0f64; SH_COEFFS]; SH_COEFFS];
        let mut v = [0f32; SH_COEFFS];
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            sh4(
                [(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32],
                &mut v,
            );
            for a in 0..SH_COEFFS {
                for b in 0..SH_COEFFS {
                    gram[a][b] += v[a] as f64 * v[b] as f64;
                }
            }
        }
        let w = 4.0 * std::f64::consts::PI / n as f64;
        for a in 0..SH_COEFFS {
            for b in 0..SH_COEFFS {
                let expect = if a == b { 1.0 } else { 0.0 };
                assert!(
                    (gram[a][b] * w - expect).abs() < 2e-3,
                    "{a},{b}: {}",
                    gram[a][b] * w
                );
            }
        }
    }
}
