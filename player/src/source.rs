//! Where a `.msth` file's bytes come from: a local file or an HTTP(S) URL read with Range requests.
//!
//! [`ByteSource`] is the one interface the streaming layer needs: the total length and "give me
//! bytes `a..b`". [`HttpSource`] implements it with RFC 9110 Range requests over HTTP/1.1, plain
//! (`http://`) or over TLS (`https://`), with `ureq`, and
//! - a stall deadline on every read ([`HttpOptions::read_timeout`]) and a deadline on every read of
//!   the file, retries included ([`HttpOptions::request_timeout`]), optionally an overall one
//!   ([`HttpOptions::deadline`]), so a stalled or trickling server cannot hang the player; the
//!   messages say which bytes were awaited and how many had come;
//! - retries with exponential back-off for failures that can heal (connection errors, stalls,
//!   truncated bodies, 5xx, 429), none for those that cannot (4xx, a certificate refused, a
//!   server that ignores ranges after promising them, a file that changed on the server);
//! - `If-Range` with the first response's validator on every later request, so a file replaced
//!   on the server mid-stream is detected (the server answers 200 instead of 206) instead of
//!   splicing two files;
//! - every response checked: status, `Content-Range` equal to what was asked, body length exact,
//!   and never more read than was asked for, whatever the server sends.
//!
//! Lengths: before the file's header is read, a response is bounded by the prefix being read
//! (the first request asks for [`HttpOptions::probe_bytes`]); once the stream has parsed the
//! header it calls [`ByteSource::limit_to`] with the length the header declares, and from then on
//! nothing past it is read. A length the server declared (`Content-Range` total, `Content-Length`)
//! that disagrees with the header is an error naming both numbers.
//!
//! A server that does not do ranges at all (200 to the first request) still works: its body is
//! read as a stream ([`ByteSource::sequential`]), the first bytes kept, the rest handed to the
//! decoder in file order as it arrives, never buffered whole; a body without `Content-Length`
//! (even an endless one) is read only up to the length the header declares.
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
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

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
    /// A read of the file did not complete by its deadline.
    #[error("{url}: {what}not complete within the {secs:.0} s deadline ({message})")]
    Deadline {
        url: String,
        /// The byte range, as `bytes A-B: ` (empty for the first request).
        what: String,
        secs: f64,
        /// How far it got, or the last attempt's failure.
        message: String,
    },
    #[error("{what}: bytes {start}..{end} are outside the file ({len} bytes)")]
    OutOfRange {
        what: String,
        start: u64,
        end: u64,
        len: u64,
    },
}

/// [`ByteSource::len`] of a source whose length nobody has declared yet: a server that answers
/// 200 without `Content-Length`, before [`ByteSource::limit_to`].
pub const UNKNOWN_LEN: u64 = u64::MAX;

