//! The server's HTTP/1.1 endpoint (`--http-port`, alias `--metrics-port`): a small hand-written
//! responder on tokio, one request per connection, that serves
//!
//! - `/` — the sessions page, and `/watch/{session_id}?env=K` — one environment drawn live
//!   (static files compiled into the binary, [`assets`]; an unknown session is a readable 404);
//! - `/api/sessions`, `/api/watch/{id}?env=K` — their data as JSON, and the same under `/events`
//!   as server-sent events ([`feeds`]);
//! - `/metrics` — the Prometheus counters.
//!
//! The pages themselves hold no data and need no token; the feeds and `/metrics` ask for one of
//! the server's tokens when it has any ([`access`]), as `Authorization: Bearer <token>`.
//!
//! - [`access`]: tokens, and which sessions a viewer may see.
//! - [`feeds`]: the JSON of the sessions and of a watched environment, and their event streams.
//! - [`assets`]: the pages, scripts and style, and the 404 page.

pub mod access;
pub mod assets;
pub mod feeds;

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;

use crate::metrics::Metrics;
use crate::session::Store;
use crate::shutdown::Shutdown;

pub use access::{Access, Refused, Viewer};

/// Largest HTTP request head read; anything longer is answered 431 and closed.
const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// How long a client may take to send its request before the connection is dropped.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// Longest one write to a client may block (its socket buffer full): a viewer that does not
/// read for this long is dropped rather than waited for.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(2);
/// Most connections served at once, event streams included; more are answered 503. Each
/// viewer costs a task, a socket and one frame in flight; the sockets come out of the
/// descriptors [`crate::connections::fd_limit`] keeps beside the gRPC connections, so there are few.
pub const MAX_CONNECTIONS: usize = 32;

/// What the endpoint serves from. Shared by every connection.
#[derive(Debug)]
pub struct Site {
    /// The sessions.
    pub store: Store,
    /// The counters, for `/metrics` and the server totals.
    pub metrics: Arc<Metrics>,
    /// The tokens.
    pub access: Access,
    /// Connections being served, at most [`MAX_CONNECTIONS`].
    connections: Arc<Semaphore>,
    /// When the endpoint started (the first rates are measured from it).
    pub started: Instant,
}

impl Site {
    /// A site over `store`, asking for `access`'s tokens.
    pub fn new(store: Store, metrics: Arc<Metrics>, access: Access) -> Site {
        Site {
            store,
            metrics,
            access,
            connections: Arc::new(Semaphore::new(MAX_CONNECTIONS)),
            started: Instant::now(),
        }
    }
}

/// Serves `listener` until `shutdown` fires; event streams end then too.
pub async fn serve(listener: TcpListener, site: Arc<Site>, mut shutdown: Shutdown) {
    loop {
        tokio::select! {
            () = shutdown.wait() => return,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    let site = Arc::clone(&site);
                    let stopping = shutdown.clone();
                    tokio::spawn(async move {
                        if let Err(e) = connection(stream, &site, stopping).await {
                            tracing::debug!("http request failed: {e}");
                        }
                    });
                }
                Err(e) => {
                    // Out of file descriptors and the like: wait instead of spinning.
                    tracing::warn!("http listener: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            },
        }
    }
}

/// The request method, as far as the endpoint cares.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// GET.
    Get,
    /// HEAD: the same headers as GET, no body.
    Head,
    /// Anything else: 405.
    Other,
}

/// One parsed request head.
#[derive(Debug, Clone)]
pub struct Request {
    /// Its method.
    pub method: Method,
    /// The path, without the query.
    pub path: String,
    /// The query, without the `?`.
    pub query: String,
    /// The `Authorization` header's value.
    pub authorization: Option<Vec<u8>>,
}

impl Request {
    /// Parses a request head; `None` when it is not HTTP.
    pub fn parse(head: &[u8]) -> Option<Request> {
        let mut lines = head.split(|&b| b == b'\n').map(|l| l.trim_ascii_end());
        let first = std::str::from_utf8(lines.next()?).ok()?;
        let mut parts = first.split(' ');
        let method = match parts.next()? {
            "GET" => Method::Get,
            "HEAD" => Method::Head,
            _ => Method::Other,
        };
        let target = parts.next()?;
        if !parts.next()?.starts_with("HTTP/1.") || !target.starts_with('/') {
            return None;
        }
        let (path, query) = target.split_once('?').unwrap_or((target, ""));
        let authorization = lines.find_map(|line| {
            let colon = line.iter().position(|&b| b == b':')?;
            let (name, value) = line.split_at(colon);
            name.eq_ignore_ascii_case(b"authorization")
                .then(|| value[1..].trim_ascii().to_vec())
        });
        Some(Request {
            method,
            path: path.to_owned(),
            query: query.to_owned(),
            authorization,
        })
    }

