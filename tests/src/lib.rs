//! Helpers shared by the end-to-end tests in `tests/tests/`: where the shared datasets are, small
//! built-in scenes, and running the `msth` command in-process.

use std::path::{Path, PathBuf};

use msth_core::config::Preset;
use msth_trainer::dataset::Dataset;
use msth_trainer::synth::{generate, SynthConfig};
use msth_trainer::train::TrainSettings;

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

/// The fast preset cut down to a short run for tests: `iters` steps of 512 rays, proposal
/// annealing over the first quarter (rounded up), no intermediate checkpoints.
pub fn short_run(data: &Dataset, iters: usize) -> TrainSettings {
    let mut s = TrainSettings::for_preset(Preset::Fast, data);
    s.iters = iters;
    s.batch_rays = 512;
    s.anneal_steps = iters.div_ceil(4).max(1);
    s.checkpoint_every = 0;
    s
}

/// The settings of the codec fixture (`tests/fixtures/v1.*`): small tables, trained long enough
/// (200 steps of 1024 rays) for the moving objects to show up as dynamic pixels.
pub fn fixture_run(data: &Dataset) -> TrainSettings {
    let mut s = short_run(data, 200);
    for enc in [&mut s.model.field.encoding, &mut s.model.proposal.encoding] {
        enc.resize(6, 12, 96.0, 16);
    }
    s.model.proposal.encoding.grid3.log2_table_size = 10;
    s.model.proposal.encoding.grid4.log2_table_size = 10;
    s.batch_rays = 1024;
    s
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
