//! The AVX2 hash-grid kernels (`core/src/grid/simd.rs`) give the scalar kernels' bits, forward
//! and backward, on paired, 3D-only and 4D-only levels.
//!
//! On a CPU without AVX2 there is nothing to compare, and the test is reported as ignored with
//! the reason (unless `MSTH_REQUIRE_AVX2=1`): this binary runs on `msth-testkit`'s harness.

use msth_core::grid::{
    backward_pair_with, encode_pair_with, simd_available, GridConfig, GridLayout,
};
use msth_core::rng::Rng;
use msth_testkit::{Need, Tests};

fn main() -> std::process::ExitCode {
    let avx2 = Need::new("avx2", || {
        if simd_available() {
            Ok(())
        } else {
            Err("this CPU has no AVX2 (or is not x86_64)".into())
        }
    });
    Tests::new(file!())
        .needs(
            &[&avx2],
            "simd_matches_scalar_exactly",
            simd_matches_scalar_exactly,
        )
        .run()
}

fn cfg(dims: usize, log2: u32) -> GridConfig {
    GridConfig {
        levels: 8,
        features_per_level: 2,
        log2_table_size: log2,
        base_resolution: vec![4.0; dims],
        finest_resolution: if dims == 3 {
            vec![64.0; 3]
        } else {
            vec![64.0, 64.0, 64.0, 20.0]
        },
    }
}

/// Full blocks and a tail, NaN, infinite, negative-zero and out-of-range coordinates, zero
/// gradients on some points, point strides of 4 and 5, tables of 2^6 to 2^15 rows (dense and
/// hashed levels). The scalar pair equals the scalar separate passes
/// (`grid::tests::pair_matches_separate_passes_exactly`), so the 3D-only and 4D-only passes,
/// which take the AVX2 kernels, are compared with the scalar pair's outputs.
fn simd_matches_scalar_exactly() {
    let mut rng = Rng::new(5);
    for (log2, n, ps) in [(6, 77, 4), (12, 64, 4), (15, 203, 5), (9, 5, 4)] {
        let (g3, g4) = (
            GridLayout::new(&cfg(3, log2)),
            GridLayout::new(&cfg(4, log2)),
        );
        assert!(g3.levels.iter().any(|l| !l.dense));
        let t3: Vec<f32> = (0..g3.num_params)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let t4: Vec<f32> = (0..g4.num_params)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let mut pts: Vec<f32> = (0..n * ps).map(|_| rng.range_f32(-0.2, 1.2)).collect();
        pts[1] = f32::NAN;
        pts[ps + 3] = f32::INFINITY;
        pts[2 * ps] = -0.0;
        let e = g3.output_dim() + 1;
        let run = |simd: bool| {
            let (mut o3, mut o4) = (vec![0f32; n * e], vec![0f32; n * e]);
            encode_pair_with(simd, &g3, &t3, &g4, &t4, &pts, ps, &mut o3, &mut o4, e, 1);
            (o3, o4)
        };
        let (scalar, fast) = (run(false), run(true));
        assert_eq!(scalar, fast, "pair forward, 2^{log2} rows, {n} points");
        let mut only3 = vec![0f32; n * e];
        g3.encode(&t3, &pts, ps, &mut only3, e, 1);
        assert_eq!(scalar.0, only3, "3D forward, 2^{log2} rows, {n} points");
        let mut only4 = vec![0f32; n * e];
        g4.encode(&t4, &pts, ps, &mut only4, e, 1);
        assert_eq!(scalar.1, only4, "4D forward, 2^{log2} rows, {n} points");

        let mut d3: Vec<f32> = (0..n * e).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let mut d4: Vec<f32> = (0..n * e).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        d3[..3 * e].fill(0.0);
        d4[2 * e..(5 * e).min(n * e)].fill(0.0);
        let run = |simd: bool| {
            let (mut s3, mut s4) = (vec![0f32; g3.num_params], vec![0f32; g4.num_params]);
            backward_pair_with(simd, &g3, &g4, &pts, ps, &d3, &d4, e, 1, &mut s3, &mut s4);
            (s3, s4)
        };
        let (scalar, fast) = (run(false), run(true));
        assert_eq!(scalar, fast, "pair backward, 2^{log2} rows, {n} points");
        let mut only3 = vec![0f32; g3.num_params];
        g3.backward(&pts, ps, &d3, e, 1, &mut only3);
        assert_eq!(scalar.0, only3, "3D backward, 2^{log2} rows, {n} points");
        let mut only4 = vec![0f32; g4.num_params];
        g4.backward(&pts, ps, &d4, e, 1, &mut only4);
        assert_eq!(scalar.1, only4, "4D backward, 2^{log2} rows, {n} points");
    }
}
