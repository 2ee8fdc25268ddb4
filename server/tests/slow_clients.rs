//! Slow and greedy clients against a real server on loopback, over real TCP (issue #19.3): clients
//! that send a partial request and then one header line every 2 s, more of them than the server
//! has slots, from one address and from many (Linux routes all of 127.0.0.0/8 to loopback, so a
//! client socket bound to 127.0.0.N is a distinct client address). A normal client must still be
//! served, while they are all still connected; a header that trickles in and an idle keep-alive
//! connection are closed after `header_read_timeout`; a connection whose response is being
//! written is never shed.
//!
//! Latencies are printed (run with `--nocapture` to see them), not asserted: timing does not
//! belong in pass/fail checks on a shared machine. What is asserted is that the normal request is
//! answered at all before its 5 s client deadline while every slow client is still connected and
//! their header deadline (30 s) is far away: before these limits the server left it waiting in the
//! accept queue until a slow client left, so it was never answered in that time.

#![cfg(target_os = "linux")]

use std::io;
use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::time::{Duration, Instant};

use msth_server::{BackgroundServer, Limits, ServerConfig};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use tokio::task::JoinHandle;

const FILE_BYTES: usize = 1000;

fn fixture(limits: Limits) -> (tempfile::TempDir, BackgroundServer) {
    let dir = tempfile::tempdir().unwrap();
    let bytes: Vec<u8> = (0..FILE_BYTES as u32).map(|i| (i % 251) as u8).collect();
    std::fs::write(dir.path().join("a.msth"), bytes).unwrap();
    let big: Vec<u8> = (0..16u32 << 20).map(|i| (i % 253) as u8).collect();
    std::fs::write(dir.path().join("big.msth"), big).unwrap();
    let mut config = ServerConfig::new(dir.path());
    config.addr = "127.0.0.1:0".parse().unwrap();
    config.limits = limits;
    let server = BackgroundServer::start(config).unwrap();
    (dir, server)
}

fn loopback(n: u8) -> IpAddr {
    IpAddr::V4(Ipv4Addr::new(127, 0, 0, n))
}

async fn connect_from(src: IpAddr, server: SocketAddr) -> io::Result<TcpStream> {
    let socket = TcpSocket::new_v4()?;
    socket.bind(SocketAddr::new(src, 0))?;
    socket.connect(server).await
}

/// A slow client: the request line and `Host`, then one more header line every `every`, never
/// the blank line that ends the head. The task ends when the server closes the connection and
/// returns how long after connecting that was.
fn spawn_slow(mut stream: TcpStream, every: Duration) -> JoinHandle<Duration> {
    tokio::spawn(async move {
        let started = Instant::now();
        if stream
            .write_all(b"GET /models/a.msth HTTP/1.1\r\nHost: slow\r\n")
            .await
            .is_err()
        {
            return started.elapsed();
        }
        let mut buf = [0u8; 256];
        loop {
            tokio::select! {
                read = stream.read(&mut buf) => match read {
                    Ok(0) | Err(_) => return started.elapsed(),
                    Ok(_) => {}
                },
                () = tokio::time::sleep(every) => {
                    if stream.write_all(b"X-Slow: 1\r\n").await.is_err() {
                        return started.elapsed();
                    }
                }
            }
        }
    })
}

/// Opens `count` slow connections, the i-th from `source(i)`.
async fn open_slow(
    server: SocketAddr,
    count: usize,
    source: impl Fn(usize) -> IpAddr,
    every: Duration,
) -> Vec<JoinHandle<Duration>> {
    let mut slow = Vec::with_capacity(count);
    for i in 0..count {
        let stream = connect_from(source(i), server).await.unwrap();
        slow.push(spawn_slow(stream, every));
    }
    slow
}

/// One `GET path` with `Connection: close` from `src`: status, body, time to the last byte.
async fn normal_get(src: IpAddr, server: SocketAddr, path: &str) -> (u16, Vec<u8>, Duration) {
    let started = Instant::now();
    let exchange = async {
        let mut stream = connect_from(src, server).await?;
        stream
            .write_all(
                format!("GET {path} HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n").as_bytes(),
            )
            .await?;
        let mut reply = Vec::new();
        stream.read_to_end(&mut reply).await?;
        io::Result::Ok(reply)
    };
    let reply = tokio::time::timeout(Duration::from_secs(5), exchange)
        .await
        .unwrap_or_else(|_| {
            panic!(
                "the normal request was not answered within 5 s ({:?} elapsed)",
                started.elapsed()
            )
        })
        .expect("the normal request's connection works");
    let elapsed = started.elapsed();
    let (status, body) = parse_reply(&reply);
    (status, body.to_vec(), elapsed)
}

