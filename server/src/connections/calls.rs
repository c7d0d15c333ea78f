//! The calls the server lets be open at once, so that what an open call costs is bounded
//! whoever sends it, with a token or without:
//!
//! - Calls outside the DinerDash service (health checks, reflection, unknown paths) are served
//!   or reach the token check without a token: at most [`PROBE_CALLS`] of them are open at once
//!   in all and [`PROBE_CALLS_PER_PEER`] from one peer address, of which health Watches (calls
//!   that never end) [`WATCHES`] and [`WATCHES_PER_PEER`] ([`ProbeLayer`]); more are answered
//!   `RESOURCE_EXHAUSTED` at their headers. Their one message is 1 KiB at most and must arrive
//!   within 10 s of the call (`codec::intake`).
//! - Each DinerDash call that passed the token check ([`Admit`]) is charged
//!   [`CALL_BYTES`] against the intake bound for as long as it is open, and counted against its
//!   identity's `streams` quota: a tenant's or the shared token's `max_streams`, by default its
//!   fair part of the calls that bound holds and at most 1/[`IDENTITY_SHARE`] of them
//!   (`auth::TenantRules`); on a server without tokens, all calls together at most
//!   1/[`IDENTITY_SHARE`]. More are refused `RESOURCE_EXHAUSTED` before their message is read.
//! - Only these calls count as in flight for shedding, and the first one makes its connection
//!   its identity's (those that never made one are shed first), counted against the identity's
//!   `connections` quota (`max_connections`, by default its fair part of `--max-connections`)
//!   until it closes: a call that would pass it is refused `RESOURCE_EXHAUSTED`, and the
//!   connection stays nobody's.

use std::collections::HashMap;
use std::future::Future;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::task::{Context, Poll};

use tonic::Status;
use tonic::codegen::http;
use tonic::server::NamedService;

use super::conn_info_in;
use super::in_flight::{Call, CallBody, CallFuture};
use super::table::Activity;
use crate::budget::{Budget, Held, IntakeCharge, SharedShare, Tenant, intake_bound};
use crate::codec::intake::CALL_BYTES;
use crate::metrics::{Metrics, Refusal};

/// Most calls outside the DinerDash service open at once, from everyone.
pub const PROBE_CALLS: usize = 256;
/// Most calls outside the DinerDash service open at once from one peer address.
pub const PROBE_CALLS_PER_PEER: usize = 32;
/// Most health Watches open at once, from everyone (Kubernetes' probes and the Python client
/// send Checks).
pub const WATCHES: usize = 64;
/// Most health Watches open at once from one peer address.
pub const WATCHES_PER_PEER: usize = 4;
/// The path of a health Watch.
const WATCH: &str = "/grpc.health.v1.Health/Watch";
/// One identity may hold at most this part of the calls the intake bound holds (1/2: two
/// identities are needed to fill it).
pub const IDENTITY_SHARE: usize = 2;
/// The calls the intake bound of a server of `--max-memory` `max_memory` holds at
/// [`CALL_BYTES`] each.
pub fn calls_held(max_memory: u64) -> u64 {
    intake_bound(max_memory) / CALL_BYTES
}

/// The paths of the DinerDash service.
const SERVICE_PREFIX: &str = "/dinerdash.v1.DinerDash/";

/// The calls outside the DinerDash service open now.
#[derive(Debug, Default)]
struct Probes {
    /// From everyone: other calls, then Watches.
    open: [usize; 2],
    /// By kind (0: other calls, 1: Watches) and peer address.
    by_peer: HashMap<(usize, Option<IpAddr>), usize>,
}

/// The caps of each kind of [`Probes`]: in all, and from one peer.
const PROBE_CAPS: [(usize, usize); 2] = [
    (
        PROBE_CALLS - WATCHES,
        PROBE_CALLS_PER_PEER - WATCHES_PER_PEER,
    ),
    (WATCHES, WATCHES_PER_PEER),
];

/// Shared by [`ProbeLayer`]'s services.
type SharedProbes = Arc<Mutex<Probes>>;

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The tower layer that caps the calls outside the DinerDash service; every service is behind
/// it: `Server::builder().layer(ProbeLayer::new(metrics))`.
#[derive(Debug, Clone)]
pub struct ProbeLayer {
    /// The calls open now.
    probes: SharedProbes,
    /// Counts the refusals.
    metrics: Arc<Metrics>,
}

impl ProbeLayer {
    /// Caps the calls outside the DinerDash service, counting refusals in `metrics`.
    pub fn new(metrics: Arc<Metrics>) -> ProbeLayer {
        ProbeLayer {
            probes: SharedProbes::default(),
            metrics,
        }
    }
}

impl<S> tower::Layer<S> for ProbeLayer {
    type Service = ProbeCalls<S>;

