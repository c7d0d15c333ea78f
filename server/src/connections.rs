//! Client connections: the accept loop, what each connection carries, and shedding.
//!
//! - Accept errors (out of file descriptors, mostly) back off from 5 ms to 1 s with a warning,
//!   instead of spinning a core while other clients time out.
//! - The connection limit is capped below the open-file limit with headroom
//!   ([`Budget::for_limit`]), logged once at start, so that the loop sheds connections before
//!   `accept` runs out of descriptors.
//! - A connection that has not sent the 24 bytes of the HTTP/2 preface within
//!   [`Limits::preface_timeout`] is closed (with TLS, the first 24 bytes of its handshake).
//! - A connection that sends nothing for [`Limits::idle_timeout`] is closed. Live HTTP/2 clients
//!   answer the server's keepalive pings, which count as traffic, so only silent or dead peers
//!   are closed.
//! - At [`Limits::max_connections`], a new connection is admitted by closing the longest-idle
//!   connection with no call in flight, those that never sent the preface first. Sessions live
//!   on: they are keyed by ID, not by connection, and the client's next call reconnects.
//!   [`InFlightLayer`] counts each connection's calls in flight.
//!   A shed connection closes when its task next runs; the loop accepts no more while too many
//!   are still closing, so that a burst of new connections cannot outrun them into the
//!   open-file limit.
//! - When every connection has a call in flight, a new connection is still accepted, but only to
//!   be answered `RESOURCE_EXHAUSTED` (see [`ConnInfo::over_limit`]) and closed after a short
//!   grace; beyond [`Budget::max_over_limit`] of those (counting the shed ones still closing) it
//!   is closed at once.
//! - A connection may have [`MAX_STREAMS_PER_CONNECTION`] requests open at once.
//! - Each connection is its own [`Tenant`] when the server has no tenant tokens: what it may hold
//!   is that tenant's share.
//! - On shutdown the loop drops the listener at once, so new connections are refused while the
//!   calls in flight finish.

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::task::{Context, Poll, ready};
use std::time::Duration;

use http_body::{Body, Frame, SizeHint};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{Notify, mpsc, oneshot};
use tokio::time::{Instant, Sleep};
use tokio_stream::wrappers::ReceiverStream;
use tonic::codegen::http;

use crate::budget::{Share, Tenant};
use crate::fd_limit::{Budget, soft_limit};
use crate::metrics::Metrics;
use crate::shutdown::Shutdown;

/// Default most connections served at once.
pub const DEFAULT_MAX_CONNECTIONS: usize = 1024;
/// Default time a connection may stay silent (no bytes, not even a keepalive ping's answer).
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(120);
/// Default time a new connection has to send the HTTP/2 preface. Clients send it with their
/// first bytes, so only broken or hostile peers take longer.
pub const DEFAULT_PREFACE_TIMEOUT: Duration = Duration::from_secs(3);
/// Length of the HTTP/2 connection preface, `PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n`.
const PREFACE_BYTES: usize = 24;
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
/// Connections the kernel queues until the accept loop takes them. A burst of clients (a
/// thousand environments reconnecting at once) then waits in the queue rather than having its
/// connection attempts dropped and retried a second later, as with the usual 128. Linux caps it
/// at `net.core.somaxconn` (4096 by default).
pub const LISTEN_BACKLOG: u32 = 1024;
/// How long a connection over the limit lives to receive its `RESOURCE_EXHAUSTED`.
const OVER_LIMIT_GRACE: Duration = Duration::from_secs(2);
/// First and longest pause after an accept error.
const BACKOFF: (Duration, Duration) = (Duration::from_millis(5), Duration::from_secs(1));

/// The connection limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Most connections served at once (capped below the open-file limit:
    /// [`Budget::for_limit`]).
    pub max_connections: usize,
    /// A connection silent this long is closed.
    pub idle_timeout: Duration,
    /// A connection that has not sent the HTTP/2 preface this long after it was accepted is
    /// closed.
    pub preface_timeout: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
            preface_timeout: DEFAULT_PREFACE_TIMEOUT,
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
    /// What [`InFlightLayer`] counts its calls in; `None` over the limit (never shed).
    activity: Option<Arc<Activity>>,
}

