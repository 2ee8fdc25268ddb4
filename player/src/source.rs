//! Where a `.msth` file's bytes come from: a local file or an HTTP(S) URL read with Range requests.
//!
//! [`ByteSource`] is the one interface the streaming layer needs: the total length and "give me
//! bytes `a..b`". [`HttpSource`] implements it with RFC 9110 Range requests over HTTP/1.1, plain
//! (`http://`) or over TLS (`https://`), with `ureq`, and
//! - timeouts on connecting and on every read, so a stalled server cannot hang the player;
//! - retries with exponential back-off for failures that can heal (connection errors, timeouts,
//!   truncated bodies, 5xx, 429), none for those that cannot (4xx, a certificate refused, a
//!   server that ignores ranges after promising them, a file that changed on the server);
//! - `If-Range` with the first response's validator on every later request, so a file replaced
//!   on the server mid-stream is detected (the server answers 200 instead of 206) instead of
//!   splicing two files;
//! - every response checked: status, `Content-Range` equal to what was asked, body length exact.
//!
//! A server that does not do ranges at all (200 to the first request) still works: the whole file
//! is downloaded once (bounded by [`HttpOptions::max_file_bytes`]) and served from memory.
//!
//! TLS is rustls with the `ring` crypto provider (it builds with a C compiler alone; aws-lc-rs
//! would need cmake). Server certificates are checked against a bundled root set, Mozilla's
//! (`webpki-roots`), not the operating system's store: the same roots on every platform and in
//! minimal containers that ship no `/etc/ssl`, no extra crates, and a build that behaves the same
//! in CI as on a laptop. Hosts with publicly trusted certificates (object stores, CDNs, GitHub
//! Pages) need nothing more. A private CA or a self-signed server is trusted through
//! [`HttpOptions::ca_cert_file`], a PEM file whose certificates then *replace* the bundled roots
//! (as `curl --cacert` and OpenSSL's `SSL_CERT_FILE` do); pointing it at the system bundle
//! (`/etc/ssl/certs/ca-certificates.crt`) gives the platform's roots. A refused certificate is a
//! fatal (not retried) error naming the host and the reason.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Everything that can go wrong reading bytes.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// (The message carries the cause, so it is not also chained as a source.)
    #[error("{path}: {error}")]
    File {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error("{url}: {message}")]
    Http { url: String, message: String },
    /// The certificate file of [`HttpOptions::ca_cert_file`] is unreadable or holds no usable
    /// certificate.
    #[error("CA certificate file {}: {message}", path.display())]
    CaCerts { path: PathBuf, message: String },
    #[error("{url}: {message} (gave up after {attempts} attempts)")]
    GaveUp {
        url: String,
        message: String,
        attempts: u32,
    },
    #[error("{what}: bytes {start}..{end} are outside the file ({len} bytes)")]
    OutOfRange {
        what: String,
        start: u64,
        end: u64,
        len: u64,
    },
}

/// Random-access bytes of one file.
pub trait ByteSource: Send + Sync {
    /// Total length in bytes.
    fn len(&self) -> u64;
    /// Whether the file is empty.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Exactly the bytes of `range` (end exclusive).
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, SourceError>;
    /// A name for messages (path or URL).
    fn name(&self) -> &str;
    /// Transfer statistics so far.
    fn stats(&self) -> TransferStats;
}

/// Counters of a source (requests include retries).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct TransferStats {
    pub requests: u64,
    pub retries: u64,
    pub bytes: u64,
}

/// A shared source is a source (tests keep a handle to inspect what was read).
impl<T: ByteSource + ?Sized> ByteSource for std::sync::Arc<T> {
    fn len(&self) -> u64 {
        self.as_ref().len()
    }
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, SourceError> {
        self.as_ref().read_range(range)
    }
    fn name(&self) -> &str {
        self.as_ref().name()
    }
    fn stats(&self) -> TransferStats {
        self.as_ref().stats()
    }
}

