//! Helpers shared by the end-to-end tests in `tests/tests/`: where the shared datasets are, small
//! built-in scenes, and running the `msth` command in-process.

use std::path::{Path, PathBuf};

use msth_trainer::dataset::Dataset;
use msth_trainer::synth::{generate, SynthConfig};

/// `../shared/data/NAME` next to the repository, if present.
pub fn shared_dataset(name: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(name);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!(
            "SKIPPED: {} is not present (CI and developer machines have it)",
            p.display()
        );
        None
    }
}

/// A small version of the built-in scene that trains in seconds.
pub fn tiny_scene() -> (SynthConfig, Dataset) {
    let cfg = SynthConfig {
        width: 48,
        height: 36,
        num_frames: 6,
        num_train_cams: 6,
        supersample: 2,
        ..SynthConfig::default()
    };
    let d = generate(&cfg);
    (cfg, d)
}

/// Runs `msth ARGS...` in-process.
pub fn msth(args: &[&str]) -> anyhow_like::Result {
    let mut v = vec!["msth"];
    v.extend_from_slice(args);
    msth_cli::run(v).map_err(|e| format!("{e:#}"))
}

pub mod anyhow_like {
    /// The error of a command as its displayed message.
    pub type Result = std::result::Result<(), String>;
}
