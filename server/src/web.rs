//! The web player's static files at `/`: a URL path becomes a file only after percent-decoding,
//! refusing `.`/`..`/hidden/empty segments, backslashes, colons and NUL, and checking that the
//! canonical file lies inside the canonical web folder. Without a web folder (or without an
//! `index.html` in it) `/` answers a small built-in placeholder page.

use std::path::{Path, PathBuf};

use axum::body::Body;
use axum::http::{header, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use tokio_util::io::ReaderStream;

const PLACEHOLDER: &str = "<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>msth serve</title></head>\n<body><h1>msth serve</h1>\n<p>The web player is not installed here. The models are listed at <a href=\"/models\">/models</a>\nand each is served at <code>/models/NAME.msth</code> with HTTP Range requests.</p>\n</body></html>\n";

/// Answers `GET`/`HEAD` for a path outside `/models`.
pub(crate) async fn static_file(web_dir: Option<&Path>, raw_path: &str) -> Response {
    let Some(rel) = sanitize(raw_path) else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let is_index = rel.as_os_str().is_empty() || rel == Path::new("index.html");
    if let Some(dir) = web_dir {
        if let Some(file) = resolve(dir, &rel).await {
            return send(&file).await;
        }
    }
    if is_index {
        return Html(PLACEHOLDER).into_response();
    }
    StatusCode::NOT_FOUND.into_response()
}

/// The relative path a URL path names, or `None` if it could name anything outside.
fn sanitize(raw_path: &str) -> Option<PathBuf> {
    let decoded = percent_decode(raw_path)?;
    let trimmed = decoded.strip_prefix('/')?;
    let mut rel = PathBuf::new();
    let segments: Vec<&str> = trimmed.split('/').collect();
    let last = segments.len() - 1;
    for (i, seg) in segments.iter().enumerate() {
        if seg.is_empty() {
            if i == last {
                break; // trailing slash: the folder's index
            }
            return None;
        }
        if seg.starts_with('.') || seg.contains(['\\', ':', '\0']) {
            return None;
        }
        rel.push(seg);
    }
    Some(rel)
}

fn percent_decode(s: &str) -> Option<String> {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            let hex = bytes.get(i + 1..i + 3)?;
            let hex = std::str::from_utf8(hex).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            i += 3;
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

async fn resolve(dir: &Path, rel: &Path) -> Option<PathBuf> {
    let root = tokio::fs::canonicalize(dir).await.ok()?;
    let mut file = tokio::fs::canonicalize(root.join(rel)).await.ok()?;
    if tokio::fs::metadata(&file).await.ok()?.is_dir() {
        file = tokio::fs::canonicalize(file.join("index.html"))
            .await
            .ok()?;
    }
    let is_file = tokio::fs::metadata(&file).await.ok()?.is_file();
    (is_file && file.starts_with(&root)).then_some(file)
}

async fn send(path: &Path) -> Response {
    let Ok(file) = tokio::fs::File::open(path).await else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let Ok(meta) = file.metadata().await else {
        return StatusCode::NOT_FOUND.into_response();
    };
    (
        [
            (header::CONTENT_TYPE, content_type(path)),
            (header::CONTENT_LENGTH, &meta.len().to_string()),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        Body::from_stream(ReaderStream::new(file)),
    )
        .into_response()
}

fn content_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()).unwrap_or("") {
        "html" | "htm" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript; charset=utf-8",
        "css" => "text/css; charset=utf-8",
        "json" => "application/json",
        "wasm" => "application/wasm",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "svg" => "image/svg+xml",
        "txt" | "md" | "wgsl" => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sanitize_refuses_escapes() {
        assert_eq!(sanitize("/"), Some(PathBuf::new()));
        assert_eq!(sanitize("/a/b.js"), Some(PathBuf::from("a/b.js")));
        for bad in [
            "/../x",
            "/%2e%2e/x",
            "/a/%2E%2E/b",
            "/a%2f..%2fb",
            "//etc/passwd",
            "/.git/config",
            "/a\\b",
            "/%5c..",
            "/c:/x",
            "/%00",
            "/%zz",
            "x",
        ] {
            assert_eq!(sanitize(bad), None, "{bad}");
        }
    }
}
