//! The routes and the middleware: `GET/HEAD /models` (JSON listing), `GET/HEAD /models/NAME`
//! (the file, with Range, conditional requests and validators), the static web files for
//! everything else, and one middleware for limits, CORS and request logging.

use std::sync::Arc;
use std::time::Instant;

use axum::body::Body;
use axum::extract::{Path as UrlPath, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde::Serialize;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;

use crate::catalog::Catalog;
use crate::range;
use crate::{web, Limits};

/// Media type of a `.msth` body.
pub const MSTH_CONTENT_TYPE: &str = "application/octet-stream";

#[derive(Clone)]
pub(crate) struct AppState {
    pub catalog: Arc<Catalog>,
    pub web_dir: Option<Arc<std::path::Path>>,
    pub limits: Limits,
}

pub(crate) fn router(state: AppState) -> Router {
    Router::new()
        .route("/models", get(listing))
        .route("/models/{name}", get(model_file))
        .fallback(static_files)
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            guard_cors_log,
        ))
        .with_state(state)
}

/// One row of `GET /models`.
#[derive(Serialize)]
struct ListingRow {
    name: String,
    url: String,
    bytes: u64,
    /// RFC 3339, UTC, whole seconds.
    modified: String,
}

async fn listing(State(state): State<AppState>) -> Response {
    let catalog = state.catalog.clone();
    match tokio::task::spawn_blocking(move || catalog.list()).await {
        Ok(Ok(entries)) => {
            let rows: Vec<ListingRow> = entries
                .into_iter()
                .map(|e| ListingRow {
                    url: format!("/models/{}", e.name),
                    name: e.name,
                    bytes: e.bytes,
                    modified: rfc3339(range::unix_secs(e.modified)),
                })
                .collect();
            ([(header::CACHE_CONTROL, "no-cache")], Json(rows)).into_response()
        }
        Ok(Err(e)) => {
            tracing::error!("listing failed: {e}");
            StatusCode::INTERNAL_SERVER_ERROR.into_response()
        }
        Err(_) => StatusCode::INTERNAL_SERVER_ERROR.into_response(),
    }
}

async fn model_file(
    State(state): State<AppState>,
    UrlPath(name): UrlPath<String>,
    headers: HeaderMap,
) -> Response {
    let catalog = state.catalog.clone();
    let Ok(Some(entry)) = tokio::task::spawn_blocking(move || catalog.lookup(&name)).await else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let Ok(mut file) = tokio::fs::File::open(&entry.path).await else {
        return StatusCode::NOT_FOUND.into_response();
    };
    // Validators from the open handle, so they describe the bytes we send.
    let Ok(meta) = file.metadata().await else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let len = meta.len();
    let modified = meta.modified().unwrap_or(std::time::SystemTime::UNIX_EPOCH);
    let etag = range::etag_for(len, modified);
    let last_modified = httpdate::fmt_http_date(modified);
    let text = |name: header::HeaderName| headers.get(name).and_then(|v| v.to_str().ok());

    let not_modified = match text(header::IF_NONE_MATCH) {
        Some(v) => range::none_match_hits(v, &etag),
        None => {
            text(header::IF_MODIFIED_SINCE).is_some_and(|v| range::not_modified_since(v, modified))
        }
    };
    let validators = [
        (header::ETAG, etag.clone()),
        (header::LAST_MODIFIED, last_modified),
        (header::ACCEPT_RANGES, "bytes".to_string()),
    ];
    if not_modified {
        return (StatusCode::NOT_MODIFIED, validators).into_response();
    }

    let spec = text(header::RANGE)
        .and_then(range::parse_range)
        .filter(|_| {
            text(header::IF_RANGE).is_none_or(|v| range::if_range_matches(v, &etag, modified))
        });
    let (status, first, count) = match spec {
        None => (StatusCode::OK, 0, len),
        Some(spec) => match range::resolve(spec, len) {
            Some((a, b)) => (StatusCode::PARTIAL_CONTENT, a, b - a + 1),
            None => {
                return (
                    StatusCode::RANGE_NOT_SATISFIABLE,
                    validators,
                    [(header::CONTENT_RANGE, format!("bytes */{len}"))],
                )
                    .into_response()
            }
        },
    };
    if first > 0 && file.seek(std::io::SeekFrom::Start(first)).await.is_err() {
        return StatusCode::INTERNAL_SERVER_ERROR.into_response();
    }
    let body = Body::from_stream(ReaderStream::with_capacity(file.take(count), 64 * 1024));
    let mut response = (
        status,
        validators,
        [
            (header::CONTENT_TYPE, MSTH_CONTENT_TYPE.to_string()),
            (header::CONTENT_LENGTH, count.to_string()),
        ],
        body,
    )
        .into_response();
    if status == StatusCode::PARTIAL_CONTENT {
        let value = format!("bytes {first}-{}/{len}", first + count - 1);
        if let Ok(v) = HeaderValue::from_str(&value) {
            response.headers_mut().insert(header::CONTENT_RANGE, v);
        }
    }
    response
}

