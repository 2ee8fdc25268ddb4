//! The player's streaming client against real sockets: the built-in server, and small hand-written
//! HTTP servers that misbehave on purpose (stall, cut connections, ignore ranges, change the file,
//! answer the wrong range). Each failure must end in a clear error within the configured timeouts,
//! never a hang; failures that can heal must be retried.

use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::ops::Range;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use msth_codec::Limits;
use msth_player::source::TransferStats;
use msth_player::{ByteSource, FileSource, HttpOptions, HttpSource, ModelStream};
use msth_server::{BackgroundServer, ServerConfig};

fn fixture_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/v1.msth")
}

fn fixture() -> Vec<u8> {
    std::fs::read(fixture_path()).unwrap()
}

fn quick() -> HttpOptions {
    HttpOptions {
        connect_timeout: Duration::from_secs(2),
        read_timeout: Duration::from_millis(300),
        request_timeout: Duration::from_secs(10),
        retries: 2,
        backoff: Duration::from_millis(10),
        ..HttpOptions::default()
    }
}

/// What a hand-written server does with request number `n` (0-based) for `range` (`None`: no
/// Range header).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Reply {
    /// A correct 206 (or 200 without a Range header), with `etag`.
    Good { etag: &'static str },
    /// Accept and never answer.
    Stall,
    /// Announce the full length, send half the body, close.
    CutShort,
    /// Ignore the Range header: 200 with the whole file.
    Whole,
    /// 206 for a different range than asked.
    WrongRange,
    /// 200 + the whole file when `If-Range` does not match `etag` (a replaced file).
    Changed { etag: &'static str },
    /// 200 without `Content-Length`: the file, then zeros without end.
    Endless,
    /// A correct 206 whose `Content-Range` total is 1000 bytes more than the file.
    WrongTotal,
}

/// A tiny HTTP/1.1 server on a loopback port, one thread per connection, `Connection: close`.
struct TestServer {
    url: String,
    requests: Arc<AtomicUsize>,
}

fn parse_range(v: &str, len: u64) -> Option<Range<u64>> {
    let (a, b) = v.trim().strip_prefix("bytes=")?.split_once('-')?;
    let a: u64 = a.parse().ok()?;
    let b: u64 = b.parse::<u64>().ok()?.min(len - 1);
    Some(a..b + 1)
}

fn serve_one(
    mut s: TcpStream,
    body: &[u8],
    reply: Reply,
    if_range: Option<String>,
    range: Option<Range<u64>>,
) {
    let len = body.len() as u64;
    let head = |status: &str, extra: String, n: usize| {
        format!("HTTP/1.1 {status}\r\nContent-Length: {n}\r\nConnection: close\r\n{extra}\r\n")
    };
    let whole = |s: &mut TcpStream| {
        let _ = s.write_all(head("200 OK", String::new(), body.len()).as_bytes());
        let _ = s.write_all(body);
    };
    match (reply, range) {
        (Reply::Stall, _) => std::thread::sleep(Duration::from_secs(5)),
        (Reply::Endless, _) => {
            let _ = s.write_all(b"HTTP/1.1 200 OK\r\nConnection: close\r\n\r\n");
            let _ = s.write_all(body);
            let zeros = vec![0u8; 64 << 10];
            while s.write_all(&zeros).is_ok() {}
        }
        (Reply::WrongTotal, Some(r)) => {
            let extra = format!(
                "Content-Range: bytes {}-{}/{}\r\n",
                r.start,
                r.end - 1,
                len + 1000
            );
            let part = &body[r.start as usize..r.end as usize];
            let _ = s.write_all(head("206 Partial Content", extra, part.len()).as_bytes());
            let _ = s.write_all(part);
        }
        (Reply::Whole, _) | (_, None) => whole(&mut s),
        (Reply::Changed { etag }, Some(_)) if if_range.as_deref() != Some(etag) => whole(&mut s),
        (Reply::Good { etag } | Reply::Changed { etag }, Some(r)) => {
            let extra = format!(
                "Content-Range: bytes {}-{}/{len}\r\nETag: {etag}\r\n",
                r.start,
                r.end - 1
            );
            let part = &body[r.start as usize..r.end as usize];
            let _ = s.write_all(head("206 Partial Content", extra, part.len()).as_bytes());
            let _ = s.write_all(part);
        }
        (Reply::CutShort, Some(r)) => {
            let extra = format!("Content-Range: bytes {}-{}/{len}\r\n", r.start, r.end - 1);
            let part = &body[r.start as usize..r.end as usize];
            let _ = s.write_all(head("206 Partial Content", extra, part.len()).as_bytes());
            let _ = s.write_all(&part[..part.len() / 2]);
        }
        (Reply::WrongRange, Some(r)) => {
            let extra = format!(
                "Content-Range: bytes {}-{}/{len}\r\n",
                r.start + 1,
                r.end.min(len - 1)
            );
            let n = (r.end.min(len - 1) - r.start) as usize;
            let _ = s.write_all(head("206 Partial Content", extra, n).as_bytes());
            let _ = s.write_all(&body[r.start as usize + 1..r.start as usize + 1 + n]);
        }
    }
}

impl TestServer {
    fn start(body: Vec<u8>, behaviour: impl Fn(usize) -> Reply + Send + Sync + 'static) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}/scene.msth", listener.local_addr().unwrap());
        let requests = Arc::new(AtomicUsize::new(0));
        let counter = Arc::clone(&requests);
        let body = Arc::new(body);
        let behaviour = Arc::new(behaviour);
        std::thread::spawn(move || {
            for conn in listener.incoming() {
                let Ok(s) = conn else { return };
                let (body, behaviour, counter) = (
                    Arc::clone(&body),
                    Arc::clone(&behaviour),
                    Arc::clone(&counter),
                );
                std::thread::spawn(move || {
                    let mut reader = BufReader::new(s.try_clone().unwrap());
                    let (mut range, mut if_range) = (None, None);
                    loop {
                        let mut line = String::new();
                        if reader.read_line(&mut line).unwrap_or(0) == 0 {
                            return;
                        }
                        let line = line.trim_end();
                        if line.is_empty() {
                            break;
                        }
                        if let Some((k, v)) = line.split_once(':') {
                            match k.to_ascii_lowercase().as_str() {
                                "range" => range = parse_range(v, body.len() as u64),
                                "if-range" => if_range = Some(v.trim().to_string()),
                                _ => {}
                            }
                        }
                    }
                    let n = counter.fetch_add(1, Ordering::SeqCst);
                    serve_one(s, &body, behaviour(n), if_range, range);
                });
            }
        });
        TestServer { url, requests }
    }
}

#[test]
fn a_stalled_server_gives_a_timeout_error_not_a_hang() {
    let server = TestServer::start(fixture(), |_| Reply::Stall);
    let err = match HttpSource::open(&server.url, quick()) {
        Ok(_) => panic!("a server that never answers cannot be opened"),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("stalled: nothing received for 0.3 s"), "{err}");
    assert!(err.contains("gave up after 3 attempts"), "{err}");
    assert_eq!(server.requests.load(Ordering::SeqCst), 3);
}

#[test]
fn cut_connections_are_retried_and_the_stream_completes() {
    let data = fixture();
    // The first request (the probe) works; the next two are cut short; then all is well.
    let server = TestServer::start(data.clone(), |n| match n {
        1 | 2 => Reply::CutShort,
        _ => Reply::Good { etag: "\"v1\"" },
    });
    let opts = HttpOptions {
        probe_bytes: 64,
        ..quick()
    };
    let src = HttpSource::open(&server.url, opts).unwrap();
    assert!(src.supports_ranges());
    let stream = ModelStream::open(Box::new(src), &Limits::default()).unwrap();
    stream.wait_all(Duration::from_secs(30)).unwrap();
    let p = stream.progress();
    assert_eq!(p.sections_ready, p.sections);
    assert!(p.transfer.retries >= 2, "{:?}", p.transfer);
    // What streamed equals what a local read gives.
    let local = ModelStream::open(
        Box::new(FileSource::open(&fixture_path()).unwrap()),
        &Limits::default(),
    )
    .unwrap();
    local.wait_all(Duration::from_secs(30)).unwrap();
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for t in [0.0, 0.5, 1.0] {
        stream
            .params_for_time(t, &mut a, Duration::from_secs(5))
            .unwrap();
        local
            .params_for_time(t, &mut b, Duration::from_secs(5))
            .unwrap();
        assert!(a == b, "parameters at time {t} differ");
    }
}

#[test]
fn connections_that_keep_failing_end_in_a_clear_error() {
    let server = TestServer::start(fixture(), |n| match n {
        0 => Reply::Good { etag: "\"v1\"" },
        _ => Reply::CutShort,
    });
    let opts = HttpOptions {
        probe_bytes: 64,
        ..quick()
    };
    let src = HttpSource::open(&server.url, opts).unwrap();
    // The prefix read (in `open`) or a section read (on the fetch thread) fails.
    let err = match ModelStream::open(Box::new(src), &Limits::default()) {
        Err(e) => e.to_string(),
        Ok(stream) => stream
            .wait_static(Duration::from_secs(30))
            .unwrap_err()
            .to_string(),
    };
    assert!(err.contains("gave up after 3 attempts"), "{err}");
    assert_eq!(server.requests.load(Ordering::SeqCst), 4);
}

#[test]
fn a_server_without_ranges_still_plays() {
    let data = fixture();
    let server = TestServer::start(data.clone(), |_| Reply::Whole);
    let src = HttpSource::open(&server.url, quick()).unwrap();
    assert!(!src.supports_ranges());
    assert_eq!(src.len(), data.len() as u64);
    let stream = ModelStream::open(Box::new(src), &Limits::default()).unwrap();
    stream.wait_all(Duration::from_secs(30)).unwrap();
    assert_eq!(server.requests.load(Ordering::SeqCst), 1);
}

#[test]
fn an_endless_body_is_read_only_as_far_as_the_header_says() {
    let data = fixture();
    let server = TestServer::start(data.clone(), |_| Reply::Endless);
    let opts = HttpOptions {
        probe_bytes: 4096,
        ..quick()
    };
    let src = HttpSource::open(&server.url, opts).unwrap();
    assert!(!src.supports_ranges());
    assert_eq!(src.len(), msth_player::source::UNKNOWN_LEN);
    let stream = ModelStream::open(Box::new(src), &Limits::default()).unwrap();
    stream.wait_all(Duration::from_secs(30)).unwrap();
    let p = stream.progress();
    assert_eq!(p.sections_ready, p.sections);
    // One response, read to the header's length and not a byte further.
    assert_eq!(p.transfer.bytes, data.len() as u64);
    assert_eq!(server.requests.load(Ordering::SeqCst), 1);
}

#[test]
fn a_content_range_total_that_disagrees_with_the_header_is_refused() {
    let len = fixture().len();
    let server = TestServer::start(fixture(), |_| Reply::WrongTotal);
    let opts = HttpOptions {
        probe_bytes: 64,
        ..quick()
    };
    let src = HttpSource::open(&server.url, opts).unwrap();
    let err = match ModelStream::open(Box::new(src), &Limits::default()) {
        Ok(_) => panic!("a length the header contradicts was accepted"),
        Err(e) => e.to_string(),
    };
    let both = [
        format!("file is {} bytes", len + 1000),
        format!("header says {len}"),
    ];
    assert!(both.iter().all(|w| err.contains(w)), "{err}");
}

#[test]
fn a_file_replaced_on_the_server_is_detected() {
    // The probe sees ETag "v1"; every later If-Range "v1" fails as if the file had changed.
    let server = TestServer::start(fixture(), |n| match n {
        0 => Reply::Good { etag: "\"v1\"" },
        _ => Reply::Changed { etag: "\"v2\"" },
    });
    let opts = HttpOptions {
        probe_bytes: 64,
        ..quick()
    };
    let src = HttpSource::open(&server.url, opts).unwrap();
    let stream = ModelStream::open(Box::new(src), &Limits::default());
    let err = match stream {
        Err(e) => e.to_string(),
        Ok(s) => s
            .wait_static(Duration::from_secs(30))
            .unwrap_err()
            .to_string(),
    };
    assert!(err.contains("changed on the server"), "{err}");
}

#[test]
fn a_wrong_content_range_is_refused() {
    let server = TestServer::start(fixture(), |n| match n {
        0 => Reply::Good { etag: "\"v1\"" },
        _ => Reply::WrongRange,
    });
    let opts = HttpOptions {
        probe_bytes: 64,
        ..quick()
    };
    let src = HttpSource::open(&server.url, opts).unwrap();
    let err = src.read_range(100..200).unwrap_err().to_string();
    assert!(err.contains("got Content-Range"), "{err}");
    // Not retried: a wrong answer does not heal.
    assert_eq!(server.requests.load(Ordering::SeqCst), 2);
}

#[test]
fn missing_models_and_bad_urls_are_clear() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("a.msth"), fixture()).unwrap();
    let server = BackgroundServer::start(ServerConfig {
        addr: "127.0.0.1:0".parse().unwrap(),
        ..ServerConfig::new(dir.path())
    })
    .unwrap();
    let base = format!("http://{}", server.addr());
    let err = HttpSource::open(&format!("{base}/models/nope.msth"), quick())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("HTTP 404"), "{err}");
    let err = HttpSource::open("ftp://127.0.0.1:1/a.msth", quick())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("not an http:// or https:// URL"), "{err}");
    // Nothing listens on port 1: connection refused, retried, then a clear error.
    let err = HttpSource::open("http://127.0.0.1:1/a.msth", quick())
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("gave up after"), "{err}");
    // The real file plays.
    let src = HttpSource::open(&format!("{base}/models/a.msth"), quick()).unwrap();
    let stream = ModelStream::open(Box::new(src), &Limits::default()).unwrap();
    stream.wait_all(Duration::from_secs(30)).unwrap();
}