#[derive(Default)]
struct Counters {
    requests: AtomicU64,
    retries: AtomicU64,
    bytes: AtomicU64,
}

impl Counters {
    fn snapshot(&self) -> TransferStats {
        TransferStats {
            requests: self.requests.load(Ordering::Relaxed),
            retries: self.retries.load(Ordering::Relaxed),
            bytes: self.bytes.load(Ordering::Relaxed),
        }
    }
}

fn check_range(what: &str, range: &Range<u64>, len: u64) -> Result<(), SourceError> {
    if range.start > range.end || range.end > len {
        return Err(SourceError::OutOfRange {
            what: what.to_string(),
            start: range.start,
            end: range.end,
            len,
        });
    }
    Ok(())
}

/// A local file.
pub struct FileSource {
    path: PathBuf,
    name: String,
    file: Mutex<File>,
    len: u64,
    counters: Counters,
}

impl FileSource {
    pub fn open(path: &Path) -> Result<Self, SourceError> {
        let err = |error| SourceError::File {
            path: path.to_path_buf(),
            error,
        };
        let file = File::open(path).map_err(err)?;
        let meta = file.metadata().map_err(err)?;
        if !meta.is_file() {
            return Err(err(std::io::Error::other("not a regular file")));
        }
        Ok(FileSource {
            path: path.to_path_buf(),
            name: path.display().to_string(),
            file: Mutex::new(file),
            len: meta.len(),
            counters: Counters::default(),
        })
    }
}

impl ByteSource for FileSource {
    fn len(&self) -> u64 {
        self.len
    }
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, SourceError> {
        check_range(&self.name, &range, self.len)?;
        let mut buf = vec![0u8; (range.end - range.start) as usize];
        let mut f = self.file.lock().unwrap_or_else(|p| p.into_inner());
        f.seek(SeekFrom::Start(range.start))
            .and_then(|_| f.read_exact(&mut buf))
            .map_err(|error| SourceError::File {
                path: self.path.clone(),
                error,
            })?;
        self.counters.requests.fetch_add(1, Ordering::Relaxed);
        self.counters
            .bytes
            .fetch_add(buf.len() as u64, Ordering::Relaxed);
        Ok(buf)
    }
    fn name(&self) -> &str {
        &self.name
    }
    fn stats(&self) -> TransferStats {
        self.counters.snapshot()
    }
}

/// Network settings of [`HttpSource`].
#[derive(Clone, Debug)]
pub struct HttpOptions {
    /// Time to establish a connection.
    pub connect_timeout: Duration,
    /// Longest wait for any single read (headers or body): a stalled server fails after this.
    pub read_timeout: Duration,
    /// Longest time for one whole request, body included (a trickling server fails after this).
    pub request_timeout: Duration,
    /// Retries after the first attempt, for failures that can heal.
    pub retries: u32,
    /// First back-off; doubled after every retry, at most 16 times this.
    pub backoff: Duration,
    /// Bytes asked for by the first request (the header and index usually fit).
    pub probe_bytes: u64,
    /// Largest file accepted from a server that ignores ranges (downloaded whole).
    pub max_file_bytes: u64,
    /// PEM file of the certificates trusted for `https://` instead of the bundled Mozilla roots:
    /// a private CA's certificate, or a self-signed server's own. `None`: the bundled roots.
    pub ca_cert_file: Option<PathBuf>,
}

impl Default for HttpOptions {
    fn default() -> Self {
        HttpOptions {
            connect_timeout: Duration::from_secs(5),
            read_timeout: Duration::from_secs(15),
            request_timeout: Duration::from_secs(300),
            retries: 4,
            backoff: Duration::from_millis(200),
            probe_bytes: 64 << 10,
            max_file_bytes: 4 << 30,
            ca_cert_file: None,
        }
    }
}

/// Largest CA certificate file read (a full system bundle is about 200 KiB).
const MAX_CA_FILE_BYTES: u64 = 16 << 20;