/// What the accept loop reads of a connection to choose which to shed.
#[derive(Debug)]
struct Activity {
    /// Milliseconds from the table's epoch to the last byte read (or to the accept).
    last_read_ms: AtomicU64,
    /// The first [`PREFACE_BYTES`] bytes have arrived.
    preface: AtomicBool,
    /// Calls in flight ([`InFlightLayer`]).
    in_flight: AtomicUsize,
}

impl Activity {
    /// What the choice reads, now.
    fn idle(&self) -> Idle {
        Idle {
            preface: self.preface.load(Ordering::Relaxed),
            last_read_ms: self.last_read_ms.load(Ordering::Relaxed),
            in_flight: self.in_flight.load(Ordering::Acquire),
        }
    }
}

/// A connection's activity at one moment, for [`choose_to_shed`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Idle {
    /// It has sent the HTTP/2 preface.
    preface: bool,
    /// When it last sent a byte, in milliseconds from the table's epoch.
    last_read_ms: u64,
    /// Calls in flight.
    in_flight: usize,
}

/// The connection to close for a new one: among those with no call in flight, those that never
/// sent the preface first, then the one idle longest (the oldest on a tie). `None`: every
/// connection has a call in flight.
fn choose_to_shed(conns: impl IntoIterator<Item = (u64, Idle)>) -> Option<u64> {
    conns
        .into_iter()
        .filter(|(_, idle)| idle.in_flight == 0)
        .min_by_key(|&(id, idle)| (idle.preface, idle.last_read_ms, id))
        .map(|(id, _)| id)
}

/// The connections admitted, which the accept loop sheds from. Shared by the loop and by every
/// connection, which removes itself when it closes. A std mutex: it is held for an insert, a
/// removal or one scan of the table, never across an await.
#[derive(Debug)]
struct Table {
    /// What `last_read_ms` counts from.
    epoch: Instant,
    /// The connections.
    open: Mutex<Open>,
    /// Notified when a shed connection has closed.
    closed: Notify,
}

/// The table's contents.
#[derive(Debug, Default)]
struct Open {
    /// The next connection's key.
    next_id: u64,
    /// Admitted connections that are neither closed nor shed.
    conns: HashMap<u64, Entry>,
    /// Connections shed and not closed yet: their descriptors are still open.
    closing: usize,
}

/// One admitted connection in the table.
#[derive(Debug)]
struct Entry {
    /// What the choice reads.
    activity: Arc<Activity>,
    /// Sent or dropped to close the connection.
    close: oneshot::Sender<()>,
}

impl Table {
    fn new() -> Table {
        Table {
            epoch: Instant::now(),
            open: Mutex::new(Open::default()),
            closed: Notify::new(),
        }
    }

    /// Connections shed and not closed yet.
    fn closing(&self) -> usize {
        self.lock().closing
    }

    /// Returns once fewer than `most` shed connections are still closing.
    async fn until_closing_below(&self, most: usize) {
        // `notify_one` keeps a permit when nobody waits: a close between the check and the wait
        // is not missed.
        while self.closing() >= most {
            self.closed.notified().await;
        }
    }

    fn lock(&self) -> MutexGuard<'_, Open> {
        self.open.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn millis(&self, at: Instant) -> u64 {
        u64::try_from(at.saturating_duration_since(self.epoch).as_millis()).unwrap_or(u64::MAX)
    }

    /// Admits a connection: below `max` at once, at `max` by shedding one (`shed` is then
    /// true). `None`: the table is full of connections with calls in flight.
    fn admit(self: &Arc<Self>, max: usize) -> Option<(Tracked, bool)> {
        let now = Instant::now();
        let mut open = self.lock();
        let shed = open.conns.len() >= max;
        if shed {
            let victim = choose_to_shed(
                open.conns
                    .iter()
                    .map(|(&id, entry)| (id, entry.activity.idle())),
            )?;
            if let Some(entry) = open.conns.remove(&victim) {
                // The connection sees it at its next read (one is always pending) and closes.
                let _ = entry.close.send(());
                open.closing += 1;
            }
        }
        let id = open.next_id;
        open.next_id += 1;
        let activity = Arc::new(Activity {
            last_read_ms: AtomicU64::new(self.millis(now)),
            preface: AtomicBool::new(false),
            in_flight: AtomicUsize::new(0),
        });
        let (close, closed) = oneshot::channel();
        open.conns.insert(
            id,
            Entry {
                activity: Arc::clone(&activity),
                close,
            },
        );
        let tracked = Tracked {
            table: Arc::clone(self),
            id,
            activity,
            closed,
            shed: false,
        };
        Some((tracked, shed))
    }
}

