//! `msth bench tradeoff` end to end on a tiny built-in scene: the tables and plots are written
//! and parse, the marked Pareto fronts are exactly the non-dominated rows, and a second run
//! reuses the cached variants instead of training again.
//!
//! This binary runs on `msth-testkit`'s harness (`harness = false`): [`main`] lists its tests.
//! Drawing needs a TrueType font; without one the plot test is reported as ignored with the
//! reason, unless `MSTH_REQUIRE_FONT=1` (then it fails).

use std::path::Path;

use msth_cli::tradeoff_plot::{self, PlotPoint};
use msth_testkit::{Need, Tests};
use msth_tests::{msth, synth_cmd};

fn main() -> std::process::ExitCode {
    let font = Need::new("font", || {
        tradeoff_plot::ensure_font().map(drop).ok_or_else(|| {
            "no TrueType font (MSTH_FONT, /usr/share/fonts): install fonts-dejavu-core".into()
        })
    });
    Tests::new(file!())
        .test(
            "tradeoff_sweep_writes_tables_plots_and_fronts",
            tradeoff_sweep_writes_tables_plots_and_fronts,
        )
        .test("tradeoff_rejects_bad_options", tradeoff_rejects_bad_options)
        .test(
            "converged_sweeps_stop_each_variant_when_it_stalls",
            converged_sweeps_stop_each_variant_when_it_stalls,
        )
        .needs(
            &[&font],
            "scatter_draws_points_and_front",
            scatter_draws_points_and_front,
        )
        .run()
}

fn f(v: &serde_json::Value, k: &str) -> f64 {
    v[k].as_f64()
        .unwrap_or_else(|| panic!("`{k}` is not a number in {v}"))
}

fn b(v: &serde_json::Value, k: &str) -> bool {
    v[k].as_bool()
        .unwrap_or_else(|| panic!("`{k}` is not a bool in {v}"))
}

/// Whether row `i` is dominated in `(x, y)` (both maximised) by another row.
fn dominated(pts: &[(f64, f64)], i: usize) -> bool {
    let p = pts[i];
    pts.iter()
        .any(|q| q.0 >= p.0 && q.1 >= p.1 && (q.0 > p.0 || q.1 > p.1))
}

