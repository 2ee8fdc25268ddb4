//! A small HTTP/1.1 server on a loopback port that serves one `.msth` file badly on purpose, one
//! fault per [`Fault`] mode, and the web player's files (`web/`) and a `/models` listing as
//! `msth serve` does, so that the page can be pointed at it too. One thread per connection,
//! `Connection: close` on every response. Used by `cli/tests/faults.rs`.

use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// How the server answers requests for the model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// Correct 206 answers (the baseline).
    Good,
    /// 200 with the whole file and its `Content-Length`, whatever the `Range`.
    IgnoresRange,
    /// 200 without `Content-Length` whose body is the file followed by zeros, without end.
    EndlessBody,
    /// Correct 206 headers, then the body one byte at a time, one per `DRIP`.
    DripFeed,
    /// 206 for the range asked, with a `Content-Range` total 1000 bytes more than the file.
    WrongTotal,
    /// The first request right; later ones answered with a range shifted by one byte.
    WrongRange,
    /// The first request right; later ones announce their length and send half of it.
    ShortBody,
    /// `302` to the same URL, for ever.
    RedirectLoop,
    /// The first request right (validator `"v1"`); later ones answered as if the file had been
    /// replaced (validator `"v2"`: `If-Range: "v1"` gets 200 and the whole file).
    ChangedMidStream,
    /// The first request right; later ones send their headers and 100 bytes, then nothing.
    Stall,
}

impl Fault {
    pub const ALL: [Fault; 10] = [
        Fault::Good,
        Fault::IgnoresRange,
        Fault::EndlessBody,
        Fault::DripFeed,
        Fault::WrongTotal,
        Fault::WrongRange,
        Fault::ShortBody,
        Fault::RedirectLoop,
        Fault::ChangedMidStream,
        Fault::Stall,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Fault::Good => "good",
            Fault::IgnoresRange => "ignores-range",
            Fault::EndlessBody => "endless-body",
            Fault::DripFeed => "drip-feed",
            Fault::WrongTotal => "wrong-total",
            Fault::WrongRange => "wrong-range",
            Fault::ShortBody => "short-body",
            Fault::RedirectLoop => "redirect-loop",
            Fault::ChangedMidStream => "changed-mid-stream",
            Fault::Stall => "stall",
        }
    }
}

/// Time between two bytes of [`Fault::DripFeed`] (shorter than any stall deadline the tests set,
/// so only the overall deadline can end it).
pub const DRIP: Duration = Duration::from_millis(500);

/// A running fault server; stops accepting when dropped (connections in progress end when their
/// client goes away).
pub struct FaultServer {
    pub addr: std::net::SocketAddr,
    requests: Arc<AtomicUsize>,
    stop: Arc<AtomicBool>,
}

impl FaultServer {
    /// Serves `model` under `/models/NAME` with `fault`, and `web` (if given) for every other path.
    pub fn start(model: &Path, name: &str, fault: Fault, web: Option<PathBuf>) -> FaultServer {
        let listener = TcpListener::bind("127.0.0.1:0").expect("binding a loopback port");
        let addr = listener.local_addr().unwrap();
        let body = Arc::new(std::fs::read(model).expect("reading the model"));
        let requests = Arc::new(AtomicUsize::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let state = Arc::new(State {
            body,
            name: name.to_string(),
            fault,
            web,
            model_requests: AtomicUsize::new(0),
        });
        let (counter, stopping) = (requests.clone(), stop.clone());
        std::thread::spawn(move || {
            for conn in listener.incoming() {
                if stopping.load(Ordering::SeqCst) {
                    return;
                }
                let Ok(s) = conn else { continue };
                let (state, counter) = (state.clone(), counter.clone());
                std::thread::spawn(move || {
                    counter.fetch_add(1, Ordering::SeqCst);
                    let _ = serve(s, &state);
                });
            }
        });
        FaultServer {
            addr,
            requests,
            stop,
        }
    }

    /// `http://ADDR` + `path`.
    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    /// Requests received so far (all paths).
    #[allow(dead_code)]
    pub fn requests(&self) -> usize {
        self.requests.load(Ordering::SeqCst)
    }
}

impl Drop for FaultServer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop so that it sees the flag.
        let _ = TcpStream::connect(self.addr);
    }
}

