//! `msth play https://…` against a real HTTPS server on loopback: the built-in server behind a
//! TLS terminator (tokio-rustls, as nginx or Caddy would front it), with certificates the test
//! makes (rcgen: a CA and leaves signed by it). The codec fixture streamed over https must give
//! the same frames, byte for byte, as over http and from the local file; certificates that must
//! not be trusted (unknown CA, wrong name, expired, https to a plain-HTTP port) must fail with a
//! clear error naming the host and the reason, at once (no retries), never a panic or a hang.
//!
//! The figures (bytes fetched, time to first frame over https and http in the same run) are
//! printed, not asserted: `cargo test --release -p msth-tests --test play_https -- --nocapture`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use msth_player::{ByteSource, FileSource, HttpOptions, HttpSource, SourceError};
use msth_server::{BackgroundServer, ServerConfig};
use msth_tests::{msth, play_report};
use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, IsCa, KeyPair};
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

fn fixture_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/v1.msth")
}

/// A certificate authority made by the test.
struct TestCa {
    issuer: CertifiedIssuer<'static, KeyPair>,
}

impl TestCa {
    fn new(name: &str) -> Self {
        let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
        params
            .distinguished_name
            .push(rcgen::DnType::CommonName, name);
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        let issuer = CertifiedIssuer::self_signed(params, KeyPair::generate().unwrap()).unwrap();
        TestCa { issuer }
    }

    /// Writes the CA certificate as PEM to `dir/name` and returns that path.
    fn write_pem(&self, dir: &Path, name: &str) -> PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, self.issuer.pem()).unwrap();
        path
    }

    /// A server certificate for `names` signed by this CA; `expired`: valid only in 2000.
    fn leaf(&self, names: &[&str], expired: bool) -> ServerCert {
        let mut params =
            CertificateParams::new(names.iter().map(|n| n.to_string()).collect::<Vec<_>>())
                .unwrap();
        if expired {
            params.not_before = rcgen::date_time_ymd(2000, 1, 1);
            params.not_after = rcgen::date_time_ymd(2000, 12, 31);
        }
        let key = KeyPair::generate().unwrap();
        let cert = params.signed_by(&key, &*self.issuer).unwrap();
        ServerCert {
            chain: vec![cert.der().clone(), self.issuer.der().clone()],
            pem: cert.pem(),
            key: key.serialize_der(),
        }
    }
}

/// A certificate chain (leaf first) and the leaf's PKCS#8 key.
struct ServerCert {
    chain: Vec<CertificateDer<'static>>,
    /// The leaf alone, PEM.
    pem: String,
    key: Vec<u8>,
}

/// A self-signed server certificate for `names` (no CA).
fn self_signed(names: &[&str]) -> ServerCert {
    let params =
        CertificateParams::new(names.iter().map(|n| n.to_string()).collect::<Vec<_>>()).unwrap();
    let key = KeyPair::generate().unwrap();
    let cert = params.self_signed(&key).unwrap();
    ServerCert {
        chain: vec![cert.der().clone()],
        pem: cert.pem(),
        key: key.serialize_der(),
    }
}

/// A TLS terminator on a loopback port: each TLS connection is forwarded, decrypted, to
/// `backend` (one backend connection per client connection, so keep-alive carries through).
/// Handshakes the client aborts (an untrusted certificate) just end that connection.
struct TlsFront {
    addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl TlsFront {
    fn start(backend: SocketAddr, cert: &ServerCert) -> Self {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let key = PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(cert.key.clone()));
        let config = rustls::ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .unwrap()
            .with_no_client_auth()
            .with_single_cert(cert.chain.clone(), key)
            .unwrap();
        let acceptor = tokio_rustls::TlsAcceptor::from(Arc::new(config));
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .unwrap();
        let addr = listener.local_addr().unwrap();
        let (stop_tx, mut stop_rx) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::spawn(move || {
            runtime.block_on(async move {
                loop {
                    let tcp = tokio::select! {
                        _ = &mut stop_rx => break,
                        accepted = listener.accept() => match accepted {
                            Ok((tcp, _)) => tcp,
                            Err(_) => continue,
                        },
                    };
                    let acceptor = acceptor.clone();
                    tokio::spawn(async move {
                        // No Nagle on either leg: small TLS records must not wait for the
                        // peer's delayed ACK (40 ms on Linux) in a loopback measurement.
                        let _ = tcp.set_nodelay(true);
                        let Ok(mut tls) = acceptor.accept(tcp).await else {
                            return; // the client refused the certificate
                        };
                        let Ok(mut plain) = tokio::net::TcpStream::connect(backend).await else {
                            return;
                        };
                        let _ = plain.set_nodelay(true);
                        let _ = tokio::io::copy_bidirectional(&mut tls, &mut plain).await;
                    });
                }
            });
            // Dropping the runtime ends the forwarding tasks still open.
        });
        TlsFront {
            addr,
            stop: Some(stop_tx),
            thread: Some(thread),
        }
    }

