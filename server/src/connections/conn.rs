//! One accepted connection: the socket wrapped with its preface and idle timers, closed when
//! the accept loop sheds it, and counted among the open connections while it lives.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::time::{Instant, Sleep};

use super::ConnInfo;
use super::table::Tracked;
use crate::metrics::Metrics;

/// Length of the HTTP/2 connection preface, `PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n`.
pub(super) const PREFACE_BYTES: usize = 24;

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
            self.metrics.over_limit_connections.inner()
        } else {
            self.metrics.open_connections.inner()
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

impl Conn {
    /// Wraps `io`, which must send its preface (and then traffic) before `deadline`; after the
    /// preface, each read moves the deadline `idle_after` ahead (`None`: never, for a connection
    /// over the limit). `tracked`: its place in the table (`None` over the limit).
    pub(super) fn new(
        io: TcpStream,
        info: ConnInfo,
        tracked: Option<Tracked>,
        metrics: &Arc<Metrics>,
        deadline: Duration,
        idle_after: Option<Duration>,
    ) -> Conn {
        let over_limit = tracked.is_none();
        Conn {
            io,
            idle: Box::pin(tokio::time::sleep(deadline)),
            idle_after,
            preface_left: PREFACE_BYTES,
            tracked,
            info,
            counted: Counted::new(metrics, over_limit),
            timed_out: false,
        }
    }
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
                        counter.inc();
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
