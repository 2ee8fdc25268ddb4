//! Finding and loading a dataset from a command-line argument.

use std::path::Path;

use anyhow::{bail, Context, Result};

use msth_trainer::dataset::{dnerf, Dataset};
use msth_trainer::synth::{generate, SynthConfig};

/// `builtin` is the procedural scene (generated in memory); anything else is a folder.
pub fn load(arg: &str, downscale: u32) -> Result<Dataset> {
    if arg == "builtin" {
        let mut cfg = SynthConfig::default();
        if downscale > 1 {
            cfg.width = (cfg.width / downscale).max(1);
            cfg.height = (cfg.height / downscale).max(1);
        }
        return Ok(generate(&cfg));
    }
    let dir = Path::new(arg);
    if !dir.is_dir() {
        bail!("{arg}: no such dataset folder (or use `builtin` for the built-in scene)");
    }
    if dir.join("transforms_train.json").is_file() {
        let opts = dnerf::LoadOptions {
            downscale,
            ..Default::default()
        };
        return dnerf::load(dir, &opts).with_context(|| format!("loading dataset {arg}"));
    }
    bail!("{arg}: not a dataset folder I can read (expected transforms_train.json, D-NeRF / Blender layout)")
}
