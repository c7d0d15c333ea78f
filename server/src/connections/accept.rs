//! The accept loop: binds the listener, accepts with backoff, admits each connection into the
//! table (shedding at the limit) or answers it over the limit, and hands the connections to
//! tonic.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

use super::conn::Conn;
use super::fd_limit::{Capacity, soft_limit};
use super::table::{Shed, Table, Tracked};
use super::{ConnInfo, Limits};
use crate::budget::{Share, Tenant};
use crate::metrics::{Metrics, Refusal};
use crate::shutdown::Shutdown;

/// Connections the kernel queues until the accept loop takes them. A burst of clients (a
/// thousand environments reconnecting at once) then waits in the queue rather than having its
/// connection attempts dropped and retried a second later, as with the usual 128. Linux caps it
/// at `net.core.somaxconn` (4096 by default).
pub const LISTEN_BACKLOG: u32 = 1024;
/// How long a connection over the limit lives to receive its `RESOURCE_EXHAUSTED`.
const OVER_LIMIT_GRACE: Duration = Duration::from_secs(2);
/// First and longest pause after an accept error.
const BACKOFF: (Duration, Duration) = (Duration::from_millis(5), Duration::from_secs(1));

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
/// The connection limit is capped below the process's open-file limit ([`Capacity::for_limit`]).
pub fn accept(
    listener: TcpListener,
    limits: Limits,
    share: Share,
    metrics: Arc<Metrics>,
    shutdown: Shutdown,
) -> Incoming {
    let nofile = soft_limit();
    let capacity = Capacity::for_limit(limits.max_connections, nofile);
    if capacity.max_connections < limits.max_connections {
        tracing::info!(
            requested = limits.max_connections,
            max_connections = capacity.max_connections,
            max_over_limit = capacity.max_over_limit,
            open_files = nofile,
            "connection limit capped below the open-file limit, with headroom for the rest of \
             the server"
        );
    }
    let (tx, rx) = mpsc::channel(16);
    let accepting = Accepting {
        limits,
        per_address: limits.strangers_per_address(capacity.max_connections),
        capacity,
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
    capacity: Capacity,
    /// Most connections from one address without an authenticated call.
    per_address: usize,
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
        // Connections shed for their address's cap.
        let mut peer_sheds: u64 = 0;
        // A shed connection closes when its task next runs; until then its descriptor is open.
        // A burst of new connections must not outrun them into the open-file limit.
        let most_closing = (self.capacity.max_over_limit / 2).max(1);
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
            let admitted = self.table.admit(
                self.capacity.max_connections,
                self.per_address,
                Some(remote.ip()),
            );
            match &admitted {
                Some((_, Shed::Peer)) => {
                    self.metrics.count_refusal(Refusal::AddressCap);
                    // A warning for the first, then one every 1,024: a flood must not flood the log.
                    if peer_sheds % 1024 == 0 {
                        tracing::warn!(
                            peer = %remote.ip(),
                            max_connections_per_address = self.per_address,
                            shed = peer_sheds + 1,
                            "an address holds its most connections without an authenticated \
                             call: closing its longest-idle one to admit each new one"
                        );
                    }
                    peer_sheds += 1;
                }
                Some((_, Shed::Limit)) => {
                    self.metrics.connections_shed.inc();
                    if shed_run == 0 {
                        tracing::warn!(
                            max_connections = self.capacity.max_connections,
                            "at the connection limit: closing the longest-idle connection with \
                             no call in flight to admit each new one"
                        );
                    }
                    shed_run += 1;
                }
                Some((_, Shed::No)) if shed_run > 0 => {
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
        let leaving = self
            .metrics
            .over_limit_connections
            .inner()
            .load(Ordering::Acquire)
            + self.table.closing() as u64;
        if over_limit && leaving >= self.capacity.max_over_limit as u64 {
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
        let info = ConnInfo {
            remote: Some(remote),
            over_limit: over_limit.then_some(self.capacity.max_connections),
            tenant: Arc::new(Tenant::new(format!("connection {remote}"), self.share)),
            activity: tracked.as_ref().map(|t| Arc::clone(&t.activity)),
        };
        Some(Conn::new(
            io,
            info,
            tracked,
            &self.metrics,
            deadline,
            idle_after,
        ))
    }
}
