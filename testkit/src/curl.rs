//! The real `curl` as an HTTP client for tests of the server: one request per call, the
//! response's status line, headers and body. Tests that use it declare [`Need::curl`] so that a
//! machine without `/usr/bin/curl` reports them as ignored.

use std::process::Command;

use crate::Need;

/// The curl binary the tests run.
pub const CURL: &str = "/usr/bin/curl";

impl Need {
    /// `/usr/bin/curl` (kind `curl`).
    pub fn curl() -> Need {
        Need::program("curl", None, CURL, &["--version"])
    }
}

/// What curl received.
pub struct Reply {
    pub status: u16,
    /// The header block, status line first.
    pub headers: String,
    pub body: Vec<u8>,
}

impl Reply {
    /// The value of header `name` (case-insensitive), if present.
    pub fn header(&self, name: &str) -> Option<String> {
        header_in(&self.headers, name)
    }
}

/// The value of header `name` (case-insensitive) in a block of `Name: value` lines.
pub fn header_in(block: &str, name: &str) -> Option<String> {
    block.lines().find_map(|l| {
        let (k, v) = l.split_once(':')?;
        k.trim()
            .eq_ignore_ascii_case(name)
            .then(|| v.trim().to_string())
    })
}

/// Runs `curl -s --max-time 10 ARGS URL`; the headers go to a temporary file, the body to
/// stdout. Panics (failing the test) when curl gives no status line.
pub fn curl(url: &str, args: &[&str]) -> Reply {
    let dir = tempfile::tempdir().expect("a temporary folder");
    let head = dir.path().join("headers");
    let out = Command::new(CURL)
        .args(["-s", "--max-time", "10", "-D"])
        .arg(&head)
        .args(args)
        .arg(url)
        .output()
        .expect("curl runs");
    let headers = std::fs::read_to_string(&head).unwrap_or_default();
    let status = headers
        .lines()
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no status from curl {args:?} {url}: {headers:?}"));
    Reply {
        status,
        headers,
        body: out.stdout,
    }
}
