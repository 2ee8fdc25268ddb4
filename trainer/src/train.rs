//! The training loop: batches of random (view, pixel) rays, chunks processed in parallel with
//! one gradient buffer per worker, Adam with the fused mask loss, periodic atomic checkpoints,
//! `--resume`, and a divergence guard that stops before a NaN reaches a checkpoint.
//!
//! Repeatability: for a given seed and worker count the run is bit-for-bit repeatable (each
//! chunk draws from its own random stream; worker gradients are summed in a fixed order).

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use msth_core::config::{Background, ModelConfig, ModelConfigError, Preset};
use msth_core::field::ModelLayout;
use msth_core::pipeline::{
    train_chunk_with, AuxStep, ChunkLosses, StepSettings, TimedRay, Workspace,
};
use msth_core::rng::Rng;
use msth_core::scene::SceneBounds;
use msth_core::uncertainty::{AuxLayout, InvalidMaskLearning, MaskLearningConfig};
use msth_core::Camera;
use msth_gpu::adam::{AdamHyper, MaskSlice};
use msth_gpu::step::{GpuStep, HostBatch};
use msth_gpu::GpuError;

use crate::adam::{Adam, AdamConfig, ScaledSlice};
use crate::checkpoint::{
    AuxCheckpoint, Checkpoint, CheckpointError, CheckpointFormatError, CheckpointHeader,
};
use crate::device::{self, DeviceError, GpuTraining, TrainDevice};
use crate::ray_sampling::{
    InvalidSamplingConfig, PixelMotion, RaySampler, SamplingConfig, SamplingError, SamplingMode,
};
use msth_dataset::Dataset;

/// Every knob of a training run. Presets fill it; a config file and `--set key=value` override
/// any field (see [`TrainSettings::apply_overrides`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainSettings {
    pub preset: Preset,
    pub iters: usize,
    pub batch_rays: usize,
    /// Rays per work item of a worker.
    pub chunk_rays: usize,
    pub seed: u64,
    pub adam: AdamConfig,
    pub interlevel_weight: f32,
    pub distortion_weight: f32,
    pub mask_loss_weight: f32,
    /// Steps over which the proposal weights are annealed (`w^a`, `a = 10f/(9f+1)`).
    pub anneal_steps: usize,
    /// Checkpoint every this many steps (0: only at the end).
    pub checkpoint_every: usize,
    /// Also checkpoint when this many seconds have passed since the last checkpoint (0: by steps
    /// only). Saving does not change the run: a resumed run goes on as an uninterrupted one.
    #[serde(default)]
    pub checkpoint_secs: f64,
    /// Evaluate every `eval_stride`-th test view.
    pub eval_stride: usize,
    /// Train until converged: every `converge_every` steps the held-out PSNR (every
    /// `eval_stride`-th test view) is measured, and the run stops once it gained less than
    /// `converge_min_gain_db` since the last measurement ([`converged`]); `iters` is then the cap
    /// (the schedules follow it). 0: run to `iters`.
    #[serde(default)]
    pub converge_every: usize,
    #[serde(default = "default_min_gain")]
    pub converge_min_gain_db: f64,
    /// Stop early after this many seconds of training (0: no limit). The learning rate then
    /// decays with time as well as steps; such runs depend on the machine's speed and are not
    /// bit-for-bit repeatable.
    pub time_limit_secs: f64,
    /// For images with transparency: composite each training ray on a random background colour
    /// (so empty space must be transparent rather than white).
    pub random_background: bool,
    /// Jitter training rays inside their pixel (else through the pixel centre).
    pub pixel_jitter: bool,
    /// Uncertainty-guided mask learning (paper §3.3): every term off by default.
    #[serde(default)]
    pub mask_learning: MaskLearningConfig,
    /// World lengths are multiplied by this before training ([`TrainSettings::scale_world`]):
    /// the model, its checkpoint cameras and its exported file live in scaled units. Densities
    /// are per world unit, so a scene far from unit size trains slowly; the sizing
    /// ([`crate::autosize`]) picks a scale that brings the scene to about 3 units.
    #[serde(default = "one")]
    pub scene_scale: f32,
    /// Which rays and times a batch draws (paper §3.4; `ray_sampling.rs`).
    #[serde(default)]
    pub sampling: SamplingConfig,
    /// Multiplies the learning rate of the mask grids (see [`ScaledSlice`]): Adam moves a
    /// logit by at most about `lr` per step, so this bounds how far the mask can move in a run.
    #[serde(default = "one")]
    pub mask_lr_scale: f32,
    /// Weight of the per-sample mask loss (`StepSettings::sample_mask_weight`); 0: off.
    #[serde(default)]
    pub sample_mask_weight: f32,
    /// Rays through a pixel whose colour's temporal standard deviation (over its camera's
    /// frames, colour units in `[0, 1]`, as the dynamics-aware sampler measures it) exceeds this
    /// get no per-sample mask loss: the loss pulls toward static only what the data shows still,
    /// so a moving object seen by few rays is not pulled static (docs/mask-learning.md, "The
    /// mask decides"). 0: every ray gets the loss (settings written before it existed).
    #[serde(default)]
    pub sample_mask_moving_std: f32,
    /// Multiplies the learning rate of the proposal network (its grids and MLP; its mask, if
    /// any, keeps `mask_lr_scale`): how fast the proposal follows the main field's surfaces
    /// (docs/convergence.md: one seed in three loses that race on a stage). 1: the common rate.
    #[serde(default = "one")]
    pub proposal_lr_scale: f32,
    /// Weight of the free-space loss (`StepSettings::free_space_weight`): random points of the
    /// volume pulled empty, so space no training ray sees holds no density; 0: off.
    #[serde(default)]
    pub free_space_weight: f32,
    /// Coarse-to-fine over the main field's hash-grid levels (`StepSettings::active_levels`):
    /// the run starts with `level_ramp_start` of the levels on and turns the finer ones on
    /// linearly over these many steps, so coarse levels settle the geometry before fine ones can
    /// fit per-view detail into it (docs/convergence.md, "Coarse-to-fine and the free-space loss").
    /// 0: off.
    #[serde(default)]
    pub level_ramp_steps: usize,
    /// Share of the main field's levels on at step 0 of the ramp, in `(0, 1]`.
    #[serde(default = "one")]
    pub level_ramp_start: f32,
    /// Nested dropout over the progressive layers (docs/streaming.md): the share of steps, in
    /// `[0, 1]`, that train a prefix of the main field's levels only, the finer levels' features
    /// at 0, as a player holding only the first layers of a layered file renders it. The prefix
    /// is `k` of `nested_dropout_layers` layers (`msth_core::layers::layer_level_ends`), `k`
    /// drawn evenly from `1..nested_dropout_layers` per step. 0: off.
    #[serde(default)]
    pub nested_dropout: f32,
    /// The layers nested dropout trains prefixes of: the `--layers` the file will be exported
    /// with (2..=16).
    #[serde(default = "default_dropout_layers")]
    pub nested_dropout_layers: usize,
    /// The distortion loss's weight moves linearly from `distortion_weight` to
    /// `distortion_late_weight` over `distortion_ramp_steps` steps from step
    /// `distortion_ramp_start` (0: no ramp).
    #[serde(default)]
    pub distortion_ramp_start: usize,
    #[serde(default)]
    pub distortion_ramp_steps: usize,
    #[serde(default)]
    pub distortion_late_weight: f32,
    /// Weight decay of the main field's hash tables (Zip-NeRF): the loss
    /// `grid_decay * sum_levels mean(x^2)` over the 3D and 4D tables; 0: off.
    #[serde(default)]
    pub grid_decay: f32,
    pub model: ModelConfig,
    /// Where the steps run (`msth train --device`): not a setting of the model or the run, so
    /// not saved with it (a checkpoint resumes on either device).
    #[serde(skip)]
    pub device: TrainDevice,
}

/// The shortest proposal annealing of the presets (`anneal_steps`; all but `fast` on an
/// object-centred scene): steps, not a share of `--iters`, because the race it settles (the
/// proposal following the field's surfaces) is run in the first few hundred steps whatever the
/// run's length.
pub const MIN_ANNEAL_STEPS: usize = 2000;

/// [`TrainSettings::nested_dropout_layers`]'s default: `msth export --layers`'s.
pub const DEFAULT_DROPOUT_LAYERS: usize = 4;

fn default_dropout_layers() -> usize {
    DEFAULT_DROPOUT_LAYERS
}

/// The presets' ray sampler for a scene's bounds.
///
/// - An object-centred scene (a box; cameras around it): the paper's dynamics-aware sampler,
///   the ablation's choice on the built-in scene (docs/mask-learning.md; monocular data falls
///   back to uniform with a note).
/// - A forward-facing capture (contracted bounds; cameras on one side, as in Plenoptic Video
///   and the stages): uniform. There the dynamics-aware sampler fits the 4D part hardest where
///   a shallow arc of cameras constrains depth least: on `box_animated_stage` one seed in three
///   drew the moving box as ghosts only a new view sees (26.45 dB), while the uniform sampler
///   converged on all three (30.40, 31.50, 31.53 dB; docs/convergence.md, "The uniform sampler
///   on stages").
pub fn default_sampling_mode(bounds: &SceneBounds) -> SamplingMode {
    match bounds {
        SceneBounds::Box { .. } => SamplingMode::Dynamics,
        SceneBounds::Contracted { .. } => SamplingMode::Uniform,
    }
}