async fn static_files(State(state): State<AppState>, request: Request) -> Response {
    web::static_file(state.web_dir.as_deref(), request.uri().path()).await
}

/// Limits first (414, 431, 405), CORS on every answer (and preflights), then one log line.
async fn guard_cors_log(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let started = Instant::now();
    let method = request.method().clone();
    let path = request.uri().path().to_string();
    let limits = state.limits;
    let header_bytes: usize = request
        .headers()
        .iter()
        .map(|(k, v)| k.as_str().len() + v.len() + 4)
        .sum();
    let mut response = if request.uri().to_string().len() > limits.max_uri_bytes {
        StatusCode::URI_TOO_LONG.into_response()
    } else if header_bytes > limits.max_header_bytes {
        StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE.into_response()
    } else if method == Method::OPTIONS {
        preflight()
    } else if method != Method::GET && method != Method::HEAD {
        (
            StatusCode::METHOD_NOT_ALLOWED,
            [(header::ALLOW, "GET, HEAD, OPTIONS")],
        )
            .into_response()
    } else {
        next.run(request).await
    };
    let h = response.headers_mut();
    h.insert(
        header::ACCESS_CONTROL_ALLOW_ORIGIN,
        HeaderValue::from_static("*"),
    );
    h.insert(
        header::ACCESS_CONTROL_EXPOSE_HEADERS,
        HeaderValue::from_static(
            "Content-Range, Accept-Ranges, ETag, Content-Length, Last-Modified",
        ),
    );
    let bytes = response
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("-")
        .to_string();
    tracing::info!(
        %method,
        path,
        status = response.status().as_u16(),
        bytes,
        ms = started.elapsed().as_secs_f64() * 1e3,
        "request"
    );
    response
}

fn preflight() -> Response {
    (
        StatusCode::NO_CONTENT,
        [
            (header::ACCESS_CONTROL_ALLOW_METHODS, "GET, HEAD, OPTIONS"),
            (
                header::ACCESS_CONTROL_ALLOW_HEADERS,
                "Range, If-Range, If-None-Match, If-Modified-Since",
            ),
            (header::ACCESS_CONTROL_MAX_AGE, "86400"),
        ],
    )
        .into_response()
}

/// `YYYY-MM-DDTHH:MM:SSZ` for seconds since the Unix epoch (Howard Hinnant's civil_from_days).
fn rfc3339(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
mod tests {
    #[test]
    fn rfc3339_dates() {
        assert_eq!(super::rfc3339(0), "1970-01-01T00:00:00Z");
        assert_eq!(super::rfc3339(951_782_400), "2000-02-29T00:00:00Z");
        assert_eq!(super::rfc3339(1_700_000_000), "2023-11-14T22:13:20Z");
    }
}
