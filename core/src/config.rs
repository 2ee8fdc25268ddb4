//! Model configuration: what a user sets (grids, mask, blend mode, decoders, sampling, scene) and
//! the presets. Everything derives from these structs; presets are values, never copied code.

use serde::{Deserialize, Serialize};

use crate::grid::{GridConfig, InvalidGrid};
use crate::sampling::Spacing;
use crate::scene::{InvalidBounds, SceneBounds};

/// How the 3D and 4D encodings are combined (method.md §1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BlendMode {
    /// The paper: `m h3 + (1 - m) h4`.
    Mst,
    /// The reference code: `h3 + (1 - m) h4`.
    Mt,
    /// Ablation: `h3 + h4`, no mask.
    Add,
    /// Ablation: `h4` alone.
    FourD,
    /// A static scene: `h3` alone, no 4D table.
    Static,
}

impl BlendMode {
    /// Every mode, in the order of the GPU blend codes (0..4).
    pub const ALL: [BlendMode; 5] = [
        BlendMode::Mst,
        BlendMode::Mt,
        BlendMode::Add,
        BlendMode::FourD,
        BlendMode::Static,
    ];

    pub fn uses_h3(self) -> bool {
        !matches!(self, BlendMode::FourD)
    }
    pub fn uses_h4(self) -> bool {
        !matches!(self, BlendMode::Static)
    }
    pub fn uses_mask(self) -> bool {
        matches!(self, BlendMode::Mst | BlendMode::Mt)
    }

    /// The mask value `m` an encoding without a mask reports: 1 for h3 alone (all static), 0 for
    /// h4 alone, 0.5 for addition, meaning "both". The one home of this constant: the GPU
    /// uniforms (`gpu/src/layout.rs`) and the page (`web/js/renderer.js`) mirror it.
    pub fn no_mask_value(self) -> f32 {
        match self {
            BlendMode::Static => 1.0,
            BlendMode::FourD => 0.0,
            _ => 0.5,
        }
    }

    /// The coefficients `(a, b)` in `enc = a * h3 + b * h4` at mask value `m` (a grid the mode
    /// does not use gets 0).
    pub fn coefficients(self, m: f32) -> (f32, f32) {
        match self {
            BlendMode::Mt => (1.0, 1.0 - m),
            BlendMode::Mst => (m, 1.0 - m),
            BlendMode::Add => (1.0, 1.0),
            BlendMode::FourD => (0.0, 1.0),
            BlendMode::Static => (1.0, 0.0),
        }
    }

    /// Whether a point with mask value `m` needs the 4D grid (its time-dependent part) when
    /// points whose dynamic weight `1 - m` is below `cutoff` skip it, as rendering does
    /// ([`crate::field::EncodingScratch::static_cutoff`]); `has_mask`: the encoding has a mask.
    pub fn is_dynamic(self, has_mask: bool, m: f32, cutoff: f32) -> bool {
        match self {
            BlendMode::Static => false,
            BlendMode::Add | BlendMode::FourD => true,
            BlendMode::Mt | BlendMode::Mst => !has_mask || 1.0 - m >= cutoff,
        }
    }
}

/// The masked space-time encoding: a 3D grid, a 4D grid and a dense mask grid.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EncodingConfig {
    pub blend: BlendMode,
    pub grid3: GridConfig,
    pub grid4: GridConfig,
    /// Mask grid resolution per axis (vertices).
    pub mask_resolution: usize,
    /// Initial mask logit (-1: m = 0.27, as the reference code).
    pub mask_init: f32,
}

impl EncodingConfig {
    /// Sets the level count, table size and finest spatial resolution of both grids and the mask
    /// resolution (time resolutions and the base stay): the quick way to a small model.
    pub fn resize(
        &mut self,
        levels: usize,
        log2_table_size: u32,
        finest: f32,
        mask_resolution: usize,
    ) {
        for g in [&mut self.grid3, &mut self.grid4] {
            g.levels = levels;
            g.log2_table_size = log2_table_size;
            for r in g.finest_resolution.iter_mut().take(3) {
                *r = finest;
            }
        }
        self.mask_resolution = mask_resolution;
    }
}