/// Random-access bytes of one file.
pub trait ByteSource: Send + Sync {
    /// Total length in bytes ([`UNKNOWN_LEN`] while it is not known).
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
    /// The file's header declares `len` bytes: nothing past them is read from now on, and a
    /// source whose server declared another length fails, naming both. The default accepts it
    /// (a local file longer than its index is the decoder's business).
    fn limit_to(&self, len: u64) -> Result<(), SourceError> {
        let _ = len;
        Ok(())
    }
    /// Whether reads should go forward through the file: a server that ignores Range requests
    /// streams its body once from the start, and a read behind what has streamed costs a new
    /// download of everything before it.
    fn sequential(&self) -> bool {
        false
    }
    /// The request in progress, for messages about a wait that ran out: which bytes, how many
    /// have come, how long since the last one.
    fn activity(&self) -> Option<String> {
        None
    }
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
    fn limit_to(&self, len: u64) -> Result<(), SourceError> {
        self.as_ref().limit_to(len)
    }
    fn sequential(&self) -> bool {
        self.as_ref().sequential()
    }
    fn activity(&self) -> Option<String> {
        self.as_ref().activity()
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
    /// The stall deadline: the longest wait for any single read (response head or body). A
    /// request that receives nothing for this long fails, and is retried while its deadline
    /// leaves time.
    pub read_timeout: Duration,
    /// The deadline of one read of the file: a byte range, with every attempt, back-off and body
    /// included (a trickling server fails after this).
    pub request_timeout: Duration,
    /// An overall deadline: no read goes on past this moment (`None`: none beyond
    /// `request_timeout`). `msth inspect --deadline` sets it.
    pub deadline: Option<Instant>,
    /// Retries after the first attempt, for failures that can heal.
    pub retries: u32,
    /// First back-off; doubled after every retry, at most 16 times this.
    pub backoff: Duration,
    /// Bytes asked for by the first request (the header and index usually fit).
    pub probe_bytes: u64,
    /// PEM file of the certificates trusted for `https://` instead of the bundled Mozilla roots:
    /// a private CA's certificate, or a self-signed server's own. `None`: the bundled roots.
    pub ca_cert_file: Option<PathBuf>,
}

impl Default for HttpOptions {
    fn default() -> Self {
        HttpOptions {
            connect_timeout: Duration::from_secs(5),
            read_timeout: Duration::from_secs(15),
            request_timeout: Duration::from_secs(120),
            deadline: None,
            retries: 4,
            backoff: Duration::from_millis(200),
            probe_bytes: 64 << 10,
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
    /// What [`HttpSource::describe`] needs to explain a TLS failure.
    tls: TlsContext,
    agent: ureq::Agent,
    opts: HttpOptions,
    /// The file's length: what the server declared, [`UNKNOWN_LEN`] while a body of undeclared
    /// length streams and the header has not been read, the header's after
    /// [`ByteSource::limit_to`].
    len: AtomicU64,
    /// Whether `len` is the header's ([`ByteSource::limit_to`] was called).
    limited: AtomicBool,
    /// The length the server declared and how (`Content-Range` total, `Content-Length`, or
    /// the length of a body that ended within the first request).
    declared: Option<(u64, String)>,
    /// `If-Range` value: the first response's strong ETag, else its Last-Modified.
    validator: Option<String>,
    /// The first response's bytes (from offset 0), served without another request.
    head: Vec<u8>,
    /// Whether the server answered the first request with 206.
    ranges: bool,
    /// A server that ignores ranges: its body, streaming from the start of the file.
    body: Mutex<Option<Streamed>>,
    /// The read in progress, for messages.
    activity: Mutex<Option<Activity>>,
    counters: Counters,
}

/// The body of a 200 response and how many of its bytes have been read.
struct Streamed {
    reader: ureq::BodyReader<'static>,
    pos: u64,
}

/// The read in progress: bytes `start..end` of the file, `got` of them in so far.
#[derive(Clone, Copy, Debug)]
struct Activity {
    start: u64,
    end: u64,
    got: u64,
    since: Instant,
    last: Instant,
}

/// What the first response told.
struct Probe {
    len: u64,
    declared: Option<(u64, String)>,
    validator: Option<String>,
    head: Vec<u8>,
    ranges: bool,
    body: Option<Streamed>,
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

/// Seconds for messages: `15`, `0.5`.
fn secs(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s >= 10.0 || s == s.round() {
        format!("{s:.0}")
    } else {
        format!("{s:.1}")
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

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// The scratch buffer bytes are read through (and skipped with).
const READ_BYTES: usize = 64 << 10;

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
        // The deadlines of whole reads are set per request (a streamed body outlives any one).
        let config = ureq::Agent::config_builder()
            .tls_config(tls_config)
            .http_status_as_error(false)
            .timeout_connect(Some(opts.connect_timeout))
            .timeout_per_read(Some(opts.read_timeout))
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
            len: AtomicU64::new(UNKNOWN_LEN),
            limited: AtomicBool::new(false),
            declared: None,
            validator: None,
            head: Vec::new(),
            ranges: false,
            body: Mutex::new(None),
            activity: Mutex::new(None),
            counters: Counters::default(),
        };
        let probe = src.opts.probe_bytes.max(1);
        let deadline = src.read_deadline();
        let p = src
            .retry("", deadline, || src.first_request(probe, deadline))
            .map_err(|e| match e {
                // Which bytes did not come in time, as for every later read.
                SourceError::Deadline {
                    url, secs, message, ..
                } => SourceError::Deadline {
                    url,
                    what: format!("bytes 0-{}: ", probe - 1),
                    secs,
                    message,
                },
                e => e,
            })?;
        *lock(&src.activity) = None;
        src.len = AtomicU64::new(p.len);
        src.declared = p.declared;
        src.validator = p.validator;
        src.head = p.head;
        src.ranges = p.ranges;
        src.body = Mutex::new(p.body);
        Ok(src)
    }

    /// Whether the server honours Range requests (false: its body streams from the start).
    pub fn supports_ranges(&self) -> bool {
        self.ranges
    }

    /// When a read starting now must be done: `request_timeout` from now, or the overall
    /// deadline if that comes first.
    fn read_deadline(&self) -> Instant {
        let own = Instant::now() + self.opts.request_timeout;
        self.opts.deadline.map_or(own, |d| d.min(own))
    }

    /// A failure of ureq in words, and whether trying again can help.
    fn describe(&self, e: &ureq::Error) -> Attempt {
        use ureq::Error as E;
        let tls = &self.tls;
        match e {
            E::Timeout(ureq::Timeout::PerRead) => Attempt::transient(format!(
                "stalled: nothing received for {} s",
                secs(self.opts.read_timeout)
            )),
            E::Timeout(ureq::Timeout::Connect) => Attempt::transient(format!(
                "no connection within {} s",
                secs(self.opts.connect_timeout)
            )),
            E::Timeout(ureq::Timeout::Global) => Attempt::transient(self.progress_note()),
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
            E::TooManyRedirects => Attempt::fatal("too many redirects (more than 4)"),
            E::RedirectFailed => Attempt::fatal("a redirect could not be followed"),
            E::BadUri(u) => Attempt::fatal(format!("bad URL: {u}")),
            other => Attempt::fatal(other.to_string()),
        }
    }

    /// Time left before `deadline`; an error (retried into [`SourceError::Deadline`]) when none.
    fn left(&self, deadline: Instant) -> Result<Duration, Attempt> {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(Attempt::transient(self.progress_note()));
        }
        Ok(left)
    }

    /// How far the read in progress got, for a deadline's message.
    fn progress_note(&self) -> String {
        match *lock(&self.activity) {
            Some(a) => format!(
                "{} of {} bytes received{}",
                a.got,
                a.end - a.start,
                match a.last.elapsed() {
                    d if d >= Duration::from_secs(1) => format!(", the last {} s ago", secs(d)),
                    _ => String::new(),
                }
            ),
            None => "no answer yet".into(),
        }
    }

    /// Runs `f` until it succeeds, fails for good, has used up the retries, or `deadline` has
    /// passed; `context` prefixes the message (e.g. the byte range).
    fn retry<T>(
        &self,
        context: &str,
        deadline: Instant,
        mut f: impl FnMut() -> Result<T, Attempt>,
    ) -> Result<T, SourceError> {
        let mut wait = self.opts.backoff;
        let mut attempts = 0;
        let total = deadline.saturating_duration_since(Instant::now());
        let past_deadline = |message: String| SourceError::Deadline {
            url: self.url.clone(),
            what: context.to_string(),
            secs: total.as_secs_f64(),
            message,
        };
        // Why the last attempt that did not run into the deadline failed.
        let mut earlier: Option<String> = None;
        loop {
            attempts += 1;
            self.counters.requests.fetch_add(1, Ordering::Relaxed);
            let a = match f() {
                Ok(v) => return Ok(v),
                Err(a) => a,
            };
            if !a.retryable {
                let url = self.url.clone();
                let message = format!("{context}{}", a.message);
                return Err(SourceError::Http { url, message });
            }
            let note = self.progress_note();
            if a.message != note {
                earlier = Some(a.message.clone());
            }
            if Instant::now() >= deadline {
                let message = match (&earlier, attempts) {
                    (None, 1) => note,
                    (None, n) => format!("{n} attempts; {note}"),
                    (Some(m), 1) => format!("{m}; {note}"),
                    (Some(m), n) => format!("{n} attempts, {m}; {note}"),
                };
                return Err(past_deadline(message));
            }
            if attempts > self.opts.retries {
                let url = self.url.clone();
                let message = format!("{context}{}", a.message);
                return Err(SourceError::GaveUp {
                    url,
                    message,
                    attempts,
                });
            }
            if Instant::now() + wait >= deadline {
                return Err(past_deadline(format!(
                    "{}; no time left for attempt {}",
                    a.message,
                    attempts + 1
                )));
            }
            self.counters.retries.fetch_add(1, Ordering::Relaxed);
            std::thread::sleep(wait);
            wait = (wait * 2).min(self.opts.backoff * 16);
        }
    }

    /// The response's `ETag` if strong, else its `Last-Modified`.
    fn validator_of(resp: &ureq::http::Response<ureq::Body>) -> Option<String> {
        let header = |name: &str| {
            resp.headers()
                .get(name)
                .and_then(|v| v.to_str().ok())
                .map(str::to_string)
        };
        let etag = header("etag").filter(|e| !e.starts_with("W/"));
        etag.or_else(|| header("last-modified"))
    }

    fn first_request(&self, probe: u64, deadline: Instant) -> Result<Probe, Attempt> {
        let left = self.left(deadline)?;
        self.start_activity(0, probe);
        let mut resp = self
            .agent
            .get(&self.url)
            .header("Range", format!("bytes=0-{}", probe - 1))
            .config()
            .timeout_recv_response(Some(left))
            .build()
            .call()
            .map_err(|e| self.describe(&e))?;
        let status = resp.status().as_u16();
        let header = |name: &str| {
            resp.headers()
                .get(name)
                .and_then(|v| v.to_str().ok())
                .map(str::to_string)
        };
        let validator = Self::validator_of(&resp);
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
                self.start_activity(0, want);
                let mut reader = resp
                    .body_mut()
                    .with_config()
                    .limit(want.saturating_add(1))
                    .reader();
                let head = self.read_exact_body(&mut reader, want, deadline)?;
                Ok(Probe {
                    len: total,
                    declared: Some((total, format!("Content-Range `{cr}`"))),
                    validator,
                    head,
                    ranges: true,
                    body: None,
                })
            }
            200 => {
                // No range support: the body streams from the start. Keep the first `probe`
                // bytes, and the rest of the body for the later reads, in file order.
                let declared = header("content-length").and_then(|v| v.parse::<u64>().ok());
                let mut reader = resp.into_body().into_reader();
                let mut head = Vec::new();
                let ended = self.read_up_to(&mut reader, probe, &mut head, deadline)?;
                let got = head.len() as u64;
                if ended {
                    if let Some(n) = declared.filter(|&n| n != got) {
                        return Err(Attempt::transient(format!(
                            "body ended after {got} of {n} bytes"
                        )));
                    }
                    return Ok(Probe {
                        len: got,
                        declared: Some((got, "the length of its body".into())),
                        validator,
                        head,
                        ranges: false,
                        body: None,
                    });
                }
                Ok(Probe {
                    len: declared.unwrap_or(UNKNOWN_LEN),
                    declared: declared.map(|n| (n, "Content-Length".to_string())),
                    validator,
                    head,
                    ranges: false,
                    body: Some(Streamed { reader, pos: got }),
                })
            }
            416 => Err(Attempt::fatal("the file is empty (HTTP 416)")),
            s => Err(status_attempt(s)),
        }
    }