    /// The value of query parameter `name`, if given.
    pub fn param(&self, name: &str) -> Option<&str> {
        self.query
            .split('&')
            .filter_map(|pair| pair.split_once('=').or(Some((pair, ""))))
            .find_map(|(k, v)| (k == name).then_some(v))
    }
}

/// A whole response.
#[derive(Debug, Clone)]
pub struct Response {
    /// Status code.
    pub status: u16,
    /// Content type.
    pub content_type: &'static str,
    /// The body.
    pub body: Vec<u8>,
    /// Header lines to add, each ending in `\r\n`.
    pub headers: String,
}

impl Response {
    /// A response of `status` with `body` of `content_type`.
    pub fn new(status: u16, content_type: &'static str, body: impl Into<Vec<u8>>) -> Response {
        Response {
            status,
            content_type,
            body: body.into(),
            headers: String::new(),
        }
    }

    /// A JSON response.
    pub fn json(status: u16, body: String) -> Response {
        Response::new(status, "application/json", body)
    }

    /// A JSON `{"error": message}` response.
    pub fn error(status: u16, message: &str) -> Response {
        let body = serde_json::json!({ "error": message }).to_string();
        Response::json(status, body)
    }

    /// The refusal of a request without a valid token.
    pub fn refused(why: Refused) -> Response {
        let mut r = Response::error(401, &why.to_string());
        r.headers.push_str("WWW-Authenticate: Bearer\r\n");
        r
    }

    /// The head and (unless `head_only`) the body, as written to the socket.
    pub fn encode(&self, head_only: bool) -> Vec<u8> {
        let mut out = head_lines(self.status, self.content_type, Some(self.body.len()));
        out.extend_from_slice(self.headers.as_bytes());
        out.extend_from_slice(b"\r\n");
        if !head_only {
            out.extend_from_slice(&self.body);
        }
        out
    }
}

/// The reason phrase of the status codes the endpoint uses.
fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        401 => "Unauthorized",
        404 => "Not Found",
        405 => "Method Not Allowed",
        431 => "Request Header Fields Too Large",
        503 => "Service Unavailable",
        _ => "Internal Server Error",
    }
}

/// A response head up to its own header lines: every response closes its connection, none is
/// cached (the data is live and the URLs hold capabilities), and none is sent as a referrer.
fn head_lines(status: u16, content_type: &str, length: Option<usize>) -> Vec<u8> {
    let mut out = format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: {content_type}\r\nCache-Control: no-store\r\n\
         X-Content-Type-Options: nosniff\r\nReferrer-Policy: no-referrer\r\n\
         Content-Security-Policy: default-src 'self'; img-src 'self' data:\r\n\
         Connection: close\r\n",
        reason(status)
    );
    if let Some(n) = length {
        out.push_str(&format!("Content-Length: {n}\r\n"));
    }
    out.into_bytes()
}

/// Writes `bytes`, or fails if the client has not taken them within [`WRITE_TIMEOUT`].
pub async fn send(stream: &mut TcpStream, bytes: &[u8]) -> std::io::Result<()> {
    match tokio::time::timeout(WRITE_TIMEOUT, stream.write_all(bytes)).await {
        Ok(result) => result,
        Err(_) => Err(std::io::Error::new(
            std::io::ErrorKind::TimedOut,
            "the client did not read",
        )),
    }
}

/// Reads a request head (up to the blank line) within [`REQUEST_TIMEOUT`].
async fn read_head(stream: &mut TcpStream) -> std::io::Result<Vec<u8>> {
    let mut head = Vec::with_capacity(512);
    let mut buf = [0u8; 1024];
    let read = async {
        loop {
            let n = stream.read(&mut buf).await?;
            if n == 0 {
                break;
            }
            head.extend_from_slice(&buf[..n]);
            if head.windows(4).any(|w| w == b"\r\n\r\n") || head.len() > MAX_REQUEST_BYTES {
                break;
            }
        }
        Ok::<_, std::io::Error>(())
    };
    tokio::time::timeout(REQUEST_TIMEOUT, read)
        .await
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "request head"))??;
    Ok(head)
}

