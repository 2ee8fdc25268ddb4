//! Looking for a GPU prints nothing that reads like an error. Mesa's device-select Vulkan layer
//! (`mesa-vulkan-drivers`) printed "error: XDG_RUNTIME_DIR is invalid or not set in the
//! environment." each time a Vulkan instance was created without a desktop session (CI,
//! containers, ssh): `msth play` (and `msth demo`, twice) showed it although nothing was wrong.
//! Needs that layer installed; elsewhere the test is reported as ignored, unless
//! `MSTH_REQUIRE_GPU=1` (CI), where it fails.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};

use msth_testkit::{Need, Tests};

fn main() -> ExitCode {
    let layer = Need::new("gpu", || {
        device_select_layer().map(drop).ok_or_else(|| {
            "Mesa's device-select Vulkan layer is not installed (mesa-vulkan-drivers)".to_string()
        })
    });
    Tests::new(file!())
        .needs(
            &[&layer],
            "no_wayland_error_without_a_desktop_session",
            no_wayland_error_without_a_desktop_session,
        )
        .run()
}

/// The layer's manifest, where the Vulkan loader looks for implicit layers.
fn device_select_layer() -> Option<PathBuf> {
    [
        "/usr/share/vulkan/implicit_layer.d",
        "/etc/vulkan/implicit_layer.d",
    ]
    .iter()
    .map(|d| Path::new(d).join("VkLayer_MESA_device_select.json"))
    .find(|p| p.exists())
}

fn no_wayland_error_without_a_desktop_session() {
    let dir = tempfile::tempdir().unwrap();
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/v1.msth");
    // Software adapters allowed, so that the GPU renderer opens lavapipe where it is installed.
    let out = Command::new(env!("CARGO_BIN_EXE_msth"))
        .arg("play")
        .arg(&file)
        .args([
            "--size",
            "8x6",
            "--frames",
            "1",
            "--no-video",
            "--quiet",
            "--out",
        ])
        .arg(dir.path())
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("NODEVICE_SELECT")
        .env("MSTH_GPU_SOFTWARE", "1")
        .output()
        .expect("msth runs");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "msth play failed:\n{err}");
    assert!(
        !err.contains("XDG_RUNTIME_DIR") && !err.contains("error"),
        "msth play printed an error that is none:\n{err}"
    );
    assert!(dir.path().join("frame_00000.png").exists());
}
