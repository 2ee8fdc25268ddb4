//! `--rate-limit`: a throttled server answers with the same bytes, whole and in ranges, never
//! faster than its rate (a lower bound on the time, which a slow machine only makes longer), and
//! a schedule's later rate applies to the responses after its time.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Instant;

use msth_server::throttle::RateSchedule;
use msth_server::{BackgroundServer, ServerConfig};

/// `GET path` with `extra` header lines: status, body and the seconds it took.
fn get(server: &BackgroundServer, path: &str, extra: &str) -> (u16, Vec<u8>, f64) {
    let t = Instant::now();
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
    (
        status,
        reply[split + 4..].to_vec(),
        t.elapsed().as_secs_f64(),
    )
}

fn serve(dir: &std::path::Path, schedule: &str) -> BackgroundServer {
    let mut config = ServerConfig::new(dir);
    config.addr = "127.0.0.1:0".parse().unwrap();
    config.rate_limit = Some(RateSchedule::parse(schedule).unwrap());
    BackgroundServer::start(config).unwrap()
}

#[test]
fn throttled_responses_hold_the_bytes_and_keep_to_the_rate() {
    let dir = tempfile::tempdir().unwrap();
    let data: Vec<u8> = (0..120_000u32).map(|i| (i * 7 % 251) as u8).collect();
    std::fs::write(dir.path().join("a.msth"), &data).unwrap();
    // 200 kB/s: 120 kB take at least 0.6 s (the first 50 ms piece leaves at once).
    let server = serve(dir.path(), "200k");
    let (status, body, secs) = get(&server, "/models/a.msth", "");
    assert_eq!(status, 200);
    assert!(body == data, "the throttled body differs");
    assert!(secs >= 0.5, "120 kB at 200 kB/s in {secs:.3} s");
    let (status, body, secs) = get(&server, "/models/a.msth", "Range: bytes=1000-40999\r\n");
    assert_eq!(status, 206);
    assert!(body == data[1000..41000]);
    assert!(secs >= 0.15, "40 kB at 200 kB/s in {secs:.3} s");
    server.stop().unwrap();
}

#[test]
fn a_schedule_changes_the_rate_at_its_times() {
    let dir = tempfile::tempdir().unwrap();
    let data = vec![7u8; 100_000];
    std::fs::write(dir.path().join("a.msth"), &data).unwrap();
    // Fast for the first second, then 100 kB/s.
    let server = serve(dir.path(), "1G,100k@1");
    let (_, body, fast) = get(&server, "/models/a.msth", "");
    assert!(body == data);
    std::thread::sleep(std::time::Duration::from_secs_f64((1.1 - fast).max(0.0)));
    let (_, body, slow) = get(&server, "/models/a.msth", "");
    assert!(body == data);
    assert!(slow >= 0.8, "100 kB at 100 kB/s in {slow:.3} s");
    server.stop().unwrap();
}