/// The priors against per-view overfitting that the presets set by the kind of scene (the
/// [`TrainSettings`] fields of the same names).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScenePriors {
    pub level_ramp_steps: usize,
    pub level_ramp_start: f32,
    pub free_space_weight: f32,
    pub distortion_ramp_start: usize,
    pub distortion_ramp_steps: usize,
    pub distortion_late_weight: f32,
    pub grid_decay: f32,
}

/// On forward-facing captures (contracted bounds): coarse-to-fine from half the levels, all on
/// after 300 steps, with the free-space loss at 1e-3; off on object-centred scenes (not measured
/// there). Together they lifted a generated stage with finely textured walls from 19.06 to
/// 22.60 dB held-out (mean of 3 seeds, each better) and cost `box_animated_stage` 0.97 dB
/// (docs/convergence.md, "Coarse-to-fine and the free-space loss"); the ramp alone kept the
/// walls' structure but left a haze of floaters, the free-space loss alone did not help.
///
/// Once every level is on, the distortion loss rises from 2e-3 to 0.05 (steps 300-600), so a
/// ray's weight gathers at one surface instead of thin dark texture being learned as holes to a
/// far background: +0.49 dB held-out on the generated stage over 3 seeds, each better
/// (docs/convergence.md, "The distortion loss ramped in after coarse-to-fine"). At 0.02 from
/// the first step it collapsed the geometry before it formed.
///
/// The main field's hash tables decay toward zero (`grid_decay` 0.3, Zip-NeRF's weight decay on
/// its grids): rows that few training rays reach no longer keep what one view fitted
/// (docs/convergence.md, "Weight decay on the hash tables").
pub fn default_priors(bounds: &SceneBounds) -> ScenePriors {
    match bounds {
        SceneBounds::Box { .. } => ScenePriors {
            level_ramp_steps: 0,
            level_ramp_start: 1.0,
            free_space_weight: 0.0,
            distortion_ramp_start: 0,
            distortion_ramp_steps: 0,
            distortion_late_weight: 0.0,
            grid_decay: 0.0,
        },
        SceneBounds::Contracted { .. } => ScenePriors {
            level_ramp_steps: 300,
            level_ramp_start: 0.5,
            free_space_weight: 1e-3,
            distortion_ramp_start: 300,
            distortion_ramp_steps: 300,
            distortion_late_weight: 0.05,
            grid_decay: 0.3,
        },
    }
}

/// Where rays start on a forward-facing capture that states its near bound ([`Dataset::near`]):
/// there rather than at the preset's 5% of the contraction radius, which on a stage lies far in
/// front of anything the cameras see and leaves the field free to put floaters there
/// (docs/convergence.md, "Rays from the capture's near bound"). `None` on object-centred
/// scenes (rays are clipped to the box) and where the data has no near bound.
pub fn capture_near(data: &Dataset, model: &ModelConfig) -> Option<f32> {
    match model.bounds {
        SceneBounds::Contracted { .. } => data
            .near
            .filter(|n| n.is_finite() && *n > 0.0 && *n < model.sampler.far),
        SceneBounds::Box { .. } => None,
    }
}

/// Default of [`TrainSettings::mask_lr_scale`] (issue #16's measurements).
pub const DEFAULT_MASK_LR_SCALE: f32 = 10.0;
/// Default of [`TrainSettings::sample_mask_weight`] (issue #16's measurements).
pub const DEFAULT_SAMPLE_MASK_WEIGHT: f32 = 5e-3;
/// Default of [`TrainSettings::sample_mask_moving_std`] (docs/mask-learning.md, "The mask
/// decides"): half the temporal std above which `msth bench ablation` counts a held-out
/// pixel as dynamic, so faint moving shadows are spared too (0.02 left a third of
/// `box_animated_stage`'s dynamic held-out pixels cached as static, 0.01 a quarter).
pub const DEFAULT_SAMPLE_MASK_MOVING_STD: f32 = 0.01;

