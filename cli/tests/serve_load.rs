//! A loopback load test of `msth serve` as a separate process: rounds of 200 concurrent clients
//! each stream a whole model with the player's HTTP client. No request may fail, and the server's
//! resident memory must stay flat from round to round. Bounded in count (3 rounds) and in time
//! (every request has timeouts).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use msth_codec::Limits;
use msth_player::{HttpOptions, HttpSource, ModelStream};

mod support;

const CLIENTS: usize = 200;
const ROUNDS: usize = 3;

fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// One round: `CLIENTS` threads stream the whole file; returns the failures' messages.
fn round(url: &str) -> Vec<String> {
    let handles: Vec<_> = (0..CLIENTS)
        .map(|_| {
            let url = url.to_string();
            std::thread::spawn(move || -> Result<u64, String> {
                let opts = HttpOptions {
                    read_timeout: Duration::from_secs(30),
                    retries: 0,
                    ..HttpOptions::default()
                };
                let src = HttpSource::open(&url, opts).map_err(|e| e.to_string())?;
                let stream = ModelStream::open(Box::new(src), &Limits::default())
                    .map_err(|e| e.to_string())?;
                stream
                    .wait_all(Duration::from_secs(120))
                    .map_err(|e| e.to_string())?;
                Ok(stream.progress().transfer.requests)
            })
        })
        .collect();
    handles
        .into_iter()
        .filter_map(|h| match h.join() {
            Ok(Ok(_)) => None,
            Ok(Err(e)) => Some(e),
            Err(_) => Some("client thread panicked".into()),
        })
        .collect()
}

#[test]
fn two_hundred_concurrent_clients_stream_without_failures_and_flat_memory() {
    let file = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/v1.msth");
    // Every client here comes from 127.0.0.1, where real clients come from many addresses:
    // raise the per-address cap (default 64, tested in server/tests/slow_clients.rs) above the
    // client count so that this test measures the load, not the cap.
    let cap = (2 * CLIENTS).to_string();
    let (server, base) = support::serve(&file, &["--max-connections-per-ip", &cap]);
    let url = format!("{base}/models/v1.msth");
    let pid = server.0.id();
    let idle = rss_kib(pid);
    let mut after = Vec::new();
    for r in 0..ROUNDS {
        let t = Instant::now();
        let failures = round(&url);
        assert!(
            failures.is_empty(),
            "round {r}: {} of {CLIENTS} clients failed, e.g. {}",
            failures.len(),
            failures[0]
        );
        // Let the server drop the closed connections.
        std::thread::sleep(Duration::from_millis(300));
        let rss = rss_kib(pid);
        println!(
            "round {r}: {CLIENTS} clients streamed the model in {:.2} s; server RSS {:?} KiB",
            t.elapsed().as_secs_f64(),
            rss
        );
        after.push(rss);
    }
    println!("server RSS idle: {idle:?} KiB");
    if let (Some(first), Some(last)) = (after[0], after[ROUNDS - 1]) {
        // Flat: the later rounds hold no more than the first one did (plus allocator slack).
        assert!(
            last <= first + 16 * 1024,
            "server memory grew from {first} KiB after round 1 to {last} KiB after round {ROUNDS}"
        );
    }
}
