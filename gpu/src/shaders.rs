//! The render kernels' WGSL, in modules: `shaders/render/NAME.wgsl`, each a few hundred lines at
//! most, naming the modules it uses on `// #import NAME` lines; [`compose`] writes the modules
//! reachable from some roots into one shader text, each once, after its imports.
//!
//! | module | holds |
//! |---|---|
//! | `common` | limits, msth-core's rendering thresholds, clamps, activations, `invocation` |
//! | `bindings` | the `Model` and `View` uniforms, the hash tables (`table2`, the "Hash tables" region), `rest` (bindings 0-4) |
//! | `io` | the entry points' pixel `list` and output `frame` (bindings 5-6) |
//! | `camera` | `pixel_ray_dir`, `ray_limits`, `to_unit` (the contraction), `t_of_s` (the spacing), `sample_point` |
//! | `sh` | `sh4`, the view-direction encoding (also in the training kernels: [`crate::sh`]) |
//! | `mask` | `mask_at`, the dense mask grid |
//! | `hashgrid` | `grid_level`, `grid_level_at`: one level of a 3D/4D hash grid |
//! | `mlp` | the generic one-sample MLP layers and their activations |
//! | `field` | `encode`, `blend_of`, `reads4`, `proposal_sigma`, `field_density`, `field_color`: the fields at one point |
//! | `points` | the entry point `eval_points`: the fields at given points (kernel tests, the volume's bake) |
//! | `passes_work` | the per-sample passes' `Pass` uniform, `work` buffer and counters (bindings 7-10) and helpers |
//! | `passes_lanes` | `LANES` and the activations of the passes' MLPs (`hid4`, `out4`) |
//! | `specialise` | the region [`crate::specialise`] rewrites for a model: the passes' encodings and MLPs |
//! | `passes_rays`, `passes_shade`, `passes_cache` | the `pass_*` entry points (to the main samples; to the pixel; the sample cache) |
//! | `passes` | the root of the per-sample passes |
//! | `volume` | `volume_march`: one pixel's ray through the play-time volume (bindings 7-9; root of `volume.wgsl`) |
//!
//! A kernel that evaluates the field per point (a per-pixel ray march, say) imports `field` and
//! `camera` (and `io`, or bindings of its own) and none of the passes; its shader text is
//! [`compose_render`] of its entry module, or a build-time constant like [`RENDER_WGSL`] through
//! an entry in `shaders/sets.rs`. The composer's output is plain WGSL: native code compiles it,
//! and the web page loads the same text (`web/shaders/render.wgsl`, a generated copy checked by
//! `tests/web_copy.rs`).

mod compose;
mod sets;

pub use compose::{compose, imports, order, ComposeError, IMPORT, MODULE};
pub use sets::SETS;

/// The modules of `shaders/render/`: (name, text), by name (the build's registry).
pub const RENDER_MODULES: &[(&str, &str)] =
    include!(concat!(env!("OUT_DIR"), "/render_modules.rs"));

/// The renderer's kernels, composed when the crate builds: roots `points` and `passes` (the
/// first entry of [`SETS`]).
pub const RENDER_WGSL: &str = include_str!(concat!(env!("OUT_DIR"), "/render.wgsl"));

/// The march through the play-time volume ([`crate::volume`]): root `volume` (the second entry
/// of [`SETS`]).
pub const VOLUME_WGSL: &str = include_str!(concat!(env!("OUT_DIR"), "/volume.wgsl"));

/// The shader text of the render modules `roots` and their imports ([`compose`] over
/// [`RENDER_MODULES`]).
pub fn compose_render(roots: &[&str]) -> Result<String, ComposeError> {
    compose(RENDER_MODULES, roots)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The build's texts are the composer's (the build script and the crate compile the same
    /// composer; this pins that they were given the same modules).
    #[test]
    fn build_time_texts_are_the_composition() {
        assert_eq!(SETS[0].0, "render.wgsl");
        assert_eq!(compose_render(SETS[0].1).unwrap(), RENDER_WGSL);
        assert_eq!(SETS[1].0, "volume.wgsl");
        assert_eq!(compose_render(SETS[1].1).unwrap(), VOLUME_WGSL);
    }

    /// Every module is reachable from the roots of some set, composes on its own (its imports
    /// are complete enough to order it), and the specialise and "Hash tables" markers appear
    /// once in the renderer's text.
    #[test]
    fn render_modules_compose() {
        let mut all = Vec::new();
        for (_, roots) in SETS {
            for m in order(RENDER_MODULES, roots).unwrap() {
                if !all.contains(&m) {
                    all.push(m);
                }
            }
        }
        let mut names: Vec<&str> = RENDER_MODULES.iter().map(|(n, _)| *n).collect();
        let mut reached = all.clone();
        names.sort();
        reached.sort();
        assert_eq!(reached, names, "a module no root imports");
        for (name, _) in RENDER_MODULES {
            compose_render(&[name]).unwrap_or_else(|e| panic!("{name}: {e}"));
        }
        for marker in [
            crate::specialise::BEGIN,
            crate::specialise::END,
            "// ---- Hash tables: begin",
            "// ---- Hash tables: end ----\n",
            "const LANES: u32 = 4u;\n",
        ] {
            assert_eq!(RENDER_WGSL.matches(marker).count(), 1, "{marker:?}");
        }
    }

    /// `text` parsed and validated as WGSL (naga, as wgpu does before any device sees it), with
    /// the capabilities of WebGPU core that the kernels use (`unpack2x16float`).
    fn validate(text: &str) -> Result<(), String> {
        use wgpu::naga;
        let module = naga::front::wgsl::parse_str(text).map_err(|e| e.emit_to_string(text))?;
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::SHADER_FLOAT16_IN_FLOAT32,
        )
        .validate(&module)
        .map_err(|e| format!("{e:?}"))?;
        Ok(())
    }

    /// Each module with its imports alone is valid WGSL: every module imports all it uses. And
    /// the renderer's text, with either table format, is too.
    #[test]
    fn every_module_is_valid_with_its_imports() {
        for (name, _) in RENDER_MODULES {
            let text = compose_render(&[name]).unwrap();
            validate(&text).unwrap_or_else(|e| panic!("module `{name}` with its imports: {e}"));
        }
        for tables in [crate::TableFormat::F32, crate::TableFormat::F16] {
            let text = tables.source(RENDER_WGSL).unwrap();
            validate(&text).unwrap_or_else(|e| panic!("{} tables: {e}", tables.name()));
        }
        validate(VOLUME_WGSL).unwrap_or_else(|e| panic!("volume.wgsl: {e}"));
    }

    /// What a per-point kernel imports brings no per-sample pass, and the SH module alone is
    /// `sh4` and its array.
    #[test]
    fn field_modules_stand_without_the_passes() {
        let field = compose_render(&["field", "camera", "io"]).unwrap();
        for name in [
            "field_density",
            "field_color",
            "proposal_sigma",
            "encode",
            "mask_at",
        ] {
            assert!(field.contains(&format!("fn {name}(")), "{name}");
        }
        for name in ["pixel_ray_dir", "ray_limits", "to_unit", "t_of_s", "sh4"] {
            assert!(field.contains(&format!("fn {name}(")), "{name}");
        }
        assert!(!field.contains("pass_"), "a pass in the field's modules");
        assert!(!field.contains("@compute"));
        let sh = compose_render(&["sh"]).unwrap();
        assert!(sh.contains("var<private> sh: array<f32, 16>;\n"));
        assert_eq!(sh.matches("\nfn ").count(), 1);
    }
}