    fn start_activity(&self, start: u64, len: u64) {
        let now = Instant::now();
        *lock(&self.activity) = Some(Activity {
            start,
            end: start + len,
            got: 0,
            since: now,
            last: now,
        });
    }

    /// Counts `n` bytes received.
    fn received(&self, n: usize) {
        self.counters.bytes.fetch_add(n as u64, Ordering::Relaxed);
        if let Some(a) = lock(&self.activity).as_mut() {
            a.got += n as u64;
            a.last = Instant::now();
        }
    }

    /// Reads from `reader` into `out` until `out` has grown by `n` bytes or the body ends (then
    /// `true`), never more; fails once `deadline` has passed.
    fn read_up_to(
        &self,
        reader: &mut impl Read,
        n: u64,
        out: &mut Vec<u8>,
        deadline: Instant,
    ) -> Result<bool, Attempt> {
        let target = out.len() as u64 + n;
        while (out.len() as u64) < target {
            self.left(deadline)?;
            let old = out.len();
            let want = (target - old as u64).min(READ_BYTES as u64) as usize;
            out.resize(old + want, 0);
            match reader.read(&mut out[old..]) {
                Ok(0) => {
                    out.truncate(old);
                    return Ok(true);
                }
                Ok(k) => {
                    out.truncate(old + k);
                    self.received(k);
                }
                Err(e) => {
                    out.truncate(old);
                    match e.kind() {
                        std::io::ErrorKind::Interrupted => continue,
                        // The server closed the connection before the length it announced.
                        std::io::ErrorKind::UnexpectedEof => return Ok(true),
                        _ => return Err(self.describe(&ureq::Error::from(e))),
                    }
                }
            }
        }
        Ok(false)
    }