/// The main field: encoding, density MLP (`enc -> hidden -> 1 + geo`), colour MLP
/// (`SH(16) + geo -> hidden x layers -> 3`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldConfig {
    pub encoding: EncodingConfig,
    pub density_hidden: usize,
    pub geo_features: usize,
    pub color_hidden: usize,
    pub color_layers: usize,
}

/// The proposal field: an encoding and a density MLP `enc -> hidden -> 1`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProposalConfig {
    pub encoding: EncodingConfig,
    pub hidden: usize,
}

/// What the renderer does with the transmittance left at the end of a ray.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Background {
    Color {
        rgb: [f32; 3],
    },
    /// The colour of the ray's last sample (the reference code on real scenes).
    LastSample,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SamplerConfig {
    pub num_proposal_samples: usize,
    pub num_samples: usize,
    pub spacing: Spacing,
    /// Closest distance from the camera, world units.
    pub near: f32,
    /// Farthest distance, world units.
    pub far: f32,
    /// Added to every proposal bin before resampling.
    pub histogram_padding: f32,
}

impl SamplerConfig {
    /// Sets the samples per ray: `proposal` for the proposal field, `main` for the main field.
    pub fn set_samples(&mut self, proposal: usize, main: usize) {
        self.num_proposal_samples = proposal;
        self.num_samples = main;
    }
}

/// A named playback level of [`PlaySamples`]: a fraction of the model's proposal and main samples
/// per ray. The page offers the same levels (`web/js/generated/contract.js`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SampleLevel {
    /// The model's own counts, the ones it was trained with.
    Full,
    /// 2/3 of the proposal samples and 3/4 of the main samples.
    Fast,
    /// Half of each.
    Faster,
}

impl SampleLevel {
    pub const ALL: [SampleLevel; 3] = [SampleLevel::Full, SampleLevel::Fast, SampleLevel::Faster];

    pub fn name(self) -> &'static str {
        match self {
            SampleLevel::Full => "full",
            SampleLevel::Fast => "fast",
            SampleLevel::Faster => "faster",
        }
    }

    /// `(numerator, denominator)` of the proposal samples' and the main samples' fraction.
    pub fn fractions(self) -> [(usize, usize); 2] {
        match self {
            SampleLevel::Full => [(1, 1), (1, 1)],
            SampleLevel::Fast => [(2, 3), (3, 4)],
            SampleLevel::Faster => [(1, 2), (1, 2)],
        }
    }
}

/// Samples per ray at play time (`msth play --samples`, `msth eval --samples`, the page's
/// samples menu); by default the counts the file stores (`msth export` chooses them). Fewer samples than the model was trained with trade accuracy for speed; the
/// trade is measured in docs/tradeoff.md ("Samples per ray at play time").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PlaySamples {
    /// The counts the file stores for playback (`.msth` version 3, `play_samples`), or the
    /// model's own when it stores none: what players use unless told otherwise.
    #[default]
    File,
    Level(SampleLevel),
    /// Exact counts: proposal samples, main samples.
    Counts(usize, usize),
}

impl std::str::FromStr for PlaySamples {
    type Err = String;

    /// `file`, `full`, `fast`, `faster` or `P,M` (proposal and main samples per ray).
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "file" {
            return Ok(PlaySamples::File);
        }
        if let Some(l) = SampleLevel::ALL.into_iter().find(|l| l.name() == s) {
            return Ok(PlaySamples::Level(l));
        }
        let parsed = s
            .split_once(',')
            .and_then(|(p, m)| Some((p.trim().parse().ok()?, m.trim().parse().ok()?)));
        match parsed {
            Some((p, m)) if p >= 1 && m >= 1 => Ok(PlaySamples::Counts(p, m)),
            _ => Err(format!(
                "samples {s:?}: file, full, fast, faster or P,M (proposal and main samples per ray, each at least 1)"
            )),
        }
    }
}

