//! StepStream's replies: a hand-written stream that steps each request exactly as the unary Step
//! does, reading the next request only once the previous reply has gone to the transport.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};

use tonic::{Status, Streaming};

use super::DinerDashService;
use crate::pb;
use crate::session::Owner;
use crate::shutdown::{self, Shutdown};

/// The reply of one StepStream request and the stream's state for the next; `None`: the client
/// closed its side.
type NextReply = Option<(Result<pb::Batch, Status>, Inbound)>;

/// The replies of one StepStream, computed one at a time as the transport asks for them: the
/// next request is read only once the previous reply has been handed on (see
/// its `Stream::poll_next`), so a client that does not read its replies holds at most one
/// reply beyond HTTP/2 flow control, and stops the server reading its requests.
pub struct StepReplies {
    /// Reads the next request and steps it; `None` once the stream has ended.
    next: Option<Pin<Box<dyn Future<Output = NextReply> + Send>>>,
    /// A reply was just yielded and not yet handed to the transport.
    handed: bool,
}

impl StepReplies {
    /// The replies to `requests`, each stepped by `service` for `owner` (the stream's identity,
    /// fixed when it opened); the stream ends with `UNAVAILABLE` once `stopping` fires.
    pub(super) fn new(
        service: DinerDashService,
        owner: Owner,
        requests: Streaming<pb::StepRequest>,
        stopping: Shutdown,
    ) -> StepReplies {
        let inbound = Inbound {
            service,
            owner,
            requests,
            stopping,
        };
        StepReplies {
            next: Some(Box::pin(inbound.next())),
            handed: false,
        }
    }
}

/// What a StepStream reads from.
struct Inbound {
    /// Steps each request as the unary Step does.
    service: DinerDashService,
    /// The identity the stream's token stands for: each request's session must be its own.
    owner: Owner,
    /// The client's requests.
    requests: Streaming<pb::StepRequest>,
    /// Fires when the server drains.
    stopping: Shutdown,
}

impl Inbound {
    /// Waits for the next request (or the server's shutdown) and steps it.
    async fn next(mut self) -> NextReply {
        let message = tokio::select! {
            // A draining server answers UNAVAILABLE, as it does new unary calls; a stream waiting
            // for a request ends at once rather than holding the drain until its deadline.
            biased;
            () = self.stopping.wait() => return Some((Err(shutdown::unavailable()), self)),
            message = self.requests.message() => message,
        };
        match message {
            Ok(Some(request)) => {
                let reply = self.service.step_one(&self.owner, request).await;
                Some((reply, self))
            }
            Ok(None) => None,
            // Undecodable or oversized (the codec's and transport's statuses, as for Step), or
            // the client reset the stream.
            Err(status) => Some((Err(status), self)),
        }
    }
}

impl tokio_stream::Stream for StepReplies {
    type Item = Result<pb::Batch, Status>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        // tonic's encoder polls again right after a reply, to pack more into one frame: answer
        // Pending once (waking ourselves), so that the reply goes to the transport before the
        // next request is read. Without this, a client pipelining requests without reading
        // would have up to the encoder's 32 KiB of replies computed ahead of flow control.
        if std::mem::take(&mut self.handed) {
            cx.waker().wake_by_ref();
            return Poll::Pending;
        }
        let Some(next) = self.next.as_mut() else {
            return Poll::Ready(None);
        };
        match next.as_mut().poll(cx) {
            Poll::Pending => Poll::Pending,
            Poll::Ready(None) => {
                self.next = None;
                Poll::Ready(None)
            }
            Poll::Ready(Some((reply, inbound))) => {
                // An error ends the stream, as it ends a unary call.
                self.next = match reply {
                    Ok(_) => Some(Box::pin(inbound.next())),
                    Err(_) => None,
                };
                self.handed = true;
                Poll::Ready(Some(reply))
            }
        }
    }
}
