//! The models behind the crate's per-sample counts (the crate header's tables), its kernel tests
//! and its benchmarks: the demo (fast preset) and paper configurations of a 300-frame scene in
//! the D-NeRF box on a white background.

use msth_core::config::{Background, ModelConfig, Preset};
use msth_core::SceneBounds;

/// `(name, preset)` of the demo and paper configurations.
pub const REFERENCE_PRESETS: [(&str, Preset); 2] =
    [("demo", Preset::Fast), ("paper", Preset::Paper)];

/// `preset`'s model for a 300-frame scene (the time resolution follows the frame count).
pub fn reference_model(preset: Preset) -> ModelConfig {
    ModelConfig::preset(
        preset,
        SceneBounds::dnerf_default(),
        Background::Color { rgb: [1.0; 3] },
        300,
    )
}