struct State {
    body: Arc<Vec<u8>>,
    name: String,
    fault: Fault,
    web: Option<PathBuf>,
    /// Requests for the model so far.
    model_requests: AtomicUsize,
}

/// `bytes=A-B` / `bytes=A-` against a file of `len` bytes.
fn parse_range(v: &str, len: u64) -> Option<Range<u64>> {
    let (a, b) = v.trim().strip_prefix("bytes=")?.split_once('-')?;
    let a: u64 = a.trim().parse().ok()?;
    let b: u64 = match b.trim() {
        "" => len - 1,
        b => b.parse::<u64>().ok()?.min(len - 1),
    };
    (a <= b).then_some(a..b + 1)
}

fn head(status: &str, headers: &[(&str, String)]) -> Vec<u8> {
    let mut h = format!("HTTP/1.1 {status}\r\nConnection: close\r\n");
    for (k, v) in headers {
        h.push_str(&format!("{k}: {v}\r\n"));
    }
    h.push_str("\r\n");
    h.into_bytes()
}

fn serve(mut s: TcpStream, st: &State) -> std::io::Result<()> {
    let mut reader = BufReader::new(s.try_clone()?);
    let mut request_line = String::new();
    if reader.read_line(&mut request_line)? == 0 {
        return Ok(());
    }
    let (mut range, mut if_range) = (None, None);
    let len = st.body.len() as u64;
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line)? == 0 {
            return Ok(());
        }
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':') {
            match k.to_ascii_lowercase().as_str() {
                "range" => range = parse_range(v, len),
                "if-range" => if_range = Some(v.trim().to_string()),
                _ => {}
            }
        }
    }
    let path = request_line
        .split_whitespace()
        .nth(1)
        .unwrap_or("/")
        .split('?')
        .next()
        .unwrap_or("/")
        .to_string();
    if path == "/models" {
        let json = format!(
            r#"[{{"name":"{0}","url":"/models/{0}","bytes":{len},"modified":"2026-01-01T00:00:00Z"}}]"#,
            st.name
        );
        s.write_all(&head(
            "200 OK",
            &[
                ("Content-Type", "application/json".into()),
                ("Content-Length", json.len().to_string()),
            ],
        ))?;
        return s.write_all(json.as_bytes());
    }
    if path == format!("/models/{}", st.name) {
        let n = st.model_requests.fetch_add(1, Ordering::SeqCst);
        return model(s, st, n, range, if_range);
    }
    static_file(s, st.web.as_deref(), &path)
}

/// The web player's files; 404 for anything else.
fn static_file(mut s: TcpStream, web: Option<&Path>, path: &str) -> std::io::Result<()> {
    let rel = if path == "/" {
        "index.html"
    } else {
        &path[1..]
    };
    let file = web
        .filter(|_| !rel.split('/').any(|p| p == ".." || p.is_empty()))
        .map(|w| w.join(rel))
        .and_then(|p| std::fs::read(p).ok());
    let Some(bytes) = file else {
        return s.write_all(&head("404 Not Found", &[("Content-Length", "0".into())]));
    };
    let ext = rel.rsplit('.').next().unwrap_or("");
    let ctype = match ext {
        "html" => "text/html; charset=utf-8",
        "js" | "mjs" => "text/javascript",
        "css" => "text/css",
        "json" => "application/json",
        "png" => "image/png",
        _ => "text/plain; charset=utf-8",
    };
    s.write_all(&head(
        "200 OK",
        &[
            ("Content-Type", ctype.into()),
            ("Content-Length", bytes.len().to_string()),
        ],
    ))?;
    s.write_all(&bytes)
}