    /// Exactly `want` bytes of a body that must end there.
    fn read_exact_body(
        &self,
        reader: &mut ureq::BodyReader<'_>,
        want: u64,
        deadline: Instant,
    ) -> Result<Vec<u8>, Attempt> {
        let longer = || Attempt::fatal(format!("body longer than the {want} bytes announced"));
        let mut body = Vec::with_capacity(want.min(READ_BYTES as u64 * 16) as usize);
        if self.read_up_to(reader, want, &mut body, deadline)? {
            return Err(Attempt::transient(format!(
                "body ended after {} of {want} bytes",
                body.len()
            )));
        }
        // The body must end here: one more byte is a wrong answer, and no more is read.
        let mut extra = [0u8; 1];
        loop {
            match reader.read(&mut extra) {
                Ok(0) => return Ok(body),
                Ok(_) => return Err(longer()),
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => match ureq::Error::from(e) {
                    ureq::Error::BodyExceedsLimit(_) => return Err(longer()),
                    e => return Err(self.describe(&e)),
                },
            }
        }
    }

    fn range_request(&self, range: &Range<u64>, deadline: Instant) -> Result<Vec<u8>, Attempt> {
        let left = self.left(deadline)?;
        let want = range.end - range.start;
        self.start_activity(range.start, want);
        let mut req = self
            .agent
            .get(&self.url)
            .header("Range", format!("bytes={}-{}", range.start, range.end - 1));
        if let Some(v) = &self.validator {
            req = req.header("If-Range", v.as_str());
        }
        let mut resp = req
            .config()
            .timeout_global(Some(left))
            .build()
            .call()
            .map_err(|e| self.describe(&e))?;
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
        let len = self.len();
        match parse_content_range(&cr) {
            Some((a, b, total)) if a == range.start && b + 1 == range.end => {
                if let Some(t) = total.filter(|&t| t != len) {
                    let whose = if self.limited.load(Ordering::Relaxed) {
                        "its header"
                    } else {
                        "the first response"
                    };
                    return Err(Attempt::fatal(format!(
                        "the server says the file is {t} bytes (Content-Range `{cr}`), {whose} \
                         says {len}"
                    )));
                }
            }
            _ => {
                return Err(Attempt::fatal(format!(
                    "asked for bytes {}-{} of {len}, got Content-Range `{cr}`",
                    range.start,
                    range.end - 1
                )))
            }
        }
        let mut reader = resp
            .body_mut()
            .with_config()
            .limit(want.saturating_add(1))
            .reader();
        self.read_exact_body(&mut reader, want, deadline)
    }

