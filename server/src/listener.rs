//! The accept loop and the connection table: each TCP connection is served by hyper's HTTP/1.1
//! connection with a timer, under the limits of [`Limits`]:
//!
//! - **header deadline and keep-alive idle timeout**: hyper's `header_read_timeout`. In hyper 1.x
//!   its clock starts when the connection begins waiting for a request head (at accept, and again
//!   when the previous response is written), so the one setting bounds both a client that is slow
//!   to send its headers and a keep-alive connection left idle. The connection is then closed.
//! - **slots**: at most `max_connections` connections are open at once; further clients wait in
//!   the kernel's accept queue.
//! - **per client address**: a connection from an address that already holds
//!   `max_connections_per_ip` is closed at once, without an answer. An IPv6 client counts by its
//!   /64 prefix (one host usually holds a whole /64), an IPv4-mapped one by its IPv4 address.
//! - **shedding when full**: when a client is accepted while every slot is taken, the oldest
//!   connection that has no request in progress (idle keep-alive, or still sending its headers)
//!   is closed to make room. A connection whose response is being written is never shed; if every
//!   slot is busy that way, the new client waits for one to end.
//!
//! So clients that trickle headers in can hold slots only for `header_read_timeout` each, cannot
//! take more than `max_connections_per_ip` from one address, and cannot keep a new client waiting
//! while they hold slots without a request in progress.

use std::collections::{BTreeMap, HashMap};
use std::convert::Infallible;
use std::future::Future;
use std::io;
use std::net::{IpAddr, Ipv6Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::body::Body;
use axum::extract::Request;
use axum::response::Response;
use http_body_util::BodyExt;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore};
use tower::ServiceExt;

use crate::Limits;

/// Counters of what the accept loop did, shared with the owner of the server (tests, logs).
#[derive(Debug, Default)]
pub struct ConnectionStats {
    open: AtomicUsize,
    accepted: AtomicU64,
    refused_per_ip: AtomicU64,
    shed: AtomicU64,
    timed_out: AtomicU64,
}

/// A snapshot of [`ConnectionStats`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ConnectionCounts {
    /// Connections open now (each holds a slot).
    pub open: usize,
    /// Connections accepted and served since the start.
    pub accepted: u64,
    /// Connections closed at accept because their address held `max_connections_per_ip`.
    pub refused_per_ip: u64,
    /// Connections without a request in progress closed to make room for a new client.
    pub shed: u64,
    /// Connections closed because a request head did not arrive within `header_read_timeout`
    /// (this includes idle keep-alive connections).
    pub timed_out: u64,
}

impl ConnectionStats {
    pub fn snapshot(&self) -> ConnectionCounts {
        ConnectionCounts {
            open: self.open.load(Ordering::Relaxed),
            accepted: self.accepted.load(Ordering::Relaxed),
            refused_per_ip: self.refused_per_ip.load(Ordering::Relaxed),
            shed: self.shed.load(Ordering::Relaxed),
            timed_out: self.timed_out.load(Ordering::Relaxed),
        }
    }
}

/// What the accept loop knows about one open connection.
struct Entry {
    ip: IpAddr,
    /// Requests whose response has not been fully written (or dropped) yet.
    in_flight: Arc<AtomicUsize>,
    /// Notified to close the connection if it has no request in progress.
    shed: Arc<Notify>,
}

/// The open connections by id; ids grow with time, so the first entry is the oldest.
#[derive(Default)]
struct Table {
    next_id: u64,
    entries: BTreeMap<u64, Entry>,
    per_ip: HashMap<IpAddr, usize>,
}

impl Table {
    fn count(&self, ip: IpAddr) -> usize {
        self.per_ip.get(&ip).copied().unwrap_or(0)
    }

    fn insert(&mut self, entry: Entry) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        *self.per_ip.entry(entry.ip).or_insert(0) += 1;
        self.entries.insert(id, entry);
        id
    }

    fn remove(&mut self, id: u64) {
        if let Some(entry) = self.entries.remove(&id) {
            if let Some(n) = self.per_ip.get_mut(&entry.ip) {
                *n -= 1;
                if *n == 0 {
                    self.per_ip.remove(&entry.ip);
                }
            }
        }
    }

    /// Asks the oldest connection without a request in progress to close; false if none.
    fn shed_oldest_idle(&self) -> bool {
        match self
            .entries
            .values()
            .find(|e| e.in_flight.load(Ordering::Acquire) == 0)
        {
            Some(entry) => {
                entry.shed.notify_one();
                true
            }
            None => false,
        }
    }
}

