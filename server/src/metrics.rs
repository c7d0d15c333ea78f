//! Counters of what the server did, and a tiny HTTP responder that serves them in Prometheus'
//! text format on `--metrics-port` (any path; `GET /metrics` is what Prometheus asks for).
//!
//! Counters are plain atomics bumped on the hot path (relaxed: they are statistics, not
//! synchronisation); nothing here allocates per step.

use std::fmt::Write as _;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::shutdown::Shutdown;

/// Largest HTTP request head the responder reads; anything longer is answered and closed.
const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// How long a scraper may take to send its request before the connection is dropped.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);

/// gRPC status code names, indexed by code number, for the error counter's label.
const CODE_NAMES: [&str; 17] = [
    "OK",
    "CANCELLED",
    "UNKNOWN",
    "INVALID_ARGUMENT",
    "DEADLINE_EXCEEDED",
    "NOT_FOUND",
    "ALREADY_EXISTS",
    "PERMISSION_DENIED",
    "RESOURCE_EXHAUSTED",
    "FAILED_PRECONDITION",
    "ABORTED",
    "OUT_OF_RANGE",
    "UNIMPLEMENTED",
    "INTERNAL",
    "UNAVAILABLE",
    "DATA_LOSS",
    "UNAUTHENTICATED",
];

/// The server's counters. Shared by the session store, the service and the responder.
#[derive(Debug, Default)]
pub struct Metrics {
    /// Sessions created by CreateSession, Fork and Restore.
    pub sessions_created: AtomicU64,
    /// Sessions closed by CloseSession.
    pub sessions_closed: AtomicU64,
    /// Sessions evicted for being idle longer than the TTL.
    pub sessions_expired: AtomicU64,
    /// Live sessions right now: the one counter the session limit is checked against
    /// ([`crate::budget::Budget`] keeps it).
    pub live_sessions: AtomicU64,
    /// Bytes sessions and Rollout streams hold now, as the memory budget counts them.
    pub memory_used_bytes: AtomicU64,
    /// The memory budget, `--max-memory`.
    pub memory_budget_bytes: AtomicU64,
    /// Rollout streams running now.
    pub live_rollouts: AtomicU64,
    /// Connections open now.
    pub open_connections: AtomicU64,
    /// Connections accepted over the connection limit, open now (answered RESOURCE_EXHAUSTED).
    pub over_limit_connections: AtomicU64,
    /// Step RPCs that succeeded.
    pub step_calls: AtomicU64,
    /// Environment steps: a Step of N environments counts N.
    pub env_steps: AtomicU64,
    /// Environment resets, by Reset and by autoreset.
    pub env_resets: AtomicU64,
    /// Episodes recorded by Rollout.
    pub rollout_episodes: AtomicU64,
    /// RPCs that failed, by gRPC status code.
    pub rpc_errors: [AtomicU64; 17],
}

impl Metrics {
    /// Counts one failed RPC with gRPC status code `code` (0..=16; others count as UNKNOWN).
    pub fn count_error(&self, code: usize) {
        let code = if code < CODE_NAMES.len() { code } else { 2 };
        self.rpc_errors[code].fetch_add(1, Ordering::Relaxed);
    }

