//! The server's HTTP/1.1 endpoint (`--http-port`, alias `--metrics-port`), on hyper with axum's
//! router, that serves
//!
//! - `/` — the sessions page, and `/watch/{session_id}?env=K` — one environment drawn live
//!   (static files compiled into the binary, [`assets`]; an unknown session is a readable 404);
//! - `/api/sessions`, `/api/watch/{id}?env=K` — their data as JSON, and the same under `/events`
//!   as server-sent events ([`feeds`]);
//! - `/play` — a game a person plays, and `/api/play...` its actions and recording ([`play`]);
//! - `/metrics` — the Prometheus counters ([`crate::metrics`]).
//!
//! The pages themselves hold no data and need no token; the feeds and `/metrics` ask for one of
//! the server's tokens when it has any ([`access`]), as `Authorization: Bearer <token>`.
//!
//! How it faces the network ([`Exposure`]): with a certificate (`--tls-cert`) it speaks only
//! HTTPS, with the certificate gRPC serves ([`tls`]), so that those tokens never cross the
//! network in clear; and every request must name a `Host` the endpoint answers to ([`hosts`]),
//! or it is answered 421 before any route sees it (DNS rebinding).
//!
//! Why hyper and axum: both are already in the build (tonic serves gRPC on hyper, and its router
//! is axum's), so the endpoint adds no HTTP stack of its own: hyper parses requests (head size,
//! read timeout, malformed requests answered 400), axum routes them and frames the event
//! streams. axum is built lean (`tokio` and `query` features only: no JSON, forms or
//! `axum::serve`). The accept loop ([`serve`]) stays ours, because the endpoint's two limits
//! are per connection, which a router cannot see: at most [`MAX_CONNECTIONS`] at once, of which
//! one identity holds at most [`PER_IDENTITY`] and a stranger's (no valid token) are closed
//! first to make room ([`slots`]; with none to close, a new one is answered 503), and a client
//! that does not read is cut off after [`WRITE_TIMEOUT`]
//! ([`deadline`]; its socket's send buffer is [`SEND_BUFFER`], so that a write blocks soon). Each connection serves one request and closes, as browsers' event streams
//! hold their own connection anyway.
//!
//! - [`routes`]: the URLs, the GET/HEAD rule, the headers every response carries.
//! - [`access`]: tokens, and which sessions a viewer may see.
//! - [`feeds`]: the JSON of the sessions and of a watched environment, and their event streams.
//! - [`assets`]: the pages, scripts and style, and the 404 pages.
//! - [`play`]: the games played in the browser and their recordings.
//! - [`deadline`]: the slow-viewer cut-off.
//! - [`slots`]: the connection slots, by identity.
//! - [`tls`]: the endpoint's TLS acceptor and its certificate's names.
//! - [`hosts`]: the `Host` names a request may give.

pub mod access;
pub mod assets;
pub mod deadline;
pub mod feeds;
pub mod hosts;
pub mod play;
pub mod routes;
pub mod slots;
pub mod tls;

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpListener;
use tower::ServiceExt as _;

use crate::metrics::Metrics;
use crate::session::Store;
use crate::shutdown::Shutdown;

pub use access::{Access, Refused, Viewer};
pub use deadline::{WRITE_TIMEOUT, WriteDeadline};
pub use hosts::Hosts;
pub use slots::{Identity, PER_IDENTITY, Slot, Slots};
pub use tls::{HttpTls, TlsError};

/// Largest HTTP request head read (hyper's smallest buffer); anything longer is answered 431.
const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// How long a client may take to send its request head before the connection is dropped.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// Most connections served at once, event streams included; more are answered 503. Each
/// viewer costs a task, a socket and one frame in flight; the sockets come out of the
/// descriptors [`crate::connections::fd_limit`] keeps beside the gRPC connections, so there are
/// few.
pub const MAX_CONNECTIONS: usize = 32;
/// The kernel's send buffer of each web connection. Left alone, Linux lets a socket's buffer
/// grow to `net.ipv4.tcp_wmem`'s maximum (4 MiB by default): a viewer that stops reading would
/// hold that much kernel memory, and a watch stream (~30 frames, ~30 KB a second) would take
/// minutes to fill it before a write could block and [`WRITE_TIMEOUT`] start counting. Fixed,
/// the buffer is full within seconds; the largest page or frame still goes in one write.
pub const SEND_BUFFER: usize = 128 * 1024;

