use super::*;
use crate::rng::Rng;

fn cfg(dims: usize, levels: usize, log2: u32, f: usize) -> GridConfig {
    GridConfig {
        levels,
        features_per_level: f,
        log2_table_size: log2,
        base_resolution: vec![4.0; dims],
        finest_resolution: if dims == 3 {
            vec![64.0; 3]
        } else {
            vec![64.0, 64.0, 64.0, 20.0]
        },
    }
}

fn random(n: usize, rng: &mut Rng) -> Vec<f32> {
    (0..n).map(|_| rng.f32()).collect()
}

#[test]
fn method_md_reference_geometry() {
    // method.md: 16 levels, base 16, finest 2048 -> per-level scale 1.38191.
    let c = GridConfig {
        levels: 16,
        features_per_level: 2,
        log2_table_size: 19,
        base_resolution: vec![16.0, 16.0, 16.0, 15.0],
        finest_resolution: vec![2048.0, 2048.0, 2048.0, 300.0],
    };
    let g = GridLayout::new(&c);
    assert_eq!(g.levels[0].scale[0], 15.0);
    assert_eq!(g.levels[0].res[0], 16);
    assert!((g.levels[1].scale[0] - (16.0 * 1.381_91 - 1.0)).abs() < 1e-3);
    assert!((g.levels[1].scale[3] - (15.0 * 1.221_06 - 1.0)).abs() < 1e-3);
    assert!((g.levels[15].scale[0] - 2047.0).abs() < 0.05);
    assert!((g.levels[15].scale[3] - 299.0).abs() < 0.05);
    // 17^3*16 = 78608 rows fit in 2^19, so level 0 of the 4D grid is dense.
    assert!(g.levels[0].dense);
    assert_eq!(g.levels[0].rows, 17 * 17 * 17 * 16);
    assert!(!g.levels[3].dense);
    assert_eq!(g.levels[3].rows, 1 << 19);
}

#[test]
fn fast_matches_reference_all_shapes() {
    let mut rng = Rng::new(1);
    for dims in [3, 4] {
        for f in [1, 2, 4, 8] {
            for log2 in [6, 12] {
                let c = cfg(dims, 5, log2, f);
                c.validate("test").unwrap();
                let g = GridLayout::new(&c);
                let table: Vec<f32> = (0..g.num_params)
                    .map(|_| rng.range_f32(-1.0, 1.0))
                    .collect();
                let n = 64;
                let mut pts = random(n * 4, &mut rng);
                pts[0] = 0.0;
                pts[5] = 1.0;
                pts[6] = f32::NAN;
                pts[7] = -3.0;
                let e = g.output_dim();
                let mut out = vec![0f32; n * (e + 3)];
                g.encode(&table, &pts, 4, &mut out, e + 3, 1);
                let d_out: Vec<f32> = (0..n * (e + 3)).map(|_| rng.range_f32(-1.0, 1.0)).collect();
                let mut grad_fast = vec![0f32; g.num_params];
                g.backward(&pts, 4, &d_out, e + 3, 1, &mut grad_fast);
                let mut grad_ref = vec![0f32; g.num_params];
                for i in 0..n {
                    let r = g.encode_point_reference(&table, &pts[i * 4..i * 4 + dims]);
                    for k in 0..e {
                        let v = out[i * (e + 3) + 1 + k];
                        assert!(
                            (v - r[k]).abs() < 1e-5,
                            "dims {dims} f {f}: {v} vs {}",
                            r[k]
                        );
                    }
                    g.backward_point_reference(
                        &pts[i * 4..i * 4 + dims],
                        &d_out[i * (e + 3) + 1..i * (e + 3) + 1 + e],
                        &mut grad_ref,
                    );
                }
                for (a, b) in grad_fast.iter().zip(&grad_ref) {
                    assert!((a - b).abs() < 1e-4);
                }
            }
        }
    }
}

