//! `msth serve` checked with a real client: the server runs in-process on `127.0.0.1:0` and the
//! real `curl` binary drives it: full GET, HEAD, single/open/suffix/unsatisfiable ranges,
//! If-Range, the listing, CORS, and traversal attempts. Where `/usr/bin/curl` is absent the tests
//! are reported as ignored with the reason, unless `MSTH_REQUIRE_CURL=1` (then they fail). This
//! binary runs on `msth-testkit`'s harness (`harness = false`): [`main`] lists its tests.

use msth_server::{BackgroundServer, ServerConfig};
use msth_testkit::curl::curl;
use msth_testkit::{Need, Tests};

fn main() -> std::process::ExitCode {
    let curl = Need::curl();
    Tests::new(file!())
        .needs(
            &[&curl],
            "full_get_head_and_listing",
            full_get_head_and_listing,
        )
        .needs(&[&curl], "ranges", ranges)
        .needs(&[&curl], "traversal_is_refused", traversal_is_refused)
        .run()
}

/// A served folder `root/served` with `a.msth` (1000 known bytes) and `b.msth`, a secret file
/// next to it, and (on Unix) a symlink inside pointing at the secret.
fn fixture() -> (tempfile::TempDir, Vec<u8>, BackgroundServer) {
    let root = tempfile::tempdir().unwrap();
    let served = root.path().join("served");
    std::fs::create_dir(&served).unwrap();
    let bytes: Vec<u8> = (0..1000u32).map(|i| (i * 7 % 251) as u8).collect();
    std::fs::write(served.join("a.msth"), &bytes).unwrap();
    std::fs::write(served.join("b.msth"), b"bee").unwrap();
    std::fs::write(root.path().join("secret.msth"), b"SECRET").unwrap();
    #[cfg(unix)]
    std::os::unix::fs::symlink(root.path().join("secret.msth"), served.join("link.msth")).unwrap();
    let mut config = ServerConfig::new(&served);
    config.addr = "127.0.0.1:0".parse().unwrap();
    let server = BackgroundServer::start(config).unwrap();
    (root, bytes, server)
}