/// A connection's place in the [`Table`]; it leaves the table when dropped.
#[derive(Debug)]
struct Tracked {
    /// The table.
    table: Arc<Table>,
    /// Its key there.
    id: u64,
    /// What it shares with the table and its calls.
    activity: Arc<Activity>,
    /// Ready when the accept loop sheds the connection.
    closed: oneshot::Receiver<()>,
    /// `closed` was ready (a oneshot may not be polled again).
    shed: bool,
}

impl Tracked {
    /// Whether the accept loop has shed this connection; registers the waker if not.
    fn poll_shed(&mut self, cx: &mut Context<'_>) -> bool {
        if !self.shed && Pin::new(&mut self.closed).poll(cx).is_ready() {
            self.shed = true;
        }
        self.shed
    }
}

impl Drop for Tracked {
    fn drop(&mut self) {
        let mut open = self.table.lock();
        if open.conns.remove(&self.id).is_none() {
            // It was shed, and is closed now.
            open.closing -= 1;
            drop(open);
            self.table.closed.notify_one();
        }
    }
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

/// An accepted TCP connection that closes itself when it sends no preface in time, when silent
/// for too long, or when the accept loop sheds it.
#[derive(Debug)]
pub struct Conn {
    /// The socket.
    io: TcpStream,
    /// Fires when the preface is late, when the connection has been silent too long, or when
    /// its grace over the limit ended.
    idle: Pin<Box<Sleep>>,
    /// The silence allowed; `None` for a connection over the limit, whose deadline never moves.
    idle_after: Option<Duration>,
    /// Preface bytes still to come: until they have, reads do not move the deadline.
    preface_left: usize,
    /// Its place among the connections that may be shed; `None` over the limit. Declared after
    /// `io`: fields drop in order, so the socket is closed by the time it leaves the table.
    tracked: Option<Tracked>,
    /// For the service.
    info: ConnInfo,
    /// Counted while it lives.
    counted: Counted,
    /// Its deadline passed: counted once among the timeouts, however often it is read after.
    timed_out: bool,
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
        if self.tracked.as_mut().is_some_and(|t| t.poll_shed(cx)) {
            return Poll::Ready(Err(std::io::Error::new(
                std::io::ErrorKind::ConnectionAborted,
                "connection closed to admit another at the connection limit",
            )));
        }
        let before = buf.filled().len();
        match Pin::new(&mut self.io).poll_read(cx, buf) {
            Poll::Ready(Ok(())) => {
                let read = buf.filled().len() - before;
                if read > 0 {
                    self.on_read(read);
                }
                Poll::Ready(Ok(()))
            }
            Poll::Pending => match self.idle.as_mut().poll(cx) {
                Poll::Ready(()) => {
                    let no_preface = self.preface_left > 0;
                    // Connections over the limit end their grace here too: not a timeout.
                    if self.tracked.is_some() && !std::mem::replace(&mut self.timed_out, true) {
                        let metrics = &self.counted.metrics;
                        let counter = if no_preface {
                            &metrics.connections_without_preface
                        } else {
                            &metrics.connections_idle_closed
                        };
                        counter.fetch_add(1, Ordering::Relaxed);
                    }
                    Poll::Ready(Err(std::io::Error::new(
                        std::io::ErrorKind::TimedOut,
                        if no_preface {
                            "no HTTP/2 preface in time"
                        } else {
                            "connection idle for too long"
                        },
                    )))
                }
                Poll::Pending => Poll::Pending,
            },
            Poll::Ready(Err(e)) => Poll::Ready(Err(e)),
        }
    }
}

