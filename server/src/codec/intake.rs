//! Requests being received, decoded and converted: their bytes are counted from the moment the
//! 5-byte gRPC header of a message announces its length until the call is done with it, against
//! a bound of their own beside `--max-memory` ([`Budget::max_intake_bytes`]: a quarter of it, at
//! least 64 MiB). So the server's memory stays under `--max-memory` plus that bound plus its
//! runtime, whatever clients send.
//!
//! - A message longer than its method could ever need ([`MethodBounds::max_bytes`]: 16 KiB for
//!   the requests that only name a session or describe one, about 256 KiB for a Step, 108 KiB for
//!   a Rollout) is refused `INVALID_ARGUMENT` at its header, before tonic buffers it.
//! - A message over [`SMALL_MESSAGE_BYTES`] is charged [`MethodBounds::expansion`] times its
//!   announced length (tonic's buffer, prost's structs, the converted arguments) before its first
//!   byte is buffered; when the bound cannot hold that, the call is refused
//!   `RESOURCE_EXHAUSTED` (the message names `--max-memory`) and tonic never buffers it. The
//!   charge is given back when the call's handler has answered (a unary call) or when the next
//!   message of the stream starts (StepStream).
//! - A charged message must arrive whole within [`INTAKE_TIMEOUT`], so that a client cannot hold
//!   the budget by sending a large message slowly; any other message within
//!   [`SMALL_INTAKE_TIMEOUT`], so that no partly sent message is held for ever.
//! - Calls outside the DinerDash service (health checks, reflection, unknown paths) take
//!   messages of [`PROBE_MESSAGE_BYTES`] at most, and their first one must start within
//!   [`SMALL_INTAKE_TIMEOUT`] of the call: they are served before the token is checked.
//!
//! Smaller messages (every Step of up to 4096 environments, CreateSession, most Resets) are not
//! charged here: each authenticated call is charged a fixed [`CALL_BYTES`] for the whole call
//! instead (`connections::calls`), which covers one of them.

use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll, ready};
use std::time::Duration;

use http_body::{Frame, SizeHint};
use tonic::Status;
use tonic::body::Body;
use tonic::codegen::{Bytes, http};

use super::MAX_ENVS;
use crate::budget::{Budget, IntakeCharge};
use crate::rollout::MAX_ROLLOUT_EPISODES;

/// Messages up to this size are not charged: a Step of 4096 environments, a CreateSession, a
/// Reset with seeds for 2048 environments.
pub const SMALL_MESSAGE_BYTES: u64 = 16 << 10;
/// Longest a charged message may take to arrive whole.
pub const INTAKE_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a message up to [`SMALL_MESSAGE_BYTES`] may take to arrive whole once its header
/// has: 16 KiB in 10 s is 1.6 KB/s.
pub const SMALL_INTAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// The longest message of a call outside the DinerDash service: a health check names a
/// service, a reflection request a symbol.
pub const PROBE_MESSAGE_BYTES: u64 = 1024;
/// What one open authenticated call may cost the server besides its charged messages: an
/// uncharged message of up to [`SMALL_MESSAGE_BYTES`] in tonic's buffer (which may have grown
/// to twice that), the HTTP/2 stream and the call's task (docs/security.md).
pub const CALL_BYTES: u64 = 48 << 10;
/// Length of the gRPC message header: a compression flag, then the length (big-endian u32).
const HEADER: usize = 5;
/// Room for a request's fields besides its large one: a session ID, tags, lengths, a config.
const FIELDS_BYTES: u64 = 1024;

/// What one method's request messages may be and cost.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MethodBounds {
    /// How many times its size a message may cost while it is received, decoded and converted.
    pub expansion: u64,
    /// The longest message the method takes (`MAX_MESSAGE_BYTES` caps every one).
    pub max_bytes: u64,
}

/// The bounds of the method at `path`. The expansion is tonic's buffer (1) plus what prost and
/// the conversion make of a message once [`crate::codec`] has bounded its repeated fields. A
/// Reset's or a Rollout's packed seeds are the worst: a one-byte varint becomes 8 bytes in a
/// vector that may have doubled (16); an arrival list of one group (8 bytes on the wire) a
/// 24-byte vector and an 8-byte group, converted once more. A snapshot (Restore) is copied once
/// and its environments decoded, at most a few times their bytes. Every other request is its
/// bytes and a copy of them.
pub fn bounds(path: &str) -> MethodBounds {
    let (expansion, max_bytes) = match path.strip_prefix("/dinerdash.v1.DinerDash/") {
        Some("Reset") => (17, u64::MAX),
        // Unpacked seeds are 11 bytes at most each.
        Some("Rollout") => (17, 11 * u64::from(MAX_ROLLOUT_EPISODES) + FIELDS_BYTES),
        Some("Restore") => (10, u64::MAX),
        Some("Step" | "StepStream") => (2, 4 * MAX_ENVS as u64 + FIELDS_BYTES),
        // CreateSession, CloseSession, Fork, Snapshot, Render, ServerInfo: a few dozen bytes.
        Some(_) => (2, SMALL_MESSAGE_BYTES),
        // Health, reflection and unknown paths.
        None => (2, PROBE_MESSAGE_BYTES),
    };
    MethodBounds {
        expansion,
        max_bytes,
    }
}