fn full_get_head_and_listing() {
    let (_root, bytes, server) = fixture();
    let url = server.url("/models/a.msth");

    let full = curl(&url, &[]);
    assert_eq!(full.status, 200);
    assert_eq!(full.body, bytes);
    assert_eq!(full.header("accept-ranges").as_deref(), Some("bytes"));
    assert_eq!(full.header("content-length").as_deref(), Some("1000"));
    assert!(full.header("etag").is_some_and(|t| t.starts_with('"')));
    assert!(full.header("last-modified").is_some());
    assert_eq!(
        full.header("access-control-allow-origin").as_deref(),
        Some("*")
    );
    assert!(full
        .header("access-control-expose-headers")
        .is_some_and(|v| v.contains("Content-Range") && v.contains("ETag")));

    let head = curl(&url, &["-I"]);
    assert_eq!(head.status, 200);
    // With -I curl prints the header block to stdout; anything more would be a body.
    assert_eq!(String::from_utf8_lossy(&head.body), head.headers);
    assert_eq!(head.header("content-length").as_deref(), Some("1000"));
    assert_eq!(head.header("etag"), full.header("etag"));

    let etag = full.header("etag").unwrap();
    let cached = curl(&url, &["-H", &format!("If-None-Match: {etag}")]);
    assert_eq!(cached.status, 304);
    assert!(cached.body.is_empty());

    let list = curl(&server.url("/models"), &[]);
    assert_eq!(list.status, 200);
    let json: serde_json::Value = serde_json::from_slice(&list.body).unwrap();
    let rows = json.as_array().unwrap();
    let names: Vec<&str> = rows.iter().map(|r| r["name"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        ["a.msth", "b.msth"],
        "the outside symlink is not listed"
    );
    assert_eq!(rows[0]["url"], "/models/a.msth");
    assert_eq!(rows[0]["bytes"], 1000);
    assert!(rows[0]["modified"].as_str().unwrap().ends_with('Z'));

    let index = curl(&server.url("/"), &[]);
    assert_eq!(index.status, 200);
    assert!(String::from_utf8_lossy(&index.body).contains("/models"));
    server.stop().unwrap();
}

fn ranges() {
    let (_root, bytes, server) = fixture();
    let url = server.url("/models/a.msth");

    let single = curl(&url, &["-r", "10-19"]);
    assert_eq!(single.status, 206);
    assert_eq!(single.body, &bytes[10..20]);
    assert_eq!(
        single.header("content-range").as_deref(),
        Some("bytes 10-19/1000")
    );
    assert_eq!(single.header("content-length").as_deref(), Some("10"));

    let clipped = curl(&url, &["-r", "990-5000"]);
    assert_eq!(clipped.status, 206);
    assert_eq!(clipped.body, &bytes[990..]);
    assert_eq!(
        clipped.header("content-range").as_deref(),
        Some("bytes 990-999/1000")
    );

    let open = curl(&url, &["-r", "900-"]);
    assert_eq!(open.status, 206);
    assert_eq!(open.body, &bytes[900..]);
    assert_eq!(
        open.header("content-range").as_deref(),
        Some("bytes 900-999/1000")
    );

    let suffix = curl(&url, &["-r", "-100"]);
    assert_eq!(suffix.status, 206);
    assert_eq!(suffix.body, &bytes[900..]);
    assert_eq!(
        suffix.header("content-range").as_deref(),
        Some("bytes 900-999/1000")
    );

    let unsat = curl(&url, &["-r", "1000-1100"]);
    assert_eq!(unsat.status, 416);
    assert_eq!(
        unsat.header("content-range").as_deref(),
        Some("bytes */1000")
    );

    let invalid = curl(&url, &["-H", "Range: bytes=50-10"]);
    assert_eq!(invalid.status, 200, "an invalid Range is ignored");
    assert_eq!(invalid.body, bytes);

    // Several ranges: a multipart/byteranges 206 (its parts are checked in the server crate's
    // tests/byteranges.rs); overlapping ones are merged into one plain 206.
    let multi = curl(&url, &["-r", "0-1,5-6"]);
    assert_eq!(multi.status, 206, "several ranges get a multipart 206");
    assert!(multi
        .header("content-type")
        .is_some_and(|t| t.starts_with("multipart/byteranges; boundary=")));
    let merged = curl(&url, &["-r", "0-9,5-19"]);
    assert_eq!(merged.status, 206);
    assert_eq!(merged.body, &bytes[..20]);
    assert_eq!(
        merged.header("content-range").as_deref(),
        Some("bytes 0-19/1000")
    );

    let etag = curl(&url, &["-I"]).header("etag").unwrap();
    let fresh = curl(&url, &["-r", "0-3", "-H", &format!("If-Range: {etag}")]);
    assert_eq!(fresh.status, 206);
    assert_eq!(fresh.body, &bytes[..4]);
    let stale = curl(&url, &["-r", "0-3", "-H", "If-Range: \"stale\""]);
    assert_eq!(stale.status, 200);
    assert_eq!(stale.body, bytes);
    let date = curl(&url, &["-I"]).header("last-modified").unwrap();
    let by_date = curl(&url, &["-r", "0-3", "-H", &format!("If-Range: {date}")]);
    assert_eq!(by_date.status, 206);
    server.stop().unwrap();
}

fn traversal_is_refused() {
    let (_root, _bytes, server) = fixture();
    for (path, extra) in [
        ("/models/..%2f..%2fetc%2fpasswd", &[][..]),
        ("/models/%2e%2e/Cargo.toml", &[][..]),
        ("/models/%2e%2e%2fsecret.msth", &[][..]),
        ("/models/../secret.msth", &["--path-as-is"][..]),
        ("/models/../Cargo.toml", &["--path-as-is"][..]),
        ("/../secret.msth", &["--path-as-is"][..]),
        ("/%2e%2e/secret.msth", &[][..]),
        ("/etc/passwd", &[][..]),
        ("//etc/passwd", &["--path-as-is"][..]),
        ("/models//etc/passwd", &["--path-as-is"][..]),
        ("/models/%2fetc%2fpasswd", &[][..]),
        ("/models/..%5csecret.msth", &[][..]),
        ("/models/link.msth", &[][..]),
        ("/models/.hidden.msth", &[][..]),
    ] {
        let reply = curl(&server.url(path), extra);
        assert!(
            reply.status == 404 || reply.status == 400,
            "{path}: status {}",
            reply.status
        );
        assert!(
            !String::from_utf8_lossy(&reply.body).contains("SECRET")
                && !String::from_utf8_lossy(&reply.body).contains("root:"),
            "{path} leaked"
        );
    }
    let post = curl(&server.url("/models/a.msth"), &["-X", "DELETE"]);
    assert_eq!(post.status, 405);
    server.stop().unwrap();
}
