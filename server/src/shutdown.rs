//! Graceful shutdown: the signals that start it, the drain of a planned restart, the deadline
//! that ends it, the handles that tell background tasks, and the answers of a server on its way
//! out: [`Draining`] (no new session) and [`unavailable`] (nothing more).
//!
//! A server goes through three phases ([`Phase`]). It *serves*; on the first SIGINT/SIGTERM it
//! *drains* (for `--drain-timeout`, see [`Trigger::drain`]): it refuses new sessions, says
//! NOT_SERVING to health checks and tells its clients, in every Batch, how long they have left,
//! while the sessions it has keep being served; once they are all closed, or the drain timeout
//! has passed, it *stops*: it closes its port, answers new calls `UNAVAILABLE`, lets the RPCs in
//! flight finish, and gives them [`DRAIN_DEADLINE`] before the process exits anyway. A second
//! signal ends the process at once ([`serve_until_signal`]).
//!
//! The server (`server::run`) takes any future as the start of its drain, so tests pass a oneshot
//! and the binary passes the first of its [`Signals`].

use std::future::Future;
use std::time::{Duration, Instant};

/// How long in-flight RPCs may run on after the drain before the process exits anyway.
pub const DRAIN_DEADLINE: Duration = Duration::from_secs(10);
/// How long a Rollout stream may go on after the server stops before it ends with
/// `UNAVAILABLE`: well inside [`DRAIN_DEADLINE`], so that streams end cleanly rather than being
/// cut.
pub const STREAM_DRAIN_DEADLINE: Duration = Duration::from_secs(2);
/// The default `--drain-timeout`: how long the sessions of a signalled server are served on.
/// Orchestrators must wait longer than this before they kill (Kubernetes'
/// `terminationGracePeriodSeconds`, `docker stop --time`).
pub const DEFAULT_DRAIN_TIMEOUT: Duration = Duration::from_secs(30);
/// How often a draining server looks whether its last session has gone.
const DRAIN_POLL: Duration = Duration::from_millis(50);

/// Runs `serve` with a future that completes on the first of `signals` (the start of the drain),
/// and returns what it returns; returns `Ok` anyway, ending the process, on a second signal or
/// once `drain_timeout` and then [`DRAIN_DEADLINE`] have passed since the first. The caller
/// makes `signals` before it tells anyone the server is up, so that a signal sent at once is
/// a drain, not the default action that kills the process.
pub async fn serve_until_signal<F, E>(
    mut signals: Signals,
    drain_timeout: Duration,
    serve: impl FnOnce(std::pin::Pin<Box<dyn Future<Output = ()> + Send>>) -> F,
) -> Result<(), E>
where
    F: Future<Output = Result<(), E>>,
{
    let (signalled, first) = tokio::sync::oneshot::channel();
    let stop = Box::pin(async move {
        if first.await.is_err() {
            // The watcher is gone: the server has returned already.
            std::future::pending::<()>().await;
        }
    });
    let watch = async move {
        signals.recv().await;
        let _ = signalled.send(());
        tokio::select! {
            () = signals.recv() => tracing::warn!("a second signal: exiting at once"),
            () = tokio::time::sleep(drain_timeout + DRAIN_DEADLINE) => tracing::warn!(
                "RPCs still running {} s after the drain; exiting anyway",
                DRAIN_DEADLINE.as_secs()
            ),
        }
    };
    tokio::select! {
        served = serve(stop) => served,
        () = watch => Ok(()),
    }
}

/// SIGINT (Ctrl-C) and SIGTERM (`docker stop`, Kubernetes), one after the other: listened for
/// from creation on, so that a second signal soon after the first is not missed.
#[derive(Debug)]
pub struct Signals {
    /// SIGTERM, when it could be listened for.
    #[cfg(unix)]
    term: Option<tokio::signal::unix::Signal>,
    /// SIGINT, when it could be listened for.
    #[cfg(unix)]
    interrupt: Option<tokio::signal::unix::Signal>,
}

impl Signals {
    /// Starts listening (inside a tokio runtime).
    pub fn new() -> Signals {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{SignalKind, signal};
            let listen = |kind: SignalKind, name: &str| {
                signal(kind)
                    .map_err(|e| tracing::warn!("cannot listen for {name} ({e})"))
                    .ok()
            };
            Signals {
                term: listen(SignalKind::terminate(), "SIGTERM"),
                interrupt: listen(SignalKind::interrupt(), "SIGINT"),
            }
        }
        #[cfg(not(unix))]
        Signals {}
    }

    /// Completes on the next SIGINT or SIGTERM.
    pub async fn recv(&mut self) {
        #[cfg(unix)]
        {
            async fn next(signal: Option<&mut tokio::signal::unix::Signal>) {
                // A listener that could not be set up, or has closed, never completes.
                if let Some(s) = signal {
                    if s.recv().await.is_some() {
                        return;
                    }
                }
                std::future::pending().await
            }
            tokio::select! {
                () = next(self.term.as_mut()) => {}
                () = next(self.interrupt.as_mut()) => {}
            }
        }
        #[cfg(not(unix))]
        {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

impl Default for Signals {
    fn default() -> Signals {
        Signals::new()
    }
}

/// The answer to calls that arrive, or streams still running, once the server stops.
pub fn unavailable() -> tonic::Status {
    tonic::Status::unavailable("the server is shutting down; retry on another server")
}

/// Why a draining server refuses to start new work (CreateSession, Fork, Restore, Rollout):
/// `UNAVAILABLE` with reason `DRAINING` at the service edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error(
    "the server is draining before a restart: it starts no new session, and ends the ones it \
     serves in {} ms; create this one on another server",
    .remaining_ms
)]
pub struct Draining {
    /// Milliseconds left before the server ends the sessions it still serves.
    pub remaining_ms: u32,
}