/// Serves `router` on `tcp` until `shutdown` completes; then stops accepting, closes the
/// connections without a request in progress, lets the others finish their response, and
/// returns once every connection is closed.
pub(crate) async fn serve(
    tcp: TcpListener,
    router: axum::Router,
    limits: Limits,
    stats: Arc<ConnectionStats>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> io::Result<()> {
    let max_connections = limits.max_connections.max(1);
    let slots = Arc::new(Semaphore::new(max_connections));
    let table = Arc::new(Mutex::new(Table::default()));
    let stopping = Arc::new(tokio::sync::watch::Sender::new(false));
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let (stream, peer) = tokio::select! {
            accepted = tcp.accept() => match accepted {
                Ok(pair) => pair,
                Err(e) => {
                    // Out of file descriptors and the like: wait and retry rather than spin.
                    tracing::warn!("accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let ip = client_key(peer.ip());
        if lock(&table).count(ip) >= limits.max_connections_per_ip.max(1) {
            stats.refused_per_ip.fetch_add(1, Ordering::Relaxed);
            tracing::debug!(%peer, "refused: too many connections from this address");
            continue;
        }
        let permit = tokio::select! {
            permit = take_slot(&slots, &table, &stats) => permit,
            () = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let in_flight = Arc::new(AtomicUsize::new(0));
        let shed = Arc::new(Notify::new());
        let id = lock(&table).insert(Entry {
            ip,
            in_flight: in_flight.clone(),
            shed: shed.clone(),
        });
        stats.accepted.fetch_add(1, Ordering::Relaxed);
        stats.open.fetch_add(1, Ordering::Relaxed);
        let connection = Connection {
            stream,
            peer,
            router: router.clone(),
            limits,
            in_flight,
            shed,
            stopping: stopping.subscribe(),
            stats: stats.clone(),
        };
        let table = table.clone();
        tokio::spawn(async move {
            connection.run().await;
            lock(&table).remove(id);
            drop(permit);
        });
    }
    drop(tcp);
    stopping.send_replace(true);
    // Every connection holds a permit until it is removed from the table: wait for all.
    let all = u32::try_from(max_connections).unwrap_or(u32::MAX);
    let _ = slots.acquire_many(all).await;
    Ok(())
}

/// The address a connection counts against: IPv4 as is, IPv6 by its /64 prefix.
fn client_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(_) => ip,
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let s = v6.segments();
                IpAddr::V6(Ipv6Addr::new(s[0], s[1], s[2], s[3], 0, 0, 0, 0))
            }
        },
    }
}

fn lock(table: &Mutex<Table>) -> std::sync::MutexGuard<'_, Table> {
    // A panic while holding this short lock leaves the table consistent: keep going.
    table
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A free slot, shedding idle connections while there is none.
async fn take_slot(
    slots: &Arc<Semaphore>,
    table: &Mutex<Table>,
    stats: &ConnectionStats,
) -> OwnedSemaphorePermit {
    loop {
        if let Ok(permit) = slots.clone().try_acquire_owned() {
            return permit;
        }
        if lock(table).shed_oldest_idle() {
            stats.shed.fetch_add(1, Ordering::Relaxed);
        }
        // The shed connection (or any other that ends) returns its slot; if every connection
        // is busy, look again for one that has become idle a little later.
        if let Ok(Ok(permit)) =
            tokio::time::timeout(Duration::from_millis(100), slots.clone().acquire_owned()).await
        {
            return permit;
        }
    }
}

/// One accepted connection and what it needs to be served.
struct Connection {
    stream: TcpStream,
    peer: SocketAddr,
    router: axum::Router,
    limits: Limits,
    in_flight: Arc<AtomicUsize>,
    shed: Arc<Notify>,
    stopping: tokio::sync::watch::Receiver<bool>,
    stats: Arc<ConnectionStats>,
}

impl Connection {
    async fn run(mut self) {
        let router = self.router.clone();
        let in_flight = self.in_flight.clone();
        let service = hyper::service::service_fn(move |request: Request<Incoming>| {
            let guard = InFlight::enter(&in_flight);
            let router = router.clone();
            async move {
                let response: Response = match router.oneshot(request.map(Body::new)).await {
                    Ok(response) => response,
                    Err(never) => match never {},
                };
                // The guard lives as long as the body: until hyper has written or dropped it.
                Ok::<_, Infallible>(response.map(|body| {
                    Body::new(body.map_frame(move |frame| {
                        let _ = &guard;
                        frame
                    }))
                }))
            }
        });
        let mut builder = hyper::server::conn::http1::Builder::new();
        builder
            .timer(TokioTimer::new())
            .header_read_timeout(self.limits.header_read_timeout)
            .keep_alive(true);
        let conn = builder.serve_connection(TokioIo::new(self.stream), service);
        let mut conn = std::pin::pin!(conn);
        let mut graceful = false;
        loop {
            tokio::select! {
                result = conn.as_mut() => {
                    if let Err(e) = result {
                        if e.is_timeout() {
                            self.stats.timed_out.fetch_add(1, Ordering::Relaxed);
                            tracing::debug!(peer = %self.peer, "closed: no request head within the header read timeout");
                        } else {
                            tracing::debug!(peer = %self.peer, "connection error: {e}");
                        }
                    }
                    break;
                }
                () = self.shed.notified() => {
                    if self.in_flight.load(Ordering::Acquire) == 0 {
                        tracing::debug!(peer = %self.peer, "shed: all slots taken and this connection had no request in progress");
                        break;
                    }
                }
                changed = self.stopping.changed(), if !graceful => {
                    if changed.is_err() || *self.stopping.borrow() {
                        if self.in_flight.load(Ordering::Acquire) == 0 {
                            break;
                        }
                        graceful = true;
                        conn.as_mut().graceful_shutdown();
                    }
                }
            }
        }
        self.stats.open.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Counts one request in progress on its connection while alive.
struct InFlight(Arc<AtomicUsize>);

impl InFlight {
    fn enter(counter: &Arc<AtomicUsize>) -> Self {
        counter.fetch_add(1, Ordering::AcqRel);
        Self(counter.clone())
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::client_key;

    #[test]
    fn client_keys() {
        let key = |s: &str| client_key(s.parse().unwrap()).to_string();
        assert_eq!(key("192.0.2.7"), "192.0.2.7");
        assert_eq!(key("::ffff:192.0.2.7"), "192.0.2.7");
        assert_eq!(key("2001:db8:1:2:aaaa::1"), "2001:db8:1:2::");
        assert_eq!(key("2001:db8:1:2:bbbb::9"), "2001:db8:1:2::");
        assert_eq!(key("::1"), "::");
    }
}
