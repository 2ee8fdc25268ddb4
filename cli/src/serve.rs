//! `msth serve PATH [--addr 127.0.0.1:8080] [--web DIR] [limits]`: a thin layer over `msth-server` that
//! sets up logging and a tokio runtime, prints the URLs served, and runs until Ctrl-C.

use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

#[derive(Args)]
pub struct ServeArgs {
    /// One `.msth` file, or a folder whose `.msth` files are served.
    pub path: PathBuf,
    /// Address to listen on (port 0: any free port).
    #[arg(long, default_value = msth_server::DEFAULT_ADDR)]
    pub addr: SocketAddr,
    /// The web player's folder, served at `/` (default: `web/` if it exists).
    #[arg(long)]
    pub web: Option<PathBuf>,
    /// Most connections open at once (when all are taken, the oldest one without a request in
    /// progress is closed to make room for a new client).
    #[arg(long, default_value_t = msth_server::Limits::default().max_connections)]
    pub max_connections: usize,
    /// Most connections open at once from one client IP address.
    #[arg(long, default_value_t = msth_server::Limits::default().max_connections_per_ip)]
    pub max_connections_per_ip: usize,
    /// Seconds a connection may take to send a request's headers, counted from accept or from
    /// the end of the previous response (so also the idle keep-alive timeout).
    #[arg(long, default_value_t = msth_server::Limits::default().header_read_timeout.as_secs_f64())]
    pub header_timeout_secs: f64,
    /// MiB of served files held in memory (each file up to a quarter of it; larger ones are
    /// streamed from disk). 0: every response is read from disk.
    #[arg(long, default_value_t = msth_server::DEFAULT_CACHE_BYTES >> 20, value_name = "MIB")]
    pub cache_mib: u64,
    /// Pace every response to RATE bytes/s (units k, M, G of bytes or kbit, mbit, gbit: `10mbit`),
    /// optionally changing over the server's lifetime: `50mbit,3mbit@5,50mbit@10` (seconds since
    /// start). A slow or changing link on loopback, to test players with.
    #[arg(long, value_name = "RATE[,RATE@SECONDS...]")]
    pub rate_limit: Option<String>,
}

/// The server `msth serve` starts for `args` (`msth demo` starts the same one in-process).
pub(crate) fn server_config(args: &ServeArgs) -> anyhow::Result<msth_server::ServerConfig> {
    let mut config = msth_server::ServerConfig::new(&args.path);
    config.addr = args.addr;
    config.web_dir = args.web.clone().or_else(default_web_dir);
    config.limits.max_connections = args.max_connections.max(1);
    config.limits.max_connections_per_ip = args.max_connections_per_ip.max(1);
    config.rate_limit = args
        .rate_limit
        .as_deref()
        .map(msth_server::throttle::RateSchedule::parse)
        .transpose()
        .map_err(|e| anyhow::anyhow!("--rate-limit {e}"))?;
    config.cache_bytes = args
        .cache_mib
        .checked_mul(1 << 20)
        .context("--cache-mib is too large")?;
    config.limits.header_read_timeout =
        std::time::Duration::try_from_secs_f64(args.header_timeout_secs)
            .ok()
            .filter(|d| !d.is_zero())
            .context("--header-timeout-secs must be a positive number of seconds")?;
    Ok(config)
}

/// The web player's folder when `--web` is not given: `web/` in the current directory, if any.
pub(crate) fn default_web_dir() -> Option<PathBuf> {
    Some(PathBuf::from("web")).filter(|p| p.is_dir())
}

pub fn serve(args: ServeArgs) -> anyhow::Result<()> {
    // Request log lines on stderr; a second call (tests) keeps the first subscriber.
    let _ = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
    let config = server_config(&args)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(async move {
        let server = msth_server::Server::bind(config).await?;
        let base = format!("http://{}", server.local_addr());
        let models = server.models()?;
        // A closed stdout (`msth serve ... | head -1`) must not stop the server: ignore write
        // errors instead of panicking as `println!` does.
        let mut out = std::io::stdout();
        let _ = writeln!(
            out,
            "serving {} model(s) from {} at {base}/ (listing: {base}/models); Ctrl-C stops",
            models.len(),
            server.root().display()
        );
        for m in &models {
            let _ = writeln!(out, "  {base}/models/{} ({} bytes)", m.name, m.bytes);
        }
        let _ = out.flush();
        server
            .run_until(async {
                let _ = tokio::signal::ctrl_c().await;
                let _ = writeln!(
                    std::io::stderr(),
                    "Ctrl-C: finishing open requests and stopping"
                );
            })
            .await?;
        anyhow::Ok(())
    })
}