impl PlaySamples {
    /// The proposal and main samples per ray for a model whose sampler is `model` in a file
    /// that stores `stored` for playback: a level's fraction of each of the model's counts,
    /// rounded up (at least 1), the exact counts, or `stored` (the model's own when `None`).
    pub fn counts(self, model: &SamplerConfig, stored: Option<(usize, usize)>) -> (usize, usize) {
        match self {
            PlaySamples::File => stored.unwrap_or((model.num_proposal_samples, model.num_samples)),
            PlaySamples::Counts(p, m) => (p, m),
            PlaySamples::Level(l) => {
                let [(pn, pd), (mn, md)] = l.fractions();
                let scale = |n: usize, num: usize, den: usize| (n * num).div_ceil(den).max(1);
                (
                    scale(model.num_proposal_samples, pn, pd),
                    scale(model.num_samples, mn, md),
                )
            }
        }
    }

    /// `model` with its sampler's counts replaced by [`PlaySamples::counts`], checked against
    /// `max_proposal` and `max_main` (the bounds a file's own counts must meet).
    pub fn apply(
        self,
        model: &ModelConfig,
        stored: Option<(usize, usize)>,
        max_proposal: usize,
        max_main: usize,
    ) -> Result<ModelConfig, String> {
        let (p, m) = self.counts(&model.sampler, stored);
        if !(1..=max_proposal).contains(&p) || !(1..=max_main).contains(&m) {
            return Err(format!(
                "samples {p},{m}: proposal samples must lie in 1..={max_proposal} and main samples in 1..={max_main}"
            ));
        }
        let mut out = model.clone();
        out.sampler.set_samples(p, m);
        Ok(out)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    pub field: FieldConfig,
    pub proposal: ProposalConfig,
    pub sampler: SamplerConfig,
    pub bounds: SceneBounds,
    pub background: Background,
    /// Number of time steps the model was trained on (for players and the codec).
    pub num_frames: usize,
}

/// Upper bounds on sizes read from configs and files (checked before allocating).
pub const MAX_SAMPLES_PER_RAY: usize = 4096;
pub const MAX_MLP_WIDTH: usize = 1024;
pub const MAX_MASK_RESOLUTION: usize = 1024;

/// Why [`ModelConfig::validate`] rejected a configuration; the message names the field.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ModelConfigError {
    #[error(transparent)]
    Grid(#[from] InvalidGrid),
    #[error("bounds: {0}")]
    Bounds(InvalidBounds),
    #[error("{0}")]
    Invalid(String),
}

impl ModelConfig {
    /// Checks every value a user or a file could get wrong; the message names the field.
    pub fn validate(&self) -> Result<(), ModelConfigError> {
        for (name, enc) in [
            ("field.encoding", &self.field.encoding),
            ("proposal.encoding", &self.proposal.encoding),
        ] {
            if enc.blend.uses_h3() {
                enc.grid3.validate(&format!("{name}.grid3"))?;
                if enc.grid3.dims() != 3 {
                    return Err(ModelConfigError::Invalid(format!(
                        "{name}.grid3 must have 3 axes"
                    )));
                }
            }
            if enc.blend.uses_h4() {
                enc.grid4.validate(&format!("{name}.grid4"))?;
                if enc.grid4.dims() != 4 {
                    return Err(ModelConfigError::Invalid(format!(
                        "{name}.grid4 must have 4 axes"
                    )));
                }
            }
            if enc.blend.uses_h3()
                && enc.blend.uses_h4()
                && enc.grid3.output_dim() != enc.grid4.output_dim()
            {
                return Err(ModelConfigError::Invalid(format!(
                    "{name}: grid3 and grid4 must produce the same number of features (levels x features): {} vs {}",
                    enc.grid3.output_dim(),
                    enc.grid4.output_dim()
                )));
            }
            if enc.blend.uses_mask() && !(2..=MAX_MASK_RESOLUTION).contains(&enc.mask_resolution) {
                return Err(ModelConfigError::Invalid(format!(
                    "{name}.mask_resolution must be in 2..={MAX_MASK_RESOLUTION} (got {})",
                    enc.mask_resolution
                )));
            }
            if !enc.mask_init.is_finite() {
                return Err(ModelConfigError::Invalid(format!(
                    "{name}.mask_init must be finite"
                )));
            }
        }
        let f = &self.field;
        for (n, v) in [
            ("field.density_hidden", f.density_hidden),
            ("field.color_hidden", f.color_hidden),
            ("field.geo_features", f.geo_features),
            ("proposal.hidden", self.proposal.hidden),
        ] {
            if v == 0 || v > MAX_MLP_WIDTH {
                return Err(ModelConfigError::Invalid(format!(
                    "{n} must be in 1..={MAX_MLP_WIDTH} (got {v})"
                )));
            }
        }
        if f.color_layers == 0 || f.color_layers > 8 {
            return Err(ModelConfigError::Invalid(format!(
                "field.color_layers must be in 1..=8 (got {})",
                f.color_layers
            )));
        }
        let s = &self.sampler;
        if !(1..=MAX_SAMPLES_PER_RAY).contains(&s.num_samples)
            || !(1..=MAX_SAMPLES_PER_RAY).contains(&s.num_proposal_samples)
        {
            return Err(ModelConfigError::Invalid(format!(
                "sampler: num_samples and num_proposal_samples must be in 1..={MAX_SAMPLES_PER_RAY}"
            )));
        }
        if !(s.near.is_finite() && s.far.is_finite() && s.near >= 0.0 && s.far > s.near) {
            return Err(ModelConfigError::Invalid(format!(
                "sampler: need 0 <= near < far, finite (got {} .. {})",
                s.near, s.far
            )));
        }
        if !(s.histogram_padding.is_finite() && s.histogram_padding >= 0.0) {
            return Err(ModelConfigError::Invalid(
                "sampler.histogram_padding must be finite and >= 0".into(),
            ));
        }
        self.bounds.validate().map_err(ModelConfigError::Bounds)?;
        if let Background::Color { rgb } = self.background {
            if !rgb.iter().all(|v| v.is_finite()) {
                return Err(ModelConfigError::Invalid(
                    "background colour must be finite".into(),
                ));
            }
        }
        if self.num_frames == 0 {
            return Err(ModelConfigError::Invalid(
                "num_frames must be at least 1".into(),
            ));
        }
        Ok(())
    }
}

/// Named size presets. `Paper` is method.md's configuration (2^19 rows, 16 levels, 128^3 mask,
/// 128 -> 48 samples); the others trade accuracy for speed on a CPU.
///
/// There was a `quality` preset: the paper's model trained for half the paper's steps. Both
/// converged trade-off studies (docs/tradeoff.md) found it dominated, so it was removed; settings
/// and checkpoints that name it still read, as `Paper`, whose model it shares.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    Fast,
    Balanced,
    #[serde(alias = "quality")]
    Paper,
}

