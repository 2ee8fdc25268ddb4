//! The routes and the middleware: `GET/HEAD /models` (JSON listing), `GET/HEAD /models/NAME`
//! (the file, with Range and multipart byte ranges, preconditions and validators), the static web files for
//! everything else, and one middleware for limits, CORS and request logging.

use std::sync::Arc;
use std::time::Instant;

use axum::body::{Body, Bytes};
use axum::extract::{Path as UrlPath, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde::Serialize;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;

use crate::cache::{read_version, FileCache, FileId};
use crate::catalog::Catalog;
use crate::range::{self, Precondition, RangePlan};
use crate::{web, Limits};

/// Media type of a `.msth` body.
pub const MSTH_CONTENT_TYPE: &str = "application/octet-stream";

#[derive(Clone)]
pub(crate) struct AppState {
    pub catalog: Arc<Catalog>,
    pub cache: Arc<FileCache>,
    pub web_dir: Option<Arc<std::path::Path>>,
    pub limits: Limits,
    /// `--rate-limit`: the schedule and when the server started.
    pub rate_limit: Option<(Arc<crate::throttle::RateSchedule>, Instant)>,
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
    // The lookup is a few metadata calls on a local disk, made here rather than through the
    // blocking pool: under load the hop cost more than the calls.
    let Some((entry, meta)) = state.catalog.lookup_with_meta(&name) else {
        return StatusCode::NOT_FOUND.into_response();
    };
    let id = FileId::of(&meta);
    // A file the cache admits is answered from memory: read once (on the blocking pool), then
    // sliced for every response while it stays the same on disk.
    let cached = if state.cache.admits(meta.len()) {
        match state.cache.get(&entry.path, id) {
            Some(bytes) => Some(bytes),
            None => {
                let path = entry.path.clone();
                let read = tokio::task::spawn_blocking(move || read_version(&path, id))
                    .await
                    .ok()
                    .flatten();
                if let Some(bytes) = &read {
                    state.cache.insert(&entry.path, id, bytes.clone());
                }
                read
            }
        }
    } else {
        None
    };
    let content = match cached {
        Some(bytes) => Content::Memory(bytes),
        None => {
            let Ok(file) = tokio::fs::File::open(&entry.path).await else {
                return StatusCode::NOT_FOUND.into_response();
            };
            // Validators from the open handle, so they describe the bytes we send.
            let Ok(meta) = file.metadata().await else {
                return StatusCode::NOT_FOUND.into_response();
            };
            return respond(&headers, Content::Disk(file), &meta).await;
        }
    };
    respond(&headers, content, &meta).await
}

/// Where a response's bytes come from.
enum Content {
    /// The whole file, from the cache.
    Memory(Bytes),
    /// The open file, streamed.
    Disk(tokio::fs::File),
}

/// The answer to a GET or HEAD of a file of `meta`'s length and time, with `content`: the
/// preconditions, then the range.
async fn respond(headers: &HeaderMap, content: Content, meta: &std::fs::Metadata) -> Response {
    let len = meta.len();
    let modified = meta.modified().unwrap_or(std::time::SystemTime::UNIX_EPOCH);
    let etag = range::etag_for(len, modified);
    let last_modified = httpdate::fmt_http_date(modified);
    let validators = [
        (header::ETAG, etag.clone()),
        (header::LAST_MODIFIED, last_modified),
        (header::ACCEPT_RANGES, "bytes".to_string()),
    ];

    let if_match = list_field(headers, header::IF_MATCH);
    let if_none_match = list_field(headers, header::IF_NONE_MATCH);
    let conditions = range::Conditions {
        if_match: if_match.as_deref(),
        if_unmodified_since: single_field(headers, header::IF_UNMODIFIED_SINCE),
        if_none_match: if_none_match.as_deref(),
        if_modified_since: single_field(headers, header::IF_MODIFIED_SINCE),
    };
    match range::evaluate_preconditions(&conditions, &etag, modified) {
        Precondition::Failed => {
            return (StatusCode::PRECONDITION_FAILED, validators).into_response();
        }
        Precondition::NotModified => return (StatusCode::NOT_MODIFIED, validators).into_response(),
        Precondition::Proceed => {}
    }

    // RFC 9110 §13.2.2 step 5: If-Range decides whether Range applies; a Range sent twice, or
    // an If-Range that cannot be read, leaves the Range ignored.
    let if_range_holds = match headers.get_all(header::IF_RANGE).iter().count() {
        0 => true,
        _ => single_field(headers, header::IF_RANGE)
            .is_some_and(|v| range::if_range_matches(v, &etag, modified)),
    };
    let specs = single_field(headers, header::RANGE)
        .and_then(range::parse_range)
        .filter(|_| if_range_holds);
    let mut content = content;
    let (status, first, count) = match specs.map(|s| range::plan_ranges(&s, len)) {
        None => (StatusCode::OK, 0, len),
        Some(RangePlan::Single(a, b)) => (StatusCode::PARTIAL_CONTENT, a, b - a + 1),
        Some(RangePlan::Multi(parts)) => {
            match multipart(content, &parts, len, validators.clone()) {
                Ok(response) => return response,
                Err(back) => {
                    content = back;
                    (StatusCode::OK, 0, len)
                }
            }
        }
        Some(RangePlan::Unsatisfiable) => {
            return (
                StatusCode::RANGE_NOT_SATISFIABLE,
                validators,
                [(header::CONTENT_RANGE, format!("bytes */{len}"))],
            )
                .into_response()
        }
    };
    let body = match content {
        // Slices of the cached buffer, written to the socket as they are. In frames of
        // CHUNK_BYTES, as from disk: hyper asks for the next only once it has written most of
        // the last, so the body (and the request's in-flight mark, which keeps a connection
        // whose response is being written from being shed) lives until the end is near.
        Content::Memory(bytes) => {
            let part = bytes.slice(first as usize..(first + count) as usize);
            if part.len() <= CHUNK_BYTES {
                Body::from(part)
            } else {
                let frames = (0..part.len()).step_by(CHUNK_BYTES).map(move |a| {
                    Ok::<_, std::io::Error>(part.slice(a..(a + CHUNK_BYTES).min(part.len())))
                });
                Body::from_stream(futures_util::stream::iter(frames))
            }
        }
        Content::Disk(mut file) => {
            if first > 0 && file.seek(std::io::SeekFrom::Start(first)).await.is_err() {
                return StatusCode::INTERNAL_SERVER_ERROR.into_response();
            }
            Body::from_stream(ReaderStream::with_capacity(file.take(count), CHUNK_BYTES))
        }
    };
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

/// Bytes read from a file streamed from disk per body chunk (each read is a trip to the
/// blocking pool).
const CHUNK_BYTES: usize = 256 * 1024;

/// A list-valued field (`#entity-tag`), its lines joined with `", "` (RFC 9110 §5.3). A line
/// that is not visible ASCII makes the whole value empty, hence malformed.
fn list_field(headers: &HeaderMap, name: header::HeaderName) -> Option<String> {
    let lines: Vec<&HeaderValue> = headers.get_all(name).iter().collect();
    if lines.is_empty() {
        return None;
    }
    let texts: Option<Vec<&str>> = lines.iter().map(|v| v.to_str().ok()).collect();
    Some(texts.map(|t| t.join(", ")).unwrap_or_default())
}

/// A field that must appear once: its text, or `None` when absent, repeated or not ASCII.
fn single_field(headers: &HeaderMap, name: header::HeaderName) -> Option<&str> {
    let mut values = headers.get_all(name).iter();
    match (values.next(), values.next()) {
        (Some(v), None) => v.to_str().ok(),
        _ => None,
    }
}

/// A 206 `multipart/byteranges` (RFC 9110 §14.6) of `parts` (ascending, disjoint, inclusive):
/// each part with its `Content-Type` and `Content-Range`, streamed from the open file, with an
/// exact `Content-Length`.
///
/// Gives the file back (`Err`) when that body would be longer than the whole file: the caller
/// then sends the file with 200 instead, so no `Range` makes a response larger than the file.
fn multipart(
    content: Content,
    parts: &[(u64, u64)],
    len: u64,
    validators: [(header::HeaderName, String); 3],
) -> Result<Response, Content> {
    let boundary = boundary();
    let heads: Vec<Bytes> = parts
        .iter()
        .enumerate()
        .map(|(i, (a, b))| {
            let lead = if i == 0 { "" } else { "\r\n" };
            Bytes::from(format!(
                "{lead}--{boundary}\r\nContent-Type: {MSTH_CONTENT_TYPE}\r\nContent-Range: bytes {a}-{b}/{len}\r\n\r\n"
            ))
        })
        .collect();
    let tail = Bytes::from(format!("\r\n--{boundary}--\r\n"));
    let total: u64 = heads.iter().map(|h| h.len() as u64).sum::<u64>()
        + parts.iter().map(|(a, b)| b - a + 1).sum::<u64>()
        + tail.len() as u64;
    if total > len {
        return Err(content);
    }
    let body = match content {
        Content::Memory(bytes) => {
            let mut chunks: Vec<Result<Bytes, std::io::Error>> = Vec::new();
            for (head, &(a, b)) in heads.into_iter().zip(parts) {
                chunks.push(Ok(head));
                chunks.push(Ok(bytes.slice(a as usize..b as usize + 1)));
            }
            chunks.push(Ok(tail));
            Body::from_stream(futures_util::stream::iter(chunks))
        }
        Content::Disk(file) => {
            let state = PartsState {
                file,
                parts: parts.to_vec(),
                heads,
                tail,
                phase: Phase::Head(0),
            };
            Body::from_stream(futures_util::stream::unfold(state, next_chunk))
        }
    };
    Ok((
        StatusCode::PARTIAL_CONTENT,
        validators,
        [
            (
                header::CONTENT_TYPE,
                format!("multipart/byteranges; boundary={boundary}"),
            ),
            (header::CONTENT_LENGTH, total.to_string()),
        ],
        body,
    )
        .into_response())
}

/// 32 hex digits from a randomly keyed hash (std's `RandomState`) of the time and a counter:
/// unpredictable, so a file cannot be crafted to contain the delimiter of its own response.
fn boundary() -> String {
    use std::hash::{BuildHasher, Hasher};
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let word = |salt: u64| {
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write_u64(n);
        h.write_u64(salt);
        h.write_u128(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos())
                .unwrap_or(0),
        );
        h.finish()
    };
    format!("{:016x}{:016x}", word(1), word(2))
}

enum Phase {
    Head(usize),
    Data { part: usize, left: u64 },
    Tail,
    Done,
}

struct PartsState {
    file: tokio::fs::File,
    parts: Vec<(u64, u64)>,
    heads: Vec<Bytes>,
    tail: Bytes,
    phase: Phase,
}

/// The next chunk of a multipart body: a part's header, up to [`CHUNK_BYTES`] of its bytes, or
/// the closing delimiter. A read error or a file that shrank ends the body with an error (hyper
/// then closes the connection, so the client sees a truncated response, not a wrong one).
async fn next_chunk(mut st: PartsState) -> Option<(std::io::Result<Bytes>, PartsState)> {
    loop {
        match st.phase {
            Phase::Head(i) => {
                let (a, b) = st.parts[i];
                if let Err(e) = st.file.seek(std::io::SeekFrom::Start(a)).await {
                    st.phase = Phase::Done;
                    return Some((Err(e), st));
                }
                st.phase = Phase::Data {
                    part: i,
                    left: b - a + 1,
                };
                let head = st.heads[i].clone();
                return Some((Ok(head), st));
            }
            Phase::Data { part, left: 0 } => {
                st.phase = if part + 1 < st.parts.len() {
                    Phase::Head(part + 1)
                } else {
                    Phase::Tail
                };
            }
            Phase::Data { part, left } => {
                let want = usize::try_from(left).map_or(CHUNK_BYTES, |l| l.min(CHUNK_BYTES));
                let mut buf = vec![0u8; want];
                match st.file.read(&mut buf).await {
                    Ok(0) => {
                        st.phase = Phase::Done;
                        let e = std::io::Error::new(
                            std::io::ErrorKind::UnexpectedEof,
                            "the file shrank while it was being sent",
                        );
                        return Some((Err(e), st));
                    }
                    Ok(n) => {
                        buf.truncate(n);
                        st.phase = Phase::Data {
                            part,
                            left: left - n as u64,
                        };
                        return Some((Ok(Bytes::from(buf)), st));
                    }
                    Err(e) => {
                        st.phase = Phase::Done;
                        return Some((Err(e), st));
                    }
                }
            }
            Phase::Tail => {
                st.phase = Phase::Done;
                let tail = st.tail.clone();
                return Some((Ok(tail), st));
            }
            Phase::Done => return None,
        }
    }
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
    if let Some((schedule, start)) = &state.rate_limit {
        response = response.map(|b| crate::throttle::throttle(b, schedule.clone(), *start));
    }
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
                "Range, If-Range, If-Match, If-None-Match, If-Modified-Since, If-Unmodified-Since",
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