    fn layer(&self, inner: S) -> ProbeCalls<S> {
        ProbeCalls {
            inner,
            probes: Arc::clone(&self.probes),
            metrics: Arc::clone(&self.metrics),
        }
    }
}

/// The service [`ProbeLayer`] makes.
#[derive(Debug, Clone)]
pub struct ProbeCalls<S> {
    /// The services behind it.
    inner: S,
    /// The calls open now.
    probes: SharedProbes,
    /// Counts the refusals.
    metrics: Arc<Metrics>,
}

/// A call outside the DinerDash service, counted until its response ends.
#[derive(Debug)]
pub struct ProbeSlot {
    /// Where it is counted.
    probes: SharedProbes,
    /// Its kind and its peer's address.
    key: (usize, Option<IpAddr>),
}

impl ProbeSlot {
    /// A slot for a call to `path` from `peer`, unless the caps are reached.
    fn take(probes: &SharedProbes, path: &str, peer: Option<IpAddr>) -> Result<ProbeSlot, Status> {
        let kind = usize::from(path == WATCH);
        let (most, most_from_peer) = PROBE_CAPS[kind];
        let mut open = lock(probes);
        let from_peer = open.by_peer.get(&(kind, peer)).copied().unwrap_or(0);
        if open.open[kind] >= most || from_peer >= most_from_peer {
            let what = if kind == 1 {
                "health Watches"
            } else {
                "calls outside the DinerDash service (health checks, reflection)"
            };
            return Err(Status::resource_exhausted(format!(
                "at most {most} {what} may be open at once, {most_from_peer} from one address: \
                 retry later"
            )));
        }
        open.open[kind] += 1;
        *open.by_peer.entry((kind, peer)).or_default() += 1;
        Ok(ProbeSlot {
            probes: Arc::clone(probes),
            key: (kind, peer),
        })
    }
}

impl Drop for ProbeSlot {
    fn drop(&mut self) {
        let mut open = lock(&self.probes);
        open.open[self.key.0] -= 1;
        if let Some(n) = open.by_peer.get_mut(&self.key) {
            *n -= 1;
            if *n == 0 {
                open.by_peer.remove(&self.key);
            }
        }
    }
}

impl<S, ReqBody, ResBody> tower::Service<http::Request<ReqBody>> for ProbeCalls<S>
where
    S: tower::Service<http::Request<ReqBody>, Response = http::Response<ResBody>>,
    S::Future: Unpin,
    ResBody: Default + Unpin,
{
    type Response = http::Response<CallBody<ResBody, ProbeSlot>>;
    type Error = S::Error;
    type Future = Answer<S::Future, ResBody, ProbeSlot>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<ReqBody>) -> Self::Future {
        if request.uri().path().starts_with(SERVICE_PREFIX) {
            return Answer::call(self.inner.call(request), None);
        }
        let peer = conn_info_in(request.extensions())
            .and_then(|info| info.remote)
            .map(|addr| addr.ip());
        match ProbeSlot::take(&self.probes, request.uri().path(), peer) {
            Ok(slot) => Answer::call(self.inner.call(request), Some(slot)),
            Err(status) => {
                self.metrics.count_refusal(Refusal::ProbeCalls);
                Answer::Refused(Some(status.into_http()))
            }
        }
    }
}

/// The response future of [`ProbeCalls`] and [`Admit`]: the call's, with its guard `G`, or a
/// refusal made without calling the service.
#[derive(Debug)]
pub enum Answer<F, B, G> {
    /// The service's answer.
    Call(CallFuture<F, G>),
    /// Refused at its headers.
    Refused(Option<http::Response<B>>),
}

impl<F, B, G> Answer<F, B, G> {
    fn call(inner: F, guard: Option<G>) -> Self {
        Answer::Call(CallFuture { inner, call: guard })
    }
}

impl<F, B, E, G> Future for Answer<F, B, G>
where
    F: Future<Output = Result<http::Response<B>, E>> + Unpin,
    B: Unpin,
    G: Unpin,
{
    type Output = Result<http::Response<CallBody<B, G>>, E>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        match self.get_mut() {
            Answer::Call(call) => Pin::new(call).poll(cx),
            Answer::Refused(refusal) => {
                let response = refusal.take().expect("an answer polled after it was ready");
                Poll::Ready(Ok(response.map(|body| CallBody { body, call: None })))
            }
        }
    }
}

/// The authenticated calls open now: each counted against its identity's `streams` quota and
/// charged against the intake bound.
#[derive(Debug)]
pub struct Admitted {
    /// Where each call is charged [`CALL_BYTES`].
    budget: Arc<Budget>,
    /// Most calls open at once on a server without tokens (all its calls are nobody's).
    per_identity: u64,
    /// Calls open on a server without tokens.
    anonymous: AtomicU64,
}