/// The tower layer that charges every request's messages ([`IntakeBody`]); every service is
/// behind it: `Server::builder().layer(IntakeLayer::new(budget))`.
#[derive(Debug, Clone)]
pub struct IntakeLayer {
    /// Where the messages are charged.
    budget: Arc<Budget>,
}

impl IntakeLayer {
    /// Charges against `budget`.
    pub fn new(budget: Arc<Budget>) -> IntakeLayer {
        IntakeLayer { budget }
    }
}

impl<S> tower::Layer<S> for IntakeLayer {
    type Service = Intake<S>;

    fn layer(&self, inner: S) -> Intake<S> {
        Intake {
            inner,
            budget: Arc::clone(&self.budget),
        }
    }
}

/// The service [`IntakeLayer`] makes.
#[derive(Debug, Clone)]
pub struct Intake<S> {
    /// The services behind it.
    inner: S,
    /// Where the messages are charged.
    budget: Arc<Budget>,
}

/// The charge of a call's current message, shared by its request body (which replaces it when
/// a message starts) and its response future (which keeps it until the handler has answered).
type Held = Arc<Mutex<Option<IntakeCharge>>>;

impl<S, ResBody> tower::Service<http::Request<Body>> for Intake<S>
where
    S: tower::Service<http::Request<Body>, Response = http::Response<ResBody>>,
    S::Future: Unpin,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = IntakeFuture<S::Future>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<Body>) -> Self::Future {
        let held = Held::default();
        let path = request.uri().path();
        let (limits, method) = (bounds(path), path.rsplit('/').next().unwrap_or_default());
        let method = method.to_owned();
        let (budget, charge) = (Arc::clone(&self.budget), Arc::clone(&held));
        // A call outside the DinerDash service (served before the token is checked) must send
        // its message soon, not hold its stream open for ever.
        let probe = limits.max_bytes == PROBE_MESSAGE_BYTES;
        let request = request.map(|inner| {
            let mut body = IntakeBody::new(inner, budget, limits, method, charge);
            if probe {
                body.deadline = Some(Box::pin(tokio::time::sleep(SMALL_INTAKE_TIMEOUT)));
            }
            Body::new(body)
        });
        IntakeFuture {
            inner: self.inner.call(request),
            held: Some(held),
        }
    }
}

/// The response future of [`Intake`]: keeps the request's charge until the handler answers.
#[derive(Debug)]
pub struct IntakeFuture<F> {
    /// The inner service's future.
    inner: F,
    /// The request's charge, until the response is ready.
    held: Option<Held>,
}

impl<F: Future + Unpin> Future for IntakeFuture<F> {
    type Output = F::Output;

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<F::Output> {
        let output = ready!(Pin::new(&mut self.inner).poll(cx));
        self.held = None;
        Poll::Ready(output)
    }
}