/// The paired 3D + 4D pass gives the same bits as the two grids' own passes, forward and
/// backward, on dense, hashed and mixed levels (and zero gradients on some points).
#[test]
fn pair_matches_separate_passes_exactly() {
    let mut rng = Rng::new(11);
    for f in [1, 2, 4, 8] {
        for log2 in [6, 9, 12] {
            let (g3, g4) = (
                GridLayout::new(&cfg(3, 6, log2, f)),
                GridLayout::new(&cfg(4, 6, log2, f)),
            );
            assert!(pairable(&g3, &g4));
            let t3: Vec<f32> = (0..g3.num_params)
                .map(|_| rng.range_f32(-1.0, 1.0))
                .collect();
            let t4: Vec<f32> = (0..g4.num_params)
                .map(|_| rng.range_f32(-1.0, 1.0))
                .collect();
            let n = 77;
            let mut pts = random(n * 4, &mut rng);
            pts[2] = f32::NAN;
            pts[7] = 1.0;
            let e = g3.output_dim();
            let (mut a3, mut a4) = (vec![0f32; n * (e + 1)], vec![0f32; n * (e + 1)]);
            g3.encode(&t3, &pts, 4, &mut a3, e + 1, 1);
            g4.encode(&t4, &pts, 4, &mut a4, e + 1, 1);
            let (mut b3, mut b4) = (vec![0f32; n * (e + 1)], vec![0f32; n * (e + 1)]);
            encode_pair(&g3, &t3, &g4, &t4, &pts, 4, &mut b3, &mut b4, e + 1, 1);
            assert_eq!(a3, b3);
            assert_eq!(a4, b4);
            let mut d3: Vec<f32> = (0..n * (e + 1)).map(|_| rng.range_f32(-1.0, 1.0)).collect();
            let mut d4: Vec<f32> = (0..n * (e + 1)).map(|_| rng.range_f32(-1.0, 1.0)).collect();
            d3[..5 * (e + 1)].fill(0.0);
            d4[3 * (e + 1)..9 * (e + 1)].fill(0.0);
            let (mut s3, mut s4) = (vec![0f32; g3.num_params], vec![0f32; g4.num_params]);
            g3.backward(&pts, 4, &d3, e + 1, 1, &mut s3);
            g4.backward(&pts, 4, &d4, e + 1, 1, &mut s4);
            let (mut p3, mut p4) = (vec![0f32; g3.num_params], vec![0f32; g4.num_params]);
            backward_pair(&g3, &g4, &pts, 4, &d3, &d4, e + 1, 1, &mut p3, &mut p4);
            assert_eq!(s3, p3);
            assert_eq!(s4, p4);
        }
    }
    // Different spatial scales cannot share corners.
    let mut c4 = cfg(4, 6, 9, 2);
    c4.finest_resolution[0] = 32.0;
    assert!(!pairable(
        &GridLayout::new(&cfg(3, 6, 9, 2)),
        &GridLayout::new(&c4)
    ));
}

/// The encoding is linear in the table, so the finite-difference check of the table gradient
/// is exact up to rounding; the check still runs through the public API end to end.
#[test]
fn backward_matches_finite_differences() {
    let mut rng = Rng::new(3);
    for dims in [3, 4] {
        let c = cfg(dims, 4, 8, 2);
        let g = GridLayout::new(&c);
        let mut table: Vec<f64> = (0..g.num_params)
            .map(|_| rng.range_f32(-1.0, 1.0) as f64)
            .collect();
        let x: Vec<f32> = random(dims, &mut rng);
        let w: Vec<f32> = random(g.output_dim(), &mut rng);
        let loss = |t: &[f64]| -> f64 {
            let t32: Vec<f32> = t.iter().map(|&v| v as f32).collect();
            let o = g.encode_point_reference(&t32, &x);
            o.iter()
                .zip(&w)
                .map(|(a, b)| (*a as f64) * (*b as f64))
                .sum()
        };
        let mut grad = vec![0f32; g.num_params];
        g.backward_point_reference(&x, &w, &mut grad);
        let touched: Vec<usize> = (0..g.num_params).filter(|&i| grad[i] != 0.0).collect();
        assert!(!touched.is_empty());
        for &i in touched.iter().take(40) {
            let h = 1e-2;
            let v = table[i];
            table[i] = v + h;
            let lp = loss(&table);
            table[i] = v - h;
            let lm = loss(&table);
            table[i] = v;
            let fd = (lp - lm) / (2.0 * h);
            assert!((fd - grad[i] as f64).abs() < 1e-4, "{fd} vs {}", grad[i]);
        }
    }
}