impl Admitted {
    /// Charges calls against `budget`'s intake bound.
    pub fn new(budget: Arc<Budget>) -> Arc<Admitted> {
        let holds = budget.max_intake_bytes() / CALL_BYTES;
        let per_identity = (holds / IDENTITY_SHARE as u64).max(1);
        Arc::new(Admitted {
            budget,
            per_identity,
            anonymous: AtomicU64::new(0),
        })
    }

    fn metrics(&self) -> &Metrics {
        self.budget.metrics()
    }

    /// Most calls open at once on a server without tokens.
    pub fn per_identity(&self) -> u64 {
        self.per_identity
    }

    /// Opens a call of `tenant` (`None`: a server without tokens), or says why not.
    fn open(self: &Arc<Self>, tenant: Option<&Arc<Tenant>>) -> Result<CallSlot, Status> {
        let counted = match tenant {
            Some(tenant) => Counted::Tenant(tenant.take_stream().map_err(|(open, max)| {
                self.metrics().count_refusal(Refusal::StreamsQuota);
                Status::resource_exhausted(format!(
                    "{} has {open} calls open, its streams quota of {max} calls at once (its \
                     part of those the intake bound holds, or streams= in the tokens file): \
                     end some",
                    tenant.name()
                ))
            })?),
            None => {
                let max = self.per_identity;
                self.anonymous
                    .fetch_update(Ordering::AcqRel, Ordering::Acquire, |open| {
                        (open < max).then_some(open + 1)
                    })
                    .map_err(|open| {
                        self.metrics().count_refusal(Refusal::CallsOpen);
                        Status::resource_exhausted(format!(
                            "{open} calls are open, the most a server without tokens takes \
                             (1/{IDENTITY_SHARE} of what the intake bound, a quarter of \
                             --max-memory, holds at {} KiB a call): end some, or raise \
                             --max-memory",
                            CALL_BYTES >> 10
                        ))
                    })?;
                Counted::Anonymous(Arc::clone(self))
            }
        };
        let charge = self.budget.charge_intake(CALL_BYTES).map_err(|e| {
            self.metrics().count_refusal(Refusal::Intake);
            Status::resource_exhausted(format!(
                "an open call is charged {} KiB while it lasts: {e}",
                CALL_BYTES >> 10
            ))
        })?;
        Ok(CallSlot {
            _counted: counted,
            _charge: charge,
            call: None,
        })
    }
}