/// What the endpoint serves from. Shared by every connection.
#[derive(Debug)]
pub struct Site {
    /// The sessions.
    pub store: Store,
    /// The counters, for `/metrics` and the server totals.
    pub metrics: Arc<Metrics>,
    /// The tokens.
    pub access: Access,
    /// When the endpoint started (the first rates are measured from it).
    pub started: Instant,
    /// The games played on `/play` and their recordings.
    pub plays: play::Plays,
}

impl Site {
    /// A site over `store`, asking for `access`'s tokens.
    pub fn new(store: Store, metrics: Arc<Metrics>, access: Access) -> Site {
        Site {
            store,
            metrics,
            access,
            started: Instant::now(),
            plays: play::Plays::default(),
        }
    }
}

/// A JSON response of 200.
pub fn json(body: String) -> Response {
    ([(header::CONTENT_TYPE, "application/json")], body).into_response()
}

/// A JSON `{"error": message}` response of `status`.
pub fn error(status: StatusCode, message: &str) -> Response {
    let body = serde_json::json!({ "error": message }).to_string();
    (status, json(body)).into_response()
}

/// How the endpoint faces the network: TLS or not, and the host names it answers to besides
/// its own address, IP literals and (on loopback or a wildcard address) localhost.
#[derive(Debug, Clone, Default)]
pub struct Exposure {
    /// Serve HTTPS only, with this identity (the gRPC certificate); `None` serves plain HTTP.
    pub tls: Option<HttpTls>,
    /// More host names a request may give (`--http-allowed-host`).
    pub allowed_hosts: Vec<String>,
}

/// Serves `listener` in plain HTTP until `shutdown` fires, answering to its own address, IP
/// literals and localhost; event streams end then too.
pub async fn serve(listener: TcpListener, site: Arc<Site>, shutdown: Shutdown) {
    serve_exposed(listener, site, shutdown, Exposure::default()).await;
}