/// Serves one connection: one request, one response or event stream.
async fn connection(mut stream: TcpStream, site: &Site, shutdown: Shutdown) -> std::io::Result<()> {
    let Ok(_permit) = Arc::clone(&site.connections).try_acquire_owned() else {
        let busy = Response::error(
            503,
            &format!("this endpoint serves its maximum of {MAX_CONNECTIONS} connections"),
        );
        send(&mut stream, &busy.encode(false)).await?;
        return stream.shutdown().await;
    };
    let head = read_head(&mut stream).await?;
    let request = match Request::parse(&head) {
        _ if head.len() > MAX_REQUEST_BYTES => Err(Response::error(431, "request head too large")),
        None => Err(Response::error(400, "not an HTTP/1.x request")),
        Some(r) if r.method == Method::Other => {
            let mut refused = Response::error(405, "only GET and HEAD are served");
            refused.headers.push_str("Allow: GET, HEAD\r\n");
            Err(refused)
        }
        Some(r) => Ok(r),
    };
    let bytes = match request {
        Err(response) => response.encode(false),
        Ok(request) => match route(site, &request) {
            Routed::Whole(response) => response.encode(request.method == Method::Head),
            Routed::Events(feed) => {
                let mut out = head_lines(200, "text/event-stream", None);
                out.extend_from_slice(b"\r\n");
                send(&mut stream, &out).await?;
                if request.method == Method::Get {
                    feed.run(&mut stream, site, shutdown).await?;
                }
                return stream.shutdown().await;
            }
        },
    };
    send(&mut stream, &bytes).await?;
    stream.shutdown().await
}

/// What a request gets.
pub enum Routed {
    /// One response.
    Whole(Response),
    /// An event stream.
    Events(feeds::Feed),
}

/// Answers `request`.
pub fn route(site: &Site, request: &Request) -> Routed {
    let path = request.path.as_str();
    let segments: Vec<&str> = path.trim_start_matches('/').split('/').collect();
    let viewer = || {
        site.access
            .viewer(request.authorization.as_deref())
            .map_err(Response::refused)
    };
    let whole = Routed::Whole;
    match segments.as_slice() {
        [""] | ["index.html"] => whole(assets::page(assets::SESSIONS_PAGE)),
        ["watch", id] => whole(if site.store.exists(id) {
            assets::page(assets::WATCH_PAGE)
        } else {
            assets::not_found(id)
        }),
        ["static", name] => whole(assets::file(name)),
        ["metrics"] => whole(match viewer() {
            Ok(_) => Response::new(
                200,
                "text/plain; version=0.0.4; charset=utf-8",
                site.metrics.render(),
            ),
            Err(refused) => refused,
        }),
        ["api", "sessions"] => whole(match viewer() {
            Ok(v) => Response::json(200, feeds::Sessions::new(v).snapshot(site)),
            Err(refused) => refused,
        }),
        ["api", "sessions", "events"] => match viewer() {
            Ok(v) => Routed::Events(feeds::Feed::Sessions(feeds::Sessions::new(v))),
            Err(refused) => whole(refused),
        },
        ["api", "watch", id] | ["api", "watch", id, "events"] => {
            let viewer = match viewer() {
                Ok(v) => v,
                Err(refused) => return whole(refused),
            };
            match feeds::Watching::attach(site, &viewer, id, request.param("env")) {
                Ok(watching) if segments.len() == 4 => {
                    Routed::Events(feeds::Feed::Watch(Box::new(watching)))
                }
                Ok(watching) => whole(Response::json(200, watching.snapshot())),
                Err(response) => whole(response),
            }
        }
        _ => whole(Response::new(
            404,
            "text/html; charset=utf-8",
            assets::not_found_page("Nothing here", "This address is not a page of this server."),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_heads_parse() {
        let r = Request::parse(
            b"GET /api/watch/abc?env=3&x HTTP/1.1\r\nHost: h\r\nauthorization:  Bearer t \r\n\r\n",
        )
        .unwrap();
        assert_eq!(r.method, Method::Get);
        assert_eq!(r.path, "/api/watch/abc");
        assert_eq!(r.param("env"), Some("3"));
        assert_eq!(r.param("x"), Some(""));
        assert_eq!(r.param("y"), None);
        assert_eq!(r.authorization.as_deref(), Some(&b"Bearer t"[..]));
        assert_eq!(
            Request::parse(b"POST / HTTP/1.1\r\n\r\n").unwrap().method,
            Method::Other
        );
        assert!(Request::parse(b"hello\r\n\r\n").is_none());
        assert!(Request::parse(b"GET x HTTP/1.1\r\n\r\n").is_none());
    }
}