/// Why [`TrainSettings::validate`] or [`TrainSettings::apply_overrides`] refused settings; the
/// message names the setting.
#[derive(Debug, thiserror::Error)]
pub enum SettingsError {
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    MaskLearning(#[from] InvalidMaskLearning),
    #[error(transparent)]
    Sampling(#[from] InvalidSamplingConfig),
    #[error("model.{0}")]
    Model(ModelConfigError),
    #[error("--set `{0}`: expected key=value")]
    SetSyntax(String),
    #[error("--set `{key}`: unknown setting `{part}`")]
    UnknownSet { key: String, part: String },
    #[error("config: unknown setting `{0}`")]
    UnknownConfigKey(String),
    #[error("{0}")]
    Serialize(serde_json::Error),
    #[error("invalid settings: {0}")]
    Deserialize(serde_json::Error),
}

impl TrainSettings {
    pub fn for_preset(preset: Preset, data: &Dataset) -> Self {
        let background = Background::Color {
            rgb: data.background,
        };
        let mut model = ModelConfig::preset(preset, data.bounds, background, data.num_frames);
        if let Some(near) = capture_near(data, &model) {
            model.sampler.near = near;
        }
        Self::for_model(preset, model)
    }

    /// The preset's run settings around a given model configuration.
    pub fn for_model(preset: Preset, model: ModelConfig) -> Self {
        let (iters, batch) = match preset {
            Preset::Fast => (1400, 2048),
            Preset::Balanced => (4000, 4096),
            Preset::Paper => (20_000, 16_384),
        };
        let priors = default_priors(&model.bounds);
        TrainSettings {
            preset,
            iters,
            batch_rays: batch,
            chunk_rays: 128,
            seed: 0,
            adam: AdamConfig::default(),
            interlevel_weight: 1.0,
            distortion_weight: 2e-3,
            mask_loss_weight: 1e-2,
            // A quarter of the preset's run, as the MSTH release (5000 of 20,000 steps), but at
            // least MIN_ANNEAL_STEPS, except for the fast preset on an object-centred scene (the
            // demo's; docs/convergence.md, "Proposal annealing": on a stage, annealing over 1000
            // steps let the proposal lose its race with the field in one seed of three, over 2000
            // three of three converged; the fast preset there went from 16.60 to 23.06 dB).
            anneal_steps: match (preset, model.bounds) {
                (Preset::Fast, SceneBounds::Box { .. }) => (iters / 4).max(1),
                _ => (iters / 4).max(MIN_ANNEAL_STEPS),
            },
            checkpoint_every: 1000,
            checkpoint_secs: 600.0,
            eval_stride: 1,
            converge_every: 0,
            converge_min_gain_db: DEFAULT_MIN_GAIN_DB,
            time_limit_secs: 0.0,
            random_background: true,
            pixel_jitter: false,
            mask_learning: MaskLearningConfig::default(),
            scene_scale: 1.0,
            sampling: SamplingConfig {
                mode: default_sampling_mode(&model.bounds),
                ..SamplingConfig::default()
            },
            // The mask decides (docs/mask-learning.md, "The mask decides", issue #16): a logit
            // step 10x the field's, so empty space and seen static surfaces reach m >= 0.9 within
            // a short run, and the per-sample mask loss, which pulls seen voxels static unless the
            // 4D table lowers the image loss by more than its weight.
            mask_lr_scale: DEFAULT_MASK_LR_SCALE,
            sample_mask_weight: DEFAULT_SAMPLE_MASK_WEIGHT,
            sample_mask_moving_std: DEFAULT_SAMPLE_MASK_MOVING_STD,
            proposal_lr_scale: 1.0,
            free_space_weight: priors.free_space_weight,
            level_ramp_steps: priors.level_ramp_steps,
            level_ramp_start: priors.level_ramp_start,
            nested_dropout: 0.0,
            nested_dropout_layers: DEFAULT_DROPOUT_LAYERS,
            distortion_ramp_start: priors.distortion_ramp_start,
            distortion_ramp_steps: priors.distortion_ramp_steps,
            distortion_late_weight: priors.distortion_late_weight,
            grid_decay: priors.grid_decay,
            model,
            device: TrainDevice::Cpu,
        }
    }

    /// The distortion loss's weight at `step` (see [`TrainSettings::distortion_ramp_start`]).
    pub fn distortion_weight_at(&self, step: usize) -> f32 {
        if self.distortion_ramp_start == 0 || step < self.distortion_ramp_start {
            return self.distortion_weight;
        }
        let f = ((step - self.distortion_ramp_start) as f32
            / self.distortion_ramp_steps.max(1) as f32)
            .min(1.0);
        self.distortion_weight + (self.distortion_late_weight - self.distortion_weight) * f
    }

    /// Applies [`TrainSettings::scene_scale`] to the dataset and to the world lengths of the
    /// model (bounds, near and far, all given in the dataset's units). Call it once, after every
    /// override; the scale stays recorded (the checkpoint's settings carry it, see
    /// [`crate::checkpoint::CheckpointHeader::scene_scale`]). Returns the scale applied.
    pub fn scale_world(&mut self, data: &mut Dataset) -> f32 {
        let s = self.scene_scale;
        if s != 1.0 {
            data.rescale(s);
            self.model.bounds = self.model.bounds.scaled(s);
            self.model.sampler.near *= s;
            self.model.sampler.far *= s;
        }
        s
    }

    /// Applies a JSON object of overrides (e.g. read from a config file) and `key=value` pairs
    /// with dotted paths (`model.sampler.num_samples=32`, values parsed as JSON, else as strings).
    pub fn apply_overrides(
        &mut self,
        file: Option<serde_json::Value>,
        sets: &[String],
    ) -> Result<(), SettingsError> {
        let mut v = serde_json::to_value(&*self).map_err(SettingsError::Serialize)?;
        if let Some(f) = file {
            merge(&mut v, f, "")?;
        }
        for s in sets {
            let (key, val) = s
                .split_once('=')
                .ok_or_else(|| SettingsError::SetSyntax(s.clone()))?;
            let val: serde_json::Value = serde_json::from_str(val)
                .unwrap_or_else(|_| serde_json::Value::String(val.to_string()));
            let mut node = &mut v;
            for part in key.split('.') {
                node = node
                    .get_mut(part)
                    .ok_or_else(|| SettingsError::UnknownSet {
                        key: key.to_string(),
                        part: part.to_string(),
                    })?;
            }
            *node = val;
        }
        *self = serde_json::from_value(v).map_err(SettingsError::Deserialize)?;
        self.validate()
    }

    /// The coarse-to-fine value of step `step` (`StepSettings::active_levels`): `None` when the
    /// ramp is off or over.
    pub fn active_levels(&self, step: usize) -> Option<f32> {
        if step >= self.level_ramp_steps {
            return None;
        }
        let enc = &self.model.field.encoding;
        let levels = enc.grid3.levels.max(enc.grid4.levels) as f32;
        let f = step as f32 / self.level_ramp_steps as f32;
        Some(levels * (self.level_ramp_start + (1.0 - self.level_ramp_start) * f))
    }

    /// The levels step `step` trains (`StepSettings::active_levels`): the coarse-to-fine ramp's
    /// value, lowered to a prefix of the layers on the steps nested dropout picks (drawn from the
    /// seed and the step alone, so a resumed run drops the same steps).
    pub fn step_levels(&self, step: usize) -> Option<f32> {
        self.nested_levels(step).0
    }

    /// The main field's and the proposal field's levels step `step` trains
    /// (`StepSettings::active_levels`, `proposal_levels`): the proposal's finer levels drop with
    /// the same layers, as a player holding those layers has none of them.
    pub fn nested_levels(&self, step: usize) -> (Option<f32>, Option<f32>) {
        let ramp = self.active_levels(step);
        if self.nested_dropout <= 0.0 || self.nested_dropout_layers < 2 {
            return (ramp, None);
        }
        let mut rng = Rng::stream(self.seed ^ 0x4E57_D000, step as u64);
        if rng.f32() >= self.nested_dropout {
            return (ramp, None);
        }
        let enc = &self.model.field.encoding;
        let levels = enc.grid3.levels.max(enc.grid4.levels);
        let n = msth_core::layers::layer_count(levels, self.nested_dropout_layers);
        if n < 2 {
            return (ramp, None);
        }
        let k = 1 + rng.below(n as u64 - 1) as usize;
        let prefix = msth_core::layers::level_end(levels, n, k - 1) as f32;
        let prop = &self.model.proposal.encoding;
        let prop_levels = prop.grid3.levels.max(prop.grid4.levels);
        let prop_prefix = msth_core::layers::level_end(prop_levels, n, k - 1) as f32;
        (
            Some(ramp.map_or(prefix, |r| r.min(prefix))),
            Some(prop_prefix),
        )
    }

    pub fn validate(&self) -> Result<(), SettingsError> {
        if self.iters == 0 {
            return Err(SettingsError::Invalid("iters must be at least 1".into()));
        }
        if !(self.level_ramp_start > 0.0 && self.level_ramp_start <= 1.0) {
            return Err(SettingsError::Invalid(format!(
                "level_ramp_start must be in (0, 1] (got {})",
                self.level_ramp_start
            )));
        }
        if !(self.nested_dropout.is_finite() && (0.0..=1.0).contains(&self.nested_dropout)) {
            return Err(SettingsError::Invalid(format!(
                "nested_dropout must be in [0, 1] (got {})",
                self.nested_dropout
            )));
        }
        if !(2..=msth_core::layers::MAX_LAYERS).contains(&self.nested_dropout_layers) {
            return Err(SettingsError::Invalid(format!(
                "nested_dropout_layers must be in 2..={} (got {})",
                msth_core::layers::MAX_LAYERS,
                self.nested_dropout_layers
            )));
        }
        if !(1..=1 << 22).contains(&self.batch_rays) || !(1..=1 << 16).contains(&self.chunk_rays) {
            return Err(SettingsError::Invalid(
                "batch_rays must be in 1..=4194304 and chunk_rays in 1..=65536".into(),
            ));
        }
        for (n, v) in [
            ("adam.lr", self.adam.lr),
            ("adam.lr_final", self.adam.lr_final),
            ("adam.eps", self.adam.eps),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(SettingsError::Invalid(format!(
                    "{n} must be finite and positive"
                )));
            }
        }
        for (n, v) in [
            ("interlevel_weight", self.interlevel_weight),
            ("distortion_weight", self.distortion_weight),
            ("mask_loss_weight", self.mask_loss_weight),
            ("mask_lr_scale", self.mask_lr_scale),
            ("sample_mask_weight", self.sample_mask_weight),
            ("sample_mask_moving_std", self.sample_mask_moving_std),
            ("proposal_lr_scale", self.proposal_lr_scale),
            ("free_space_weight", self.free_space_weight),
            ("distortion_late_weight", self.distortion_late_weight),
            ("grid_decay", self.grid_decay),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(SettingsError::Invalid(format!(
                    "{n} must be finite and >= 0"
                )));
            }
        }
        if !(self.scene_scale.is_finite() && self.scene_scale > 0.0) {
            return Err(SettingsError::Invalid(format!(
                "scene_scale must be finite and positive (got {})",
                self.scene_scale
            )));
        }
        if !(self.converge_min_gain_db.is_finite() && self.converge_min_gain_db >= 0.0) {
            return Err(SettingsError::Invalid(format!(
                "converge_min_gain_db must be finite and >= 0 (got {})",
                self.converge_min_gain_db
            )));
        }
        if self.eval_stride == 0 {
            return Err(SettingsError::Invalid(
                "eval_stride must be at least 1".into(),
            ));
        }
        if !(self.checkpoint_secs.is_finite() && self.checkpoint_secs >= 0.0) {
            return Err(SettingsError::Invalid(format!(
                "checkpoint_secs must be finite and >= 0 (got {})",
                self.checkpoint_secs
            )));
        }
        self.mask_learning.validate()?;
        self.sampling.validate()?;
        if self.mask_learning.uncertainty && !self.model.field.encoding.blend.uses_h3() {
            return Err(SettingsError::Invalid(
                "mask_learning.uncertainty needs a 3D grid (its static branch decodes h3 alone)"
                    .into(),
            ));
        }
        self.model.validate().map_err(SettingsError::Model)
    }
}

/// [`TrainSettings::converge_min_gain_db`] by default: 0.1 dB per measurement.
pub const DEFAULT_MIN_GAIN_DB: f64 = 0.1;

fn default_min_gain() -> f64 {
    DEFAULT_MIN_GAIN_DB
}

/// Whether a run whose held-out PSNR was measured at the points of `curve` (step, dB), at equal
/// intervals, has converged: the last measurement gained less than `min_gain_db` over the one
/// before (a NaN counts as no gain).
pub fn converged(curve: &[(usize, f64)], min_gain_db: f64) -> bool {
    match curve {
        // NaN gains compare as nothing: converged.
        [.., (_, a), (_, b)] => (b - a).partial_cmp(&min_gain_db).is_none_or(|o| o.is_lt()),
        _ => false,
    }
}

fn one() -> f32 {
    1.0
}

fn merge(
    dst: &mut serde_json::Value,
    src: serde_json::Value,
    path: &str,
) -> Result<(), SettingsError> {
    match src {
        serde_json::Value::Object(map) => {
            for (k, v) in map {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                let slot = dst
                    .get_mut(&k)
                    .ok_or_else(|| SettingsError::UnknownConfigKey(p.clone()))?;
                if v.is_object() && slot.is_object() {
                    merge(slot, v, &p)?;
                } else {
                    *slot = v;
                }
            }
            Ok(())
        }
        other => {
            *dst = other;
            Ok(())
        }
    }
}

