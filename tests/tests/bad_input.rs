//! Bad datasets end with one clear error naming the file and the field, and leave nothing behind.

use std::path::Path;

use msth_tests::{synth_cmd, train_cmd};

/// Writes a tiny valid dataset and returns its folder.
fn valid_dataset(root: &Path) -> std::path::PathBuf {
    let d = root.join("data");
    let size = [
        "--width",
        "16",
        "--height",
        "12",
        "--frames",
        "3",
        "--cameras",
        "2",
    ];
    synth_cmd(&d, &size).unwrap();
    d
}

fn edit_json(path: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(path, serde_json::to_string(&v).unwrap()).unwrap();
}

/// The image file of training frame `k`.
fn training_image(data: &Path, k: usize) -> std::path::PathBuf {
    let json = data.join("transforms_train.json");
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    let rel = v["frames"][k]["file_path"].as_str().unwrap();
    let mut img = data.join(rel.trim_start_matches("./"));
    if img.extension().is_none() {
        img.set_extension("png");
    }
    img
}

/// Trains on the broken dataset and checks the error and that no output was written.
fn expect_failure(root: &Path, data: &Path, needles: &[&str]) {
    let out = root.join("run");
    let err = train_cmd(data, &out, &["--preset", "fast", "--iters", "1"])
        .expect_err("training on a broken dataset must fail");
    for n in needles {
        assert!(err.contains(n), "error should mention `{n}`: {err}");
    }
    assert!(
        !out.join("model.ckpt").exists(),
        "no checkpoint may be left behind"
    );
    assert!(!out.join("metrics.json").exists());
}

/// A valid dataset with `edit` applied to `transforms_train.json` fails to train with an error
/// naming the file and `field`.
fn edited_transforms_fail(field: &str, edit: impl FnOnce(&mut serde_json::Value)) {
    let t = tempfile::tempdir().unwrap();
    let d = valid_dataset(t.path());
    edit_json(&d.join("transforms_train.json"), edit);
    expect_failure(t.path(), &d, &["transforms_train.json", field]);
}

#[test]
fn missing_transforms_file() {
    let t = tempfile::tempdir().unwrap();
    let d = valid_dataset(t.path());
    std::fs::remove_file(d.join("transforms_train.json")).unwrap();
    expect_failure(t.path(), &d, &["transforms_train.json"]);
}

#[test]
fn malformed_transforms_file() {
    let t = tempfile::tempdir().unwrap();
    let d = valid_dataset(t.path());
    std::fs::write(
        d.join("transforms_train.json"),
        "{\"frames\": [ {\"time\": 0.1,",
    )
    .unwrap();
    expect_failure(t.path(), &d, &["transforms_train.json", "JSON"]);
}

#[test]
fn missing_image() {
    let t = tempfile::tempdir().unwrap();
    let d = valid_dataset(t.path());
    let img = training_image(&d, 0);
    std::fs::remove_file(&img).unwrap();
    expect_failure(t.path(), &d, &[img.file_name().unwrap().to_str().unwrap()]);
}

#[test]
fn images_of_mixed_sizes() {
    let t = tempfile::tempdir().unwrap();
    let d = valid_dataset(t.path());
    let json = d.join("transforms_train.json");
    let img = training_image(&d, 1);
    // A valid PNG of another size.
    let small = msth_dataset::Image8::new(8, 8);
    msth_dataset::imageio::save_png_atomic(&img, &small).unwrap();
    // Without explicit w/h in the JSON the size mismatch is caught between images.
    edit_json(&json, |v| {
        for k in ["w", "h"] {
            v.as_object_mut().unwrap().remove(k);
        }
        for f in v["frames"].as_array_mut().unwrap() {
            for k in ["w", "h"] {
                f.as_object_mut().unwrap().remove(k);
            }
        }
    });
    expect_failure(
        t.path(),
        &d,
        &[img.file_name().unwrap().to_str().unwrap(), "8x8"],
    );
}

#[test]
fn non_finite_pose() {
    // JSON has no NaN; 1e39 overflows f32 to infinity.
    edited_transforms_fail("transform_matrix", |v| {
        v["frames"][0]["transform_matrix"][0][3] = serde_json::json!(1e39)
    });
}

#[test]
fn non_invertible_pose() {
    edited_transforms_fail("transform_matrix", |v| {
        v["frames"][0]["transform_matrix"] =
            serde_json::json!([[0, 0, 0, 1], [0, 0, 0, 2], [0, 0, 0, 3], [0, 0, 0, 1]]);
    });
}

#[test]
fn time_outside_unit_interval() {
    edited_transforms_fail("time", |v| v["frames"][1]["time"] = serde_json::json!(1.5));
}

#[test]
fn bad_settings_are_rejected_before_training() {
    let t = tempfile::tempdir().unwrap();
    let d = valid_dataset(t.path());
    let out = t.path().join("run");
    let run = |set: &str| train_cmd(&d, &out, &["--iters", "1", "--set", set]).unwrap_err();
    assert!(run("model.sampler.num_samples=0").contains("num_samples"));
    assert!(run("model.field.encoding.grid3.log2_table_size=40").contains("log2_table_size"));
    assert!(run("no_such_knob=1").contains("no_such_knob"));
    assert!(run("adam.lr=-1").contains("adam.lr"));
    assert!(!out.join("model.ckpt").exists());
}