/// Serves `listener` as `exposure` says (TLS, allowed hosts) until `shutdown` fires.
pub async fn serve_exposed(
    listener: TcpListener,
    site: Arc<Site>,
    mut shutdown: Shutdown,
    exposure: Exposure,
) {
    let slots = Slots::new(MAX_CONNECTIONS);
    let access = site.access.clone();
    let pages = routes::router(site, shutdown.clone());
    let busy = routes::busy();
    let bound = match listener.local_addr() {
        Ok(bound) => bound,
        Err(e) => {
            tracing::warn!("http listener: {e}");
            return;
        }
    };
    let hosts = Arc::new(Hosts::new(
        bound,
        &exposure.allowed_hosts,
        exposure.tls.clone(),
    ));
    let acceptor = exposure.tls.map(|tls| tls.acceptor);
    loop {
        let accepted = tokio::select! {
            () = shutdown.wait() => return,
            accepted = listener.accept() => accepted,
        };
        match accepted {
            Ok((stream, _)) => {
                if let Err(e) = socket2::SockRef::from(&stream).set_send_buffer_size(SEND_BUFFER) {
                    tracing::debug!("http connection's send buffer: {e}");
                }
                // Over the limit, the connection is still read (hyper needs the request to
                // answer it), but only to be told 503 within the request timeout.
                let (slot, closed) = match slots.admit() {
                    Some((slot, closed)) => (Some(Arc::new(slot)), Some(closed)),
                    None => (None, None),
                };
                let routes = if slot.is_some() { &pages } else { &busy };
                let viewer = Viewing {
                    routes: routes.clone(),
                    hosts: Arc::clone(&hosts),
                    access: access.clone(),
                    slot,
                };
                let acceptor = acceptor.clone();
                tokio::spawn(async move {
                    let serving = async move {
                        match acceptor {
                            None => connection(stream, viewer).await,
                            Some(acceptor) => {
                                // The handshake gets the time the request head would.
                                let handshake = acceptor.accept(stream);
                                match tokio::time::timeout(REQUEST_TIMEOUT, handshake).await {
                                    Ok(Ok(stream)) => connection(stream, viewer).await,
                                    Ok(Err(e)) => Err(format!("TLS handshake: {e}")),
                                    Err(_) => Err("no TLS handshake in time".into()),
                                }
                            }
                        }
                    };
                    // A stranger's connection is closed when a new one needs its slot.
                    let shed = async move {
                        if let Some(closed) = closed {
                            if closed.await.is_ok() {
                                return;
                            }
                        }
                        std::future::pending::<()>().await;
                    };
                    let served = tokio::select! {
                        served = serving => served,
                        () = shed => Err("closed to make room for another connection".into()),
                    };
                    if let Err(e) = served {
                        tracing::debug!("http connection failed: {e}");
                    }
                });
            }
            Err(e) => {
                // Out of file descriptors and the like: wait instead of spinning.
                tracing::warn!("http listener: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

/// What one connection is served with.
struct Viewing {
    /// The pages, or the 503 answer over the limit.
    routes: Router,
    /// The host names a request may give.
    hosts: Arc<Hosts>,
    /// The tokens, to tell whose the request is.
    access: Access,
    /// The connection's slot; `None` over the limit.
    slot: Option<Arc<Slot>>,
}

impl Viewing {
    /// Counts the request's identity in the connection's slot: `Some(answer)` when that
    /// identity holds all its connections already.
    fn identify(&self, headers: &axum::http::HeaderMap) -> Option<Response> {
        let slot = self.slot.as_ref()?;
        let authorization = headers.get(header::AUTHORIZATION).map(|v| v.as_bytes());
        let identity = match self.access.viewer(authorization) {
            Err(_) => Identity::Stranger,
            Ok(Viewer::Anyone) => Identity::Everyone,
            Ok(Viewer::SharedToken) => Identity::Token(0),
            Ok(Viewer::Tenant(tenant)) => Identity::Token(Arc::as_ptr(&tenant) as usize),
        };
        let held = slot.identify(identity).err()?;
        Some(error(
            StatusCode::SERVICE_UNAVAILABLE,
            &format!(
                "this token holds {held} connections to this endpoint, the most one token may \
                 (of {MAX_CONNECTIONS} in all): close one"
            ),
        ))
    }
}

/// Serves one connection (TCP, or TLS over it) as `viewing` says: one request, then the
/// connection closes. A request naming a host the endpoint does not answer to is answered 421
/// without routing.
async fn connection<S>(stream: S, viewing: Viewing) -> Result<(), String>
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let io = TokioIo::new(WriteDeadline::new(stream, WRITE_TIMEOUT));
    let viewing = Arc::new(viewing);
    let service = hyper::service::service_fn(move |request: hyper::Request<_>| {
        // An absolute URI's authority is the host (RFC 9112 3.2.2); else the Host header.
        let host = match request.uri().authority() {
            Some(authority) => Some(authority.as_str().rsplit('@').next().unwrap_or_default()),
            None => request
                .headers()
                .get(header::HOST)
                .and_then(|h| h.to_str().ok()),
        };
        let allowed = host.is_some_and(|host| viewing.hosts.allows(host));
        let full = allowed
            .then(|| viewing.identify(request.headers()))
            .flatten();
        let routes = viewing.routes.clone();
        async move {
            if !allowed {
                return Ok(misdirected());
            }
            if let Some(full) = full {
                return Ok(full);
            }
            routes.oneshot(request.map(axum::body::Body::new)).await
        }
    });
    http1::Builder::new()
        .timer(TokioTimer::new())
        .header_read_timeout(REQUEST_TIMEOUT)
        .max_buf_size(MAX_REQUEST_BYTES)
        .keep_alive(false)
        .serve_connection(io, service)
        .await
        .map_err(|e| e.to_string())
}

/// The answer to a request naming a host the endpoint does not answer to: 421, never cached.
fn misdirected() -> Response {
    let mut response = error(
        StatusCode::MISDIRECTED_REQUEST,
        "this endpoint does not answer to the host this request names (a DNS name rebound to \
         it?): reach it by its IP address, by localhost, by a name of its TLS certificate, or \
         by a name the server was given with --http-allowed-host",
    );
    let headers = response.headers_mut();
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    headers.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    response
}