/// The mask-learning share of a step's loss, `lambda * mean L_u - gamma * I` (0 when off).
pub fn mask_learning_loss(ml: &MaskLearningConfig, l: &ChunkLosses) -> f64 {
    let rays = l.rays.max(1) as f64;
    let mut loss = 0.0;
    if ml.uncertainty {
        loss += ml.uncertainty_weight as f64 * l.uncertainty / rays;
    }
    if ml.mine {
        loss -= ml.mine_weight as f64 * l.mine / rays;
    }
    loss
}

/// Reported after each step. The trainer prints nothing itself: what it has to tell (its notes)
/// travels here, and the caller (the cli) shows it.
#[derive(Clone, Debug)]
pub struct Progress {
    /// Notes about the run (for example the sampler falling back to uniform sampling), given
    /// once, with the first step reported; empty otherwise.
    pub notes: Vec<String>,
    pub step: usize,
    pub iters: usize,
    pub loss: f32,
    /// The weighted terms that sum to `loss`, per ray: colour, interlevel (proposal), distortion,
    /// and the mask terms (per-sample mask loss and any mask-learning objective).
    pub terms: LossTerms,
    /// PSNR of the batch's colours.
    pub psnr: f32,
    pub elapsed_secs: f64,
    pub field_samples_per_sec: f64,
    /// The held-out PSNR measured at this step ([`TrainSettings::converge_every`]), if any.
    pub held_out_psnr: Option<f64>,
}

/// The weighted terms of a step's loss ([`Progress::terms`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LossTerms {
    pub rgb: f32,
    pub interlevel: f32,
    pub distortion: f32,
    pub mask: f32,
    /// The free-space loss (0 when off).
    pub free_space: f32,
}

#[derive(Clone, Debug)]
pub struct TrainOutcome {
    pub checkpoint: PathBuf,
    pub steps: usize,
    pub train_seconds: f64,
    pub field_samples_per_sec: f64,
    pub rays_per_sec: f64,
    pub last_loss: f32,
    /// The held-out PSNR measured every [`TrainSettings::converge_every`] steps: (step, dB).
    pub held_out: Vec<(usize, f64)>,
    /// Whether the run stopped because the held-out PSNR stopped gaining ([`converged`]).
    pub converged: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("invalid settings: {0}")]
    Settings(SettingsError),
    #[error("invalid settings: {0}")]
    Sampling(SamplingError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// Writing a checkpoint failed (a full disk, say); the file there before is untouched.
    /// (The message carries the cause, so it is not also chained as a source.)
    #[error("writing the checkpoint of step {step} failed: {error}; {kept}")]
    Save {
        step: usize,
        error: CheckpointError,
        /// What is on disk instead: the previous checkpoint, unchanged, or none.
        kept: String,
    },
    #[error("training diverged at step {step}: {what} is not finite; the last good checkpoint is {last_good}")]
    Diverged {
        step: usize,
        what: String,
        last_good: String,
    },
    #[error("the dataset has no training views")]
    NoData,
    #[error("a training batch: {0}")]
    Batch(String),
    #[error(transparent)]
    Device(#[from] DeviceError),
    #[error("measuring the held-out PSNR: {0}")]
    Eval(std::io::Error),
}

/// The slices of the main field's hash tables under `grid_decay` (its 3D and 4D tables), with
/// the gradient of [`grid_decay_loss`]: `2 * grid_decay / (rows * features) * x`.
fn grid_decay_slices(settings: &TrainSettings, layout: &ModelLayout) -> Vec<ScaledSlice> {
    if settings.grid_decay == 0.0 {
        return Vec::new();
    }
    decayed_grids(layout)
        .map(|(range, slots)| ScaledSlice {
            range,
            weight: 0.0,
            lr_scale: 1.0,
            decay: 2.0 * settings.grid_decay / slots as f32,
        })
        .collect()
}

/// The main field's hash tables that `grid_decay` acts on: each table's parameter range and the
/// floats of one full level (`rows * features`, the table size of a hashed level).
fn decayed_grids(layout: &ModelLayout) -> impl Iterator<Item = (Range<usize>, usize)> + '_ {
    let enc = &layout.field.encoding;
    [enc.h3.as_ref(), enc.h4.as_ref()]
        .into_iter()
        .flatten()
        .map(|(g, r)| (r.clone(), g.table_size * g.features))
}

/// The weight decay of the hash tables (Zip-NeRF's): `grid_decay * sum_levels mean(x^2)` over
/// the main field's 3D and 4D tables, each level's mean taken over a full table's rows (a dense
/// coarse level's unused rows count as zeros). It pulls toward zero the rows that few training
/// rays reach, where the field would otherwise keep what it fitted to one view
/// (docs/convergence.md, "Weight decay on the hash tables").
pub fn grid_decay_loss(settings: &TrainSettings, layout: &ModelLayout, params: &[f32]) -> f64 {
    decayed_grids(layout)
        .map(|(range, slots)| {
            let sum: f64 = params[range].iter().map(|&x| (x as f64) * (x as f64)).sum();
            settings.grid_decay as f64 * sum / slots as f64
        })
        .sum()
}

/// The state of a run: parameters, optimiser, workers' buffers.
pub struct Trainer {
    pub settings: TrainSettings,
    pub layout: ModelLayout,
    pub params: Vec<f32>,
    pub adam: Adam,
    pub step: usize,
    slices: Vec<ScaledSlice>,
    /// Training-only parameters of mask learning (uncertainty grid, MINE network) with their
    /// own optimiser state; never exported, not part of the checkpoint.
    pub aux: Option<AuxState>,
    workers: Vec<Worker>,
    /// Fraction of the time budget used (0 without a time limit); the learning rate follows
    /// whichever of steps and time is further along, so a time-limited run still decays fully.
    pub time_fraction: f32,
    /// The model on a GPU, when the steps run there ([`Trainer::use_device`]).
    gpu: Option<GpuTraining>,
}

/// One worker's scratch and gradient buffers. The gradients are zero between steps: a step
/// accumulates into them and `Adam::update_summed_and_clear` clears them.
struct Worker {
    ws: Workspace,
    grad: Vec<f32>,
    aux_grad: Vec<f32>,
}

/// The auxiliary parameters of mask learning and their Adam state.
pub struct AuxState {
    pub layout: AuxLayout,
    pub params: Vec<f32>,
    pub adam: Adam,
}

impl Trainer {
    pub fn new(settings: TrainSettings) -> Result<Self, TrainError> {
        settings.validate().map_err(TrainError::Settings)?;
        let layout = ModelLayout::new(&settings.model);
        let params = layout.init_params(settings.seed);
        let adam = Adam::new(params.len());
        Ok(Self::assemble(settings, layout, params, adam, 0))
    }

    /// Continues from a checkpoint (its model configuration wins over `settings.model`).
    pub fn resume(mut settings: TrainSettings, ckpt: Checkpoint) -> Result<Self, TrainError> {
        settings.model = ckpt.header.model.clone();
        settings.validate().map_err(TrainError::Settings)?;
        let layout = ModelLayout::new(&settings.model);
        let n = ckpt.params.len();
        let adam = ckpt.adam.unwrap_or_else(|| Adam::new(n));
        Ok(Self::assemble(
            settings,
            layout,
            ckpt.params,
            adam,
            ckpt.header.step as usize,
        ))
    }

    fn assemble(
        settings: TrainSettings,
        layout: ModelLayout,
        params: Vec<f32>,
        adam: Adam,
        step: usize,
    ) -> Self {
        let aux = settings.mask_learning.enabled().then(|| {
            let layout = AuxLayout::new(&settings.mask_learning);
            let params = layout.init_params(settings.seed);
            let adam = Adam::new(params.len());
            AuxState {
                layout,
                params,
                adam,
            }
        });
        let aux_len = aux.as_ref().map_or(0, |a| a.params.len());
        let workers_n = rayon::current_num_threads().max(1);
        let workers = (0..workers_n)
            .map(|_| Worker {
                ws: Workspace::default(),
                grad: vec![0.0; params.len()],
                aux_grad: vec![0.0; aux_len],
            })
            .collect();
        let slices = layout
            .params
            .entries
            .iter()
            .filter(|e| e.name.ends_with(".mask"))
            .map(|e| ScaledSlice {
                range: e.range(),
                weight: settings.mask_loss_weight,
                lr_scale: settings.mask_lr_scale,
                decay: 0.0,
            })
            .chain(
                layout
                    .params
                    .entries
                    .iter()
                    .filter(|e| {
                        settings.proposal_lr_scale != 1.0
                            && e.name.starts_with("proposal.")
                            && !e.name.ends_with(".mask")
                    })
                    .map(|e| ScaledSlice {
                        range: e.range(),
                        weight: 0.0,
                        lr_scale: settings.proposal_lr_scale,
                        decay: 0.0,
                    }),
            )
            .chain(grid_decay_slices(&settings, &layout))
            .collect();
        Trainer {
            settings,
            layout,
            params,
            adam,
            step,
            slices,
            aux,
            workers,
            time_fraction: 0.0,
            gpu: None,
        }
    }