    /// The counters in Prometheus' text exposition format.
    pub fn render(&self) -> String {
        let mut out = String::with_capacity(2048);
        let counters: [(&str, &str, &AtomicU64); 7] = [
            (
                "dinerdash_sessions_created_total",
                "Sessions created by CreateSession, Fork and Restore.",
                &self.sessions_created,
            ),
            (
                "dinerdash_sessions_closed_total",
                "Sessions closed by CloseSession.",
                &self.sessions_closed,
            ),
            (
                "dinerdash_sessions_expired_total",
                "Sessions evicted after being idle longer than the TTL.",
                &self.sessions_expired,
            ),
            (
                "dinerdash_step_calls_total",
                "Step RPCs that succeeded.",
                &self.step_calls,
            ),
            (
                "dinerdash_env_steps_total",
                "Environment steps (a Step of N environments counts N).",
                &self.env_steps,
            ),
            (
                "dinerdash_env_resets_total",
                "Environment resets, by Reset and by autoreset.",
                &self.env_resets,
            ),
            (
                "dinerdash_rollout_episodes_total",
                "Episodes recorded by Rollout.",
                &self.rollout_episodes,
            ),
        ];
        for (name, help, value) in counters {
            let _ = writeln!(out, "# HELP {name} {help}");
            let _ = writeln!(out, "# TYPE {name} counter");
            let _ = writeln!(out, "{name} {}", value.load(Ordering::Relaxed));
        }
        let gauges: [(&str, &str, &AtomicU64); 5] = [
            (
                "dinerdash_live_sessions",
                "Sessions alive now.",
                &self.live_sessions,
            ),
            (
                "dinerdash_memory_used_bytes",
                "Bytes sessions and Rollout streams hold now, as the memory budget counts them.",
                &self.memory_used_bytes,
            ),
            (
                "dinerdash_memory_budget_bytes",
                "The memory budget (--max-memory).",
                &self.memory_budget_bytes,
            ),
            (
                "dinerdash_live_rollouts",
                "Rollout streams running now.",
                &self.live_rollouts,
            ),
            (
                "dinerdash_open_connections",
                "Client connections open now.",
                &self.open_connections,
            ),
        ];
        for (name, help, value) in gauges {
            let _ = writeln!(out, "# HELP {name} {help}");
            let _ = writeln!(out, "# TYPE {name} gauge");
            let _ = writeln!(out, "{name} {}", value.load(Ordering::Relaxed));
        }
        let _ = writeln!(
            out,
            "# HELP dinerdash_rpc_errors_total RPCs that failed, by gRPC status code."
        );
        let _ = writeln!(out, "# TYPE dinerdash_rpc_errors_total counter");
        for (name, value) in CODE_NAMES.iter().zip(&self.rpc_errors) {
            let value = value.load(Ordering::Relaxed);
            if value > 0 {
                let _ = writeln!(out, "dinerdash_rpc_errors_total{{code=\"{name}\"}} {value}");
            }
        }
        out
    }
}

/// Answers every HTTP request on `listener` with the metrics until `shutdown` fires. When
/// `tokens` holds any `Bearer <token>` value, a request must send one of them in its
/// `Authorization` header (Prometheus' `authorization` / `bearer_token` settings), or is
/// answered 401.
pub async fn serve(
    listener: TcpListener,
    metrics: Arc<Metrics>,
    tokens: Arc<[Box<[u8]>]>,
    mut shutdown: Shutdown,
) {
    loop {
        tokio::select! {
            () = shutdown.wait() => return,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    let metrics = Arc::clone(&metrics);
                    let tokens = Arc::clone(&tokens);
                    tokio::spawn(async move {
                        if let Err(e) = answer(stream, &metrics, &tokens).await {
                            tracing::debug!("metrics request failed: {e}");
                        }
                    });
                }
                Err(e) => {
                    // Out of file descriptors and the like: wait instead of spinning.
                    tracing::warn!("metrics listener: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            },
        }
    }
}

/// Reads one request head and writes one response, then closes the connection.
async fn answer(
    mut stream: TcpStream,
    metrics: &Metrics,
    tokens: &[Box<[u8]>],
) -> std::io::Result<()> {
    let mut head = Vec::with_capacity(512);
    let mut buf = [0u8; 1024];
    let read_head = async {
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
    tokio::time::timeout(REQUEST_TIMEOUT, read_head)
        .await
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "request head"))??;
    let line = head.split(|&b| b == b'\n').next().unwrap_or_default();
    let response = if !tokens.is_empty() && !authorized(&head, tokens) {
        "HTTP/1.1 401 Unauthorized\r\nWWW-Authenticate: Bearer\r\nContent-Length: 0\r\n\
         Connection: close\r\n\r\n"
            .to_owned()
    } else if line.starts_with(b"GET ") || line.starts_with(b"HEAD ") {
        let body = metrics.render();
        format!(
            "HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4; charset=utf-8\r\n\
             Content-Length: {}\r\nConnection: close\r\n\r\n{}",
            body.len(),
            if line.starts_with(b"HEAD ") {
                ""
            } else {
                &body
            }
        )
    } else {
        "HTTP/1.1 405 Method Not Allowed\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
            .to_owned()
    };
    stream.write_all(response.as_bytes()).await?;
    stream.shutdown().await
}

/// Whether the request head carries `Authorization: <one of tokens>` (`Bearer <token>`).
fn authorized(head: &[u8], tokens: &[Box<[u8]>]) -> bool {
    head.split(|&b| b == b'\n').any(|line| {
        let line = line.strip_suffix(b"\r").unwrap_or(line);
        let Some(colon) = line.iter().position(|&b| b == b':') else {
            return false;
        };
        let (name, value) = line.split_at(colon);
        name.eq_ignore_ascii_case(b"authorization") && {
            let value = value[1..].trim_ascii();
            // Every token compared, so that the time taken does not reveal which one matched.
            tokens
                .iter()
                .fold(false, |hit, t| hit | crate::service::same_bytes(value, t))
        }
    })
}