/// Where an open call is counted.
#[derive(Debug)]
enum Counted {
    /// Against its tenant's (or the shared token's) `streams` quota.
    Tenant(#[allow(dead_code, reason = "held to be given back when dropped")] Held),
    /// Among a server without tokens' calls.
    Anonymous(Arc<Admitted>),
}

impl Drop for Counted {
    fn drop(&mut self) {
        if let Counted::Anonymous(admitted) = self {
            admitted.anonymous.fetch_sub(1, Ordering::AcqRel);
        }
    }
}

/// Makes the connection of `activity` its first authenticated caller's: counted against that
/// `tenant`'s `connections` quota until it closes (none on a server without tokens), or refused
/// (it stays nobody's). Once it is someone's, one atomic load.
fn claim(
    activity: &Activity,
    tenant: Option<&Arc<Tenant>>,
    metrics: &Metrics,
) -> Result<(), Status> {
    if activity.authenticated.load(Ordering::Acquire) {
        return Ok(());
    }
    let mut owner = lock(&activity.owner);
    if activity.authenticated.load(Ordering::Acquire) {
        return Ok(());
    }
    if let Some(tenant) = tenant {
        let held = tenant.take_connection().map_err(|(held, max)| {
            metrics.count_refusal(Refusal::ConnectionsQuota);
            Status::resource_exhausted(format!(
                "{} holds {held} connections, its connections quota of {max} (its part of \
                 --max-connections, or connections= in the tokens file): make its calls on the \
                 connections it has, or close one",
                tenant.name()
            ))
        })?;
        *owner = Some(held);
    }
    activity.authenticated.store(true, Ordering::Release);
    Ok(())
}

/// An authenticated call, counted and charged until its response ends.
#[derive(Debug)]
pub struct CallSlot {
    /// Where it is counted.
    _counted: Counted,
    /// Its [`CALL_BYTES`].
    _charge: IntakeCharge,
    /// Counted in flight on its connection.
    call: Option<Call>,
}

/// The DinerDash service behind the token check: each call is admitted ([`Admitted`]),
/// counted in flight on its connection, and marks the connection as a tenant's.
#[derive(Debug, Clone)]
pub struct Admit<S> {
    /// The service.
    inner: S,
    /// The calls open.
    admitted: Arc<Admitted>,
}

impl<S> Admit<S> {
    /// `inner`, its calls admitted by `admitted`.
    pub fn new(inner: S, admitted: Arc<Admitted>) -> Admit<S> {
        Admit { inner, admitted }
    }
}

impl<S: NamedService> NamedService for Admit<S> {
    const NAME: &'static str = S::NAME;
}

impl<S, ReqBody, ResBody> tower::Service<http::Request<ReqBody>> for Admit<S>
where
    S: tower::Service<http::Request<ReqBody>, Response = http::Response<ResBody>>,
    S::Future: Unpin,
    ResBody: Default + Unpin,
{
    type Response = http::Response<CallBody<ResBody, CallSlot>>;
    type Error = S::Error;
    type Future = Answer<S::Future, ResBody, CallSlot>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<ReqBody>) -> Self::Future {
        let ext = request.extensions();
        // A tenant's, or the shared token's; none on a server without tokens.
        let tenant = ext
            .get::<Arc<Tenant>>()
            .or_else(|| ext.get::<SharedShare>().map(|shared| &shared.0));
        let activity = conn_info_in(ext).and_then(|info| info.activity.as_ref());
        let admitted = activity
            .map_or(Ok(()), |activity| {
                claim(activity, tenant, self.admitted.metrics())
            })
            .and_then(|()| self.admitted.open(tenant));
        match admitted {
            Ok(mut slot) => {
                slot.call = activity.map(Call::new);
                Answer::call(self.inner.call(request), Some(slot))
            }
            Err(status) => Answer::Refused(Some(status.into_http())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::budget::Share;
    use crate::metrics::Metrics;

    #[test]
    fn one_identity_holds_at_most_its_share_of_the_calls() {
        let budget = Arc::new(Budget::new(1 << 20, 10, Arc::new(Metrics::default())));
        let admitted = Admitted::new(Arc::clone(&budget));
        // The intake bound's floor, 64 MiB, holds 1365 calls of 48 KiB: on a server without
        // tokens, all its calls together 682.
        assert_eq!(calls_held(1 << 20), 1365);
        assert_eq!(admitted.per_identity(), 682);
        let share = Share {
            max_streams: 455,
            ..Share::default()
        };
        let a = Arc::new(Tenant::new("tenant a".into(), share));
        let mut held: Vec<CallSlot> = (0..455).map(|_| admitted.open(Some(&a)).unwrap()).collect();
        assert_eq!(budget.intake_bytes(), 455 * CALL_BYTES);
        assert_eq!(a.streams(), 455);
        let e = admitted.open(Some(&a)).unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
        assert!(
            e.message()
                .starts_with("tenant a has 455 calls open, its streams quota of 455"),
            "{e:?}"
        );
        // Another identity is not refused for it.
        let others: Vec<CallSlot> = (0..682).map(|_| admitted.open(None).unwrap()).collect();
        let e = admitted.open(None).unwrap_err();
        assert!(e.message().starts_with("682 calls are open"), "{e:?}");
        held.pop();
        held.push(admitted.open(Some(&a)).unwrap());
        drop((held, others));
        assert_eq!(budget.intake_bytes(), 0);
        assert_eq!(a.streams(), 0);
        assert_eq!(admitted.anonymous.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn probe_calls_are_capped_in_all_and_by_peer() {
        let probes = SharedProbes::default();
        let peer = |i: u8| Some(IpAddr::from([10, 0, 0, i]));
        const CHECK: &str = "/grpc.health.v1.Health/Check";
        let (calls, calls_per_peer) = PROBE_CAPS[0];
        let take = |path, i| ProbeSlot::take(&probes, path, peer(i));
        let mut held: Vec<ProbeSlot> = (0..calls_per_peer)
            .map(|_| take(CHECK, 1).unwrap())
            .collect();
        assert!(take(CHECK, 1).is_err());
        // Watches have their own, smaller caps.
        for _ in 0..WATCHES_PER_PEER {
            held.push(take(WATCH, 1).unwrap());
        }
        let e = take(WATCH, 1).unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
        assert!(
            e.message().starts_with("at most 64 health Watches"),
            "{e:?}"
        );
        for i in 2.. {
            match take(CHECK, i) {
                Ok(slot) => held.push(slot),
                Err(e) => {
                    assert_eq!(e.code(), tonic::Code::ResourceExhausted);
                    break;
                }
            }
        }
        assert_eq!(held.len(), calls + WATCHES_PER_PEER);
        held.truncate(calls_per_peer - 1);
        take(CHECK, 1).unwrap();
        drop(held);
        assert_eq!(lock(&probes).open, [0, 0]);
        assert!(lock(&probes).by_peer.is_empty());
    }
}
