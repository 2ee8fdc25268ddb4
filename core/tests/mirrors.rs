//! Which Rust item each GPU (WGSL) and page (JavaScript) rule mirrors, checked against the
//! text of those files. The field's blend rules live in `msth_core::config::BlendMode`
//! (`coefficients`, `is_dynamic`, `no_mask_value`) and the render cut-off in
//! `msth_core::pipeline::RENDER_STATIC_CUTOFF`; the copies that cannot call them are listed here:
//!
//! | copy | mirrors |
//! |---|---|
//! | `gpu/shaders/render/field.wgsl`, `blend_of` (used by `encode` and the specialised encodings): `k3`, `k4` per blend code | `BlendMode::coefficients` |
//! | `gpu/shaders/render/field.wgsl`, `blend_of`: `skip4` | `BlendMode::is_dynamic` |
//! | `gpu/src/layout.rs`: `consts.x` of the encoding uniform | `BlendMode::no_mask_value` |
//! | `web/js/renderer.js`: `noMask` | `BlendMode::no_mask_value` |
//! | `web/js/renderer.js`: `RENDER_STATIC_CUTOFF` | `pipeline::RENDER_STATIC_CUTOFF` |
//! | `web/js/renderer.js`: the `Model` uniform's padding (`Math.min` with `RENDER_HISTOGRAM_PADDING`) | `pipeline::render_histogram_padding` |
//!
//! A copy that calls the Rust item (or a constant generated from it) passes by naming it.

use std::path::PathBuf;

use msth_core::config::BlendMode;
use msth_core::pipeline::RENDER_STATIC_CUTOFF;

fn read(rel: &str) -> String {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(rel);
    std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn wgsl_blend_mirrors_blend_coefficients() {
    let wgsl = read("gpu/shaders/render/field.wgsl");
    // Blend codes 0..4 are Mst, Mt, Add, FourD, Static (gpu/src/layout.rs, blend_code); the
    // shader blends `v = k3 f3 + k4 f4` with the two coefficients chosen per code by these
    // lines, transcribed below (WGSL `select(f, t, c)` is `if c { t } else { f }`).
    let k3 = "let k3 = select(select(1.0, m, blend == 0u), 0.0, blend == 3u);";
    let k4 = "let k4 = select(select(1.0 - m, 1.0, blend >= 2u), 0.0, blend == 4u);";
    for text in [k3, k4] {
        assert!(wgsl.contains(text), "field.wgsl: no `{text}`");
    }
    assert!(wgsl.contains("let va = k3 * f3.a + k4 * f4.a;"));
    let select = |f: f32, t: f32, c: bool| if c { t } else { f };
    for (code, mode) in BlendMode::ALL.iter().enumerate() {
        for m in [0.0f32, 0.3, 1.0] {
            let k3 = select(select(1.0, m, code == 0), 0.0, code == 3);
            let k4 = select(select(1.0 - m, 1.0, code >= 2), 0.0, code == 4);
            assert_eq!((k3, k4), mode.coefficients(m), "{mode:?} at m = {m}");
        }
    }
    // A blend's unread lookup is skipped: Static never reads 4D (k4 = 0), FourD never 3D (k3 = 0).
    assert!(wgsl.contains("let skip4 = blend == 4u ||"));
    assert!(wgsl.contains("let skip3 = blend == 3u;"));
    // skip4: only Mst/Mt (codes <= 1) with a mask skip h4, where 1 - m < cutoff.
    assert!(wgsl.contains("blend <= 1u && (1.0 - m) < cutoff"));
    // (Static has no h4 to skip: it is never dynamic.)
    for mode in BlendMode::ALL
        .into_iter()
        .filter(|&m| m != BlendMode::Static)
    {
        let skips = matches!(mode, BlendMode::Mst | BlendMode::Mt);
        assert_eq!(!mode.is_dynamic(true, 1.0, 1e-3), skips, "{mode:?}");
        assert!(mode.is_dynamic(true, 0.0, 1e-3));
    }
}

#[test]
fn no_mask_value_copies_mirror_blend_mode() {
    let expect = |m: BlendMode| m.no_mask_value();
    let layout = read("gpu/src/layout.rs");
    if !layout.contains("no_mask_value()") {
        for (arm, m) in [
            ("BlendMode::Static => 1.0", BlendMode::Static),
            ("BlendMode::FourD => 0.0", BlendMode::FourD),
            ("_ => 0.5", BlendMode::Add),
        ] {
            assert!(layout.contains(arm), "gpu/src/layout.rs: no `{arm}`");
            let v: f32 = arm.rsplit("=> ").next().unwrap().parse().unwrap();
            assert_eq!(v, expect(m));
        }
    }
    let js = read("web/js/renderer.js");
    if !js.contains("no_mask_value") && !js.contains("NO_MASK") {
        let line = js
            .lines()
            .find(|l| l.contains("const noMask"))
            .expect("renderer.js: noMask");
        assert!(
            line.contains(&format!("\"static\" ? {}", expect(BlendMode::Static)))
                && line.contains(&format!("\"four_d\" ? {}", expect(BlendMode::FourD)))
                && line.contains(&format!(": {};", expect(BlendMode::Mt))),
            "renderer.js: {line}"
        );
    }
    if let Some(line) = js
        .lines()
        .find(|l| l.contains("const RENDER_STATIC_CUTOFF ="))
    {
        let v: f32 = line
            .split('=')
            .nth(1)
            .unwrap()
            .trim()
            .trim_end_matches(';')
            .parse()
            .unwrap();
        assert_eq!(v, RENDER_STATIC_CUTOFF);
    }
}

/// The page's `Model` uniform holds the padding rendering resamples with
/// (`pipeline::render_histogram_padding`: the model's own or `RENDER_HISTOGRAM_PADDING`, the
/// smaller), as msth-gpu's does (its unit test `the_model_uniform_holds_the_render_histogram_padding`).
#[test]
fn the_page_resamples_with_the_render_padding() {
    let js = read("web/js/renderer.js");
    assert!(
        js.contains("const padding = Math.min(s.histogram_padding, RENDER_HISTOGRAM_PADDING);"),
        "renderer.js: no render padding"
    );
    assert!(
        js.contains("f.set([s.near, s.far, padding, "),
        "renderer.js: the Model uniform's limits do not hold the render padding"
    );
}
