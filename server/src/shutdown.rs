//! Graceful shutdown: the signals that start it, the deadline that ends it, the handles that
//! tell background tasks, and the `UNAVAILABLE` answer ([`unavailable`]) of a draining server.
//!
//! The server (`server::run`) takes any future as its shutdown trigger, so tests pass a oneshot
//! and the binary passes [`signal`]. Once triggered the server stops accepting connections and
//! lets in-flight RPCs finish; the binary gives them [`DRAIN_DEADLINE`] before it exits anyway.

use std::future::Future;
use std::time::Duration;

/// How long in-flight RPCs may run on after SIGINT/SIGTERM before the process exits anyway.
pub const DRAIN_DEADLINE: Duration = Duration::from_secs(10);
/// How long a Rollout stream may go on after the signal before it ends with `UNAVAILABLE`:
/// well inside [`DRAIN_DEADLINE`], so that streams end cleanly rather than being cut.
pub const STREAM_DRAIN_DEADLINE: Duration = Duration::from_secs(2);

/// Runs `serve` with a shutdown future that completes on SIGINT/SIGTERM, and returns what it
/// returns; once signalled, gives it [`DRAIN_DEADLINE`] before returning `Ok` anyway.
pub async fn serve_until_signal<F, E>(
    serve: impl FnOnce(std::pin::Pin<Box<dyn Future<Output = ()> + Send>>) -> F,
) -> Result<(), E>
where
    F: Future<Output = Result<(), E>>,
{
    let (signalled, drain) = tokio::sync::oneshot::channel();
    let stop = Box::pin(async move {
        signal().await;
        let _ = signalled.send(());
    });
    let deadline = async move {
        if drain.await.is_ok() {
            tokio::time::sleep(DRAIN_DEADLINE).await;
        } else {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        served = serve(stop) => served,
        () = deadline => {
            tracing::warn!(
                "RPCs still running {} s after the signal; exiting anyway",
                DRAIN_DEADLINE.as_secs()
            );
            Ok(())
        }
    }
}

/// Completes on the first SIGINT (Ctrl-C) or SIGTERM (`docker stop`, Kubernetes).
pub async fn signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut sigterm) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = sigterm.recv() => {}
                }
            }
            Err(e) => {
                tracing::warn!("cannot listen for SIGTERM ({e}); Ctrl-C still works");
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// The answer to calls that arrive, or streams still running, once the server drains.
pub fn unavailable() -> tonic::Status {
    tonic::Status::unavailable("the server is shutting down; retry on another server")
}

/// Fires the [`Shutdown`] handles made with it; dropping it fires them too.
#[derive(Debug)]
pub struct Trigger {
    /// Turns true once; every handle watches it.
    tx: tokio::sync::watch::Sender<bool>,
}

/// Tells a background task (the idle-session sweeper, the metrics responder) that the server
/// is stopping. Cloning is cheap.
#[derive(Debug, Clone)]
pub struct Shutdown {
    /// The trigger's flag.
    rx: tokio::sync::watch::Receiver<bool>,
}

/// A trigger and a first handle.
pub fn channel() -> (Trigger, Shutdown) {
    let (tx, rx) = tokio::sync::watch::channel(false);
    (Trigger { tx }, Shutdown { rx })
}

impl Trigger {
    /// Tells every handle to stop.
    pub fn fire(&self) {
        self.tx.send_replace(true);
    }
}

impl Shutdown {
    /// Whether the trigger has fired (or is gone): the server is draining.
    pub fn is_stopping(&self) -> bool {
        *self.rx.borrow() || self.rx.has_changed().is_err()
    }

    /// Completes once the trigger fired or was dropped.
    pub async fn wait(&mut self) {
        // An error means the trigger is gone, which also means stop.
        let _ = self.rx.wait_for(|stop| *stop).await;
    }
}
