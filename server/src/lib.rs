//! `msth-server`: a read-only HTTP server for `.msth` files. It serves bytes and never parses
//! them, so it links neither wgpu, the field math nor the trainer.
//!
//! - `GET/HEAD /models`: JSON `[{"name", "url", "bytes", "modified"}]` (see [`catalog`]).
//! - `GET/HEAD /models/NAME.msth`: the file, streamed, with RFC 9110 Range (one range -> 206,
//!   several -> 206 `multipart/byteranges` after merging overlaps, unsatisfiable -> 416
//!   `bytes */LEN`; invalid or more than [`range::MAX_RANGE_SPECS`] ranges -> 200 full body), a
//!   strong `ETag`, `Last-Modified`, and the preconditions in RFC 9110 §13.2.2 order:
//!   `If-Match`/`If-Unmodified-Since` -> 412, `If-None-Match`/`If-Modified-Since` -> 304, then
//!   `If-Range` ([`range`]). `HEAD` answers what `GET` would, without the body.
//! - anything else: the web player's static files ([`web`]), or a placeholder page at `/`.
//! - permissive CORS, request logging with `tracing`, limits ([`Limits`]) against slow or greedy
//!   clients: a header deadline that is also the keep-alive idle timeout, connection slots, a
//!   per-address cap, and shedding of idle connections when full ([`listener`]).
//! - files up to a quarter of [`ServerConfig::cache_bytes`] are answered from memory while they
//!   stay the same on disk (read once, then sliced for every response), larger ones streamed.
//!
//! The main types: [`ServerConfig`] -> [`Server::bind`] -> [`Server::run_until`]; [`serve`] runs
//! until Ctrl-C; [`BackgroundServer`] runs one on its own thread (tests, the player's tests).

mod cache;
pub mod catalog;
mod http;
pub mod listener;
pub mod range;
pub mod throttle;
mod web;

use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

pub use catalog::{Catalog, ModelEntry};
pub use http::MSTH_CONTENT_TYPE;
pub use listener::{ConnectionCounts, ConnectionStats};

/// What went wrong, grouped by who is at fault: the path given, the address, the runtime.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("{}", path.display())]
    Path {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: not servable: give a folder or a regular file whose name matches [A-Za-z0-9._-]+.msth (not starting with '.')", path.display())]
    NotServable { path: PathBuf },
    #[error("cannot listen on {addr}")]
    Bind {
        addr: SocketAddr,
        source: std::io::Error,
    },
    #[error("server: {0}")]
    Runtime(std::io::Error),
}

/// Limits on what one client may hold or send (see [`listener`] for how they act together).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Open connections at once (slots); more wait in the accept queue, and when all are taken
    /// a new client takes the slot of the oldest connection without a request in progress.
    /// Default 512.
    pub max_connections: usize,
    /// Open connections from one client IP address; more are closed at accept. Default 64
    /// (a browser opens at most 6 per host; room is left for several users behind one NAT).
    pub max_connections_per_ip: usize,
    /// Deadline for a request head (request line and header fields) to arrive complete,
    /// counted from the moment the connection waits for it: at accept, and after each response
    /// on a keep-alive connection, so it is also the idle keep-alive timeout. hyper's
    /// `header_read_timeout`. Default 10 s.
    pub header_read_timeout: Duration,
    /// Longest request target, in bytes (else 414).
    pub max_uri_bytes: usize,
    /// Total size of the request's header fields, in bytes (else 431).
    pub max_header_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_connections: 512,
            max_connections_per_ip: 64,
            header_read_timeout: Duration::from_secs(10),
            max_uri_bytes: 2048,
            max_header_bytes: 16 * 1024,
        }
    }
}

/// Everything [`Server::bind`] needs.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// One `.msth` file, or a folder whose `.msth` files are served.
    pub path: PathBuf,
    /// Default `127.0.0.1:8080`; port 0 picks a free port (read it back with
    /// [`Server::local_addr`]).
    pub addr: SocketAddr,
    /// The web player's folder, served at `/`; `None`: a placeholder page at `/`.
    pub web_dir: Option<PathBuf>,
    pub limits: Limits,
    /// Bytes of served files held in memory at most (default 256 MiB; 0: every response read
    /// from disk). Files larger than a quarter of it are always streamed from disk.
    pub cache_bytes: u64,
    /// Every response body paced to this rate (bytes/s, over the server's lifetime): a slow or
    /// changing link on loopback, for testing players ([`throttle`]). `None`: no limit.
    pub rate_limit: Option<throttle::RateSchedule>,
}

/// The default of [`ServerConfig::cache_bytes`].
pub const DEFAULT_CACHE_BYTES: u64 = 256 << 20;

/// The default bind address.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8080";

impl ServerConfig {
    /// Defaults for serving `path`: [`DEFAULT_ADDR`], no web folder, default limits.
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self {
            path: path.into(),
            addr: SocketAddr::from(([127, 0, 0, 1], 8080)),
            web_dir: None,
            limits: Limits::default(),
            cache_bytes: DEFAULT_CACHE_BYTES,
            rate_limit: None,
        }
    }
}

