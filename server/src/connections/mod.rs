//! Client connections: the accept loop, what each connection carries, and shedding.
//!
//! - Accept errors (out of file descriptors, mostly) back off from 5 ms to 1 s with a warning,
//!   instead of spinning a core while other clients time out.
//! - The connection limit is capped below the open-file limit with headroom
//!   ([`Capacity::for_limit`]), logged once at start, so that the loop sheds connections before
//!   `accept` runs out of descriptors.
//! - A connection that has not sent the 24 bytes of the HTTP/2 preface within
//!   [`Limits::preface_timeout`] is closed (with TLS, the first 24 bytes of its handshake).
//! - A connection that sends nothing for [`Limits::idle_timeout`] is closed. Live HTTP/2 clients
//!   answer the server's keepalive pings, which count as traffic, so only silent or dead peers
//!   are closed.
//! - At [`Limits::max_connections`], a new connection is admitted by closing the longest-idle
//!   connection with no authenticated call in flight: those that never made an authenticated
//!   call first (a health Watch is no call in flight), among them those that never sent the
//!   preface. Sessions live on: they are keyed by ID, not by connection, and the client's next
//!   call reconnects. [`calls::Admit`] counts each connection's authenticated calls in flight.
//!   A shed connection closes when its task next runs; the loop accepts no more while too many
//!   are still closing, so that a burst of new connections cannot outrun them into the
//!   open-file limit.
//! - Connections from one peer address that have made no authenticated call hold at most
//!   [`Limits::max_connections_per_address`] (by default a quarter of the limit): at that
//!   cap, a new one from the address closes the longest idle of them, so that strangers from
//!   one address never hold more, while a tenant from it still connects.
//! - A connection is its first authenticated caller's, counted against that identity's
//!   `connections` quota until it closes ([`calls`]).
//! - When every connection has a call in flight, a new connection is still accepted, but only to
//!   be answered `RESOURCE_EXHAUSTED` (see [`ConnInfo::over_limit`]) and closed after a short
//!   grace; beyond [`Capacity::max_over_limit`] of those (counting the shed ones still closing) it
//!   is closed at once.
//! - A connection may have [`MAX_STREAMS_PER_CONNECTION`] requests open at once; the server, its
//!   calls as [`calls`] bounds them.
//! - Each connection is its own [`Tenant`] when the server has no token at all: what it may hold
//!   is that tenant's share. (The shared token's holders are one identity, tenants one each.)
//! - On shutdown the loop drops the listener at once, so new connections are refused while the
//!   calls in flight finish.
//!
//! One job a file:
//! - [`accept`](mod@accept): binding the listener, the accept loop with its backoff, admitting or answering
//!   each connection over the limit.
//! - `table`: the admitted connections, and the choice of which to shed.
//! - [`conn`]: one connection: the socket with its preface and idle timers.
//! - [`calls`]: the calls open at once, outside the DinerDash service and by identity.
//! - [`in_flight`]: what keeps a call counted until its response ends.
//! - [`fd_limit`]: the open-file limit, and the connections it has room for ([`Capacity`]).

pub mod accept;
pub mod calls;
pub mod conn;
pub mod fd_limit;
pub mod in_flight;
mod table;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tonic::codegen::http;

pub use accept::{Incoming, LISTEN_BACKLOG, accept, bind};
pub use conn::Conn;
pub use fd_limit::Capacity;
pub use in_flight::{CallBody, CallFuture};

use crate::budget::Tenant;
use table::Activity;

/// Default most connections served at once.
pub const DEFAULT_MAX_CONNECTIONS: usize = 1024;
/// By default, the connections of one peer address that made no authenticated call may hold
/// 1/4 of `--max-connections` (`--max-connections-per-address`).
pub const STRANGERS_PER_ADDRESS: usize = 4;
/// Default time a connection may stay silent (no bytes, not even a keepalive ping's answer).
pub const DEFAULT_IDLE_TIMEOUT: Duration = Duration::from_secs(120);
/// Default time a new connection has to send the HTTP/2 preface. Clients send it with their
/// first bytes, so only broken or hostile peers take longer.
pub const DEFAULT_PREFACE_TIMEOUT: Duration = Duration::from_secs(3);
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

/// The connection limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Most connections served at once (capped below the open-file limit:
    /// [`Capacity::for_limit`]).
    pub max_connections: usize,
    /// A connection silent this long is closed.
    pub idle_timeout: Duration,
    /// A connection that has not sent the HTTP/2 preface this long after it was accepted is
    /// closed.
    pub preface_timeout: Duration,
    /// Most connections from one peer address that have made no authenticated call; at it, a
    /// new one from that address closes the longest idle of them. `None`:
    /// [`STRANGERS_PER_ADDRESS`] of `max_connections`.
    pub max_connections_per_address: Option<usize>,
}

impl Limits {
    /// Most connections from one address without an authenticated call, of `max_connections`
    /// (the limit under the open-file limit): the one given, or its default part, at least 1.
    pub fn strangers_per_address(&self, max_connections: usize) -> usize {
        self.max_connections_per_address
            .unwrap_or(max_connections / STRANGERS_PER_ADDRESS)
            .max(1)
    }
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_connections: DEFAULT_MAX_CONNECTIONS,
            idle_timeout: DEFAULT_IDLE_TIMEOUT,
            preface_timeout: DEFAULT_PREFACE_TIMEOUT,
            max_connections_per_address: None,
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
    /// The tenant this connection is when the server has no token at all.
    pub tenant: Arc<Tenant>,
    /// What [`calls::Admit`] counts its calls in; `None` over the limit (never shed).
    activity: Option<Arc<Activity>>,
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
