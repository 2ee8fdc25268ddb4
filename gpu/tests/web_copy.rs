//! The browser page's `web/shaders/render.wgsl`, `web/shaders/volume.wgsl` and
//! `web/shaders/tables_f16.wgsl` are generated copies of this crate's render shader and volume
//! march as composed from the modules of `shaders/render/` ([`msth_gpu::RENDER_WGSL`],
//! [`msth_gpu::VOLUME_WGSL`], `msth_gpu::shaders`) and of `shaders/tables_f16.wgsl`
//! ([`msth_gpu::layout::TABLES_F16_WGSL`], the binary16 tables' region): this test fails when a
//! copy differs by a byte, so the native and the web renderers cannot drift apart.
//! `MSTH_UPDATE_WEB_WGSL=1` rewrites the copies (each through a temporary file and a rename)
//! instead of failing.

use std::path::PathBuf;

fn web_copy(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../web/shaders")
        .join(name)
}

#[test]
fn web_page_wgsl_is_the_crate_wgsl() {
    for (name, source, from) in [
        (
            "render.wgsl",
            msth_gpu::RENDER_WGSL,
            "the composition of gpu/shaders/render/",
        ),
        (
            "volume.wgsl",
            msth_gpu::VOLUME_WGSL,
            "the composition of gpu/shaders/render/ from `volume`",
        ),
        (
            "tables_f16.wgsl",
            msth_gpu::layout::TABLES_F16_WGSL,
            "gpu/shaders/tables_f16.wgsl",
        ),
    ] {
        let path = web_copy(name);
        if std::env::var("MSTH_UPDATE_WEB_WGSL").is_ok_and(|v| v == "1") {
            let tmp = path.with_extension("wgsl.tmp");
            std::fs::write(&tmp, source).expect("write the web copy");
            std::fs::rename(&tmp, &path).expect("replace the web copy");
        }
        let copy = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("{}: {e} (the web page needs it)", path.display()));
        if copy != source {
            let line = copy
                .lines()
                .zip(source.lines())
                .position(|(a, b)| a != b)
                .map(|i| i + 1)
                .unwrap_or_else(|| copy.lines().count().min(source.lines().count()) + 1);
            panic!(
                "{} differs from {from} (first at line {line}); run \
                 `MSTH_UPDATE_WEB_WGSL=1 cargo test --release -p msth-gpu --test web_copy`",
                path.display()
            );
        }
    }
}