/// A preset name that [`Preset`]'s `FromStr` does not know.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum UnknownPreset {
    #[error("unknown preset `{0}` (expected fast, balanced or paper)")]
    Unknown(String),
    #[error(
        "the `quality` preset was removed: balanced matched or beat it on every measured scene, \
         smaller and faster to train (docs/tradeoff.md); use `balanced`, or `paper` for the \
         same model as quality"
    )]
    Removed,
}

impl std::str::FromStr for Preset {
    type Err = UnknownPreset;
    fn from_str(s: &str) -> Result<Self, UnknownPreset> {
        match s {
            "fast" => Ok(Preset::Fast),
            "balanced" => Ok(Preset::Balanced),
            "paper" => Ok(Preset::Paper),
            "quality" => Err(UnknownPreset::Removed),
            _ => Err(UnknownPreset::Unknown(s.to_string())),
        }
    }
}

fn grid(levels: usize, log2: u32, base: f32, finest: f32) -> GridConfig {
    GridConfig {
        levels,
        features_per_level: 2,
        log2_table_size: log2,
        base_resolution: vec![base; 3],
        finest_resolution: vec![finest; 3],
    }
}

fn grid4(
    levels: usize,
    log2: u32,
    base: f32,
    finest: f32,
    base_t: f32,
    finest_t: f32,
) -> GridConfig {
    GridConfig {
        levels,
        features_per_level: 2,
        log2_table_size: log2,
        base_resolution: vec![base, base, base, base_t],
        finest_resolution: vec![finest, finest, finest, finest_t],
    }
}