/// A bound, not yet running server.
pub struct Server {
    tcp: tokio::net::TcpListener,
    limits: Limits,
    stats: Arc<ConnectionStats>,
    local_addr: SocketAddr,
    catalog: Arc<Catalog>,
    router: axum::Router,
}

impl Server {
    /// Checks the path and binds the address; must run inside a tokio runtime.
    pub async fn bind(config: ServerConfig) -> Result<Self, ServeError> {
        let catalog = Arc::new(Catalog::open(&config.path)?);
        let web_dir = match &config.web_dir {
            Some(dir) => Some(Arc::<Path>::from(std::fs::canonicalize(dir).map_err(
                |source| ServeError::Path {
                    path: dir.clone(),
                    source,
                },
            )?)),
            None => None,
        };
        let tcp = tokio::net::TcpListener::bind(config.addr)
            .await
            .map_err(|source| ServeError::Bind {
                addr: config.addr,
                source,
            })?;
        let local_addr = tcp.local_addr().map_err(ServeError::Runtime)?;
        let router = http::router(http::AppState {
            catalog: catalog.clone(),
            cache: Arc::new(cache::FileCache::new(config.cache_bytes)),
            web_dir,
            limits: config.limits,
            rate_limit: config
                .rate_limit
                .clone()
                .map(|s| (Arc::new(s), std::time::Instant::now())),
        });
        Ok(Self {
            tcp,
            limits: config.limits,
            stats: Arc::new(ConnectionStats::default()),
            local_addr,
            catalog,
            router,
        })
    }

    /// The address actually bound (the port when 0 was asked).
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// What the accept loop has done so far (open connections, refusals, shedding, timeouts).
    pub fn stats(&self) -> Arc<ConnectionStats> {
        self.stats.clone()
    }

    /// The models served right now.
    pub fn models(&self) -> Result<Vec<ModelEntry>, ServeError> {
        self.catalog.list()
    }

    /// What is served (canonical folder or file).
    pub fn root(&self) -> &Path {
        self.catalog.describe()
    }

    /// Serves until `shutdown` completes, then stops accepting, closes connections that have no
    /// request in progress and lets open responses finish.
    pub async fn run_until(
        self,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> Result<(), ServeError> {
        listener::serve(self.tcp, self.router, self.limits, self.stats, shutdown)
            .await
            .map_err(ServeError::Runtime)
    }
}

/// Binds and serves until Ctrl-C.
pub async fn serve(config: ServerConfig) -> Result<(), ServeError> {
    Server::bind(config)
        .await?
        .run_until(async {
            let _ = tokio::signal::ctrl_c().await;
        })
        .await
}

/// A server on its own thread and tokio runtime; stopped (gracefully) on [`BackgroundServer::stop`]
/// or drop. For tests and tools that are not async.
pub struct BackgroundServer {
    addr: SocketAddr,
    stats: Arc<ConnectionStats>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<(), ServeError>>>,
}

impl BackgroundServer {
    /// Starts serving `config`; returns once the address is bound.
    pub fn start(config: ServerConfig) -> Result<Self, ServeError> {
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let thread = std::thread::Builder::new()
            .name("msth-server".into())
            .spawn(move || {
                let runtime = tokio::runtime::Builder::new_multi_thread()
                    .worker_threads(2)
                    .enable_all()
                    .build()
                    .map_err(ServeError::Runtime)?;
                runtime.block_on(async move {
                    let server = match Server::bind(config).await {
                        Ok(s) => s,
                        Err(e) => {
                            let _ = ready_tx.send(Err(e));
                            return Ok(());
                        }
                    };
                    let _ = ready_tx.send(Ok((server.local_addr(), server.stats())));
                    server
                        .run_until(async {
                            let _ = stop_rx.await;
                        })
                        .await
                })
            })
            .map_err(ServeError::Runtime)?;
        match ready_rx.recv() {
            Ok(Ok((addr, stats))) => Ok(Self {
                addr,
                stats,
                stop: Some(stop_tx),
                thread: Some(thread),
            }),
            Ok(Err(e)) => Err(e),
            Err(_) => Err(match thread.join() {
                Ok(Err(e)) => e,
                _ => ServeError::Runtime(std::io::Error::other("server thread ended early")),
            }),
        }
    }

    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// What the accept loop has done so far.
    pub fn connections(&self) -> ConnectionCounts {
        self.stats.snapshot()
    }

    /// `http://ADDR` + `path` (which starts with `/`).
    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    /// Stops accepting, waits for open requests, joins the thread.
    pub fn stop(mut self) -> Result<(), ServeError> {
        self.shutdown()
    }

    fn shutdown(&mut self) -> Result<(), ServeError> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        match self.thread.take().map(std::thread::JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(ServeError::Runtime(std::io::Error::other(
                "server thread panicked",
            ))),
            None => Ok(()),
        }
    }
}

impl Drop for BackgroundServer {
    fn drop(&mut self) {
        let _ = self.shutdown();
    }
}
