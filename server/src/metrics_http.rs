//! A tiny HTTP responder that serves the [`Metrics`] in Prometheus' text format on
//! `--metrics-port` (any path; `GET /metrics` is what Prometheus asks for), asking for the same
//! bearer tokens as the RPCs when the server has any.

use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::auth::same_bytes;
use crate::metrics::Metrics;
use crate::shutdown::Shutdown;

/// Largest HTTP request head the responder reads; anything longer is answered and closed.
const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// How long a scraper may take to send its request before the connection is dropped.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);

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
                .fold(false, |hit, t| hit | same_bytes(value, t))
        }
    })
}