fn tradeoff_sweep_writes_tables_plots_and_fronts() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let out = tmp.path().join("out");
    synth_cmd(
        &data,
        &["--size", "32x24", "--frames", "3", "--cameras", "3"],
    )
    .unwrap();
    let args = [
        "--threads",
        "2",
        "bench",
        "tradeoff",
        data.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quick",
        "--iters",
        "3",
        "--presets",
        "fast",
        "--factors",
        "samples-,mask-,quant",
        "--variant",
        "tiny tables:model.field.encoding.grid3.log2_table_size=12;model.field.encoding.grid4.log2_table_size=12",
        "--fps-size",
        "16x12",
        "--fps-frames",
        "1",
        "--stride",
        "1",
    ];
    msth(&args).unwrap();
    for name in ["tradeoff.md", "tradeoff.csv", "tradeoff.json"] {
        assert!(out.join(name).is_file(), "{name} missing");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("tradeoff.json")).unwrap()).unwrap();
    let rows = json["rows"].as_array().unwrap();
    // fast (q5) + its f32 and k3 files, samples-, mask-, the custom variant.
    assert_eq!(rows.len(), 6, "{json:#}");
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    for want in [
        "fast",
        "fast-f32",
        "fast-k3",
        "fast-samples-24+12",
        "fast-mask-32",
    ] {
        assert!(names.contains(&want), "{want} not in {names:?}");
    }
    assert!(names.contains(&"fast-custom-tiny_tables"), "{names:?}");
    for r in rows {
        assert_eq!(r["steps"].as_u64(), Some(3), "{r}");
        let psnr = f(r, "psnr");
        assert!(psnr.is_finite() && psnr > 5.0, "{r}");
        assert!(f(r, "file_bytes") > 0.0 && f(r, "fps") > 0.0, "{r}");
        // A fixed camera's incremental frames re-render part of the frame: faster than full ones.
        assert!(f(r, "fps_fixed") > 0.0, "{r}");
        assert!(f(r, "train_seconds") > 0.0, "{r}");
    }
    // Lossless f32 files decode to the trained parameters: same PSNR as f32 evaluation.
    let f32row = rows.iter().find(|r| r["name"] == "fast-f32").unwrap();
    assert!(
        (f(f32row, "psnr") - f(f32row, "psnr_f32")).abs() < 0.05,
        "{f32row}"
    );
    // Quantised files are smaller than the lossless one (k3 against q5 depends on the values:
    // at 3 steps the codebooks can cost more than they save).
    let size = |n: &str| f(rows.iter().find(|r| r["name"] == n).unwrap(), "file_bytes");
    assert!(size("fast-k3") < size("fast-f32") && size("fast") < size("fast-f32"));
    // Fronts: the marked rows are exactly the non-dominated ones (quant rows only take part
    // in the size front: they share their model's training and rendering).
    let model_rows: Vec<&serde_json::Value> =
        rows.iter().filter(|r| r["factor"] != "quant").collect();
    let time: Vec<(f64, f64)> = model_rows
        .iter()
        .map(|r| (-f(r, "train_seconds"), f(r, "psnr")))
        .collect();
    let fps: Vec<(f64, f64)> = model_rows
        .iter()
        .map(|r| (f(r, "psnr"), f(r, "fps")))
        .collect();
    let size_pts: Vec<(f64, f64)> = rows
        .iter()
        .map(|r| (-f(r, "file_bytes"), f(r, "psnr")))
        .collect();
    for (i, r) in model_rows.iter().enumerate() {
        assert_eq!(b(r, "front_time"), !dominated(&time, i), "{r}");
        assert_eq!(b(r, "front_fps"), !dominated(&fps, i), "{r}");
    }
    for (i, r) in rows.iter().enumerate() {
        assert_eq!(b(r, "front_size"), !dominated(&size_pts, i), "{r}");
        if r["factor"] == "quant" {
            assert!(!b(r, "front_time") && !b(r, "front_fps"), "{r}");
        }
    }
    assert!(rows.iter().any(|r| b(r, "front_size")));
    // CSV: a header and one line per row, same names, same column count.
    let csv = std::fs::read_to_string(out.join("tradeoff.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), rows.len() + 1);
    let cols = lines[0].split(',').count();
    for (l, r) in lines[1..].iter().zip(rows) {
        assert_eq!(l.split(',').count(), cols, "{l}");
        assert!(
            l.starts_with(&format!("{},", r["name"].as_str().unwrap())),
            "{l}"
        );
    }
    let md = std::fs::read_to_string(out.join("tradeoff.md")).unwrap();
    assert_eq!(
        md.lines().filter(|l| l.starts_with("| ")).count(),
        rows.len() + 1,
        "{md}"
    );
    // Plots: PNGs of the plot size when a font exists, else a note saying why not (drawing
    // itself is `scatter_draws_points_and_front`, which needs a font).
    let pngs = ["psnr_vs_time.png", "psnr_vs_size.png", "fps_vs_psnr.png"];
    let font = tradeoff_plot::ensure_font();
    assert_eq!(
        md.contains("Plots skipped"),
        font.is_none(),
        "font {font:?}: {md}"
    );
    if font.is_some() {
        for p in pngs {
            let img = image::open(out.join(p)).unwrap_or_else(|e| panic!("{p}: {e}"));
            assert_eq!((img.width(), img.height()), (960, 640), "{p}");
        }
    }
    // A second run measures nothing again: every result is cached and left untouched.
    let mtimes = |dir: &Path| -> Vec<_> {
        let mut v: Vec<_> = std::fs::read_dir(dir.join("runs"))
            .unwrap()
            .map(|e| {
                let p = e.unwrap().path().join("result.json");
                (
                    p.clone(),
                    std::fs::metadata(&p).unwrap().modified().unwrap(),
                )
            })
            .collect();
        v.sort();
        v
    };
    let before = mtimes(&out);
    assert_eq!(before.len(), 4, "{before:?}");
    msth(&args).unwrap();
    assert_eq!(mtimes(&out), before);
    let again: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("tradeoff.json")).unwrap()).unwrap();
    assert_eq!(again["rows"], json["rows"]);
    // A changed budget is a different variant: not taken from the cache.
    let mut changed = args.to_vec();
    changed[9] = "4";
    changed[13] = "samples-";
    msth(&changed).unwrap();
    let third: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("tradeoff.json")).unwrap()).unwrap();
    assert!(third["rows"]
        .as_array()
        .unwrap()
        .iter()
        .all(|r| r["steps"].as_u64() == Some(4)));
}

