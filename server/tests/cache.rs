//! Files answered from memory are never stale: a file replaced (renamed over) or rewritten in
//! place (same length) while being served is answered with its new bytes at once, whole and in
//! ranges, and with the cache off every answer is the same.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;

use msth_server::{BackgroundServer, ServerConfig};

/// `GET path` with `extra` header lines: status and body.
fn get(server: &BackgroundServer, path: &str, extra: &str) -> (u16, Vec<u8>) {
    let mut s = TcpStream::connect(server.addr()).unwrap();
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: t\r\nConnection: close\r\n{extra}\r\n"
    )
    .unwrap();
    let mut reply = Vec::new();
    s.read_to_end(&mut reply).unwrap();
    let split = reply.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
    let head = String::from_utf8_lossy(&reply[..split]).to_string();
    let status = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (status, reply[split + 4..].to_vec())
}

fn pattern(len: usize, seed: u8) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u8).wrapping_mul(31) ^ seed)
        .collect()
}

fn serve(dir: &Path, cache_bytes: u64) -> BackgroundServer {
    let mut config = ServerConfig::new(dir);
    config.addr = "127.0.0.1:0".parse().unwrap();
    config.cache_bytes = cache_bytes;
    BackgroundServer::start(config).unwrap()
}

#[test]
fn replaced_and_rewritten_files_are_served_fresh() {
    for cache_bytes in [msth_server::DEFAULT_CACHE_BYTES, 0] {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a.msth");
        let len = 700_000; // more than one body frame
        std::fs::write(&file, pattern(len, 1)).unwrap();
        let server = serve(dir.path(), cache_bytes);
        let (status, body) = get(&server, "/models/a.msth", "");
        assert_eq!((status, body == pattern(len, 1)), (200, true));
        // Replaced: a new file renamed over the old one.
        let tmp = dir.path().join("a.tmp");
        std::fs::write(&tmp, pattern(len, 2)).unwrap();
        std::fs::rename(&tmp, &file).unwrap();
        let (_, body) = get(&server, "/models/a.msth", "");
        assert!(
            body == pattern(len, 2),
            "cache {cache_bytes}: stale after a rename"
        );
        // Rewritten in place, same length.
        std::fs::write(&file, pattern(len, 3)).unwrap();
        let (_, body) = get(&server, "/models/a.msth", "");
        assert!(
            body == pattern(len, 3),
            "cache {cache_bytes}: stale after a rewrite"
        );
        // Ranges come from the same bytes.
        let (status, body) = get(&server, "/models/a.msth", "Range: bytes=1000-1999\r\n");
        assert_eq!(status, 206);
        assert!(body == pattern(len, 3)[1000..2000]);
        let (status, body) = get(&server, "/models/a.msth", "Range: bytes=-10\r\n");
        assert_eq!(status, 206);
        assert!(body == pattern(len, 3)[len - 10..]);
        // Gone: 404, not the bytes held.
        std::fs::remove_file(&file).unwrap();
        assert_eq!(get(&server, "/models/a.msth", "").0, 404);
        server.stop().unwrap();
    }
}