    fn url(&self, path: &str) -> String {
        format!("https://{}{path}", self.addr)
    }
}

impl Drop for TlsFront {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn serve_fixture() -> BackgroundServer {
    BackgroundServer::start(ServerConfig {
        addr: "127.0.0.1:0".parse().unwrap(),
        ..ServerConfig::new(fixture_path())
    })
    .unwrap()
}

fn quick(ca: Option<&Path>) -> HttpOptions {
    HttpOptions {
        connect_timeout: Duration::from_secs(2),
        read_timeout: Duration::from_secs(5),
        request_timeout: Duration::from_secs(20),
        retries: 2,
        backoff: Duration::from_millis(10),
        ca_cert_file: ca.map(Path::to_path_buf),
        ..HttpOptions::default()
    }
}

/// The PNG frames of a playback folder, by name, as file bytes.
fn frames(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = msth_testkit::files_with_extension(dir, "png")
        .into_iter()
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).unwrap())
        })
        .collect();
    v.sort();
    v
}

#[test]
fn https_playback_equals_http_and_the_local_file() {
    let dir = tempfile::tempdir().unwrap();
    let ca = TestCa::new("msth test CA");
    let ca_pem = ca.write_pem(dir.path(), "ca.pem");
    let server = serve_fixture();
    let front = TlsFront::start(server.addr(), &ca.leaf(&["localhost", "127.0.0.1"], false));
    let https = front.url("/models/v1.msth");
    let http = server.url("/models/v1.msth");
    let ca_arg = ["--ca-cert", ca_pem.to_str().unwrap()];

    // Local first (it warms the renderer), then http and https twice each, interleaved, so the
    // times to first frame compare like with like.
    let local = play_report(
        fixture_path().to_str().unwrap(),
        &dir.path().join("local"),
        &[],
    );
    let mut runs = Vec::new();
    for round in 0..2 {
        for (scheme, url) in [("http", &http), ("https", &https)] {
            let out = dir.path().join(format!("{scheme}{round}"));
            let r = play_report(url, &out, &ca_arg);
            runs.push((scheme, out, r));
        }
    }

    let expected = frames(&dir.path().join("local"));
    assert_eq!(
        expected.len(),
        local["frames"].as_array().unwrap().len(),
        "one PNG per frame"
    );
    assert!(!expected.is_empty());
    let file_len = std::fs::metadata(fixture_path()).unwrap().len();
    for (scheme, out, r) in &runs {
        let got = frames(out);
        assert_eq!(got.len(), expected.len(), "{scheme}: frame count");
        for ((name, a), (_, b)) in got.iter().zip(&expected) {
            assert!(a == b, "{scheme}: {name} differs from the local playback");
        }
        assert_eq!(r["file_len"], file_len);
        assert_eq!(r["transfer"]["retries"], 0, "{scheme}: {}", r["transfer"]);
        let bytes = r["transfer"]["bytes"].as_u64().unwrap();
        assert!(bytes > 0, "{scheme}: {bytes} bytes");
        println!(
            "{scheme:>5}: {} frames byte-equal to the local file's; fetched {bytes} of \
             {file_len} bytes in {} requests; time to first frame {:.3} s; total {:.3} s",
            got.len(),
            r["transfer"]["requests"],
            r["time_to_first_frame"].as_f64().unwrap(),
            r["seconds"].as_f64().unwrap(),
        );
    }
    // The same bytes travel either way.
    let bytes = |s: &str| -> Vec<u64> {
        runs.iter()
            .filter(|(scheme, ..)| *scheme == s)
            .map(|(_, _, r)| r["transfer"]["bytes"].as_u64().unwrap())
            .collect()
    };
    assert_eq!(bytes("http"), bytes("https"));

    // Transfer alone: the whole file in 64 KiB ranges, through HttpSource, both schemes
    // alternated three times (figures only).
    let want = FileSource::open(&fixture_path())
        .unwrap()
        .read_range(0..file_len)
        .unwrap();
    let mut seconds = [Vec::new(), Vec::new()];
    for _ in 0..3 {
        for (i, url) in [&http, &https].into_iter().enumerate() {
            let t = Instant::now();
            let src = HttpSource::open(url, quick(Some(&ca_pem))).unwrap();
            let mut got = Vec::new();
            let mut at = 0;
            while at < file_len {
                let end = (at + (64 << 10)).min(file_len);
                got.extend(src.read_range(at..end).unwrap());
                at = end;
            }
            seconds[i].push(t.elapsed().as_secs_f64());
            assert!(got == want, "{url}: bytes differ from the file");
        }
    }
    println!(
        "whole file ({file_len} bytes, 64 KiB ranges, new connection each time): http {:?} s, \
         https {:?} s",
        seconds[0]
            .iter()
            .map(|s| format!("{s:.4}"))
            .collect::<Vec<_>>(),
        seconds[1]
            .iter()
            .map(|s| format!("{s:.4}"))
            .collect::<Vec<_>>(),
    );
}