impl Conn {
    /// `read` bytes arrived: counts the preface, moves the idle deadline once it is complete,
    /// and tells the table when the connection was last heard from.
    fn on_read(&mut self, read: usize) {
        let now = Instant::now();
        if self.preface_left > 0 {
            self.preface_left = self.preface_left.saturating_sub(read);
            if self.preface_left == 0 {
                if let Some(tracked) = &self.tracked {
                    tracked.activity.preface.store(true, Ordering::Relaxed);
                }
            }
        }
        if self.preface_left == 0 {
            if let Some(after) = self.idle_after {
                self.idle.as_mut().reset(now + after);
            }
        }
        if let Some(tracked) = &self.tracked {
            let at = tracked.table.millis(now);
            tracked.activity.last_read_ms.store(at, Ordering::Relaxed);
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

/// Listens on the first address of `host:port` that binds, with a queue of [`LISTEN_BACKLOG`].
pub async fn bind(host: &str, port: u16) -> std::io::Result<TcpListener> {
    let mut last = None;
    for addr in tokio::net::lookup_host((host, port)).await? {
        match bind_addr(addr) {
            Ok(listener) => return Ok(listener),
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "the host resolves to no address",
        )
    }))
}

fn bind_addr(addr: SocketAddr) -> std::io::Result<TcpListener> {
    let socket = if addr.is_ipv4() {
        TcpSocket::new_v4()?
    } else {
        TcpSocket::new_v6()?
    };
    // As `TcpListener::bind` does: a restarted server may bind while old connections linger.
    #[cfg(unix)]
    socket.set_reuseaddr(true)?;
    socket.bind(addr)?;
    socket.listen(LISTEN_BACKLOG)
}

/// Starts accepting on `listener` until `shutdown` fires; returns the connections to serve.
/// The connection limit is capped below the process's open-file limit ([`Budget::for_limit`]).
pub fn accept(
    listener: TcpListener,
    limits: Limits,
    share: Share,
    metrics: Arc<Metrics>,
    shutdown: Shutdown,
) -> Incoming {
    let nofile = soft_limit();
    let budget = Budget::for_limit(limits.max_connections, nofile);
    if budget.max_connections < limits.max_connections {
        tracing::info!(
            requested = limits.max_connections,
            max_connections = budget.max_connections,
            max_over_limit = budget.max_over_limit,
            open_files = nofile,
            "connection limit capped below the open-file limit, with headroom for the rest of \
             the server"
        );
    }
    let (tx, rx) = mpsc::channel(16);
    let accepting = Accepting {
        limits,
        budget,
        share,
        metrics,
        table: Arc::new(Table::new()),
    };
    tokio::spawn(accepting.run(listener, shutdown, tx));
    ReceiverStream::new(rx)
}

/// What the accept loop decides with.
struct Accepting {
    /// The limits given.
    limits: Limits,
    /// The limits under the open-file limit.
    budget: Budget,
    /// Each connection's tenant share.
    share: Share,
    /// The connection counters.
    metrics: Arc<Metrics>,
    /// The connections admitted.
    table: Arc<Table>,
}

impl Accepting {
    async fn run(
        self,
        listener: TcpListener,
        mut shutdown: Shutdown,
        tx: mpsc::Sender<Result<Conn, std::io::Error>>,
    ) {
        let mut backoff = BACKOFF.0;
        let mut failures: u64 = 0;
        // Connections shed since the loop last admitted one without shedding.
        let mut shed_run: u64 = 0;
        // A shed connection closes when its task next runs; until then its descriptor is open.
        // A burst of new connections must not outrun them into the open-file limit.
        let most_closing = (self.budget.max_over_limit / 2).max(1);
        loop {
            tokio::select! {
                () = shutdown.wait() => break,
                () = self.table.until_closing_below(most_closing) => {}
            }
            let accepted = tokio::select! {
                () = shutdown.wait() => break,
                accepted = listener.accept() => accepted,
            };
            let (io, remote) = match accepted {
                Ok(pair) => pair,
                Err(e) => {
                    // EMFILE/ENFILE and the like: the error repeats until something closes, so
                    // wait (longer each time) rather than spin. One warning per run of failures.
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
            let admitted = self.table.admit(self.budget.max_connections);
            match &admitted {
                Some((_, true)) => {
                    self.metrics
                        .connections_shed
                        .fetch_add(1, Ordering::Relaxed);
                    if shed_run == 0 {
                        tracing::warn!(
                            max_connections = self.budget.max_connections,
                            "at the connection limit: closing the longest-idle connection with \
                             no call in flight to admit each new one"
                        );
                    }
                    shed_run += 1;
                }
                Some((_, false)) if shed_run > 0 => {
                    tracing::info!(shed = shed_run, "below the connection limit again");
                    shed_run = 0;
                }
                _ => {}
            }
            let Some(conn) = self.conn(io, remote, admitted.map(|(tracked, _)| tracked)) else {
                continue;
            };
            if tx.send(Ok(conn)).await.is_err() {
                break;
            }
        }
        // Dropping the listener here closes the port at once: new connections are refused.
        drop(listener);
    }

    /// The connection to serve: admitted (`tracked`), or over the limit to be answered
    /// `RESOURCE_EXHAUSTED`; `None` when too many are answered already (it is closed at once).
    fn conn(&self, io: TcpStream, remote: SocketAddr, tracked: Option<Tracked>) -> Option<Conn> {
        let over_limit = tracked.is_none();
        // Connections over the limit share their descriptors with those shed and closing.
        let leaving = self.metrics.over_limit_connections.load(Ordering::Acquire)
            + self.table.closing() as u64;
        if over_limit && leaving >= self.budget.max_over_limit as u64 {
            // Far over the limit: even an answer would hold a descriptor for its grace period.
            return None;
        }
        // Over the limit, the deadline is the grace period and traffic does not move it.
        let (idle_after, deadline) = if over_limit {
            (None, OVER_LIMIT_GRACE)
        } else {
            let first = self.limits.preface_timeout.min(self.limits.idle_timeout);
            (Some(self.limits.idle_timeout), first)
        };
        Some(Conn {
            io,
            idle: Box::pin(tokio::time::sleep(deadline)),
            idle_after,
            preface_left: PREFACE_BYTES,
            info: ConnInfo {
                remote: Some(remote),
                over_limit: over_limit.then_some(self.budget.max_connections),
                tenant: Arc::new(Tenant::new(format!("connection {remote}"), self.share)),
                activity: tracked.as_ref().map(|t| Arc::clone(&t.activity)),
            },
            tracked,
            counted: Counted::new(&self.metrics, over_limit),
            timed_out: false,
        })
    }
}

/// The connection a request came on, plaintext or TLS.
pub fn conn_info<T>(request: &tonic::Request<T>) -> Option<&ConnInfo> {
    conn_info_in(request.extensions())
}

fn conn_info_in(ext: &http::Extensions) -> Option<&ConnInfo> {
    ext.get::<ConnInfo>().or_else(|| {
        ext.get::<tonic::transport::server::TlsConnectInfo<ConnInfo>>()
            .map(|tls| tls.get_ref())
    })
}

/// Counts each connection's calls in flight, from the request's arrival until its response body
/// ends or is dropped (streams included), so that the accept loop never sheds a connection in
/// the middle of a call. Every service is behind it: `Server::builder().layer(InFlightLayer)`.
#[derive(Debug, Clone, Copy, Default)]
pub struct InFlightLayer;

impl<S> tower::Layer<S> for InFlightLayer {
    type Service = InFlight<S>;

    fn layer(&self, inner: S) -> InFlight<S> {
        InFlight { inner }
    }
}

/// The service [`InFlightLayer`] makes.
#[derive(Debug, Clone)]
pub struct InFlight<S> {
    /// The services behind it.
    inner: S,
}

impl<S, ReqBody, ResBody> tower::Service<http::Request<ReqBody>> for InFlight<S>
where
    S: tower::Service<http::Request<ReqBody>, Response = http::Response<ResBody>>,
    S::Future: Unpin,
{
    type Response = http::Response<CallBody<ResBody>>;
    type Error = S::Error;
    type Future = CallFuture<S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<ReqBody>) -> Self::Future {
        let call = conn_info_in(request.extensions())
            .and_then(|info| info.activity.as_ref())
            .map(Call::new);
        CallFuture {
            inner: self.inner.call(request),
            call,
        }
    }
}

/// A call in flight on a connection: counted until dropped.
#[derive(Debug)]
struct Call(Arc<Activity>);

impl Call {
    fn new(activity: &Arc<Activity>) -> Call {
        activity.in_flight.fetch_add(1, Ordering::AcqRel);
        Call(Arc::clone(activity))
    }
}

impl Drop for Call {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Ordering::AcqRel);
    }
}