/// `--converge`: each variant stops at the measurement that gains less than `--min-gain` (here
/// an unreachable 1000 dB: the second one), the steps and the measured curve are recorded, and
/// the report says how the variants were trained.
fn converged_sweeps_stop_each_variant_when_it_stalls() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let out = tmp.path().join("out");
    synth_cmd(
        &data,
        &["--size", "32x24", "--frames", "3", "--cameras", "3"],
    )
    .unwrap();
    let run = |extra: &[&str]| {
        let mut args = vec![
            "--threads",
            "2",
            "bench",
            "tradeoff",
            data.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--quick",
            "--converge",
            "--converge-every",
            "2",
            "--min-gain",
            "1000",
            "--iters",
            "50",
            "--presets",
            "fast",
            "--factors",
            "iters,mask-",
            "--fps-size",
            "16x12",
            "--fps-frames",
            "1",
            "--stride",
            "1",
        ];
        args.extend_from_slice(extra);
        msth(&args).unwrap()
    };
    run(&[]);
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("tradeoff.json")).unwrap()).unwrap();
    let rows = json["rows"].as_array().unwrap();
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    // The iters factor means nothing when runs choose their steps: left out.
    assert_eq!(names, ["fast", "fast-mask-32"], "{json:#}");
    for r in rows {
        assert_eq!(r["steps"].as_u64(), Some(4), "{r}");
    }
    let result: serde_json::Value = serde_json::from_slice(
        &std::fs::read(out.join("runs").join("fast").join("result.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(result["converged"], true, "{result}");
    let curve = result["held_out"].as_array().unwrap();
    assert_eq!(curve.len(), 2, "{result}");
    assert_eq!(curve[1][0].as_u64(), Some(4));
    let md = std::fs::read_to_string(out.join("tradeoff.md")).unwrap();
    assert!(md.contains("until converged"), "{md}");
    // A second run reuses both: the cached results are not written again.
    let cached = out.join("runs").join("fast").join("result.json");
    let before = std::fs::read(&cached).unwrap();
    let modified = std::fs::metadata(&cached).unwrap().modified().unwrap();
    run(&[]);
    assert_eq!(std::fs::read(&cached).unwrap(), before);
    assert_eq!(
        std::fs::metadata(&cached).unwrap().modified().unwrap(),
        modified
    );
    // A variant with its own budget trains to it; the others stay cached.
    run(&["--cap", "fast-mask-32=2"]);
    assert_eq!(std::fs::read(&cached).unwrap(), before);
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("tradeoff.json")).unwrap()).unwrap();
    let steps: Vec<(&str, u64)> = json["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["name"].as_str().unwrap(), r["steps"].as_u64().unwrap()))
        .collect();
    assert_eq!(steps, [("fast", 4), ("fast-mask-32", 2)], "{json:#}");
    let md = std::fs::read_to_string(out.join("tradeoff.md")).unwrap();
    assert!(md.contains("own budgets: fast-mask-32 2"), "{md}");
    let e = msth(&[
        "bench",
        "tradeoff",
        "builtin",
        "--out",
        out.to_str().unwrap(),
        "--converge",
        "--converge-every",
        "0",
    ])
    .unwrap_err();
    assert!(e.contains("--converge-every"), "{e}");
}

fn tradeoff_rejects_bad_options() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let o = out.to_str().unwrap();
    // (option, bad value, what the error says)
    for (flag, value, needle) in [
        ("--factors", "colour", "unknown factor `colour`"),
        ("--variant", "nolabel", "--variant"),
        ("--fps-size", "0x5", "--fps-size"),
        ("--presets", "huge", "unknown preset"),
        ("--cap", "quality=0", "--cap quality=0"),
        ("--cap", "nosuch=5", "no variant `nosuch`"),
    ] {
        let e = msth(&["bench", "tradeoff", "builtin", "--out", o, flag, value]).unwrap_err();
        assert!(e.contains(needle), "{flag} {value}: {e}");
    }
    let e = msth(&["bench", "tradeoff", "/no/such/dir", "--out", o]).unwrap_err();
    assert!(e.contains("/no/such/dir"), "{e}");
}

/// A scatter plot with a front: red (front) and blue (dominated) markers are drawn, a NaN point
/// is left out.
fn scatter_draws_points_and_front() {
    let point = |x: f64, y: f64, label: &str, front: bool| PlotPoint {
        x,
        y,
        label: label.into(),
        front,
    };
    let pts = vec![
        point(10.0, 20.0, "a", true),
        point(100.0, 25.0, "b", true),
        point(50.0, 18.0, "c", false),
        point(f64::NAN, 1.0, "nan", false),
    ];
    let img = tradeoff_plot::scatter("t", "x", "y", true, &pts).unwrap();
    let px = img.data.loaded();
    let (w, h) = (tradeoff_plot::WIDTH, tradeoff_plot::HEIGHT);
    assert_eq!(px.len(), (w * h * 3) as usize);
    // Some pure-ish red (front markers) and blue (dominated markers) pixels were drawn.
    let has = |f: &dyn Fn(&[u8]) -> bool| px.chunks(3).any(f);
    assert!(has(&|p| p[0] > 180 && p[1] < 60 && p[2] < 60));
    assert!(has(&|p| p[2] > 150 && p[0] < 80));
}