impl ModelConfig {
    /// A model for `preset`, a scene and a frame count. The time resolution follows the frame
    /// count: the finest time resolution is `max(num_frames, 2)`, the coarsest `min(15, finest)`
    /// (method.md: 15 -> 300 for 300 frames).
    pub fn preset(
        preset: Preset,
        bounds: SceneBounds,
        background: Background,
        num_frames: usize,
    ) -> Self {
        let frames = num_frames.max(1) as f32;
        let finest_t = frames.max(2.0);
        let base_t = finest_t.min(15.0);
        let (levels, log2, finest, mask_res, np, nf, log2_prop, hidden_c) = match preset {
            Preset::Fast => (12, 15, 512.0, 64, 48, 24, 14, 64),
            Preset::Balanced => (16, 17, 1024.0, 96, 96, 32, 16, 64),
            Preset::Paper => (16, 19, 2048.0, 128, 128, 48, 18, 64),
        };
        let (spacing, near, far) = match bounds {
            SceneBounds::Box { .. } => (Spacing::Linear, 0.0, 1e4),
            SceneBounds::Contracted { radius, .. } => {
                (Spacing::LinDisp, 0.05 * radius, 1000.0 * radius)
            }
        };
        let prop_finest_t = finest_t.min(150.0);
        let prop_base_t = base_t.min(prop_finest_t);
        ModelConfig {
            field: FieldConfig {
                encoding: EncodingConfig {
                    blend: BlendMode::Mt,
                    grid3: grid(levels, log2, 16.0, finest),
                    grid4: grid4(levels, log2, 16.0, finest, base_t, finest_t),
                    mask_resolution: mask_res,
                    mask_init: -1.0,
                },
                density_hidden: 64,
                geo_features: 15,
                color_hidden: hidden_c,
                color_layers: 2,
            },
            proposal: ProposalConfig {
                encoding: EncodingConfig {
                    blend: BlendMode::Mt,
                    grid3: grid(5, log2_prop, 16.0, 128.0),
                    grid4: grid4(5, log2_prop, 16.0, 128.0, prop_base_t, prop_finest_t),
                    mask_resolution: 64,
                    mask_init: -1.0,
                },
                hidden: 16,
            },
            sampler: SamplerConfig {
                num_proposal_samples: np,
                num_samples: nf,
                spacing,
                near,
                far,
                histogram_padding: 0.01,
            },
            bounds,
            background,
            num_frames: num_frames.max(1),
        }
    }

    /// The fast preset over [`SceneBounds::dnerf_default`] on a white background (D-NeRF's
    /// synthetic scenes), `num_frames` frames: where the small models of tests, examples and
    /// benches start before [`EncodingConfig::resize`] and [`ModelConfig::resize_mlps`].
    pub fn fast_on_white(num_frames: usize) -> Self {
        let white = Background::Color { rgb: [1.0; 3] };
        Self::preset(
            Preset::Fast,
            SceneBounds::dnerf_default(),
            white,
            num_frames,
        )
    }