    /// Runs the following steps on `device`; returns a line that says where they run. A GPU
    /// takes the parameters and Adam's state as they are now. Errors (`gpu`; `auto` falls back
    /// to the CPU and says why): no adapter, a model or batch the adapter's limits refuse
    /// (named), or settings the GPU step does not have (uncertainty-guided mask learning).
    pub fn use_device(&mut self, device: TrainDevice) -> Result<String, TrainError> {
        self.sync()?;
        self.gpu = None;
        let Some(dev) = device::open(device)? else {
            return Ok(match device {
                TrainDevice::Auto => {
                    "device: the CPU (auto: no hardware GPU adapter; --device gpu takes a software one)"
                        .to_string()
                }
                _ => "device: the CPU".to_string(),
            });
        };
        if self.aux.is_some() {
            let why = "uncertainty-guided mask learning (mask_learning.uncertainty, mask_learning.mine) is not on the GPU step yet";
            if device == TrainDevice::Auto {
                return Ok(format!("device: the CPU (auto: {why})"));
            }
            return Err(DeviceError::Unsupported(why.into()).into());
        }
        let state = (self.adam.m.clone(), self.adam.v.clone(), self.adam.step);
        let step = match GpuStep::new(
            &dev,
            &self.settings.model,
            &self.params,
            Some(state),
            self.settings.batch_rays,
        ) {
            Ok(s) => s,
            // `auto` is best effort: a model the adapter cannot take trains on the CPU.
            Err(e) if device == TrainDevice::Auto => {
                return Ok(format!(
                    "device: the CPU (auto: {} cannot take this model: {e})",
                    dev.adapter_name()
                ))
            }
            Err(e) => return Err(DeviceError::Gpu(e).into()),
        };
        let line = format!("device: {}", dev.adapter_name());
        self.gpu = Some(GpuTraining {
            dev,
            step,
            stale: false,
        });
        Ok(line)
    }

    /// Whether the steps run on a GPU.
    pub fn on_gpu(&self) -> bool {
        self.gpu.is_some()
    }

    /// Brings the parameters and Adam's state back from the GPU (when the steps run there and
    /// have moved them); `params` and `adam` are then current.
    pub fn sync(&mut self) -> Result<(), TrainError> {
        if let Some(g) = self.gpu.as_mut().filter(|g| g.stale) {
            let read = |e: GpuError| TrainError::Device(DeviceError::Gpu(e));
            self.params = g.step.params(&g.dev).map_err(read)?;
            let (m, v, step) = g.step.adam_state(&g.dev).map_err(read)?;
            self.adam = Adam { m, v, step };
            g.stale = false;
        }
        Ok(())
    }

    fn step_settings(&self, rays: usize) -> StepSettings {
        let s = &self.settings;
        let f = (self.step as f32 / s.anneal_steps.max(1) as f32).min(1.0);
        let (active_levels, proposal_levels) = s.nested_levels(self.step);
        StepSettings {
            anneal: 10.0 * f / (9.0 * f + 1.0),
            interlevel_weight: s.interlevel_weight,
            distortion_weight: s.distortion_weight_at(self.step),
            loss_scale: 1.0 / rays.max(1) as f32,
            sample_mask_weight: s.sample_mask_weight,
            free_space_weight: s.free_space_weight,
            active_levels,
            proposal_levels,
        }
    }

    fn learning_rate(&self) -> f32 {
        let by_steps = self.step as f32 / (self.settings.iters.max(2) - 1) as f32;
        self.settings
            .adam
            .lr_at_fraction(by_steps.max(self.time_fraction))
    }

    /// [`Trainer::step_on`] on the GPU.
    fn step_on_gpu(
        &mut self,
        rays: &[TimedRay],
        targets: &[[f32; 3]],
        backgrounds: Option<&[[f32; 3]]>,
        mask_weights: Option<&[f32]>,
    ) -> Result<ChunkLosses, TrainError> {
        let step_settings = self.step_settings(rays.len());
        let lr = self.learning_rate();
        let s = &self.settings;
        let (jitters, free_points) = device::host_draws(
            rays,
            s.chunk_rays,
            s.seed,
            self.step as u64,
            step_settings.free_space_weight != 0.0,
        );
        let slices: Vec<MaskSlice> = self
            .slices
            .iter()
            .map(|sl| MaskSlice {
                range: sl.range.clone(),
                weight: sl.weight,
                lr_scale: sl.lr_scale,
                decay: sl.decay,
            })
            .collect();
        let hyper = AdamHyper {
            beta1: s.adam.beta1,
            beta2: s.adam.beta2,
            eps: s.adam.eps,
        };
        let Some(g) = self.gpu.as_mut() else {
            return Err(DeviceError::Unsupported("no GPU is set up".into()).into());
        };
        let batch = HostBatch {
            rays,
            targets,
            backgrounds,
            jitters: Some(&jitters),
            free_points: Some(&free_points),
            mask_weights,
        };
        let run = |g: &mut GpuTraining| -> Result<ChunkLosses, GpuError> {
            g.step
                .train_step(&g.dev, &batch, &step_settings, &hyper, lr, &slices)?;
            g.step.losses(&g.dev)
        };
        let l = run(g).map_err(DeviceError::Gpu)?;
        g.stale = true;
        self.step += 1;
        Ok(l)
    }

    /// One optimisation step on the given rays, on the device in use ([`Trainer::use_device`]);
    /// returns the summed chunk losses. `mask_weights`: one factor per ray for the per-sample
    /// mask loss (`train` gives 0 to rays through pixels that change over time:
    /// [`PixelMotion::mask_weights`]); `None` is 1 for every ray. Errors: a GPU's, or factors
    /// that do not match the rays.
    pub fn step_on(
        &mut self,
        rays: &[TimedRay],
        targets: &[[f32; 3]],
        backgrounds: Option<&[[f32; 3]]>,
        mask_weights: Option<&[f32]>,
    ) -> Result<ChunkLosses, TrainError> {
        if mask_weights.is_some_and(|m| m.len() != rays.len()) {
            return Err(TrainError::Batch(format!(
                "{} rays need {} mask-loss factors",
                rays.len(),
                rays.len()
            )));
        }
        if self.gpu.is_some() {
            return self.step_on_gpu(rays, targets, backgrounds, mask_weights);
        }
        Ok(self.step_on_cpu(rays, targets, backgrounds, mask_weights))
    }

    /// [`Trainer::step_on`] on the CPU.
    fn step_on_cpu(
        &mut self,
        rays: &[TimedRay],
        targets: &[[f32; 3]],
        backgrounds: Option<&[[f32; 3]]>,
        mask_weights: Option<&[f32]>,
    ) -> ChunkLosses {
        let step_settings = self.step_settings(rays.len());
        let s = &self.settings;
        let chunk = s.chunk_rays;
        let n_chunks = rays.len().div_ceil(chunk);
        let n_workers = self.workers.len();
        let (cfg, layout, params, seed, step) = (
            &s.model,
            &self.layout,
            &self.params,
            s.seed,
            self.step as u64,
        );
        let ml = &s.mask_learning;
        let aux = self.aux.as_ref();
        let losses: Vec<ChunkLosses> = self
            .workers
            .par_iter_mut()
            .enumerate()
            .map(|(w, worker)| {
                // `worker.grad` and `worker.aux_grad` are zero here: Adam cleared them after
                // the last step.
                let mut acc = ChunkLosses::default();
                let mut c = w;
                while c < n_chunks {
                    let r = c * chunk..((c + 1) * chunk).min(rays.len());
                    let mut rng = device::chunk_stream(seed, step, c);
                    acc += train_chunk_with(
                        cfg,
                        layout,
                        params,
                        &mut worker.grad,
                        &rays[r.clone()],
                        &targets[r.clone()],
                        backgrounds.map(|b| &b[r.clone()]),
                        mask_weights.map(|m| &m[r]),
                        &step_settings,
                        &mut rng,
                        &mut worker.ws,
                        aux.map(|a| AuxStep {
                            cfg: ml,
                            layout: &a.layout,
                            params: &a.params,
                            grad: &mut worker.aux_grad,
                        }),
                    );
                    c += n_workers;
                }
                acc
            })
            .collect();
        let mut total = ChunkLosses::default();
        for l in losses {
            total += l;
        }
        let lr = self.learning_rate();
        // Sum the worker gradients in a fixed order, update, and clear them for the next step.
        let mut grads: Vec<&mut [f32]> = self.workers.iter_mut().map(|w| &mut w.grad[..]).collect();
        self.adam.update_summed_and_clear(
            &self.settings.adam,
            lr,
            &mut self.params,
            &mut grads,
            &self.slices,
        );
        if let Some(aux) = self.aux.as_mut() {
            let mut grads: Vec<&mut [f32]> = self
                .workers
                .iter_mut()
                .map(|w| &mut w.aux_grad[..])
                .collect();
            aux.adam.update_summed_and_clear(
                &self.settings.adam,
                lr,
                &mut aux.params,
                &mut grads,
                &[],
            );
        }
        self.step += 1;
        total
    }

