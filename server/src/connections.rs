//! Client connections: the accept loop and what each connection carries.
//!
//! - Accept errors (out of file descriptors, mostly) back off from 5 ms to 1 s with a warning,
//!   instead of spinning a core while other clients time out.
//! - A connection that sends nothing for [`Limits::idle_timeout`] is closed. Live HTTP/2 clients
//!   answer the server's keepalive pings, which count as traffic, so only silent or dead peers
//!   are closed.
//! - Beyond [`Limits::max_connections`] a connection is still accepted, but only to be answered
//!   `RESOURCE_EXHAUSTED` (see [`ConnInfo::over_limit`]) and closed after a short grace; beyond
//!   twice the limit it is closed at once.
//! - A connection may have [`MAX_STREAMS_PER_CONNECTION`] requests open at once.
//! - Each connection is its own [`Tenant`] when the server has no tenant tokens: what it may hold
//!   is that tenant's share.
//! - On shutdown the loop drops the listener at once, so new connections are refused while the
//!   calls in flight finish.

use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::time::{Instant, Sleep};
use tokio_stream::wrappers::ReceiverStream;

use crate::budget::{Share, Tenant};
use crate::metrics::Metrics;
use crate::shutdown::Shutdown;

/// Default most connections served at once.
pub const DEFAULT_MAX_CONNECTIONS: usize = 1024;
/// Default time a connection may stay silent (no bytes, not even a keepalive ping's answer).
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(120);
/// The server pings every connection this often (HTTP/2 keepalive): well inside the idle
/// timeout, so a live client always has traffic.
pub const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(30);
/// A keepalive ping unanswered this long closes the connection.
pub const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);
/// Most requests (HTTP/2 streams) open at once on one connection, announced in the server's
/// SETTINGS: a client that opens more waits for one to end. Without it, one connection could
/// hold any number of idle StepStreams (or unary calls whose body never comes), each holding
/// buffers and a task.
pub const MAX_STREAMS_PER_CONNECTION: u32 = 256;
/// How long a connection over the limit lives to receive its `RESOURCE_EXHAUSTED`.
const OVER_LIMIT_GRACE: Duration = Duration::from_secs(2);
/// First and longest pause after an accept error.
const BACKOFF: (Duration, Duration) = (Duration::from_millis(5), Duration::from_secs(1));

/// The connection limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Most connections served at once.
    pub max_connections: usize,
    /// A connection silent this long is closed.
    pub idle_timeout: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
        }
    }
}

/// What the service knows of the connection a request came on (a request extension).
#[derive(Debug, Clone)]
pub struct ConnInfo {
    /// The peer.
    pub remote: Option<SocketAddr>,
    /// Accepted beyond the connection limit: every call is answered `RESOURCE_EXHAUSTED`.
    pub over_limit: Option<usize>,
    /// The tenant this connection is when the server has no tenant tokens.
    pub tenant: Arc<Tenant>,
}

/// Counts a connection until dropped: among open ones, or among those over the limit.
#[derive(Debug)]
struct Counted {
    /// Holds the counters.
    metrics: Arc<Metrics>,
    /// Which counter.
    over_limit: bool,
}

impl Counted {
    fn new(metrics: &Arc<Metrics>, over_limit: bool) -> Counted {
        let counted = Counted {
            metrics: Arc::clone(metrics),
            over_limit,
        };
        counted.counter().fetch_add(1, Ordering::AcqRel);
        counted
    }

    fn counter(&self) -> &AtomicU64 {
        if self.over_limit {
            &self.metrics.over_limit_connections
        } else {
            &self.metrics.open_connections
        }
    }
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.counter().fetch_sub(1, Ordering::AcqRel);
    }
}

/// An accepted TCP connection that closes itself when silent for too long.
#[derive(Debug)]
pub struct Conn {
    /// The socket.
    io: TcpStream,
    /// Fires when the connection has been silent too long (or its grace over the limit ended).
    idle: Pin<Box<Sleep>>,
    /// The silence allowed; `None` for a connection over the limit, whose deadline never moves.
    idle_after: Option<Duration>,
    /// For the service.
    info: ConnInfo,
    /// Counted while it lives.
    _counted: Counted,
}

impl tonic::transport::server::Connected for Conn {
    type ConnectInfo = ConnInfo;