/// Status and body of one HTTP/1.1 response held in `reply`.
fn parse_reply(reply: &[u8]) -> (u16, &[u8]) {
    let split = reply
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a complete response head");
    let head = String::from_utf8_lossy(&reply[..split]);
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .expect("a status code");
    (status, &reply[split + 4..])
}

/// Waits (at most 3 s) until `check` holds for the server's connection counts.
async fn wait_for(
    server: &BackgroundServer,
    what: &str,
    check: impl Fn(&msth_server::ConnectionCounts) -> bool,
) {
    let deadline = Instant::now() + Duration::from_secs(3);
    loop {
        let counts = server.connections();
        if check(&counts) {
            return;
        }
        assert!(Instant::now() < deadline, "{what}: {counts:?}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

const SLOTS: usize = 32;
const SLOW: usize = 64;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_address_cannot_take_all_slots() {
    let limits = Limits {
        max_connections: SLOTS,
        max_connections_per_ip: 8,
        header_read_timeout: Duration::from_secs(30),
        ..Limits::default()
    };
    let (_dir, server) = fixture(limits);
    let slow = open_slow(server.addr(), SLOW, |_| loopback(2), Duration::from_secs(2)).await;
    wait_for(&server, "8 slow connections held, 56 refused", |c| {
        c.open == 8 && c.refused_per_ip == (SLOW - 8) as u64
    })
    .await;
    let (status, body, elapsed) = normal_get(loopback(1), server.addr(), "/models/a.msth").await;
    assert_eq!(status, 200);
    assert_eq!(body.len(), FILE_BYTES);
    let counts = server.connections();
    println!(
        "one address: {SLOTS} slots, {SLOW} slow connections from 127.0.0.2 (8 allowed per \
         address), normal request served in {:.1} ms; {counts:?}",
        elapsed.as_secs_f64() * 1e3
    );
    let still_open = slow.iter().filter(|h| !h.is_finished()).count();
    assert_eq!(
        still_open, 8,
        "the 8 admitted slow clients are still connected"
    );
    for h in slow {
        h.abort();
    }
    server.stop().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn many_addresses_cannot_starve_a_new_client() {
    let limits = Limits {
        max_connections: SLOTS,
        max_connections_per_ip: 8,
        header_read_timeout: Duration::from_secs(30),
        ..Limits::default()
    };
    let (_dir, server) = fixture(limits);
    // One slow connection from each of 64 addresses: the per-address cap never applies.
    let slow = open_slow(
        server.addr(),
        SLOW,
        |i| loopback(2 + i as u8),
        Duration::from_secs(2),
    )
    .await;
    wait_for(&server, "every slot taken by a slow client", |c| {
        c.open == SLOTS && c.accepted == SLOW as u64
    })
    .await;
    let before = server.connections();
    let (status, body, elapsed) = normal_get(loopback(1), server.addr(), "/models/a.msth").await;
    assert_eq!(status, 200);
    assert_eq!(body.len(), FILE_BYTES);
    let counts = server.connections();
    assert_eq!(counts.timed_out, 0, "no header deadline was involved");
    assert!(
        counts.shed > before.shed,
        "a slow client made room: {counts:?}"
    );
    println!(
        "many addresses: {SLOTS} slots, {SLOW} slow connections from 64 addresses, normal \
         request served in {:.1} ms; {counts:?}",
        elapsed.as_secs_f64() * 1e3
    );
    let still_open = slow.iter().filter(|h| !h.is_finished()).count();
    assert_eq!(
        still_open,
        SLOTS - 1,
        "the newest slow clients still hold the other slots"
    );
    for h in slow {
        h.abort();
    }
    server.stop().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn header_deadline_and_idle_keep_alive() {
    let timeout = Duration::from_millis(500);
    let limits = Limits {
        max_connections: 4,
        header_read_timeout: timeout,
        ..Limits::default()
    };
    let (_dir, server) = fixture(limits);
    // Clients that keep sending a header line every 100 ms: alive, but never done.
    let slow = open_slow(
        server.addr(),
        4,
        |_| loopback(1),
        Duration::from_millis(100),
    )
    .await;
    let mut closed_after = Vec::new();
    for h in slow {
        let t = tokio::time::timeout(Duration::from_secs(5), h)
            .await
            .expect("a trickling client is closed by the header deadline")
            .unwrap();
        assert!(t >= timeout / 2, "closed too early: {t:?}");
        closed_after.push(t);
    }
    wait_for(&server, "4 header timeouts", |c| {
        c.timed_out >= 4 && c.open == 0
    })
    .await;

    // Keep-alive: two requests on one connection, then idle until the server closes it.
    let mut stream = connect_from(loopback(1), server.addr()).await.unwrap();
    for _ in 0..2 {
        stream
            .write_all(b"GET /models/a.msth HTTP/1.1\r\nHost: t\r\n\r\n")
            .await
            .unwrap();
        let mut reply = Vec::new();
        let mut buf = [0u8; 4096];
        while parse_reply_len(&reply) > reply.len() {
            let n = stream.read(&mut buf).await.unwrap();
            assert!(
                n > 0,
                "keep-alive connection closed before the response ended"
            );
            reply.extend_from_slice(&buf[..n]);
        }
        let (status, body) = parse_reply(&reply);
        assert_eq!((status, body.len()), (200, FILE_BYTES));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let idle_from = Instant::now();
    let mut buf = [0u8; 16];
    let n = tokio::time::timeout(Duration::from_secs(5), stream.read(&mut buf))
        .await
        .expect("an idle keep-alive connection is closed by the server");
    assert!(matches!(n, Ok(0) | Err(_)), "no bytes after the responses");
    let idle = idle_from.elapsed();
    println!(
        "header_read_timeout {timeout:?}: trickling clients closed after {closed_after:?}; \
         idle keep-alive connection closed after {idle:?}; {:?}",
        server.connections()
    );
    server.stop().unwrap();
}

/// Total length (head + Content-Length) of the response at the start of `reply`, or `usize::MAX`
/// while its head is incomplete.
fn parse_reply_len(reply: &[u8]) -> usize {
    let Some(split) = reply.windows(4).position(|w| w == b"\r\n\r\n") else {
        return usize::MAX;
    };
    let head = String::from_utf8_lossy(&reply[..split]).to_ascii_lowercase();
    let len: usize = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .and_then(|v| v.trim().parse().ok())
        .expect("a content-length");
    split + 4 + len
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_response_in_progress_is_never_shed() {
    let limits = Limits {
        max_connections: 2,
        header_read_timeout: Duration::from_secs(30),
        ..Limits::default()
    };
    let (dir, server) = fixture(limits);
    let big_len = std::fs::metadata(dir.path().join("big.msth"))
        .unwrap()
        .len() as usize;
    // A download that reads only its first bytes, so the server is stuck writing the rest.
    let mut download = connect_from(loopback(2), server.addr()).await.unwrap();
    download
        .write_all(b"GET /models/big.msth HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut first = vec![0u8; 4096];
    let got = download.read(&mut first).await.unwrap();
    assert!(got > 0);
    // A slow client takes the other slot.
    let mut slow = open_slow(server.addr(), 1, |_| loopback(3), Duration::from_secs(2)).await;
    wait_for(&server, "both slots taken", |c| c.open == 2).await;
    let (status, _, elapsed) = normal_get(loopback(1), server.addr(), "/models/a.msth").await;
    assert_eq!(status, 200);
    tokio::time::timeout(Duration::from_secs(2), slow.remove(0))
        .await
        .expect("the slow client was shed")
        .unwrap();
    // The download still gets every byte.
    let mut rest = Vec::new();
    download.read_to_end(&mut rest).await.unwrap();
    let mut reply = first[..got].to_vec();
    reply.extend_from_slice(&rest);
    let (status, body) = parse_reply(&reply);
    assert_eq!((status, body.len()), (200, big_len));
    println!(
        "busy download kept, slow client shed, normal request in {:.1} ms; {:?}",
        elapsed.as_secs_f64() * 1e3,
        server.connections()
    );
    server.stop().unwrap();
}