/// The response future of [`InFlight`]: hands the call to the response body.
#[derive(Debug)]
pub struct CallFuture<F> {
    /// The inner service's future.
    inner: F,
    /// The call, until the response is ready.
    call: Option<Call>,
}

impl<F, B, E> Future for CallFuture<F>
where
    F: Future<Output = Result<http::Response<B>, E>> + Unpin,
{
    type Output = Result<http::Response<CallBody<B>>, E>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let response = ready!(Pin::new(&mut self.inner).poll(cx));
        let call = self.call.take();
        Poll::Ready(response.map(|r| r.map(|body| CallBody { body, call })))
    }
}

/// A response body that keeps its call counted until it ends or is dropped.
#[derive(Debug)]
pub struct CallBody<B> {
    /// The body.
    body: B,
    /// The call, until the body ends.
    call: Option<Call>,
}

impl<B: Body + Unpin> Body for CallBody<B> {
    type Data = B::Data;
    type Error = B::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        let frame = ready!(Pin::new(&mut self.body).poll_frame(cx));
        if frame.is_none() {
            self.call = None;
        }
        Poll::Ready(frame)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.body.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Longest a test waits for what should be immediate.
    const PATIENCE: Duration = Duration::from_secs(10);

    fn idle(preface: bool, last_read_ms: u64, in_flight: usize) -> Idle {
        Idle {
            preface,
            last_read_ms,
            in_flight,
        }
    }

