//! The browser page's `web/shaders/render.wgsl` is a generated copy of this crate's
//! `shaders/render.wgsl` ([`msth_gpu::RENDER_WGSL`]): this test fails when the two differ, so
//! the native and the web renderers cannot drift apart. `MSTH_UPDATE_WEB_WGSL=1` rewrites the
//! copy (through a temporary file and a rename) instead of failing.

use std::path::PathBuf;

fn web_copy() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../web/shaders/render.wgsl")
}

#[test]
fn web_page_wgsl_is_the_crate_wgsl() {
    let path = web_copy();
    if std::env::var("MSTH_UPDATE_WEB_WGSL").is_ok_and(|v| v == "1") {
        let tmp = path.with_extension("wgsl.tmp");
        std::fs::write(&tmp, msth_gpu::RENDER_WGSL).expect("write the web copy");
        std::fs::rename(&tmp, &path).expect("replace the web copy");
    }
    let copy = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("{}: {e} (the web page needs it)", path.display()));
    if copy != msth_gpu::RENDER_WGSL {
        let line = copy
            .lines()
            .zip(msth_gpu::RENDER_WGSL.lines())
            .position(|(a, b)| a != b)
            .map(|i| i + 1)
            .unwrap_or_else(|| {
                copy.lines()
                    .count()
                    .min(msth_gpu::RENDER_WGSL.lines().count())
                    + 1
            });
        panic!(
            "{} differs from gpu/shaders/render.wgsl (first at line {line}); run \
             `MSTH_UPDATE_WEB_WGSL=1 cargo test --release -p msth-gpu --test web_copy`",
            path.display()
        );
    }
}