/// Gradient with respect to the input position (not used in training, but it validates the
/// interpolation weights): the encoding must be continuous across cell borders.
#[test]
fn encoding_is_continuous() {
    let mut rng = Rng::new(9);
    let g = GridLayout::new(&cfg(4, 6, 10, 2));
    let table: Vec<f32> = (0..g.num_params)
        .map(|_| rng.range_f32(-1.0, 1.0))
        .collect();
    for _ in 0..200 {
        let x = random(4, &mut rng);
        let mut y = x.clone();
        y[rng.below(4) as usize] += 1e-5;
        let a = g.encode_point_reference(&table, &x);
        let b = g.encode_point_reference(&table, &y);
        for k in 0..a.len() {
            assert!((a[k] - b[k]).abs() < 1e-2);
        }
    }
}

#[test]
fn extreme_configs_do_not_overflow() {
    for log2 in [3, 10, 24] {
        for levels in [1, 32] {
            let c = GridConfig {
                levels,
                features_per_level: 2,
                log2_table_size: log2,
                base_resolution: vec![1.0, 1.0, 1.0, 1.0],
                finest_resolution: vec![65536.0, 65536.0, 65536.0, 65536.0],
            };
            c.validate("t").unwrap();
            let g = GridLayout::new(&c);
            for level in &g.levels {
                assert!(level.rows <= 1 << log2);
            }
            let x = [1.0f32, 1.0, 1.0, 1.0];
            let mut rows_seen = 0;
            g.visit_rows(&x, |l, r| {
                assert!(r < g.levels[l].rows);
                rows_seen += 1;
            });
            assert_eq!(rows_seen, 16 * levels);
        }
    }
}

#[test]
fn dense_rows_stay_in_table() {
    let g = GridLayout::new(&cfg(3, 8, 16, 2));
    let mut rng = Rng::new(4);
    for _ in 0..2000 {
        let mut x = random(3, &mut rng);
        if rng.f32() < 0.3 {
            x[0] = 1.0;
            x[1] = 1.0;
        }
        g.visit_rows(&x, |l, r| {
            assert!(r < g.levels[l].rows, "level {l} row {r}")
        });
    }
}

#[test]
fn dense_grid_matches_fd() {
    let dg = DenseGrid3 { res: 5 };
    let mut rng = Rng::new(5);
    let vals: Vec<f32> = (0..dg.num_params())
        .map(|_| rng.range_f32(-1.0, 1.0))
        .collect();
    let x = [0.3f32, 0.77, 0.51];
    let mut grad = vec![0f32; vals.len()];
    dg.backward(&x, 1.0, &mut grad);
    for i in 0..vals.len() {
        let mut v = vals.clone();
        v[i] += 1e-2;
        let fd = (dg.sample(&v, &x) - dg.sample(&vals, &x)) / 1e-2;
        assert!((fd - grad[i]).abs() < 1e-3);
    }
    // corners are exact
    assert_eq!(dg.sample(&vals, &[0.0, 0.0, 0.0]), vals[0]);
    assert_eq!(dg.sample(&vals, &[1.0, 1.0, 1.0]), vals[124]);
}
