//! What keeps a call counted while it runs: a guard ([`Call`], or the slots of
//! [`calls`](super::calls)) carried by the response future and then by the response body until
//! it ends or is dropped, streams included.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::task::{Context, Poll, ready};

use http_body::{Body, Frame, SizeHint};
use tonic::codegen::http;

use super::table::Activity;

/// A call in flight on a connection: counted until dropped.
#[derive(Debug)]
pub struct Call(Arc<Activity>);

impl Call {
    pub(super) fn new(activity: &Arc<Activity>) -> Call {
        activity.in_flight.fetch_add(1, Ordering::AcqRel);
        Call(Arc::clone(activity))
    }
}

impl Drop for Call {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A call's response future: hands the call's guard `G` to the response body.
#[derive(Debug)]
pub struct CallFuture<F, G = Call> {
    /// The inner service's future.
    pub(super) inner: F,
    /// The call, until the response is ready.
    pub(super) call: Option<G>,
}

impl<F, B, E, G: Unpin> Future for CallFuture<F, G>
where
    F: Future<Output = Result<http::Response<B>, E>> + Unpin,
{
    type Output = Result<http::Response<CallBody<B, G>>, E>;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let response = ready!(Pin::new(&mut self.inner).poll(cx));
        let call = self.call.take();
        Poll::Ready(response.map(|r| r.map(|body| CallBody { body, call })))
    }
}

/// A response body that keeps its call's guard `G` until it ends or is dropped.
#[derive(Debug)]
pub struct CallBody<B, G = Call> {
    /// The body.
    pub(super) body: B,
    /// The call, until the body ends.
    pub(super) call: Option<G>,
}

impl<B: Body + Unpin, G: Unpin> Body for CallBody<B, G> {
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