/// A local file whose reads past the prefix wait for a gate, and which logs every read.
struct GatedSource {
    inner: FileSource,
    prefix: u64,
    open: Mutex<bool>,
    opened: Condvar,
    log: Mutex<Vec<Range<u64>>>,
}

impl ByteSource for GatedSource {
    fn len(&self) -> u64 {
        self.inner.len()
    }
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, msth_player::SourceError> {
        if range.start >= self.prefix {
            let mut open = self.open.lock().unwrap();
            while !*open {
                open = self.opened.wait(open).unwrap();
            }
        }
        self.log.lock().unwrap().push(range.clone());
        self.inner.read_range(range)
    }
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn stats(&self) -> TransferStats {
        self.inner.stats()
    }
}

#[test]
fn seeking_fetches_the_wanted_chunk_first_then_plays_on_from_it() {
    let index = msth_codec::format::FileIndex::parse(&fixture(), &Limits::default()).unwrap();
    let chunks = index.metadata.chunks.len();
    assert!(chunks >= 2, "the fixture has {chunks} chunks");
    let gated = Arc::new(GatedSource {
        inner: FileSource::open(&fixture_path()).unwrap(),
        prefix: index.header.header_size as u64,
        open: Mutex::new(false),
        opened: Condvar::new(),
        log: Mutex::new(Vec::new()),
    });
    let stream = ModelStream::open(Box::new(Arc::clone(&gated)), &Limits::default()).unwrap();
    // Seek to the middle of the last chunk before anything past the prefix has been read.
    let last = &index.metadata.chunks[chunks - 1];
    stream.seek(0.5 * (last.t_start + last.t_end));
    *gated.open.lock().unwrap() = true;
    gated.opened.notify_all();
    stream.wait_all(Duration::from_secs(30)).unwrap();
    let log = gated.log.lock().unwrap().clone();
    let chunk_of = |r: &Range<u64>| {
        index.sections[index.first_chunk()..]
            .iter()
            .position(|s| s.offset == r.start)
    };
    let order: Vec<usize> = log.iter().filter_map(chunk_of).collect();
    let mut expected = vec![chunks - 1];
    expected.extend(0..chunks - 1);
    assert_eq!(order, expected, "requests: {log:?}");
    // The static sections came in one request, before any chunk.
    let first_chunk_at = log.iter().position(|r| chunk_of(r).is_some()).unwrap();
    let statics: Vec<_> = log[..first_chunk_at]
        .iter()
        .filter(|r| r.start >= gated.prefix)
        .collect();
    assert_eq!(statics.len(), 1, "requests: {log:?}");
}