/// The certificates of a PEM file, each checked to be usable as a trust anchor.
fn load_ca_certs(path: &Path) -> Result<Vec<ureq::tls::Certificate<'static>>, SourceError> {
    let err = |message: String| SourceError::CaCerts {
        path: path.to_path_buf(),
        message,
    };
    let file = File::open(path).map_err(|e| err(e.to_string()))?;
    let len = file.metadata().map_err(|e| err(e.to_string()))?.len();
    if len > MAX_CA_FILE_BYTES {
        return Err(err(format!(
            "{len} bytes, more than the {MAX_CA_FILE_BYTES} a certificate file may have"
        )));
    }
    let mut pem = Vec::with_capacity(len as usize);
    file.take(MAX_CA_FILE_BYTES)
        .read_to_end(&mut pem)
        .map_err(|e| err(e.to_string()))?;
    let mut certs = Vec::new();
    for item in ureq::tls::parse_pem(&pem) {
        match item {
            Ok(ureq::tls::PemItem::Certificate(c)) => certs.push(c.to_owned()),
            Ok(_) => {} // private keys and the like: not trust anchors
            Err(e) => return Err(err(format!("malformed PEM: {e}"))),
        }
    }
    if certs.is_empty() {
        return Err(err(
            "no certificate in it (expected PEM blocks `-----BEGIN CERTIFICATE-----`)".into(),
        ));
    }
    let mut store = rustls::RootCertStore::empty();
    for (i, c) in certs.iter().enumerate() {
        let der = rustls::pki_types::CertificateDer::from(c.der());
        store
            .add(der)
            .map_err(|e| err(format!("certificate {} of {}: {e}", i + 1, certs.len())))?;
    }
    Ok(certs)
}

/// The host of `url` (no scheme, user, port or path), for messages.
fn url_host(url: &str) -> &str {
    let rest = url.split_once("://").map_or(url, |(_, r)| r);
    let authority = rest.split(['/', '?', '#']).next().unwrap_or_default();
    let host_port = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    if let Some(v6) = host_port.strip_prefix('[') {
        return v6.split_once(']').map_or(v6, |(h, _)| h);
    }
    host_port.split_once(':').map_or(host_port, |(h, _)| h)
}

/// A `.msth` file behind an `http://` or `https://` URL.
pub struct HttpSource {
    url: String,
    /// What [`describe`] needs to explain a TLS failure.
    tls: TlsContext,
    agent: ureq::Agent,
    opts: HttpOptions,
    len: u64,
    /// `If-Range` value: the first response's strong ETag, else its Last-Modified.
    validator: Option<String>,
    /// The first response's bytes (from offset 0), served without another request.
    head: Vec<u8>,
    /// Whether the server answered the first request with 206.
    ranges: bool,
    counters: Counters,
}

/// What the first response told.
struct Probe {
    len: u64,
    validator: Option<String>,
    head: Vec<u8>,
    ranges: bool,
}

/// The host and the roots its certificate was checked against, for messages.
struct TlsContext {
    host: String,
    /// `None`: the bundled Mozilla roots.
    ca_cert_file: Option<PathBuf>,
}

/// A failed attempt and whether trying again can help.
struct Attempt {
    message: String,
    retryable: bool,
}

impl Attempt {
    fn fatal(message: impl Into<String>) -> Self {
        Attempt {
            message: message.into(),
            retryable: false,
        }
    }
    fn transient(message: impl Into<String>) -> Self {
        Attempt {
            message: message.into(),
            retryable: true,
        }
    }
}

