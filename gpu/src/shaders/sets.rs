//! The shader texts the crate's build composes from the WGSL modules of `shaders/render/`: each
//! a file name in the build's output folder and the root modules it holds (every module they
//! import comes with them). The build script compiles this file too (`build.rs`).

/// (file name, root modules) of each composed shader text. `render.wgsl` is the renderer's
/// ([`crate::RENDER_WGSL`]): `eval_points` and the per-sample passes; `volume.wgsl` the
/// march through the play-time volume ([`crate::VOLUME_WGSL`]). Another set of entry points is
/// another entry here, rooted at its entry module, and a constant in `shaders.rs` that includes
/// its text.
pub const SETS: &[(&str, &[&str])] = &[
    ("render.wgsl", &["points", "passes"]),
    ("volume.wgsl", &["volume"]),
];