    /// A new 200 response streaming the file from the start (after a failure, or for a read
    /// behind what has streamed); it must be the same file.
    fn restart(&self, deadline: Instant) -> Result<Streamed, Attempt> {
        let left = self.left(deadline)?;
        let resp = self
            .agent
            .get(&self.url)
            .config()
            .timeout_recv_response(Some(left))
            .build()
            .call()
            .map_err(|e| self.describe(&e))?;
        match resp.status().as_u16() {
            200 => {}
            206 => {
                return Err(Attempt::fatal(
                    "the server answered 206 to a request without Range after ignoring Range",
                ))
            }
            s => return Err(status_attempt(s)),
        }
        let validator = Self::validator_of(&resp);
        let length = resp
            .headers()
            .get("content-length")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse::<u64>().ok());
        let declared = self
            .declared
            .as_ref()
            .filter(|(_, how)| how == "Content-Length")
            .map(|(n, _)| *n);
        if validator != self.validator || length != declared {
            return Err(Attempt::fatal(
                "the file changed on the server while it was being streamed (another validator \
                 or length); start again",
            ));
        }
        Ok(Streamed {
            reader: resp.into_body().into_reader(),
            pos: 0,
        })
    }

    /// Bytes `range` from the streaming body (and the kept first bytes): skips forward to its
    /// start, restarting the download when the start has already streamed past.
    fn stream_read(&self, range: &Range<u64>, deadline: Instant) -> Result<Vec<u8>, Attempt> {
        let head_len = self.head.len() as u64;
        let cap = (range.end - range.start).min(READ_BYTES as u64 * 16);
        let mut out = Vec::with_capacity(cap as usize);
        let mut at = range.start;
        if at < head_len {
            let to = range.end.min(head_len);
            out.extend_from_slice(&self.head[at as usize..to as usize]);
            at = to;
        }
        if at == range.end {
            return Ok(out);
        }
        self.start_activity(range.start, range.end - range.start);
        let mut body = lock(&self.body);
        let result = (|| {
            if body.as_ref().is_none_or(|s| s.pos > at) {
                *body = None;
                *body = Some(self.restart(deadline)?);
            }
            let s = body.as_mut().expect("set above");
            // Skip to `at`, through a small buffer.
            let mut scratch = Vec::new();
            while s.pos < at {
                scratch.clear();
                let n = (at - s.pos).min(READ_BYTES as u64);
                let ended = self.read_up_to(&mut s.reader, n, &mut scratch, deadline)?;
                s.pos += scratch.len() as u64;
                if ended {
                    return Err(Attempt::transient(format!(
                        "the body ended at byte {}, before byte {at}",
                        s.pos
                    )));
                }
            }
            let before = out.len();
            let ended = self.read_up_to(&mut s.reader, range.end - at, &mut out, deadline)?;
            s.pos += (out.len() - before) as u64;
            if ended {
                return Err(Attempt::transient(format!(
                    "the body ended at byte {}, before byte {}",
                    s.pos, range.end
                )));
            }
            Ok(())
        })();
        if result.is_err() {
            // A failed read leaves the stream somewhere unknown: the next one starts again.
            *body = None;
        }
        result.map(|()| out)
    }
}

