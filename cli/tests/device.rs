//! `msth train --device` as a separate process, on a machine made to have no GPU adapter (the
//! Vulkan loader pointed at a driver manifest that does not exist, wgpu told to use Vulkan
//! only): `gpu` is an error that says what to install or choose instead, `auto` trains on the
//! CPU and says so, and a device that is not one is named before any data is read.

use std::process::Command;

/// Runs `msth train builtin` with no GPU adapter; returns (success, stdout, stderr).
fn train_without_adapter(out: &std::path::Path, device: &str) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_msth"))
        .args(["train", "builtin", "--preset", "fast", "--iters", "1"])
        .args([
            "--batch-rays",
            "64",
            "--no-eval",
            "--device",
            device,
            "--out",
        ])
        .arg(out)
        .env("WGPU_BACKEND", "vulkan")
        .env("VK_ICD_FILENAMES", "/nonexistent/icd.json")
        .env("VK_DRIVER_FILES", "/nonexistent/icd.json")
        .env_remove("MSTH_GPU_SOFTWARE")
        .output()
        .expect("msth runs");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into(),
        String::from_utf8_lossy(&out.stderr).into(),
    )
}

#[test]
fn device_gpu_without_an_adapter_is_a_clear_error_and_auto_falls_back() {
    let dir = tempfile::tempdir().unwrap();
    let (ok, _, err) = train_without_adapter(&dir.path().join("gpu"), "gpu");
    assert!(!ok, "--device gpu without an adapter succeeded");
    assert!(
        err.contains("no GPU adapter found") && err.contains("--device cpu"),
        "{err}"
    );
    assert!(!dir.path().join("gpu/model.ckpt").exists());
    let (ok, out, err) = train_without_adapter(&dir.path().join("auto"), "auto");
    assert!(ok, "--device auto: {err}");
    assert!(
        out.contains("device: the CPU") || err.contains("device: the CPU"),
        "{out}\n{err}"
    );
    assert!(dir.path().join("auto/model.ckpt").exists());
    let (ok, _, err) = train_without_adapter(&dir.path().join("x"), "tpu");
    assert!(!ok);
    assert!(
        err.contains("`tpu` is not a device: auto, cpu or gpu"),
        "{err}"
    );
    assert!(
        !dir.path().join("x").exists(),
        "the run started before the flag was checked"
    );
}