fn describe(e: &ureq::Error, tls: &TlsContext) -> Attempt {
    use ureq::Error as E;
    match e {
        E::Timeout(t) => Attempt::transient(format!("timed out ({t})")),
        E::Io(io) => match io
            .get_ref()
            .and_then(|inner| inner.downcast_ref::<rustls::Error>())
        {
            // rustls reports handshake failures (a refused certificate) as I/O errors.
            Some(t) => Attempt::fatal(tls_message(t, tls)),
            None => Attempt::transient(format!("connection error: {io}")),
        },
        E::Rustls(t) => Attempt::fatal(tls_message(t, tls)),
        E::Tls(m) => Attempt::fatal(format!("TLS with {}: {m}", tls.host)),
        E::ConnectionFailed => Attempt::transient("connection failed"),
        E::HostNotFound => Attempt::fatal("host not found"),
        E::Protocol(p) => Attempt::transient(format!("HTTP protocol error: {p}")),
        E::BodyExceedsLimit(n) => Attempt::fatal(format!("response body larger than {n} bytes")),
        E::BadUri(u) => Attempt::fatal(format!("bad URL: {u}")),
        other => Attempt::fatal(other.to_string()),
    }
}

/// A TLS failure in words: the host, what was wrong, and for an untrusted certificate how to
/// trust it.
fn tls_message(e: &rustls::Error, tls: &TlsContext) -> String {
    use rustls::{CertificateError as C, Error as R};
    let host = &tls.host;
    let (roots, hint) = match &tls.ca_cert_file {
        Some(p) => (
            format!("the certificates in {}", p.display()),
            "is that the CA (or the self-signed certificate) this server uses?",
        ),
        None => (
            "the bundled Mozilla roots".to_string(),
            "for a private CA or a self-signed server, give that certificate as a PEM file: \
             `msth play --ca-cert FILE` or SSL_CERT_FILE",
        ),
    };
    match e {
        R::InvalidCertificate(C::UnknownIssuer) => format!(
            "TLS: the certificate of {host} is not trusted: its issuer is not among {roots} \
             (unknown issuer; {hint})"
        ),
        R::InvalidCertificate(C::BadSignature) => format!(
            "TLS: the certificate of {host} is not trusted: its signature does not verify \
             against {roots} (bad signature)"
        ),
        R::InvalidCertificate(c) => {
            format!("TLS: the certificate of {host} is refused: {c}")
        }
        R::InvalidMessage(_) | R::InappropriateMessage { .. } => format!(
            "TLS handshake with {host} failed: {e} (does the server speak https on this port? \
             plain-HTTP servers need an http:// URL)"
        ),
        R::AlertReceived(a) => format!("TLS handshake with {host} failed: the server sent {a:?}"),
        other => format!("TLS with {host} failed: {other}"),
    }
}

/// Parses `Content-Range: bytes FIRST-LAST/TOTAL` (TOTAL may be `*`).
fn parse_content_range(v: &str) -> Option<(u64, u64, Option<u64>)> {
    let rest = v.trim().strip_prefix("bytes ")?;
    let (span, total) = rest.split_once('/')?;
    let (a, b) = span.split_once('-')?;
    let (a, b): (u64, u64) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
    let total = match total.trim() {
        "*" => None,
        t => Some(t.parse().ok()?),
    };
    if b < a || total.is_some_and(|t| b >= t) {
        return None;
    }
    Some((a, b, total))
}

fn status_attempt(status: u16) -> Attempt {
    let reason = match status {
        404 => " Not Found",
        403 => " Forbidden",
        416 => " Range Not Satisfiable",
        500 => " Internal Server Error",
        503 => " Service Unavailable",
        _ => "",
    };
    let message = format!("HTTP {status}{reason}");
    if status >= 500 || status == 429 || status == 408 {
        Attempt::transient(message)
    } else {
        Attempt::fatal(message)
    }
}