/// A request body that reads the gRPC header of each message as it passes and charges the
/// message before tonic buffers it.
#[derive(Debug)]
pub struct IntakeBody {
    /// The body.
    inner: Body,
    /// Where the messages are charged.
    budget: Arc<Budget>,
    /// What the call's method takes.
    limits: MethodBounds,
    /// The call's method, for messages.
    method: String,
    /// The charge of the current message.
    held: Held,
    /// The header being read.
    header: [u8; HEADER],
    /// Bytes of `header` read so far.
    have: usize,
    /// Bytes of the current message still to come.
    left: u64,
    /// Length of the current message.
    length: u64,
    /// When a charged message must have arrived whole.
    deadline: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl IntakeBody {
    /// `inner`, a request to `method` whose messages are bounded by `limits`, charged against
    /// `budget` and held in `held`.
    fn new(
        inner: Body,
        budget: Arc<Budget>,
        limits: MethodBounds,
        method: String,
        held: Held,
    ) -> Self {
        IntakeBody {
            inner,
            budget,
            limits,
            method,
            held,
            header: [0; HEADER],
            have: 0,
            left: 0,
            length: 0,
            deadline: None,
        }
    }

    /// Reads `data` through the headers and payloads it holds, charging each message that
    /// starts in it.
    fn measure(&mut self, mut data: &[u8]) -> Result<(), Status> {
        while !data.is_empty() {
            if self.left > 0 {
                let n = self.left.min(data.len() as u64);
                self.left -= n;
                data = &data[n as usize..];
                if self.left == 0 {
                    self.deadline = None;
                }
                continue;
            }
            let n = (HEADER - self.have).min(data.len());
            self.header[self.have..self.have + n].copy_from_slice(&data[..n]);
            self.have += n;
            data = &data[n..];
            if self.have == HEADER {
                self.have = 0;
                let [_, a, b, c, d] = self.header;
                self.length = u64::from(u32::from_be_bytes([a, b, c, d]));
                self.left = self.length;
                self.admit()?;
            }
        }
        Ok(())
    }

    /// Charges the message whose header was just read (and gives back the previous one's).
    fn admit(&mut self) -> Result<(), Status> {
        let mut held = self.held.lock().unwrap_or_else(PoisonError::into_inner);
        *held = None;
        self.deadline = None;
        if self.length > self.limits.max_bytes {
            return Err(Status::invalid_argument(format!(
                "a {} message may be at most {} bytes, got {}",
                self.method, self.limits.max_bytes, self.length
            )));
        }
        if self.length <= SMALL_MESSAGE_BYTES {
            if self.left > 0 {
                self.deadline = Some(Box::pin(tokio::time::sleep(SMALL_INTAKE_TIMEOUT)));
            }
            return Ok(());
        }
        let factor = self.limits.expansion;
        let cost = self.length.saturating_mul(factor);
        let charge = self.budget.charge_intake(cost).map_err(|e| {
            Status::resource_exhausted(format!(
                "a {} message of {} bytes is charged {factor} times its size while it is \
                 received and decoded: {e}",
                self.method, self.length
            ))
        })?;
        *held = Some(charge);
        if self.left > 0 {
            self.deadline = Some(Box::pin(tokio::time::sleep(INTAKE_TIMEOUT)));
        }
        Ok(())
    }

    /// The refusal of a message that took too long to arrive.
    fn too_slow(&self) -> Status {
        let within = if self.length > SMALL_MESSAGE_BYTES {
            INTAKE_TIMEOUT
        } else {
            SMALL_INTAKE_TIMEOUT
        };
        Status::resource_exhausted(format!(
            "a {} message of {} bytes did not arrive whole within {} s: a message up to {} bytes \
             must arrive within {} s of its header, a longer one (which holds its share of \
             --max-memory while it arrives) within {} s",
            self.method,
            self.length,
            within.as_secs(),
            SMALL_MESSAGE_BYTES,
            SMALL_INTAKE_TIMEOUT.as_secs(),
            INTAKE_TIMEOUT.as_secs(),
        ))
    }
}

impl http_body::Body for IntakeBody {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    if let Err(status) = this.measure(data) {
                        return Poll::Ready(Some(Err(status)));
                    }
                }
                if this.deadline.as_ref().is_some_and(|d| d.is_elapsed()) {
                    return Poll::Ready(Some(Err(this.too_slow())));
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Pending => {
                let late = (this.deadline.as_mut()).is_some_and(|d| d.as_mut().poll(cx).is_ready());
                if late {
                    return Poll::Ready(Some(Err(this.too_slow())));
                }
                Poll::Pending
            }
            other => other,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::Metrics;

    fn body(budget: &Arc<Budget>, path: &str) -> IntakeBody {
        let limits = bounds(path);
        IntakeBody::new(
            Body::empty(),
            Arc::clone(budget),
            limits,
            "Reset".into(),
            Held::default(),
        )
    }

    fn header(len: u32) -> Vec<u8> {
        let mut h = vec![0];
        h.extend_from_slice(&len.to_be_bytes());
        h
    }

    #[tokio::test]
    async fn each_large_message_is_charged_from_its_header_until_the_next() {
        // The bound is its floor, 64 MiB.
        let budget = Arc::new(Budget::new(1 << 20, 10, Arc::new(Metrics::default())));
        let mut b = body(&budget, "/dinerdash.v1.DinerDash/Reset");
        // A small message, split across frames: not charged, but given a deadline while it is
        // partly sent.
        b.measure(&header(100)[..3]).unwrap();
        assert!(b.deadline.is_none());
        b.measure(&header(100)[3..]).unwrap();
        assert!(b.deadline.is_some());
        b.measure(&[0; 100]).unwrap();
        assert!(b.deadline.is_none());
        assert_eq!(budget.intake_bytes(), 0);
        // A large one: 17 times its length, from its header on.
        b.measure(&header(20_000)).unwrap();
        assert_eq!(budget.intake_bytes(), 17 * 20_000);
        assert_eq!(budget.used_bytes(), 0);
        assert!(b.deadline.is_some());
        b.measure(&[0; 20_000]).unwrap();
        assert!(b.deadline.is_none());
        // The next message gives the previous one back; one the budget cannot hold is refused.
        let e = b.measure(&header(4 << 20)).unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
        assert!(e.message().contains("--max-memory"), "{}", e.message());
        assert_eq!(budget.intake_bytes(), 0);
        b.measure(&header(20_000)).unwrap();
        drop(b);
        assert_eq!(budget.intake_bytes(), 0);
        // A message longer than its method takes is refused at its header.
        let mut c = body(&budget, "/dinerdash.v1.DinerDash/CreateSession");
        let e = c.measure(&header(1 << 20)).unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert_eq!(bounds("/dinerdash.v1.DinerDash/Step").expansion, 2);
        // Outside the DinerDash service (served before the token is checked): 1 KiB.
        let mut h = body(&budget, "/grpc.health.v1.Health/Check");
        let e = h.measure(&header(4 << 20)).unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert_eq!(budget.intake_bytes(), 0);
        h.measure(&header(1024)).unwrap();
        assert_eq!(bounds("/no.Such/Path").max_bytes, PROBE_MESSAGE_BYTES);
    }
}