/// Where the server is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Serving everything.
    Serving,
    /// Refusing new sessions, serving the ones it has until this instant at the latest.
    Draining(Instant),
    /// Closing: new calls are answered `UNAVAILABLE`, the ones in flight finish.
    Stopping,
}

/// Moves the server through its [`Phase`]s, telling the [`Shutdown`] handles made with it;
/// dropping it stops them too.
#[derive(Debug)]
pub struct Trigger {
    /// The phase; every handle watches it.
    tx: tokio::sync::watch::Sender<Phase>,
}

/// Tells the service and the background tasks (the idle-session sweeper, the HTTP endpoint)
/// whether the server drains or stops. Cloning is cheap.
#[derive(Debug, Clone)]
pub struct Shutdown {
    /// The trigger's phase.
    rx: tokio::sync::watch::Receiver<Phase>,
}

/// A trigger and a first handle.
pub fn channel() -> (Trigger, Shutdown) {
    let (tx, rx) = tokio::sync::watch::channel(Phase::Serving);
    (Trigger { tx }, Shutdown { rx })
}

impl Trigger {
    /// Starts the drain: the sessions left are served for `timeout` at most. Returns the
    /// deadline. A server already draining or stopping keeps its phase.
    pub fn drain(&self, timeout: Duration) -> Instant {
        let until = Instant::now() + timeout;
        self.tx.send_if_modified(|phase| {
            let serving = *phase == Phase::Serving;
            if serving {
                *phase = Phase::Draining(until);
            }
            serving
        });
        match *self.tx.borrow() {
            Phase::Draining(until) => until,
            _ => Instant::now(),
        }
    }

    /// Tells every handle to stop.
    pub fn fire(&self) {
        self.tx.send_replace(Phase::Stopping);
    }
}

/// Completes once `sessions_left` says no session is left, or at `until` (the deadline
/// [`Trigger::drain`] returned), whichever comes first.
pub async fn drained(until: Instant, sessions_left: impl Fn() -> usize) {
    let timeout = until.saturating_duration_since(Instant::now());
    if timeout.is_zero() {
        return;
    }
    tracing::info!(
        sessions = sessions_left(),
        drain_timeout_s = timeout.as_secs_f64(),
        "draining: no new sessions; serving the ones left until they close or the drain timeout \
         passes (a second Ctrl-C or SIGTERM exits at once)"
    );
    let deadline = tokio::time::Instant::from_std(until);
    let mut poll = tokio::time::interval(DRAIN_POLL);
    poll.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            () = tokio::time::sleep_until(deadline) => {
                let left = sessions_left();
                if left > 0 {
                    tracing::warn!(sessions = left, "the drain timeout passed: ending the sessions left");
                }
                return;
            }
            _ = poll.tick() => {
                if sessions_left() == 0 {
                    tracing::info!("drained: no session left");
                    return;
                }
            }
        }
    }
}

impl Shutdown {
    /// Whether the server stops (or its trigger is gone): new calls are refused.
    pub fn is_stopping(&self) -> bool {
        *self.rx.borrow() == Phase::Stopping || self.rx.has_changed().is_err()
    }

    /// The phase now.
    pub fn phase(&self) -> Phase {
        *self.rx.borrow()
    }

    /// `Err` while the server drains or stops: it takes no new session then.
    pub fn admit(&self) -> Result<(), Draining> {
        match self.drain_remaining_ms() {
            0 => Ok(()),
            remaining_ms => Err(Draining { remaining_ms }),
        }
    }

    /// What a Batch's `drain_remaining_ms` says: 0 while serving; while draining, the
    /// milliseconds left before the server ends its sessions (at least 1, rounded up); 1 once
    /// it stops.
    pub fn drain_remaining_ms(&self) -> u32 {
        match self.phase() {
            Phase::Serving => 0,
            Phase::Draining(until) => {
                let left = until.saturating_duration_since(Instant::now());
                u32::try_from(left.as_micros().div_ceil(1000))
                    .unwrap_or(u32::MAX)
                    .max(1)
            }
            Phase::Stopping => 1,
        }
    }

    /// Completes once the server stops, or the trigger was dropped.
    pub async fn wait(&mut self) {
        // An error means the trigger is gone, which also means stop.
        let _ = self.rx.wait_for(|phase| *phase == Phase::Stopping).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn phases_and_what_handles_see() {
        let (trigger, handle) = channel();
        assert_eq!(handle.drain_remaining_ms(), 0);
        assert!(handle.admit().is_ok() && !handle.is_stopping());
        trigger.drain(Duration::from_secs(5));
        let left = handle.drain_remaining_ms();
        assert!((4_000..=5_000).contains(&left), "{left}");
        assert_eq!(handle.admit().unwrap_err().remaining_ms / 1000, left / 1000);
        assert!(!handle.is_stopping());
        // A second drain keeps the first deadline.
        trigger.drain(Duration::from_secs(60));
        assert!(handle.drain_remaining_ms() <= 5_000);
        trigger.fire();
        assert!(handle.is_stopping());
        assert_eq!(handle.drain_remaining_ms(), 1);
        assert!(handle.admit().is_err());
        drop(trigger);
        assert!(handle.is_stopping());
    }

    #[tokio::test]
    async fn a_drain_ends_at_its_deadline_or_with_the_last_session() {
        let started = Instant::now();
        drained(started + Duration::from_secs(600), || 0).await;
        assert!(started.elapsed() < Duration::from_secs(60));
        let started = Instant::now();
        drained(started + Duration::from_millis(300), || 1).await;
        assert!(started.elapsed() >= Duration::from_millis(300));
        drained(Instant::now(), || 1).await;
    }
}
