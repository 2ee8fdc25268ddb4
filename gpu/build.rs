//! Composes the render shader from the WGSL modules of `shaders/render/` (`src/shaders/`): the
//! modules' registry (`render_modules.rs`) and each composed text of `SETS` (`render.wgsl`) in
//! the output folder, which `src/shaders.rs` includes. A missing module, an import cycle or a
//! malformed import line fails the build with the composer's message.

use std::path::{Path, PathBuf};

#[allow(dead_code)]
#[path = "src/shaders/compose.rs"]
mod compose;

#[path = "src/shaders/sets.rs"]
mod sets;

fn main() {
    if let Err(e) = run() {
        println!("cargo::error=msth-gpu render shaders: {e}");
    }
}

fn run() -> Result<(), String> {
    let manifest = std::env::var("CARGO_MANIFEST_DIR").map_err(|e| e.to_string())?;
    let out_dir = PathBuf::from(std::env::var("OUT_DIR").map_err(|e| e.to_string())?);
    let dir = Path::new(&manifest).join("shaders/render");
    println!("cargo::rerun-if-changed=shaders/render");
    println!("cargo::rerun-if-changed=src/shaders/compose.rs");
    println!("cargo::rerun-if-changed=src/shaders/sets.rs");
    let mut files: Vec<(String, PathBuf)> = Vec::new();
    let entries = std::fs::read_dir(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    for entry in entries {
        let path = entry.map_err(|e| e.to_string())?.path();
        if path.extension().is_some_and(|x| x == "wgsl") {
            let name = path
                .file_stem()
                .and_then(|s| s.to_str())
                .ok_or_else(|| format!("{}: not a UTF-8 module name", path.display()))?;
            files.push((name.to_string(), path.clone()));
        }
    }
    files.sort();
    let mut texts = Vec::new();
    for (name, path) in &files {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        texts.push((name.clone(), text));
    }
    let modules: Vec<(&str, &str)> = texts
        .iter()
        .map(|(n, t)| (n.as_str(), t.as_str()))
        .collect();

    let mut registry = String::from("&[\n");
    for (name, path) in &files {
        registry.push_str(&format!(
            "    ({name:?}, include_str!({:?})),\n",
            path.display().to_string()
        ));
    }
    registry.push_str("]\n");
    write(&out_dir.join("render_modules.rs"), &registry)?;

    for (file, roots) in sets::SETS {
        let text = compose::compose(&modules, roots).map_err(|e| format!("{file}: {e}"))?;
        write(&out_dir.join(file), &text)?;
    }
    Ok(())
}

/// Writes `text` to `path` unless it holds it already (so that what includes it is not rebuilt).
fn write(path: &Path, text: &str) -> Result<(), String> {
    if std::fs::read_to_string(path).is_ok_and(|t| t == text) {
        return Ok(());
    }
    std::fs::write(path, text).map_err(|e| format!("{}: {e}", path.display()))
}