    #[test]
    fn the_longest_idle_without_a_call_is_shed_preface_less_first() {
        // Longest idle: the earliest last read.
        let conns = [
            (1, idle(true, 500, 0)),
            (2, idle(true, 100, 0)),
            (3, idle(true, 300, 0)),
        ];
        assert_eq!(choose_to_shed(conns), Some(2));
        // A call in flight (a unary call or an open stream) protects even the longest idle.
        let conns = [
            (1, idle(true, 500, 0)),
            (2, idle(true, 100, 1)),
            (3, idle(true, 300, 0)),
        ];
        assert_eq!(choose_to_shed(conns), Some(3));
        // A connection that never sent the preface goes first, however recent.
        let conns = [
            (1, idle(true, 100, 0)),
            (2, idle(false, 900, 0)),
            (3, idle(false, 950, 0)),
        ];
        assert_eq!(choose_to_shed(conns), Some(2));
        // Ties go to the oldest connection.
        let conns = [(7, idle(false, 5, 0)), (4, idle(false, 5, 0))];
        assert_eq!(choose_to_shed(conns), Some(4));
        // Every connection busy (or none at all): nothing to shed.
        let conns = [(1, idle(true, 1, 2)), (2, idle(false, 1, 1))];
        assert_eq!(choose_to_shed(conns), None);
        assert_eq!(choose_to_shed([]), None);
    }

    #[tokio::test]
    async fn admitting_at_the_limit_closes_the_chosen_connection() {
        let table = Arc::new(Table::new());
        let (mut first, shed) = table.admit(2).unwrap();
        assert!(!shed);
        let (second, shed) = table.admit(2).unwrap();
        assert!(!shed);
        // The first has sent its preface and has a call in flight; the second is silent.
        first.activity.preface.store(true, Ordering::Relaxed);
        let call = Call::new(&first.activity);
        let (third, shed) = table.admit(2).unwrap();
        assert!(shed);
        let mut second = second;
        let waker = std::task::Waker::noop();
        let mut cx = Context::from_waker(waker);
        assert!(second.poll_shed(&mut cx), "the silent one was not closed");
        assert!(!first.poll_shed(&mut cx));
        assert_eq!(table.lock().conns.len(), 2);
        assert_eq!(table.closing(), 1);
        // A shed connection, once closed, is no longer counted as closing; the accept loop,
        // waiting for that, goes on.
        drop(second);
        assert_eq!(table.lock().conns.len(), 2);
        assert_eq!(table.closing(), 0);
        tokio::time::timeout(PATIENCE, table.until_closing_below(1))
            .await
            .unwrap();
        // Both left have calls in flight: nothing to shed, the next one is over the limit.
        let third_call = Call::new(&third.activity);
        assert!(table.admit(2).is_none());
        // A call ended: that connection may go now.
        drop(call);
        let (_fourth, shed) = table.admit(2).unwrap();
        assert!(shed);
        assert!(first.poll_shed(&mut cx));
        drop(third_call);
        drop(third);
        assert_eq!(table.lock().conns.len(), 1);
        drop(first);
        assert_eq!(table.closing(), 0);
    }
}