impl ByteSource for HttpSource {
    fn len(&self) -> u64 {
        self.len.load(Ordering::Relaxed)
    }
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, SourceError> {
        check_range(&self.url, &range, self.len())?;
        if range.end <= self.head.len() as u64 {
            return Ok(self.head[range.start as usize..range.end as usize].to_vec());
        }
        if range.is_empty() {
            return Ok(Vec::new());
        }
        let context = format!("bytes {}-{}: ", range.start, range.end - 1);
        let deadline = self.read_deadline();
        let result = if self.ranges {
            self.retry(&context, deadline, || self.range_request(&range, deadline))
        } else {
            self.retry(&context, deadline, || self.stream_read(&range, deadline))
        };
        *lock(&self.activity) = None;
        result
    }
    fn name(&self) -> &str {
        &self.url
    }
    fn stats(&self) -> TransferStats {
        self.counters.snapshot()
    }
    fn limit_to(&self, len: u64) -> Result<(), SourceError> {
        if let Some((n, how)) = self.declared.as_ref().filter(|(n, _)| *n != len) {
            return Err(SourceError::Http {
                url: self.url.clone(),
                message: format!(
                    "the server says the file is {n} bytes ({how}), its header says {len}"
                ),
            });
        }
        self.len.store(len, Ordering::Relaxed);
        self.limited.store(true, Ordering::Relaxed);
        Ok(())
    }
    fn sequential(&self) -> bool {
        !self.ranges
    }
    fn activity(&self) -> Option<String> {
        let a = (*lock(&self.activity))?;
        let quiet = a.last.elapsed();
        Some(format!(
            "the request for bytes {}-{} had received {} of {} bytes in {} s{}",
            a.start,
            a.end - 1,
            a.got,
            a.end - a.start,
            secs(a.since.elapsed()),
            if quiet >= Duration::from_secs(1) {
                format!(", nothing received for the last {} s", secs(quiet))
            } else {
                String::new()
            }
        ))
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