    fn connect_info(&self) -> ConnInfo {
        self.info.clone()
    }
}

impl AsyncRead for Conn {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        match Pin::new(&mut self.io).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                if let Some(after) = self.idle_after {
                    if buf.filled().len() > before {
                        self.idle.as_mut().reset(Instant::now() + after);
                    }
                }
                Poll::Ready(Ok(()))
            }
            Poll::Pending => match self.idle.as_mut().poll(cx) {
                Poll::Ready(()) => Poll::Ready(Err(std::io::Error::new(
                    std::io::ErrorKind::TimedOut,
                    "connection idle for too long",
                ))),
                Poll::Pending => Poll::Pending,
            },
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
        }
    }
}

impl AsyncWrite for Conn {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.io).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }
}

/// The stream of connections tonic serves, fed by [`accept`].
pub type Incoming = ReceiverStream<Result<Conn, std::io::Error>>;

/// Starts accepting on `listener` until `shutdown` fires; returns the connections to serve.
pub fn accept(
    listener: TcpListener,
    limits: Limits,
    share: Share,
    metrics: Arc<Metrics>,
    shutdown: Shutdown,
) -> Incoming {
    let (tx, rx) = mpsc::channel(16);
    tokio::spawn(accept_loop(listener, limits, share, metrics, shutdown, tx));
    ReceiverStream::new(rx)
}

async fn accept_loop(
    listener: TcpListener,
    limits: Limits,
    share: Share,
    metrics: Arc<Metrics>,
    mut shutdown: Shutdown,
    tx: mpsc::Sender<Result<Conn, std::io::Error>>,
) {
    let mut backoff = BACKOFF.0;
    let mut failures: u64 = 0;
    loop {
        let accepted = tokio::select! {
            () = shutdown.wait() => break,
            accepted = listener.accept() => accepted,
        };
        let (io, remote) = match accepted {
            Ok(pair) => pair,
            Err(e) => {
                // EMFILE/ENFILE and the like: the error repeats until something closes, so wait
                // (longer each time) rather than spin. One warning per run of failures.
                if failures == 0 {
                    tracing::warn!(
                        "cannot accept connections ({e}); backing off until it recovers \
                         (raise `ulimit -n` or lower --max-connections)"
                    );
                }
                failures += 1;
                tokio::select! {
                    () = shutdown.wait() => break,
                    () = tokio::time::sleep(backoff) => {}
                }
                backoff = (backoff * 2).min(BACKOFF.1);
                continue;
            }
        };
        if failures > 0 {
            tracing::info!(failures, "accepting connections again");
            failures = 0;
        }
        backoff = BACKOFF.0;
        // Small request/reply pairs are the hot path: Nagle's algorithm would hold them back.
        let _ = io.set_nodelay(true);
        let open = metrics.open_connections.load(Ordering::Acquire);
        let over_limit = open >= limits.max_connections as u64;
        if over_limit
            && metrics.over_limit_connections.load(Ordering::Acquire)
                >= limits.max_connections as u64
        {
            // Far over the limit: even an answer would hold a descriptor for its grace period.
            drop(io);
            continue;
        }
        // Over the limit, the deadline is the grace period and traffic does not move it.
        let (idle_after, deadline) = if over_limit {
            (None, OVER_LIMIT_GRACE)
        } else {
            (Some(limits.idle_timeout), limits.idle_timeout)
        };
        let conn = Conn {
            io,
            idle: Box::pin(tokio::time::sleep(deadline)),
            idle_after,
            info: ConnInfo {
                remote: Some(remote),
                over_limit: over_limit.then_some(limits.max_connections),
                tenant: Arc::new(Tenant::new(format!("connection {remote}"), share)),
            },
            _counted: Counted::new(&metrics, over_limit),
        };
        if tx.send(Ok(conn)).await.is_err() {
            break;
        }
    }
    // Dropping the listener here closes the port at once: new connections are refused.
    drop(listener);
}

/// The connection a request came on, plaintext or TLS.
pub fn conn_info<T>(request: &tonic::Request<T>) -> Option<&ConnInfo> {
    let ext = request.extensions();
    ext.get::<ConnInfo>().or_else(|| {
        ext.get::<tonic::transport::server::TlsConnectInfo<ConnInfo>>()
            .map(|tls| tls.get_ref())
    })
}