impl HttpSource {
    /// Connects, learns the file's length and validator, and keeps the first
    /// [`HttpOptions::probe_bytes`] bytes.
    pub fn open(url: &str, opts: HttpOptions) -> Result<Self, SourceError> {
        let http_err = |message: String| SourceError::Http {
            url: url.to_string(),
            message,
        };
        if !(url.starts_with("http://") || url.starts_with("https://")) {
            return Err(http_err("not an http:// or https:// URL".into()));
        }
        let roots = match &opts.ca_cert_file {
            Some(p) if url.starts_with("https://") => ureq::tls::RootCerts::from(load_ca_certs(p)?),
            _ => ureq::tls::RootCerts::WebPki,
        };
        let tls_config = ureq::tls::TlsConfig::builder()
            .provider(ureq::tls::TlsProvider::Rustls)
            .root_certs(roots)
            // ring, whatever provider another part of the process may have made the default.
            .unversioned_rustls_crypto_provider(Arc::new(rustls::crypto::ring::default_provider()))
            .build();
        let config = ureq::Agent::config_builder()
            .tls_config(tls_config)
            .http_status_as_error(false)
            .timeout_connect(Some(opts.connect_timeout))
            .timeout_per_read(Some(opts.read_timeout))
            .timeout_per_call(Some(opts.request_timeout))
            .max_redirects(4)
            .user_agent(concat!("msth-player/", env!("CARGO_PKG_VERSION")))
            .build();
        let mut src = HttpSource {
            url: url.to_string(),
            tls: TlsContext {
                host: url_host(url).to_string(),
                ca_cert_file: opts.ca_cert_file.clone(),
            },
            agent: ureq::Agent::new_with_config(config),
            opts,
            len: 0,
            validator: None,
            head: Vec::new(),
            ranges: false,
            counters: Counters::default(),
        };
        let probe = src.opts.probe_bytes.max(1);
        let p = src.retry("", || src.first_request(probe))?;
        src.len = p.len;
        src.validator = p.validator;
        src.head = p.head;
        src.ranges = p.ranges;
        Ok(src)
    }

    /// Whether the server honours Range requests (false: the whole file is in memory).
    pub fn supports_ranges(&self) -> bool {
        self.ranges
    }

    /// Runs `f` until it succeeds, fails for good, or has used up the retries; `context`
    /// prefixes the message (e.g. the byte range).
    fn retry<T>(
        &self,
        context: &str,
        mut f: impl FnMut() -> Result<T, Attempt>,
    ) -> Result<T, SourceError> {
        let mut wait = self.opts.backoff;
        let mut attempts = 0;
        loop {
            attempts += 1;
            self.counters.requests.fetch_add(1, Ordering::Relaxed);
            let a = match f() {
                Ok(v) => return Ok(v),
                Err(a) => a,
            };
            let message = format!("{context}{}", a.message);
            if !a.retryable {
                let url = self.url.clone();
                return Err(SourceError::Http { url, message });
            }
            if attempts > self.opts.retries {
                let url = self.url.clone();
                return Err(SourceError::GaveUp {
                    url,
                    message,
                    attempts,
                });
            }
            self.counters.retries.fetch_add(1, Ordering::Relaxed);
            std::thread::sleep(wait);
            wait = (wait * 2).min(self.opts.backoff * 16);
        }
    }

