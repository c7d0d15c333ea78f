//! Graceful shutdown: the signals that start it and the deadline that ends it.
//!
//! [`crate::server::run`] takes any future as its shutdown trigger, so tests pass a oneshot and
//! the binary passes [`signal`]. Once triggered the server stops accepting connections and lets
//! in-flight RPCs finish; the binary gives them [`DRAIN_DEADLINE`] before it exits anyway.

use std::time::Duration;

/// How long in-flight RPCs (a long Rollout, say) may run on after SIGINT/SIGTERM.
pub const DRAIN_DEADLINE: Duration = Duration::from_secs(10);

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
    /// Completes once the trigger fired or was dropped.
    pub async fn wait(&mut self) {
        // An error means the trigger is gone, which also means stop.
        let _ = self.rx.wait_for(|stop| *stop).await;
    }
}