    pub fn checkpoint(&self, data: &Dataset, train_seconds: f64) -> Checkpoint {
        let cameras = playback_cameras_split(data);
        Checkpoint {
            header: CheckpointHeader {
                model: self.settings.model.clone(),
                train: serde_json::to_value(&self.settings).unwrap_or_default(),
                step: self.step as u64,
                dataset: data.name.clone(),
                cameras: cameras.0,
                train_cameras: cameras.1,
                train_seconds,
            },
            params: self.params.clone(),
            adam: Some(self.adam.clone()),
        }
    }
}

/// Distinct camera poses of a dataset, training cameras first, then the held-out ones (at most
/// 64): camera 0 of a checkpoint, and of the `.msth` file exported from it, is the first
/// training camera, the view the players open at.
pub fn playback_cameras(data: &Dataset) -> Vec<Camera> {
    playback_cameras_split(data).0
}

/// [`playback_cameras`] and how many of them (the first ones) are the training views' poses:
/// `None` when the list stopped at 64 before every training pose was in it (monocular data with
/// a pose per frame), so that the list cannot stand for what training saw.
pub fn playback_cameras_split(data: &Dataset) -> (Vec<Camera>, Option<usize>) {
    let listed = |out: &[Camera], v: &Camera| {
        out.iter().any(|c| {
            c.world_from_camera.abs_diff_eq(v.world_from_camera, 1e-5) && c.width == v.width
        })
    };
    let mut out: Vec<Camera> = Vec::new();
    let mut train = None;
    for (k, v) in data.train.iter().chain(&data.test).enumerate() {
        if k == data.train.len() {
            train = Some(out.len());
        }
        if !listed(&out, &v.camera) {
            out.push(v.camera);
        }
        if out.len() >= 64 {
            break;
        }
    }
    // Every training view visited (the loop reached the held-out ones), or every training
    // pose listed before the cap.
    let train = train.or_else(|| {
        data.train
            .iter()
            .all(|v| listed(&out, &v.camera))
            .then_some(out.len())
    });
    (out, train)
}

/// Runs a whole training: `iters` steps (or until the time limit), checkpoints to
/// `out_dir/model.ckpt`, reporting progress after every step. `progress` returns `false` to stop
/// early (the run is checkpointed and can be resumed exactly).
pub fn train(
    data: &Dataset,
    settings: TrainSettings,
    out_dir: &Path,
    resume: Option<Checkpoint>,
    progress: &mut dyn FnMut(&Progress) -> bool,
) -> Result<(Trainer, TrainOutcome), TrainError> {
    if data.train.is_empty() {
        return Err(TrainError::NoData);
    }
    let prior_secs = resume
        .as_ref()
        .map(|c| c.header.train_seconds)
        .unwrap_or(0.0);
    let mut trainer = match resume {
        Some(c) => Trainer::resume(settings, c)?,
        None => Trainer::new(settings)?,
    };
    std::fs::create_dir_all(out_dir).map_err(|source| CheckpointError::Io {
        path: out_dir.to_path_buf(),
        source,
    })?;
    let ckpt_path = out_dir.join("model.ckpt");
    // Mask learning's own state lives next to the checkpoint (never in it: the codec reads the
    // checkpoint's buffer). A resumed run continues it when it belongs to the same step.
    let aux_path = out_dir.join("model.aux");
    // The state of the checkpoint being written: `model.aux.next` is written before the
    // checkpoint and renamed onto `model.aux` after it, so one of the two always belongs to the
    // checkpoint on disk, wherever a crash stops the sequence.
    let aux_next = out_dir.join("model.aux.next");
    remove_stale_temporaries(out_dir, &["model.ckpt", "model.aux", "model.aux.next"]);
    if let Some(aux) = trainer.aux.as_mut() {
        if trainer.step > 0 && (aux_path.exists() || aux_next.exists()) {
            let mut found = None;
            for p in [&aux_path, &aux_next].into_iter().filter(|p| p.exists()) {
                let a = AuxCheckpoint::load(p, aux.params.len())?;
                if a.step == trainer.step as u64 {
                    found = Some(Ok(a));
                    break;
                }
                found.get_or_insert(Err((p.clone(), a.step)));
            }
            match found {
                Some(Ok(a)) => {
                    aux.params = a.params;
                    aux.adam = a.adam;
                }
                Some(Err((path, aux_step))) => {
                    return Err(CheckpointError::Format {
                        path,
                        reason: CheckpointFormatError::StepMismatch {
                            aux_step,
                            step: trainer.step,
                        },
                    }
                    .into())
                }
                None => {}
            }
        }
    }
    let mut saved = on_disk(&ckpt_path, trainer.step);
    let mut last_good = match saved {
        Some(_) => ckpt_path.display().to_string(),
        None => "none (no checkpoint was written yet)".into(),
    };
    let iters = trainer.settings.iters;
    let batch = trainer.settings.batch_rays;
    let time_limit = trainer.settings.time_limit_secs;
    // Each step's batch depends only on the seed and the step, so a resumed run sees the same
    // batches as an uninterrupted one.
    let batch_seed = trainer.settings.seed ^ 0xBA7C_0000;
    let sampler =
        RaySampler::new(data, &trainer.settings.sampling).map_err(TrainError::Sampling)?;
    let mut notes: Vec<String> = sampler.note.iter().cloned().collect();
    // The per-sample mask loss spares rays through pixels that change over time.
    let moving_std = trainer.settings.sample_mask_moving_std;
    let motion = if trainer.settings.sample_mask_weight > 0.0 && moving_std > 0.0 {
        PixelMotion::new(data, &sampler).map_err(TrainError::Sampling)?
    } else {
        None
    };
    if let Some(m) = &motion {
        notes.push(format!(
            "per-sample mask loss: spares rays through the {:.1}% of training pixels whose colour changes over time (temporal std > {moving_std})",
            100.0 * m.moving_share(moving_std)
        ));
    }
    let mut pixels: Vec<[u32; 3]> = Vec::with_capacity(if motion.is_some() { batch } else { 0 });
    let mut mask_weights: Vec<f32> = Vec::new();
    let device = trainer.settings.device;
    let device_line = trainer.use_device(device)?;
    if device != TrainDevice::Cpu {
        notes.push(device_line);
    }
    let mut rays = Vec::with_capacity(batch);
    let mut targets = Vec::with_capacity(batch);
    let use_bg = trainer.settings.random_background && data.train.iter().any(|v| v.alpha.is_some());
    let mut backgrounds = Vec::with_capacity(if use_bg { batch } else { 0 });
    let start = Instant::now();
    let mut last_save = Instant::now();
    let mut samples = 0usize;
    let mut steps_run = 0usize;
    let mut last_loss = f32::NAN;
    let converge_every = trainer.settings.converge_every;
    if converge_every > 0 && data.test.is_empty() {
        return Err(TrainError::Settings(SettingsError::Invalid(
            "converge_every needs held-out views to measure, and the dataset has none".into(),
        )));
    }
    let mut held_out: Vec<(usize, f64)> = Vec::new();
    let mut converged_at = false;
    // Time spent measuring the held-out PSNR: not training time.
    let mut eval_secs = 0.0f64;
    while trainer.step < iters {
        let mut step_rng = Rng::stream(batch_seed, trainer.step as u64);
        let fraction = (trainer.step as f32 / iters.max(1) as f32).max(trainer.time_fraction);
        sampler.sample_batch(
            data,
            batch,
            fraction,
            &mut step_rng,
            &mut rays,
            &mut targets,
            use_bg.then_some(&mut backgrounds),
            trainer.settings.pixel_jitter,
            motion.is_some().then_some(&mut pixels),
        );
        if let Some(m) = &motion {
            m.mask_weights(&pixels, moving_std, &mut mask_weights);
        }
        if time_limit > 0.0 {
            trainer.time_fraction = (start.elapsed().as_secs_f64() / time_limit) as f32;
        }
        let l = trainer.step_on(
            &rays,
            &targets,
            use_bg.then_some(&backgrounds[..]),
            motion.is_some().then_some(&mask_weights[..]),
        )?;
        steps_run += 1;
        samples += l.field_samples;
        let mse = l.sq_err / l.rays.max(1) as f64;
        let per_ray = |v: f64| v / l.rays.max(1) as f64;
        let terms = LossTerms {
            rgb: mse as f32,
            interlevel: (trainer.settings.interlevel_weight as f64 * per_ray(l.interlevel)) as f32,
            distortion: (trainer
                .settings
                .distortion_weight_at(trainer.step.saturating_sub(1))
                as f64
                * per_ray(l.distortion)) as f32,
            mask: (per_ray(l.sample_mask) + mask_learning_loss(&trainer.settings.mask_learning, &l))
                as f32,
            free_space: per_ray(l.free_space) as f32,
        };
        let loss = terms.rgb + terms.interlevel + terms.distortion + terms.mask + terms.free_space;
        if !loss.is_finite() {
            return Err(TrainError::Diverged {
                step: trainer.step,
                what: format!("the loss ({loss})"),
                last_good,
            });
        }
        if let Some(i) = trainer
            .aux
            .as_ref()
            .and_then(|a| a.params.iter().position(|v| !v.is_finite()))
        {
            return Err(TrainError::Diverged {
                step: trainer.step,
                what: format!("mask-learning parameter {i} (uncertainty grid or MINE network)"),
                last_good,
            });
        }
        last_loss = loss;
        let mut measured = None;
        if converge_every > 0 && trainer.step % converge_every == 0 {
            let t = Instant::now();
            trainer.sync()?;
            let m = crate::eval::evaluate(
                data,
                &trainer.settings.model,
                &trainer.layout,
                &trainer.params,
                trainer.settings.eval_stride,
                None,
            )
            .map_err(TrainError::Eval)?;
            held_out.push((trainer.step, m.psnr));
            measured = Some(m.psnr);
            converged_at = converged(&held_out, trainer.settings.converge_min_gain_db);
            eval_secs += t.elapsed().as_secs_f64();
        }
        let elapsed = start.elapsed().as_secs_f64() - eval_secs;
        let keep_going = progress(&Progress {
            notes: std::mem::take(&mut notes),
            step: trainer.step,
            iters,
            loss,
            terms,
            psnr: (-10.0 * mse.max(1e-12).log10()) as f32,
            elapsed_secs: elapsed,
            field_samples_per_sec: samples as f64 / elapsed.max(1e-9),
            held_out_psnr: measured,
        }) && !converged_at;

        let every = trainer.settings.checkpoint_every;
        let every_secs = trainer.settings.checkpoint_secs;
        let out_of_time = (time_limit > 0.0 && elapsed >= time_limit) || !keep_going;
        let at_end = trainer.step >= iters || out_of_time;
        let due = (every > 0 && trainer.step % every == 0)
            || (every_secs > 0.0 && last_save.elapsed().as_secs_f64() >= every_secs);
        if at_end || due {
            trainer.sync()?;
            if let Some(i) = trainer.params.iter().position(|v| !v.is_finite()) {
                let name = trainer
                    .layout
                    .params
                    .entries
                    .iter()
                    .find(|e| (e.offset..e.offset + e.len).contains(&i))
                    .map_or("?", |e| e.name.as_str());
                return Err(TrainError::Diverged {
                    step: trainer.step,
                    what: format!("parameter {i} (of {name})"),
                    last_good,
                });
            }
            let step = trainer.step;
            let failed = |error: CheckpointError| TrainError::Save {
                step,
                error,
                kept: match &saved {
                    Some(k) => format!(
                        "the previous checkpoint {} ({k}) is unchanged",
                        ckpt_path.display()
                    ),
                    None => "no checkpoint was written before".into(),
                },
            };
            if let Some(aux) = &trainer.aux {
                AuxCheckpoint {
                    step: step as u64,
                    params: aux.params.clone(),
                    adam: aux.adam.clone(),
                }
                .save(&aux_next)
                .map_err(failed)?;
            }
            trainer
                .checkpoint(data, prior_secs + elapsed)
                .save(&ckpt_path)
                .map_err(failed)?;
            if trainer.aux.is_some() {
                std::fs::rename(&aux_next, &aux_path)
                    .map_err(|source| CheckpointError::Io {
                        path: aux_path.clone(),
                        source,
                    })
                    .map_err(failed)?;
            }
            saved = Some(format!("step {step}"));
            last_save = Instant::now();
            last_good = ckpt_path.display().to_string();
        }
        if out_of_time {
            break;
        }
    }
    trainer.sync()?;
    let secs = start.elapsed().as_secs_f64() - eval_secs;
    let outcome = TrainOutcome {
        checkpoint: ckpt_path,
        steps: steps_run,
        train_seconds: prior_secs + secs,
        field_samples_per_sec: samples as f64 / secs.max(1e-9),
        rays_per_sec: (steps_run * batch) as f64 / secs.max(1e-9),
        last_loss,
        held_out,
        converged: converged_at,
    };
    Ok((trainer, outcome))
}