    fn first_request(&self, probe: u64) -> Result<Probe, Attempt> {
        let mut resp = self
            .agent
            .get(&self.url)
            .header("Range", format!("bytes=0-{}", probe - 1))
            .call()
            .map_err(|e| describe(&e, &self.tls))?;
        let status = resp.status().as_u16();
        let header = |name: &str| {
            resp.headers()
                .get(name)
                .and_then(|v| v.to_str().ok())
                .map(str::to_string)
        };
        let etag = header("etag").filter(|e| !e.starts_with("W/"));
        let validator = etag.or_else(|| header("last-modified"));
        match status {
            206 => {
                let cr = header("content-range")
                    .ok_or_else(|| Attempt::fatal("206 response without Content-Range"))?;
                let (a, b, total) = parse_content_range(&cr)
                    .ok_or_else(|| Attempt::fatal(format!("malformed Content-Range `{cr}`")))?;
                let total = total
                    .ok_or_else(|| Attempt::fatal("the server does not tell the file length"))?;
                if a != 0 || b >= probe {
                    return Err(Attempt::fatal(format!(
                        "asked for bytes 0-{}, got Content-Range `{cr}`",
                        probe - 1
                    )));
                }
                let want = b + 1;
                let head = self.read_body(&mut resp, want)?;
                Ok(Probe {
                    len: total,
                    validator,
                    head,
                    ranges: true,
                })
            }
            200 => {
                // No range support: take the whole file, bounded.
                let declared = header("content-length").and_then(|v| v.parse::<u64>().ok());
                if let Some(n) = declared {
                    if n > self.opts.max_file_bytes {
                        return Err(Attempt::fatal(format!(
                            "the server ignores Range requests and the file is {n} bytes, more \
                             than the {} this player downloads whole",
                            self.opts.max_file_bytes
                        )));
                    }
                }
                let body = resp
                    .body_mut()
                    .with_config()
                    .limit(self.opts.max_file_bytes.saturating_add(1))
                    .read_to_vec()
                    .map_err(|e| describe(&e, &self.tls))?;
                if let Some(n) = declared {
                    if body.len() as u64 != n {
                        return Err(Attempt::transient(format!(
                            "body ended after {} of {n} bytes",
                            body.len()
                        )));
                    }
                }
                self.counters
                    .bytes
                    .fetch_add(body.len() as u64, Ordering::Relaxed);
                Ok(Probe {
                    len: body.len() as u64,
                    validator: None,
                    head: body,
                    ranges: false,
                })
            }
            416 => Err(Attempt::fatal("the file is empty (HTTP 416)")),
            s => Err(status_attempt(s)),
        }
    }

    fn read_body(
        &self,
        resp: &mut ureq::http::Response<ureq::Body>,
        want: u64,
    ) -> Result<Vec<u8>, Attempt> {
        // ureq fails a read once the limit is reached, so allow one byte more than wanted and
        // check the length here.
        let body = resp
            .body_mut()
            .with_config()
            .limit(want + 1)
            .read_to_vec()
            .map_err(|e| match e {
                ureq::Error::BodyExceedsLimit(_) => {
                    Attempt::fatal(format!("body longer than the {want} bytes announced"))
                }
                e => describe(&e, &self.tls),
            })?;
        self.counters
            .bytes
            .fetch_add(body.len() as u64, Ordering::Relaxed);
        if body.len() as u64 > want {
            return Err(Attempt::fatal(format!(
                "body longer than the {want} bytes announced"
            )));
        }
        if (body.len() as u64) < want {
            return Err(Attempt::transient(format!(
                "body ended after {} of {want} bytes",
                body.len()
            )));
        }
        Ok(body)
    }

    fn range_request(&self, range: &Range<u64>) -> Result<Vec<u8>, Attempt> {
        let mut req = self
            .agent
            .get(&self.url)
            .header("Range", format!("bytes={}-{}", range.start, range.end - 1));
        if let Some(v) = &self.validator {
            req = req.header("If-Range", v.as_str());
        }
        let mut resp = req.call().map_err(|e| describe(&e, &self.tls))?;
        match resp.status().as_u16() {
            206 => {}
            200 => {
                return Err(Attempt::fatal(
                    "the file changed on the server while it was being streamed (If-Range \
                     answered with the whole file); start again",
                ))
            }
            s => return Err(status_attempt(s)),
        }
        let cr = resp
            .headers()
            .get("content-range")
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default()
            .to_string();
        match parse_content_range(&cr) {
            Some((a, b, total))
                if a == range.start
                    && b + 1 == range.end
                    && total.is_none_or(|t| t == self.len) => {}
            _ => {
                return Err(Attempt::fatal(format!(
                    "asked for bytes {}-{} of {}, got Content-Range `{cr}`",
                    range.start,
                    range.end - 1,
                    self.len
                )))
            }
        }
        self.read_body(&mut resp, range.end - range.start)
    }
}