    /// Sets the MLP widths: `hidden` for the main field's density and colour MLPs,
    /// `proposal_hidden` for the proposal's density MLP (the geometry features and the colour
    /// layers stay): the MLP half of cutting a model down, next to [`EncodingConfig::resize`].
    pub fn resize_mlps(&mut self, hidden: usize, proposal_hidden: usize) {
        self.field.density_hidden = hidden;
        self.field.color_hidden = hidden;
        self.proposal.hidden = proposal_hidden;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn play_samples_parse_scale_and_bound_the_counts() {
        let white = Background::Color { rgb: [1.0; 3] };
        let fast = ModelConfig::preset(Preset::Fast, SceneBounds::dnerf_default(), white, 7);
        let balanced =
            ModelConfig::preset(Preset::Balanced, SceneBounds::dnerf_default(), white, 7);
        let counts =
            |s: &str, c: &ModelConfig| s.parse::<PlaySamples>().unwrap().counts(&c.sampler, None);
        assert_eq!(counts("full", &fast), (48, 24));
        assert_eq!(counts("fast", &fast), (32, 18));
        assert_eq!(counts("faster", &fast), (24, 12));
        assert_eq!(counts("fast", &balanced), (64, 24));
        assert_eq!(counts("faster", &balanced), (48, 16));
        assert_eq!(counts("7, 3", &fast), (7, 3));
        // Rounded up, never to zero.
        let mut tiny = fast.clone();
        tiny.sampler.set_samples(1, 1);
        assert_eq!(counts("faster", &tiny), (1, 1));
        tiny.sampler.set_samples(5, 3);
        assert_eq!(counts("fast", &tiny), (4, 3));
        for bad in ["", "half", "0,4", "4,0", "4", "4,x", "-1,2", "4,4,4"] {
            let e = bad.parse::<PlaySamples>().unwrap_err();
            assert!(e.contains("file, full, fast, faster or P,M"), "{bad}: {e}");
        }
        // `file`: the file's stored counts, the model's own without them.
        assert_eq!(counts("file", &fast), (48, 24));
        assert_eq!(
            PlaySamples::File.counts(&fast.sampler, Some((20, 9))),
            (20, 9)
        );
        assert_eq!(
            PlaySamples::Level(SampleLevel::Full).counts(&fast.sampler, Some((20, 9))),
            (48, 24)
        );
        assert_eq!(PlaySamples::default(), PlaySamples::File);
        let m = PlaySamples::Counts(64, 8)
            .apply(&fast, None, 1024, 512)
            .unwrap();
        assert_eq!(
            (m.sampler.num_proposal_samples, m.sampler.num_samples),
            (64, 8)
        );
        // Nothing but the counts moves.
        let mut back = m.clone();
        back.sampler.set_samples(48, 24);
        assert_eq!(back, fast);
        let e = PlaySamples::Counts(2000, 8)
            .apply(&fast, None, 1024, 512)
            .unwrap_err();
        assert!(e.contains("1..=1024"), "{e}");
        assert!(PlaySamples::Counts(8, 513)
            .apply(&fast, None, 1024, 512)
            .is_err());
    }

    #[test]
    fn small_model_helpers_set_what_they_name() {
        let white = Background::Color { rgb: [1.0; 3] };
        let base = ModelConfig::preset(Preset::Fast, SceneBounds::dnerf_default(), white, 7);
        let mut c = ModelConfig::fast_on_white(7);
        assert_eq!(c, base);
        c.resize_mlps(8, 4);
        c.sampler.set_samples(12, 6);
        // These fields and nothing else moved.
        let mut expected = base.clone();
        (expected.field.density_hidden, expected.field.color_hidden) = (8, 8);
        expected.proposal.hidden = 4;
        (
            expected.sampler.num_proposal_samples,
            expected.sampler.num_samples,
        ) = (12, 6);
        assert_eq!(c, expected);
        c.validate().unwrap();
    }

    #[test]
    fn the_removed_quality_preset_names_what_to_use() {
        let e = "quality".parse::<Preset>().unwrap_err().to_string();
        assert!(
            e.contains("removed") && e.contains("balanced") && e.contains("paper"),
            "{e}"
        );
        let e = "qualty".parse::<Preset>().unwrap_err().to_string();
        assert!(e.contains("unknown preset `qualty`"), "{e}");
        for (name, p) in [
            ("fast", Preset::Fast),
            ("balanced", Preset::Balanced),
            ("paper", Preset::Paper),
        ] {
            assert_eq!(name.parse::<Preset>(), Ok(p));
        }
    }

    #[test]
    fn presets_validate() {
        for p in [Preset::Fast, Preset::Balanced, Preset::Paper] {
            for frames in [1, 2, 30, 300, 10_000] {
                let c = ModelConfig::preset(
                    p,
                    SceneBounds::dnerf_default(),
                    Background::Color { rgb: [1.0; 3] },
                    frames,
                );
                c.validate()
                    .unwrap_or_else(|e| panic!("{p:?} {frames}: {e}"));
            }
        }
    }
}
