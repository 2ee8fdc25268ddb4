//! What the `msth` process tests in `cli/tests/` share: a child process that is killed when the
//! test ends (passed or panicked), and `msth serve` started on a free loopback port.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};

/// A child process, killed and reaped when dropped.
pub struct KillOnDrop(pub Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `msth serve SRC --addr 127.0.0.1:0 EXTRA...` as a child process: returns it and the base URL
/// it prints on its first line (no trailing `/`). The rest of its output is drained so that the
/// server never writes into a closed pipe.
#[allow(dead_code)] // not every test binary that includes this module serves
pub fn serve(src: &Path, extra: &[&str]) -> (KillOnDrop, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_msth"))
        .args(["serve", src.to_str().unwrap(), "--addr", "127.0.0.1:0"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("starting msth serve");
    let stdout = child.stdout.take().unwrap();
    let server = KillOnDrop(child);
    let mut reader = BufReader::new(stdout);
    let mut first = String::new();
    reader.read_line(&mut first).unwrap();
    std::thread::spawn(move || std::io::copy(&mut reader, &mut std::io::sink()));
    let base = first
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no URL in `{first}`"))
        .trim_end_matches('/')
        .to_string();
    (server, base)
}