impl ByteSource for HttpSource {
    fn len(&self) -> u64 {
        self.len
    }
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, SourceError> {
        check_range(&self.url, &range, self.len)?;
        if range.end <= self.head.len() as u64 {
            return Ok(self.head[range.start as usize..range.end as usize].to_vec());
        }
        if range.is_empty() {
            return Ok(Vec::new());
        }
        let context = format!("bytes {}-{}: ", range.start, range.end - 1);
        self.retry(&context, || self.range_request(&range))
    }
    fn name(&self) -> &str {
        &self.url
    }
    fn stats(&self) -> TransferStats {
        self.counters.snapshot()
    }
}

/// Opens `location`: an `http://` or `https://` URL, or a local path.
pub fn open(location: &str, http: &HttpOptions) -> Result<Box<dyn ByteSource>, SourceError> {
    if location.starts_with("http://") || location.starts_with("https://") {
        Ok(Box::new(HttpSource::open(location, http.clone())?))
    } else {
        Ok(Box::new(FileSource::open(Path::new(location))?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn content_range_parsing() {
        assert_eq!(
            parse_content_range("bytes 0-99/1000"),
            Some((0, 99, Some(1000)))
        );
        assert_eq!(parse_content_range("bytes 5-5/*"), Some((5, 5, None)));
        assert_eq!(parse_content_range("bytes 9-5/100"), None);
        assert_eq!(parse_content_range("bytes 0-100/100"), None);
        assert_eq!(parse_content_range("items 0-1/2"), None);
        assert_eq!(parse_content_range("bytes 0-x/2"), None);
    }

    #[test]
    fn url_hosts() {
        assert_eq!(
            url_host("https://127.0.0.1:8443/models/a.msth"),
            "127.0.0.1"
        );
        assert_eq!(url_host("https://example.org/a.msth?x=1"), "example.org");
        assert_eq!(url_host("http://user:pw@host.example:80/x"), "host.example");
        assert_eq!(url_host("https://[::1]:8443/x"), "::1");
        assert_eq!(url_host("https://cdn.example#frag"), "cdn.example");
    }

    #[test]
    fn ca_cert_files_are_checked() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.pem");
        let e = load_ca_certs(&missing).unwrap_err().to_string();
        assert!(e.contains("missing.pem"), "{e}");
        let empty = dir.path().join("empty.pem");
        std::fs::write(&empty, "not a certificate\n").unwrap();
        let e = load_ca_certs(&empty).unwrap_err().to_string();
        assert!(e.contains("no certificate"), "{e}");
        // A well-formed PEM block whose contents are not a certificate.
        let junk = dir.path().join("junk.pem");
        std::fs::write(
            &junk,
            "-----BEGIN CERTIFICATE-----\nAAECAwQFBgcICQ==\n-----END CERTIFICATE-----\n",
        )
        .unwrap();
        let e = load_ca_certs(&junk).unwrap_err().to_string();
        assert!(e.contains("certificate 1 of 1"), "{e}");
        // And HttpSource::open reports it before any connection.
        let opts = HttpOptions {
            ca_cert_file: Some(junk.clone()),
            ..HttpOptions::default()
        };
        let e = HttpSource::open("https://127.0.0.1:9/x.msth", opts)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("junk.pem"), "{e}");
    }

    #[test]
    fn file_source_reads_and_refuses_out_of_range() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f.bin");
        std::fs::write(&p, (0u8..200).collect::<Vec<_>>()).unwrap();
        let s = FileSource::open(&p).unwrap();
        assert_eq!(s.len(), 200);
        assert_eq!(s.read_range(10..13).unwrap(), vec![10, 11, 12]);
        assert!(matches!(
            s.read_range(150..201),
            Err(SourceError::OutOfRange { .. })
        ));
        assert!(FileSource::open(dir.path()).is_err());
    }
}
