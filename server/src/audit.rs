//! What the operator reads about refused callers: every failed authentication is counted
//! (`dinerdash_auth_failures_total`) and logged with its peer and method, at most
//! [`LINES_PER_WINDOW`] lines every [`LOG_WINDOW`] (the next line says how many were left out),
//! so that a client guessing tokens can neither hide nor flood the log. The method comes from
//! [`MethodLayer`], which tags each request with its path before the request gate sees it.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tonic::codegen::http;

use crate::metrics::Metrics;

/// How long a window of audit lines lasts.
pub const LOG_WINDOW: Duration = Duration::from_secs(10);
/// Most authentication failures logged in one [`LOG_WINDOW`]; the rest are only counted.
pub const LINES_PER_WINDOW: u32 = 5;

/// Why a request's token was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AuthFailure {
    /// No `authorization` metadata.
    Missing,
    /// A token that is none of the server's.
    Invalid,
}

impl AuthFailure {
    /// What the caller is told (`UNAUTHENTICATED`).
    pub fn message(self) -> &'static str {
        match self {
            AuthFailure::Missing => {
                "missing authorization metadata: send `authorization: Bearer <token>`"
            }
            AuthFailure::Invalid => "invalid auth token",
        }
    }

    /// How the log line names it.
    fn reason(self) -> &'static str {
        match self {
            AuthFailure::Missing => "no token",
            AuthFailure::Invalid => "unknown token",
        }
    }
}

/// The lines logged in the current window.
#[derive(Debug)]
struct Window {
    /// When it began.
    began: Instant,
    /// Lines logged in it.
    logged: u32,
    /// Failures left out of the log since the last line.
    left_out: u64,
}

/// Counts and logs failed authentications.
#[derive(Debug)]
pub struct Audit {
    /// Holds `auth_failures`.
    metrics: Arc<Metrics>,
    /// The rate limit of the log lines.
    window: Mutex<Window>,
}

impl Audit {
    /// An audit counting in `metrics`.
    pub fn new(metrics: Arc<Metrics>) -> Audit {
        Audit {
            metrics,
            window: Mutex::new(Window {
                began: Instant::now(),
                logged: 0,
                left_out: 0,
            }),
        }
    }

    /// A request from `peer` calling `method` was refused for `failure`: counted, and logged
    /// unless this window has logged its lines already.
    pub fn auth_failed(&self, peer: Option<SocketAddr>, method: &str, failure: AuthFailure) {
        self.metrics.auth_failures.inc();
        let left_out = {
            let mut window = self.window.lock().unwrap_or_else(PoisonError::into_inner);
            let now = Instant::now();
            if now.duration_since(window.began) >= LOG_WINDOW {
                window.began = now;
                window.logged = 0;
            }
            if window.logged >= LINES_PER_WINDOW {
                window.left_out += 1;
                return;
            }
            window.logged += 1;
            std::mem::take(&mut window.left_out)
        };
        let peer = peer.map_or_else(|| "unknown".to_owned(), |p| p.to_string());
        tracing::warn!(
            peer = %peer,
            method = %method,
            reason = failure.reason(),
            left_out,
            "authentication failed"
        );
    }
}

/// The path of the gRPC method a request calls (`/dinerdash.v1.DinerDash/Step`), a request
/// extension [`MethodLayer`] adds.
#[derive(Debug, Clone)]
pub struct CalledMethod(http::uri::PathAndQuery);

/// The method a request calls, as [`MethodLayer`] tagged it; `"unknown"` without the tag.
pub fn called_method(extensions: &http::Extensions) -> &str {
    extensions
        .get::<CalledMethod>()
        .map_or("unknown", |m| m.0.path())
}

/// Tags each request with the method it calls ([`CalledMethod`]), which a tonic interceptor
/// cannot see otherwise: `Server::builder().layer(MethodLayer)`.
#[derive(Debug, Clone, Copy, Default)]
pub struct MethodLayer;

impl<S> tower::Layer<S> for MethodLayer {
    type Service = Method<S>;

    fn layer(&self, inner: S) -> Method<S> {
        Method { inner }
    }
}

/// The service [`MethodLayer`] makes.
#[derive(Debug, Clone)]
pub struct Method<S> {
    /// The services behind it.
    inner: S,
}

impl<S, ReqBody> tower::Service<http::Request<ReqBody>> for Method<S>
where
    S: tower::Service<http::Request<ReqBody>>,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = S::Future;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: http::Request<ReqBody>) -> Self::Future {
        if let Some(path) = request.uri().path_and_query().cloned() {
            request.extensions_mut().insert(CalledMethod(path));
        }
        self.inner.call(request)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_failure_is_counted_and_few_are_logged() {
        let metrics = Arc::new(Metrics::default());
        let audit = Audit::new(Arc::clone(&metrics));
        for _ in 0..51 {
            audit.auth_failed(None, "/dinerdash.v1.DinerDash/Step", AuthFailure::Invalid);
        }
        assert_eq!(metrics.auth_failures.get(), 51);
        let window = audit.window.lock().unwrap();
        assert!(window.logged <= LINES_PER_WINDOW);
        assert_eq!(u64::from(window.logged) + window.left_out, 51);
    }
}