/// Opening `url` must fail, at once and without retries, with a message naming the host and
/// containing every one of `reasons`.
fn refused(url: &str, ca: Option<&Path>, reasons: &[&str]) -> String {
    let t = Instant::now();
    let e = match HttpSource::open(url, quick(ca)) {
        Ok(_) => panic!("{url}: opened, but the certificate should have been refused"),
        Err(e) => e,
    };
    assert!(
        matches!(e, SourceError::Http { .. }),
        "{url}: a fatal error, not retried: {e:?}"
    );
    let m = e.to_string();
    assert!(m.contains("127.0.0.1"), "{m}");
    for r in reasons {
        assert!(m.contains(r), "`{r}` not in: {m}");
    }
    assert!(t.elapsed() < Duration::from_secs(10), "{m}");
    println!("refused as expected: {m}");
    m
}

#[test]
fn untrusted_certificates_fail_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let ca = TestCa::new("msth test CA");
    let ca_pem = ca.write_pem(dir.path(), "ca.pem");
    let other_ca = TestCa::new("another CA");
    let other_pem = other_ca.write_pem(dir.path(), "other.pem");
    let server = serve_fixture();
    let good = TlsFront::start(server.addr(), &ca.leaf(&["localhost", "127.0.0.1"], false));
    let path = "/models/v1.msth";

    // The bundled Mozilla roots do not know the test CA.
    refused(
        &good.url(path),
        None,
        &[
            "not trusted",
            "unknown issuer",
            "bundled Mozilla roots",
            "--ca-cert",
        ],
    );
    // Nor does another CA.
    refused(
        &good.url(path),
        Some(&other_pem),
        &["not trusted", "unknown issuer", "other.pem", "the CA"],
    );
    // Through `msth play`: the same message, as an error (not a panic).
    let e = msth(&[
        "play",
        &good.url(path),
        "--ca-cert",
        other_pem.to_str().unwrap(),
        "--quiet",
        "--retries",
        "0",
    ])
    .unwrap_err();
    assert!(
        e.contains("127.0.0.1") && e.contains("unknown issuer"),
        "{e}"
    );
    println!("msth play: {e}");

    // A certificate of the right CA for another name.
    let wrong_name = TlsFront::start(server.addr(), &ca.leaf(&["example.invalid"], false));
    refused(
        &wrong_name.url(path),
        Some(&ca_pem),
        &["refused", "not valid for name", "example.invalid"],
    );
    // An expired one.
    let expired = TlsFront::start(server.addr(), &ca.leaf(&["127.0.0.1"], true));
    refused(&expired.url(path), Some(&ca_pem), &["refused", "expired"]);
    // https to the plain-HTTP port.
    let plain = format!("https://{}{path}", server.addr());
    refused(&plain, Some(&ca_pem), &["TLS handshake", "http://"]);

    // The right CA still works on the same server (the refusals left it serving).
    let src = HttpSource::open(&good.url(path), quick(Some(&ca_pem))).unwrap();
    let file = FileSource::open(&fixture_path()).unwrap();
    assert_eq!(src.len(), file.len());
    let n = src.len();
    assert_eq!(
        src.read_range(n - 100..n).unwrap(),
        file.read_range(n - 100..n).unwrap()
    );
}

#[test]
fn self_signed_server_trusted_by_its_own_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let cert = self_signed(&["127.0.0.1"]);
    let pem = dir.path().join("server.pem");
    std::fs::write(&pem, &cert.pem).unwrap();
    let server = serve_fixture();
    let front = TlsFront::start(server.addr(), &cert);
    let url = front.url("/models/v1.msth");

    refused(&url, None, &["not trusted"]);
    let src = HttpSource::open(&url, quick(Some(&pem))).unwrap();
    let file = FileSource::open(&fixture_path()).unwrap();
    let n = file.len();
    assert_eq!(src.len(), n);
    assert!(src.supports_ranges());
    assert_eq!(
        src.read_range(0..n).unwrap(),
        file.read_range(0..n).unwrap()
    );
}