/// Request number `n` for the model.
fn model(
    mut s: TcpStream,
    st: &State,
    n: usize,
    range: Option<Range<u64>>,
    if_range: Option<String>,
) -> std::io::Result<()> {
    let body = &st.body[..];
    let len = body.len() as u64;
    let octets = ("Content-Type", "application/octet-stream".to_string());
    let whole = |s: &mut TcpStream, etag: &str| {
        s.write_all(&head(
            "200 OK",
            &[
                octets.clone(),
                ("Content-Length", len.to_string()),
                ("ETag", etag.to_string()),
            ],
        ))?;
        s.write_all(body)
    };
    let partial = |s: &mut TcpStream, r: &Range<u64>, total: u64, etag: &str| {
        s.write_all(&head(
            "206 Partial Content",
            &[
                octets.clone(),
                ("Content-Length", (r.end - r.start).to_string()),
                (
                    "Content-Range",
                    format!("bytes {}-{}/{total}", r.start, r.end - 1),
                ),
                ("ETag", etag.to_string()),
            ],
        ))
    };
    let part = |r: &Range<u64>| &body[r.start as usize..r.end as usize];
    let first = n == 0;
    match (st.fault, range) {
        (Fault::RedirectLoop, _) => s.write_all(&head(
            "302 Found",
            &[
                ("Location", format!("/models/{}", st.name)),
                ("Content-Length", "0".into()),
            ],
        )),
        (Fault::EndlessBody, _) => {
            s.write_all(&head("200 OK", std::slice::from_ref(&octets)))?;
            s.write_all(body)?;
            let zeros = vec![0u8; 64 << 10];
            // Until the client goes away (the write then fails).
            loop {
                s.write_all(&zeros)?;
            }
        }
        (Fault::IgnoresRange, _) | (_, None) => whole(&mut s, "\"v1\""),
        (Fault::ChangedMidStream, Some(_)) if !first && if_range.as_deref() != Some("\"v2\"") => {
            whole(&mut s, "\"v2\"")
        }
        (Fault::Good, Some(r)) | (Fault::ChangedMidStream, Some(r)) => {
            partial(&mut s, &r, len, "\"v1\"")?;
            s.write_all(part(&r))
        }
        (Fault::WrongRange | Fault::ShortBody | Fault::Stall, Some(r)) if first => {
            partial(&mut s, &r, len, "\"v1\"")?;
            s.write_all(part(&r))
        }
        (Fault::DripFeed, Some(r)) => {
            partial(&mut s, &r, len, "\"v1\"")?;
            for b in part(&r) {
                s.write_all(&[*b])?;
                s.flush()?;
                std::thread::sleep(DRIP);
            }
            Ok(())
        }
        (Fault::WrongTotal, Some(r)) => {
            partial(&mut s, &r, len + 1000, "\"v1\"")?;
            s.write_all(part(&r))
        }
        (Fault::WrongRange, Some(r)) => {
            let shifted = r.start + 1..(r.end + 1).min(len);
            partial(&mut s, &shifted, len, "\"v1\"")?;
            s.write_all(part(&shifted))
        }
        (Fault::ShortBody, Some(r)) => {
            partial(&mut s, &r, len, "\"v1\"")?;
            let p = part(&r);
            s.write_all(&p[..p.len() / 2])
        }
        (Fault::Stall, Some(r)) => {
            partial(&mut s, &r, len, "\"v1\"")?;
            let p = part(&r);
            s.write_all(&p[..p.len().min(100)])?;
            s.flush()?;
            // Nothing more until the client gives up (the read then returns 0 or fails).
            let mut buf = [0u8; 1];
            let _ = s.set_read_timeout(Some(Duration::from_secs(600)));
            let _ = std::io::Read::read(&mut s, &mut buf);
            Ok(())
        }
    }
}