/// What the checkpoint at `path` holds when a run starts at `step`: that step when resuming,
/// an earlier run's file, or nothing.
fn on_disk(path: &Path, step: usize) -> Option<String> {
    match (step, path.exists()) {
        (_, false) => None,
        (0, true) => Some("of an earlier run".into()),
        (k, true) => Some(format!("step {k}")),
    }
}

/// Removes the temporary files a run killed while writing left in `dir` (`.NAME.tmp-PID-N` of
/// [`crate::checkpoint::write_atomic`], for each of `names`): a checkpoint-sized file each.
fn remove_stale_temporaries(dir: &Path, names: &[&str]) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let name = name.to_string_lossy();
        if names
            .iter()
            .any(|n| name.starts_with(&format!(".{n}.tmp-")))
        {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_that_name_the_removed_quality_preset_still_read() {
        let data = crate::synth::generate(&crate::synth::SynthConfig {
            width: 8,
            height: 6,
            num_frames: 2,
            num_train_cams: 2,
            supersample: 1,
            ..Default::default()
        });
        let s = TrainSettings::for_preset(Preset::Paper, &data);
        let mut v = serde_json::to_value(&s).unwrap();
        assert_eq!(v["preset"], "paper");
        v["preset"] = "quality".into();
        let back: TrainSettings = serde_json::from_value(v).unwrap();
        assert_eq!(back.preset, Preset::Paper);
        assert_eq!(back.iters, s.iters);
    }

    #[test]
    fn playback_cameras_list_the_training_cameras_first() {
        let data = crate::synth::generate(&crate::synth::SynthConfig {
            width: 8,
            height: 6,
            num_frames: 2,
            num_train_cams: 3,
            supersample: 1,
            ..Default::default()
        });
        assert!(!data.test.is_empty());
        let cams = playback_cameras(&data);
        // The players open at camera 0: a training camera, the held-out one last.
        assert_eq!(cams[0], data.train[0].camera);
        assert_eq!(*cams.last().unwrap(), data.test[0].camera);
        assert_eq!(cams.len(), 4);
        assert_eq!(playback_cameras_split(&data).1, Some(3));
        // More training poses than the list holds: it cannot say what training saw.
        let many = crate::synth::generate(&crate::synth::SynthConfig {
            width: 4,
            height: 3,
            num_frames: 1,
            num_train_cams: 70,
            supersample: 1,
            ..Default::default()
        });
        let (cams, train) = playback_cameras_split(&many);
        assert_eq!((cams.len(), train), (64, None));
        // Exactly as many as it holds, held-out ones after them: all listed.
        let full = crate::synth::generate(&crate::synth::SynthConfig {
            width: 4,
            height: 3,
            num_frames: 1,
            num_train_cams: 64,
            supersample: 1,
            ..Default::default()
        });
        assert_eq!(playback_cameras_split(&full).1, Some(64));
    }

    fn settings() -> TrainSettings {
        let model = ModelConfig::fast_on_white(10);
        TrainSettings::for_model(Preset::Fast, model)
    }

    /// `grid_decay` reaches Adam as slices over the main field's 3D and 4D tables (nothing else),
    /// whose `decay * x` is the gradient of `grid_decay_loss` (central differences); off, no
    /// slice decays.
    #[test]
    fn grid_decay_slices_carry_the_gradient_of_their_loss() {
        let mut s = settings();
        s.grid_decay = 0.0;
        let t = Trainer::new(s.clone()).unwrap();
        assert!(t.slices.iter().all(|sl| sl.decay == 0.0));
        assert_eq!(grid_decay_loss(&s, &t.layout, &t.params), 0.0);
        s.grid_decay = 0.3;
        let t = Trainer::new(s.clone()).unwrap();
        let decayed: Vec<&ScaledSlice> = t.slices.iter().filter(|sl| sl.decay != 0.0).collect();
        let tables: Vec<Range<usize>> = ["field.h3", "field.h4"]
            .iter()
            .map(|n| t.layout.params.get(n).unwrap().range())
            .collect();
        let ranges: Vec<Range<usize>> = decayed.iter().map(|sl| sl.range.clone()).collect();
        assert_eq!(ranges, tables);
        let mut p = t.params.clone();
        let outside = t
            .layout
            .params
            .get("field.density_mlp")
            .unwrap()
            .range()
            .start;
        let mut checked = 0;
        for sl in &decayed {
            for i in [sl.range.start, sl.range.start + 7919, sl.range.end - 1] {
                p[i] = 0.75;
                let h = 1.0 / 64.0; // exact in f32 around 0.75
                p[i] = 0.75 + h;
                let up = grid_decay_loss(&s, &t.layout, &p);
                p[i] = 0.75 - h;
                let down = grid_decay_loss(&s, &t.layout, &p);
                p[i] = 0.75;
                let fd = (up - down) / (2.0 * h as f64);
                let analytic = (sl.decay * 0.75) as f64;
                assert!(
                    (fd - analytic).abs() <= 1e-6 * analytic.abs(),
                    "{fd} {analytic}"
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 6);
        let base = grid_decay_loss(&s, &t.layout, &p);
        p[outside] += 1.0;
        assert_eq!(grid_decay_loss(&s, &t.layout, &p), base);
        for bad in [-0.1, f32::NAN, f32::INFINITY] {
            s.grid_decay = bad;
            assert!(s.validate().is_err(), "{bad}");
        }
    }

    /// The presets sample forward-facing captures (contracted bounds) uniformly and
    /// object-centred scenes (boxes) with the paper's dynamics-aware sampler, in every preset;
    /// `--set sampling.mode` still overrides either. Every preset anneals over at least
    /// `MIN_ANNEAL_STEPS` on a forward-facing capture; `fast` on an object over a quarter of
    /// its run. Forward-facing captures get the coarse-to-fine schedule and the free-space loss;
    /// objects neither.
    #[test]
    fn the_presets_follow_the_scene_bounds() {
        let stage = SceneBounds::Contracted {
            center: glam::Vec3::ZERO,
            radius: 4.0,
        };
        let bg = Background::Color { rgb: [0.0; 3] };
        for preset in [Preset::Fast, Preset::Balanced, Preset::Paper] {
            let object = ModelConfig::preset(preset, SceneBounds::dnerf_default(), bg, 10);
            let s = TrainSettings::for_model(preset, object);
            assert_eq!(s.sampling.mode, SamplingMode::Dynamics, "{preset:?}");
            assert_eq!((s.level_ramp_steps, s.free_space_weight), (0, 0.0));
            assert_eq!(s.grid_decay, 0.0);
            assert_eq!(s.active_levels(0), None);
            assert_eq!(s.distortion_weight_at(100_000), s.distortion_weight);
            if preset == Preset::Fast {
                assert_eq!(s.anneal_steps, s.iters / 4);
            } else {
                assert!(s.anneal_steps >= MIN_ANNEAL_STEPS);
            }
            let forward = ModelConfig::preset(preset, stage, bg, 10);
            let mut s = TrainSettings::for_model(preset, forward);
            assert_eq!(s.sampling.mode, SamplingMode::Uniform, "{preset:?}");
            assert!(s.anneal_steps >= MIN_ANNEAL_STEPS, "{preset:?}");
            // Coarse-to-fine: half the levels at step 0, linear, all from the ramp's end on.
            assert_eq!((s.level_ramp_steps, s.free_space_weight), (300, 1e-3));
            assert_eq!(s.grid_decay, 0.3);
            let levels = s.model.field.encoding.grid3.levels as f32;
            assert_eq!(s.active_levels(0), Some(0.5 * levels));
            assert_eq!(s.active_levels(150), Some(0.75 * levels));
            assert_eq!(s.active_levels(300), None);
            // The distortion loss: the common weight until the ramp, then linear to its end.
            assert_eq!(s.distortion_weight_at(300), s.distortion_weight);
            let mid = s.distortion_weight_at(450);
            assert!(
                (mid - 0.5 * (s.distortion_weight + 0.05)).abs() < 1e-6,
                "{mid}"
            );
            assert_eq!(s.distortion_weight_at(600), 0.05);
            assert_eq!(s.distortion_weight_at(100_000), 0.05);
            s.apply_overrides(None, &["sampling.mode=dynamics".into()])
                .unwrap();
            assert_eq!(s.sampling.mode, SamplingMode::Dynamics);
            s.apply_overrides(None, &["level_ramp_start=0".into()])
                .unwrap_err();
        }
    }

    /// Nested dropout: off by default; at probability p about p of the steps train a proper
    /// prefix of the layers (a layer end, below the level count), the same steps for the same
    /// seed, and under the coarse-to-fine ramp the lower of the two.
    #[test]
    fn nested_dropout_trains_prefixes_of_the_layers() {
        let bg = Background::Color { rgb: [0.0; 3] };
        let object = ModelConfig::preset(Preset::Fast, SceneBounds::dnerf_default(), bg, 10);
        let mut s = TrainSettings::for_model(Preset::Fast, object);
        assert!((0..200).all(|step| s.step_levels(step).is_none()));
        s.apply_overrides(None, &["nested_dropout=0.5".into()])
            .unwrap();
        let levels = s.model.field.encoding.grid3.levels;
        let ends = msth_core::layers::layer_level_ends(levels, s.nested_dropout_layers);
        let picked: Vec<(usize, f32)> = (0..1000)
            .filter_map(|step| s.step_levels(step).map(|a| (step, a)))
            .collect();
        assert!((400..600).contains(&picked.len()), "{}", picked.len());
        for &(_, a) in &picked {
            assert!(ends[..ends.len() - 1].contains(&(a as usize)), "{a}");
            assert_eq!(a.fract(), 0.0);
        }
        for k in 0..ends.len() - 1 {
            assert!(
                picked.iter().any(|&(_, a)| a as usize == ends[k]),
                "prefix {k}"
            );
        }
        // The proposal's levels drop with the same layers (5 levels in 4 layers: 2, 3, 4).
        let prop = s.model.proposal.encoding.grid3.levels;
        for &(step, a) in &picked {
            let k = ends.iter().position(|&e| e == a as usize).unwrap();
            let want = msth_core::layers::level_end(prop, ends.len(), k) as f32;
            assert_eq!(s.nested_levels(step).1, Some(want));
        }
        assert!((0..1000)
            .filter(|step| !picked.iter().any(|p| p.0 == *step))
            .all(|step| s.nested_levels(step).1.is_none()));
        let again: Vec<Option<f32>> = (0..1000).map(|step| s.step_levels(step)).collect();
        assert!(picked.iter().all(|&(step, a)| again[step] == Some(a)));
        s.level_ramp_steps = 1000;
        s.level_ramp_start = 0.5;
        for step in 0..1000 {
            let ramp = s.active_levels(step).unwrap();
            let got = s.step_levels(step).unwrap();
            assert!(got <= ramp);
            if let Some(&(_, a)) = picked.iter().find(|p| p.0 == step) {
                assert_eq!(got, a.min(ramp));
            }
        }
        s.apply_overrides(None, &["nested_dropout=1.5".into()])
            .unwrap_err();
        s.nested_dropout = 0.5;
        s.apply_overrides(None, &["nested_dropout_layers=1".into()])
            .unwrap_err();
    }

    #[test]
    fn config_file_and_set_override_any_knob() {
        let mut s = settings();
        let file = serde_json::json!({
            "iters": 77,
            "model": {"sampler": {"num_samples": 16}, "field": {"encoding": {"blend": "mst"}}}
        });
        s.apply_overrides(
            Some(file),
            &[
                "batch_rays=512".into(),
                "model.field.encoding.grid3.levels=8".into(),
                "model.field.encoding.grid4.levels=8".into(),
            ],
        )
        .unwrap();
        assert_eq!(s.iters, 77);
        assert_eq!(s.batch_rays, 512);
        assert_eq!(s.model.sampler.num_samples, 16);
        assert_eq!(s.model.field.encoding.grid3.levels, 8);
        assert_eq!(
            s.model.field.encoding.blend,
            msth_core::config::BlendMode::Mst
        );
        // Other knobs keep the preset's values.
        assert_eq!(s.adam, AdamConfig::default());
    }

    #[test]
    fn converged_means_the_last_measurement_gained_too_little() {
        assert!(!converged(&[], 0.1));
        assert!(!converged(&[(500, 20.0)], 0.1));
        assert!(!converged(&[(500, 20.0), (1000, 20.1)], 0.1));
        assert!(converged(&[(500, 20.0), (1000, 20.09)], 0.1));
        assert!(converged(&[(500, 20.0), (1000, 19.0)], 0.1));
        assert!(converged(&[(500, 20.0), (1000, f64::NAN)], 0.1));
        // Only the last two count.
        assert!(!converged(&[(500, 20.0), (1000, 20.05), (1500, 21.0)], 0.1));
    }

    #[test]
    fn unknown_or_invalid_settings_are_named() {
        let mut s = settings();
        let e = s
            .apply_overrides(Some(serde_json::json!({"modle": {}})), &[])
            .unwrap_err();
        assert!(e.to_string().contains("modle"), "{e}");
        let e = s.apply_overrides(None, &["iters".into()]).unwrap_err();
        assert!(e.to_string().contains("key=value"), "{e}");
        let e = s
            .apply_overrides(None, &["iters=\"many\"".into()])
            .unwrap_err();
        assert!(e.to_string().contains("invalid settings"), "{e}");
        let e = s
            .apply_overrides(None, &["model.sampler.near=-1".into()])
            .unwrap_err();
        assert!(e.to_string().contains("near"), "{e}");
        // Settings that disagree with each other are caught too.
        let e = s
            .apply_overrides(None, &["model.field.encoding.grid3.levels=8".into()])
            .unwrap_err();
        assert!(e.to_string().contains("same number of features"), "{e}");
    }
}
